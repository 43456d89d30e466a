//! Nanoseconds per model step for each form, as the emulator calls it: one
//! `ForceStepper::step` per loop period (parameter updates included, since the preload
//! factor is recomputed from the state inside every step).

use std::hint::black_box;
use std::time::Instant;

use crate::model::{ElementModel, ForceStepper, KelvinVoigtParams, ZenerParams};

/// Result for one form: median and spread of the per-run ns/step.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FormTiming {
    pub form: &'static str,
    pub median_ns_per_step: f64,
    pub min_ns_per_step: f64,
    pub max_ns_per_step: f64,
    pub runs: usize,
    pub steps_per_run: usize,
}

/// A displacement history typical of the loop: 20 kN-ish preload plus a 5 Hz and a
/// 170 Hz component, at 4096 Hz, 1 s long (cycled over).
pub fn bench_input(n: usize, dt_s: f64) -> Vec<f64> {
    (0..n)
        .map(|i| {
            let t = i as f64 * dt_s;
            4e-4 + 1e-4 * (2.0 * std::f64::consts::PI * 5.0 * t).sin()
                + 2e-6 * (2.0 * std::f64::consts::PI * 170.0 * t).sin()
        })
        .collect()
}

pub fn time_form(model: ElementModel, runs: usize, steps_per_run: usize) -> FormTiming {
    let dt = 1.0 / 4096.0;
    let input = bench_input(4096, dt);
    let mut per_run = Vec::with_capacity(runs);
    let mut stepper = ForceStepper::new(model, dt, input[0]);
    for _ in 0..runs {
        let start = Instant::now();
        let mut acc = 0.0;
        for i in 0..steps_per_run {
            let (f, _) = stepper.step(black_box(input[i & 4095]));
            acc += f;
        }
        black_box(acc);
        per_run.push(start.elapsed().as_nanos() as f64 / steps_per_run as f64);
    }
    FormTiming {
        form: model.form().name(),
        median_ns_per_step: super::median(&per_run),
        min_ns_per_step: per_run.iter().copied().fold(f64::INFINITY, f64::min),
        max_ns_per_step: per_run.iter().copied().fold(0.0, f64::max),
        runs,
        steps_per_run,
    }
}

/// Times the three forms with the 750 mm sample's parameters, interleaved in rounds so
/// machine drift affects all alike.
pub fn time_all_forms(rounds: usize, steps_per_run: usize) -> Vec<FormTiming> {
    let zener = ZenerParams::paper_table3(0.75);
    let models = [
        ElementModel::Consistent(zener),
        ElementModel::Paper(zener),
        ElementModel::KelvinVoigt(KelvinVoigtParams::paper_linear(0.75)),
    ];
    let mut samples: Vec<Vec<f64>> = vec![Vec::new(); models.len()];
    for _ in 0..rounds {
        for (i, m) in models.iter().enumerate() {
            samples[i].push(time_form(*m, 1, steps_per_run).median_ns_per_step);
        }
    }
    models
        .iter()
        .zip(samples)
        .map(|(m, s)| FormTiming {
            form: m.form().name(),
            median_ns_per_step: super::median(&s),
            min_ns_per_step: s.iter().copied().fold(f64::INFINITY, f64::min),
            max_ns_per_step: s.iter().copied().fold(0.0, f64::max),
            runs: rounds,
            steps_per_run,
        })
        .collect()
}
