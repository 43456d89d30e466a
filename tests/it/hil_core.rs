//! The runtime's loop logic without processes: the emulator iteration with a mock
//! transport and clock (per-sample steps, interpolation of missing samples, trips,
//! determinism, zero allocation), the controller (law and force modes, limits,
//! keep-alive, watchdog and the hold commands per configured action), the local law
//! against the model it linearises, and the rig core's allocation-free period.

use crate::alloc_counter::count_allocations;
use crate::common::sample;
use fastemu::hil::config::{default_hil_config, CommandMode, HilConfig};
use fastemu::hil::controller::ControllerCore;
use fastemu::hil::emulator::{EmulatorCore, EmulatorIo, EmulatorRecord};
use fastemu::hil::fault::{Fault, FaultAction, FaultActions};
use fastemu::ipc::messages::{
    command_mode, controller_state, emulator_state, sample_status, DisplacementSample,
    ForceSetpoint, LocalLaw,
};
use fastemu::model::effects::{ModelStepper, StepperMode};
use fastemu::records::RecorderBuilder;
use fastemu::rig::core::RigCore;
use fastemu::rt::{wait_until, Clock, CycleTurn, MockClock, Scheduler, WaitMode};

/// A mock transport: the samples that arrive in each cycle (empty = nothing new).
struct MockIo {
    script: Vec<Vec<DisplacementSample>>,
    cycle: usize,
    published: Vec<ForceSetpoint>,
}

impl EmulatorIo for MockIo {
    fn receive_samples(&mut self, _expected: u64, on_sample: &mut dyn FnMut(DisplacementSample)) {
        if let Some(batch) = self.script.get(self.cycle) {
            for s in batch {
                on_sample(*s);
            }
        }
        self.cycle += 1;
    }
    fn publish_setpoint(&mut self, setpoint: ForceSetpoint) {
        if self.published.len() < self.published.capacity() {
            self.published.push(setpoint);
        }
    }
}

fn config() -> HilConfig {
    default_hil_config().unwrap()
}

fn z_of(k: u64) -> f64 {
    4e-4 + 5e-5 * (k as f64 * 0.01).sin()
}

/// One sample per cycle for `n` cycles, except the listed cycles (nothing arrives).
fn one_per_cycle(n: u64, missing: impl Fn(u64) -> bool) -> Vec<Vec<DisplacementSample>> {
    (0..n)
        .map(|k| {
            if missing(k) {
                vec![]
            } else {
                vec![sample(k, z_of(k))]
            }
        })
        .collect()
}

/// Runs the emulator core over `script` on a mock clock; returns records, setpoints, core.
fn run_core(
    cfg: &HilConfig,
    script: Vec<Vec<DisplacementSample>>,
) -> (Vec<EmulatorRecord>, Vec<ForceSetpoint>, EmulatorCore) {
    let clock = MockClock::new(0);
    let mut scheduler = Scheduler::new(cfg.loop_.period_ns, 1_000, WaitMode::Sleep);
    let mut core = EmulatorCore::new(
        &cfg.augmented,
        &cfg.loop_,
        cfg.emulator,
        cfg.stall_limit_periods(),
    );
    let n = script.len();
    let mut io = MockIo {
        script,
        cycle: 0,
        published: Vec::with_capacity(n),
    };
    let mut records = Vec::with_capacity(4 * n + 8);
    for _ in 0..n {
        let stats = scheduler.wait_next(&clock);
        core.cycle(&stats, &mut io, &mut |r| records.push(r));
    }
    (records, io.published, core)
}

