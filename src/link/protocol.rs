//! The UDP rig link's datagrams, link protocol version `LINK_VERSION`: fixed
//! little-endian layouts, one per kind, each a 24-byte header (magic `FEMU`, version,
//! kind, the sender's sequence number for that kind, the sender's clock) and a fixed
//! payload. The README's protocol table and `include/fastemu_rig.h` give the same offsets;
//! `encode_*` and `decode` are the only code that knows them.
//!
//! A datagram is accepted only if its length is exactly its kind's size, its magic and
//! version match, and its kind travels in the receiver's direction; otherwise `decode`
//! names the reason (`Reject`). Sequence checks (duplicates, reordering, loss) belong to
//! the receiver (`socket.rs`).
//!
//! Must not: allocate, log or do I/O (encode and decode run per datagram in the loops).

use std::fmt;

use crate::ipc::messages::{ActuatorCommand, Compensation, DisplacementSample, LocalLaw};

/// First four bytes of every datagram.
pub const MAGIC: [u8; 4] = *b"FEMU";
/// Version of the datagram layouts and their meaning; bumped on any change.
/// 3: the sample carries the rig's commanded force (rig ABI 4).
pub const LINK_VERSION: u16 = 3;
/// Bytes of the common header.
pub const HEADER_BYTES: usize = 24;

/// Datagram kinds (header offset 6).
pub mod kind {
    /// Rig -> fastemu: one displacement sample and the rig's state.
    pub const SAMPLE: u16 = 1;
    /// fastemu -> rig: the actuator command (mode, local law, force limits).
    pub const COMMAND: u16 = 2;
    /// fastemu -> rig: run control (start, stop, hold, resume, end).
    pub const CONTROL: u16 = 3;
    /// Rig -> fastemu: readiness before the start, the end after the run.
    pub const STATUS: u16 = 4;
}

/// Size of each kind's datagram, bytes (a datagram of any other length is rejected).
pub const SAMPLE_BYTES: usize = 96;
pub const COMMAND_BYTES: usize = 184;
pub const CONTROL_BYTES: usize = 56;
pub const STATUS_BYTES: usize = 40;
/// The largest datagram of the protocol.
pub const MAX_DATAGRAM_BYTES: usize = COMMAND_BYTES;

/// The size of a kind's datagram, `None` for an unknown kind.
pub fn datagram_bytes(kind: u16) -> Option<usize> {
    match kind {
        kind::SAMPLE => Some(SAMPLE_BYTES),
        kind::COMMAND => Some(COMMAND_BYTES),
        kind::CONTROL => Some(CONTROL_BYTES),
        kind::STATUS => Some(STATUS_BYTES),
        _ => None,
    }
}

/// Whether a peer's period is the same loop period: equal up to rounding (a relative
/// 1e-5, 2.4 ns at 4096 Hz), so a rig that truncates 1e9/4096 instead of rounding it
/// is not refused.
pub fn same_period(a_ns: u64, b_ns: u64) -> bool {
    a_ns.abs_diff(b_ns) as f64 <= 1e-5 * a_ns.max(b_ns) as f64
}

/// Which end of the link decodes: each accepts only the kinds sent to it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// fastemu's end: accepts `SAMPLE` and `STATUS`.
    Fastemu,
    /// The rig's end: accepts `COMMAND` and `CONTROL`.
    Rig,
}

impl Side {
    pub fn accepts(self, kind: u16) -> bool {
        match self {
            Side::Fastemu => matches!(kind, kind::SAMPLE | kind::STATUS),
            Side::Rig => matches!(kind, kind::COMMAND | kind::CONTROL),
        }
    }
}

/// Why a datagram was rejected (counted per reason, never used).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reject {
    /// Shorter than its header or its kind's size.
    Truncated,
    /// Longer than its kind's size.
    Oversized,
    BadMagic,
    BadVersion,
    UnknownKind,
    /// A known kind that does not travel to this end (e.g. a `COMMAND` sent to fastemu).
    WrongDirection,
    /// From an address other than the configured peer.
    ForeignSender,
    /// The same sequence number as the newest accepted datagram of its kind.
    Duplicate,
    /// Older than the newest accepted datagram of its kind (late, or replayed).
    Reordered,
    /// Framing right, content not: an unknown run command, a status with another period.
    BadContent,
}

