//! `fastemu paper`: the physics of each reproduced figure against independent
//! calculations (closed forms written out here, not taken from the crate), and the
//! command's output contract (files and summary keys).

use std::path::PathBuf;
use std::process::Command;

use fastemu::model::element::simulate_force;
use fastemu::model::{ElementModel, KelvinVoigtParams, ZenerParams};
use fastemu::paper::equivalent::equivalent_rows;
use fastemu::paper::free_response::free_response;
use fastemu::paper::harmonic::{harmonic_response, small_signal_frf, SettlePlan};
use fastemu::paper::loops::force_controlled_cycle;
use fastemu::paper::train::hann_amplitude_spectrum;
use fastemu::paper::{single_bin_dft, OUTPUT_FILES};

const TWO_PI: f64 = 2.0 * std::f64::consts::PI;
const RAIL_MASS_KG: f64 = 60.21;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("fastemu-it-paper-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn assert_rel(actual: f64, expected: f64, tol: f64, what: &str) {
    let rel = (actual - expected).abs() / expected.abs();
    assert!(
        rel <= tol,
        "{what}: got {actual:e}, expected {expected:e} (relative error {rel:e} > {tol:e})"
    );
}

#[test]
fn f10_values_equal_eq2_computed_by_hand() {
    // Table 3 per metre: k1_0 62 MN/m^2, k2_0 9.6, c2_0 0.7 MN s/m^2, chi 0.21, P0 64 kN.
    let check = |preload_n: f64, frequency_hz: f64| {
        let g = (1.0 + preload_n / 64e3).powf(0.21);
        let (k1, k2, c2) = (62e6 * g, 9.6e6 * g, 0.7e6 * g);
        let a = (c2 * TWO_PI * frequency_hz / k2).powi(2);
        let k_eq = k1 + k2 * a / (1.0 + a);
        let c_eq = c2 / (1.0 + a);
        let row = equivalent_rows(&[preload_n], &[frequency_hz])[0];
        assert_rel(row.eq2.k_eq_n_per_m, k_eq, 1e-12, "k_eq");
        assert_rel(row.eq2.c_eq_ns_per_m, c_eq, 1e-12, "c_eq");
    };
    for (p, f) in [(6e3, 1.0), (18e3, 20.0), (37e3, 100.0), (55e3, 250.0)] {
        check(p, f);
    }
    // The paper's description of Fig. 10: c_eq falls from ~1 to ~1e-4 MN s/m^2.
    let low = equivalent_rows(&[6e3], &[0.5])[0].eq2.c_eq_ns_per_m;
    let high = equivalent_rows(&[6e3], &[250.0])[0].eq2.c_eq_ns_per_m;
    assert!((0.5e6..1.0e6).contains(&low), "c_eq at 0.5 Hz {low}");
    assert!((3e1..3e2).contains(&high), "c_eq at 250 Hz {high}");
}

#[test]
fn f11_machinery_on_the_linear_model_gives_the_closed_form_values() {
    let (k, c) = (80e6, 1e3);
    let model = ElementModel::KelvinVoigt(KelvinVoigtParams {
        k_n_per_m: k,
        c_ns_per_m: c,
    });
    let response = free_response(model, RAIL_MASS_KG, 55e3, 1.0);
    let omega_n = (k / RAIL_MASS_KG).sqrt();
    let zeta = c / (2.0 * (k * RAIL_MASS_KG).sqrt());
    let damped_hz = omega_n * (1.0 - zeta * zeta).sqrt() / TWO_PI;
    let decay_s = 10f64.ln() / (zeta * omega_n);
    // SPEC 3's derived values.
    assert!((damped_hz - 183.4).abs() < 0.1, "closed form {damped_hz}");
    assert!((zeta - 0.0072).abs() < 5e-5, "closed form {zeta}");
    assert_rel(
        response.natural_frequency_hz,
        damped_hz,
        1e-4,
        "natural frequency",
    );
    assert_rel(response.damping_ratio, zeta, 5e-3, "damping ratio");
    assert_rel(
        response.decay_90_percent_s.expect("decays within 1 s"),
        decay_s,
        1e-2,
        "90 % decay time",
    );
    assert!((response.decay_90_percent_s.unwrap() - 0.275).abs() < 0.005);
}

