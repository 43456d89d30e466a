/*
 * fastemu_rig.h: the interface between fastemu and a rig it did not start.
 *
 *   rig ABI version 4   (iceoryx2 shared memory, same machine)
 *   link protocol 3     (UDP datagrams, any machine: Speedgoat, TwinCAT, VeriStand, a DAQ PC)
 *
 * Every layout below is checked against fastemu's Rust types by the test
 * tests/it/rig_header.rs (sizes and offsets of every field). Units are SI; displacement
 * and force are positive in compression (the specimen moving into the elastomer; the
 * actuator's force pushing back against compression). Times are nanoseconds.
 * The README, section "Connecting a rig", says the same with examples.
 *
 * ======================================================================================
 * 1. iceoryx2 (fastemu hil --rig external [--run-id NAME])
 * ======================================================================================
 * Run id R (printed by hil, or --run-id R). iceoryx2 config: the default config with
 * global.prefix = "R_" (every iceoryx2 file of the run starts with R_). Services,
 * publish-subscribe, payload types registered under the type names below:
 *
 *   fastemu/R/displacement  fastemu_displacement_sample  "fastemu::DisplacementSample"  rig publishes
 *   fastemu/R/command       fastemu_actuator_command     "fastemu::ActuatorCommand"     rig subscribes
 *   fastemu/R/heartbeat     fastemu_heartbeat            "fastemu::Heartbeat"           rig publishes
 *   fastemu/R/control       fastemu_run_control          "fastemu::RunControl"          rig subscribes
 *
 * hil creates these services before it waits for the rig: open them. A rig that starts
 * before hil and creates them must use these settings (history size, subscriber buffer,
 * max publishers, max subscribers; every service: safe overflow on, max 8 nodes):
 *   displacement 0, 4096, 1, 4   command 0, 8, 1, 4    heartbeat 0, 64, 4, 6
 *   control      1, 8,    4, 4
 *
 * Start handshake: the rig publishes a heartbeat {process 0, state FASTEMU_HEARTBEAT_READY}
 * every 5-10 ms until a run control START arrives. START.start_time_ns is the
 * CLOCK_MONOTONIC time of sample 0: the rig takes sample k at start_time_ns + k * T
 * (T = 1 / [loop] rate_hz of the configuration; 244140.625 ns -> 244141 ns at 4096 Hz)
 * and publishes it at once, with publish_time_ns = CLOCK_MONOTONIC now.
 * The iceoryx2 version must be fastemu's (0.10; any language binding), payloads without
 * a user header.
 * Heartbeats: after the start, one every 10 ms {process 0, state (FASTEMU_RIG_*),
 * sequence, time_ns, fault_code}. hil treats 1 s without one as the rig lost.
 *
 * ======================================================================================
 * 2. What the rig does every period k (both transports)
 * ======================================================================================
 *  a. Measure displacement z_k (and, if it can, the actuator force); send the sample
 *     {sequence k, rig_time_ns k*T, displacement, force (NaN if not measured), status,
 *     its state (FASTEMU_RIG_STARTING from sample 0 until the first FORCE or LAW command
 *     takes over) and latched fault code, and the force command applied over period k-1
 *     (NaN if the rig does not say; from sample 0, its own servo's command in newtons;
 *     a servo that commands a valve or a position, not a force, sends NaN: fastemu then
 *     reads the actuator's gain from the first samples in force control instead)}.
 *  b. Take every command that arrived since the last period; the newest counts. A
 *     command with mode HOLD or HOLD_UNLOAD latches the interlock (fault 22
 *     hold-requested) and is never left in this session. Drop, as if it had not
 *     arrived, a command with an unknown mode, or a FORCE/LAW command with a non-finite
 *     law or force limits that are not finite and ordered: it neither drives the output
 *     nor counts for the interlock (d).
 *  c. Output, by the newest command's mode:
 *     (none yet: from sample 0 until the first command) position control: hold the
 *            starting position with the load programme's change fed forward (a servo
 *            controller starts in displacement control), the programme running.
 *     FORCE  F = clamp(law.force_n, force_min_n, force_max_n), held until the next one.
 *     LAW    F = (clamp(fastemu_law_evaluate(&law, z_L, v_L, since_s) + D v_hp,
 *            force_min_n, force_max_n)) / g, re-evaluated every period with the rig's own
 *            measurement and the command's compensation (fastemu_compensated_force()
 *            below does all of it):
 *              z_L, v_L: displacement and velocity predicted over the command's lead
 *                L = compensation.lead_s (the actuator's effective output delay as
 *                fastemu's controller identified it: half a period of zero-order hold +
 *                transport delay + lag; it changes while the controller learns) by the
 *                Lagrange polynomial of order n = compensation.lead_order through the
 *                newest n+1 measurements: fastemu_lead_weights() below (recompute when
 *                L or n change).
 *              since_s = (k - command.sample_sequence) * T + L, at most the stale limit
 *                N * T (below); 0 when sample_sequence is UINT64_MAX.
 *              D = compensation.added_damping_ns_per_m (the passivity guard, 0 while the
 *                loop is passive), v_hp = v_L minus its first-order low-pass with corner
 *                compensation.added_damping_corner_hz (updated every period; corner 0:
 *                v_hp = v_L).
 *              g = compensation.gain, the actuator's identified force per command.
 *     HOLD / HOLD_UNLOAD  position control: hold the displacement measured when the
 *            interlock latched (as a servo controller's interlock does), the load
 *            programme held; HOLD_UNLOAD: once the specimen is at rest, ramp the load
 *            programme to zero while holding position. Never a constant force on a free
 *            mass.
 *  d. The rig's own interlock: more than N periods without a new command, counted from
 *     sample 0 until the first command and from the newest command after it (any mode;
 *     keep-alive repeats count: fastemu repeats the last command every 8 periods when it
 *     has nothing new; its first command follows sample 0 within a few periods) latch
 *     fault 20 commands-stale and hold (as HOLD). N = [rig] command_stale_periods (205 = 50 ms by default). The
 *     rig detects this itself: it holds even when every fastemu process is dead, the
 *     link is cut, or the network is flooded.
 *  e. Run control: STOP ends the session now; HOLD (operator) holds position and pauses
 *     the load programme; RESUME returns to force control (blend from the held force
 *     over [safety] resume_blend_ms) and continues the programme without a jump; END
 *     holds, unloads the programme to zero, then ends the session.
 *  f. The session ends when the rig's programme ends, or after a hold once the specimen
 *     is at rest (at least [safety] hold_min_s, at most hold_max_s). The rig sends a
 *     last sample with status FASTEMU_SAMPLE_END_OF_RUN and state FASTEMU_RIG_FINISHED,
 *     and a heartbeat (iceoryx2) or status datagrams (UDP) with state FINISHED.
 *
 * ======================================================================================
 * 3. UDP rig link (fastemu hil --rig external --rig-link udp --link-bind A --link-peer B)
 * ======================================================================================
 * fastemu binds A (one interface, never 0.0.0.0) and accepts datagrams only from B, the
 * rig's address and port; the rig must bind B and accept datagrams only from A. All
 * fields little-endian, no padding: on a little-endian machine the structs below are the
 * datagrams byte for byte. Every datagram: the 24-byte header, then its kind's payload;
 * its length is exactly its kind's size. A receiver drops (and counts) datagrams with a
 * wrong length, magic, version or kind, from any other address, with content nobody may
 * act on (a START or STATUS with another period, an unknown run-control command, a
 * COMMAND with an unknown mode, a non-finite law or non-finite or unordered force limits,
 * a LAW command whose compensation is out of range (fastemu_compensation_ok);
 * checked before the sequence, so a dropped datagram moves nothing), or whose sequence is
 * not newer than the newest accepted one of its kind (duplicates, reordering).
 *
 *   kind 1 SAMPLE   rig -> fastemu   96 bytes, one per period
 *   kind 2 COMMAND  fastemu -> rig  184 bytes, one per command
 *   kind 3 CONTROL  fastemu -> rig   56 bytes, run control (sent 3 times; START repeated
 *                                    every 5 ms until the first sample): act once per
 *                                    control_sequence
 *   kind 4 STATUS   rig -> fastemu   40 bytes: state READY (100) every 10 ms until START;
 *                                    state FINISHED (3) three times after the last sample
 *
 * header.sequence counts the sender's datagrams of that kind from 0, +1 each.
 * header.sender_time_ns is the sender's own monotonic clock (any epoch).
 * START: the rig takes sample 0 start_delay_ns after the START datagram arrived and runs
 * at period_ns (refuse a START whose period_ns differs from the rig's own by more than
 * rounding; fastemu likewise checks the status datagram's period). The rig's clock
 * then runs free: fastemu steps its model once per sample, whenever it arrives.
 * Echo for the link's round trip: each sample carries the sender_time_ns of the newest
 * command datagram the rig received and the rig time since it read that datagram.
 * A silent link is a stale link: no commands -> the rig holds (2d); no samples -> the
 * emulator trips (too-many-stale-samples) and fastemu's controller sends HOLD; after 2 s
 * without any datagram fastemu ends the session.
 */
