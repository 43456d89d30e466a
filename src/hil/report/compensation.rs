//! The report's `compensation` object and the faithful band, from the records in
//! streaming passes: the controller's records give the lead, gain and guard it sent (the
//! estimate's trajectory, decimated), the emulator's records the element's force and the
//! force the rig measured at every sample, whose cross-spectrum (Welch, 1 Hz bins) gives
//! the rendered force per element force by frequency.
//!
//! Must not: hold a run's records in memory (bounded sums and decimated series only).

use realfft::num_complex::Complex64;
use realfft::RealFftPlanner;
use serde::Serialize;

use crate::hil::controller::ControllerRecord;
use crate::hil::emulator::EmulatorRecord;
use crate::ipc::messages::{command_mode, rig_state};

/// Welch segment length, samples (1 s at 4096 Hz: 1 Hz bins).
const SEGMENT: usize = 4096;
/// Highest frequency the faithful band is looked for up to, Hz.
const BAND_TOP_HZ: f64 = 200.0;
// Bins whose coherence is below this carry too little of the load to judge (the rules are
// shared with the controller's `LoadBandDelay`).
use crate::hil::compensation::welch_rules::MIN_COHERENCE;
/// Fewest Welch segments (1 s, half overlapping: 3 s of force control) to judge a band.
/// With one segment every bin's coherence is 1 whatever the two forces hold, with two or
/// three overlapping ones nearly so (2026-11-27: a 2 s run killed at 1.5 s reported
/// "faithful band 3 Hz ... limited at 4 Hz: amplitude -99.52 %" from 1.55 s of force
/// control, two segments).
const MIN_SEGMENTS: u64 = crate::hil::compensation::welch_rules::MIN_SEGMENTS as u64;
// Bins where the element's force spectrum lies more than 80 dB below its strongest bin
// in the band are not judged either: what is there is the loop's noise, not load, and
// the two forces' noise can be coherent without being a rendering (an external rig's run
// with the emulator's samples often stale: the element's force 90 dB down at 8-60 Hz,
// the measured force 130 dB down, coherence 0.99, so "amplitude -99.6 %" was reported at
// 8 Hz of a run whose load was 1-3 Hz). The default run's passages reach 200 Hz at
// 70-80 dB down.
use crate::hil::compensation::welch_rules::MIN_RELATIVE_EXCITATION;
/// Faithful: amplitude within 1 %, phase within 2 degrees.
const AMPLITUDE_TOL: f64 = 0.01;
const PHASE_TOL_DEG: f64 = 2.0;
/// The top of the load band a run must render faithfully (SPEC 6.1: 1-20 Hz), Hz; a
/// faithful band below it is warned about on the console.
pub const LOAD_BAND_TOP_HZ: f64 = 20.0;

/// The guard's activity over the run.
#[derive(Debug, Clone, Serialize, Default)]
pub struct GuardReport {
    pub enabled: bool,
    /// Time with damping added, s, and its share of the time in force control.
    pub active_s: f64,
    pub active_fraction: f64,
    /// The safe start: time from the first law command until the guard was disarmed (the
    /// lead agreed with the delay the estimator resolved), s; all of force control when it
    /// never was (null: the guard never armed).
    pub safe_start_s: Option<f64>,
    /// Whether the safe start ended (the last law command had the guard disarmed); null
    /// when it never armed. False: the delay was never learned and the guard damped
    /// above its corner all run.
    pub safe_start_ended: Option<bool>,
    /// When it ended: the first law command with the guard disarmed, s (null: it never
    /// armed, or never ended).
    pub safe_start_ended_at_s: Option<f64>,
    /// Energy the added damping dissipated (its force on the high-passed velocity), J.
    pub dissipated_j: f64,
    /// Largest damping added, N s/m.
    pub max_damping_ns_per_m: f64,
    /// Largest energy the guard's observer saw generated in its band, J.
    pub max_generated_j: f64,
    /// Bursts of energy after a stall of the setpoints (a gap the controller does not
    /// bridge) that the guard excused rather than damped (at most one per 0.25 s), and the
    /// largest excused, J (at most `guard_full_energy_j`): the fresh law's step rings the
    /// specimen once; a loop that keeps generating is answered after the burst's 16 ms.
    pub stall_bursts_excused: u32,
    pub max_stall_burst_j: f64,
    /// The displacement sensor's noise as the controller read it at the run's end, m (null:
    /// never read), and the largest factor it put on the guard's energy thresholds (1:
    /// none; a sensor noisier than 0.25 um raises them with its variance, so that the
    /// guard does not answer the noise's own work: docs/compensation.md).
    pub sensor_noise_m: Option<f64>,
    pub max_threshold_scale: f64,
    /// The band the guard observes and acts in, Hz.
    pub band_hz: (f64, f64),
}

/// One point of the estimate's trajectory.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct EstimatePoint {
    pub t_s: f64,
    pub lead_us: f64,
    /// The lead's estimator (`compensation::DelayEstimator`) and its standard error (NaN:
    /// not yet).
    pub lead_estimate_us: f64,
    pub lead_estimate_sigma_us: f64,
    /// The delay over the load band (`compensation::LoadBandDelay`) and its standard
    /// error (NaN: not identified).
    pub load_band_delay_us: f64,
    pub load_band_delay_sigma_us: f64,
    pub gain: f64,
    pub guard_damping_ns_per_m: f64,
}

/// The rendered force per element force at one frequency.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct RenderingPoint {
    pub frequency_hz: f64,
    pub amplitude_ratio: f64,
    pub phase_deg: f64,
    pub coherence: f64,
}

/// The actuator's effective delay from the record: at each excited bin of 1-20 Hz, the
/// lead in effect (its mean over force control) less the rendered force's phase against
/// the element's over the frequency (the phase unwrapped from the lowest bin), and their
/// mean: the same mean phase delay over 1-20 Hz as `actuator_truth.effective_delay_s`,
/// where the online estimator weighs the band by the load's content (mostly below 5 Hz:
/// a servo-hydraulic force loop, 0.7 ms at 1 Hz and 3.3 ms at 20 Hz, reads about 1 ms).
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct RecordDelay {
    pub mean_us: f64,
    /// The smallest and largest bin's delay: how far the delay varies over the band.
    pub min_us: f64,
    pub max_us: f64,
    /// Excited bins it rests on, and the band they span, Hz.
    pub bins: usize,
    pub from_hz: f64,
    pub to_hz: f64,
    /// The lead it was read against (the mean over force control), us.
    pub lead_us: f64,
}

// Fewer excited bins in the load band than this leave the record's delay unread.
use crate::hil::compensation::welch_rules::MIN_BINS as MIN_DELAY_BINS;

/// `RecordDelay` from the rendering and the lead in effect.
pub fn record_delay(rendering: &[RenderingPoint], lead_s: f64) -> Option<RecordDelay> {
    let mut previous = 0.0;
    let mut delays = Vec::new();
    for p in rendering
        .iter()
        .filter(|p| (1.0..=LOAD_BAND_TOP_HZ).contains(&p.frequency_hz))
    {
        let mut phase = p.phase_deg.to_radians();
        while phase - previous > std::f64::consts::PI {
            phase -= 2.0 * std::f64::consts::PI;
        }
        while phase - previous < -std::f64::consts::PI {
            phase += 2.0 * std::f64::consts::PI;
        }
        previous = phase;
        let omega = 2.0 * std::f64::consts::PI * p.frequency_hz;
        delays.push((p.frequency_hz, lead_s - phase / omega));
    }
    if delays.len() < MIN_DELAY_BINS || !lead_s.is_finite() {
        return None;
    }
    let n = delays.len() as f64;
    Some(RecordDelay {
        mean_us: delays.iter().map(|d| d.1).sum::<f64>() / n * 1e6,
        min_us: delays.iter().map(|d| d.1).fold(f64::INFINITY, f64::min) * 1e6,
        max_us: delays.iter().map(|d| d.1).fold(f64::NEG_INFINITY, f64::max) * 1e6,
        bins: delays.len(),
        from_hz: delays[0].0,
        to_hz: delays[delays.len() - 1].0,
        lead_us: super::json_us(lead_s),
    })
}

