//! Plots shared by `identify` and `diagnose`: k_eq / c_eq against frequency per preload
//! (paper Fig. 6 style) and measured vs simulated force-displacement loops.

use std::f64::consts::PI;
use std::path::Path;

use super::history::predict_history;
use crate::ident::campaign::{cdiv, N_HARMONICS};
use crate::ident::fit::{predict_cycle, predict_cycle_with_waveform, CycleData};
use crate::model::effects::AugmentedModel;
use crate::plot::{draw_png, Panel, Series};

/// Distinct values (sorted), merging values within 1 % of each other.
pub fn distinct_levels(values: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut v: Vec<f64> = values.collect();
    v.sort_by(f64::total_cmp);
    let mut out: Vec<f64> = Vec::new();
    for x in v {
        match out.last() {
            Some(&last) if (x - last).abs() <= 0.01 * last.abs().max(x.abs()) + 1e-9 => {}
            _ => out.push(x),
        }
    }
    out
}

fn same_level(a: f64, b: f64) -> bool {
    (a - b).abs() <= 0.01 * a.abs().max(b.abs()) + 1e-9
}

/// k_eq (MN/m^2) and c_eq (MN s/m^2) of a test's first harmonic per metre.
pub fn equivalent_mn(
    force_1: (f64, f64),
    z_1: (f64, f64),
    frequency_hz: f64,
    length_m: f64,
) -> (f64, f64) {
    let (re, im) = cdiv(force_1, z_1);
    (
        re / length_m / 1e6,
        im / (2.0 * PI * frequency_hz) / length_m / 1e6,
    )
}

