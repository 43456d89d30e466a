//! F13 and F14: one metre of ERS (rail mass on the element) under an ETR 500 coach at
//! 72 km/h plus a 20 N force at 170 Hz (rail roughness of 120 mm wavelength).
//!
//! The quasi-static passage force per metre is the static Winkler foundation force
//! `k_static w(t)` (60 MN/m^2 times the F7 deflection at 20 m/s), the first bogie's
//! centre passing at t = 1.5 s so that the paper's windows (1.2-1.8 s, 1.7-1.8 s, and
//! the 3 s spectrum window 0-3 s) are centred on it; the second bogie follows at 2.45 s.
//! The simulation starts at t = 0 in static equilibrium under the first force sample
//! (practically zero: the first axle is 28.5 m away) and the 170 Hz force starts then as
//! `20 N sin(W t)`, so it does not jump. Its start excites the rail's free vibration at
//! the natural frequency at low preload (173.5 Hz for the nonlinear model, whose damping
//! there lets it ring for seconds): this is the paper's "transient peak near 173 Hz".
//!
//! Step: 1/17000 s, i.e. exactly 100 samples per 170 Hz cycle, so a moving average over
//! 100 samples removes the 170 Hz component exactly: that average is the low-frequency
//! displacement, and the rest is the high-frequency vibration.
//!
//! Spectra (F14): one-sided amplitude spectra of the rail velocity and the transmitted
//! (element) force over 0-3 s with a Hann window (amplitude-corrected: a sinusoid of
//! amplitude A shows a peak of A), zero-padded 4x for a smooth plot; resolution is still
//! the window's 1/3 Hz (Hann main lobe +-0.67 Hz), enough to separate 170 from 173 Hz.

use std::path::Path;

use realfft::RealFftPlanner;
use serde_json::{json, Value};

use super::{model_color, out_path, single_bin_dft, write_csv, ModelSet, RAIL_MASS_UNIT_LENGTH_KG};
use crate::model::oscillator::{simulate_rail, RailSample, StartCondition};
use crate::plot::{draw_png, Panel, Series};
use crate::track::{kmh_to_m_per_s, TrainPassage};

const TWO_PI: f64 = 2.0 * std::f64::consts::PI;
/// Train speed of paper Figs. 13-14, km/h.
pub const TRAIN_SPEED_KMH: f64 = 72.0;
/// Roughness force: amplitude N and frequency Hz.
pub const ROUGHNESS_FORCE_N: f64 = 20.0;
pub const ROUGHNESS_FREQUENCY_HZ: f64 = 170.0;
/// Samples per roughness cycle.
pub const SAMPLES_PER_CYCLE: usize = 100;
/// Instant the first bogie's centre passes, s.
pub const BOGIE_CENTRE_S: f64 = 1.5;
/// Simulated time = the F14 spectrum window, s.
pub const DURATION_S: f64 = 3.0;
/// Window of the high-frequency comparison (paper Fig. 13b), s.
pub const RIPPLE_WINDOW_S: (f64, f64) = (1.7, 1.8);
/// Band searched for the nonlinear model's transient peak, Hz.
pub const TRANSIENT_BAND_HZ: (f64, f64) = (171.0, 180.0);

/// Time step of the F13 simulation, s.
pub fn train_dt_s() -> f64 {
    1.0 / (ROUGHNESS_FREQUENCY_HZ * SAMPLES_PER_CYCLE as f64)
}

/// The external force per metre: passage + roughness, N.
pub fn external_force_n() -> (Vec<f64>, Vec<f64>) {
    let dt = train_dt_s();
    let train = TrainPassage::etr500_coach(kmh_to_m_per_s(TRAIN_SPEED_KMH));
    // First axle passes 1.5 m (half the wheelbase) before the bogie centre.
    let t_first_s = BOGIE_CENTRE_S - 1.5 / train.speed_m_per_s;
    let n = (DURATION_S / dt).round() as usize;
    let time_s: Vec<f64> = (0..n).map(|i| i as f64 * dt).collect();
    let force = time_s
        .iter()
        .map(|&t| {
            train.force_per_m_history(t, t_first_s)
                + ROUGHNESS_FORCE_N * (TWO_PI * ROUGHNESS_FREQUENCY_HZ * t).sin()
        })
        .collect();
    (time_s, force)
}

