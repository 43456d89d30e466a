//! The registry of running `hil` runs, so `fastemu ctl` finds a run from another terminal:
//! one JSON file per run in a directory only the user can read (`/tmp/fastemu-runs-<uid>`,
//! mode 0700, like the user's own shared memory), written when a run starts and removed
//! when it ends; files of runs whose orchestrator died are skipped and cleared.
//!
//! Must not: be touched by the loop processes.

use std::path::PathBuf;

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

/// The registry directory of this user.
pub fn registry_dir() -> PathBuf {
    // SAFETY: getuid cannot fail.
    let uid = unsafe { libc::getuid() };
    std::env::temp_dir().join(format!("fastemu-runs-{uid}"))
}

fn alive(pid: u32) -> bool {
    // SAFETY: signal 0 only checks for existence/permission.
    let rc = unsafe { libc::kill(pid as libc::pid_t, 0) };
    rc == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// Registers a run; the returned guard removes the entry when dropped.
pub fn register(entry: &RunEntry) -> std::io::Result<Registration> {
    use std::os::unix::fs::DirBuilderExt;
    let dir = registry_dir();
    let _ = std::fs::DirBuilder::new()
        .mode(0o700)
        .recursive(true)
        .create(&dir);
    let path = dir.join(format!("{}.json", entry.run_id));
    std::fs::write(
        &path,
        serde_json::to_string_pretty(entry).unwrap_or_default(),
    )?;
    Ok(Registration { path })
}

/// Removes a run's registry entry when dropped.
pub struct Registration {
    path: PathBuf,
}

impl Drop for Registration {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// The runs whose orchestrator is alive, oldest first (dead entries are removed).
pub fn running() -> Vec<RunEntry> {
    let mut runs = Vec::new();
    if let Ok(entries) = std::fs::read_dir(registry_dir()) {
        for e in entries.flatten() {
            let Ok(text) = std::fs::read_to_string(e.path()) else {
                continue;
            };
            match serde_json::from_str::<RunEntry>(&text) {
                Ok(run) if alive(run.pid) => runs.push(run),
                _ => {
                    let _ = std::fs::remove_file(e.path());
                }
            }
        }
    }
    runs.sort_by_key(|r| r.started_unix_s);
    runs
}