#[test]
fn f12_time_domain_linear_response_equals_the_analytic_frf() {
    let (k, c) = (80e6, 1e3);
    let model = ElementModel::KelvinVoigt(KelvinVoigtParams {
        k_n_per_m: k,
        c_ns_per_m: c,
    });
    for frequency_hz in [20.0, 150.0, 183.0, 184.0, 300.0, 500.0] {
        let omega = TWO_PI * frequency_hz;
        // |1/(k - m w^2 + i c w)| and its phase, written out.
        let re = k - RAIL_MASS_KG * omega * omega;
        let im = c * omega;
        let magnitude = 1.0 / (re * re + im * im).sqrt();
        let phase = -im.atan2(re);
        let point = harmonic_response(
            model,
            RAIL_MASS_KG,
            6e3,
            1e3,
            frequency_hz,
            SettlePlan::FULL,
        );
        assert_rel(
            point.amplitude_ratio_m_per_n,
            magnitude,
            2e-3,
            "amplitude ratio",
        );
        assert!(
            (point.phase_rad - phase).abs() < 3e-3,
            "{frequency_hz} Hz: phase {} vs {phase}",
            point.phase_rad
        );
        assert!(point.settle_change < 2e-3, "{}", point.settle_change);
    }
}

#[test]
fn f12_time_domain_zener_response_tends_to_the_small_signal_frf() {
    // With a 10 N harmonic the response is linear around the preload, so the time-domain
    // ratio must equal the linearised modulus of each form (Eq. 2 for the consistent form).
    let zener = ZenerParams::paper_table3(1.0);
    for model in [ElementModel::Consistent(zener), ElementModel::Paper(zener)] {
        for (preload_n, frequency_hz) in [(18e3, 100.0), (55e3, 250.0)] {
            let point = harmonic_response(
                model,
                RAIL_MASS_KG,
                preload_n,
                10.0,
                frequency_hz,
                SettlePlan::FULL,
            );
            let expected = small_signal_frf(&model, RAIL_MASS_KG, preload_n, frequency_hz);
            assert_rel(
                point.amplitude_ratio_m_per_n,
                expected.norm(),
                2e-3,
                "small-signal ratio",
            );
        }
    }
}

