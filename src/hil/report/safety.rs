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
    /// Specimen displacement at the detection, m (none: no rig record at or after it).
    pub position_at_fault_m: Option<f64>,
    /// Largest |x - x(fault)| after the detection, m (none: no rig record at or after it).
    pub largest_excursion_m: Option<f64>,
    /// Range of the displacement before the fault, m.
    pub prefault_range_m: [f64; 2],
    /// How far the specimen went outside the pre-fault range after the fault, m (0: within;
    /// none: no rig record before and after it).
    pub beyond_prefault_range_m: Option<f64>,
    /// From the detection to the rig's at-rest event (an external rig's: read from its
    /// measured displacement, `SafetyTracker::measured_rest`), s (none: never at rest; 0
    /// when the specimen was already at rest in an earlier fault's hold).
    pub time_to_rest_s: Option<f64>,
    /// The rig already held the specimen when this fault came (a second fault in the
    /// hold of an earlier one): since when, s. `hold_started_at_s` is then that hold's.
    pub already_held_since_s: Option<f64>,
    /// For `loop-unstable`: what the emulator's stability monitor saw before the trip.
    pub instability: Option<InstabilitySeen>,
    /// For `loop-unstable` and `displacement-out-of-range` in law mode: whether any lead
    /// would have held the linearised loop in front of the actuator the run met
    /// (`check::after_trip`).
    pub leads_after_trip: Option<crate::hil::check::after_trip::LeadsAfterTrip>,
}

/// What the stability monitor saw in the window before a `loop-unstable` trip (from the
/// emulator's records: the energy the loop generated in the monitored band and the
/// displacement's oscillation in it), against its bounds.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct InstabilitySeen {
    /// The window before the detection, s (the persistence plus 50 ms).
    pub window_s: f64,
    pub peak_generated_energy_j: f64,
    pub max_generated_energy_j: f64,
    pub peak_oscillation_m: f64,
    pub max_oscillation_m: f64,
    pub band_hz: (f64, f64),
}

impl InstabilitySeen {
    /// Which bound the loop crossed: the energy is checked first, as the monitor does.
    pub fn bound(&self) -> &'static str {
        if self.peak_generated_energy_j > self.max_generated_energy_j {
            "generated energy"
        } else if self.peak_oscillation_m > self.max_oscillation_m {
            "oscillation"
        } else {
            "neither in the records"
        }
    }

    /// One clause for the console.
    pub fn describe(&self) -> String {
        format!(
            "the {} bound: in the {:.0}-{:.0} Hz band the loop generated up to {:.3} J (bound {:.3} J) and the displacement oscillated up to {:.1} um (bound {:.1} um) in the {:.2} s before",
            self.bound(),
            self.band_hz.0,
            self.band_hz.1,
            self.peak_generated_energy_j,
            self.max_generated_energy_j,
            self.peak_oscillation_m * 1e6,
            self.max_oscillation_m * 1e6,
            self.window_s
        )
    }
}

/// The energy the loop generated over the whole run, as the stability monitor measured
/// it (the emulator's records): its peak and the longest stretch above the bound. A
/// stretch longer than the monitor's persistence that did not trip was a ring dying away
/// (`StabilityMonitor`): stable, but the rendering was not passive there.
#[derive(Debug, Clone, Copy, Serialize, PartialEq, Default)]
pub struct LoopEnergy {
    pub band_hz: (f64, f64),
    pub peak_generated_energy_j: f64,
    pub max_generated_energy_j: f64,
    /// The longest stretch with the generated energy above `max_generated_energy_j`, s,
    /// and where it began (0 and NaN: never above).
    pub longest_above_bound_s: f64,
    pub longest_above_bound_at_s: f64,
    /// The monitor's persistence, s.
    pub persist_s: f64,
}

impl LoopEnergy {
    /// Above the bound for longer than the persistence: not passive (tripped or not).
    pub fn not_passive(&self) -> bool {
        self.longest_above_bound_s > self.persist_s
    }

