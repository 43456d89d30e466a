//! The actuator's servo controller on the rig side: what a real servo controller (or a
//! calculated channel, a Speedgoat or dSPACE model) runs every actuator period.
//!
//! - `LAW` commands: applies the element's local linear law with the rig's own
//!   displacement measurement, predicted over the lead the command's `Compensation` names
//!   (the controller's estimate of the actuator's output delay), plus the passivity
//!   guard's damping on the high-passed velocity, divided by the identified actuator gain,
//!   so neither the loop's delay nor a short stall of the loop leaves the specimen on a
//!   constant force.
//! - `FORCE` commands: applies the force (zero-order hold).
//! - The interlock: stale commands, a hold command, a lost orchestrator or an operator
//!   hold make it leave force control and hold the specimen's position where it tripped
//!   (PID position control, as a servo controller's interlock does); the load programme
//!   holds too. Then, when configured, the programme unloads to zero while position is held.
//!
//! Must not: allocate, lock, log, read a clock or do I/O (`update` and `on_command` run in
//! the rig's loop; time is the period index).

use crate::hil::fault::{Fault, FaultAction};
use crate::ipc::messages::{command_mode, rig_state, ActuatorCommand};

/// Longest window for rest detection, samples (50 ms at up to 20 kHz).
const REST_WINDOW_MAX: usize = 1024;

/// Weights of a Lagrange polynomial through the newest `order + 1` equally spaced samples
/// (newest first, spacing `h`) for its value and slope at `lead` past the newest sample.
/// Allocation-free: the servo recomputes them when a command's lead changes.
pub fn lead_weights(order: usize, h: f64, lead: f64) -> ([f64; 4], [f64; 4]) {
    let n = order.min(3) + 1;
    let mut t = [0.0; 4];
    for (i, ti) in t.iter_mut().enumerate().take(n) {
        *ti = -(i as f64) * h;
    }
    let mut value = [0.0; 4];
    let mut slope = [0.0; 4];
    for i in 0..n {
        let mut li = 1.0;
        for j in 0..n {
            if i != j {
                li *= (lead - t[j]) / (t[i] - t[j]);
            }
        }
        value[i] = li;
        // d/dx prod_j (x - t_j)/(t_i - t_j) = sum_m 1/(t_i - t_m) prod_{j != m} (...).
        let mut d = 0.0;
        for m in 0..n {
            if m == i {
                continue;
            }
            let mut term = 1.0 / (t[i] - t[m]);
            for j in 0..n {
                if j != i && j != m {
                    term *= (lead - t[j]) / (t[i] - t[j]);
                }
            }
            d += term;
        }
        slope[i] = d;
    }
    (value, slope)
}

/// The servo controller's settings (from `[rig]` and `[safety]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServoConfig {
    pub period_s: f64,
    /// No new command for more than this many periods: interlock (`commands-stale`).
    pub command_stale_periods: u64,
    /// Position-hold PID gains: N/m, N/(m s), N s/m.
    pub hold_kp: f64,
    pub hold_ki: f64,
    pub hold_kd: f64,
    /// Action on the rig's own detections (commands stale; orchestrator lost).
    pub commands_stale_action: FaultAction,
    pub orchestrator_lost_action: FaultAction,
    /// At rest: the measured displacement stayed within this band over `rest_window_s`, m.
    pub rest_band_m: f64,
    pub rest_window_s: f64,
    /// Minimum and maximum hold before the run ends, s.
    pub hold_min_s: f64,
    pub hold_max_s: f64,
    /// Rate at which an unload takes the programme to zero, N/s.
    pub unload_rate_n_per_s: f64,
    /// Back to force control after an operator hold: blend over this long, s.
    pub resume_blend_s: f64,
    /// The actuator holds position itself (a servo-hydraulic actuator's stroke control on
    /// its own displacement transducer) instead of through a position PID on its force:
    /// the hold then asks it for a position (`ServoOutput::stroke_target_m`).
    pub stroke_hold: bool,
}

