//! Streaming readers of a run's records: `records.mcap`, or the per-process parts a
//! crashed run left in `parts/`. Memory is bounded by one chunk, whatever the run's length;
//! a file cut short by a killed writer is read up to its last closed chunk and reported.

use std::fmt;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Record, META_TOPIC};

/// A records error: the file and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordsError {
    pub path: String,
    pub message: String,
}

impl fmt::Display for RecordsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.path, self.message)
    }
}

impl std::error::Error for RecordsError {}

fn err(path: &Path, message: impl Into<String>) -> RecordsError {
    RecordsError {
        path: path.display().to_string(),
        message: message.into(),
    }
}

/// The `/meta` message each process writes first: what replay and the report need.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunMeta {
    pub process: String,
    pub run_id: String,
    pub abi_version: u32,
    pub rate_hz: f64,
    pub start_unix_ns: u64,
    pub config_origin: String,
    pub config_base_dir: Option<PathBuf>,
    pub config_text: String,
}

/// How a pass over the records went.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ReadStats {
    pub messages: u64,
    /// Files that ended early (a killed writer) or are damaged past some point, with the
    /// reader's error; everything before that point was read.
    pub truncated: Vec<(PathBuf, String)>,
}

/// The record files of one run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordSet {
    pub files: Vec<PathBuf>,
}

/// Order of the parts: rig, emulator, controller, then anything else, each by index.
fn part_rank(path: &Path) -> (usize, String) {
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default()
        .to_string();
    let rank = ["rig-", "emulator-", "controller-"]
        .iter()
        .position(|p| name.starts_with(p))
        .unwrap_or(3);
    (rank, name)
}

/// The parts in `dir` (`*.mcap`), in a stable order.
pub fn list_parts(dir: &Path) -> Vec<PathBuf> {
    let mut parts: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .flatten()
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
                .collect()
        })
        .unwrap_or_default();
    parts.sort_by_key(|p| part_rank(p));
    parts
}

impl RecordSet {
    /// `path` is a `.mcap` file, a report directory (its `records.mcap`, else the parts a
    /// crashed run left in `parts/`), or a `parts/` directory. A missing `records.mcap`
    /// whose parts exist reads the parts.
    pub fn open(path: &Path) -> Result<RecordSet, RecordsError> {
        if path.is_file() {
            return Ok(RecordSet {
                files: vec![path.to_path_buf()],
            });
        }
        let dir = if path.is_dir() {
            path.to_path_buf()
        } else if path.file_name().is_some_and(|n| n == "records.mcap") {
            path.parent().map(Path::to_path_buf).unwrap_or_default()
        } else {
            return Err(err(
                path,
                "no such file or directory (expected records.mcap or a report directory)",
            ));
        };
        let merged = dir.join("records.mcap");
        if merged.is_file() {
            return Ok(RecordSet {
                files: vec![merged],
            });
        }
        for parts_dir in [dir.join("parts"), dir.clone()] {
            let parts = list_parts(&parts_dir);
            if !parts.is_empty() {
                return Ok(RecordSet { files: parts });
            }
        }
        Err(err(
            path,
            "no records: expected records.mcap, or parts/*.mcap left by a run that did not finish",
        ))
    }

    /// Whether these are the parts of a run that did not finish (no `records.mcap`).
    pub fn is_parts(&self) -> bool {
        self.files.len() != 1
            || self.files[0]
                .file_name()
                .is_some_and(|n| n != "records.mcap")
    }

    /// Calls `f(topic, log_time_ns, data)` for every message, file by file, in file order.
    pub fn visit(&self, mut f: impl FnMut(&str, u64, &[u8])) -> Result<ReadStats, RecordsError> {
        let mut stats = ReadStats::default();
        for path in &self.files {
            let file = std::fs::File::open(path).map_err(|e| err(path, e.to_string()))?;
            let reader = mcap::io::MessageReader::new(BufReader::with_capacity(1 << 16, file));
            for message in reader {
                match message {
                    Ok(m) => {
                        stats.messages += 1;
                        f(&m.channel.topic, m.log_time, &m.data);
                    }
                    Err(e) => {
                        stats.truncated.push((path.clone(), e.to_string()));
                        break;
                    }
                }
            }
        }
        Ok(stats)
    }

    /// Calls `f(log_time_ns, record)` for every record of type `R`.
    pub fn for_each<R: Record>(
        &self,
        mut f: impl FnMut(u64, R),
    ) -> Result<ReadStats, RecordsError> {
        let mut bad = 0u64;
        let stats = self.visit(|topic, t, data| {
            if topic == R::TOPIC {
                match R::decode(data) {
                    Some(r) => f(t, r),
                    None => bad += 1,
                }
            }
        })?;
        self.refuse_short::<R>(bad)?;
        Ok(stats)
    }

    /// `for_each` for two record types in one pass over the files (each type's records in
    /// their own order; the two streams are not merged by time).
    pub fn for_each_of_two<A: Record, B: Record>(
        &self,
        mut fa: impl FnMut(u64, A),
        mut fb: impl FnMut(u64, B),
    ) -> Result<ReadStats, RecordsError> {
        let (mut bad_a, mut bad_b) = (0u64, 0u64);
        let stats = self.visit(|topic, t, data| {
            if topic == A::TOPIC {
                match A::decode(data) {
                    Some(r) => fa(t, r),
                    None => bad_a += 1,
                }
            } else if topic == B::TOPIC {
                match B::decode(data) {
                    Some(r) => fb(t, r),
                    None => bad_b += 1,
                }
            }
        })?;
        self.refuse_short::<A>(bad_a)?;
        self.refuse_short::<B>(bad_b)?;
        Ok(stats)
    }

    /// The error for `bad` messages of type `R` that did not decode (none: `Ok`).
    fn refuse_short<R: Record>(&self, bad: u64) -> Result<(), RecordsError> {
        if bad == 0 {
            return Ok(());
        }
        Err(err(
            &self.files[0],
            format!(
                "{bad} messages on {} shorter than its schema {} ({} bytes): written by another version?",
                R::TOPIC,
                R::SCHEMA_NAME,
                R::SIZE
            ),
        ))
    }

    /// Every record of type `R` (offline convenience for short runs and tests).
    pub fn read_all<R: Record>(&self) -> Result<Vec<R>, RecordsError> {
        let mut out = Vec::new();
        self.for_each::<R>(|_, r| out.push(r))?;
        Ok(out)
    }

    /// The `/meta` messages (one per process and part).
    pub fn metas(&self) -> Result<Vec<RunMeta>, RecordsError> {
        let mut out = Vec::new();
        let mut bad = None;
        self.visit(|topic, _, data| {
            if topic == META_TOPIC {
                match serde_json::from_slice::<RunMeta>(data) {
                    Ok(m) => out.push(m),
                    Err(e) => bad = Some(e.to_string()),
                }
            }
        })?;
        if let Some(e) = bad {
            return Err(err(
                &self.files[0],
                format!("bad {META_TOPIC} message: {e}"),
            ));
        }
        Ok(out)
    }

    /// The meta of `process` (`rig`, `emulator`, `controller`).
    pub fn meta_of(&self, process: &str) -> Result<RunMeta, RecordsError> {
        self.metas()?
            .into_iter()
            .find(|m| m.process == process)
            .ok_or_else(|| {
                err(
                    &self.files[0],
                    format!("no {META_TOPIC} message of the {process}"),
                )
            })
    }
}