    /// One clause for the console.
    pub fn describe(&self) -> String {
        format!(
            "the loop generated up to {:.3} J in the {:.0}-{:.0} Hz band, above the {:.3} J bound for {:.2} s from {:.3} s (longer than the monitor's {:.2} s persistence; a ring dying away is not tripped, but it is not the passive element's)",
            self.peak_generated_energy_j,
            self.band_hz.0,
            self.band_hz.1,
            self.max_generated_energy_j,
            self.longest_above_bound_s,
            self.longest_above_bound_at_s,
            self.persist_s
        )
    }
}

/// Follows the emulator's records for the windows before its `loop-unstable` trips, and
/// the loop's energy over the whole run.
#[derive(Debug, Clone)]
pub struct InstabilityTracker {
    bounds: crate::hil::passivity::StabilityBounds,
    /// (detection time, what was seen).
    trips: Vec<(f64, InstabilitySeen)>,
    energy: LoopEnergy,
    /// The stretch above the bound in progress: (start s, last s).
    above: Option<(f64, f64)>,
}

impl InstabilityTracker {
    pub fn new(events: &[EventRecord], bounds: crate::hil::passivity::StabilityBounds) -> Self {
        let window_s = bounds.persist_s + 0.05;
        let trips = events
            .iter()
            .filter(|e| {
                e.kind == event_kind::FAULT
                    && e.fault_code == crate::hil::fault::Fault::LoopUnstable.code()
            })
            .map(|e| {
                (
                    e.t_s,
                    InstabilitySeen {
                        // Never longer than the run before the trip.
                        window_s: window_s.min(e.t_s.max(0.0)),
                        peak_generated_energy_j: 0.0,
                        max_generated_energy_j: bounds.max_generated_energy_j,
                        peak_oscillation_m: 0.0,
                        max_oscillation_m: bounds.max_oscillation_m,
                        band_hz: bounds.band_hz,
                    },
                )
            })
            .collect();
        InstabilityTracker {
            bounds,
            trips,
            energy: LoopEnergy {
                band_hz: bounds.band_hz,
                max_generated_energy_j: bounds.max_generated_energy_j,
                longest_above_bound_at_s: f64::NAN,
                persist_s: bounds.persist_s,
                ..LoopEnergy::default()
            },
            above: None,
        }
    }

    /// The loop's energy over the records pushed so far.
    pub fn loop_energy(&self) -> LoopEnergy {
        self.energy
    }

    /// One emulator record: `t_s`, the band's generated energy and oscillation.
    pub fn push(&mut self, t_s: f64, generated_energy_j: f64, oscillation_m: f64) {
        if generated_energy_j.is_finite() {
            let e = &mut self.energy;
            e.peak_generated_energy_j = e.peak_generated_energy_j.max(generated_energy_j);
            if generated_energy_j > e.max_generated_energy_j {
                let (start, _) = self.above.unwrap_or((t_s, t_s));
                self.above = Some((start, t_s));
                if t_s - start > e.longest_above_bound_s {
                    e.longest_above_bound_s = t_s - start;
                    e.longest_above_bound_at_s = start;
                }
            } else {
                self.above = None;
            }
        }
        let window = self.bounds.persist_s + 0.05;
        for (at, seen) in &mut self.trips {
            if t_s <= *at + 1e-9 && t_s >= *at - window {
                if generated_energy_j.is_finite() {
                    seen.peak_generated_energy_j =
                        seen.peak_generated_energy_j.max(generated_energy_j);
                }
                if oscillation_m.is_finite() {
                    seen.peak_oscillation_m = seen.peak_oscillation_m.max(oscillation_m.abs());
                }
            }
        }
    }