impl ServoConfig {
    /// PID gains for a position loop on mass `mass_kg` with closed-loop poles
    /// `(s^2 + 2 zeta w s + w^2)(s + w/4)`, `w = 2 pi bandwidth_hz`.
    pub fn hold_gains(mass_kg: f64, bandwidth_hz: f64, damping_ratio: f64) -> (f64, f64, f64) {
        let w = 2.0 * std::f64::consts::PI * bandwidth_hz;
        let wi = 0.25 * w;
        let kp = mass_kg * (w * w + 2.0 * damping_ratio * w * wi);
        let ki = mass_kg * w * w * wi;
        let kd = mass_kg * (2.0 * damping_ratio * w + wi);
        (kp, ki, kd)
    }
}

/// A trip of the interlock, as the rig records it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Trip {
    pub fault: Fault,
    /// The controller's fault code when it asked for the hold (`hold-requested`), else 0.
    pub remote_fault_code: u32,
    /// Period index of the detection.
    pub step_idx: u64,
    /// Periods between the last good input and the detection.
    pub detection_latency_periods: u64,
    pub action: FaultAction,
    /// Position held, m (measured at the trip).
    pub hold_position_m: f64,
}

/// What the servo asks the actuator for in one period.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServoOutput {
    /// Actuator force command, N.
    pub command_n: f64,
    /// One of `rig_state`.
    pub state: u32,
    /// `command_mode` in effect (`HOLD` while holding).
    pub mode: u32,
    /// Periods since the last command of any kind.
    pub command_age_periods: u64,
    /// Periods since the law last changed (a new setpoint behind the command).
    pub law_age_periods: u64,
    /// Position the actuator must hold in stroke control, m; NaN in force control (and
    /// always with `ServoConfig::stroke_hold` false). While it is finite `command_n` is
    /// the force the actuator measures (what a switch back to force control starts from).
    pub stroke_target_m: f64,
}

/// What the programme must do this period (the servo owns the decision).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProgrammeRequest {
    Run,
    Hold,
    Unload,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    /// From the start until the first command: position hold at the starting position
    /// (a servo controller starts in displacement control), the programme running; the
    /// first force or law command hands over to force control.
    Awaiting,
    Force,
    Holding {
        since_step: u64,
        unload: bool,
        operator: bool,
    },
    /// Back from an operator hold: blend from the (still active) position hold to force
    /// control, so the specimen is restrained by both all through the blend.
    Resuming {
        since_step: u64,
    },
}

/// The servo controller's state.
#[derive(Debug, Clone)]
pub struct Servo {
    cfg: ServoConfig,
    value_weights: [f64; 4],
    slope_weights: [f64; 4],
    /// The (lead, order) the weights were computed for.
    weights_for: (f64, u32),
    /// Low-passed predicted velocity (the guard's damping acts on the rest), m/s.
    velocity_lp_m_per_s: f64,
    /// Measured displacements, newest first.
    z_history_m: [f64; 4],
    command: Option<ActuatorCommand>,
    last_command_step: Option<u64>,
    law_setpoint_seq: u64,
    law_since_step: u64,
    phase: Phase,
    hold_position_m: f64,
    hold_feedforward_n: f64,
    /// External load when the hold began, and now (fed forward while holding).
    hold_load_at_start_n: f64,
    load_now_n: f64,
    hold_integral_m_s: f64,
    last_output_n: f64,
    /// The actuator's measured force this period (its load cell), N.
    measured_force_n: f64,
    /// Stroke-control hold: the measured force when the resume began (the blend's start).
    resume_from_n: f64,
    /// The current period (set by `update`).
    step_idx: u64,
    trip: Option<Trip>,
    new_trip: bool,
    /// Ring of recent measurements for rest detection (allocated once, in `new`).
    rest_ring: Vec<f64>,
    rest_len: usize,
    rest_head: usize,
    rest_filled: usize,
    at_rest_since_step: Option<u64>,
    unload_done: bool,
    finished: bool,
    /// Commands dropped for their content (`ActuatorCommand::content_ok`).
    rejected_commands: u64,
}

impl Servo {
    /// A servo at rest at measured displacement `z0_m` under the load `force0_n`, holding
    /// that position (with `force0_n` fed forward) until the first command arrives.
    pub fn new(cfg: ServoConfig, z0_m: f64, force0_n: f64) -> Servo {
        Servo::converged(cfg, z0_m, force0_n, force0_n)
    }

