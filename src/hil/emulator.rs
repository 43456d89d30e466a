//! The emulator's loop iteration: every displacement sample received since the last cycle,
//! oldest first, is validated and stepped through the model (one model step per rig
//! sample, so model time is the rig's sample time; a missing sample is interpolated), and
//! one setpoint per cycle carries the element's force and local linear law (unchanged,
//! with the same sample sequence, when no sample came). Transport,
//! clock and record sink are injected, so tests drive it with mocks.
//!
//! Must not (in `EmulatorCore::cycle`): allocate, lock, log, read a clock or do I/O.
//! Same sample stream gives bit-identical records (replay contract).

use super::config::{EmulatorConfig, LoopConfig};
use super::fault::Fault;
use super::passivity::{StabilityBounds, StabilityMonitor};
use crate::ipc::messages::{
    emulator_state, process_id, rig_state, sample_status, DisplacementSample, ForceSetpoint,
    LocalLaw,
};
use crate::model::effects::{AugmentedModel, ModelStepper, StepperMode};
use crate::record_type;
use crate::records::event::{action_code, event_kind};
use crate::records::EventRecord;
use crate::rt::CycleStats;

/// The emulator's view of its transport.
pub trait EmulatorIo {
    /// Calls `on_sample` for every sample received since the last call, oldest first.
    /// The transport may wait (bounded) for the sample with sequence `expected_seq`.
    fn receive_samples(&mut self, expected_seq: u64, on_sample: &mut dyn FnMut(DisplacementSample));
    fn publish_setpoint(&mut self, setpoint: ForceSetpoint);
}

record_type! {
    /// One model step (`/emulator`; `replay` re-runs `z_used_m`).
    pub struct EmulatorRecord {
        topic: "/emulator",
        schema: "fastemu/EmulatorRecord",
        log_time: |r| (r.t_s * 1e9).round() as u64,
        fields: {
            /// rig time of the sample the step used, s
            t_s: f64,
            /// model step counter
            step_idx: u64,
            /// emulator cycle (deadline grid index of its wake-up) in which the step was taken
            cycle_idx: u64,
            /// sequence of the sample the step used (interpolated step: the missing one)
            sample_seq: u64,
            /// 1 if the sample was missing and its displacement interpolated
            interpolated: u8,
            /// model step flags (1 tension clamped, 2 non-finite input)
            model_flags: u32,
            /// how late the emulator's loop woke for the cycle, ns
            wake_late_ns: u64,
            /// displacement the model stepped to, m
            z_used_m: f64,
            /// element force after the step, N
            force_n: f64,
            /// local law: tangent stiffness, N/m
            law_stiffness_n_per_m: f64,
            /// local law: tangent damping, N s/m
            law_damping_ns_per_m: f64,
            /// local law: force drift at fixed displacement, N/s
            law_force_rate_n_per_s: f64,
            /// the rig's measured actuator force in the sample, N (NaN: not measured, or interpolated)
            rig_force_n: f64,
            /// the rig's state in the sample: 1 running, 2 hold, 4 unload, 5 operator hold
            rig_state: u32,
            /// the rig's latched fault code in the sample, 0 none
            rig_fault_code: u32,
            /// stability monitor: energy the loop generated above its band, J (0 while not monitored)
            generated_energy_j: f64,
            /// stability monitor: the displacement's oscillation above its band, m
            oscillation_m: f64,
            /// the element's self-heating rise above its ambient after the step, K (0 without self-heating)
            element_temperature_rise_k: f64,
        }
    }
}

/// What a sample says about the rig itself (recorded with each step, so a report on an
/// external rig, whose own records fastemu does not have, knows its state).
#[derive(Debug, Clone, Copy, PartialEq)]
struct RigView {
    force_n: f64,
    state: u32,
    fault_code: u32,
}

impl RigView {
    fn of(sample: &DisplacementSample) -> RigView {
        RigView {
            force_n: sample.actuator_force_n,
            state: sample.rig_state,
            fault_code: sample.rig_fault_code,
        }
    }
}

