//! The rig's end of the UDP rig link, as the simulated rig (`bench_rig --link-bind ...`)
//! runs it, and as a real-time target must: status datagrams until the start, one sample
//! datagram per period (with the echo of the newest command for fastemu's round-trip
//! measurement), commands and run control drained once per period, a bounded number of
//! datagrams per period so a flood cannot stop the rig's clock, each run-control message
//! acted on once. The rig's own interlock (hold on stale commands) needs nothing from
//! here: a silent link delivers no commands, and the servo holds.
//!
//! Must not: allocate, lock or log in `send_sample`/`receive_commands` (per period).

use std::net::SocketAddr;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use super::protocol::{Datagram, SampleDatagram, Side, StatusDatagram};
use super::socket::{open_link, LinkError, LinkReceiver, LinkSender, Receive};
use crate::hil::process::{termination_requested, ControlRequests, ProcessError, StartInfo};
use crate::ipc::messages::{
    rig_state, run_command, ActuatorCommand, DisplacementSample, Heartbeat, HEARTBEAT_READY,
};
use crate::rig::transport::RigTransport;
use crate::rt::clock::monotonic_now_ns;

/// Most datagrams read per period; the rest wait for the next period (a flood of
/// garbage then costs at most this many reads per period).
pub const MAX_DATAGRAMS_PER_PERIOD: usize = 64;
/// Status datagrams before the start, one per this many ns.
const READY_EVERY_NS: u64 = 10_000_000;
/// Status datagrams sent after the end-of-run sample (several: one may be lost).
const FINISHED_REPEATS: usize = 3;

/// The rig's end of the link.
#[derive(Debug)]
pub struct UdpRigEnd {
    sender: LinkSender,
    receiver: LinkReceiver,
    period_ns: u64,
    start_timeout: Duration,
    /// Sender time of the newest command, and when this rig read it (its clock).
    echo_command_time_ns: u64,
    command_read_ns: u64,
    /// Newest run-control message acted on.
    control_seen: Option<u64>,
    pending: ControlRequests,
    /// Periods that ended with datagrams still waiting (the bound was reached).
    pub bound_reached: u64,
}

impl UdpRigEnd {
    /// Opens the rig's end: bound to `bind`, talking to `peer`, at loop period `period_ns`.
    pub fn open(
        bind: SocketAddr,
        peer: SocketAddr,
        period_ns: u64,
        start_timeout: Duration,
    ) -> Result<UdpRigEnd, LinkError> {
        let (sender, receiver) = open_link(bind, peer, Side::Rig, None)?;
        Ok(UdpRigEnd::on(sender, receiver, period_ns, start_timeout))
    }

    /// The rig's end on a socket already bound (see `open_link_socket`).
    pub fn open_socket(
        socket: std::net::UdpSocket,
        peer: SocketAddr,
        period_ns: u64,
        start_timeout: Duration,
    ) -> Result<UdpRigEnd, LinkError> {
        let (sender, receiver) = super::socket::open_link_socket(socket, peer, Side::Rig, None)?;
        Ok(UdpRigEnd::on(sender, receiver, period_ns, start_timeout))
    }

    fn on(
        sender: LinkSender,
        mut receiver: LinkReceiver,
        period_ns: u64,
        start_timeout: Duration,
    ) -> UdpRigEnd {
        receiver.expect_period(period_ns);
        UdpRigEnd {
            sender,
            receiver,
            period_ns,
            start_timeout,
            echo_command_time_ns: 0,
            command_read_ns: 0,
            control_seen: None,
            pending: ControlRequests::default(),
            bound_reached: 0,
        }
    }