    /// As `new`, the command that holds the specimen under `force0_n` being `command0_n`
    /// (an actuator with a gain error: `RigPhysics::holding`).
    pub fn converged(cfg: ServoConfig, z0_m: f64, force0_n: f64, command0_n: f64) -> Servo {
        let (value_weights, slope_weights) = lead_weights(0, cfg.period_s, 0.0);
        let rest_len =
            ((cfg.rest_window_s / cfg.period_s).round() as usize).clamp(2, REST_WINDOW_MAX);
        Servo {
            cfg,
            value_weights,
            slope_weights,
            weights_for: (0.0, 0),
            velocity_lp_m_per_s: 0.0,
            z_history_m: [z0_m; 4],
            command: None,
            last_command_step: None,
            law_setpoint_seq: u64::MAX,
            law_since_step: 0,
            phase: Phase::Awaiting,
            hold_position_m: z0_m,
            hold_feedforward_n: command0_n,
            hold_load_at_start_n: force0_n,
            load_now_n: force0_n,
            hold_integral_m_s: 0.0,
            last_output_n: command0_n,
            measured_force_n: force0_n,
            resume_from_n: force0_n,
            step_idx: 0,
            trip: None,
            new_trip: false,
            rest_ring: vec![z0_m; REST_WINDOW_MAX],
            rest_len,
            rest_head: 0,
            rest_filled: 0,
            at_rest_since_step: None,
            unload_done: false,
            finished: false,
            rejected_commands: 0,
        }
    }

    /// Commands dropped so far because the rig must not act on their content.
    pub fn rejected_commands(&self) -> u64 {
        self.rejected_commands
    }

    pub fn config(&self) -> &ServoConfig {
        &self.cfg
    }

    /// The latched trip, if any.
    pub fn trip(&self) -> Option<Trip> {
        self.trip
    }

    /// Returns a trip once, in the period it happened (for the event record).
    pub fn take_new_trip(&mut self) -> Option<Trip> {
        if self.new_trip {
            self.new_trip = false;
            self.trip
        } else {
            None
        }
    }

    /// Whether the run should end: held for at least `hold_min_s` and at rest (and
    /// unloaded when unloading), or held for `hold_max_s`.
    pub fn finished(&self) -> bool {
        self.finished
    }

    /// Whether the specimen is at rest now (measured displacement within the rest band).
    pub fn at_rest(&self) -> bool {
        self.at_rest_since_step.is_some()
    }

    pub fn holding(&self) -> bool {
        matches!(self.phase, Phase::Holding { .. })
    }

    /// A command arrived in period `step_idx`. One the rig must not act on (unknown
    /// mode, non-finite law or limits) is dropped and counted: it neither drives the
    /// actuator nor refreshes the interlock, so a stream of them ends in commands-stale.
    #[inline]
    pub fn on_command(&mut self, cmd: &ActuatorCommand, step_idx: u64) {
        if !cmd.content_ok() {
            self.rejected_commands += 1;
            return;
        }
        let age = self
            .last_command_step
            .map_or(0, |s| step_idx.saturating_sub(s));
        self.last_command_step = Some(step_idx);
        if cmd.setpoint_sequence != self.law_setpoint_seq {
            self.law_setpoint_seq = cmd.setpoint_sequence;
            self.law_since_step = step_idx;
        }
        match cmd.mode {
            command_mode::HOLD | command_mode::HOLD_UNLOAD => {
                let action = if cmd.mode == command_mode::HOLD {
                    FaultAction::Hold
                } else {
                    FaultAction::HoldUnload
                };
                self.latch(Fault::HoldRequested, cmd.fault_code, step_idx, age, action);
            }
            _ => {
                let c = &cmd.compensation;
                if (c.lead_s, c.lead_order) != self.weights_for {
                    let (value, slope) =
                        lead_weights(c.lead_order as usize, self.cfg.period_s, c.lead_s);
                    self.value_weights = value;
                    self.slope_weights = slope;
                    self.weights_for = (c.lead_s, c.lead_order);
                }
                self.command = Some(*cmd);
                if matches!(self.phase, Phase::Awaiting) {
                    self.phase = Phase::Force;
                }
            }
        }
    }

    /// The orchestrator died (its death signal reached the rig) in period `step_idx`.
    pub fn on_orchestrator_lost(&mut self, step_idx: u64) {
        let action = self.cfg.orchestrator_lost_action;
        self.latch(Fault::OrchestratorLost, 0, step_idx, 0, action);
    }

