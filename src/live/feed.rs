//! From records to the live view's messages: the rig's displacement and forces decimated
//! for display, the offline reference in lockstep (programme time; restarted after an
//! operator hold; stopped at a fault hold), state changes, events, and per-second timing
//! (deadline misses, end-to-end latency percentiles, stalls) and a running fidelity
//! estimate. Pure: records in, JSON messages out; no I/O, no clock.

use hdrhistogram::Histogram;
use serde_json::{json, Value};

use crate::hil::config::HilConfig;
use crate::hil::controller::ControllerRecord;
use crate::hil::emulator::EmulatorRecord;
use crate::hil::fault::fault_code_name;
use crate::hil::report::safety::rig_state_name;
use crate::ipc::messages::{command_mode, rig_state};
use crate::records::{EventRecord, Record};
use crate::rig::core::RigRecord;
use crate::rig::reference::{OperatorPause, PauseStep, ReferenceStepper};

/// Live topics.
pub mod topic {
    pub const DISPLACEMENT: &str = "/live/displacement";
    pub const FORCE: &str = "/live/force";
    pub const ELEMENT: &str = "/live/element";
    pub const STATE: &str = "/live/state";
    pub const TIMING: &str = "/live/timing";
    pub const FIDELITY: &str = "/live/fidelity";
    pub const EVENTS: &str = "/live/events";
    pub const ALL: [&str; 7] = [
        DISPLACEMENT,
        FORCE,
        ELEMENT,
        STATE,
        TIMING,
        FIDELITY,
        EVENTS,
    ];
}

/// One live message: topic, time since the run's start (s), JSON.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveMessage {
    pub topic: &'static str,
    pub t_s: f64,
    pub value: Value,
}

/// Per-second window statistics.
struct Window {
    start_s: f64,
    end_to_end: Histogram<u64>,
    deadline_misses: u64,
    stall_periods_max: u64,
    stalls: u64,
    err2: f64,
    ref2: f64,
    resonant_peak_m: f64,
}

impl Window {
    fn new(start_s: f64) -> Window {
        Window {
            start_s,
            end_to_end: Histogram::new_with_bounds(1, 1_000_000_000_000, 3).expect("valid bounds"),
            deadline_misses: 0,
            stall_periods_max: 0,
            stalls: 0,
            err2: 0.0,
            ref2: 0.0,
            resonant_peak_m: 0.0,
        }
    }
}

/// Turns records into live messages.
pub struct LiveFeed {
    dt_s: f64,
    period_ns: u64,
    decimation: u64,
    reference: ReferenceStepper,
    pause: OperatorPause,
    stopped: bool,
    last_state: Option<(u32, u32)>,
    window: Window,
    total_err2: f64,
    total_ref2: f64,
    last_state_s: f64,
    last_emulator_cycle: Option<u64>,
    in_stall: bool,
    /// Centred running mean of the residual for the >100 Hz part (10 ms).
    residual_ring: Vec<f64>,
    residual_head: usize,
    residual_sum: f64,
    block_names: Vec<String>,
}

impl LiveFeed {
    /// A feed publishing the rig's streams at about `rate_hz`.
    pub fn new(cfg: &HilConfig, rate_hz: f64) -> LiveFeed {
        let dt_s = cfg.loop_.dt_s();
        let half = ((cfg.loop_.rate_hz / 200.0) as usize).max(1);
        LiveFeed {
            dt_s,
            period_ns: cfg.loop_.period_ns,
            decimation: ((cfg.loop_.rate_hz / rate_hz.max(1.0)).round() as u64).max(1),
            reference: ReferenceStepper::new(cfg, cfg.programme.end_s + cfg.safety.hold_max_s),
            pause: OperatorPause::new(cfg.safety.resume_blend_s, dt_s),
            stopped: false,
            last_state: None,
            window: Window::new(0.0),
            total_err2: 0.0,
            total_ref2: 0.0,
            last_state_s: f64::NEG_INFINITY,
            last_emulator_cycle: None,
            in_stall: false,
            residual_ring: vec![0.0; 2 * half + 1],
            residual_head: 0,
            residual_sum: 0.0,
            block_names: cfg
                .programme
                .blocks
                .iter()
                .map(|b| b.name.clone())
                .collect(),
        }
    }

    /// Handles one record message; pushes the live messages it produces into `out`.
    pub fn push(&mut self, topic: &str, data: &[u8], out: &mut Vec<LiveMessage>) {
        match topic {
            t if t == RigRecord::TOPIC => {
                if let Some(r) = RigRecord::decode(data) {
                    self.on_rig(&r, out);
                }
            }
            t if t == EmulatorRecord::TOPIC => {
                if let Some(r) = EmulatorRecord::decode(data) {
                    if r.sample_seq.is_multiple_of(self.decimation) {
                        out.push(LiveMessage {
                            topic: topic::ELEMENT,
                            t_s: r.t_s,
                            value: json!({
                                "t_s": r.t_s,
                                "force_kn": r.force_n * 1e-3,
                                "displacement_um": r.z_used_m * 1e6,
                                "law_stiffness_mn_per_m": r.law_stiffness_n_per_m * 1e-6,
                            }),
                        });
                    }
                    if self.last_emulator_cycle != Some(r.cycle_idx) {
                        if r.wake_late_ns >= self.period_ns {
                            self.window.deadline_misses += r.wake_late_ns / self.period_ns;
                        }
                        self.last_emulator_cycle = Some(r.cycle_idx);
                    }
                }
            }
            t if t == ControllerRecord::TOPIC => {
                if let Some(r) = ControllerRecord::decode(data) {
                    if r.end_to_end_ns > 0 {
                        self.window.end_to_end.saturating_record(r.end_to_end_ns);
                    }
                }
            }
            t if t == EventRecord::TOPIC => {
                if let Some(e) = EventRecord::decode(data) {
                    out.push(LiveMessage {
                        topic: topic::EVENTS,
                        t_s: e.t_s,
                        value: json!({"t_s": e.t_s, "text": e.describe()}),
                    });
                }
            }
            _ => {}
        }
    }