    /// Reads what is waiting (at most `MAX_DATAGRAMS_PER_PERIOD`): commands go to
    /// `on_command`, run control into `pending` (a `START` is returned with its arrival).
    fn drain(
        &mut self,
        on_command: &mut dyn FnMut(&ActuatorCommand),
    ) -> Option<(u64, super::protocol::ControlDatagram)> {
        let mut start = None;
        for _ in 0..MAX_DATAGRAMS_PER_PERIOD {
            let received = match self.receiver.receive() {
                Receive::Nothing => return start,
                Receive::Rejected(_) => continue,
                Receive::Accepted(r) => r,
            };
            match received.datagram {
                Datagram::Command(c) => {
                    self.echo_command_time_ns = received.header.sender_time_ns;
                    self.command_read_ns = received.arrival_ns;
                    on_command(&c.command);
                }
                Datagram::Control(c) => {
                    if self.control_seen.is_some_and(|s| c.control_sequence <= s) {
                        continue; // a repeat of a message already acted on
                    }
                    // The receiver checked the command and START's period.
                    self.control_seen = Some(c.control_sequence);
                    match c.command {
                        run_command::START => start = Some((received.arrival_ns, c)),
                        run_command::STOP => self.pending.stop = true,
                        run_command::HOLD => self.pending.hold = true,
                        run_command::RESUME => self.pending.resume = true,
                        _ => self.pending.end = true,
                    }
                }
                // The receiver only accepts the rig's kinds.
                _ => {}
            }
        }
        self.bound_reached += 1;
        start
    }

    /// The counts for the rig's summary (`link` in `rig-summary.json`).
    pub fn summary_json(&self) -> serde_json::Value {
        let c = &self.receiver.counts;
        serde_json::json!({
            "bind": self.receiver.local_addr().map(|a| a.to_string()).unwrap_or_default(),
            "peer": self.sender.peer().to_string(),
            "sent": self.sender.sent,
            "send_errors": self.sender.send_errors,
            "received": c.accepted,
            "rejected": c.rejected_json(),
            "rejected_total": c.rejected_total(),
            "lost": c.lost,
            "socket_errors": c.socket_errors,
            "periods_at_read_bound": self.bound_reached,
        })
    }
}

impl RigTransport for UdpRigEnd {
    fn wait_for_start(&mut self) -> Result<StartInfo, ProcessError> {
        let deadline = monotonic_now_ns() + self.start_timeout.as_nanos() as u64;
        let mut next_status = 0u64;
        loop {
            let now = monotonic_now_ns();
            if now >= next_status {
                next_status = now + READY_EVERY_NS;
                self.sender.send_status(&StatusDatagram {
                    rig_state: HEARTBEAT_READY,
                    rig_fault_code: 0,
                    period_ns: self.period_ns,
                });
            }
            // Commands before the start are not used (the servo is not running yet).
            if let Some((arrival_ns, start)) = self.drain(&mut |_| {}) {
                let t0_ns = arrival_ns + start.start_delay_ns;
                let unix_now = SystemTime::now()
                    .duration_since(UNIX_EPOCH)
                    .map_or(0, |d| d.as_nanos() as u64);
                let now = monotonic_now_ns();
                return Ok(StartInfo {
                    t0_ns,
                    start_unix_ns: unix_now + t0_ns.saturating_sub(now),
                });
            }
            if self.pending.stop || termination_requested() {
                return Err(ProcessError("stopped before start".into()));
            }
            if now > deadline {
                return Err(ProcessError(format!(
                    "no start datagram from {} within {:?}",
                    self.sender.peer(),
                    self.start_timeout
                )));
            }
            // Wake when a datagram arrives: the START's arrival time sets the clock.
            self.receiver.wait_readable(Duration::from_millis(2));
        }
    }

    #[inline]
    fn send_sample(&mut self, sample: &DisplacementSample) {
        let hold_ns = if self.echo_command_time_ns == 0 {
            0
        } else {
            monotonic_now_ns().saturating_sub(self.command_read_ns)
        };
        self.sender.send_sample(&SampleDatagram::of(
            sample,
            self.echo_command_time_ns,
            hold_ns,
        ));
    }

    #[inline]
    fn receive_commands(&mut self, on_command: &mut dyn FnMut(&ActuatorCommand)) {
        // A START repeated after the start is already known (`control_seen`).
        let _ = self.drain(on_command);
    }

    fn heartbeat(&mut self, _heartbeat: &Heartbeat) -> ControlRequests {
        // The rig's state travels in every sample datagram: no separate heartbeat.
        std::mem::take(&mut self.pending)
    }

    fn counts_json(&self) -> Option<serde_json::Value> {
        Some(self.summary_json())
    }
    fn finish(&mut self, last: &DisplacementSample, heartbeat: &Heartbeat) {
        self.send_sample(last);
        for _ in 0..FINISHED_REPEATS {
            self.sender.send_status(&StatusDatagram {
                rig_state: rig_state::FINISHED,
                rig_fault_code: heartbeat.fault_code,
                period_ns: self.period_ns,
            });
        }
    }
}
