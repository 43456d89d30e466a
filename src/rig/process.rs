//! The `bench_rig` process: runs `RigCore` on its own fixed-step clock, publishes one
//! displacement sample per period, feeds commands to the actuator's servo, and streams
//! its records. It behaves as hardware does: a late wake-up does not stop time (the missed
//! periods run in a catch-up, servo included), its interlock holds the specimen on stale
//! commands without help from any other process, and when `fastemu hil` dies it holds,
//! records until the specimen is at rest, writes its records, clears the run's shared
//! memory and exits.
//!
//! Must not: allocate or do I/O in the loop body (records go through `RecordSink`).

use std::path::Path;
use std::time::{Duration, Instant};

use super::core::{RigCore, RigRecord};
use crate::hil::config::{HilConfig, LoopProcess};
use crate::hil::process::{
    install_termination_handler, meta_json, poll_control, real_time_setup, termination_requested,
    wait_for_start, write_summary, Injector, ProcessError, HEARTBEAT_PERIOD_NS,
};
use crate::ipc::messages::{
    process_id, rig_state, sample_status, ActuatorCommand, DisplacementSample, Heartbeat,
};
use crate::ipc::{count_nodes, In, IpcNode, Out};
use crate::records::event::event_kind;
use crate::records::{EventRecord, RecordSink, RecorderBuilder, SinkCounts};
use crate::rt::clock::monotonic_now_ns;
use crate::rt::{MonotonicClock, Scheduler, WaitMode};

/// Rig end-of-run summary (`rig-summary.json`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct RigSummary {
    pub steps: u64,
    /// Periods run in a catch-up after a late wake-up of this process.
    pub missed_deadlines: u64,
    /// Periods in which no new command arrived.
    pub periods_without_command: u64,
    pub fault: Option<String>,
    pub held: bool,
    pub at_rest: bool,
    pub orchestrator_lost: bool,
    pub records: SinkCounts,
    pub events: SinkCounts,
    pub record_error: Option<String>,
}

/// The rig's ports.
struct RigPorts {
    samples: Out<DisplacementSample>,
    commands: In<ActuatorCommand>,
}

/// One rig period: measure and publish, take commands, servo, physics, record.
#[inline]
fn run_period(
    core: &mut RigCore,
    ports: &RigPorts,
    wake_late_ns: u64,
    catch_up: bool,
    records: &RecordSink<RigRecord>,
    events: &RecordSink<EventRecord>,
    without_command: &mut u64,
) {
    if let Some(sample) = core.measure(monotonic_now_ns()) {
        ports.samples.publish(sample);
    }
    let mut any = false;
    ports.commands.receive_each(|cmd| {
        core.on_command(&cmd);
        any = true;
    });
    if !any {
        *without_command += 1;
    }
    records.push(core.finish_period(wake_late_ns, catch_up));
    core.drain_events(|e| events.push(e));
}

/// Runs the rig until the scenario ends, a hold is over, or STOP.
pub fn run_rig(
    cfg: &HilConfig,
    config_text: &str,
    config_base_dir: Option<&Path>,
    run_id: &str,
    out_dir: &Path,
) -> Result<RigSummary, ProcessError> {
    install_termination_handler();
    std::fs::create_dir_all(out_dir)?;
    let node = IpcNode::new(run_id, "rig")?;
    let ports = RigPorts {
        samples: node.displacement_out()?,
        commands: node.command_in()?,
    };
    let heartbeat = node.heartbeat_out()?;
    let control = node.control_in()?;
    let mut builder = RecorderBuilder::new(out_dir, "rig");
    let records = builder.sink::<RigRecord>(cfg.loop_.record_queue_capacity);
    let events = builder.sink::<EventRecord>(256);
    let recorder = builder.spawn()?;
    let mut core = RigCore::new(cfg);

    real_time_setup(cfg, &cfg.loop_.rig_cpus, "bench_rig");
    let start = wait_for_start(process_id::RIG, &heartbeat, &control)?;
    recorder.start(
        start.start_unix_ns,
        meta_json(
            cfg,
            "rig",
            run_id,
            config_text,
            config_base_dir,
            start.start_unix_ns,
        ),
    );
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
    loop {
        let stats = scheduler.wait_next(&clock);
        // A late wake-up skipped deadlines: the hardware did not stop, so those periods
        // run now (servo and physics included), in order.
        while core.step_idx() < stats.cycle_idx {
            run_period(
                &mut core,
                &ports,
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
            &ports,
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
            heartbeat.publish(Heartbeat {
                process: process_id::RIG,
                state: core.servo_state(),
                sequence: core.step_idx(),
                time_ns: stats.woke_ns,
                fault_code: core.servo().trip().map_or(0, |t| t.fault.code()),
                reserved: 0,
            });
            let requests = poll_control(&control);
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
    core.finish_event();
    core.drain_events(|e| events.push(e));
    ports.samples.publish(DisplacementSample {
        sequence: core.step_idx(),
        rig_time_ns: core.step_idx() * cfg.loop_.period_ns,
        publish_time_ns: monotonic_now_ns(),
        displacement_m: core.physics().x_m,
        status: sample_status::END_OF_RUN,
        reserved: 0,
    });
    heartbeat.publish(Heartbeat {
        process: process_id::RIG,
        state: rig_state::FINISHED,
        sequence: core.step_idx(),
        time_ns: monotonic_now_ns(),
        fault_code: core.servo().trip().map_or(0, |t| t.fault.code()),
        reserved: 0,
    });
    let written = recorder.finish();
    let summary = RigSummary {
        steps: core.step_idx(),
        missed_deadlines: missed,
        periods_without_command: without_command,
        fault: core.servo().trip().map(|t| t.fault.name().to_string()),
        held: core.servo().holding(),
        at_rest: core.servo().at_rest(),
        orchestrator_lost,
        records: written.counts_of("/rig"),
        events: written.counts_of("/events"),
        record_error: written.error,
    };
    write_summary(out_dir, "rig", &summary)?;
    if orchestrator_lost {
        // Last one out of a run whose orchestrator died: wait (bounded) for the other
        // processes to go, then clear the run's shared memory.
        drop((ports, heartbeat, control, node));
        let t = Instant::now();
        while count_nodes(run_id).unwrap_or(0) > 0 && t.elapsed() < Duration::from_secs(3) {
            let _ = crate::ipc::cleanup_dead_nodes(run_id);
            std::thread::sleep(Duration::from_millis(50));
        }
        crate::ipc::cleanup::clear_run(run_id);
    }
    Ok(summary)
}
