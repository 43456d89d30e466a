//! The controller's compensation of the actuator (SPEC 6.1), sent with every command as a
//! `Compensation`: the lead the rig predicts its displacement over, the actuator gain it
//! divides by, and the passivity guard's damping.
//!
//! - `DelayEstimator` (`estimator.rs`): learns the actuator's effective delay and gain online from the force
//!   the rig measured against the element's force at the same sample (the adaptive time
//!   series compensator's idea, Chae et al. 2013): both low-passed to the load band, the
//!   measured force regressed on the element force and its rate by exponentially weighted
//!   least squares (`F_meas ~ a F + b dF/dt`: residual gain `a`, residual delay `-b/a`),
//!   and the lead and gain moved towards the estimate smoothly, with bounded steps.
//! - `PassivityGuard` (`guard.rs`): a passivity observer (`hil::passivity`) above the load band and a
//!   variable damper that adds damping there only while the loop has generated energy
//!   (Hannaford and Ryu 2002), released slowly once the energy is gone. With `adapt`, it
//!   starts armed (the safe start): damping (all of it, or the largest fraction the starting
//!   lead stays stable with, `check::safe_start_damping_ns_per_m`; none at a start the plan
//!   moved to a lead stable by itself, `start_planned`) from the first command until the lead has
//!   reached the delay the estimator resolved, because until then nobody knows whether the
//!   loop is passive (a guess of 0 in front of a 722 us actuator rang the resonance up to
//!   0.3 % error before the observer saw energy). A loop that rings anyway gives its lead:
//!   the phase delay where it rings (`oscillation::OscillationDelay`), which ends the safe
//!   start.
//!
//! Must not: allocate, lock, log, read a clock or do I/O (runs per setpoint in the
//! controller's loop); same setpoint stream gives the same compensation bit for bit.

mod contact;
mod estimator;
mod guard;
mod load_band;
mod noise;
mod nudge;
mod oscillation;

use contact::*;
pub use estimator::*;
pub use guard::*;

pub use load_band::{LoadBandDelay, LoadBandEstimate};
/// The Welch rules the report's record estimates share with `LoadBandDelay`.
pub mod welch_rules {
    pub use super::load_band::{MIN_BINS, MIN_COHERENCE, MIN_RELATIVE_EXCITATION, MIN_SEGMENTS};
}
pub use noise::SensorNoise;
pub use nudge::{LeadNudge, NudgeRange};
pub use oscillation::{OscillationDelay, OscillationEstimate};

use super::passivity::{LowPass2, PassivityObserver};
use crate::ipc::messages::Compensation;

/// `[compensation]`: the controller's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompensationConfig {
    /// The actuator's effective output delay as first guessed, s.
    pub initial_delay_s: f64,
    /// The longest lead the run may start with, s (`check::starting_lead_cap_s`: a lead
    /// too long for the fastest actuator the guess allows diverges within milliseconds,
    /// before anything is learned; one too short is what the guard makes up for).
    pub starting_lead_cap_s: f64,
    /// The safe start's damping, N s/m (`check::safe_start_damping_ns_per_m`: the largest
    /// of `guard_max_damping_ns_per_m` and its halves that the starting lead stays stable
    /// with in front of every actuator the guess allows; not a key).
    pub safe_start_damping_ns_per_m: f64,
    /// The plan moved the start off the guess to a lead stable by itself for the actuators
    /// the declaration allows (`check::CompensationPlan::start_moved_from_us`): no cap on
    /// it and no safe start's damping (not a key).
    pub start_planned: bool,
    /// Prediction polynomial order (0-3).
    pub lead_order: u32,
    /// Learn the delay and gain during the run.
    pub adapt: bool,
    /// With `adapt`, whether the lead follows the identified delay (false: the lead stays
    /// where it starts and only the gain is learned; set by `check::compensation_plan`
    /// when the identified delay would take the loop out of its stable leads).
    pub adapt_lead: bool,
    /// Let `check::compensation_plan` choose the lead (and whether it adapts and the
    /// guard acts) from the simulated rig's declared actuator within `actuator_tolerance`.
    pub plan_from_actuator: bool,
    /// With `--rig external`: the external rig's actuator and specimen are the ones
    /// `[rig.actuator]` and `[rig]` declare, so the launcher judges and plans for them as
    /// for the simulated rig (`check::declares_the_rig`). Off: nothing is known of them.
    pub plan_for_external_rig: bool,
    /// How far the hardware may be from the declared actuator: each parameter within
    /// this fraction (the plan's draws).
    pub actuator_tolerance: f64,
    /// With the lead fixed by the plan: where a loop that keeps oscillating may step it
    /// (`nudge::LeadNudge`); `None` otherwise.
    pub nudge: Option<NudgeRange>,
    /// Add damping above the load band while the loop generates energy.
    pub passivity_guard: bool,
    /// Largest lead the adaptation may reach, s.
    pub max_delay_s: f64,
    /// Low-pass corner of the estimator's regression (the band the lead is right in), Hz.
    pub estimator_band_hz: f64,
    /// Memory of the estimator's least squares, s.
    pub estimator_memory_s: f64,
    /// Time constant with which the lead and gain follow the estimate, s.
    pub adapt_time_s: f64,
    /// Corner above which the guard observes energy and adds damping, Hz (its observer
    /// stops at `guard_band_top_hz`, where the sensor's noise takes over).
    pub guard_band_hz: f64,
    pub guard_band_top_hz: f64,
    /// Energy generated in the band (over the observer's 100 ms) below which the guard
    /// adds nothing, J: the ringing of the resonance after an axle passage stays below it.
    pub guard_onset_energy_j: f64,
    /// Energy generated in the band at which the guard's damping is full, J.
    pub guard_full_energy_j: f64,
    /// Largest damping the guard adds, N s/m.
    pub guard_max_damping_ns_per_m: f64,
    /// The most damping by the lead in effect (`check::guard_damping_by_lead`; not a key).
    pub guard_damping_by_lead: DampingByLead,
    /// Time constant of the guard's release once the energy is gone, s.
    pub guard_release_s: f64,
}

impl CompensationConfig {
    /// The shipped settings around a starting guess.
    pub fn with_initial_delay(initial_delay_s: f64) -> CompensationConfig {
        CompensationConfig {
            initial_delay_s,
            starting_lead_cap_s: f64::INFINITY,
            safe_start_damping_ns_per_m: f64::INFINITY,
            start_planned: false,
            lead_order: 2,
            adapt: true,
            adapt_lead: true,
            plan_from_actuator: true,
            plan_for_external_rig: false,
            actuator_tolerance: 0.3,
            nudge: None,
            passivity_guard: true,
            max_delay_s: 0.01,
            estimator_band_hz: 30.0,
            estimator_memory_s: 0.25,
            adapt_time_s: 0.2,
            guard_band_hz: 60.0,
            guard_band_top_hz: 400.0,
            guard_onset_energy_j: 0.5e-3,
            guard_full_energy_j: 5.0e-3,
            guard_max_damping_ns_per_m: 40.0e3,
            guard_damping_by_lead: DampingByLead::NONE,
            guard_release_s: 0.25,
        }
    }
}

/// The compensation's state for records and the report.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompensationStatus {
    pub compensation: Compensation,
    /// The effective delay identified now (lead plus the residual), s; NaN before any.
    pub identified_delay_s: f64,
    pub identified_delay_sigma_s: f64,
    /// The actuator's effective delay over the load band (`LoadBandDelay`), after the last
    /// whole segment (None: not yet, or too few excited bins).
    pub load_band: Option<LoadBandEstimate>,
    pub guard: GuardState,
    /// The displacement sensor's noise as read online (`noise::SensorNoise`), m; NaN
    /// before the first reading.
    pub sensor_noise_m: f64,
}

