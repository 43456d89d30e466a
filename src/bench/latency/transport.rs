//! Ping-pong hop latency over five transports with the loop's real messages: iceoryx2
//! busy polling, iceoryx2 with an event listener's wake-up and a crossbeam channel between two
//! threads of this process (the lower bound) carry `DisplacementSample`; UDP on 127.0.0.1
//! and a Unix datagram socket carry the UDP rig link's datagrams (a sample out, a command
//! back), UDP through the link's own socket code (`crate::link`).
//!
//! The measuring process (`PeerSession`) spawns a copy of the current executable
//! (`fastemu bench latency-peer`, served by `serve_peer`) and drives it over a Unix
//! stream control socket with one line per round: `round <transport> <count>` ->
//! `go` -> `count` echoes -> `done`. Only the transport under test is active during a
//! round; between rounds the peer blocks on the control socket, so busy polling never
//! runs in the background of another transport's round.
//!
//! What is recorded: one-way hop = round-trip time / 2, ns, timed in the pinger with
//! `CLOCK_MONOTONIC` around send + receive of the echo. Receives time out after
//! `RECEIVE_TIMEOUT` so a dead peer fails the run instead of hanging it.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixDatagram, UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context};
use hdrhistogram::Histogram;

use crate::child::ChildGuard;
use crate::ipc::messages::{
    command_mode, controller_state, ActuatorCommand, DisplacementSample, LocalLaw,
};
use crate::ipc::pingpong::{IoxPingPong, IoxRole};
use crate::link::protocol::{
    decode, encode_command, encode_sample, CommandDatagram, Datagram, SampleDatagram, Side,
    COMMAND_BYTES, MAX_DATAGRAM_BYTES, SAMPLE_BYTES,
};
use crate::link::socket::{free_loopback_pair, open_link, LinkReceiver, LinkSender, Receive};
use crate::rt::clock::monotonic_now_ns;
use crate::rt::{apply_rt_setup, RtSetup};

/// How long one receive may wait before the run is declared broken.
pub const RECEIVE_TIMEOUT: Duration = Duration::from_secs(5);
/// How long the peer may take to start and to answer control lines.
const CONTROL_TIMEOUT: Duration = Duration::from_secs(30);

/// Bytes of the iceoryx2 and crossbeam message (`DisplacementSample`).
pub const MESSAGE_BYTES: usize = std::mem::size_of::<DisplacementSample>();
/// The socket transports carry the UDP rig link's datagrams: a sample datagram out, a
/// command datagram back (the link's own encoding, `crate::link::protocol`).
pub const SOCKET_BYTES: (usize, usize) = (SAMPLE_BYTES, COMMAND_BYTES);

/// A transport under test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Transport {
    /// iceoryx2 publish-subscribe, both sides busy-poll their subscriber.
    Iceoryx2,
    /// iceoryx2 publish-subscribe plus an event service; both sides sleep on its listener.
    Iceoryx2Event,
    /// UDP datagrams on 127.0.0.1, blocking receive.
    Udp,
    /// Unix domain datagram socket, blocking receive.
    Uds,
    /// crossbeam bounded channel between two threads of one process, busy polling.
    Crossbeam,
}

impl Transport {
    /// Every transport, in the order the rounds interleave them and the report lists them.
    pub const ALL: [Transport; 5] = [
        Transport::Iceoryx2,
        Transport::Iceoryx2Event,
        Transport::Udp,
        Transport::Uds,
        Transport::Crossbeam,
    ];

    /// Key in the JSON report, hlog tag and control-protocol name.
    pub fn key(self) -> &'static str {
        match self {
            Transport::Iceoryx2 => "iceoryx2",
            Transport::Iceoryx2Event => "iceoryx2_event",
            Transport::Udp => "udp",
            Transport::Uds => "uds",
            Transport::Crossbeam => "crossbeam",
        }
    }

    pub fn from_key(key: &str) -> Option<Transport> {
        Transport::ALL.into_iter().find(|t| t.key() == key)
    }

    /// One-line description for the report.
    pub fn description(self) -> &'static str {
        match self {
            Transport::Iceoryx2 => "iceoryx2 shared memory, busy polling, 2 processes",
            Transport::Iceoryx2Event => {
                "iceoryx2 shared memory + event, listener wake-up, 2 processes"
            }
            Transport::Udp => "UDP 127.0.0.1, blocking recv, 2 processes",
            Transport::Uds => "Unix datagram socket, blocking recv, 2 processes",
            Transport::Crossbeam => "crossbeam channel, busy polling, 2 threads (lower bound)",
        }
    }
}

