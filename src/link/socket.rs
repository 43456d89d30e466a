//! The UDP socket of one end of the rig link: bound to the configured interface only,
//! talking to one configured peer. `LinkReceiver` accepts a datagram only from that peer,
//! with the right framing (`protocol::decode`) and a sequence number newer than the newest
//! of its kind; everything else is counted by reason and dropped. `LinkSender` numbers
//! and timestamps what it sends. Both ends of the link (fastemu's link process, the
//! simulated rig) and the UDP rounds of `bench latency` use these, so there is one
//! implementation of the protocol on sockets.
//!
//! The socket is not `connect`ed: a connected UDP socket would have the kernel drop
//! foreign datagrams unseen, and the link must count them.
//!
//! Must not: allocate, lock or log per datagram (`send_*`, `receive` run in the loops).

use std::fmt;
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::time::Duration;

use serde::Serialize;

use super::protocol::{
    decode, encode_command, encode_control, encode_sample, encode_status, kind, same_period,
    CommandDatagram, ControlDatagram, Datagram, Header, Reject, SampleDatagram, Side,
    StatusDatagram, MAX_DATAGRAM_BYTES,
};
use crate::ipc::messages::run_command;
use crate::rt::clock::monotonic_now_ns;

/// A link setup error: which address and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkError(pub String);

impl fmt::Display for LinkError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for LinkError {}

/// Parses `ip:port` for `--link-bind`/`--link-peer`: an explicit interface address
/// (never `0.0.0.0` or `::`: nobody else on the lab network may move the actuator).
pub fn parse_link_address(what: &str, text: &str) -> Result<SocketAddr, LinkError> {
    let addr: SocketAddr = text.parse().map_err(|_| {
        LinkError(format!(
            "{what} `{text}` is not valid: expected IP:PORT, e.g. 192.168.10.2:50000"
        ))
    })?;
    if addr.ip().is_unspecified() {
        return Err(LinkError(format!(
            "{what} `{text}` is not valid: give the address of the one interface that faces the rig, not {} (every interface)",
            addr.ip()
        )));
    }
    Ok(addr)
}

/// Two loopback addresses with ports that were free a moment ago (released here for
/// whoever binds them; `bound_loopback_pair` keeps them).
pub fn free_loopback_pair() -> Result<(SocketAddr, SocketAddr), LinkError> {
    let (a, b) = bound_loopback_pair()?;
    let err = |e: io::Error| LinkError(format!("cannot find free UDP ports on 127.0.0.1: {e}"));
    Ok((a.local_addr().map_err(err)?, b.local_addr().map_err(err)?))
}

/// Two sockets bound to free loopback ports, for a link whose two ends `hil` starts on
/// this machine: `hil` hands each to the process that uses it (`HANDED_SOCKET_ENV`), so
/// no other process can take a port between the choice and its use.
pub fn bound_loopback_pair() -> Result<(UdpSocket, UdpSocket), LinkError> {
    let err = |e: io::Error| LinkError(format!("cannot find free UDP ports on 127.0.0.1: {e}"));
    let a = UdpSocket::bind("127.0.0.1:0").map_err(err)?;
    let b = UdpSocket::bind("127.0.0.1:0").map_err(err)?;
    Ok((a, b))
}

/// Environment variable through which `hil` hands a child the link socket it bound for
/// it: an inherited descriptor number. `open_link` takes it when its address is the one
/// asked for.
pub const HANDED_SOCKET_ENV: &str = "FASTEMU_LINK_SOCKET_FD";

/// The socket the parent handed this process for `bind`, if it did (taken once).
fn handed_socket(bind: SocketAddr) -> Option<UdpSocket> {
    use std::os::fd::{FromRawFd, IntoRawFd};
    use std::sync::atomic::{AtomicBool, Ordering};
    static TAKEN: AtomicBool = AtomicBool::new(false);
    let fd: i32 = std::env::var(HANDED_SOCKET_ENV).ok()?.parse().ok()?;
    if fd < 3 || TAKEN.swap(true, Ordering::SeqCst) {
        return None;
    }
    // SAFETY: `hil` names under this variable a UDP socket it bound for this process and
    // left open across exec; anything else (no socket, another address) is given back
    // untouched (not closed) below.
    let socket = unsafe { UdpSocket::from_raw_fd(fd) };
    match socket.local_addr() {
        Ok(addr) if addr == bind => Some(socket),
        _ => {
            let _ = socket.into_raw_fd();
            TAKEN.store(false, Ordering::SeqCst);
            None
        }
    }
}

/// Sequence numbers per kind of the datagrams one end receives.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct SequenceWindow {
    newest: Option<u64>,
}

