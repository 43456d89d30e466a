//! The integrators against closed-form (or exactly computed) solutions of linear cases:
//! the linear Zener model (`chi = 0`) in both Zener forms and the Kelvin-Voigt model.
//!
//! Tolerances follow from the schemes:
//! - `ForceStepper` is exact for displacement linear over each step (exponential
//!   integrator, SPEC 2.2), so piecewise-linear inputs leave only round-off (1e-9).
//!   For a sampled sine the only error is the linear interpolation between samples,
//!   relative `(W dt)^2 / 12`.
//! - `Oscillator` is classical RK4 with `W h <= 0.1`: phase and amplitude errors of
//!   about `(W h)^5 / 120` per sub-step, i.e. 1e-5..1e-4 relative over the runs below,
//!   plus the force's linear interpolation between input samples.

use fastemu::model::element::simulate_force;
use fastemu::model::oscillator::{simulate_rail, Oscillator, StartCondition};
use fastemu::model::{ElementModel, ForceStepper, KelvinVoigtParams, ZenerParams};
use nalgebra::{Complex, SMatrix, SVector};

use crate::common::{linear_zener, phasor, rel_err, zener_modulus, PI};

/// Ramp `z = V t` up to `T`, then hold: the linear Zener force is
/// `k1 z + c2 V (1 - e^{-t/tau})` on the ramp and relaxes as `e^{-(t-T)/tau}` after.
fn ramp_hold_force(p: &ZenerParams, speed_m_per_s: f64, ramp_s: f64, t_s: f64) -> f64 {
    let (k1, k2, c2) = (p.k1_0_n_per_m, p.k2_0_n_per_m, p.c2_0_ns_per_m);
    let tau = c2 / k2;
    let maxwell_at = |t: f64| c2 * speed_m_per_s * (1.0 - (-t / tau).exp());
    if t_s <= ramp_s {
        k1 * speed_m_per_s * t_s + maxwell_at(t_s)
    } else {
        k1 * speed_m_per_s * ramp_s + maxwell_at(ramp_s) * (-(t_s - ramp_s) / tau).exp()
    }
}

#[test]
fn linear_zener_relaxation_after_ramp_is_exact_for_any_step() {
    let p = linear_zener(1.0);
    let (ramp_s, end_s, z_max_m) = (0.5, 2.0, 1e-3);
    let speed = z_max_m / ramp_s;
    // Steps from fine to far coarser than the 73 ms relaxation time; all divide the ramp,
    // so the input is exactly piecewise linear and the scheme exact up to round-off.
    for dt in [1e-4f64, 1.0 / 1024.0, 0.01, 0.125, 0.5] {
        let n = (end_s / dt).round() as usize + 1;
        let z: Vec<f64> = (0..n)
            .map(|i| speed * (i as f64 * dt).min(ramp_s))
            .collect();
        for model in [ElementModel::Consistent(p), ElementModel::Paper(p)] {
            let (forces, flags) = simulate_force(model, dt, &z);
            assert!(flags.is_empty(), "{model:?}: flags {flags:?}");
            let scale = ramp_hold_force(&p, speed, ramp_s, ramp_s);
            for (i, &f) in forces.iter().enumerate() {
                let expected = ramp_hold_force(&p, speed, ramp_s, i as f64 * dt);
                assert!(
                    (f - expected).abs() <= 1e-9 * scale,
                    "{} dt {dt}: t {}: force {f} vs closed form {expected}",
                    model.form(),
                    i as f64 * dt
                );
            }
        }
    }
}

#[test]
fn kelvin_voigt_force_follows_spring_and_backward_velocity() {
    let kv = KelvinVoigtParams::paper_linear(0.75);
    let dt = 1e-3;
    let speed = 2e-3;
    let z: Vec<f64> = (0..200).map(|i| speed * (i as f64 * dt).min(0.1)).collect();
    let (forces, _) = simulate_force(ElementModel::KelvinVoigt(kv), dt, &z);
    for (i, (&f, &zi)) in forces.iter().zip(&z).enumerate() {
        // The step sees the velocity of the step that ends at sample i.
        let velocity = if i == 0 || i > 100 { 0.0 } else { speed };
        let expected = kv.k_n_per_m * zi + kv.c_ns_per_m * velocity;
        assert!(
            (f - expected).abs() <= 1e-9 * (1.0 + expected.abs()),
            "sample {i}"
        );
    }
}