/// The report's `compensation` object.
#[derive(Debug, Clone, Serialize, Default)]
pub struct CompensationReport {
    pub adapt: bool,
    /// Whether the lead adapted (`adapt` on and the plan did not fix the lead).
    pub lead_adapted: bool,
    pub initial_delay_us: f64,
    /// The lead of the first law command, us: the guess, or less when it was capped
    /// (`check::starting_lead_cap_s`; null: no law command).
    pub starting_lead_us: Option<f64>,
    /// The actuator's effective delay the controller identified online by the end of force
    /// control, and its standard error, us (null: never identified): the mean phase delay
    /// over the excited bins of 1-20 Hz (`compensation::LoadBandDelay`, the truth's
    /// definition) when the load excited enough of them, else the lead's estimator's.
    pub identified_delay_us: Option<f64>,
    pub identified_delay_sigma_us: Option<f64>,
    /// Which: `"load-band"` or `"lead-estimator"` (null: never identified).
    pub identified_from: Option<&'static str>,
    /// For `"load-band"`: the excited, coherent bins the mean rests on, and the lowest and
    /// highest, Hz (the mean is over those bins, not the whole of 1-20 Hz).
    pub identified_bins: Option<u32>,
    pub identified_from_hz: Option<f64>,
    pub identified_to_hz: Option<f64>,
    /// The lead's estimator's delay at the end of force control (the regression the lead
    /// follows, weighing the band by the load's content), and its standard error, us.
    pub lead_estimate_us: Option<f64>,
    pub lead_estimate_sigma_us: Option<f64>,
    /// The lead and gain sent last in force control.
    pub final_lead_us: f64,
    pub final_gain: f64,
    /// When the lead first came and stayed within 5 % (or 10 us) of its final value, s (a
    /// lead the plan fixed: when it last moved, its nudge's last step).
    pub settled_at_s: Option<f64>,
    /// With the lead fixed by the plan: how many times the nudge stepped it because the
    /// loop kept oscillating (`compensation::LeadNudge`); null when the lead was not fixed
    /// with a nudge.
    pub lead_nudges: Option<u32>,
    pub guard: GuardReport,
    /// The highest frequency up to which the rendered force stays within 1 % in amplitude
    /// and 2 degrees in phase of the element's (every bin from 1 Hz up that the load
    /// excited); null when no bin was excited enough to judge.
    pub faithful_band_hz: Option<f64>,
    /// The first excited bin beyond it and why it is not faithful.
    pub faithful_band_limited_by: Option<String>,
    /// The same judged only on the force-control time after the safe start (the lead
    /// learned, the start's damping gone): what the loop renders once it has learned the
    /// actuator; null when the guard never armed, or no whole 1 s segment came after it.
    pub faithful_band_after_safe_start_hz: Option<f64>,
    pub faithful_band_after_safe_start_limited_by: Option<String>,
    /// Rendering by frequency (excited bins up to 200 Hz).
    pub rendering: Vec<RenderingPoint>,
    /// The actuator's delay as the record shows it over the load band (null: fewer than
    /// `MIN_DELAY_BINS` excited bins there).
    pub record_delay: Option<RecordDelay>,
    /// The estimate's trajectory (decimated to at most 400 points).
    pub trajectory: Vec<EstimatePoint>,
    /// Whether the law was left for a hold (a fault's, or an operator's hold never resumed)
    /// rather than rendered to the run's end: the law's time was then cut short.
    pub law_ended_in_hold: bool,
}

/// The lead's moves in `points` (its changes, in time order): a change more than
/// `STEP_GAP_S` after the previous one begins a move. A nudge takes the lead to its target
/// within 5 ms (5 % of at most 10 ms at 0.1 s per s) and the next comes at least its
/// refractory time (0.25 s) later, so only a record gap of over 0.1 s inside a move's
/// 5 ms could count it twice.
fn lead_steps(points: &[(f64, f64)]) -> u32 {
    const STEP_GAP_S: f64 = 0.1;
    points
        .windows(2)
        .filter(|w| w[1].0 - w[0].0 > STEP_GAP_S)
        .count() as u32
}

impl CompensationReport {
    /// Why an identified delay below zero (by more than two standard errors) is not a
    /// delay: the actuator's force leads its command, as a servo-hydraulic force loop's
    /// uncompensated velocity feedback through the oil's flow makes it; no lead (which
    /// cannot be negative) makes up for it, and read at the lead in effect the force per
    /// The guard's thresholds raised for a noisy sensor, for the console ("" when not).
    fn noise_note(&self) -> String {
        match self.guard.sensor_noise_m {
            Some(s) if self.guard.max_threshold_scale > 1.0 => format!(
                ", thresholds up to {:.1} times for {:.2} um of sensor noise",
                self.guard.max_threshold_scale,
                s * 1e6
            ),
            _ => String::new(),
        }
    }

