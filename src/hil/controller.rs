//! The actuator-controller's logic between the emulator and the actuator side.
//!
//! - `law` mode (default): forwards the element's local linear law with the force limits
//!   the actuator side must respect; the actuator side evaluates it with its own
//!   displacement, so the loop's delay needs no extrapolation here.
//! - `force` mode (plain force commands): delay compensation by polynomial extrapolation
//!   of the force setpoints (orders 0-3, OpenFresco style) over the loop delay.
//! - Force limits with the configured action; keep-alive repeats of the last command so
//!   the actuator side can tell a dead controller from a stalled emulator.
//! - The watchdog: setpoints stale beyond the stall limit, a lost emulator heartbeat, a
//!   tripped emulator or an invalid law latch a named fault, and the commands then ask
//!   the actuator side to hold the specimen (or only indicate, as configured).
//!
//! Delay estimate in force mode (adaptive per command): the force history is kept on the
//! rig's sample grid (`sample_sequence * period`). A command sent at `now` reaches the rig
//! at its next sample instant `t_next` (the grid is known from the common start time), and
//! acts from there through the zero-order hold, the actuator's transport delay and lag:
//! the controller predicts the force at `t_next + compensation_delay`.
//!
//! Must not: allocate, log, read a clock or do I/O (times come in as arguments).

use super::compensation::{CompensationConfig, Compensator};
use super::config::{CommandMode, ControllerConfig, LimitAction};
use super::fault::{Fault, FaultAction, FaultActions};
use crate::ipc::messages::{
    command_mode, controller_state, emulator_state, ActuatorCommand, ForceSetpoint, LocalLaw,
};
use crate::ipc::messages::{process_id, rig_state, Compensation};
use crate::record_type;
use crate::records::event::{action_code, event_kind};
use crate::records::EventRecord;

/// Value at `t_eval` of the polynomial through the points `(t[i], y[i])` (Lagrange form;
/// works for uneven spacing, e.g. after a skipped sample).
#[inline]
pub fn lagrange_extrapolate(t: &[f64], y: &[f64], t_eval: f64) -> f64 {
    let n = t.len().min(y.len());
    let mut sum = 0.0;
    for i in 0..n {
        let mut w = 1.0;
        for j in 0..n {
            if i != j {
                w *= (t_eval - t[j]) / (t[i] - t[j]);
            }
        }
        sum += w * y[i];
    }
    sum
}

