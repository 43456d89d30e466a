//! The emulator process: iceoryx2 ports around `EmulatorCore`, the fixed-step loop on
//! absolute deadlines (run by its primary thread, and by a standby thread on another CPU
//! when the primary has not begun a cycle in time), heartbeats, events and records,
//! end-of-run summary.
//!
//! Must not: allocate, log or do I/O inside the loop body (records and events go through
//! `RecordSink`; progress only before and after the loop).

use std::cell::UnsafeCell;
use std::path::Path;
use std::time::Duration;

use super::config::{HilConfig, LoopProcess};
use super::emulator::{
    AfterFaultSampleRecord, CycleOutcome, EmulatorCore, EmulatorIo, EmulatorRecord, EmulatorRecords,
};
use super::fault::Fault;
use super::process::{
    install_termination_handler, meta_json, poll_control, real_time_setup, termination_requested,
    wait_for_start, write_summary, Injector, Priority, ProcessError, HEARTBEAT_PERIOD_NS,
    IDLE_EXIT_S,
};
use crate::ipc::messages::{
    emulator_state, process_id, sample_status, DisplacementSample, ForceSetpoint, Heartbeat,
    LocalLaw, RunControl,
};
use crate::ipc::{In, IpcNode, Out, Wake};
use crate::records::{EventRecord, RecordSink, RecorderBuilder, SinkCounts};
use crate::rt::clock::monotonic_now_ns;
use crate::rt::{wait_until, Clock, CycleStats, CycleTurn, MonotonicClock, WaitMode};

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
    /// CPUs of the standby loop thread (empty: none).
    pub standby_cpus: Vec<usize>,
    /// Cycles the standby ran because the primary had not begun them in time.
    pub standby_cycles: u64,
    pub records: SinkCounts,
    pub events: SinkCounts,
    pub record_error: Option<String>,
    pub fault: Option<String>,
}

/// Everything a cycle of the emulator's loop touches; owned by the loop thread that holds
/// the turn.
struct EmulatorLoop<'a> {
    core: EmulatorCore,
    io: IpcEmulatorIo<'a>,
    injector: Injector,
    heartbeat: &'a Out<Heartbeat>,
    control: &'a In<RunControl>,
    records: &'a RecordSink<EmulatorRecord>,
    after_fault: &'a RecordSink<AfterFaultSampleRecord>,
    events: &'a RecordSink<EventRecord>,
    dt: f64,
    heartbeat_every: u64,
    /// Ends the loop after this many cycles without a sample (the rig and the
    /// orchestrator both gone).
    idle_limit: u64,
    idle_cycles: u64,
    last_steps: u64,
    standby_cycles: u64,
}

impl EmulatorLoop<'_> {
    /// One cycle: whether the loop goes on, and a CPU stall injected on the thread that
    /// ran it (served outside the turn).
    #[inline]
    fn cycle(&mut self, stats: &CycleStats, by_standby: bool) -> (bool, Option<Duration>) {
        self.standby_cycles += u64::from(by_standby);
        let now_idx = stats.cycle_idx + stats.missed_deadlines;
        let cpu_stall = self
            .injector
            .fire_due(now_idx as f64 * self.dt, now_idx, self.events);
        let mut sinks = Sinks {
            steps: self.records,
            after_fault: self.after_fault,
        };
        let outcome = self.core.cycle(stats, &mut self.io, &mut sinks);
        if let Some(event) = self.core.take_fault_event(now_idx) {
            self.events.push(event);
        }
        let steps = self.core.counts.model_steps;
        self.idle_cycles = if steps == self.last_steps {
            self.idle_cycles + 1
        } else {
            0
        };
        self.last_steps = steps;
        if outcome == CycleOutcome::EndOfRun || self.idle_cycles > self.idle_limit {
            return (false, cpu_stall);
        }
        if stats.cycle_idx.is_multiple_of(self.heartbeat_every) {
            self.heartbeat.publish(Heartbeat {
                process: process_id::EMULATOR,
                state: self.core.state(),
                sequence: stats.cycle_idx,
                time_ns: stats.woke_ns,
                fault_code: self.core.fault().map_or(0, Fault::code),
                reserved: 0,
            });
            if poll_control(self.control).stop || termination_requested() {
                return (false, cpu_stall);
            }
        }
        (true, cpu_stall)
    }
}

/// The record queues the loop pushes into (bounded, lock-free).
struct Sinks<'a> {
    steps: &'a RecordSink<EmulatorRecord>,
    after_fault: &'a RecordSink<AfterFaultSampleRecord>,
}

impl EmulatorRecords for Sinks<'_> {
    #[inline]
    fn step(&mut self, r: EmulatorRecord) {
        self.steps.push(r);
    }

    #[inline]
    fn after_fault(&mut self, r: AfterFaultSampleRecord) {
        self.after_fault.push(r);
    }
}

/// The loop as the primary and the standby thread share it.
struct SharedLoop<'a> {
    turn: CycleTurn,
    state: UnsafeCell<EmulatorLoop<'a>>,
}