#[test]
fn emulator_cycle_does_not_allocate() {
    let cfg = config();
    let n = 2000u64;
    // Every 7th cycle nothing arrives; the next brings two samples.
    let mut script: Vec<Vec<DisplacementSample>> = Vec::new();
    for k in 0..n {
        match k % 7 {
            3 => script.push(vec![]),
            4 => script.push(vec![sample(k - 1, z_of(k - 1)), sample(k, z_of(k))]),
            _ => script.push(vec![sample(k, z_of(k))]),
        }
    }
    let clock = MockClock::new(0);
    let mut scheduler = Scheduler::new(cfg.loop_.period_ns, 1_000, WaitMode::Sleep);
    let mut core = EmulatorCore::new(
        &cfg.augmented,
        &cfg.loop_,
        cfg.emulator,
        cfg.stall_limit_periods(),
    );
    let mut io = MockIo {
        script,
        cycle: 0,
        published: Vec::with_capacity(n as usize),
    };
    let dir = crate::common::TempDir::new("alloc");
    let mut builder = RecorderBuilder::new(&dir.path, "emulator");
    let sink = builder.sink::<EmulatorRecord>(8192);
    let recorder = builder.spawn().unwrap();
    recorder.start(0, "{}".into());
    // Every few cycles the mock clock wakes late by more than a period.
    let allocations = count_allocations(|| {
        for k in 0..n {
            clock.set_wake_lateness_ns(if k % 500 == 499 {
                3 * cfg.loop_.period_ns
            } else {
                0
            });
            let stats = scheduler.wait_next(&clock);
            clock.advance_ns(1);
            core.cycle(&stats, &mut io, &mut |r| sink.push(r));
        }
    });
    let result = recorder.finish();
    assert_eq!(allocations, 0, "the emulator loop body allocated");
    assert_eq!(core.counts.model_steps, n, "one model step per sample");
    assert_eq!(result.counts[0].1.dropped, 0);
    assert_eq!(result.counts[0].1.written, n);
}

#[test]
fn the_loop_turn_shared_with_the_standby_does_not_allocate() {
    // What the emulator's two loop threads add around each cycle: wait, claim, release;
    // every 5th cycle claimed by the standby after its delay, every 11th the primary late
    // by three periods (the standby's claim then skips them).
    let period_ns = config().loop_.period_ns;
    let turn = CycleTurn::new(period_ns, 1_000);
    let clock = MockClock::new(0);
    let mut claimed = 0u64;
    let mut skipped = 0u64;
    let allocations = count_allocations(|| {
        for k in 0..2000u64 {
            let idx = turn.next_idx().expect("not finished");
            let after_ns = if k % 5 == 0 { 100_000 } else { 0 };
            clock.set_wake_lateness_ns(if k % 11 == 0 { 3 * period_ns } else { 0 });
            wait_until(&clock, turn.deadline_ns(idx) + after_ns, WaitMode::Sleep);
            let stats = turn.try_claim(idx, clock.now_ns()).expect("free");
            assert!(turn.try_claim(idx, clock.now_ns()).is_none());
            claimed += 1;
            skipped += stats.missed_deadlines;
            turn.release(&stats);
        }
    });
    assert_eq!(allocations, 0, "the turn allocated");
    assert_eq!(claimed, 2000);
    // Each late wake (3 periods, plus the standby's delay on every 55th) skips 3.
    assert_eq!(skipped, 3 * 2000u64.div_ceil(11));
}

#[test]
fn controller_and_rig_cores_do_not_allocate() {
    let cfg = config();
    let period_ns = cfg.loop_.period_ns;
    let mut controller =
        ControllerCore::new(cfg.controller, cfg.safety.actions, period_ns, 25_000_000)
            .with_compensation(cfg.compensation);
    controller.set_start_time_ns(0);
    let mut rig = RigCore::new(&cfg);
    let mut sent = 0;
    let mut records = Vec::with_capacity(4000);
    let allocations = count_allocations(|| {
        for k in 0..2000u64 {
            let sample = rig.measure(k * period_ns).expect("no injection");
            let sp = ForceSetpoint {
                sequence: k,
                sample_sequence: sample.sequence,
                sample_publish_time_ns: k * period_ns,
                loop_time_ns: k * period_ns,
                law: LocalLaw {
                    force_n: 20_000.0 + 1000.0 * (k as f64 * 0.05).sin(),
                    displacement_m: sample.displacement_m,
                    stiffness_n_per_m: 5.7e7,
                    damping_ns_per_m: 75.0,
                    ..LocalLaw::default()
                },
                emulator_state: emulator_state::RUNNING,
                fault_code: 0,
                model_flags: 0,
                // The rig in force control with its measured force: the compensator
                // (estimator, guard) runs on every setpoint.
                rig_state: sample.rig_state,
                measured_force_n: sample.actuator_force_n,
                commanded_force_n: sample.commanded_force_n,
            };
            let now = k * period_ns + 50_000;
            if let Some((cmd, _)) = controller.on_setpoint(&sp, now) {
                rig.on_command(&cmd);
                sent += 1;
            }
            controller.on_tick(now + 1_000);
            records.push(rig.finish_period(0, false));
            rig.drain_events(|_| {});
        }
    });
    assert_eq!(allocations, 0, "controller or rig period allocated");
    // Every setpoint is answered but the first: the rig reports its commanded force, and
    // the controller reads the gain from samples 0 and 1 under the rig's own servo before
    // its first command (`Compensator::ready_to_command`).
    assert_eq!(sent, 1999);
    assert_eq!(records.len(), 2000);
}

