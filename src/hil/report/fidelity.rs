//! Fidelity and stability from the displacement residual (HIL minus offline reference),
//! sample by sample: running sums for the errors, a centred moving-average high-pass
//! (>~100 Hz) for the loop's resonant residual, online regressions for its growth, a
//! log histogram for its median, and the band errors on a bounded leading window (FFT).
//! Memory does not grow with the run's length.

use realfft::num_complex::Complex;
use realfft::RealFftPlanner;
use serde::Serialize;

/// Amplitude and phase error of the HIL displacement against the reference in a band.
#[derive(Debug, Clone, Serialize)]
pub struct BandError {
    pub band: String,
    pub f_lo_hz: f64,
    pub f_hi_hz: f64,
    /// `sqrt(sum |X_hil|^2 / sum |X_ref|^2) - 1`.
    pub amplitude_rel_error: f64,
    /// Power-weighted phase of `X_hil` relative to `X_ref`, degrees.
    pub phase_error_deg: f64,
    /// Reference RMS displacement in the band, m (how much there is to compare).
    pub reference_rms_m: f64,
}

#[derive(Debug, Clone, Serialize, Default)]
pub struct Fidelity {
    /// `rms(x_hil - x_ref) / rms(x_ref)` of the specimen displacement (up to a fault hold; operator holds and their resume blend left out).
    pub displacement_rel_rms: f64,
    /// The same with the means removed (dynamic part only; stricter).
    pub displacement_dynamic_rel_rms: f64,
    /// The worst `DYNAMIC_WINDOW_S` stretch's dynamic error, for a run longer than that
    /// (none otherwise): a long run's quiet stretches dilute the whole run's.
    pub dynamic_worst_window: Option<WindowError>,
    pub displacement_error_rms_m: f64,
    /// Periods compared (up to a fault hold, operator holds left out).
    pub compared_steps: u64,
    /// Sample time of the rig's first period on a command, s, where the comparison
    /// starts: until then the rig's own servo held the start (not the rendering's; not
    /// compared). None: no command was sent, and the whole run is compared.
    pub compared_from_s: Option<f64>,
    /// Seconds of the run the band errors cover (a bounded leading window).
    pub bands_window_s: f64,
    pub bands: Vec<BandError>,
}

/// One stretch's dynamic displacement error (`Fidelity::dynamic_worst_window`).
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct WindowError {
    pub rel_rms: f64,
    /// Where it starts and how long it is, s of compared periods (holds left out).
    pub from_s: f64,
    pub window_s: f64,
}

/// The stretch the worst dynamic error is judged over, s: the shipped programme's 6 s
/// (its block, which `configs/hil-durability.toml` repeats), so a long run is judged as a
/// run of that programme is. Stretches whose reference moves less than
/// `DYNAMIC_WINDOW_MIN_MOTION` of the whole run's are left out (a hold of the programme's
/// load: the error against no motion is no measure).
pub const DYNAMIC_WINDOW_S: f64 = 6.0;
const DYNAMIC_WINDOW_MIN_MOTION: f64 = 0.25;

/// Sums of one stretch of compared periods: n, sum d, sum d^2, sum r, sum r^2.
type Sums = [f64; 5];

fn dynamic_rel(s: &Sums) -> (f64, f64) {
    let n = s[0].max(1.0);
    let (md, mr) = (s[1] / n, s[3] / n);
    (
        (s[2] / n - md * md).max(0.0).sqrt(),
        (s[4] / n - mr * mr).max(0.0).sqrt(),
    )
}

/// The worst `window` blocks in a row (`DYNAMIC_WINDOW_S`), sliding a block at a time;
/// none when the run is no longer than a window.
fn worst_dynamic_window(blocks: &[Sums], window: usize, rate_hz: f64) -> Option<WindowError> {
    if blocks.len() <= window {
        return None;
    }
    let mut whole = [0.0; 5];
    for b in blocks {
        for k in 0..5 {
            whole[k] += b[k];
        }
    }
    let floor = DYNAMIC_WINDOW_MIN_MOTION * dynamic_rel(&whole).1;
    let mut worst: Option<WindowError> = None;
    let mut before = 0.0;
    for start in 0..=blocks.len() - window {
        if start > 0 {
            before += blocks[start - 1][0];
        }
        let mut w = [0.0; 5];
        for b in &blocks[start..start + window] {
            for k in 0..5 {
                w[k] += b[k];
            }
        }
        let (err, reference) = dynamic_rel(&w);
        if reference <= floor || reference <= 0.0 {
            continue;
        }
        let rel = err / reference;
        // The first of stretches that tie (to rounding).
        if worst.is_none_or(|x| rel > x.rel_rms * (1.0 + 1e-9)) {
            worst = Some(WindowError {
                rel_rms: rel,
                from_s: before / rate_hz,
                window_s: w[0] / rate_hz,
            });
        }
    }
    worst
}

