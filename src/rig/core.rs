//! One period of the simulated rig, without transport: measure the specimen (sensor,
//! injected sample faults), take commands, run the actuator's servo (local law or
//! position hold), advance the load programme and the physics, and record. The rig process
//! wraps it with iceoryx2 ports and a clock; the in-process loop wires it directly.
//!
//! Must not: allocate, lock, log, read a clock or do I/O per period.

use super::load::LoadProgramme;
use super::physics::{RigPhysics, Sensor};
use super::programme::ProgrammeRunner;
use super::servo::{ProgrammeRequest, Servo};
use crate::hil::config::{HilConfig, InjectKind, Injection, LoopProcess};
use crate::ipc::messages::{process_id, sample_status, ActuatorCommand, DisplacementSample};
use crate::record_type;
use crate::records::event::{action_code, event_kind, injected_kind};
use crate::records::EventRecord;

record_type! {
    /// One rig period (`/rig`).
    pub struct RigRecord {
        topic: "/rig",
        schema: "fastemu/RigRecord",
        log_time: |r| (r.t_s * 1e9).round() as u64,
        fields: {
            /// rig time of the period's start (its sample instant), s
            t_s: f64,
            /// period index from the first sample
            step_idx: u64,
            /// true specimen displacement at t_s (before the sensor), m, positive in compression
            x_m: f64,
            /// true specimen velocity, m/s
            v_m_per_s: f64,
            /// displacement sample published (sensor noise and quantisation; injected faults), m
            z_measured_m: f64,
            /// actuator command applied from t_s over the period, N
            command_n: f64,
            /// force the actuator applies at t_s, N (the element's reaction)
            actuator_force_n: f64,
            /// external load programme at t_s, N
            external_force_n: f64,
            /// load programme time (pauses while held), s
            programme_time_s: f64,
            /// completed passes through the programme's block sequence (durability cycles)
            programme_cycle: u64,
            /// the programme block running (index in the sequence)
            programme_block: u32,
            /// sample sequence behind the command in effect (-1 none yet)
            command_sample_seq: u64,
            /// periods since the last command of any kind
            command_age_periods: u64,
            /// periods since the local law last changed (a stall of the loop shows here)
            law_age_periods: u64,
            /// command mode in effect: 0 force, 1 law, 2 hold
            mode: u32,
            /// rig state: 1 running, 2 hold, 4 unload, 5 operator hold
            state: u32,
            /// latched fault code, 0 none
            fault_code: u32,
            /// how late the rig's loop woke for this period, ns
            wake_late_ns: u64,
            /// 1 if this period ran in a catch-up after a late wake-up (hardware time went on)
            catch_up: u8,
            /// 1 if the period's sample was published (0: dropped by an injection)
            published: u8,
        }
    }
}

/// Events a rig core can produce in one period (at most this many).
const MAX_EVENTS_PER_PERIOD: usize = 4;

/// The simulated rig's state between periods.
#[derive(Debug, Clone)]
pub struct RigCore {
    dt_s: f64,
    period_ns: u64,
    physics: RigPhysics,
    sensor: Sensor,
    servo: Servo,
    programme: ProgrammeRunner,
    duration_s: f64,
    step_idx: u64,
    /// Injected sample faults for this rig, in time order (allocated in `new`).
    injections: Vec<Injection>,
    next_injection: usize,
    drop_remaining: u64,
    command_sample_seq: u64,
    z_measured_m: f64,
    z_published_m: f64,
    published: bool,
    was_at_rest: bool,
    was_unloaded: bool,
    last_state: u32,
    /// The command applied over the last period (in effect at the next sample), N.
    last_command_n: f64,
    events: [Option<EventRecord>; MAX_EVENTS_PER_PERIOD],
}