/// Paper Fig. 6 style: one column per preload, k_eq on top, c_eq below; measured points
/// and, for each model, its value at each test (points) and a curve at the reference
/// temperature and the preload's median displacement amplitude.
pub fn plot_equivalents(
    path: &Path,
    data: &[CycleData],
    length_m: f64,
    models: &[(&str, &AugmentedModel)],
    reference_temperature_c: f64,
) -> anyhow::Result<()> {
    let preloads = distinct_levels(data.iter().map(|d| d.preload_n));
    let mut k_panels = Vec::new();
    let mut c_panels = Vec::new();
    for &preload in &preloads {
        let tests: Vec<&CycleData> = data
            .iter()
            .filter(|d| same_level(d.preload_n, preload))
            .collect();
        let title = format!("P = {:.1} kN", preload / 1e3);
        let mut k_panel = Panel::new(title.clone(), "frequency (Hz)", "k_eq (MN/m^2)").log_x();
        let mut c_panel = Panel::new(title, "frequency (Hz)", "c_eq (MN s/m^2)").log_x();
        let f: Vec<f64> = tests.iter().map(|d| d.frequency_hz).collect();
        let measured: Vec<(f64, f64)> = tests
            .iter()
            .map(|d| {
                equivalent_mn(
                    d.force_harmonics_n[0],
                    d.displacement_harmonics_m[0],
                    d.frequency_hz,
                    length_m,
                )
            })
            .collect();
        k_panel = k_panel.with(Series::points(
            "measured",
            f.clone(),
            measured.iter().map(|m| m.0).collect(),
            0,
        ));
        c_panel = c_panel.with(Series::points(
            "measured",
            f.clone(),
            measured.iter().map(|m| m.1).collect(),
            0,
        ));
        let f_lo = f.iter().copied().fold(f64::INFINITY, f64::min);
        let f_hi = f.iter().copied().fold(0.0, f64::max);
        let mut amplitudes: Vec<f64> = tests.iter().map(|d| d.displacement_amplitude_m()).collect();
        amplitudes.sort_by(f64::total_cmp);
        let z_amp = amplitudes[amplitudes.len() / 2];
        let force_mean = tests.iter().map(|d| d.force_mean_n).sum::<f64>() / tests.len() as f64;
        for (model_idx, (label, model)) in models.iter().enumerate() {
            let color = model_idx + 1;
            let at_tests: Vec<(f64, f64)> = tests
                .iter()
                .map(|d| {
                    let p = predict_cycle(model, d);
                    equivalent_mn(
                        p[0],
                        d.displacement_harmonics_m[0],
                        d.frequency_hz,
                        length_m,
                    )
                })
                .collect();
            k_panel = k_panel.with(Series::points(
                format!("{label} (at tests)"),
                f.clone(),
                at_tests.iter().map(|m| m.0).collect(),
                color,
            ));
            c_panel = c_panel.with(Series::points(
                format!("{label} (at tests)"),
                f.clone(),
                at_tests.iter().map(|m| m.1).collect(),
                color,
            ));
            let n_grid = 16;
            let grid: Vec<f64> = (0..n_grid)
                .map(|i| f_lo * (f_hi / f_lo).powf(i as f64 / (n_grid - 1) as f64))
                .collect();
            let curve: Vec<(f64, f64)> = grid
                .iter()
                .map(|&freq| {
                    let probe = CycleData {
                        id: String::new(),
                        frequency_hz: freq,
                        preload_n: preload,
                        amplitude_n: 0.0,
                        temperature_c: reference_temperature_c,
                        force_mean_n: force_mean,
                        displacement_harmonics_m: {
                            let mut z = [(0.0, 0.0); N_HARMONICS];
                            z[0] = (z_amp, 0.0);
                            z
                        },
                        force_harmonics_n: [(0.0, 0.0); N_HARMONICS],
                        scale_n: 1.0,
                        noise_relative: 0.0,
                        noise_smoothed: 0.0,
                        duration_s: 1.0 / freq,
                        weight: 1.0,
                        order: 0.0,
                        history: None,
                        time: Default::default(),
                    };
                    let p = predict_cycle(model, &probe);
                    equivalent_mn(p[0], (z_amp, 0.0), freq, length_m)
                })
                .collect();
            k_panel = k_panel.with(Series::line(
                label.to_string(),
                grid.clone(),
                curve.iter().map(|m| m.0).collect(),
                color,
            ));
            c_panel = c_panel.with(Series::line(
                label.to_string(),
                grid,
                curve.iter().map(|m| m.1).collect(),
                color,
            ));
        }
        k_panels.push(k_panel);
        c_panels.push(c_panel);
    }
    let cols = preloads.len().max(1);
    let panels: Vec<Panel> = k_panels.into_iter().chain(c_panels).collect();
    draw_png(path, (420 * cols) as u32, 760, cols, &panels)
}

/// Picks up to four tests spanning the design: lowest/highest preload x frequency.
pub fn loop_tests(data: &[CycleData]) -> Vec<usize> {
    let mut picks = Vec::new();
    if data.is_empty() {
        return picks;
    }
    let preloads = distinct_levels(data.iter().map(|d| d.preload_n));
    let targets = [
        (preloads[0], false),
        (preloads[0], true),
        (*preloads.last().unwrap_or(&0.0), false),
        (*preloads.last().unwrap_or(&0.0), true),
    ];
    for (preload, high_f) in targets {
        let best = data
            .iter()
            .enumerate()
            .filter(|(_, d)| same_level(d.preload_n, preload))
            .max_by(|a, b| {
                let fa = if high_f {
                    a.1.frequency_hz
                } else {
                    -a.1.frequency_hz
                };
                let fb = if high_f {
                    b.1.frequency_hz
                } else {
                    -b.1.frequency_hz
                };
                fa.total_cmp(&fb)
            })
            .map(|(i, _)| i);
        if let Some(i) = best {
            if !picks.contains(&i) {
                picks.push(i);
            }
        }
    }
    picks
}

