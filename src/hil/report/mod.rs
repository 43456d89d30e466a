//! The `hil` report, built from the run's records in streaming passes (no whole-run
//! arrays, so a run of hours reports in constant memory): the side streams first (events,
//! emulator, controller: latency histograms, the processes' own gaps), then the rig's
//! records against the offline reference stepped in lockstep (fidelity, stability,
//! stalls and their transients, what each fault did to the specimen), then decimated plots.
//! Offline code: never runs inside a loop.

pub mod actuator;
pub mod compensation;
pub mod decimate;
pub mod element;
pub mod fidelity;
pub mod latency;
pub mod safety;
pub mod stalls;

use std::collections::VecDeque;
use std::path::Path;

use hdrhistogram::Histogram;
use serde::Serialize;

use super::config::HilConfig;
use super::controller::ControllerRecord;
use super::emulator::{AfterFaultSampleRecord, EmulatorRecord};
use crate::ipc::messages::{command_mode, rig_state};
use crate::plot::{draw_png, Panel, Series};
use crate::records::{EventRecord, RecordSet};
use crate::rig::actuator::{ActuatorParamRecord, ActuatorTruthRecord};
use crate::rig::core::RigRecord;
use crate::rig::reference::{OperatorPause, PauseStep, ReferenceStepper};
use decimate::Decimator;
use fidelity::{CentredHighPass, Fidelity, ResidualAnalyser, Stability};
use latency::{histogram, log_bins, percentiles, Latency};
use safety::{InstabilityTracker, Safety, SafetyTracker};
use stalls::{Gap, StallTracker, Stalls, STALL_MIN_PERIODS};

pub use fidelity::{
    band_errors, BandError, STABLE_MAX_GROWTH_PER_S, STABLE_MAX_MEDIAN_RESONANT_PEAK_M,
};
pub use latency::Percentiles;

/// Points per plotted series (each bucket contributes its min and max).
const PLOT_BUCKETS: usize = 4000;

/// How far the load programme got.
#[derive(Debug, Clone, Serialize, Default)]
pub struct ProgrammeSummary {
    /// Completed passes through the block sequence (durability cycles).
    pub cycles_completed: u64,
    /// The block running at the end (index) and its name.
    pub last_block: u32,
    pub last_block_name: String,
    /// Programme time reached, s (it pauses while held).
    pub programme_time_s: f64,
    /// Programme time at which it would have ended, s.
    pub end_s: f64,
    /// Whether it reached its end (rather than a hold or an operator stop ending the run).
    pub completed: bool,
}

/// Where the analysis read the records from.
#[derive(Debug, Clone, Serialize, Default)]
pub struct RecordsInfo {
    pub files: Vec<String>,
    /// Files cut short (a killed writer): read up to their last closed chunk.
    pub truncated: Vec<String>,
}

/// Results of the analysis of one run's records.
#[derive(Debug, Clone, Serialize, Default)]
pub struct Analysis {
    /// Emulator model steps.
    pub steps: u64,
    pub rig_steps: u64,
    pub fidelity: Fidelity,
    pub stability: Stability,
    pub latency_ns: Latency,
    pub safety: Safety,
    /// The energy the loop generated in the stability monitor's band over the run.
    pub loop_energy: safety::LoopEnergy,
    pub stalls: Stalls,
    pub programme: ProgrammeSummary,
    /// Largest resonant (>100 Hz) residual compared (no holds), m: the largest transient.
    pub largest_transient_m: f64,
    pub records: RecordsInfo,
    /// The controller's compensation: lead and gain identified, the guard's activity, the
    /// faithful band.
    pub compensation: compensation::CompensationReport,
    /// Every event, as one line each.
    pub events: Vec<String>,
    /// Where the rig's view comes from: its own records, or (an external rig) what it
    /// sent in its samples, from the emulator's records.
    pub rig_view: String,
    /// The rig's actuator as it truly was (its `/rig/actuator` records; none for an
    /// external rig).
    pub actuator_truth: Option<actuator::ActuatorTruth>,
    /// The element's self-heating over the run (only with `self-heating` in the model).
    pub element_thermal: Option<element::ElementThermal>,
}

/// `Analysis::rig_view` when the rig's own records exist.
pub const RIG_VIEW_OWN: &str = "the rig's own records";
/// `Analysis::rig_view` for an external rig.
pub const RIG_VIEW_EXTERNAL: &str = "external rig: what it sent in its samples (measured displacement, measured force, its state and fault), from the emulator's records; its true displacement, load programme, commands applied and own events are not available, and its own fault is dated by the first sample that carried it; the fidelity compares the measured displacement with the offline reference of this configuration's scenario, meaningful only if the rig ran that scenario on the configured specimen";