impl Reject {
    pub const ALL: [Reject; 10] = [
        Reject::Truncated,
        Reject::Oversized,
        Reject::BadMagic,
        Reject::BadVersion,
        Reject::UnknownKind,
        Reject::WrongDirection,
        Reject::ForeignSender,
        Reject::Duplicate,
        Reject::Reordered,
        Reject::BadContent,
    ];

    /// Key in reports (`link.rejected.<name>`).
    pub fn name(self) -> &'static str {
        match self {
            Reject::Truncated => "truncated",
            Reject::Oversized => "oversized",
            Reject::BadMagic => "bad_magic",
            Reject::BadVersion => "bad_version",
            Reject::UnknownKind => "unknown_kind",
            Reject::WrongDirection => "wrong_direction",
            Reject::ForeignSender => "foreign_sender",
            Reject::Duplicate => "duplicate",
            Reject::Reordered => "reordered",
            Reject::BadContent => "bad_content",
        }
    }

    pub fn index(self) -> usize {
        self as usize
    }
}

impl fmt::Display for Reject {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// The common header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    pub kind: u16,
    /// The sender's counter of datagrams of this kind, from 0, +1 per datagram.
    pub sequence: u64,
    /// The sender's own monotonic clock when it sent the datagram, ns (any epoch).
    pub sender_time_ns: u64,
}

/// Rig -> fastemu: one sample (the iceoryx2 `DisplacementSample` without its publish
/// time, plus the echo that lets fastemu measure the link's round trip).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SampleDatagram {
    pub sample_sequence: u64,
    pub rig_time_ns: u64,
    pub displacement_m: f64,
    pub actuator_force_n: f64,
    pub status: u32,
    pub rig_state: u32,
    pub rig_fault_code: u32,
    /// `sender_time_ns` of the newest command datagram the rig received, 0 none yet.
    pub echo_command_time_ns: u64,
    /// Rig clock from that command's arrival to this datagram's sending, ns.
    pub echo_hold_ns: u64,
    /// The force command applied over the period before the sample, N; NaN: the rig does
    /// not say.
    pub commanded_force_n: f64,
}

impl SampleDatagram {
    /// The datagram of an iceoryx2 sample (`publish_time_ns` is not carried).
    pub fn of(sample: &DisplacementSample, echo_command_time_ns: u64, echo_hold_ns: u64) -> Self {
        SampleDatagram {
            sample_sequence: sample.sequence,
            rig_time_ns: sample.rig_time_ns,
            displacement_m: sample.displacement_m,
            actuator_force_n: sample.actuator_force_n,
            status: sample.status,
            rig_state: sample.rig_state,
            rig_fault_code: sample.rig_fault_code,
            echo_command_time_ns,
            echo_hold_ns,
            commanded_force_n: sample.commanded_force_n,
        }
    }

    /// The iceoryx2 sample, published at `publish_time_ns` (this machine's clock).
    pub fn to_sample(&self, publish_time_ns: u64) -> DisplacementSample {
        DisplacementSample {
            sequence: self.sample_sequence,
            rig_time_ns: self.rig_time_ns,
            publish_time_ns,
            displacement_m: self.displacement_m,
            actuator_force_n: self.actuator_force_n,
            status: self.status,
            rig_state: self.rig_state,
            rig_fault_code: self.rig_fault_code,
            reserved: 0,
            commanded_force_n: self.commanded_force_n,
        }
    }
}

/// fastemu -> rig: the actuator command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CommandDatagram {
    pub command: ActuatorCommand,
    /// `sender_time_ns` of the newest sample datagram fastemu received, 0 none yet (the
    /// rig may time its own round trip with it).
    pub echo_sample_time_ns: u64,
}