impl SequenceWindow {
    /// Accepts `sequence` if newer than the newest; returns how many were skipped.
    fn accept(&mut self, sequence: u64) -> Result<u64, Reject> {
        match self.newest {
            Some(n) if sequence == n => Err(Reject::Duplicate),
            Some(n) if sequence < n => Err(Reject::Reordered),
            Some(n) => {
                self.newest = Some(sequence);
                Ok(sequence - n - 1)
            }
            None => {
                self.newest = Some(sequence);
                Ok(0)
            }
        }
    }
}

/// Per-kind counters (`sample`, `command`, `control`, `status`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct KindCounts {
    pub sample: u64,
    pub command: u64,
    pub control: u64,
    pub status: u64,
}

impl KindCounts {
    fn bump(&mut self, kind: u16, by: u64) {
        match kind {
            kind::SAMPLE => self.sample += by,
            kind::COMMAND => self.command += by,
            kind::CONTROL => self.control += by,
            _ => self.status += by,
        }
    }

    pub fn total(&self) -> u64 {
        self.sample + self.command + self.control + self.status
    }
}

/// What one end received: accepted per kind, rejected per reason, lost per kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReceiveCounts {
    pub accepted: KindCounts,
    pub rejected: [u64; Reject::ALL.len()],
    /// Datagrams never accepted between accepted ones (gaps in the sequence numbers).
    pub lost: KindCounts,
    /// Socket errors other than "nothing to read".
    pub socket_errors: u64,
}

impl ReceiveCounts {
    pub fn rejected_total(&self) -> u64 {
        self.rejected.iter().sum()
    }

    pub fn rejected_of(&self, reason: Reject) -> u64 {
        self.rejected[reason.index()]
    }

    /// `{"truncated": n, ...}` with every reason.
    pub fn rejected_json(&self) -> serde_json::Value {
        let mut map = serde_json::Map::new();
        for r in Reject::ALL {
            map.insert(r.name().to_string(), self.rejected[r.index()].into());
        }
        serde_json::Value::Object(map)
    }
}

/// The sending half of one end.
#[derive(Debug)]
pub struct LinkSender {
    socket: UdpSocket,
    peer: SocketAddr,
    next_sequence: KindCounts,
    pub sent: KindCounts,
    pub send_errors: u64,
    buf: [u8; MAX_DATAGRAM_BYTES],
}

/// The receiving half of one end.
#[derive(Debug)]
pub struct LinkReceiver {
    socket: UdpSocket,
    peer: SocketAddr,
    side: Side,
    windows: [SequenceWindow; 5],
    pub counts: ReceiveCounts,
    /// The loop period status and START datagrams must name, ns (`expect_period`).
    expected_period_ns: Option<u64>,
    /// The period named by the newest datagram rejected for naming another, ns (0 none).
    pub wrong_period_ns: u64,
    /// The link protocol version named by the newest datagram from the peer rejected for
    /// its version (0 none): a rig of another version, told apart from noise.
    pub peer_version: u16,
    buf: [u8; MAX_DATAGRAM_BYTES + 1],
}

/// Opens one end: a UDP socket bound to `bind` (an explicit interface address) that
/// talks to `peer` only. Receives block for at most `receive_timeout` (`None`: never
/// block).
pub fn open_link(
    bind: SocketAddr,
    peer: SocketAddr,
    side: Side,
    receive_timeout: Option<Duration>,
) -> Result<(LinkSender, LinkReceiver), LinkError> {
    if bind.ip().is_unspecified() {
        return Err(LinkError(format!(
            "link bind address {bind}: give one interface's address, not every interface"
        )));
    }
    if peer.ip().is_unspecified() || peer.port() == 0 {
        return Err(LinkError(format!(
            "link peer address {peer}: expected the rig's IP:PORT"
        )));
    }
    let socket = match handed_socket(bind) {
        Some(socket) => socket,
        None => UdpSocket::bind(bind)
            .map_err(|e| LinkError(format!("cannot bind the link's UDP socket to {bind}: {e}")))?,
    };
    open_link_socket(socket, peer, side, receive_timeout)
}

/// `open_link` on a socket already bound (e.g. to port 0 by whoever needs its address
/// first, so no other process can take the port in between).
pub fn open_link_socket(
    socket: UdpSocket,
    peer: SocketAddr,
    side: Side,
    receive_timeout: Option<Duration>,
) -> Result<(LinkSender, LinkReceiver), LinkError> {
    let bind = socket
        .local_addr()
        .map_err(|e| LinkError(format!("link socket: {e}")))?;
    if peer.ip().is_unspecified() || peer.port() == 0 {
        return Err(LinkError(format!(
            "link peer address {peer}: expected the rig's IP:PORT"
        )));
    }
    let receive_socket = socket
        .try_clone()
        .map_err(|e| LinkError(format!("link socket {bind}: {e}")))?;
    match receive_timeout {
        Some(t) => receive_socket.set_read_timeout(Some(t.max(Duration::from_micros(1)))),
        None => receive_socket.set_nonblocking(true),
    }
    .map_err(|e| LinkError(format!("link socket {bind}: {e}")))?;
    Ok((
        LinkSender {
            socket,
            peer,
            next_sequence: KindCounts::default(),
            sent: KindCounts::default(),
            send_errors: 0,
            buf: [0; MAX_DATAGRAM_BYTES],
        },
        LinkReceiver {
            socket: receive_socket,
            peer,
            side,
            windows: [SequenceWindow::default(); 5],
            counts: ReceiveCounts::default(),
            expected_period_ns: None,
            wrong_period_ns: 0,
            peer_version: 0,
            buf: [0; MAX_DATAGRAM_BYTES + 1],
        },
    ))
}