impl RigCore {
    /// The rig at rest in static equilibrium under the programme's first force.
    pub fn new(cfg: &HilConfig) -> RigCore {
        let dt_s = cfg.loop_.dt_s();
        let load = LoadProgramme::new(&cfg.programme, cfg.model.length_m);
        let programme = ProgrammeRunner::new(load, dt_s);
        let f0 = programme.force_n();
        let x0 = cfg.model.element.static_displacement_m(f0);
        let (physics, command0) = RigPhysics::holding(&cfg.rig, x0, f0);
        let injections = cfg
            .injections_for(LoopProcess::Rig)
            .into_iter()
            .filter(|i| {
                matches!(
                    i.kind,
                    InjectKind::Nan | InjectKind::OutOfRange | InjectKind::DropSamples { .. }
                )
            })
            .collect();
        RigCore {
            dt_s,
            period_ns: cfg.loop_.period_ns,
            physics,
            sensor: Sensor::new(
                cfg.rig.sensor_noise_m,
                cfg.rig.sensor_resolution_m,
                cfg.rig.seed,
            ),
            servo: Servo::converged(cfg.servo_config(), x0, f0, command0),
            programme,
            duration_s: cfg.programme.end_s,
            step_idx: 0,
            injections,
            next_injection: 0,
            drop_remaining: 0,
            command_sample_seq: u64::MAX,
            z_measured_m: x0,
            z_published_m: x0,
            published: true,
            was_at_rest: false,
            was_unloaded: false,
            last_state: crate::ipc::messages::rig_state::STARTING,
            last_command_n: command0,
            events: [None; MAX_EVENTS_PER_PERIOD],
        }
    }

    pub fn step_idx(&self) -> u64 {
        self.step_idx
    }

    pub fn physics(&self) -> &RigPhysics {
        &self.physics
    }

    /// The actuator's truth, recorded once per run: its parameters after perturbation,
    /// the nominal ones, the effective delay on the element's tangent stiffness at the
    /// configured preload.
    pub fn actuator_truth(
        &self,
        cfg: &HilConfig,
    ) -> (
        super::actuator::ActuatorTruthRecord,
        Vec<super::actuator::ActuatorParamRecord>,
    ) {
        let k = cfg
            .model
            .element
            .high_frequency_stiffness_n_per_m(cfg.scenario.preload_n);
        super::actuator::actuator_truth_records(&cfg.rig.actuator, self.physics.plant(), k)
    }

    pub fn servo(&self) -> &Servo {
        &self.servo
    }

    pub fn servo_mut(&mut self) -> &mut Servo {
        &mut self.servo
    }

    /// The rig state of the last period (`rig_state`).
    pub fn servo_state(&self) -> u32 {
        self.last_state
    }

    fn time_s(&self) -> f64 {
        self.step_idx as f64 * self.dt_s
    }

    fn push_event(
        &mut self,
        kind: u32,
        fault_code: u32,
        remote: u32,
        action: u32,
        latency: u64,
        value: f64,
    ) {
        let event = EventRecord {
            t_s: self.time_s(),
            process: process_id::RIG,
            kind,
            fault_code,
            remote_fault_code: remote,
            action,
            detection_latency_periods: latency,
            step_idx: self.step_idx,
            value,
        };
        if let Some(slot) = self.events.iter_mut().find(|e| e.is_none()) {
            *slot = Some(event);
        }
    }

    /// Hands the period's events to `f` (oldest first) and clears them.
    pub fn drain_events(&mut self, mut f: impl FnMut(EventRecord)) {
        for slot in &mut self.events {
            if let Some(e) = slot.take() {
                f(e);
            }
        }
    }

    /// Start of the period: the measured displacement and the sample to publish (`None`
    /// when an injection drops it).
    #[inline]
    pub fn measure(&mut self, publish_time_ns: u64) -> Option<DisplacementSample> {
        let t = self.time_s();
        self.z_measured_m = self.sensor.measure(self.physics.x_m);
        // Injections corrupt the published sample (the stream), not the servo's reading.
        let mut z = self.z_measured_m;
        if let Some(inj) = self.injections.get(self.next_injection).copied() {
            if t >= inj.at_s {
                self.next_injection += 1;
                let (code, value) = match inj.kind {
                    InjectKind::Nan => {
                        z = f64::NAN;
                        (injected_kind::NAN, 0.0)
                    }
                    InjectKind::OutOfRange => {
                        z = 1.0;
                        (injected_kind::OUT_OF_RANGE, 0.0)
                    }
                    InjectKind::DropSamples { count } => {
                        self.drop_remaining = count;
                        (injected_kind::DROP_SAMPLES, count as f64)
                    }
                    _ => (0, 0.0),
                };
                self.push_event(event_kind::INJECTED, code, 0, action_code::NONE, 0, value);
            }
        }
        self.z_published_m = z;
        self.published = self.drop_remaining == 0;
        if self.drop_remaining > 0 {
            self.drop_remaining -= 1;
            return None;
        }
        Some(DisplacementSample {
            sequence: self.step_idx,
            rig_time_ns: self.step_idx * self.period_ns,
            publish_time_ns,
            displacement_m: z,
            actuator_force_n: self.physics.actuator_force_n,
            status: sample_status::OK,
            rig_state: self.last_state,
            rig_fault_code: self.servo.trip().map_or(0, |t| t.fault.code()),
            reserved: 0,
            commanded_force_n: self.last_command_n,
        })
    }

