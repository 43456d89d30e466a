//! The actuator-controller process: event-driven on new setpoints (an iceoryx2 listener),
//! with the watchdog and keep-alive checked on every wake-up and on wait time-outs;
//! heartbeats, events, records and end-of-run summary.
//!
//! Must not: allocate, log or do I/O inside the loop body (records and events go through
//! `RecordSink`).

use std::path::Path;
use std::time::Duration;

use super::config::{HilConfig, LoopProcess};
use super::controller::{ControllerCore, ControllerRecord};
use super::fault::Fault;
use super::process::{
    install_termination_handler, meta_json, poll_control, real_time_setup, termination_requested,
    wait_for_start, write_summary, Injector, Priority, ProcessError, HEARTBEAT_PERIOD_NS,
    IDLE_EXIT_S,
};
use crate::ipc::messages::{
    controller_state, emulator_state, process_id, ActuatorCommand, Heartbeat, HEARTBEAT_READY,
};
use crate::records::{EventRecord, RecordSink, RecorderBuilder, SinkCounts};
use crate::rt::clock::monotonic_now_ns;

/// Controller end-of-run summary (`controller-summary.json`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct ControllerSummary {
    pub commands: u64,
    pub limited_commands: u64,
    pub repeated_commands: u64,
    pub records: SinkCounts,
    pub events: SinkCounts,
    pub record_error: Option<String>,
    pub fault: Option<String>,
    pub emulator_fault: Option<String>,
    pub action: Option<String>,
    pub final_state: u32,
}

