//! The `bench_rig` process: runs `RigCore` on its own fixed-step clock, publishes one
//! displacement sample per period, feeds commands to the actuator's servo, and streams
//! its records. It behaves as hardware does: a late wake-up does not stop time (the missed
//! periods run in a catch-up, servo included), its interlock holds the specimen on stale
//! commands without help from any other process, and when `fastemu hil` dies it holds,
//! records until the specimen is at rest, writes its records, clears the run's shared
//! memory and exits.
//!
//! The same loop runs on iceoryx2 (`run_rig_ipc`: the simulated rig started by `hil`, or
//! started by hand as an external rig) or over any `RigTransport` its caller builds
//! (`run_rig`: the far end of the UDP rig link, `link::rig_end::UdpRigEnd`, built by the
//! CLI; `rig/` never imports `link/`).
//!
//! Must not: allocate or do I/O in the loop body beyond the transport's send and receive
//! (records go through `RecordSink`).

use std::path::Path;
use std::time::{Duration, Instant};

use super::actuator::{ActuatorParamRecord, ActuatorTruthRecord, MAX_PARAMS};
use super::core::{RigCore, RigRecord};
use crate::hil::config::{HilConfig, LoopProcess};
use crate::hil::process::{
    install_termination_handler, meta_json, poll_control, real_time_setup, termination_requested,
    wait_for_start_within, write_summary, ControlRequests, Injector, Priority, ProcessError,
    StartInfo, HEARTBEAT_PERIOD_NS,
};
use crate::ipc::messages::{
    process_id, rig_state, sample_status, ActuatorCommand, DisplacementSample, Heartbeat,
    RunControl,
};
use crate::ipc::{count_nodes, In, IpcNode, Out};
use crate::records::event::event_kind;
use crate::records::{EventRecord, RecordSink, RecorderBuilder, SinkCounts};
use crate::rt::clock::monotonic_now_ns;
use crate::rt::{MonotonicClock, Scheduler, WaitMode};

pub use super::transport::RigTransport;

/// The rig's iceoryx2 ports.
struct IpcRigTransport {
    samples: Out<DisplacementSample>,
    commands: In<ActuatorCommand>,
    heartbeat: Out<Heartbeat>,
    control: In<RunControl>,
    start_timeout: Duration,
}

impl RigTransport for IpcRigTransport {
    fn wait_for_start(&mut self) -> Result<StartInfo, ProcessError> {
        let start = wait_for_start_within(
            process_id::RIG,
            &self.heartbeat,
            &self.control,
            self.start_timeout,
        )?;
        // Every process's ports exist now: connect before the loop (`ipc::Connect`).
        crate::ipc::connect_all(&[
            &self.samples,
            &self.commands,
            &self.heartbeat,
            &self.control,
        ]);
        Ok(start)
    }
    #[inline]
    fn send_sample(&mut self, sample: &DisplacementSample) {
        self.samples.publish(*sample);
    }
    #[inline]
    fn receive_commands(&mut self, on_command: &mut dyn FnMut(&ActuatorCommand)) {
        self.commands.receive_each(|c| on_command(&c));
    }
    fn heartbeat(&mut self, heartbeat: &Heartbeat) -> ControlRequests {
        self.heartbeat.publish(*heartbeat);
        poll_control(&self.control)
    }
    fn finish(&mut self, last: &DisplacementSample, heartbeat: &Heartbeat) {
        self.samples.publish(*last);
        self.heartbeat.publish(*heartbeat);
    }
}

/// Rig end-of-run summary (`rig-summary.json`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct RigSummary {
    pub steps: u64,
    /// Periods run in a catch-up after a late wake-up of this process.
    pub missed_deadlines: u64,
    /// Periods in which no new command arrived.
    pub periods_without_command: u64,
    /// Commands dropped for their content (unknown mode, non-finite law or limits).
    pub rejected_commands: u64,
    pub fault: Option<String>,
    pub held: bool,
    pub at_rest: bool,
    pub orchestrator_lost: bool,
    pub records: SinkCounts,
    pub events: SinkCounts,
    pub record_error: Option<String>,
    /// The transport's own counts (the rig's end of the UDP link: datagrams sent,
    /// received, rejected by reason, lost).
    pub link: Option<serde_json::Value>,
}

