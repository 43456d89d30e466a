//! F5: force-displacement loops of the 750 mm sample under a force-controlled load
//! `F(t) = P + F1 cos(W t)` (F1 = 5 kN): (6 kN, 1 Hz) and (18 kN, 5 Hz).
//!
//! The rig controls force, so the displacement is the unknown. No mass is involved (the
//! paper compensates the loading head's inertia), and a mass-on-element simulation with
//! a small mass would add a spurious resonance and a stiff ODE. Instead each form is
//! inverted exactly:
//!
//! - consistent form: `F = Fs(z) + Fm` and `dFm/dt = k2 dz/dt - a Fm` with
//!   `k2 dz/dt = (k2_0/k1_0) dFs/dt` (because `dFs/dz = k1_0 g(Fs)` and
//!   `k2 = k2_0 g(Fs)`). With `r = k2_0/k1_0` and `Fs = F - Fm` this is the *linear*
//!   ODE `(1 + r) dFm/dt = r dF/dt - a Fm` driven by the known force; then
//!   `z = Fs^-1(F - Fm)`.
//! - paper form (Eq. 3, P = F(t)): `dF/dt = g(F) [(k1_0 + k2_0) dz/dt + a k1_0 z] - a F`
//!   solved for `dz/dt = [(dF/dt + a F)/g(F) - a k1_0 z] / (k1_0 + k2_0)`, linear in `z`.
//! - Kelvin-Voigt: the closed-form steady state `z = P/k + Re{F1 e^(iWt) / (k + i c W)}`.
//!
//! Both ODEs are integrated with RK4 at 4000 steps per cycle from static equilibrium
//! under `F(0) = P + F1`; their transients decay at `a/(1 + r)` = 11.9 1/s, so after
//! `20 (1 + r)/a` ~ 1.7 s (e^-20) the last whole cycle is periodic to round-off.

use std::path::Path;

use realfft::num_complex::Complex64;
use serde_json::{json, Value};

use super::{model_color, out_path, write_csv, ModelSet, SAMPLE_LENGTH_M};
use crate::model::ElementModel;
use crate::plot::{draw_png, Panel, Series};

const TWO_PI: f64 = 2.0 * std::f64::consts::PI;
/// Force amplitude of the paper's tests (Table 2), N.
pub const FORCE_AMPLITUDE_N: f64 = 5e3;
/// The two test conditions of paper Fig. 5: (preload N, frequency Hz).
pub const FIGURE5_CASES: [(f64, f64); 2] = [(6e3, 1.0), (18e3, 5.0)];
const STEPS_PER_CYCLE: usize = 4000;

/// One steady-state cycle of a force-controlled test.
#[derive(Debug, Clone, PartialEq)]
pub struct ForceControlledCycle {
    pub time_s: Vec<f64>,
    pub force_n: Vec<f64>,
    pub displacement_m: Vec<f64>,
}

/// The steady-state displacement cycle of `model` under `P + F1 cos(W t)` (force control).
///
/// Returns `STEPS_PER_CYCLE + 1` samples of the last cycle (times from its start).
pub fn force_controlled_cycle(
    model: &ElementModel,
    preload_n: f64,
    amplitude_n: f64,
    frequency_hz: f64,
) -> ForceControlledCycle {
    let omega = TWO_PI * frequency_hz;
    let period_s = 1.0 / frequency_hz;
    let h = period_s / STEPS_PER_CYCLE as f64;
    let force = |t: f64| preload_n + amplitude_n * (omega * t).cos();
    let force_rate = |t: f64| -amplitude_n * omega * (omega * t).sin();
    let time_s: Vec<f64> = (0..=STEPS_PER_CYCLE).map(|i| i as f64 * h).collect();
    let force_n: Vec<f64> = time_s.iter().map(|&t| force(t)).collect();
    let displacement_m = match model {
        ElementModel::KelvinVoigt(p) => {
            let response = Complex64::new(amplitude_n, 0.0)
                / Complex64::new(p.k_n_per_m, p.c_ns_per_m * omega);
            time_s
                .iter()
                .map(|&t| {
                    preload_n / p.k_n_per_m + (response * Complex64::from_polar(1.0, omega * t)).re
                })
                .collect()
        }
        ElementModel::Consistent(p) | ElementModel::Paper(p) => {
            let a = p.relaxation_rate_per_s();
            let r = p.k2_0_n_per_m / p.k1_0_n_per_m;
            let settle_s = 20.0 * (1.0 + r) / a;
            let n_settle_cycles = (settle_s / period_s).ceil().max(1.0) as usize;
            // State: Fm (consistent) or z (paper), from static equilibrium under F(0).
            let consistent = matches!(model, ElementModel::Consistent(_));
            let rhs = |t: f64, y: f64| -> f64 {
                if consistent {
                    (r * force_rate(t) - a * y) / (1.0 + r)
                } else {
                    let f = force(t);
                    let g = p.preload_factor(f);
                    ((force_rate(t) + a * f) / g - a * p.k1_0_n_per_m * y)
                        / (p.k1_0_n_per_m + p.k2_0_n_per_m)
                }
            };
            let mut y = if consistent {
                0.0
            } else {
                model.static_displacement_m(force(0.0))
            };
            // Settle whole cycles; the last cycle starts at t = 0 again (periodic force).
            let mut t = 0.0;
            for _ in 0..n_settle_cycles * STEPS_PER_CYCLE {
                y = rk4(&rhs, t, y, h);
                t += h;
            }
            let mut states = Vec::with_capacity(STEPS_PER_CYCLE + 1);
            states.push(y);
            for i in 0..STEPS_PER_CYCLE {
                // Restart the clock each cycle: the force is periodic, so t mod T.
                y = rk4(&rhs, i as f64 * h, y, h);
                states.push(y);
            }
            if consistent {
                states
                    .iter()
                    .zip(&force_n)
                    .map(|(&fm, &f)| model.static_displacement_m(f - fm))
                    .collect()
            } else {
                states
            }
        }
    };
    ForceControlledCycle {
        time_s,
        force_n,
        displacement_m,
    }
}

