//! The `hil` orchestrator: starts the three loop processes under a unique run id (with an
//! external rig, the emulator and controller once the rig is ready; with the UDP rig link,
//! the link process in the rig's place and the simulated rig behind it), waits
//! until they are ready, starts them on a common clock, supervises them (exits,
//! heartbeats, faults), lets the rig end the run (after a fault: once its hold is over),
//! stops and reaps the others on every exit path (`ChildGuard`), removes the run's shared
//! memory and merges the records. SIGINT/SIGTERM to `hil` are an operator stop: the rig
//! holds, unloads and finishes; a second one stops at once.
//!
//! Must not: leave a child process or a file of its run behind, on any path; stop the rig
//! before its hold is over (unless the operator insists).

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, AtomicI32, AtomicU32, Ordering};
use std::time::{Duration, Instant};

use super::fault::fault_code_name;
use super::process::ProcessError;
use crate::child::ChildGuard;
use crate::ipc::cleanup::clear_run;
use crate::ipc::messages::{
    operator_answer, process_id, rig_state, run_command, Heartbeat, RunControl, HEARTBEAT_READY,
};
use crate::ipc::{In, IpcNode, Out};
use crate::rt::clock::monotonic_now_ns;

/// Names of the three processes, indexed by `process_id`.
pub const PROCESS_NAMES: [&str; 3] = ["bench_rig", "emulator", "controller"];

static INTERRUPTS: AtomicU32 = AtomicU32::new(0);
static INTERRUPT_SIGNAL: AtomicI32 = AtomicI32::new(0);
static INTERRUPTED: AtomicBool = AtomicBool::new(false);

extern "C" fn on_terminate_signal(signal: libc::c_int) {
    INTERRUPTS.fetch_add(1, Ordering::SeqCst);
    INTERRUPTED.store(true, Ordering::SeqCst);
    INTERRUPT_SIGNAL.store(signal, Ordering::SeqCst);
}

