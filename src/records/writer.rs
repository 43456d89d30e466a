//! A process's record writer: bounded lock-free queues (crossbeam `ArrayQueue`) filled by
//! the loop, drained by one non-real-time thread into the process's MCAP part file
//! (`<dir>/parts/<process>-<n>.mcap`, zstd chunks). Every `FLUSH_INTERVAL` the open chunk
//! is closed and the file flushed, so a killed process leaves every record up to the last
//! flush readable; every `ROLL_INTERVAL` the part is finished and a new one begun, so the
//! writer's index (one entry per chunk) stays bounded however long the run.
//!
//! Must not: block, allocate or do I/O in `RecordSink::push`.

use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam::queue::ArrayQueue;

use super::{Record, META_TOPIC, PROFILE};

/// Longest time a record waits in memory before its chunk is closed and flushed.
pub const FLUSH_INTERVAL: Duration = Duration::from_millis(80);
/// A part file is finished and the next begun after this long. The writer's chunk index
/// (one entry per `FLUSH_INTERVAL`) grows until then: at 300 s it reached about 1 MB and
/// left the allocator's high-water mark stepping up at part changes over an hour; at 60 s
/// each loop process's memory was flat within 0.1 MB from minute 5 to minute 10.
pub const ROLL_INTERVAL: Duration = Duration::from_secs(60);
/// The writer thread's poll period.
const POLL: Duration = Duration::from_millis(2);

/// Producer side of one record queue: cheap to clone, `push` never blocks.
pub struct RecordSink<R: Record> {
    queue: Arc<ArrayQueue<R>>,
    dropped: Arc<AtomicU64>,
    /// The writer's completed flushes (closed chunks on disk), counted.
    flushes: Arc<AtomicU64>,
}

impl<R: Record> Clone for RecordSink<R> {
    fn clone(&self) -> Self {
        RecordSink {
            queue: self.queue.clone(),
            dropped: self.dropped.clone(),
            flushes: self.flushes.clone(),
        }
    }
}