/// One rig period: measure and send, take commands, servo, physics, record.
#[inline]
fn run_period(
    core: &mut RigCore,
    transport: &mut impl RigTransport,
    wake_late_ns: u64,
    catch_up: bool,
    records: &RecordSink<RigRecord>,
    events: &RecordSink<EventRecord>,
    without_command: &mut u64,
) {
    if let Some(sample) = core.measure(monotonic_now_ns()) {
        transport.send_sample(&sample);
    }
    let mut any = false;
    transport.receive_commands(&mut |cmd| {
        core.on_command(cmd);
        any = true;
    });
    if !any {
        *without_command += 1;
    }
    records.push(core.finish_period(wake_late_ns, catch_up));
    core.drain_events(|e| events.push(e));
}

/// Runs the rig over its iceoryx2 services (the simulated rig `hil` starts, or an external
/// rig started by hand) until the scenario ends, a hold is over, or STOP; `start_timeout`
/// bounds the wait for the start (a rig started by hand waits longer than one `hil`
/// started). When the orchestrator died, the last one out clears the run's shared memory.
pub fn run_rig_ipc(
    cfg: &HilConfig,
    config_text: &str,
    config_base_dir: Option<&Path>,
    run_id: &str,
    out_dir: &Path,
    start_timeout: Duration,
) -> Result<RigSummary, ProcessError> {
    install_termination_handler();
    std::fs::create_dir_all(out_dir)?;
    let node = IpcNode::new(run_id, "rig")?;
    let mut transport = IpcRigTransport {
        samples: node.displacement_out()?,
        commands: node.command_in()?,
        heartbeat: node.heartbeat_out()?,
        control: node.control_in()?,
        start_timeout,
    };
    let context = RunContext {
        cfg,
        config_text,
        config_base_dir,
        run_id,
        out_dir,
    };
    let summary = run_rig_loop(&context, &mut transport)?;
    if summary.orchestrator_lost {
        // Last one out of a run whose orchestrator died: wait (bounded) for the
        // other processes to go, then clear the run's shared memory.
        drop(transport);
        drop(node);
        let t = Instant::now();
        while count_nodes(run_id).unwrap_or(0) > 0 && t.elapsed() < Duration::from_secs(3) {
            let _ = crate::ipc::cleanup_dead_nodes(run_id);
            std::thread::sleep(Duration::from_millis(50));
        }
        crate::ipc::cleanup::clear_run(run_id);
    }
    write_summary(out_dir, "rig", &summary)?;
    Ok(summary)
}

/// Runs the rig over a transport its caller built (the far end of the UDP rig link, from
/// `link::rig_end`), as `run_rig_ipc` does over iceoryx2.
pub fn run_rig(
    cfg: &HilConfig,
    config_text: &str,
    config_base_dir: Option<&Path>,
    run_id: &str,
    out_dir: &Path,
    transport: &mut impl RigTransport,
) -> Result<RigSummary, ProcessError> {
    install_termination_handler();
    std::fs::create_dir_all(out_dir)?;
    let context = RunContext {
        cfg,
        config_text,
        config_base_dir,
        run_id,
        out_dir,
    };
    let mut summary = run_rig_loop(&context, transport)?;
    summary.link = transport.counts_json();
    write_summary(out_dir, "rig", &summary)?;
    Ok(summary)
}

/// What the rig's loop needs besides its transport.
struct RunContext<'a> {
    cfg: &'a HilConfig,
    config_text: &'a str,
    config_base_dir: Option<&'a Path>,
    run_id: &'a str,
    out_dir: &'a Path,
}