    /// Attaches what was seen to the emulator's `loop-unstable` reports.
    pub fn attach(self, safety: &mut Safety) {
        for f in &mut safety.faults {
            if f.process != "emulator" || f.fault != "loop-unstable" {
                continue;
            }
            if let Some((_, seen)) = self
                .trips
                .iter()
                .find(|(at, _)| (at - f.detected_at_s).abs() < 1e-9)
            {
                f.instability = Some(*seen);
            }
        }
    }
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
    /// How the run ended for the specimen: `finished` when the rig ended its programme
    /// while running (its end-of-run event), else the rig's state in its last record
    /// (`hold`, `unload`, `operator-hold`, ...).
    pub final_state: String,
    /// Whether the rig reported the specimen at rest in its hold (an external rig: whether
    /// its measured displacement came to rest in it, `SafetyTracker::measured_rest`).
    pub at_rest: bool,
    /// An external rig whose records (the emulator's of its samples) end in force
    /// control after a fault: the hold its heartbeat still told (when and why), or that
    /// how it ended is unknown; either way `held_s`, the excursions and `at_rest` cover
    /// only what was recorded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hold_not_recorded: Option<String>,
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

/// Whether a rig in `state` holds the specimen (a fault's hold, the final unload, an
/// operator hold): its programme stands still.
pub fn is_holding(state: u32) -> bool {
    matches!(
        state,
        rig_state::HOLD | rig_state::UNLOAD | rig_state::OPERATOR_HOLD
    )
}

/// The periods a record in `state` at period `step` adds to the time held, after the
/// record before it (`previous`: its period and whether it held). An external rig's
/// samples reach the report through the link, which may lose some: a gap between two
/// records that both hold counts whole as held (a resume and a new fault both lost inside
/// one gap would be counted as held too; the events are not consulted); any other record
/// counts its own period, a repeated one none.
pub fn held_periods(previous: Option<(u64, bool)>, step: u64, state: u32) -> u64 {
    if !is_holding(state) {
        return 0;
    }
    match previous {
        Some((before, true)) if step > before => step - before,
        // The same sample again (a duplicate over the link): its period is counted already.
        Some((before, _)) if step == before => 0,
        _ => 1,
    }
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
    /// The last record's period and whether it held (`held_periods`).
    last_period: Option<(u64, bool)>,
    /// When the rig's current hold began (none: not holding).
    hold_since_s: Option<f64>,
    /// The rig recorded its end-of-run event.
    rig_finished: bool,
    /// An external rig records no at-rest event: its rest is read from its measured
    /// displacement in a hold (`[safety] rest_band_m` over `rest_window_s`, the simulated
    /// rig's rule), in this window of samples; `None` for the simulated rig.
    measured_rest: Option<MeasuredRest>,
    pub safety: Safety,
}

/// `SafetyTracker::measured_rest`: the hold's last samples, the window's length and band,
/// and whether this hold's rest was read already.
#[derive(Debug, Clone)]
struct MeasuredRest {
    window: std::collections::VecDeque<f64>,
    samples: usize,
    band_m: f64,
    read: bool,
    /// The last sample's period taken (a duplicate over the link is not taken twice).
    last_step: Option<u64>,
}

impl SafetyTracker {
    pub fn new(events: &[EventRecord], dt_s: f64) -> SafetyTracker {
        let mut safety = Safety::default();
        let mut faults = Vec::new();
        let mut rest_times = Vec::new();
        let mut rig_finished = false;
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
                        position_at_fault_m: None,
                        largest_excursion_m: None,
                        prefault_range_m: [f64::NAN, f64::NAN],
                        beyond_prefault_range_m: None,
                        time_to_rest_s: None,
                        already_held_since_s: None,
                        instability: None,
                        leads_after_trip: None,
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
                event_kind::FINISHED => rig_finished = true,
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
            last_period: None,
            hold_since_s: None,
            rig_finished,
            measured_rest: None,
            safety,
        }
    }

    /// For an external rig: read its rest from its measured displacement in a hold, within
    /// `band_m` over `window_s` (`measured_rest`).
    pub fn reading_rest_from_samples(mut self, band_m: f64, window_s: f64) -> SafetyTracker {
        let samples = ((window_s / self.dt_s).round() as usize).max(2);
        self.measured_rest = Some(MeasuredRest {
            window: std::collections::VecDeque::with_capacity(samples),
            samples,
            band_m,
            read: false,
            last_step: None,
        });
        self
    }

    /// The earliest fault's detection time, s.
    pub fn first_fault_s(&self) -> Option<f64> {
        self.faults.first().map(|f| f.report.detected_at_s)
    }