/// An external rig's faults named as such (the events' process label is the simulated
/// rig's, `bench_rig`).
fn external_rig_named(mut safety: safety::Safety) -> safety::Safety {
    for f in &mut safety.faults {
        f.process = crate::records::event::external_rig_labelled(&f.process);
    }
    safety
}

/// Whether `t_s` comes before the rig fault found so far (the streams are not read in
/// time order: the first fault is the earliest, not the first met).
fn earlier(found: &Option<(f64, u64, u32, u32)>, t_s: f64) -> bool {
    found.is_none_or(|(t, _, _, _)| t_s < t)
}

/// A time in s as us for the reports' JSON, to the nanosecond: `2850 us` reads 2850, not
/// the 2849.9999999999995 that `s * 1e6` leaves of a lead given in us.
pub(crate) fn json_us(s: f64) -> f64 {
    (s * 1e9).round() / 1e3
}

/// A range for the console, `lo-hi` to the unit (`lo to hi` when an end is negative: not
/// "-1510-5158").
pub(crate) fn span(lo: f64, hi: f64) -> String {
    // Rounded first, and `+ 0.0` makes a -0 a 0.
    let (lo, hi) = (lo.round() + 0.0, hi.round() + 0.0);
    if lo < 0.0 || hi < 0.0 {
        format!("{lo:.0} to {hi:.0}")
    } else {
        format!("{lo:.0}-{hi:.0}")
    }
}

/// The rig's view of one period from the emulator's record of its sample (external rig).
fn rig_record_from_sample(e: &EmulatorRecord) -> RigRecord {
    rig_view_record(
        e.t_s,
        e.sample_seq,
        e.z_used_m,
        e.rig_force_n,
        e.rig_state,
        e.rig_fault_code,
    )
}

/// The same from a sample the emulator recorded after its own fault (the rig's hold).
fn rig_record_after_fault(a: &AfterFaultSampleRecord) -> RigRecord {
    rig_view_record(
        a.t_s,
        a.sample_seq,
        a.z_measured_m,
        a.rig_force_n,
        a.rig_state,
        a.rig_fault_code,
    )
}

fn rig_view_record(
    t_s: f64,
    seq: u64,
    z_m: f64,
    force_n: f64,
    state: u32,
    fault_code: u32,
) -> RigRecord {
    RigRecord {
        t_s,
        step_idx: seq,
        x_m: z_m,
        // Unknown: a resume from an operator hold restarts the reference at rest.
        v_m_per_s: 0.0,
        z_measured_m: z_m,
        command_n: f64::NAN,
        actuator_force_n: force_n,
        external_force_n: f64::NAN,
        // Unknown: the rig's sample time stands in (the comparison ends at a hold).
        programme_time_s: t_s,
        programme_cycle: 0,
        programme_block: 0,
        command_sample_seq: u64::MAX,
        command_age_periods: 0,
        law_age_periods: 0,
        mode: crate::ipc::messages::command_mode::LAW,
        state,
        fault_code,
        wake_late_ns: 0,
        catch_up: 0,
        published: 1,
    }
}

/// What the side streams give.
struct SideStreams {
    events: Vec<EventRecord>,
    emulator_steps: u64,
    end_to_end: Histogram<u64>,
    wake_jitter: Histogram<u64>,
    emulator_gaps: Vec<Gap>,
    controller_gaps: Vec<Gap>,
    emulator_force: Decimator,
    truncated: Vec<String>,
    /// Records of the rig itself (0: an external rig; its view comes from the samples).
    rig_records: u64,
    /// The first fault an external rig reported in its samples: (t_s, sample, code).
    /// The external rig's first fault from its samples: time, sequence, code, its state.
    sample_rig_fault: Option<(f64, u64, u32, u32)>,
    compensation: compensation::CompensationAnalyser,
    actuator_truth: Option<ActuatorTruthRecord>,
    actuator_params: Vec<ActuatorParamRecord>,
    element: Option<element::ElementTracker>,
    /// The sample the controller's first force or law command answered (none: it sent
    /// none): the rig's own servo held the start until that command reached it.
    first_command_sample: Option<u64>,
}