fn run_rig_loop(
    context: &RunContext,
    transport: &mut impl RigTransport,
) -> Result<RigSummary, ProcessError> {
    let cfg = context.cfg;
    let mut builder = RecorderBuilder::new(context.out_dir, "rig");
    let records = builder.sink::<RigRecord>(cfg.loop_.record_queue_capacity);
    let events = builder.sink::<EventRecord>(256);
    let actuator_truth = builder.sink::<ActuatorTruthRecord>(2);
    let actuator_params = builder.sink::<ActuatorParamRecord>(2 * MAX_PARAMS);
    let recorder = builder.spawn()?;
    let mut core = RigCore::new(cfg);

    real_time_setup(cfg, &cfg.loop_.rig_cpus, "bench_rig", Priority::Loop);
    let start = transport.wait_for_start()?;
    recorder.start(
        start.start_unix_ns,
        meta_json(
            cfg,
            "rig",
            context.run_id,
            context.config_text,
            context.config_base_dir,
            start.start_unix_ns,
        ),
    );
    // Once per run, before the loop: what the rig's actuator truly is.
    let (truth, params) = core.actuator_truth(cfg);
    actuator_truth.push(truth);
    for p in params {
        actuator_params.push(p);
    }
    let clock = MonotonicClock;
    let mut scheduler = Scheduler::new(
        cfg.loop_.period_ns,
        start.t0_ns,
        WaitMode::SleepSpin {
            spin_ns: cfg.loop_.spin_ns,
        },
    );
    let heartbeat_every = (HEARTBEAT_PERIOD_NS / cfg.loop_.period_ns).max(1);
    let mut injector = Injector::new(cfg, LoopProcess::Rig, process_id::RIG);
    let dt = cfg.loop_.dt_s();
    let mut missed = 0u64;
    let mut without_command = 0u64;
    let mut orchestrator_lost = false;
    let in_loop = crate::rt::pool::LoopSection::enter();
    loop {
        let stats = scheduler.wait_next(&clock);
        // A late wake-up skipped deadlines: the hardware did not stop, so those periods
        // run now (servo and physics included), in order.
        while core.step_idx() < stats.cycle_idx {
            run_period(
                &mut core,
                transport,
                0,
                true,
                &records,
                &events,
                &mut without_command,
            );
            missed += 1;
            if core.finished() {
                break;
            }
        }
        if core.finished() {
            break;
        }
        injector.fire_due(core.step_idx() as f64 * dt, core.step_idx(), &events);
        run_period(
            &mut core,
            transport,
            stats.wake_late_ns,
            false,
            &records,
            &events,
            &mut without_command,
        );
        if !orchestrator_lost && termination_requested() {
            // SIGTERM: our parent-death signal (or an operator's kill): hold, then end.
            orchestrator_lost = true;
            core.on_orchestrator_lost();
        }
        if core.finished() {
            break;
        }
        if core.step_idx().is_multiple_of(heartbeat_every) {
            let requests = transport.heartbeat(&Heartbeat {
                process: process_id::RIG,
                state: core.servo_state(),
                sequence: core.step_idx(),
                time_ns: stats.woke_ns,
                fault_code: core.servo().trip().map_or(0, |t| t.fault.code()),
                reserved: 0,
            });
            if requests.hold {
                core.operator(event_kind::OPERATOR_HOLD);
            }
            if requests.resume {
                core.operator(event_kind::OPERATOR_RESUME);
            }
            if requests.end {
                core.operator(event_kind::OPERATOR_STOP);
            }
            core.drain_events(|e| events.push(e));
            if requests.stop {
                break;
            }
        }
    }
    drop(in_loop);
    core.finish_event();
    core.drain_events(|e| events.push(e));
    let fault_code = core.servo().trip().map_or(0, |t| t.fault.code());
    transport.finish(
        &DisplacementSample {
            sequence: core.step_idx(),
            rig_time_ns: core.step_idx() * cfg.loop_.period_ns,
            publish_time_ns: monotonic_now_ns(),
            displacement_m: core.physics().x_m,
            actuator_force_n: core.physics().actuator_force_n,
            status: sample_status::END_OF_RUN,
            rig_state: rig_state::FINISHED,
            rig_fault_code: fault_code,
            reserved: 0,
            commanded_force_n: f64::NAN,
        },
        &Heartbeat {
            process: process_id::RIG,
            state: rig_state::FINISHED,
            sequence: core.step_idx(),
            time_ns: monotonic_now_ns(),
            fault_code,
            reserved: 0,
        },
    );
    let written = recorder.finish();
    Ok(RigSummary {
        steps: core.step_idx(),
        missed_deadlines: missed,
        periods_without_command: without_command,
        rejected_commands: core.servo().rejected_commands(),
        fault: core.servo().trip().map(|t| t.fault.name().to_string()),
        held: core.servo().holding(),
        at_rest: core.servo().at_rest(),
        orchestrator_lost,
        records: written.counts_of("/rig"),
        events: written.counts_of("/events"),
        record_error: written.error,
        link: None,
    })
}
