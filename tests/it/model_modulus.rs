//! The small-signal modulus each time-domain form shows, measured by simulation the way
//! the lab measures it (SPEC 4: single-bin DFT over whole cycles after transients), vs
//! paper Eq. 2 (consistent form) and the paper form's linearised modulus (SPEC 2.1).

use fastemu::model::equiv::{paper_form_linearised, zener_eq2, Equivalent};
use fastemu::model::{ElementModel, ForceStepper, ZenerParams};

use crate::common::{phasor, rel_err, PI};

/// Equivalent stiffness and damping of `model` for a small harmonic displacement of
/// `amp_m` around the static displacement under `preload_n`, at `freq_hz`.
fn simulated_equivalent(
    model: ElementModel,
    preload_n: f64,
    freq_hz: f64,
    amp_m: f64,
) -> Equivalent {
    let per_cycle = 500usize;
    let dt = 1.0 / (freq_hz * per_cycle as f64);
    let omega = 2.0 * PI * freq_hz;
    // Transients decay at least as e^{-t a (1 - d)} (a = 13.7/s, d < 0.1): 2.5 s -> 1e-13.
    let settle_cycles = (2.5 * freq_hz).ceil() as usize;
    let analysed_cycles = 2;
    let z0 = model.static_displacement_m(preload_n);
    let mut stepper = ForceStepper::new(model, dt, z0);
    assert!(
        rel_err(stepper.force_n(), preload_n) < 1e-9,
        "static start at the preload"
    );
    let (mut zs, mut fs) = (Vec::new(), Vec::new());
    for i in 1..=(settle_cycles + analysed_cycles) * per_cycle {
        let z = z0 + amp_m * (omega * i as f64 * dt).sin();
        let (f, flags) = stepper.step(z);
        assert!(flags.is_empty());
        if i > settle_cycles * per_cycle {
            zs.push(z);
            fs.push(f);
        }
    }
    let t0 = (settle_cycles * per_cycle + 1) as f64 * dt;
    let modulus = phasor(&fs, t0, dt, omega) / phasor(&zs, t0, dt, omega);
    Equivalent {
        k_eq_n_per_m: modulus.re,
        c_eq_ns_per_m: modulus.im / omega,
    }
}

const PRELOADS_N: [f64; 4] = [6e3, 18e3, 37e3, 55e3];

/// Largest relative errors (k, c) of simulated vs expected over the Table 2 preloads and
/// 1..=20 Hz.
fn worst_errors(
    model: ElementModel,
    expected: impl Fn(&ZenerParams, f64, f64) -> Equivalent,
) -> (f64, f64) {
    let p = *model.zener().unwrap();
    let (mut worst_k, mut worst_c) = (0.0f64, 0.0f64);
    for preload_n in PRELOADS_N {
        for freq in 1..=20 {
            let freq_hz = freq as f64;
            // 1 um: the stiffness changes by ~chi k z / (P0 + P) ~ 2e-4 over the cycle,
            // and that first-order change only feeds the second harmonic.
            let got = simulated_equivalent(model, preload_n, freq_hz, 1e-6);
            let want = expected(&p, preload_n, 2.0 * PI * freq_hz);
            let (ek, ec) = (
                rel_err(got.k_eq_n_per_m, want.k_eq_n_per_m),
                rel_err(got.c_eq_ns_per_m, want.c_eq_ns_per_m),
            );
            assert!(
                ek < 1e-4 && ec < 2e-3,
                "{} at {preload_n} N, {freq_hz} Hz: simulated {got:?} vs {want:?}",
                model.form()
            );
            worst_k = worst_k.max(ek);
            worst_c = worst_c.max(ec);
        }
    }
    (worst_k, worst_c)
}

#[test]
fn consistent_form_small_signal_modulus_is_eq2_at_table2_preloads() {
    // The 750 mm lab sample: P is the force on this element (SPEC 2).
    let model = ElementModel::Consistent(ZenerParams::paper_table3(0.75));
    let (k, c) = worst_errors(model, zener_eq2);
    // Observed 1.6e-6 (k) and 1.3e-5 (c) with 500 samples per cycle: the bounds (1e-4,
    // 2e-3) are far inside the 1 % and a few %, with margin for round-off.
    assert!(k < 1e-4 && c < 2e-3, "worst k {k:e}, c {c:e}");
}

#[test]
fn paper_form_small_signal_modulus_is_its_linearisation() {
    let model = ElementModel::Paper(ZenerParams::paper_table3(0.75));
    let (k, c) = worst_errors(model, paper_form_linearised);
    // Observed 1.2e-6 (k) and 2e-4 (c): the predictor-corrector freezes g at the step's
    // midpoint, second order in dt, and c is the small quadrature part.
    assert!(k < 1e-4 && c < 2e-3, "worst k {k:e}, c {c:e}");
}

#[test]
fn paper_form_differs_from_eq2_by_the_specs_numbers_at_55kn_1hz() {
    // SPEC 2.1: 78.9 vs 72.5 MN/m^2 and 0.215 vs 0.659 MN s/m^2 (per metre, 1 Hz, 55 kN).
    let p = ZenerParams::paper_table3(1.0);
    let omega = 2.0 * PI;
    let paper = simulated_equivalent(ElementModel::Paper(p), 55e3, 1.0, 1e-6);
    let consistent = simulated_equivalent(ElementModel::Consistent(p), 55e3, 1.0, 1e-6);
    let eq2 = zener_eq2(&p, 55e3, omega);
    let check = |label: &str, got: f64, published: f64, half_ulp_of_print: f64| {
        assert!(
            (got - published).abs() <= half_ulp_of_print,
            "{label}: {got} vs SPEC {published}"
        );
    };
    check("paper-form k", paper.k_eq_n_per_m / 1e6, 78.9, 0.05);
    check("paper-form c", paper.c_eq_ns_per_m / 1e6, 0.215, 0.0005);
    check("consistent k", consistent.k_eq_n_per_m / 1e6, 72.5, 0.05);
    check(
        "consistent c",
        consistent.c_eq_ns_per_m / 1e6,
        0.659,
        0.0005,
    );
    check("Eq. 2 k", eq2.k_eq_n_per_m / 1e6, 72.5, 0.05);
    check("Eq. 2 c", eq2.c_eq_ns_per_m / 1e6, 0.659, 0.0005);
}
