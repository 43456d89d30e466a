//! The planned fixed lead's nudge: when the plan fixed the lead (`check::compensation_plan`,
//! a servo-hydraulic force loop) and the loop keeps oscillating instead of ringing down,
//! the lead steps towards the side the oscillation's frequency names, within the leads
//! the plan found stable for some actuator within the tolerance. Owns only the detection
//! (a band-passed displacement's block peaks and zero crossings); the compensator moves
//! the lead.
//!
//! Why: no fixed lead is stable for every actuator the tolerance allows (`fatigue-150kn`'s
//! draw of seed 11 needs 2890-5370 us, seed 8 1800-2870 us), and the linearised loop says
//! which way a lead is wrong by where the loop goes unstable: too short at the force
//! loop's crossover (18-51 Hz for the three servo-hydraulic presets over seeds 0-15), too
//! long near the oil column's and the specimen's resonances (171-475 Hz). A ring that an
//! axle starts in a stable loop dies away within a few of its periods; one that keeps its
//! amplitude over `NUDGE_BLOCKS` blocks is a loop at or past its edge.
//!
//! Must not: allocate, lock, log, read a clock or do I/O (runs per rig sample in the
//! controller's loop); the same sample stream gives the same steps bit for bit.

use crate::hil::passivity::{HighPass2, LowPass2};

/// What the plan allows the nudge (`CompensationConfig::nudge`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NudgeRange {
    /// The leads the nudge may reach: the lowest and the highest lead stable for some
    /// actuator within the tolerance, s.
    pub low_s: f64,
    pub high_s: f64,
    /// Below this frequency an oscillation says the lead is too short, above it too long
    /// (the geometric mean of the highest frequency a lead too short goes unstable at and
    /// the lowest a lead too long does, over the plan's actuators), Hz.
    pub split_hz: f64,
}

/// Blocks of this length (about a period at a servo loop's crossover, 20-50 Hz), s.
const NUDGE_BLOCK_S: f64 = 0.03;
/// Blocks an oscillation must keep its amplitude over (120 ms).
const NUDGE_BLOCKS: usize = 4;
/// Each block's peak at least this share of the largest of them: kept, not dying away
/// (a ring that halves every 50 ms, as an axle's does in a stable planned run, falls to
/// 0.25 over three blocks).
const NUDGE_SUSTAIN: f64 = 0.7;
/// The smallest peak that counts (the band-passed programme and the sensor stay below).
const NUDGE_FLOOR_M: f64 = 20e-6;
/// Each step: this share of the lead in effect (about 140 us at 2.85 ms).
const NUDGE_STEP: f64 = 0.05;
/// After a step, the loop is given this long to ring down before another.
const NUDGE_REFRACTORY_S: f64 = 0.25;
/// Steps per run at most: the detector cannot tell a loop at its edge from a programme
/// that itself drives 10-600 Hz for 120 ms and more (a sine or sweep there), which would
/// otherwise walk the lead to the end of the range, 0.37 s a step. Three steps (about
/// 15 %) keep such a programme within the planned lead's neighbourhood; the rigs that
/// needed a step took one or two.
const NUDGE_MAX_STEPS: u32 = 3;
/// The band the displacement is watched in, Hz: above the programme's harmonics, below
/// the sensor's noise.
const NUDGE_BAND_HZ: (f64, f64) = (10.0, 600.0);
/// The programme's own drive: while the element's force, low-passed at `NUDGE_LOAD_HZ`
/// (second order), changes faster than `NUDGE_LOAD_RATE_N_PER_S`, and for
/// `NUDGE_LOAD_HOLD_S` after, no block counts: an axle's passage drives the band itself,
/// and a loop at its edge is one that keeps oscillating under a quiet load. The default
/// programme (`fatigue-150kn` seed 202, `fastemu hil`, 2026-11-28): 57-155 kN/s outside
/// the axles (the 2 Hz harmonic, the loop's own rings filtered out: a 38 Hz ring of 50 um
/// passes as about 50 kN/s, a 20 Hz one as 90 kN/s), 3.4 MN/s in their passage at 2.0-2.4
/// s, whose 30-90 Hz content of 50-65 um met the sustain rule, read as a lead too short,
/// and stepped the lead from 2850 to 2992 us, away from the truth's stable leads
/// (2020-2620 us); its 230 Hz mode then grew and tripped `loop-unstable` at 3.66 s.
const NUDGE_LOAD_HZ: f64 = 10.0;
const NUDGE_LOAD_RATE_N_PER_S: f64 = 1.0e6;
const NUDGE_LOAD_HOLD_S: f64 = 0.1;

/// The detector (`LeadNudge::update`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LeadNudge {
    range: NudgeRange,
    dt_s: f64,
    high_pass: HighPass2,
    low_pass: LowPass2,
    block_len: u32,
    block_samples: u32,
    block_peak_m: f64,
    block_crossings: u32,
    last_value: f64,
    /// The last `NUDGE_BLOCKS` blocks' peaks and zero crossings (a ring).
    peaks_m: [f64; NUDGE_BLOCKS],
    crossings: [u32; NUDGE_BLOCKS],
    blocks: usize,
    /// Samples left before the filters have settled, or the loop has rung down after a
    /// step.
    wait: u32,
    /// The element's force low-passed (`NUDGE_LOAD_HZ`), its last value, and the samples
    /// left while the programme drives the band (`NUDGE_LOAD_RATE_N_PER_S`).
    load_lp: LowPass2,
    last_load_n: f64,
    loud: u32,
    /// Steps taken.
    pub steps: u32,
}