    /// A command arrived this period.
    #[inline]
    pub fn on_command(&mut self, cmd: &ActuatorCommand) {
        self.servo.on_command(cmd, self.step_idx);
        if cmd.sample_sequence != u64::MAX {
            self.command_sample_seq = cmd.sample_sequence;
        }
    }

    /// `fastemu hil` died.
    pub fn on_orchestrator_lost(&mut self) {
        self.servo.on_orchestrator_lost(self.step_idx);
    }

    /// Operator hold / resume / orderly end.
    pub fn operator(&mut self, kind: u32) {
        match kind {
            event_kind::OPERATOR_HOLD => self.servo.operator_hold(self.step_idx),
            event_kind::OPERATOR_RESUME => self.servo.operator_resume(self.step_idx),
            event_kind::OPERATOR_STOP => self.servo.operator_end(self.step_idx),
            _ => return,
        }
        self.push_event(kind, 0, 0, action_code::NONE, 0, 0.0);
    }

    /// Runs the servo with the period's measurement, moves the programme and the physics
    /// through the period, and returns the period's record.
    #[inline]
    pub fn finish_period(&mut self, wake_late_ns: u64, catch_up: bool) -> RigRecord {
        let t = self.time_s();
        let (out, request) = self.servo.update(
            self.step_idx,
            self.z_measured_m,
            self.programme.force_n(),
            self.physics.actuator_force_n,
        );
        if let Some(trip) = self.servo.take_new_trip() {
            self.push_event(
                event_kind::FAULT,
                trip.fault.code(),
                trip.remote_fault_code,
                action_code::of(trip.action),
                trip.detection_latency_periods,
                trip.hold_position_m,
            );
        }
        match request {
            ProgrammeRequest::Run => self.programme.resume(),
            ProgrammeRequest::Hold => self.programme.hold(),
            ProgrammeRequest::Unload => self
                .programme
                .unload(self.servo.config().unload_rate_n_per_s),
        }
        let at_rest = self.servo.at_rest();
        if at_rest && !self.was_at_rest {
            self.push_event(
                event_kind::AT_REST,
                0,
                0,
                action_code::NONE,
                0,
                self.z_measured_m,
            );
        }
        self.was_at_rest = at_rest;
        let f_start = self.programme.force_n();
        let position = self
            .programme
            .load()
            .position(self.programme.programme_time_s());
        self.last_state = out.state;
        self.last_command_n = out.command_n;
        let record = RigRecord {
            t_s: t,
            step_idx: self.step_idx,
            x_m: self.physics.x_m,
            v_m_per_s: self.physics.v_m_per_s,
            z_measured_m: self.z_published_m,
            command_n: out.command_n,
            actuator_force_n: self.physics.actuator_force_n,
            external_force_n: f_start,
            programme_time_s: self.programme.programme_time_s(),
            programme_cycle: position.cycle,
            programme_block: position.block,
            command_sample_seq: self.command_sample_seq,
            command_age_periods: out.command_age_periods,
            law_age_periods: out.law_age_periods,
            mode: out.mode,
            state: out.state,
            fault_code: self.servo.trip().map_or(0, |t| t.fault.code()),
            wake_late_ns,
            catch_up: u8::from(catch_up),
            published: u8::from(self.published),
        };
        let f_end = self.programme.advance();
        if self.programme.unloaded() && !self.was_unloaded {
            self.was_unloaded = true;
            self.servo.on_unloaded();
            self.push_event(event_kind::UNLOADED, 0, 0, action_code::NONE, 0, 0.0);
        }
        self.physics.advance(
            t,
            self.dt_s,
            out.command_n,
            out.stroke_target_m,
            f_start,
            f_end,
        );
        self.step_idx += 1;
        record
    }

    /// Whether the run is over: the programme reached its end while running, or a hold
    /// has lasted long enough (at rest, unloaded when unloading).
    pub fn finished(&self) -> bool {
        self.servo.finished()
            || (self.programme.running()
                && self.programme.programme_time_s() >= self.duration_s - 0.5 * self.dt_s)
    }

    /// The end-of-run event (call once, when `finished`).
    pub fn finish_event(&mut self) {
        let after_hold = if self.servo.finished() { 1.0 } else { 0.0 };
        self.push_event(event_kind::FINISHED, 0, 0, action_code::NONE, 0, after_hold);
    }
}