record_type! {
    /// A rig sample the emulator received after its own fault (`/emulator/after_fault`):
    /// the model is no longer stepped, but the rig's view goes on being recorded, so the
    /// hold an external rig keeps (whose own records fastemu does not have) is in the
    /// records and the report.
    pub struct AfterFaultSampleRecord {
        topic: "/emulator/after_fault",
        schema: "fastemu/AfterFaultSampleRecord",
        log_time: |r| (r.t_s * 1e9).round() as u64,
        fields: {
            /// rig time of the sample, s
            t_s: f64,
            /// the sample's sequence
            sample_seq: u64,
            /// the rig's measured displacement, m
            z_measured_m: f64,
            /// the rig's measured actuator force, N (NaN: not measured)
            rig_force_n: f64,
            /// the rig's state in the sample: 1 running, 2 hold, 4 unload, 5 operator hold
            rig_state: u32,
            /// the rig's latched fault code in the sample, 0 none
            rig_fault_code: u32,
        }
    }
}

/// Where the emulator's loop puts its records: one per model step, and after its fault
/// one per rig sample (`after_fault`, dropped by default). A closure taking
/// `EmulatorRecord` is one.
pub trait EmulatorRecords {
    fn step(&mut self, r: EmulatorRecord);
    fn after_fault(&mut self, _r: AfterFaultSampleRecord) {}
}

impl<F: FnMut(EmulatorRecord)> EmulatorRecords for F {
    #[inline]
    fn step(&mut self, r: EmulatorRecord) {
        self(r)
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
    /// Cycles in which no new sample arrived.
    pub stale_cycles: u64,
    /// Samples that never arrived (stepped by interpolation).
    pub missing_samples: u64,
    pub missed_deadlines: u64,
    /// Longest wake-up delay, ns (a stall of this process).
    pub longest_stall_ns: u64,
}

/// Largest gap of missing samples bridged by interpolation; a longer gap is stepped on
/// the new sample directly (the model cannot have missed more than the transport holds).
const MAX_INTERPOLATED_GAP: u64 = 1024;

/// The emulator's state between cycles.
#[derive(Debug, Clone)]
pub struct EmulatorCore {
    /// The element plus its material effects; rig artefacts (`channel-delay`,
    /// `moving-mass`) are left out (`StepperMode::Emulation`).
    stepper: ModelStepper,
    limits: EmulatorConfig,
    trip_after_stale: u32,
    stall_trip_deadlines: u64,
    period_ns: u64,
    dt_s: f64,
    started: bool,
    last_sample: Option<DisplacementSample>,
    stale_run: u32,
    fault: Option<Fault>,
    fault_reported: bool,
    end_of_run: bool,
    /// The newest sample recorded after the fault.
    last_after_fault_seq: Option<u64>,
    setpoint_seq: u64,
    step_idx: u64,
    flags: u32,
    /// The online stability monitor (`loop-unstable`).
    monitor: StabilityMonitor,
    pub counts: EmulatorCounts,
}

impl EmulatorCore {
    /// `stall_trip_deadlines`: a wake-up that skipped more deadlines than this trips the
    /// emulator (`emulator-stalled`): it was out of the loop for longer than the
    /// ride-through limit.
    pub fn new(
        model: &AugmentedModel,
        loop_: &LoopConfig,
        limits: EmulatorConfig,
        stall_trip_deadlines: u64,
    ) -> EmulatorCore {
        EmulatorCore {
            stepper: ModelStepper::new(model, StepperMode::Emulation, loop_.dt_s(), 0.0)
                .with_law_frequency(model, limits.law_frequency_hz),
            limits,
            trip_after_stale: loop_.trip_after_stale_samples,
            stall_trip_deadlines,
            period_ns: loop_.period_ns,
            dt_s: loop_.dt_s(),
            started: false,
            last_sample: None,
            stale_run: 0,
            fault: None,
            fault_reported: false,
            end_of_run: false,
            last_after_fault_seq: None,
            setpoint_seq: 0,
            step_idx: 0,
            flags: 0,
            monitor: StabilityMonitor::new(StabilityBounds::DEFAULT, loop_.dt_s()),
            counts: EmulatorCounts::default(),
        }
    }

