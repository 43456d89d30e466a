//! Tension beyond the model's domain and non-finite inputs (SPEC 2.1): never NaN or
//! infinity, keep going, raise a flag.

use fastemu::model::oscillator::{Oscillator, StartCondition};
use fastemu::model::{ElementModel, ForceStepper, Form, StepFlags};

use crate::model_determinism::all_models;

#[test]
fn force_stepper_deep_tension_stays_finite_and_is_flagged() {
    let dt = 1.0 / 4096.0;
    for model in all_models(0.75) {
        let mut stepper = ForceStepper::new(model, dt, 0.0);
        let mut flags = StepFlags::NONE;
        // 0 -> -20 mm (the domain ends near -1.7 mm for the lab sample), hold, come back.
        let path = (0..=400)
            .map(|i| -20e-3 * i as f64 / 400.0)
            .chain(std::iter::repeat_n(-20e-3, 400))
            .chain((0..=400).map(|i| -20e-3 + 21e-3 * i as f64 / 400.0));
        for z in path {
            let (f, step_flags) = stepper.step(z);
            assert!(f.is_finite(), "{}: force {f} at z {z}", model.form());
            flags |= step_flags;
        }
        assert!(!flags.contains(StepFlags::NONFINITE_INPUT));
        if model.form() == Form::KelvinVoigt {
            // The linear model has no domain limit: nothing to clamp.
            assert!(flags.is_empty());
        } else {
            assert!(
                flags.contains(StepFlags::TENSION_CLAMPED),
                "{}",
                model.form()
            );
            // Back in compression the model recovers to a finite compressive force.
            assert!(stepper.force_n() > 0.0, "{}", model.form());
        }
    }
}

#[test]
fn force_stepper_nonfinite_input_is_flagged_and_holds_the_force() {
    for model in all_models(0.75) {
        let mut stepper = ForceStepper::new(model, 1e-3, 1e-4);
        stepper.step(2e-4);
        let before = stepper.force_n();
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let (f, flags) = stepper.step(bad);
            assert!(
                flags.contains(StepFlags::NONFINITE_INPUT),
                "{}",
                model.form()
            );
            assert_eq!(f.to_bits(), before.to_bits(), "{}", model.form());
        }
        let (f, flags) = stepper.step(2e-4);
        assert!(f.is_finite() && flags.is_empty(), "{}", model.form());
    }
}

#[test]
fn oscillator_pulled_into_deep_tension_stays_finite_and_is_flagged() {
    let dt = 1e-4;
    for model in all_models(1.0) {
        let mut osc = Oscillator::new(model, 60.21, dt, 400e3);
        osc.start(StartCondition::Rest, 0.0);
        let mut flags = StepFlags::NONE;
        // -200 kN pulls far beyond the domain (-P0 = -64 kN is the Zener forms' floor).
        for _ in 0..2000 {
            flags |= osc.step(-200e3, -200e3);
            assert!(
                osc.displacement_m().is_finite()
                    && osc.velocity_m_per_s().is_finite()
                    && osc.element_force_n().is_finite(),
                "{}",
                model.form()
            );
        }
        if matches!(model, ElementModel::KelvinVoigt(_)) {
            assert!(flags.is_empty());
        } else {
            assert!(
                flags.contains(StepFlags::TENSION_CLAMPED),
                "{}",
                model.form()
            );
        }
        let x = osc.displacement_m();
        let flags = osc.step(f64::NAN, 0.0);
        assert!(flags.contains(StepFlags::NONFINITE_INPUT));
        assert_eq!(osc.displacement_m().to_bits(), x.to_bits());
    }
}
