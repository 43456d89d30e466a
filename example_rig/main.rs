//! A small external rig written from `include/fastemu_rig.h` and the README alone: its own
//! `#[repr(C)]` messages (none of fastemu's types), the iceoryx2 crate for
//! `--ipc RUN_ID` (rig ABI 4) and std's UDP socket for `--udp BIND PEER` (link protocol 3).
//!
//! The "hardware" is a mass on the actuator (`m x'' = P(t) - F - c x'`, P the external
//! load programme: preload + harmonic, F the actuator force), integrated in sub-steps; its
//! sensor is exact. Every period it does what the header's section 2 says: send the
//! sample, take commands, apply the local law with its own measurement (lead-extrapolated
//! over half a period of zero-order hold), hold position on HOLD commands or when commands
//! go stale, obey run control, and end the session with an end-of-run sample.
//!
//! Its loop allocates nothing of its own (fixed datagram buffers, storage set up before
//! the loop) and says in its closing line how many allocations it counted (over
//! iceoryx2, iceoryx2 0.10's one per publish).
//!
//! Simplifications a real rig would not make: the sensor is exact, the actuator ideal
//! (no lag), a resume from an operator hold does not blend.
//!
//! Run: `fastemu hil --rig external --run-id lab1` then `example_rig --ipc lab1`; or
//! `fastemu hil --rig external --rig-link udp --link-bind 127.0.0.1:50000 --link-peer
//! 127.0.0.1:50001` then `example_rig --udp 127.0.0.1:50001 127.0.0.1:50000`.
//! Options: --rate-hz 4096 --duration-s 6 --mass-kg 60.16 --damping-ns-per-m 3600
//! --preload-n 0 --amplitude-n 4000 --frequency-hz 2 --stale-periods 205.