    /// Operator hold: position hold and programme pause, without a fault.
    pub fn operator_hold(&mut self, step_idx: u64) {
        if matches!(self.phase, Phase::Force | Phase::Resuming { .. }) {
            self.enter_hold(step_idx, false, true);
        }
    }

    /// Operator resume from an operator hold (a fault hold is never resumed, nor the
    /// hold of an operator's end: a stop cannot be taken back).
    pub fn operator_resume(&mut self, step_idx: u64) {
        if let Phase::Holding {
            operator: true,
            unload: false,
            ..
        } = self.phase
        {
            if self.trip.is_none() {
                self.phase = Phase::Resuming {
                    since_step: step_idx,
                };
                self.resume_from_n = self.measured_force_n;
            }
        }
    }

    /// Orderly end requested by the operator: hold, unload, finish. The hold's clock
    /// restarts, so an end after a long operator hold still unloads before finishing;
    /// an end repeated while already unloading changes nothing (restarting the clock
    /// each time would keep the run from ever finishing).
    pub fn operator_end(&mut self, step_idx: u64) {
        match self.phase {
            Phase::Holding {
                ref mut unload,
                ref mut since_step,
                ..
            } => {
                if !*unload {
                    *unload = true;
                    *since_step = step_idx;
                }
            }
            _ => self.enter_hold(step_idx, true, true),
        }
    }

    /// The actuator's force per commanded force as the last command identified it (1
    /// before any command). Feed-forwards in the hold divide by it, as the law does.
    #[inline]
    fn actuator_gain(&self) -> f64 {
        self.command
            .as_ref()
            .map(|c| c.compensation.gain)
            .filter(|g| g.is_finite() && *g > 0.0)
            .unwrap_or(1.0)
    }

    fn enter_hold(&mut self, step_idx: u64, unload: bool, operator: bool) {
        self.hold_position_m = self.z_history_m[0];
        // The force that holds the specimen at rest there is the load it carries; the last
        // output may be far from it when the hold ends an unstable loop (an actuator
        // slamming between its limits), and fed forward it would push the specimen away.
        // Within the normal band the last output is kept (a bumpless hold).
        // Both are commands: the actuator delivers the identified gain times its command,
        // so the load is carried by load / gain (an actuator 0.74 strong fed the load
        // itself forward lets the specimen go by a quarter of its load).
        let needed_n = self.load_now_n / self.actuator_gain();
        let deviation = (self.last_output_n - needed_n).abs();
        self.hold_feedforward_n = if deviation <= 0.2 * needed_n.abs().max(1e3) {
            self.last_output_n
        } else {
            needed_n
        };
        self.hold_load_at_start_n = self.load_now_n;
        self.hold_integral_m_s = 0.0;
        self.at_rest_since_step = None;
        self.phase = Phase::Holding {
            since_step: step_idx,
            unload,
            operator,
        };
    }

    fn latch(
        &mut self,
        fault: Fault,
        remote_fault_code: u32,
        step_idx: u64,
        detection_latency_periods: u64,
        action: FaultAction,
    ) {
        if self.trip.is_some() {
            return;
        }
        self.trip = Some(Trip {
            fault,
            remote_fault_code,
            step_idx,
            detection_latency_periods,
            action,
            hold_position_m: self.z_history_m[0],
        });
        self.new_trip = true;
        match action {
            FaultAction::Indicate => {}
            FaultAction::Hold | FaultAction::HoldUnload => {
                let unload = action == FaultAction::HoldUnload;
                match self.phase {
                    // Already held by the operator: the hold becomes the fault's.
                    Phase::Holding {
                        since_step,
                        unload: u,
                        ..
                    } => {
                        self.phase = Phase::Holding {
                            since_step,
                            unload: u || unload,
                            operator: false,
                        }
                    }
                    _ => self.enter_hold(step_idx, unload, false),
                }
            }
        }
    }

    fn push_rest(&mut self, z_m: f64) {
        self.rest_head = (self.rest_head + 1) % self.rest_len;
        self.rest_ring[self.rest_head] = z_m;
        self.rest_filled = (self.rest_filled + 1).min(self.rest_len);
    }

    fn rest_range_m(&self) -> f64 {
        let window = &self.rest_ring[..self.rest_len];
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for &z in window {
            lo = lo.min(z);
            hi = hi.max(z);
        }
        hi - lo
    }

