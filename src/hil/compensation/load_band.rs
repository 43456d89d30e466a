//! The actuator's effective delay over the load band (1-20 Hz), identified online the way
//! the report reads it from the record and the rig's truth defines it: at each 1 Hz bin,
//! the phase of the force the actuator rendered per element force, less the lead it was
//! rendered with, over the frequency; their mean over the bins the load excites. Owns only
//! the spectra; the compensator feeds it and reports the estimate (it moves no lead: a
//! servo-hydraulic force loop's delay varies over the band, and the lead that keeps the loop
//! stable is not the band's mean).
//!
//! Must not: allocate, lock, log, read a clock or do I/O (runs per rig sample in the
//! controller's loop); the same sample stream gives the same estimate bit for bit.

use realfft::num_complex::Complex64;
use std::f64::consts::PI;

/// Bins of the load band: 1-20 Hz at 1 Hz.
pub const LOAD_BAND_BINS: usize = 20;
/// Rectangular bins accumulated: 1-21 Hz (the Hann window's bin `k` takes `k - 1`, `k` and
/// `k + 1`; bin 0, the mean, is removed).
const RECT: usize = LOAD_BAND_BINS + 1;
/// The rules this estimate and the report's Welch estimate of the record
/// (`report::compensation`: the faithful band and the record's delay) share, so the two
/// read the same bins: bins below this coherence, or whose element force lies more than
/// 80 dB below the strongest bin, carry too little of the load; fewer than 5 segments (3 s
/// of force control) judge nothing.
pub const MIN_COHERENCE: f64 = 0.98;
pub const MIN_RELATIVE_EXCITATION: f64 = 1e-8;
pub const MIN_SEGMENTS: u32 = 5;
/// Fewer excited bins of the load band than this leave the delay unread.
pub const MIN_BINS: usize = 5;
/// The spectra forget with a memory of this many segments (half-overlapping 1 s segments:
/// 30 s), so a run of hours follows an actuator whose delay moves with its oil.
const MEMORY_SEGMENTS: f64 = 60.0;

/// The delay over the load band after the last whole segment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadBandEstimate {
    /// The mean over the excited bins of each bin's phase delay, s.
    pub delay_s: f64,
    /// Its standard error from the bins' coherence (Welch), s.
    pub delay_sigma_s: f64,
    /// The smallest and largest bin's delay, s: how far the delay varies over the band.
    pub min_s: f64,
    pub max_s: f64,
    /// Excited bins it rests on, and the lowest and highest, Hz.
    pub bins: u32,
    pub from_hz: f64,
    pub to_hz: f64,
}

/// One segment's rectangular transforms of the two forces, and its lead's sum.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Segment {
    element: [Complex64; RECT],
    own: [Complex64; RECT],
    lead_sum_s: f64,
}

impl Segment {
    const EMPTY: Segment = Segment {
        element: [Complex64::new(0.0, 0.0); RECT],
        own: [Complex64::new(0.0, 0.0); RECT],
        lead_sum_s: 0.0,
    };
}

/// Welch's cross-spectrum of the actuator's own force against the element's, computed as the
/// samples come: 1 s segments overlapping by half, each a rectangular DFT at 1-21 Hz summed
/// with rotating phasors (reset exactly each segment length), turned into the Hann window's
/// bins with the mean removed (`0.5 Y_k - 0.25 Y_(k-1) - 0.25 Y_(k+1)`, `Y_0 = 0`: the same
/// bins as the report's FFT of the detrended, windowed segment). Each segment's cross-spectrum
/// is turned back by the lead it was rendered with (its mean over the segment), so what
/// accumulates is the actuator's own response, also while the lead moves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadBandDelay {
    dt_s: f64,
    /// Samples in a segment, and since the last restart.
    len: u64,
    n: u64,
    /// `exp(-i 2 pi k / len)` for `k` = 1..=21, and the phasors at `n mod len`.
    step: [Complex64; RECT],
    phasor: [Complex64; RECT],
    /// The second segment starts half a segment later: `exp(i 2 pi k (len / 2) / len)`.
    late_shift: [Complex64; RECT],
    segments_open: [Segment; 2],
    see: [f64; LOAD_BAND_BINS],
    smm: [f64; LOAD_BAND_BINS],
    sme: [Complex64; LOAD_BAND_BINS],
    forget: f64,
    /// Segments added, and their forgetting-weighted count.
    segments: u32,
    weight: f64,
    estimate: Option<LoadBandEstimate>,
}