/// Quasi-static creep of the standard linear solid under a load ramped linearly to
/// `F` over `T` and then held: `x(t) = (F/T) [I(t) - I(t - T)]` with
/// `I(s) = integral of the creep compliance J = s/k1 - (1/k1 - 1/(k1+k2)) tau_c (1 - e^{-s/tau_c})`,
/// `tau_c = c2 (k1 + k2) / (k1 k2)`.
fn creep_displacement(p: &ZenerParams, force_n: f64, ramp_s: f64, t_s: f64) -> f64 {
    let (k1, k2, c2) = (p.k1_0_n_per_m, p.k2_0_n_per_m, p.c2_0_ns_per_m);
    let tau_c = c2 * (k1 + k2) / (k1 * k2);
    let delta = 1.0 / k1 - 1.0 / (k1 + k2);
    let integral = |s: f64| {
        if s <= 0.0 {
            0.0
        } else {
            s / k1 - delta * tau_c * (1.0 - (-s / tau_c).exp())
        }
    };
    force_n / ramp_s * (integral(t_s) - integral(t_s - ramp_s))
}

#[test]
fn linear_zener_creep_under_held_load_matches_creep_compliance() {
    // A 1 g mass makes the oscillator quasi-static (inertia error ~ m / (k tau_c^2) ~ 1e-8);
    // the 20 ms ramp leaves a free oscillation of relative amplitude <= 2/(W T) ~ 4e-4,
    // hence the 1e-3 tolerance relative to the final creep displacement F/k1.
    let p = linear_zener(1.0);
    let (force_n, ramp_s, dt) = (55e3, 0.02, 1e-4);
    let n = 10_001;
    let load: Vec<f64> = (0..n)
        .map(|i| force_n * (i as f64 * dt / ramp_s).min(1.0))
        .collect();
    let scale = force_n / p.k1_0_n_per_m;
    for model in [ElementModel::Consistent(p), ElementModel::Paper(p)] {
        let (samples, flags) = simulate_rail(model, 1e-3, dt, &load, StartCondition::Rest);
        assert!(flags.is_empty());
        let mut worst = 0.0f64;
        for (i, s) in samples.iter().enumerate() {
            let expected = creep_displacement(&p, force_n, ramp_s, i as f64 * dt);
            worst = worst.max((s.displacement_m - expected).abs() / scale);
        }
        assert!(
            worst < 1e-3,
            "{}: creep error {worst:e} of F/k1",
            model.form()
        );
        // The creep is real: the end point is far from the instantaneous compliance.
        let end = samples.last().unwrap().displacement_m;
        assert!(rel_err(end, scale) < 1e-3, "{}: end {end}", model.form());
    }
}

/// Exact propagation of the linear mass-on-Zener system under a force linear in each
/// step: state `[x, v, Fm, f, df/dt]`, `x' = v`, `m v' = f - k1 x - Fm`,
/// `Fm' = k2 v - (k2/c2) Fm`, `f' = df/dt`, `(df/dt)' = 0`, one matrix exponential.
fn exact_linear_zener_rail(p: &ZenerParams, mass_kg: f64, dt: f64, load: &[f64]) -> Vec<[f64; 3]> {
    let (k1, k2, c2) = (p.k1_0_n_per_m, p.k2_0_n_per_m, p.c2_0_ns_per_m);
    let mut a = SMatrix::<f64, 5, 5>::zeros();
    a[(0, 1)] = 1.0;
    a[(1, 0)] = -k1 / mass_kg;
    a[(1, 2)] = -1.0 / mass_kg;
    a[(1, 3)] = 1.0 / mass_kg;
    a[(2, 1)] = k2;
    a[(2, 2)] = -k2 / c2;
    a[(3, 4)] = 1.0;
    let transition = (a * dt).exp();
    let mut out = Vec::with_capacity(load.len());
    let (mut x, mut v, mut fm) = (0.0, 0.0, 0.0);
    out.push([x, v, k1 * x + fm]);
    for pair in load.windows(2) {
        let y = transition * SVector::<f64, 5>::new(x, v, fm, pair[0], (pair[1] - pair[0]) / dt);
        (x, v, fm) = (y[0], y[1], y[2]);
        out.push([x, v, k1 * x + fm]);
    }
    out
}