    /// command is not the delay a lead would have to make up for (docs/compensation.md).
    fn negative_delay_note(&self) -> &'static str {
        match (self.identified_delay_us, self.identified_delay_sigma_us) {
            (Some(d), sigma) if d < -2.0 * sigma.unwrap_or(0.0) && d < 0.0 => {
                " (negative: the actuator's force leads its command, as a force loop's velocity feedback through the oil does when its servo controller does not compensate it; a lead cannot make up for that, and the delay read is only roughly the actuator's)"
            }
            _ => "",
        }
    }

    /// One line for the console: the lead from start to end, what was identified, the
    /// guard and the faithful band; a warning when the safe start never ended.
    pub fn describe(&self) -> String {
        let us = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.0} us"));
        // A lead within its settling band from the first command on settled from the start.
        let from_start = |t: f64| self.trajectory.first().is_some_and(|p| t <= p.t_s);
        let settled = self.settled_at_s.map_or("never".to_string(), |t| {
            if from_start(t) {
                "from the start".to_string()
            } else {
                format!("at {t:.2} s")
            }
        }) + &match self.lead_nudges {
            Some(n) if n > 0 => format!(
                " (the lead the plan fixed, stepped {n} time{} because the loop kept oscillating)",
                if n == 1 { "" } else { "s" }
            ),
            _ => String::new(),
        };
        let mut line = format!(
            "compensation: lead {} -> {:.0} us, identified {}{}{}{}, gain {:.3}, settled {}; guard: safe start {}, active {:.2} s, largest {:.1} kN s/m{}; faithful band {}",
            us(self.starting_lead_us),
            self.final_lead_us,
            us(self.identified_delay_us),
            self.identified_delay_sigma_us
                .map_or(String::new(), |s| format!(" (+- {s:.1})")),
            match (self.identified_from, self.lead_estimate_us) {
                (Some("load-band"), lead) => format!(
                    " over {:.0}-{:.0} Hz ({} bins){}",
                    self.identified_from_hz.unwrap_or(f64::NAN),
                    self.identified_to_hz.unwrap_or(f64::NAN),
                    self.identified_bins.unwrap_or(0),
                    lead.map_or(String::new(), |e| format!(" (the lead's estimator: {e:.0} us)"))
                ),
                (Some(_), _) => " (the lead's estimator, weighing the load band by the load's content: too few bins of 1-20 Hz were excited coherently, or too short a run, to identify the delay over the band)".to_string(),
                _ => String::new(),
            },
            self.negative_delay_note(),
            self.final_gain,
            settled,
            self.guard.safe_start_s.map_or("none".to_string(), |t| {
                if self.guard.max_damping_ns_per_m > 0.0 {
                    format!("{t:.2} s")
                } else {
                    // A start the plan moved to a lead stable by itself: the safe start
                    // only follows the ringing.
                    format!("{t:.2} s without damping")
                }
            }),
            self.guard.active_s,
            self.guard.max_damping_ns_per_m * 1e-3,
            match self.guard.stall_bursts_excused {
                0 => String::new(),
                n => format!(
                    ", {n} stall burst{} excused (largest {:.1} mJ)",
                    if n == 1 { "" } else { "s" },
                    self.guard.max_stall_burst_j * 1e3
                ),
            } + &self.noise_note(),
            band_text(self.faithful_band_hz, &self.faithful_band_limited_by),
        );
        if self.faithful_band_after_safe_start_hz.is_some()
            || self.faithful_band_after_safe_start_limited_by.is_some()
        {
            line.push_str(&format!(
                " ({} after the safe start)",
                band_text(
                    self.faithful_band_after_safe_start_hz,
                    &self.faithful_band_after_safe_start_limited_by
                )
            ));
        }
        let limited = self
            .faithful_band_limited_by
            .as_ref()
            .map_or(String::new(), |l| format!(", limited at {l}"));
        let warning = "; WARNING: the rendered force is not faithful over the load band";
        let band = format!("1-{LOAD_BAND_TOP_HZ:.0} Hz within 1 % and 2 degrees");
        match (self.faithful_band_hz, &self.faithful_band_limited_by) {
            // The first failing excited bin lies above the load band: every excited bin of
            // the load band was faithful, the bins between were not excited (a short run,
            // a slow load).
            (Some(b), Some(l))
                if b < LOAD_BAND_TOP_HZ
                    && limited_at_hz(l).is_some_and(|f| f > LOAD_BAND_TOP_HZ) =>
            {
                line.push_str(&format!(
                    " (the load excited nothing between {b:.0} and {:.0} Hz{limited})",
                    limited_at_hz(l).unwrap_or(f64::NAN)
                ))
            }
            (Some(b), Some(_)) if b < LOAD_BAND_TOP_HZ => line.push_str(&format!(
                "{warning} ({band}) but only up to {b:.0} Hz{limited}"
            )),
            // Nothing above the band was excited enough to judge: not a failure.
            (Some(b), None) if b < LOAD_BAND_TOP_HZ => {
                line.push_str(" (the highest frequency the load excites; above it not judged)")
            }
            (None, Some(_)) => line.push_str(&format!(
                "{warning} ({band}), not even at its lowest excited bin{limited}"
            )),
            _ => {}
        }
        if let Some(d) = &self.record_delay {
            line.push_str(&format!(
                "; the record's delay over {:.0}-{:.0} Hz {:.0} us ({} us over {} bins)",
                d.from_hz,
                d.to_hz,
                d.mean_us,
                super::span(d.min_us, d.max_us),
                d.bins
            ));
        }
        if let Some(d) = self
            .identified_delay_us
            .filter(|d| *d < 0.0 && self.identified_delay_sigma_us.is_none_or(|s| -d > 2.0 * s))
        {
            line.push_str(&format!(
                "; the identified delay ({d:.0} us) is negative: the rendered force leads the element's in the load band, which no delay does; the actuator adds a force of its own on the specimen's motion (a damper: a servo-hydraulic force loop without velocity compensation, for one), which a lead, kept at 0 here, cannot take out"
            ));
        }
        if self.guard.safe_start_ended == Some(false) && self.law_ended_in_hold {
            line.push_str(&format!(
                "; the safe start had not ended when the law gave way to a hold, after {:.2} s",
                self.guard.safe_start_s.unwrap_or(0.0)
            ));
        } else if self.guard.safe_start_ended == Some(false) {
            line.push_str(&format!(
                "; WARNING: the safe start never ended (the delay was never learned to within 10 %, or the gain lay outside 0.5-2){}",
                // A start the plan moved carries no damping (`check::planned`).
                if self.guard.max_damping_ns_per_m > 0.0 {
                    format!(
                        ": the guard damped above {:.0} Hz for as long as the law was rendered",
                        self.guard.band_hz.0
                    )
                } else {
                    String::new()
                }
            ));
        }
        line
    }
}

/// The frequency of a `faithful_band_limited_by` ("114 Hz: amplitude ..., phase ...", as
/// `faithful_band` writes it).
fn limited_at_hz(limited_by: &str) -> Option<f64> {
    limited_by.split(" Hz").next()?.trim().parse().ok()
}

/// A faithful band for the console: its top, "none" when the first excited bin already
/// fails, "not judged" when no bin was excited enough.
fn band_text(band_hz: Option<f64>, limited_by: &Option<String>) -> String {
    match (band_hz, limited_by) {
        (Some(f), _) => format!("{f:.0} Hz"),
        (None, Some(_)) => "none".to_string(),
        (None, None) => "not judged".to_string(),
    }
}

/// Streaming analyser of the controller's and emulator's records.
pub struct CompensationAnalyser {
    dt_s: f64,
    // Controller side.
    last: Option<ControllerRecord>,
    /// The last law command (not a repeat): the lead and gain the run ended with.
    last_law: Option<ControllerRecord>,
    force_control_s: f64,
    /// The lead integrated over force control, s^2 (its mean: the lead the rendering had).
    lead_time_s2: f64,
    active_s: f64,
    /// Time in force control with the guard armed, s, and whether it ever was.
    armed_s: f64,
    armed_seen: bool,
    /// The last law command's `guard_armed`.
    armed_last: bool,
    max_damping: f64,
    max_generated: f64,
    /// Stall bursts excused (the records' running count) and the largest, J.
    stall_bursts: u32,
    max_stall_burst: f64,
    /// The last finite noise reading, m, and the largest onset read, J.
    sensor_noise: Option<f64>,
    max_onset: f64,
    identified: Option<(f64, f64)>,
    /// The last law command's delay over the load band, sigma, bins, from and to (None
    /// when it had none: not yet, or no longer, identified).
    load_band: Option<(f64, f64, u32, f64, f64)>,
    trajectory: Vec<EstimatePoint>,
    stride_s: f64,
    next_point_s: f64,
    /// (t, lead) at each change of the lead (for when it settled).
    lead_points: Vec<(f64, f64)>,
    // Emulator side: the rendering over the whole run (after the safe start: `SettledRendering`).
    whole: Welch,
    /// The first law command with the guard disarmed after it was armed, s.
    disarmed_at_s: Option<f64>,
    dissipated_j: f64,
    last_guard: Option<(f64, f64)>,
}

impl CompensationAnalyser {
    /// `duration_s`: the run's expected length (for the trajectory's decimation).
    pub fn new(dt_s: f64, duration_s: f64) -> CompensationAnalyser {
        CompensationAnalyser {
            dt_s,
            last: None,
            last_law: None,
            force_control_s: 0.0,
            lead_time_s2: 0.0,
            active_s: 0.0,
            max_damping: 0.0,
            max_generated: 0.0,
            stall_bursts: 0,
            max_stall_burst: 0.0,
            sensor_noise: None,
            max_onset: 0.0,
            armed_s: 0.0,
            armed_seen: false,
            armed_last: false,
            identified: None,
            load_band: None,
            trajectory: Vec::new(),
            stride_s: (duration_s / 400.0).max(dt_s),
            next_point_s: 0.0,
            lead_points: Vec::new(),
            whole: Welch::new(),
            disarmed_at_s: None,
            dissipated_j: 0.0,
            last_guard: None,
        }
    }