impl LoadBandDelay {
    pub fn new(dt_s: f64) -> LoadBandDelay {
        let len = (1.0 / dt_s).round().max(2.0 * RECT as f64 + 2.0) as u64;
        let half = len / 2;
        let mut step = [Complex64::new(1.0, 0.0); RECT];
        let mut late_shift = [Complex64::new(1.0, 0.0); RECT];
        for j in 0..RECT {
            let k = (j + 1) as f64;
            step[j] = Complex64::from_polar(1.0, -2.0 * PI * k / len as f64);
            late_shift[j] = Complex64::from_polar(1.0, 2.0 * PI * k * half as f64 / len as f64);
        }
        LoadBandDelay {
            dt_s,
            len,
            n: 0,
            step,
            phasor: [Complex64::new(1.0, 0.0); RECT],
            late_shift,
            segments_open: [Segment::EMPTY; 2],
            see: [0.0; LOAD_BAND_BINS],
            smm: [0.0; LOAD_BAND_BINS],
            sme: [Complex64::new(0.0, 0.0); LOAD_BAND_BINS],
            forget: (-1.0 / MEMORY_SEGMENTS).exp(),
            segments: 0,
            weight: 0.0,
            estimate: None,
        }
    }

    /// A gap in the samples: the open segments are dropped, the spectra kept.
    pub fn restart(&mut self) {
        self.n = 0;
        self.segments_open = [Segment::EMPTY; 2];
    }

    pub fn estimate(&self) -> Option<LoadBandEstimate> {
        self.estimate
    }

    /// One rig sample: the element's force, the actuator's own force (measured times the
    /// gain the rig divided by) and the lead in effect, s. True when a segment has just been
    /// added (`estimate` then describes the spectra with it: `None` when they no longer
    /// hold enough coherent, excited bins).
    #[inline]
    pub fn update(&mut self, element_force_n: f64, own_force_n: f64, lead_s: f64) -> bool {
        if !(element_force_n.is_finite() && own_force_n.is_finite() && lead_s.is_finite()) {
            self.restart();
            return false;
        }
        let half = self.len / 2;
        if self.n.is_multiple_of(self.len) {
            self.phasor = [Complex64::new(1.0, 0.0); RECT];
        }
        let late_open = self.n >= half;
        for j in 0..RECT {
            let p = self.phasor[j];
            self.segments_open[0].element[j] += p * element_force_n;
            self.segments_open[0].own[j] += p * own_force_n;
            if late_open {
                self.segments_open[1].element[j] += p * element_force_n;
                self.segments_open[1].own[j] += p * own_force_n;
            }
            self.phasor[j] = p * self.step[j];
        }
        self.segments_open[0].lead_sum_s += lead_s;
        if late_open {
            self.segments_open[1].lead_sum_s += lead_s;
        }
        self.n += 1;
        let mut added = false;
        if self.n.is_multiple_of(self.len) {
            self.add_segment(0);
            added = true;
        }
        if self.n > half && (self.n - half).is_multiple_of(self.len) {
            self.add_segment(1);
            added = true;
        }
        if added {
            self.estimate = self.compute();
        }
        added
    }

