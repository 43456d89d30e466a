//! Latency percentiles (hdrhistogram, ns), filled record by record.

use hdrhistogram::Histogram;
use serde::Serialize;

/// Percentiles of a latency, ns.
#[derive(Debug, Clone, Copy, Serialize, Default, PartialEq)]
pub struct Percentiles {
    pub p50: u64,
    pub p99: u64,
    pub p999: u64,
    pub max: u64,
    pub count: u64,
}

#[derive(Debug, Clone, Serialize, Default)]
pub struct Latency {
    pub end_to_end: Percentiles,
    pub wake_jitter: Percentiles,
}

/// A histogram of ns values from 1 ns to 1000 s.
pub fn histogram() -> Histogram<u64> {
    Histogram::<u64>::new_with_bounds(1, 1_000_000_000_000, 3).expect("valid histogram bounds")
}

pub fn percentiles(h: &Histogram<u64>) -> Percentiles {
    if h.is_empty() {
        return Percentiles::default();
    }
    Percentiles {
        p50: h.value_at_quantile(0.5),
        p99: h.value_at_quantile(0.99),
        p999: h.value_at_quantile(0.999),
        max: h.max(),
        count: h.len(),
    }
}

/// Counts per log-spaced bin (0.1 us to 10 ms, 50 bins) for the histogram plot: bin
/// centres in us and counts.
pub fn log_bins(h: &Histogram<u64>) -> (Vec<f64>, Vec<f64>) {
    let edges: Vec<f64> = (0..=50)
        .map(|i| 10f64.powf(-1.0 + i as f64 * 5.0 / 50.0))
        .collect();
    let mut counts = vec![0.0; 50];
    for v in h.iter_recorded() {
        let us = v.value_iterated_to() as f64 / 1e3;
        if let Some(b) = edges.windows(2).position(|w| us >= w[0] && us < w[1]) {
            counts[b] += v.count_at_value() as f64;
        }
    }
    let centres = edges.windows(2).map(|w| (w[0] * w[1]).sqrt()).collect();
    (centres, counts.iter().map(|c| c + 0.5).collect())
}