/// Routes SIGINT and SIGTERM of the orchestrator into a counter its loops check: the
/// first is an orderly stop, a second stops at once; the children are always reaped.
pub fn install_signal_handlers() {
    let handler = on_terminate_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
    // SAFETY: the handler only touches atomics (async-signal-safe).
    unsafe {
        libc::signal(libc::SIGINT, handler);
        libc::signal(libc::SIGTERM, handler);
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

/// Which rig the run has and how it connects.
#[derive(Debug, Clone, PartialEq)]
pub enum RigSetup {
    /// The simulated rig on iceoryx2 (the default).
    Simulated,
    /// The simulated rig on the far side of a UDP link: fastemu's link process at `link`
    /// (the rig, as the loop sees it), the simulated rig at `rig`.
    SimulatedUdp { link: SocketAddr, rig: SocketAddr },
    /// A rig fastemu did not start, on the run's iceoryx2 services; waited for this long.
    External { wait: Duration },
    /// A rig fastemu did not start, behind the UDP link.
    ExternalUdp {
        link: SocketAddr,
        rig: SocketAddr,
        wait: Duration,
    },
}

impl RigSetup {
    fn external_wait(&self) -> Option<Duration> {
        match self {
            RigSetup::External { wait } | RigSetup::ExternalUdp { wait, .. } => Some(*wait),
            _ => None,
        }
    }
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
    /// The longest hold the rig may take before it ends the run, s.
    pub hold_max_s: f64,
    pub rig: RigSetup,
    /// Sockets `hil` bound for the link ends it starts (`RigSetup::SimulatedUdp`): each
    /// is handed to the child that binds its address.
    pub handed_sockets: Vec<std::sync::Arc<std::net::UdpSocket>>,
}

/// How the run ended.
#[derive(Debug, Clone, Default)]
pub struct RunOutcome {
    /// Faults, each "<process>: <what>", in the order seen (process deaths first).
    pub faults: Vec<String>,
    pub exit_statuses: BTreeMap<String, String>,
    /// Files of the run still present after the children were reaped (then removed).
    pub leftover_files: Vec<PathBuf>,
    /// Whether the rig ended the run itself (scenario end or the end of a hold).
    pub rig_finished: bool,
    /// The rig's last hold as its heartbeat told it, while the rig's last heartbeat
    /// before it finished still said it held (its state: hold, unload or operator hold;
    /// its fault code; when the hold's first heartbeat came); `None` when the rig never
    /// held or resumed from its last hold. An external rig's own account, which the
    /// report needs when the records, written from its samples by the emulator, end
    /// before that hold (the emulator dead, the link silent).
    pub rig_hold_seen: Option<RigHoldSeen>,
    /// Whether the operator stopped the run (SIGINT/SIGTERM to `hil`).
    pub operator_stop: bool,
    /// Whether the orchestrator sent START (every process was ready): false, the loop
    /// never ran.
    pub started: bool,
    pub completed: bool,
}

/// A hold the rig reported in its heartbeat (`RunOutcome::rig_hold_seen`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigHoldSeen {
    pub state: u32,
    pub fault_code: u32,
    /// When the heartbeat arrived, s of the loop's time (`None`: before the start).
    pub at_s: Option<f64>,
}

/// Whether a child's exit is part of the run's end rather than a death: an exit with a
/// code once the rig has finished or a stop was sent, or with code 3 (a loop process that
/// ended on its own fault) when its heartbeat has already named that fault (an emulator
/// that tripped exits at the rig's end of run, which it can see before the orchestrator
/// sees the rig's exit).
fn exit_is_orderly(name: &str, code: Option<i32>, ending: bool, faults: &[String]) -> bool {
    let ended_on_named_fault =
        code == Some(3) && faults.iter().any(|f| f.starts_with(&format!("{name}: ")));
    code.is_some() && (ending || ended_on_named_fault)
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

/// A process `hil` starts: its name, what it runs, and which loop process it is on
/// iceoryx2 (`None`: the simulated rig behind the UDP link, not on iceoryx2).
struct ChildSpec {
    name: &'static str,
    exe: PathBuf,
    args: Vec<String>,
    process: Option<u32>,
    /// The link address the child binds (its socket is handed over if `hil` holds it).
    binds: Option<SocketAddr>,
}

/// The processes of `plan`, in start order; with an external rig, the emulator and the
/// controller come after the rig is ready (`after_rig`).
fn child_specs(plan: &RunPlan) -> Result<(Vec<ChildSpec>, Vec<ChildSpec>), ProcessError> {
    let fastemu = std::env::current_exe()
        .map_err(|e| ProcessError(format!("cannot find own executable: {e}")))?;
    // `bench_rig` next to this executable; if it was not built (`cargo run` builds only
    // the binary it runs), the same rig from this binary's hidden `rig` subcommand.
    let bench_rig = plan.bin_dir.join("bench_rig");
    let (rig_exe, rig_sub) = if bench_rig.exists() {
        (bench_rig, vec![])
    } else {
        (fastemu.clone(), vec!["rig".to_string()])
    };
    let spec = |name, exe: &PathBuf, sub: Vec<String>, extra: Vec<String>, process| ChildSpec {
        name,
        exe: exe.clone(),
        args: sub.into_iter().chain(extra).collect(),
        process,
        binds: None,
    };
    let link = |link: &SocketAddr, rig: &SocketAddr, wait: Option<Duration>| {
        let mut extra = vec![
            "--bind".to_string(),
            link.to_string(),
            "--peer".to_string(),
            rig.to_string(),
        ];
        if let Some(w) = wait {
            extra.extend(["--rig-wait-s".to_string(), w.as_secs_f64().to_string()]);
        }
        ChildSpec {
            binds: Some(*link),
            ..spec(
                "link",
                &fastemu,
                vec!["link".into()],
                extra,
                Some(process_id::RIG),
            )
        }
    };
    let loop_processes = || {
        vec![
            spec(
                PROCESS_NAMES[1],
                &fastemu,
                vec!["emulator".into()],
                vec![],
                Some(process_id::EMULATOR),
            ),
            spec(
                PROCESS_NAMES[2],
                &fastemu,
                vec!["controller".into()],
                vec![],
                Some(process_id::CONTROLLER),
            ),
        ]
    };
    let mut first = Vec::new();
    match &plan.rig {
        RigSetup::Simulated => first.push(spec(
            PROCESS_NAMES[0],
            &rig_exe,
            rig_sub,
            vec![],
            Some(process_id::RIG),
        )),
        RigSetup::SimulatedUdp { link: l, rig } => {
            first.push(link(l, rig, None));
            let far = vec![
                "--link-bind".to_string(),
                rig.to_string(),
                "--link-peer".to_string(),
                l.to_string(),
            ];
            first.push(ChildSpec {
                binds: Some(*rig),
                ..spec(PROCESS_NAMES[0], &rig_exe, rig_sub, far, None)
            });
        }
        RigSetup::External { .. } => {}
        RigSetup::ExternalUdp { link: l, rig, wait } => first.push(link(l, rig, Some(*wait))),
    }
    if plan.rig.external_wait().is_some() {
        Ok((first, loop_processes()))
    } else {
        first.extend(loop_processes());
        Ok((first, vec![]))
    }
}

/// Starts `specs`; each dies with SIGTERM when the orchestrator dies, so the rig holds and
/// the others end with their records flushed.
fn spawn_children(
    plan: &RunPlan,
    specs: Vec<ChildSpec>,
    sup: &mut Supervisor,
) -> Result<(), ProcessError> {
    for spec in specs {
        let mut cmd = Command::new(&spec.exe);
        cmd.args(&spec.args)
            .arg("--config")
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
        // The link socket bound for this child, left open across its exec.
        let handed_fd = spec.binds.and_then(|addr| {
            use std::os::fd::AsRawFd;
            plan.handed_sockets
                .iter()
                .find(|s| s.local_addr().ok() == Some(addr))
                .map(|s| s.as_raw_fd())
        });
        if let Some(fd) = handed_fd {
            cmd.env(crate::link::socket::HANDED_SOCKET_ENV, fd.to_string());
        }
        // If the orchestrator itself is killed (SIGKILL cannot be handled), the kernel
        // sends the children SIGTERM: the rig holds, the others flush and end.
        // SAFETY: prctl and fcntl are async-signal-safe and touch no memory of the parent.
        unsafe {
            use std::os::unix::process::CommandExt;
            cmd.pre_exec(move || {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                if let Some(fd) = handed_fd {
                    if libc::fcntl(fd, libc::F_SETFD, 0) != 0 {
                        return Err(std::io::Error::last_os_error());
                    }
                }
                Ok(())
            });
        }
        let child = cmd.spawn().map_err(|e| {
            ProcessError(format!(
                "cannot start {} ({}): {e}",
                spec.name,
                spec.exe.display()
            ))
        })?;
        sup.children
            .push((spec.name.to_string(), ChildGuard::new(child)));
        sup.child_process.push(spec.process);
        sup.finished.push(false);
    }
    Ok(())
}

/// Supervision state of a run.
struct Supervisor {
    children: Vec<(String, ChildGuard)>,
    /// The loop process (`process_id`) each child is on iceoryx2, if any.
    child_process: Vec<Option<u32>>,
    outcome: RunOutcome,
    /// Per child: exited and reaped.
    finished: Vec<bool>,
    /// An external rig's heartbeat stopped (it is not a child whose exit can be seen).
    rig_lost: bool,
    last_heartbeat: [Option<Instant>; 3],
    ready: [bool; 3],
    started_at: Option<Instant>,
    /// The loop's time zero sent with START (monotonic ns).
    loop_t0_ns: Option<u64>,
    first_fault_at: Option<Instant>,
    stop_sent_at: Option<Instant>,
    end_sent_at: Option<Instant>,
    interrupts_seen: u32,
    sequence: u64,
    /// Where the link process writes its summary (its error, if it fails).
    link_summary_error: Option<PathBuf>,
    /// Every heartbeat received, relayed to `fastemu ctl` (`Stream::OperatorStatus`),
    /// with the answers to its requests.
    status_relay: Option<Out<Heartbeat>>,
    /// The last `ctl` requests answered (sequence, answer), so a repeat is not relayed
    /// twice.
    answered: [(u64, u32); 16],
    answered_next: usize,
}

impl Supervisor {
    fn push_fault(&mut self, fault: String) {
        if !self.outcome.faults.contains(&fault) {
            self.outcome.faults.push(fault);
        }
        self.first_fault_at.get_or_insert_with(Instant::now);
    }

    fn send(
        &mut self,
        control: &Out<RunControl>,
        command: u32,
        start_time_ns: u64,
        start_unix_ns: u64,
    ) {
        self.sequence += 1;
        control.publish(RunControl {
            sequence: self.sequence,
            start_time_ns,
            start_unix_ns,
            command,
            reserved: 0,
        });
    }

    /// Reaps exited children; a death before the end is a fault.
    fn check_exits(&mut self) {
        for i in 0..self.children.len() {
            if self.finished[i] {
                continue;
            }
            let (name, child) = &mut self.children[i];
            if let Ok(Some(status)) = child.try_wait() {
                let name = name.clone();
                let pid = child.id();
                self.finished[i] = true;
                self.outcome
                    .exit_statuses
                    .insert(name.clone(), describe_status(&status));
                if self.child_process[i] == Some(process_id::RIG) && status.code().is_some() {
                    self.outcome.rig_finished = true;
                }
                let orderly = exit_is_orderly(
                    &name,
                    status.code(),
                    self.outcome.rig_finished || self.stop_sent_at.is_some(),
                    &self.outcome.faults,
                );
                if name == "link" && !status.success() {
                    // The link names its own failure (a silent rig, a wrong period).
                    self.push_fault(format!("link: {}", self.link_error(&status)));
                } else if !status.success() && !orderly {
                    self.push_fault(format!(
                        "{name}: process (pid {pid}) {}",
                        describe_status(&status)
                    ));
                }
            }
        }
    }

    fn check_heartbeats(&mut self, heartbeats: &In<Heartbeat>) {
        let mut faults = Vec::new();
        heartbeats.receive_each(|hb| {
            let i = hb.process as usize;
            if let Some(relay) = &self.status_relay {
                relay.publish(hb);
            }
            if i < 3 {
                self.last_heartbeat[i] = Some(Instant::now());
                if hb.state == HEARTBEAT_READY {
                    self.ready[i] = true;
                }
                if hb.process == process_id::RIG && hb.state == rig_state::FINISHED {
                    self.outcome.rig_finished = true;
                }
                let holding = matches!(
                    hb.state,
                    rig_state::HOLD | rig_state::UNLOAD | rig_state::OPERATOR_HOLD
                );
                let counts = !matches!(hb.state, rig_state::FINISHED | HEARTBEAT_READY);
                if hb.process == process_id::RIG && counts {
                    if !holding {
                        // Resumed (or not yet held): no hold stands.
                        self.outcome.rig_hold_seen = None;
                    } else if let Some(h) = &mut self.outcome.rig_hold_seen {
                        // The same hold: its latest state and fault (an operator hold a
                        // fault latched in), its first time.
                        h.state = hb.state;
                        h.fault_code = hb.fault_code;
                    } else {
                        let now = monotonic_now_ns();
                        self.outcome.rig_hold_seen = Some(RigHoldSeen {
                            state: hb.state,
                            fault_code: hb.fault_code,
                            at_s: self
                                .loop_t0_ns
                                .map(|t0| now.saturating_sub(t0) as f64 * 1e-9),
                        });
                    }
                }
                if let Some(f) = heartbeat_fault(&hb) {
                    faults.push(f);
                }
            }
        });
        for f in faults {
            self.push_fault(f);
        }
    }

    /// Whether loop process `process` has ended: its child exited (an external rig, which
    /// is no child: it said it finished, or its heartbeat stopped).
    fn process_finished(&self, process: u32) -> bool {
        match self.child_process.iter().position(|&p| p == Some(process)) {
            Some(i) => self.finished[i],
            None => process == process_id::RIG && (self.outcome.rig_finished || self.rig_lost),
        }
    }

    /// The link's own account of why it failed (`link-summary.json`).
    fn link_error(&self, status: &ExitStatus) -> String {
        self.link_summary_error
            .as_ref()
            .and_then(|path| std::fs::read_to_string(path).ok())
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            .and_then(|v| v["error"].as_str().map(String::from))
            .unwrap_or_else(|| describe_status(status))
    }

    /// A process that stops sending heartbeats (e.g. SIGSTOP) is a fault too; an external
    /// rig that stops is gone (the run stops).
    fn check_silence(&mut self, now: Instant) {
        let quiet_ok = self.stop_sent_at.is_some() || self.outcome.rig_finished;
        let silent: Vec<u32> = (0..3u32)
            .filter(|&p| {
                !self.process_finished(p)
                    && self.last_heartbeat[p as usize]
                        .is_some_and(|h| now.duration_since(h) > Duration::from_millis(1000))
            })
            .collect();
        if !quiet_ok {
            for p in silent {
                let external = p == process_id::RIG && !self.child_process.contains(&Some(p));
                let name = if external {
                    "rig (external)"
                } else {
                    PROCESS_NAMES[p as usize]
                };
                self.push_fault(format!("{name}: heartbeat lost (no heartbeat for 1 s)"));
                if external {
                    self.rig_lost = true;
                }
            }
        }
    }
}

impl Supervisor {
    fn new(plan: &RunPlan) -> Supervisor {
        Supervisor {
            children: Vec::new(),
            child_process: Vec::new(),
            outcome: RunOutcome::default(),
            finished: Vec::new(),
            rig_lost: false,
            last_heartbeat: [None; 3],
            ready: [false; 3],
            started_at: None,
            loop_t0_ns: None,
            first_fault_at: None,
            stop_sent_at: None,
            end_sent_at: None,
            interrupts_seen: 0,
            sequence: 0,
            link_summary_error: Some(plan.out_dir.join("link-summary.json")),
            status_relay: None,
            answered: [(u64::MAX, 0); 16],
            answered_next: 0,
        }
    }

    /// `fastemu ctl`'s requests (`Stream::OperatorRequest`), relayed to the rig on the
    /// run's control stream as the live view's are: `ctl` never opens a loop's ports, so
    /// no loop connects to a port that appears mid-run. Before the start only `stop` is
    /// acted on (as a signal is: the run ends before it starts). Every request is
    /// answered on the status stream (`operator_answer`); `ctl` sends a request again
    /// until it is answered, and a repeat gets the first answer again, not a second
    /// relay.
    fn relay_operator_requests(
        &mut self,
        requests: &In<RunControl>,
        control: &Out<RunControl>,
        progress: bool,
    ) {
        let mut received = [(0u64, 0u32); 16];
        let mut n = 0;
        requests.receive_each(|r| {
            // More than 16 in 5 ms: the rest are sent again by their `ctl`.
            if n < received.len() {
                received[n] = (r.sequence, r.command);
                n += 1;
            }
        });
        for &(sequence, command) in &received[..n] {
            let answer = match self.answered.iter().find(|a| a.0 == sequence) {
                Some(&(_, answer)) => answer,
                None => {
                    let answer = self.act_on_operator_request(command, control, progress);
                    self.answered[self.answered_next % self.answered.len()] = (sequence, answer);
                    self.answered_next += 1;
                    answer
                }
            };
            if let Some(relay) = &self.status_relay {
                relay.publish(Heartbeat {
                    process: process_id::HIL,
                    state: answer,
                    sequence,
                    time_ns: monotonic_now_ns(),
                    fault_code: 0,
                    reserved: command,
                });
            }
        }
    }

    /// Acts on one `ctl` request; its answer (`operator_answer`).
    fn act_on_operator_request(
        &mut self,
        command: u32,
        control: &Out<RunControl>,
        progress: bool,
    ) -> u32 {
        let name = match command {
            run_command::HOLD => "hold",
            run_command::RESUME => "resume",
            run_command::END => "stop",
            _ => {
                eprintln!("hil: unknown request {command} from fastemu ctl: ignored");
                return operator_answer::UNKNOWN;
            }
        };
        if self.started_at.is_some() && self.end_sent_at.is_some() && command != run_command::END {
            eprintln!("hil: fastemu ctl {name} after a stop: ignored (the run is ending)");
            operator_answer::IGNORED_ENDING
        } else if self.started_at.is_some() {
            if progress {
                eprintln!("hil: operator request from fastemu ctl: {name}");
            }
            self.send(control, command, 0, 0);
            if command == run_command::END {
                self.end_sent_at.get_or_insert_with(Instant::now);
            }
            operator_answer::RELAYED
        } else if command == run_command::END {
            self.outcome.operator_stop = true;
            self.push_fault("hil: stopped by fastemu ctl before the start".into());
            operator_answer::ENDED_BEFORE_START
        } else {
            eprintln!("hil: fastemu ctl {name} before the start: ignored");
            operator_answer::IGNORED_BEFORE_START
        }
    }

    /// Sends STOP once (the processes end now).
    fn stop_once(&mut self, control: &Out<RunControl>, now: Instant) {
        if self.stop_sent_at.is_none() {
            self.send(control, run_command::STOP, 0, 0);
            self.stop_sent_at = Some(now);
        }
    }

    /// Before the start: START once every process is ready; a signal, or a process not
    /// ready within 20 s, is a fault that stops the run.
    fn before_start(
        &mut self,
        plan: &RunPlan,
        control: &Out<RunControl>,
        interrupts: u32,
        start_wait: Instant,
        now: Instant,
        progress: bool,
    ) {
        if interrupts > 0 {
            self.outcome.operator_stop = true;
            self.push_fault(format!(
                "hil: interrupted by signal {} before the start",
                INTERRUPT_SIGNAL.load(Ordering::SeqCst)
            ));
        } else if self.ready.iter().all(|&r| r) && self.first_fault_at.is_none() {
            // (Not after a fault, such as a `ctl stop` in this same tick.)
            let t0 = monotonic_now_ns() + 100_000_000;
            self.loop_t0_ns = Some(t0);
            self.outcome.started = true;
            let unix_now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos() as u64);
            self.send(control, run_command::START, t0, unix_now + 100_000_000);
            self.started_at = Some(now);
            if progress {
                eprintln!(
                    "hil: all processes ready, starting ({} s of scenario)",
                    plan.duration_s
                );
            }
        } else if now.duration_since(start_wait) > Duration::from_secs(20)
            && self.first_fault_at.is_none()
        {
            let missing: Vec<&str> = (0..3)
                .filter(|&i| !self.ready[i])
                .map(|i| PROCESS_NAMES[i])
                .collect();
            self.push_fault(format!(
                "hil: not ready within 20 s: {}",
                missing.join(", ")
            ));
        }
        if self.first_fault_at.is_some() {
            self.stop_once(control, now);
        }
    }

    /// While running: silence checks, the operator's signals and live requests relayed
    /// to the rig, STOP once the rig ended the run.
    fn while_running(
        &mut self,
        control: &Out<RunControl>,
        live: Option<&crate::live::LiveHandle>,
        interrupts: u32,
        now: Instant,
        progress: bool,
    ) {
        self.check_silence(now);
        // Operator stop: an orderly end (hold, unload, finish); a second signal stops at
        // once.
        if interrupts > self.interrupts_seen {
            self.interrupts_seen = interrupts;
            self.outcome.operator_stop = true;
            if self.end_sent_at.is_none() {
                if progress {
                    eprintln!("hil: operator stop: the rig holds, unloads and finishes (signal again to stop at once)");
                }
                self.send(control, run_command::END, 0, 0);
                self.end_sent_at = Some(now);
            } else {
                self.stop_once(control, now);
            }
        }
        if let Some(command) = live.and_then(|l| l.take_request()) {
            if progress {
                eprintln!(
                    "hil: operator request from the live view: {}",
                    match command {
                        run_command::HOLD => "hold",
                        run_command::RESUME => "resume",
                        _ => "stop",
                    }
                );
            }
            self.send(control, command, 0, 0);
            if command == run_command::END {
                self.end_sent_at.get_or_insert_with(Instant::now);
            }
        }
        // The rig ended the run (or died): the others stop now.
        if self.process_finished(process_id::RIG) {
            self.stop_once(control, now);
        }
    }

    /// Whether the supervision is over: every child reaped, or the grace after STOP has
    /// passed (the simulated rig behind a link that died holds on its own until at rest:
    /// it gets as long as a hold may take; the others 3 s).
    fn supervision_over(&self, plan: &RunPlan, now: Instant) -> bool {
        if self.finished.iter().all(|&f| f) {
            return true;
        }
        let far_rig_holding = self
            .child_process
            .iter()
            .zip(&self.finished)
            .any(|(p, f)| p.is_none() && !f);
        let grace = if far_rig_holding {
            Duration::from_secs_f64(plan.hold_max_s + 3.0)
        } else {
            Duration::from_secs(3)
        };
        self.stop_sent_at
            .is_some_and(|s| now.duration_since(s) > grace)
    }

    /// The run's outcome; children still running are killed and reaped (their guards).
    fn into_outcome(mut self) -> RunOutcome {
        self.outcome.completed = self.first_fault_at.is_none() && self.outcome.rig_finished;
        let mut outcome = self.outcome;
        for (name, mut child) in self.children.drain(..) {
            if let Ok(None) = child.try_wait() {
                outcome
                    .exit_statuses
                    .insert(name.clone(), "killed by hil (did not stop)".into());
            }
            drop(child);
        }
        outcome
    }
}

/// Spawns the three processes and runs the scenario until the rig ends it; operator
/// requests from the live view's services (`live`) are relayed to the rig.
pub fn run_processes(
    plan: &RunPlan,
    progress: bool,
    live: Option<&crate::live::LiveHandle>,
) -> Result<RunOutcome, ProcessError> {
    let node = IpcNode::new(&plan.run_id, "hil")?;
    // With an external rig, the rig's services exist (with the loop's settings) before
    // it connects, and as long as the run.
    let rig_services = match plan.rig {
        RigSetup::External { .. } => Some(node.hold_rig_services()?),
        _ => None,
    };
    let heartbeats = node.heartbeat_in()?;
    let control = node.control_out()?;
    let operator_requests = node.operator_request_in()?;
    let (first, after_rig) = child_specs(plan)?;
    let mut sup = Supervisor::new(plan);
    sup.status_relay = Some(node.operator_status_out()?);
    spawn_children(plan, first, &mut sup)?;
    if let Some(wait) = plan.rig.external_wait() {
        if wait_for_external_rig(
            &mut sup,
            &heartbeats,
            (&operator_requests, &control, progress),
            wait,
        )? {
            spawn_children(plan, after_rig, &mut sup)?;
        } else {
            sup.stop_once(&control, Instant::now());
        }
    }
    let start_wait = Instant::now();
    let mut last_progress = Instant::now();
    // No wall-clock limit on the run: an operator hold lasts as long as the operator
    // wants; the rig ends the run, and a silent process is a fault (heartbeats).
    loop {
        std::thread::sleep(Duration::from_millis(5));
        let now = Instant::now();
        sup.check_exits();
        sup.check_heartbeats(&heartbeats);
        sup.relay_operator_requests(&operator_requests, &control, progress);
        let interrupts = INTERRUPTS.load(Ordering::SeqCst);
        match sup.started_at {
            None => sup.before_start(plan, &control, interrupts, start_wait, now, progress),
            Some(t) => {
                sup.while_running(&control, live, interrupts, now, progress);
                if progress && now.duration_since(last_progress) > Duration::from_secs(1) {
                    last_progress = now;
                    let elapsed_s = now.duration_since(t).as_secs_f64();
                    if sup.first_fault_at.is_some() {
                        // The programme stopped at the fault; the hold runs its own time.
                        // A fault whose action is "indicate" leaves the rig running.
                        // Wall time: the programme stopped at the fault.
                        if sup.outcome.rig_hold_seen.is_some() {
                            eprintln!(
                                "hil: {elapsed_s:.1} s since the start (wall clock; the programme stopped at the fault): holding"
                            );
                        } else {
                            eprintln!(
                                "hil: {elapsed_s:.1} s since the start (wall clock): a fault; the rig has not reported a hold (an \"indicate\" action leaves it running)"
                            );
                        }
                    } else {
                        eprintln!(
                            "hil: t = {elapsed_s:.1} s of {:.1} s{}",
                            plan.duration_s,
                            if elapsed_s > plan.duration_s {
                                " of programme (it paused while the rig held, or is unloading)"
                            } else {
                                ""
                            }
                        );
                    }
                }
            }
        }
        if sup.supervision_over(plan, now) {
            break;
        }
    }
    let mut outcome = sup.into_outcome();
    drop(heartbeats);
    drop(operator_requests);
    drop(control);
    drop(rig_services);
    drop(node);
    outcome.leftover_files = match plan.rig {
        RigSetup::External { .. } => clear_external_run(&plan.run_id),
        _ => clear_run(&plan.run_id),
    };
    Ok(outcome)
}

/// Waits until the external rig (or the link, for a rig behind it) reports ready, at
/// most `wait`; false if it did not come, the link died, or the operator stopped (a
/// signal, or `fastemu ctl stop`).
fn wait_for_external_rig(
    sup: &mut Supervisor,
    heartbeats: &In<Heartbeat>,
    (operator_requests, control, progress): (&In<RunControl>, &Out<RunControl>, bool),
    wait: Duration,
) -> Result<bool, ProcessError> {
    let t0 = Instant::now();
    loop {
        sup.check_exits();
        sup.check_heartbeats(heartbeats);
        // A `ctl stop` is a fault before the start (checked below).
        sup.relay_operator_requests(operator_requests, control, progress);
        if sup.ready[process_id::RIG as usize] {
            eprintln!("hil: the rig is ready; starting the emulator and the controller");
            return Ok(true);
        }
        if INTERRUPTS.load(Ordering::SeqCst) > 0 {
            sup.outcome.operator_stop = true;
            sup.push_fault("hil: interrupted while waiting for the rig".into());
            return Ok(false);
        }
        if sup.process_finished(process_id::RIG) || sup.first_fault_at.is_some() {
            return Ok(false);
        }
        if t0.elapsed() > wait {
            sup.push_fault(format!(
                "hil: no rig connected within {} s (docs/rig-interface.md; a rig built for an older rig ABI cannot open this run's services: in ABI {} the DisplacementSample is {} bytes (ABI 4 added the rig's commanded force; ABI 3's was 56) and the ActuatorCommand {} bytes (ABI 3 added the controller's compensation; ABI 2's was 120), and iceoryx2 refuses the old types)",
                wait.as_secs_f64(),
                crate::ipc::messages::ABI_VERSION,
                std::mem::size_of::<crate::ipc::messages::DisplacementSample>(),
                std::mem::size_of::<crate::ipc::messages::ActuatorCommand>()
            ));
            return Ok(false);
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Clears a run with an external rig once its node is gone (waits up to 3 s for it, so
/// a rig finishing its last records is not cut off); a rig still connected keeps its
/// files, and they are reported.
fn clear_external_run(run_id: &str) -> Vec<PathBuf> {
    let t = Instant::now();
    while crate::ipc::count_nodes(run_id).unwrap_or(0) > 0 && t.elapsed() < Duration::from_secs(3) {
        let _ = crate::ipc::cleanup_dead_nodes(run_id);
        std::thread::sleep(Duration::from_millis(50));
    }
    if crate::ipc::count_nodes(run_id).unwrap_or(0) > 0 {
        eprintln!(
            "hil: warning: the external rig is still connected to run {run_id}; its files stay"
        );
        return crate::ipc::cleanup::files_with_prefix(&crate::ipc::file_prefix(run_id));
    }
    clear_run(run_id)
}

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

#[cfg(test)]
mod tests {
    use super::exit_is_orderly;

    #[test]
    fn a_process_that_ended_on_its_own_named_fault_did_not_die() {
        let faults = vec!["emulator: loop-unstable".to_string()];
        // The emulator tripped, then exited with code 3 before the rig's exit was seen.
        assert!(exit_is_orderly("emulator", Some(3), false, &faults));
        // Code 3 without its fault named, another code, or a signal: a death.
        assert!(!exit_is_orderly("controller", Some(3), false, &faults));
        assert!(!exit_is_orderly("emulator", Some(1), false, &faults));
        assert!(!exit_is_orderly("emulator", None, false, &faults));
        // At the run's end any exit with a code is orderly; a signal never is.
        assert!(exit_is_orderly("controller", Some(0), true, &[]));
        assert!(!exit_is_orderly("controller", None, true, &[]));
    }
}
