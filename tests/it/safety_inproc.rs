//! The specimen's safety, proved with physics on the deterministic in-process loop (rig,
//! emulator and controller cores wired directly; no OS timing): ride-through of stalls
//! below the limit, the hold on every fault class with its excursion bound and rest, the
//! configured actions, injected sample faults, bit-identical reruns. The transient is
//! measured independently here: the >100 Hz part (a centred 10 ms moving average taken
//! off) of the true displacement minus the offline reference.

use fastemu::hil::config::{
    default_hil_config, CommandMode, HilConfig, InjectKind, Injection, LoopProcess,
};
use fastemu::hil::fault::{Fault, FaultAction};
use fastemu::hil::inproc::{run_in_process, InProcessRun, InProcessScript};
use fastemu::ipc::messages::rig_state;
use fastemu::records::event::event_kind;
use fastemu::records::Record;
use fastemu::rig::reference::{reference_displacement_m, ReferenceStepper};

const RATE: f64 = 4096.0;
/// The first axle of the default passage reaches the sample at 2.0 s.
const FIRST_AXLE_S: f64 = 2.0;

fn cfg() -> HilConfig {
    default_hil_config().unwrap()
}

fn step_at(t_s: f64) -> u64 {
    (t_s * RATE).round() as u64
}

fn script(duration_s: f64) -> InProcessScript {
    InProcessScript {
        max_steps: step_at(duration_s) + 200_000,
        command_delay_periods: 1,
        ..InProcessScript::default()
    }
}