    /// One controller record.
    pub fn controller(&mut self, r: &ControllerRecord) {
        if r.mode != command_mode::LAW || r.repeat != 0 {
            self.last = Some(*r);
            return;
        }
        if let Some(prev) = self.last {
            if prev.mode == command_mode::LAW {
                let dt = (r.t_s - prev.t_s).clamp(0.0, 0.05);
                self.force_control_s += dt;
                self.lead_time_s2 += prev.lead_s * dt;
                if prev.guard_damping_ns_per_m > 0.0 {
                    self.active_s += dt;
                }
                if prev.guard_armed != 0 {
                    self.armed_s += dt;
                }
            }
        }
        self.armed_seen |= r.guard_armed != 0;
        if self.armed_seen && r.guard_armed == 0 && self.disarmed_at_s.is_none() {
            self.disarmed_at_s = Some(r.t_s);
        }
        self.armed_last = r.guard_armed != 0;
        self.max_damping = self.max_damping.max(r.guard_damping_ns_per_m);
        if r.guard_generated_j.is_finite() {
            self.max_generated = self.max_generated.max(r.guard_generated_j);
        }
        self.stall_bursts = self.stall_bursts.max(r.guard_stall_bursts);
        self.max_stall_burst = self.max_stall_burst.max(r.guard_excused_j);
        if r.sensor_noise_m.is_finite() {
            self.sensor_noise = Some(r.sensor_noise_m);
        }
        if r.guard_onset_j.is_finite() {
            self.max_onset = self.max_onset.max(r.guard_onset_j);
        }
        if r.identified_delay_s.is_finite() {
            self.identified = Some((r.identified_delay_s, r.identified_delay_sigma_s));
        }
        self.load_band = r.load_band_delay_s.is_finite().then_some((
            r.load_band_delay_s,
            r.load_band_delay_sigma_s,
            r.load_band_bins,
            r.load_band_from_hz,
            r.load_band_to_hz,
        ));
        // The guard's dissipation: its damping on the velocity of the law's displacement.
        if let Some((t0, z0)) = self.last_guard {
            let dt = r.t_s - t0;
            if dt > 0.0 && dt < 0.01 && r.guard_damping_ns_per_m > 0.0 {
                let v = (r.law_displacement_m - z0) / dt;
                self.dissipated_j += r.guard_damping_ns_per_m * v * v * dt;
            }
        }
        self.last_guard = Some((r.t_s, r.law_displacement_m));
        self.lead_points_push(r.t_s, r.lead_s);
        self.last_law = Some(*r);
        if r.t_s >= self.next_point_s {
            self.next_point_s = r.t_s + self.stride_s;
            self.trajectory.push(EstimatePoint {
                t_s: r.t_s,
                lead_us: super::json_us(r.lead_s),
                lead_estimate_us: super::json_us(r.identified_delay_s),
                lead_estimate_sigma_us: super::json_us(r.identified_delay_sigma_s),
                load_band_delay_us: super::json_us(r.load_band_delay_s),
                load_band_delay_sigma_us: super::json_us(r.load_band_delay_sigma_s),
                gain: r.actuator_gain,
                guard_damping_ns_per_m: r.guard_damping_ns_per_m,
            });
        }
        self.last = Some(*r);
    }

    fn lead_points_push(&mut self, t: f64, lead: f64) {
        // Keep the lead's changes only (a bounded list: the lead moves slowly and little).
        match self.lead_points.last() {
            Some(&(_, l)) if (l - lead).abs() < 1e-6 => {}
            _ if self.lead_points.len() < 100_000 => self.lead_points.push((t, lead)),
            _ => {}
        }
    }

    /// One emulator record: a sample of the element's force and the rig's measured force.
    pub fn emulator(&mut self, r: &EmulatorRecord) {
        self.whole.sample(r, true);
    }

    pub fn finish(self, cfg: &crate::hil::config::HilConfig) -> CompensationReport {
        let c = &cfg.compensation;
        // The last law command's, also when the run ended in a hold (the hold's commands
        // carry no compensation).
        let (final_lead, final_gain) = self
            .last_law
            .map_or((c.initial_delay_s, 1.0), |r| (r.lead_s, r.actuator_gain));
        let settled_at_s = {
            // A lead the plan fixed moves only by its nudge's steps (5 %, within the 5 %
            // an adapted lead settles to): it settled when it last moved.
            let tol = if c.adapt_lead {
                (0.05 * final_lead).max(10e-6)
            } else {
                1e-6
            };
            let mut settled = self.lead_points.first().map(|p| p.0);
            for &(t, l) in &self.lead_points {
                if (l - final_lead).abs() > tol {
                    settled = None;
                } else if settled.is_none() {
                    settled = Some(t);
                }
            }
            settled
        };
        // Rendering by frequency and the faithful band.
        let (rendering, faithful, limited_by) = self.whole.faithful_band(self.dt_s);
        let mean_lead = if self.force_control_s > 0.0 {
            self.lead_time_s2 / self.force_control_s
        } else {
            final_lead
        };
        let record_delay = record_delay(&rendering, mean_lead);
        let (identified, identified_from) = match (self.load_band, self.identified) {
            (Some((d, s, ..)), _) => (Some((d, s)), Some("load-band")),
            (None, Some(d)) => (Some(d), Some("lead-estimator")),
            (None, None) => (None, None),
        };
        // Whole-hertz bins: the loop's period is whole nanoseconds, so they read 0.9999985.
        let span = self
            .load_band
            .map(|(_, _, n, from, to)| (n, from.round(), to.round()));
        CompensationReport {
            adapt: c.adapt,
            lead_adapted: c.adapt && c.adapt_lead,
            initial_delay_us: super::json_us(c.initial_delay_s),
            starting_lead_us: self.lead_points.first().map(|p| super::json_us(p.1)),
            lead_nudges: (!c.adapt_lead && c.nudge.is_some())
                .then(|| lead_steps(&self.lead_points)),
            identified_delay_us: identified.map(|(d, _)| super::json_us(d)),
            identified_delay_sigma_us: identified.map(|(_, s)| super::json_us(s)),
            identified_from,
            identified_bins: span.map(|s| s.0),
            identified_from_hz: span.map(|s| s.1),
            identified_to_hz: span.map(|s| s.2),
            lead_estimate_us: self.identified.map(|(d, _)| super::json_us(d)),
            lead_estimate_sigma_us: self.identified.map(|(_, s)| super::json_us(s)),
            final_lead_us: super::json_us(final_lead),
            final_gain,
            settled_at_s,
            guard: GuardReport {
                enabled: c.passivity_guard,
                active_s: self.active_s,
                active_fraction: if self.force_control_s > 0.0 {
                    self.active_s / self.force_control_s
                } else {
                    0.0
                },
                safe_start_s: self.armed_seen.then_some(self.armed_s),
                safe_start_ended: self.armed_seen.then_some(!self.armed_last),
                safe_start_ended_at_s: self.disarmed_at_s.filter(|_| !self.armed_last),
                dissipated_j: self.dissipated_j,
                max_damping_ns_per_m: self.max_damping,
                max_generated_j: self.max_generated,
                stall_bursts_excused: self.stall_bursts,
                max_stall_burst_j: self.max_stall_burst,
                sensor_noise_m: self.sensor_noise,
                max_threshold_scale: (self.max_onset / c.guard_onset_energy_j).max(1.0),
                band_hz: (c.guard_band_hz, c.guard_band_top_hz),
            },
            faithful_band_hz: faithful,
            faithful_band_limited_by: limited_by,
            faithful_band_after_safe_start_hz: None,
            faithful_band_after_safe_start_limited_by: None,
            rendering,
            record_delay,
            trajectory: self.trajectory,
            law_ended_in_hold: self.last_law.is_some()
                && self.last.is_some_and(|l| {
                    l.mode == command_mode::HOLD || l.mode == command_mode::HOLD_UNLOAD
                }),
        }
    }
}