    fn add_segment(&mut self, which: usize) {
        let seg = self.segments_open[which];
        self.segments_open[which] = Segment::EMPTY;
        let shift = |j: usize| {
            if which == 1 {
                self.late_shift[j]
            } else {
                Complex64::new(1.0, 0.0)
            }
        };
        // The rectangular bin `k` (1..=21) of a signal, the mean (k = 0) removed.
        let rect = |values: &[Complex64; RECT], k: usize| {
            if k == 0 {
                Complex64::new(0.0, 0.0)
            } else {
                values[k - 1] * shift(k - 1)
            }
        };
        let hann = |values: &[Complex64; RECT], k: usize| {
            rect(values, k) * 0.5 - rect(values, k - 1) * 0.25 - rect(values, k + 1) * 0.25
        };
        let lead_s = seg.lead_sum_s / self.len as f64;
        let df = 1.0 / (self.len as f64 * self.dt_s);
        for b in 0..LOAD_BAND_BINS {
            let k = b + 1;
            let e = hann(&seg.element, k);
            let m = hann(&seg.own, k);
            let omega = 2.0 * PI * k as f64 * df;
            let back = Complex64::from_polar(1.0, -omega * lead_s);
            self.see[b] = self.forget * self.see[b] + e.norm_sqr();
            self.smm[b] = self.forget * self.smm[b] + m.norm_sqr();
            self.sme[b] = self.sme[b] * self.forget + m * e.conj() * back;
        }
        self.segments = self.segments.saturating_add(1);
        self.weight = self.forget * self.weight + 1.0;
    }

