//! Seeded synthetic campaigns for a first run (`fastemu synth-campaign`): 41 harmonic
//! tests (the paper's preload x frequency grid, an amplitude series, a temperature series,
//! the first test repeated at the end), three recorded passages of rising size, with
//! `started_at` times; the truth goes to `truth.toml`, which `diagnose` never reads, and a
//! baseline with its parameters off to `baseline.toml`.
//!
//! The force comes from the crate's own model (`ModelStepper`, measurement mode, on a
//! grid eight times finer than the record) with the hidden effect added (a self-heating
//! specimen is stepped with its thermal state carried from test to test and cooled in the
//! rests, with 20 s records so that it warms within a test), or from the older truths
//! `load-path-resonance` (an 80 Hz load path, applied after the model) and
//! `softening-specimen` (the moduli falling linearly by 6 %), kept for comparison with
//! `load-train-resonance` and `specimen-drift`. Both channels get white noise, the force also AR(1) noise.
//! This is a demonstration, not a test oracle: the project's tests use their own,
//! independent generator.
//!
//! Must not: read anything; it writes only under its output directory.

use std::f64::consts::PI;
use std::fmt::Write as _;
use std::path::Path;

use crate::model::effects::{
    AugmentedModel, Effect, FrictionLaw, ModelStepper, StepperMode, EFFECT_NAMES,
};
use crate::model::params::{ElementModel, ZenerParams};

/// What a synthetic campaign can hide besides the library's effects (`EFFECT_NAMES`).
pub const OTHER_HIDDEN: [&str; 4] = [
    "none",
    "load-path-resonance",
    "softening-specimen",
    "friction-passages-only",
];

/// Every value `--hidden` takes.
pub fn hidden_choices() -> Vec<&'static str> {
    OTHER_HIDDEN[..1]
        .iter()
        .chain(EFFECT_NAMES.iter())
        .chain(OTHER_HIDDEN[1..].iter())
        .copied()
        .collect()
}

const LENGTH_M: f64 = 0.75;
const SUBSTEPS: usize = 8;

/// Deterministic SplitMix64 with Box-Muller normals.
struct Rng(u64);

impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        (((z ^ (z >> 31)) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (2.0 * PI * u2).cos()
    }
}

/// One harmonic test of the design.
#[derive(Debug, Clone, Copy)]
struct Point {
    preload_n: f64,
    amplitude_n: f64,
    frequency_hz: f64,
    temperature_c: f64,
}

fn design(one_amplitude: bool) -> Vec<Point> {
    let point = |preload_n, amplitude_n, frequency_hz, temperature_c| Point {
        preload_n,
        amplitude_n,
        frequency_hz,
        temperature_c,
    };
    let mut out = Vec::new();
    for p in [6e3, 18e3, 37e3, 55e3] {
        for f in [1.0, 3.0, 5.0, 10.0, 20.0] {
            out.push(point(p, 5e3, f, 23.0));
        }
    }
    for p in [18e3, 37e3] {
        if !one_amplitude {
            for a in [2e3, 9e3] {
                for f in [3.0, 10.0] {
                    out.push(point(p, a, f, 23.0));
                }
            }
        }
        for t in [10.0, 35.0] {
            for f in [1.0, 5.0, 20.0] {
                out.push(point(p, 5e3, f, t));
            }
        }
    }
    // The lab's habit: the first test again at the end (a direct drift check).
    out.push(out[0]);
    out
}

/// Whether `hidden` (one choice, or several joined by `+`) names a valid truth.
pub fn valid_hidden(hidden: &str) -> bool {
    let choices = hidden_choices();
    hidden.split('+').all(|part| choices.contains(&part))
}

fn hides(hidden: &str, name: &str) -> bool {
    hidden.split('+').any(|part| part == name)
}

/// The truth's model: the paper's element plus the hidden library effects, if any.
fn truth_model(hidden: &str) -> AugmentedModel {
    AugmentedModel {
        effects: hidden.split('+').filter_map(effect_of).collect(),
        ..truth_element(hidden)
    }
}