    /// The stability monitor's bounds (`[safety]`).
    pub fn with_stability_bounds(mut self, bounds: StabilityBounds) -> EmulatorCore {
        self.monitor = StabilityMonitor::new(bounds, self.dt_s);
        self
    }

    pub fn monitor(&self) -> &StabilityMonitor {
        &self.monitor
    }

    pub fn fault(&self) -> Option<Fault> {
        self.fault
    }

    /// The latched fault as an event record, once (call after each cycle); `now_idx` is
    /// the loop's period index now.
    pub fn take_fault_event(&mut self, now_idx: u64) -> Option<EventRecord> {
        let fault = self.fault?;
        if self.fault_reported {
            return None;
        }
        self.fault_reported = true;
        let latency = match fault {
            Fault::TooManyStaleSamples => u64::from(self.trip_after_stale) + 1,
            Fault::EmulatorStalled => self.counts.longest_stall_ns / self.period_ns,
            // The others are seen in the first sample that shows them.
            _ => 0,
        };
        Some(EventRecord {
            t_s: now_idx as f64 * self.dt_s,
            process: process_id::EMULATOR,
            kind: event_kind::FAULT,
            fault_code: fault.code(),
            remote_fault_code: 0,
            action: action_code::NONE,
            detection_latency_periods: latency,
            step_idx: now_idx,
            value: 0.0,
        })
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
        Ok(())
    }

    #[inline]
    fn step_and_record(
        &mut self,
        z_m: f64,
        sample_seq: u64,
        interpolated: bool,
        rig: RigView,
        stats: &CycleStats,
        record: &mut impl EmulatorRecords,
    ) {
        let (force, flags) = self.stepper.step(z_m);
        self.flags = flags.0 as u32;
        let law = self.stepper.local_law();
        self.counts.model_steps += 1;
        // The monitor follows the loop while the rig renders the element (force control);
        // an interpolated step (no measurement) or a hold restarts it.
        if interpolated || rig.state != rig_state::RUNNING {
            self.monitor.restart();
        } else if self.fault.is_none() && self.monitor.update(z_m, force, rig.force_n).is_some() {
            self.fault = Some(Fault::LoopUnstable);
        }
        let energy = self.monitor.state();
        record.step(EmulatorRecord {
            t_s: sample_seq as f64 * self.dt_s,
            step_idx: self.step_idx,
            cycle_idx: stats.cycle_idx + stats.missed_deadlines,
            sample_seq,
            interpolated: u8::from(interpolated),
            model_flags: self.flags,
            wake_late_ns: stats.wake_late_ns,
            z_used_m: z_m,
            force_n: force,
            law_stiffness_n_per_m: law.stiffness_n_per_m,
            law_damping_ns_per_m: law.damping_ns_per_m,
            law_force_rate_n_per_s: law.force_rate_n_per_s,
            rig_force_n: if interpolated { f64::NAN } else { rig.force_n },
            rig_state: rig.state,
            rig_fault_code: rig.fault_code,
            generated_energy_j: energy.generated_high_j,
            oscillation_m: energy.oscillation_m,
            element_temperature_rise_k: self.stepper.temperature_rise_k(),
        });
        self.step_idx += 1;
    }