/// Pass 1: events, the emulator's and the controller's records.
fn read_side_streams(set: &RecordSet, cfg: &HilConfig) -> anyhow::Result<SideStreams> {
    let dt = cfg.loop_.dt_s();
    let mut side = SideStreams {
        events: Vec::new(),
        emulator_steps: 0,
        end_to_end: histogram(),
        wake_jitter: histogram(),
        emulator_gaps: Vec::new(),
        controller_gaps: Vec::new(),
        emulator_force: Decimator::new(0.0, 1e-3, PLOT_BUCKETS),
        truncated: Vec::new(),
        rig_records: 0,
        sample_rig_fault: None,
        compensation: compensation::CompensationAnalyser::new(dt, cfg.programme.end_s),
        actuator_truth: None,
        actuator_params: Vec::new(),
        element: element::ElementTracker::new(&cfg.augmented),
        first_command_sample: None,
    };
    let mut last_cycle: Option<u64> = None;
    let mut last_command_t: Option<f64> = None;
    let keepalive_s = cfg.controller.keepalive_ns as f64 * 1e-9;
    let stats = set.visit(|topic, _, data| {
        use crate::records::Record;
        match topic {
            t if t == EventRecord::TOPIC => {
                if let Some(e) = EventRecord::decode(data) {
                    side.events.push(e);
                }
            }
            t if t == RigRecord::TOPIC => side.rig_records += 1,
            t if t == ActuatorTruthRecord::TOPIC => {
                side.actuator_truth = side.actuator_truth.or(ActuatorTruthRecord::decode(data));
            }
            t if t == ActuatorParamRecord::TOPIC => {
                if let Some(p) = ActuatorParamRecord::decode(data) {
                    if side.actuator_params.len() < 64 {
                        side.actuator_params.push(p);
                    }
                }
            }
            t if t == AfterFaultSampleRecord::TOPIC => {
                if let Some(r) = AfterFaultSampleRecord::decode(data) {
                    if r.rig_fault_code != 0 && earlier(&side.sample_rig_fault, r.t_s) {
                        side.sample_rig_fault =
                            Some((r.t_s, r.sample_seq, r.rig_fault_code, r.rig_state));
                    }
                }
            }
            t if t == EmulatorRecord::TOPIC => {
                if let Some(r) = EmulatorRecord::decode(data) {
                    side.emulator_steps += 1;
                    side.compensation.emulator(&r);
                    // An interpolated step carries the view of the sample after the gap:
                    // it would date the rig's fault to the gap's start.
                    if r.rig_fault_code != 0
                        && r.interpolated == 0
                        && earlier(&side.sample_rig_fault, r.t_s)
                    {
                        side.sample_rig_fault =
                            Some((r.t_s, r.sample_seq, r.rig_fault_code, r.rig_state));
                    }
                    side.emulator_force.push(r.t_s, r.force_n);
                    if let Some(e) = &mut side.element {
                        e.push(r.t_s, r.element_temperature_rise_k);
                    }
                    if last_cycle != Some(r.cycle_idx) {
                        side.wake_jitter.saturating_record(r.wake_late_ns.max(1));
                        if let Some(c) = last_cycle {
                            let gap = r.cycle_idx.saturating_sub(c);
                            if gap >= STALL_MIN_PERIODS && side.emulator_gaps.len() < 10_000 {
                                side.emulator_gaps.push((c as f64 * dt, gap as f64 * dt));
                            }
                        }
                        last_cycle = Some(r.cycle_idx);
                    }
                }
            }
            t if t == ControllerRecord::TOPIC => {
                if let Some(r) = ControllerRecord::decode(data) {
                    side.compensation.controller(&r);
                    if side.first_command_sample.is_none()
                        && matches!(r.mode, command_mode::FORCE | command_mode::LAW)
                        && r.sample_seq != u64::MAX
                    {
                        side.first_command_sample = Some(r.sample_seq);
                    }
                    if r.end_to_end_ns > 0 {
                        side.end_to_end.saturating_record(r.end_to_end_ns);
                    }
                    if let Some(t0) = last_command_t {
                        let gap = r.t_s - t0;
                        if gap > keepalive_s + STALL_MIN_PERIODS as f64 * dt
                            && side.controller_gaps.len() < 10_000
                        {
                            side.controller_gaps.push((t0, gap));
                        }
                    }
                    last_command_t = Some(r.t_s);
                }
            }
            _ => {}
        }
    })?;
    side.truncated = stats
        .truncated
        .iter()
        .map(|(p, e)| format!("{}: {e}", p.display()))
        .collect();
    if side.rig_records == 0 {
        // An external rig records nothing here: its own fault is known from its samples.
        if let Some((t_s, step_idx, code, state)) = side.sample_rig_fault {
            // What the rig did, as its sample says (a rig's own fault is its interlock).
            // The protocol asks a hold of the rig on its own faults.
            let action = match state {
                rig_state::UNLOAD => crate::records::event::action_code::HOLD_UNLOAD,
                _ => crate::records::event::action_code::HOLD,
            };
            side.events.push(EventRecord {
                t_s,
                process: crate::ipc::messages::process_id::RIG,
                kind: crate::records::event_kind::FAULT,
                fault_code: code,
                remote_fault_code: 0,
                action,
                detection_latency_periods: 0,
                step_idx,
                value: f64::NAN,
            });
        }
    }
    side.events.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
    Ok(side)
}