/// The command datagram that answers `sample` (its sequence and send time echoed): what
/// fastemu's end of the link sends the rig.
fn answer(sample: &SampleDatagram, sample_time_ns: u64) -> CommandDatagram {
    CommandDatagram {
        command: ActuatorCommand {
            sequence: sample.sample_sequence,
            setpoint_sequence: sample.sample_sequence,
            sample_sequence: sample.sample_sequence,
            sample_publish_time_ns: 0,
            law: LocalLaw::constant(2.0e4),
            force_min_n: -5e3,
            force_max_n: 1.2e5,
            mode: command_mode::LAW,
            controller_state: controller_state::RUNNING,
            fault_code: 0,
            reserved: 0,
            compensation: crate::ipc::messages::Compensation::lead(2.52e-4, 2),
        },
        echo_sample_time_ns: sample_time_ns,
    }
}

/// The sample a command datagram answers (its sequence), for the ping loop.
fn answered(command: &CommandDatagram) -> DisplacementSample {
    SampleDatagram {
        sample_sequence: command.command.sample_sequence,
        rig_time_ns: 0,
        displacement_m: 0.0,
        actuator_force_n: 0.0,
        status: 0,
        rig_state: 0,
        rig_fault_code: 0,
        echo_command_time_ns: 0,
        echo_hold_ns: 0,
        commanded_force_n: 0.0,
    }
    .to_sample(0)
}

/// Receives on the link until a datagram of the wanted kind is accepted (rejected ones
/// are skipped); fails after `RECEIVE_TIMEOUT` of silence.
fn link_receive(receiver: &mut LinkReceiver, what: &str) -> anyhow::Result<Datagram> {
    let start_ns = monotonic_now_ns();
    loop {
        match receiver.receive() {
            Receive::Accepted(r) => return Ok(r.datagram),
            Receive::Rejected(reason) => bail!("{what}: datagram rejected ({reason})"),
            Receive::Nothing => {
                if monotonic_now_ns() - start_ns > RECEIVE_TIMEOUT.as_nanos() as u64 {
                    bail!("{what}: nothing received for {RECEIVE_TIMEOUT:?}");
                }
            }
        }
    }
}

/// Busy-polls `poll` until it yields a sample; fails after `RECEIVE_TIMEOUT`.
/// `yield_while_spinning` gives the CPU away on every miss (for two spinners sharing
/// one CPU, where a pure spin would only measure the scheduler's time slice).
#[inline]
fn spin_receive<E: std::fmt::Display>(
    mut poll: impl FnMut() -> Result<Option<DisplacementSample>, E>,
    yield_while_spinning: bool,
    what: &str,
) -> anyhow::Result<DisplacementSample> {
    let start_ns = monotonic_now_ns();
    let mut misses: u32 = 0;
    loop {
        match poll() {
            Ok(Some(sample)) => return Ok(sample),
            Ok(None) => {}
            Err(e) => bail!("{what}: {e}"),
        }
        misses = misses.wrapping_add(1);
        if yield_while_spinning {
            std::thread::yield_now();
        } else {
            std::hint::spin_loop();
        }
        if misses.is_multiple_of(4096)
            && monotonic_now_ns() - start_ns > RECEIVE_TIMEOUT.as_nanos() as u64
        {
            bail!("{what}: nothing received for {RECEIVE_TIMEOUT:?}");
        }
    }
}

