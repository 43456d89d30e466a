//! The loop's iceoryx2 services and ports: one `IpcNode` per process, services named
//! `fastemu/<run_id>/<stream>`, all iceoryx2 files named with a per-run file prefix.
//!
//! Must not: allocate, lock or log on `publish`/`receive_newest`/`notify`/`wait_for` (the
//! per-sample path) beyond what iceoryx2 0.10 does inside a publish: one small block per
//! loan (the sample's shared state, an `Rc`), freed when it is sent (`ipc_alloc` counts it);
//! on a loop thread that block comes from `rt::pool`, not the system allocator.
//! Every service is opened-or-created with the same settings by every process, so the
//! start order of the processes does not matter.

use std::fmt;
use std::time::Duration;

use iceoryx2::config::Config;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;

use super::messages::{ActuatorCommand, DisplacementSample, ForceSetpoint, Heartbeat, RunControl};

/// An IPC setup error: which step failed and the iceoryx2 error text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IpcError {
    pub what: String,
    pub detail: String,
}

impl fmt::Display for IpcError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "iceoryx2: {}: {}", self.what, self.detail)
    }
}

impl std::error::Error for IpcError {}

fn ipc_err(what: impl Into<String>) -> impl FnOnce(String) -> IpcError {
    let what = what.into();
    move |detail| IpcError { what, detail }
}

/// The streams of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stream {
    Displacement,
    Setpoint,
    Command,
    Heartbeat,
    Control,
    /// `fastemu ctl`'s requests to the run's orchestrator (never read by a loop).
    OperatorRequest,
    /// The heartbeats the orchestrator relays to `fastemu ctl` (never written by a loop).
    OperatorStatus,
}

impl Stream {
    pub fn name(self) -> &'static str {
        match self {
            Stream::Displacement => "displacement",
            Stream::Setpoint => "setpoint",
            Stream::Command => "command",
            Stream::Heartbeat => "heartbeat",
            Stream::Control => "control",
            Stream::OperatorRequest => "operator_request",
            Stream::OperatorStatus => "operator_status",
        }
    }
}

/// File-name prefix of every iceoryx2 file of run `run_id` (`/dev/shm/<prefix>*`,
/// `/tmp/iceoryx2/**/<prefix>*`). Run ids are `fe<orchestrator pid>x<counter>`, so a
/// crashed run's files can be found and its orchestrator checked for life.
pub fn file_prefix(run_id: &str) -> String {
    format!("{run_id}_")
}

/// Quiets iceoryx2's own logging (warnings such as "no config file was loaded").
pub fn quiet_iceoryx2_logs() {
    set_log_level(LogLevel::Error);
}

/// The iceoryx2 config of run `run_id`: the default config with a per-run file prefix.
pub fn run_config(run_id: &str) -> Result<Config, IpcError> {
    let mut config = Config::default();
    config.global.prefix = FileName::new(file_prefix(run_id).as_bytes())
        .map_err(|e| ipc_err(format!("run id `{run_id}` as file prefix"))(format!("{e:?}")))?;
    Ok(config)
}

/// Removes the iceoryx2 resources of dead nodes of run `run_id`; returns (cleaned, failed).
pub fn cleanup_dead_nodes(run_id: &str) -> Result<(u64, u64), IpcError> {
    let config = run_config(run_id)?;
    let mut cleaned = 0;
    let mut failed = 0;
    let mut dead = Vec::new();
    Node::<ipc::Service>::list(&config, |state| {
        if let NodeState::Dead(view) = state {
            dead.push(view);
        }
        CallbackProgression::Continue
    })
    .map_err(|e| ipc_err("listing nodes")(format!("{e:?}")))?;
    for view in dead {
        match view.try_remove_stale_resources() {
            Ok(()) => cleaned += 1,
            Err(_) => failed += 1,
        }
    }
    Ok((cleaned, failed))
}

/// Number of live (or undecidable) iceoryx2 nodes of run `run_id`.
pub fn count_nodes(run_id: &str) -> Result<usize, IpcError> {
    let config = run_config(run_id)?;
    let mut n = 0;
    Node::<ipc::Service>::list(&config, |_| {
        n += 1;
        CallbackProgression::Continue
    })
    .map_err(|e| ipc_err("listing nodes")(format!("{e:?}")))?;
    Ok(n)
}

/// One process's iceoryx2 node for run `run_id`.
pub struct IpcNode {
    node: Node<ipc::Service>,
    run_id: String,
}

type Pub<T> = Publisher<ipc::Service, T, ()>;
type Sub<T> = Subscriber<ipc::Service, T, ()>;

/// A publisher: `publish` adds no allocation of its own to the one block iceoryx2 0.10's
/// loan makes and frees within the call (`ipc_alloc`).
pub struct Out<T: fmt::Debug + ZeroCopySend + Copy + 'static> {
    publisher: Pub<T>,
}

