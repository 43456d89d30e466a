//! Wall-clock time of the offline mass-on-element simulation (`simulate_rail`) on a given
//! load history: the compute kernel behind `fastemu simulate rail`, without process
//! start-up and CSV I/O, for the comparison with SciPy (`benches/scipy_rail.py`).

use std::hint::black_box;
use std::time::Instant;

use crate::model::oscillator::{simulate_rail, StartCondition};
use crate::model::ElementModel;

/// Timing of repeated runs of one scenario.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RailTiming {
    pub form: &'static str,
    pub n_samples: usize,
    pub dt_s: f64,
    pub substeps_per_step: u32,
    pub runs: usize,
    pub median_s: f64,
    pub min_s: f64,
    pub max_s: f64,
    pub median_ns_per_step: f64,
}

/// Runs `simulate_rail` `runs` times on the same input and reports the spread.
pub fn time_simulate_rail(
    model: ElementModel,
    mass_kg: f64,
    dt_s: f64,
    external_force_n: &[f64],
    start: StartCondition,
    runs: usize,
) -> RailTiming {
    let max_force = external_force_n.iter().fold(0.0f64, |m, f| m.max(f.abs()));
    // Same sub-step sizing as `simulate_rail`, reported for context.
    let substeps = crate::model::Oscillator::new(model, mass_kg, dt_s, 2.0 * max_force).substeps();
    let mut seconds = Vec::with_capacity(runs);
    for _ in 0..runs {
        let started = Instant::now();
        let out = simulate_rail(model, mass_kg, dt_s, black_box(external_force_n), start);
        black_box(&out);
        seconds.push(started.elapsed().as_secs_f64());
    }
    let median_s = super::median(&seconds);
    let steps = external_force_n.len().saturating_sub(1).max(1);
    RailTiming {
        form: model.form().name(),
        n_samples: external_force_n.len(),
        dt_s,
        substeps_per_step: substeps,
        runs,
        median_s,
        min_s: seconds.iter().copied().fold(f64::INFINITY, f64::min),
        max_s: seconds.iter().copied().fold(0.0, f64::max),
        median_ns_per_step: median_s * 1e9 / steps as f64,
    }
}