    /// The displacement and velocity predicted over the command's lead.
    #[inline]
    fn predicted(&self) -> (f64, f64) {
        let mut z = 0.0;
        let mut v = 0.0;
        for i in 0..4 {
            z += self.value_weights[i] * self.z_history_m[i];
            v += self.slope_weights[i] * self.z_history_m[i];
        }
        (z, v)
    }

    /// The law's force at the displacement predicted over the command's lead, plus the
    /// guard's damping, clamped, divided by the actuator's identified gain.
    #[inline]
    fn law_force_n(&self, cmd: &ActuatorCommand) -> f64 {
        let (z, v) = self.predicted();
        let c = &cmd.compensation;
        // Time since the law's sample, at the instant the force will act. The rate term
        // is a first-order relaxation: valid for a stall's length, not for ever, so it
        // stops growing at the rig's own stale-command limit.
        let horizon_s = self.cfg.command_stale_periods as f64 * self.cfg.period_s;
        let since_s = if cmd.sample_sequence == u64::MAX {
            0.0
        } else {
            (self.step_idx.saturating_sub(cmd.sample_sequence) as f64 * self.cfg.period_s
                + c.lead_s)
                .min(horizon_s)
        };
        let v_hp = if c.added_damping_corner_hz > 0.0 {
            v - self.velocity_lp_m_per_s
        } else {
            v
        };
        let force = cmd.law.evaluate(z, v, since_s) + c.added_damping_ns_per_m * v_hp;
        force.max(cmd.force_min_n).min(cmd.force_max_n) / c.gain
    }

    /// Advances the guard's velocity low-pass by one period (corner from the command).
    #[inline]
    fn update_velocity_filter(&mut self) {
        let corner_hz = self
            .command
            .as_ref()
            .map_or(0.0, |c| c.compensation.added_damping_corner_hz);
        let (_, v) = self.predicted();
        if corner_hz > 0.0 {
            let a = 1.0 - (-2.0 * std::f64::consts::PI * corner_hz * self.cfg.period_s).exp();
            self.velocity_lp_m_per_s += a * (v - self.velocity_lp_m_per_s);
        } else {
            self.velocity_lp_m_per_s = v;
        }
    }

    #[inline]
    fn force_control_n(&self) -> (f64, u32) {
        match &self.command {
            Some(cmd) if cmd.mode == command_mode::LAW => {
                (self.law_force_n(cmd), command_mode::LAW)
            }
            Some(cmd) => (
                cmd.law.force_n.max(cmd.force_min_n).min(cmd.force_max_n),
                command_mode::FORCE,
            ),
            None => (self.last_output_n, command_mode::FORCE),
        }
    }

