//! The actuator-controller's logic: delay compensation by polynomial extrapolation of the
//! force setpoints (orders 0-3, OpenFresco style) over the loop delay, force
//! and force-rate limits with the configured action, and the watchdog (stale setpoints,
//! lost emulator heartbeat, tripped emulator) that latches a named fault and ramps the
//! actuator to its safe force.
//!
//! Delay estimate (adaptive per command): the force history is kept on the rig's sample
//! grid (`sample_sequence * period`). A command sent at `now` reaches the rig at its
//! next sample instant `t_next` (the grid is known from the common start time), and acts
//! from there through the zero-order hold, the actuator's transport delay and lag: the
//! controller predicts the force at `t_next + compensation_delay`. So late wake-ups or a
//! held sample lengthen the extrapolation by exactly what they cost.
//!
//! Must not: allocate, log, read a clock or do I/O (times come in as arguments).

use std::io::Write;

use super::config::{ControllerConfig, LimitAction};
use super::fault::Fault;
use super::records::{sequence_column, CsvRecord};
use crate::ipc::messages::{controller_state, emulator_state, ActuatorCommand, ForceSetpoint};

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

/// One command, as recorded (CSV `controller.csv`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControllerRecord {
    pub command_seq: u64,
    pub setpoint_seq: u64,
    pub sample_seq: u64,
    pub setpoint_force_n: f64,
    pub predicted_force_n: f64,
    pub command_force_n: f64,
    pub state: u32,
    pub fault_code: u32,
    pub limited: u8,
    /// Sample publish -> command publish, ns (0 for watchdog ramp commands).
    pub end_to_end_ns: u64,
}

impl CsvRecord for ControllerRecord {
    const HEADER: &'static str = "command_seq,setpoint_seq,sample_seq,setpoint_force_n,predicted_force_n,command_force_n,state,fault_code,limited,end_to_end_ns";
    fn write_csv(&self, out: &mut dyn Write) -> std::io::Result<()> {
        let seq = sequence_column(self.sample_seq);
        writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{}",
            self.command_seq,
            self.setpoint_seq,
            seq,
            self.setpoint_force_n,
            self.predicted_force_n,
            self.command_force_n,
            self.state,
            self.fault_code,
            self.limited,
            self.end_to_end_ns
        )
    }
}

const MAX_POINTS: usize = 4;

/// The controller's state between events.
#[derive(Debug, Clone)]
pub struct ControllerCore {
    cfg: ControllerConfig,
    period_s: f64,
    period_ns: u64,
    t_hist_s: [f64; MAX_POINTS],
    f_hist_n: [f64; MAX_POINTS],
    n_hist: usize,
    last_command_n: Option<f64>,
    last_setpoint_rx_ns: Option<u64>,
    last_emulator_heartbeat_ns: Option<u64>,
    last_setpoint_seq: Option<u64>,
    last_node_sample_seq: Option<u64>,
    start_time_ns: u64,
    fault: Option<Fault>,
    /// Fault code the emulator reported, when `fault == EmulatorTripped`.
    pub emulator_fault_code: u32,
    ramp_target_n: f64,
    reached_safe: bool,
    command_seq: u64,
    pub limited_commands: u64,
}

impl ControllerCore {
    pub fn new(cfg: ControllerConfig, period_ns: u64) -> ControllerCore {
        ControllerCore {
            cfg,
            period_s: period_ns as f64 * 1e-9,
            period_ns,
            t_hist_s: [0.0; MAX_POINTS],
            f_hist_n: [0.0; MAX_POINTS],
            n_hist: 0,
            last_command_n: None,
            last_setpoint_rx_ns: None,
            last_emulator_heartbeat_ns: None,
            last_setpoint_seq: None,
            last_node_sample_seq: None,
            start_time_ns: 0,
            fault: None,
            emulator_fault_code: 0,
            ramp_target_n: cfg.safe_force_n,
            reached_safe: false,
            command_seq: 0,
            limited_commands: 0,
        }
    }

    /// The rig's first sample instant (`CLOCK_MONOTONIC`, ns): origin of the sample grid.
    pub fn set_start_time_ns(&mut self, t0_ns: u64) {
        self.start_time_ns = t0_ns;
    }

    pub fn fault(&self) -> Option<Fault> {
        self.fault
    }

    pub fn state(&self) -> u32 {
        match (self.fault, self.reached_safe) {
            (None, _) if self.last_command_n.is_some() => controller_state::RUNNING,
            (None, _) => controller_state::STARTING,
            (Some(_), false) => controller_state::RAMPING_TO_SAFE,
            (Some(_), true) => controller_state::SAFE,
        }
    }