/// Decimated series of the rig pass, for the plots.
struct RigPlots {
    x_hil: Decimator,
    x_ref: Decimator,
    error: Decimator,
    external: Decimator,
    actuator: Decimator,
    /// Around the first fault: (t, x, x_ref, actuator force, state), bounded.
    fault_window: Vec<(f64, f64, f64, f64, u32)>,
}

/// What the rig pass gives.
struct RigPass {
    rig_steps: u64,
    /// The last record's programme position: (cycle, block, programme time).
    programme_at_end: (u64, u32, f64),
    residual: ResidualAnalyser,
    stalls: Stalls,
    safety: Safety,
    loop_energy: safety::LoopEnergy,
    plots: RigPlots,
    /// Where the comparison starts (`Fidelity::compared_from_s`).
    compared_from_s: Option<f64>,
}

/// Pass 2: the rig's records against the offline reference.
fn read_rig_stream(
    set: &RecordSet,
    cfg: &HilConfig,
    side: &SideStreams,
    mut settled: Option<&mut compensation::SettledRendering>,
) -> anyhow::Result<RigPass> {
    let rate = cfg.loop_.rate_hz;
    let dt = cfg.loop_.dt_s();
    let mut reference = ReferenceStepper::new(cfg, cfg.programme.end_s + cfg.safety.hold_max_s);
    let mut residual = ResidualAnalyser::new(rate);
    let mut high_pass = CentredHighPass::new(rate);
    let mut hp_steps: VecDeque<u64> = VecDeque::new();
    let mut stalls = StallTracker::new(rate);
    let mut safety = SafetyTracker::new(&side.events, dt);
    if side.rig_records == 0 {
        safety = safety.reading_rest_from_samples(cfg.safety.rest_band_m, cfg.safety.rest_window_s);
    }
    let mut instability = InstabilityTracker::new(&side.events, cfg.safety.stability);
    let first_fault = safety.first_fault_s();
    let rig_gaps: std::cell::RefCell<Vec<Gap>> = std::cell::RefCell::new(Vec::new());
    let mut catch_up_run: Option<(f64, u64)> = None;
    // A fault hold (or the final unload) ends the comparison; an operator hold pauses it,
    // and the reference restarts from the measured state once the rig is back on the law.
    let mut held = false;
    let mut pause = if side.rig_records == 0 {
        OperatorPause::immediate()
    } else {
        OperatorPause::new(cfg.safety.resume_blend_s, dt)
    };
    let mut rig_steps = 0u64;
    let mut programme_at_end = (0u64, 0u32, 0.0f64);
    // An external rig's samples carry no programme time: its sample time less the time it
    // held (its programme pauses in a hold, as the simulated rig's does).
    let mut external_held_s = 0.0f64;
    let mut external_last: Option<(u64, bool)> = None;
    // Until the first force or law command reaches the rig, its own servo holds the start:
    // that wait is the rig's, not the rendering's. The comparison starts where the rig
    // first applies a command, the reference from the measured state there (relaxed at
    // rest, as after a hold: the element has seen the held start). Without any command
    // sent, the whole run is compared, as before.
    let mut awaiting = side.first_command_sample.is_some();
    let mut compared_from_s: Option<f64> = None;
    let mut plots = RigPlots {
        x_hil: Decimator::new(0.0, 1e-3, PLOT_BUCKETS),
        x_ref: Decimator::new(0.0, 1e-3, PLOT_BUCKETS),
        error: Decimator::new(0.0, 1e-3, PLOT_BUCKETS),
        external: Decimator::new(0.0, 1e-3, PLOT_BUCKETS),
        actuator: Decimator::new(0.0, 1e-3, PLOT_BUCKETS),
        fault_window: Vec::new(),
    };
    let on_hp = |i_hp: (usize, f64),
                 hp_steps: &mut VecDeque<u64>,
                 residual: &mut ResidualAnalyser,
                 stalls: &mut StallTracker| {
        let step = hp_steps.pop_front().unwrap_or(i_hp.0 as u64);
        residual.push_high_passed(i_hp.1);
        let gaps = rig_gaps.borrow();
        let sources: [(&str, &[Gap]); 3] = [
            ("emulator", &side.emulator_gaps),
            ("controller", &side.controller_gaps),
            ("bench_rig", &gaps),
        ];
        stalls.push_high_passed(step, i_hp.1, &sources);
    };
    let mut on_rig_record = |r: &RigRecord| {
        rig_steps += 1;
        // Samples the link lost within a hold count as held (`safety::held_periods`): they
        // come before this record's programme time, its own period after it.
        let held_now = if side.rig_records == 0 {
            let periods = safety::held_periods(external_last, r.step_idx, r.state);
            external_last = Some((r.step_idx, safety::is_holding(r.state)));
            let lost = periods.saturating_sub(1);
            external_held_s += lost as f64 * dt;
            (periods - lost) as f64 * dt
        } else {
            0.0
        };
        let programme_time_s = if side.rig_records > 0 {
            r.programme_time_s
        } else {
            r.t_s - external_held_s
        };
        external_held_s += held_now;
        programme_at_end = (r.programme_cycle, r.programme_block, programme_time_s);
        // The reference follows programme time (it pauses while the rig holds).
        let programme_step = (programme_time_s / dt).round() as u64;
        let step = pause.push(r.state);
        if step == PauseStep::Restart {
            // The simulated rig is wholly on the law here: the force it applies is the
            // element's. An external rig restarts at rest where it held, element relaxed.
            let element_force = (side.rig_records > 0).then_some(r.actuator_force_n);
            reference.resync(r.x_m, r.v_m_per_s, element_force, programme_step);
        }
        if awaiting {
            let applied = if side.rig_records > 0 {
                r.state == rig_state::RUNNING
                    && matches!(r.mode, command_mode::FORCE | command_mode::LAW)
            } else {
                side.first_command_sample.is_some_and(|s| r.step_idx > s)
            };
            if applied {
                awaiting = false;
                compared_from_s = Some(r.t_s);
                reference.resync(r.x_m, r.v_m_per_s, None, programme_step);
            }
        }
        let x_ref_now = reference.advance_to(programme_step);
        safety.push(r);
        // A process's own gap: consecutive catch-up periods of the rig.
        match (&mut catch_up_run, r.catch_up) {
            (Some((_, n)), 1) => *n += 1,
            (None, 1) => catch_up_run = Some((r.t_s, 1)),
            (Some((t0, n)), _) => {
                if *n >= STALL_MIN_PERIODS {
                    rig_gaps.borrow_mut().push((*t0, *n as f64 * dt));
                }
                catch_up_run = None;
            }
            _ => {}
        }
        held |= matches!(r.state, rig_state::HOLD | rig_state::UNLOAD);
        if step == PauseStep::HoldBegins {
            // The segment before the hold is complete: flush the high-pass.
            for out in high_pass.finish() {
                on_hp(out, &mut hp_steps, &mut residual, &mut stalls);
            }
            hp_steps.clear();
            high_pass = CentredHighPass::new(rate);
        }
        if !held && !pause.paused() && !awaiting {
            residual.push_displacement(r.x_m, x_ref_now);
            stalls.push_law_age(r.step_idx, r.law_age_periods);
            hp_steps.push_back(r.step_idx);
            if let Some(out) = high_pass.push(r.x_m - x_ref_now) {
                on_hp(out, &mut hp_steps, &mut residual, &mut stalls);
            }
            plots.error.push(r.t_s, r.x_m - x_ref_now);
            plots.x_ref.push(r.t_s, x_ref_now);
        }
        plots.x_hil.push(r.t_s, r.x_m);
        plots.external.push(r.t_s, r.external_force_n);
        plots.actuator.push(r.t_s, r.actuator_force_n);
        if let Some(tf) = first_fault {
            if r.t_s >= tf - 0.25 && plots.fault_window.len() < 200_000 {
                plots
                    .fault_window
                    .push((r.t_s, r.x_m, x_ref_now, r.actuator_force_n, r.state));
            }
        }
    };
    if side.rig_records > 0 {
        // The rig's records, and the emulator's for the rendering after the safe start.
        set.for_each_of_two::<RigRecord, EmulatorRecord>(
            |_, r| on_rig_record(&r),
            |_, e| {
                instability.push(e.t_s, e.generated_energy_j, e.oscillation_m);
                if let Some(s) = settled.as_deref_mut() {
                    s.emulator(&e);
                }
            },
        )?;
    } else {
        set.for_each::<EmulatorRecord>(|_, e| {
            instability.push(e.t_s, e.generated_energy_j, e.oscillation_m);
            if let Some(s) = settled.as_deref_mut() {
                s.emulator(&e);
            }
            // The rig's view only where it sent a sample (not the interpolated steps).
            if e.interpolated == 0 {
                on_rig_record(&rig_record_from_sample(&e));
            }
        })?;
        // After the emulator's own fault: the rig's samples (its hold), model not stepped.
        set.for_each::<AfterFaultSampleRecord>(|_, a| on_rig_record(&rig_record_after_fault(&a)))?;
    }
    for out in high_pass.finish() {
        on_hp(out, &mut hp_steps, &mut residual, &mut stalls);
    }
    let gaps = rig_gaps.borrow();
    let sources: [(&str, &[Gap]); 3] = [
        ("emulator", &side.emulator_gaps),
        ("controller", &side.controller_gaps),
        ("bench_rig", &gaps),
    ];
    let stalls = stalls.finish(&sources);
    let mut safety = safety.finish();
    let loop_energy = instability.loop_energy();
    instability.attach(&mut safety);
    Ok(RigPass {
        loop_energy,
        rig_steps,
        programme_at_end,
        residual,
        stalls,
        safety,
        plots,
        compared_from_s,
    })
}