/// The controller's compensator: estimator, adaptation and guard around one `Compensation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Compensator {
    cfg: CompensationConfig,
    dt_s: f64,
    estimator: DelayEstimator,
    guard: PassivityGuard,
    lead_s: f64,
    gain: f64,
    last_sample_seq: Option<u64>,
    /// The last setpoint's (displacement, element force, measured force).
    last_values: (f64, f64, f64),
    status: CompensationStatus,
    /// The first contact's gain read (`ContactGain`).
    contact: ContactGain,
    /// The share of the samples in the estimator's memory that no setpoint carried
    /// (bridged, or lost in a longer gap): exponentially weighted over the memory.
    missing_share: f64,
    /// Per-sample decay of `missing_share` (`exp(-dt / estimator_memory)`).
    missing_decay: f64,
    /// The safe start's estimate of the phase delay where the loop rings
    /// (`follow_oscillation`), on the force the rig was asked for without its lead.
    oscillation: OscillationDelay,
    /// The actuator's effective delay over the load band, for the report (moves no lead).
    load_band: LoadBandDelay,
    /// The rig's view of the guard's damping, replayed: the two previous displacements
    /// and the low-passed velocity (`Servo::law_force_n`'s first-order high-pass).
    replay_z_m: [f64; 2],
    replay_velocity_lp: f64,
    replay_samples: u32,
    /// Samples fed since the oscillation estimate last moved the lead.
    since_oscillation_move: u64,
    /// The lead the oscillation estimate asked for, while the lead moves to it
    /// (`follow_oscillation`).
    oscillation_target: Option<f64>,
    /// The lead the last ringing gave: the load band's estimator moves the lead between it
    /// and `RING_LEAD_RANGE` above it.
    ring_lead: Option<f64>,
    /// The guard's generated energy when the lead arrived at the ring's target, J
    /// (`RING_GROWN_AFTER_ARRIVAL`).
    ring_energy_at_arrival_j: f64,
    /// The oscillation estimate's target averaged over about a period of the ring
    /// (`RING_PERIODS_AVERAGED`); NaN before the window is full.
    ring_target_avg: f64,
    /// The delay estimator's latest estimate (`adapt`).
    last_estimate: Option<DelayEstimate>,
    /// The planned fixed lead's nudge (`CompensationConfig::nudge`), and the lead it asked
    /// for while the lead moves there.
    nudge: Option<LeadNudge>,
    nudge_target: Option<f64>,
    /// The displacement sensor's noise, which scales the guard's thresholds.
    noise: SensorNoise,
    /// The weights' sum since the first sample (`1 - decay^n`): `missing_share /
    /// missing_weight` is the share without the start's bias towards 0.
    missing_weight: f64,
}

/// The lead agrees with a resolved delay within this fraction: the safe start ends.
const SAFE_START_AGREEMENT: f64 = 0.1;

/// The tolerance of `SAFE_START_AGREEMENT` around a delay `target_s`, never under 20 us.
#[inline]
fn safe_start_tolerance(target_s: f64) -> f64 {
    (SAFE_START_AGREEMENT * target_s).max(20e-6)
}

/// An estimate precise enough to end the safe start: its standard error within
/// `safe_start_tolerance` of the delay (clamped to the lead's bounds), from at least
/// `MIN_INDEPENDENT` residuals.
#[inline]
fn safe_start_precise(e: DelayEstimate, max_delay_s: f64) -> bool {
    let target = e.delay_s.clamp(0.0, max_delay_s);
    e.independent >= MIN_INDEPENDENT
        && e.delay_sigma_s.is_finite()
        && e.delay_sigma_s <= safe_start_tolerance(target)
}

/// Under the safe start, a precise delay estimate (`safe_start_precise`) within this
/// fraction of the lead is reached at `OSCILLATION_MAX_RATE`, not at
/// `adapt_time`'s, so that the safe start ends as soon as the estimate is in; and a ring
/// reading that would move the lead away from such an estimate (longer when it says
/// shorter, or the reverse) is not taken. The safe start's full damping is a precaution
/// for a lead too short; kept on a lead a little too long it is itself what generates
/// energy at the band's top, and the ring read there points the wrong way. In-process,
/// `perturb = 0.3` seeds 1-20 (2026-11-28): `lag-delay` 300 + 100 us from a guess of
/// 800 us read 445-545 us precisely by 0.15-0.3 s while the lead crept down from 800 us
/// at `adapt_time`'s pace; a 398-399 Hz ring then read 1054-1062 us, the lead went there
/// and seeds 9, 13 and 14 tripped `loop-unstable` (now 0.08-0.09 %, no fault). Within
/// the fraction only: a servo-hydraulic force loop's precise estimate is its load band's
/// delay, not the lead its loop needs (`slow-250kn` read 4.2 ms against the 252 us guess
/// and, moved there at once, swung 1.3-1.5 mm for 3 s instead of tripping at 0.28 s).
const SAFE_START_FAST_RANGE: f64 = 0.5;

/// Longest run of samples without a setpoint that the compensator bridges (8 ms at
/// 4096 Hz); a longer gap restarts the estimator, whose warm-up is 133 ms. Under emulator
/// stalls of 1-8 periods every 4-16 ms (a loaded machine) a limit of 8 restarted it more
/// often than it warmed up: no estimate came, and the safe start's damping stayed on all
/// run (0.26-0.30 % displacement error instead of 0.034 %). Bridges are counted in the
/// missing share, and the standard error counts their residuals.
const MAX_BRIDGED_GAP: u64 = 32;

/// The lead follows the estimate only while at most this share of the samples in the
/// estimator's memory came without a setpoint. On a loaded machine the emulator may take
/// several samples per cycle for a while (one setpoint carries the newest); the estimate
/// from the rest is not the actuator's (2026-11-27: a 2 s run on the shipped actuator with
/// 564 setpoint gaps in 1.5 s, 21 % of the samples missing, read 5283 +- 405 us, which
/// passed the quarter-of-the-difference rule, and the lead went from 252 to 583 us; clean
/// default runs on the loaded machine of the same day missed 1-4 % while they learned,
/// with spikes to 10-37 % later).
const MAX_MISSING_SHARE: f64 = 0.1;
/// The oscillation estimate (`follow_oscillation`): its memory (two periods of the
/// specimen's resonance on the element, half a period of a servo-hydraulic loop ringing at
/// 35 Hz: a ring that grows by e in 20 ms leaves no time for more), the share of the
/// band's power its fit must explain, the band's lower edge (a servo-hydraulic force loop
/// with a lead too short rings at 17-55 Hz; below 27 Hz the window holds less than 0.4 of
/// a period and the reading is noise: `slow-250kn`, ringing at about 20 Hz, took leads
/// from it that held it at the edge of its stable range, swinging 2 mm at 10-40 Hz around
/// the axles with 16-98 % displacement error (2026-11-28), where without a reading it trips
/// within 0.3 s and holds; the band was 10-400 Hz until then), and the rate at which the
/// lead moves to its
/// target (s of lead per s; 25 us per sample at 4096 Hz: the force changes by the velocity
/// times that times the stiffness, 0.14 kN per sample for 0.1 m/s on 57 MN/m).
const OSCILLATION_MEMORY_S: f64 = 0.015;
const OSCILLATION_MIN_FIT: f64 = 0.8;
const OSCILLATION_LOW_HZ: f64 = 27.0;
const OSCILLATION_MAX_RATE: f64 = 0.1;
/// Once a ringing has given the lead, the load band's estimator may raise it by up to
/// this fraction and never lower it: a lag-and-delay actuator's delay is the same in both
/// bands (the ring read 0.76 ms, the load band 0.81), a servo-hydraulic one's is not (the
/// ring 2.2 ms, the load band under 1 ms), and a lead too short is where such a loop rings
/// (`rths-fast-150kn` seed 2, its lead free, tripped at 1.06 s; nominal `fatigue-150kn`,
/// its lead free to go 15 % lower, rang up again at 35 Hz over the last second).
const RING_LEAD_RANGE: f64 = 0.15;
/// The ring's target is the estimate averaged over about one period of the ring
/// (exponentially, time constant `1 / (RING_PERIODS_AVERAGED f)`): the estimate's memory
/// (`OSCILLATION_MEMORY_S`) is half a period of a servo-hydraulic loop ringing at 37 Hz,
/// and over a period it swings by +-1 ms around its mean (`fatigue-150kn`, 2026-11-28:
/// 2.3-4.5 ms, so the target taken was where the swing happened to be when the ring
/// qualified: 2413 us in one run and 3845 us, beyond the stable leads' 3360 us, in another
/// that a loaded machine had shifted by a few ms; that one tripped `loop-unstable`).
const RING_PERIODS_AVERAGED: f64 = 1.0;
/// A ring moves the lead only once the guard's observer has seen this many times its
/// onset energy generated: at the onset itself (0.5 mJ) the band holds little more than
/// the sensor's noise through the safe start's damping, whose reading (1.85 ms, fit 0.99,
/// at 70-100 Hz, in front of a 0.58 ms `lag-delay` started at 742 us) took the lead to
/// 1.5 ms and the loop into `loop-unstable` within 10 ms.
const RING_MIN_ENERGY_ONSETS: f64 = 4.0;
/// The lead has arrived at the oscillation's target within this, s.
const OSCILLATION_ARRIVED_S: f64 = 2e-6;
/// The ring's follow-up: for `RING_FOLLOW_UP_S` after the lead arrived at a ring's target
/// with the safe start over, a ring that has grown to `RING_GROWN_AFTER_ARRIVAL` times the
/// guard's energy at the arrival says the lead is still too short, and the lead steps up
/// by `RING_LEAD_UP` (down by `RING_LEAD_DOWN` where `w L` says the lead is too long). The
/// phase at a servo-hydraulic loop's ring is no stable lead of its own: `rths-fast-150kn`
/// seed 5, stable with leads 1750-2660 us, read 1399 us at its 48 Hz ring, the safe start
/// ended there, the guard can add no damping at that lead, and the ring grew until
/// `loop-unstable` at 0.18 s; now 1399 -> 1749 -> 2187 us within 0.04 s. Reading the
/// ring's phase again instead left more runs tripping (32 and 52 of 117 undeclared servo
/// runs without a fault against 56; 66 with the step). Later rings are the guard's: an
/// axle's passage 2 s in, taken for one, stepped a stable lead out of its range
/// (`rths-fast-150kn` seed 6 from 504 us).
const RING_FOLLOW_UP_S: f64 = 0.25;
const RING_GROWN_AFTER_ARRIVAL: f64 = 4.0;
const RING_LEAD_UP: f64 = 1.25;