/// fastemu -> rig: run control.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ControlDatagram {
    /// One of `run_command`.
    pub command: u32,
    /// The run-control message's own sequence: repeats of one message carry the same
    /// number, and the rig acts once per number.
    pub control_sequence: u64,
    /// `START`: the rig takes its first sample this long after the datagram arrived, ns.
    pub start_delay_ns: u64,
    /// The loop period the rig must run at, ns.
    pub period_ns: u64,
}

/// Rig -> fastemu: readiness and end.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StatusDatagram {
    /// `HEARTBEAT_READY` (100) before the start, `rig_state::FINISHED` after the run.
    pub rig_state: u32,
    pub rig_fault_code: u32,
    /// The rig's own period, ns (checked against the configuration's).
    pub period_ns: u64,
}

/// A decoded datagram.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Datagram {
    Sample(SampleDatagram),
    Command(CommandDatagram),
    Control(ControlDatagram),
    Status(StatusDatagram),
}

/// Little-endian writer over a fixed buffer.
struct Put<'a> {
    buf: &'a mut [u8],
    at: usize,
}

impl Put<'_> {
    #[inline]
    fn bytes(&mut self, b: &[u8]) {
        self.buf[self.at..self.at + b.len()].copy_from_slice(b);
        self.at += b.len();
    }
    #[inline]
    fn u16(&mut self, v: u16) {
        self.bytes(&v.to_le_bytes());
    }
    #[inline]
    fn u32(&mut self, v: u32) {
        self.bytes(&v.to_le_bytes());
    }
    #[inline]
    fn u64(&mut self, v: u64) {
        self.bytes(&v.to_le_bytes());
    }
    #[inline]
    fn f64(&mut self, v: f64) {
        self.bytes(&v.to_le_bytes());
    }
}

/// Little-endian reader over a datagram whose length was checked.
struct Get<'a> {
    buf: &'a [u8],
    at: usize,
}

impl Get<'_> {
    #[inline]
    fn array<const N: usize>(&mut self) -> [u8; N] {
        let mut a = [0u8; N];
        a.copy_from_slice(&self.buf[self.at..self.at + N]);
        self.at += N;
        a
    }
    #[inline]
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.array())
    }
    #[inline]
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.array())
    }
    #[inline]
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.array())
    }
    #[inline]
    fn f64(&mut self) -> f64 {
        f64::from_le_bytes(self.array())
    }
}

fn header<'a>(buf: &'a mut [u8], header: &Header) -> Put<'a> {
    let mut put = Put { buf, at: 0 };
    put.bytes(&MAGIC);
    put.u16(LINK_VERSION);
    put.u16(header.kind);
    put.u64(header.sequence);
    put.u64(header.sender_time_ns);
    put
}

/// Writes a sample datagram into `buf`; returns its length.
#[inline]
pub fn encode_sample(
    buf: &mut [u8; MAX_DATAGRAM_BYTES],
    sequence: u64,
    sender_time_ns: u64,
    d: &SampleDatagram,
) -> usize {
    let h = Header {
        kind: kind::SAMPLE,
        sequence,
        sender_time_ns,
    };
    let mut p = header(buf, &h);
    p.u64(d.sample_sequence);
    p.u64(d.rig_time_ns);
    p.f64(d.displacement_m);
    p.f64(d.actuator_force_n);
    p.u32(d.status);
    p.u32(d.rig_state);
    p.u32(d.rig_fault_code);
    p.u32(0);
    p.u64(d.echo_command_time_ns);
    p.u64(d.echo_hold_ns);
    p.f64(d.commanded_force_n);
    debug_assert_eq!(p.at, SAMPLE_BYTES);
    SAMPLE_BYTES
}