record_type! {
    /// One command (`/controller`).
    pub struct ControllerRecord {
        topic: "/controller",
        schema: "fastemu/ControllerRecord",
        log_time: |r| (r.t_s.max(0.0) * 1e9).round() as u64,
        fields: {
            /// time the command was sent, since the run's start, s
            t_s: f64,
            command_seq: u64,
            /// setpoint behind the command (-1 none)
            setpoint_seq: u64,
            /// sample at the origin of the chain (-1 none)
            sample_seq: u64,
            /// command mode: 0 force, 1 law, 2 hold, 3 hold-unload
            mode: u32,
            /// the emulator's element force, N (NaN for repeats and holds)
            setpoint_force_n: f64,
            /// force mode: the extrapolated force; law mode: the law's force after limits, N
            predicted_force_n: f64,
            /// the command's force (law.force_n), N
            command_force_n: f64,
            /// local law: the displacement the force belongs to, m
            law_displacement_m: f64,
            /// local law: stiffness, N/m
            law_stiffness_n_per_m: f64,
            /// local law: damping, N s/m
            law_damping_ns_per_m: f64,
            /// local law: force drift at fixed displacement, N/s
            law_force_rate_n_per_s: f64,
            /// controller state: 1 running, 2 fault indicated, 3 holding
            state: u32,
            /// latched fault code, 0 none
            fault_code: u32,
            /// 1 if the force or rate limit acted
            limited: u8,
            /// 1 for a keep-alive repeat of the previous command
            repeat: u8,
            /// sample publish -> command publish, ns (0 for repeats and holds)
            end_to_end_ns: u64,
            /// the rig's measured force at the setpoint's sample, N (NaN: none)
            measured_force_n: f64,
            /// compensation sent: the lead the rig predicts over, s
            lead_s: f64,
            /// compensation sent: the order of the rig's prediction polynomial
            lead_order: u32,
            /// compensation sent: the actuator gain the rig divides by
            actuator_gain: f64,
            /// compensation sent: the passivity guard's added damping, N s/m
            guard_damping_ns_per_m: f64,
            /// the guard's observer: energy generated above its band corner, J
            guard_generated_j: f64,
            /// of it, the burst after a stall of the setpoints that the guard excuses, J
            guard_excused_j: f64,
            /// the stall bursts the guard has excused so far in the run
            guard_stall_bursts: u32,
            /// 1 while the guard is armed (the safe start: its damping until the lead is learned)
            guard_armed: u8,
            /// the energy the guard damps from now, J (its onset scaled for the sensor's noise; inf: noise not read yet; NaN: no guard)
            guard_onset_j: f64,
            /// the displacement sensor's noise as the controller reads it, m (NaN: not yet)
            sensor_noise_m: f64,
            /// the effective delay identified now (lead + residual), s (NaN: not yet)
            identified_delay_s: f64,
            /// its standard error, s
            identified_delay_sigma_s: f64,
            /// the actuator's effective delay over the load band (1-20 Hz bins), s (NaN: not yet)
            load_band_delay_s: f64,
            /// its standard error, s
            load_band_delay_sigma_s: f64,
            /// the excited, coherent bins it rests on (0: not yet), and the lowest and highest, Hz
            load_band_bins: u32,
            load_band_from_hz: f64,
            load_band_to_hz: f64,
        }
    }
}

/// A fault the controller latched, for its event record.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControllerTrip {
    pub fault: Fault,
    /// The emulator's own fault code (`emulator-tripped`), else 0.
    pub emulator_fault_code: u32,
    /// Periods between the last good input and the detection.
    pub detection_latency_periods: u64,
    pub action: FaultAction,
    pub detected_ns: u64,
}

impl ControllerTrip {
    /// The trip as an event record (`t0_ns`: the loop's time origin).
    pub fn event(&self, t0_ns: u64, period_ns: u64) -> EventRecord {
        let since = self.detected_ns.saturating_sub(t0_ns);
        EventRecord {
            t_s: since as f64 * 1e-9,
            process: process_id::CONTROLLER,
            kind: event_kind::FAULT,
            fault_code: self.fault.code(),
            remote_fault_code: self.emulator_fault_code,
            action: action_code::of(self.action),
            detection_latency_periods: self.detection_latency_periods,
            step_idx: since / period_ns,
            value: 0.0,
        }
    }
}

const MAX_POINTS: usize = 4;

/// The controller's state between events.
#[derive(Debug, Clone)]
pub struct ControllerCore {
    cfg: ControllerConfig,
    actions: FaultActions,
    period_s: f64,
    period_ns: u64,
    /// Setpoints older than this are a fault (the ride-through limit), ns.
    stall_limit_ns: u64,
    t_hist_s: [f64; MAX_POINTS],
    f_hist_n: [f64; MAX_POINTS],
    n_hist: usize,
    last_command: Option<ActuatorCommand>,
    last_sent_ns: Option<u64>,
    last_force_n: Option<f64>,
    last_setpoint_rx_ns: Option<u64>,
    last_emulator_heartbeat_ns: Option<u64>,
    last_setpoint_seq: Option<u64>,
    last_node_sample_seq: Option<u64>,
    start_time_ns: u64,
    trip: Option<ControllerTrip>,
    new_trip: bool,
    hold_sent: bool,
    command_seq: u64,
    pub limited_commands: u64,
    pub repeated_commands: u64,
    compensator: Compensator,
}