#ifndef FASTEMU_RIG_H
#define FASTEMU_RIG_H

#include <math.h>
#include <stdint.h>

#define FASTEMU_RIG_ABI_VERSION 4u
#define FASTEMU_LINK_VERSION 3u

/* fastemu_displacement_sample.status */
#define FASTEMU_SAMPLE_OK 0u          /* reading valid */
#define FASTEMU_SAMPLE_SENSOR_FAULT 1u /* the rig knows the reading is invalid: the emulator trips */
#define FASTEMU_SAMPLE_END_OF_RUN 2u  /* the rig's last sample of the session */

/* rig state (samples, heartbeats, status datagrams) */
#define FASTEMU_RIG_STARTING 0u
#define FASTEMU_RIG_RUNNING 1u       /* force control (FORCE or LAW commands) */
#define FASTEMU_RIG_HOLD 2u          /* interlock: position hold where it tripped */
#define FASTEMU_RIG_FINISHED 3u
#define FASTEMU_RIG_UNLOAD 4u        /* position hold while the programme unloads */
#define FASTEMU_RIG_OPERATOR_HOLD 5u /* operator hold: resumes on RESUME */
#define FASTEMU_HEARTBEAT_READY 100u /* before START */

/* fastemu_actuator_command.mode */
#define FASTEMU_MODE_FORCE 0u
#define FASTEMU_MODE_LAW 1u
#define FASTEMU_MODE_HOLD 2u
#define FASTEMU_MODE_HOLD_UNLOAD 3u

