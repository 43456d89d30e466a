//! The `hil` report: reads the processes' records, computes fidelity against the offline
//! reference (displacement error, per-band amplitude/phase errors), stability (growth
//! of the loop's resonant residual), latency percentiles (hdrhistogram), and draws the
//! plots. Offline code: allocates freely, never runs inside a loop.

use std::path::Path;

use hdrhistogram::Histogram;
use realfft::num_complex::Complex;
use realfft::RealFftPlanner;
use serde::Serialize;

use super::config::HilConfig;
use crate::csvio::read_columns;
use crate::plot::{draw_png, Panel, Series};
use crate::rig::reference::reference_displacement_m;

/// Percentiles of a latency, ns.
#[derive(Debug, Clone, Copy, Serialize, Default)]
pub struct Percentiles {
    pub p50: u64,
    pub p99: u64,
    pub p999: u64,
    pub max: u64,
    pub count: u64,
}

#[derive(Debug, Clone, Serialize, Default)]
pub struct Latency {
    pub end_to_end: Percentiles,
    pub wake_jitter: Percentiles,
}

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
    /// `rms(x_hil - x_ref) / rms(x_ref)` of the specimen displacement.
    pub displacement_rel_rms: f64,
    /// The same with the means removed (dynamic part only; stricter).
    pub displacement_dynamic_rel_rms: f64,
    pub displacement_error_rms_m: f64,
    pub bands: Vec<BandError>,
}

#[derive(Debug, Clone, Serialize, Default)]
pub struct Stability {
    pub stable: bool,
    /// Least-squares growth rate of the energy of the >100 Hz displacement residual
    /// (HIL - reference) over 0.25 s windows, 1/s (> 0: growing).
    pub resonant_energy_growth_per_s: f64,
    /// Largest >100 Hz displacement residual, m.
    pub resonant_residual_max_m: f64,
    /// Last window's >100 Hz residual RMS over the median window's.
    pub resonant_residual_last_over_median: f64,
    /// Least-squares growth rate of the >100 Hz residual's amplitude (peak per 10 ms
    /// window), from the start to the emulator's trip (or the end), 1/s.
    pub resonant_amplitude_growth_per_s: f64,
    /// `-growth / omega_0` with `omega_0 = sqrt(k_tangent(preload) / m)`: the net damping
    /// ratio the loop showed (negative: the loop delay's negative damping wins).
    pub equivalent_damping_ratio: f64,
    /// Rows analysed for the growth (up to the trip).
    pub growth_rows: usize,
    /// Median over 10 ms windows of the >100 Hz residual's peak, m.
    pub resonant_residual_median_peak_m: f64,
}

/// Median over 10 ms windows of the peak >100 Hz residual, m.
pub fn median_window_peak_m(residual: &[f64], rate_hz: f64) -> f64 {
    let hp = high_pass(residual, rate_hz);
    let window = ((rate_hz * 0.01) as usize).max(1);
    let mut peaks: Vec<f64> = hp
        .chunks(window)
        .filter(|c| c.len() == window)
        .map(|c| c.iter().fold(0.0f64, |m, x| m.max(x.abs())))
        .collect();
    peaks.sort_by(|a, b| a.total_cmp(b));
    peaks.get(peaks.len() / 2).copied().unwrap_or(0.0)
}

/// High-pass (>~100 Hz at `rate_hz`): subtracts a centred moving average over 1/100 s.
fn high_pass(residual: &[f64], rate_hz: f64) -> Vec<f64> {
    let half = ((rate_hz / 200.0) as usize).max(1);
    let n = residual.len();
    let mut prefix = vec![0.0; n + 1];
    for i in 0..n {
        prefix[i + 1] = prefix[i] + residual[i];
    }
    (0..n)
        .map(|i| {
            let (a, b) = (i.saturating_sub(half), (i + half + 1).min(n));
            residual[i] - (prefix[b] - prefix[a]) / (b - a) as f64
        })
        .collect()
}