#[derive(Debug, Clone, Serialize, Default)]
pub struct Stability {
    pub stable: bool,
    /// Least-squares growth rate of the energy of the >100 Hz displacement residual over
    /// 0.25 s windows, 1/s (> 0: growing).
    pub resonant_energy_growth_per_s: f64,
    /// Largest >100 Hz displacement residual, m (the largest transient).
    pub resonant_residual_max_m: f64,
    /// Last window's >100 Hz residual RMS over the median window's.
    pub resonant_residual_last_over_median: f64,
    /// Least-squares growth rate of the >100 Hz residual's amplitude (peak per 10 ms
    /// window), up to the first trip or hold, 1/s.
    pub resonant_amplitude_growth_per_s: f64,
    /// `-growth / omega_0` with `omega_0 = sqrt(k_tangent(preload) / m)`: the net damping
    /// ratio the loop showed (negative: the loop delay's negative damping wins).
    pub equivalent_damping_ratio: f64,
    /// Rows analysed for the growth (up to a fault hold, operator holds left out).
    pub growth_rows: u64,
    /// Median over 10 ms windows of the >100 Hz residual's peak, m.
    pub resonant_residual_median_peak_m: f64,
}

/// Largest >100 Hz residual amplitude growth rate still called stable, 1/s: a net
/// damping ratio of about -0.5 % at the ~160 Hz loop resonance. The fit runs over the
/// whole run (10 ms windows), so a single disturbance hardly moves it, while a loop that
/// lost its damping shows 100+/s.
pub const STABLE_MAX_GROWTH_PER_S: f64 = 5.0;
/// Largest median (over 10 ms windows) >100 Hz residual peak still called stable, m.
/// A loop that lost its damping grows into a sustained oscillation present in most
/// windows; a one-off disturbance decays in ~0.1 s and leaves the median at noise level.
pub const STABLE_MAX_MEDIAN_RESONANT_PEAK_M: f64 = 2e-5;

/// Leading samples kept for the band errors (FFT): 2^20 (256 s at 4096 Hz).
const BAND_WINDOW_MAX: usize = 1 << 20;

/// Online least-squares slope of y against x.
#[derive(Debug, Clone, Copy, Default)]
struct Slope {
    n: f64,
    sx: f64,
    sy: f64,
    sxx: f64,
    sxy: f64,
}

impl Slope {
    fn push(&mut self, x: f64, y: f64) {
        self.n += 1.0;
        self.sx += x;
        self.sy += y;
        self.sxx += x * x;
        self.sxy += x * y;
    }
    fn slope(&self) -> f64 {
        if self.n < 2.0 {
            return 0.0;
        }
        let den = self.n * self.sxx - self.sx * self.sx;
        if den == 0.0 {
            0.0
        } else {
            (self.n * self.sxy - self.sx * self.sy) / den
        }
    }
}

/// Median of positive values from a log histogram (20 bins per decade, 1e-15..1e3).
#[derive(Debug, Clone)]
struct LogMedian {
    counts: Vec<u64>,
    total: u64,
}

impl LogMedian {
    const LO: f64 = -15.0;
    const PER_DECADE: f64 = 20.0;
    fn new() -> LogMedian {
        LogMedian {
            counts: vec![0; (18.0 * Self::PER_DECADE) as usize],
            total: 0,
        }
    }
    fn push(&mut self, v: f64) {
        let b = ((v.max(1e-15).log10() - Self::LO) * Self::PER_DECADE)
            .floor()
            .clamp(0.0, (self.counts.len() - 1) as f64) as usize;
        self.counts[b] += 1;
        self.total += 1;
    }
    fn median(&self) -> f64 {
        let half = self.total.div_ceil(2);
        let mut acc = 0;
        for (b, &c) in self.counts.iter().enumerate() {
            acc += c;
            if acc >= half && c > 0 {
                return 10f64.powf(Self::LO + (b as f64 + 0.5) / Self::PER_DECADE);
            }
        }
        0.0
    }
}