fn rk4(rhs: &impl Fn(f64, f64) -> f64, t: f64, y: f64, h: f64) -> f64 {
    let k1 = rhs(t, y);
    let k2 = rhs(t + 0.5 * h, y + 0.5 * h * k1);
    let k3 = rhs(t + 0.5 * h, y + 0.5 * h * k2);
    let k4 = rhs(t + h, y + h * k3);
    y + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
}

/// Equivalent stiffness and damping of one cycle (in-phase and quadrature components of
/// the force vs displacement at the test frequency, as in the paper's Sec. 2), N/m, N s/m.
pub fn cycle_equivalent(cycle: &ForceControlledCycle, frequency_hz: f64) -> (f64, f64) {
    let n = cycle.time_s.len() - 1; // drop the repeated end point: whole cycle
    let dt = cycle.time_s[1] - cycle.time_s[0];
    let x = super::single_bin_dft(&cycle.displacement_m[..n], dt, 0.0, frequency_hz);
    let f = super::single_bin_dft(&cycle.force_n[..n], dt, 0.0, frequency_hz);
    let modulus = f / x;
    (modulus.re, modulus.im / (TWO_PI * frequency_hz))
}

/// F5: loops for the two test conditions and the three models. Returns, per case and
/// model, the loop's equivalent stiffness/damping per metre and its displacement range.
pub fn write_figure5(out_dir: &Path) -> anyhow::Result<Value> {
    let models = ModelSet::paper_models(SAMPLE_LENGTH_M);
    // Force control: time and force are the same for every model; one column per model.
    let mut columns: Vec<Vec<f64>> = vec![Vec::new(); 7];
    let mut panels = Vec::new();
    let mut summary = Vec::new();
    for &(preload_n, frequency_hz) in &FIGURE5_CASES {
        let mut panel = Panel::new(
            format!(
                "750 mm sample, force control: {:.0} kN + 5 kN cos, {:.0} Hz",
                preload_n * 1e-3,
                frequency_hz
            ),
            "displacement, compression positive (mm)",
            "force on sample, compression positive (kN)",
        )
        // Headroom above the loops keeps the legend (upper right) off the curves.
        .y_range(
            (preload_n - FORCE_AMPLITUDE_N) * 1e-3 - 0.5,
            (preload_n + 2.0 * FORCE_AMPLITUDE_N) * 1e-3,
        );
        for (model_idx, (key, label, model)) in models.named().into_iter().enumerate() {
            let cycle = force_controlled_cycle(&model, preload_n, FORCE_AMPLITUDE_N, frequency_hz);
            let (k_eq, c_eq) = cycle_equivalent(&cycle, frequency_hz);
            let (z_min, z_max) = cycle
                .displacement_m
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &z| {
                    (a.min(z), b.max(z))
                });
            summary.push(json!({
                "model": key,
                "preload_n": preload_n,
                "frequency_hz": frequency_hz,
                "k_eq_per_metre_n_per_m2": k_eq / SAMPLE_LENGTH_M,
                "c_eq_per_metre_ns_per_m2": c_eq / SAMPLE_LENGTH_M,
                "displacement_min_m": z_min,
                "displacement_max_m": z_max,
            }));
            if model_idx == 0 {
                let n = cycle.time_s.len();
                columns[0].extend(std::iter::repeat_n(preload_n, n));
                columns[1].extend(std::iter::repeat_n(frequency_hz, n));
                columns[2].extend(&cycle.time_s);
                columns[3].extend(&cycle.force_n);
            }
            columns[4 + model_idx].extend(&cycle.displacement_m);
            let z_mm: Vec<f64> = cycle.displacement_m.iter().map(|z| z * 1e3).collect();
            let f_kn: Vec<f64> = cycle.force_n.iter().map(|f| f * 1e-3).collect();
            panel = panel.with(Series::line(label, z_mm, f_kn, model_color(key)));
        }
        panels.push(panel);
    }
    write_csv(
        &out_path(out_dir, "f5_force_displacement_loops.csv"),
        &[
            "preload_n",
            "frequency_hz",
            "t_s",
            "force_n",
            "displacement_paper_m",
            "displacement_consistent_m",
            "displacement_linear_m",
        ],
        &columns.iter().map(Vec::as_slice).collect::<Vec<_>>(),
    )?;
    draw_png(
        &out_path(out_dir, "f5_force_displacement_loops.png"),
        1400,
        600,
        2,
        &panels,
    )?;
    Ok(json!({ "loops": summary }))
}
