//! The link process (`fastemu link`, started by `hil --rig-link udp`): fastemu's end of
//! the UDP rig link. To the loop it is the rig: it publishes the rig's samples on the
//! displacement service and heartbeats as the rig, and forwards the controller's commands
//! and the orchestrator's run control to the rig as datagrams.
//!
//! Two threads: the receiving thread blocks on the socket and republishes each accepted
//! sample at once; the main thread sleeps on the controller's command event and sends
//! each command at once, then handles the handshake, run control, heartbeats and the
//! end. Nothing is fabricated: a rig that falls silent delivers no samples (the emulator
//! trips on stale samples), a link that dies delivers no commands (the rig holds on stale
//! commands); after `RIG_SILENCE` without a datagram the link ends the session itself.
//!
//! Must not: allocate, lock or log per datagram (beyond the one block iceoryx2 0.10 makes
//! inside each publish of what it forwards, `ipc::transport`).

use std::net::SocketAddr;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use hdrhistogram::Histogram;
use serde::Serialize;

use super::protocol::{CommandDatagram, ControlDatagram, Datagram, Reject, Side};
use super::socket::{open_link, LinkReceiver, LinkSender, Receive, ReceiveCounts};
use crate::hil::config::HilConfig;
use crate::hil::process::{
    install_termination_handler, poll_control, real_time_setup, termination_requested,
    wait_for_start_within, write_summary, Priority, ProcessError, HEARTBEAT_PERIOD_NS,
};
use crate::hil::report::latency::{histogram, percentiles, Percentiles};
use crate::ipc::messages::{
    process_id, rig_state, run_command, sample_status, DisplacementSample, Heartbeat,
    HEARTBEAT_READY,
};
use crate::ipc::messages::{ActuatorCommand, RunControl};
use crate::ipc::{In, IpcNode, Out, WakeListener};
use crate::rt::clock::monotonic_now_ns;

/// No datagram from the rig for this long after the start: the rig is gone, the link
/// ends the session (the emulator has long tripped on stale samples by then).
pub const RIG_SILENCE: Duration = Duration::from_secs(2);
/// How long the receiving thread blocks in one read.
const RECEIVE_TIMEOUT: Duration = Duration::from_millis(2);
/// `START` is repeated this often until the first sample arrives.
const START_REPEAT: Duration = Duration::from_millis(5);
/// The rig is started this much ahead of the loop's grid: its sample k then leaves about
/// this long before the grid instant k and, after the START's and the sample's trips
/// through the network stack, arrives around the emulator's wake-up for cycle k, not
/// just after the emulator stopped waiting for it (which costs a whole period).
const START_LEAD_NS: u64 = 60_000;
/// Every other run-control message is sent this many times (same control sequence).
const CONTROL_REPEATS: usize = 3;

/// What the link needs besides the configuration.
#[derive(Debug, Clone)]
pub struct LinkPlan {
    pub run_id: String,
    pub bind: SocketAddr,
    pub peer: SocketAddr,
    /// How long to wait for the rig's first status datagram.
    pub rig_wait: Duration,
}

/// The link's end-of-run summary (`link-summary.json`, and `link` in `hil --json`).
#[derive(Debug, Clone, Serialize)]
pub struct LinkSummary {
    pub transport: &'static str,
    pub bind: String,
    pub peer: String,
    pub link_version: u16,
    pub sent: super::socket::KindCounts,
    pub send_errors: u64,
    pub received: super::socket::KindCounts,
    pub rejected: serde_json::Value,
    pub rejected_total: u64,
    pub lost: super::socket::KindCounts,
    /// Sample datagrams lost / samples the rig numbered (up to the last received).
    pub sample_loss: f64,
    pub socket_errors: u64,
    /// Sample datagram one way (rig sent -> link received), ns: only when both ends read
    /// the same clock (a loopback peer whose times are plausible), else null.
    pub sample_one_way_ns: Option<Percentiles>,
    /// Command sent -> sample received back, minus the time the rig held the command
    /// before that sample (from the rig's echo), ns: the link's round trip including the
    /// wait until the rig reads its socket.
    pub round_trip_ns: Option<Percentiles>,
    /// When the rig sends its samples within the loop's period (rig send time minus the
    /// sample's grid instant, modulo the period), ns: only with a common clock.
    pub rig_phase_ns: Option<Percentiles>,
    /// `START` datagrams sent (repeats until the first sample).
    pub start_datagrams: u64,
    pub rig_finished: bool,
    pub rig_silent: bool,
    pub error: Option<String>,
}