/// Runs the controller process until the emulator stops, STOP, termination or its cap.
pub fn run_controller(
    cfg: &HilConfig,
    config_text: &str,
    config_base_dir: Option<&Path>,
    run_id: &str,
    out_dir: &Path,
) -> Result<ControllerSummary, ProcessError> {
    install_termination_handler();
    std::fs::create_dir_all(out_dir)?;
    let node = crate::ipc::IpcNode::new(run_id, "controller")?;
    let setpoints = node.setpoint_in()?;
    let listener = node.setpoint_listener()?;
    let commands = node.command_out()?;
    // Wakes a UDP rig link that forwards commands (nobody listens with an iceoryx2 rig).
    let command_wake = node.command_wake()?;
    let heartbeats_in = node.heartbeat_in()?;
    let heartbeat = node.heartbeat_out()?;
    let control = node.control_in()?;
    let mut builder = RecorderBuilder::new(out_dir, "controller");
    let records = builder.sink::<ControllerRecord>(cfg.loop_.record_queue_capacity);
    let events = builder.sink::<EventRecord>(256);
    let recorder = builder.spawn()?;
    // The starting compensation (a frequency sweep of the linearised loop when the guess
    // is capped) before the thread gets its real-time priority on the rig's CPU.
    // The launcher's plan for the simulated rig's declared actuator (none for an external
    // rig, or a controller started by hand).
    let plan = crate::hil::check::read_plan(out_dir).map_err(|e| ProcessError(format!("{e:#}")))?;
    let compensation = crate::hil::check::starting_compensation(cfg, plan.as_ref());
    // One priority above the rig's loop beside it: it blocks on the emulator's
    // notification, so it never delays the rig by more than a command's work.
    real_time_setup(
        cfg,
        &cfg.loop_.controller_cpus,
        "controller",
        Priority::EventDriven,
    );
    let start = wait_for_start(process_id::CONTROLLER, &heartbeat, &control)?;
    // Every process's ports exist now: connect before the loop (`ipc::Connect`).
    crate::ipc::connect_all(&[
        &setpoints,
        &commands,
        &command_wake,
        &heartbeats_in,
        &heartbeat,
        &control,
    ]);
    recorder.start(
        start.start_unix_ns,
        meta_json(
            cfg,
            "controller",
            run_id,
            config_text,
            config_base_dir,
            start.start_unix_ns,
        ),
    );

    let period_ns = cfg.loop_.period_ns;
    let mut core = ControllerCore::new(
        cfg.controller,
        cfg.safety.actions,
        period_ns,
        (cfg.safety.stall_limit_s * 1e9) as u64,
    )
    .with_compensation(compensation);
    core.set_start_time_ns(start.t0_ns);
    let mut injector = Injector::new(cfg, LoopProcess::Controller, process_id::CONTROLLER);
    // Ends when the emulator stops, on STOP or SIGTERM; as a last resort, after a minute
    // without any setpoint (the emulator and the orchestrator both gone).
    let mut last_setpoint_ns = monotonic_now_ns();
    let mut next_heartbeat_ns = 0u64;
    let mut commands_sent = 0u64;
    let mut emulator_stopped = false;
    let mut stopped = false;
    let mut hb_seq = 0u64;
    let wait = Duration::from_nanos(cfg.controller.keepalive_ns.max(50_000));
    let publish = |out: Option<(ActuatorCommand, ControllerRecord)>,
                   sent: &mut u64,
                   records: &RecordSink<ControllerRecord>| {
        if let Some((cmd, rec)) = out {
            commands.publish(cmd);
            command_wake.notify();
            records.push(rec);
            *sent += 1;
        }
    };
    let in_loop = crate::rt::pool::LoopSection::enter();
    loop {
        // Block until the emulator notifies, at most one keep-alive period (on the
        // listener itself: a `WaitSet` allocates on every wake-up, `ipc_alloc`).
        listener.wait_for(wait);
        let now = monotonic_now_ns();
        injector.fire_due(
            now.saturating_sub(start.t0_ns) as f64 * 1e-9,
            now.saturating_sub(start.t0_ns) / period_ns,
            &events,
        );
        setpoints.receive_each(|sp| {
            last_setpoint_ns = monotonic_now_ns();
            if sp.emulator_state == emulator_state::STOPPED {
                emulator_stopped = true;
                return;
            }
            let out = core.on_setpoint(&sp, monotonic_now_ns());
            publish(out, &mut commands_sent, &records);
        });
        let now = monotonic_now_ns();
        let out = core.on_tick(now);
        publish(out, &mut commands_sent, &records);
        if let Some(trip) = core.take_new_trip() {
            events.push(trip.event(start.t0_ns, period_ns));
        }
        if now >= next_heartbeat_ns {
            next_heartbeat_ns = now + HEARTBEAT_PERIOD_NS;
            heartbeats_in.receive_each(|hb| {
                if hb.process == process_id::EMULATOR && hb.state != HEARTBEAT_READY {
                    core.on_emulator_heartbeat(now);
                }
            });
            heartbeat.publish(Heartbeat {
                process: process_id::CONTROLLER,
                state: core.state(),
                sequence: hb_seq,
                time_ns: now,
                fault_code: core.fault().map_or(0, Fault::code),
                reserved: core.emulator_fault_code(),
            });
            hb_seq += 1;
            stopped |= poll_control(&control).stop;
        }
        let idle = now.saturating_sub(last_setpoint_ns) > (IDLE_EXIT_S * 1e9) as u64;
        if emulator_stopped || stopped || termination_requested() || idle {
            break;
        }
    }
    drop(in_loop);
    heartbeat.publish(Heartbeat {
        process: process_id::CONTROLLER,
        state: controller_state::STOPPED,
        sequence: u64::MAX,
        time_ns: monotonic_now_ns(),
        fault_code: core.fault().map_or(0, Fault::code),
        reserved: core.emulator_fault_code(),
    });
    let written = recorder.finish();
    let summary = ControllerSummary {
        commands: commands_sent,
        limited_commands: core.limited_commands,
        repeated_commands: core.repeated_commands,
        records: written.counts_of("/controller"),
        events: written.counts_of("/events"),
        record_error: written.error,
        fault: core.fault().map(|f| f.name().to_string()),
        emulator_fault: (core.emulator_fault_code() != 0)
            .then(|| super::fault::fault_code_name(core.emulator_fault_code())),
        action: core.trip().map(|t| t.action.name().to_string()),
        final_state: core.state(),
    };
    write_summary(out_dir, "controller", &summary)?;
    Ok(summary)
}