    fn latch(&mut self, fault: Fault) {
        if self.fault.is_none() {
            self.fault = Some(fault);
            self.ramp_target_n = if fault == Fault::ForceLimitExceeded {
                0.0
            } else {
                self.cfg.safe_force_n
            };
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

    /// Predicted force at `t_eval_s` from the newest setpoints.
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

    fn limit(&mut self, wanted_n: f64) -> (f64, bool) {
        let last = self.last_command_n.unwrap_or(wanted_n);
        let max_step = self.cfg.force_rate_max_n_per_s * self.period_s;
        let out_of_force = !(self.cfg.force_min_n..=self.cfg.force_max_n).contains(&wanted_n);
        let out_of_rate = (wanted_n - last).abs() > max_step;
        if !(out_of_force || out_of_rate) {
            return (wanted_n, false);
        }
        self.limited_commands += 1;
        let saturated = wanted_n
            .clamp(self.cfg.force_min_n, self.cfg.force_max_n)
            .clamp(last - max_step, last + max_step);
        match self.cfg.limit_action {
            LimitAction::Saturate => (saturated, true),
            LimitAction::Hold => (last, true),
            LimitAction::RampToZero => {
                self.latch(Fault::ForceLimitExceeded);
                (self.ramp_step(), true)
            }
        }
    }

    fn ramp_step(&mut self) -> f64 {
        let last = self.last_command_n.unwrap_or(self.ramp_target_n);
        let step = self.cfg.safe_ramp_n_per_s * self.period_s;
        let next = if (self.ramp_target_n - last).abs() <= step {
            self.reached_safe = true;
            self.ramp_target_n
        } else {
            last + step * (self.ramp_target_n - last).signum()
        };
        self.last_command_n = Some(next);
        next
    }

    fn command(
        &mut self,
        sp: Option<&ForceSetpoint>,
        force_n: f64,
        predicted_n: f64,
        limited: bool,
        e2e_ns: u64,
    ) -> (ActuatorCommand, ControllerRecord) {
        let (setpoint_seq, sample_seq, sample_time, setpoint_force) =
            sp.map_or((u64::MAX, u64::MAX, 0, f64::NAN), |s| {
                (
                    s.sequence,
                    s.sample_sequence,
                    s.sample_publish_time_ns,
                    s.force_n,
                )
            });
        let cmd = ActuatorCommand {
            sequence: self.command_seq,
            setpoint_sequence: setpoint_seq,
            sample_sequence: sample_seq,
            sample_publish_time_ns: sample_time,
            force_n,
            controller_state: self.state(),
            fault_code: self.fault.map_or(0, Fault::code),
        };
        let rec = ControllerRecord {
            command_seq: self.command_seq,
            setpoint_seq,
            sample_seq,
            setpoint_force_n: setpoint_force,
            predicted_force_n: predicted_n,
            command_force_n: force_n,
            state: self.state(),
            fault_code: self.fault.map_or(0, Fault::code),
            limited: u8::from(limited),
            end_to_end_ns: e2e_ns,
        };
        self.command_seq += 1;
        (cmd, rec)
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
            if self.fault.is_none() {
                self.emulator_fault_code = sp.fault_code;
            }
            self.latch(Fault::EmulatorTripped);
        }
        if sp.emulator_state == emulator_state::STARTING {
            return None;
        }
        if self.fault.is_some() {
            let f = self.ramp_step();
            return Some(self.command(Some(sp), f, f, false, 0));
        }
        // A setpoint computed on a held sample adds no new point to the history.
        if self.last_node_sample_seq == Some(sp.sample_sequence) {
            return None;
        }
        self.last_node_sample_seq = Some(sp.sample_sequence);
        // Shift the history and append (t, F) on the rig's sample grid.
        let t_s = sp.sample_sequence as f64 * self.period_s;
        if self.n_hist == MAX_POINTS {
            self.t_hist_s.copy_within(1.., 0);
            self.f_hist_n.copy_within(1.., 0);
            self.n_hist -= 1;
        }
        self.t_hist_s[self.n_hist] = t_s;
        self.f_hist_n[self.n_hist] = sp.force_n;
        self.n_hist += 1;
        let predicted = self.predict(self.target_time_s(now_ns));
        let (force, limited) = self.limit(predicted);
        if self.fault.is_none() {
            self.last_command_n = Some(force);
        }
        let e2e = now_ns.saturating_sub(sp.sample_publish_time_ns);
        Some(self.command(Some(sp), force, predicted, limited, e2e))
    }

    /// Watchdog check at `now_ns` (called when a wait times out or between events);
    /// while a fault is latched, returns the next ramp command (one per period).
    pub fn on_tick(&mut self, now_ns: u64) -> Option<(ActuatorCommand, ControllerRecord)> {
        if self.fault.is_none() {
            if let Some(rx) = self.last_setpoint_rx_ns {
                if now_ns.saturating_sub(rx)
                    > self.cfg.stale_setpoint_periods as u64 * self.period_ns
                {
                    self.latch(Fault::SetpointsStale);
                }
            }
            if let Some(hb) = self.last_emulator_heartbeat_ns {
                if now_ns.saturating_sub(hb) > self.cfg.emulator_heartbeat_timeout_ns {
                    self.latch(Fault::EmulatorHeartbeatLost);
                }
            }
        }
        if self.fault.is_some() && self.last_command_n.is_some() {
            let f = self.ramp_step();
            return Some(self.command(None, f, f, false, 0));
        }
        None
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