fn truth_element(hidden: &str) -> AugmentedModel {
    let chi = if hides(hidden, "preload-stiffening") {
        0.3
    } else {
        0.2
    };
    let element = ElementModel::Consistent(ZenerParams {
        k1_0_n_per_m: 60e6 * LENGTH_M,
        k2_0_n_per_m: 10e6 * LENGTH_M,
        c2_0_ns_per_m: 0.75e6 * LENGTH_M,
        chi,
        p0_n: 64e3,
    });
    AugmentedModel {
        element,
        length_m: LENGTH_M,
        effects: Vec::new(),
    }
}

/// The library effect a hidden truth adds (`None`: none, or a truth applied otherwise).
fn effect_of(hidden: &str) -> Option<Effect> {
    match hidden {
        "load-train-resonance" => Some(Effect::LoadTrainResonance {
            natural_frequency_hz: 80.0,
            damping_ratio: 0.04,
        }),
        // Poorly cooled (0.05 W/K), a minute's time constant: a 5 kN, 20 Hz test warms it
        // by about 2 K within its 20 s record.
        // Filled-rubber Mullins softening: up to 5 % below the largest load, over 30 kN.
        "cyclic-softening" => Some(Effect::CyclicSoftening {
            softening_limit: 0.05,
            force_scale_n: 30e3,
            max_force_n: 0.0,
        }),
        "self-heating" => Some(Effect::SelfHeating {
            heat_capacity_j_per_k: 3.0,
            heat_transfer_w_per_k: 0.05,
            temperature_rise_k: 0.0,
        }),
        "amplitude-friction" | "friction-passages-only" => Some(Effect::AmplitudeFriction {
            stiffness_n_per_m: 20e6 * LENGTH_M,
            slip_force_n: 1.0e3 * LENGTH_M,
            law: FrictionLaw::Dahl { exponent: 1.0 },
        }),
        "fractional-damping" => Some(Effect::FractionalDamping {
            coefficient_ns_alpha_per_m: 7e5 * LENGTH_M,
            alpha: 0.3,
        }),
        "temperature-shift" => Some(Effect::TemperatureShift {
            reference_temperature_c: 23.0,
            operating_temperature_c: 23.0,
            log10_time_shift_per_c: 0.03,
            ln_modulus_shift_per_c: 0.006,
        }),
        "channel-delay" => Some(Effect::ChannelDelay { force_lag_s: 4e-4 }),
        "moving-mass" => Some(Effect::MovingMass { mass_kg: 40.0 }),
        _ => None,
    }
}

/// The baseline a user would start from: no effects, parameters 10-30 % off, chi 0 when
/// preload stiffening is what is hidden.
fn baseline_toml(hidden: &str) -> String {
    let chi = if hides(hidden, "preload-stiffening") {
        0.0
    } else {
        0.3
    };
    format!(
        "# Baseline for the synthetic campaign: parameters off; diagnose recalibrates them.\nform = \"consistent\"\nlength_m = {LENGTH_M}\nk1_0_n_per_m2 = 75e6\nk2_0_n_per_m2 = 7e6\nc2_0_ns_per_m2 = 0.5e6\nchi = {chi:?}\np0_n = 64e3\n"
    )
}

/// The truth at one test: the specimen's moduli scaled for a softening specimen.
fn model_at(truth: &AugmentedModel, softening: f64, temperature_c: f64) -> AugmentedModel {
    let mut model = truth.at_temperature(temperature_c);
    if let ElementModel::Consistent(p) = &mut model.element {
        p.k1_0_n_per_m *= 1.0 - softening;
        p.k2_0_n_per_m *= 1.0 - softening;
        p.c2_0_ns_per_m *= 1.0 - softening;
    }
    model
}

/// Force through a resonance of the load path (80 Hz, 4 % damping), bilinear transform.
fn load_path(force_n: &[f64], dt_s: f64) -> Vec<f64> {
    let w = 2.0 * PI * 80.0;
    let zeta = 0.04;
    let k = 2.0 / dt_s;
    let a0 = k * k + 2.0 * zeta * w * k + w * w;
    let b = [w * w / a0, 2.0 * w * w / a0, w * w / a0];
    let a = [
        2.0 * (w * w - k * k) / a0,
        (k * k - 2.0 * zeta * w * k + w * w) / a0,
    ];
    let first = force_n.first().copied().unwrap_or(0.0);
    let (mut x1, mut x2, mut y1, mut y2) = (first, first, first, first);
    force_n
        .iter()
        .map(|&x| {
            let y = b[0] * x + b[1] * x1 + b[2] * x2 - a[0] * y1 - a[1] * y2;
            (x2, x1, y2, y1) = (x1, x, y1, y);
            y
        })
        .collect()
}