/// The frequency bands of the fidelity report.
fn bands(cfg: &HilConfig) -> Vec<(String, f64, f64)> {
    let harmonic = cfg.scenario.harmonic_frequency_hz;
    let mut bands: Vec<(String, f64, f64)> = vec![
        ("quasi-static 0-1 Hz".into(), 0.0, 1.0),
        ("low 1-20 Hz".into(), 1.0, 20.0),
        ("mid 20-100 Hz".into(), 20.0, 100.0),
        ("resonance 100-300 Hz".into(), 100.0, 300.0),
    ];
    if harmonic > 0.0 {
        bands.insert(
            0,
            (
                format!("harmonic {harmonic} Hz"),
                harmonic * 0.9,
                harmonic * 1.1,
            ),
        );
    }
    bands
}

/// Analyses the records in `dir` (its `records.mcap`, or the parts a crashed run left)
/// and draws the plots there.
pub fn analyse_run(cfg: &HilConfig, dir: &Path) -> anyhow::Result<Analysis> {
    let set = RecordSet::open(dir)?;
    let side = read_side_streams(&set, cfg)?;
    let mut side = side;
    let mut compensation_report = std::mem::replace(
        &mut side.compensation,
        compensation::CompensationAnalyser::new(cfg.loop_.dt_s(), 0.0),
    )
    .finish(cfg);
    compensation::draw(dir, &compensation_report)?;
    let mut settled = compensation::SettledRendering::after(&compensation_report);
    let element_thermal = match side
        .element
        .take()
        .and_then(element::ElementTracker::finish)
    {
        Some((summary, rise)) => {
            draw_element_plot(dir, &summary, rise)?;
            Some(summary)
        }
        None => None,
    };
    let rig = read_rig_stream(&set, cfg, &side, settled.as_mut())?;
    if let Some(s) = settled {
        s.finish(cfg.loop_.dt_s(), &mut compensation_report);
    }
    anyhow::ensure!(
        rig.rig_steps > 16,
        "the rig's record has only {} rows",
        rig.rig_steps
    );
    let k_tangent = cfg
        .model
        .element
        .high_frequency_stiffness_n_per_m(cfg.scenario.preload_n);
    let omega0 = (k_tangent / cfg.rig.specimen_mass_kg).sqrt();
    let stability = rig.residual.stability(omega0);
    let latency_ns = Latency {
        end_to_end: percentiles(&side.end_to_end),
        wake_jitter: percentiles(&side.wake_jitter),
    };
    draw_plots(dir, &side, &rig)?;
    let (cycle, block, programme_time_s) = rig.programme_at_end;
    let end_s = cfg.programme.end_s;
    // The rig's last record is the period before the end: within one period of it.
    let completed = programme_time_s + 1.5 * cfg.loop_.dt_s() >= end_s;
    let sequence_s = cfg.programme.sequence_s();
    // Passes finished by the end of the last recorded period.
    let finished_passes = if sequence_s > 0.0 {
        ((programme_time_s + 1.5 * cfg.loop_.dt_s()) / sequence_s).floor() as u64
    } else {
        cycle
    };
    let programme = ProgrammeSummary {
        cycles_completed: finished_passes.max(cycle),
        last_block: block,
        last_block_name: cfg
            .programme
            .blocks
            .get(block as usize)
            .map_or(String::new(), |b| b.name.clone()),
        programme_time_s,
        end_s,
        completed,
    };
    let actuator_truth = actuator::ActuatorTruth::from_records(
        side.actuator_truth.as_ref(),
        &side.actuator_params,
        cfg.loop_.dt_s(),
    );
    let mut safety = if side.rig_records > 0 {
        rig.safety
    } else {
        external_rig_named(rig.safety)
    };
    attach_leads_after_trip(
        cfg,
        &mut safety,
        actuator_truth.as_ref(),
        side.rig_records == 0,
        &compensation_report,
    );
    Ok(Analysis {
        programme,
        steps: side.emulator_steps,
        rig_steps: rig.rig_steps,
        fidelity: Fidelity {
            compared_from_s: rig.compared_from_s,
            ..rig.residual.fidelity(&bands(cfg))
        },
        largest_transient_m: stability.resonant_residual_max_m,
        stability,
        latency_ns,
        safety,
        stalls: rig.stalls,
        loop_energy: rig.loop_energy,
        compensation: compensation_report,
        records: RecordsInfo {
            files: set.files.iter().map(|p| p.display().to_string()).collect(),
            truncated: side.truncated.clone(),
        },
        events: side
            .events
            .iter()
            .map(|e| {
                let line = e.describe();
                if side.rig_records == 0 {
                    crate::records::event::external_rig_labelled(&line)
                } else {
                    line
                }
            })
            .collect(),
        rig_view: if side.rig_records > 0 {
            RIG_VIEW_OWN
        } else {
            RIG_VIEW_EXTERNAL
        }
        .to_string(),
        actuator_truth,
        element_thermal,
    })
}

