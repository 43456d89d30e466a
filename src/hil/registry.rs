//! The registry of running `hil` runs, so `fastemu ctl` finds a run from another terminal:
//! one JSON file per run in a directory only the user can read (`/tmp/fastemu-runs-<uid>`,
//! mode 0700, like the user's own shared memory), written when a run starts and removed
//! when it ends.
//!
//! An entry is written whole or not at all: into a temporary file of the same directory
//! (`.tmp.<writer pid>.<n>.<run id>.json`, never read as an entry), then renamed over the
//! entry, so a reader sees the old entry or the new one, never a part. A reader never
//! removes an entry it cannot read or parse (it may be another run's, or a writer's
//! moment): it skips it and says why ([`Scan::skipped`]). Only an entry that parsed and
//! names a process that provably no longer exists (`kill(pid, 0)` says ESRCH) is
//! cleared, and a writer's temporary file only when its writer provably no longer exists.
//!
//! Must not: be touched by the loop processes.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use serde::{Deserialize, Serialize};

/// One running run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunEntry {
    pub run_id: String,
    /// The orchestrator's pid.
    pub pid: u32,
    pub report_dir: PathBuf,
    pub config_origin: String,
    pub rate_hz: f64,
    pub started_unix_s: u64,
    /// The live server's address, when `--live`.
    pub live_addr: Option<String>,
}

/// An entry a reader could not use, and why (it is left in place).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skipped {
    pub path: PathBuf,
    pub reason: String,
}

impl std::fmt::Display for Skipped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "skipped {}: {}", self.path.display(), self.reason)
    }
}

/// What a reading of the registry found.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Scan {
    /// The runs whose orchestrator is alive, oldest first.
    pub runs: Vec<RunEntry>,
    /// The entries that could not be used (unreadable, unparsable, implausible), left in
    /// place.
    pub skipped: Vec<Skipped>,
    /// Entries (and writers' temporary files) of processes that no longer exist, removed.
    pub cleared: Vec<PathBuf>,
}

/// The registry directory of this user.
pub fn registry_dir() -> PathBuf {
    // SAFETY: getuid cannot fail.
    let uid = unsafe { libc::getuid() };
    std::env::temp_dir().join(format!("fastemu-runs-{uid}"))
}

/// The prefix of a writer's temporary files; run ids never start with a dot.
const TMP_PREFIX: &str = ".tmp.";

/// Whether `pid` names a process that provably no longer exists (ESRCH) or has exited
/// (a zombie its parent has not reaped). Anything else (alive, not ours, an implausible
/// pid, an unexpected error) is not proof.
fn provably_dead(pid: u32) -> bool {
    let Ok(pid) = libc::pid_t::try_from(pid) else {
        return false;
    };
    if pid <= 0 {
        return false;
    }
    // SAFETY: signal 0 only checks for existence/permission.
    let rc = unsafe { libc::kill(pid, 0) };
    if rc != 0 {
        return std::io::Error::last_os_error().raw_os_error() == Some(libc::ESRCH);
    }
    // A zombie (exited, not yet reaped by its parent) answers signal 0 too.
    std::fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|stat| {
        stat.rsplit_once(')')
            .is_some_and(|(_, rest)| rest.trim_start().starts_with('Z'))
    })
}

/// Whether run `run` has ended: its orchestrator provably no longer exists, or its entry
/// is gone from the registry (removed at the run's end).
pub fn has_ended(run: &RunEntry) -> bool {
    provably_dead(run.pid) || !registry_dir().join(format!("{}.json", run.run_id)).exists()
}

