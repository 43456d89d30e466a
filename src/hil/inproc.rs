//! A deterministic in-process closed loop: the rig core, the emulator core and the
//! controller core wired by queues with fixed transport delays on one simulated clock,
//! with scripted stalls and deaths of the emulator and the controller. For tests and
//! design studies of ride-through, holds and stability: no threads, no clock, no I/O, so
//! a result depends on the configuration and the script only.
//!
//! Must not: be used by the real-time processes (it allocates freely).

use std::collections::VecDeque;

use super::config::HilConfig;
use super::controller::{ControllerCore, ControllerRecord};
use super::emulator::{EmulatorCore, EmulatorIo, EmulatorRecord};
use crate::ipc::messages::{ActuatorCommand, DisplacementSample, ForceSetpoint};
use crate::records::EventRecord;
use crate::rig::core::{RigCore, RigRecord};
use crate::rt::CycleStats;

/// The script of an in-process run.
#[derive(Debug, Clone, Default)]
pub struct InProcessScript {
    /// Periods to run at most (the rig may finish earlier).
    pub max_steps: u64,
    /// Emulator stalls: (first period, length in periods). It does not run, then wakes
    /// with the skipped deadlines.
    pub emulator_stalls: Vec<(u64, u64)>,
    pub controller_stalls: Vec<(u64, u64)>,
    /// Period from which the emulator (controller) is dead.
    pub emulator_dies_at: Option<u64>,
    pub controller_dies_at: Option<u64>,
    /// Periods from a command being sent to the rig applying it (>= 1).
    pub command_delay_periods: u64,
    /// Operator actions: (period, `event_kind::OPERATOR_HOLD` / `_RESUME` / `_STOP`).
    pub operator: Vec<(u64, u32)>,
}

/// Records of an in-process run.
#[derive(Debug, Clone, Default)]
pub struct InProcessRun {
    pub rig: Vec<RigRecord>,
    pub emulator: Vec<EmulatorRecord>,
    pub controller: Vec<ControllerRecord>,
    pub events: Vec<EventRecord>,
    /// The compensation plan the controller ran with (`check::compensation_plan`).
    pub plan: Option<crate::hil::check::CompensationPlan>,
}

struct QueueIo<'a> {
    samples: &'a mut VecDeque<DisplacementSample>,
    setpoints: &'a mut VecDeque<ForceSetpoint>,
}

impl EmulatorIo for QueueIo<'_> {
    fn receive_samples(&mut self, _expected: u64, on_sample: &mut dyn FnMut(DisplacementSample)) {
        while let Some(s) = self.samples.pop_front() {
            on_sample(s);
        }
    }
    fn publish_setpoint(&mut self, setpoint: ForceSetpoint) {
        self.setpoints.push_back(setpoint);
    }
}

fn stalled(stalls: &[(u64, u64)], k: u64) -> bool {
    stalls.iter().any(|&(a, n)| k >= a && k < a + n)
}