    fn on_rig(&mut self, r: &RigRecord, out: &mut Vec<LiveMessage>) {
        // The reference: programme time; restarted after an operator hold.
        let programme_step = (r.programme_time_s / self.dt_s).round() as u64;
        if matches!(r.state, rig_state::HOLD | rig_state::UNLOAD) {
            self.stopped = true;
        }
        if self.pause.push(r.state) == PauseStep::Restart {
            // Wholly back on the law: the force the actuator applies is the element's.
            let element_force = Some(r.actuator_force_n);
            self.reference
                .resync(r.x_m, r.v_m_per_s, element_force, programme_step);
        }
        let comparing = !self.pause.paused() && !self.stopped;
        let x_ref = if comparing {
            Some(self.reference.advance_to(programme_step))
        } else {
            None
        };
        if let Some(x_ref) = x_ref {
            let e = r.x_m - x_ref;
            self.window.err2 += e * e;
            self.window.ref2 += x_ref * x_ref;
            // >100 Hz: the residual minus its running mean (a trailing 10 ms window here;
            // the report's is centred).
            let n = self.residual_ring.len();
            self.residual_sum += e - self.residual_ring[self.residual_head];
            self.residual_ring[self.residual_head] = e;
            self.residual_head = (self.residual_head + 1) % n;
            let hp = e - self.residual_sum / n as f64;
            self.window.resonant_peak_m = self.window.resonant_peak_m.max(hp.abs());
        }
        // Stalls: the law unchanged for 4 periods or more (as the report counts them).
        let stalled = r.law_age_periods >= 4 && r.state == rig_state::RUNNING;
        if stalled {
            self.window.stall_periods_max = self.window.stall_periods_max.max(r.law_age_periods);
            if !self.in_stall {
                self.window.stalls += 1;
            }
        }
        self.in_stall = stalled;
        if r.step_idx.is_multiple_of(self.decimation) {
            out.push(LiveMessage {
                topic: topic::DISPLACEMENT,
                t_s: r.t_s,
                value: json!({
                    "t_s": r.t_s,
                    "measured_um": r.z_measured_m * 1e6,
                    "true_um": r.x_m * 1e6,
                    "reference_um": x_ref.map(|x| x * 1e6),
                }),
            });
            out.push(LiveMessage {
                topic: topic::FORCE,
                t_s: r.t_s,
                value: json!({
                    "t_s": r.t_s,
                    "command_kn": r.command_n * 1e-3,
                    "actuator_kn": r.actuator_force_n * 1e-3,
                    "external_kn": r.external_force_n * 1e-3,
                }),
            });
        }
        let state = (r.state, r.fault_code);
        if self.last_state != Some(state) || r.t_s - self.last_state_s >= 0.1 {
            self.last_state = Some(state);
            self.last_state_s = r.t_s;
            out.push(LiveMessage {
                topic: topic::STATE,
                t_s: r.t_s,
                value: json!({
                    "t_s": r.t_s,
                    "rig": rig_state_name(r.state),
                    "mode": match r.mode {
                        command_mode::LAW => "law",
                        command_mode::FORCE => "force",
                        _ => "hold",
                    },
                    "fault": (r.fault_code != 0).then(|| fault_code_name(r.fault_code)),
                    "programme_time_s": r.programme_time_s,
                    "cycle": r.programme_cycle,
                    "block": r.programme_block,
                    "block_name": self.block_names.get(r.programme_block as usize),
                }),
            });
        }
        if r.t_s - self.window.start_s >= 1.0 {
            self.close_window(r.t_s, out);
        }
    }

    fn close_window(&mut self, t_s: f64, out: &mut Vec<LiveMessage>) {
        let w = std::mem::replace(&mut self.window, Window::new(t_s));
        let us = |q: f64| {
            (!w.end_to_end.is_empty()).then(|| w.end_to_end.value_at_quantile(q) as f64 / 1e3)
        };
        out.push(LiveMessage {
            topic: topic::TIMING,
            t_s,
            value: json!({
                "t_s": t_s,
                "deadline_misses": w.deadline_misses,
                "end_to_end_p50_us": us(0.5),
                "end_to_end_p99_us": us(0.99),
                "end_to_end_p999_us": us(0.999),
                "end_to_end_max_us": (!w.end_to_end.is_empty()).then(|| w.end_to_end.max() as f64 / 1e3),
                "stalls": w.stalls,
                "longest_stall_ms": w.stall_periods_max as f64 * self.dt_s * 1e3,
            }),
        });
        self.total_err2 += w.err2;
        self.total_ref2 += w.ref2;
        let rel = |e: f64, r: f64| (r > 0.0).then(|| (e / r).sqrt());
        out.push(LiveMessage {
            topic: topic::FIDELITY,
            t_s,
            value: json!({
                "t_s": t_s,
                "displacement_rel_rms_last_s": rel(w.err2, w.ref2),
                "displacement_rel_rms": rel(self.total_err2, self.total_ref2),
                "resonant_peak_um_last_s": w.resonant_peak_m * 1e6,
                "comparing": !self.pause.paused() && !self.stopped,
            }),
        });
    }
}