/// A ring at `w` with the lead `L` in effect where `w L` exceeds this (rad) is the
/// prediction's, not a lead too short: the order-2 prediction's gain `|1 + j w L - (w
/// L)^2 / 2|` is 2.2 there, and a lead too short rings at the specimen's resonance on the
/// element with `w L` under about 1.6 (1.6 ms at 155 Hz). Such a ring moves the lead down
/// by `RING_LEAD_DOWN`, not up to the phase read there.
const RING_LEAD_TOO_LONG_RAD: f64 = 2.0;
const RING_LEAD_DOWN: f64 = 0.75;
/// Any ring's target below the lead (a lead too long stepped down, or a phase read below
/// it) is taken at this rate (s of lead per s; 244 us per sample at 4096 Hz), not at
/// `OSCILLATION_MAX_RATE`: a lead too long grows its ring at 200-250 Hz by e in a few ms.
/// The step moves the command by the stiffness times `(v + a L)` times the step (the
/// order-2 prediction's change): at 225 Hz and 5.25 ms on a 3 um ring, about 0.5 kN a
/// sample and 2.6 kN over a quarter step, mostly the too-long prediction's own
/// amplification of the ring taken out. Undeclared `fatigue-150kn` seed 5 from 5250 us
/// (effective delay 1.7 ms): at 0.1 s per s the quarter step took 13 ms and arrived at
/// 3937 us, still too long, with the guard reading 20 mJ; the ring's follow-up (four times
/// that) never came, and the ring grew until `loop-unstable` at 0.20 s. At this rate the
/// step takes 1.4 ms and arrives with 3 mJ; the ring that goes on passes four times that
/// and the follow-up steps on to 2953 us by 0.04 s; stable to the end (2.1 %). In-process, undeclared servo-hydraulic presets from 1.5 and 2 times
/// their delay, seeds 0-7 (2026-11-29): 27 of 48 without a fault against 24 (4 saved, 1
/// lost); the 117 runs from 0-504 us (66 without a fault), 180 `lag-delay` (141), 120
/// random servo-hydraulic and electrodynamic (106) and the 84 declared presets (84) the
/// same, their errors to 0.003 points.
const RING_DOWN_RATE: f64 = 1.0;
/// Independent residuals (`DelayEstimate::independent`) below which a delay estimate
/// neither moves the lead nor ends the safe start: its standard error, from so few, is
/// itself a guess. The first estimate after the warm-up rests on about one (70 samples
/// low-passed at 30 Hz); under emulator stalls of 2 periods every 4-16 ms it read 887 +-
/// 125 us against 265, and the lead followed it to 348 us, out of the shipped actuator's
/// stable leads, where the safe start's damping then stayed all run.
const MIN_INDEPENDENT: f64 = 3.0;

impl Compensator {
    pub fn new(cfg: CompensationConfig, dt_s: f64) -> Compensator {
        let lead_s = cfg
            .initial_delay_s
            .min(cfg.starting_lead_cap_s)
            .clamp(0.0, cfg.max_delay_s);
        // The safe start: full damping from the first command (`PassivityGuard`).
        let armed = cfg.adapt && cfg.adapt_lead && cfg.passivity_guard;
        let guard = GuardState {
            damping_ns_per_m: if armed { safe_start_damping(&cfg) } else { 0.0 },
            generated_j: 0.0,
            excused_j: 0.0,
            stall_bursts: 0,
            armed,
            onset_j: f64::INFINITY,
        };
        let compensation = Compensation {
            lead_s,
            added_damping_ns_per_m: guard.damping_ns_per_m,
            added_damping_corner_hz: cfg.guard_band_hz,
            ..Compensation::lead(lead_s, cfg.lead_order)
        };
        Compensator {
            cfg,
            dt_s,
            estimator: DelayEstimator::new(cfg.estimator_band_hz, cfg.estimator_memory_s, dt_s),
            guard: PassivityGuard::new(&cfg, dt_s),
            lead_s,
            gain: 1.0,
            last_sample_seq: None,
            last_values: (0.0, 0.0, 0.0),
            status: CompensationStatus {
                compensation,
                identified_delay_s: f64::NAN,
                identified_delay_sigma_s: f64::NAN,
                load_band: None,
                guard,
                sensor_noise_m: f64::NAN,
            },
            contact: ContactGain::new(lead_s, dt_s),
            missing_share: 0.0,
            missing_weight: 0.0,
            missing_decay: (-dt_s / cfg.estimator_memory_s.max(dt_s)).exp(),
            oscillation: OscillationDelay::new(
                (OSCILLATION_LOW_HZ, cfg.guard_band_top_hz),
                OSCILLATION_MEMORY_S,
                dt_s,
            ),
            load_band: LoadBandDelay::new(dt_s),
            replay_z_m: [0.0; 2],
            replay_velocity_lp: 0.0,
            replay_samples: 0,
            since_oscillation_move: u64::MAX,
            oscillation_target: None,
            ring_lead: None,
            ring_energy_at_arrival_j: f64::INFINITY,
            ring_target_avg: f64::NAN,
            last_estimate: None,
            nudge: cfg.nudge.map(|r| LeadNudge::new(r, dt_s)),
            nudge_target: None,
            noise: SensorNoise::new(),
        }
    }

    /// The share of the samples in the estimator's memory that no setpoint carried.
    pub fn missing_share(&self) -> f64 {
        if self.missing_weight > 0.0 {
            self.missing_share / self.missing_weight
        } else {
            0.0
        }
    }

    pub fn config(&self) -> &CompensationConfig {
        &self.cfg
    }

    pub fn status(&self) -> CompensationStatus {
        self.status
    }

    pub fn guard_activity(&self) -> GuardActivity {
        self.guard.activity
    }

    /// Every new sample of a rig, in any state, before `on_sample` (or `pause`): its
    /// sequence, the rig's measured and commanded force (NaN when it does not report them). With `adapt`, the
    /// actuator's gain is read from the first samples where the actuator has settled on the
    /// rig's command (`ContactGain::observe_commanded`), so the first commands already
    /// carry it.
    #[inline]
    pub fn observe_rig(&mut self, sample_seq: u64, measured_force_n: f64, commanded_force_n: f64) {
        if self.cfg.adapt {
            if let Some(gain) =
                self.contact
                    .observe_commanded(sample_seq, measured_force_n, commanded_force_n)
            {
                self.gain = gain;
            }
        }
    }