/* fastemu_actuator_command.controller_state */
#define FASTEMU_CONTROLLER_STARTING 0u
#define FASTEMU_CONTROLLER_RUNNING 1u
#define FASTEMU_CONTROLLER_FAULT_INDICATED 2u
#define FASTEMU_CONTROLLER_HOLDING 3u
#define FASTEMU_CONTROLLER_STOPPED 4u

/* fastemu_heartbeat.process */
#define FASTEMU_PROCESS_RIG 0u
#define FASTEMU_PROCESS_EMULATOR 1u
#define FASTEMU_PROCESS_CONTROLLER 2u

/* fastemu_run_control.command, fastemu_link_control.command */
#define FASTEMU_RUN_START 1u
#define FASTEMU_RUN_STOP 2u
#define FASTEMU_RUN_HOLD 3u
#define FASTEMU_RUN_RESUME 4u
#define FASTEMU_RUN_END 5u

/* fault codes a rig reports (fault_code fields) or receives (command.fault_code) */
#define FASTEMU_FAULT_NONE 0u
#define FASTEMU_FAULT_NON_FINITE_SAMPLE 1u
#define FASTEMU_FAULT_DISPLACEMENT_OUT_OF_RANGE 2u
#define FASTEMU_FAULT_SEQUENCE_BACKWARDS 3u
#define FASTEMU_FAULT_TOO_MANY_STALE_SAMPLES 4u
#define FASTEMU_FAULT_SENSOR_FAULT 5u
#define FASTEMU_FAULT_EMULATOR_STALLED 6u
#define FASTEMU_FAULT_LOOP_UNSTABLE 7u     /* the loop generated energy or oscillated */
#define FASTEMU_FAULT_SETPOINTS_STALE 10u
#define FASTEMU_FAULT_EMULATOR_HEARTBEAT_LOST 11u
#define FASTEMU_FAULT_EMULATOR_TRIPPED 12u
#define FASTEMU_FAULT_FORCE_LIMIT_EXCEEDED 13u
#define FASTEMU_FAULT_INVALID_LAW 14u
#define FASTEMU_FAULT_COMMANDS_STALE 20u   /* the rig's own: no command for N periods */
#define FASTEMU_FAULT_ORCHESTRATOR_LOST 21u
#define FASTEMU_FAULT_HOLD_REQUESTED 22u   /* the rig's own: a HOLD command arrived */