/// Writes `entry` as `<dir>/<run id>.json` atomically (temporary file in `dir`, rename);
/// returns the entry's path. No fsync: the rename alone makes readers see a whole entry,
/// and after a crash of the machine every registered run is over anyway.
fn write_entry(dir: &Path, entry: &RunEntry) -> std::io::Result<PathBuf> {
    use std::io::Write;
    static SEQ: AtomicU64 = AtomicU64::new(0);
    let name = format!("{}.json", entry.run_id);
    let path = dir.join(&name);
    let tmp = dir.join(format!(
        "{TMP_PREFIX}{}.{}.{name}",
        std::process::id(),
        SEQ.fetch_add(1, Ordering::Relaxed)
    ));
    let text = serde_json::to_string_pretty(entry).map_err(std::io::Error::other)?;
    let written = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(text.as_bytes())?;
        std::fs::rename(&tmp, &path)
    })();
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written.map(|()| path)
}

/// Registers a run; the returned guard removes the entry when dropped.
pub fn register(entry: &RunEntry) -> std::io::Result<Registration> {
    register_in(&registry_dir(), entry)
}

/// [`register`] in the registry directory `dir` (created, mode 0700, when missing).
pub fn register_in(dir: &Path, entry: &RunEntry) -> std::io::Result<Registration> {
    use std::os::unix::fs::DirBuilderExt;
    let _ = std::fs::DirBuilder::new()
        .mode(0o700)
        .recursive(true)
        .create(dir);
    let path = write_entry(dir, entry)?;
    Ok(Registration {
        dir: dir.to_path_buf(),
        path,
    })
}

/// Removes a run's registry entry when dropped.
pub struct Registration {
    dir: PathBuf,
    path: PathBuf,
}

impl Registration {
    /// Rewrites the entry (atomically, like [`register`]); its run id must not change.
    pub fn update(&self, entry: &RunEntry) -> std::io::Result<()> {
        let path = write_entry(&self.dir, entry)?;
        debug_assert_eq!(path, self.path, "a registration's run id is fixed");
        Ok(())
    }
}

impl Drop for Registration {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// The registry of this user: see [`scan_dir`].
pub fn running() -> Scan {
    scan_dir(&registry_dir())
}

/// Reads the registry directory `dir`: the runs whose orchestrator is alive (oldest first),
/// the entries skipped and why, and the entries of dead orchestrators, which it removes.
/// A missing directory is an empty registry.
pub fn scan_dir(dir: &Path) -> Scan {
    let mut scan = Scan::default();
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return scan,
        Err(e) => {
            scan.skipped.push(Skipped {
                path: dir.to_path_buf(),
                reason: format!("registry directory not readable: {e}"),
            });
            return scan;
        }
    };
    for e in entries {
        let e = match e {
            Ok(e) => e,
            Err(err) => {
                scan.skipped.push(Skipped {
                    path: dir.to_path_buf(),
                    reason: format!("listing the registry failed: {err}"),
                });
                continue;
            }
        };
        let path = e.path();
        let name = e.file_name();
        let name = name.to_string_lossy();
        if let Some(rest) = name.strip_prefix(TMP_PREFIX) {
            // A writer's temporary file: never an entry; cleared only once its writer is gone.
            let writer = rest.split('.').next().and_then(|p| p.parse::<u32>().ok());
            if writer.is_some_and(provably_dead) && std::fs::remove_file(&path).is_ok() {
                scan.cleared.push(path);
            }
            continue;
        }
        if name.starts_with('.') || !name.ends_with(".json") {
            continue;
        }
        match read_entry(&path) {
            Err(reason) => scan.skipped.push(Skipped { path, reason }),
            Ok((run, _)) if run.pid == 0 || libc::pid_t::try_from(run.pid).is_err() => {
                scan.skipped.push(Skipped {
                    path,
                    reason: format!("names pid {}, which is not a process id", run.pid),
                });
            }
            Ok((run, id)) if provably_dead(run.pid) => {
                // Remove only the very file that was read: a new run of the same id may have
                // renamed its own entry over it since.
                if same_file(&path, id) && std::fs::remove_file(&path).is_ok() {
                    scan.cleared.push(path);
                }
            }
            Ok((run, _)) => scan.runs.push(run),
        }
    }
    scan.runs
        .sort_by(|a, b| (a.started_unix_s, &a.run_id).cmp(&(b.started_unix_s, &b.run_id)));
    scan
}