/// The planned fixed lead's nudge (`compensation::LeadNudge`) on the compensator's path:
/// a sustained 33 Hz oscillation of 0.2 mm steps the lead (twice in 0.75 s), and no
/// sample allocates.
#[test]
fn the_planned_leads_nudge_does_not_allocate() {
    use fastemu::hil::compensation::{CompensationConfig, Compensator, NudgeRange};
    let cfg = CompensationConfig {
        initial_delay_s: 2.85e-3,
        adapt_lead: false,
        passivity_guard: false,
        nudge: Some(NudgeRange {
            low_s: 2.0e-3,
            high_s: 5.0e-3,
            split_hz: 100.0,
        }),
        ..CompensationConfig::with_initial_delay(2.85e-3)
    };
    let dt = 1.0 / 4096.0;
    let mut c = Compensator::new(cfg, dt);
    let mut lead = 0.0;
    let allocations = count_allocations(|| {
        for k in 0..3072u64 {
            let t = k as f64 * dt;
            let z = 0.4e-3 + 0.2e-3 * (2.0 * std::f64::consts::PI * 33.0 * t).sin();
            let f = 20e3 + 5.7e7 * (z - 0.4e-3);
            lead = c.on_sample(k, z, f, 0.86 * f).lead_s;
        }
    });
    assert_eq!(allocations, 0, "the nudge allocated");
    assert_eq!(c.lead_nudges(), 2);
    assert!((lead - 2.85e-3 * 1.05 * 1.05).abs() < 1e-9, "{lead}");
}

#[test]
fn missing_samples_are_interpolated_and_a_silent_rig_trips_the_emulator() {
    let mut cfg = config();
    cfg.loop_.trip_after_stale_samples = 5;
    // Samples 10-12 never arrive (the transport lost them); 13-17 arrive; then silence.
    let mut script = one_per_cycle(18, |k| (10..13).contains(&k));
    script.extend(std::iter::repeat_n(vec![], 8));
    let (records, published, core) = run_core(&cfg, script);
    assert_eq!(core.counts.missing_samples, 3);
    assert_eq!(
        core.counts.model_steps, 18,
        "one step per sample, missing ones included"
    );
    // The three missing samples are stepped on the straight line from 9 to 13.
    for j in 1..=3u64 {
        let r = &records[(9 + j) as usize];
        let want = z_of(9) + j as f64 / 4.0 * (z_of(13) - z_of(9));
        assert_eq!(r.sample_seq, 9 + j);
        assert_eq!(r.interpolated, 1);
        assert!(
            (r.z_used_m - want).abs() < 1e-15,
            "{} vs {want}",
            r.z_used_m
        );
    }
    assert_eq!(core.fault(), Some(Fault::TooManyStaleSamples));
    assert!(published
        .last()
        .is_some_and(|s| s.emulator_state == emulator_state::TRIPPED
            && s.fault_code == Fault::TooManyStaleSamples.code()));
}

fn check_trip(bad: DisplacementSample, expected: Fault) {
    let cfg = config();
    let mut script = one_per_cycle(20, |_| false);
    script.push(vec![bad]);
    script.extend((21..30).map(|k| vec![sample(k, z_of(k))]));
    let (records, published, core) = run_core(&cfg, script);
    assert_eq!(core.fault(), Some(expected));
    assert_eq!(records.len(), 20, "no model step after the trip");
    let after: Vec<_> = published.iter().skip(20).collect();
    assert!(!after.is_empty());
    assert!(after
        .iter()
        .all(|s| s.emulator_state == emulator_state::TRIPPED && s.fault_code == expected.code()));
}

