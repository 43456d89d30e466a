//! What each fault did to the specimen, from the rig's records and the processes' events:
//! who detected it, when and after how long, the action, the hold, the largest excursion
//! after it (and beyond the pre-fault range), the time to rest.

use serde::Serialize;

use crate::hil::fault::fault_code_name;
use crate::ipc::messages::rig_state;
use crate::records::event::{event_kind, EventRecord};
use crate::rig::core::RigRecord;

/// One fault and the specimen's response.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct FaultReport {
    /// Process that detected it (`controller`, `bench_rig`, `emulator`).
    pub process: String,
    pub fault: String,
    /// The fault behind it, when another process reported one (e.g. the emulator's own).
    pub cause: Option<String>,
    pub detected_at_s: f64,
    /// Periods between the last good input and the detection.
    pub detection_latency_periods: u64,
    /// `indicate`, `hold`, `hold-unload` (none: the emulator's own trip; the controller acts).
    pub action: Option<String>,
    /// When the rig left force control for the position hold, s.
    pub hold_started_at_s: Option<f64>,
    /// Specimen displacement at the detection, m.
    pub position_at_fault_m: f64,
    /// Largest |x - x(fault)| after the detection, m.
    pub largest_excursion_m: f64,
    /// Range of the displacement before the fault, m.
    pub prefault_range_m: [f64; 2],
    /// How far the specimen went outside the pre-fault range after the fault, m (0: within).
    pub beyond_prefault_range_m: f64,
    /// From the detection to the rig's at-rest event, s (none: never at rest).
    pub time_to_rest_s: Option<f64>,
}

/// The run's safety record.
#[derive(Debug, Clone, Serialize, Default)]
pub struct Safety {
    pub faults: Vec<FaultReport>,
    /// Injected faults that fired (from the events).
    pub injected: Vec<String>,
    /// Operator actions (hold, resume, stop) with their times.
    pub operator_actions: Vec<String>,
    /// Seconds the rig spent in a hold (fault or operator).
    pub held_s: f64,
    /// The rig's state in its last record.
    pub final_state: String,
    /// Whether the rig reported the specimen at rest in its hold.
    pub at_rest: bool,
}

pub fn rig_state_name(state: u32) -> &'static str {
    match state {
        rig_state::STARTING => "starting",
        rig_state::RUNNING => "running",
        rig_state::HOLD => "hold",
        rig_state::FINISHED => "finished",
        rig_state::UNLOAD => "unload",
        rig_state::OPERATOR_HOLD => "operator-hold",
        _ => "unknown",
    }
}

#[derive(Debug, Clone)]
struct Tracked {
    report: FaultReport,
    seen: bool,
    after_min: f64,
    after_max: f64,
}

/// Follows the rig's records against the fault events.
#[derive(Debug, Clone)]
pub struct SafetyTracker {
    faults: Vec<Tracked>,
    rest_times: Vec<f64>,
    prefault_min: f64,
    prefault_max: f64,
    held_periods: u64,
    dt_s: f64,
    last_state: u32,
    pub safety: Safety,
}

impl SafetyTracker {
    pub fn new(events: &[EventRecord], dt_s: f64) -> SafetyTracker {
        let mut safety = Safety::default();
        let mut faults = Vec::new();
        let mut rest_times = Vec::new();
        for e in events {
            match e.kind {
                event_kind::FAULT => faults.push(Tracked {
                    report: FaultReport {
                        process: e.process_name().to_string(),
                        fault: fault_code_name(e.fault_code),
                        cause: (e.remote_fault_code != 0)
                            .then(|| fault_code_name(e.remote_fault_code)),
                        detected_at_s: e.t_s,
                        detection_latency_periods: e.detection_latency_periods,
                        action: e.action_name().map(String::from),
                        hold_started_at_s: None,
                        position_at_fault_m: f64::NAN,
                        largest_excursion_m: 0.0,
                        prefault_range_m: [f64::NAN, f64::NAN],
                        beyond_prefault_range_m: 0.0,
                        time_to_rest_s: None,
                    },
                    seen: false,
                    after_min: f64::INFINITY,
                    after_max: f64::NEG_INFINITY,
                }),
                event_kind::INJECTED => safety.injected.push(e.describe()),
                event_kind::OPERATOR_HOLD
                | event_kind::OPERATOR_RESUME
                | event_kind::OPERATOR_STOP => safety.operator_actions.push(e.describe()),
                event_kind::AT_REST => rest_times.push(e.t_s),
                _ => {}
            }
        }
        faults.sort_by(|a, b| a.report.detected_at_s.total_cmp(&b.report.detected_at_s));
        rest_times.sort_by(f64::total_cmp);
        SafetyTracker {
            faults,
            rest_times,
            prefault_min: f64::INFINITY,
            prefault_max: f64::NEG_INFINITY,
            held_periods: 0,
            dt_s,
            last_state: rig_state::STARTING,
            safety,
        }
    }

    /// The earliest fault's detection time, s.
    pub fn first_fault_s(&self) -> Option<f64> {
        self.faults.first().map(|f| f.report.detected_at_s)
    }

    pub fn push(&mut self, r: &RigRecord) {
        let holding = matches!(
            r.state,
            rig_state::HOLD | rig_state::UNLOAD | rig_state::OPERATOR_HOLD
        );
        if holding {
            self.held_periods += 1;
        }
        self.last_state = r.state;
        let (pre_min, pre_max) = (self.prefault_min, self.prefault_max);
        for f in &mut self.faults {
            // A record at the detection's period counts as "after": the hold starts there.
            if r.t_s + 0.5 * self.dt_s < f.report.detected_at_s {
                continue;
            }
            if !f.seen {
                f.seen = true;
                f.report.position_at_fault_m = r.x_m;
                f.report.prefault_range_m = [pre_min, pre_max];
            }
            if holding && f.report.hold_started_at_s.is_none() {
                f.report.hold_started_at_s = Some(r.t_s);
            }
            f.report.largest_excursion_m = f
                .report
                .largest_excursion_m
                .max((r.x_m - f.report.position_at_fault_m).abs());
            f.after_min = f.after_min.min(r.x_m);
            f.after_max = f.after_max.max(r.x_m);
        }
        let before_all = self
            .faults
            .iter()
            .all(|f| r.t_s + 0.5 * self.dt_s < f.report.detected_at_s);
        if before_all || self.faults.is_empty() {
            self.prefault_min = self.prefault_min.min(r.x_m);
            self.prefault_max = self.prefault_max.max(r.x_m);
        }
    }

    pub fn finish(mut self) -> Safety {
        for f in &mut self.faults {
            let [lo, hi] = f.report.prefault_range_m;
            if f.seen && lo.is_finite() {
                f.report.beyond_prefault_range_m =
                    (f.after_max - hi).max(lo - f.after_min).max(0.0);
            }
            f.report.time_to_rest_s = self
                .rest_times
                .iter()
                .find(|&&t| t >= f.report.detected_at_s - 0.5 * self.dt_s)
                .map(|t| (t - f.report.detected_at_s).max(0.0));
        }
        self.safety.faults = self.faults.into_iter().map(|f| f.report).collect();
        self.safety.held_s = self.held_periods as f64 * self.dt_s;
        self.safety.final_state = rig_state_name(self.last_state).to_string();
        self.safety.at_rest = !self.rest_times.is_empty();
        self.safety
    }
}
