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