const USAGE: &str = "\
usage: example_rig (--ipc RUN_ID | --udp BIND_IP:PORT PEER_IP:PORT) [options]
  an external rig from include/fastemu_rig.h: a mass on an ideal actuator
  --ipc RUN_ID          the run's iceoryx2 services (fastemu hil --rig external --run-id RUN_ID)
  --udp BIND PEER       the UDP rig link (hil's --link-peer is BIND, its --link-bind PEER)
  --rate-hz 4096  --duration-s 6  --mass-kg 60.16  --damping-ns-per-m 3600
  --preload-n 0  --amplitude-n 4000  --frequency-hz 2  --stale-periods 205";

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::net::{SocketAddr, UdpSocket};
use std::time::Duration;

use iceoryx2::prelude::*;

// ---- the loop allocates nothing: counted -------------------------------------------------

/// Counts the allocations its thread makes while `COUNTING` is set (the loop's), so the
/// closing line can say the loop made none (a real-time loop does not allocate: the
/// allocator may take a lock or a page fault). `const` thread-locals without destructors:
/// touching them never allocates.
struct CountingAllocator;

thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

fn count_allocation() {
    if COUNTING.try_with(Cell::get).unwrap_or(false) {
        let _ = ALLOCATIONS.try_with(|n| n.set(n.get() + 1));
    }
}

// SAFETY: forwards to the system allocator unchanged; counting touches only `const`
// thread-locals.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count_allocation();
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        count_allocation();
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count_allocation();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

// ---- the messages, as fastemu_rig.h declares them ---------------------------------------

/// Header: FASTEMU_LINK_VERSION.
const LINK_VERSION: u16 = 3;
const HEARTBEAT_READY: u32 = 100;
const RIG_RUNNING: u32 = 1;
const RIG_HOLD: u32 = 2;
const RIG_FINISHED: u32 = 3;
const RIG_UNLOAD: u32 = 4;
const RIG_OPERATOR_HOLD: u32 = 5;
const SAMPLE_OK: u32 = 0;
const SAMPLE_END_OF_RUN: u32 = 2;
const MODE_FORCE: u32 = 0;
const MODE_LAW: u32 = 1;
const MODE_HOLD: u32 = 2;
const MODE_HOLD_UNLOAD: u32 = 3;
const RUN_START: u32 = 1;
const RUN_STOP: u32 = 2;
const RUN_HOLD: u32 = 3;
const RUN_RESUME: u32 = 4;
const RUN_END: u32 = 5;
const FAULT_COMMANDS_STALE: u32 = 20;
const FAULT_HOLD_REQUESTED: u32 = 22;

#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("fastemu::DisplacementSample")]
#[repr(C)]
struct Sample {
    sequence: u64,
    rig_time_ns: u64,
    publish_time_ns: u64,
    displacement_m: f64,
    actuator_force_n: f64,
    status: u32,
    rig_state: u32,
    rig_fault_code: u32,
    reserved: u32,
    commanded_force_n: f64,
}

#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("fastemu::LocalLaw")]
#[repr(C)]
struct Law {
    force_n: f64,
    displacement_m: f64,
    velocity_m_per_s: f64,
    stiffness_n_per_m: f64,
    damping_ns_per_m: f64,
    force_rate_n_per_s: f64,
    stiffness_slope_n_per_m2: f64,
}

#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("fastemu::ActuatorCommand")]
#[repr(C)]
struct Command {
    sequence: u64,
    setpoint_sequence: u64,
    sample_sequence: u64,
    sample_publish_time_ns: u64,
    law: Law,
    force_min_n: f64,
    force_max_n: f64,
    mode: u32,
    controller_state: u32,
    fault_code: u32,
    reserved: u32,
    compensation: Compensation,
}

/// Header, `fastemu_compensation`: how a LAW command becomes the force command.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("fastemu::Compensation")]
#[repr(C)]
struct Compensation {
    lead_s: f64,
    added_damping_ns_per_m: f64,
    added_damping_corner_hz: f64,
    gain: f64,
    lead_order: u32,
    reserved: u32,
}

impl Compensation {
    /// Header, `fastemu_compensation_ok`.
    fn ok(&self) -> bool {
        (0.0..=0.02).contains(&self.lead_s)
            && self.added_damping_ns_per_m >= 0.0
            && self.added_damping_ns_per_m.is_finite()
            && self.added_damping_corner_hz >= 0.0
            && self.added_damping_corner_hz.is_finite()
            && (0.25..=4.0).contains(&self.gain)
            && self.lead_order <= 3
    }
}

impl Command {
    /// Header, section 2b: a known mode; for FORCE and LAW a finite law and finite,
    /// ordered force limits.
    fn content_ok(&self) -> bool {
        let l = &self.law;
        match self.mode {
            MODE_HOLD | MODE_HOLD_UNLOAD => true,
            MODE_FORCE | MODE_LAW => {
                [
                    l.force_n,
                    l.displacement_m,
                    l.velocity_m_per_s,
                    l.stiffness_n_per_m,
                    l.damping_ns_per_m,
                    l.force_rate_n_per_s,
                    l.stiffness_slope_n_per_m2,
                    self.force_min_n,
                    self.force_max_n,
                ]
                .iter()
                .all(|x| x.is_finite())
                    && self.force_min_n <= self.force_max_n
                    && (self.mode == MODE_FORCE || self.compensation.ok())
            }
            _ => false,
        }
    }
}

#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("fastemu::Heartbeat")]
#[repr(C)]
struct Heartbeat {
    process: u32,
    state: u32,
    sequence: u64,
    time_ns: u64,
    fault_code: u32,
    reserved: u32,
}

#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("fastemu::RunControl")]
#[repr(C)]
struct RunControl {
    sequence: u64,
    start_time_ns: u64,
    start_unix_ns: u64,
    command: u32,
    reserved: u32,
}

fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: a valid timespec to fill.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

// ---- the two transports -----------------------------------------------------------------

/// What the rig needs from either transport.
trait Transport {
    /// Announces readiness until START; returns the monotonic time of sample 0.
    fn wait_for_start(&mut self, period_ns: u64) -> Result<u64, String>;
    fn send(&mut self, sample: &Sample);
    fn commands(&mut self, out: &mut Vec<Command>);
    /// Run commands received since the last call.
    fn control(&mut self, out: &mut Vec<u32>);
    fn heartbeat(&mut self, state: u32, fault_code: u32);
    fn finish(&mut self, last: &Sample);
}

struct Ipc {
    _node: Node<ipc::Service>,
    samples: iceoryx2::port::publisher::Publisher<ipc::Service, Sample, ()>,
    commands: iceoryx2::port::subscriber::Subscriber<ipc::Service, Command, ()>,
    heartbeats: iceoryx2::port::publisher::Publisher<ipc::Service, Heartbeat, ()>,
    control: iceoryx2::port::subscriber::Subscriber<ipc::Service, RunControl, ()>,
    heartbeat_seq: u64,
}

fn err(what: &str, x: impl std::fmt::Debug) -> String {
    format!("iceoryx2: {what}: {x:?}")
}

impl Ipc {
    fn open(run_id: &str) -> Result<Ipc, String> {
        let mut config = iceoryx2::config::Config::default();
        config.global.prefix =
            FileName::new(format!("{run_id}_").as_bytes()).map_err(|x| err("prefix", x))?;
        let node = NodeBuilder::new()
            .config(&config)
            .create::<ipc::Service>()
            .map_err(|x| err("node", x))?;
        let name = |s: &str| -> Result<ServiceName, String> {
            ServiceName::new(&format!("fastemu/{run_id}/{s}")).map_err(|x| err("service name", x))
        };
        // open_or_create with the header's settings: works whether hil or this rig
        // starts first.
        macro_rules! service {
            ($t:ty, $name:literal, $history:expr, $buffer:expr, $pubs:expr, $subs:expr) => {
                node.service_builder(&name($name)?)
                    .publish_subscribe::<$t>()
                    .history_size($history)
                    .subscriber_max_buffer_size($buffer)
                    .enable_safe_overflow(true)
                    .max_publishers($pubs)
                    .max_subscribers($subs)
                    .max_nodes(8)
                    .open_or_create()
                    .map_err(|x| err($name, x))?
            };
        }
        let samples = service!(Sample, "displacement", 0, 4096, 1, 4)
            .publisher_builder()
            .create()
            .map_err(|x| err("displacement publisher", x))?;
        let commands = service!(Command, "command", 0, 8, 1, 4)
            .subscriber_builder()
            .create()
            .map_err(|x| err("command subscriber", x))?;
        let heartbeats = service!(Heartbeat, "heartbeat", 0, 64, 4, 6)
            .publisher_builder()
            .create()
            .map_err(|x| err("heartbeat publisher", x))?;
        let control = service!(RunControl, "control", 1, 8, 4, 4)
            .subscriber_builder()
            .create()
            .map_err(|x| err("control subscriber", x))?;
        Ok(Ipc {
            _node: node,
            samples,
            commands,
            heartbeats,
            control,
            heartbeat_seq: 0,
        })
    }
}

impl Transport for Ipc {
    fn wait_for_start(&mut self, _period_ns: u64) -> Result<u64, String> {
        let give_up = monotonic_ns() + 300_000_000_000;
        loop {
            while let Ok(Some(c)) = self.control.receive() {
                match c.command {
                    RUN_START => return Ok(c.start_time_ns),
                    RUN_STOP => return Err("stopped before the start".into()),
                    _ => {}
                }
            }
            self.heartbeat(HEARTBEAT_READY, 0);
            if monotonic_ns() > give_up {
                return Err("no START within 300 s".into());
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    fn send(&mut self, sample: &Sample) {
        let mut s = *sample;
        s.publish_time_ns = monotonic_ns();
        let _ = self.samples.send_copy(s);
    }
    fn commands(&mut self, out: &mut Vec<Command>) {
        // At most what `out` holds without growing (the loop does not allocate); the rest
        // waits for the next period.
        while out.len() < out.capacity() {
            let Ok(Some(c)) = self.commands.receive() else {
                break;
            };
            out.push(*c);
        }
    }
    fn control(&mut self, out: &mut Vec<u32>) {
        while out.len() < out.capacity() {
            let Ok(Some(c)) = self.control.receive() else {
                break;
            };
            out.push(c.command);
        }
    }
    fn heartbeat(&mut self, state: u32, fault_code: u32) {
        let _ = self.heartbeats.send_copy(Heartbeat {
            process: 0,
            state,
            sequence: self.heartbeat_seq,
            time_ns: monotonic_ns(),
            fault_code,
            reserved: 0,
        });
        self.heartbeat_seq += 1;
    }
    fn finish(&mut self, last: &Sample) {
        self.send(last);
        self.heartbeat(RIG_FINISHED, last.rig_fault_code);
    }
}

/// The UDP rig link, from the header's section 3 (little-endian, exact sizes).
struct Udp {
    socket: UdpSocket,
    peer: SocketAddr,
    sent: [u64; 5],
    newest: [Option<u64>; 5],
    last_control: u64,
    controls: Vec<u32>,
    echo_command_time_ns: u64,
    command_read_ns: u64,
    /// Datagrams dropped: wrong sender, length, magic, version, kind or sequence.
    rejected: u64,
    period_ns: u64,
}

impl Udp {
    fn open(bind: SocketAddr, peer: SocketAddr) -> Result<Udp, String> {
        let socket = UdpSocket::bind(bind).map_err(|e| format!("bind {bind}: {e}"))?;
        socket
            .set_nonblocking(true)
            .map_err(|e| format!("{bind}: {e}"))?;
        Ok(Udp {
            socket,
            peer,
            sent: [0; 5],
            newest: [None; 5],
            last_control: 0,
            controls: Vec::with_capacity(MAX_DATAGRAMS_READ),
            echo_command_time_ns: 0,
            command_read_ns: 0,
            rejected: 0,
            period_ns: 0,
        })
    }

    fn header<const N: usize>(&mut self, kind: u16) -> Datagram<N> {
        let mut d = Datagram::new();
        d.put(b"FEMU");
        d.put(&LINK_VERSION.to_le_bytes());
        d.put(&kind.to_le_bytes());
        d.put(&self.sent[kind as usize].to_le_bytes());
        d.put(&monotonic_ns().to_le_bytes());
        self.sent[kind as usize] += 1;
        d
    }

    fn status(&mut self, state: u32, fault_code: u32, period_ns: u64) {
        let mut d = self.header::<40>(4);
        d.put(&state.to_le_bytes());
        d.put(&fault_code.to_le_bytes());
        d.put(&period_ns.to_le_bytes());
        let _ = self.socket.send_to(d.bytes(), self.peer);
    }

    /// Reads what is waiting (at most `MAX_DATAGRAMS_READ`, and at most what `out` holds
    /// without growing): commands to `out`, run control to `controls`; a START comes back
    /// as (arrival, start_delay_ns, period_ns).
    fn drain(&mut self, out: &mut Vec<Command>) -> Option<(u64, u64, u64)> {
        let mut start = None;
        let mut buf = [0u8; 2048];
        for _ in 0..MAX_DATAGRAMS_READ {
            if out.len() == out.capacity() || self.controls.len() == self.controls.capacity() {
                break;
            }
            let Ok((len, from)) = self.socket.recv_from(&mut buf) else {
                break;
            };
            let now = monotonic_ns();
            let d = &buf[..len];
            let u16_at = |o: usize| u16::from_le_bytes(d[o..o + 2].try_into().unwrap());
            let u32_at = |o: usize| u32::from_le_bytes(d[o..o + 4].try_into().unwrap());
            let u64_at = |o: usize| u64::from_le_bytes(d[o..o + 8].try_into().unwrap());
            let f64_at = |o: usize| f64::from_le_bytes(d[o..o + 8].try_into().unwrap());
            if from != self.peer || len < 24 || &d[0..4] != b"FEMU" || u16_at(4) != LINK_VERSION {
                self.rejected += 1;
                continue;
            }
            let kind = u16_at(6);
            let size = match kind {
                2 => 184,
                3 => 56,
                _ => 0,
            };
            let seq = u64_at(8);
            let k = kind as usize;
            // Content nobody may act on is dropped before its sequence counts (header,
            // section 3): an unknown mode or run command, a non-finite law, bad limits.
            let content_ok = len == size
                && match kind {
                    2 => match u32_at(120) {
                        MODE_HOLD | MODE_HOLD_UNLOAD => true,
                        MODE_FORCE | MODE_LAW => {
                            let (lo, hi) = (f64_at(104), f64_at(112));
                            (0..7).all(|i| f64_at(48 + 8 * i).is_finite())
                                && lo.is_finite()
                                && hi.is_finite()
                                && lo <= hi
                                && (u32_at(120) == MODE_FORCE || compensation_at(d).ok())
                        }
                        _ => false,
                    },
                    _ => (1..=5).contains(&u32_at(24)),
                };
            if !content_ok || self.newest[k].is_some_and(|n| seq <= n) {
                self.rejected += 1;
                continue;
            }
            self.newest[k] = Some(seq);
            if kind == 2 {
                self.echo_command_time_ns = u64_at(16);
                self.command_read_ns = now;
                let f = |i: usize| f64_at(48 + 8 * i);
                out.push(Command {
                    sequence: u64_at(24),
                    setpoint_sequence: u64_at(32),
                    sample_sequence: u64_at(40),
                    sample_publish_time_ns: 0,
                    law: Law {
                        force_n: f(0),
                        displacement_m: f(1),
                        velocity_m_per_s: f(2),
                        stiffness_n_per_m: f(3),
                        damping_ns_per_m: f(4),
                        force_rate_n_per_s: f(5),
                        stiffness_slope_n_per_m2: f(6),
                    },
                    force_min_n: f64_at(104),
                    force_max_n: f64_at(112),
                    mode: u32_at(120),
                    controller_state: u32_at(124),
                    fault_code: u32_at(128),
                    reserved: 0,
                    compensation: compensation_at(d),
                });
            } else {
                let control_sequence = u64_at(32);
                if control_sequence <= self.last_control {
                    continue; // a repeat
                }
                self.last_control = control_sequence;
                let command = u32_at(24);
                if command == RUN_START {
                    start = Some((now, u64_at(40), u64_at(48)));
                } else {
                    self.controls.push(command);
                }
            }
        }
        start
    }
}

/// Datagrams read per period at most; the loop's command and control lists hold this many.
const MAX_DATAGRAMS_READ: usize = 64;

/// A datagram of `N` bytes built in place (the loop does not allocate).
struct Datagram<const N: usize> {
    bytes: [u8; N],
    len: usize,
}

impl<const N: usize> Datagram<N> {
    fn new() -> Datagram<N> {
        Datagram {
            bytes: [0; N],
            len: 0,
        }
    }
    fn put(&mut self, b: &[u8]) {
        self.bytes[self.len..self.len + b.len()].copy_from_slice(b);
        self.len += b.len();
    }
    /// The whole datagram (its kind's exact size: every field put).
    fn bytes(&self) -> &[u8] {
        assert_eq!(self.len, N, "a datagram of {N} bytes with {} put", self.len);
        &self.bytes[..self.len]
    }
}

/// The compensation of a COMMAND datagram (offset 144).
fn compensation_at(d: &[u8]) -> Compensation {
    let f = |o: usize| f64::from_le_bytes(d[o..o + 8].try_into().unwrap());
    Compensation {
        lead_s: f(144),
        added_damping_ns_per_m: f(152),
        added_damping_corner_hz: f(160),
        gain: f(168),
        lead_order: u32::from_le_bytes(d[176..180].try_into().unwrap()),
        reserved: 0,
    }
}

impl Transport for Udp {
    fn wait_for_start(&mut self, period_ns: u64) -> Result<u64, String> {
        self.period_ns = period_ns;
        let give_up = monotonic_ns() + 300_000_000_000;
        let mut next_status = 0;
        let mut ignored = Vec::with_capacity(MAX_DATAGRAMS_READ);
        loop {
            // Commands before the start are not acted on, and run control other than STOP
            // waits for none: both lists are emptied, so `drain` always has room to read.
            ignored.clear();
            if monotonic_ns() >= next_status {
                self.status(HEARTBEAT_READY, 0, period_ns);
                next_status = monotonic_ns() + 10_000_000;
            }
            if let Some((arrival, delay, period)) = self.drain(&mut ignored) {
                if period != period_ns {
                    return Err(format!(
                        "fastemu runs at a period of {period} ns, this rig at {period_ns} ns"
                    ));
                }
                return Ok(arrival + delay);
            }
            if self.controls.contains(&RUN_STOP) {
                return Err("stopped before the start".into());
            }
            self.controls.clear();
            if monotonic_ns() > give_up {
                return Err("no START within 300 s".into());
            }
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    fn send(&mut self, s: &Sample) {
        let mut d = self.header::<96>(1);
        d.put(&s.sequence.to_le_bytes());
        d.put(&s.rig_time_ns.to_le_bytes());
        d.put(&s.displacement_m.to_le_bytes());
        d.put(&s.actuator_force_n.to_le_bytes());
        d.put(&s.status.to_le_bytes());
        d.put(&s.rig_state.to_le_bytes());
        d.put(&s.rig_fault_code.to_le_bytes());
        d.put(&0u32.to_le_bytes());
        let hold = if self.echo_command_time_ns == 0 {
            0
        } else {
            monotonic_ns() - self.command_read_ns
        };
        d.put(&self.echo_command_time_ns.to_le_bytes());
        d.put(&hold.to_le_bytes());
        d.put(&s.commanded_force_n.to_le_bytes());
        let _ = self.socket.send_to(d.bytes(), self.peer);
    }
    fn commands(&mut self, out: &mut Vec<Command>) {
        let _ = self.drain(out);
    }
    fn control(&mut self, out: &mut Vec<u32>) {
        // `out` holds as many as `controls` without growing (both `MAX_DATAGRAMS_READ`).
        out.append(&mut self.controls);
    }
    fn heartbeat(&mut self, _state: u32, _fault_code: u32) {
        // Over UDP the state travels in every sample.
    }
    fn finish(&mut self, last: &Sample) {
        self.send(last);
        for _ in 0..3 {
            self.status(RIG_FINISHED, last.rig_fault_code, self.period_ns);
        }
        if self.rejected > 0 {
            eprintln!("example_rig: {} datagrams rejected", self.rejected);
        }
    }
}

// ---- the rig ------------------------------------------------------------------------------

struct Options {
    rate_hz: f64,
    duration_s: f64,
    mass_kg: f64,
    damping_ns_per_m: f64,
    preload_n: f64,
    amplitude_n: f64,
    frequency_hz: f64,
    stale_periods: u64,
}

/// The external load programme at programme time `t`, N.
fn load_n(o: &Options, t: f64) -> f64 {
    o.preload_n + o.amplitude_n * (2.0 * std::f64::consts::PI * o.frequency_hz * t).sin()
}

/// Lagrange weights for value and slope at `lead` past the newest of `order + 1`
/// samples spaced `h` (the header's fastemu_lead_weights).
fn lead_weights(order: usize, h: f64, lead: f64) -> ([f64; 4], [f64; 4]) {
    let n = order.min(3) + 1;
    let t = [0.0, -h, -2.0 * h, -3.0 * h];
    let (mut value, mut slope) = ([0.0; 4], [0.0; 4]);
    for i in 0..n {
        let mut li = 1.0;
        let mut d = 0.0;
        for j in 0..n {
            if j != i {
                li *= (lead - t[j]) / (t[i] - t[j]);
            }
        }
        for m in 0..n {
            if m == i {
                continue;
            }
            let mut term = 1.0 / (t[i] - t[m]);
            for j in 0..n {
                if j != i && j != m {
                    term *= (lead - t[j]) / (t[i] - t[j]);
                }
            }
            d += term;
        }
        value[i] = li;
        slope[i] = d;
    }
    (value, slope)
}

/// A rig's loop is real-time: SCHED_FIFO 80 and locked memory where the OS permits (as
/// root, or with CAP_SYS_NICE), else a warning: a rig that stalls for longer than
/// fastemu's stale-sample limit (59 ms by default) trips the emulator.
fn real_time() {
    // SAFETY: plain system calls on this process with valid arguments.
    unsafe {
        let param = libc::sched_param { sched_priority: 80 };
        if libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) != 0 {
            eprintln!(
                "example_rig: warning: no SCHED_FIFO (not permitted); running at normal priority"
            );
        }
        libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE);
    }
}

fn run(transport: &mut dyn Transport, o: &Options) -> Result<(), String> {
    real_time();
    let period_ns = (1e9 / o.rate_hz).round() as u64;
    let dt = 1.0 / o.rate_hz;
    // At rest in equilibrium with the load programme's first value, the actuator holding it.
    let (mut x, mut v) = (0.0f64, 0.0f64);
    let mut force = load_n(o, 0.0);
    // The prediction over the command's lead (header 2c, fastemu_compensated_force): its
    // weights are recomputed when a command's lead or order changes.
    let (mut wv, mut ws) = lead_weights(0, dt, 0.0);
    let mut weights_for = (0.0f64, 0u32);
    let mut v_lp = 0.0f64;
    let mut history = [0.0f64; 4];
    let mut command: Option<Command> = None;
    let mut last_command_k: Option<u64> = None;
    let (mut state, mut fault) = (RIG_RUNNING, 0u32);
    // Until the first command the rig holds its starting position (displacement control).
    let (mut hold_x, mut hold_force, mut hold_since) = (x, force, 0u64);
    let mut unload = false;
    let mut programme_t = 0.0;
    let mut programme_held_n = 0.0;
    // The last 50 ms of displacement while holding, a ring filled before the loop.
    let rest_len = ((0.05 * o.rate_hz) as usize).max(1);
    let mut rest_window = vec![0.0f64; rest_len];
    let (mut rest_filled, mut rest_next) = (0usize, 0usize);
    let mut finished_after_hold = false;
    let (kp, kd) = {
        // Position hold: a PD loop at 30 Hz, damping ratio 0.8, on the mass.
        let w = 2.0 * std::f64::consts::PI * 30.0;
        (o.mass_kg * w * w, o.mass_kg * 2.0 * 0.8 * w)
    };
    let t0 = transport.wait_for_start(period_ns)?;
    eprintln!("example_rig: started");
    let total = (o.duration_s * o.rate_hz).round() as u64;
    let mut commands = Vec::with_capacity(MAX_DATAGRAMS_READ);
    let mut controls = Vec::with_capacity(MAX_DATAGRAMS_READ);
    COUNTING.with(|c| c.set(true));
    let mut k = 0u64;
    let mut stop = false;
    while !stop {
        // Sleep to this period's instant (std's sleep; a late wake runs the missed periods).
        let due = t0 + k * period_ns;
        let now = monotonic_ns();
        if due > now {
            std::thread::sleep(Duration::from_nanos(due - now));
        }
        // a. measure and send.
        history = [x, history[0], history[1], history[2]];
        if k == 0 {
            history = [x; 4];
        }
        transport.send(&Sample {
            sequence: k,
            rig_time_ns: k * period_ns,
            publish_time_ns: 0,
            displacement_m: x,
            actuator_force_n: force,
            status: SAMPLE_OK,
            rig_state: state,
            rig_fault_code: fault,
            reserved: 0,
            // The actuator is ideal: it applies what it was commanded.
            commanded_force_n: force,
        });
        // b. commands; HOLD commands latch the interlock; a command nobody may act on is
        // dropped as if it had not arrived (it does not count for the interlock either).
        commands.clear();
        transport.commands(&mut commands);
        commands.retain(Command::content_ok);
        let latch =
            |state: &mut u32, fault: &mut u32, code: u32, unload_now: &mut bool, u: bool| {
                if *fault == 0 {
                    *fault = code;
                }
                *unload_now |= u;
                if *state == RIG_RUNNING || *state == RIG_OPERATOR_HOLD {
                    *state = RIG_HOLD;
                    true
                } else {
                    false
                }
            };
        let mut entered_hold = false;
        for c in &commands {
            last_command_k = Some(k);
            match c.mode {
                MODE_HOLD | MODE_HOLD_UNLOAD => {
                    let was_operator = state == RIG_OPERATOR_HOLD;
                    entered_hold |= latch(
                        &mut state,
                        &mut fault,
                        FAULT_HOLD_REQUESTED,
                        &mut unload,
                        c.mode == MODE_HOLD_UNLOAD,
                    ) && !was_operator;
                }
                _ => command = Some(*c),
            }
        }
        // d. the rig's own interlock on stale commands.
        // Armed from sample 0: a first command that never comes is stale too.
        if k.saturating_sub(last_command_k.unwrap_or(0)) > o.stale_periods && fault == 0 {
            let was_operator = state == RIG_OPERATOR_HOLD;
            entered_hold |= latch(
                &mut state,
                &mut fault,
                FAULT_COMMANDS_STALE,
                &mut unload,
                false,
            ) && !was_operator;
        }
        // e. run control.
        controls.clear();
        transport.control(&mut controls);
        for &c in &controls {
            match c {
                RUN_STOP => stop = true,
                RUN_HOLD if state == RIG_RUNNING => {
                    state = RIG_OPERATOR_HOLD;
                    entered_hold = true;
                }
                RUN_RESUME if state == RIG_OPERATOR_HOLD && fault == 0 => state = RIG_RUNNING,
                RUN_END => {
                    unload = true;
                    if state == RIG_RUNNING {
                        state = RIG_HOLD;
                        entered_hold = true;
                    } else if state == RIG_OPERATOR_HOLD {
                        state = RIG_HOLD;
                    }
                }
                _ => {}
            }
        }
        if entered_hold {
            // Position control where it latched, the held load fed forward (rig-interface.md, the interlock): not
            // the last force, which in a loop that tripped is mid-swing (a 2 kN swing held
            // as the equilibrium moved the specimen 0.93 mm into the hold, 2026-11-29).
            hold_x = x;
            programme_held_n = load_n(o, programme_t);
            hold_force = programme_held_n;
            hold_since = k;
            rest_filled = 0;
        }
        // c. the actuator force for this period.
        let holding = state != RIG_RUNNING;
        force = if holding {
            hold_force + kp * (x - hold_x) + kd * v
        } else {
            match &command {
                Some(c) if c.mode == MODE_LAW => {
                    let comp = &c.compensation;
                    if (comp.lead_s, comp.lead_order) != weights_for {
                        (wv, ws) = lead_weights(comp.lead_order as usize, dt, comp.lead_s);
                        weights_for = (comp.lead_s, comp.lead_order);
                    }
                    let z: f64 = (0..4).map(|i| wv[i] * history[i]).sum();
                    let zdot: f64 = (0..4).map(|i| ws[i] * history[i]).sum();
                    let v_hp = if comp.added_damping_corner_hz > 0.0 {
                        let a = 1.0
                            - (-2.0 * std::f64::consts::PI * comp.added_damping_corner_hz * dt)
                                .exp();
                        v_lp += a * (zdot - v_lp);
                        zdot - v_lp
                    } else {
                        v_lp = zdot;
                        zdot
                    };
                    let since = if c.sample_sequence == u64::MAX {
                        0.0
                    } else {
                        ((k.saturating_sub(c.sample_sequence)) as f64 * dt + comp.lead_s)
                            .min(o.stale_periods as f64 * dt)
                    };
                    let l = &c.law;
                    let dz = z - l.displacement_m;
                    let f = l.force_n
                        + (l.stiffness_n_per_m + 0.5 * l.stiffness_slope_n_per_m2 * dz) * dz
                        + l.damping_ns_per_m * (zdot - l.velocity_m_per_s)
                        + l.force_rate_n_per_s * since
                        + comp.added_damping_ns_per_m * v_hp;
                    f.max(c.force_min_n).min(c.force_max_n) / comp.gain
                }
                Some(c) if c.mode == MODE_FORCE => {
                    c.law.force_n.max(c.force_min_n).min(c.force_max_n)
                }
                // Before the first command: the starting position held, the programme's
                // change fed forward (header 2c), so the specimen waits at rest.
                None => load_n(o, programme_t) + kp * (x - hold_x) + kd * v,
                _ => force,
            }
        };
        // Rest and unload while holding; the end of the session.
        if holding {
            rest_window[rest_next] = x;
            rest_next = (rest_next + 1) % rest_len;
            rest_filled = (rest_filled + 1).min(rest_len);
            let at_rest = rest_filled == rest_len
                && rest_window.iter().cloned().fold(f64::MIN, f64::max)
                    - rest_window.iter().cloned().fold(f64::MAX, f64::min)
                    < 5e-6;
            if unload && at_rest && state != RIG_OPERATOR_HOLD {
                state = RIG_UNLOAD;
            }
            if state == RIG_UNLOAD {
                let step = 20_000.0 * dt;
                let next = if programme_held_n > 0.0 {
                    (programme_held_n - step).max(0.0)
                } else {
                    (programme_held_n + step).min(0.0)
                };
                // The hold's equilibrium force follows the load it holds.
                hold_force += next - programme_held_n;
                programme_held_n = next;
            }
            let held_s = (k - hold_since) as f64 * dt;
            let settled = at_rest && (!unload || programme_held_n == 0.0);
            if state != RIG_OPERATOR_HOLD && ((held_s >= 1.0 && settled) || held_s >= 10.0) {
                finished_after_hold = true;
                stop = true;
            }
        }
        // The physics over the period (the force held: zero-order hold), in sub-steps.
        let load = if holding {
            programme_held_n
        } else {
            load_n(o, programme_t)
        };
        let h = dt / 16.0;
        for _ in 0..16 {
            let a = (load - force - o.damping_ns_per_m * v) / o.mass_kg;
            v += a * h;
            x += v * h;
        }
        if !holding {
            programme_t += dt;
        }
        if k.is_multiple_of(((0.01 * o.rate_hz) as u64).max(1)) {
            transport.heartbeat(state, fault);
        }
        k += 1;
        if !holding && k >= total {
            stop = true;
        }
    }
    COUNTING.with(|c| c.set(false));
    let allocations = ALLOCATIONS.with(Cell::get);
    transport.finish(&Sample {
        sequence: k,
        rig_time_ns: k * period_ns,
        publish_time_ns: 0,
        displacement_m: x,
        actuator_force_n: force,
        status: SAMPLE_END_OF_RUN,
        rig_state: RIG_FINISHED,
        rig_fault_code: fault,
        reserved: 0,
        commanded_force_n: force,
    });
    eprintln!(
        "example_rig: {k} periods, final state {}, fault code {fault}{}; {allocations} allocations in the loop",
        if finished_after_hold {
            "held, at rest"
        } else {
            "finished"
        },
        if stop && !finished_after_hold && k < total {
            " (stopped)"
        } else {
            ""
        }
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut o = Options {
        rate_hz: 4096.0,
        duration_s: 6.0,
        mass_kg: 60.16,
        damping_ns_per_m: 3600.0,
        preload_n: 0.0,
        amplitude_n: 4000.0,
        frequency_hz: 2.0,
        stale_periods: 205,
    };
    let mut transport: Option<Box<dyn Transport>> = None;
    let mut i = 0;
    let fail = |m: String| {
        eprintln!("example_rig: {m}");
        std::process::ExitCode::FAILURE
    };
    while i < args.len() {
        let value = |n: usize| args.get(i + n).cloned().unwrap_or_default();
        let number = |n: usize| {
            value(n)
                .parse::<f64>()
                .map_err(|_| format!("{}: not a number: `{}`", args[i], value(n)))
        };
        let r: Result<usize, String> = match args[i].as_str() {
            "--help" | "-h" => {
                println!("{USAGE}");
                std::process::exit(0);
            }
            "--ipc" => Ipc::open(&value(1)).map(|t| {
                transport = Some(Box::new(t));
                2
            }),
            "--udp" => match (value(1).parse(), value(2).parse()) {
                (Ok(bind), Ok(peer)) => Udp::open(bind, peer).map(|t| {
                    transport = Some(Box::new(t));
                    3
                }),
                _ => Err("--udp BIND_IP:PORT PEER_IP:PORT".into()),
            },
            "--rate-hz" => number(1).map(|x| {
                o.rate_hz = x;
                2
            }),
            "--duration-s" => number(1).map(|x| {
                o.duration_s = x;
                2
            }),
            "--mass-kg" => number(1).map(|x| {
                o.mass_kg = x;
                2
            }),
            "--damping-ns-per-m" => number(1).map(|x| {
                o.damping_ns_per_m = x;
                2
            }),
            "--preload-n" => number(1).map(|x| {
                o.preload_n = x;
                2
            }),
            "--amplitude-n" => number(1).map(|x| {
                o.amplitude_n = x;
                2
            }),
            "--frequency-hz" => number(1).map(|x| {
                o.frequency_hz = x;
                2
            }),
            "--stale-periods" => number(1).map(|x| {
                o.stale_periods = x as u64;
                2
            }),
            other => Err(format!("unknown argument `{other}`\n{USAGE}")),
        };
        match r {
            Ok(n) => i += n,
            Err(e) => return fail(e),
        }
    }
    let Some(mut transport) = transport else {
        return fail("give --ipc RUN_ID or --udp BIND PEER".into());
    };
    match run(transport.as_mut(), &o) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => fail(e),
    }
}