/// `compensation.png`: the lead and the identified delay, the gain, the guard's damping
/// over the run, and the rendering's amplitude and phase by frequency.
pub fn draw(dir: &std::path::Path, r: &CompensationReport) -> anyhow::Result<()> {
    use crate::plot::{draw_png, Panel, Series};
    let t: Vec<f64> = r.trajectory.iter().map(|p| p.t_s).collect();
    let lead: Vec<f64> = r.trajectory.iter().map(|p| p.lead_us).collect();
    let (ti, id): (Vec<f64>, Vec<f64>) = r
        .trajectory
        .iter()
        .filter(|p| p.lead_estimate_us.is_finite())
        .map(|p| (p.t_s, p.lead_estimate_us))
        .unzip();
    let (tb, band): (Vec<f64>, Vec<f64>) = r
        .trajectory
        .iter()
        .filter(|p| p.load_band_delay_us.is_finite())
        .map(|p| (p.t_s, p.load_band_delay_us))
        .unzip();
    let gain: Vec<f64> = r
        .trajectory
        .iter()
        .map(|p| (p.gain - 1.0) * 100.0)
        .collect();
    let guard: Vec<f64> = r
        .trajectory
        .iter()
        .map(|p| p.guard_damping_ns_per_m * 1e-3)
        .collect();
    let estimate = Panel::new("delay compensation over the run", "time, s", "us")
        .with(Series::line("lead sent", t.clone(), lead, 0))
        .with(Series::points("the lead's estimator", ti, id, 1))
        .with(Series::points(
            "delay over 1-20 Hz (identified)",
            tb,
            band,
            2,
        ));
    let gain_panel = Panel::new(
        "identified actuator gain, departure from 1",
        "time, s",
        "gain - 1, %",
    )
    .with(Series::line("gain - 1", t.clone(), gain, 2));
    let guard_panel = Panel::new(
        format!(
            "passivity guard ({:.0}-{:.0} Hz): damping added",
            r.guard.band_hz.0, r.guard.band_hz.1
        ),
        "time, s",
        "kN s/m",
    )
    .with(Series::line("guard damping", t, guard, 3));
    let f: Vec<f64> = r.rendering.iter().map(|p| p.frequency_hz).collect();
    let amp: Vec<f64> = r
        .rendering
        .iter()
        .map(|p| (p.amplitude_ratio - 1.0) * 100.0)
        .collect();
    let phase: Vec<f64> = r.rendering.iter().map(|p| p.phase_deg).collect();
    let title = match r.faithful_band_hz {
        Some(b) => format!("rendered / element force (faithful up to {b:.0} Hz)"),
        None => "rendered / element force (no excited bin within tolerance)".to_string(),
    };
    let mut rendering = Panel::new(&title, "frequency, Hz", "amplitude error %, phase deg");
    if !f.is_empty() {
        let (lo, hi) = (f[0], *f.last().unwrap());
        rendering = rendering
            .log_x()
            .with(Series::points("amplitude error, %", f.clone(), amp, 0))
            .with(Series::points("phase, deg", f, phase, 1))
            .with(Series::dashed("+1 %", vec![lo, hi], vec![1.0, 1.0], 3))
            .with(Series::dashed("-1 %", vec![lo, hi], vec![-1.0, -1.0], 3));
    }
    draw_png(
        &dir.join("compensation.png"),
        1000,
        1300,
        1,
        &[estimate, gain_panel, guard_panel, rendering],
    )
}

/// The rendering judged after the safe start only: a second pass over the emulator's
/// records (the records' files are not in time order across processes, so the instant the
/// safe start ended must be known before the samples are judged).
pub struct SettledRendering {
    from_s: f64,
    welch: Welch,
}

impl SettledRendering {
    /// For a run whose safe start ended (`guard.safe_start_ended_at_s`); `None` otherwise.
    pub fn after(report: &CompensationReport) -> Option<SettledRendering> {
        report
            .guard
            .safe_start_ended_at_s
            .map(|from_s| SettledRendering {
                from_s,
                welch: Welch::new(),
            })
    }

    /// One emulator record (any order relative to other streams; its own in time order).
    pub fn emulator(&mut self, r: &EmulatorRecord) {
        self.welch.sample(r, r.t_s >= self.from_s);
    }

    /// Sets the report's band after the safe start (left null without a whole segment).
    pub fn finish(self, dt_s: f64, report: &mut CompensationReport) {
        if self.welch.segments > 0 {
            let (_, band, limited_by) = self.welch.faithful_band(dt_s);
            report.faithful_band_after_safe_start_hz = band;
            report.faithful_band_after_safe_start_limited_by = limited_by;
        }
    }
}

/// Welch sums of the element's force (x) and the measured force (y): 1 s Hann segments,
/// 50 % overlap, restarted at every break in the samples.
struct Welch {
    /// Sequence of the last sample offered (a gap breaks the segment).
    last_seq: Option<u64>,
    seg_x: Vec<f64>,
    seg_y: Vec<f64>,
    sxx: Vec<f64>,
    syy: Vec<f64>,
    sxy: Vec<Complex64>,
    segments: u64,
}

impl Welch {
    fn new() -> Welch {
        let bins = SEGMENT / 2 + 1;
        Welch {
            last_seq: None,
            seg_x: Vec::with_capacity(SEGMENT),
            seg_y: Vec::with_capacity(SEGMENT),
            sxx: vec![0.0; bins],
            syy: vec![0.0; bins],
            sxy: vec![Complex64::new(0.0, 0.0); bins],
            segments: 0,
        }
    }

    /// One emulator record: its element and measured force join the segment when `wanted`
    /// and usable (measured, not interpolated, while the rig runs, right after the previous
    /// sample); anything else breaks the segment.
    fn sample(&mut self, r: &EmulatorRecord, wanted: bool) {
        let usable = wanted
            && r.interpolated == 0
            && r.rig_state == rig_state::RUNNING
            && r.rig_force_n.is_finite()
            && r.force_n.is_finite();
        let consecutive = self.last_seq.is_some_and(|s| r.sample_seq == s + 1);
        self.last_seq = Some(r.sample_seq);
        if !usable || !consecutive {
            self.break_segment();
            if !usable {
                return;
            }
        }
        self.push(r.force_n, r.rig_force_n);
    }

    fn break_segment(&mut self) {
        self.seg_x.clear();
        self.seg_y.clear();
    }

    fn push(&mut self, x: f64, y: f64) {
        self.seg_x.push(x);
        self.seg_y.push(y);
        if self.seg_x.len() == SEGMENT {
            self.add_segment();
            // 50 % overlap.
            self.seg_x.drain(..SEGMENT / 2);
            self.seg_y.drain(..SEGMENT / 2);
        }
    }

