//! The `hil` orchestrator: clears stale state of crashed runs, starts the three loop
//! processes under a unique run id, waits until they are ready, starts them on a common
//! clock, watches heartbeats and exits, stops and reaps them on every exit path
//! (`ChildGuard`), and removes the run's shared memory.
//!
//! Must not: leave a child process or a file of its run behind, on any path.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::time::{Duration, Instant};

use super::fault::fault_code_name;
use super::process::ProcessError;
use crate::ipc::messages::{process_id, run_command, Heartbeat, RunControl, HEARTBEAT_READY};
use crate::ipc::{cleanup_dead_nodes, file_prefix, IpcNode};
use crate::rt::clock::monotonic_now_ns;

/// Names of the three processes, indexed by `process_id`.
pub const PROCESS_NAMES: [&str; 3] = ["bench_rig", "emulator", "controller"];

static INTERRUPTED: AtomicBool = AtomicBool::new(false);
static INTERRUPT_SIGNAL: AtomicI32 = AtomicI32::new(0);

extern "C" fn on_terminate_signal(signal: libc::c_int) {
    INTERRUPTED.store(true, Ordering::SeqCst);
    INTERRUPT_SIGNAL.store(signal, Ordering::SeqCst);
}

/// Routes SIGINT and SIGTERM of the orchestrator into a flag its loops check, so the
/// children are stopped and reaped instead of orphaned.
pub fn install_signal_handlers() {
    let handler = on_terminate_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
    // SAFETY: the handler only stores into atomics (async-signal-safe).
    unsafe {
        libc::signal(libc::SIGINT, handler);
        libc::signal(libc::SIGTERM, handler);
    }
}

/// Kills (SIGKILL) and reaps every child still running when dropped.
#[derive(Default)]
pub struct ChildGuard {
    pub children: Vec<(String, Child)>,
}

impl ChildGuard {
    pub fn kill_all(&mut self) {
        for (_, child) in &mut self.children {
            if let Ok(None) = child.try_wait() {
                let _ = child.kill();
            }
            let _ = child.wait();
        }
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        self.kill_all();
    }
}

/// A new run id: `fe<pid>x<microsecond clock mod 1e6>`.
pub fn new_run_id() -> String {
    format!(
        "fe{}x{}",
        std::process::id(),
        (monotonic_now_ns() / 1000) % 1_000_000
    )
}

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
/// still left after iceoryx2's dead-node cleanup (removed as well).
pub fn clear_run(run_id: &str) -> Vec<PathBuf> {
    let _ = cleanup_dead_nodes(run_id);
    let left = files_with_prefix(&file_prefix(run_id));
    remove_paths(&left);
    left
}

/// What the orchestrator needs to run.
#[derive(Debug, Clone)]
pub struct RunPlan {
    pub run_id: String,
    pub config_path: PathBuf,
    pub out_dir: PathBuf,
    pub duration_s: f64,
    pub duration_override_s: Option<f64>,
    pub bin_dir: PathBuf,
}

/// How the run ended.
#[derive(Debug, Clone, Default)]
pub struct RunOutcome {
    /// Faults, each "<process>: <what>", in the order seen (process deaths first).
    pub faults: Vec<String>,
    pub exit_statuses: BTreeMap<String, String>,
    /// Files of the run still present after the children were reaped (then removed).
    pub leftover_files: Vec<PathBuf>,
    pub completed: bool,
}

fn describe_status(status: &ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match (status.code(), status.signal()) {
        (Some(c), _) => format!("exited with code {c}"),
        (None, Some(s)) => format!("killed by signal {s}"),
        _ => "ended".into(),
    }
}

fn heartbeat_fault(hb: &Heartbeat) -> Option<String> {
    if hb.fault_code == 0 {
        return None;
    }
    let name = PROCESS_NAMES
        .get(hb.process as usize)
        .copied()
        .unwrap_or("unknown");
    let mut text = format!("{name}: {}", fault_code_name(hb.fault_code));
    if hb.process == process_id::CONTROLLER && hb.reserved != 0 {
        text.push_str(&format!(" (emulator: {})", fault_code_name(hb.reserved)));
    }
    Some(text)
}

