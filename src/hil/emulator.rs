//! The emulator's loop iteration: newest displacement sample in, validated, one model
//! step per loop period (plus one per skipped deadline), force setpoint out, one record
//! per model step. Transport, clock and record sink are injected, so tests drive it with
//! mocks.
//!
//! Must not (in `EmulatorCore::cycle`): allocate, lock, log, read a clock or do I/O.
//! Same inputs give bit-identical records (replay contract).

use std::io::Write;

use super::config::{EmulatorConfig, LoopConfig};
use super::fault::Fault;
use super::records::{sequence_column, CsvRecord};
use crate::ipc::messages::{emulator_state, sample_status, DisplacementSample, ForceSetpoint};
use crate::model::effects::{AugmentedModel, ModelStepper, StepperMode};
use crate::rt::CycleStats;

/// The emulator's view of its transport.
pub trait EmulatorIo {
    /// Newest displacement sample received since the last call, if any. The transport
    /// may wait (bounded) for the sample with sequence `expected_seq` to arrive.
    fn receive_newest_sample(&mut self, expected_seq: u64) -> Option<DisplacementSample>;
    fn publish_setpoint(&mut self, setpoint: ForceSetpoint);
}

/// One model step, as recorded (CSV `emulator.csv`; `replay` re-runs `z_used_m`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EmulatorRecord {
    pub step_idx: u64,
    pub cycle_idx: u64,
    /// Sequence of the sample the step used (`u64::MAX` before the first sample).
    pub sample_seq: u64,
    /// 1 if no new sample arrived for this step (value held), else 0.
    pub stale: u8,
    /// 1 for a catch-up step of a skipped deadline.
    pub catch_up: u8,
    /// One of `emulator_state`.
    pub state: u32,
    pub fault_code: u32,
    pub model_flags: u32,
    pub wake_late_ns: u64,
    pub z_used_m: f64,
    pub force_n: f64,
}

impl CsvRecord for EmulatorRecord {
    const HEADER: &'static str = "step_idx,cycle_idx,sample_seq,stale,catch_up,state,fault_code,model_flags,wake_late_ns,z_used_m,force_n";
    fn write_csv(&self, out: &mut dyn Write) -> std::io::Result<()> {
        // `{}` on f64 prints the shortest text that parses back to the same bits.
        let seq = sequence_column(self.sample_seq);
        writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{}",
            self.step_idx,
            self.cycle_idx,
            seq,
            self.stale,
            self.catch_up,
            self.state,
            self.fault_code,
            self.model_flags,
            self.wake_late_ns,
            self.z_used_m,
            self.force_n
        )
    }
}

/// What the loop should do after a cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CycleOutcome {
    Continue,
    /// The rig sent its end-of-run sample.
    EndOfRun,
}

/// Counters reported at the end of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct EmulatorCounts {
    pub cycles: u64,
    pub model_steps: u64,
    pub stale_samples: u64,
    pub skipped_samples: u64,
    pub missed_deadlines: u64,
}

/// The emulator's state between cycles.
#[derive(Debug, Clone)]
pub struct EmulatorCore {
    /// The element plus its material effects; rig artefacts (`channel-delay`,
    /// `moving-mass`) are left out (`StepperMode::Emulation`).
    stepper: ModelStepper,
    limits: EmulatorConfig,
    trip_after_stale: u32,
    period_ns: u64,
    started: bool,
    last_sample: Option<DisplacementSample>,
    stale_run: u32,
    fault: Option<Fault>,
    setpoint_seq: u64,
    step_idx: u64,
    pub counts: EmulatorCounts,
}

impl EmulatorCore {
    pub fn new(model: &AugmentedModel, loop_: &LoopConfig, limits: EmulatorConfig) -> EmulatorCore {
        EmulatorCore {
            stepper: ModelStepper::new(model, StepperMode::Emulation, loop_.dt_s(), 0.0),
            limits,
            trip_after_stale: loop_.trip_after_stale_samples,
            period_ns: loop_.period_ns,
            started: false,
            last_sample: None,
            stale_run: 0,
            fault: None,
            setpoint_seq: 0,
            step_idx: 0,
            counts: EmulatorCounts::default(),
        }
    }

    pub fn fault(&self) -> Option<Fault> {
        self.fault
    }