impl LinkSender {
    /// The address this end is bound to (the port, when bound to port 0).
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.socket.local_addr()
    }

    pub fn peer(&self) -> SocketAddr {
        self.peer
    }

    #[inline]
    fn send(
        &mut self,
        kind: u16,
        encode: impl FnOnce(&mut [u8; MAX_DATAGRAM_BYTES], u64, u64) -> usize,
    ) -> u64 {
        let sequence = match kind {
            kind::SAMPLE => &mut self.next_sequence.sample,
            kind::COMMAND => &mut self.next_sequence.command,
            kind::CONTROL => &mut self.next_sequence.control,
            _ => &mut self.next_sequence.status,
        };
        let seq = *sequence;
        *sequence += 1;
        let now = monotonic_now_ns();
        let n = encode(&mut self.buf, seq, now);
        match self.socket.send_to(&self.buf[..n], self.peer) {
            Ok(sent) if sent == n => self.sent.bump(kind, 1),
            _ => self.send_errors += 1,
        }
        now
    }

    /// Sends a sample datagram; returns its sender time.
    #[inline]
    pub fn send_sample(&mut self, d: &SampleDatagram) -> u64 {
        self.send(kind::SAMPLE, |b, s, t| encode_sample(b, s, t, d))
    }

    #[inline]
    pub fn send_command(&mut self, d: &CommandDatagram) -> u64 {
        self.send(kind::COMMAND, |b, s, t| encode_command(b, s, t, d))
    }

    pub fn send_control(&mut self, d: &ControlDatagram) -> u64 {
        self.send(kind::CONTROL, |b, s, t| encode_control(b, s, t, d))
    }

    pub fn send_status(&mut self, d: &StatusDatagram) -> u64 {
        self.send(kind::STATUS, |b, s, t| encode_status(b, s, t, d))
    }
}

/// One accepted datagram with its arrival time on this machine's clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Received {
    pub header: Header,
    pub datagram: Datagram,
    pub arrival_ns: u64,
}

/// What one call to `LinkReceiver::receive` found.
#[derive(Debug, Clone, Copy, PartialEq)]
// The accepted datagram stays inline: boxing it would allocate per datagram, which the
// link must not (a command datagram is 184 bytes since link protocol 2).
#[allow(clippy::large_enum_variant)]
pub enum Receive {
    Accepted(Received),
    /// A datagram arrived and was rejected (counted).
    Rejected(Reject),
    /// Nothing to read (time-out, or nothing waiting on a non-blocking socket).
    Nothing,
}