/// Spawns the three processes and runs the scenario to its end or first fault.
pub fn run_processes(plan: &RunPlan, progress: bool) -> Result<RunOutcome, ProcessError> {
    let node = IpcNode::new(&plan.run_id, "hil")?;
    let heartbeats = node.heartbeat_in()?;
    let control = node.control_out()?;
    let mut guard = ChildGuard::default();
    let mut outcome = RunOutcome::default();

    let fastemu = std::env::current_exe()
        .map_err(|e| ProcessError(format!("cannot find own executable: {e}")))?;
    // `bench_rig` next to this executable; if it was not built (`cargo run` builds only
    // the binary it runs), the same rig from this binary's hidden `rig` subcommand.
    let bench_rig = plan.bin_dir.join("bench_rig");
    let (rig_exe, rig_sub) = if bench_rig.exists() {
        (bench_rig, None)
    } else {
        (fastemu.clone(), Some("rig"))
    };
    let exes = [rig_exe, fastemu.clone(), fastemu];
    let subcommands: [Option<&str>; 3] = [rig_sub, Some("emulator"), Some("controller")];
    for (i, name) in PROCESS_NAMES.iter().enumerate() {
        let mut cmd = Command::new(&exes[i]);
        if let Some(sub) = subcommands[i] {
            cmd.arg(sub);
        }
        cmd.arg("--config")
            .arg(&plan.config_path)
            .arg("--run-id")
            .arg(&plan.run_id)
            .arg("--out")
            .arg(&plan.out_dir);
        if let Some(d) = plan.duration_override_s {
            cmd.arg("--duration-s").arg(d.to_string());
        }
        cmd.stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit());
        // If the orchestrator itself is killed (SIGKILL cannot be handled), the kernel
        // kills the children too; the next run then clears the dead run's files.
        // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
        unsafe {
            use std::os::unix::process::CommandExt;
            cmd.pre_exec(|| {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = cmd.spawn().map_err(|e| {
            ProcessError(format!("cannot start {name} ({}): {e}", exes[i].display()))
        })?;
        guard.children.push((name.to_string(), child));
    }

    let mut finished = [false; 3];
    let mut last_heartbeat = [None::<Instant>; 3];
    let mut ready = [false; 3];
    let mut first_fault_at: Option<Instant> = None;
    let mut started_at: Option<Instant> = None;
    let start_wait = Instant::now();
    let mut last_progress = Instant::now();
    let run_timeout = Duration::from_secs_f64(plan.duration_s + 20.0);
    let mut stop_sent_at: Option<Instant> = None;

    let push_fault = |outcome: &mut RunOutcome, f: String, first: &mut Option<Instant>| {
        if !outcome.faults.contains(&f) {
            outcome.faults.push(f);
        }
        first.get_or_insert_with(Instant::now);
    };

    loop {
        std::thread::sleep(Duration::from_millis(5));
        if INTERRUPTED.load(Ordering::SeqCst) && stop_sent_at.is_none() {
            let s = INTERRUPT_SIGNAL.load(Ordering::SeqCst);
            push_fault(
                &mut outcome,
                format!("hil: interrupted by signal {s}"),
                &mut first_fault_at,
            );
        }
        // Process exits.
        for (i, (name, child)) in guard.children.iter_mut().enumerate() {
            if finished[i] {
                continue;
            }
            if let Ok(Some(status)) = child.try_wait() {
                finished[i] = true;
                outcome
                    .exit_statuses
                    .insert(name.clone(), describe_status(&status));
                if !status.success() && stop_sent_at.is_none() {
                    let pid = child.id();
                    push_fault(
                        &mut outcome,
                        format!("{name}: process (pid {pid}) {}", describe_status(&status)),
                        &mut first_fault_at,
                    );
                }
            }
        }
        // Heartbeats.
        heartbeats.receive_each(|hb| {
            let i = hb.process as usize;
            if i < 3 {
                last_heartbeat[i] = Some(Instant::now());
                if hb.state == HEARTBEAT_READY {
                    ready[i] = true;
                }
                if let Some(f) = heartbeat_fault(&hb) {
                    if !outcome.faults.contains(&f) {
                        outcome.faults.push(f);
                    }
                    first_fault_at.get_or_insert_with(Instant::now);
                }
            }
        });
        let now = Instant::now();
        if started_at.is_none() {
            if ready.iter().all(|&r| r) {
                let t0 = monotonic_now_ns() + 100_000_000;
                control.publish(RunControl {
                    sequence: 0,
                    start_time_ns: t0,
                    command: run_command::START,
                    reserved: 0,
                });
                started_at = Some(now);
                if progress {
                    eprintln!(
                        "hil: all processes ready, starting ({} s of scenario)",
                        plan.duration_s
                    );
                }
            } else if now.duration_since(start_wait) > Duration::from_secs(20)
                && first_fault_at.is_none()
            {
                let missing: Vec<&str> = (0..3)
                    .filter(|&i| !ready[i])
                    .map(|i| PROCESS_NAMES[i])
                    .collect();
                push_fault(
                    &mut outcome,
                    format!("hil: not ready within 20 s: {}", missing.join(", ")),
                    &mut first_fault_at,
                );
            }
        } else if let Some(t) = started_at {
            // A process that stops sending heartbeats (e.g. SIGSTOP) is a fault too.
            for i in 0..3 {
                if !finished[i]
                    && last_heartbeat[i]
                        .is_some_and(|h| now.duration_since(h) > Duration::from_millis(1000))
                    && stop_sent_at.is_none()
                {
                    push_fault(
                        &mut outcome,
                        format!(
                            "{}: heartbeat lost (no heartbeat for 1 s)",
                            PROCESS_NAMES[i]
                        ),
                        &mut first_fault_at,
                    );
                }
            }
            if now.duration_since(t) > run_timeout && first_fault_at.is_none() {
                push_fault(
                    &mut outcome,
                    "hil: run timed out".into(),
                    &mut first_fault_at,
                );
            }
            if progress && now.duration_since(last_progress) > Duration::from_secs(1) {
                last_progress = now;
                eprintln!(
                    "hil: t = {:.1} s of {:.1} s",
                    now.duration_since(t).as_secs_f64().min(plan.duration_s),
                    plan.duration_s
                );
            }
        }
        if finished.iter().all(|&f| f) {
            outcome.completed = first_fault_at.is_none();
            break;
        }
        // After the first fault, give the survivors 300 ms to report their safe states,
        // then ask them to stop, and kill whoever has not exited 2 s later.
        if let Some(f) = first_fault_at {
            if stop_sent_at.is_none() && now.duration_since(f) > Duration::from_millis(300) {
                control.publish(RunControl {
                    sequence: 1,
                    start_time_ns: 0,
                    command: run_command::STOP,
                    reserved: 0,
                });
                stop_sent_at = Some(now);
            }
            if stop_sent_at.is_some_and(|s| now.duration_since(s) > Duration::from_secs(2)) {
                break;
            }
        }
    }
    guard.kill_all();
    for (name, child) in &mut guard.children {
        if let Ok(Some(status)) = child.try_wait() {
            outcome
                .exit_statuses
                .entry(name.clone())
                .or_insert_with(|| describe_status(&status));
        }
    }
    drop(guard);
    drop(heartbeats);
    drop(control);
    drop(node);
    outcome.leftover_files = clear_run(&plan.run_id);
    Ok(outcome)
}

/// Machine-wide lock serialising `hil` runs: two real-time loops sharing the CPUs would
/// spoil each other's timing (and their reports). Released when dropped.
pub struct MachineLock {
    _file: std::fs::File,
}

/// Path of the machine-wide `hil` lock file.
pub const MACHINE_LOCK_PATH: &str = "/tmp/fastemu-hil.lock";

/// Takes the machine-wide lock, waiting up to `timeout` for another run to finish;
/// calls `on_wait` once if it has to wait.
pub fn lock_machine(
    timeout: Duration,
    on_wait: impl FnOnce(),
) -> Result<MachineLock, ProcessError> {
    use std::os::unix::io::AsRawFd;
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(MACHINE_LOCK_PATH)
        .map_err(|e| ProcessError(format!("cannot open {MACHINE_LOCK_PATH}: {e}")))?;
    let t0 = Instant::now();
    let mut on_wait = Some(on_wait);
    loop {
        // SAFETY: flock on a valid descriptor we own.
        if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0 {
            return Ok(MachineLock { _file: file });
        }
        if let Some(f) = on_wait.take() {
            f();
        }
        if t0.elapsed() > timeout || INTERRUPTED.load(Ordering::SeqCst) {
            return Err(ProcessError(format!(
                "another hil run held {MACHINE_LOCK_PATH} for more than {timeout:?}"
            )));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}
