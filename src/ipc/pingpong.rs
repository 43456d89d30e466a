//! iceoryx2 ping-pong endpoints for the latency benchmark (`bench::latency`).
//!
//! One `IoxPingPong` per process holds two pairs of publish-subscribe services carrying
//! the loop's real `DisplacementSample`: a pair read by busy polling, and a pair whose
//! publishers also notify an event service so the reader can block on its listener
//! (the way the loop's controller, which must not burn a core, waits). The pinger publishes
//! on `<prefix>/…/ping` and reads `…/pong`; the ponger does the opposite.
//! Must not: time anything or allocate on the send/receive path beyond the one block
//! iceoryx2 0.10 makes per loan (`ipc::transport`; from `rt::pool` on the bench's threads,
//! which their set-up marks real-time); that cost is measured.

use std::fmt;
use std::time::{Duration, Instant};

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

use super::messages::DisplacementSample;

/// Which side of the ping-pong this process is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IoxRole {
    /// Sends pings, reads pongs (the measuring process).
    Pinger,
    /// Reads pings, sends pongs (the echo peer).
    Ponger,
}

/// A failure of the iceoryx2 layer, with iceoryx2's own error text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum IpcError {
    /// Creating the node, a service or a port failed.
    Setup { what: String, detail: String },
    /// Loaning or sending a sample or notifying failed.
    Send { detail: String },
    /// Receiving a sample or waiting failed.
    Receive { detail: String },
}

impl fmt::Display for IpcError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            IpcError::Setup { what, detail } => {
                write!(f, "iceoryx2: cannot create {what}: {detail}")
            }
            IpcError::Send { detail } => write!(f, "iceoryx2: send failed: {detail}"),
            IpcError::Receive { detail } => write!(f, "iceoryx2: receive failed: {detail}"),
        }
    }
}

impl std::error::Error for IpcError {}

fn setup_err(what: impl Into<String>) -> impl FnOnce(String) -> IpcError {
    let what = what.into();
    move |detail| IpcError::Setup { what, detail }
}

/// Silences iceoryx2's informational logging (e.g. "No config file was loaded"), which
/// would otherwise interleave with the benchmark's stderr progress.
pub fn quiet_iceoryx2_logging() {
    set_log_level(LogLevel::Error);
}

type SamplePublisher = Publisher<ipc::Service, DisplacementSample, ()>;
type SampleSubscriber = Subscriber<ipc::Service, DisplacementSample, ()>;

/// Both ping-pong channels of one process. Dropping it removes this process's ports;
/// the services disappear with the last node that uses them.
pub struct IoxPingPong {
    busy_publisher: SamplePublisher,
    busy_subscriber: SampleSubscriber,
    event_publisher: SamplePublisher,
    event_subscriber: SampleSubscriber,
    event_notifier: Notifier<ipc::Service>,
    event_listener: Listener<ipc::Service>,
    // Declared last so the ports above are dropped before their node.
    _node: Node<ipc::Service>,
}

impl IoxPingPong {
    /// Opens (or creates) the services under `prefix`, which must be unique per run so
    /// parallel runs and tests never share a service. Every iceoryx2 file of the session is
    /// named with `file_prefix(prefix)` (as a run's are), so `cleanup::clear_run(prefix)`
    /// removes them all afterwards, iceoryx2's own management files included.
    pub fn new(prefix: &str, role: IoxRole) -> Result<IoxPingPong, IpcError> {
        let config =
            super::transport::run_config(prefix).map_err(|e| setup_err("config")(e.to_string()))?;
        let node = NodeBuilder::new()
            .config(&config)
            // Ctrl-C must end the benchmark at once, not set a flag nobody polls while
            // a busy-polling round runs.
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| setup_err("node")(format!("{e:?}")))?;
        let (out_suffix, in_suffix) = match role {
            IoxRole::Pinger => ("ping", "pong"),
            IoxRole::Ponger => ("pong", "ping"),
        };
        let busy_out = open_sample_service(&node, &format!("{prefix}/busy/{out_suffix}"))?;
        let busy_in = open_sample_service(&node, &format!("{prefix}/busy/{in_suffix}"))?;
        let event_out = open_sample_service(&node, &format!("{prefix}/event/{out_suffix}"))?;
        let event_in = open_sample_service(&node, &format!("{prefix}/event/{in_suffix}"))?;
        let wake_out = open_event_service(&node, &format!("{prefix}/wake/{out_suffix}"))?;
        let wake_in = open_event_service(&node, &format!("{prefix}/wake/{in_suffix}"))?;