#[test]
fn f7_static_deflection_peak_matches_the_winkler_closed_form() {
    let dir = temp_dir("f7");
    let peak_m = fastemu::paper::passage::write_figure7(&dir).unwrap();
    // Hetenyi: w(x) = Q beta/(2k) e^(-beta|x|) (cos beta|x| + sin beta|x|), summed over the
    // coach's axles at 0, -3, -19, -22 m; the maximum is within 1 m of an axle.
    let (q, k, ei): (f64, f64, f64) = (110e3, 60e6, 210e9 * 3038.3e-8);
    let beta = (k / (4.0 * ei)).powf(0.25);
    let w = |x: f64| {
        [0.0, -3.0, -19.0, -22.0]
            .iter()
            .map(|axle| {
                let b = beta * (x - axle).abs();
                q * beta / (2.0 * k) * (-b).exp() * (b.cos() + b.sin())
            })
            .sum::<f64>()
    };
    let closed_form_peak = (0..=2000)
        .map(|i| -1.0 + 1e-3 * i as f64)
        .map(w)
        .fold(f64::NEG_INFINITY, f64::max);
    assert_rel(peak_m, closed_form_peak, 1e-5, "peak deflection");
    // About 1.1 mm: one axle's Q beta / 2k = 1.135 mm less the neighbour's uplift.
    assert!((1.0e-3..1.2e-3).contains(&peak_m), "{peak_m}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn f5_force_controlled_cycle_imposed_as_displacement_gives_back_the_force() {
    // Independent check of the inversion: impose the computed displacement cycle
    // (repeated until periodic) with the force-from-displacement stepper.
    let zener = ZenerParams::paper_table3(0.75);
    for model in [ElementModel::Consistent(zener), ElementModel::Paper(zener)] {
        for (preload_n, frequency_hz) in [(6e3, 1.0), (18e3, 5.0)] {
            let cycle = force_controlled_cycle(&model, preload_n, 5e3, frequency_hz);
            let n = cycle.time_s.len() - 1;
            let dt = cycle.time_s[1] - cycle.time_s[0];
            let repeats = (4.0 * frequency_hz).ceil() as usize + 1;
            let z: Vec<f64> = (0..repeats * n + 1)
                .map(|i| cycle.displacement_m[i % n])
                .collect();
            let (force, flags) = simulate_force(model, dt, &z);
            assert!(flags.is_empty());
            let last = &force[(repeats - 1) * n..];
            let worst = last
                .iter()
                .zip(&cycle.force_n)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(
                worst < 5e3 * 1e-4,
                "{:?} {preload_n} N {frequency_hz} Hz: worst force error {worst} N",
                model.form()
            );
        }
    }
}

#[test]
fn single_bin_dft_and_hann_spectrum_recover_a_sinusoid() {
    let dt = 1e-3;
    let x: Vec<f64> = (0..1000)
        .map(|i| 0.3 + 2.0 * (TWO_PI * 10.0 * i as f64 * dt - 0.4).cos())
        .collect();
    let bin = single_bin_dft(&x, dt, 0.0, 10.0);
    assert_rel(bin.norm(), 2.0, 1e-12, "DFT amplitude");
    assert!((bin.arg() + 0.4).abs() < 1e-12);
    let (freqs, amps) = hann_amplitude_spectrum(&x, dt, 4);
    let k = freqs.iter().position(|&f| (f - 10.0).abs() < 1e-9).unwrap();
    assert_rel(amps[k], 2.0, 1e-9, "Hann amplitude at the line");
}

#[test]
fn paper_command_writes_every_file_and_the_documented_summary_keys() {
    let dir = temp_dir("cli");
    let output = Command::new(env!("CARGO_BIN_EXE_fastemu"))
        .args(["paper", "--quick", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(String::from_utf8_lossy(&output.stderr).contains("F12"));
    for name in OUTPUT_FILES {
        let path = dir.join(name);
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
        if name.ends_with(".png") {
            assert_eq!(&bytes[1..4], b"PNG", "{name}");
        } else {
            assert!(bytes.len() > 50, "{name} is nearly empty");
        }
    }
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("summary.json")).unwrap()).unwrap();
    for model in ["paper", "consistent", "linear"] {
        assert!(summary["f11"][model]["natural_frequency_hz"].is_f64());
        assert!(summary["f11"][model].get("decay_90_percent_s").is_some());
        assert!(summary["f8"][model]["first_valley_paper_sign_n"].is_f64());
        assert!(summary["f8"][model]["second_valley_paper_sign_n"].is_f64());
        assert!(summary["f8"][model]["overshoot_paper_sign_n"].is_f64());
    }
    let peaks = summary["f12"]["peaks"].as_array().unwrap();
    assert_eq!(peaks.len(), 8, "4 preloads x 2 nonlinear forms");
    for key in [
        "grid_peak_frequency_hz",
        "grid_peak_amplitude_ratio_m_per_n",
        "grid_peak_over_linear_grid_peak",
        "true_peak_frequency_hz",
        "true_peak_amplitude_ratio_m_per_n",
        "true_peak_over_linear_peak",
    ] {
        assert!(peaks.iter().all(|p| p[key].is_f64()), "{key}");
    }
    for model in ["paper_over_linear", "consistent_over_linear"] {
        assert!(summary["f13"][model]["low_frequency_displacement_ratio"].is_f64());
        assert!(summary["f13"][model]["amplitude_170_hz_ratio"].is_f64());
    }
    assert!(summary["f12"]["linear"]["peak_frequency_hz"].is_f64());
    // The linear model's F11 values do not depend on --quick.
    let f = summary["f11"]["linear"]["natural_frequency_hz"]
        .as_f64()
        .unwrap();
    assert!((f - 183.4).abs() < 0.2, "{f}");
    std::fs::remove_dir_all(&dir).unwrap();
}