    /// Each excited, coherent bin's phase delay (the phase unwrapped from the lowest bin),
    /// and their mean.
    fn compute(&self) -> Option<LoadBandEstimate> {
        if self.segments < MIN_SEGMENTS {
            return None;
        }
        let strongest = self.see.iter().cloned().fold(0.0, f64::max);
        let df = 1.0 / (self.len as f64 * self.dt_s);
        let (mut previous, mut bins) = (0.0, 0u32);
        let (mut sum, mut var_sum) = (0.0, 0.0);
        let (mut min_s, mut max_s) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut from_hz, mut to_hz) = (f64::NAN, f64::NAN);
        for b in 0..LOAD_BAND_BINS {
            if self.see[b] <= MIN_RELATIVE_EXCITATION * strongest || self.smm[b] <= 0.0 {
                continue;
            }
            let coherence = self.sme[b].norm_sqr() / (self.see[b] * self.smm[b]);
            // NaN (no power in one force) reads as incoherent.
            if coherence.is_nan() || coherence < MIN_COHERENCE {
                continue;
            }
            let mut phase = self.sme[b].arg();
            while phase - previous > PI {
                phase -= 2.0 * PI;
            }
            while phase - previous < -PI {
                phase += 2.0 * PI;
            }
            previous = phase;
            let f_hz = (b + 1) as f64 * df;
            let omega = 2.0 * PI * f_hz;
            let delay = -phase / omega;
            // Welch's phase error: sqrt((1 - c) / (2 n c)) rad over n segments.
            let sigma_phase = ((1.0 - coherence) / (2.0 * self.weight * coherence)).sqrt();
            sum += delay;
            var_sum += (sigma_phase / omega).powi(2);
            min_s = min_s.min(delay);
            max_s = max_s.max(delay);
            if bins == 0 {
                from_hz = f_hz;
            }
            to_hz = f_hz;
            bins += 1;
        }
        if (bins as usize) < MIN_BINS {
            return None;
        }
        let n = bins as f64;
        Some(LoadBandEstimate {
            delay_s: sum / n,
            delay_sigma_s: var_sum.sqrt() / n,
            min_s,
            max_s,
            bins,
            from_hz,
            to_hz,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: f64 = 1.0 / 4096.0;

    /// Seeded uniform white noise in [-0.5, 0.5) (xorshift64).
    fn white_noise(mut state: u64) -> impl FnMut() -> f64 {
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        }
    }

    /// A broadband load (a preload and seeded white noise) rendered with a lead of 2
    /// samples through a transport delay of 4 samples and a first-order lag `tau` (Tustin):
    /// each bin's delay is the lag's `atan(w tau) / w` plus the net 2 samples, and the
    /// estimate is their mean over 1-20 Hz (the independent calculation). The window
    /// spreads each bin over its neighbours; for a smooth response that changes a bin's
    /// phase little, except at 1 Hz, whose lower neighbour (the mean) is removed: it reads
    /// up to 1.2 times its delay, about +1 % on the mean, as the report's record delay does.
    #[test]
    fn the_estimate_is_the_mean_phase_delay_of_a_lag_and_a_delay_over_the_band() {
        let tau = 2.0e-3;
        let (lead_samples, delay_samples) = (2usize, 4usize);
        let lead = lead_samples as f64 * DT;
        let net = (delay_samples - lead_samples) as f64 * DT;
        let mut noise = white_noise(0x2545_f491_4f6c_dd1d);
        let n: usize = 20 * 4096;
        let element: Vec<f64> = (0..n).map(|_| 20e3 + 4e3 * noise()).collect();
        // Tustin lag: y_k = a (x_k + x_(k-1)) + b y_(k-1).
        let c = 2.0 * tau / DT;
        let (a, b) = (1.0 / (1.0 + c), (c - 1.0) / (c + 1.0));
        let (mut y, mut x_prev) = (20e3, 20e3);
        let mut est = LoadBandDelay::new(DT);
        let mut last = None;
        for i in 0..n {
            let x = element[i.saturating_sub(delay_samples - lead_samples)];
            y = a * (x + x_prev) + b * y;
            x_prev = x;
            if est.update(element[i], y, lead) {
                last = est.estimate();
            }
        }
        let e = last.expect("an estimate");
        let at = |f: f64| (2.0 * PI * f * tau).atan() / (2.0 * PI * f) + net + lead;
        let exact: f64 =
            (1..=LOAD_BAND_BINS).map(|k| at(k as f64)).sum::<f64>() / LOAD_BAND_BINS as f64;
        assert_eq!(e.bins as usize, LOAD_BAND_BINS);
        assert!(
            (e.delay_s - exact).abs() < 0.01 * exact,
            "{} us against {} us",
            e.delay_s * 1e6,
            exact * 1e6
        );
        // The spread: the lag's delay is longest at 1 Hz and shortest at 20 Hz. The 1 Hz
        // bin, with the mean removed, has one neighbour left, so it reads between its own
        // delay and its mix with the 2 Hz bin's phase (the window's weights in power: 1/4
        // and 1/16; as the report's bins do).
        let phase_1 = (0.25 * 2.0 * PI * at(1.0) + 0.0625 * 4.0 * PI * at(2.0)) / 0.3125;
        let bin_1 = phase_1 / (2.0 * PI);
        assert!(
            e.max_s > 0.98 * at(1.0) && e.max_s < 1.02 * bin_1,
            "{} us, between {} and {} us",
            e.max_s * 1e6,
            at(1.0) * 1e6,
            bin_1 * 1e6
        );
        assert!(
            (e.min_s - at(20.0)).abs() < 0.02 * at(20.0),
            "{}",
            e.min_s * 1e6
        );
        // The standard error from the bins' coherence covers what the mean missed.
        assert!(
            e.delay_sigma_s < 0.02 * exact && (e.delay_s - exact).abs() < 3.0 * e.delay_sigma_s,
            "sigma {} us, off by {} us",
            e.delay_sigma_s * 1e6,
            (e.delay_s - exact) * 1e6
        );
    }

    /// The lead moves during the run: each segment is turned back by its own lead, so the
    /// estimate stays the actuator's (a pure 0.8 ms delay here), not the mean lead's.
    #[test]
    fn a_moving_lead_is_taken_out_segment_by_segment() {
        let d = 0.8e-3;
        let mut est = LoadBandDelay::new(DT);
        let mut last = None;
        for i in 0..(10 * 4096) {
            let t = i as f64 * DT;
            // The lead steps each second (0, 0.5, 1.0, ... ms), between segments' ends.
            let lead = 0.5e-3 * (t.floor() % 4.0);
            let (mut element, mut own) = (0.0, 0.0);
            for k in 1..=LOAD_BAND_BINS {
                let w = 2.0 * PI * k as f64;
                element += (w * t + k as f64).sin();
                own += (w * (t + lead - d) + k as f64).sin();
            }
            if est.update(element, own, lead) {
                last = est.estimate();
            }
        }
        let e = last.unwrap();
        // Half the segments straddle a step of the lead: their mean lead is off by up to a
        // quarter of the step for part of them, which the mean over segments mostly cancels.
        assert!((e.delay_s - d).abs() < 0.05 * d, "{} us", e.delay_s * 1e6);
    }

    /// Too few segments, or a load with fewer than five excited bins, read nothing; a gap
    /// drops the open segments only.
    #[test]
    fn too_little_load_reads_nothing() {
        let mut est = LoadBandDelay::new(DT);
        for i in 0..(10 * 4096) {
            let t = i as f64 * DT;
            // One harmonic: its bin and the two the window spreads it into.
            let f = 20e3 + 4e3 * (2.0 * PI * 2.0 * t).sin();
            est.update(f, f, 0.0);
        }
        assert_eq!(est.estimate(), None);
        let mut est = LoadBandDelay::new(DT);
        for i in 0..(2 * 4096) {
            let t = i as f64 * DT;
            let f: f64 = (1..=20).map(|k| (2.0 * PI * k as f64 * t).sin()).sum();
            est.update(f, f, 0.0);
        }
        assert_eq!(est.estimate(), None, "3 segments only");
    }
    /// White noise through a pure delay at a rate whose segment is an odd number of samples
    /// (4095 Hz: the late segment's half-segment shift is no longer a sign): the estimate
    /// is the delay, read a little long through the 1 Hz bin (about +1 % of the mean).
    #[test]
    fn an_odd_segment_length_reads_a_pure_delay() {
        let dt = 1.0 / 4095.0;
        let delay_samples = 8usize;
        let delay = delay_samples as f64 * dt;
        let mut noise = white_noise(0x9e37_79b9_7f4a_7c15);
        let n: usize = 20 * 4095;
        let element: Vec<f64> = (0..n).map(|_| 20e3 + 4e3 * noise()).collect();
        let mut est = LoadBandDelay::new(dt);
        for i in 0..n {
            est.update(element[i], element[i.saturating_sub(delay_samples)], 0.0);
        }
        let e = est.estimate().expect("an estimate");
        assert_eq!(e.bins as usize, LOAD_BAND_BINS);
        assert!(
            e.delay_s > delay && e.delay_s < 1.025 * delay,
            "{} us against {} us",
            e.delay_s * 1e6,
            delay * 1e6
        );
        // No bin reads it more than 5 % short (20 s of noise: a few % of scatter per bin).
        assert!(e.min_s > 0.95 * delay, "{}", e.min_s * 1e6);
    }

    /// A gap (a non-finite sample) drops the open segments and keeps the spectra: the
    /// estimate stands, and the next segment ends one segment length after the gap.
    #[test]
    fn a_gap_drops_the_open_segments_only() {
        let mut est = LoadBandDelay::new(DT);
        let f = |i: usize| {
            let t = i as f64 * DT;
            (1..=20)
                .map(|k| (2.0 * PI * k as f64 * t + k as f64).sin())
                .sum::<f64>()
        };
        let gap_at = 4096 * 4 + 1000;
        for i in 0..gap_at {
            est.update(f(i), f(i.saturating_sub(2)), 0.0);
        }
        let before = est.estimate().expect("an estimate before the gap");
        assert!(!est.update(f(gap_at), f64::NAN, 0.0));
        assert_eq!(est.estimate(), Some(before));
        let ended: Vec<usize> = (1..=4096)
            .filter(|j| est.update(f(gap_at + j), f(gap_at + j - 2), 0.0))
            .collect();
        assert_eq!(
            ended,
            vec![4096],
            "a segment ended only one length after the gap"
        );
    }
}
