//! Fixed-size `#[repr(C)]` messages carried on the loop's publish-subscribe services: the
//! rig ABI (`ABI_VERSION`). A rig that fastemu did not start publishes `DisplacementSample`
//! and `Heartbeat`, and consumes `ActuatorCommand` and `RunControl`, with exactly these
//! layouts (`include/fastemu_rig.h`, README "Connecting a rig"; a test checks the header's
//! sizes and offsets against these types).
//!
//! Times are `CLOCK_MONOTONIC` nanoseconds (the same base in every process on one
//! machine), so a timestamp set by the rig can be compared with the controller's clock for
//! end-to-end latency. Every message carries the sequence numbers it answers, so records
//! from the processes can be joined. Must not: hold pointers, `Vec` or `String` (zero-copy).

use iceoryx2::prelude::ZeroCopySend;

/// Version of the message layouts and their meaning; bumped on any change.
/// 2: `DisplacementSample` carries the rig's measured force, state and latched fault.
/// 3: `ActuatorCommand` carries the controller's `Compensation` (output lead, actuator
/// gain, guard damping): the rig no longer has a lead of its own.
/// 4: `DisplacementSample` carries the force the rig commanded its actuator
/// (`commanded_force_n`), so the controller reads the actuator's gain from the rig's own
/// equilibrium before its first command.
pub const ABI_VERSION: u32 = 4;

/// Status of a displacement sample (`DisplacementSample::status`).
pub mod sample_status {
    /// Sensor reading valid.
    pub const OK: u32 = 0;
    /// The rig knows the sensor value is invalid (e.g. out of its measuring range).
    pub const SENSOR_FAULT: u32 = 1;
    /// The rig is stopping: last sample of the run.
    pub const END_OF_RUN: u32 = 2;
}

/// Rig -> emulator: one measured displacement sample.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::DisplacementSample")]
#[repr(C)]
pub struct DisplacementSample {
    /// Sample counter, strictly increasing from 0.
    pub sequence: u64,
    /// Rig time of the sample (its own clock, starting at 0), ns.
    pub rig_time_ns: u64,
    /// Monotonic time when the sample was published, ns (end-to-end latency start).
    pub publish_time_ns: u64,
    /// Measured displacement, m, positive in compression.
    pub displacement_m: f64,
    /// Force the actuator applies at the sample instant (load cell), N, positive pushing
    /// against compression; NaN when the rig does not measure it.
    pub actuator_force_n: f64,
    /// One of `sample_status`.
    pub status: u32,
    /// The rig's state at the sample (`rig_state`).
    pub rig_state: u32,
    /// The rig's latched fault code (its own interlock, e.g. `commands-stale`), 0 none.
    pub rig_fault_code: u32,
    pub reserved: u32,
    /// The force command applied over the period before the sample, N (what the rig asked
    /// its actuator for: the evaluated law divided by the gain, the
    /// guard's damping, or its own hold servo's command); NaN when the rig does not say.
    /// Measured over commanded force at rest is the actuator's gain.
    pub commanded_force_n: f64,
}

/// The element's local linear law at an operating point: near the point, the force the
/// element exerts at displacement `z`, velocity `v` and time `t` is
///
/// `force_n + (stiffness_n_per_m + stiffness_slope_n_per_m2 (z - z0) / 2) (z - z0)
///  + damping_ns_per_m (v - velocity_m_per_s) + force_rate_n_per_s (t - t0)`,
/// `z0 = displacement_m`,
///
/// where `t0` is the instant of the displacement sample the law answers (the command's
/// `sample_sequence`, on the actuator side's own sample clock). `force_rate_n_per_s` is the
/// force's drift at fixed displacement (the element's relaxation).
///
/// The actuator side evaluates it at its own rate with its own displacement measurement
/// until the next command arrives, so a short stall of the loop leaves the specimen on the
/// element's linearised law, never on a constant force.
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("fastemu::LocalLaw")]
#[repr(C)]
pub struct LocalLaw {
    /// Element force at the operating point, N, positive in compression.
    pub force_n: f64,
    /// Displacement the force belongs to, m.
    pub displacement_m: f64,
    /// Velocity the force belongs to, m/s.
    pub velocity_m_per_s: f64,
    /// Tangent stiffness at the operating point, N/m (>= 0).
    pub stiffness_n_per_m: f64,
    /// Tangent damping at the operating point, N s/m (>= 0).
    pub damping_ns_per_m: f64,
    /// Force drift at fixed displacement (relaxation), N/s.
    pub force_rate_n_per_s: f64,
    /// Change of the stiffness with displacement (the element's nonlinearity), N/m^2.
    pub stiffness_slope_n_per_m2: f64,
}