/// The centred moving-average high-pass, streaming: `hp[i] = r[i] - mean(r[i-h..=i+h])`
/// (window clipped at the ends), output `h` samples late.
#[derive(Debug, Clone)]
pub struct CentredHighPass {
    half: usize,
    ring: Vec<f64>,
    /// Samples pushed so far.
    n: usize,
}

impl CentredHighPass {
    /// A high-pass above ~100 Hz at `rate_hz` (a 1/100 s window).
    pub fn new(rate_hz: f64) -> CentredHighPass {
        let half = ((rate_hz / 200.0) as usize).max(1);
        CentredHighPass {
            half,
            ring: vec![0.0; 2 * half + 1],
            n: 0,
        }
    }

    fn get(&self, i: usize) -> f64 {
        self.ring[i % self.ring.len()]
    }

    fn output(&self, i: usize, last: usize) -> f64 {
        let lo = i.saturating_sub(self.half);
        let hi = (i + self.half).min(last);
        let sum: f64 = (lo..=hi).map(|j| self.get(j)).sum();
        self.get(i) - sum / (hi - lo + 1) as f64
    }

    /// Adds sample `r`; returns `(index, hp)` of the sample now complete, if any.
    pub fn push(&mut self, r: f64) -> Option<(usize, f64)> {
        let len = self.ring.len();
        self.ring[self.n % len] = r;
        self.n += 1;
        let newest = self.n - 1;
        (newest >= self.half).then(|| {
            let i = newest - self.half;
            (i, self.output(i, newest))
        })
    }

    /// The last `half` samples, with the window clipped at the end.
    pub fn finish(&self) -> Vec<(usize, f64)> {
        if self.n == 0 {
            return Vec::new();
        }
        let last = self.n - 1;
        (self.n.saturating_sub(self.half)..self.n)
            .map(|i| (i, self.output(i, last)))
            .collect()
    }
}

/// Accumulates fidelity and stability over the residual compared (no holds).
#[derive(Debug, Clone)]
pub struct ResidualAnalyser {
    rate_hz: f64,
    n: u64,
    sum_d2: f64,
    sum_d: f64,
    sum_r2: f64,
    sum_r: f64,
    /// Per second of compared periods (`DYNAMIC_WINDOW_S`): the whole ones, the one filling.
    blocks: Vec<Sums>,
    block: Sums,
    band_hil: Vec<f64>,
    band_ref: Vec<f64>,
    // >100 Hz residual.
    max_abs: f64,
    window10: usize,
    peak_run: (usize, f64),
    peak_slope: Slope,
    peak_median: LogMedian,
    window250: usize,
    energy_run: (usize, f64),
    energy_slope: Slope,
    energy_median: LogMedian,
    last_energy: Option<f64>,
    hp_rows: u64,
}

impl ResidualAnalyser {
    pub fn new(rate_hz: f64) -> ResidualAnalyser {
        ResidualAnalyser {
            rate_hz,
            n: 0,
            sum_d2: 0.0,
            sum_d: 0.0,
            sum_r2: 0.0,
            sum_r: 0.0,
            blocks: Vec::new(),
            block: [0.0; 5],
            band_hil: Vec::new(),
            band_ref: Vec::new(),
            max_abs: 0.0,
            window10: ((rate_hz * 0.01) as usize).max(1),
            peak_run: (0, 1e-15),
            peak_slope: Slope::default(),
            peak_median: LogMedian::new(),
            window250: ((rate_hz * 0.25) as usize).max(1),
            energy_run: (0, 0.0),
            energy_slope: Slope::default(),
            energy_median: LogMedian::new(),
            last_energy: None,
            hp_rows: 0,
        }
    }

    /// One compared period: HIL and reference displacement.
    pub fn push_displacement(&mut self, x_hil: f64, x_ref: f64) {
        let d = x_hil - x_ref;
        self.n += 1;
        self.sum_d2 += d * d;
        self.sum_d += d;
        self.sum_r2 += x_ref * x_ref;
        self.sum_r += x_ref;
        for (k, v) in [1.0, d, d * d, x_ref, x_ref * x_ref]
            .into_iter()
            .enumerate()
        {
            self.block[k] += v;
        }
        if self.block[0] >= self.rate_hz.round() {
            self.blocks.push(self.block);
            self.block = [0.0; 5];
        }
        if self.band_hil.len() < BAND_WINDOW_MAX {
            self.band_hil.push(x_hil);
            self.band_ref.push(x_ref);
        }
    }