/// Writes a command datagram into `buf`; returns its length.
#[inline]
pub fn encode_command(
    buf: &mut [u8; MAX_DATAGRAM_BYTES],
    sequence: u64,
    sender_time_ns: u64,
    d: &CommandDatagram,
) -> usize {
    let h = Header {
        kind: kind::COMMAND,
        sequence,
        sender_time_ns,
    };
    let c = &d.command;
    let mut p = header(buf, &h);
    p.u64(c.sequence);
    p.u64(c.setpoint_sequence);
    p.u64(c.sample_sequence);
    p.f64(c.law.force_n);
    p.f64(c.law.displacement_m);
    p.f64(c.law.velocity_m_per_s);
    p.f64(c.law.stiffness_n_per_m);
    p.f64(c.law.damping_ns_per_m);
    p.f64(c.law.force_rate_n_per_s);
    p.f64(c.law.stiffness_slope_n_per_m2);
    p.f64(c.force_min_n);
    p.f64(c.force_max_n);
    p.u32(c.mode);
    p.u32(c.controller_state);
    p.u32(c.fault_code);
    p.u32(0);
    p.u64(d.echo_sample_time_ns);
    let k = &c.compensation;
    p.f64(k.lead_s);
    p.f64(k.added_damping_ns_per_m);
    p.f64(k.added_damping_corner_hz);
    p.f64(k.gain);
    p.u32(k.lead_order);
    p.u32(0);
    debug_assert_eq!(p.at, COMMAND_BYTES);
    COMMAND_BYTES
}

/// Writes a control datagram into `buf`; returns its length.
#[inline]
pub fn encode_control(
    buf: &mut [u8; MAX_DATAGRAM_BYTES],
    sequence: u64,
    sender_time_ns: u64,
    d: &ControlDatagram,
) -> usize {
    let h = Header {
        kind: kind::CONTROL,
        sequence,
        sender_time_ns,
    };
    let mut p = header(buf, &h);
    p.u32(d.command);
    p.u32(0);
    p.u64(d.control_sequence);
    p.u64(d.start_delay_ns);
    p.u64(d.period_ns);
    debug_assert_eq!(p.at, CONTROL_BYTES);
    CONTROL_BYTES
}

/// Writes a status datagram into `buf`; returns its length.
#[inline]
pub fn encode_status(
    buf: &mut [u8; MAX_DATAGRAM_BYTES],
    sequence: u64,
    sender_time_ns: u64,
    d: &StatusDatagram,
) -> usize {
    let h = Header {
        kind: kind::STATUS,
        sequence,
        sender_time_ns,
    };
    let mut p = header(buf, &h);
    p.u32(d.rig_state);
    p.u32(d.rig_fault_code);
    p.u64(d.period_ns);
    debug_assert_eq!(p.at, STATUS_BYTES);
    STATUS_BYTES
}

