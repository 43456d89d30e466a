//! Records as CSV, one file per record stream, in one streaming pass (for MATLAB, pandas
//! and the CSV tools): the same columns as the record types' fields.

use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use super::reader::{ReadStats, RecordSet, RecordsError};
use super::Record;

/// One CSV file fed with the messages of one topic.
pub trait TopicCsv {
    fn topic(&self) -> &'static str;
    fn write(&mut self, data: &[u8]) -> std::io::Result<bool>;
    fn finish(&mut self) -> std::io::Result<(PathBuf, u64)>;
}

/// The CSV writer of record type `R`.
pub struct CsvOf<R: Record> {
    path: PathBuf,
    out: BufWriter<std::fs::File>,
    rows: u64,
    _marker: std::marker::PhantomData<R>,
}

impl<R: Record> CsvOf<R> {
    pub fn create(path: &Path) -> std::io::Result<Box<dyn TopicCsv>> {
        let mut out = BufWriter::with_capacity(1 << 20, std::fs::File::create(path)?);
        writeln!(out, "{}", R::csv_header())?;
        Ok(Box::new(CsvOf::<R> {
            path: path.to_path_buf(),
            out,
            rows: 0,
            _marker: std::marker::PhantomData,
        }))
    }
}

impl<R: Record> TopicCsv for CsvOf<R> {
    fn topic(&self) -> &'static str {
        R::TOPIC
    }
    fn write(&mut self, data: &[u8]) -> std::io::Result<bool> {
        match R::decode(data) {
            Some(r) => {
                r.write_csv(&mut self.out)?;
                self.rows += 1;
                Ok(true)
            }
            None => Ok(false),
        }
    }
    fn finish(&mut self) -> std::io::Result<(PathBuf, u64)> {
        self.out.flush()?;
        Ok((self.path.clone(), self.rows))
    }
}

/// Writes every message of the sinks' topics; returns (file, rows) per sink.
pub fn export_csv(
    set: &RecordSet,
    mut sinks: Vec<Box<dyn TopicCsv>>,
) -> Result<(Vec<(PathBuf, u64)>, ReadStats), RecordsError> {
    let mut failure: Option<String> = None;
    let stats = set.visit(|topic, _, data| {
        if failure.is_some() {
            return;
        }
        if let Some(sink) = sinks.iter_mut().find(|s| s.topic() == topic) {
            match sink.write(data) {
                Ok(true) => {}
                Ok(false) => {
                    failure = Some(format!("a message on {topic} is shorter than its schema"))
                }
                Err(e) => failure = Some(e.to_string()),
            }
        }
    })?;
    let first = set.files.first().cloned().unwrap_or_default();
    if let Some(message) = failure {
        return Err(RecordsError {
            path: first.display().to_string(),
            message,
        });
    }
    let mut written = Vec::new();
    for sink in &mut sinks {
        written.push(sink.finish().map_err(|e| RecordsError {
            path: first.display().to_string(),
            message: e.to_string(),
        })?);
    }
    Ok((written, stats))
}
