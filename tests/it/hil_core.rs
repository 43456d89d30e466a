//! The runtime's loop logic without processes: the emulator iteration with a mock
//! transport and clock (stale handling, trips, determinism, zero allocation), the
//! controller's compensation and watchdog, and the rig physics step.

use crate::alloc_counter::count_allocations;
use fastemu::hil::config::{default_hil_config, HilConfig};
use fastemu::hil::controller::ControllerCore;
use fastemu::hil::emulator::{EmulatorCore, EmulatorIo, EmulatorRecord};
use fastemu::hil::fault::Fault;
use fastemu::hil::records::RecordSink;
use fastemu::ipc::messages::{emulator_state, sample_status, DisplacementSample, ForceSetpoint};
use fastemu::rig::{LoadProgramme, RigPhysics};
use fastemu::rt::{MockClock, Scheduler, WaitMode};

/// A mock transport: samples scripted per cycle (None = nothing new arrives).
struct MockIo {
    script: Vec<Option<DisplacementSample>>,
    cycle: usize,
    published: Vec<ForceSetpoint>,
}

impl EmulatorIo for MockIo {
    fn receive_newest_sample(&mut self, _expected_seq: u64) -> Option<DisplacementSample> {
        let s = self.script.get(self.cycle).copied().flatten();
        self.cycle += 1;
        s
    }
    fn publish_setpoint(&mut self, setpoint: ForceSetpoint) {
        if self.published.len() < self.published.capacity() {
            self.published.push(setpoint);
        }
    }
}

fn sample(seq: u64, z: f64) -> DisplacementSample {
    DisplacementSample {
        sequence: seq,
        rig_time_ns: seq * 244_141,
        publish_time_ns: 0,
        displacement_m: z,
        status: sample_status::OK,
        reserved: 0,
    }
}

fn config() -> HilConfig {
    default_hil_config().unwrap()
}

fn z_of(k: u64) -> f64 {
    4e-4 + 5e-5 * (k as f64 * 0.01).sin()
}

/// Runs the emulator core over `script` on a mock clock; returns records and the core.
fn run_core(
    cfg: &HilConfig,
    script: Vec<Option<DisplacementSample>>,
) -> (Vec<EmulatorRecord>, EmulatorCore) {
    let clock = MockClock::new(0);
    let mut scheduler = Scheduler::new(cfg.loop_.period_ns, 1_000, WaitMode::Sleep);
    let mut core = EmulatorCore::new(&cfg.augmented, &cfg.loop_, cfg.emulator);
    let n = script.len();
    let mut io = MockIo {
        script,
        cycle: 0,
        published: Vec::with_capacity(n),
    };
    let mut records = Vec::with_capacity(n + 8);
    for _ in 0..n {
        let stats = scheduler.wait_next(&clock);
        core.cycle(&stats, &mut io, &mut |r| records.push(r));
    }
    (records, core)
}