/// Centred moving average over one roughness cycle (the low-frequency part); the ends
/// repeat the nearest full average.
pub fn low_frequency_part(x: &[f64]) -> Vec<f64> {
    let n = SAMPLES_PER_CYCLE;
    if x.len() < n {
        return x.to_vec();
    }
    let mut out = vec![0.0; x.len()];
    let mut sum: f64 = x[..n].iter().sum();
    let half = n / 2;
    let mut averages = Vec::with_capacity(x.len() - n + 1);
    averages.push(sum / n as f64);
    for i in n..x.len() {
        sum += x[i] - x[i - n];
        averages.push(sum / n as f64);
    }
    for (i, o) in out.iter_mut().enumerate() {
        let j = i.saturating_sub(half).min(averages.len() - 1);
        *o = averages[j];
    }
    out
}

/// One-sided Hann-windowed amplitude spectrum, zero-padded by `pad`: (frequency Hz, amplitude).
pub fn hann_amplitude_spectrum(x: &[f64], dt_s: f64, pad: usize) -> (Vec<f64>, Vec<f64>) {
    let n = x.len();
    let n_fft = n * pad.max(1);
    let window: Vec<f64> = (0..n)
        .map(|i| 0.5 - 0.5 * (TWO_PI * i as f64 / n as f64).cos())
        .collect();
    let window_sum: f64 = window.iter().sum();
    let mut input = vec![0.0; n_fft];
    for (i, v) in input.iter_mut().take(n).enumerate() {
        *v = x[i] * window[i];
    }
    let mut planner = RealFftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(n_fft);
    let mut spectrum = fft.make_output_vec();
    // Lengths come from the plan itself, so the transform cannot fail.
    fft.process(&mut input, &mut spectrum)
        .expect("buffer lengths match the plan");
    let df = 1.0 / (n_fft as f64 * dt_s);
    let freqs = (0..spectrum.len()).map(|k| k as f64 * df).collect();
    let amps = spectrum
        .iter()
        .map(|c| 2.0 * c.norm() / window_sum)
        .collect();
    (freqs, amps)
}

/// Largest local maximum of a spectrum within `band`: (frequency, amplitude), and its
/// prominence (its amplitude over the lowest value between the band's start and it).
pub fn band_peak(freqs: &[f64], amps: &[f64], band: (f64, f64)) -> Option<(f64, f64, f64)> {
    let idx: Vec<usize> = (1..freqs.len() - 1)
        .filter(|&k| freqs[k] > band.0 && freqs[k] <= band.1)
        .collect();
    let start = *idx.first()?;
    idx.iter()
        .copied()
        .filter(|&k| amps[k] > amps[k - 1] && amps[k] >= amps[k + 1])
        .max_by(|&a, &b| amps[a].total_cmp(&amps[b]))
        .map(|k| {
            let trough = amps[start..=k]
                .iter()
                .copied()
                .fold(f64::INFINITY, f64::min);
            (freqs[k], amps[k], amps[k] / trough.max(1e-300))
        })
}