    /// One >100 Hz residual sample (in order).
    pub fn push_high_passed(&mut self, hp: f64) {
        self.hp_rows += 1;
        self.max_abs = self.max_abs.max(hp.abs());
        self.peak_run.0 += 1;
        self.peak_run.1 = self.peak_run.1.max(hp.abs());
        if self.peak_run.0 == self.window10 {
            let k = self.peak_slope.n;
            self.peak_slope.push(k * 0.01, self.peak_run.1.ln());
            self.peak_median.push(self.peak_run.1);
            self.peak_run = (0, 1e-15);
        }
        self.energy_run.0 += 1;
        self.energy_run.1 += hp * hp;
        if self.energy_run.0 == self.window250 {
            let e = self.energy_run.1 / self.window250 as f64;
            let k = self.energy_slope.n;
            self.energy_slope.push(k * 0.25, (e + 1e-30).ln());
            self.energy_median.push(e);
            self.last_energy = Some(e);
            self.energy_run = (0, 0.0);
        }
    }

    /// Fidelity over the compared periods; bands from the leading window.
    pub fn fidelity(&self, bands: &[(String, f64, f64)]) -> Fidelity {
        let n = self.n.max(1) as f64;
        let rms_err = (self.sum_d2 / n).sqrt();
        let rms_ref = (self.sum_r2 / n).sqrt();
        let (mean_d, mean_r) = (self.sum_d / n, self.sum_r / n);
        let dyn_err = (self.sum_d2 / n - mean_d * mean_d).max(0.0).sqrt();
        let dyn_ref = (self.sum_r2 / n - mean_r * mean_r).max(0.0).sqrt();
        let band_refs: Vec<(&str, f64, f64)> =
            bands.iter().map(|(s, a, b)| (s.as_str(), *a, *b)).collect();
        Fidelity {
            displacement_rel_rms: rms_err / rms_ref,
            displacement_dynamic_rel_rms: dyn_err / dyn_ref,
            // Whole seconds only (the part second at the end is in the whole run's).
            dynamic_worst_window: worst_dynamic_window(
                &self.blocks,
                DYNAMIC_WINDOW_S as usize,
                self.rate_hz,
            ),
            displacement_error_rms_m: rms_err,
            compared_steps: self.n,
            compared_from_s: None,
            bands_window_s: self.band_hil.len() as f64 / self.rate_hz,
            bands: band_errors(&self.band_hil, &self.band_ref, self.rate_hz, &band_refs),
        }
    }

    /// Stability of the loop over the analysed residual. `omega0` is the loop's resonance.
    pub fn stability(&self, omega0_rad_per_s: f64) -> Stability {
        let growth = self.peak_slope.slope();
        let median_energy = self.energy_median.median();
        let last_over_median = match self.last_energy {
            Some(last) if median_energy > 0.0 => (last / median_energy).sqrt(),
            _ => 1.0,
        };
        let median_peak = self.peak_median.median();
        let finite = self.max_abs.is_finite();
        Stability {
            stable: finite
                && growth < STABLE_MAX_GROWTH_PER_S
                && median_peak < STABLE_MAX_MEDIAN_RESONANT_PEAK_M,
            resonant_energy_growth_per_s: self.energy_slope.slope(),
            resonant_residual_max_m: self.max_abs,
            resonant_residual_last_over_median: last_over_median,
            resonant_amplitude_growth_per_s: growth,
            equivalent_damping_ratio: -growth / omega0_rad_per_s,
            growth_rows: self.hp_rows,
            resonant_residual_median_peak_m: median_peak,
        }
    }
}

fn spectrum(x: &[f64]) -> Vec<Complex<f64>> {
    let m = x.iter().sum::<f64>() / x.len().max(1) as f64;
    let mut input: Vec<f64> = x.iter().map(|v| v - m).collect();
    let mut planner = RealFftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(input.len());
    let mut out = fft.make_output_vec();
    let _ = fft.process(&mut input, &mut out);
    out
}