impl<T: fmt::Debug + ZeroCopySend + Copy + 'static> Out<T> {
    /// Publishes a copy of `value`; returns false if iceoryx2 refused it.
    #[inline]
    pub fn publish(&self, value: T) -> bool {
        self.publisher.send_copy(value).is_ok()
    }
}

/// A subscriber with a small overwrite-oldest buffer.
pub struct In<T: fmt::Debug + ZeroCopySend + Copy + 'static> {
    subscriber: Sub<T>,
}

impl<T: fmt::Debug + ZeroCopySend + Copy + 'static> In<T> {
    /// Drains the buffer and returns the newest value, if any arrived.
    #[inline]
    pub fn receive_newest(&self) -> Option<T> {
        let mut newest = None;
        while let Ok(Some(sample)) = self.subscriber.receive() {
            newest = Some(*sample);
        }
        newest
    }

    /// Calls `f` on every value received since the last call, oldest first.
    #[inline]
    pub fn receive_each(&self, mut f: impl FnMut(T)) {
        while let Ok(Some(sample)) = self.subscriber.receive() {
            f(*sample);
        }
    }
}

/// Wakes a blocked listener.
pub struct Wake {
    notifier: Notifier<ipc::Service>,
}

impl Wake {
    #[inline]
    pub fn notify(&self) {
        let _ = self.notifier.notify();
    }
}

/// A port whose connections to the counterparts that exist now can be made before its
/// loop: iceoryx2 0.10 builds a connection (names, paths, shared-memory handles, on the
/// heap) in the first send, receive or notify after a counterpart appears, so a loop that
/// starts before they are made allocates in its first periods (the processes' `rt_pool`
/// counted 3-15 such requests per loop). After START every process's ports exist.
pub trait Connect {
    fn connect(&self);
}

impl<T: fmt::Debug + ZeroCopySend + Copy + 'static> Connect for Out<T> {
    fn connect(&self) {
        let _ = self.publisher.update_connections();
    }
}

impl<T: fmt::Debug + ZeroCopySend + Copy + 'static> Connect for In<T> {
    fn connect(&self) {
        let _ = self.subscriber.update_connections();
    }
}

impl Connect for Wake {
    fn connect(&self) {
        let _ = self.notifier.update_connections();
    }
}

/// Makes `ports`' connections now (`Connect`): called by each loop process after START,
/// before its loop.
pub fn connect_all(ports: &[&dyn Connect]) {
    for port in ports {
        port.connect();
    }
}

/// Blocks until woken (event-driven, no busy polling).
pub struct WakeListener {
    listener: Listener<ipc::Service>,
}

impl WakeListener {
    /// Blocks until a notification arrives or `timeout` passes; consumes every pending
    /// notification, so the next wait blocks again; returns whether woken
    /// (`wait_on_listener`).
    pub fn wait_for(&self, timeout: Duration) -> bool {
        wait_on_listener(&self.listener, timeout)
    }
}

/// Blocks until `listener` is notified or `timeout` passes, then consumes every pending
/// notification; returns whether one was pending. Allocates nothing: it polls the
/// listener's own descriptor (`ppoll`, a nanosecond timeout; a 1.95 ms wait lasts
/// 2.02-2.09 ms) where a `WaitSet` allocated two blocks per wake-up in iceoryx2 0.10, and
/// the listener's `timed_wait` rounds its timeout up to kernel ticks (the same wait
/// lasted 8.0 ms, median of 20, at this kernel's 250 Hz: the controller's keep-alive of 8
/// periods would come every 33).
pub fn wait_on_listener(listener: &Listener<ipc::Service>, timeout: Duration) -> bool {
    // SAFETY: the listener's descriptor, which iceoryx2 keeps for the listener's life.
    let fd = unsafe { listener.file_descriptor().native_handle() };
    let mut poll = libc::pollfd {
        fd,
        events: libc::POLLIN,
        revents: 0,
    };
    let ts = libc::timespec {
        tv_sec: timeout.as_secs().min(i32::MAX as u64) as libc::time_t,
        tv_nsec: timeout.subsec_nanos() as libc::c_long,
    };
    // SAFETY: one valid pollfd, a valid timespec, no signal mask.
    let ready = unsafe { libc::ppoll(&mut poll, 1, &ts, std::ptr::null()) };
    let consumed = listener.try_wait(|_| {}).unwrap_or(0);
    if ready < 0 && consumed == 0 {
        // A wait that fails at once (not a signal) must not turn its caller (a SCHED_FIFO
        // thread above the loops) into a spin: it waits out its timeout instead.
        if std::io::Error::last_os_error().raw_os_error() != Some(libc::EINTR) {
            std::thread::sleep(timeout);
        }
        return false;
    }
    ready > 0 || consumed > 0
}

