//! F12: steady-state response of one metre of ERS (rail mass on the element) to
//! `P + F1 cos(W t)` by time-domain simulation, as amplitude ratio |X|/F1 (m/N) and phase
//! delay of the displacement's component at W: (a) P = 6 kN, 10-500 Hz; (b) P = 6, 18,
//! 37, 55 kN, 150-210 Hz; F1 = 1 kN; the paper's 2 Hz grid, then the true peak of each
//! (b) curve: a 0.25 Hz scan from 6 Hz below to 4 Hz above the grid maximum, refined by a
//! golden-section search around the scan maximum (the resonance softens and jumps at this
//! amplitude, see `write_figure12`). The linear model's curve is its
//! exact FRF `1/(k - m W^2 + i c W)` (the paper computed it in the frequency domain too).
//!
//! Settling. Each run starts in static equilibrium under `F(0) = P + F1` (the force has
//! zero slope there, so nothing jumps). What is left is a free transient at the natural
//! frequency that decays at `s = c_ss / 2m`, with `c_ss` the model's small-signal damping
//! at the preload near resonance: 8.3 1/s for the linear model but ~0.9 1/s for the
//! consistent form and down to ~0.26 1/s for the paper form at 55 kN (its linearised
//! damping is 70 % below Eq. 2 there, SPEC 2.1). Each run therefore lasts
//! `ln(1/eps)/s` before the measurement (eps = 1e-3: the transient is 0.1 % of its start,
//! and its leakage into the measured bin is smaller again), capped at 40 s, then two
//! measurement windows of whole cycles (>= 1 s each). The displacement's component at W
//! comes from a single-bin DFT over the last window (exact for whole cycles); the
//! relative change from the previous window is reported as `settle_change` so a run that
//! had not settled shows itself. Near resonance the response is strongly nonlinear (the
//! element force swings by tens of kN around a 6 kN preload), so the linearised decay
//! rate is only a guide: that is why the settling is checked, not assumed.
//!
//! Sampling: at least 100 samples per cycle and a step <= 0.1 ms, with a whole number of
//! samples per cycle; the force is linear between samples, which attenuates the forcing
//! fundamental by `(W dt)^2 / 12` <= 3.3e-4. The oscillator sub-steps RK4 as it needs.
//!
//! Cost: ~1200 runs of 1-40 s simulated time (~50 s of CPU in all, release build). Runs
//! go to two worker threads through a shared queue (the machine has 2 cores).

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use indicatif::{ProgressBar, ProgressStyle};
use realfft::num_complex::Complex64;
use serde_json::{json, Value};

use super::{
    model_color, out_path, stage, write_csv, ModelSet, PaperOptions, COLOR_PRELOAD,
    RAIL_MASS_UNIT_LENGTH_KG,
};
use crate::model::equiv::equivalent;
use crate::model::oscillator::{Oscillator, StartCondition};
use crate::model::{ElementModel, StepFlags};
use crate::plot::{draw_png, Panel, Series};

const TWO_PI: f64 = 2.0 * std::f64::consts::PI;
/// Harmonic force amplitude of paper Fig. 12, N.
pub const FORCE_AMPLITUDE_N: f64 = 1e3;
/// Preloads of paper Fig. 12b, N.
pub const PRELOADS_N: [f64; 4] = [6e3, 18e3, 37e3, 55e3];
/// Largest sample step, s.
const MAX_DT_S: f64 = 1e-4;
const MIN_SAMPLES_PER_CYCLE: usize = 100;
/// Longest settling time before measuring, s.
const MAX_SETTLE_S: f64 = 40.0;

/// How long to settle and measure.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SettlePlan {
    /// Fraction of the initial transient left when the measurement starts.
    pub residual_fraction: f64,
    /// Shortest measurement window, s (rounded up to whole cycles, at least 10).
    pub window_s: f64,
}

impl SettlePlan {
    pub const FULL: SettlePlan = SettlePlan {
        residual_fraction: 1e-3,
        window_s: 1.0,
    };
    pub const QUICK: SettlePlan = SettlePlan {
        residual_fraction: 3e-2,
        window_s: 0.3,
    };
}