    /// One actuator period `step_idx` with the displacement measured at its start, the
    /// external load the programme applies now (a servo controller generates its load
    /// programme, so it knows it) and the force the actuator's load cell measures. Returns
    /// the actuator command and what the load programme must do.
    #[inline]
    pub fn update(
        &mut self,
        step_idx: u64,
        z_measured_m: f64,
        external_load_n: f64,
        measured_force_n: f64,
    ) -> (ServoOutput, ProgrammeRequest) {
        self.load_now_n = external_load_n;
        if measured_force_n.is_finite() {
            self.measured_force_n = measured_force_n;
        }
        // A non-finite reading is never used: the last good one stands in.
        let z_measured_m = if z_measured_m.is_finite() {
            z_measured_m
        } else {
            self.z_history_m[0]
        };
        self.z_history_m = [
            z_measured_m,
            self.z_history_m[0],
            self.z_history_m[1],
            self.z_history_m[2],
        ];
        self.push_rest(z_measured_m);
        self.step_idx = step_idx;
        self.update_velocity_filter();
        // The rig's own interlock: commands stopped (controller dead or stalled, link
        // lost), or never came. Armed from sample 0 (the run's start): the loop was ready
        // before the start, so its first command is due within a few periods, and a rig
        // whose link dies before it must not run its programme against a constant force.
        let command_age = step_idx.saturating_sub(self.last_command_step.unwrap_or(0));
        if command_age > self.cfg.command_stale_periods {
            let action = self.cfg.commands_stale_action;
            self.latch(Fault::CommandsStale, 0, step_idx, command_age, action);
        }
        let (command_n, state, mode, request) = match self.phase {
            Phase::Awaiting => (
                self.hold_force_n(z_measured_m),
                rig_state::RUNNING,
                command_mode::HOLD,
                ProgrammeRequest::Run,
            ),
            Phase::Force => {
                let (f, mode) = self.force_control_n();
                (f, rig_state::RUNNING, mode, ProgrammeRequest::Run)
            }
            Phase::Resuming { since_step } => {
                let (f, mode) = self.force_control_n();
                // A stroke-control hold ended at the resume: the blend starts from the
                // force the actuator carried then (bumpless), the PID's otherwise.
                let hold = if self.cfg.stroke_hold {
                    self.resume_from_n
                } else {
                    self.hold_force_n(z_measured_m)
                };
                let w = ((step_idx - since_step) as f64 * self.cfg.period_s
                    / self.cfg.resume_blend_s.max(self.cfg.period_s))
                .min(1.0);
                if w >= 1.0 {
                    self.phase = Phase::Force;
                }
                (
                    (1.0 - w) * hold + w * f,
                    rig_state::RUNNING,
                    mode,
                    ProgrammeRequest::Run,
                )
            }
            Phase::Holding {
                since_step,
                unload,
                operator,
            } => self.hold_step(step_idx, z_measured_m, since_step, unload, operator),
        };
        let holding = matches!(self.phase, Phase::Awaiting | Phase::Holding { .. });
        let (command_n, stroke_target_m) = if self.cfg.stroke_hold && holding {
            (self.measured_force_n, self.hold_position_m)
        } else {
            (command_n, f64::NAN)
        };
        self.last_output_n = command_n;
        let law_age = step_idx.saturating_sub(self.law_since_step);
        (
            ServoOutput {
                command_n,
                state,
                mode,
                command_age_periods: command_age,
                law_age_periods: law_age,
                stroke_target_m,
            },
            request,
        )
    }

    /// The position hold's force at measured displacement `z_m` (PID about the hold
    /// position; the load's change since the hold began is fed forward, as equilibrium
    /// needs it, and the PID takes the rest). Advances the integrator by one period.
    fn hold_force_n(&mut self, z_m: f64) -> f64 {
        let dt = self.cfg.period_s;
        let error_m = z_m - self.hold_position_m;
        self.hold_integral_m_s += error_m * dt;
        let velocity = (self.z_history_m[0] - self.z_history_m[1]) / dt;
        // The feed-forward is a command already; the load's change and the PID are
        // forces, so they are divided by the actuator's gain, which keeps the position
        // loop's poles where `hold_gains` placed them.
        self.hold_feedforward_n
            + ((self.load_now_n - self.hold_load_at_start_n)
                + self.cfg.hold_kp * error_m
                + self.cfg.hold_ki * self.hold_integral_m_s
                + self.cfg.hold_kd * velocity)
                / self.actuator_gain()
    }

    fn hold_step(
        &mut self,
        step_idx: u64,
        z_m: f64,
        since_step: u64,
        unload: bool,
        operator: bool,
    ) -> (f64, u32, u32, ProgrammeRequest) {
        let dt = self.cfg.period_s;
        let command_n = self.hold_force_n(z_m);
        // At rest: the window since the hold began is full and within the band.
        let held_periods = step_idx - since_step;
        let window_full = held_periods as usize >= self.rest_len;
        if window_full && self.rest_range_m() <= self.cfg.rest_band_m {
            self.at_rest_since_step.get_or_insert(step_idx);
        } else {
            self.at_rest_since_step = None;
        }
        let held_s = held_periods as f64 * dt;
        let request = if unload && self.at_rest() {
            ProgrammeRequest::Unload
        } else {
            ProgrammeRequest::Hold
        };
        let state = if request == ProgrammeRequest::Unload || (unload && self.unload_done) {
            rig_state::UNLOAD
        } else if operator && self.trip.is_none() {
            rig_state::OPERATOR_HOLD
        } else {
            rig_state::HOLD
        };
        let settled = self.at_rest() && (!unload || self.unload_done);
        if (!operator || self.trip.is_some() || unload)
            && ((held_s >= self.cfg.hold_min_s && settled) || held_s >= self.cfg.hold_max_s)
        {
            self.finished = true;
        }
        (command_n, state, command_mode::HOLD, request)
    }

    /// The programme reports that an unload reached zero.
    pub fn on_unloaded(&mut self) {
        self.unload_done = true;
    }
}