/// Reconstructs a cycle `x(t) = sum_h Re(X_h e^{i h W t})` at `n` samples.
pub fn reconstruct(harmonics: &[(f64, f64); N_HARMONICS], n: usize) -> Vec<f64> {
    (0..=n)
        .map(|k| {
            let phase = 2.0 * PI * k as f64 / n as f64;
            harmonics
                .iter()
                .enumerate()
                .map(|(h, x)| {
                    let p = (h + 1) as f64 * phase;
                    x.0 * p.cos() - x.1 * p.sin()
                })
                .sum()
        })
        .collect()
}

/// Measured vs simulated steady-state loops (dynamic parts, mean removed) of the tests
/// `indices` (see `loop_tests`).
pub fn plot_loops(
    path: &Path,
    data: &[CycleData],
    indices: &[usize],
    models: &[(&str, &AugmentedModel)],
) -> anyhow::Result<()> {
    let mut panels = Vec::new();
    for &i in indices {
        let d = &data[i];
        let n = 128;
        let z_mm: Vec<f64> = reconstruct(&d.displacement_harmonics_m, n)
            .iter()
            .map(|z| z * 1e3)
            .collect();
        let f_kn: Vec<f64> = reconstruct(&d.force_harmonics_n, n)
            .iter()
            .map(|f| f / 1e3)
            .collect();
        let mut panel = Panel::new(
            format!(
                "{} ({:.1} kN, {} Hz)",
                d.id,
                d.preload_n / 1e3,
                d.frequency_hz
            ),
            "dynamic displacement (mm)",
            "dynamic force (kN)",
        )
        .with(Series::points("measured", z_mm.clone(), f_kn, 0));
        for (model_idx, (label, model)) in models.iter().enumerate() {
            let (p, _, _) = predict_cycle_with_waveform(model, d);
            let f_sim: Vec<f64> = reconstruct(&p, n).iter().map(|f| f / 1e3).collect();
            panel = panel.with(Series::line(
                label.to_string(),
                z_mm.clone(),
                f_sim,
                model_idx + 1,
            ));
        }
        panels.push(panel);
    }
    let cols = panels.len().clamp(1, 2);
    let rows = panels.len().div_ceil(cols).max(1);
    draw_png(path, 560 * cols as u32, 420 * rows as u32, cols, &panels)
}

/// Measured force of each history test against the force each model predicts for its
/// displacement (band-limited as compared, see `history`), one panel per test.
pub fn plot_histories(
    path: &Path,
    data: &[CycleData],
    models: &[(&str, &AugmentedModel)],
) -> anyhow::Result<()> {
    let mut panels = Vec::new();
    for d in data {
        let Some(history) = &d.history else { continue };
        let t = history.time_s();
        let to_kn = |v: &[f64]| v.iter().map(|f| f / 1e3).collect::<Vec<f64>>();
        let mut panel = Panel::new(
            format!("{} (history, band to {:.0} Hz)", d.id, history.band_hz),
            "time (s)",
            "force (kN)",
        )
        .with(Series::line(
            "measured",
            t.clone(),
            to_kn(&history.force_n),
            0,
        ));
        for (model_idx, (label, model)) in models.iter().enumerate() {
            let predicted = predict_history(
                &crate::ident::fit::model_for_test(model, d),
                history,
                d.temperature_c,
                d.time.schedule.is_some(),
            );
            // The comparison removes the mean difference; so does the plot.
            let shift = (history.force_n.iter().sum::<f64>() - predicted.iter().sum::<f64>())
                / predicted.len().max(1) as f64;
            let shifted: Vec<f64> = predicted.iter().map(|f| f + shift).collect();
            panel = panel.with(Series::line(
                label.to_string(),
                t.clone(),
                to_kn(&shifted),
                model_idx + 1,
            ));
        }
        panels.push(panel);
    }
    if panels.is_empty() {
        return Ok(());
    }
    let cols = panels.len().clamp(1, 2);
    let rows = panels.len().div_ceil(cols).max(1);
    draw_png(path, 700 * cols as u32, 420 * rows as u32, cols, &panels)
}