impl LeadNudge {
    pub fn new(range: NudgeRange, dt_s: f64) -> LeadNudge {
        LeadNudge {
            range,
            dt_s,
            high_pass: HighPass2::high_pass(NUDGE_BAND_HZ.0, dt_s),
            low_pass: LowPass2::low_pass(NUDGE_BAND_HZ.1.min(0.45 / dt_s), dt_s),
            block_len: (NUDGE_BLOCK_S / dt_s).round().max(1.0) as u32,
            block_samples: 0,
            block_peak_m: 0.0,
            block_crossings: 0,
            last_value: 0.0,
            peaks_m: [0.0; NUDGE_BLOCKS],
            crossings: [0; NUDGE_BLOCKS],
            blocks: 0,
            wait: (NUDGE_REFRACTORY_S / dt_s) as u32,
            load_lp: LowPass2::low_pass(NUDGE_LOAD_HZ, dt_s),
            last_load_n: f64::NAN,
            loud: 0,
            steps: 0,
        }
    }

    /// Forgets the blocks (a gap in the samples, a hold); the filters settle again.
    pub fn restart(&mut self) {
        *self = LeadNudge {
            steps: self.steps,
            ..LeadNudge::new(self.range, self.dt_s)
        };
    }

    /// One rig sample's displacement and the element's force there, with the lead in
    /// effect; returns the lead to move to when the loop keeps oscillating under a quiet
    /// load (one step, within the range), once per `NUDGE_REFRACTORY_S`.
    #[inline]
    pub fn update(
        &mut self,
        displacement_m: f64,
        element_force_n: f64,
        lead_s: f64,
    ) -> Option<f64> {
        if self.steps >= NUDGE_MAX_STEPS {
            return None;
        }
        let y = self.low_pass.step(self.high_pass.step(displacement_m));
        if self.last_load_n.is_nan() {
            self.load_lp.reset(element_force_n);
            self.last_load_n = element_force_n;
        }
        let load = self.load_lp.step(element_force_n);
        if ((load - self.last_load_n) / self.dt_s).abs() > NUDGE_LOAD_RATE_N_PER_S {
            self.loud = (NUDGE_LOAD_HOLD_S / self.dt_s) as u32;
        }
        self.last_load_n = load;
        if self.wait > 0 {
            self.wait -= 1;
            self.last_value = y;
            return None;
        }
        if self.loud > 0 {
            // The programme drives the band: the blocks start afresh after it.
            self.loud -= 1;
            self.last_value = y;
            self.blocks = 0;
            self.block_samples = 0;
            self.block_peak_m = 0.0;
            self.block_crossings = 0;
            return None;
        }
        if (y > 0.0) != (self.last_value > 0.0) {
            self.block_crossings += 1;
        }
        self.last_value = y;
        self.block_peak_m = self.block_peak_m.max(y.abs());
        self.block_samples += 1;
        if self.block_samples < self.block_len {
            return None;
        }
        let slot = self.blocks % NUDGE_BLOCKS;
        self.peaks_m[slot] = self.block_peak_m;
        self.crossings[slot] = self.block_crossings;
        self.blocks += 1;
        self.block_samples = 0;
        self.block_peak_m = 0.0;
        self.block_crossings = 0;
        if self.blocks < NUDGE_BLOCKS {
            return None;
        }
        let (mut low, mut high) = (f64::INFINITY, 0.0f64);
        for &p in &self.peaks_m {
            low = low.min(p);
            high = high.max(p);
        }
        if low < NUDGE_FLOOR_M || low < NUDGE_SUSTAIN * high {
            return None;
        }
        let crossings: u32 = self.crossings.iter().sum();
        let span_s = (NUDGE_BLOCKS as u32 * self.block_len) as f64 * self.dt_s;
        let frequency_hz = f64::from(crossings) / (2.0 * span_s);
        let step = NUDGE_STEP * lead_s.max(self.range.low_s);
        let target = if frequency_hz < self.range.split_hz {
            lead_s + step
        } else {
            lead_s - step
        }
        .clamp(self.range.low_s, self.range.high_s);
        self.restart();
        if target == lead_s {
            return None;
        }
        self.steps += 1;
        Some(target)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    const DT: f64 = 1.0 / 4096.0;
    const RANGE: NudgeRange = NudgeRange {
        low_s: 2.0e-3,
        high_s: 5.0e-3,
        split_hz: 100.0,
    };

    /// Feeds `secs` of `z(t)`; returns the first target and when it came.
    fn first_step(z: impl Fn(f64) -> f64, secs: f64, lead_s: f64) -> Option<(f64, f64)> {
        let mut n = LeadNudge::new(RANGE, DT);
        (0..(secs / DT) as usize).find_map(|i| {
            let t = i as f64 * DT;
            n.update(z(t), 20e3, lead_s).map(|target| (t, target))
        })
    }

    /// A sustained 33 Hz oscillation of 0.2 mm on a 2 Hz motion (a lead too short at a
    /// servo loop's crossover): one step of 5 % up, after the settling wait and four
    /// blocks; at 250 Hz (a lead too long) one step down; clamped to the range.
    #[test]
    fn a_sustained_oscillation_steps_the_lead_the_way_its_frequency_says() {
        let slow = |t: f64| 0.4e-3 + 0.075e-3 * (2.0 * PI * 2.0 * t).sin();
        let low = |t: f64| slow(t) + 0.2e-3 * (2.0 * PI * 33.0 * t).sin();
        let (at, target) = first_step(low, 1.0, 2.85e-3).expect("a step");
        assert!((target - 2.85e-3 * 1.05).abs() < 1e-12, "{target}");
        // The wait (0.25 s) plus four 30 ms blocks, within a block.
        assert!((0.36..0.40).contains(&at), "{at}");
        let high = |t: f64| slow(t) + 0.05e-3 * (2.0 * PI * 250.0 * t).sin();
        let (_, target) = first_step(high, 1.0, 2.85e-3).expect("a step");
        assert!((target - 2.85e-3 * 0.95).abs() < 1e-12, "{target}");
        let (_, target) = first_step(low, 1.0, 4.9e-3).expect("a step");
        assert_eq!(target, RANGE.high_s);
        // At the range's end already: nothing to move.
        assert_eq!(first_step(low, 1.0, RANGE.high_s), None);
        // However long it goes on, three steps at most.
        let mut n = LeadNudge::new(RANGE, DT);
        let mut lead = 2.5e-3;
        for i in 0..(3.0 / DT) as usize {
            if let Some(t) = n.update(low(i as f64 * DT), 20e3, lead) {
                lead = t;
            }
        }
        assert_eq!(n.steps, NUDGE_MAX_STEPS);
        assert!((lead - 2.5e-3 * 1.05f64.powi(3)).abs() < 1e-12, "{lead}");
    }

    /// An oscillation the programme drives: axle-like pulses of 50 kN in 40 ms every 0.1 s
    /// from 0.3 to 0.8 s, with a 33 Hz oscillation of 0.2 mm while they last, steps
    /// nothing (without the load's gate it stepped at 0.43 s); the same oscillation going
    /// on after the pulses, under a quiet load, steps the lead once the gate's 0.1 s after
    /// the last pulse and four blocks have passed.
    #[test]
    fn an_oscillation_the_programme_drives_does_not_step_the_lead() {
        let load = |t: f64| {
            let since = (t - 0.3) % 0.1;
            if (0.3..0.8).contains(&t) && since < 0.04 {
                20e3 + 25e3 * (1.0 - (2.0 * PI * since / 0.04).cos())
            } else {
                20e3
            }
        };
        let z = |t: f64, until: f64| {
            0.4e-3
                + if (0.3..until).contains(&t) {
                    0.2e-3 * (2.0 * PI * 33.0 * t).sin()
                } else {
                    0.0
                }
        };
        let run = |until: f64, gated: bool| {
            let mut n = LeadNudge::new(RANGE, DT);
            (0..(2.0 / DT) as usize).find_map(|i| {
                let t = i as f64 * DT;
                let f = if gated { load(t) } else { 20e3 };
                n.update(z(t, until), f, 2.85e-3).map(|_| t)
            })
        };
        assert_eq!(run(0.8, true), None);
        let ungated = run(0.8, false).expect("a step without the gate");
        assert!(ungated < 0.8, "{ungated}");
        let after = run(2.0, true).expect("a step under the quiet load");
        // The last pulse ends at 0.74 s; the gate's 0.1 s, then four 30 ms blocks.
        assert!(
            (0.74 + 0.1 + 0.1..0.74 + 0.1 + 0.16).contains(&after),
            "{after}"
        );
    }

    /// What a stable planned loop does at an axle: a ring at 38 Hz of 80 um that halves
    /// every 50 ms, every 0.25 s; the programme's 2 Hz motion alone; an oscillation below
    /// the floor. None of them moves the lead.
    #[test]
    fn rings_that_die_away_and_small_ones_do_not() {
        let slow = |t: f64| 0.4e-3 + 0.075e-3 * (2.0 * PI * 2.0 * t).sin();
        let ringing = |t: f64| {
            let since = t % 0.25;
            slow(t) + 80e-6 * (-since * 2f64.ln() / 0.05).exp() * (2.0 * PI * 38.0 * since).sin()
        };
        assert_eq!(first_step(ringing, 3.0, 2.85e-3), None);
        assert_eq!(first_step(slow, 3.0, 2.85e-3), None);
        let small = |t: f64| slow(t) + 10e-6 * (2.0 * PI * 33.0 * t).sin();
        assert_eq!(first_step(small, 3.0, 2.85e-3), None);
    }
}