impl<R: Record> RecordSink<R> {
    /// Queues a record; a full queue drops it and counts the drop.
    #[inline]
    pub fn push(&self, record: R) {
        if self.queue.push(record).is_err() {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Waits, up to `timeout`, until every record pushed to this sink before the call is
    /// in a flushed chunk on disk (its queue drained, then a flush after that); whether it
    /// is. For a process about to kill itself (an injected kill): not for a loop's turn.
    pub fn wait_flushed(&self, timeout: std::time::Duration) -> bool {
        let until = Instant::now() + timeout;
        while !self.queue.is_empty() {
            if Instant::now() >= until {
                return false;
            }
            std::thread::sleep(POLL);
        }
        // The drain that emptied the queue wrote its records before the flush that
        // follows it in the writer's turn: any flush counted from here on holds them.
        let seen = self.flushes.load(Ordering::Acquire);
        while self.flushes.load(Ordering::Acquire) <= seen {
            if Instant::now() >= until {
                return false;
            }
            std::thread::sleep(POLL);
        }
        true
    }

    /// Records dropped so far.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

/// Counts of one record stream at the end.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct SinkCounts {
    pub written: u64,
    pub dropped: u64,
}

type McapWriter = mcap::Writer<BufWriter<std::fs::File>>;

trait Drain: Send {
    fn topic(&self) -> &'static str;
    fn register(&mut self, writer: &mut McapWriter) -> mcap::McapResult<()>;
    /// Writes everything queued; returns how many.
    fn drain(&mut self, writer: &mut McapWriter, start_unix_ns: u64) -> mcap::McapResult<u64>;
    /// Empties the queue without writing (after a write error), counting drops.
    fn discard(&mut self);
    fn counts(&self) -> SinkCounts;
}

struct QueueDrain<R: Record> {
    queue: Arc<ArrayQueue<R>>,
    dropped: Arc<AtomicU64>,
    channel_id: u16,
    sequence: u32,
    written: u64,
    buf: Vec<u8>,
}

impl<R: Record> Drain for QueueDrain<R> {
    fn topic(&self) -> &'static str {
        R::TOPIC
    }

    fn register(&mut self, writer: &mut McapWriter) -> mcap::McapResult<()> {
        let schema = writer.add_schema(R::SCHEMA_NAME, "ros1msg", R::schema_text().as_bytes())?;
        self.channel_id = writer.add_channel(schema, R::TOPIC, "ros1", &Default::default())?;
        Ok(())
    }

    fn drain(&mut self, writer: &mut McapWriter, start_unix_ns: u64) -> mcap::McapResult<u64> {
        let mut n = 0;
        while let Some(record) = self.queue.pop() {
            self.buf.clear();
            record.encode(&mut self.buf);
            let time = start_unix_ns + record.log_time_ns();
            writer.write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: self.channel_id,
                    sequence: self.sequence,
                    log_time: time,
                    publish_time: time,
                },
                &self.buf,
            )?;
            self.sequence = self.sequence.wrapping_add(1);
            n += 1;
        }
        self.written += n;
        Ok(n)
    }

    fn discard(&mut self) {
        while self.queue.pop().is_some() {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    fn counts(&self) -> SinkCounts {
        SinkCounts {
            written: self.written,
            dropped: self.dropped.load(Ordering::Relaxed),
        }
    }
}

/// Sets up a process's record streams before its writer thread starts.
pub struct RecorderBuilder {
    parts_dir: PathBuf,
    process: String,
    drains: Vec<Box<dyn Drain>>,
    flushes: Arc<AtomicU64>,
}

impl RecorderBuilder {
    /// Records of `process` go to `<report_dir>/parts/<process>-<n>.mcap`.
    pub fn new(report_dir: &Path, process: &str) -> RecorderBuilder {
        RecorderBuilder {
            parts_dir: report_dir.join("parts"),
            process: process.to_string(),
            drains: Vec::new(),
            flushes: Arc::new(AtomicU64::new(0)),
        }
    }

    /// Adds a record stream (one MCAP channel) with a queue of `capacity` records.
    pub fn sink<R: Record>(&mut self, capacity: usize) -> RecordSink<R> {
        let queue = Arc::new(ArrayQueue::new(capacity.max(1)));
        let dropped = Arc::new(AtomicU64::new(0));
        self.drains.push(Box::new(QueueDrain::<R> {
            queue: queue.clone(),
            dropped: dropped.clone(),
            channel_id: 0,
            sequence: 0,
            written: 0,
            buf: Vec::with_capacity(256),
        }));
        RecordSink {
            queue,
            dropped,
            flushes: self.flushes.clone(),
        }
    }

    /// Creates the parts directory and starts the writer thread. It writes nothing until
    /// `Recorder::start` gives it the run's time base and metadata.
    pub fn spawn(self) -> std::io::Result<Recorder> {
        std::fs::create_dir_all(&self.parts_dir)?;
        let RecorderBuilder {
            parts_dir,
            process,
            drains,
            flushes,
        } = self;
        let shared = Arc::new(Shared {
            stop: AtomicBool::new(false),
            start_unix_ns: AtomicU64::new(u64::MAX),
            meta_json: std::sync::Mutex::new(String::new()),
            flushes,
        });
        let thread_shared = shared.clone();
        let label = format!("{}-records", process);
        let handle = std::thread::Builder::new()
            .name(label)
            .spawn(move || write_loop(&parts_dir, &process, drains, &thread_shared))?;
        Ok(Recorder {
            shared,
            handle: Some(handle),
        })
    }
}

struct Shared {
    stop: AtomicBool,
    start_unix_ns: AtomicU64,
    meta_json: std::sync::Mutex<String>,
    /// Completed flushes (`RecordSink::wait_flushed`).
    flushes: Arc<AtomicU64>,
}

/// The running writer of one process.
pub struct Recorder {
    shared: Arc<Shared>,
    handle: Option<JoinHandle<WriterResult>>,
}

/// What the writer thread reports when it ends.
#[derive(Debug, Clone, Default)]
pub struct WriterResult {
    /// Counts per topic, in registration order.
    pub counts: Vec<(String, SinkCounts)>,
    pub files: Vec<PathBuf>,
    /// The first write error, if any (records after it were dropped and counted).
    pub error: Option<String>,
}

impl WriterResult {
    /// The counts of `topic` (zeros if it was not recorded).
    pub fn counts_of(&self, topic: &str) -> SinkCounts {
        self.counts
            .iter()
            .find(|(t, _)| t == topic)
            .map_or(SinkCounts::default(), |(_, c)| *c)
    }
}

impl Recorder {
    /// Gives the writer the run's time base (Unix ns at loop time 0) and the `/meta`
    /// message (JSON); records are written from now on. Call before the loop starts.
    pub fn start(&self, start_unix_ns: u64, meta_json: String) {
        if let Ok(mut m) = self.shared.meta_json.lock() {
            *m = meta_json;
        }
        self.shared
            .start_unix_ns
            .store(start_unix_ns, Ordering::Release);
    }

    /// Drains every queue, finishes the part file (summary and index) and returns counts.
    pub fn finish(mut self) -> WriterResult {
        self.shared.stop.store(true, Ordering::Release);
        // A run stopped before it started still writes its (empty) part.
        self.shared
            .start_unix_ns
            .compare_exchange(u64::MAX, 0, Ordering::AcqRel, Ordering::Acquire)
            .ok();
        self.handle
            .take()
            .and_then(|h| h.join().ok())
            .unwrap_or_default()
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        self.shared
            .start_unix_ns
            .compare_exchange(u64::MAX, 0, Ordering::AcqRel, Ordering::Acquire)
            .ok();
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

fn open_part(
    parts_dir: &Path,
    process: &str,
    index: usize,
    drains: &mut [Box<dyn Drain>],
    meta_json: &str,
    start_unix_ns: u64,
) -> Result<(McapWriter, PathBuf), String> {
    let path = parts_dir.join(format!("{process}-{index:04}.mcap"));
    let file = std::fs::File::create(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut writer = mcap::WriteOptions::new()
        .profile(PROFILE)
        .compression(Some(mcap::Compression::Zstd))
        // Compress in this (non-real-time) thread: no worker threads beside the loops.
        .compression_threads(0)
        // Assemble each chunk in memory and write it whole when closed: a reader following
        // the file (the live view) or a killed writer's file never holds a chunk header
        // whose lengths are still to be patched.
        .disable_seeking(true)
        .chunk_size(None)
        .create(BufWriter::with_capacity(1 << 16, file))
        .map_err(|e| format!("{}: {e}", path.display()))?;
    let setup = (|| -> mcap::McapResult<()> {
        let schema = writer.add_schema("fastemu/RunMeta", "jsonschema", META_SCHEMA.as_bytes())?;
        let channel = writer.add_channel(schema, META_TOPIC, "json", &Default::default())?;
        writer.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: channel,
                sequence: 0,
                log_time: start_unix_ns,
                publish_time: start_unix_ns,
            },
            meta_json.as_bytes(),
        )?;
        for d in drains.iter_mut() {
            d.register(&mut writer)?;
        }
        writer.flush()
    })();
    setup.map_err(|e| format!("{}: {e}", path.display()))?;
    Ok((writer, path))
}

/// JSON schema of the `/meta` message.
const META_SCHEMA: &str = r#"{"type":"object","properties":{"process":{"type":"string"},"run_id":{"type":"string"},"abi_version":{"type":"integer"},"rate_hz":{"type":"number"},"start_unix_ns":{"type":"integer"},"config_origin":{"type":"string"},"config_base_dir":{"type":["string","null"]},"config_text":{"type":"string"}}}"#;

fn write_loop(
    parts_dir: &Path,
    process: &str,
    mut drains: Vec<Box<dyn Drain>>,
    shared: &Shared,
) -> WriterResult {
    let mut result = WriterResult::default();
    // Wait for the run's time base.
    let start_unix_ns = loop {
        let t = shared.start_unix_ns.load(Ordering::Acquire);
        if t != u64::MAX {
            break t;
        }
        std::thread::sleep(POLL);
    };
    let meta_json = shared
        .meta_json
        .lock()
        .map(|m| m.clone())
        .unwrap_or_default();
    let mut index = 0;
    let open =
        |index: usize, drains: &mut [Box<dyn Drain>], result: &mut WriterResult| match open_part(
            parts_dir,
            process,
            index,
            drains,
            &meta_json,
            start_unix_ns,
        ) {
            Ok((w, p)) => {
                result.files.push(p);
                Some(w)
            }
            Err(e) => {
                result.error.get_or_insert(e);
                None
            }
        };
    let mut current = open(index, &mut drains, &mut result);
    let mut last_flush = Instant::now();
    let mut part_started = Instant::now();
    loop {
        let stopping = shared.stop.load(Ordering::Acquire);
        if let Some(writer) = current.as_mut() {
            let mut failed = None;
            for d in drains.iter_mut() {
                if let Err(e) = d.drain(writer, start_unix_ns) {
                    failed = Some(e.to_string());
                    break;
                }
            }
            if failed.is_none() && last_flush.elapsed() >= FLUSH_INTERVAL {
                last_flush = Instant::now();
                match writer.flush() {
                    Ok(()) => {
                        shared.flushes.fetch_add(1, Ordering::Release);
                    }
                    Err(e) => failed = Some(e.to_string()),
                }
            }
            if let Some(e) = failed {
                result.error.get_or_insert(e);
                current = None;
            } else if part_started.elapsed() >= ROLL_INTERVAL && !stopping {
                if let Err(e) = writer.finish() {
                    result.error.get_or_insert(e.to_string());
                }
                index += 1;
                part_started = Instant::now();
                current = open(index, &mut drains, &mut result);
            }
        } else {
            for d in drains.iter_mut() {
                d.discard();
            }
        }
        if stopping {
            break;
        }
        std::thread::sleep(POLL);
    }
    if let Some(mut writer) = current {
        let mut last = Ok(0);
        for d in drains.iter_mut() {
            last = last.and_then(|_| d.drain(&mut writer, start_unix_ns));
        }
        if let Err(e) = last.and_then(|_| writer.finish().map(|_| 0)) {
            result.error.get_or_insert(e.to_string());
        }
    }
    result.counts = drains
        .iter()
        .map(|d| (d.topic().to_string(), d.counts()))
        .collect();
    result
}
