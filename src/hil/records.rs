//! Per-cycle records: the loop pushes `Copy` records into a bounded lock-free queue
//! (crossbeam `ArrayQueue`); a non-real-time thread drains it into a CSV file.
//!
//! Must not: block, allocate or do I/O in `RecordSink::push` (a full queue drops the
//! record and counts the drop; drops are reported, never silent).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;

use crossbeam::queue::ArrayQueue;

/// A record that can be written as one CSV line.
/// A sample sequence as a CSV column: `u64::MAX` ("no sample yet") is written as -1.
pub fn sequence_column(sequence: u64) -> i64 {
    if sequence == u64::MAX {
        -1
    } else {
        sequence as i64
    }
}

pub trait CsvRecord: Copy + Send + 'static {
    const HEADER: &'static str;
    fn write_csv(&self, out: &mut dyn Write) -> std::io::Result<()>;
}

/// Counts reported by a finished sink.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SinkCounts {
    pub written: u64,
    pub dropped: u64,
}

/// Producer side of a record queue plus its writer thread.
pub struct RecordSink<R: CsvRecord> {
    queue: Arc<ArrayQueue<R>>,
    dropped: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
    writer: Option<JoinHandle<std::io::Result<u64>>>,
    path: PathBuf,
}

impl<R: CsvRecord> RecordSink<R> {
    /// Creates `path` and starts the writer thread.
    pub fn create(path: &Path, capacity: usize) -> std::io::Result<RecordSink<R>> {
        let file = std::fs::File::create(path)?;
        let queue: Arc<ArrayQueue<R>> = Arc::new(ArrayQueue::new(capacity));
        let stop = Arc::new(AtomicBool::new(false));
        let (q, s) = (queue.clone(), stop.clone());
        let writer = std::thread::Builder::new()
            .name("record-writer".into())
            .spawn(move || -> std::io::Result<u64> {
                let mut out = std::io::BufWriter::with_capacity(1 << 20, file);
                out.write_all(R::HEADER.as_bytes())?;
                out.write_all(b"\n")?;
                let mut written = 0u64;
                let mut unflushed = false;
                loop {
                    let stopping = s.load(Ordering::Acquire);
                    let mut any = false;
                    while let Some(r) = q.pop() {
                        r.write_csv(&mut out)?;
                        written += 1;
                        any = true;
                        unflushed = true;
                    }
                    if stopping && q.is_empty() {
                        break;
                    }
                    if !any {
                        // Flush while idle, so a killed process leaves its records up to
                        // the last few ms on disk.
                        if unflushed {
                            out.flush()?;
                            unflushed = false;
                        }
                        std::thread::sleep(std::time::Duration::from_millis(2));
                    }
                }
                out.flush()?;
                Ok(written)
            })?;
        Ok(RecordSink {
            queue,
            dropped: Arc::new(AtomicU64::new(0)),
            stop,
            writer: Some(writer),
            path: path.to_path_buf(),
        })
    }

    /// Queues a record; a full queue drops it and counts the drop.
    #[inline]
    pub fn push(&self, record: R) {
        if self.queue.push(record).is_err() {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Records dropped so far.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Stops the writer after it drained the queue; returns the counts.
    pub fn finish(mut self) -> std::io::Result<SinkCounts> {
        self.stop.store(true, Ordering::Release);
        let written = match self.writer.take() {
            Some(handle) => handle.join().map_err(|_| {
                std::io::Error::other(format!(
                    "record writer for {} panicked",
                    self.path.display()
                ))
            })??,
            None => 0,
        };
        Ok(SinkCounts {
            written,
            dropped: self.dropped(),
        })
    }
}

impl<R: CsvRecord> Drop for RecordSink<R> {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(handle) = self.writer.take() {
            let _ = handle.join();
        }
    }
}