/// Runs the model over `z(t)` on the fine grid from `t_start_s` (at rest there) and
/// returns the record's samples from t = 0 at step `dt_s`, and the self-heating rise at
/// the end.
fn record(
    model: &AugmentedModel,
    resonance: bool,
    z_of: &dyn Fn(f64) -> f64,
    t_start_s: f64,
    dt_s: f64,
    n: usize,
) -> (Vec<f64>, Vec<f64>, (f64, f64)) {
    let h = dt_s / SUBSTEPS as f64;
    let n_settle = (-t_start_s / dt_s).round() as usize * SUBSTEPS;
    let t_start_s = -(n_settle as f64) * h;
    let n_fine = n_settle + n * SUBSTEPS;
    let mut stepper = ModelStepper::new(model, StepperMode::Measurement, h, z_of(t_start_s));
    let mut fine = Vec::with_capacity(n_fine);
    for j in 0..n_fine {
        fine.push(stepper.step(z_of(t_start_s + (j + 1) as f64 * h)).0);
    }
    if resonance {
        fine = load_path(&fine, h);
    }
    let z = (0..n).map(|i| z_of(i as f64 * dt_s)).collect();
    let f = (0..n)
        .map(|i| fine[(n_settle + i * SUBSTEPS).saturating_sub(1)])
        .collect();
    (z, f, (stepper.temperature_rise_k(), stepper.max_force_n()))
}

/// The truth at the start of a test: the self-heating rise carried from the last test's
/// end, cooled over the rest between them, and the largest load carried so far.
fn carried(truth: &AugmentedModel, state: (f64, f64), rest_s: f64) -> AugmentedModel {
    let (rise_k, max_n) = state;
    let mut out = truth.clone();
    for effect in &mut out.effects {
        match effect {
            Effect::SelfHeating {
                heat_capacity_j_per_k,
                heat_transfer_w_per_k,
                temperature_rise_k,
            } => {
                let tau_s = *heat_capacity_j_per_k / *heat_transfer_w_per_k;
                *temperature_rise_k = rise_k * (-rest_s.max(0.0) / tau_s).exp();
            }
            Effect::CyclicSoftening { max_force_n, .. } => *max_force_n = max_n,
            _ => {}
        }
    }
    out
}

/// Writes the campaign; returns the number of tests.
pub fn write_synthetic_campaign(dir: &Path, hidden: &str, seed: u64) -> std::io::Result<usize> {
    write_synthetic_campaign_with(dir, hidden, seed, false)
}