/// For the emulator's `loop-unstable` or `displacement-out-of-range` trip in law mode, not
/// in a hold already nor in a run with injected faults (a loop that
/// diverges slowly leaves the range before the monitor's band sees it), whether any lead
/// would have held the
/// linearised loop (`check::after_trip`): in front of the rig's recorded actuator when it
/// recorded one, else of the declared actuator when the configuration declares the
/// external rig (`plan_for_external_rig`), else of delay-and-lag actuators of the
/// identified delay (none when nothing was identified).
fn attach_leads_after_trip(
    cfg: &HilConfig,
    safety: &mut safety::Safety,
    truth: Option<&actuator::ActuatorTruth>,
    external_rig: bool,
    compensation: &compensation::CompensationReport,
) {
    use crate::hil::check::after_trip;
    if cfg.controller.command_mode != crate::hil::config::CommandMode::Law {
        return;
    }
    // A run whose faults were injected tests the safety chain, not the loop.
    if !safety.injected.is_empty() {
        return;
    }
    let lead_s = compensation.final_lead_us * 1e-6;
    let mut judged = None;
    for f in safety.faults.iter_mut().filter(|f| {
        f.process == "emulator"
            && f.already_held_since_s.is_none()
            && (f.fault == "loop-unstable" || f.fault == "displacement-out-of-range")
    }) {
        if judged.is_none() {
            judged = match (
                truth.and_then(|t| t.plant().map(|p| (t, p))),
                compensation.identified_delay_us,
            ) {
                (Some((t, plant)), _) => Some(after_trip::leads_after_trip_truth(
                    cfg,
                    &plant,
                    t.effective_delay_s,
                    lead_s,
                    compensation.final_gain,
                    compensation.lead_adapted,
                )),
                (None, _) if external_rig && cfg.compensation.plan_for_external_rig => {
                    Some(after_trip::leads_after_trip_declared(
                        cfg,
                        lead_s,
                        compensation.final_gain,
                        compensation.lead_adapted,
                    ))
                }
                (None, Some(d)) if d.is_finite() && d > 0.0 => {
                    Some(after_trip::leads_after_trip_identified(
                        cfg,
                        d * 1e-6,
                        lead_s,
                        compensation.lead_adapted,
                    ))
                }
                _ => None,
            };
        }
        f.leads_after_trip = judged.clone();
    }
}