/// The >100 Hz residual (true displacement minus reference), per rig record.
fn high_passed_residual(cfg: &HilConfig, run: &InProcessRun) -> Vec<f64> {
    let n = run.rig.len();
    let reference = reference_displacement_m(cfg, n);
    let r: Vec<f64> = run
        .rig
        .iter()
        .map(|x| x.x_m - reference[x.step_idx as usize])
        .collect();
    let half = (RATE / 200.0) as usize;
    (0..n)
        .map(|i| {
            let (a, b) = (i.saturating_sub(half), (i + half + 1).min(n));
            r[i] - r[a..b].iter().sum::<f64>() / (b - a) as f64
        })
        .collect()
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

/// Largest transient from `from_s` on, m.
fn transient_after(cfg: &HilConfig, run: &InProcessRun, from_s: f64) -> f64 {
    let hp = high_passed_residual(cfg, run);
    max_abs(&hp[step_at(from_s) as usize..])
}

fn faults(run: &InProcessRun) -> Vec<(u32, Fault, f64, u64)> {
    run.events
        .iter()
        .filter(|e| e.kind == event_kind::FAULT)
        .map(|e| {
            (
                e.process,
                Fault::from_code(e.fault_code).unwrap(),
                e.t_s,
                e.detection_latency_periods,
            )
        })
        .collect()
}

#[test]
fn law_commands_follow_the_offline_reference() {
    let cfg = cfg();
    let run = run_in_process(&cfg, &script(3.0));
    let reference = reference_displacement_m(&cfg, run.rig.len());
    let (mut e2, mut r2) = (0.0, 0.0);
    for r in &run.rig {
        let x_ref = reference[r.step_idx as usize];
        e2 += (r.x_m - x_ref).powi(2);
        r2 += x_ref * x_ref;
    }
    let rel = (e2 / r2).sqrt();
    assert!(rel < 1e-3, "displacement relative RMS error {rel}");
    assert!(faults(&run).is_empty());
    let transient = max_abs(&high_passed_residual(&cfg, &run));
    assert!(transient < 2e-6, "resonant residual {transient} m");
}

/// The target: a 5 ms emulator stall at the first axle leaves < 20 um. With plain
/// force commands the same stall rings ~0.3 mm (what the issue measured on main).
#[test]
fn a_5_ms_emulator_stall_at_the_first_axle_leaves_a_few_um_with_the_law_and_rings_with_forces() {
    let cfg = cfg();
    let stall = InProcessScript {
        emulator_stalls: vec![(step_at(FIRST_AXLE_S), step_at(0.005))],
        ..script(3.0)
    };
    let with_law = transient_after(&cfg, &run_in_process(&cfg, &stall), FIRST_AXLE_S);
    assert!(with_law < 20e-6, "law commands: {} um", with_law * 1e6);
    let mut force_cfg = cfg.clone();
    force_cfg.controller.command_mode = CommandMode::Force;
    let run = run_in_process(&force_cfg, &stall);
    let with_forces = transient_after(&force_cfg, &run, FIRST_AXLE_S);
    assert!(
        with_forces > 100e-6,
        "force commands: {} um",
        with_forces * 1e6
    );
    // Ringing beyond 0.1 mm for 100 ms hammers the specimen: the stability monitor names
    // it (`loop-unstable`) and the rig holds.
    let f = faults(&run);
    assert!(
        f.first()
            .is_some_and(|x| x.0 == 1 && x.1 == Fault::LoopUnstable),
        "{f:?}"
    );
}

#[test]
fn stalls_below_the_limit_are_ridden_through_without_a_fault() {
    let cfg = cfg();
    let limit_ms = cfg.safety.stall_limit_s * 1e3;
    for start in [1.5, 1.95, 2.0, 2.05, 2.3] {
        for ms in [2.0, 5.0, 10.0, 20.0, limit_ms - 1.0] {
            for who in ["emulator", "controller"] {
                let stall = vec![(step_at(start), step_at(ms * 1e-3))];
                let s = if who == "emulator" {
                    InProcessScript {
                        emulator_stalls: stall,
                        ..script(2.6)
                    }
                } else {
                    InProcessScript {
                        controller_stalls: stall,
                        ..script(2.6)
                    }
                };
                let run = run_in_process(&cfg, &s);
                let label = format!("{who} stall of {ms} ms at {start} s");
                assert!(faults(&run).is_empty(), "{label}: {:?}", faults(&run));
                assert!(
                    run.rig.iter().all(|r| r.state == rig_state::RUNNING),
                    "{label}"
                );
                let transient = transient_after(&cfg, &run, start);
                // The law is exact to first order; what remains grows with the stall's
                // length and the passage's speed (worst: the axle peak, ~1 um per ms).
                let bound = if ms <= 5.0 { 2e-6 } else { 1.3e-6 * ms };
                assert!(
                    transient < bound,
                    "{label}: transient {} um",
                    transient * 1e6
                );
            }
        }
    }
}

/// Checks a hold: the rig holds from `hold_from_s`, where the specimen stays (excursion
/// bound), comes to rest, and the hold lasts at least `hold_min_s` in the records.
fn assert_held(cfg: &HilConfig, run: &InProcessRun, fault_s: f64, label: &str) {
    let fault_step = step_at(fault_s) as usize;
    let pre: Vec<f64> = run.rig[..fault_step].iter().map(|r| r.x_m).collect();
    let (lo, hi) = (
        pre.iter().fold(f64::INFINITY, |m, x| m.min(*x)),
        pre.iter().fold(f64::NEG_INFINITY, |m, x| m.max(*x)),
    );
    let after = &run.rig[fault_step..];
    let first_hold = after
        .iter()
        .position(|r| r.state == rig_state::HOLD)
        .unwrap_or_else(|| panic!("{label}: never held"));
    let hold_rows: Vec<_> = after[first_hold..].iter().collect();
    assert!(
        hold_rows
            .iter()
            .all(|r| matches!(r.state, rig_state::HOLD | rig_state::UNLOAD)),
        "{label}: left the hold"
    );
    let held_s = hold_rows.len() as f64 / RATE;
    assert!(held_s >= cfg.safety.hold_min_s, "{label}: held {held_s} s");
    // Within the pre-fault range +- 0.5 mm, and close to where it tripped.
    let x_hold = hold_rows[0].x_m;
    for r in after {
        assert!(
            r.x_m > lo - 0.5e-3 && r.x_m < hi + 0.5e-3,
            "{label}: {} outside [{lo}, {hi}] +- 0.5 mm",
            r.x_m
        );
    }
    let drift = hold_rows
        .iter()
        .fold(0.0f64, |m, r| m.max((r.x_m - x_hold).abs()));
    assert!(
        drift < 100e-6,
        "{label}: moved {} um in the hold",
        drift * 1e6
    );
    // At rest at the end: the last 50 ms within 5 um, velocity near zero.
    let tail = &hold_rows[hold_rows.len() - (0.05 * RATE) as usize..];
    let range = tail.iter().fold(f64::NEG_INFINITY, |m, r| m.max(r.x_m))
        - tail.iter().fold(f64::INFINITY, |m, r| m.min(r.x_m));
    assert!(
        range < 5e-6,
        "{label}: not at rest ({} um in the last 50 ms)",
        range * 1e6
    );
    assert!(
        run.events.iter().any(|e| e.kind == event_kind::AT_REST),
        "{label}: no at-rest event"
    );
    assert!(
        run.events
            .iter()
            .any(|e| e.kind == event_kind::FINISHED && e.value == 1.0),
        "{label}: the rig did not end the run after its hold"
    );
}

#[test]
fn death_or_long_stall_of_the_emulator_ends_in_a_hold_where_it_tripped() {
    let cfg = cfg();
    let limit = cfg.stall_limit_periods();
    for (label, s) in [
        (
            "emulator dies",
            InProcessScript {
                emulator_dies_at: Some(step_at(FIRST_AXLE_S)),
                ..script(6.0)
            },
        ),
        (
            "emulator stalls 300 ms",
            InProcessScript {
                emulator_stalls: vec![(step_at(FIRST_AXLE_S), step_at(0.3))],
                ..script(6.0)
            },
        ),
    ] {
        let run = run_in_process(&cfg, &s);
        let f = faults(&run);
        let (process, fault, t, latency) = f[0];
        assert_eq!(
            (process, fault),
            (2, Fault::SetpointsStale),
            "{label}: {f:?}"
        );
        assert!(
            (limit..=limit + 2).contains(&latency),
            "{label}: latency {latency}"
        );
        assert!(
            (t - FIRST_AXLE_S - limit as f64 / RATE).abs() < 3.0 / RATE,
            "{label}: at {t}"
        );
        // The rig acted on the controller's hold command within two periods.
        assert!(
            f.iter().any(|&(p, fault, tr, _)| p == 0
                && fault == Fault::HoldRequested
                && tr - t < 2.5 / RATE),
            "{label}: {f:?}"
        );
        assert_held(&cfg, &run, t, label);
    }
}

#[test]
fn death_or_long_stall_of_the_controller_trips_the_rigs_own_interlock() {
    let cfg = cfg();
    let limit = u64::from(cfg.rig.command_stale_periods);
    for (label, s) in [
        (
            "controller dies",
            InProcessScript {
                controller_dies_at: Some(step_at(FIRST_AXLE_S)),
                ..script(6.0)
            },
        ),
        (
            "controller stalls 300 ms",
            InProcessScript {
                controller_stalls: vec![(step_at(FIRST_AXLE_S), step_at(0.3))],
                ..script(6.0)
            },
        ),
        // No first command ever (a link that died right after the start): the interlock
        // is armed from sample 0, so the programme never runs against a constant force.
        (
            "controller dead from the start",
            InProcessScript {
                controller_dies_at: Some(0),
                ..script(6.0)
            },
        ),
    ] {
        let run = run_in_process(&cfg, &s);
        let f = faults(&run);
        let (process, fault, t, latency) = f[0];
        assert_eq!(
            (process, fault),
            (0, Fault::CommandsStale),
            "{label}: {f:?}"
        );
        assert!(
            (limit + 1..=limit + 2).contains(&latency),
            "{label}: latency {latency}"
        );
        assert_held(&cfg, &run, t, label);
    }
}

/// An actuator weaker than its command (a perturbed shaker, seed 2: 0.74 of it) loses its
/// loop mid-passage. The hold's feed-forward is a command too: the load divided by the
/// actuator's identified gain, as the law divides. (Fed the load itself forward, the
/// specimen sank 1.4 mm in 10 ms before the hold's PID caught it.) Either side's death
/// ends in a hold where it tripped, within the pre-fault range +- 0.5 mm.
#[test]
fn a_weak_actuators_hold_carries_the_load_where_it_tripped() {
    let text = include_str!("../../configs/hil-default.toml").replace(
        "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0",
        "preset = \"shaker-150kn\"\nperturb = 0.3\nperturb_seed = 2",
    );
    let cfg = fastemu::hil::config::parse_hil_config(&text, "shaker.toml", None).unwrap();
    let at = step_at(FIRST_AXLE_S + 0.3);
    for (label, s) in [
        (
            "emulator dies mid-passage",
            InProcessScript {
                emulator_dies_at: Some(at),
                ..script(6.0)
            },
        ),
        (
            "controller dies mid-passage",
            InProcessScript {
                controller_dies_at: Some(at),
                ..script(6.0)
            },
        ),
    ] {
        let run = run_in_process(&cfg, &s);
        let gain = run
            .controller
            .iter()
            .rev()
            .find(|r| r.mode == fastemu::ipc::messages::command_mode::LAW)
            .expect("law commands")
            .actuator_gain;
        assert!((0.6..0.85).contains(&gain), "{label}: gain {gain}");
        let f = faults(&run);
        assert!(!f.is_empty(), "{label}: no fault");
        assert_held(&cfg, &run, f[0].2, label);
    }
}

#[test]
fn indicate_only_keeps_force_control_on_the_last_law() {
    let mut cfg = cfg();
    cfg.safety.actions.emulator = FaultAction::Indicate;
    let run = run_in_process(
        &cfg,
        &InProcessScript {
            emulator_dies_at: Some(step_at(2.5)),
            ..script(6.0)
        },
    );
    let f = faults(&run);
    assert_eq!(f.first().map(|x| x.1), Some(Fault::SetpointsStale), "{f:?}");
    assert!(
        run.rig.iter().all(|r| r.state == rig_state::RUNNING),
        "no hold with indicate"
    );
    assert_eq!(
        run.rig.len() as u64,
        step_at(6.0),
        "the scenario ran to its end"
    );
    // The frozen law is a spring: the specimen follows the programme (2 Hz, 4 kN) on it.
    let after: Vec<f64> = run.rig[step_at(3.0) as usize..]
        .iter()
        .map(|r| r.x_m)
        .collect();
    let swing = after.iter().fold(f64::NEG_INFINITY, |m, x| m.max(*x))
        - after.iter().fold(f64::INFINITY, |m, x| m.min(*x));
    assert!(swing < 0.3e-3, "swing {} mm on the frozen law", swing * 1e3);
}

#[test]
fn hold_unload_takes_the_programme_to_zero_with_the_specimen_at_rest() {
    let mut cfg = cfg();
    cfg.safety.actions.controller = FaultAction::HoldUnload;
    let run = run_in_process(
        &cfg,
        &InProcessScript {
            controller_dies_at: Some(step_at(1.0)),
            ..script(6.0)
        },
    );
    let last = run.rig.last().unwrap();
    assert_eq!(last.external_force_n, 0.0, "unloaded");
    assert!(run.rig.iter().any(|r| r.state == rig_state::UNLOAD));
    assert!(run.events.iter().any(|e| e.kind == event_kind::UNLOADED));
    let t = faults(&run)[0].2;
    assert_held(&cfg, &run, t, "hold-unload");
    // The unload ran at the configured rate: 20 kN at 20 kN/s takes about a second.
    let unload_rows = run
        .rig
        .iter()
        .filter(|r| r.state == rig_state::UNLOAD)
        .count() as f64
        / RATE;
    assert!(unload_rows > 0.8, "unloaded in {unload_rows} s");
}

#[test]
fn injected_sample_faults_trip_the_emulator_and_end_in_a_hold() {
    for (kind, expected) in [
        (InjectKind::Nan, Fault::NonFiniteSample),
        (InjectKind::OutOfRange, Fault::DisplacementOutOfRange),
        (
            InjectKind::DropSamples { count: 400 },
            Fault::TooManyStaleSamples,
        ),
    ] {
        let mut cfg = cfg();
        cfg.injections = vec![Injection {
            process: LoopProcess::Rig,
            kind,
            at_s: 1.0,
        }];
        let run = run_in_process(&cfg, &script(4.0));
        let f = faults(&run);
        assert!(
            f.iter()
                .any(|&(p, fault, _, _)| p == 1 && fault == expected),
            "{kind:?}: {f:?}"
        );
        let ctl = f.iter().find(|x| x.0 == 2).expect("the controller latched");
        assert_eq!(ctl.1, Fault::EmulatorTripped);
        assert!(run.events.iter().any(|e| e.kind == event_kind::INJECTED));
        assert_held(&cfg, &run, ctl.2, kind.name());
    }
}

#[test]
fn a_short_drop_of_samples_is_interpolated_and_ridden_through() {
    let mut cfg = cfg();
    cfg.injections = vec![Injection {
        process: LoopProcess::Rig,
        kind: InjectKind::DropSamples { count: 20 },
        at_s: 1.0,
    }];
    let run = run_in_process(&cfg, &script(2.0));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    assert_eq!(
        run.emulator.iter().filter(|r| r.interpolated == 1).count(),
        20
    );
    assert_eq!(run.rig.iter().filter(|r| r.published == 0).count(), 20);
    assert!(transient_after(&cfg, &run, 1.0) < 2e-6);
}

#[test]
fn in_process_runs_are_bit_identical() {
    let cfg = cfg();
    let s = InProcessScript {
        emulator_stalls: vec![(step_at(1.0), 30)],
        ..script(1.5)
    };
    let (a, b) = (run_in_process(&cfg, &s), run_in_process(&cfg, &s));
    // Bytes, not `==`: keep-alive records carry NaN setpoint forces.
    fn bytes<R: Record>(v: &[R]) -> Vec<u8> {
        let mut out = Vec::new();
        for r in v {
            r.encode(&mut out);
        }
        out
    }
    assert!(a.rig.len() > 6000);
    assert!(bytes(&a.rig) == bytes(&b.rig), "rig records differ");
    assert!(
        bytes(&a.emulator) == bytes(&b.emulator),
        "emulator records differ"
    );
    assert!(
        bytes(&a.controller) == bytes(&b.controller),
        "controller records differ"
    );
    assert!(bytes(&a.events) == bytes(&b.events), "events differ");
}

/// An operator hold in the middle of the passage (the load racing up), then a resume: the
/// hold restrains the specimen, the programme pauses, and the resume hands over to the
/// law without letting go (the blend mixes two restraining laws); the passage continues.
#[test]
fn an_operator_hold_and_resume_mid_passage_is_bumpless() {
    let cfg = cfg();
    for hold_s in [2.0, 2.05, 2.3828, 2.4] {
        let resume_s = hold_s + 1.0;
        let s = InProcessScript {
            operator: vec![
                (step_at(hold_s), event_kind::OPERATOR_HOLD),
                (step_at(resume_s), event_kind::OPERATOR_RESUME),
            ],
            ..script(4.0)
        };
        let run = run_in_process(&cfg, &s);
        let label = format!("hold at {hold_s} s");
        assert!(faults(&run).is_empty(), "{label}: {:?}", faults(&run));
        let held: Vec<_> = run
            .rig
            .iter()
            .filter(|r| r.state == rig_state::OPERATOR_HOLD)
            .collect();
        assert!(
            (held.len() as f64 / RATE - 1.0).abs() < 0.01,
            "{label}: held {} periods",
            held.len()
        );
        let programme_at_hold = held[0].programme_time_s;
        assert!(
            held.iter().all(|r| r.programme_time_s == programme_at_hold),
            "{label}: the programme ran on"
        );
        // After the resume the programme continues where it paused, and once the rig is
        // wholly back on the element's law (the blend over) the specimen follows the
        // element: against the offline reference restarted from the state it is in there,
        // at that programme time, it stays within a micrometre (the loop's own fidelity).
        let first_running = run.rig.iter().position(|r| r.t_s >= resume_s).unwrap();
        let resumed = &run.rig[first_running];
        assert_eq!(resumed.state, rig_state::RUNNING, "{label}");
        assert!(
            (resumed.programme_time_s - programme_at_hold).abs() < 2.0 / RATE,
            "{label}"
        );
        let on_law = first_running + (cfg.safety.resume_blend_s * RATE).round().max(1.0) as usize;
        let r0 = &run.rig[on_law];
        let mut reference = ReferenceStepper::new(&cfg, 6.0);
        reference.resync(
            r0.x_m,
            r0.v_m_per_s,
            Some(r0.actuator_force_n),
            (r0.programme_time_s * RATE).round() as u64,
        );
        let deviation =
            run.rig[on_law..on_law + (0.5 * RATE) as usize]
                .iter()
                .fold(0.0f64, |m, r| {
                    let x_ref = reference.advance_to((r.programme_time_s * RATE).round() as u64);
                    m.max((r.x_m - x_ref).abs())
                });
        eprintln!(
            "{label}: {:.2} um from the reference restarted on the law",
            deviation * 1e6
        );
        assert!(
            deviation < 5e-6,
            "{label}: {} um from the reference restarted on the law",
            deviation * 1e6
        );
        assert_eq!(run.rig.last().unwrap().state, rig_state::RUNNING, "{label}");
    }
}

/// An operator's resume takes the rig out of an operator hold, but not out of the hold of
/// an operator's end (a stop): the unload goes on and the run ends (a trial of
/// 2026-11-29: `ctl stop` then `ctl resume` put the rig back in force control with the
/// programme ended, and the run never finished).
#[test]
fn a_resume_does_not_take_back_a_stop() {
    use fastemu::rig::Servo;
    let cfg = cfg();
    let (z0, f0) = (4.0e-4, 2.0e4);
    let mut servo = Servo::new(cfg.servo_config(), z0, f0);
    let mut step = 0u64;
    let mut run = |servo: &mut Servo, periods: u64| {
        for _ in 0..periods {
            // The element's law, constant at the load the specimen carries.
            servo.on_command(&crate::common::law_command(step), step);
            servo.update(step, z0, f0, f0);
            step += 1;
        }
        step
    };
    let k = run(&mut servo, 10);
    servo.operator_hold(k);
    let k = run(&mut servo, 10);
    assert!(servo.holding());
    servo.operator_resume(k);
    let k = run(&mut servo, 10);
    assert!(!servo.holding(), "an operator hold is resumed");
    servo.operator_end(k);
    let k = run(&mut servo, 10);
    assert!(servo.holding());
    servo.operator_resume(k);
    let mut k = run(&mut servo, 10);
    assert!(servo.holding(), "a stop was taken back by a resume");
    assert!(servo.trip().is_none());
    // A stop repeated every period (an operator pressing it again and again) does not
    // restart the hold's clock: the unloaded specimen at rest ends the run.
    servo.on_unloaded();
    let periods = ((cfg.servo_config().hold_min_s + 1.0) / cfg.loop_.dt_s()) as u64;
    for _ in 0..periods {
        servo.operator_end(k);
        k = run(&mut servo, 1);
    }
    assert!(
        servo.finished(),
        "repeated stops kept the run from finishing"
    );
}

/// Commands a rig must not act on (unknown mode, a non-finite law, limits out of order)
/// neither drive the actuator nor keep the interlock fed: after the last good command the
/// servo latches commands-stale exactly `command_stale_periods` later and holds, as if
/// nothing had arrived. The same check guards the iceoryx2 path and the UDP link.
#[test]
fn commands_with_bad_content_are_dropped_and_end_in_commands_stale() {
    use fastemu::ipc::messages::{command_mode, ActuatorCommand, LocalLaw};
    use fastemu::rig::Servo;
    let cfg = cfg();
    let servo_cfg = cfg.servo_config();
    let stale = servo_cfg.command_stale_periods;
    let (z0, f0) = (4.0e-4, 2.0e4);
    let mut servo = Servo::new(servo_cfg, z0, f0);
    let good = ActuatorCommand {
        sequence: 0,
        setpoint_sequence: 0,
        sample_sequence: 0,
        sample_publish_time_ns: 0,
        law: LocalLaw::constant(2.5e4),
        force_min_n: -5e3,
        force_max_n: 1.2e5,
        mode: command_mode::FORCE,
        controller_state: 1,
        fault_code: 0,
        reserved: 0,
        compensation: fastemu::ipc::messages::Compensation::NONE,
    };
    let mut nan_law = good;
    nan_law.law.force_n = f64::NAN;
    let bad = [
        ActuatorCommand { mode: 9, ..good },
        nan_law,
        ActuatorCommand {
            force_min_n: 1e5,
            force_max_n: 0.0,
            ..good
        },
    ];
    // Period 0: the good command is taken; its force is what the actuator is told.
    servo.on_command(&good, 0);
    let (out, _) = servo.update(0, z0, f0, f0);
    assert_eq!(out.command_n, 2.5e4);
    assert_eq!(out.mode, command_mode::FORCE);
    let mut tripped_at = None;
    for step in 1..=stale + 10 {
        let mut c = bad[(step % 3) as usize];
        c.sequence = step;
        c.setpoint_sequence = step;
        servo.on_command(&c, step);
        let (out, _) = servo.update(step, z0, f0, f0);
        if tripped_at.is_none() {
            if let Some(trip) = servo.trip() {
                tripped_at = Some(trip.step_idx);
                assert_eq!(trip.fault, Fault::CommandsStale);
                assert_eq!(trip.detection_latency_periods, stale + 1);
            } else {
                // Until the trip the last good command stands: never a bad one.
                assert_eq!(out.command_n, 2.5e4, "step {step}");
                assert_eq!(out.command_age_periods, step, "step {step}");
            }
        }
    }
    assert_eq!(tripped_at, Some(stale + 1));
    assert!(servo.holding());
    assert_eq!(servo.rejected_commands(), stale + 10);
}