    pub fn state(&self) -> u32 {
        if self.fault.is_some() {
            emulator_state::TRIPPED
        } else if self.started {
            emulator_state::RUNNING
        } else {
            emulator_state::STARTING
        }
    }

    fn validate(&self, sample: &DisplacementSample) -> Result<(), Fault> {
        if sample.status == sample_status::SENSOR_FAULT {
            return Err(Fault::SensorFault);
        }
        if !sample.displacement_m.is_finite() {
            return Err(Fault::NonFiniteSample);
        }
        if !(self.limits.displacement_min_m..=self.limits.displacement_max_m)
            .contains(&sample.displacement_m)
        {
            return Err(Fault::DisplacementOutOfRange);
        }
        if let Some(last) = &self.last_sample {
            if sample.sequence < last.sequence {
                return Err(Fault::SequenceBackwards);
            }
        }
        Ok(())
    }

    /// One loop iteration after the scheduler woke with `stats`.
    #[inline]
    pub fn cycle(
        &mut self,
        stats: &CycleStats,
        io: &mut impl EmulatorIo,
        record: &mut impl FnMut(EmulatorRecord),
    ) -> CycleOutcome {
        self.counts.cycles += 1;
        self.counts.missed_deadlines += stats.missed_deadlines;
        let received = io.receive_newest_sample(stats.cycle_idx + stats.missed_deadlines);
        let mut fresh = false;
        if let Some(sample) = received {
            if sample.status == sample_status::END_OF_RUN {
                return CycleOutcome::EndOfRun;
            }
            let is_new = self
                .last_sample
                .is_none_or(|l| sample.sequence != l.sequence);
            if self.fault.is_none() && is_new {
                match self.validate(&sample) {
                    Ok(()) => {
                        if let Some(last) = &self.last_sample {
                            self.counts.skipped_samples +=
                                sample.sequence.saturating_sub(last.sequence + 1);
                        }
                        if !self.started {
                            // Start in static equilibrium at the first sample.
                            self.stepper.reset_static(sample.displacement_m);
                            self.started = true;
                        }
                        self.last_sample = Some(sample);
                        fresh = true;
                    }
                    Err(fault) => self.fault = Some(fault),
                }
            }
        }
        if self.fault.is_none() && self.started && !fresh {
            self.counts.stale_samples += 1;
            self.stale_run += 1;
            if self.stale_run > self.trip_after_stale {
                self.fault = Some(Fault::TooManyStaleSamples);
            }
        } else if fresh {
            self.stale_run = 0;
        }

        let (sample_seq, sample_time, z) = match &self.last_sample {
            Some(s) => (s.sequence, s.publish_time_ns, s.displacement_m),
            None => (u64::MAX, 0, 0.0),
        };
        let mut force = self.stepper.force_n();
        let mut flags = 0u32;
        // Skipped deadlines are caught up with steps on the held value, so model time
        // stays on the loop grid; each is recorded.
        let n_steps = 1 + stats.missed_deadlines;
        for i in 0..n_steps {
            let running = self.fault.is_none() && self.started;
            if running {
                let (f, step_flags) = self.stepper.step(z);
                force = f;
                flags = step_flags.0 as u32;
                self.counts.model_steps += 1;
            }
            record(EmulatorRecord {
                step_idx: self.step_idx,
                cycle_idx: stats.cycle_idx + i,
                sample_seq,
                stale: u8::from(!fresh || i > 0),
                catch_up: u8::from(i < n_steps - 1),
                state: self.state(),
                fault_code: self.fault.map_or(0, Fault::code),
                model_flags: flags,
                wake_late_ns: stats.wake_late_ns,
                z_used_m: z,
                force_n: force,
            });
            self.step_idx += 1;
        }
        let cycle_idx = stats.cycle_idx + stats.missed_deadlines;
        io.publish_setpoint(ForceSetpoint {
            sequence: self.setpoint_seq,
            sample_sequence: sample_seq,
            sample_publish_time_ns: sample_time,
            loop_time_ns: cycle_idx * self.period_ns,
            force_n: force,
            emulator_state: self.state(),
            fault_code: self.fault.map_or(0, Fault::code),
            model_flags: flags,
            reserved: 0,
        });
        self.setpoint_seq += 1;
        CycleOutcome::Continue
    }
}