    /// One received sample: validate, then step the model through it (and through any
    /// missing samples before it, interpolated).
    #[inline]
    fn on_sample(
        &mut self,
        sample: DisplacementSample,
        stats: &CycleStats,
        record: &mut impl EmulatorRecords,
    ) {
        if sample.status == sample_status::END_OF_RUN {
            self.end_of_run = true;
            return;
        }
        if self.end_of_run {
            return;
        }
        if self.fault.is_some() {
            // The model stops; the rig's view (its hold) goes on being recorded.
            if self
                .last_after_fault_seq
                .is_none_or(|last| sample.sequence > last)
            {
                self.last_after_fault_seq = Some(sample.sequence);
                record.after_fault(AfterFaultSampleRecord {
                    t_s: sample.sequence as f64 * self.dt_s,
                    sample_seq: sample.sequence,
                    z_measured_m: sample.displacement_m,
                    rig_force_n: sample.actuator_force_n,
                    rig_state: sample.rig_state,
                    rig_fault_code: sample.rig_fault_code,
                });
            }
            return;
        }
        if let Some(last) = self.last_sample {
            if sample.sequence < last.sequence {
                self.fault = Some(Fault::SequenceBackwards);
                return;
            }
            if sample.sequence == last.sequence {
                return; // a duplicate carries nothing new
            }
        }
        if let Err(fault) = self.validate(&sample) {
            self.fault = Some(fault);
            return;
        }
        match self.last_sample {
            None => {
                // Start in static equilibrium at the first sample.
                self.stepper.reset_static(sample.displacement_m);
                self.started = true;
            }
            Some(last) => {
                let gap = sample.sequence - last.sequence - 1;
                self.counts.missing_samples += gap;
                if gap <= MAX_INTERPOLATED_GAP {
                    let span = (gap + 1) as f64;
                    for j in 1..=gap {
                        let w = j as f64 / span;
                        let z =
                            last.displacement_m + w * (sample.displacement_m - last.displacement_m);
                        let rig = RigView::of(&sample);
                        self.step_and_record(z, last.sequence + j, true, rig, stats, record);
                    }
                }
            }
        }
        let rig = RigView::of(&sample);
        self.step_and_record(
            sample.displacement_m,
            sample.sequence,
            false,
            rig,
            stats,
            record,
        );
        self.last_sample = Some(sample);
    }

    /// One loop iteration after the scheduler woke with `stats`.
    #[inline]
    pub fn cycle(
        &mut self,
        stats: &CycleStats,
        io: &mut impl EmulatorIo,
        record: &mut impl EmulatorRecords,
    ) -> CycleOutcome {
        self.counts.cycles += 1;
        self.counts.missed_deadlines += stats.missed_deadlines;
        // `wake_late_ns` already spans the skipped deadlines.
        self.counts.longest_stall_ns = self.counts.longest_stall_ns.max(stats.wake_late_ns);
        if self.fault.is_none()
            && self.started
            && stats.missed_deadlines > self.stall_trip_deadlines
        {
            self.fault = Some(Fault::EmulatorStalled);
        }
        let steps_before = self.counts.model_steps;
        // The rig's sample of this cycle's grid instant, or the next one after the last:
        // expecting only "the next after the last" would, after one late sample (a slow
        // link), stay a cycle behind for good, taking each sample a cycle late.
        let expected = self
            .last_sample
            .map_or(0, |s| s.sequence + 1)
            .max(stats.cycle_idx + stats.missed_deadlines);
        io.receive_samples(expected, &mut |s| self.on_sample(s, stats, record));
        if self.end_of_run {
            return CycleOutcome::EndOfRun;
        }
        let stepped = self.counts.model_steps > steps_before;
        if self.fault.is_none() && self.started && !stepped {
            self.counts.stale_cycles += 1;
            self.stale_run += 1;
            if self.stale_run > self.trip_after_stale {
                self.fault = Some(Fault::TooManyStaleSamples);
            }
        } else if stepped {
            self.stale_run = 0;
        }
        // A setpoint every cycle once started: a new law when the model moved, the same
        // one otherwise (the controller's proof that the emulator is alive, so a silent
        // rig is told apart from a silent emulator), the trip as soon as it happens.
        if self.started {
            let law = self.stepper.local_law();
            let (sample_seq, sample_time) = self
                .last_sample
                .map_or((u64::MAX, 0), |s| (s.sequence, s.publish_time_ns));
            io.publish_setpoint(ForceSetpoint {
                sequence: self.setpoint_seq,
                sample_sequence: sample_seq,
                sample_publish_time_ns: sample_time,
                loop_time_ns: (stats.cycle_idx + stats.missed_deadlines) * self.period_ns,
                law: LocalLaw::from(law),
                emulator_state: self.state(),
                fault_code: self.fault.map_or(0, Fault::code),
                model_flags: self.flags,
                rig_state: self
                    .last_sample
                    .map_or(rig_state::STARTING, |s| s.rig_state),
                measured_force_n: self.last_sample.map_or(f64::NAN, |s| s.actuator_force_n),
                commanded_force_n: self.last_sample.map_or(f64::NAN, |s| s.commanded_force_n),
            });
            self.setpoint_seq += 1;
        }
        CycleOutcome::Continue
    }
}
