//! Percentile bookkeeping on hdrhistogram: the one histogram shape every latency figure
//! uses (1 ns to 1 s, 3 significant digits), the summary the report prints, and the
//! percentile-distribution curve the plot draws. No clocks, no I/O.

use hdrhistogram::Histogram;

/// Lowest and highest trackable latency, ns, and significant decimal digits.
pub const LOWEST_NS: u64 = 1;
pub const HIGHEST_NS: u64 = 1_000_000_000;
pub const SIGNIFICANT_DIGITS: u8 = 3;

/// An empty latency histogram in ns (values above 1 s saturate to 1 s).
pub fn new_latency_histogram() -> Histogram<u64> {
    Histogram::<u64>::new_with_bounds(LOWEST_NS, HIGHEST_NS, SIGNIFICANT_DIGITS)
        .expect("constant histogram bounds are valid")
}

/// The percentiles every latency line reports, ns (hdrhistogram's equivalent-value
/// rounding: within 0.1 % of the recorded value).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct PercentileSummary {
    pub p50_ns: u64,
    pub p90_ns: u64,
    pub p99_ns: u64,
    pub p999_ns: u64,
    pub p9999_ns: u64,
    pub max_ns: u64,
    pub samples: u64,
}

impl PercentileSummary {
    pub fn from_histogram(hist: &Histogram<u64>) -> PercentileSummary {
        PercentileSummary {
            p50_ns: hist.value_at_quantile(0.50),
            p90_ns: hist.value_at_quantile(0.90),
            p99_ns: hist.value_at_quantile(0.99),
            p999_ns: hist.value_at_quantile(0.999),
            p9999_ns: hist.value_at_quantile(0.9999),
            max_ns: hist.max(),
            samples: hist.len(),
        }
    }
}

/// Points of the percentile distribution for a plot on HdrHistogram's "1/(1-p)" axis:
/// `(1 / (1 - quantile), value_ns)`, from p0 up to the last recorded value. The final
/// point (quantile 1, infinite on that axis) is placed one decade past the previous.
pub fn percentile_curve(hist: &Histogram<u64>) -> Vec<(f64, f64)> {
    let mut points = Vec::new();
    if hist.is_empty() {
        return points;
    }
    for step in hist.iter_quantiles(5) {
        let quantile = step.quantile_iterated_to();
        let value_ns = hist.highest_equivalent(step.value_iterated_to()) as f64;
        let x = if quantile < 1.0 {
            1.0 / (1.0 - quantile)
        } else {
            points.last().map_or(10.0, |&(x, _)| x * 10.0)
        };
        points.push((x, value_ns.max(1.0)));
    }
    points
}