impl IpcNode {
    /// The service name of `stream` in this run: `fastemu/<run_id>/<stream>`.
    pub fn stream_service_name(run_id: &str, stream: Stream) -> String {
        format!("fastemu/{run_id}/{}", stream.name())
    }

    /// Creates the node of process `process_name` in run `run_id`.
    pub fn new(run_id: &str, process_name: &str) -> Result<IpcNode, IpcError> {
        let config = run_config(run_id)?;
        let name =
            NodeName::new(process_name).map_err(|e| ipc_err("node name")(format!("{e:?}")))?;
        let node = NodeBuilder::new()
            .name(&name)
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| ipc_err("creating node")(format!("{e:?}")))?;
        Ok(IpcNode {
            node,
            run_id: run_id.to_string(),
        })
    }

    fn service_name(&self, stream: &str) -> Result<ServiceName, IpcError> {
        let text = format!("fastemu/{}/{}", self.run_id, stream);
        ServiceName::new(&text)
            .map_err(|e| ipc_err(format!("service name {text}"))(format!("{e:?}")))
    }

    fn pubsub<T: fmt::Debug + ZeroCopySend + Copy + 'static>(
        &self,
        stream: Stream,
    ) -> Result<
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, T, ()>,
        IpcError,
    > {
        // Loop streams keep the newest few samples (the reader wants the newest; older
        // ones are overwritten, never block the writer).
        let (history, buffer, max_publishers, max_subscribers) = service_settings(stream);
        self.node
            .service_builder(&self.service_name(stream.name())?)
            .publish_subscribe::<T>()
            .history_size(history)
            .subscriber_max_buffer_size(buffer)
            .enable_safe_overflow(true)
            .max_publishers(max_publishers)
            .max_subscribers(max_subscribers)
            .max_nodes(MAX_NODES)
            .open_or_create()
            .map_err(|e| ipc_err(format!("opening service {}", stream.name()))(format!("{e:?}")))
    }

    fn out<T: fmt::Debug + ZeroCopySend + Copy + 'static>(
        &self,
        stream: Stream,
    ) -> Result<Out<T>, IpcError> {
        let publisher = self
            .pubsub::<T>(stream)?
            .publisher_builder()
            .create()
            .map_err(|e| ipc_err(format!("publisher on {}", stream.name()))(format!("{e:?}")))?;
        Ok(Out { publisher })
    }

    fn input<T: fmt::Debug + ZeroCopySend + Copy + 'static>(
        &self,
        stream: Stream,
    ) -> Result<In<T>, IpcError> {
        let subscriber = self
            .pubsub::<T>(stream)?
            .subscriber_builder()
            .create()
            .map_err(|e| ipc_err(format!("subscriber on {}", stream.name()))(format!("{e:?}")))?;
        Ok(In { subscriber })
    }

    fn event(
        &self,
        stream: Stream,
    ) -> Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>, IpcError> {
        self.node
            .service_builder(&self.service_name(&format!("{}_event", stream.name()))?)
            .event()
            .max_notifiers(2)
            .max_listeners(2)
            .max_nodes(8)
            .open_or_create()
            .map_err(|e| ipc_err(format!("opening event {}", stream.name()))(format!("{e:?}")))
    }

    pub fn displacement_out(&self) -> Result<Out<DisplacementSample>, IpcError> {
        self.out(Stream::Displacement)
    }
    pub fn displacement_in(&self) -> Result<In<DisplacementSample>, IpcError> {
        self.input(Stream::Displacement)
    }
    pub fn setpoint_out(&self) -> Result<Out<ForceSetpoint>, IpcError> {
        self.out(Stream::Setpoint)
    }
    pub fn setpoint_in(&self) -> Result<In<ForceSetpoint>, IpcError> {
        self.input(Stream::Setpoint)
    }
    pub fn command_out(&self) -> Result<Out<ActuatorCommand>, IpcError> {
        self.out(Stream::Command)
    }
    pub fn command_in(&self) -> Result<In<ActuatorCommand>, IpcError> {
        self.input(Stream::Command)
    }
    pub fn heartbeat_out(&self) -> Result<Out<Heartbeat>, IpcError> {
        self.out(Stream::Heartbeat)
    }
    pub fn heartbeat_in(&self) -> Result<In<Heartbeat>, IpcError> {
        self.input(Stream::Heartbeat)
    }
    pub fn control_out(&self) -> Result<Out<RunControl>, IpcError> {
        self.out(Stream::Control)
    }
    pub fn control_in(&self) -> Result<In<RunControl>, IpcError> {
        self.input(Stream::Control)
    }
    pub fn operator_request_out(&self) -> Result<Out<RunControl>, IpcError> {
        self.out(Stream::OperatorRequest)
    }
    pub fn operator_request_in(&self) -> Result<In<RunControl>, IpcError> {
        self.input(Stream::OperatorRequest)
    }
    pub fn operator_status_out(&self) -> Result<Out<Heartbeat>, IpcError> {
        self.out(Stream::OperatorStatus)
    }
    pub fn operator_status_in(&self) -> Result<In<Heartbeat>, IpcError> {
        self.input(Stream::OperatorStatus)
    }

    /// Notifier that wakes whoever waits for new setpoints.
    pub fn setpoint_wake(&self) -> Result<Wake, IpcError> {
        let notifier = self
            .event(Stream::Setpoint)?
            .notifier_builder()
            .create()
            .map_err(|e| ipc_err("setpoint notifier")(format!("{e:?}")))?;
        Ok(Wake { notifier })
    }

    /// Listener for new-setpoint notifications.
    pub fn setpoint_listener(&self) -> Result<WakeListener, IpcError> {
        let listener = self
            .event(Stream::Setpoint)?
            .listener_builder()
            .create()
            .map_err(|e| ipc_err("setpoint listener")(format!("{e:?}")))?;
        Ok(WakeListener { listener })
    }

    /// Notifier that wakes whoever forwards new commands (the UDP rig link).
    pub fn command_wake(&self) -> Result<Wake, IpcError> {
        let notifier = self
            .event(Stream::Command)?
            .notifier_builder()
            .create()
            .map_err(|e| ipc_err("command notifier")(format!("{e:?}")))?;
        Ok(Wake { notifier })
    }

    /// Listener for new-command notifications.
    pub fn command_listener(&self) -> Result<WakeListener, IpcError> {
        let listener = self
            .event(Stream::Command)?
            .listener_builder()
            .create()
            .map_err(|e| ipc_err("command listener")(format!("{e:?}")))?;
        Ok(WakeListener { listener })
    }

    /// Creates (or opens) the services a rig connects to and keeps them while the
    /// returned value lives, so an external rig started later can simply open them.
    pub fn hold_rig_services(&self) -> Result<RigServices, IpcError> {
        Ok(RigServices {
            _displacement: self.pubsub::<DisplacementSample>(Stream::Displacement)?,
            _command: self.pubsub::<ActuatorCommand>(Stream::Command)?,
            _heartbeat: self.pubsub::<Heartbeat>(Stream::Heartbeat)?,
            _control: self.pubsub::<RunControl>(Stream::Control)?,
        })
    }
}