/// The steady-state response at one frequency.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HarmonicPoint {
    pub frequency_hz: f64,
    /// |X| / F1, m/N.
    pub amplitude_ratio_m_per_n: f64,
    /// Phase of the displacement relative to the force, rad (0 to -pi: it lags).
    pub phase_rad: f64,
    /// |X_last - X_previous| / |X_last| over the two measurement windows.
    pub settle_change: f64,
    /// The element went beyond its tension domain at some step (see `StepFlags`).
    pub tension_clamped: bool,
}

/// Decay rate of the free transient at `preload_n`, 1/s: the small-signal damping of the
/// model's own time-domain form at its natural frequency, over twice the mass.
pub fn transient_decay_rate_per_s(model: &ElementModel, mass_kg: f64, preload_n: f64) -> f64 {
    let omega_n = (model.high_frequency_stiffness_n_per_m(preload_n) / mass_kg).sqrt();
    let c = equivalent(model, preload_n, omega_n).c_eq_ns_per_m;
    (c / (2.0 * mass_kg)).max(1e-3)
}

/// Simulates `P + F1 cos(W t)` on the mass-on-element model and measures the steady state.
pub fn harmonic_response(
    model: ElementModel,
    mass_kg: f64,
    preload_n: f64,
    amplitude_n: f64,
    frequency_hz: f64,
    plan: SettlePlan,
) -> HarmonicPoint {
    let period_s = 1.0 / frequency_hz;
    let samples_per_cycle = ((period_s / MAX_DT_S).ceil() as usize).max(MIN_SAMPLES_PER_CYCLE);
    let dt_s = period_s / samples_per_cycle as f64;
    let decay = transient_decay_rate_per_s(&model, mass_kg, preload_n);
    let settle_s = ((1.0 / plan.residual_fraction).ln() / decay).min(MAX_SETTLE_S);
    let settle_cycles = (settle_s * frequency_hz).ceil() as usize;
    let window_cycles = ((plan.window_s * frequency_hz).ceil() as usize).max(10);
    // One table of cos/sin per sample of a cycle serves both the force and the DFT.
    let table: Vec<(f64, f64)> = (0..samples_per_cycle)
        .map(|i| {
            let phase = TWO_PI * i as f64 / samples_per_cycle as f64;
            (phase.cos(), phase.sin())
        })
        .collect();
    let force_at = |i: usize| preload_n + amplitude_n * table[i % samples_per_cycle].0;
    let mut osc = Oscillator::new(model, mass_kg, dt_s, preload_n + amplitude_n);
    osc.start(StartCondition::Static, force_at(0));
    let mut flags = StepFlags::NONE;
    let settle_samples = settle_cycles * samples_per_cycle;
    let window_samples = window_cycles * samples_per_cycle;
    let mut step_idx = 0usize;
    for _ in 0..settle_samples {
        flags |= osc.step(force_at(step_idx), force_at(step_idx + 1));
        step_idx += 1;
    }
    let mut windows = [Complex64::new(0.0, 0.0); 2];
    for window in &mut windows {
        let mut sum = Complex64::new(0.0, 0.0);
        for _ in 0..window_samples {
            // Sample at the start of the step (sample `step_idx`), then step.
            let (c, s) = table[step_idx % samples_per_cycle];
            let x = osc.displacement_m();
            sum += Complex64::new(x * c, -x * s);
            flags |= osc.step(force_at(step_idx), force_at(step_idx + 1));
            step_idx += 1;
        }
        *window = sum * (2.0 / window_samples as f64);
    }
    let response = windows[1] / amplitude_n;
    HarmonicPoint {
        frequency_hz,
        amplitude_ratio_m_per_n: response.norm(),
        phase_rad: lagging_phase(response),
        settle_change: (windows[1] - windows[0]).norm() / windows[1].norm().max(1e-300),
        tension_clamped: flags.contains(StepFlags::TENSION_CLAMPED),
    }
}

/// Phase in (-3pi/2, pi/2]: a passive response lags by 0 to pi, so keep it continuous there.
fn lagging_phase(response: Complex64) -> f64 {
    let phase = response.arg();
    if phase > 0.5 * std::f64::consts::PI {
        phase - TWO_PI
    } else {
        phase
    }
}