/// Sends `n_warmup + n_measured` pings through `exchange` (send one, return the echo)
/// and records the measured ones' RTT/2 into `hop_ns`.
#[inline]
fn ping_loop(
    n_warmup: u64,
    n_measured: u64,
    hop_ns: &mut Histogram<u64>,
    mut exchange: impl FnMut(DisplacementSample) -> anyhow::Result<DisplacementSample>,
) -> anyhow::Result<()> {
    for sequence in 0..n_warmup + n_measured {
        let sent_ns = monotonic_now_ns();
        let ping = DisplacementSample {
            sequence,
            rig_time_ns: sequence,
            publish_time_ns: sent_ns,
            displacement_m: 4e-4,
            actuator_force_n: 0.0,
            status: 0,
            rig_state: 0,
            rig_fault_code: 0,
            reserved: 0,
            commanded_force_n: 0.0,
        };
        let echo = exchange(ping)?;
        let round_trip_ns = monotonic_now_ns() - sent_ns;
        ensure!(
            echo.sequence == sequence,
            "echo out of order: sent {sequence}, got {}",
            echo.sequence
        );
        if sequence >= n_warmup {
            hop_ns.saturating_record(round_trip_ns.div_ceil(2));
        }
    }
    Ok(())
}

/// Echoes `count` samples: `receive` one, `send` it back unchanged.
#[inline]
fn echo_loop(
    count: u64,
    mut receive: impl FnMut() -> anyhow::Result<DisplacementSample>,
    mut send: impl FnMut(DisplacementSample) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    for _ in 0..count {
        let sample = receive()?;
        send(sample)?;
    }
    Ok(())
}

/// Receives one datagram on a Unix socket and decodes it for `side`.
fn uds_receive(
    uds: &UnixDatagram,
    buf: &mut [u8; MAX_DATAGRAM_BYTES + 1],
    side: Side,
    what: &str,
) -> anyhow::Result<Datagram> {
    let len = uds.recv(buf).with_context(|| format!("{what} receive"))?;
    decode(&buf[..len], side)
        .map(|(_, d)| d)
        .map_err(|reason| anyhow::anyhow!("{what}: datagram rejected ({reason})"))
}

fn uds_send(uds: &UnixDatagram, bytes: &[u8], what: &str) -> anyhow::Result<()> {
    let len = uds.send(bytes).with_context(|| format!("{what} send"))?;
    ensure!(len == bytes.len(), "{what}: sent {len} bytes");
    Ok(())
}

/// Crossbeam round: this thread pings, a scoped thread (set up with `echo_setup`)
/// echoes. Returns the echo thread's setup warnings.
pub fn crossbeam_round(
    n_warmup: u64,
    n_measured: u64,
    hop_ns: &mut Histogram<u64>,
    echo_setup: &RtSetup,
    yield_while_spinning: bool,
) -> anyhow::Result<Vec<String>> {
    use crossbeam::channel::{bounded, TryRecvError};
    let (ping_tx, ping_rx) = bounded::<DisplacementSample>(1);
    let (pong_tx, pong_rx) = bounded::<DisplacementSample>(1);
    let total = n_warmup + n_measured;
    let poll = |rx: &crossbeam::channel::Receiver<DisplacementSample>| match rx.try_recv() {
        Ok(sample) => Ok(Some(sample)),
        Err(TryRecvError::Empty) => Ok(None),
        Err(TryRecvError::Disconnected) => Err("channel closed"),
    };
    // The echo thread inherits this thread's CPU mask and SCHED_FIFO priority: until it
    // has moved itself, a spinning pinger on the same CPU at the same priority would
    // never let it run. So the pinger blocks until the echo thread is set up.
    let echo_ready = std::sync::Barrier::new(2);
    std::thread::scope(|scope| {
        let echo_ready = &echo_ready;
        let echo = scope.spawn(move || -> anyhow::Result<Vec<String>> {
            let warnings = apply_rt_setup(echo_setup);
            echo_ready.wait();
            echo_loop(
                total,
                || spin_receive(|| poll(&ping_rx), yield_while_spinning, "crossbeam echo"),
                |sample| pong_tx.send(sample).context("crossbeam echo send"),
            )?;
            Ok(warnings)
        });
        echo_ready.wait();
        let pinged = ping_loop(n_warmup, n_measured, hop_ns, |ping| {
            ping_tx.send(ping).context("crossbeam send")?;
            spin_receive(|| poll(&pong_rx), yield_while_spinning, "crossbeam")
        });
        // Dropping the sender unblocks the echo thread if pinging failed midway.
        drop(ping_tx);
        let echoed = echo
            .join()
            .map_err(|_| anyhow::anyhow!("crossbeam echo thread panicked"))?;
        pinged?;
        echoed
    })
}