    /// Whether the controller may send its first command: with `adapt`, not while the
    /// gain is being read from the rig's own command (`ContactGain::observe_commanded`,
    /// at most `CONTACT_COMMANDED_SAMPLES` samples), so that the read never meets the
    /// controller's own commands and the run starts the same way whenever the first
    /// command would have come. Always true once true.
    #[inline]
    pub fn ready_to_command(&self) -> bool {
        !self.cfg.adapt || self.contact.commanded_read_over()
    }

    /// The rig left force control (a hold): the observers restart when it comes back.
    pub fn pause(&mut self) {
        self.last_sample_seq = None;
    }

    /// One setpoint in force control: the element's force and displacement at sample
    /// `sample_seq` and the force the rig measured there. Returns the compensation to send.
    #[inline]
    pub fn on_sample(
        &mut self,
        sample_seq: u64,
        displacement_m: f64,
        element_force_n: f64,
        measured_force_n: f64,
    ) -> Compensation {
        // A few samples without a setpoint (the emulator took two in one cycle, or stalled
        // briefly) are bridged by linear interpolation, as the emulator bridges missing
        // samples; a longer gap, or a sample out of order, restarts the estimator and the
        // guard's observer. (The straight lines of a bridge through noisy ends read, in a
        // near-static stretch, as a delay of several ms: the estimator's standard error,
        // counted honestly (`DelayEstimator::correlation`), keeps the lead from following
        // them; emulator stalls of 1-8 periods every 4-16 ms walked it from 252 to 1980 us
        // and into `displacement-out-of-range` before.)
        let gap = match self.last_sample_seq {
            Some(last) if sample_seq > last => sample_seq - last,
            _ => u64::MAX,
        };
        let now = (displacement_m, element_force_n, measured_force_n);
        self.noise.update(displacement_m, gap == 1);
        self.status.sensor_noise_m = self.noise.sigma_m().unwrap_or(f64::NAN);
        if self.cfg.passivity_guard {
            self.guard.set_energy_scale(self.noise.energy_scale());
        }
        // The missing share: `gap - 1` samples without a setpoint, then this one.
        let d = self.missing_decay;
        if gap == u64::MAX {
            self.missing_share = 0.0;
            self.missing_weight = 1.0 - d;
        } else {
            let missed = (gap - 1).min(1 << 20) as i32;
            self.missing_share = (1.0 - (1.0 - self.missing_share) * d.powi(missed)) * d;
            self.missing_weight = 1.0 - (1.0 - self.missing_weight) * d.powi(missed + 1);
        }
        if gap == u64::MAX || gap > MAX_BRIDGED_GAP {
            self.estimator.restart();
            // A stall: samples came again, later than the bridge reaches (not the first
            // after a hold, not one out of order).
            if self.cfg.passivity_guard && gap != u64::MAX {
                self.guard.restart_after_stall();
            } else {
                self.guard.restart();
            }
            self.oscillation.restart();
            self.load_band.restart();
            self.oscillation_target = None;
            self.ring_target_avg = f64::NAN;
            self.replay_samples = 0;
            if let Some(n) = &mut self.nudge {
                n.restart();
            }
            self.feed(now);
        } else {
            let (z0, e0, m0) = self.last_values;
            for j in 1..=gap {
                let w = j as f64 / gap as f64;
                self.feed((
                    z0 + w * (now.0 - z0),
                    e0 + w * (now.1 - e0),
                    m0 + w * (now.2 - m0),
                ));
            }
        }
        self.last_sample_seq = Some(sample_seq);
        self.last_values = now;
        self.status.compensation = Compensation {
            lead_s: self.lead_s,
            added_damping_ns_per_m: self.status.guard.damping_ns_per_m,
            added_damping_corner_hz: self.cfg.guard_band_hz,
            gain: self.gain,
            lead_order: self.cfg.lead_order,
            reserved: 0,
        };
        self.status.compensation
    }

    /// One rig sample (measured or bridged) through the estimator and the guard.
    #[inline]
    fn feed(&mut self, (displacement_m, element_force_n, measured_force_n): (f64, f64, f64)) {
        if self.cfg.adapt {
            let own = measured_force_n * self.gain;
            if let Some(gain) = self.contact.observe(own / element_force_n, element_force_n) {
                self.gain = gain;
            }
            if self.guard.armed() || self.oscillation_target.is_some() || self.ring_follow_up() {
                let asked = self.asked_without_lead(displacement_m, element_force_n);
                let o = self.oscillation.update(asked, own, self.lead_s);
                self.follow_oscillation(o);
            }
            self.since_oscillation_move = self.since_oscillation_move.saturating_add(1);
            // The estimate after the last whole segment: None again when the load stops
            // exciting enough bins coherently (never an old estimate kept as the current).
            if self.load_band.update(element_force_n, own, self.lead_s) {
                self.status.load_band = self.load_band.estimate();
            }
            // The rig divided by the gain in effect: the actuator's own force per command
            // is the measured force times that gain.
            if let Some(e) =
                self.estimator
                    .update(element_force_n, measured_force_n * self.gain, self.lead_s)
            {
                self.adapt(e);
            }
        }
        let guard = if self.cfg.passivity_guard {
            self.guard.update(
                displacement_m,
                element_force_n,
                measured_force_n,
                self.lead_s,
            )
        } else {
            GuardState {
                onset_j: f64::NAN,
                ..GuardState::default()
            }
        };
        self.status.guard = guard;
        self.nudge_lead(displacement_m, element_force_n);
    }

    /// The planned fixed lead's nudge (`nudge::LeadNudge`): a step asked for is taken at
    /// `OSCILLATION_MAX_RATE` (140 us in 1.4 ms), as a ring's target above the lead is.
    #[inline]
    fn nudge_lead(&mut self, displacement_m: f64, element_force_n: f64) {
        if self.cfg.adapt_lead {
            return;
        }
        let Some(n) = &mut self.nudge else {
            return;
        };
        if let Some(target) = n.update(displacement_m, element_force_n, self.lead_s) {
            self.nudge_target = Some(target);
        }
        if let Some(target) = self.nudge_target {
            let max_step = OSCILLATION_MAX_RATE * self.dt_s;
            if (target - self.lead_s).abs() <= max_step {
                self.lead_s = target;
                self.nudge_target = None;
            } else {
                self.lead_s += max_step.copysign(target - self.lead_s);
            }
        }
    }

    /// Steps the planned fixed lead's nudge took (`nudge::LeadNudge`).
    pub fn lead_nudges(&self) -> u32 {
        self.nudge.map_or(0, |n| n.steps)
    }

    /// The force the rig was asked for, as it would be without the lead: the element's
    /// force plus the guard's damping in effect times the velocity high-passed as the rig
    /// does it (`Servo::law_force_n`: the second-order slope of the last three
    /// displacements, less its first-order low-pass at the damping's corner). The damping
    /// is a quarter period ahead of the displacement, so leaving it out of the reference
    /// reads the safe start's full damping (0.7 of the element's force at 155 Hz) as a
    /// phase lead of a third of a radian.
    #[inline]
    fn asked_without_lead(&mut self, displacement_m: f64, element_force_n: f64) -> f64 {
        let [z1, z2] = self.replay_z_m;
        self.replay_z_m = [displacement_m, z1];
        if self.replay_samples < 2 {
            self.replay_samples += 1;
            self.replay_velocity_lp = 0.0;
            return element_force_n;
        }
        let v = (3.0 * displacement_m - 4.0 * z1 + z2) / (2.0 * self.dt_s);
        let corner = self.cfg.guard_band_hz;
        let v_hp = v - self.replay_velocity_lp;
        let a = 1.0 - (-2.0 * std::f64::consts::PI * corner * self.dt_s).exp();
        self.replay_velocity_lp += a * (v - self.replay_velocity_lp);
        element_force_n + self.status.guard.damping_ns_per_m * v_hp
    }

    /// Whether the lead arrived at a ring's target less than `RING_FOLLOW_UP_S` ago.
    #[inline]
    fn ring_follow_up(&self) -> bool {
        self.ring_lead.is_some()
            && (self.since_oscillation_move as f64) * self.dt_s < RING_FOLLOW_UP_S
    }