    fn add_segment(&mut self) {
        let mut planner = RealFftPlanner::<f64>::new();
        let fft = planner.plan_fft_forward(SEGMENT);
        let hann =
            |i: usize| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * i as f64 / SEGMENT as f64).cos();
        let mean_x = self.seg_x.iter().sum::<f64>() / SEGMENT as f64;
        let mean_y = self.seg_y.iter().sum::<f64>() / SEGMENT as f64;
        let mut bx: Vec<f64> = (0..SEGMENT)
            .map(|i| (self.seg_x[i] - mean_x) * hann(i))
            .collect();
        let mut by: Vec<f64> = (0..SEGMENT)
            .map(|i| (self.seg_y[i] - mean_y) * hann(i))
            .collect();
        let mut fx = fft.make_output_vec();
        let mut fy = fft.make_output_vec();
        if fft.process(&mut bx, &mut fx).is_err() || fft.process(&mut by, &mut fy).is_err() {
            return;
        }
        for k in 0..fx.len() {
            self.sxx[k] += fx[k].norm_sqr();
            self.syy[k] += fy[k].norm_sqr();
            self.sxy[k] += fx[k].conj() * fy[k];
        }
        self.segments += 1;
    }

    /// Rendering by frequency (excited bins up to `BAND_TOP_HZ`), the faithful band and the
    /// first excited bin beyond it.
    fn faithful_band(&self, dt_s: f64) -> (Vec<RenderingPoint>, Option<f64>, Option<String>) {
        let df = 1.0 / (SEGMENT as f64 * dt_s);
        let mut rendering = Vec::new();
        let mut faithful = None;
        let mut limited_by = None;
        if self.segments >= MIN_SEGMENTS {
            let top = ((BAND_TOP_HZ / df) as usize).min(self.sxx.len() - 1);
            let strongest = self.sxx[1..=top].iter().cloned().fold(0.0, f64::max);
            let mut broken = false;
            for k in 1..=top {
                if self.sxx[k] <= MIN_RELATIVE_EXCITATION * strongest || self.syy[k] <= 0.0 {
                    continue;
                }
                let coherence = self.sxy[k].norm_sqr() / (self.sxx[k] * self.syy[k]);
                if coherence.is_nan() || coherence < MIN_COHERENCE {
                    continue;
                }
                let h = self.sxy[k] / self.sxx[k];
                let p = RenderingPoint {
                    frequency_hz: k as f64 * df,
                    amplitude_ratio: h.norm(),
                    phase_deg: h.arg().to_degrees(),
                    coherence,
                };
                rendering.push(p);
                if broken {
                    continue;
                }
                let amp_err = (p.amplitude_ratio - 1.0).abs();
                if amp_err <= AMPLITUDE_TOL && p.phase_deg.abs() <= PHASE_TOL_DEG {
                    faithful = Some(p.frequency_hz);
                } else {
                    broken = true;
                    limited_by = Some(format!(
                        "{:.0} Hz: amplitude {:+.2} %, phase {:+.2} deg",
                        p.frequency_hz,
                        (p.amplitude_ratio - 1.0) * 100.0,
                        p.phase_deg
                    ));
                }
            }
        }
        (rendering, faithful, limited_by)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The record's delay is the mean over the load band's bins of the lead less the
    /// rendered phase over the frequency: for a lag and a delay, `d + atan(w tau) / w` per
    /// bin, also where the phase passes -180 degrees (30 ms at 20 Hz is 216 degrees, which
    /// the rendering gives wrapped); bins above the band do not count, and too few bins
    /// read nothing.
    #[test]
    fn the_records_delay_is_the_mean_phase_delay_over_the_load_band() {
        for (delay, lag, lead) in [(2e-3, 3e-3, 0.3e-3), (30e-3, 1e-3, 0.0)] {
            let mut rendering = Vec::new();
            let mut expected = Vec::new();
            for k in 1..=40 {
                let f = k as f64;
                let w = 2.0 * std::f64::consts::PI * f;
                let phase = w * lead - w * delay - (w * lag).atan();
                // As `faithful_band` gives it: `arg`, in (-180, 180].
                let wrapped = Complex64::from_polar(1.0, phase).arg();
                rendering.push(RenderingPoint {
                    frequency_hz: f,
                    amplitude_ratio: 1.0,
                    phase_deg: wrapped.to_degrees(),
                    coherence: 1.0,
                });
                if f <= LOAD_BAND_TOP_HZ {
                    expected.push(delay + (w * lag).atan() / w);
                }
            }
            let d = record_delay(&rendering, lead).unwrap();
            let mean = expected.iter().sum::<f64>() / expected.len() as f64;
            assert!(
                (d.mean_us - mean * 1e6).abs() < 1e-6,
                "{d:?} against {mean}"
            );
            assert_eq!(d.bins, 20);
            assert_eq!((d.from_hz, d.to_hz), (1.0, 20.0));
            let max = expected.iter().cloned().fold(f64::MIN, f64::max);
            assert!((d.max_us - max * 1e6).abs() < 1e-6);
            assert_eq!(record_delay(&rendering[..4], lead), None);
        }
    }

    /// A nudge's move (the lead changing on consecutive samples for ~1.4 ms) counts once;
    /// the starting lead is no move; the console says how many.
    #[test]
    fn the_planned_leads_steps_are_counted_and_said() {
        let dt = 1.0 / 4096.0;
        let mut points = vec![(0.0, 2.85e-3)];
        for (start, from) in [(2.1, 2.85e-3), (2.6, 2.9925e-3)] {
            for k in 1..=6 {
                points.push((start + k as f64 * dt, from + k as f64 * 24e-6));
            }
        }
        assert_eq!(lead_steps(&points), 2);
        assert_eq!(lead_steps(&points[..1]), 0);
        // Records lost for 40 ms in the middle of the first move: still one move.
        let gapped: Vec<(f64, f64)> = points
            .iter()
            .map(|&(t, l)| {
                (
                    if t > 2.1 + 3.5 * dt && t < 2.5 {
                        t + 0.04
                    } else {
                        t
                    },
                    l,
                )
            })
            .collect();
        assert_eq!(lead_steps(&gapped), 2);
        let r = CompensationReport {
            starting_lead_us: Some(2850.0),
            final_lead_us: 3135.0,
            lead_nudges: Some(2),
            ..CompensationReport::default()
        };
        assert!(
            r.describe().contains(
                "(the lead the plan fixed, stepped 2 times because the loop kept oscillating)"
            ),
            "{}",
            r.describe()
        );
        let quiet = CompensationReport {
            lead_nudges: Some(0),
            ..r
        };
        assert!(!quiet.describe().contains("stepped"));
    }

    /// The console line warns when the safe start never ended, and only then.
    #[test]
    fn the_console_line_warns_when_the_safe_start_never_ended() {
        let mut r = CompensationReport {
            starting_lead_us: Some(0.0),
            final_lead_us: 710.0,
            identified_delay_us: Some(712.0),
            final_gain: 1.0,
            ..CompensationReport::default()
        };
        r.guard.band_hz = (60.0, 400.0);
        assert!(!r.describe().contains("WARNING"), "{}", r.describe());
        r.guard.safe_start_s = Some(0.57);
        r.guard.safe_start_ended = Some(true);
        let line = r.describe();
        assert!(
            line.contains("safe start 0.57 s") && !line.contains("WARNING"),
            "{line}"
        );
        r.guard.safe_start_ended = Some(false);
        assert!(
            r.describe().contains("the safe start never ended"),
            "{}",
            r.describe()
        );
        // A law cut short by a hold: said so, not warned as a delay never learned.
        r.law_ended_in_hold = true;
        r.guard.safe_start_s = Some(0.12);
        let line = r.describe();
        assert!(
            line.contains(
                "the safe start had not ended when the law gave way to a hold, after 0.12 s"
            ) && !line.contains("WARNING"),
            "{line}"
        );
    }

    /// A negative identified delay (beyond two standard errors) is explained, not left as
    /// if it were an actuator's delay; a positive one or one within its error is not.
    #[test]
    fn a_negative_identified_delay_is_explained() {
        let mut r = CompensationReport {
            identified_delay_us: Some(-4420.0),
            identified_delay_sigma_us: Some(34.0),
            ..CompensationReport::default()
        };
        assert!(
            r.describe().contains("(-4420 us) is negative"),
            "{}",
            r.describe()
        );
        r.identified_delay_sigma_us = Some(3000.0);
        assert!(!r.describe().contains("is negative"), "{}", r.describe());
        r.identified_delay_us = Some(250.0);
        r.identified_delay_sigma_us = Some(5.0);
        assert!(!r.describe().contains("is negative"), "{}", r.describe());
    }

    /// The console line warns when the faithful band ends inside the load band, names the
    /// bin that limits it, and says nothing of the band when it reaches past 20 Hz.
    #[test]
    fn the_console_line_warns_when_the_load_band_is_not_rendered_faithfully() {
        let mut r = CompensationReport {
            faithful_band_hz: Some(194.0),
            ..CompensationReport::default()
        };
        assert!(!r.describe().contains("WARNING"), "{}", r.describe());
        r.faithful_band_hz = Some(20.0);
        assert!(!r.describe().contains("WARNING"), "{}", r.describe());
        r.faithful_band_hz = Some(9.0);
        // Limited above the load band (a short run: nothing excited between): no warning.
        r.faithful_band_hz = Some(3.0);
        r.faithful_band_limited_by = Some("114 Hz: amplitude -99.00 %, phase +4.00 deg".into());
        let line = r.describe();
        assert!(
            !line.contains("WARNING")
                && line
                    .contains("the load excited nothing between 3 and 114 Hz, limited at 114 Hz"),
            "{line}"
        );
        r.faithful_band_hz = Some(9.0);
        r.faithful_band_limited_by = Some("10 Hz: amplitude -1.20 %, phase -0.40 deg".into());
        let line = r.describe();
        assert!(
            line.contains("WARNING: the rendered force is not faithful over the load band")
                && line.contains("only up to 9 Hz, limited at 10 Hz: amplitude -1.20 %"),
            "{line}"
        );
        // The load excites nothing above the band's top: said so, not warned.
        r.faithful_band_limited_by = None;
        let line = r.describe();
        assert!(
            line.contains("faithful band 9 Hz (the highest frequency the load excites")
                && !line.contains("WARNING"),
            "{line}"
        );
        // Not faithful at the first excited bin: no band at all.
        r.faithful_band_hz = None;
        r.faithful_band_limited_by = Some("1 Hz: amplitude -3.00 %, phase -1.10 deg".into());
        let line = r.describe();
        assert!(
            line.contains("faithful band none")
                && line.contains("not even at its lowest excited bin, limited at 1 Hz"),
            "{line}"
        );
        // Not judged (no bin excited enough) is not a warning: nothing was seen.
        r.faithful_band_limited_by = None;
        let line = r.describe();
        assert!(
            line.contains("faithful band not judged") && !line.contains("WARNING"),
            "{line}"
        );
    }

    /// The faithful band judges the bins the load excites: a 2 Hz load rendered exactly
    /// with the loop's noise far below the 80 dB threshold, the element's noise coherent with the measured
    /// force's but 250 times stronger (an external rig's run with stale samples), is
    /// faithful up to its highest excited bin and limited by nothing; a 10 Hz content 30 dB
    /// down rendered at 95 % limits it there, as before.
    #[test]
    fn the_faithful_band_judges_the_bins_the_load_excites() {
        let mut seed = 7u64;
        let mut noise = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let dt = 1.0 / 4096.0;
        let mut quiet = Welch::new();
        let mut loud = Welch::new();
        let mut ringing = Welch::new();
        for i in 0..6 * 4096 {
            let t = i as f64 * dt;
            let load = 2e4 + 4e3 * (2.0 * std::f64::consts::PI * 2.0 * t).sin();
            let n = noise();
            quiet.push(load + 0.2 * n, load + 0.2 / 250.0 * n);
            // A 150 Hz ringing rendered faithfully, beyond a gap the load left.
            let ring = 3e1 * (2.0 * std::f64::consts::PI * 150.0 * t).sin();
            ringing.push(load + ring + 0.2 * n, load + ring + 0.2 / 250.0 * n);
            let upper = 1e2 * (2.0 * std::f64::consts::PI * 10.0 * t).sin();
            loud.push(
                load + upper + 0.2 * n,
                load + 0.95 * upper + 0.2 / 250.0 * n,
            );
        }
        // The Hann window spreads the 2 Hz line over 1-3 Hz, the 10 Hz line over 9-11 Hz.
        let (_, band, limited_by) = quiet.faithful_band(dt);
        assert_eq!((band, limited_by), (Some(3.0), None));
        // Judged across the gap the load left (the rendering is a smooth response).
        let (_, band, limited_by) = ringing.faithful_band(dt);
        assert_eq!((band, limited_by), (Some(151.0), None));
        let (_, band, limited_by) = loud.faithful_band(dt);
        assert_eq!(band, Some(3.0));
        assert!(
            limited_by
                .as_deref()
                .is_some_and(|l| l.starts_with("9 Hz: amplitude -5.00 %")),
            "{limited_by:?}"
        );
    }

    fn command(t_s: f64, mode: u32, lead_s: f64) -> ControllerRecord {
        ControllerRecord {
            t_s,
            command_seq: (t_s * 4096.0) as u64,
            setpoint_seq: 0,
            sample_seq: 0,
            mode,
            setpoint_force_n: f64::NAN,
            predicted_force_n: 2e4,
            command_force_n: 2e4,
            law_displacement_m: 3.5e-4,
            law_stiffness_n_per_m: 5.7e7,
            law_damping_ns_per_m: 0.0,
            law_force_rate_n_per_s: 0.0,
            state: 1,
            fault_code: 0,
            limited: 0,
            repeat: 0,
            end_to_end_ns: 0,
            measured_force_n: 2e4,
            lead_s,
            lead_order: 2,
            actuator_gain: 1.0,
            guard_damping_ns_per_m: 0.0,
            guard_generated_j: 0.0,
            guard_excused_j: 0.0,
            guard_stall_bursts: 0,
            guard_armed: 0,
            guard_onset_j: 0.5e-3,
            sensor_noise_m: f64::NAN,
            identified_delay_s: f64::NAN,
            identified_delay_sigma_s: f64::NAN,
            load_band_delay_s: f64::NAN,
            load_band_delay_sigma_s: f64::NAN,
            load_band_bins: 0,
            load_band_from_hz: f64::NAN,
            load_band_to_hz: f64::NAN,
        }
    }

    fn emulator_sample(seq: u64, force_n: f64, rig_force_n: f64) -> EmulatorRecord {
        EmulatorRecord {
            t_s: seq as f64 / 4096.0,
            step_idx: seq,
            cycle_idx: seq,
            sample_seq: seq,
            interpolated: 0,
            model_flags: 0,
            wake_late_ns: 0,
            z_used_m: 0.0,
            force_n,
            law_stiffness_n_per_m: 5.7e7,
            law_damping_ns_per_m: 0.0,
            law_force_rate_n_per_s: 0.0,
            rig_force_n,
            rig_state: rig_state::RUNNING,
            rig_fault_code: 0,
            generated_energy_j: 0.0,
            oscillation_m: 0.0,
            element_temperature_rise_k: 0.0,
        }
    }

    /// The stall bursts the guard excused: the records' running count (whichever records
    /// were lost), the largest excused, and the console line says so (and nothing without
    /// one).
    #[test]
    fn the_stall_bursts_the_guard_excused_are_counted() {
        let cfg = crate::hil::config::default_hil_config().expect("embedded config");
        // (excused, the running count); the record that opened the second window lost.
        let records = [
            (0.0, 0),
            (0.0, 1),
            (1e-3, 1),
            (2.5e-3, 1),
            (2e-3, 1),
            (4e-3, 2),
            (3e-3, 2),
            (0.0, 2),
        ];
        let mut a = CompensationAnalyser::new(1.0 / 4096.0, 1.0);
        for (k, &(x, n)) in records.iter().enumerate() {
            let mut c = command(k as f64 * 0.01, command_mode::LAW, 252e-6);
            c.guard_excused_j = x;
            c.guard_stall_bursts = n;
            a.controller(&c);
        }
        let r = a.finish(&cfg);
        assert_eq!(r.guard.stall_bursts_excused, 2);
        assert_eq!(r.guard.max_stall_burst_j, 4e-3);
        assert!(
            r.describe()
                .contains("largest 0.0 kN s/m, 2 stall bursts excused (largest 4.0 mJ);"),
            "{}",
            r.describe()
        );
        let mut quiet = CompensationAnalyser::new(1.0 / 4096.0, 1.0);
        quiet.controller(&command(0.0, command_mode::LAW, 252e-6));
        assert!(!quiet.finish(&cfg).describe().contains("stall burst"));
    }

    /// The faithful band after the safe start is judged on the samples after it alone: a
    /// run that rendered 3 % short while the guard was armed (its first 3 s) and exactly
    /// after has no faithful band over the whole run and one up to the highest excited
    /// bin after the safe start (61 Hz, with the Hann window's neighbour 62 Hz); a run whose
    /// guard never armed has none after it.
    #[test]
    fn the_band_after_the_safe_start_leaves_the_learning_out() {
        let cfg = crate::hil::config::default_hil_config().expect("embedded config");
        let dt = 1.0 / 4096.0;
        let run = |armed_until_s: Option<f64>| {
            let mut a = CompensationAnalyser::new(dt, 8.0);
            let mut noise = 1u64;
            let (mut commands, mut samples) = (Vec::new(), Vec::new());
            for k in 0..(8 * 4096u64) {
                let t = k as f64 * dt;
                let armed = armed_until_s.is_some_and(|u| t < u);
                let mut c = command(t, command_mode::LAW, 252e-6);
                c.guard_armed = u8::from(armed);
                commands.push(c);
                // Element force: 2, 7, 23 and 61 Hz.
                let f = [2.0, 7.0, 23.0, 61.0]
                    .iter()
                    .map(|&h| 1e4 * (2.0 * std::f64::consts::PI * h * t).sin())
                    .sum::<f64>();
                // The load cell's noise, 10 N (a fixed sequence), so that bins the load
                // does not excite are incoherent.
                noise = noise
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                let e = 20.0 * ((noise >> 11) as f64 / (1u64 << 53) as f64 - 0.5);
                let measured = if armed { 0.97 * f } else { f } + e;
                samples.push(emulator_sample(k, f, measured));
            }
            // The emulator's records before the controller's, as a merged file may
            // hold them: the band after the safe start must not depend on that order.
            for e in &samples {
                a.emulator(e);
            }
            for c in &commands {
                a.controller(c);
            }
            let mut r = a.finish(&cfg);
            if let Some(mut settled) = SettledRendering::after(&r) {
                for e in &samples {
                    settled.emulator(e);
                }
                settled.finish(dt, &mut r);
            }
            r
        };
        let r = run(Some(3.0));
        // Over the whole run the 3 % short stretch breaks the band at its first bin.
        assert!(
            r.faithful_band_hz.is_none_or(|b| b < 2.5),
            "{:?}",
            r.faithful_band_hz
        );
        assert!(r.faithful_band_limited_by.is_some());
        // The highest excited bin: 61 Hz and the Hann window's neighbour, 62 Hz.
        assert_eq!(r.guard.safe_start_ended_at_s, Some(3.0));
        assert_eq!(r.faithful_band_after_safe_start_hz, Some(62.0));
        assert!(
            r.describe().contains("(62 Hz after the safe start)"),
            "{}",
            r.describe()
        );
        let never = run(None);
        assert_eq!(never.faithful_band_hz, Some(62.0));
        assert_eq!(never.faithful_band_after_safe_start_hz, None);
        assert!(
            !never.describe().contains("after the safe start"),
            "{}",
            never.describe()
        );
    }

    /// The final lead is the last law command's, also when the run ended in a hold (it
    /// read the configured guess then: "lead 2800 us -> 2800 us" for a run whose lead had
    /// walked down to 1545 us before `loop-unstable`).
    #[test]
    fn the_final_lead_is_the_last_law_commands_when_a_hold_ends_the_run() {
        let mut cfg = crate::hil::config::default_hil_config().expect("embedded config");
        cfg.compensation.initial_delay_s = 2800e-6;
        let mut a = CompensationAnalyser::new(1.0 / 4096.0, 1.0);
        let mut t = 0.0;
        for k in 0..400 {
            let lead = 2800e-6 - 3e-6 * k as f64;
            a.controller(&command(t, command_mode::LAW, lead));
            t += 1.0 / 4096.0;
        }
        for _ in 0..50 {
            a.controller(&command(t, command_mode::HOLD, 2800e-6));
            t += 1.0 / 4096.0;
        }
        let r = a.finish(&cfg);
        assert!(
            (r.final_lead_us - 1603.0).abs() < 1e-6,
            "{}",
            r.final_lead_us
        );
        assert!(r.law_ended_in_hold);
        // Only law commands: the same, and no hold.
        let mut b = CompensationAnalyser::new(1.0 / 4096.0, 1.0);
        b.controller(&command(0.0, command_mode::LAW, 900e-6));
        let r = b.finish(&cfg);
        assert!((r.final_lead_us - 900.0).abs() < 1e-6);
        assert!(!r.law_ended_in_hold);
    }
    /// A lead the plan fixed settles when it last moved: its nudge's 5 % step (2850 ->
    /// 2992.5 us at 2.42 s) is within the 5 % an adapted lead settles to, yet it is the
    /// moment the lead settled. An adapted lead that moved as much settled at its start.
    #[test]
    fn a_fixed_leads_nudge_is_when_it_settled() {
        let run = |adapt_lead: bool| {
            let mut cfg = crate::hil::config::default_hil_config().expect("embedded config");
            cfg.compensation.adapt_lead = adapt_lead;
            let mut a = CompensationAnalyser::new(1.0 / 4096.0, 6.0);
            for k in 0..12 {
                let t = 0.22 * k as f64;
                let lead = if k >= 11 { 2992.5e-6 } else { 2850e-6 };
                a.controller(&command(t, command_mode::LAW, lead));
            }
            a.controller(&command(3.0, command_mode::LAW, 2992.5e-6));
            a.finish(&cfg).settled_at_s.expect("settled")
        };
        assert!((run(false) - 2.42).abs() < 1e-12, "{}", run(false));
        assert_eq!(run(true), 0.0);
    }

    /// A sensor noisier than the guard's thresholds were chosen at: the report keeps the
    /// last reading and the largest scale, and the console says it; at the shipped noise
    /// it says nothing.
    #[test]
    fn a_noisy_sensors_scale_on_the_guard_is_reported() {
        let cfg = crate::hil::config::default_hil_config().expect("embedded config");
        let onset = cfg.compensation.guard_onset_energy_j;
        let mut a = CompensationAnalyser::new(1.0 / 4096.0, 1.0);
        for (k, (noise, scale)) in [(f64::NAN, f64::INFINITY), (1.3e-6, 27.0), (1.0e-6, 16.0)]
            .into_iter()
            .enumerate()
        {
            let mut c = command(k as f64 * 0.01, command_mode::LAW, 252e-6);
            c.sensor_noise_m = noise;
            c.guard_onset_j = onset * scale;
            a.controller(&c);
        }
        let r = a.finish(&cfg);
        assert_eq!(r.guard.sensor_noise_m, Some(1.0e-6));
        assert!((r.guard.max_threshold_scale - 27.0).abs() < 1e-9);
        assert!(
            r.describe()
                .contains("thresholds up to 27.0 times for 1.00 um of sensor noise"),
            "{}",
            r.describe()
        );
        let mut quiet = CompensationAnalyser::new(1.0 / 4096.0, 1.0);
        let mut c = command(0.0, command_mode::LAW, 252e-6);
        c.sensor_noise_m = 0.1e-6;
        quiet.controller(&c);
        let r = quiet.finish(&cfg);
        assert_eq!(r.guard.max_threshold_scale, 1.0);
        assert!(!r.describe().contains("sensor noise"));
    }

    /// The identified delay is the load band's when the last law command carried one, with
    /// its bins and span on the console; a run whose load band was never (or is no longer)
    /// identified falls back to the lead's estimator, and the JSON and the console say so.
    #[test]
    fn the_identified_delay_is_the_load_bands_and_the_fallback_says_so() {
        let cfg = crate::hil::config::default_hil_config().expect("embedded config");
        let with = |band: Option<f64>| {
            let mut a = CompensationAnalyser::new(1.0 / 4096.0, 1.0);
            let mut r = command(0.0, command_mode::LAW, 252e-6);
            r.identified_delay_s = 914e-6;
            r.identified_delay_sigma_s = 3e-6;
            a.controller(&r);
            let mut r = command(1.0, command_mode::LAW, 252e-6);
            r.identified_delay_s = 914e-6;
            r.identified_delay_sigma_s = 3e-6;
            if let Some(d) = band {
                r.load_band_delay_s = d;
                r.load_band_delay_sigma_s = 15e-6;
                r.load_band_bins = 18;
                r.load_band_from_hz = 0.9999985;
                r.load_band_to_hz = 18.9999716;
            }
            a.controller(&r);
            a.finish(&cfg)
        };
        let r = with(Some(2565e-6));
        assert_eq!(r.identified_from, Some("load-band"));
        assert!((r.identified_delay_us.unwrap() - 2565.0).abs() < 1e-9);
        assert!((r.lead_estimate_us.unwrap() - 914.0).abs() < 1e-9);
        let line = r.describe();
        assert!(
            line.contains("identified 2565 us (+- 15.0) over 1-19 Hz (18 bins) (the lead's estimator: 914 us)"),
            "{line}"
        );
        assert!(!line.contains("negative"), "{line}");
        // A delay below zero is said to be no delay.
        let r = with(Some(-2582e-6));
        assert!(
            r.describe()
                .contains("identified -2582 us (+- 15.0) over 1-19 Hz (18 bins) (the lead's estimator: 914 us) (negative: the actuator's force leads its command"),
            "{}",
            r.describe()
        );
        let r = with(None);
        assert_eq!(r.identified_from, Some("lead-estimator"));
        assert!((r.identified_delay_us.unwrap() - 914.0).abs() < 1e-9);
        assert_eq!(r.identified_bins, None);
        assert!(
            r.describe()
                .contains("identified 914 us (+- 3.0) (the lead's estimator, weighing"),
            "{}",
            r.describe()
        );
    }
}