/// The small-signal FRF `1/(k_eq - m W^2 + i c_eq W)` of the model's time-domain form
/// linearised at `preload_n` (`equivalent`), at `frequency_hz`, m/N. For the linear
/// Kelvin-Voigt model this is its exact FRF `1/(k - m W^2 + i c W)` at any preload; for
/// the Zener forms it is the limit of F12's time-domain ratio as F1 -> 0.
pub fn small_signal_frf(
    model: &ElementModel,
    mass_kg: f64,
    preload_n: f64,
    frequency_hz: f64,
) -> Complex64 {
    let omega = TWO_PI * frequency_hz;
    let lin = equivalent(model, preload_n, omega);
    Complex64::new(1.0, 0.0)
        / Complex64::new(
            lin.k_eq_n_per_m - mass_kg * omega * omega,
            lin.c_eq_ns_per_m * omega,
        )
}

/// The linear Kelvin-Voigt FRF at `frequency_hz`, m/N.
pub fn linear_frf(model: &ElementModel, mass_kg: f64, frequency_hz: f64) -> Complex64 {
    small_signal_frf(model, mass_kg, 0.0, frequency_hz)
}

/// Peak of the small-signal FRF in 150-210 Hz on a 1 mHz grid: (frequency Hz, |H| m/N).
pub fn small_signal_peak(model: &ElementModel, mass_kg: f64, preload_n: f64) -> (f64, f64) {
    (0..=60_000)
        .map(|i| 150.0 + 1e-3 * i as f64)
        .map(|f| (f, small_signal_frf(model, mass_kg, preload_n, f).norm()))
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap_or((f64::NAN, f64::NAN))
}

/// One simulation job: which curve, which model, which preload and frequency.
#[derive(Debug, Clone, Copy)]
struct Job {
    curve_idx: usize,
    model: ElementModel,
    preload_n: f64,
    frequency_hz: f64,
}

/// Runs `jobs` on two threads; returns the points in job order.
fn run_jobs(jobs: &[Job], plan: SettlePlan, progress: &ProgressBar) -> Vec<HarmonicPoint> {
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<HarmonicPoint>>> = Mutex::new(vec![None; jobs.len()]);
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| loop {
                let idx = next.fetch_add(1, Ordering::Relaxed);
                let Some(job) = jobs.get(idx) else { break };
                let point = harmonic_response(
                    job.model,
                    RAIL_MASS_UNIT_LENGTH_KG,
                    job.preload_n,
                    FORCE_AMPLITUDE_N,
                    job.frequency_hz,
                    plan,
                );
                results.lock().expect("no worker panics holding the lock")[idx] = Some(point);
                progress.inc(1);
            });
        }
    });
    results
        .into_inner()
        .expect("workers finished")
        .into_iter()
        .map(|p| p.expect("every job ran"))
        .collect()
}

/// Golden-section search for the largest amplitude ratio in `[lo, hi]`.
pub fn golden_section_peak(
    model: ElementModel,
    preload_n: f64,
    lo_hz: f64,
    hi_hz: f64,
    iterations: usize,
    plan: SettlePlan,
) -> HarmonicPoint {
    let ratio = |f: f64| {
        harmonic_response(
            model,
            RAIL_MASS_UNIT_LENGTH_KG,
            preload_n,
            FORCE_AMPLITUDE_N,
            f,
            plan,
        )
    };
    let inv_phi = (5f64.sqrt() - 1.0) / 2.0;
    let (mut a, mut b) = (lo_hz, hi_hz);
    let mut c = b - inv_phi * (b - a);
    let mut d = a + inv_phi * (b - a);
    let mut pc = ratio(c);
    let mut pd = ratio(d);
    for _ in 0..iterations {
        if pc.amplitude_ratio_m_per_n >= pd.amplitude_ratio_m_per_n {
            b = d;
            d = c;
            pd = pc;
            c = b - inv_phi * (b - a);
            pc = ratio(c);
        } else {
            a = c;
            c = d;
            pc = pd;
            d = a + inv_phi * (b - a);
            pd = ratio(d);
        }
    }
    if pc.amplitude_ratio_m_per_n >= pd.amplitude_ratio_m_per_n {
        pc
    } else {
        pd
    }
}