type Factory<T> =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, T, ()>;

/// The rig's services, kept open (see `IpcNode::hold_rig_services`).
pub struct RigServices {
    _displacement: Factory<DisplacementSample>,
    _command: Factory<ActuatorCommand>,
    _heartbeat: Factory<Heartbeat>,
    _control: Factory<RunControl>,
}

/// The settings every process opens or creates a stream's service with: (history size,
/// subscriber buffer size, max publishers, max subscribers); every service also has
/// safe overflow on and at most `MAX_NODES` nodes. An external rig that creates a service
/// (it starts before `hil`) must use these (README "Connecting a rig").
pub fn service_settings(stream: Stream) -> (usize, usize, usize, usize) {
    match stream {
        // The displacement stream holds 4096 samples (1 s at 4096 Hz): a reader stalled
        // by the OS for milliseconds still drains and validates every sample it missed,
        // so a single bad sample cannot be overwritten unseen; and an external rig's
        // samples, which are its only record, survive an emulator stall long enough to
        // trip the loop. With 256 (62 ms), a 300 ms emulator stall in front of an external
        // rig lost 974 samples, among them the rig's hold, which the report then dated at
        // the first sample after the gap, 187 ms late (2026-11-28).
        Stream::Displacement => (0, 4096, 1, 4),
        Stream::Setpoint | Stream::Command => (0, 8, 1, 4),
        // Heartbeats and control messages are rarer; control keeps its last message for
        // late subscribers.
        // The orchestrator subscribes to heartbeats and publishes control (for itself,
        // the live view and `fastemu ctl`); an external rig may read them too.
        Stream::Heartbeat => (0, 64, 4, 6),
        Stream::Control => (1, 8, 4, 4),
        // `fastemu ctl` speaks to the orchestrator only, never to a loop's ports: a port
        // that appears mid-run makes its counterparts build a connection (allocations,
        // shared-memory handles) in their next send or receive, and the loops' ports are
        // connected once, before the loops (`connect_all`). Up to 4 `ctl` at once.
        Stream::OperatorRequest => (0, 8, 4, 1),
        Stream::OperatorStatus => (0, 64, 1, 4),
    }
}

/// Largest number of nodes on any service of a run.
pub const MAX_NODES: usize = 8;