/// Checks the framing of `bytes` for the receiving `side` and decodes it.
#[inline]
pub fn decode(bytes: &[u8], side: Side) -> Result<(Header, Datagram), Reject> {
    if bytes.len() < HEADER_BYTES {
        // Too short to hold a header; a wrong magic says more when there is one.
        if bytes.len() >= 4 && bytes[0..4] != MAGIC {
            return Err(Reject::BadMagic);
        }
        return Err(Reject::Truncated);
    }
    let mut g = Get { buf: bytes, at: 0 };
    if g.array::<4>() != MAGIC {
        return Err(Reject::BadMagic);
    }
    if g.u16() != LINK_VERSION {
        return Err(Reject::BadVersion);
    }
    let kind = g.u16();
    let size = datagram_bytes(kind).ok_or(Reject::UnknownKind)?;
    if !side.accepts(kind) {
        return Err(Reject::WrongDirection);
    }
    if bytes.len() < size {
        return Err(Reject::Truncated);
    }
    if bytes.len() > size {
        return Err(Reject::Oversized);
    }
    let header = Header {
        kind,
        sequence: g.u64(),
        sender_time_ns: g.u64(),
    };
    let datagram = match kind {
        kind::SAMPLE => {
            let sample_sequence = g.u64();
            let rig_time_ns = g.u64();
            let displacement_m = g.f64();
            let actuator_force_n = g.f64();
            let status = g.u32();
            let rig_state = g.u32();
            let rig_fault_code = g.u32();
            let _reserved = g.u32();
            Datagram::Sample(SampleDatagram {
                sample_sequence,
                rig_time_ns,
                displacement_m,
                actuator_force_n,
                status,
                rig_state,
                rig_fault_code,
                echo_command_time_ns: g.u64(),
                echo_hold_ns: g.u64(),
                commanded_force_n: g.f64(),
            })
        }
        kind::COMMAND => {
            let sequence = g.u64();
            let setpoint_sequence = g.u64();
            let sample_sequence = g.u64();
            let law = LocalLaw {
                force_n: g.f64(),
                displacement_m: g.f64(),
                velocity_m_per_s: g.f64(),
                stiffness_n_per_m: g.f64(),
                damping_ns_per_m: g.f64(),
                force_rate_n_per_s: g.f64(),
                stiffness_slope_n_per_m2: g.f64(),
            };
            let force_min_n = g.f64();
            let force_max_n = g.f64();
            let mode = g.u32();
            let controller_state = g.u32();
            let fault_code = g.u32();
            let _reserved = g.u32();
            let echo_sample_time_ns = g.u64();
            let compensation = Compensation {
                lead_s: g.f64(),
                added_damping_ns_per_m: g.f64(),
                added_damping_corner_hz: g.f64(),
                gain: g.f64(),
                lead_order: g.u32(),
                reserved: 0,
            };
            Datagram::Command(CommandDatagram {
                command: ActuatorCommand {
                    sequence,
                    setpoint_sequence,
                    sample_sequence,
                    sample_publish_time_ns: 0,
                    law,
                    force_min_n,
                    force_max_n,
                    mode,
                    controller_state,
                    fault_code,
                    reserved: 0,
                    compensation,
                },
                echo_sample_time_ns,
            })
        }
        kind::CONTROL => {
            let command = g.u32();
            let _reserved = g.u32();
            Datagram::Control(ControlDatagram {
                command,
                control_sequence: g.u64(),
                start_delay_ns: g.u64(),
                period_ns: g.u64(),
            })
        }
        _ => Datagram::Status(StatusDatagram {
            rig_state: g.u32(),
            rig_fault_code: g.u32(),
            period_ns: g.u64(),
        }),
    };
    Ok((header, datagram))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ipc::messages::{command_mode, controller_state, run_command, sample_status};

    fn sample() -> SampleDatagram {
        SampleDatagram {
            sample_sequence: 41,
            rig_time_ns: 41 * 244_141,
            displacement_m: -3.25e-4,
            actuator_force_n: 19_876.5,
            status: sample_status::OK,
            rig_state: 1,
            rig_fault_code: 0,
            echo_command_time_ns: 77,
            echo_hold_ns: 12_000,
            commanded_force_n: 26_842.0,
        }
    }

    fn command() -> CommandDatagram {
        CommandDatagram {
            command: ActuatorCommand {
                sequence: 9,
                setpoint_sequence: 8,
                sample_sequence: u64::MAX,
                sample_publish_time_ns: 0,
                law: LocalLaw {
                    force_n: 2.0e4,
                    displacement_m: 3.5e-4,
                    velocity_m_per_s: -1e-3,
                    stiffness_n_per_m: 5.7e7,
                    damping_ns_per_m: 75.0,
                    force_rate_n_per_s: -12.5,
                    stiffness_slope_n_per_m2: 1e10,
                },
                force_min_n: -5e3,
                force_max_n: 1.2e5,
                mode: command_mode::LAW,
                controller_state: controller_state::RUNNING,
                fault_code: 0,
                reserved: 0,
                compensation: Compensation {
                    lead_s: 2.52e-4,
                    added_damping_ns_per_m: 1.5e3,
                    added_damping_corner_hz: 60.0,
                    gain: 0.97,
                    lead_order: 2,
                    reserved: 0,
                },
            },
            echo_sample_time_ns: 5,
        }
    }

    #[test]
    fn every_kind_round_trips_bit_for_bit_at_its_documented_size() {
        let mut buf = [0u8; MAX_DATAGRAM_BYTES];
        let n = encode_sample(&mut buf, 3, 99, &sample());
        assert_eq!(n, SAMPLE_BYTES);
        let (h, d) = decode(&buf[..n], Side::Fastemu).unwrap();
        assert_eq!(
            (h.kind, h.sequence, h.sender_time_ns),
            (kind::SAMPLE, 3, 99)
        );
        assert_eq!(d, Datagram::Sample(sample()));
        let n = encode_command(&mut buf, 4, 100, &command());
        assert_eq!(n, COMMAND_BYTES);
        assert_eq!(
            decode(&buf[..n], Side::Rig).unwrap().1,
            Datagram::Command(command())
        );
        let control = ControlDatagram {
            command: run_command::START,
            control_sequence: 1,
            start_delay_ns: 50_000_000,
            period_ns: 244_141,
        };
        let n = encode_control(&mut buf, 0, 1, &control);
        assert_eq!(n, CONTROL_BYTES);
        assert_eq!(
            decode(&buf[..n], Side::Rig).unwrap().1,
            Datagram::Control(control)
        );
        let status = StatusDatagram {
            rig_state: 100,
            rig_fault_code: 0,
            period_ns: 244_141,
        };
        let n = encode_status(&mut buf, 0, 1, &status);
        assert_eq!(n, STATUS_BYTES);
        assert_eq!(
            decode(&buf[..n], Side::Fastemu).unwrap().1,
            Datagram::Status(status)
        );
    }

    #[test]
    fn the_header_is_little_endian_with_the_magic_first() {
        let mut buf = [0u8; MAX_DATAGRAM_BYTES];
        encode_sample(&mut buf, 0x0102_0304_0506_0708, 0x1112, &sample());
        assert_eq!(&buf[0..4], b"FEMU");
        assert_eq!(&buf[4..6], &[3, 0]);
        assert_eq!(&buf[6..8], &[1, 0]);
        assert_eq!(&buf[8..16], &[8, 7, 6, 5, 4, 3, 2, 1]);
        assert_eq!(&buf[16..18], &[0x12, 0x11]);
        // Displacement at offset 40, as the README table says.
        assert_eq!(
            f64::from_le_bytes(buf[40..48].try_into().unwrap()),
            -3.25e-4
        );
        // The commanded force, last, at offset 88 (link protocol 3).
        assert_eq!(
            f64::from_le_bytes(buf[88..96].try_into().unwrap()),
            26_842.0
        );
    }

    #[test]
    fn malformed_datagrams_are_rejected_by_reason() {
        let mut buf = [0u8; MAX_DATAGRAM_BYTES];
        let n = encode_sample(&mut buf, 0, 0, &sample());
        let good = buf[..n].to_vec();
        let check = |bytes: &[u8], side: Side, reason: Reject| {
            assert_eq!(decode(bytes, side).unwrap_err(), reason, "{bytes:?}");
        };
        check(&good[..n - 1], Side::Fastemu, Reject::Truncated);
        check(&good[..10], Side::Fastemu, Reject::Truncated);
        check(&[], Side::Fastemu, Reject::Truncated);
        let mut long = good.clone();
        long.push(0);
        check(&long, Side::Fastemu, Reject::Oversized);
        let mut bad = good.clone();
        bad[0] = b'X';
        check(&bad, Side::Fastemu, Reject::BadMagic);
        let mut bad = good.clone();
        bad[4] = 1; // the previous link protocol
        check(&bad, Side::Fastemu, Reject::BadVersion);
        let mut bad = good.clone();
        bad[6] = 9;
        check(&bad, Side::Fastemu, Reject::UnknownKind);
        check(&good, Side::Rig, Reject::WrongDirection);
        // Random bytes never decode.
        let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
        for len in 0..300 {
            let bytes: Vec<u8> = (0..len)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    x as u8
                })
                .collect();
            assert!(decode(&bytes, Side::Fastemu).is_err());
            assert!(decode(&bytes, Side::Rig).is_err());
        }
    }
}