/// A directory for this run's sockets, removed on drop.
#[derive(Debug)]
pub struct RunDir {
    path: PathBuf,
}

impl RunDir {
    /// Creates `<tmp>/fastemu-latency-<unique>`, where `unique` starts with this
    /// process's pid; first removes such directories left by runs whose process died
    /// without unwinding (e.g. `kill -9`).
    pub fn create(unique: &str) -> anyhow::Result<RunDir> {
        remove_dead_run_dirs();
        let path = std::env::temp_dir().join(format!("fastemu-latency-{unique}"));
        std::fs::create_dir_all(&path)
            .with_context(|| format!("cannot create {}", path.display()))?;
        Ok(RunDir { path })
    }
    pub fn path(&self) -> &Path {
        &self.path
    }
}

fn remove_dead_run_dirs() {
    let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
        return;
    };
    for entry in entries.filter_map(Result::ok) {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = name
            .strip_prefix("fastemu-latency-")
            .and_then(|rest| rest.split('_').next())
            .and_then(|pid| pid.parse::<libc::pid_t>().ok())
        else {
            continue;
        };
        // SAFETY: signal 0 only checks whether the process exists.
        let dead = unsafe { libc::kill(pid, 0) } != 0
            && std::io::Error::last_os_error().raw_os_error() == Some(libc::ESRCH);
        if dead {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
}

impl Drop for RunDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

/// What the peer process needs to know (passed on its command line).
#[derive(Debug, Clone)]
pub struct PeerConfig {
    pub control_path: PathBuf,
    pub iox_prefix: String,
    pub parent_udp_port: u16,
    pub peer_udp_port: u16,
    pub parent_uds_path: PathBuf,
    pub peer_uds_path: PathBuf,
    pub rt: RtSetup,
    pub yield_while_spinning: bool,
}

/// The measuring side: the spawned peer, the control socket and this process's end of
/// every inter-process transport.
pub struct PeerSession {
    control_reader: BufReader<UnixStream>,
    control_writer: UnixStream,
    iox: IoxPingPong,
    udp: (LinkSender, LinkReceiver),
    uds: UnixDatagram,
    yield_while_spinning: bool,
    /// Warnings the peer reported for its real-time setup.
    pub peer_warnings: Vec<String>,
    // Dropped after the sockets above: killing the peer last keeps its errors readable.
    peer: ChildGuard,
    _dir: RunDir,
    // Dropped after both ends' iceoryx2 nodes are gone: removes every file of the session.
    _iox_files: IoxFiles,
}

/// The iceoryx2 files of a session (`IoxPingPong` names them with its prefix): removed on
/// drop, so a bench leaves none behind, iceoryx2's management files included.
struct IoxFiles(String);

impl Drop for IoxFiles {
    fn drop(&mut self) {
        crate::ipc::cleanup::clear_run(&self.0);
    }
}

impl PeerSession {
    /// Creates this side's endpoints, spawns `exe bench latency-peer ...` with
    /// `peer_rt`, and waits until the peer reports ready.
    pub fn start(
        exe: &Path,
        unique: &str,
        peer_rt: &RtSetup,
        yield_while_spinning: bool,
    ) -> anyhow::Result<PeerSession> {
        let dir = RunDir::create(unique)?;
        let iox_prefix = format!("fastemu_latency_{unique}");
        let iox_files = IoxFiles(iox_prefix.clone());
        let iox = IoxPingPong::new(&iox_prefix, IoxRole::Pinger)?;
        // The pinger is the rig's end of a UDP rig link, the peer fastemu's end.
        let (parent_udp, peer_udp) = free_loopback_pair()?;
        let udp = open_link(parent_udp, peer_udp, Side::Rig, Some(RECEIVE_TIMEOUT))?;
        let parent_udp_port = parent_udp.port();
        let parent_uds_path = dir.path().join("main.sock");
        let peer_uds_path = dir.path().join("peer.sock");
        let control_path = dir.path().join("control.sock");
        let uds = UnixDatagram::bind(&parent_uds_path)
            .with_context(|| format!("binding {}", parent_uds_path.display()))?;
        let control_listener = UnixListener::bind(&control_path)
            .with_context(|| format!("binding {}", control_path.display()))?;
        control_listener.set_nonblocking(true)?;

        let config = PeerConfig {
            control_path,
            iox_prefix,
            parent_udp_port,
            peer_udp_port: peer_udp.port(),
            parent_uds_path,
            peer_uds_path: peer_uds_path.clone(),
            rt: peer_rt.clone(),
            yield_while_spinning,
        };
        let mut command = Command::new(exe);
        command
            .args(peer_command_args(&config))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit());
        let mut peer = ChildGuard::new(
            command
                .spawn()
                .with_context(|| format!("cannot spawn peer {}", exe.display()))?,
        );

        let started = Instant::now();
        let control = loop {
            match control_listener.accept() {
                Ok((stream, _)) => break stream,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    if let Some(status) = peer.try_wait()? {
                        bail!("latency peer exited before connecting ({status})");
                    }
                    ensure!(
                        started.elapsed() < CONTROL_TIMEOUT,
                        "latency peer did not connect within {CONTROL_TIMEOUT:?}"
                    );
                    std::thread::sleep(Duration::from_millis(2));
                }
                Err(e) => return Err(e).context("accepting the peer's control connection"),
            }
        };
        control.set_nonblocking(false)?;
        control.set_read_timeout(Some(CONTROL_TIMEOUT))?;
        let control_writer = control.try_clone()?;
        let mut session_reader = BufReader::new(control);
        let mut peer_warnings = Vec::new();
        loop {
            let line = read_control_line(&mut session_reader)?;
            if let Some(warning) = line.strip_prefix("warn ") {
                peer_warnings.push(warning.to_string());
            } else if let Some(port) = line.strip_prefix("ready ") {
                ensure!(
                    port == peer_udp.port().to_string(),
                    "peer bound UDP port `{port}`, expected {}",
                    peer_udp.port()
                );
                break;
            } else if let Some(error) = line.strip_prefix("error ") {
                bail!("latency peer failed to start: {error}");
            } else {
                bail!("unexpected line from latency peer: `{line}`");
            }
        }
        uds.connect(&peer_uds_path)
            .with_context(|| format!("connecting to {}", peer_uds_path.display()))?;
        uds.set_read_timeout(Some(RECEIVE_TIMEOUT))?;
        Ok(PeerSession {
            control_reader: session_reader,
            control_writer,
            iox,
            udp,
            uds,
            yield_while_spinning,
            peer_warnings,
            peer,
            _dir: dir,
            _iox_files: iox_files,
        })
    }

    /// Runs one round of `transport` (not crossbeam, which needs no peer).
    pub fn round(
        &mut self,
        transport: Transport,
        n_warmup: u64,
        n_measured: u64,
        hop_ns: &mut Histogram<u64>,
    ) -> anyhow::Result<()> {
        ensure!(
            transport != Transport::Crossbeam,
            "crossbeam rounds run in-process (crossbeam_round)"
        );
        let total = n_warmup + n_measured;
        writeln!(self.control_writer, "round {} {total}", transport.key())?;
        let line = read_control_line(&mut self.control_reader)?;
        ensure!(line == "go", "peer answered `{line}` to round start");
        let yield_spin = self.yield_while_spinning;
        match transport {
            Transport::Iceoryx2 => {
                let iox = &self.iox;
                ping_loop(n_warmup, n_measured, hop_ns, |ping| {
                    iox.send_busy(ping)?;
                    spin_receive(|| iox.try_receive_busy(), yield_spin, "iceoryx2")
                })?;
            }
            Transport::Iceoryx2Event => {
                let iox = &self.iox;
                iox.with_event_waiter(|waiter| {
                    ping_loop(n_warmup, n_measured, hop_ns, |ping| {
                        iox.send_event(ping)?;
                        waiter.receive(RECEIVE_TIMEOUT)?.with_context(|| {
                            format!("iceoryx2_event: no echo within {RECEIVE_TIMEOUT:?}")
                        })
                    })
                })??;
            }
            Transport::Udp => {
                let (sender, receiver) = &mut self.udp;
                ping_loop(n_warmup, n_measured, hop_ns, |ping| {
                    sender.send_sample(&SampleDatagram::of(&ping, 0, 0));
                    match link_receive(receiver, "udp")? {
                        Datagram::Command(c) => Ok(answered(&c)),
                        other => bail!("udp: expected a command datagram, got {other:?}"),
                    }
                })?;
            }
            Transport::Uds => {
                let uds = &self.uds;
                let mut out = [0u8; MAX_DATAGRAM_BYTES];
                let mut buf = [0u8; MAX_DATAGRAM_BYTES + 1];
                ping_loop(n_warmup, n_measured, hop_ns, |ping| {
                    let n = encode_sample(
                        &mut out,
                        ping.sequence,
                        ping.publish_time_ns,
                        &SampleDatagram::of(&ping, 0, 0),
                    );
                    uds_send(uds, &out[..n], "uds")?;
                    match uds_receive(uds, &mut buf, Side::Rig, "uds")? {
                        Datagram::Command(c) => Ok(answered(&c)),
                        other => bail!("uds: expected a command datagram, got {other:?}"),
                    }
                })?;
            }
            Transport::Crossbeam => unreachable!("checked above"),
        }
        let line = read_control_line(&mut self.control_reader)?;
        ensure!(line == "done", "peer answered `{line}` at round end");
        Ok(())
    }

    /// Asks the peer to exit and reaps it (killed if it does not exit within 2 s).
    pub fn finish(mut self) -> anyhow::Result<()> {
        let _ = writeln!(self.control_writer, "quit");
        let status = self.peer.wait_timeout(Duration::from_secs(2))?;
        match status {
            Some(s) if s.success() => Ok(()),
            Some(s) => bail!("latency peer (pid {}) exited with {s}", self.peer.id()),
            None => bail!("latency peer did not exit when asked; killed"),
        }
    }
}