// SAFETY: `state` is reached only in `run_thread`, between a successful
// `CycleTurn::try_claim` (an acquire) and the `release` or `finish` that ends the cycle (a
// release): by one thread at a time, each seeing all that the one before it wrote. The
// iceoryx2 ports it refers to (single-threaded `Rc` inside, hence not `Sync`) are so never
// used by two threads at once, and both threads end before anything is dropped.
unsafe impl Sync for SharedLoop<'_> {}

impl SharedLoop<'_> {
    /// Runs one loop thread until the loop ends: wait until `after_ns` past the next
    /// cycle's deadline, claim the cycle, run it; a cycle the other thread took is skipped.
    fn run_thread(&self, mode: WaitMode, after_ns: u64, by_standby: bool) {
        let clock = MonotonicClock;
        let _loop = crate::rt::pool::LoopSection::enter();
        while let Some(idx) = self.turn.next_idx() {
            wait_until(&clock, self.turn.deadline_ns(idx) + after_ns, mode);
            let Some(stats) = self.turn.try_claim(idx, clock.now_ns()) else {
                continue;
            };
            // SAFETY: this thread holds the turn (see `unsafe impl Sync for SharedLoop`).
            let state = unsafe { &mut *self.state.get() };
            let (go_on, cpu_stall) = state.cycle(&stats, by_standby);
            if go_on {
                self.turn.release(&stats);
            } else {
                self.turn.finish();
            }
            if let Some(stall) = cpu_stall {
                std::thread::sleep(stall);
            }
        }
    }
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
    let after_fault = builder.sink::<AfterFaultSampleRecord>(cfg.loop_.record_queue_capacity);
    let events = builder.sink::<EventRecord>(256);
    let recorder = builder.spawn()?;

    real_time_setup(cfg, &cfg.loop_.emulator_cpus, "emulator", Priority::Loop);
    let start = wait_for_start(process_id::EMULATOR, &heartbeat, &control)?;
    // Every process's ports exist now: connect before the loop (`ipc::Connect`).
    crate::ipc::connect_all(&[&input, &output, &wake, &heartbeat, &control]);
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

    let shared = SharedLoop {
        turn: CycleTurn::new(
            cfg.loop_.period_ns,
            start.t0_ns + cfg.loop_.emulator_phase_ns,
        ),
        state: UnsafeCell::new(EmulatorLoop {
            core: EmulatorCore::new(
                &cfg.augmented,
                &cfg.loop_,
                cfg.emulator,
                cfg.stall_limit_periods(),
            )
            .with_stability_bounds(cfg.safety.stability),
            io: IpcEmulatorIo {
                input: &input,
                output: &output,
                wake: &wake,
                sample_wait_ns: cfg.loop_.sample_wait_ns,
            },
            injector: Injector::new(cfg, LoopProcess::Emulator, process_id::EMULATOR),
            heartbeat: &heartbeat,
            control: &control,
            records: &records,
            after_fault: &after_fault,
            events: &events,
            dt: cfg.loop_.dt_s(),
            heartbeat_every: (HEARTBEAT_PERIOD_NS / cfg.loop_.period_ns).max(1),
            // Ends on the rig's end-of-run sample, STOP or SIGTERM; as a last resort,
            // after a minute without any sample.
            idle_limit: (IDLE_EXIT_S * cfg.loop_.rate_hz) as u64,
            idle_cycles: 0,
            last_steps: 0,
            standby_cycles: 0,
        }),
    };
    let primary = WaitMode::SleepSpin {
        spin_ns: cfg.loop_.spin_ns,
    };
    match &cfg.loop_.emulator_standby {
        None => shared.run_thread(primary, 0, false),
        Some(standby) => std::thread::scope(|scope| {
            let shared = &shared;
            scope.spawn(move || {
                real_time_setup(cfg, &standby.cpus, "emulator standby", Priority::Standby);
                shared.run_thread(WaitMode::Sleep, standby.after_ns, true);
            });
            shared.run_thread(primary, 0, false);
        }),
    }
    let EmulatorLoop {
        core,
        standby_cycles,
        ..
    } = shared.state.into_inner();
    output.publish(ForceSetpoint {
        sequence: u64::MAX,
        sample_sequence: u64::MAX,
        sample_publish_time_ns: 0,
        loop_time_ns: 0,
        law: LocalLaw::default(),
        emulator_state: emulator_state::STOPPED,
        fault_code: core.fault().map_or(0, Fault::code),
        model_flags: 0,
        rig_state: 0,
        measured_force_n: f64::NAN,
        commanded_force_n: f64::NAN,
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
        standby_cpus: cfg
            .loop_
            .emulator_standby
            .as_ref()
            .map_or(Vec::new(), |s| s.cpus.clone()),
        standby_cycles,
        records: written.counts_of("/emulator"),
        events: written.counts_of("/events"),
        record_error: written.error,
        fault: core.fault().map(|f| f.name().to_string()),
    };
    write_summary(out_dir, "emulator", &summary)?;
    Ok(summary)
}