/* ---- iceoryx2 payloads (natural alignment, 8-byte aligned) ---------------------------- */

/* Rig -> emulator, "fastemu::DisplacementSample", 64 bytes. */
typedef struct fastemu_displacement_sample {
    uint64_t sequence;        /*  0  sample counter k, from 0, +1 per period               */
    uint64_t rig_time_ns;     /*  8  k * T, the sample instant on the rig's clock, ns      */
    uint64_t publish_time_ns; /* 16  CLOCK_MONOTONIC when published, ns                    */
    double displacement_m;    /* 24  measured displacement, m, + compression               */
    double actuator_force_n;  /* 32  measured actuator force, N, + pushing back; NaN: none */
    uint32_t status;          /* 40  FASTEMU_SAMPLE_*                                      */
    uint32_t rig_state;       /* 44  FASTEMU_RIG_*                                         */
    uint32_t rig_fault_code;  /* 48  the rig's latched fault, 0 none                       */
    uint32_t reserved;        /* 52  0                                                     */
    double commanded_force_n; /* 56  the force command applied over the period before the  */
                              /*     sample, N: what the rig asked its actuator for         */
                              /*     (law / gain + damping, or its own hold servo's         */
                              /*     command); NaN: not reported. fastemu reads the          */
                              /*     actuator's gain as measured / commanded at rest (the   */
                              /*     first samples, under the rig's servo) (ABI 4)          */
} fastemu_displacement_sample;

/* The element's local linear law at an operating point (see fastemu_law_evaluate), 56 bytes. */
typedef struct fastemu_local_law {
    double force_n;                  /*  0  element force at the operating point, N        */
    double displacement_m;           /*  8  z0: displacement the force belongs to, m       */
    double velocity_m_per_s;         /* 16  v0: velocity the force belongs to, m/s         */
    double stiffness_n_per_m;        /* 24  tangent stiffness, N/m (>= 0)                  */
    double damping_ns_per_m;         /* 32  tangent damping, N s/m (>= 0)                  */
    double force_rate_n_per_s;       /* 40  force drift at fixed displacement, N/s         */
    double stiffness_slope_n_per_m2; /* 48  change of stiffness with displacement, N/m^2   */
} fastemu_local_law;

/* How the rig turns a LAW command into its force command (2c), 40 bytes. */
typedef struct fastemu_compensation {
    double lead_s;                  /*  0  prediction horizon L, s (0 .. 0.02)              */
    double added_damping_ns_per_m;  /*  8  guard damping D on v_hp, N s/m (>= 0)            */
    double added_damping_corner_hz; /* 16  high-pass corner of v_hp, Hz (>= 0; 0: none)     */
    double gain;                    /* 24  actuator force per command g (0.25 .. 4)         */
    uint32_t lead_order;            /* 32  prediction polynomial order n (0-3)              */
    uint32_t reserved;              /* 36                                                   */
} fastemu_compensation;