/// The grid of a sweep: `lo..=hi` in steps of `step` Hz.
fn grid(lo_hz: f64, hi_hz: f64, step_hz: f64) -> Vec<f64> {
    let n = ((hi_hz - lo_hz) / step_hz).round() as usize;
    (0..=n).map(|i| lo_hz + step_hz * i as f64).collect()
}

fn progress_bar(len: usize, message: &'static str) -> ProgressBar {
    let bar = ProgressBar::new(len as u64);
    if let Ok(style) = ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} ({eta})") {
        bar.set_style(style);
    }
    bar.set_message(message);
    bar
}

/// The grid maximum of one curve.
fn grid_peak(points: &[HarmonicPoint]) -> HarmonicPoint {
    *points
        .iter()
        .max_by(|a, b| {
            a.amplitude_ratio_m_per_n
                .total_cmp(&b.amplitude_ratio_m_per_n)
        })
        .expect("a sweep has points")
}

/// F12 (a) and (b), with the true peaks. Returns the headline values.
pub fn write_figure12(out_dir: &Path, options: &PaperOptions) -> anyhow::Result<Value> {
    let models = ModelSet::paper_models(1.0);
    let nonlinear = [("paper", models.paper), ("consistent", models.consistent)];
    let plan = if options.quick {
        SettlePlan::QUICK
    } else {
        SettlePlan::FULL
    };
    let (step_a, step_b) = if options.quick {
        (10.0, 6.0)
    } else {
        (2.0, 2.0)
    };
    let freqs_a = grid(10.0, 500.0, step_a);
    let freqs_b = grid(150.0, 210.0, step_b);
    let mass = RAIL_MASS_UNIT_LENGTH_KG;

    // Curves: (a) = 2 models at 6 kN; (b) = 2 models x 4 preloads.
    let mut jobs = Vec::new();
    for (model_idx, (_, model)) in nonlinear.iter().enumerate() {
        for &f in &freqs_a {
            jobs.push(Job {
                curve_idx: model_idx,
                model: *model,
                preload_n: PRELOADS_N[0],
                frequency_hz: f,
            });
        }
    }
    for (preload_idx, &preload_n) in PRELOADS_N.iter().enumerate() {
        for (model_idx, (_, model)) in nonlinear.iter().enumerate() {
            for &f in &freqs_b {
                jobs.push(Job {
                    curve_idx: 2 + 2 * preload_idx + model_idx,
                    model: *model,
                    preload_n,
                    frequency_hz: f,
                });
            }
        }
    }
    stage(&format!(
        "F12: {} steady-state runs on the grids (2 threads)",
        jobs.len()
    ));
    let bar = progress_bar(jobs.len(), "F12 grid");
    let points = run_jobs(&jobs, plan, &bar);
    bar.finish_and_clear();
    let curve = |idx: usize| -> Vec<HarmonicPoint> {
        jobs.iter()
            .zip(&points)
            .filter(|(j, _)| j.curve_idx == idx)
            .map(|(_, p)| *p)
            .collect()
    };

    // True peaks of (b)'s curves. At F1 = 1 kN the resonance is strongly nonlinear: the
    // element reaches the tension limit, the resonance softens and bends to lower
    // frequencies with a jump, so the response of a run started from static equilibrium
    // is not a smooth unimodal curve and the true peak can lie more than one grid step
    // below the grid maximum (a golden-section search within +-1 step ran into its lower
    // bracket). So: scan [grid max - 6 Hz, grid max + 4 Hz] finely, then golden-section
    // search within +-1 scan step of the scan maximum.
    let (scan_step, iterations) = if options.quick { (1.0, 6) } else { (0.25, 12) };
    let peak_curves: Vec<(usize, usize, f64, HarmonicPoint)> = (0..PRELOADS_N.len())
        .flat_map(|p| (0..2).map(move |m| (p, m)))
        .map(|(p, m)| (p, m, PRELOADS_N[p], grid_peak(&curve(2 + 2 * p + m))))
        .collect();
    let mut scan_jobs = Vec::new();
    for (curve_idx, &(_, m, preload_n, gp)) in peak_curves.iter().enumerate() {
        let lo = (gp.frequency_hz - 6.0).max(freqs_b[0]);
        let hi = (gp.frequency_hz + 4.0).min(freqs_b[freqs_b.len() - 1]);
        for f in grid(lo, hi, scan_step) {
            scan_jobs.push(Job {
                curve_idx,
                model: nonlinear[m].1,
                preload_n,
                frequency_hz: f,
            });
        }
    }
    stage(&format!(
        "F12: scanning {} peaks at {scan_step} Hz ({} runs), then golden-section search",
        peak_curves.len(),
        scan_jobs.len()
    ));
    let bar = progress_bar(scan_jobs.len(), "F12 peak scan");
    let scan_points = run_jobs(&scan_jobs, plan, &bar);
    bar.finish_and_clear();
    let scan_peak = |curve_idx: usize| -> HarmonicPoint {
        let pts: Vec<HarmonicPoint> = scan_jobs
            .iter()
            .zip(&scan_points)
            .filter(|(j, _)| j.curve_idx == curve_idx)
            .map(|(_, p)| *p)
            .collect();
        grid_peak(&pts)
    };
    let bar = progress_bar(peak_curves.len(), "F12 golden-section");
    let next = AtomicUsize::new(0);
    let true_peaks: Mutex<Vec<Option<HarmonicPoint>>> = Mutex::new(vec![None; peak_curves.len()]);
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| loop {
                let idx = next.fetch_add(1, Ordering::Relaxed);
                let Some(&(_, m, preload_n, _)) = peak_curves.get(idx) else {
                    break;
                };
                let sp = scan_peak(idx);
                let found = golden_section_peak(
                    nonlinear[m].1,
                    preload_n,
                    sp.frequency_hz - scan_step,
                    sp.frequency_hz + scan_step,
                    iterations,
                    plan,
                );
                // The search samples only inside the bracket; keep the scan point if higher.
                let best = if found.amplitude_ratio_m_per_n >= sp.amplitude_ratio_m_per_n {
                    found
                } else {
                    sp
                };
                true_peaks
                    .lock()
                    .expect("no worker panics holding the lock")[idx] = Some(best);
                bar.inc(1);
            });
        }
    });
    bar.finish_and_clear();
    let true_peaks: Vec<HarmonicPoint> = true_peaks
        .into_inner()
        .expect("workers finished")
        .into_iter()
        .map(|p| p.expect("every peak ran"))
        .collect();
    let peak_jobs = peak_curves;
    let scan_cols: Vec<Vec<f64>> = vec![
        scan_jobs.iter().map(|j| j.preload_n).collect(),
        scan_jobs
            .iter()
            .map(|j| (peak_jobs[j.curve_idx].1) as f64)
            .collect(),
        scan_jobs.iter().map(|j| j.frequency_hz).collect(),
        scan_points
            .iter()
            .map(|p| p.amplitude_ratio_m_per_n)
            .collect(),
        scan_points.iter().map(|p| p.phase_rad).collect(),
        scan_points.iter().map(|p| p.settle_change).collect(),
        scan_points
            .iter()
            .map(|p| f64::from(u8::from(p.tension_clamped)))
            .collect(),
    ];
    write_csv(
        &out_path(out_dir, "f12_peak_scans.csv"),
        &[
            "preload_n",
            "model_index",
            "frequency_hz",
            "amplitude_ratio_m_per_n",
            "phase_rad",
            "settle_change",
            "tension_clamped",
        ],
        &scan_cols.iter().map(Vec::as_slice).collect::<Vec<_>>(),
    )?;

    // The linear model: exact FRF on the grids and its exact peak.
    let linear_ratio = |f: f64| linear_frf(&models.linear, mass, f).norm();
    let linear_phase = |f: f64| lagging_phase(linear_frf(&models.linear, mass, f));
    let lin = equivalent(&models.linear, 0.0, 1.0);
    let zeta = lin.c_eq_ns_per_m / (2.0 * (lin.k_eq_n_per_m * mass).sqrt());
    let linear_peak_hz =
        (lin.k_eq_n_per_m / mass).sqrt() * (1.0 - 2.0 * zeta * zeta).sqrt() / TWO_PI;
    let linear_peak_ratio = linear_ratio(linear_peak_hz);
    let linear_grid_peak_hz = freqs_b
        .iter()
        .copied()
        .max_by(|a, b| linear_ratio(*a).total_cmp(&linear_ratio(*b)))
        .unwrap_or(f64::NAN);
    let linear_grid_peak_ratio = linear_ratio(linear_grid_peak_hz);

    // CSVs.
    let (pa, pc) = (curve(0), curve(1));
    let col = |pts: &[HarmonicPoint], f: &dyn Fn(&HarmonicPoint) -> f64| -> Vec<f64> {
        pts.iter().map(f).collect()
    };
    write_csv(
        &out_path(out_dir, "f12a_harmonic_sweep.csv"),
        &[
            "frequency_hz",
            "amplitude_ratio_paper_m_per_n",
            "phase_paper_rad",
            "settle_change_paper",
            "amplitude_ratio_consistent_m_per_n",
            "phase_consistent_rad",
            "settle_change_consistent",
            "amplitude_ratio_linear_m_per_n",
            "phase_linear_rad",
            "tension_clamped_paper",
            "tension_clamped_consistent",
        ],
        &[
            &freqs_a,
            &col(&pa, &|p| p.amplitude_ratio_m_per_n),
            &col(&pa, &|p| p.phase_rad),
            &col(&pa, &|p| p.settle_change),
            &col(&pc, &|p| p.amplitude_ratio_m_per_n),
            &col(&pc, &|p| p.phase_rad),
            &col(&pc, &|p| p.settle_change),
            &freqs_a.iter().map(|&f| linear_ratio(f)).collect::<Vec<_>>(),
            &freqs_a.iter().map(|&f| linear_phase(f)).collect::<Vec<_>>(),
            &col(&pa, &|p| f64::from(u8::from(p.tension_clamped))),
            &col(&pc, &|p| f64::from(u8::from(p.tension_clamped))),
        ],
    )?;
    let mut b_cols: Vec<Vec<f64>> = vec![Vec::new(); 12];
    for (p_idx, &preload_n) in PRELOADS_N.iter().enumerate() {
        let (cp, cc) = (curve(2 + 2 * p_idx), curve(3 + 2 * p_idx));
        for (i, &f) in freqs_b.iter().enumerate() {
            let row = [
                preload_n,
                f,
                cp[i].amplitude_ratio_m_per_n,
                cp[i].phase_rad,
                cp[i].settle_change,
                cc[i].amplitude_ratio_m_per_n,
                cc[i].phase_rad,
                cc[i].settle_change,
                linear_ratio(f),
                linear_phase(f),
                f64::from(u8::from(cp[i].tension_clamped)),
                f64::from(u8::from(cc[i].tension_clamped)),
            ];
            for (c, v) in b_cols.iter_mut().zip(row) {
                c.push(v);
            }
        }
    }
    write_csv(
        &out_path(out_dir, "f12b_harmonic_sweep.csv"),
        &[
            "preload_n",
            "frequency_hz",
            "amplitude_ratio_paper_m_per_n",
            "phase_paper_rad",
            "settle_change_paper",
            "amplitude_ratio_consistent_m_per_n",
            "phase_consistent_rad",
            "settle_change_consistent",
            "amplitude_ratio_linear_m_per_n",
            "phase_linear_rad",
            "tension_clamped_paper",
            "tension_clamped_consistent",
        ],
        &b_cols.iter().map(Vec::as_slice).collect::<Vec<_>>(),
    )?;
    let mut peak_cols: Vec<Vec<f64>> = vec![Vec::new(); 8];
    let mut peak_json = Vec::new();
    for (i, &(_, m, preload_n, gp)) in peak_jobs.iter().enumerate() {
        let tp = true_peaks[i];
        let row = [
            preload_n,
            m as f64,
            gp.frequency_hz,
            gp.amplitude_ratio_m_per_n,
            tp.frequency_hz,
            tp.amplitude_ratio_m_per_n,
            tp.settle_change,
            f64::from(u8::from(tp.tension_clamped)),
        ];
        for (c, v) in peak_cols.iter_mut().zip(row) {
            c.push(v);
        }
        let (ss_f, ss_ratio) = small_signal_peak(&nonlinear[m].1, mass, preload_n);
        let clamped: Vec<f64> = curve(2 + 2 * peak_jobs[i].0 + m)
            .iter()
            .filter(|p| p.tension_clamped)
            .map(|p| p.frequency_hz)
            .collect();
        let clamped_band = match (clamped.first(), clamped.last()) {
            (Some(lo), Some(hi)) => json!([lo, hi]),
            _ => Value::Null,
        };
        peak_json.push(json!({
            "small_signal_peak_frequency_hz": ss_f,
            "small_signal_peak_amplitude_ratio_m_per_n": ss_ratio,
            "small_signal_peak_over_linear_peak": ss_ratio / linear_peak_ratio,
            "grid_tension_clamped_band_hz": clamped_band,
            "model": nonlinear[m].0,
            "preload_n": preload_n,
            "grid_peak_frequency_hz": gp.frequency_hz,
            "grid_peak_amplitude_ratio_m_per_n": gp.amplitude_ratio_m_per_n,
            "grid_peak_over_linear_grid_peak": gp.amplitude_ratio_m_per_n / linear_grid_peak_ratio,
            "true_peak_frequency_hz": tp.frequency_hz,
            "true_peak_amplitude_ratio_m_per_n": tp.amplitude_ratio_m_per_n,
            "true_peak_over_linear_peak": tp.amplitude_ratio_m_per_n / linear_peak_ratio,
            "true_peak_settle_change": tp.settle_change,
            "true_peak_tension_clamped": tp.tension_clamped,
            "frequency_shift_from_linear_peak_hz": tp.frequency_hz - linear_peak_hz,
        }));
    }
    write_csv(
        &out_path(out_dir, "f12_true_peaks.csv"),
        &[
            "preload_n",
            "model_index",
            "grid_peak_frequency_hz",
            "grid_peak_amplitude_ratio_m_per_n",
            "true_peak_frequency_hz",
            "true_peak_amplitude_ratio_m_per_n",
            "true_peak_settle_change",
            "true_peak_tension_clamped",
        ],
        &peak_cols.iter().map(Vec::as_slice).collect::<Vec<_>>(),
    )?;

    // Plots.
    let fine = |lo: f64, hi: f64| grid(lo, hi, 0.05);
    let fa = fine(10.0, 500.0);
    let mut amp_a = Panel::new(
        "(a) P = 6 kN, F1 = 1 kN, per metre: amplitude ratio",
        "frequency (Hz)",
        "|X| / F1 (m/N)",
    )
    .log_y()
    .with(Series::line(
        "linear Kelvin-Voigt (exact FRF)",
        fa.clone(),
        fa.iter().map(|&f| linear_ratio(f)).collect(),
        model_color("linear"),
    ));
    let mut phase_a =
        Panel::new("(a) phase delay", "frequency (Hz)", "phase (rad)").with(Series::line(
            "linear Kelvin-Voigt (exact FRF)",
            fa.clone(),
            fa.iter().map(|&f| linear_phase(f)).collect(),
            model_color("linear"),
        ));
    for (m, (key, _)) in nonlinear.iter().enumerate() {
        let pts = curve(m);
        let label = format!("nonlinear, {key} form (time domain, {step_a} Hz grid)");
        let series =
            |y: Vec<f64>| Series::line(label.clone(), freqs_a.clone(), y, model_color(key));
        amp_a = amp_a.with(series(col(&pts, &|p| p.amplitude_ratio_m_per_n)));
        phase_a = phase_a.with(series(col(&pts, &|p| p.phase_rad)));
    }
    draw_png(
        &out_path(out_dir, "f12a_harmonic_sweep.png"),
        1200,
        1000,
        1,
        &[amp_a, phase_a],
    )?;
    let fb = fine(150.0, 210.0);
    let mut panels_b = Vec::new();
    for (m, (key, _)) in nonlinear.iter().enumerate() {
        let mut amp = Panel::new(
            format!("(b) {key} form, F1 = 1 kN: amplitude ratio, lines on the {step_b} Hz grid"),
            "frequency (Hz)",
            "|X| / F1 (m/N)",
        )
        .log_y()
        .with(Series::line(
            "linear Kelvin-Voigt",
            fb.clone(),
            fb.iter().map(|&f| linear_ratio(f)).collect(),
            5,
        ));
        let mut phase = Panel::new(
            format!("(b) {key} form: phase delay"),
            "frequency (Hz)",
            "phase (rad)",
        )
        .with(Series::line(
            "linear Kelvin-Voigt",
            fb.clone(),
            fb.iter().map(|&f| linear_phase(f)).collect(),
            5,
        ));
        for (p_idx, &preload_n) in PRELOADS_N.iter().enumerate() {
            let pts = curve(2 + 2 * p_idx + m);
            let color = COLOR_PRELOAD[p_idx];
            let label = format!("P = {:.0} kN", preload_n * 1e-3);
            amp = amp.with(Series::line(
                label.clone(),
                freqs_b.clone(),
                col(&pts, &|p| p.amplitude_ratio_m_per_n),
                color,
            ));
            // The F1 -> 0 limit, to show what the 1 kN amplitude's nonlinearity removes.
            amp = amp.with(Series::dashed(
                if p_idx == 0 {
                    "dashed: small-signal FRF (F1 -> 0)"
                } else {
                    ""
                },
                fb.clone(),
                fb.iter()
                    .map(|&f| small_signal_frf(&nonlinear[m].1, mass, preload_n, f).norm())
                    .collect(),
                color,
            ));
            let (scan_f, scan_r): (Vec<f64>, Vec<f64>) = scan_jobs
                .iter()
                .zip(&scan_points)
                .filter(|(j, _)| j.curve_idx == 2 * p_idx + m)
                .map(|(j, p)| (j.frequency_hz, p.amplitude_ratio_m_per_n))
                .unzip();
            amp = amp.with(Series::points(
                if p_idx == 0 {
                    format!("dots: {scan_step} Hz scan for the true peak")
                } else {
                    String::new()
                },
                scan_f,
                scan_r,
                color,
            ));
            // The true peak is the top of the scan dots (refined by at most one scan step).
            phase = phase.with(Series::line(
                label,
                freqs_b.clone(),
                col(&pts, &|p| p.phase_rad),
                color,
            ));
        }
        panels_b.push(amp);
        panels_b.push(phase);
    }
    // Order: amplitude row on top, phase row below, paper form left, consistent right.
    let ordered = vec![
        panels_b[0].clone(),
        panels_b[2].clone(),
        panels_b[1].clone(),
        panels_b[3].clone(),
    ];
    draw_png(
        &out_path(out_dir, "f12b_harmonic_sweep.png"),
        1600,
        1100,
        2,
        &ordered,
    )?;

    let grid_a = |m: usize| grid_peak(&curve(m));
    let max_settle_change = points
        .iter()
        .map(|p| p.settle_change)
        .fold(0.0f64, f64::max);
    let any_clamped = points.iter().any(|p| p.tension_clamped);
    Ok(json!({
        "force_amplitude_n": FORCE_AMPLITUDE_N,
        "mass_kg": mass,
        "grid_step_a_hz": step_a,
        "grid_step_b_hz": step_b,
        "linear": {
            "peak_frequency_hz": linear_peak_hz,
            "peak_amplitude_ratio_m_per_n": linear_peak_ratio,
            "grid_peak_frequency_hz": linear_grid_peak_hz,
            "grid_peak_amplitude_ratio_m_per_n": linear_grid_peak_ratio,
        },
        // Sweep (a) is the 6 kN curve of (b) extended to 10-500 Hz (same model, preload
        // and amplitude), so its true peak is (b)'s 6 kN true peak.
        "sweep_a": {
            "paper": {
                "grid_peak_frequency_hz": grid_a(0).frequency_hz,
                "grid_peak_amplitude_ratio_m_per_n": grid_a(0).amplitude_ratio_m_per_n,
                "true_peak_frequency_hz": true_peaks[0].frequency_hz,
                "true_peak_amplitude_ratio_m_per_n": true_peaks[0].amplitude_ratio_m_per_n,
            },
            "consistent": {
                "grid_peak_frequency_hz": grid_a(1).frequency_hz,
                "grid_peak_amplitude_ratio_m_per_n": grid_a(1).amplitude_ratio_m_per_n,
                "true_peak_frequency_hz": true_peaks[1].frequency_hz,
                "true_peak_amplitude_ratio_m_per_n": true_peaks[1].amplitude_ratio_m_per_n,
            },
        },
        "model_index": {"0": "paper", "1": "consistent"},
        "peaks": peak_json,
        "max_settle_change": max_settle_change,
        "any_tension_clamped": any_clamped,
    }))
}