impl ControllerCore {
    pub fn new(
        cfg: ControllerConfig,
        actions: FaultActions,
        period_ns: u64,
        stall_limit_ns: u64,
    ) -> ControllerCore {
        ControllerCore {
            cfg,
            actions,
            period_s: period_ns as f64 * 1e-9,
            period_ns,
            stall_limit_ns,
            t_hist_s: [0.0; MAX_POINTS],
            f_hist_n: [0.0; MAX_POINTS],
            n_hist: 0,
            last_command: None,
            last_sent_ns: None,
            last_force_n: None,
            last_setpoint_rx_ns: None,
            last_emulator_heartbeat_ns: None,
            last_setpoint_seq: None,
            last_node_sample_seq: None,
            start_time_ns: 0,
            trip: None,
            new_trip: false,
            hold_sent: false,
            command_seq: 0,
            limited_commands: 0,
            repeated_commands: 0,
            compensator: Compensator::new(
                CompensationConfig::with_initial_delay(0.0),
                period_ns as f64 * 1e-9,
            ),
        }
    }

    /// The compensation the controller sends with its law commands (`[compensation]`).
    pub fn with_compensation(mut self, cfg: CompensationConfig) -> ControllerCore {
        self.compensator = Compensator::new(cfg, self.period_s);
        self
    }

    pub fn compensator(&self) -> &Compensator {
        &self.compensator
    }

    /// The rig's first sample instant (`CLOCK_MONOTONIC`, ns): origin of the sample grid.
    pub fn set_start_time_ns(&mut self, t0_ns: u64) {
        self.start_time_ns = t0_ns;
    }

    pub fn fault(&self) -> Option<Fault> {
        self.trip.map(|t| t.fault)
    }

    pub fn trip(&self) -> Option<ControllerTrip> {
        self.trip
    }

    /// Returns a trip once, when it was latched (for the event record).
    pub fn take_new_trip(&mut self) -> Option<ControllerTrip> {
        if self.new_trip {
            self.new_trip = false;
            self.trip
        } else {
            None
        }
    }

    /// The emulator's fault code when it reported itself tripped, else 0.
    pub fn emulator_fault_code(&self) -> u32 {
        self.trip.map_or(0, |t| t.emulator_fault_code)
    }

    fn holding(&self) -> bool {
        self.trip.is_some_and(|t| t.action != FaultAction::Indicate)
    }

    pub fn state(&self) -> u32 {
        match self.trip {
            Some(t) if t.action != FaultAction::Indicate => controller_state::HOLDING,
            Some(_) => controller_state::FAULT_INDICATED,
            None if self.last_command.is_some() => controller_state::RUNNING,
            None => controller_state::STARTING,
        }
    }

    fn latch(&mut self, fault: Fault, emulator_fault_code: u32, latency_periods: u64, now_ns: u64) {
        if self.trip.is_none() {
            self.trip = Some(ControllerTrip {
                fault,
                emulator_fault_code,
                detection_latency_periods: latency_periods,
                action: self.actions.for_fault(fault),
                detected_ns: now_ns,
            });
            self.new_trip = true;
        }
    }

    /// Notes an emulator heartbeat received at `now_ns`.
    pub fn on_emulator_heartbeat(&mut self, now_ns: u64) {
        self.last_emulator_heartbeat_ns = Some(now_ns);
    }

    /// Time on the sample grid at which a command sent at `now_ns` takes effect, s.
    pub fn target_time_s(&self, now_ns: u64) -> f64 {
        let since_start = now_ns.saturating_sub(self.start_time_ns);
        let next_tick = since_start / self.period_ns + 1;
        next_tick as f64 * self.period_s + self.cfg.compensation_delay_s
    }