impl LinkReceiver {
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.socket.local_addr()
    }

    /// Waits until a datagram is waiting or `timeout` passes (whatever the socket's own
    /// mode); returns whether one is waiting. Not for the loops: for handshakes, where
    /// the arrival time of one datagram matters (a START's).
    pub fn wait_readable(&self, timeout: Duration) -> bool {
        use std::os::unix::io::AsRawFd;
        let mut fd = libc::pollfd {
            fd: self.socket.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = timeout.as_millis().min(i32::MAX as u128) as i32;
        // SAFETY: one valid pollfd for the duration of the call.
        unsafe { libc::poll(&mut fd, 1, ms) > 0 }
    }

    fn reject(&mut self, reason: Reject) -> Receive {
        self.counts.rejected[reason.index()] += 1;
        Receive::Rejected(reason)
    }

    /// Reads one datagram (waiting as configured) and checks it.
    #[inline]
    pub fn receive(&mut self) -> Receive {
        let (len, from) = match self.socket.recv_from(&mut self.buf) {
            Ok(x) => x,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock
                        | io::ErrorKind::TimedOut
                        | io::ErrorKind::Interrupted
                ) =>
            {
                return Receive::Nothing
            }
            Err(_) => {
                self.counts.socket_errors += 1;
                return Receive::Nothing;
            }
        };
        let arrival_ns = monotonic_now_ns();
        if from != self.peer {
            return self.reject(Reject::ForeignSender);
        }
        let (header, datagram) = match decode(&self.buf[..len], self.side) {
            Ok(x) => x,
            Err(reason) => {
                if reason == Reject::BadVersion {
                    self.peer_version = u16::from_le_bytes([self.buf[4], self.buf[5]]);
                }
                return self.reject(reason);
            }
        };
        // Content before sequence: a rejected datagram moves no window and counts as no
        // sign of life.
        if !self.content_ok(&datagram) {
            return self.reject(Reject::BadContent);
        }
        let window = &mut self.windows[usize::from(header.kind).min(4)];
        match window.accept(header.sequence) {
            Ok(gap) => {
                self.counts.lost.bump(header.kind, gap);
                self.counts.accepted.bump(header.kind, 1);
                Receive::Accepted(Received {
                    header,
                    datagram,
                    arrival_ns,
                })
            }
            Err(reason) => self.reject(reason),
        }
    }

    /// Status and START datagrams must name this loop period (up to rounding), ns.
    pub fn expect_period(&mut self, period_ns: u64) {
        self.expected_period_ns = Some(period_ns);
    }

    /// Whether a well-framed datagram's content may be used (else `BadContent`): a
    /// status or START names the loop's period; run control a known command; a command a
    /// known mode and, to be applied, a finite law inside finite, ordered limits.
    #[inline]
    fn content_ok(&mut self, datagram: &Datagram) -> bool {
        let period = match datagram {
            Datagram::Sample(_) => return true,
            Datagram::Command(c) => return c.command.content_ok(),
            Datagram::Control(c) => match c.command {
                run_command::START => c.period_ns,
                run_command::STOP | run_command::HOLD | run_command::RESUME | run_command::END => {
                    return true
                }
                _ => return false,
            },
            Datagram::Status(s) => s.period_ns,
        };
        match self.expected_period_ns {
            Some(expected) if !same_period(period, expected) => {
                self.wrong_period_ns = period;
                false
            }
            _ => true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ipc::messages::{command_mode, ActuatorCommand, Compensation, LocalLaw};

    #[test]
    fn commands_a_rig_must_not_act_on_are_bad_content() {
        let good = ActuatorCommand {
            sequence: 0,
            setpoint_sequence: 0,
            sample_sequence: 0,
            sample_publish_time_ns: 0,
            law: LocalLaw::constant(2e4),
            force_min_n: -5e3,
            force_max_n: 1.2e5,
            mode: command_mode::LAW,
            controller_state: 1,
            fault_code: 0,
            reserved: 0,
            compensation: Compensation::lead(2.52e-4, 2),
        };
        assert!(good.content_ok());
        assert!(ActuatorCommand {
            mode: command_mode::FORCE,
            ..good
        }
        .content_ok());
        let mut nan_law = good;
        nan_law.law.damping_ns_per_m = f64::NAN;
        let bad = [
            ActuatorCommand { mode: 7, ..good },
            nan_law,
            ActuatorCommand {
                force_min_n: 2e5,
                ..good
            },
            ActuatorCommand {
                force_max_n: f64::INFINITY,
                ..good
            },
            // A law command whose compensation is out of range: a lead beyond 20 ms, a
            // gain a rig must not divide by, negative guard damping, a NaN.
            ActuatorCommand {
                compensation: Compensation::lead(0.021, 2),
                ..good
            },
            ActuatorCommand {
                compensation: Compensation {
                    gain: 0.0,
                    ..good.compensation
                },
                ..good
            },
            ActuatorCommand {
                compensation: Compensation {
                    added_damping_ns_per_m: -1.0,
                    ..good.compensation
                },
                ..good
            },
            ActuatorCommand {
                compensation: Compensation {
                    added_damping_corner_hz: f64::NAN,
                    ..good.compensation
                },
                ..good
            },
        ];
        for c in bad {
            assert!(!c.content_ok(), "{c:?}");
        }
        // A hold is acted on whatever its law says.
        assert!(ActuatorCommand {
            mode: command_mode::HOLD,
            ..nan_law
        }
        .content_ok());
    }

    #[test]
    fn sequence_window_counts_gaps_and_refuses_old_numbers() {
        let mut w = SequenceWindow::default();
        assert_eq!(w.accept(5), Ok(0));
        assert_eq!(w.accept(6), Ok(0));
        assert_eq!(w.accept(9), Ok(2));
        assert_eq!(w.accept(9), Err(Reject::Duplicate));
        assert_eq!(w.accept(7), Err(Reject::Reordered));
        assert_eq!(w.accept(10), Ok(0));
    }

    #[test]
    fn unspecified_addresses_are_refused_with_a_reason() {
        let e = parse_link_address("--link-bind", "0.0.0.0:5000").unwrap_err();
        assert!(e.0.contains("interface"), "{e}");
        assert!(parse_link_address("--link-peer", "rig:5000").is_err());
        assert!(parse_link_address("--link-peer", "10.0.0.2:5000").is_ok());
    }
}