/* Controller -> rig, "fastemu::ActuatorCommand", 160 bytes. */
typedef struct fastemu_actuator_command {
    uint64_t sequence;               /*   0  command counter (keep-alive repeats get new ones) */
    uint64_t setpoint_sequence;      /*   8  setpoint behind it (a repeat keeps it)            */
    uint64_t sample_sequence;        /*  16  sample the law answers; UINT64_MAX none           */
    uint64_t sample_publish_time_ns; /*  24  that sample's publish_time_ns                     */
    fastemu_local_law law;           /*  32  the law (FORCE: only law.force_n)                 */
    double force_min_n;              /*  88  limits of the force in FORCE/LAW modes, N         */
    double force_max_n;              /*  96                                                    */
    uint32_t mode;                   /* 104  FASTEMU_MODE_*                                    */
    uint32_t controller_state;       /* 108  FASTEMU_CONTROLLER_*                              */
    uint32_t fault_code;             /* 112  the controller's latched fault, 0 none            */
    uint32_t reserved;               /* 116                                                    */
    fastemu_compensation compensation; /* 120  LAW: lead, guard damping, gain (2c)            */
} fastemu_actuator_command;

/* Any process -> hil, "fastemu::Heartbeat", 32 bytes. */
typedef struct fastemu_heartbeat {
    uint32_t process;    /*  0  FASTEMU_PROCESS_RIG for a rig                 */
    uint32_t state;      /*  4  FASTEMU_HEARTBEAT_READY, then FASTEMU_RIG_*   */
    uint64_t sequence;   /*  8  heartbeat counter                              */
    uint64_t time_ns;    /* 16  CLOCK_MONOTONIC, ns                            */
    uint32_t fault_code; /* 24  the rig's latched fault, 0 none                */
    uint32_t reserved;   /* 28  0                                              */
} fastemu_heartbeat;

/* hil -> every process, "fastemu::RunControl", 32 bytes. */
typedef struct fastemu_run_control {
    uint64_t sequence;      /*  0                                                      */
    uint64_t start_time_ns; /*  8  START: CLOCK_MONOTONIC of sample 0                  */
    uint64_t start_unix_ns; /* 16  START: wall-clock (Unix epoch) at start_time_ns     */
    uint32_t command;       /* 24  FASTEMU_RUN_*                                       */
    uint32_t reserved;      /* 28                                                      */
} fastemu_run_control;

/* ---- UDP datagrams (little-endian, no padding; sizes exact) ---------------------------- */

typedef struct fastemu_link_header {
    uint8_t magic[4];        /*  0  'F' 'E' 'M' 'U'                          */
    uint16_t version;        /*  4  FASTEMU_LINK_VERSION                     */
    uint16_t kind;           /*  6  FASTEMU_LINK_SAMPLE ...                  */
    uint64_t sequence;       /*  8  sender's counter of this kind, from 0    */
    uint64_t sender_time_ns; /* 16  sender's monotonic clock, ns             */
} fastemu_link_header;       /* 24 bytes */

#define FASTEMU_LINK_SAMPLE 1u
#define FASTEMU_LINK_COMMAND 2u
#define FASTEMU_LINK_CONTROL 3u
#define FASTEMU_LINK_STATUS 4u

/* Rig -> fastemu, 96 bytes. */
typedef struct fastemu_link_sample {
    fastemu_link_header header;    /*  0                                                    */
    uint64_t sample_sequence;      /* 24  k                                                 */
    uint64_t rig_time_ns;          /* 32  k * T on the rig's clock                          */
    double displacement_m;         /* 40  measured, m, + compression                        */
    double actuator_force_n;       /* 48  measured, N; NaN: not measured                    */
    uint32_t status;               /* 56  FASTEMU_SAMPLE_*                                  */
    uint32_t rig_state;            /* 60  FASTEMU_RIG_*                                     */
    uint32_t rig_fault_code;       /* 64                                                    */
    uint32_t reserved;             /* 68  0                                                 */
    uint64_t echo_command_time_ns; /* 72  sender_time_ns of the newest command; 0 none yet  */
    uint64_t echo_hold_ns;         /* 80  rig clock from reading that command to now        */
    double commanded_force_n;      /* 88  command over the period before, N; NaN: none      */
} fastemu_link_sample;