#[test]
fn invalid_samples_trip_with_their_reason() {
    check_trip(sample(20, f64::NAN), Fault::NonFiniteSample);
    check_trip(sample(20, f64::INFINITY), Fault::NonFiniteSample);
    check_trip(sample(20, 0.5), Fault::DisplacementOutOfRange);
    check_trip(sample(20, -0.01), Fault::DisplacementOutOfRange);
    check_trip(sample(3, z_of(3)), Fault::SequenceBackwards);
    let mut flagged = sample(20, z_of(20));
    flagged.status = sample_status::SENSOR_FAULT;
    check_trip(flagged, Fault::SensorFault);
}

#[test]
fn a_wake_up_later_than_the_stall_limit_trips_the_emulator() {
    let cfg = config();
    let limit = cfg.stall_limit_periods();
    let clock = MockClock::new(0);
    let mut scheduler = Scheduler::new(cfg.loop_.period_ns, 1_000, WaitMode::Sleep);
    let mut core = EmulatorCore::new(&cfg.augmented, &cfg.loop_, cfg.emulator, limit);
    let mut io = MockIo {
        script: one_per_cycle(400, |_| false),
        cycle: 0,
        published: Vec::with_capacity(400),
    };
    for k in 0..10 {
        clock.set_wake_lateness_ns(if k == 5 {
            limit * cfg.loop_.period_ns
        } else {
            0
        });
        let stats = scheduler.wait_next(&clock);
        core.cycle(&stats, &mut io, &mut |_| {});
    }
    assert_eq!(
        core.fault(),
        None,
        "a stall of exactly the limit is ridden through"
    );
    clock.set_wake_lateness_ns((limit + 2) * cfg.loop_.period_ns);
    let stats = scheduler.wait_next(&clock);
    core.cycle(&stats, &mut io, &mut |_| {});
    assert_eq!(core.fault(), Some(Fault::EmulatorStalled));
}

#[test]
fn same_inputs_give_identical_records() {
    let cfg = config();
    let script = || one_per_cycle(3000, |k| k % 11 == 5);
    let (a, pa, _) = run_core(&cfg, script());
    let (b, pb, _) = run_core(&cfg, script());
    assert_eq!(a.len(), b.len());
    // Byte for byte: a record may hold NaN (the rig's force where a sample had none).
    let bytes = |r: &fastemu::hil::emulator::EmulatorRecord| {
        use fastemu::records::Record;
        let mut out = Vec::new();
        r.encode(&mut out);
        out
    };
    assert!(a.iter().zip(&b).all(|(x, y)| bytes(x) == bytes(y)));
    // The setpoints too, bit for bit (the measured force is NaN where a sample had none).
    let bits = |p: &[fastemu::ipc::messages::ForceSetpoint]| -> Vec<(u64, u64, u64, u64)> {
        p.iter()
            .map(|s| {
                (
                    s.sequence,
                    s.sample_sequence,
                    s.law.force_n.to_bits(),
                    s.measured_force_n.to_bits(),
                )
            })
            .collect()
    };
    assert_eq!(pa.len(), pb.len());
    assert_eq!(bits(&pa), bits(&pb));
    assert!(pa.iter().zip(&pb).all(|(x, y)| {
        let same_law = x.law == y.law;
        same_law && x.rig_state == y.rig_state && x.emulator_state == y.emulator_state
    }));
}