    /// The safe start's answer to a loop that rings: when the guard's observer sees the
    /// loop generate energy beyond `RING_MIN_ENERGY_ONSETS` times its onset and one
    /// oscillation in 10-400 Hz explains the band over a full window
    /// (`OSCILLATION_MIN_FIT`), the phase delay at that oscillation's frequency, averaged
    /// over about a period of it (`RING_PERIODS_AVERAGED`), is taken as the lead's target,
    /// and the lead moves to it fast (`OSCILLATION_MAX_RATE`; down at `RING_DOWN_RATE`): there the loop crosses over, and that phase is what a lead
    /// must cancel for the loop to be passive (a guess of 0 before a 0.81 ms lag-delay
    /// actuator rang the resonance past the monitor's bound in 0.1 s, before the load
    /// band's estimator had warmed up). Within 10 % of the target the safe start ends
    /// (its full damping at that lead can itself generate energy) and the lead goes on to
    /// the target; there the window starts afresh, so a next reading is the new lead's
    /// alone (followed continuously, the ring that grew under the old lead dominated the
    /// window while it decayed under the new one, and the lead overshot to 0.95 ms and
    /// tripped), and the load band's estimator takes the lead on, never below the ring's
    /// lead and at most `RING_LEAD_RANGE` above it. A ring that grows on after the
    /// arrival steps the lead (`RING_FOLLOW_UP_S`).
    #[inline]
    fn follow_oscillation(&mut self, estimate: Option<OscillationEstimate>) {
        if let Some(target) = self.oscillation_target {
            let rate = if target < self.lead_s {
                RING_DOWN_RATE
            } else {
                OSCILLATION_MAX_RATE
            };
            let max_step = rate * self.dt_s;
            let step = (target - self.lead_s).clamp(-max_step, max_step);
            self.lead_s = (self.lead_s + step).clamp(0.0, self.cfg.max_delay_s);
            self.since_oscillation_move = 0;
            // Near the target the lead cancels the actuator's phase where the loop crosses
            // over: the safe start's precaution is answered, and kept it can itself be
            // what generates energy (the lag turns the full damping into energy above 300
            // Hz: a 0.81 ms actuator, lead 818 us, `loop-unstable` 50 ms later). The guard
            // goes on answering energy seen.
            if (target - self.lead_s).abs() <= SAFE_START_AGREEMENT * target {
                self.guard.disarm();
            }
            if (target - self.lead_s).abs() <= OSCILLATION_ARRIVED_S {
                self.ring_lead = Some(target);
                self.ring_energy_at_arrival_j = self.status.guard.generated_j;
                self.oscillation_target = None;
                self.oscillation.clear_window();
                self.ring_target_avg = f64::NAN;
            }
            return;
        }
        let Some(o) = estimate else {
            return;
        };
        let target_now = (o.window_lead_s + o.residual_s).clamp(0.0, self.cfg.max_delay_s);
        if o.window_full && target_now.is_finite() && o.frequency_hz.is_finite() {
            let a = (self.dt_s * o.frequency_hz * RING_PERIODS_AVERAGED).min(1.0);
            self.ring_target_avg = if self.ring_target_avg.is_finite() {
                self.ring_target_avg + a * (target_now - self.ring_target_avg)
            } else {
                target_now
            };
        }
        // After the safe start only the ring's follow-up reads (`RING_FOLLOW_UP_S`); the
        // energy gate below (`RING_MIN_ENERGY_ONSETS`) still applies.
        let after_start = !self.guard.armed();
        if after_start
            && (!self.ring_follow_up()
                || self.status.guard.generated_j
                    < RING_GROWN_AFTER_ARRIVAL * self.ring_energy_at_arrival_j)
        {
            return;
        }
        if self.cfg.adapt_lead
            && o.window_full
            && self.status.guard.generated_j >= RING_MIN_ENERGY_ONSETS * self.guard.onset_j()
            && o.fit >= OSCILLATION_MIN_FIT
            && (OSCILLATION_LOW_HZ..=self.cfg.guard_band_top_hz).contains(&o.frequency_hz)
        {
            // A ring where the prediction over the lead in effect amplifies more than
            // twice (`RING_LEAD_TOO_LONG_RAD`) is the prediction's own: the lead is too
            // long, and the phase read there points up, further away.
            let theta = 2.0 * std::f64::consts::PI * o.frequency_hz * o.window_lead_s;
            let target = if theta > RING_LEAD_TOO_LONG_RAD && self.ring_target_avg > self.lead_s {
                RING_LEAD_DOWN * o.window_lead_s
            } else if after_start {
                RING_LEAD_UP * o.window_lead_s
            } else {
                self.ring_target_avg
            };
            // Under the safe start a precise delay estimate on the other side of the lead
            // overrules the ring (`SAFE_START_FAST_RANGE`).
            let contradicted = self.guard.armed()
                && self.last_estimate.is_some_and(|e| {
                    safe_start_precise(e, self.cfg.max_delay_s)
                        && (target - self.lead_s) * (e.delay_s - self.lead_s) < 0.0
                });
            if contradicted {
                return;
            }
            if (target - self.lead_s).abs() > OSCILLATION_ARRIVED_S {
                self.oscillation_target = Some(target);
            }
        }
    }

    /// Ends the safe start once the estimate is precise (standard error within
    /// `SAFE_START_AGREEMENT` of the delay, or 20 us) and the lead agrees with it as far as
    /// the lead's bounds allow (within `SAFE_START_AGREEMENT`, 20 us or two standard
    /// errors, the estimate clamped to `[0, max_delay]`: an estimate beyond them leaves
    /// the lead at the bound, and waiting for more would keep the damping on all run).
    #[inline]
    fn end_safe_start(&mut self, e: DelayEstimate) {
        if !(self.guard.armed() && e.delay_s.is_finite() && e.delay_sigma_s.is_finite()) {
            return;
        }
        if e.independent < MIN_INDEPENDENT {
            return;
        }
        let target = e.delay_s.clamp(0.0, self.cfg.max_delay_s);
        let agrees =
            (target - self.lead_s).abs() <= safe_start_tolerance(target).max(2.0 * e.delay_sigma_s);
        if safe_start_precise(e, self.cfg.max_delay_s) && agrees {
            self.guard.disarm();
        }
    }

