//! The iceoryx2 files of runs: find them by run prefix, clear a finished run's leftovers,
//! and clear the state of runs whose orchestrator died. Whoever is last out of a run (the
//! orchestrator, or the rig when the orchestrator died) calls `clear_run`.
//!
//! Must not: touch files of a run whose orchestrator is alive (except `clear_run` on the
//! caller's own run).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::transport::{cleanup_dead_nodes, file_prefix};

fn run_id_pid(name: &str) -> Option<(String, u32)> {
    let rest = name.strip_prefix("fe")?;
    let (pid, tail) = rest.split_once('x')?;
    let (counter, _) = tail.split_once('_')?;
    if pid.is_empty()
        || counter.is_empty()
        || !pid.bytes().all(|b| b.is_ascii_digit())
        || !counter.bytes().all(|b| b.is_ascii_digit())
    {
        return None;
    }
    Some((format!("fe{pid}x{counter}"), pid.parse().ok()?))
}

fn process_alive(pid: u32) -> bool {
    // SAFETY: signal 0 only checks for existence/permission.
    let rc = unsafe { libc::kill(pid as libc::pid_t, 0) };
    rc == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// Where iceoryx2 keeps files: shared memory and its root directory.
pub fn iceoryx2_dirs() -> [PathBuf; 2] {
    [PathBuf::from("/dev/shm"), PathBuf::from("/tmp/iceoryx2")]
}

fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
    if let Ok(entries) = std::fs::read_dir(dir) {
        for e in entries.flatten() {
            let p = e.path();
            if e.file_type().is_ok_and(|t| t.is_dir()) {
                walk(&p, out);
            }
            out.push(p);
        }
    }
}

/// Files and directories (under the iceoryx2 dirs) whose name starts with `prefix`.
pub fn files_with_prefix(prefix: &str) -> Vec<PathBuf> {
    let mut all = Vec::new();
    for d in iceoryx2_dirs() {
        walk(&d, &mut all);
    }
    all.into_iter()
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(prefix))
        })
        .collect()
}

fn remove_paths(paths: &[PathBuf]) {
    // Deepest first, so directories are empty when removed.
    let mut sorted = paths.to_vec();
    sorted.sort_by_key(|p| std::cmp::Reverse(p.components().count()));
    for p in sorted {
        if p.is_dir() {
            let _ = std::fs::remove_dir_all(&p);
        } else {
            let _ = std::fs::remove_file(&p);
        }
    }
}

/// Removes the iceoryx2 state of runs whose orchestrator is dead; returns their ids.
pub fn clear_stale_runs() -> Vec<String> {
    let mut all = Vec::new();
    for d in iceoryx2_dirs() {
        walk(&d, &mut all);
    }
    let mut stale: BTreeMap<String, u32> = BTreeMap::new();
    for p in &all {
        if let Some((id, pid)) = p.file_name().and_then(|n| n.to_str()).and_then(run_id_pid) {
            if !process_alive(pid) {
                stale.insert(id, pid);
            }
        }
    }
    for id in stale.keys() {
        let _ = cleanup_dead_nodes(id);
        remove_paths(&files_with_prefix(&file_prefix(id)));
    }
    stale.into_keys().collect()
}

/// Clears the run's own state after all its processes were reaped; returns what was
/// still left after iceoryx2's dead-node cleanup (removed as well), apart from iceoryx2's
/// node counter (`*.global_mgmt`), which it keeps by design and which is removed too.
pub fn clear_run(run_id: &str) -> Vec<PathBuf> {
    let _ = cleanup_dead_nodes(run_id);
    let mut left = files_with_prefix(&file_prefix(run_id));
    remove_paths(&left);
    left.retain(|p| !p.to_string_lossy().ends_with(".global_mgmt"));
    left
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clear_run_removes_every_file_and_names_only_real_leftovers() {
        // A run id no live orchestrator has (pid 0 never runs a hil).
        let run_id = format!("fe0x{}", std::process::id());
        let prefix = file_prefix(&run_id);
        let leaked = PathBuf::from("/dev/shm").join(format!("{prefix}some_service.data"));
        let counter = PathBuf::from("/dev/shm").join(format!("{prefix}node.0_10_0.global_mgmt"));
        std::fs::write(&leaked, b"x").unwrap();
        std::fs::write(&counter, b"x").unwrap();
        let named = clear_run(&run_id);
        assert_eq!(named, vec![leaked.clone()]);
        assert!(!leaked.exists() && !counter.exists());
        assert!(files_with_prefix(&prefix).is_empty());
    }
}
