//! What the three loop processes share around their loops: the start handshake, run
//! control (stop, operator hold/resume/end), termination signals, heartbeats, the
//! real-time setup, injected stalls and kills, the run's metadata for the records, and the
//! end-of-run summary file.
//!
//! Must not: allocate, log or do I/O in the calls the loops make per cycle
//! (`Injector::due`, `termination_requested`); `poll_control` runs at heartbeat rate.

use std::fmt;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::time::Duration;

use super::config::{HilConfig, InjectKind, Injection, LoopProcess};
use crate::ipc::messages::{run_command, Heartbeat, RunControl, ABI_VERSION, HEARTBEAT_READY};
use crate::ipc::{In, IpcError, Out};
use crate::records::event::{action_code, event_kind, injected_kind};
use crate::records::{EventRecord, RecordSink, RunMeta};
use crate::rt::clock::monotonic_now_ns;
use crate::rt::{apply_rt_setup, RtSetup};

/// A process-level failure: one line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProcessError(pub String);

impl fmt::Display for ProcessError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ProcessError {}

impl From<IpcError> for ProcessError {
    fn from(e: IpcError) -> ProcessError {
        ProcessError(e.to_string())
    }
}

impl From<std::io::Error> for ProcessError {
    fn from(e: std::io::Error) -> ProcessError {
        ProcessError(format!("I/O: {e}"))
    }
}

/// How long a process waits for the orchestrator's start command.
pub const START_TIMEOUT: Duration = Duration::from_secs(30);
/// Heartbeat period, ns.
pub const HEARTBEAT_PERIOD_NS: u64 = 10_000_000;
/// The emulator (controller) exits after this long without a sample (setpoint): its
/// peers and the orchestrator are gone. Not a run length: holds last as long as needed.
pub const IDLE_EXIT_S: f64 = 60.0;
/// An injected kill waits until the record writer has closed the chunk holding its event
/// (the loop is already silent, as after a real kill), at most this long. A fixed wait
/// of 120 ms (the writer flushes every 80 ms) lost the event once in CI, on a loaded
/// machine whose loops kept the writer thread off the CPU.
const KILL_FLUSH_WAIT: Duration = Duration::from_secs(2);

static TERMINATE: AtomicBool = AtomicBool::new(false);
static TERMINATE_SIGNAL: AtomicI32 = AtomicI32::new(0);

extern "C" fn on_terminate(signal: libc::c_int) {
    TERMINATE.store(true, Ordering::SeqCst);
    TERMINATE_SIGNAL.store(signal, Ordering::SeqCst);
}

/// Routes SIGTERM and SIGINT into a flag the loop polls. The orchestrator makes SIGTERM
/// its children's parent-death signal, so a loop process also learns of its death here.
pub fn install_termination_handler() {
    let handler = on_terminate as extern "C" fn(libc::c_int) as libc::sighandler_t;
    // SAFETY: the handler only stores into atomics (async-signal-safe).
    unsafe {
        libc::signal(libc::SIGTERM, handler);
        libc::signal(libc::SIGINT, handler);
    }
}

/// Whether SIGTERM or SIGINT arrived (the orchestrator died or asked us to end).
#[inline]
pub fn termination_requested() -> bool {
    TERMINATE.load(Ordering::Relaxed)
}

/// The run's time base from the START command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StartInfo {
    /// `CLOCK_MONOTONIC` of loop time 0, ns.
    pub t0_ns: u64,
    /// Wall-clock (Unix) time at loop time 0, ns.
    pub start_unix_ns: u64,
}

/// Publishes READY heartbeats until a START arrives (at most `START_TIMEOUT`).
pub fn wait_for_start(
    process: u32,
    heartbeat: &Out<Heartbeat>,
    control: &In<RunControl>,
) -> Result<StartInfo, ProcessError> {
    wait_for_start_within(process, heartbeat, control, START_TIMEOUT)
}

