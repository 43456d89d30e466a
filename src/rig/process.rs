//! The `bench_rig` process: runs `RigPhysics` on its own fixed-step clock, publishes one
//! displacement sample per period, applies the newest actuator command (zero-order hold),
//! and trips its own interlock (ramp to the safe force) when commands go stale.
//!
//! Records are kept in a vector reserved before the loop and written after it (the rig
//! is the hardware stand-in; its loop does not allocate either).

use std::io::Write;
use std::path::Path;

use super::load::LoadProgramme;
use super::physics::{RigPhysics, Sensor};
use crate::hil::config::{HilConfig, RigFault};
use crate::hil::fault::Fault;
use crate::hil::process::{
    real_time_setup, stop_requested, wait_for_start, ProcessError, HEARTBEAT_PERIOD_NS,
};
use crate::ipc::messages::{process_id, rig_state, sample_status, DisplacementSample, Heartbeat};
use crate::ipc::IpcNode;
use crate::rt::clock::monotonic_now_ns;
use crate::rt::{MonotonicClock, Scheduler, WaitMode};

/// One rig period, as recorded (CSV `rig.csv`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigRecord {
    pub step_idx: u64,
    pub t_s: f64,
    /// True specimen displacement at `t_s` (before the sensor), m.
    pub x_m: f64,
    pub v_m_per_s: f64,
    pub z_measured_m: f64,
    /// Command applied from `t_s` over the next period, N.
    pub command_n: f64,
    pub actuator_force_n: f64,
    pub external_force_n: f64,
    /// Sample sequence the applied command answers (-1: none yet).
    pub command_sample_seq: i64,
    pub wake_late_ns: u64,
    pub state: u32,
}

const RIG_HEADER: &str = "step_idx,t_s,x_m,v_m_per_s,z_measured_m,command_n,actuator_force_n,external_force_n,command_sample_seq,wake_late_ns,state";

/// Rig end-of-run summary (`rig-summary.json`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct RigSummary {
    pub steps: u64,
    pub missed_deadlines: u64,
    /// Periods in which no new command had arrived (command held).
    pub held_commands: u64,
    pub fault: Option<String>,
}