/// The law sent with a setpoint predicts the model: a small displacement increment from
/// the operating point is the tangent stiffness times it (up to the curvature term), and
/// the force's drift at fixed displacement is the law's rate.
#[test]
fn the_local_law_linearises_the_model_at_its_operating_point() {
    let cfg = config();
    let dt = cfg.loop_.dt_s();
    let mut stepper = ModelStepper::new(&cfg.augmented, StepperMode::Emulation, dt, 4e-4)
        .with_law_frequency(&cfg.augmented, cfg.emulator.law_frequency_hz);
    // A ramp builds up the Maxwell branch, so the rate is not zero.
    for k in 0..400 {
        stepper.step(4e-4 + 1e-6 * k as f64);
    }
    let law = stepper.local_law();
    assert!(
        law.stiffness_n_per_m > 5e7 && law.force_rate_n_per_s < -1e3,
        "{law:?}"
    );
    // Held displacement: the drift over 4 steps is the rate to first order; the
    // relaxation's second-order term is (4 dt / tau) / 2 = 0.7 % of the drift (tau = 73 ms).
    let mut held = stepper.clone();
    let mut f = 0.0;
    for _ in 0..4 {
        f = held.step(law.displacement_m).0;
    }
    let predicted = law.force_n + law.force_rate_n_per_s * 4.0 * dt;
    assert!(
        (f - predicted).abs() < 1e-2 * (f - law.force_n).abs(),
        "{f} vs {predicted}"
    );
    // A fast increment of 2 um: the tangent stiffness plus the curvature.
    let dz = 2e-6;
    let mut jumped = stepper.clone();
    let f1 = jumped.step(law.displacement_m + dz).0;
    let as_law = LocalLaw {
        force_n: law.force_n,
        displacement_m: law.displacement_m,
        velocity_m_per_s: 0.0,
        stiffness_n_per_m: law.stiffness_n_per_m,
        damping_ns_per_m: 0.0,
        force_rate_n_per_s: law.force_rate_n_per_s,
        stiffness_slope_n_per_m2: law.stiffness_slope_n_per_m2,
    };
    let predicted = as_law.evaluate(law.displacement_m + dz, 0.0, dt);
    let increment = f1 - law.force_n;
    assert!(
        (f1 - predicted).abs() < 2e-3 * increment.abs(),
        "{f1} vs {predicted} (increment {increment})"
    );
}

fn setpoint(k: u64, period_ns: u64, law: LocalLaw) -> ForceSetpoint {
    ForceSetpoint {
        sequence: k,
        sample_sequence: k,
        sample_publish_time_ns: k * period_ns,
        loop_time_ns: k * period_ns,
        law,
        emulator_state: emulator_state::RUNNING,
        fault_code: 0,
        model_flags: 0,
        rig_state: fastemu::ipc::messages::rig_state::RUNNING,
        measured_force_n: f64::NAN,
        commanded_force_n: f64::NAN,
    }
}

#[test]
fn force_mode_compensation_predicts_a_smooth_force_at_the_target_time() {
    let mut cfg = config();
    cfg.controller.command_mode = CommandMode::Force;
    let period_ns = cfg.loop_.period_ns;
    let mut core = ControllerCore::new(cfg.controller, cfg.safety.actions, period_ns, 25_000_000);
    core.set_start_time_ns(0);
    let omega = 2.0 * std::f64::consts::PI * 20.0;
    let force = |t: f64| 20_000.0 + 1_000.0 * (omega * t).sin();
    let mut last = None;
    for k in 0..50u64 {
        let sp = setpoint(
            k,
            period_ns,
            LocalLaw::constant(force(k as f64 * period_ns as f64 * 1e-9)),
        );
        let now = k * period_ns + 60_000;
        last = core
            .on_setpoint(&sp, now)
            .map(|(c, _)| (c, core.target_time_s(now)));
    }
    let (cmd, t_target) = last.unwrap();
    assert_eq!(cmd.mode, command_mode::FORCE);
    assert!(
        (cmd.law.force_n - force(t_target)).abs() < 1.0,
        "{} vs {}",
        cmd.law.force_n,
        force(t_target)
    );
}

#[test]
fn law_mode_forwards_the_law_with_the_limits_the_actuator_side_applies() {
    let cfg = config();
    let period_ns = cfg.loop_.period_ns;
    let mut core = ControllerCore::new(cfg.controller, cfg.safety.actions, period_ns, 25_000_000);
    core.set_start_time_ns(0);
    let law = LocalLaw {
        force_n: 21_000.0,
        displacement_m: 4.1e-4,
        velocity_m_per_s: 1e-3,
        stiffness_n_per_m: 5.7e7,
        damping_ns_per_m: 75.0,
        force_rate_n_per_s: -3e4,
        stiffness_slope_n_per_m2: 8e9,
    };
    let (cmd, rec) = core
        .on_setpoint(&setpoint(0, period_ns, law), 60_000)
        .unwrap();
    assert_eq!(cmd.mode, command_mode::LAW);
    assert_eq!(cmd.law, law);
    assert_eq!(
        (cmd.force_min_n, cmd.force_max_n),
        (cfg.controller.force_min_n, cfg.controller.force_max_n)
    );
    assert_eq!(rec.law_stiffness_n_per_m, law.stiffness_n_per_m);
    // Beyond the force limit: saturated, stiffness kept.
    let big = LocalLaw {
        force_n: 1e6,
        ..law
    };
    let (cmd, rec) = core
        .on_setpoint(&setpoint(1, period_ns, big), period_ns + 60_000)
        .unwrap();
    assert!(cmd.law.force_n <= cfg.controller.force_max_n);
    assert_eq!(cmd.law.stiffness_n_per_m, law.stiffness_n_per_m);
    assert_eq!(rec.limited, 1);
}