/// F13 and F14 for the three models. Returns the two summaries.
pub fn write_figures13_14(out_dir: &Path) -> anyhow::Result<(Value, Value)> {
    let dt = train_dt_s();
    let (time_s, force_n) = external_force_n();
    let models = ModelSet::paper_models(1.0);
    let runs: Vec<(&str, &str, Vec<RailSample>)> = models
        .named()
        .into_iter()
        .map(|(key, label, model)| {
            let (samples, _flags) = simulate_rail(
                model,
                RAIL_MASS_UNIT_LENGTH_KG,
                dt,
                &force_n,
                StartCondition::Static,
            );
            (key, label, samples)
        })
        .collect();

    let mut f13 = serde_json::Map::new();
    let mut columns: Vec<Vec<f64>> = vec![time_s.clone(), force_n.clone()];
    let mut panel_a = Panel::new(
        "(a) Coach at 72 km/h + 20 N at 170 Hz, per metre: first bogie",
        "time (s)",
        "rail displacement, downward positive (mm)",
    )
    .x_range(1.2, 1.8);
    let mut panel_b = Panel::new(
        "(b) Detail: high-frequency vibration after the first bogie",
        "time (s)",
        "rail displacement, downward positive (mm)",
    )
    .x_range(RIPPLE_WINDOW_S.0, RIPPLE_WINDOW_S.1);
    let window_idx = |t0: f64, t1: f64| {
        let i0 = (t0 / dt).round() as usize;
        let i1 = ((t1 / dt).round() as usize).min(time_s.len());
        (i0, i1)
    };
    let (r0, r1) = window_idx(RIPPLE_WINDOW_S.0, RIPPLE_WINDOW_S.1);
    let mut spectra_cols: Vec<Vec<f64>> = Vec::new();
    let mut spectrum_panels = [
        Panel::new(
            "(a) Rail velocity spectrum, 0-50 Hz (3 s Hann window)",
            "frequency (Hz)",
            "velocity amplitude (m/s)",
        )
        .log_y()
        .x_range(0.0, 50.0),
        Panel::new(
            "(a) Rail velocity spectrum, 150-200 Hz",
            "frequency (Hz)",
            "velocity amplitude (m/s)",
        )
        .log_y()
        .x_range(150.0, 200.0),
        Panel::new(
            "(b) Transmitted force spectrum, 0-50 Hz",
            "frequency (Hz)",
            "force amplitude (N)",
        )
        .log_y()
        .x_range(0.0, 50.0),
        Panel::new(
            "(b) Transmitted force spectrum, 150-200 Hz",
            "frequency (Hz)",
            "force amplitude (N)",
        )
        .log_y()
        .x_range(150.0, 200.0),
    ];
    let mut f14 = serde_json::Map::new();
    let mut detail_range_mm = (f64::INFINITY, f64::NEG_INFINITY);
    for (key, label, samples) in &runs {
        let x: Vec<f64> = samples.iter().map(|s| s.displacement_m).collect();
        let v: Vec<f64> = samples.iter().map(|s| s.velocity_m_per_s).collect();
        let f: Vec<f64> = samples.iter().map(|s| s.element_force_n).collect();
        let low = low_frequency_part(&x);
        let high: Vec<f64> = x.iter().zip(&low).map(|(a, b)| a - b).collect();
        let max_low = low.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let (hmin, hmax) = high[r0..r1]
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &h| {
                (a.min(h), b.max(h))
            });
        let bin_170 = single_bin_dft(&high[r0..r1], dt, r0 as f64 * dt, ROUGHNESS_FREQUENCY_HZ);
        let (freqs, v_amp) = hann_amplitude_spectrum(&v, dt, 4);
        let (_, f_amp) = hann_amplitude_spectrum(&f, dt, 4);
        let line = |amps: &[f64]| band_peak(&freqs, amps, (169.0, 171.0)).map_or(f64::NAN, |p| p.1);
        let transient = |amps: &[f64]| {
            band_peak(&freqs, amps, TRANSIENT_BAND_HZ).map(
                |(fr, a, prom)| json!({"frequency_hz": fr, "amplitude": a, "prominence": prom}),
            )
        };
        f13.insert(
            key.to_string(),
            json!({
                "max_low_frequency_displacement_m": max_low,
                "ripple_half_swing_1_7_to_1_8_s_m": 0.5 * (hmax - hmin),
                "amplitude_170_hz_1_7_to_1_8_s_m": bin_170.norm(),
            }),
        );
        f14.insert(
            key.to_string(),
            json!({
                "velocity_170_hz_m_per_s": line(&v_amp),
                "force_170_hz_n": line(&f_amp),
                "velocity_peak_171_to_180_hz": transient(&v_amp),
                "force_peak_171_to_180_hz": transient(&f_amp),
            }),
        );
        let color = model_color(key);
        let x_mm: Vec<f64> = x.iter().map(|x| x * 1e3).collect();
        let series = |label: &str, xs: Vec<f64>, ys: Vec<f64>| Series::line(label, xs, ys, color);
        let (a0, a1) = window_idx(1.2, 1.8);
        panel_a = panel_a.with(series(
            label,
            time_s[a0..a1].to_vec(),
            x_mm[a0..a1].to_vec(),
        ));
        detail_range_mm = x_mm[r0..r1]
            .iter()
            .fold(detail_range_mm, |(lo, hi), &v| (lo.min(v), hi.max(v)));
        panel_b = panel_b.with(series(
            label,
            time_s[r0..r1].to_vec(),
            x_mm[r0..r1].to_vec(),
        ));
        let keep = |lo: f64, hi: f64| -> Vec<usize> {
            (0..freqs.len())
                .filter(|&k| freqs[k] >= lo && freqs[k] <= hi)
                .collect()
        };
        for (panel_idx, (amps, lo, hi)) in [
            (&v_amp, 0.0, 50.0),
            (&v_amp, 150.0, 200.0),
            (&f_amp, 0.0, 50.0),
            (&f_amp, 150.0, 200.0),
        ]
        .into_iter()
        .enumerate()
        {
            let k = keep(lo, hi);
            let panel = std::mem::take(&mut spectrum_panels[panel_idx]);
            spectrum_panels[panel_idx] = panel.with(series(
                label,
                k.iter().map(|&i| freqs[i]).collect(),
                k.iter().map(|&i| amps[i]).collect(),
            ));
        }
        if spectra_cols.is_empty() {
            spectra_cols.push(freqs.iter().copied().filter(|&f| f <= 250.0).collect());
        }
        let n_keep = spectra_cols[0].len();
        spectra_cols.push(v_amp[..n_keep].to_vec());
        spectra_cols.push(f_amp[..n_keep].to_vec());
        columns.push(x);
        columns.push(v);
        columns.push(f);
    }
    // Headroom above the detail's curves keeps the legend (upper right) off them.
    let (lo, hi) = detail_range_mm;
    panel_b = panel_b.y_range(lo - 0.05 * (hi - lo), hi + 0.45 * (hi - lo));
    let ratio = |map: &serde_json::Map<String, Value>, model: &str, field: &str| {
        map[model][field].as_f64().unwrap_or(f64::NAN)
            / map["linear"][field].as_f64().unwrap_or(f64::NAN)
    };
    for model in ["paper", "consistent"] {
        let entry = json!({
            "low_frequency_displacement_ratio":
                ratio(&f13, model, "max_low_frequency_displacement_m"),
            "ripple_half_swing_ratio": ratio(&f13, model, "ripple_half_swing_1_7_to_1_8_s_m"),
            "amplitude_170_hz_ratio": ratio(&f13, model, "amplitude_170_hz_1_7_to_1_8_s_m"),
        });
        f13.insert(format!("{model}_over_linear"), entry);
    }
    f13.insert("speed_kmh".into(), json!(TRAIN_SPEED_KMH));
    f13.insert("bogie_centre_s".into(), json!(BOGIE_CENTRE_S));
    f14.insert("window_s".into(), json!([0.0, DURATION_S]));
    f14.insert("window_function".into(), json!("hann"));
    write_csv(
        &out_path(out_dir, "f13_train_passage.csv"),
        &[
            "t_s",
            "external_force_n",
            "displacement_paper_m",
            "velocity_paper_m_per_s",
            "element_force_paper_n",
            "displacement_consistent_m",
            "velocity_consistent_m_per_s",
            "element_force_consistent_n",
            "displacement_linear_m",
            "velocity_linear_m_per_s",
            "element_force_linear_n",
        ],
        &columns.iter().map(Vec::as_slice).collect::<Vec<_>>(),
    )?;
    write_csv(
        &out_path(out_dir, "f14_spectra.csv"),
        &[
            "frequency_hz",
            "velocity_amplitude_paper_m_per_s",
            "force_amplitude_paper_n",
            "velocity_amplitude_consistent_m_per_s",
            "force_amplitude_consistent_n",
            "velocity_amplitude_linear_m_per_s",
            "force_amplitude_linear_n",
        ],
        &spectra_cols.iter().map(Vec::as_slice).collect::<Vec<_>>(),
    )?;
    draw_png(
        &out_path(out_dir, "f13_train_passage.png"),
        1200,
        1000,
        1,
        &[panel_a, panel_b],
    )?;
    draw_png(
        &out_path(out_dir, "f14_spectra.png"),
        1600,
        1100,
        2,
        &spectrum_panels,
    )?;
    Ok((Value::Object(f13), Value::Object(f14)))
}