/// State the receiving thread shares with the main thread.
#[derive(Debug, Default)]
struct Shared {
    stop: AtomicBool,
    ready: AtomicBool,
    /// The rig's period when it differs from the configuration's (0: fine).
    wrong_period_ns: AtomicU64,
    /// The link protocol version of a rig that speaks another one (0: none seen).
    peer_version: std::sync::atomic::AtomicU32,
    first_sample: AtomicBool,
    finished: AtomicBool,
    end_of_run_published: AtomicBool,
    rig_state: AtomicU32,
    rig_fault_code: AtomicU32,
    last_arrival_ns: AtomicU64,
    newest_sample_time_ns: AtomicU64,
    /// The loop's time origin (from the orchestrator's start).
    t0_ns: AtomicU64,
}

/// The link's threads run one SCHED_FIFO priority above the loops: they only wake for a
/// datagram or a command and pass it on in microseconds, and at the loops' priority they
/// would wait behind a loop spinning for exactly that sample. They sit on the
/// controller's CPUs (`[loop] controller_cpus`): the command path then hangs on one CPU,
/// the one the emulator's standby covers for, not on whichever the kernel picked (an
/// outside rig saw the link forward nothing for 49 ms while the controller published
/// and the emulator kept pace: what a held CPU under an unpinned thread gives).
fn link_rt_setup(cfg: &HilConfig) {
    real_time_setup(
        cfg,
        &cfg.loop_.controller_cpus,
        "link",
        Priority::EventDriven,
    );
}

/// What the receiving thread returns.
struct ReceiveResult {
    counts: ReceiveCounts,
    one_way: Histogram<u64>,
    round_trip: Histogram<u64>,
    phase: Histogram<u64>,
    same_clock: bool,
}

/// The receiving thread: rig datagrams -> the displacement service.
fn receive_loop(
    mut receiver: LinkReceiver,
    run_id: &str,
    period_ns: u64,
    loopback: bool,
    shared: &Shared,
) -> Result<ReceiveResult, ProcessError> {
    let node = IpcNode::new(run_id, "link_rx")?;
    let samples = node.displacement_out()?;
    let mut result = ReceiveResult {
        counts: ReceiveCounts::default(),
        one_way: histogram(),
        round_trip: histogram(),
        phase: histogram(),
        same_clock: false,
    };
    let mut clock_checked = false;
    let mut last_echo = 0u64;
    // The loop proper begins at START (the run's time zero known): the displacement port
    // connects to the emulator's then (`ipc::Connect`), outside it.
    let mut in_loop = None;
    // Also just before a sample is published: a receive already waiting when START came.
    let start_the_loop = |in_loop: &mut Option<crate::rt::pool::LoopSection>| {
        if in_loop.is_none() && shared.t0_ns.load(Ordering::Relaxed) != 0 {
            crate::ipc::Connect::connect(&samples);
            *in_loop = Some(crate::rt::pool::LoopSection::enter());
        }
    };
    while !shared.stop.load(Ordering::Relaxed) {
        start_the_loop(&mut in_loop);
        let r = match receiver.receive() {
            Receive::Accepted(r) => r,
            Receive::Rejected(Reject::BadContent) if receiver.wrong_period_ns != 0 => {
                shared
                    .wrong_period_ns
                    .store(receiver.wrong_period_ns, Ordering::Relaxed);
                continue;
            }
            Receive::Rejected(Reject::BadVersion) => {
                shared
                    .peer_version
                    .store(u32::from(receiver.peer_version), Ordering::Relaxed);
                continue;
            }
            _ => continue,
        };
        shared
            .last_arrival_ns
            .store(r.arrival_ns, Ordering::Relaxed);
        match r.datagram {
            Datagram::Status(s) => {
                shared.rig_state.store(s.rig_state, Ordering::Relaxed);
                shared
                    .rig_fault_code
                    .store(s.rig_fault_code, Ordering::Relaxed);
                if s.rig_state == HEARTBEAT_READY {
                    shared.ready.store(true, Ordering::Relaxed);
                }
                if s.rig_state == rig_state::FINISHED {
                    if !shared.end_of_run_published.swap(true, Ordering::Relaxed) {
                        // The end-of-run sample datagram was lost; the status says the same.
                        samples.publish(end_of_run_sample());
                    }
                    shared.finished.store(true, Ordering::Relaxed);
                }
            }
            Datagram::Sample(d) => {
                if !clock_checked {
                    // The rig's times are on this machine's clock only over loopback and
                    // when the first one is plausible (sent within the last second).
                    clock_checked = true;
                    let age = r.arrival_ns.wrapping_sub(r.header.sender_time_ns);
                    result.same_clock = loopback && age < 1_000_000_000;
                }
                // With a common clock the sample counts as published when the rig sent
                // it, so the loop's end-to-end latency includes the link.
                let published = if result.same_clock {
                    result
                        .one_way
                        .saturating_record(r.arrival_ns.saturating_sub(r.header.sender_time_ns));
                    r.header.sender_time_ns
                } else {
                    r.arrival_ns
                };
                start_the_loop(&mut in_loop);
                samples.publish(d.to_sample(published));
                if result.same_clock {
                    // Where in the loop's period the rig sends (its clock offset, plus its
                    // wake-up lateness), modulo the period.
                    let t0 = shared.t0_ns.load(Ordering::Relaxed);
                    let offset = r
                        .header
                        .sender_time_ns
                        .wrapping_sub(t0)
                        .wrapping_sub(d.rig_time_ns) as i64;
                    result
                        .phase
                        .saturating_record(offset.rem_euclid(period_ns as i64) as u64 + 1);
                }
                shared
                    .newest_sample_time_ns
                    .store(r.header.sender_time_ns, Ordering::Relaxed);
                shared.rig_state.store(d.rig_state, Ordering::Relaxed);
                shared
                    .rig_fault_code
                    .store(d.rig_fault_code, Ordering::Relaxed);
                shared.first_sample.store(true, Ordering::Relaxed);
                if d.echo_command_time_ns != 0 && d.echo_command_time_ns != last_echo {
                    last_echo = d.echo_command_time_ns;
                    let rtt = r
                        .arrival_ns
                        .saturating_sub(d.echo_command_time_ns)
                        .saturating_sub(d.echo_hold_ns);
                    result.round_trip.saturating_record(rtt.max(1));
                }
                if d.status == sample_status::END_OF_RUN {
                    shared.end_of_run_published.store(true, Ordering::Relaxed);
                    shared.finished.store(true, Ordering::Relaxed);
                }
            }
            _ => {}
        }
    }
    result.counts = receiver.counts;
    Ok(result)
}