#[test]
fn mass_on_linear_zener_matches_matrix_exponential_solution() {
    // The benchmark scenario on the linear model: 55 kN step at t = 0 from rest plus a
    // 1 kN, 170 Hz harmonic, unit length, 60.21 kg, 0.5 s at 10 kHz (~87 cycles of the
    // weakly damped 174 Hz mode). RK4 phase error ~ (W h)^5/120 per sub-step accumulates
    // to ~5e-5 rad here, hence 2e-4 of the displacement scale.
    let p = linear_zener(1.0);
    let (mass_kg, dt) = (60.21, 1e-4);
    let load: Vec<f64> = (0..5001)
        .map(|i| 55e3 + 1e3 * (2.0 * PI * 170.0 * i as f64 * dt).sin())
        .collect();
    let exact = exact_linear_zener_rail(&p, mass_kg, dt, &load);
    let x_scale = 55e3 / p.k1_0_n_per_m;
    for model in [ElementModel::Consistent(p), ElementModel::Paper(p)] {
        let (samples, _) = simulate_rail(model, mass_kg, dt, &load, StartCondition::Rest);
        let (mut worst_x, mut worst_f) = (0.0f64, 0.0f64);
        for (s, e) in samples.iter().zip(&exact) {
            worst_x = worst_x.max((s.displacement_m - e[0]).abs() / x_scale);
            worst_f = worst_f.max((s.element_force_n - e[2]).abs() / 55e3);
        }
        assert!(
            worst_x < 2e-4,
            "{}: displacement error {worst_x:e}",
            model.form()
        );
        assert!(worst_f < 2e-4, "{}: force error {worst_f:e}", model.form());
    }
}

/// Runs `ForceStepper` on `z = Z sin(W t)` and returns the measured modulus `F/z`
/// (phasor ratio) over `analysed_cycles` whole cycles after `settle_s`.
fn measured_modulus(model: ElementModel, z0_m: f64, amp_m: f64, freq_hz: f64) -> Complex<f64> {
    let per_cycle = 1000usize;
    let dt = 1.0 / (freq_hz * per_cycle as f64);
    let omega = 2.0 * PI * freq_hz;
    // The Maxwell transient decays as e^{-t k2/c2} (13.7/s): 2 s leaves ~1e-12.
    let settle_cycles = (2.0 * freq_hz).ceil() as usize;
    let analysed_cycles = 4;
    let n = (settle_cycles + analysed_cycles) * per_cycle;
    let mut stepper = ForceStepper::new(model, dt, z0_m);
    let mut zs = Vec::with_capacity(analysed_cycles * per_cycle);
    let mut fs = Vec::with_capacity(analysed_cycles * per_cycle);
    for i in 1..=n {
        let t = i as f64 * dt;
        let z = z0_m + amp_m * (omega * t).sin();
        let (f, _) = stepper.step(z);
        if i > settle_cycles * per_cycle {
            zs.push(z);
            fs.push(f);
        }
    }
    let t0 = (settle_cycles * per_cycle + 1) as f64 * dt;
    phasor(&fs, t0, dt, omega) / phasor(&zs, t0, dt, omega)
}