/// Runs the loop in process on `cfg` with `script`.
pub fn run_in_process(cfg: &HilConfig, script: &InProcessScript) -> InProcessRun {
    let period_ns = cfg.loop_.period_ns;
    let mut rig = RigCore::new(cfg);
    let mut emulator = EmulatorCore::new(
        &cfg.augmented,
        &cfg.loop_,
        cfg.emulator,
        cfg.stall_limit_periods(),
    )
    .with_stability_bounds(cfg.safety.stability);
    let plan = crate::hil::check::compensation_plan(cfg);
    let mut controller = ControllerCore::new(
        cfg.controller,
        cfg.safety.actions,
        period_ns,
        (cfg.safety.stall_limit_s * 1e9) as u64,
    )
    .with_compensation(crate::hil::check::starting_compensation(cfg, plan.as_ref()));
    controller.set_start_time_ns(0);
    let mut samples: VecDeque<DisplacementSample> = VecDeque::new();
    let mut setpoints: VecDeque<ForceSetpoint> = VecDeque::new();
    // Commands with the period from which the rig sees them.
    let mut commands: VecDeque<(u64, ActuatorCommand)> = VecDeque::new();
    let mut run = InProcessRun {
        plan,
        ..InProcessRun::default()
    };
    let mut emulator_last_cycle: Option<u64> = None;
    let delay = script.command_delay_periods.max(1);
    for k in 0..script.max_steps {
        let t_ns = k * period_ns;
        if let Some(s) = rig.measure(t_ns) {
            samples.push_back(s);
        }
        for &(at, kind) in &script.operator {
            if at == k {
                rig.operator(kind);
            }
        }
        while commands.front().is_some_and(|&(at, _)| at <= k) {
            let (_, cmd) = commands.pop_front().expect("front checked");
            rig.on_command(&cmd);
        }
        run.rig.push(rig.finish_period(0, false));
        rig.drain_events(|e| run.events.push(e));
        if rig.finished() {
            rig.finish_event();
            rig.drain_events(|e| run.events.push(e));
            break;
        }
        let emulator_alive = script.emulator_dies_at.is_none_or(|d| k < d);
        if emulator_alive && !stalled(&script.emulator_stalls, k) {
            // The scheduler's convention: the cycle is the first deadline it woke late
            // for; `missed_deadlines` more passed while it was stalled.
            let missed = emulator_last_cycle.map_or(0, |c| k - c - 1);
            emulator_last_cycle = Some(k);
            let stats = CycleStats {
                cycle_idx: k - missed,
                deadline_ns: (k - missed) * period_ns,
                woke_ns: t_ns,
                wake_late_ns: missed * period_ns,
                missed_deadlines: missed,
            };
            let mut io = QueueIo {
                samples: &mut samples,
                setpoints: &mut setpoints,
            };
            emulator.cycle(&stats, &mut io, &mut |r| run.emulator.push(r));
            if let Some(e) = emulator.take_fault_event(k) {
                run.events.push(e);
            }
        }
        let controller_alive = script.controller_dies_at.is_none_or(|d| k < d);
        if controller_alive && !stalled(&script.controller_stalls, k) {
            let now = t_ns + 30_000;
            while let Some(sp) = setpoints.pop_front() {
                if let Some((cmd, rec)) = controller.on_setpoint(&sp, now) {
                    commands.push_back((k + delay, cmd));
                    run.controller.push(rec);
                }
            }
            if let Some((cmd, rec)) = controller.on_tick(now) {
                commands.push_back((k + delay, cmd));
                run.controller.push(rec);
            }
            if let Some(trip) = controller.take_new_trip() {
                run.events.push(trip.event(0, period_ns));
            }
        }
    }
    run
}

impl InProcessRun {
    /// Writes the run's records as a `fastemu hil` run would (`parts/` of each process,
    /// merged into `<report_dir>/records.mcap`), with `config_text` in every `/meta`, so
    /// that the offline tools (`replay`, `export`, `diagnose --run`) read an in-process
    /// run like a real one. Loop time 0 is Unix time 0.
    pub fn write_records(
        &self,
        report_dir: &std::path::Path,
        cfg: &HilConfig,
        config_text: &str,
    ) -> Result<crate::records::merge::MergeStats, crate::records::reader::RecordsError> {
        use crate::records::{Record, RecorderBuilder};
        fn write_all<R: Record>(
            builder: &mut RecorderBuilder,
            records: &[R],
        ) -> crate::records::RecordSink<R> {
            let sink = builder.sink::<R>(records.len());
            for r in records {
                sink.push(*r);
            }
            sink
        }
        let io_err = |e: std::io::Error| crate::records::reader::RecordsError {
            path: report_dir.display().to_string(),
            message: e.to_string(),
        };
        // Each process records its own events (labels as in `EventRecord::process_name`).
        let labels = [
            ("rig", "bench_rig"),
            ("emulator", "emulator"),
            ("controller", "controller"),
        ];
        for (process, label) in labels {
            let mut builder = RecorderBuilder::new(report_dir, process);
            let events: Vec<EventRecord> = self
                .events
                .iter()
                .filter(|e| e.process_name() == label)
                .copied()
                .collect();
            let _events = write_all(&mut builder, &events);
            // The rig records its actuator's truth once, as `rig::process` does (the
            // same configuration draws the same truth).
            // (None when the run stands for an external rig: no rig records.)
            let _truth = (process == "rig" && !self.rig.is_empty()).then(|| {
                let (truth, params) = crate::rig::core::RigCore::new(cfg).actuator_truth(cfg);
                (
                    write_all(&mut builder, &[truth]),
                    write_all(&mut builder, &params),
                )
            });
            let (_rig, _emulator, _controller) = match process {
                "rig" => (Some(write_all(&mut builder, &self.rig)), None, None),
                "emulator" => (None, Some(write_all(&mut builder, &self.emulator)), None),
                _ => (None, None, Some(write_all(&mut builder, &self.controller))),
            };
            let recorder = builder.spawn().map_err(io_err)?;
            let meta = super::process::meta_json(cfg, process, "in-process", config_text, None, 0);
            recorder.start(0, meta);
            recorder.finish();
        }
        crate::records::merge::merge_parts(report_dir)
    }
}
