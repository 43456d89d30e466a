//! The emulator process: iceoryx2 ports around `EmulatorCore`, the fixed-step loop on
//! absolute deadlines, heartbeats, events and records, end-of-run summary.
//!
//! Must not: allocate, log or do I/O inside the loop body (records and events go through
//! `RecordSink`; progress only before and after the loop).

use std::path::Path;

use super::config::{HilConfig, LoopProcess};
use super::emulator::{CycleOutcome, EmulatorCore, EmulatorIo, EmulatorRecord};
use super::fault::Fault;
use super::process::{
    install_termination_handler, meta_json, poll_control, real_time_setup, termination_requested,
    wait_for_start, write_summary, Injector, ProcessError, HEARTBEAT_PERIOD_NS, IDLE_EXIT_S,
};
use crate::ipc::messages::{
    emulator_state, process_id, sample_status, DisplacementSample, ForceSetpoint, Heartbeat,
    LocalLaw,
};
use crate::ipc::{In, IpcNode, Out, Wake};
use crate::records::{EventRecord, RecorderBuilder, SinkCounts};
use crate::rt::clock::monotonic_now_ns;
use crate::rt::{MonotonicClock, Scheduler, WaitMode};

struct IpcEmulatorIo<'a> {
    input: &'a In<DisplacementSample>,
    output: &'a Out<ForceSetpoint>,
    wake: &'a Wake,
    /// How long to poll for the expected sample after waking, ns.
    sample_wait_ns: u64,
}

impl EmulatorIo for IpcEmulatorIo<'_> {
    #[inline]
    fn receive_samples(
        &mut self,
        expected_seq: u64,
        on_sample: &mut dyn FnMut(DisplacementSample),
    ) {
        // The rig's wake-up jitters by tens of us; poll briefly for the sample this cycle
        // expects (bounded: `sample_wait_us`). Every sample is handed over, oldest first.
        let give_up_ns = monotonic_now_ns() + self.sample_wait_ns;
        loop {
            let mut arrived = false;
            self.input.receive_each(|s| {
                arrived |= s.sequence >= expected_seq || s.status != sample_status::OK;
                on_sample(s);
            });
            if arrived || monotonic_now_ns() >= give_up_ns {
                return;
            }
            std::hint::spin_loop();
        }
    }
    #[inline]
    fn publish_setpoint(&mut self, setpoint: ForceSetpoint) {
        self.output.publish(setpoint);
        self.wake.notify();
    }
}

/// Emulator end-of-run summary (`emulator-summary.json`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct EmulatorSummary {
    pub cycles: u64,
    pub model_steps: u64,
    pub stale_cycles: u64,
    pub missing_samples: u64,
    pub missed_deadlines: u64,
    pub longest_stall_ms: f64,
    pub records: SinkCounts,
    pub events: SinkCounts,
    pub record_error: Option<String>,
    pub fault: Option<String>,
}

