//! `ForceStepper::step` and `Oscillator::step` allocate nothing (SPEC 2.2).

use fastemu::model::oscillator::{Oscillator, StartCondition};
use fastemu::model::ForceStepper;

use crate::alloc_counter::count_allocations;
use crate::common::PI;
use crate::model_determinism::{all_models, displacement_trace};

#[test]
fn force_stepper_step_never_allocates() {
    let dt = 1.0 / 4096.0;
    // Inputs prepared outside the counted window; they include tension and a NaN so the
    // clamping and non-finite paths are counted too.
    let mut z = displacement_trace(50_000, dt);
    z[30_000] = -5e-3;
    z[30_001] = f64::NAN;
    for model in all_models(0.75) {
        let mut stepper = ForceStepper::new(model, dt, z[0]);
        let mut sum = 0.0;
        let allocations = count_allocations(|| {
            for &zi in &z {
                sum += stepper.step(zi).0;
            }
        });
        assert_eq!(allocations, 0, "{}", model.form());
        assert!(sum.is_finite());
    }
}

#[test]
fn oscillator_step_never_allocates() {
    let dt = 1e-4;
    let mut load: Vec<f64> = (0..20_000)
        .map(|i| 55e3 + 1e3 * (2.0 * PI * 170.0 * i as f64 * dt).sin())
        .collect();
    load[15_000] = f64::INFINITY;
    for model in all_models(1.0) {
        let mut osc = Oscillator::new(model, 60.21, dt, 120e3);
        osc.start(StartCondition::Rest, load[0]);
        let allocations = count_allocations(|| {
            for pair in load.windows(2) {
                osc.step(pair[0], pair[1]);
            }
        });
        assert_eq!(allocations, 0, "{}", model.form());
        assert!(osc.displacement_m().is_finite());
    }
}

/// A model with every effect the emulator runs step by step (self-heating retuning the
/// element as it warms) and the rig artefacts of measurement mode (load-train resonance,
/// delay line, moving mass): `ModelStepper::step` allocates nothing in either mode.
#[test]
fn model_stepper_with_self_heating_and_rig_artefacts_never_allocates() {
    use fastemu::model::effects::{AugmentedModel, Effect, ModelStepper, StepperMode};
    use fastemu::model::file::parse_model_toml;
    let text = "form = \"consistent\"\nlength_m = 0.75\nk1_0_n_per_m2 = 62e6\nk2_0_n_per_m2 = 9.6e6\nc2_0_ns_per_m2 = 0.7e6\nchi = 0.21\np0_n = 64e3\n";
    let spec = parse_model_toml(text, "m.toml").unwrap();
    let mut model = AugmentedModel::from_spec(&spec, "m.toml").unwrap();
    model.effects = vec![
        Effect::SelfHeating {
            heat_capacity_j_per_k: 0.5,
            heat_transfer_w_per_k: 0.01,
            temperature_rise_k: 0.0,
        },
        Effect::FractionalDamping {
            coefficient_ns_alpha_per_m: 5e5,
            alpha: 0.3,
        },
        Effect::LoadTrainResonance {
            natural_frequency_hz: 300.0,
            damping_ratio: 0.05,
        },
        Effect::ChannelDelay { force_lag_s: 3e-4 },
        Effect::MovingMass { mass_kg: 20.0 },
    ];
    let dt = 1.0 / 4096.0;
    let z: Vec<f64> = (0..50_000)
        .map(|i| 5e-4 + 2e-4 * (2.0 * PI * 20.0 * i as f64 * dt).sin())
        .collect();
    for mode in [StepperMode::Emulation, StepperMode::Measurement] {
        let mut stepper = ModelStepper::new(&model, mode, dt, z[0]);
        let mut sum = 0.0;
        let allocations = count_allocations(|| {
            for &zi in &z {
                sum += stepper.step(zi).0;
            }
        });
        assert_eq!(allocations, 0, "{mode:?}");
        assert!(sum.is_finite());
        assert!(stepper.temperature_rise_k() > 0.1, "it warmed");
    }
}