/// Runs the link until the rig finishes, STOP, termination, or the rig falls silent.
pub fn run_link(
    cfg: &HilConfig,
    plan: &LinkPlan,
    out_dir: &Path,
) -> Result<LinkSummary, ProcessError> {
    install_termination_handler();
    std::fs::create_dir_all(out_dir)?;
    let (mut sender, mut receiver) =
        open_link(plan.bind, plan.peer, Side::Fastemu, Some(RECEIVE_TIMEOUT))
            .map_err(|e| ProcessError(e.to_string()))?;
    receiver.expect_period(cfg.loop_.period_ns);
    let node = IpcNode::new(&plan.run_id, "link")?;
    let ports = MainPorts {
        commands: node.command_in()?,
        listener: node.command_listener()?,
        heartbeat: node.heartbeat_out()?,
        control: node.control_in()?,
    };
    let shared = Arc::new(Shared::default());
    let period_ns = cfg.loop_.period_ns;
    let loopback = plan.peer.ip().is_loopback();
    let receiving = {
        let shared = shared.clone();
        let run_id = plan.run_id.clone();
        let cfg = cfg.clone();
        std::thread::Builder::new()
            .name("link-rx".into())
            .spawn(move || {
                link_rt_setup(&cfg);
                receive_loop(receiver, &run_id, period_ns, loopback, &shared)
            })
            .map_err(|e| ProcessError(format!("cannot start the link's receiving thread: {e}")))?
    };
    link_rt_setup(cfg);
    let mut summary = LinkSummary {
        transport: "udp",
        bind: plan.bind.to_string(),
        peer: plan.peer.to_string(),
        link_version: super::protocol::LINK_VERSION,
        sent: Default::default(),
        send_errors: 0,
        received: Default::default(),
        rejected: serde_json::Value::Null,
        rejected_total: 0,
        lost: Default::default(),
        sample_loss: 0.0,
        socket_errors: 0,
        sample_one_way_ns: None,
        round_trip_ns: None,
        rig_phase_ns: None,
        start_datagrams: 0,
        rig_finished: false,
        rig_silent: false,
        error: None,
    };
    let outcome = serve(cfg, plan, &shared, &mut sender, &ports, &mut summary);
    shared.stop.store(true, Ordering::Relaxed);
    let received = receiving
        .join()
        .map_err(|_| ProcessError("the link's receiving thread panicked".into()))??;
    if let Err(e) = &outcome {
        summary.error = Some(e.to_string());
    }
    let c = &received.counts;
    summary.sent = sender.sent;
    summary.send_errors = sender.send_errors;
    summary.received = c.accepted;
    summary.rejected = c.rejected_json();
    summary.rejected_total = c.rejected_total();
    summary.lost = c.lost;
    let numbered = c.accepted.sample + c.lost.sample;
    summary.sample_loss = if numbered > 0 {
        c.lost.sample as f64 / numbered as f64
    } else {
        0.0
    };
    summary.socket_errors = c.socket_errors;
    summary.sample_one_way_ns = received.same_clock.then(|| percentiles(&received.one_way));
    summary.round_trip_ns =
        (!received.round_trip.is_empty()).then(|| percentiles(&received.round_trip));
    summary.rig_phase_ns = received.same_clock.then(|| percentiles(&received.phase));
    summary.rig_finished = shared.finished.load(Ordering::Relaxed);
    write_summary(out_dir, "link", &summary)?;
    outcome.map(|()| summary)
}

