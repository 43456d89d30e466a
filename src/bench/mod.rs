//! Benchmarks: model step speed (`model`), offline rail simulation (`rail`), the loop's
//! latency and jitter (`latency`), and what stalls do to the specimen (`ride_through`,
//! deterministic, on the in-process loop), the controller's compensation (`compensation`: its
//! work per command, fidelity per actuator and initial guess). Timing lives here and in reports, never in
//! pass/fail tests.

pub mod compensation;
pub mod latency;
pub mod model;
pub mod rail;
pub mod ride_through;

/// Median of a slice (sorts a copy). Empty slices give NaN.
pub fn median(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut v = values.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}