    /// Force mode: predicted force at `t_eval_s` from the newest setpoints.
    fn predict(&self, t_eval_s: f64) -> f64 {
        let newest = self.n_hist - 1;
        let order = if self.cfg.compensation_enabled {
            self.cfg.compensation_order as usize
        } else {
            0
        };
        if order == 0 || self.n_hist == 1 {
            return self.f_hist_n[newest];
        }
        let n_points = (order + 1).min(self.n_hist);
        let first = self.n_hist - n_points;
        // Never extrapolate further than 4 periods past the compensation delay (a very
        // late wake-up: the rig will hold the previous command anyway).
        let horizon = 4.0 * self.period_s + self.cfg.compensation_delay_s;
        let t_eval = t_eval_s.min(self.t_hist_s[newest] + horizon);
        lagrange_extrapolate(
            &self.t_hist_s[first..self.n_hist],
            &self.f_hist_n[first..self.n_hist],
            t_eval,
        )
    }

    /// Applies the force and rate limits to `wanted_n`; returns the force, whether it was
    /// limited, and `None` when the limit action asks to keep the previous command.
    fn limit(&mut self, wanted_n: f64, now_ns: u64) -> (Option<f64>, bool) {
        let last = self.last_force_n.unwrap_or(wanted_n);
        let max_step = self.cfg.force_rate_max_n_per_s * self.period_s;
        let out_of_force = !(self.cfg.force_min_n..=self.cfg.force_max_n).contains(&wanted_n);
        let out_of_rate = (wanted_n - last).abs() > max_step;
        if !(out_of_force || out_of_rate) {
            return (Some(wanted_n), false);
        }
        self.limited_commands += 1;
        let saturated = wanted_n
            .clamp(self.cfg.force_min_n, self.cfg.force_max_n)
            .clamp(last - max_step, last + max_step);
        match self.cfg.limit_action {
            LimitAction::Saturate => (Some(saturated), true),
            LimitAction::Hold => (None, true),
            LimitAction::Fault => {
                self.latch(Fault::ForceLimitExceeded, 0, 0, now_ns);
                (Some(saturated), true)
            }
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn emit(
        &mut self,
        sp: Option<&ForceSetpoint>,
        mode: u32,
        law: LocalLaw,
        predicted_n: f64,
        limited: bool,
        repeat: bool,
        e2e_ns: u64,
        now_ns: u64,
    ) -> (ActuatorCommand, ControllerRecord) {
        let (setpoint_seq, sample_seq, sample_time, setpoint_force) = match (sp, &self.last_command)
        {
            (Some(s), _) => (
                s.sequence,
                s.sample_sequence,
                s.sample_publish_time_ns,
                s.law.force_n,
            ),
            (None, Some(c)) => (
                c.setpoint_sequence,
                c.sample_sequence,
                c.sample_publish_time_ns,
                f64::NAN,
            ),
            (None, None) => (u64::MAX, u64::MAX, 0, f64::NAN),
        };
        let fault_code = self.trip.map_or(0, |t| t.fault.code());
        let status = self.compensator.status();
        let compensation = if mode == command_mode::LAW {
            status.compensation
        } else {
            Compensation::NONE
        };
        let measured_force_n = sp.map_or(f64::NAN, |s| s.measured_force_n);
        let cmd = ActuatorCommand {
            sequence: self.command_seq,
            setpoint_sequence: setpoint_seq,
            sample_sequence: sample_seq,
            sample_publish_time_ns: sample_time,
            law,
            force_min_n: self.cfg.force_min_n,
            force_max_n: self.cfg.force_max_n,
            mode,
            controller_state: self.state(),
            fault_code,
            reserved: 0,
            compensation,
        };
        let rec = ControllerRecord {
            t_s: now_ns.saturating_sub(self.start_time_ns) as f64 * 1e-9,
            command_seq: self.command_seq,
            setpoint_seq,
            sample_seq,
            mode,
            setpoint_force_n: setpoint_force,
            predicted_force_n: predicted_n,
            command_force_n: law.force_n,
            law_displacement_m: law.displacement_m,
            law_stiffness_n_per_m: law.stiffness_n_per_m,
            law_damping_ns_per_m: law.damping_ns_per_m,
            law_force_rate_n_per_s: law.force_rate_n_per_s,
            state: self.state(),
            fault_code,
            limited: u8::from(limited),
            repeat: u8::from(repeat),
            end_to_end_ns: e2e_ns,
            measured_force_n,
            lead_s: compensation.lead_s,
            lead_order: compensation.lead_order,
            actuator_gain: compensation.gain,
            guard_damping_ns_per_m: compensation.added_damping_ns_per_m,
            guard_generated_j: status.guard.generated_j,
            guard_excused_j: status.guard.excused_j,
            guard_stall_bursts: status.guard.stall_bursts,
            // As sent: only law commands carry the guard's damping.
            guard_armed: u8::from(mode == command_mode::LAW && status.guard.armed),
            guard_onset_j: status.guard.onset_j,
            sensor_noise_m: status.sensor_noise_m,
            identified_delay_s: status.identified_delay_s,
            identified_delay_sigma_s: status.identified_delay_sigma_s,
            load_band_delay_s: status.load_band.map_or(f64::NAN, |e| e.delay_s),
            load_band_delay_sigma_s: status.load_band.map_or(f64::NAN, |e| e.delay_sigma_s),
            load_band_bins: status.load_band.map_or(0, |e| e.bins),
            load_band_from_hz: status.load_band.map_or(f64::NAN, |e| e.from_hz),
            load_band_to_hz: status.load_band.map_or(f64::NAN, |e| e.to_hz),
        };
        self.command_seq += 1;
        self.last_sent_ns = Some(now_ns);
        if mode == command_mode::LAW || mode == command_mode::FORCE {
            self.last_command = Some(cmd);
        }
        if repeat {
            self.repeated_commands += 1;
        }
        (cmd, rec)
    }

    /// The hold command the configured action asks for.
    fn hold_command(&mut self, now_ns: u64) -> (ActuatorCommand, ControllerRecord) {
        let mode = match self.trip.map(|t| t.action) {
            Some(FaultAction::HoldUnload) => command_mode::HOLD_UNLOAD,
            _ => command_mode::HOLD,
        };
        let law = self.last_command.map_or_else(LocalLaw::default, |c| c.law);
        self.hold_sent = true;
        self.emit(None, mode, law, f64::NAN, false, false, 0, now_ns)
    }

    /// Handles a new setpoint received at `now_ns`; returns the command to publish.
    pub fn on_setpoint(
        &mut self,
        sp: &ForceSetpoint,
        now_ns: u64,
    ) -> Option<(ActuatorCommand, ControllerRecord)> {
        if self.last_setpoint_seq.is_some_and(|s| sp.sequence <= s) {
            return None;
        }
        self.last_setpoint_seq = Some(sp.sequence);
        self.last_setpoint_rx_ns = Some(now_ns);
        // The emulator's setpoints are its heartbeat too.
        self.last_emulator_heartbeat_ns = Some(now_ns);
        if sp.emulator_state == emulator_state::TRIPPED {
            self.latch(Fault::EmulatorTripped, sp.fault_code, 0, now_ns);
        } else if sp.emulator_state == emulator_state::RUNNING && !sp.law.is_valid() {
            self.latch(Fault::InvalidLaw, 0, 0, now_ns);
        }
        if sp.emulator_state != emulator_state::RUNNING {
            return self.holding().then(|| self.hold_command(now_ns));
        }
        if self.holding() {
            return Some(self.hold_command(now_ns));
        }
        // A setpoint on the same sample as the last one carries nothing new (the emulator
        // is alive, the rig's sample did not come): liveness only.
        if self.last_node_sample_seq == Some(sp.sample_sequence) {
            return None;
        }
        self.last_node_sample_seq = Some(sp.sample_sequence);
        let e2e = now_ns.saturating_sub(sp.sample_publish_time_ns);
        match self.cfg.command_mode {
            CommandMode::Law => {
                self.compensator.observe_rig(
                    sp.sample_sequence,
                    sp.measured_force_n,
                    sp.commanded_force_n,
                );
                // The gain's read from the rig's own command comes first (a few samples
                // under the rig's servo); the staleness bounds are tens of periods.
                if !self.compensator.ready_to_command() {
                    return None;
                }
                if sp.rig_state == rig_state::RUNNING {
                    self.compensator.on_sample(
                        sp.sample_sequence,
                        sp.law.displacement_m,
                        sp.law.force_n,
                        sp.measured_force_n,
                    );
                } else {
                    self.compensator.pause();
                }
                let (force, limited) = self.limit(sp.law.force_n, now_ns);
                if self.holding() {
                    return Some(self.hold_command(now_ns));
                }
                let force = force?;
                self.last_force_n = Some(force);
                // Saturation shifts the law's force but keeps its stiffness: the actuator
                // side clamps the evaluated force to the same limits anyway.
                let law = LocalLaw {
                    force_n: force,
                    ..sp.law
                };
                Some(self.emit(
                    Some(sp),
                    command_mode::LAW,
                    law,
                    force,
                    limited,
                    false,
                    e2e,
                    now_ns,
                ))
            }
            CommandMode::Force => {
                let t_s = sp.sample_sequence as f64 * self.period_s;
                if self.n_hist == MAX_POINTS {
                    self.t_hist_s.copy_within(1.., 0);
                    self.f_hist_n.copy_within(1.., 0);
                    self.n_hist -= 1;
                }
                self.t_hist_s[self.n_hist] = t_s;
                self.f_hist_n[self.n_hist] = sp.law.force_n;
                self.n_hist += 1;
                let predicted = self.predict(self.target_time_s(now_ns));
                let (force, limited) = self.limit(predicted, now_ns);
                if self.holding() {
                    return Some(self.hold_command(now_ns));
                }
                let force = force?;
                self.last_force_n = Some(force);
                let law = LocalLaw::constant(force);
                Some(self.emit(
                    Some(sp),
                    command_mode::FORCE,
                    law,
                    predicted,
                    limited,
                    false,
                    e2e,
                    now_ns,
                ))
            }
        }
    }

    /// Watchdog and keep-alive at `now_ns` (called on every wake-up and wait time-out):
    /// latches a fault when the emulator went silent beyond the stall limit; returns a hold
    /// command while holding, or a repeat of the last command when none was sent for a
    /// keep-alive period.
    pub fn on_tick(&mut self, now_ns: u64) -> Option<(ActuatorCommand, ControllerRecord)> {
        if self.trip.is_none() {
            if let Some(rx) = self.last_setpoint_rx_ns {
                let silent = now_ns.saturating_sub(rx);
                if silent > self.stall_limit_ns {
                    self.latch(Fault::SetpointsStale, 0, silent / self.period_ns, now_ns);
                }
            }
            if let Some(hb) = self.last_emulator_heartbeat_ns {
                let silent = now_ns.saturating_sub(hb);
                if silent > self.cfg.emulator_heartbeat_timeout_ns {
                    self.latch(
                        Fault::EmulatorHeartbeatLost,
                        0,
                        silent / self.period_ns,
                        now_ns,
                    );
                }
            }
        }
        let due = self
            .last_sent_ns
            .is_some_and(|t| now_ns.saturating_sub(t) >= self.cfg.keepalive_ns);
        // The first hold command goes out at once; then one per keep-alive period.
        if self.holding() && (due || !self.hold_sent) {
            return Some(self.hold_command(now_ns));
        }
        if !due || self.holding() {
            return None;
        }
        let last = self.last_command?;
        Some(self.emit(
            None,
            last.mode,
            last.law,
            last.law.force_n,
            false,
            true,
            0,
            now_ns,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cubic_extrapolation_is_exact_for_cubics() {
        let t = [0.0, 1.0, 2.0, 3.0];
        let y: Vec<f64> = t
            .iter()
            .map(|x| 1.0 + 2.0 * x - x * x + 0.5 * x * x * x)
            .collect();
        let e = 4.7;
        let want = 1.0 + 2.0 * e - e * e + 0.5 * e * e * e;
        assert!((lagrange_extrapolate(&t, &y, e) - want).abs() < 1e-9);
    }
}