/// `write_synthetic_campaign`; with `from_rest` each harmonic record starts where its
/// loading starts, the specimen at rest at the preload (the drive
/// `z_static + a1 sin(W t) + 0.02 a1 sin(2 W t)`), so the start-up is in the record,
/// instead of after a 1.5 s lead-in.
pub fn write_synthetic_campaign_with(
    dir: &Path,
    hidden: &str,
    seed: u64,
    from_rest: bool,
) -> std::io::Result<usize> {
    assert!(valid_hidden(hidden), "unknown hidden effect");
    std::fs::create_dir_all(dir)?;
    let truth = truth_model(hidden);
    let resonance = hides(hidden, "load-path-resonance");
    let heating = hides(hidden, "self-heating");
    let spacing_s = 360.0;
    // The specimen's state carried between tests: self-heating rise, largest load.
    let mut carry = (0.0, 0.0);
    let mut last_end_s = 0.0;
    let softening_total = if hides(hidden, "softening-specimen") || hides(hidden, "specimen-drift")
    {
        0.06
    } else {
        0.0
    };
    let points = design(hides(hidden, "friction-passages-only"));
    let n_passages = 3;
    let n_tests = points.len() + n_passages;
    let mut rng = Rng(seed);
    let mut toml = String::from(
        "# Synthetic campaign written by `fastemu synth-campaign` (truth in truth.toml).\nsample_length_m = 0.75\n",
    );
    let start_s = 1_773_478_800.0; // 2026-03-14 09:00:00 UTC
    let element = |model: &AugmentedModel| model.effective_element();
    let mut write_test = |idx: usize,
                          id: &str,
                          z: &mut [f64],
                          f: &mut [f64],
                          dt_s: f64,
                          force_scale_n: f64,
                          keys: String|
     -> std::io::Result<()> {
        let z_amp = 0.5
            * (z.iter().copied().fold(f64::NEG_INFINITY, f64::max)
                - z.iter().copied().fold(f64::INFINITY, f64::min));
        let mut ar = 0.0;
        for (zi, fi) in z.iter_mut().zip(f.iter_mut()) {
            ar = 0.98 * ar + (1.0f64 - 0.98 * 0.98).sqrt() * rng.normal();
            *fi += force_scale_n * (0.005 * rng.normal() + 0.005 * ar);
            *zi += z_amp * 0.005 * rng.normal();
        }
        let mut csv = String::from("t_s,displacement_m,force_n\n");
        for (i, (zi, fi)) in z.iter().zip(f.iter()).enumerate() {
            let _ = writeln!(csv, "{:?},{zi:?},{fi:?}", i as f64 * dt_s);
        }
        std::fs::write(dir.join(format!("{id}.csv")), csv)?;
        let started = start_s + spacing_s * idx as f64;
        let _ = write!(
            toml,
            "\n[[test]]\nid = \"{id}\"\nfile = \"{id}.csv\"\n{keys}started_at = \"{}\"\n",
            iso8601(started)
        );
        Ok(())
    };
    for (idx, p) in points.iter().enumerate() {
        let softening = softening_total * idx as f64 / (n_tests - 1) as f64;
        let started_s = spacing_s * idx as f64;
        let model = model_at(
            &carried(&truth, carry, started_s - last_end_s),
            softening,
            p.temperature_c,
        );
        let el = element(&model);
        let z_static = el.static_displacement_m(p.preload_n);
        let w = 2.0 * PI * p.frequency_hz;
        let stiffness = linear_modulus(&el, p.preload_n, w);
        let a1 = p.amplitude_n / stiffness;
        let (phi1, phi2) = if from_rest {
            (-0.5 * PI, -0.5 * PI)
        } else {
            (0.0, 0.7)
        };
        let z_of = move |t: f64| {
            z_static + a1 * (w * t + phi1).cos() + 0.02 * a1 * (2.0 * w * t + phi2).cos()
        };
        let n_cycles = if heating {
            (20.0 * p.frequency_hz).round()
        } else if p.frequency_hz < 2.0 {
            4.0
        } else {
            8.0
        };
        let dt_s = 1.0 / (64.0 * p.frequency_hz).max(500.0);
        let n = (n_cycles / p.frequency_hz / dt_s).round() as usize;
        // Start at rest 1.5 s early, so the record holds the steady state (the specimen
        // warms over the lead-in too: it is part of the test); from rest, at t = 0.
        let lead_in_s = if from_rest { 0.0 } else { -1.5 };
        let (mut z, mut f, end_state) = record(&model, resonance, &z_of, lead_in_s, dt_s, n);
        carry = end_state;
        last_end_s = started_s + n as f64 * dt_s;
        let id = format!(
            "T{idx:02}-P{:02.0}-F{}-A{}-T{}",
            p.preload_n / 1e3,
            p.frequency_hz,
            p.amplitude_n / 1e3,
            p.temperature_c
        );
        let keys = format!(
            "kind = \"harmonic\"\npreload_n = {:?}\namplitude_n = {:?}\nfrequency_hz = {:?}\ntemperature_c = {:?}\n",
            p.preload_n, p.amplitude_n, p.frequency_hz, p.temperature_c
        );
        write_test(idx, &id, &mut z, &mut f, dt_s, p.amplitude_n, keys)?;
    }
    for k in 0..n_passages {
        let idx = points.len() + k;
        let softening = softening_total * idx as f64 / (n_tests - 1) as f64;
        let started_s = spacing_s * idx as f64;
        let model = model_at(
            &carried(&truth, carry, started_s - last_end_s),
            softening,
            23.0,
        );
        let el = element(&model);
        let preload_n = 20e3;
        let peak_n = 8e3 + 8e3 * k as f64;
        let z_static = el.static_displacement_m(preload_n);
        let amp = peak_n / linear_modulus(&el, preload_n, 2.0 * PI * 5.0);
        let z_of = move |t: f64| {
            z_static
                + (0..4)
                    .map(|axle| {
                        let u = (t - 0.6 - 0.75 * axle as f64) / 0.06;
                        amp * (-u * u).exp()
                    })
                    .sum::<f64>()
        };
        let dt_s = 1e-3;
        let (mut z, mut f, end_state) = record(&model, resonance, &z_of, -0.5, dt_s, 4000);
        carry = end_state;
        last_end_s = started_s + 4.0;
        let id = format!("H{k}-passage-{:.0}kN", peak_n / 1e3);
        write_test(
            idx,
            &id,
            &mut z,
            &mut f,
            dt_s,
            0.5 * peak_n,
            "kind = \"history\"\ntemperature_c = 23.0\n".into(),
        )?;
    }
    std::fs::write(dir.join("campaign.toml"), toml)?;
    std::fs::write(dir.join("baseline.toml"), baseline_toml(hidden))?;
    let truth_text = format!(
        "# The truth behind this synthetic campaign (diagnose never reads this file).\n# hidden = \"{hidden}\", seed = {seed}\n# {}\n{}",
        hidden.split('+').map(|part| match part {
            "load-path-resonance" =>
                "load-train-resonance's cause by another law: the force reaches the load cell through an 80 Hz, 4 % damped resonance of the load path, filtered after the model.",
            "softening-specimen" =>
                "specimen-drift's cause by another law: the specimen's moduli fall linearly by 6 % from the first test to the last.",
            "specimen-drift" =>
                "specimen-drift: the specimen's moduli fall linearly by 6 % from the first test to the last (test order; started_at every 6 min, so time too). The parameters below are the first test's.",
            "cyclic-softening" =>
                "cyclic-softening (Mullins): the largest load carried so far carried from test to test; the element parameters are the virgin specimen's.",
            "self-heating" =>
                "self-heating with the default temperature law (no temperature-shift): each test's thermal state carried from the last and cooled in the 6 min between starts; 20 s records.",
            "friction-passages-only" =>
                "Amplitude friction with one harmonic force amplitude: only the passages span amplitudes.",
            "none" => "Nothing hidden: the baseline's structure is the truth (only its parameters are off).",
            _ => "A library effect, with the parameters below.",
        }).collect::<Vec<_>>().join("\n# "),
        truth.render_toml("")
    );
    std::fs::write(dir.join("truth.toml"), truth_text)?;
    Ok(n_tests)
}

