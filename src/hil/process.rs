//! The emulator and controller processes: iceoryx2 ports around `EmulatorCore` and
//! `ControllerCore`, start-up handshake, heartbeats, records and end-of-run summary.
//!
//! Must not: allocate, log or do I/O inside the per-cycle loop bodies (records go
//! through `RecordSink`, progress only before and after the loop).

use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::config::HilConfig;
use super::controller::{ControllerCore, ControllerRecord};
use super::emulator::{CycleOutcome, EmulatorCore, EmulatorIo, EmulatorRecord};
use super::fault::Fault;
use super::records::RecordSink;
use crate::ipc::messages::{
    controller_state, emulator_state, process_id, run_command, sample_status, DisplacementSample,
    ForceSetpoint, Heartbeat, RunControl, HEARTBEAT_READY,
};
use crate::ipc::{In, IpcError, IpcNode, Out, Wake};
use crate::rt::clock::monotonic_now_ns;
use crate::rt::{apply_rt_setup, MonotonicClock, RtSetup, Scheduler, WaitMode};

/// A process-level failure: one line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProcessError(pub String);

impl fmt::Display for ProcessError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ProcessError {}

impl From<IpcError> for ProcessError {
    fn from(e: IpcError) -> ProcessError {
        ProcessError(e.to_string())
    }
}

impl From<std::io::Error> for ProcessError {
    fn from(e: std::io::Error) -> ProcessError {
        ProcessError(format!("I/O: {e}"))
    }
}

/// How long a process waits for the orchestrator's start command.
pub const START_TIMEOUT: Duration = Duration::from_secs(30);
/// Heartbeat period, ns.
pub const HEARTBEAT_PERIOD_NS: u64 = 10_000_000;