impl LocalLaw {
    /// A plain force: no dependence on displacement, velocity or time.
    pub fn constant(force_n: f64) -> LocalLaw {
        LocalLaw {
            force_n,
            ..LocalLaw::default()
        }
    }

    /// The law's force at displacement `z_m`, velocity `v_m_per_s`, `since_s` after the
    /// instant of its sample, N.
    #[inline]
    pub fn evaluate(&self, z_m: f64, v_m_per_s: f64, since_s: f64) -> f64 {
        let dz = z_m - self.displacement_m;
        self.force_n
            + (self.stiffness_n_per_m + 0.5 * self.stiffness_slope_n_per_m2 * dz) * dz
            + self.damping_ns_per_m * (v_m_per_s - self.velocity_m_per_s)
            + self.force_rate_n_per_s * since_s
    }

    /// Whether every field is finite and the stiffness and damping are not negative.
    pub fn is_valid(&self) -> bool {
        [
            self.force_n,
            self.displacement_m,
            self.velocity_m_per_s,
            self.stiffness_n_per_m,
            self.damping_ns_per_m,
            self.force_rate_n_per_s,
            self.stiffness_slope_n_per_m2,
        ]
        .iter()
        .all(|v| v.is_finite())
            && self.stiffness_n_per_m >= 0.0
            && self.damping_ns_per_m >= 0.0
    }
}

impl From<crate::model::effects::LocalLinearLaw> for LocalLaw {
    fn from(l: crate::model::effects::LocalLinearLaw) -> LocalLaw {
        LocalLaw {
            force_n: l.force_n,
            displacement_m: l.displacement_m,
            velocity_m_per_s: l.velocity_m_per_s,
            stiffness_n_per_m: l.stiffness_n_per_m,
            damping_ns_per_m: l.damping_ns_per_m,
            force_rate_n_per_s: l.force_rate_n_per_s,
            stiffness_slope_n_per_m2: l.stiffness_slope_n_per_m2,
        }
    }
}

/// Emulator state carried in `ForceSetpoint::emulator_state` and heartbeats.
pub mod emulator_state {
    pub const STARTING: u32 = 0;
    pub const RUNNING: u32 = 1;
    /// A fault is latched (see the fault code): the model no longer steps.
    pub const TRIPPED: u32 = 2;
    pub const STOPPED: u32 = 3;
}

/// Emulator -> controller: the element's force and local law answering one sample.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::ForceSetpoint")]
#[repr(C)]
pub struct ForceSetpoint {
    /// Setpoint counter (one per emulator cycle), from 0.
    pub sequence: u64,
    /// Sequence of the newest displacement sample the model has stepped through.
    pub sample_sequence: u64,
    /// `publish_time_ns` of that sample (carried through for end-to-end latency).
    pub sample_publish_time_ns: u64,
    /// Emulator loop time of this cycle's deadline, ns since the loop started.
    pub loop_time_ns: u64,
    /// The element's law at that sample (`law.force_n` is the element force).
    pub law: LocalLaw,
    /// One of `emulator_state`.
    pub emulator_state: u32,
    /// Fault code when tripped (see the runtime's fault enum), else 0.
    pub fault_code: u32,
    /// Model step flags (`StepFlags` bits).
    pub model_flags: u32,
    /// The rig's state in that sample (`rig_state`): the controller learns the actuator
    /// only while the rig is in force control.
    pub rig_state: u32,
    /// The force the rig measured at that sample (its `actuator_force_n`), N; NaN when the
    /// rig does not measure it. The controller learns the actuator from it.
    pub measured_force_n: f64,
    /// The force the rig had commanded at that sample (its `commanded_force_n`), N; NaN
    /// when the rig does not say.
    pub commanded_force_n: f64,
}

/// What the actuator side does with an `ActuatorCommand` (`ActuatorCommand::mode`).
pub mod command_mode {
    /// Force control: apply `law.force_n` (zero-order hold until the next command).
    pub const FORCE: u32 = 0;
    /// Force control on the local law: every actuator period, apply `law.evaluate(z, v,
    /// t - t0)` with the actuator side's own displacement `z` and velocity `v` (extrapolated
    /// over its own output delay) and the time since the instant of sample
    /// `sample_sequence`, clamped to `force_min_n..=force_max_n`.
    pub const LAW: u32 = 1;
    /// Interlock: leave force control and hold the specimen's position where it is now
    /// (position control); hold the load programme too.
    pub const HOLD: u32 = 2;
    /// As `HOLD`, then, once the specimen is at rest, unload the load programme to zero
    /// while holding position.
    pub const HOLD_UNLOAD: u32 = 3;
}