/// Modulus magnitude of the linearised Zener element at preload `p` and `w` rad/s.
fn linear_modulus(element: &ElementModel, preload_n: f64, w: f64) -> f64 {
    match element {
        ElementModel::Consistent(p) | ElementModel::Paper(p) => {
            let g = p.preload_factor(preload_n);
            let (k1, k2, c2) = (p.k1_0_n_per_m * g, p.k2_0_n_per_m * g, p.c2_0_ns_per_m * g);
            let x = (c2 * w / k2).powi(2);
            (k1 + k2 * x / (1.0 + x)).hypot(w * c2 / (1.0 + x))
        }
        ElementModel::KelvinVoigt(p) => p.k_n_per_m.hypot(w * p.c_ns_per_m),
    }
}

/// ISO 8601 UTC of seconds since 1970 (whole seconds).
fn iso8601(seconds: f64) -> String {
    let [y, m, d, hh, mm, ss] = crate::utc::civil(seconds.round() as i64);
    format!("{y:04}-{m:02}-{d:02}T{hh:02}:{mm:02}:{ss:02}Z")
}

#[cfg(test)]
mod tests {
    use super::iso8601;
    use crate::ident::campaign::parse_iso8601_s;

    #[test]
    fn iso8601_round_trips() {
        for s in [0.0, 951_782_400.0, 1_773_478_800.0, 4_107_542_399.0] {
            assert_eq!(parse_iso8601_s(&iso8601(s)), Some(s), "{}", iso8601(s));
        }
        assert_eq!(iso8601(1_773_478_800.0), "2026-03-14T09:00:00Z");
        assert_eq!(
            parse_iso8601_s("2026-03-14T10:00:00+01:00"),
            Some(1_773_478_800.0)
        );
        assert_eq!(parse_iso8601_s("2026-03-14 09:00"), Some(1_773_478_800.0));
        assert_eq!(parse_iso8601_s("14/03/2026"), None);
    }
}