fn read_control_line(reader: &mut BufReader<UnixStream>) -> anyhow::Result<String> {
    let mut line = String::new();
    let n = reader
        .read_line(&mut line)
        .context("reading the latency peer's control socket")?;
    ensure!(n > 0, "latency peer closed its control connection");
    Ok(line.trim_end().to_string())
}

/// Command-line arguments of the hidden `bench latency-peer` subcommand for `config`.
pub fn peer_command_args(config: &PeerConfig) -> Vec<String> {
    let mut args = vec![
        "bench".to_string(),
        "latency-peer".to_string(),
        "--control".to_string(),
        config.control_path.display().to_string(),
        "--iox-prefix".to_string(),
        config.iox_prefix.clone(),
        "--parent-udp-port".to_string(),
        config.parent_udp_port.to_string(),
        "--peer-udp-port".to_string(),
        config.peer_udp_port.to_string(),
        "--parent-uds".to_string(),
        config.parent_uds_path.display().to_string(),
        "--peer-uds".to_string(),
        config.peer_uds_path.display().to_string(),
    ];
    if !config.rt.cpus.is_empty() {
        let cpus: Vec<String> = config.rt.cpus.iter().map(usize::to_string).collect();
        args.push("--pin".to_string());
        args.push(cpus.join(","));
    }
    if let Some(priority) = config.rt.fifo_priority {
        args.push("--priority".to_string());
        args.push(priority.to_string());
    }
    if config.rt.lock_memory {
        args.push("--lock-memory".to_string());
    }
    if config.yield_while_spinning {
        args.push("--yield-spin".to_string());
    }
    args
}