fn slope(ys: &[f64], dx: f64) -> f64 {
    if ys.len() < 2 {
        return 0.0;
    }
    let xs: Vec<f64> = (0..ys.len()).map(|i| i as f64 * dx).collect();
    let (mx, my) = (mean(&xs), mean(ys));
    let sxy: f64 = xs.iter().zip(ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let sxx: f64 = xs.iter().map(|x| (x - mx) * (x - mx)).sum();
    sxy / sxx
}

/// Growth rate of the residual's resonant amplitude over `residual[..end]`, 1/s.
pub fn amplitude_growth_per_s(residual: &[f64], rate_hz: f64) -> f64 {
    let hp = high_pass(residual, rate_hz);
    let window = ((rate_hz * 0.01) as usize).max(1);
    let peaks: Vec<f64> = hp
        .chunks(window)
        .filter(|c| c.len() == window)
        .map(|c| c.iter().fold(1e-15f64, |m, x| m.max(x.abs())).ln())
        .collect();
    slope(&peaks, 0.01)
}

/// Results of the analysis of one run's records.
#[derive(Debug, Clone, Serialize, Default)]
pub struct Analysis {
    pub steps: u64,
    pub rig_steps: u64,
    pub fidelity: Fidelity,
    pub stability: Stability,
    pub latency_ns: Latency,
}

fn percentiles(values: impl Iterator<Item = u64>) -> Percentiles {
    let mut h =
        Histogram::<u64>::new_with_bounds(1, 1_000_000_000, 3).expect("valid histogram bounds");
    for v in values {
        h.saturating_record(v.max(1));
    }
    if h.is_empty() {
        return Percentiles::default();
    }
    Percentiles {
        p50: h.value_at_quantile(0.5),
        p99: h.value_at_quantile(0.99),
        p999: h.value_at_quantile(0.999),
        max: h.max(),
        count: h.len(),
    }
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn spectrum(x: &[f64]) -> Vec<Complex<f64>> {
    let m = mean(x);
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

/// Largest >100 Hz residual amplitude growth rate still called stable, 1/s: a net
/// damping ratio of about -0.5 % at the ~160 Hz loop resonance. The fit runs over the
/// whole run (10 ms windows), so a single disturbance (a late wake-up, the train
/// passage) hardly moves it, while a loop that lost its damping shows 100+/s.
pub const STABLE_MAX_GROWTH_PER_S: f64 = 5.0;
/// Largest median (over 10 ms windows) >100 Hz residual peak still called stable, m.
/// A loop that lost its damping grows into a sustained oscillation (a limit cycle once
/// limits bite) present in most windows; a one-off disturbance (a stalled process, the
/// train passage) decays in ~0.1 s and leaves the median at the noise level (~1 um).
pub const STABLE_MAX_MEDIAN_RESONANT_PEAK_M: f64 = 2e-5;

/// Stability from the >100 Hz residual between HIL and reference displacement.
pub fn stability(residual: &[f64], rate_hz: f64) -> Stability {
    let hp = high_pass(residual, rate_hz);
    let window = ((rate_hz * 0.25) as usize).max(1);
    let energies: Vec<f64> = hp
        .chunks(window)
        .filter(|c| c.len() == window)
        .map(|c| mean(&c.iter().map(|x| x * x).collect::<Vec<_>>()))
        .collect();
    let max_abs = hp.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let finite = residual.iter().all(|x| x.is_finite());
    let growth = if energies.len() >= 3 {
        let ys: Vec<f64> = energies.iter().map(|e| (e + 1e-30).ln()).collect();
        let xs: Vec<f64> = (0..ys.len()).map(|i| i as f64 * 0.25).collect();
        let (mx, my) = (mean(&xs), mean(&ys));
        let sxy: f64 = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum();
        let sxx: f64 = xs.iter().map(|x| (x - mx) * (x - mx)).sum();
        sxy / sxx
    } else {
        0.0
    };
    let mut sorted = energies.clone();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let median = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
    let last_over_median = match energies.last() {
        Some(&last) if median > 0.0 => (last / median).sqrt(),
        _ => 1.0,
    };
    Stability {
        // A loop that lost its damping grows until something saturates: either the
        // residual's energy grows through the run, or its last window is far above
        // the typical one, or it went non-finite.
        stable: finite,
        resonant_energy_growth_per_s: growth,
        resonant_residual_max_m: max_abs,
        resonant_residual_last_over_median: last_over_median,
        ..Stability::default()
    }
}

fn column(path: &Path, names: &[&str]) -> anyhow::Result<Vec<Vec<f64>>> {
    Ok(read_columns(path, names)?.data)
}

/// Analyses the records in `dir` and draws the plots there.
pub fn analyse_run(cfg: &HilConfig, dir: &Path) -> anyhow::Result<Analysis> {
    let rig = column(
        &dir.join("rig.csv"),
        &[
            "step_idx",
            "t_s",
            "x_m",
            "actuator_force_n",
            "external_force_n",
        ],
    )?;
    let emu = column(
        &dir.join("emulator.csv"),
        &["cycle_idx", "wake_late_ns", "force_n", "state"],
    )?;
    let ctl = column(
        &dir.join("controller.csv"),
        &["end_to_end_ns", "command_force_n"],
    )?;
    let rate = cfg.loop_.rate_hz;
    let n = rig[0].len();
    anyhow::ensure!(n > 16, "rig record has only {n} rows");
    // Rows skipped by a late wake-up are absent from the rig record, so the step index
    // runs past the row count: simulate the reference up to the last step index.
    let last_step = rig[0].iter().fold(0.0f64, |m, &k| m.max(k)) as usize;
    let x_ref_all = reference_displacement_m(cfg, last_step);
    // Rig rows are on the sample grid; rows skipped by a late wake-up are absent, so
    // pair by step index.
    let x_ref: Vec<f64> = rig[0].iter().map(|&k| x_ref_all[k as usize]).collect();
    let x_hil = &rig[2];
    let err: Vec<f64> = x_hil.iter().zip(&x_ref).map(|(h, r)| h - r).collect();
    let (m_hil, m_ref) = (mean(x_hil), mean(&x_ref));
    let dyn_err: Vec<f64> = x_hil
        .iter()
        .zip(&x_ref)
        .map(|(h, r)| (h - m_hil) - (r - m_ref))
        .collect();
    let dyn_ref: Vec<f64> = x_ref.iter().map(|r| r - m_ref).collect();
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
    let band_refs: Vec<(&str, f64, f64)> =
        bands.iter().map(|(s, a, b)| (s.as_str(), *a, *b)).collect();
    let fidelity = Fidelity {
        displacement_rel_rms: rms(&err) / rms(&x_ref),
        displacement_dynamic_rel_rms: rms(&dyn_err) / rms(&dyn_ref),
        displacement_error_rms_m: rms(&err),
        bands: band_errors(x_hil, &x_ref, rate, &band_refs),
    };
    let mut stability = stability(&err, rate);
    // Growth up to the emulator's trip (after it the controller ramps to safe).
    let trip_cycle = emu[3]
        .iter()
        .position(|&s| s as u32 == crate::ipc::messages::emulator_state::TRIPPED)
        .map(|i| emu[0][i] as usize);
    let growth_rows = trip_cycle.map_or(err.len(), |c| c.min(err.len()));
    stability.growth_rows = growth_rows;
    stability.resonant_amplitude_growth_per_s = amplitude_growth_per_s(&err[..growth_rows], rate);
    let k_tangent = cfg
        .model
        .element
        .high_frequency_stiffness_n_per_m(cfg.scenario.preload_n);
    let omega0 = (k_tangent / cfg.rig.specimen_mass_kg).sqrt();
    stability.equivalent_damping_ratio = -stability.resonant_amplitude_growth_per_s / omega0;
    stability.resonant_residual_median_peak_m = median_window_peak_m(&err, rate);
    if trip_cycle.is_some()
        || stability.resonant_amplitude_growth_per_s >= STABLE_MAX_GROWTH_PER_S
        || stability.resonant_residual_median_peak_m >= STABLE_MAX_MEDIAN_RESONANT_PEAK_M
    {
        stability.stable = false;
    }
    let latency_ns = Latency {
        end_to_end: percentiles(ctl[0].iter().filter(|&&v| v > 0.0).map(|&v| v as u64)),
        wake_jitter: percentiles(emu[1].iter().map(|&v| v as u64)),
    };

    // Plots: histories, HIL vs reference, latency histogram.
    let t = &rig[1];
    let to_mm = |v: &[f64]| v.iter().map(|x| x * 1e3).collect::<Vec<_>>();
    let to_kn = |v: &[f64]| v.iter().map(|x| x * 1e-3).collect::<Vec<_>>();
    let t_emu: Vec<f64> = emu[0].iter().map(|k| k / rate).collect();
    draw_png(
        &dir.join("histories.png"),
        1400,
        900,
        1,
        &[
            Panel::new("Specimen displacement", "t (s)", "displacement (mm)")
                .with(Series::line("HIL (rig, true)", t.clone(), to_mm(x_hil), 0))
                .with(Series::dashed(
                    "offline reference",
                    t.clone(),
                    to_mm(&x_ref),
                    1,
                )),
            Panel::new("Forces", "t (s)", "force (kN)")
                .with(Series::line("external load", t.clone(), to_kn(&rig[4]), 2))
                .with(Series::line(
                    "emulated element force",
                    t_emu,
                    to_kn(&emu[2]),
                    0,
                ))
                .with(Series::dashed(
                    "actuator force",
                    t.clone(),
                    to_kn(&rig[3]),
                    1,
                )),
        ],
    )?;
    draw_png(
        &dir.join("hil-vs-reference.png"),
        1400,
        600,
        1,
        &[
            Panel::new("HIL - reference displacement", "t (s)", "error (um)").with(Series::line(
                "x_hil - x_ref",
                t.clone(),
                err.iter().map(|e| e * 1e6).collect(),
                3,
            )),
        ],
    )?;
    let e2e_us: Vec<f64> = ctl[0]
        .iter()
        .filter(|&&v| v > 0.0)
        .map(|v| v / 1e3)
        .collect();
    let jitter_us: Vec<f64> = emu[1].iter().map(|v| v / 1e3).collect();
    let hist = |v: &[f64]| -> (Vec<f64>, Vec<f64>) {
        // Log-spaced bins from 0.1 us to 10 ms, counts per bin.
        let edges: Vec<f64> = (0..=50)
            .map(|i| 10f64.powf(-1.0 + i as f64 * 5.0 / 50.0))
            .collect();
        let mut counts = vec![0.0; 50];
        for &x in v {
            if let Some(b) = edges.windows(2).position(|w| x >= w[0] && x < w[1]) {
                counts[b] += 1.0;
            }
        }
        let centres = edges.windows(2).map(|w| (w[0] * w[1]).sqrt()).collect();
        (centres, counts.iter().map(|c| c + 0.5).collect())
    };
    let (xe, ye) = hist(&e2e_us);
    let (xj, yj) = hist(&jitter_us);
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

    Ok(Analysis {
        steps: emu[0].len() as u64,
        rig_steps: n as u64,
        fidelity,
        stability,
        latency_ns,
    })
}