/// Feeds `n` setpoints, then silence; returns the commands of the silence.
fn silence_after_setpoints(
    actions: FaultActions,
) -> (
    ControllerCore,
    Vec<(u64, fastemu::ipc::messages::ActuatorCommand)>,
) {
    let cfg = config();
    let period_ns = cfg.loop_.period_ns;
    let stall_limit_ns = 25_000_000;
    let mut core = ControllerCore::new(cfg.controller, actions, period_ns, stall_limit_ns);
    core.set_start_time_ns(0);
    let law = LocalLaw {
        force_n: 30_000.0,
        stiffness_n_per_m: 5.7e7,
        ..LocalLaw::default()
    };
    for k in 0..10u64 {
        core.on_setpoint(&setpoint(k, period_ns, law), k * period_ns + 50_000);
    }
    let mut out = Vec::new();
    for k in 10..400u64 {
        let now = k * period_ns + 50_000;
        if let Some((cmd, _)) = core.on_tick(now) {
            out.push((k, cmd));
        }
    }
    (core, out)
}

#[test]
fn the_controller_keeps_the_law_alive_then_asks_for_a_hold_at_the_stall_limit() {
    let cfg = config();
    let period_ns = cfg.loop_.period_ns;
    let keepalive = cfg.controller.keepalive_ns / period_ns;
    let limit_periods = 25_000_000 / period_ns;
    let (core, out) = silence_after_setpoints(FaultActions::HOLD_ALL);
    assert_eq!(core.fault(), Some(Fault::SetpointsStale));
    assert_eq!(core.state(), controller_state::HOLDING);
    let trip = core.trip().unwrap();
    assert!(
        (limit_periods..=limit_periods + 2).contains(&trip.detection_latency_periods),
        "{trip:?}"
    );
    let first_hold = out
        .iter()
        .position(|(_, c)| c.mode == command_mode::HOLD)
        .unwrap();
    // Before the limit: keep-alive repeats of the last law, one per keep-alive period.
    let repeats = &out[..first_hold];
    assert!(repeats
        .iter()
        .all(|(_, c)| c.mode == command_mode::LAW && c.setpoint_sequence == 9));
    assert!(repeats.windows(2).all(|w| w[1].0 - w[0].0 == keepalive));
    // The hold goes out in the period of the detection, then once per keep-alive.
    let (k_hold, hold) = out[first_hold];
    assert_eq!(k_hold, 9 + limit_periods + 1);
    assert_eq!(hold.fault_code, Fault::SetpointsStale.code());
    assert!(out[first_hold..]
        .iter()
        .all(|(_, c)| c.mode == command_mode::HOLD));
}

#[test]
fn the_configured_action_decides_the_command_after_a_fault() {
    let indicate = FaultActions {
        emulator: FaultAction::Indicate,
        ..FaultActions::HOLD_ALL
    };
    let (core, out) = silence_after_setpoints(indicate);
    assert_eq!(core.fault(), Some(Fault::SetpointsStale));
    assert_eq!(core.state(), controller_state::FAULT_INDICATED);
    assert!(
        out.iter().all(|(_, c)| c.mode == command_mode::LAW),
        "indicate only: the law goes on"
    );
    assert!(out.last().unwrap().1.fault_code == Fault::SetpointsStale.code());
    let unload = FaultActions {
        emulator: FaultAction::HoldUnload,
        ..FaultActions::HOLD_ALL
    };
    let (_, out) = silence_after_setpoints(unload);
    assert_eq!(out.last().unwrap().1.mode, command_mode::HOLD_UNLOAD);
}