/* fastemu -> rig, 184 bytes: fastemu_actuator_command's content. */
typedef struct fastemu_link_command {
    fastemu_link_header header;   /*   0                                                   */
    uint64_t command_sequence;    /*  24                                                   */
    uint64_t setpoint_sequence;   /*  32                                                   */
    uint64_t sample_sequence;     /*  40  UINT64_MAX none                                  */
    fastemu_local_law law;        /*  48                                                   */
    double force_min_n;           /* 104                                                   */
    double force_max_n;           /* 112                                                   */
    uint32_t mode;                /* 120  FASTEMU_MODE_*                                   */
    uint32_t controller_state;    /* 124                                                   */
    uint32_t fault_code;          /* 128                                                   */
    uint32_t reserved;            /* 132                                                   */
    uint64_t echo_sample_time_ns; /* 136  sender_time_ns of the newest sample fastemu got  */
    fastemu_compensation compensation; /* 144  LAW: lead, guard damping, gain (2c)       */
} fastemu_link_command;

/* fastemu -> rig, 56 bytes. */
typedef struct fastemu_link_control {
    fastemu_link_header header; /*  0                                                     */
    uint32_t command;           /* 24  FASTEMU_RUN_*                                      */
    uint32_t reserved;          /* 28                                                     */
    uint64_t control_sequence;  /* 32  act once per value (repeats carry the same)        */
    uint64_t start_delay_ns;    /* 40  START: sample 0 this long after arrival            */
    uint64_t period_ns;         /* 48  the loop period T, ns                              */
} fastemu_link_control;

/* Rig -> fastemu, 40 bytes. */
typedef struct fastemu_link_status {
    fastemu_link_header header; /*  0                                               */
    uint32_t rig_state;         /* 24  FASTEMU_HEARTBEAT_READY or FASTEMU_RIG_*      */
    uint32_t rig_fault_code;    /* 28                                               */
    uint64_t period_ns;         /* 32  the rig's period T, ns                       */
} fastemu_link_status;

#if defined(__STDC_VERSION__) && __STDC_VERSION__ >= 201112L
_Static_assert(sizeof(fastemu_displacement_sample) == 64, "rig ABI 4");
_Static_assert(sizeof(fastemu_local_law) == 56, "rig ABI 4");
_Static_assert(sizeof(fastemu_compensation) == 40, "rig ABI 4");
_Static_assert(sizeof(fastemu_actuator_command) == 160, "rig ABI 4");
_Static_assert(sizeof(fastemu_heartbeat) == 32, "rig ABI 4");
_Static_assert(sizeof(fastemu_run_control) == 32, "rig ABI 4");
_Static_assert(sizeof(fastemu_link_header) == 24, "link protocol 3");
_Static_assert(sizeof(fastemu_link_sample) == 96, "link protocol 3");
_Static_assert(sizeof(fastemu_link_command) == 184, "link protocol 3");
_Static_assert(sizeof(fastemu_link_control) == 56, "link protocol 3");
_Static_assert(sizeof(fastemu_link_status) == 40, "link protocol 3");
#endif

/* The law's force at displacement z (m), velocity v (m/s), since_s after its sample:
 *   F = force_n + (k + s (z - z0) / 2) (z - z0) + c (v - v0) + r since_s
 * with z0 = displacement_m, v0 = velocity_m_per_s, k = stiffness_n_per_m,
 * s = stiffness_slope_n_per_m2, c = damping_ns_per_m, r = force_rate_n_per_s. */
static inline double fastemu_law_evaluate(const fastemu_local_law *law, double z, double v,
                                          double since_s) {
    double dz = z - law->displacement_m;
    return law->force_n + (law->stiffness_n_per_m + 0.5 * law->stiffness_slope_n_per_m2 * dz) * dz +
           law->damping_ns_per_m * (v - law->velocity_m_per_s) + law->force_rate_n_per_s * since_s;
}

/* Weights of the Lagrange polynomial through the newest order+1 measurements (newest
 * first, spacing h = T, nodes t_i = -i h) for its value and slope at `lead` (s) past the
 * newest: z_L = sum value[i] z_{k-i}, v_L = sum slope[i] z_{k-i}, i = 0..order (order
 * 0-3; unused weights are 0). Recompute when a command's lead or order changes. */
