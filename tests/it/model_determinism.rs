//! Determinism contract (STYLE): same model + same input trace => bit-identical output.

use fastemu::model::oscillator::{simulate_rail, Oscillator, StartCondition};
use fastemu::model::{ElementModel, ForceStepper, KelvinVoigtParams, ZenerParams};

use crate::common::PI;

pub fn all_models(length_m: f64) -> [ElementModel; 3] {
    let zener = ZenerParams::paper_table3(length_m);
    [
        ElementModel::Consistent(zener),
        ElementModel::Paper(zener),
        ElementModel::KelvinVoigt(KelvinVoigtParams::paper_linear(length_m)),
    ]
}

/// A displacement trace with preload, a slow and a fast component and some tension.
pub fn displacement_trace(n: usize, dt: f64) -> Vec<f64> {
    (0..n)
        .map(|i| {
            let t = i as f64 * dt;
            3e-4 + 5e-4 * (2.0 * PI * 3.0 * t).sin() + 3e-6 * (2.0 * PI * 170.0 * t).sin()
        })
        .collect()
}

fn force_bits(model: ElementModel, dt: f64, z: &[f64]) -> Vec<(u64, u8)> {
    let mut stepper = ForceStepper::new(model, dt, z[0]);
    z.iter()
        .map(|&zi| {
            let (f, flags) = stepper.step(zi);
            (f.to_bits(), flags.0)
        })
        .collect()
}

fn oscillator_bits(model: ElementModel, dt: f64, load: &[f64]) -> Vec<[u64; 4]> {
    let mut osc = Oscillator::new(model, 60.21, dt, 2.0 * 60e3);
    osc.start(StartCondition::Rest, load[0]);
    load.windows(2)
        .map(|pair| {
            let flags = osc.step(pair[0], pair[1]);
            [
                osc.displacement_m().to_bits(),
                osc.velocity_m_per_s().to_bits(),
                osc.element_force_n().to_bits(),
                flags.0 as u64,
            ]
        })
        .collect()
}

#[test]
fn force_stepper_reruns_are_bit_identical() {
    let dt = 1.0 / 4096.0;
    let z = displacement_trace(20_000, dt);
    for model in all_models(0.75) {
        let first = force_bits(model, dt, &z);
        let second = force_bits(model, dt, &z);
        assert!(first == second, "{}: reruns differ", model.form());
        // A stepper copied mid-run continues identically to the original.
        let mut a = ForceStepper::new(model, dt, z[0]);
        for &zi in &z[..5000] {
            a.step(zi);
        }
        let mut b = a;
        for &zi in &z[5000..] {
            assert_eq!(a.step(zi).0.to_bits(), b.step(zi).0.to_bits());
        }
    }
}

#[test]
fn oscillator_reruns_are_bit_identical() {
    let dt = 1e-4;
    let load: Vec<f64> = (0..20_000)
        .map(|i| 55e3 + 1e3 * (2.0 * PI * 170.0 * i as f64 * dt).sin())
        .collect();
    for model in all_models(1.0) {
        assert!(
            oscillator_bits(model, dt, &load) == oscillator_bits(model, dt, &load),
            "{}: reruns differ",
            model.form()
        );
        let run = || simulate_rail(model, 60.21, dt, &load, StartCondition::Static).0;
        let (a, b) = (run(), run());
        assert!(a.iter().zip(&b).all(|(x, y)| {
            x.displacement_m.to_bits() == y.displacement_m.to_bits()
                && x.velocity_m_per_s.to_bits() == y.velocity_m_per_s.to_bits()
                && x.element_force_n.to_bits() == y.element_force_n.to_bits()
        }));
    }
}