/// Controller -> rig: the actuator command.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::ActuatorCommand")]
#[repr(C)]
pub struct ActuatorCommand {
    /// Command counter, from 0 (keep-alive repeats get new numbers).
    pub sequence: u64,
    /// Setpoint this command answers (a repeat keeps it: the law is the same).
    pub setpoint_sequence: u64,
    /// Displacement sample at the origin of the chain.
    pub sample_sequence: u64,
    /// `publish_time_ns` of that sample.
    pub sample_publish_time_ns: u64,
    /// The element's law (`FORCE`: only `law.force_n` is used). Positive force pushes
    /// back against compression: the actuator applies the element's reaction.
    pub law: LocalLaw,
    /// Limits of the force the actuator side may apply in `FORCE`/`LAW` modes, N.
    pub force_min_n: f64,
    pub force_max_n: f64,
    /// One of `command_mode`.
    pub mode: u32,
    /// One of `controller_state`.
    pub controller_state: u32,
    /// Latched fault code, 0 if none.
    pub fault_code: u32,
    pub reserved: u32,
    /// How the actuator side turns the law into its force command (`LAW` mode).
    pub compensation: Compensation,
}

/// The controller's compensation of the actuator, sent with every command (ABI 3): the
/// actuator side, every period in `LAW` mode, predicts its displacement and velocity
/// `lead_s` ahead (Lagrange polynomial of order `lead_order` through its newest
/// `lead_order + 1` measurements), evaluates the law there, adds
/// `added_damping_ns_per_m` times the high-passed velocity (first-order high-pass with
/// corner `added_damping_corner_hz`; 0 = the whole velocity), clamps to the command's
/// limits and divides by `gain` (the actuator's identified force per commanded force):
///
/// `u = clamp(law(z(t + lead), v(t + lead)) + D v_hp(t + lead), min, max) / gain`.
///
/// The added damping opposes the specimen's velocity: it pushes like the element's own
/// damping (force positive in compression, so `+ D v` in the element's reaction).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::Compensation")]
#[repr(C)]
pub struct Compensation {
    /// Prediction horizon: the actuator's effective output delay (zero-order hold,
    /// transport, lag) as the controller identified it, s; 0..=`MAX_LEAD_S`.
    pub lead_s: f64,
    /// Damping the passivity guard adds while the loop generates energy, N s/m (>= 0).
    pub added_damping_ns_per_m: f64,
    /// Corner of the first-order high-pass on the velocity the added damping acts on, Hz
    /// (>= 0; 0 = no high-pass). It keeps the guard out of the band that carries the load.
    pub added_damping_corner_hz: f64,
    /// The actuator's force per commanded force, as identified (`MIN_GAIN..=MAX_GAIN`).
    pub gain: f64,
    /// Order of the prediction polynomial, 0-3.
    pub lead_order: u32,
    pub reserved: u32,
}

impl Compensation {
    /// Longest prediction a rig accepts, s.
    pub const MAX_LEAD_S: f64 = 0.02;
    pub const MIN_GAIN: f64 = 0.25;
    pub const MAX_GAIN: f64 = 4.0;

    /// No compensation: the law at the newest measurement, unit gain, no added damping.
    pub const NONE: Compensation = Compensation {
        lead_s: 0.0,
        added_damping_ns_per_m: 0.0,
        added_damping_corner_hz: 0.0,
        gain: 1.0,
        lead_order: 0,
        reserved: 0,
    };

    /// A plain lead of `lead_s` with a polynomial of `order`.
    pub fn lead(lead_s: f64, order: u32) -> Compensation {
        Compensation {
            lead_s,
            lead_order: order,
            ..Compensation::NONE
        }
    }

    /// Whether a rig may act on it: finite, within the documented ranges.
    #[inline]
    pub fn is_valid(&self) -> bool {
        self.lead_s.is_finite()
            && (0.0..=Self::MAX_LEAD_S).contains(&self.lead_s)
            && self.added_damping_ns_per_m.is_finite()
            && self.added_damping_ns_per_m >= 0.0
            && self.added_damping_corner_hz.is_finite()
            && self.added_damping_corner_hz >= 0.0
            && self.gain.is_finite()
            && (Self::MIN_GAIN..=Self::MAX_GAIN).contains(&self.gain)
            && self.lead_order <= 3
    }
}

impl Default for Compensation {
    fn default() -> Compensation {
        Compensation::NONE
    }
}