    /// Moves the lead and gain towards the estimate: a first-order step of `dt /
    /// adapt_time` of the difference, each step bounded (no jump the loop could feel).
    /// The gain, which the preload alone determines, follows as soon as the regression
    /// does; the lead only when the data resolve the delay (its standard error under
    /// 20 us, or under a quarter of the difference). The safe start ends as
    /// `end_safe_start` says (not while the identified gain is outside 0.5-2: such an
    /// actuator keeps the damping).
    #[inline]
    fn adapt(&mut self, e: DelayEstimate) {
        self.last_estimate = Some(e);
        self.status.identified_delay_s = e.delay_s;
        self.status.identified_delay_sigma_s = e.delay_sigma_s;
        if !(0.5..=2.0).contains(&e.residual_gain) {
            return;
        }
        let k = (self.dt_s / self.cfg.adapt_time_s).min(1.0);
        // At most 4 per second (0.1 % of the rendered stiffness per sample at 4096 Hz).
        let max_gain_step = 4.0 * self.dt_s;
        let gain_step = (k * (e.residual_gain - self.gain)).clamp(-max_gain_step, max_gain_step);
        self.gain = (self.gain + gain_step).clamp(0.5, 2.0);
        if !self.cfg.adapt_lead {
            return;
        }
        let difference = e.delay_s - self.lead_s;
        self.end_safe_start(e);
        // With too many bridged samples in the estimator's memory only a precise estimate
        // moves the lead (`MAX_MISSING_SHARE`): a far one is not followed on its distance.
        let far_enough =
            self.missing_share() <= MAX_MISSING_SHARE && e.delay_sigma_s < 0.25 * difference.abs();
        let resolved = e.delay_sigma_s.is_finite()
            && e.independent >= MIN_INDEPENDENT
            && (e.delay_sigma_s < 20e-6 || far_enough);
        if !resolved || !e.delay_s.is_finite() {
            return;
        }
        // While the ringing moves the lead, the load band waits (its window still holds
        // the ringing's samples).
        if (self.since_oscillation_move as f64) < OSCILLATION_MEMORY_S / self.dt_s {
            return;
        }
        // At most 20 ms of lead per second (5 us per sample at 4096 Hz): a servo-hydraulic
        // actuator a few ms slower than the first guess is reached within the first second.
        // Under the safe start a precise estimate near the lead is reached at the ring's
        // rate instead (`SAFE_START_FAST_RANGE`).
        let max_step = 20e-3 * self.dt_s;
        let step = if self.guard.armed()
            && safe_start_precise(e, self.cfg.max_delay_s)
            && difference.abs() <= SAFE_START_FAST_RANGE * self.lead_s
        {
            let fast = OSCILLATION_MAX_RATE * self.dt_s;
            difference.clamp(-fast, fast)
        } else {
            (k * difference).clamp(-max_step, max_step)
        };
        let (low, high) = match self.ring_lead {
            Some(r) => (r, (1.0 + RING_LEAD_RANGE) * r),
            None => (0.0, self.cfg.max_delay_s),
        };
        let lead = (self.lead_s + step).clamp(low, high);
        self.lead_s = lead.clamp(0.0, self.cfg.max_delay_s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    const DT: f64 = 1.0 / 4096.0;

    /// A force history rich in the load band: preload, 2 Hz and 11 Hz harmonics.
    fn element_force(t: f64) -> f64 {
        20e3 + 4e3 * (2.0 * PI * 2.0 * t).sin() + 1e3 * (2.0 * PI * 11.0 * t).sin()
    }

    #[test]
    fn estimator_finds_a_delay_and_gain() {
        for &(delay, gain) in &[(300e-6, 1.0), (2.5e-3, 0.9), (-150e-6, 1.1)] {
            // Rendered over a lead of 100 us: the estimate is the whole delay.
            let lead = 100e-6;
            let mut est = DelayEstimator::new(30.0, 0.5, DT);
            let mut last = None;
            for i in 0..(4096 * 3) {
                let t = i as f64 * DT;
                last = est.update(
                    element_force(t),
                    gain * element_force(t + lead - delay),
                    lead,
                );
            }
            let e = last.expect("determined");
            assert!(
                (e.delay_s - delay).abs() < 0.03 * delay.abs(),
                "{e:?} vs {delay}"
            );
            assert!((e.residual_gain - gain).abs() < 0.01, "{e:?} vs {gain}");
            assert!(e.delay_sigma_s < 0.1 * delay.abs());
        }
    }

    /// The compensator on a plant that renders the commanded force `d` late with gain `g`:
    /// the rendered force at `t` is `g F(t - d + lead)` (the rig predicted over the lead).
    #[test]
    fn the_lead_holds_while_too_many_samples_come_without_a_setpoint() {
        // The missing share against an independent count: one setpoint in three (two
        // samples missing each time) settles at 2/3.
        let cfg = CompensationConfig::with_initial_delay(0.0);
        let mut c = Compensator::new(cfg, DT);
        for k in 0..(4096 * 2) {
            c.on_sample(3 * k as u64, 0.0, 20e3, 20e3);
        }
        assert!(
            (c.missing_share() - 2.0 / 3.0).abs() < 0.01,
            "{}",
            c.missing_share()
        );
        // Every sample: it decays to 0 with the estimator's memory.
        for k in 0..(4096 * 3) {
            c.on_sample(3 * 4096 * 2 + k as u64, 0.0, 20e3, 20e3);
        }
        assert!(c.missing_share() < 1e-3, "{}", c.missing_share());

        // A plant 252 us late with a noisy load cell (+-125 N), a guess of 0: the
        // estimate's standard error (30-70 us) lies above 20 us, below a quarter of the
        // distance at first. With every twentieth setpoint missing (5 %) the lead follows
        // it on its distance (to 127 us, where a quarter of the distance meets the error);
        // with every fifth (20 %) it does not (9 us: what early, precise-looking estimates
        // moved it before the estimate settled).
        for (every, follows) in [(20u64, true), (5, false)] {
            let true_delay = 252e-6;
            let mut cfg = CompensationConfig::with_initial_delay(0.0);
            cfg.passivity_guard = false;
            let mut c = Compensator::new(cfg, DT);
            let mut comp = c.status().compensation;
            let mut state = 0x2545_f491_4f6c_dd1du64;
            for i in 0..(4096 * 2) {
                let t = i as f64 * DT;
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let noise = ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 250.0;
                let measured = element_force(t - true_delay + comp.lead_s) / comp.gain + noise;
                if i % every == every - 1 {
                    continue;
                }
                comp = c.on_sample(i, 0.0, element_force(t), measured);
            }
            let sigma = c.status().identified_delay_sigma_s;
            assert!((20e-6..70e-6).contains(&sigma), "{sigma}");
            if follows {
                assert!(comp.lead_s > 100e-6, "{comp:?}");
                assert!(c.missing_share() < MAX_MISSING_SHARE);
            } else {
                assert!(comp.lead_s < 20e-6, "{comp:?}");
                assert!(c.missing_share() > MAX_MISSING_SHARE);
            }
        }
    }

    #[test]
    fn adaptation_converges_from_a_guess_off_by_100_percent() {
        for &(true_delay, guess) in &[(252e-6, 0.0), (252e-6, 504e-6), (2.1e-3, 4.2e-3)] {
            let mut cfg = CompensationConfig::with_initial_delay(guess);
            cfg.passivity_guard = false;
            let mut c = Compensator::new(cfg, DT);
            let mut comp = c.status().compensation;
            // Settled within 2 s: the lead stays within 2 % from then on.
            for i in 0..(4096 * 4) {
                if i >= 4096 * 2 {
                    assert!(
                        (comp.lead_s - true_delay).abs() < 0.02 * true_delay,
                        "t = {} s: lead {} vs {true_delay}",
                        i as f64 * DT,
                        comp.lead_s
                    );
                }
                let t = i as f64 * DT;
                let measured = 0.95 * element_force(t - true_delay + comp.lead_s) / comp.gain;
                comp = c.on_sample(i as u64, 0.0, element_force(t), measured);
            }
            assert!(
                (comp.lead_s - true_delay).abs() < 0.02 * true_delay,
                "lead {} vs {true_delay}",
                comp.lead_s
            );
            assert!((comp.gain - 0.95).abs() < 0.01, "gain {}", comp.gain);
            let s = c.status();
            assert!((s.identified_delay_s - true_delay).abs() < 0.02 * true_delay);
        }
    }

    /// The gain follows the preload before the delay is resolved: a static load with a
    /// little noise leaves the delay undetermined (the lead stays at the guess) while the
    /// gain reaches the actuator's 0.8 within a second.
    #[test]
    fn the_gain_is_learned_from_the_preload_before_the_delay() {
        let guess = 300e-6;
        let mut cfg = CompensationConfig::with_initial_delay(guess);
        cfg.passivity_guard = false;
        let mut c = Compensator::new(cfg, DT);
        let mut comp = c.status().compensation;
        let mut state = 0x1234_5678_u64;
        for i in 0..4096 {
            // A uniform +-5 N of measurement noise on a 20 kN preload.
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let noise = ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 10.0;
            let measured = 0.8 * 20e3 / comp.gain + noise;
            comp = c.on_sample(i as u64, 0.0, 20e3, measured);
        }
        assert!((comp.gain - 0.8).abs() < 0.005, "gain {}", comp.gain);
        assert_eq!(comp.lead_s, guess);
    }

    /// The first contact: a static preload rendered with gain 0.75. The gain is taken at
    /// once, a few samples after the initial lead, while the estimator is still warming
    /// up; a ratio still moving (the actuator settling on its first command) is waited
    /// out, and a contact that never settles leaves the gain to the estimator.
    #[test]
    fn the_first_contact_reads_the_gain_at_once_and_only_when_settled() {
        let mut cfg = CompensationConfig::with_initial_delay(252e-6);
        cfg.passivity_guard = false;
        let mut c = Compensator::new(cfg, DT);
        let mut comp = c.status().compensation;
        let mut taken_at = None;
        for i in 0..40u64 {
            // The actuator settles on the command over the first 8 samples.
            let settling = if i < 8 {
                1.0 - (i as f64 / 8.0) * 0.25
            } else {
                0.75
            };
            let measured = settling * 20e3 / comp.gain;
            comp = c.on_sample(i, 0.0, 20e3, measured);
            if taken_at.is_none() && comp.gain != 1.0 {
                taken_at = Some(i);
            }
        }
        assert_eq!(comp.gain, 0.75, "gain {}", comp.gain);
        // Not before the ratio had settled (samples 8-10 agree).
        assert_eq!(taken_at, Some(10), "taken at {taken_at:?}");

        // A contact whose ratio keeps moving by 5 % a sample is never read.
        let mut c = Compensator::new(cfg, DT);
        let mut comp = c.status().compensation;
        for i in 0..60u64 {
            let ratio = if i % 2 == 0 { 0.75 } else { 0.79 };
            comp = c.on_sample(i, 0.0, 20e3, ratio * 20e3 / comp.gain);
        }
        assert_eq!(comp.gain, 1.0, "gain {}", comp.gain);
    }

    /// A rig of ABI 4 reports its commanded force: the gain is measured over commanded
    /// force on the first two samples that agree, before force control (the rig's servo
    /// holds the preload with a command of 20 kN / 0.74), so the very first command in
    /// force control divides by it; the element's force plays no part. A rig whose ratio
    /// keeps moving is not read this way, and one that does not report it (NaN) falls back
    /// to the contact read above.
    #[test]
    fn a_rig_that_reports_its_command_gives_the_gain_before_force_control() {
        let mut cfg = CompensationConfig::with_initial_delay(252e-6);
        cfg.passivity_guard = false;
        let mut c = Compensator::new(cfg, DT);
        let command = 20e3 / 0.74;
        // Sample 0 (the rig starting) and 1, under the rig's servo: ratio 0.74 twice. No
        // command before the read.
        assert!(!c.ready_to_command());
        c.observe_rig(0, 20e3, command);
        assert!(!c.ready_to_command());
        c.pause();
        c.observe_rig(1, 20e3 * (1.0 + 1e-4), command);
        assert!(c.ready_to_command());
        // The first sample in force control: the element's force says nothing of the gain.
        let comp = c.on_sample(2, 0.0, 25e3, 20e3);
        assert!((comp.gain - 0.74).abs() < 1e-4, "gain {}", comp.gain);

        // A ratio moving by 2 % a sample is not a settled actuator: no read.
        let mut c = Compensator::new(cfg, DT);
        for i in 0..60u64 {
            let ratio = if i % 2 == 0 { 0.74 } else { 0.755 };
            c.observe_rig(i, ratio * command, command);
        }
        assert_eq!(c.on_sample(0, 0.0, 20e3, 20e3).gain, 1.0);

        // Nor is a ramping command, though a lagging actuator's ratio barely moves
        // (1 % more command a sample, the ratio 0.74 within 0.1 %), nor two samples that
        // are not consecutive.
        let mut c = Compensator::new(cfg, DT);
        for i in 0..60u64 {
            let ramp = command * (1.0 + 0.01 * i as f64);
            c.observe_rig(i, 0.74 * (1.0 + 1e-3 * (i % 2) as f64) * ramp, ramp);
        }
        assert_eq!(c.on_sample(0, 0.0, 20e3, 20e3).gain, 1.0);
        let mut c = Compensator::new(cfg, DT);
        c.observe_rig(0, 20e3, command);
        c.observe_rig(2, 20e3, command);
        assert_eq!(c.on_sample(3, 0.0, 20e3, 20e3).gain, 1.0);

        // Only the first CONTACT_COMMANDED_SAMPLES samples are read (the controller waits
        // for them, then commands): a pair that agrees later is the transient of force
        // control, not the actuator at rest. A sample without a measured force counts.
        let mut c = Compensator::new(cfg, DT);
        for i in 0..CONTACT_COMMANDED_SAMPLES as u64 {
            assert!(!c.ready_to_command(), "{i}");
            let measured = if i == 1 {
                f64::NAN
            } else {
                0.74 + 0.02 * i as f64
            };
            c.observe_rig(i, measured * command, command);
        }
        assert!(c.ready_to_command());
        c.observe_rig(4, 0.92 * command, command);
        c.observe_rig(5, 0.92 * command, command);
        assert_eq!(c.on_sample(6, 0.0, 20e3, 20e3).gain, 1.0);

        // A rig whose first sample reports no command is not read from its command at all
        // (the controller commands at once; later agreeing samples are force control's).
        let mut c = Compensator::new(cfg, DT);
        c.observe_rig(0, 20e3, f64::NAN);
        assert!(c.ready_to_command());
        c.observe_rig(1, 0.74 * command, command);
        c.observe_rig(2, 0.74 * command, command);
        assert_eq!(c.on_sample(3, 0.0, 20e3, 20e3).gain, 1.0);

        // No command reported: nothing to wait for, and the contact read of the first
        // stretch decides (0.8 here).
        let mut c = Compensator::new(cfg, DT);
        let mut comp = c.status().compensation;
        for i in 0..20u64 {
            c.observe_rig(i, 0.8 * 20e3 / comp.gain, f64::NAN);
            assert!(c.ready_to_command());
            comp = c.on_sample(i, 0.0, 20e3, 0.8 * 20e3 / comp.gain);
        }
        assert!((comp.gain - 0.8).abs() < 1e-12, "gain {}", comp.gain);

        // Without adaptation the gain stays 1.
        let mut fixed = cfg;
        fixed.adapt = false;
        let mut c = Compensator::new(fixed, DT);
        c.observe_rig(0, 20e3, command);
        c.observe_rig(1, 20e3, command);
        assert_eq!(c.on_sample(0, 0.0, 20e3, 20e3).gain, 1.0);
    }

    /// Sample `i` of a 5 um, 155 Hz ring on the preload's 0.3 mm, `late_s` late.
    fn ring_z(i: usize, late_s: f64) -> f64 {
        3e-4 + 5e-6 * (2.0 * PI * 155.0 * (i as f64 * DT - late_s)).sin()
    }

    #[test]
    fn guard_adds_damping_only_while_energy_is_generated() {
        // Without adaptation there is no safe start: the energy alone decides.
        let cfg = CompensationConfig {
            adapt: false,
            ..CompensationConfig::with_initial_delay(0.0)
        };
        let mut g = PassivityGuard::new(&cfg, DT);
        let k = 5.7e7;
        // A passive rendering: no damping.
        for i in 0..4096 {
            let z = ring_z(i, 0.0);
            let s = g.update(z, k * z, k * z, 0.0);
            assert_eq!(s.damping_ns_per_m, 0.0);
        }
        // 200 us late at 155 Hz: energy generated, damping rises.
        let mut max_d: f64 = 0.0;
        for i in 4096..8192 {
            let (z, zl) = (ring_z(i, 0.0), ring_z(i, 2e-4));
            max_d = max_d.max(g.update(z, k * z, k * zl, 0.0).damping_ns_per_m);
        }
        assert!(max_d > 0.5 * cfg.guard_max_damping_ns_per_m, "{max_d}");
        assert!(g.activity.active_samples > 0);
        assert!(g.activity.dissipated_j > 0.0);
        // Passive again: released with its time constant (e^-4 after 4 time constants).
        let n = (4.0 * cfg.guard_release_s / DT) as usize + 1024;
        let mut last = f64::NAN;
        for i in 0..n {
            let z = ring_z(8192 + i, 0.0);
            last = g.update(z, k * z, k * z, 0.0).damping_ns_per_m;
        }
        assert!(last < 0.03 * max_d, "{last}");
    }

    /// After a stall (`restart_after_stall`), a burst of energy that ends within the window
    /// (`STALL_BURST_S`) adds no damping, where the same burst after a plain restart does;
    /// a loop that keeps generating is answered once the window is over, from the burst's
    /// level, within two of the ring's periods; energy beyond `guard_full_energy_j` is
    /// answered inside the window; a second stall within `STALL_BURST_SPACING_S` of the
    /// first is not excused.
    #[test]
    fn a_stalls_burst_is_excused_and_a_loop_generating_beyond_it_is_not() {
        let cfg = CompensationConfig {
            adapt: false,
            ..CompensationConfig::with_initial_delay(0.0)
        };
        let k = 5.7e7;
        let window = (STALL_BURST_S / DT).round() as usize;
        // The ring passive, then (from sample 2048) 200 us late for `burst` samples, then
        // passive again; the guard restarted at sample 2048 by a stall or plainly.
        let run = |after_stall: bool, burst: usize| {
            let mut g = PassivityGuard::new(&cfg, DT);
            let (mut first_damped, mut max_generated) = (None, 0.0f64);
            for i in 0..6144 {
                if i == 2048 {
                    if after_stall {
                        g.restart_after_stall();
                    } else {
                        g.restart();
                    }
                }
                let late = if (2048..2048 + burst).contains(&i) {
                    2e-4
                } else {
                    0.0
                };
                let z = ring_z(i, 0.0);
                let s = g.update(z, k * z, k * ring_z(i, late), 0.0);
                max_generated = max_generated.max(s.generated_j);
                if s.damping_ns_per_m > 0.0 && first_damped.is_none() {
                    first_damped = Some(i);
                }
            }
            (first_damped, max_generated, g.activity)
        };
        // A burst of 40 samples (a ring period and a half) generates beyond the onset.
        let (plain, generated, _) = run(false, 40);
        assert!(generated > 2.0 * cfg.guard_onset_energy_j, "{generated}");
        assert!(plain.is_some_and(|i| i < 2048 + 40), "{plain:?}");
        let (excused, generated_stall, activity) = run(true, 40);
        assert_eq!(excused, None);
        assert_eq!(generated_stall, generated);
        assert_eq!(activity.stall_bursts, 1);
        assert!(activity.max_stall_burst_j > cfg.guard_onset_energy_j);
        assert_eq!(activity.active_samples, 0);
        // Beyond `guard_full_energy_j` the burst is answered inside the window: a ring of
        // 15 um, 200 us late, generates 7.8 mJ per period.
        let mut g = PassivityGuard::new(&cfg, DT);
        let mut answered_at = None;
        for i in 0..4096 {
            if i == 2048 {
                g.restart_after_stall();
            }
            let big = |late| 3e-4 + 3.0 * (ring_z(i, late) - 3e-4);
            let s = g.update(
                big(0.0),
                k * big(0.0),
                k * big(if i >= 2048 { 2e-4 } else { 0.0 }),
                0.0,
            );
            if s.damping_ns_per_m > 0.0 && answered_at.is_none() {
                answered_at = Some(i);
                assert!(s.generated_j > cfg.guard_full_energy_j, "{}", s.generated_j);
                assert_eq!(s.excused_j, cfg.guard_full_energy_j);
            }
        }
        let at = answered_at.expect("a burst beyond the full energy was not answered");
        assert!(at < 2048 + window, "{at}");
        // A second stall 0.1 s after the first is not excused (`STALL_BURST_SPACING_S`).
        let mut g = PassivityGuard::new(&cfg, DT);
        let mut damped = false;
        for i in 0..4096 {
            if i == 1000 || i == 1000 + 410 {
                g.restart_after_stall();
            }
            let burst = (1000..1040).contains(&i) || (1410..1450).contains(&i);
            let z = ring_z(i, 0.0);
            let s = g.update(z, k * z, k * ring_z(i, if burst { 2e-4 } else { 0.0 }), 0.0);
            damped |= s.damping_ns_per_m > 0.0;
        }
        assert!(
            damped,
            "the second burst, 0.1 s after the first, was excused"
        );
        assert_eq!(g.activity.stall_bursts, 1);
        // Generating on: answered after the window, within two periods of 155 Hz.
        let (answered, _, _) = run(true, 4096);
        let period = (1.0 / (155.0 * DT)).ceil() as usize;
        let at = answered.expect("no damping for a loop generating on");
        assert!(
            at >= 2048 + window && at <= 2048 + window + 2 * period,
            "{at}"
        );
    }

    /// A safe start with less than the full damping (`check::safe_start_damping_ns_per_m`)
    /// holds that much while the loop is passive and adds up to the full damping while it
    /// generates energy, armed all the while.
    #[test]
    fn a_reduced_safe_start_rises_with_the_energy_generated() {
        let cfg = CompensationConfig {
            safe_start_damping_ns_per_m: 10e3,
            ..CompensationConfig::with_initial_delay(900e-6)
        };
        let mut g = PassivityGuard::new(&cfg, DT);
        let k = 5.7e7;
        for i in 0..4096 {
            let z = ring_z(i, 0.0);
            let s = g.update(z, k * z, k * z, 0.0);
            assert!(s.armed);
            assert_eq!(s.damping_ns_per_m, 10e3);
        }
        let mut max_d: f64 = 0.0;
        for i in 4096..8192 {
            let (z, zl) = (ring_z(i, 0.0), ring_z(i, 2e-4));
            let s = g.update(z, k * z, k * zl, 0.0);
            assert!(s.armed && s.damping_ns_per_m >= 10e3);
            max_d = max_d.max(s.damping_ns_per_m);
        }
        assert!(max_d > 0.5 * cfg.guard_max_damping_ns_per_m, "{max_d}");
        assert!(max_d <= cfg.guard_max_damping_ns_per_m);
    }

    /// The safe start: with `adapt`, the guard holds its full damping from the first
    /// sample until the lead agrees with the delay the estimator resolved (a guess of 0 in
    /// front of a 722 us actuator), then the energy decides: none here, so none is added
    /// and the guard does not arm again. Without `adapt` it never arms.
    #[test]
    fn the_guard_is_armed_until_the_lead_is_learned() {
        let true_delay = 722e-6;
        let cfg = CompensationConfig::with_initial_delay(0.0);
        let mut c = Compensator::new(cfg, DT);
        let mut comp = c.status().compensation;
        let mut disarmed_at = None;
        for i in 0..(4096 * 3) {
            let t = i as f64 * DT;
            let measured = element_force(t - true_delay + comp.lead_s) / comp.gain;
            comp = c.on_sample(i as u64, 0.0, element_force(t), measured);
            let armed = c.status().guard.armed;
            match disarmed_at {
                None if armed => {
                    assert_eq!(comp.added_damping_ns_per_m, cfg.guard_max_damping_ns_per_m)
                }
                None => {
                    disarmed_at = Some(t);
                    assert!(
                        (comp.lead_s - true_delay).abs() < 0.11 * true_delay,
                        "disarmed at {t} s with a lead of {} us",
                        comp.lead_s * 1e6
                    );
                    assert_eq!(comp.added_damping_ns_per_m, 0.0);
                }
                Some(_) => {
                    assert!(!armed, "armed again at {t} s");
                    assert_eq!(comp.added_damping_ns_per_m, 0.0);
                }
            }
        }
        let t = disarmed_at.expect("the guard was never disarmed");
        assert!(t > 0.1 && t < 1.5, "disarmed at {t} s");
        // Disarmed, the guard still answers energy: the rendering 200 us late at the
        // resonance (the specimen moving this time) gets damping again.
        let k = 5.7e7;
        let mut most: f64 = 0.0;
        for i in 0..4096 {
            let t = (4096 * 3 + i) as f64 * DT;
            let z = 3e-4 + 5e-6 * (2.0 * PI * 155.0 * t).sin();
            let late = 3e-4 + 5e-6 * (2.0 * PI * 155.0 * (t - 2e-4)).sin();
            let comp = c.on_sample((4096 * 3 + i) as u64, z, k * z, k * late / comp.gain);
            assert!(!c.status().guard.armed);
            most = most.max(comp.added_damping_ns_per_m);
        }
        assert!(most > 0.5 * cfg.guard_max_damping_ns_per_m, "{most}");

        let mut c = Compensator::new(
            CompensationConfig {
                adapt: false,
                ..cfg
            },
            DT,
        );
        for i in 0..4096 {
            let t = i as f64 * DT;
            let comp = c.on_sample(i as u64, 0.0, element_force(t), element_force(t - 1e-4));
            assert!(!c.status().guard.armed);
            assert_eq!(comp.added_damping_ns_per_m, 0.0);
        }
    }
}