/// Per-band errors of `hil` against `reference`, both sampled at `rate_hz`.
pub fn band_errors(
    hil: &[f64],
    reference: &[f64],
    rate_hz: f64,
    bands: &[(&str, f64, f64)],
) -> Vec<BandError> {
    let n = hil.len().min(reference.len());
    if n < 16 {
        return Vec::new();
    }
    let (h, r) = (spectrum(&hil[..n]), spectrum(&reference[..n]));
    let df = rate_hz / n as f64;
    bands
        .iter()
        .map(|&(name, lo, hi)| {
            let (mut ph, mut pr) = (0.0, 0.0);
            let mut cross = Complex::new(0.0, 0.0);
            for k in 1..h.len() {
                let f = k as f64 * df;
                if f >= lo && f < hi {
                    ph += h[k].norm_sqr();
                    pr += r[k].norm_sqr();
                    cross += h[k] * r[k].conj();
                }
            }
            // One-sided spectrum: RMS of the band = sqrt(2 sum |X|^2) / n.
            let reference_rms = (2.0 * pr).sqrt() / n as f64;
            BandError {
                band: name.to_string(),
                f_lo_hz: lo,
                f_hi_hz: hi,
                amplitude_rel_error: if pr > 0.0 {
                    (ph / pr).sqrt() - 1.0
                } else {
                    f64::NAN
                },
                phase_error_deg: cross.arg().to_degrees(),
                reference_rms_m: reference_rms,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A long run's worst stretch: 20 s of a 2 Hz motion on an offset, rendered 10 % too
    /// large for 2 s only. Over the whole run the dynamic error is `0.1 sqrt(2 / 20)`; over
    /// the worst 6 s, `0.1 sqrt(2 / 6)`, first at 8 s. A run no longer than 6 s has none;
    /// stretches where the reference does not move are left out.
    #[test]
    fn the_worst_stretch_of_a_long_run_is_judged_as_a_short_run() {
        use std::f64::consts::PI;
        let rate = 100.0;
        let run = |seconds: usize, quiet_until_s: f64| {
            let mut a = ResidualAnalyser::new(rate);
            for i in 0..(seconds * 100) {
                let t = i as f64 / rate;
                let motion = if t < quiet_until_s {
                    0.0
                } else {
                    (2.0 * PI * 2.0 * t).sin()
                };
                let r = 5.0 + motion;
                let hil = if (12.0..14.0).contains(&t) {
                    5.0 + 1.1 * motion
                } else {
                    // A tiny error of its own where the reference stands still.
                    r + if t < quiet_until_s {
                        1e-3 * (i % 2) as f64
                    } else {
                        0.0
                    }
                };
                a.push_displacement(hil, r);
            }
            a.fidelity(&[])
        };
        let f = run(20, 0.0);
        assert!((f.displacement_dynamic_rel_rms - 0.1 * (0.1f64).sqrt()).abs() < 1e-9);
        let w = f.dynamic_worst_window.expect("20 s is longer than 6 s");
        assert!(
            (w.rel_rms - 0.1 * (2.0f64 / 6.0).sqrt()).abs() < 1e-9,
            "{w:?}"
        );
        assert_eq!((w.from_s, w.window_s), (8.0, 6.0));
        assert_eq!(run(6, 0.0).dynamic_worst_window, None);
        // Still for the first 9 s: the windows that start there move less than a quarter
        // of the run's motion and are not judged (their error against no motion would be
        // 1e-3 over nothing).
        let w = run(20, 9.0).dynamic_worst_window.unwrap();
        assert!(w.from_s >= 4.0 && w.rel_rms < 0.1, "{w:?}");
    }

    #[test]
    fn streaming_high_pass_equals_the_batch_formula() {
        let r: Vec<f64> = (0..500)
            .map(|i| (i as f64 * 0.37).sin() + 1e-3 * i as f64)
            .collect();
        let mut hp = CentredHighPass::new(4096.0);
        let mut out = vec![f64::NAN; r.len()];
        for &v in &r {
            if let Some((i, y)) = hp.push(v) {
                out[i] = y;
            }
        }
        for (i, y) in hp.finish() {
            out[i] = y;
        }
        let half = 20;
        for i in 0..r.len() {
            let (a, b) = (i.saturating_sub(half), (i + half + 1).min(r.len()));
            let want = r[i] - r[a..b].iter().sum::<f64>() / (b - a) as f64;
            assert!((out[i] - want).abs() < 1e-12, "{i}: {} vs {want}", out[i]);
        }
    }

    #[test]
    fn growth_of_a_growing_oscillation_is_its_rate() {
        let rate = 4096.0;
        let mut a = ResidualAnalyser::new(rate);
        for k in 0..(4.0 * rate) as usize {
            let t = k as f64 / rate;
            a.push_high_passed(
                1e-6 * (3.0 * t).exp() * (2.0 * std::f64::consts::PI * 160.0 * t).sin(),
            );
        }
        let s = a.stability(1000.0);
        assert!(
            (s.resonant_amplitude_growth_per_s - 3.0).abs() < 0.1,
            "{s:?}"
        );
        assert!((s.resonant_energy_growth_per_s - 6.0).abs() < 0.3, "{s:?}");
    }
}