fn kv_discrete_modulus(kv: &KelvinVoigtParams, omega: f64, dt: f64) -> Complex<f64> {
    let backward = (Complex::new(1.0, 0.0) - Complex::new(0.0, -omega * dt).exp()) / dt;
    // It tends to i W as dt -> 0: (W dt)^2/6 relative at most here.
    assert!((backward - Complex::new(0.0, omega)).norm() < 0.01 * omega);
    Complex::new(kv.k_n_per_m, 0.0) + backward * kv.c_ns_per_m
}

#[test]
fn steady_harmonic_force_matches_linear_complex_modulus() {
    // 1000 samples per cycle: interpolation error (2 pi/1000)^2/12 ~ 3e-6.
    let p = linear_zener(0.75);
    let kv = KelvinVoigtParams::paper_linear(0.75);
    for freq_hz in [0.5, 2.0, 10.0, 50.0, 170.0] {
        let omega = 2.0 * PI * freq_hz;
        let zener = zener_modulus(p.k1_0_n_per_m, p.k2_0_n_per_m, p.c2_0_ns_per_m, omega);
        let cases = [
            (ElementModel::Consistent(p), zener),
            (ElementModel::Paper(p), zener),
            // Kelvin-Voigt's dashpot sees the step's mean velocity (z linear over the
            // step): the backward difference `(1 - e^{-i W dt})/dt` instead of `i W`,
            // whose real part adds `c W (W dt)/2` to k (1e-5 relative at 50 Hz).
            (
                ElementModel::KelvinVoigt(kv),
                kv_discrete_modulus(&kv, omega, 1.0 / (freq_hz * 1000.0)),
            ),
        ];
        for (model, expected) in cases {
            let k = measured_modulus(model, 0.0, 1e-4, freq_hz);
            assert!(
                rel_err(k.re, expected.re) < 1e-5 && rel_err(k.im, expected.im) < 1e-4,
                "{} at {freq_hz} Hz: measured {k} vs closed form {expected}",
                model.form()
            );
        }
    }
}

/// Steady-state displacement phasor per unit force phasor of a mass on an element with
/// complex modulus `K`: `H = 1 / (K(iW) - m W^2)`.
fn measured_receptance(
    model: ElementModel,
    mass_kg: f64,
    freq_hz: f64,
    settle_s: f64,
) -> Complex<f64> {
    let per_cycle = 200usize;
    let dt = 1.0 / (freq_hz * per_cycle as f64);
    let omega = 2.0 * PI * freq_hz;
    let settle_cycles = (settle_s * freq_hz).ceil() as usize;
    let n = (settle_cycles + 10) * per_cycle + 1;
    let load: Vec<f64> = (0..n)
        .map(|i| 1e3 * (omega * i as f64 * dt).sin())
        .collect();
    let (samples, _) = simulate_rail(model, mass_kg, dt, &load, StartCondition::Rest);
    let from = settle_cycles * per_cycle;
    let x: Vec<f64> = samples[from..n - 1]
        .iter()
        .map(|s| s.displacement_m)
        .collect();
    let t0 = from as f64 * dt;
    phasor(&x, t0, dt, omega) / phasor(&load[from..n - 1], t0, dt, omega)
}