        let publisher = |svc: &iceoryx2::service::port_factory::publish_subscribe::PortFactory<
            ipc::Service,
            DisplacementSample,
            (),
        >| {
            svc.publisher_builder()
                .create()
                .map_err(|e| setup_err("publisher")(format!("{e:?}")))
        };
        let subscriber = |svc: &iceoryx2::service::port_factory::publish_subscribe::PortFactory<
            ipc::Service,
            DisplacementSample,
            (),
        >| {
            svc.subscriber_builder()
                .create()
                .map_err(|e| setup_err("subscriber")(format!("{e:?}")))
        };
        Ok(IoxPingPong {
            busy_publisher: publisher(&busy_out)?,
            busy_subscriber: subscriber(&busy_in)?,
            event_publisher: publisher(&event_out)?,
            event_subscriber: subscriber(&event_in)?,
            event_notifier: wake_out
                .notifier_builder()
                .create()
                .map_err(|e| setup_err("notifier")(format!("{e:?}")))?,
            event_listener: wake_in
                .listener_builder()
                .create()
                .map_err(|e| setup_err("listener")(format!("{e:?}")))?,
            _node: node,
        })
    }

    /// Publishes on the busy-polled channel.
    #[inline]
    pub fn send_busy(&self, sample: DisplacementSample) -> Result<(), IpcError> {
        send(&self.busy_publisher, sample)
    }

    /// Takes the next sample from the busy-polled channel, if one has arrived.
    #[inline]
    pub fn try_receive_busy(&self) -> Result<Option<DisplacementSample>, IpcError> {
        match self.busy_subscriber.receive() {
            Ok(Some(sample)) => Ok(Some(*sample)),
            Ok(None) => Ok(None),
            Err(e) => Err(IpcError::Receive {
                detail: format!("{e:?}"),
            }),
        }
    }

    /// Publishes on the event channel and wakes the other side's listener.
    #[inline]
    pub fn send_event(&self, sample: DisplacementSample) -> Result<(), IpcError> {
        send(&self.event_publisher, sample)?;
        self.event_notifier
            .notify()
            .map(|_| ())
            .map_err(|e| IpcError::Send {
                detail: format!("notify: {e:?}"),
            })
    }

    /// Runs `body` with a blocking receiver on the event channel (the listener itself,
    /// as the loop's controller waits: `transport::wait_on_listener`).
    pub fn with_event_waiter<R>(
        &self,
        body: impl FnOnce(&EventWaiter<'_>) -> R,
    ) -> Result<R, IpcError> {
        let waiter = EventWaiter {
            subscriber: &self.event_subscriber,
            listener: &self.event_listener,
        };
        Ok(body(&waiter))
    }
}

/// Blocking receive on the event channel (see `IoxPingPong::with_event_waiter`).
pub struct EventWaiter<'a> {
    subscriber: &'a SampleSubscriber,
    listener: &'a Listener<ipc::Service>,
}

impl EventWaiter<'_> {
    /// Returns the next sample, sleeping on the listener until the peer notifies;
    /// `Ok(None)` if nothing arrived within `timeout`.
    pub fn receive(&self, timeout: Duration) -> Result<Option<DisplacementSample>, IpcError> {
        let deadline = Instant::now() + timeout;
        loop {
            // Data is checked before sleeping: a notification that arrived before the
            // wait is still pending on the listener, but the sample may already be here.
            match self.subscriber.receive() {
                Ok(Some(sample)) => return Ok(Some(*sample)),
                Ok(None) => {}
                Err(e) => {
                    return Err(IpcError::Receive {
                        detail: format!("{e:?}"),
                    })
                }
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            // Wakes on a notification and consumes every pending one (as the loop's
            // controller waits).
            super::transport::wait_on_listener(self.listener, deadline - now);
        }
    }
}

#[inline]
fn send(publisher: &SamplePublisher, sample: DisplacementSample) -> Result<(), IpcError> {
    let uninit = publisher.loan_uninit().map_err(|e| IpcError::Send {
        detail: format!("loan: {e:?}"),
    })?;
    uninit
        .write_payload(sample)
        .send()
        .map(|_| ())
        .map_err(|e| IpcError::Send {
            detail: format!("{e:?}"),
        })
}

fn service_name(name: &str) -> Result<ServiceName, IpcError> {
    ServiceName::new(name)
        .map_err(|e| setup_err(format!("service name `{name}`"))(format!("{e:?}")))
}

fn open_sample_service(
    node: &Node<ipc::Service>,
    name: &str,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<
        ipc::Service,
        DisplacementSample,
        (),
    >,
    IpcError,
> {
    // Ping-pong has exactly one message in flight: no history, a one-slot buffer and
    // one port of each kind. Both sides request the same settings, so either may create.
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<DisplacementSample>()
        .history_size(0)
        .subscriber_max_buffer_size(1)
        .enable_safe_overflow(true)
        .max_publishers(1)
        .max_subscribers(1)
        .max_nodes(2)
        .open_or_create()
        .map_err(|e| setup_err(format!("service `{name}`"))(format!("{e:?}")))
}

fn open_event_service(
    node: &Node<ipc::Service>,
    name: &str,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>, IpcError> {
    node.service_builder(&service_name(name)?)
        .event()
        .max_notifiers(1)
        .max_listeners(1)
        .max_nodes(2)
        .open_or_create()
        .map_err(|e| setup_err(format!("event service `{name}`"))(format!("{e:?}")))
}