#[test]
fn emulator_cycle_does_not_allocate() {
    let cfg = config();
    let n = 2000u64;
    let script: Vec<_> = (0..n)
        .map(|k| {
            if k % 7 == 3 {
                None
            } else {
                Some(sample(k, z_of(k)))
            }
        })
        .collect();
    let clock = MockClock::new(0);
    let mut scheduler = Scheduler::new(cfg.loop_.period_ns, 1_000, WaitMode::Sleep);
    let mut core = EmulatorCore::new(&cfg.augmented, &cfg.loop_, cfg.emulator);
    let mut io = MockIo {
        script,
        cycle: 0,
        published: Vec::with_capacity(n as usize),
    };
    let dir = std::env::temp_dir().join(format!("fastemu-alloc-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let sink: RecordSink<EmulatorRecord> =
        RecordSink::create(&dir.join("emulator.csv"), 4096).unwrap();
    // Every few cycles the mock clock wakes late by more than a period (catch-up steps).
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
    let counts = sink.finish().unwrap();
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(allocations, 0, "the emulator loop body allocated");
    assert!(core.counts.model_steps >= n);
    assert_eq!(counts.dropped, 0);
}

#[test]
fn controller_and_rig_steps_do_not_allocate() {
    let cfg = config();
    let mut core = ControllerCore::new(cfg.controller, cfg.loop_.period_ns);
    core.set_start_time_ns(0);
    let load = LoadProgramme::new(&cfg.scenario, cfg.model.length_m);
    let mut rig = RigPhysics::new(&cfg.rig, 4e-4, 20_000.0);
    let dt = cfg.loop_.dt_s();
    let mut sent = 0;
    let allocations = count_allocations(|| {
        for k in 0..2000u64 {
            let sp = ForceSetpoint {
                sequence: k,
                sample_sequence: k,
                sample_publish_time_ns: k * cfg.loop_.period_ns,
                loop_time_ns: k * cfg.loop_.period_ns,
                force_n: 20_000.0 + 1000.0 * (k as f64 * 0.05).sin(),
                emulator_state: emulator_state::RUNNING,
                fault_code: 0,
                model_flags: 0,
                reserved: 0,
            };
            let now = k * cfg.loop_.period_ns + 50_000;
            if let Some((cmd, _)) = core.on_setpoint(&sp, now) {
                rig.advance(k as f64 * dt, dt, cmd.force_n, &load);
                sent += 1;
            }
            core.on_tick(now + 1_000);
        }
    });
    assert_eq!(allocations, 0, "controller or rig step allocated");
    assert_eq!(sent, 2000);
}

#[test]
fn missing_samples_are_held_counted_and_trip_after_the_limit() {
    let mut cfg = config();
    cfg.loop_.trip_after_stale_samples = 5;
    // 10 good samples, 3 missing (held), 5 good, then 6 missing: trips on the 6th.
    let mut script: Vec<_> = (0..10).map(|k| Some(sample(k, z_of(k)))).collect();
    script.extend([None, None, None]);
    script.extend((13..18).map(|k| Some(sample(k, z_of(k)))));
    script.extend(std::iter::repeat_n(None, 8));
    let (records, core) = run_core(&cfg, script);
    assert_eq!(
        records[10].z_used_m, records[9].z_used_m,
        "a missing sample holds the last one"
    );
    assert_eq!(records[10].stale, 1);
    assert_eq!(core.counts.skipped_samples, 3);
    assert_eq!(core.fault(), Some(Fault::TooManyStaleSamples));
    let first_tripped = records
        .iter()
        .position(|r| r.state == emulator_state::TRIPPED)
        .unwrap();
    assert_eq!(
        first_tripped,
        18 + 5,
        "trips on the 6th consecutive missing sample"
    );
}

fn check_trip(bad: DisplacementSample, expected: Fault) {
    let cfg = config();
    let mut script: Vec<_> = (0..20).map(|k| Some(sample(k, z_of(k)))).collect();
    script.push(Some(bad));
    script.extend((21..30).map(|k| Some(sample(k, z_of(k)))));
    let (records, core) = run_core(&cfg, script);
    assert_eq!(core.fault(), Some(expected));
    assert_eq!(records[19].state, emulator_state::RUNNING);
    assert!(records[20..]
        .iter()
        .all(|r| r.state == emulator_state::TRIPPED && r.fault_code == expected.code()));
    // The safe state holds the last good force.
    assert!(records[20..]
        .iter()
        .all(|r| r.force_n.to_bits() == records[19].force_n.to_bits()));
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
fn same_inputs_give_identical_records() {
    let cfg = config();
    let script = || -> Vec<_> {
        (0..3000)
            .map(|k| {
                if k % 11 == 5 {
                    None
                } else {
                    Some(sample(k, z_of(k)))
                }
            })
            .collect()
    };
    let (a, _) = run_core(&cfg, script());
    let (b, _) = run_core(&cfg, script());
    assert_eq!(a.len(), b.len());
    assert!(a
        .iter()
        .zip(&b)
        .all(|(x, y)| x.force_n.to_bits() == y.force_n.to_bits() && x == y));
}

#[test]
fn compensation_predicts_a_smooth_force_at_the_target_time() {
    let cfg = config();
    let period_ns = cfg.loop_.period_ns;
    let mut core = ControllerCore::new(cfg.controller, period_ns);
    core.set_start_time_ns(0);
    let omega = 2.0 * std::f64::consts::PI * 20.0;
    let force = |t: f64| 20_000.0 + 1_000.0 * (omega * t).sin();
    let mut last = None;
    for k in 0..50u64 {
        let sp = ForceSetpoint {
            sequence: k,
            sample_sequence: k,
            sample_publish_time_ns: k * period_ns,
            loop_time_ns: k * period_ns,
            force_n: force(k as f64 * period_ns as f64 * 1e-9),
            emulator_state: emulator_state::RUNNING,
            fault_code: 0,
            model_flags: 0,
            reserved: 0,
        };
        let now = k * period_ns + 60_000;
        last = core
            .on_setpoint(&sp, now)
            .map(|(c, _)| (c, core.target_time_s(now)));
    }
    let (cmd, t_target) = last.unwrap();
    assert!(
        (cmd.force_n - force(t_target)).abs() < 1.0,
        "{} vs {}",
        cmd.force_n,
        force(t_target)
    );
}

#[test]
fn watchdog_latches_stale_setpoints_and_ramps_to_the_safe_force() {
    let cfg = config();
    let period_ns = cfg.loop_.period_ns;
    let mut core = ControllerCore::new(cfg.controller, period_ns);
    core.set_start_time_ns(0);
    for k in 0..10u64 {
        let sp = ForceSetpoint {
            sequence: k,
            sample_sequence: k,
            sample_publish_time_ns: k * period_ns,
            loop_time_ns: k * period_ns,
            force_n: 30_000.0,
            emulator_state: emulator_state::RUNNING,
            fault_code: 0,
            model_flags: 0,
            reserved: 0,
        };
        core.on_setpoint(&sp, k * period_ns + 50_000);
    }
    let mut t = 10 * period_ns;
    let mut last_force = 30_000.0;
    for _ in 0..2000 {
        t += period_ns;
        if let Some((cmd, _)) = core.on_tick(t) {
            assert!(
                (cmd.force_n - last_force).abs()
                    <= cfg.controller.safe_ramp_n_per_s * period_ns as f64 * 1e-9 + 1e-6
            );
            last_force = cmd.force_n;
        }
    }
    assert_eq!(core.fault(), Some(Fault::SetpointsStale));
    assert_eq!(last_force, cfg.controller.safe_force_n);
    assert_eq!(core.state(), fastemu::ipc::messages::controller_state::SAFE);
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
    let script: Vec<_> = (0..n).map(|k| Some(sample(k, z_of(k)))).collect();
    let clock = MockClock::new(0);
    let mut scheduler = Scheduler::new(cfg.loop_.period_ns, 1_000, WaitMode::Sleep);
    let mut core = EmulatorCore::new(&cfg.augmented, &cfg.loop_, cfg.emulator);
    let mut io = MockIo {
        script,
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
    let mut compared = 0;
    for r in records
        .iter()
        .filter(|r| r.state == emulator_state::RUNNING && r.sample_seq > 0)
    {
        let (base_force, _) = base.step(r.z_used_m);
        let expected = base_force + friction_stiffness_n_per_m * (r.z_used_m - z_of(0));
        assert!(
            (r.force_n - expected).abs() <= 1e-6 * expected.abs(),
            "step {}: emulator {} N, element + friction spring {} N",
            r.step_idx,
            r.force_n,
            expected
        );
        compared += 1;
    }
    assert!(compared as u64 > n - 10, "compared only {compared} steps");
}