static inline void fastemu_lead_weights(unsigned order, double h, double lead, double value[4],
                                        double slope[4]) {
    unsigned n = (order > 3 ? 3 : order) + 1, i, j, m;
    double t[4];
    for (i = 0; i < 4; i++) {
        t[i] = -(double)i * h;
        value[i] = 0.0;
        slope[i] = 0.0;
    }
    for (i = 0; i < n; i++) {
        double li = 1.0, d = 0.0;
        for (j = 0; j < n; j++)
            if (j != i) li *= (lead - t[j]) / (t[i] - t[j]);
        for (m = 0; m < n; m++) {
            double term;
            if (m == i) continue;
            term = 1.0 / (t[i] - t[m]);
            for (j = 0; j < n; j++)
                if (j != i && j != m) term *= (lead - t[j]) / (t[i] - t[j]);
            d += term;
        }
        value[i] = li;
        slope[i] = d;
    }
}

/* Whether a LAW command's compensation may be acted on (else drop the command, 2b). */
static inline int fastemu_compensation_ok(const fastemu_compensation *c) {
    return c->lead_s >= 0.0 && c->lead_s <= 0.02 && c->added_damping_ns_per_m >= 0.0 &&
           c->added_damping_ns_per_m <= 1e300 && c->added_damping_corner_hz >= 0.0 &&
           c->added_damping_corner_hz <= 1e300 && c->gain >= 0.25 && c->gain <= 4.0 &&
           c->lead_order <= 3; /* comparisons are false for NaN */
}

/* The rig's state for LAW commands: the newest four measurements and the guard's
 * velocity low-pass. Zero it, then fill z[] with the starting displacement. */
typedef struct fastemu_law_state {
    double z[4];       /* newest first, m                                   */
    double value[4];   /* fastemu_lead_weights for (order, lead) below      */
    double slope[4];
    double lead_s;     /* the lead the weights belong to (-1: none yet)     */
    unsigned order;
    double v_lp;       /* low-passed predicted velocity, m/s                */
} fastemu_law_state;

/* Every period k in LAW mode (2c): push the measurement z_k, then the force to command,
 * N, for `cmd` (its law, limits and compensation) at period k with period T (s);
 * stale_limit_s = N * T bounds since_s. Also call it (and ignore the result) in other
 * modes so the state follows the measurement: with the newest LAW command, or, before
 * the first one, a zeroed command with compensation.gain = 1 (a FORCE or HOLD command's
 * compensation is not checked, 2b: never pass it). */
static inline double fastemu_compensated_force(fastemu_law_state *st,
                                               const fastemu_actuator_command *cmd, double z_k,
                                               uint64_t k, double T, double stale_limit_s) {
    const fastemu_compensation *c = &cmd->compensation;
    double zl = 0.0, vl = 0.0, since_s, v_hp, f;
    unsigned i;
    st->z[3] = st->z[2];
    st->z[2] = st->z[1];
    st->z[1] = st->z[0];
    st->z[0] = z_k;
    if (c->lead_s != st->lead_s || c->lead_order != st->order) {
        fastemu_lead_weights(c->lead_order, T, c->lead_s, st->value, st->slope);
        st->lead_s = c->lead_s;
        st->order = c->lead_order;
    }
    for (i = 0; i < 4; i++) {
        zl += st->value[i] * st->z[i];
        vl += st->slope[i] * st->z[i];
    }
    if (c->added_damping_corner_hz > 0.0) {
        double a = 1.0 - exp(-2.0 * 3.14159265358979323846 * c->added_damping_corner_hz * T);
        st->v_lp += a * (vl - st->v_lp);
        v_hp = vl - st->v_lp;
    } else {
        st->v_lp = vl;
        v_hp = vl;
    }
    since_s = cmd->sample_sequence == UINT64_MAX
                  ? 0.0
                  : (double)(k > cmd->sample_sequence ? k - cmd->sample_sequence : 0) * T +
                        c->lead_s;
    if (since_s > stale_limit_s) since_s = stale_limit_s;
    f = fastemu_law_evaluate(&cmd->law, zl, vl, since_s) + c->added_damping_ns_per_m * v_hp;
    if (f > cmd->force_max_n) f = cmd->force_max_n;
    if (f < cmd->force_min_n) f = cmd->force_min_n;
    return f / c->gain;
}

#endif /* FASTEMU_RIG_H */