/// The main thread's iceoryx2 ports.
struct MainPorts {
    commands: In<ActuatorCommand>,
    listener: WakeListener,
    heartbeat: Out<Heartbeat>,
    control: In<RunControl>,
}

/// The main thread's work: handshake, commands, run control, heartbeats, the end.
fn serve(
    cfg: &HilConfig,
    plan: &LinkPlan,
    shared: &Shared,
    sender: &mut LinkSender,
    ports: &MainPorts,
    summary: &mut LinkSummary,
) -> Result<(), ProcessError> {
    let control = &ports.control;
    let period_ns = cfg.loop_.period_ns;
    // 1. The rig announces itself with status datagrams.
    let waited_since = monotonic_now_ns();
    while !shared.ready.load(Ordering::Relaxed) {
        let version = shared.peer_version.load(Ordering::Relaxed);
        if version != 0 {
            return Err(ProcessError(format!(
                "the rig at {} speaks link protocol {version}; this fastemu speaks {} (include/fastemu_rig.h, docs/rig-interface.md): since protocol 2 every COMMAND carries the controller's compensation (184 bytes), which the rig must apply, and since protocol 3 every SAMPLE the rig's commanded force (96 bytes)",
                plan.peer,
                super::protocol::LINK_VERSION
            )));
        }
        let wrong = shared.wrong_period_ns.load(Ordering::Relaxed);
        if wrong != 0 {
            return Err(ProcessError(format!(
                "the rig at {} runs at a period of {wrong} ns, the configuration at {period_ns} ns ({} Hz)",
                plan.peer, cfg.loop_.rate_hz
            )));
        }
        if termination_requested() || poll_control(control).stop {
            return Err(ProcessError("stopped before the rig connected".into()));
        }
        if monotonic_now_ns() - waited_since > plan.rig_wait.as_nanos() as u64 {
            return Err(ProcessError(format!(
                "no status datagram from the rig at {} within {:?}",
                plan.peer, plan.rig_wait
            )));
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    serve_started(cfg, plan, shared, sender, ports, summary)
}

/// After the rig is ready: the start, then commands, run control and heartbeats.
fn serve_started(
    cfg: &HilConfig,
    plan: &LinkPlan,
    shared: &Shared,
    sender: &mut LinkSender,
    ports: &MainPorts,
    summary: &mut LinkSummary,
) -> Result<(), ProcessError> {
    let MainPorts {
        commands,
        listener,
        heartbeat,
        control,
    } = ports;
    let period_ns = cfg.loop_.period_ns;
    // 2. Ready as the rig; wait for the orchestrator's start.
    let start =
        wait_for_start_within(process_id::RIG, heartbeat, control, Duration::from_secs(60))?;
    shared.t0_ns.store(start.t0_ns, Ordering::Relaxed);
    // Every process's ports exist now: connect before the loop (`ipc::Connect`).
    crate::ipc::connect_all(&[commands, heartbeat, control]);
    let mut control_sequence = 1u64;
    let start_datagram = |now: u64| ControlDatagram {
        command: run_command::START,
        control_sequence: 1,
        start_delay_ns: start.t0_ns.saturating_sub(now + START_LEAD_NS),
        period_ns,
    };
    summary.start_datagrams += 1;
    sender.send_control(&start_datagram(monotonic_now_ns()));
    let mut next_start_ns = monotonic_now_ns() + START_REPEAT.as_nanos() as u64;
    let start_given_up_ns = start.t0_ns + 1_000_000_000;
    let mut next_heartbeat_ns = 0u64;
    let mut hb_seq = 0u64;
    let wait = Duration::from_nanos(cfg.controller.keepalive_ns.max(100_000));
    let send_control = |sender: &mut LinkSender, command: u32, seq: u64| {
        for _ in 0..CONTROL_REPEATS {
            sender.send_control(&ControlDatagram {
                command,
                control_sequence: seq,
                start_delay_ns: 0,
                period_ns,
            });
        }
    };
    // 3. Forward commands as they come; control, heartbeats and liveness around them.
    {
        let section = crate::rt::pool::LoopSection::enter();
        loop {
            listener.wait_for(wait);
            let echo = shared.newest_sample_time_ns.load(Ordering::Relaxed);
            commands.receive_each(|command| {
                sender.send_command(&CommandDatagram {
                    command,
                    echo_sample_time_ns: echo,
                });
            });
            let now = monotonic_now_ns();
            if !shared.first_sample.load(Ordering::Relaxed)
                && now >= next_start_ns
                && now < start_given_up_ns
            {
                summary.start_datagrams += 1;
                sender.send_control(&start_datagram(now));
                next_start_ns = now + START_REPEAT.as_nanos() as u64;
            }
            if termination_requested() {
                // The orchestrator is gone: ask the rig to hold (it would on the stale
                // commands anyway).
                control_sequence += 1;
                send_control(sender, run_command::HOLD, control_sequence);
                return Err(ProcessError("terminated: the rig was asked to hold".into()));
            }
            // The rig's state and fault, as the rig's heartbeat.
            let beat = |state: u32, sequence: u64| {
                heartbeat.publish(Heartbeat {
                    process: process_id::RIG,
                    state,
                    sequence,
                    time_ns: now,
                    fault_code: shared.rig_fault_code.load(Ordering::Relaxed),
                    reserved: 0,
                })
            };
            if shared.finished.load(Ordering::Relaxed) {
                summary.rig_finished = true;
                beat(rig_state::FINISHED, hb_seq);
                return Ok(());
            }
            let last = shared
                .last_arrival_ns
                .load(Ordering::Relaxed)
                .max(start.t0_ns);
            if now > last + RIG_SILENCE.as_nanos() as u64 {
                summary.rig_silent = true;
                // The message is not the loop's work.
                drop(section);
                return Err(ProcessError(format!(
                    "no datagram from the rig at {} for {:?}: the rig link is silent",
                    plan.peer, RIG_SILENCE
                )));
            }
            if now >= next_heartbeat_ns {
                next_heartbeat_ns = now + HEARTBEAT_PERIOD_NS;
                beat(shared.rig_state.load(Ordering::Relaxed), hb_seq);
                hb_seq += 1;
                let requests = poll_control(control);
                for (wanted, command) in [
                    (requests.hold, run_command::HOLD),
                    (requests.resume, run_command::RESUME),
                    (requests.end, run_command::END),
                    (requests.stop, run_command::STOP),
                ] {
                    if wanted {
                        control_sequence += 1;
                        send_control(sender, command, control_sequence);
                    }
                }
                if requests.stop {
                    return Ok(());
                }
            }
        }
    }
}

/// A displacement sample that ends the run, for an emulator whose rig's end-of-run
/// datagram was lost (the emulator reads the status before the sequence).
fn end_of_run_sample() -> DisplacementSample {
    DisplacementSample {
        sequence: u64::MAX,
        rig_time_ns: 0,
        publish_time_ns: monotonic_now_ns(),
        displacement_m: f64::NAN,
        actuator_force_n: f64::NAN,
        status: sample_status::END_OF_RUN,
        rig_state: rig_state::FINISHED,
        rig_fault_code: 0,
        reserved: 0,
        commanded_force_n: f64::NAN,
    }
}