/// Runs the emulator process until end of run, STOP, termination or its time cap.
pub fn run_emulator(
    cfg: &HilConfig,
    config_text: &str,
    config_base_dir: Option<&Path>,
    run_id: &str,
    out_dir: &Path,
) -> Result<EmulatorSummary, ProcessError> {
    install_termination_handler();
    std::fs::create_dir_all(out_dir)?;
    let node = IpcNode::new(run_id, "emulator")?;
    let input = node.displacement_in()?;
    let output = node.setpoint_out()?;
    let wake = node.setpoint_wake()?;
    let heartbeat = node.heartbeat_out()?;
    let control = node.control_in()?;
    let mut builder = RecorderBuilder::new(out_dir, "emulator");
    let records = builder.sink::<EmulatorRecord>(cfg.loop_.record_queue_capacity);
    let events = builder.sink::<EventRecord>(256);
    let recorder = builder.spawn()?;

    real_time_setup(cfg, &cfg.loop_.emulator_cpus, "emulator");
    let start = wait_for_start(process_id::EMULATOR, &heartbeat, &control)?;
    recorder.start(
        start.start_unix_ns,
        meta_json(
            cfg,
            "emulator",
            run_id,
            config_text,
            config_base_dir,
            start.start_unix_ns,
        ),
    );

    let clock = MonotonicClock;
    let mut scheduler = Scheduler::new(
        cfg.loop_.period_ns,
        start.t0_ns + cfg.loop_.emulator_phase_ns,
        WaitMode::SleepSpin {
            spin_ns: cfg.loop_.spin_ns,
        },
    );
    let mut core = EmulatorCore::new(
        &cfg.augmented,
        &cfg.loop_,
        cfg.emulator,
        cfg.stall_limit_periods(),
    );
    let mut io = IpcEmulatorIo {
        input: &input,
        output: &output,
        wake: &wake,
        sample_wait_ns: cfg.loop_.sample_wait_ns,
    };
    let mut injector = Injector::new(cfg, LoopProcess::Emulator, process_id::EMULATOR);
    // Ends on the rig's end-of-run sample, STOP or SIGTERM; as a last resort, after a
    // minute without any sample (the rig and the orchestrator both gone).
    let idle_limit = (IDLE_EXIT_S * cfg.loop_.rate_hz) as u64;
    let mut idle_cycles = 0u64;
    let mut last_steps = 0u64;
    let heartbeat_every = (HEARTBEAT_PERIOD_NS / cfg.loop_.period_ns).max(1);
    let dt = cfg.loop_.dt_s();
    let mut push = |r: EmulatorRecord| records.push(r);
    loop {
        let stats = scheduler.wait_next(&clock);
        let now_idx = stats.cycle_idx + stats.missed_deadlines;
        injector.fire_due(now_idx as f64 * dt, now_idx, &events);
        let outcome = core.cycle(&stats, &mut io, &mut push);
        if let Some(event) = core.take_fault_event(now_idx) {
            events.push(event);
        }
        idle_cycles = if core.counts.model_steps == last_steps {
            idle_cycles + 1
        } else {
            0
        };
        last_steps = core.counts.model_steps;
        if outcome == CycleOutcome::EndOfRun || idle_cycles > idle_limit {
            break;
        }
        if stats.cycle_idx.is_multiple_of(heartbeat_every) {
            heartbeat.publish(Heartbeat {
                process: process_id::EMULATOR,
                state: core.state(),
                sequence: stats.cycle_idx,
                time_ns: stats.woke_ns,
                fault_code: core.fault().map_or(0, Fault::code),
                reserved: 0,
            });
            if poll_control(&control).stop || termination_requested() {
                break;
            }
        }
    }
    output.publish(ForceSetpoint {
        sequence: u64::MAX,
        sample_sequence: u64::MAX,
        sample_publish_time_ns: 0,
        loop_time_ns: 0,
        law: LocalLaw::default(),
        emulator_state: emulator_state::STOPPED,
        fault_code: core.fault().map_or(0, Fault::code),
        model_flags: 0,
        reserved: 0,
    });
    wake.notify();
    heartbeat.publish(Heartbeat {
        process: process_id::EMULATOR,
        state: emulator_state::STOPPED,
        sequence: u64::MAX,
        time_ns: monotonic_now_ns(),
        fault_code: core.fault().map_or(0, Fault::code),
        reserved: 0,
    });
    let written = recorder.finish();
    let summary = EmulatorSummary {
        cycles: core.counts.cycles,
        model_steps: core.counts.model_steps,
        stale_cycles: core.counts.stale_cycles,
        missing_samples: core.counts.missing_samples,
        missed_deadlines: core.counts.missed_deadlines,
        longest_stall_ms: core.counts.longest_stall_ns as f64 * 1e-6,
        records: written.counts_of("/emulator"),
        events: written.counts_of("/events"),
        record_error: written.error,
        fault: core.fault().map(|f| f.name().to_string()),
    };
    write_summary(out_dir, "emulator", &summary)?;
    Ok(summary)
}