/// Publishes READY heartbeats until a START arrives; returns the start time, ns.
pub fn wait_for_start(
    process: u32,
    heartbeat: &Out<Heartbeat>,
    control: &In<RunControl>,
) -> Result<u64, ProcessError> {
    let deadline = monotonic_now_ns() + START_TIMEOUT.as_nanos() as u64;
    let mut seq = 0;
    loop {
        let mut start = None;
        let mut stop = false;
        control.receive_each(|c| match c.command {
            run_command::START => start = Some(c.start_time_ns),
            run_command::STOP => stop = true,
            _ => {}
        });
        if stop {
            return Err(ProcessError("stopped before start".into()));
        }
        if let Some(t0) = start {
            return Ok(t0);
        }
        let now = monotonic_now_ns();
        if now > deadline {
            return Err(ProcessError(format!(
                "no start command within {START_TIMEOUT:?}"
            )));
        }
        heartbeat.publish(Heartbeat {
            process,
            state: HEARTBEAT_READY,
            sequence: seq,
            time_ns: now,
            fault_code: 0,
            reserved: 0,
        });
        seq += 1;
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Whether a STOP command is pending.
#[inline]
pub fn stop_requested(control: &In<RunControl>) -> bool {
    let mut stop = false;
    control.receive_each(|c| stop |= c.command == run_command::STOP);
    stop
}

/// Applies the configured real-time setup for a loop thread; prints warnings.
pub fn real_time_setup(cfg: &HilConfig, cpus: &[usize], who: &str) {
    let setup = RtSetup {
        lock_memory: cfg.loop_.lock_memory,
        fifo_priority: cfg.loop_.fifo_priority,
        cpus: cpus.to_vec(),
    };
    for w in apply_rt_setup(&setup) {
        eprintln!("{who}: warning: {w}");
    }
}

struct IpcEmulatorIo<'a> {
    input: &'a In<DisplacementSample>,
    output: &'a Out<ForceSetpoint>,
    wake: &'a Wake,
    /// How long to poll for the expected sample after waking, ns.
    sample_wait_ns: u64,
    newest: Option<DisplacementSample>,
    /// Valid displacement range: a sample outside it, or non-finite, or with a bad
    /// status is handed to the emulator for validation even when a newer one arrived
    /// in the same cycle, so a single bad sample can never slip by unchecked.
    displacement_range_m: (f64, f64),
}

/// A sample the emulator must see (bad status, non-finite or outside `lo..=hi`).
#[inline]
fn is_suspect(s: &DisplacementSample, (lo, hi): (f64, f64)) -> bool {
    s.status != sample_status::OK || !(s.displacement_m >= lo && s.displacement_m <= hi)
}

impl EmulatorIo for IpcEmulatorIo<'_> {
    #[inline]
    fn receive_newest_sample(&mut self, expected_seq: u64) -> Option<DisplacementSample> {
        // The rig's wake-up jitters by tens of us; poll briefly for the sample this cycle
        // expects instead of holding the previous one (bounded: `sample_wait_us`).
        let give_up_ns = monotonic_now_ns() + self.sample_wait_ns;
        let mut fresh = None;
        let mut suspect = None;
        let range = self.displacement_range_m;
        loop {
            let mut newest = self.newest;
            self.input.receive_each(|s| {
                if suspect.is_none() && is_suspect(&s, range) {
                    suspect = Some(s);
                }
                fresh = Some(s);
                newest = Some(s);
            });
            self.newest = newest;
            if suspect.is_some() {
                return suspect;
            }
            let arrived = self
                .newest
                .is_some_and(|s| s.sequence >= expected_seq || s.status != 0);
            if arrived || monotonic_now_ns() >= give_up_ns {
                return fresh;
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

/// Meta data next to `emulator.csv` that `replay` needs: the config text and rate.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct EmulatorMeta {
    pub config_text: String,
    pub config_origin: String,
    pub config_base_dir: Option<PathBuf>,
    pub rate_hz: f64,
}

/// Emulator end-of-run summary (`emulator-summary.json`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct EmulatorSummary {
    pub cycles: u64,
    pub model_steps: u64,
    pub stale_samples: u64,
    pub skipped_samples: u64,
    pub missed_deadlines: u64,
    pub records_written: u64,
    pub records_dropped: u64,
    pub fault: Option<String>,
}

/// Runs the emulator process until end of run, STOP, or its time cap.
pub fn run_emulator(
    cfg: &HilConfig,
    config_text: &str,
    config_base_dir: Option<&Path>,
    run_id: &str,
    out_dir: &Path,
) -> Result<EmulatorSummary, ProcessError> {
    std::fs::create_dir_all(out_dir)?;
    let node = IpcNode::new(run_id, "emulator")?;
    let input = node.displacement_in()?;
    let output = node.setpoint_out()?;
    let wake = node.setpoint_wake()?;
    let heartbeat = node.heartbeat_out()?;
    let control = node.control_in()?;
    let meta = EmulatorMeta {
        config_text: config_text.to_string(),
        config_origin: cfg.origin.clone(),
        config_base_dir: config_base_dir.map(Path::to_path_buf),
        rate_hz: cfg.loop_.rate_hz,
    };
    std::fs::write(
        out_dir.join("emulator-meta.json"),
        serde_json::to_string_pretty(&meta).unwrap_or_default(),
    )?;
    let sink: RecordSink<EmulatorRecord> = RecordSink::create(
        &out_dir.join("emulator.csv"),
        cfg.loop_.record_queue_capacity,
    )?;

    real_time_setup(cfg, &cfg.loop_.emulator_cpus, "emulator");
    let t0 = wait_for_start(process_id::EMULATOR, &heartbeat, &control)?;

    let clock = MonotonicClock;
    let mut scheduler = Scheduler::new(
        cfg.loop_.period_ns,
        t0 + cfg.loop_.emulator_phase_ns,
        WaitMode::SleepSpin {
            spin_ns: cfg.loop_.spin_ns,
        },
    );
    let mut core = EmulatorCore::new(&cfg.augmented, &cfg.loop_, cfg.emulator);
    let mut io = IpcEmulatorIo {
        input: &input,
        output: &output,
        wake: &wake,
        sample_wait_ns: cfg.loop_.sample_wait_ns,
        newest: None,
        displacement_range_m: (
            cfg.emulator.displacement_min_m,
            cfg.emulator.displacement_max_m,
        ),
    };
    // Hard cap: the scenario plus 30 s, in case both the rig and the orchestrator vanish.
    let max_cycles = ((cfg.scenario.duration_s + 30.0) * cfg.loop_.rate_hz) as u64;
    let heartbeat_every = (HEARTBEAT_PERIOD_NS / cfg.loop_.period_ns).max(1);
    let mut push = |r: EmulatorRecord| sink.push(r);
    loop {
        let stats = scheduler.wait_next(&clock);
        let outcome = core.cycle(&stats, &mut io, &mut push);
        if outcome == CycleOutcome::EndOfRun || stats.cycle_idx > max_cycles {
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
            if stop_requested(&control) {
                break;
            }
        }
    }
    output.publish(ForceSetpoint {
        sequence: u64::MAX,
        sample_sequence: u64::MAX,
        sample_publish_time_ns: 0,
        loop_time_ns: 0,
        force_n: 0.0,
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
    let counts = sink.finish()?;
    let summary = EmulatorSummary {
        cycles: core.counts.cycles,
        model_steps: core.counts.model_steps,
        stale_samples: core.counts.stale_samples,
        skipped_samples: core.counts.skipped_samples,
        missed_deadlines: core.counts.missed_deadlines,
        records_written: counts.written,
        records_dropped: counts.dropped,
        fault: core.fault().map(|f| f.name().to_string()),
    };
    std::fs::write(
        out_dir.join("emulator-summary.json"),
        serde_json::to_string_pretty(&summary).unwrap_or_default(),
    )?;
    Ok(summary)
}

/// Controller end-of-run summary (`controller-summary.json`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct ControllerSummary {
    pub commands: u64,
    pub limited_commands: u64,
    pub records_written: u64,
    pub records_dropped: u64,
    pub fault: Option<String>,
    pub emulator_fault: Option<String>,
    pub final_state: u32,
}

/// Runs the controller process: event-driven on new setpoints (WaitSet), with the
/// watchdog checked on every wake-up and on wait time-outs.
pub fn run_controller(
    cfg: &HilConfig,
    run_id: &str,
    out_dir: &Path,
) -> Result<ControllerSummary, ProcessError> {
    std::fs::create_dir_all(out_dir)?;
    let node = IpcNode::new(run_id, "controller")?;
    let setpoints = node.setpoint_in()?;
    let listener = node.setpoint_listener()?;
    let commands = node.command_out()?;
    let heartbeats_in = node.heartbeat_in()?;
    let heartbeat = node.heartbeat_out()?;
    let control = node.control_in()?;
    let sink: RecordSink<ControllerRecord> = RecordSink::create(
        &out_dir.join("controller.csv"),
        cfg.loop_.record_queue_capacity,
    )?;
    real_time_setup(cfg, &[], "controller");
    let t0 = wait_for_start(process_id::CONTROLLER, &heartbeat, &control)?;

    let period_ns = cfg.loop_.period_ns;
    let mut core = ControllerCore::new(cfg.controller, period_ns);
    core.set_start_time_ns(t0);
    let cap_ns = t0 + ((cfg.scenario.duration_s + 30.0) * 1e9) as u64;
    let mut next_heartbeat_ns = 0u64;
    let mut commands_sent = 0u64;
    let mut emulator_stopped = false;
    let mut stopped = false;
    let mut hb_seq = 0u64;
    listener.with_waitset(|waitset| {
        loop {
            // Block until the emulator notifies; time out after one period when a ramp
            // is running, else after the stale-setpoint limit (watchdog).
            let timeout_ns = if core.fault().is_some() {
                period_ns
            } else {
                period_ns * cfg.controller.stale_setpoint_periods as u64 / 2
            };
            listener.wait(waitset, Duration::from_nanos(timeout_ns.max(50_000)));
            let mut publish = |core: &mut ControllerCore,
                               out: Option<(
                crate::ipc::messages::ActuatorCommand,
                ControllerRecord,
            )>| {
                if let Some((cmd, rec)) = out {
                    commands.publish(cmd);
                    sink.push(rec);
                    commands_sent += 1;
                }
                let _ = core;
            };
            setpoints.receive_each(|sp| {
                if sp.emulator_state == emulator_state::STOPPED {
                    emulator_stopped = true;
                    return;
                }
                let now = monotonic_now_ns();
                let out = core.on_setpoint(&sp, now);
                publish(&mut core, out);
            });
            let now = monotonic_now_ns();
            let out = core.on_tick(now);
            publish(&mut core, out);
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
                    reserved: core.emulator_fault_code,
                });
                hb_seq += 1;
                if stop_requested(&control) {
                    stopped = true;
                }
            }
            if emulator_stopped || stopped || now > cap_ns {
                break;
            }
        }
    })?;
    heartbeat.publish(Heartbeat {
        process: process_id::CONTROLLER,
        state: controller_state::STOPPED,
        sequence: u64::MAX,
        time_ns: monotonic_now_ns(),
        fault_code: core.fault().map_or(0, Fault::code),
        reserved: core.emulator_fault_code,
    });
    let counts = sink.finish()?;
    let summary = ControllerSummary {
        commands: commands_sent,
        limited_commands: core.limited_commands,
        records_written: counts.written,
        records_dropped: counts.dropped,
        fault: core.fault().map(|f| f.name().to_string()),
        emulator_fault: (core.emulator_fault_code != 0)
            .then(|| super::fault::fault_code_name(core.emulator_fault_code)),
        final_state: core.state(),
    };
    std::fs::write(
        out_dir.join("controller-summary.json"),
        serde_json::to_string_pretty(&summary).unwrap_or_default(),
    )?;
    Ok(summary)
}