#[test]
fn mass_on_element_steady_response_matches_analytic_frf() {
    // 200 samples per cycle: the force's linear interpolation costs (2 pi/200)^2/12 ~ 8e-5;
    // RK4 adds less. Tolerance 5e-4 on the complex receptance.
    let mass_kg = 60.21;
    // A well-damped Zener (Maxwell branch tuned to the ~197 Hz resonance, damping ratio
    // ~0.08) so transients vanish within 0.3 s, and the paper's Kelvin-Voigt model
    // (damping ratio 0.0072, 4 s to settle to e^-33).
    let k2 = 30e6;
    let damped = ZenerParams {
        k1_0_n_per_m: 62e6,
        k2_0_n_per_m: k2,
        c2_0_ns_per_m: k2 / (2.0 * PI * 197.0),
        chi: 0.0,
        p0_n: 64e3,
    };
    let kv = KelvinVoigtParams::paper_linear(1.0);
    for freq_hz in [20.0, 100.0, 190.0, 250.0, 400.0] {
        let omega = 2.0 * PI * freq_hz;
        let inertia = Complex::new(mass_kg * omega * omega, 0.0);
        let one = Complex::new(1.0, 0.0);
        let k_zener = zener_modulus(damped.k1_0_n_per_m, k2, damped.c2_0_ns_per_m, omega);
        let k_kv = Complex::new(kv.k_n_per_m, omega * kv.c_ns_per_m);
        let cases = [
            (
                ElementModel::Consistent(damped),
                one / (k_zener - inertia),
                0.3,
            ),
            (ElementModel::Paper(damped), one / (k_zener - inertia), 0.3),
            (ElementModel::KelvinVoigt(kv), one / (k_kv - inertia), 4.0),
        ];
        for (model, expected, settle_s) in cases {
            let h = measured_receptance(model, mass_kg, freq_hz, settle_s);
            assert!(
                (h - expected).norm() < 5e-4 * expected.norm(),
                "{} at {freq_hz} Hz: receptance {h} vs analytic {expected}",
                model.form()
            );
        }
    }
}

/// Free vibration of a damped oscillator released from `x0` at rest.
fn damped_free(x0: f64, omega_n: f64, zeta: f64, t: f64) -> f64 {
    let omega_d = omega_n * (1.0 - zeta * zeta).sqrt();
    x0 * (-zeta * omega_n * t).exp()
        * ((omega_d * t).cos() + zeta * omega_n / omega_d * (omega_d * t).sin())
}

#[test]
fn kelvin_voigt_free_vibration_and_step_response_match_damped_oscillator() {
    // Unit length, UIC60 rail: 183.4 Hz, damping ratio 0.0072 (SPEC 3). 0.5 s is ~92
    // cycles; RK4 phase error ~ (W h)^5/120 per sub-step stays below ~1e-4 rad.
    let kv = KelvinVoigtParams::paper_linear(1.0);
    let mass_kg = 60.21;
    let omega_n = (kv.k_n_per_m / mass_kg).sqrt();
    let zeta = kv.c_ns_per_m / (2.0 * (kv.k_n_per_m * mass_kg).sqrt());
    assert!((omega_n / (2.0 * PI) - 183.4).abs() < 0.1 && (zeta - 0.0072).abs() < 5e-5);
    for dt in [1e-4f64, 1.0 / 4096.0, 1e-3] {
        let n = (0.5 / dt).round() as usize;
        // Released from 1 mm at rest, no external force.
        let x0 = 1e-3;
        let mut osc = Oscillator::new(ElementModel::KelvinVoigt(kv), mass_kg, dt, 0.0);
        osc.set_state(x0, 0.0);
        let mut worst = 0.0f64;
        for i in 1..=n {
            osc.step(0.0, 0.0);
            let expected = damped_free(x0, omega_n, zeta, i as f64 * dt);
            worst = worst.max((osc.displacement_m() - expected).abs() / x0);
        }
        assert!(
            worst < 2e-4,
            "free vibration dt {dt}: error {worst:e} of x0"
        );

        // 55 kN applied at t = 0 from rest: x = F/k - (free vibration from -F/k).
        let force_n = 55e3;
        let x_static = force_n / kv.k_n_per_m;
        let load = vec![force_n; n + 1];
        let (samples, _) = simulate_rail(
            ElementModel::KelvinVoigt(kv),
            mass_kg,
            dt,
            &load,
            StartCondition::Rest,
        );
        let mut worst = 0.0f64;
        for (i, s) in samples.iter().enumerate() {
            let expected = x_static - damped_free(x_static, omega_n, zeta, i as f64 * dt);
            worst = worst.max((s.displacement_m - expected).abs() / x_static);
        }
        assert!(worst < 2e-4, "step load dt {dt}: error {worst:e} of F/k");
    }
}