/// An entry's contents and the identity (device, inode) of the file read, or why not.
fn read_entry(path: &Path) -> Result<(RunEntry, (u64, u64)), String> {
    use std::io::Read;
    use std::os::unix::fs::MetadataExt;
    let mut f = std::fs::File::open(path).map_err(|e| format!("cannot open: {e}"))?;
    let meta = f.metadata().map_err(|e| format!("cannot stat: {e}"))?;
    let mut text = String::new();
    f.read_to_string(&mut text)
        .map_err(|e| format!("cannot read: {e}"))?;
    let run = serde_json::from_str::<RunEntry>(&text)
        .map_err(|e| format!("not a run entry ({} bytes): {e}", text.len()))?;
    Ok((run, (meta.dev(), meta.ino())))
}

fn same_file(path: &Path, id: (u64, u64)) -> bool {
    use std::os::unix::fs::MetadataExt;
    std::fs::symlink_metadata(path).is_ok_and(|m| (m.dev(), m.ino()) == id)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh registry directory of this test alone.
    fn test_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "fastemu-registry-test-{}-{name}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("test dir");
        dir
    }

    fn entry(run_id: &str, pid: u32, started_unix_s: u64) -> RunEntry {
        RunEntry {
            run_id: run_id.into(),
            pid,
            report_dir: PathBuf::from("/tmp/report"),
            config_origin: "test".into(),
            rate_hz: 1000.0,
            started_unix_s,
            live_addr: Some("127.0.0.1:9000".into()),
        }
    }

    /// A pid that provably names no process: a child that was started and reaped.
    fn dead_pid() -> u32 {
        let mut child = std::process::Command::new("true").spawn().expect("spawn");
        let pid = child.id();
        child.wait().expect("wait");
        assert!(provably_dead(pid), "a reaped child's pid is free");
        pid
    }

    #[test]
    fn a_truncated_entry_is_skipped_with_a_reason_and_kept() {
        let dir = test_dir("truncated");
        let live = entry("live", std::process::id(), 10);
        let _reg = register_in(&dir, &live).expect("register");
        let full = serde_json::to_string_pretty(&entry("half", std::process::id(), 5)).unwrap();
        let bad = dir.join("half.json");
        std::fs::write(&bad, &full[..full.len() / 2]).unwrap();
        let empty = dir.join("empty.json");
        std::fs::write(&empty, "").unwrap();

        let scan = scan_dir(&dir);
        assert_eq!(scan.runs, vec![live]);
        assert!(scan.cleared.is_empty());
        let mut skipped: Vec<_> = scan.skipped.iter().map(|s| s.path.clone()).collect();
        skipped.sort();
        assert_eq!(skipped, vec![empty.clone(), bad.clone()]);
        for s in &scan.skipped {
            assert!(s.reason.starts_with("not a run entry"), "{s}");
            assert!(s.to_string().contains(&*s.path.to_string_lossy()));
        }
        assert_eq!(
            std::fs::read_to_string(&bad).unwrap(),
            full[..full.len() / 2],
            "an unparsable entry is left as it was"
        );
        assert!(empty.exists());
        // A second reader sees the same.
        assert_eq!(scan_dir(&dir).skipped.len(), 2);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn entries_of_dead_pids_are_cleared_and_live_ones_kept() {
        let dir = test_dir("dead");
        let pid = dead_pid();
        let live = entry("live", std::process::id(), 1);
        let _reg = register_in(&dir, &live).expect("register");
        let dead_path = register_in(&dir, &entry("dead", pid, 2)).expect("register");
        let dead_path = {
            let p = dead_path.path.clone();
            std::mem::forget(dead_path); // as if the orchestrator had died
            p
        };
        // A crashed writer's temporary file, and one of a live writer.
        let dead_tmp = dir.join(format!("{TMP_PREFIX}{pid}.0.x.json"));
        std::fs::write(&dead_tmp, "{").unwrap();
        let live_tmp = dir.join(format!("{TMP_PREFIX}{}.99.y.json", std::process::id()));
        std::fs::write(&live_tmp, "{").unwrap();
        // Implausible pids are not proof of death.
        let zero = dir.join("zero.json");
        std::fs::write(&zero, serde_json::to_string(&entry("zero", 0, 3)).unwrap()).unwrap();

        let scan = scan_dir(&dir);
        assert_eq!(scan.runs, vec![live]);
        let mut cleared = scan.cleared.clone();
        cleared.sort();
        let mut want = vec![dead_path.clone(), dead_tmp.clone()];
        want.sort();
        assert_eq!(cleared, want);
        assert!(!dead_path.exists() && !dead_tmp.exists());
        assert!(live_tmp.exists(), "a live writer's temporary file is left");
        assert_eq!(scan.skipped.len(), 1);
        assert_eq!(scan.skipped[0].path, zero);
        assert!(zero.exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_exited_orchestrator_not_yet_reaped_is_dead() {
        let mut live = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        assert!(!provably_dead(live.id()));
        let mut exited = std::process::Command::new("true").spawn().unwrap();
        // Not reaped: a zombie until `wait`; signal 0 still finds it.
        let t = std::time::Instant::now();
        while !provably_dead(exited.id()) {
            assert!(t.elapsed().as_secs() < 20, "`true` never exited");
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        // SAFETY: signal 0 only checks for existence.
        assert_eq!(unsafe { libc::kill(exited.id() as libc::pid_t, 0) }, 0);
        exited.wait().unwrap();
        assert!(provably_dead(exited.id()));
        live.kill().unwrap();
        live.wait().unwrap();
    }

    #[test]
    fn registration_drop_removes_and_a_missing_dir_is_empty() {
        let dir = test_dir("drop");
        let reg = register_in(&dir, &entry("r", std::process::id(), 1)).expect("register");
        assert_eq!(scan_dir(&dir).runs.len(), 1);
        drop(reg);
        assert_eq!(scan_dir(&dir), Scan::default());
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(scan_dir(&dir), Scan::default());
    }

    #[test]
    fn a_reader_always_finds_an_entry_being_rewritten() {
        const WRITES: u64 = 500;
        let dir = test_dir("stress");
        let first = RunEntry {
            config_origin: String::new(),
            ..entry("busy", std::process::id(), 0)
        };
        let reg = register_in(&dir, &first).expect("register");
        let reads = std::thread::scope(|s| {
            let writer = s.spawn(|| {
                for i in 1..=WRITES {
                    let mut e = first.clone();
                    e.started_unix_s = i;
                    // Vary the length, so a torn read could not look whole.
                    e.config_origin = "x".repeat((i % 97) as usize);
                    reg.update(&e).expect("rewrite");
                }
            });
            let mut reads = 0u64;
            let mut last = 0;
            // Bounded: the writer ends after WRITES rewrites; one more read after it ended.
            loop {
                let finished = writer.is_finished();
                let scan = scan_dir(&dir);
                assert!(scan.skipped.is_empty(), "{:?}", scan.skipped);
                assert!(scan.cleared.is_empty(), "{:?}", scan.cleared);
                assert_eq!(
                    scan.runs.len(),
                    1,
                    "read {reads}: the entry is always there"
                );
                let run = &scan.runs[0];
                assert_eq!(run.run_id, "busy");
                assert_eq!(run.config_origin.len() as u64, run.started_unix_s % 97);
                assert!(run.started_unix_s >= last, "never an older version");
                last = run.started_unix_s;
                reads += 1;
                if finished {
                    break;
                }
            }
            writer.join().expect("writer");
            assert_eq!(last, WRITES, "the last read sees the last write");
            reads
        });
        assert!(reads >= 1);
        let names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert_eq!(names, vec!["busy.json"], "no temporary file is left behind");
        drop(reg);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