impl ActuatorCommand {
    /// Whether a rig may act on this command: a known mode, ordered finite limits, and
    /// for force and law commands a finite law (a hold needs no law). A rig drops any
    /// other command as if it had not arrived, so a stream of them ends in its own
    /// commands-stale hold. One check for every transport (iceoryx2 and the UDP link).
    #[inline]
    pub fn content_ok(&self) -> bool {
        let limits = self.force_min_n.is_finite()
            && self.force_max_n.is_finite()
            && self.force_min_n <= self.force_max_n;
        let l = &self.law;
        let law = [
            l.force_n,
            l.displacement_m,
            l.velocity_m_per_s,
            l.stiffness_n_per_m,
            l.damping_ns_per_m,
            l.force_rate_n_per_s,
            l.stiffness_slope_n_per_m2,
        ]
        .iter()
        .all(|x| x.is_finite());
        match self.mode {
            command_mode::FORCE => limits && law,
            command_mode::LAW => limits && law && self.compensation.is_valid(),
            command_mode::HOLD | command_mode::HOLD_UNLOAD => true,
            _ => false,
        }
    }
}

/// Any process -> orchestrator: liveness and state.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::Heartbeat")]
#[repr(C)]
pub struct Heartbeat {
    /// Which process (`process_id`).
    pub process: u32,
    pub state: u32,
    pub sequence: u64,
    pub time_ns: u64,
    pub fault_code: u32,
    /// Controller: the emulator's fault code when it reported itself tripped.
    pub reserved: u32,
}

/// Controller state carried in `ActuatorCommand::controller_state` and heartbeats.
pub mod controller_state {
    pub const STARTING: u32 = 0;
    pub const RUNNING: u32 = 1;
    /// A fault is latched and its action is "indicate": commands go on.
    pub const FAULT_INDICATED: u32 = 2;
    /// A fault is latched: the commands ask the actuator side to hold the specimen.
    pub const HOLDING: u32 = 3;
    pub const STOPPED: u32 = 4;
}

/// Rig state carried in heartbeats and the rig's records.
pub mod rig_state {
    pub const STARTING: u32 = 0;
    /// Force control (law or force commands).
    pub const RUNNING: u32 = 1;
    /// Interlock: position hold where it tripped, load programme held.
    pub const HOLD: u32 = 2;
    pub const FINISHED: u32 = 3;
    /// Position hold while the load programme unloads to zero.
    pub const UNLOAD: u32 = 4;
    /// Operator hold: position hold, programme paused; resumes on request.
    pub const OPERATOR_HOLD: u32 = 5;
}

/// Process ids carried in `Heartbeat::process`.
pub mod process_id {
    pub const RIG: u32 = 0;
    pub const EMULATOR: u32 = 1;
    pub const CONTROLLER: u32 = 2;
    /// The orchestrator (`fastemu hil`), on its operator-status service only (its answers
    /// to `fastemu ctl`); never on a rig's services.
    pub const HIL: u32 = 3;
}

/// The orchestrator's answer to a `fastemu ctl` request: a `Heartbeat` on the operator
/// status service with `process = process_id::HIL`, `sequence` the request's, `state`
/// one of these and `reserved` the request's command.
pub mod operator_answer {
    /// Relayed to the rig on the run's control stream.
    pub const RELAYED: u32 = 1;
    /// A stop before the start: the run ends without starting.
    pub const ENDED_BEFORE_START: u32 = 2;
    /// A hold or resume before the start: nothing to act on.
    pub const IGNORED_BEFORE_START: u32 = 3;
    /// A command `ctl` does not send.
    pub const UNKNOWN: u32 = 4;
    /// A hold or resume after a stop was sent: the run is ending (a stop is not taken
    /// back).
    pub const IGNORED_ENDING: u32 = 5;
}

/// Heartbeat state meaning "ports created, waiting for the start command" (all processes).
pub const HEARTBEAT_READY: u32 = 100;

/// Run-control commands (`RunControl::command`).
pub mod run_command {
    /// Start the loops: first deadline at `RunControl::start_time_ns`.
    pub const START: u32 = 1;
    /// Stop now: flush records and exit (sent once the rig has finished).
    pub const STOP: u32 = 2;
    /// Operator hold: the rig holds position and pauses the load programme.
    pub const HOLD: u32 = 3;
    /// Operator resume: back to force control, the programme continues without a jump.
    pub const RESUME: u32 = 4;
    /// Orderly end: hold, unload the programme to zero, then finish the run.
    pub const END: u32 = 5;
}

/// Orchestrator -> every process: start time and run control.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::RunControl")]
#[repr(C)]
pub struct RunControl {
    pub sequence: u64,
    /// `CLOCK_MONOTONIC` time of the rig's first sample, ns; every loop's grid is
    /// `start_time_ns + k * period` (plus its own phase offset).
    pub start_time_ns: u64,
    /// Wall-clock time (Unix epoch, ns) at `start_time_ns`: the records' time base.
    pub start_unix_ns: u64,
    /// One of `run_command`.
    pub command: u32,
    pub reserved: u32,
}