/// `element.png`: the element's temperature rise and the modulus it leaves.
fn draw_element_plot(
    dir: &Path,
    e: &element::ElementThermal,
    (t, rise): element::PlotSeries,
) -> anyhow::Result<()> {
    let modulus: Vec<f64> = rise
        .iter()
        .map(|r| ((-e.ln_modulus_shift_per_c * (r - e.rise_start_k)).exp() - 1.0) * 100.0)
        .collect();
    draw_png(
        &dir.join("element.png"),
        1400,
        800,
        1,
        &[
            Panel::new(
                format!(
                    "Element self-heating (C {} J/K, h {} W/K, time constant {:.0} s; {:.2} W on average)",
                    e.heat_capacity_j_per_k, e.heat_transfer_w_per_k, e.time_constant_s, e.mean_power_w
                ),
                "t (s)",
                "rise above ambient (K)",
            )
            .with(Series::line("temperature rise", t.clone(), rise, 0)),
            Panel::new("Modulus from the temperature law", "t (s)", "change since the start (%)")
                .with(Series::line("modulus", t, modulus, 1)),
        ],
    )
}

fn draw_plots(dir: &Path, side: &SideStreams, rig: &RigPass) -> anyhow::Result<()> {
    let p = &rig.plots;
    let series = |d: &Decimator, scale: f64| d.points(scale);
    let (t_h, x_h) = series(&p.x_hil, 1e3);
    let (t_r, x_r) = series(&p.x_ref, 1e3);
    let (t_e, f_e) = series(&p.external, 1e-3);
    let (t_a, f_a) = series(&p.actuator, 1e-3);
    let (t_m, f_m) = series(&side.emulator_force, 1e-3);
    draw_png(
        &dir.join("histories.png"),
        1400,
        900,
        1,
        &[
            Panel::new(
                "Specimen displacement (min/max per pixel)",
                "t (s)",
                "displacement (mm)",
            )
            .with(Series::line("HIL (rig, true)", t_h, x_h, 0))
            .with(Series::dashed(
                "offline reference (not during holds)",
                t_r,
                x_r,
                1,
            )),
            Panel::new("Forces", "t (s)", "force (kN)")
                .with(Series::line("external load", t_e, f_e, 2))
                .with(Series::line("emulated element force", t_m, f_m, 0))
                .with(Series::dashed("actuator force", t_a, f_a, 1)),
        ],
    )?;
    let (t_err, err) = series(&p.error, 1e6);
    draw_png(
        &dir.join("hil-vs-reference.png"),
        1400,
        600,
        1,
        &[Panel::new(
            "HIL - reference displacement (not during holds)",
            "t (s)",
            "error (um)",
        )
        .with(Series::line("x_hil - x_ref", t_err, err, 3))],
    )?;
    let (xe, ye) = log_bins(&side.end_to_end);
    let (xj, yj) = log_bins(&side.wake_jitter);
    draw_png(
        &dir.join("latency-histogram.png"),
        1200,
        600,
        2,
        &[
            Panel::new(
                "End-to-end latency (sample -> command)",
                "latency (us)",
                "count (+0.5)",
            )
            .log_x()
            .log_y()
            .with(Series::line("end to end", xe, ye, 0)),
            Panel::new("Emulator wake-up jitter", "late (us)", "count (+0.5)")
                .log_x()
                .log_y()
                .with(Series::line("wake late", xj, yj, 1)),
        ],
    )?;
    if !p.fault_window.is_empty() {
        draw_safety_plot(dir, rig)?;
    }
    Ok(())
}

