//! HdrHistogram interval logs (`.hlog`): one interval per benchmark round, tagged with
//! the transport or scheduler configuration, V2 + DEFLATE compressed histograms, so the
//! standard tools (`HistogramLogProcessor -tag iceoryx2 -i latency.hlog`, HdrHistogram
//! plotters) read them. Values are ns. Offline only.

use std::io::Write;
use std::path::Path;
use std::time::{Duration, SystemTime};

use anyhow::Context;
use hdrhistogram::serialization::interval_log::{IntervalLogWriterBuilder, Tag};
use hdrhistogram::serialization::V2DeflateSerializer;
use hdrhistogram::Histogram;

/// One interval: what was measured during one round of one configuration.
#[derive(Debug, Clone)]
pub struct LoggedInterval {
    /// Transport or configuration name; no commas, spaces or newlines.
    pub tag: String,
    /// Interval start, since the log's BaseTime.
    pub start_offset: Duration,
    pub duration: Duration,
    pub histogram: Histogram<u64>,
}

/// Writes `intervals` (sorted by start) as an interval log with `base_time` as BaseTime
/// and StartTime.
pub fn write_interval_log<W: Write>(
    out: &mut W,
    base_time: SystemTime,
    comments: &[String],
    intervals: &[LoggedInterval],
) -> anyhow::Result<()> {
    let mut sorted: Vec<&LoggedInterval> = intervals.iter().collect();
    sorted.sort_by_key(|i| i.start_offset);
    let mut serializer = V2DeflateSerializer::new();
    let mut builder = IntervalLogWriterBuilder::new();
    for c in comments {
        builder.add_comment(c);
    }
    let mut writer = builder
        .with_start_time(base_time)
        .with_base_time(base_time)
        .begin_log_with(out, &mut serializer)?;
    for interval in sorted {
        let tag = Tag::new(&interval.tag).with_context(|| {
            format!(
                "interval tag `{}` may not contain ',', ' ' or newlines",
                interval.tag
            )
        })?;
        writer
            .write_histogram(
                &interval.histogram,
                interval.start_offset,
                interval.duration,
                Some(tag),
            )
            .map_err(|e| anyhow::anyhow!("writing interval `{}`: {e}", interval.tag))?;
    }
    Ok(())
}

/// `write_interval_log` into a file.
pub fn write_interval_log_file(
    path: &Path,
    base_time: SystemTime,
    comments: &[String],
    intervals: &[LoggedInterval],
) -> anyhow::Result<()> {
    let mut buf = Vec::new();
    write_interval_log(&mut buf, base_time, comments, intervals)?;
    std::fs::write(path, buf).with_context(|| format!("cannot write {}", path.display()))
}