/// Runs the rig until the scenario ends (or STOP).
pub fn run_rig(cfg: &HilConfig, run_id: &str, out_dir: &Path) -> Result<RigSummary, ProcessError> {
    std::fs::create_dir_all(out_dir)?;
    let node = IpcNode::new(run_id, "rig")?;
    let samples = node.displacement_out()?;
    let commands = node.command_in()?;
    let heartbeat = node.heartbeat_out()?;
    let control = node.control_in()?;

    let dt = cfg.loop_.dt_s();
    let load = LoadProgramme::new(&cfg.scenario, cfg.model.length_m);
    let f0 = load.force_n(0.0);
    let x0 = cfg.model.element.static_displacement_m(f0);
    let mut physics = RigPhysics::new(&cfg.rig, x0, f0);
    let mut sensor = Sensor::new(
        cfg.rig.sensor_noise_m,
        cfg.rig.sensor_resolution_m,
        cfg.rig.seed,
    );
    let n_steps = (cfg.scenario.duration_s * cfg.loop_.rate_hz).round() as u64;
    let mut records: Vec<RigRecord> = Vec::with_capacity(n_steps as usize + 1);

    real_time_setup(cfg, &cfg.loop_.rig_cpus, "bench_rig");
    let t0 = wait_for_start(process_id::RIG, &heartbeat, &control)?;
    let clock = MonotonicClock;
    let mut scheduler = Scheduler::new(
        cfg.loop_.period_ns,
        t0,
        WaitMode::SleepSpin {
            spin_ns: cfg.loop_.spin_ns,
        },
    );
    let heartbeat_every = (HEARTBEAT_PERIOD_NS / cfg.loop_.period_ns).max(1);

    let mut command_n = f0;
    let mut command_sample_seq: i64 = -1;
    let mut last_command_step: Option<u64> = None;
    let mut fault: Option<Fault> = None;
    let mut held_commands = 0u64;
    let mut missed = 0u64;
    let mut k = 0u64;
    let mut fault_injected = false;
    while k < n_steps {
        let stats = scheduler.wait_next(&clock);
        // A late wake-up skips deadlines: the physics still advances through them
        // (the hardware does not wait), with the command held.
        while k < stats.cycle_idx && k < n_steps {
            let t = k as f64 * dt;
            physics.advance(t, dt, command_n, &load);
            k += 1;
            missed += 1;
        }
        if k >= n_steps {
            break;
        }
        let t = k as f64 * dt;
        let mut z = sensor.measure(physics.x_m);
        if cfg.rig.fault != RigFault::None && t >= cfg.rig.fault_at_s && !fault_injected {
            fault_injected = true;
            z = match cfg.rig.fault {
                RigFault::Nan => f64::NAN,
                RigFault::OutOfRange => 1.0,
                RigFault::None => z,
            };
        }
        samples.publish(DisplacementSample {
            sequence: k,
            rig_time_ns: k * cfg.loop_.period_ns,
            publish_time_ns: monotonic_now_ns(),
            displacement_m: z,
            status: sample_status::OK,
            reserved: 0,
        });
        if let Some(cmd) = commands.receive_newest() {
            if fault.is_none() {
                command_n = cmd.force_n;
                command_sample_seq = cmd.sample_sequence as i64;
            }
            last_command_step = Some(k);
        } else {
            held_commands += 1;
        }
        if fault.is_none()
            && last_command_step.is_some_and(|s| k - s > cfg.rig.command_stale_periods as u64)
        {
            fault = Some(Fault::CommandsStale);
        }
        if fault.is_some() {
            // Interlock: ramp the actuator to the safe force.
            let step = cfg.rig.safe_ramp_n_per_s * dt;
            let target = cfg.rig.safe_force_n;
            command_n = if (target - command_n).abs() <= step {
                target
            } else {
                command_n + step * (target - command_n).signum()
            };
        }
        let state = if fault.is_some() {
            rig_state::INTERLOCK
        } else {
            rig_state::RUNNING
        };
        records.push(RigRecord {
            step_idx: k,
            t_s: t,
            x_m: physics.x_m,
            v_m_per_s: physics.v_m_per_s,
            z_measured_m: z,
            command_n,
            actuator_force_n: physics.actuator_force_n,
            external_force_n: load.force_n(t),
            command_sample_seq,
            wake_late_ns: stats.wake_late_ns,
            state,
        });
        physics.advance(t, dt, command_n, &load);
        if k.is_multiple_of(heartbeat_every) {
            heartbeat.publish(Heartbeat {
                process: process_id::RIG,
                state,
                sequence: k,
                time_ns: stats.woke_ns,
                fault_code: fault.map_or(0, Fault::code),
                reserved: 0,
            });
            if stop_requested(&control) {
                break;
            }
        }
        k += 1;
    }
    samples.publish(DisplacementSample {
        sequence: k,
        rig_time_ns: k * cfg.loop_.period_ns,
        publish_time_ns: monotonic_now_ns(),
        displacement_m: physics.x_m,
        status: sample_status::END_OF_RUN,
        reserved: 0,
    });
    heartbeat.publish(Heartbeat {
        process: process_id::RIG,
        state: rig_state::FINISHED,
        sequence: k,
        time_ns: monotonic_now_ns(),
        fault_code: fault.map_or(0, Fault::code),
        reserved: 0,
    });
    let mut out = std::io::BufWriter::new(std::fs::File::create(out_dir.join("rig.csv"))?);
    writeln!(out, "{RIG_HEADER}")?;
    for r in &records {
        writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{}",
            r.step_idx,
            r.t_s,
            r.x_m,
            r.v_m_per_s,
            r.z_measured_m,
            r.command_n,
            r.actuator_force_n,
            r.external_force_n,
            r.command_sample_seq,
            r.wake_late_ns,
            r.state
        )?;
    }
    out.flush()?;
    let summary = RigSummary {
        steps: records.len() as u64,
        missed_deadlines: missed,
        held_commands,
        fault: fault.map(|f| f.name().to_string()),
    };
    std::fs::write(
        out_dir.join("rig-summary.json"),
        serde_json::to_string_pretty(&summary).unwrap_or_default(),
    )?;
    Ok(summary)
}