/// `safety.png`: the specimen around the first fault, the hold marked.
fn draw_safety_plot(dir: &Path, rig: &RigPass) -> anyhow::Result<()> {
    let w = &rig.plots.fault_window;
    let t0 = w[0].0;
    let mut x = Decimator::new(t0, 1e-4, PLOT_BUCKETS);
    let mut xr = Decimator::new(t0, 1e-4, PLOT_BUCKETS);
    let mut fa = Decimator::new(t0, 1e-4, PLOT_BUCKETS);
    let mut hold = Decimator::new(t0, 1e-4, PLOT_BUCKETS);
    for &(t, xi, xri, fai, state) in w {
        x.push(t, xi);
        if matches!(state, rig_state::RUNNING) {
            xr.push(t, xri);
        }
        fa.push(t, fai);
        hold.push(t, if safety::is_holding(state) { 1.0 } else { 0.0 });
    }
    let mut title = String::from("Specimen around the first fault");
    if let Some(f) = rig.safety.faults.first() {
        title = format!(
            "{}: {} at {:.3} s -> {}",
            f.process,
            f.fault,
            f.detected_at_s,
            f.action.as_deref().unwrap_or("(controller acts)")
        );
    }
    let (tx, yx) = x.points(1e3);
    let (tr, yr) = xr.points(1e3);
    let (tf, yf) = fa.points(1e-3);
    let (th, yh) = hold.points(1.0);
    draw_png(
        &dir.join("safety.png"),
        1400,
        1000,
        1,
        &[
            Panel::new(title, "t (s)", "displacement (mm)")
                .with(Series::line("specimen (true)", tx, yx, 0))
                .with(Series::dashed("offline reference", tr, yr, 1)),
            Panel::new("Actuator force", "t (s)", "force (kN)")
                .with(Series::line("actuator", tf, yf, 3)),
            Panel::new("Interlock", "t (s)", "hold (1) / force control (0)")
                .y_range(-0.1, 1.1)
                .with(Series::line("hold", th, yh, 2)),
        ],
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    /// A lead given in us reads back in us without the float noise of `s * 1e6`, and a
    /// range with a negative end is not written as "-1510-5158".
    #[test]
    fn leads_read_back_in_us_and_negative_ranges_read_as_ranges() {
        let lead_s = 2850.0 * 1e-6;
        assert_ne!(lead_s * 1e6, 2850.0);
        assert_eq!(super::json_us(lead_s), 2850.0);
        assert_eq!(super::json_us(265.6574812735871e-6), 265.657);
        assert!(super::json_us(f64::NAN).is_nan());
        assert_eq!(super::span(-1510.2, 5158.4), "-1510 to 5158");
        assert_eq!(super::span(169.0, 297.4), "169-297");
        assert_eq!(super::span(-0.4, 12.0), "0-12");
    }
}