/// Publishes READY heartbeats until a START arrives, at most `timeout`.
pub fn wait_for_start_within(
    process: u32,
    heartbeat: &Out<Heartbeat>,
    control: &In<RunControl>,
    timeout: Duration,
) -> Result<StartInfo, ProcessError> {
    let deadline = monotonic_now_ns() + timeout.as_nanos() as u64;
    let mut seq = 0;
    loop {
        let mut start = None;
        let mut stop = false;
        control.receive_each(|c| match c.command {
            run_command::START => {
                start = Some(StartInfo {
                    t0_ns: c.start_time_ns,
                    start_unix_ns: c.start_unix_ns,
                })
            }
            run_command::STOP => stop = true,
            _ => {}
        });
        if stop || termination_requested() {
            return Err(ProcessError("stopped before start".into()));
        }
        if let Some(s) = start {
            return Ok(s);
        }
        let now = monotonic_now_ns();
        if now > deadline {
            return Err(ProcessError(format!("no start command within {timeout:?}")));
        }
        heartbeat.publish(Heartbeat {
            process,
            state: HEARTBEAT_READY,
            sequence: seq,
            time_ns: now,
            fault_code: 0,
            reserved: 0,
        });
        seq += 1;
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Run-control commands received since the last call.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ControlRequests {
    pub stop: bool,
    pub hold: bool,
    pub resume: bool,
    pub end: bool,
}

/// Drains the run-control service.
#[inline]
pub fn poll_control(control: &In<RunControl>) -> ControlRequests {
    let mut r = ControlRequests::default();
    control.receive_each(|c| match c.command {
        run_command::STOP => r.stop = true,
        run_command::HOLD => r.hold = true,
        run_command::RESUME => r.resume = true,
        run_command::END => r.end = true,
        _ => {}
    });
    r
}

/// The SCHED_FIFO priority of a thread relative to the loops' `[loop] fifo_priority`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Priority {
    /// The rig's and the emulator's loops: they spin before each deadline and, when
    /// late, run their periods back to back without blocking.
    Loop,
    /// One above the loops: threads that only wake for a message and pass it on in
    /// microseconds (the controller, the link). At the loops' priority they would wait
    /// behind a loop that is catching up: a rig late for 140 ms on a slowed CPU never
    /// blocked, and the controller beside it sent no command for 38 ms.
    EventDriven,
    /// One below the loops: the emulator's standby loop thread, on the rig's CPU, never
    /// delays the rig's loop once that is runnable.
    Standby,
}

/// Applies the configured real-time setup for a thread; prints warnings. `[loop]
/// fifo_priority` is 2-98, so the three levels are distinct. Where the OS grants the
/// loops' priority but refuses one above it (an RLIMIT_RTPRIO at the loops' level), an
/// event-driven thread takes the loops' priority rather than normal scheduling beside a
/// SCHED_FIFO loop, and says so.
pub fn real_time_setup(cfg: &HilConfig, cpus: &[usize], who: &str, priority: Priority) {
    let offset = match priority {
        Priority::Loop => 0,
        Priority::EventDriven => 1,
        Priority::Standby => -1,
    };
    let setup = RtSetup {
        // mlockall is per process: the primary thread has done it for the standby.
        lock_memory: cfg.loop_.lock_memory && priority != Priority::Standby,
        fifo_priority: cfg.loop_.fifo_priority.map(|p| (p + offset).clamp(1, 99)),
        cpus: cpus.to_vec(),
    };
    let mut warnings = apply_rt_setup(&setup);
    if let (Priority::EventDriven, Some(p)) = (priority, cfg.loop_.fifo_priority) {
        // SAFETY: plain syscall on the calling thread.
        if unsafe { libc::sched_getscheduler(0) } != libc::SCHED_FIFO {
            let retry = RtSetup {
                lock_memory: false,
                fifo_priority: Some(p),
                cpus: Vec::new(),
            };
            let again = apply_rt_setup(&retry);
            if again.is_empty() {
                warnings.push(format!(
                    "running at the loops' SCHED_FIFO priority {p} instead: a loop catching up on this thread's CPU can delay it"
                ));
            }
            warnings.extend(again);
        }
    }
    for w in warnings {
        eprintln!("{who}: warning: {w}");
    }
}

/// The `/meta` message of a process.
pub fn meta_json(
    cfg: &HilConfig,
    process: &str,
    run_id: &str,
    config_text: &str,
    config_base_dir: Option<&Path>,
    start_unix_ns: u64,
) -> String {
    serde_json::to_string(&RunMeta {
        process: process.to_string(),
        run_id: run_id.to_string(),
        abi_version: ABI_VERSION,
        rate_hz: cfg.loop_.rate_hz,
        start_unix_ns,
        config_origin: cfg.origin.clone(),
        config_base_dir: config_base_dir.map(Path::to_path_buf),
        config_text: config_text.to_string(),
    })
    .unwrap_or_default()
}

/// Writes a process's end-of-run summary (`<name>-summary.json`), with what its threads
/// marked real-time took from the pool (`rt_pool`, `rt::pool::PoolStats`).
pub fn write_summary(
    out_dir: &Path,
    name: &str,
    summary: &impl serde::Serialize,
) -> std::io::Result<()> {
    // Read before serialising (which allocates on this thread, marked real-time).
    let pool = crate::rt::pool::stats();
    let mut value = serde_json::to_value(summary).unwrap_or_default();
    if let Some(object) = value.as_object_mut() {
        object.insert(
            "rt_pool".to_string(),
            serde_json::to_value(pool).unwrap_or_default(),
        );
    }
    std::fs::write(
        out_dir.join(format!("{name}-summary.json")),
        serde_json::to_string_pretty(&value).unwrap_or_default(),
    )
}

/// Injected stalls and kills of one process (`[[inject]]`), fired on its loop time.
#[derive(Debug, Clone)]
pub struct Injector {
    pending: Vec<Injection>,
    next: usize,
    process_id: u32,
}

impl Injector {
    /// The stall and kill injections of `process` (sample faults are the rig core's).
    pub fn new(cfg: &HilConfig, process: LoopProcess, process_id: u32) -> Injector {
        Injector {
            pending: cfg
                .injections_for(process)
                .into_iter()
                .filter(|i| {
                    matches!(
                        i.kind,
                        InjectKind::Stall { .. } | InjectKind::CpuStall { .. } | InjectKind::Kill
                    )
                })
                .collect(),
            next: 0,
            process_id,
        }
    }

    /// Fires the injection due at loop time `t_s`, if any: records its event, then stalls
    /// the calling thread or kills the process. A deliberate fault, not loop work. A
    /// `cpu-stall` is returned instead: the caller serves it after its cycle, outside the
    /// loop's turn.
    #[inline]
    pub fn fire_due(
        &mut self,
        t_s: f64,
        step_idx: u64,
        events: &RecordSink<EventRecord>,
    ) -> Option<Duration> {
        let inj = self.pending.get(self.next).copied()?;
        if t_s < inj.at_s {
            return None;
        }
        self.next += 1;
        let (code, value) = match inj.kind {
            InjectKind::Stall { duration_s } => (injected_kind::STALL, duration_s * 1e3),
            InjectKind::CpuStall { duration_s } => (injected_kind::CPU_STALL, duration_s * 1e3),
            _ => (injected_kind::KILL, 0.0),
        };
        events.push(EventRecord {
            t_s,
            process: self.process_id,
            kind: event_kind::INJECTED,
            fault_code: code,
            remote_fault_code: 0,
            action: action_code::NONE,
            detection_latency_periods: 0,
            step_idx,
            value,
        });
        match inj.kind {
            InjectKind::Stall { duration_s } => {
                std::thread::sleep(Duration::from_secs_f64(duration_s));
                None
            }
            InjectKind::CpuStall { duration_s } => Some(Duration::from_secs_f64(duration_s)),
            _ => {
                events.wait_flushed(KILL_FLUSH_WAIT);
                // SAFETY: raising a signal on ourselves; SIGKILL cannot be caught.
                unsafe { libc::raise(libc::SIGKILL) };
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The SCHED_FIFO priority and policy of the calling thread.
    fn own_priority() -> (i32, i32) {
        let mut param = libc::sched_param { sched_priority: 0 };
        // SAFETY: pid 0 is the calling thread; `param` is valid for writing.
        unsafe { libc::sched_getparam(0, &mut param) };
        // SAFETY: plain syscall on the calling thread.
        (unsafe { libc::sched_getscheduler(0) }, param.sched_priority)
    }

    /// The event-driven threads (controller, link) run one priority above the loops, so a
    /// loop catching up without blocking cannot starve them, the standby one below; where
    /// the OS refuses SCHED_FIFO (not root), every thread stays at normal scheduling.
    #[test]
    fn event_driven_threads_run_one_priority_above_the_loops() {
        let mut cfg = crate::hil::config::default_hil_config().unwrap();
        cfg.loop_.lock_memory = false;
        cfg.loop_.fifo_priority = Some(80);
        let applied = |cfg: &HilConfig, priority: Priority| {
            let cfg = cfg.clone();
            std::thread::spawn(move || {
                real_time_setup(&cfg, &[], "test", priority);
                own_priority()
            })
            .join()
            .unwrap()
        };
        let (loop_policy, loop_prio) = applied(&cfg, Priority::Loop);
        let (event_policy, event_prio) = applied(&cfg, Priority::EventDriven);
        if loop_policy == libc::SCHED_FIFO {
            assert_eq!(loop_prio, 80);
            assert_eq!(event_policy, libc::SCHED_FIFO);
            assert_eq!(event_prio, 81);
        } else {
            assert_eq!(
                (loop_policy, event_policy),
                (libc::SCHED_OTHER, libc::SCHED_OTHER)
            );
        }
        let (_, standby_prio) = applied(&cfg, Priority::Standby);
        cfg.loop_.fifo_priority = Some(98);
        let (_, highest) = applied(&cfg, Priority::EventDriven);
        if loop_policy == libc::SCHED_FIFO {
            assert_eq!(standby_prio, 79);
            assert_eq!(
                highest, 99,
                "98, the highest the configuration takes, plus one"
            );
        }
    }
}