/// The peer process: applies its real-time setup, opens its ends of the transports,
/// then echoes rounds as the control socket asks until told to quit (or the socket
/// closes). Dies with its parent (`PR_SET_PDEATHSIG`).
pub fn serve_peer(config: &PeerConfig) -> anyhow::Result<()> {
    // SAFETY: plain prctl with constant arguments; it only affects this process.
    unsafe { libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) };
    crate::ipc::pingpong::quiet_iceoryx2_logging();
    let control = UnixStream::connect(&config.control_path)
        .with_context(|| format!("connecting to {}", config.control_path.display()))?;
    let mut writer = control.try_clone()?;
    let mut reader = BufReader::new(control);
    for warning in apply_rt_setup(&config.rt) {
        writeln!(writer, "warn {warning}")?;
    }
    let mut endpoints = match PeerEndpoints::open(config) {
        Ok(e) => e,
        Err(e) => {
            let _ = writeln!(writer, "error {e:#}");
            return Err(e);
        }
    };
    writeln!(writer, "ready {}", endpoints.udp.0.local_addr()?.port())?;
    let yield_spin = config.yield_while_spinning;
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line)? == 0 {
            return Ok(());
        }
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["quit"] => return Ok(()),
            ["round", key, count] => {
                let transport = Transport::from_key(key)
                    .with_context(|| format!("unknown transport `{key}`"))?;
                let count: u64 = count.parse().context("bad round count")?;
                endpoints.echo_round(transport, count, yield_spin, &mut writer)?;
                writeln!(writer, "done")?;
            }
            _ => bail!("unexpected control line `{}`", line.trim_end()),
        }
    }
}