    pub fn push(&mut self, r: &RigRecord) {
        let holding = is_holding(r.state);
        self.held_periods += held_periods(self.last_period, r.step_idx, r.state);
        self.last_period = Some((r.step_idx, holding));
        // The hold this record belongs to, and whether it began before this record.
        let held_before = self.hold_since_s;
        if !holding {
            self.hold_since_s = None;
        } else if self.hold_since_s.is_none() {
            self.hold_since_s = Some(r.t_s);
        }
        self.last_state = r.state;
        if let Some(m) = self
            .measured_rest
            .as_mut()
            .filter(|m| m.last_step.is_none_or(|s| r.step_idx > s))
        {
            m.last_step = Some(r.step_idx);
            if !holding {
                m.window.clear();
                m.read = false;
            } else if !m.read {
                if m.window.len() == m.samples {
                    m.window.pop_front();
                }
                m.window.push_back(r.x_m);
                let (lo, hi) = m
                    .window
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
                        (lo.min(x), hi.max(x))
                    });
                if m.window.len() == m.samples && hi - lo <= m.band_m {
                    m.read = true;
                    self.rest_times.push(r.t_s);
                }
            }
        }
        let (pre_min, pre_max) = (self.prefault_min, self.prefault_max);
        for f in &mut self.faults {
            // A record at the detection's period counts as "after": the hold starts there.
            if r.t_s + 0.5 * self.dt_s < f.report.detected_at_s {
                continue;
            }
            let at_fault = *f.report.position_at_fault_m.get_or_insert(r.x_m);
            if !f.seen {
                f.seen = true;
                f.report.prefault_range_m = [pre_min, pre_max];
                // Already holding before its detection: a fault in an earlier one's hold.
                if let Some(since) = held_before.filter(|_| holding) {
                    f.report.already_held_since_s = Some(since);
                    f.report.hold_started_at_s = Some(since);
                }
            }
            if holding && f.report.hold_started_at_s.is_none() {
                f.report.hold_started_at_s = Some(r.t_s);
            }
            let excursion = (r.x_m - at_fault).abs();
            f.report.largest_excursion_m = Some(
                f.report
                    .largest_excursion_m
                    .map_or(excursion, |e| e.max(excursion)),
            );
            f.after_min = f.after_min.min(r.x_m);
            f.after_max = f.after_max.max(r.x_m);
        }
        // Every record so far: each fault's pre-fault range is what came before it (a
        // second fault in the first one's hold is measured against the hold's motion too).
        self.prefault_min = self.prefault_min.min(r.x_m);
        self.prefault_max = self.prefault_max.max(r.x_m);
    }

    pub fn finish(mut self) -> Safety {
        // The events' and the measured rests in one order (`find` below takes the first).
        self.rest_times.sort_by(f64::total_cmp);
        for f in &mut self.faults {
            let [lo, hi] = f.report.prefault_range_m;
            if f.seen && lo.is_finite() {
                f.report.beyond_prefault_range_m =
                    Some((f.after_max - hi).max(lo - f.after_min).max(0.0));
            }
            // In an earlier fault's hold, an at-rest event of that hold counts (0: the
            // specimen was at rest already when this one came).
            let from = f
                .report
                .already_held_since_s
                .unwrap_or(f.report.detected_at_s);
            f.report.time_to_rest_s = self
                .rest_times
                .iter()
                .find(|&&t| t >= from - 0.5 * self.dt_s)
                .map(|t| (t - f.report.detected_at_s).max(0.0));
        }
        self.safety.faults = self.faults.into_iter().map(|f| f.report).collect();
        self.safety.held_s = self.held_periods as f64 * self.dt_s;
        // The last record is the last period run; a programme that reached its end while
        // running finished, a hold or unload stays what it was.
        let ended_running = self.last_state == rig_state::RUNNING && self.rig_finished;
        self.safety.final_state = if ended_running {
            "finished"
        } else {
            rig_state_name(self.last_state)
        }
        .to_string();
        self.safety.at_rest = !self.rest_times.is_empty();
        self.safety
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::records::event::action_code;

    #[test]
    fn the_loop_energy_keeps_the_longest_stretch_above_the_bound() {
        let bounds = crate::hil::passivity::StabilityBounds::DEFAULT;
        let dt = 1.0 / 4096.0;
        let mut t = InstabilityTracker::new(&[], bounds);
        // 50 ms above the bound at 1 s, 200 ms above it (peak 0.27 J) at 2 s.
        for i in 0..(3 * 4096) {
            let ts = i as f64 * dt;
            let e = if (1.0..1.05).contains(&ts) {
                0.08
            } else if (2.0..2.2).contains(&ts) {
                0.27 - (ts - 2.0)
            } else {
                0.01
            };
            t.push(ts, e, 0.0);
        }
        let e = t.loop_energy();
        assert_eq!(e.peak_generated_energy_j, 0.27);
        assert!((e.longest_above_bound_at_s - 2.0).abs() < 1e-12, "{e:?}");
        assert!((e.longest_above_bound_s - 0.2).abs() <= dt, "{e:?}");
        assert!(e.not_passive());
        assert!(
            e.describe().contains("0.20 s from 2.000 s"),
            "{}",
            e.describe()
        );
        // The short stretch alone is within the persistence: passive enough.
        let mut t = InstabilityTracker::new(&[], bounds);
        for i in 0..4096 {
            let ts = 0.9 + i as f64 * dt;
            t.push(ts, if (1.0..1.05).contains(&ts) { 0.08 } else { 0.0 }, 0.0);
        }
        let e = t.loop_energy();
        assert!(
            (e.longest_above_bound_s - 0.05).abs() <= dt && !e.not_passive(),
            "{e:?}"
        );
    }

    const DT: f64 = 0.01;

    fn event(t_s: f64, kind: u32) -> EventRecord {
        EventRecord {
            t_s,
            process: 2,
            kind,
            fault_code: 0,
            remote_fault_code: 0,
            action: action_code::HOLD,
            detection_latency_periods: 3,
            step_idx: 0,
            value: 0.0,
        }
    }

    fn record(step: u64, x_m: f64, state: u32) -> RigRecord {
        RigRecord {
            t_s: step as f64 * DT,
            step_idx: step,
            x_m,
            v_m_per_s: 0.0,
            z_measured_m: x_m,
            command_n: 0.0,
            actuator_force_n: 0.0,
            external_force_n: 0.0,
            programme_time_s: 0.0,
            programme_cycle: 0,
            programme_block: 0,
            command_sample_seq: step,
            command_age_periods: 0,
            law_age_periods: 0,
            mode: 0,
            state,
            fault_code: 0,
            wake_late_ns: 0,
            catch_up: 0,
            published: 1,
        }
    }

    fn track(events: &[EventRecord], records: &[RigRecord]) -> Safety {
        let mut tracker = SafetyTracker::new(events, DT);
        for r in records {
            tracker.push(r);
        }
        tracker.finish()
    }

    #[test]
    fn a_programme_that_reached_its_end_running_finished_and_a_cut_one_did_not() {
        let running: Vec<_> = (0..10)
            .map(|i| record(i, 0.0, rig_state::RUNNING))
            .collect();
        let ended = track(&[event(0.1, event_kind::FINISHED)], &running);
        assert_eq!(ended.final_state, "finished");
        // No end-of-run event: the records stop in the middle of the programme.
        assert_eq!(track(&[], &running).final_state, "running");
        // A run that ended in its hold stays a hold, end-of-run event or not.
        let mut held = running.clone();
        held.push(record(10, 0.0, rig_state::HOLD));
        let ended_held = track(&[event(0.11, event_kind::FINISHED)], &held);
        assert_eq!(ended_held.final_state, "hold");
        assert!((ended_held.held_s - DT).abs() < 1e-12);
    }

    /// An external rig's samples come over a link that may lose some: a gap between two
    /// records in a hold was held all through and counts whole; a gap into a hold counts
    /// the record's own period only (the rig may have run until then).
    #[test]
    fn samples_lost_within_a_hold_count_as_held() {
        let mut records: Vec<_> = (0..10)
            .map(|i| record(i, 0.0, rig_state::RUNNING))
            .collect();
        // Running at 9, then the link loses 10-13: the hold is seen from 14.
        for step in [14, 15, 16, 40, 41] {
            records.push(record(step, 0.0, rig_state::HOLD));
        }
        let safety = track(&[], &records);
        // 14, 15, 16: one each; 17-40 lost in the hold: 24; 41: one.
        assert!(
            (safety.held_s - 28.0 * DT).abs() < 1e-12,
            "{}",
            safety.held_s / DT
        );
        assert_eq!(held_periods(None, 5, rig_state::HOLD), 1);
        assert_eq!(
            held_periods(Some((4, true)), 9, rig_state::OPERATOR_HOLD),
            5
        );
        assert_eq!(held_periods(Some((4, false)), 9, rig_state::UNLOAD), 1);
        assert_eq!(held_periods(Some((4, true)), 9, rig_state::RUNNING), 0);
        assert_eq!(held_periods(Some((9, true)), 9, rig_state::HOLD), 0);
    }

    /// An external rig records no at-rest event: its rest is read from its measured
    /// displacement in each hold, once per hold, the window restarting when it runs again;
    /// a duplicate sample is not counted twice (it would shorten the window).
    #[test]
    fn an_external_rigs_rest_is_read_from_its_samples_once_per_hold() {
        // DT = 10 ms, a 50 ms window of 5 samples within 2 um. Running to 0.09 s; a hold
        // from 0.10 s that swings 10 um to 0.15 s, then within 1 um; resumed at 0.30 s;
        // a second hold from 0.40 s, still from the first of its samples.
        let mut records = Vec::new();
        for i in 0..50u64 {
            let state = match i {
                10..=29 | 40.. => rig_state::HOLD,
                _ => rig_state::RUNNING,
            };
            let x = match i {
                10..=15 => 10e-6 * (i % 2) as f64,
                16..=29 => 0.5e-6 * (i % 2) as f64,
                _ => 0.0,
            };
            records.push(record(i, x, state));
            // The link repeats the hold's third quiet sample (counted twice, the window
            // would be full one sample early).
            if i == 18 {
                records.push(record(i, x, state));
            }
        }
        let events = [
            event(0.10, event_kind::FAULT),
            event(0.40, event_kind::FAULT),
        ];
        let mut tracker = SafetyTracker::new(&events, DT).reading_rest_from_samples(2e-6, 0.05);
        for r in &records {
            tracker.push(r);
        }
        let s = tracker.finish();
        assert!(s.at_rest);
        // Quiet from step 16: five samples (16-20) at 0.20 s, 0.10 s after the trip.
        let first = s.faults[0].time_to_rest_s.unwrap();
        assert!((first - 0.10).abs() < 1e-9, "{first}");
        // The second hold's window starts afresh at 0.40 s: 40-44, at 0.44 s.
        let second = s.faults[1].time_to_rest_s.unwrap();
        assert!((second - 0.04).abs() < 1e-9, "{second}");
        // Without the reading (the simulated rig, whose events say it): never at rest.
        let s = track(&events, &records);
        assert!(!s.at_rest && s.faults[0].time_to_rest_s.is_none());
    }

    /// A second fault in the first one's hold (the emulator's own stall trip after the
    /// controller's stale setpoints held the specimen): it says the rig already held since
    /// the first, was already at rest, and its pre-fault range includes the hold's motion.
    #[test]
    fn a_fault_in_an_earlier_faults_hold_says_so() {
        // Running at x = 0 until 0.05 s; the hold from 0.05 s moves it to 3 um and rests.
        let records: Vec<_> = (0..30)
            .map(|i| {
                if i < 5 {
                    record(i, 0.0, rig_state::RUNNING)
                } else {
                    record(i, (i.min(8) - 5) as f64 * 1e-6, rig_state::HOLD)
                }
            })
            .collect();
        let mut second = event(0.2, event_kind::FAULT);
        second.process = 1;
        let events = [
            event(0.05, event_kind::FAULT),
            event(0.1, event_kind::AT_REST),
            second,
        ];
        let s = track(&events, &records);
        let (first, second) = (&s.faults[0], &s.faults[1]);
        assert_eq!(first.already_held_since_s, None);
        assert_eq!(first.hold_started_at_s, Some(5.0 * DT));
        assert!((first.time_to_rest_s.unwrap() - 0.05).abs() < 1e-12);
        assert!((first.beyond_prefault_range_m.unwrap() - 3e-6).abs() < 1e-15);
        assert_eq!(second.already_held_since_s, Some(5.0 * DT));
        assert_eq!(second.hold_started_at_s, Some(5.0 * DT));
        assert_eq!(second.time_to_rest_s, Some(0.0));
        assert_eq!(second.prefault_range_m, [0.0, 3e-6]);
        assert_eq!(second.beyond_prefault_range_m, Some(0.0));
        assert_eq!(second.largest_excursion_m, Some(0.0));
    }

    /// The window before a `loop-unstable` trip: the peaks of the monitor's energy and
    /// oscillation from the emulator's records, attached to the emulator's report only,
    /// and the bound named.
    #[test]
    fn a_loop_unstable_trip_names_the_bound_it_crossed() {
        let bounds = crate::hil::passivity::StabilityBounds::DEFAULT;
        let mut trip = event(1.0, event_kind::FAULT);
        trip.fault_code = crate::hil::fault::Fault::LoopUnstable.code();
        let mut other = event(0.5, event_kind::FAULT);
        other.fault_code = crate::hil::fault::Fault::LoopUnstable.code();
        let events = [other, trip];
        let mut tracker = InstabilityTracker::new(&events, bounds);
        // Energy rising to 0.2 J before 1.0 s (outside the window of the trip at 0.5 s
        // after it), oscillation 40 um; a spike after the trip is not counted.
        for i in 0..=1100 {
            let t = i as f64 * 1e-3;
            let energy = if t > 0.9 && t <= 1.0 {
                0.2 * (t - 0.9) / 0.1
            } else {
                0.01
            };
            let osc = if t > 1.0 { 5e-3 } else { 40e-6 };
            tracker.push(t, energy, if i % 2 == 0 { osc } else { -osc });
        }
        let mut safety = Safety {
            faults: vec![FaultReport {
                process: "emulator".into(),
                fault: "loop-unstable".into(),
                cause: None,
                detected_at_s: 1.0,
                detection_latency_periods: 0,
                action: None,
                hold_started_at_s: None,
                position_at_fault_m: None,
                largest_excursion_m: None,
                prefault_range_m: [0.0, 0.0],
                beyond_prefault_range_m: None,
                time_to_rest_s: None,
                already_held_since_s: None,
                instability: None,
                leads_after_trip: None,
            }],
            ..Safety::default()
        };
        let mut controller = safety.faults[0].clone();
        controller.process = "controller".into();
        controller.fault = "emulator-tripped".into();
        safety.faults.push(controller);
        tracker.attach(&mut safety);
        let seen = safety.faults[0].instability.expect("attached");
        assert!(
            (seen.peak_generated_energy_j - 0.2).abs() < 1e-9,
            "{seen:?}"
        );
        assert!((seen.peak_oscillation_m - 40e-6).abs() < 1e-15, "{seen:?}");
        assert_eq!(seen.bound(), "generated energy");
        assert!(
            seen.describe().contains("0.200 J (bound 0.050 J)"),
            "{}",
            seen.describe()
        );
        assert_eq!(safety.faults[1].instability, None);
    }

    #[test]
    fn excursion_is_measured_from_the_position_at_the_fault_and_unknown_without_records() {
        // x rises 1 um per period; the fault at 0.05 s, the hold from 0.07 s.
        let records: Vec<_> = (0..10)
            .map(|i| {
                let state = if i >= 7 {
                    rig_state::HOLD
                } else {
                    rig_state::RUNNING
                };
                record(i, i as f64 * 1e-6, state)
            })
            .collect();
        let s = track(&[event(0.05, event_kind::FAULT)], &records);
        let f = &s.faults[0];
        assert_eq!(f.position_at_fault_m, Some(5.0 * 1e-6));
        assert!((f.largest_excursion_m.unwrap() - 4e-6).abs() < 1e-15);
        assert_eq!(f.prefault_range_m, [0.0, 4.0 * 1e-6]);
        assert!((f.beyond_prefault_range_m.unwrap() - 5e-6).abs() < 1e-15);
        assert_eq!(f.hold_started_at_s, Some(7.0 * DT));
        // A fault after the last record: nothing is known of the specimen after it.
        let s = track(&[event(0.5, event_kind::FAULT)], &records);
        let f = &s.faults[0];
        assert_eq!(f.position_at_fault_m, None);
        assert_eq!(f.largest_excursion_m, None);
        assert_eq!(f.beyond_prefault_range_m, None);
    }
}