/// The emulator steps the model's effects, not just the element: with an
/// `amplitude-friction` effect whose slip force is never reached, friction is a linear
/// spring, so the force is the base element's force plus `k_f (z - z_first)` exactly.
#[test]
fn emulator_runs_model_effects_without_allocating() {
    use fastemu::model::effects::{AugmentedModel, Effect, FrictionLaw};
    use fastemu::model::ForceStepper;
    let mut cfg = config();
    let friction_stiffness_n_per_m = 3e6;
    cfg.augmented = AugmentedModel {
        effects: vec![Effect::AmplitudeFriction {
            stiffness_n_per_m: friction_stiffness_n_per_m,
            slip_force_n: 1e9,
            law: FrictionLaw::Iwan { slip_spread: 0.3 },
        }],
        ..cfg.augmented.clone()
    };
    let n = 1500u64;
    let clock = MockClock::new(0);
    let mut scheduler = Scheduler::new(cfg.loop_.period_ns, 1_000, WaitMode::Sleep);
    let mut core = EmulatorCore::new(
        &cfg.augmented,
        &cfg.loop_,
        cfg.emulator,
        cfg.stall_limit_periods(),
    );
    let mut io = MockIo {
        script: one_per_cycle(n, |_| false),
        cycle: 0,
        published: Vec::with_capacity(n as usize),
    };
    let mut records = Vec::with_capacity(n as usize + 8);
    let allocations = count_allocations(|| {
        for _ in 0..n {
            let stats = scheduler.wait_next(&clock);
            core.cycle(&stats, &mut io, &mut |r| records.push(r));
        }
    });
    assert_eq!(
        allocations, 0,
        "the emulator loop body allocated with effects on"
    );
    let mut base = ForceStepper::new(cfg.augmented.element, cfg.loop_.dt_s(), z_of(0));
    for r in &records {
        let (base_force, _) = base.step(r.z_used_m);
        let expected = base_force + friction_stiffness_n_per_m * (r.z_used_m - z_of(0));
        assert!(
            (r.force_n - expected).abs() <= 1e-6 * expected.abs(),
            "step {}: emulator {} N, element + friction spring {} N",
            r.step_idx,
            r.force_n,
            expected
        );
        // The law carries the friction spring's stiffness (sliders stick for small steps).
        assert!(r.law_stiffness_n_per_m > friction_stiffness_n_per_m);
    }
    assert_eq!(records.len() as u64, n);
}

/// An injected kill waits for its event to reach the disk (`RecordSink::wait_flushed`):
/// not before the writer has its time base (nothing is drained then), and once it runs,
/// the event is readable from the part file while the writer still runs, as a killed
/// process leaves it.
#[test]
fn a_record_waited_for_is_on_disk_before_the_writer_ends() {
    use fastemu::records::event::event_kind;
    use fastemu::records::{EventRecord, RecordSet};
    use std::time::Duration;
    let dir = crate::common::TempDir::new("flushed");
    let mut builder = RecorderBuilder::new(&dir.path, "controller");
    let events = builder.sink::<EventRecord>(64);
    let recorder = builder.spawn().unwrap();
    let event = EventRecord {
        t_s: 1.25,
        process: 2,
        kind: event_kind::INJECTED,
        fault_code: 3,
        remote_fault_code: 0,
        action: 0,
        detection_latency_periods: 0,
        step_idx: 5120,
        value: 0.0,
    };
    events.push(event);
    assert!(
        !events.wait_flushed(Duration::from_millis(50)),
        "flushed before the writer had its time base"
    );
    recorder.start(0, "{}".into());
    assert!(events.wait_flushed(Duration::from_secs(5)), "never flushed");
    let on_disk = RecordSet::open(&dir.path)
        .unwrap()
        .read_all::<EventRecord>()
        .unwrap();
    assert_eq!(on_disk.len(), 1, "{on_disk:?}");
    assert_eq!(on_disk[0].step_idx, 5120);
    let result = recorder.finish();
    assert_eq!(result.counts_of("/events").written, 1);
}