struct PeerEndpoints {
    iox: IoxPingPong,
    udp: (LinkSender, LinkReceiver),
    uds: UnixDatagram,
}

impl PeerEndpoints {
    fn open(config: &PeerConfig) -> anyhow::Result<PeerEndpoints> {
        let iox = IoxPingPong::new(&config.iox_prefix, IoxRole::Ponger)?;
        let loopback = |port: u16| std::net::SocketAddr::from(([127, 0, 0, 1], port));
        let udp = open_link(
            loopback(config.peer_udp_port),
            loopback(config.parent_udp_port),
            Side::Fastemu,
            Some(RECEIVE_TIMEOUT),
        )?;
        let uds = UnixDatagram::bind(&config.peer_uds_path)
            .with_context(|| format!("binding {}", config.peer_uds_path.display()))?;
        uds.connect(&config.parent_uds_path)
            .with_context(|| format!("connecting to {}", config.parent_uds_path.display()))?;
        uds.set_read_timeout(Some(RECEIVE_TIMEOUT))?;
        Ok(PeerEndpoints { iox, udp, uds })
    }

    fn echo_round(
        &mut self,
        transport: Transport,
        count: u64,
        yield_spin: bool,
        control: &mut UnixStream,
    ) -> anyhow::Result<()> {
        match transport {
            Transport::Iceoryx2 => {
                writeln!(control, "go")?;
                echo_loop(
                    count,
                    || spin_receive(|| self.iox.try_receive_busy(), yield_spin, "iceoryx2 echo"),
                    |s| Ok(self.iox.send_busy(s)?),
                )
            }
            Transport::Iceoryx2Event => self.iox.with_event_waiter(|waiter| {
                writeln!(control, "go")?;
                echo_loop(
                    count,
                    || {
                        waiter.receive(RECEIVE_TIMEOUT)?.with_context(|| {
                            format!("iceoryx2_event echo: no ping within {RECEIVE_TIMEOUT:?}")
                        })
                    },
                    |s| Ok(self.iox.send_event(s)?),
                )
            })?,
            Transport::Udp => {
                writeln!(control, "go")?;
                let (sender, receiver) = &mut self.udp;
                for _ in 0..count {
                    match link_receive(receiver, "udp echo")? {
                        Datagram::Sample(d) => {
                            sender.send_command(&answer(&d, 0));
                        }
                        other => bail!("udp echo: expected a sample datagram, got {other:?}"),
                    }
                }
                Ok(())
            }
            Transport::Uds => {
                writeln!(control, "go")?;
                let mut out = [0u8; MAX_DATAGRAM_BYTES];
                let mut buf = [0u8; MAX_DATAGRAM_BYTES + 1];
                for i in 0..count {
                    match uds_receive(&self.uds, &mut buf, Side::Fastemu, "uds echo")? {
                        Datagram::Sample(d) => {
                            let n = encode_command(&mut out, i, 0, &answer(&d, 0));
                            uds_send(&self.uds, &out[..n], "uds echo")?;
                        }
                        other => bail!("uds echo: expected a sample datagram, got {other:?}"),
                    }
                }
                Ok(())
            }
            Transport::Crossbeam => bail!("crossbeam rounds need no peer"),
        }
    }
}
