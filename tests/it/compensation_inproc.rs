//! The loop in front of actuators whose delay fastemu does not know (issue 24, SPEC 6.1),
//! proved on the deterministic in-process loop: the controller learns the delay from a
//! wrong starting guess while the run stays faithful, the passivity guard adds damping only
//! while the loop generates energy, and an unstable loop ends in `loop-unstable` and the
//! rig's hold with a bounded excursion. Fidelity is measured independently here, against
//! the offline reference (`reference_displacement_m`).

use fastemu::hil::config::{default_hil_config, HilConfig};
use fastemu::hil::controller::ControllerRecord;
use fastemu::hil::fault::Fault;
use fastemu::hil::inproc::{run_in_process, InProcessRun, InProcessScript};
use fastemu::ipc::messages::{command_mode, process_id, rig_state};
use fastemu::records::event::event_kind;
use fastemu::rig::reference::reference_displacement_m;

const RATE: f64 = 4096.0;

fn script(duration_s: f64) -> InProcessScript {
    InProcessScript {
        max_steps: (duration_s * RATE) as u64,
        command_delay_periods: 1,
        ..InProcessScript::default()
    }
}

/// Relative RMS displacement error against the offline reference.
fn displacement_error(cfg: &HilConfig, run: &InProcessRun) -> f64 {
    displacement_error_before(cfg, run, f64::INFINITY)
}

/// The same over the rig's records before `t_s`.
fn displacement_error_before(cfg: &HilConfig, run: &InProcessRun, t_s: f64) -> f64 {
    let reference = reference_displacement_m(cfg, run.rig.len());
    let (mut e2, mut r2) = (0.0, 0.0);
    for r in run.rig.iter().filter(|r| r.t_s < t_s) {
        let x_ref = reference[r.step_idx as usize];
        e2 += (r.x_m - x_ref).powi(2);
        r2 += x_ref * x_ref;
    }
    (e2 / r2).sqrt()
}

/// How far the rig's displacement went, over the whole run, beyond the range its records
/// kept before `t_s`, m.
fn beyond_range_before(run: &InProcessRun, t_s: f64) -> f64 {
    let (lo, hi) = run
        .rig
        .iter()
        .filter(|r| r.t_s < t_s)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), r| {
            (a.min(r.x_m), b.max(r.x_m))
        });
    run.rig
        .iter()
        .map(|r| (r.x_m - hi).max(lo - r.x_m).max(0.0))
        .fold(0.0f64, f64::max)
}

fn faults(run: &InProcessRun) -> Vec<(u32, Fault, f64)> {
    run.events
        .iter()
        .filter(|e| e.kind == event_kind::FAULT)
        .map(|e| (e.process, Fault::from_code(e.fault_code).unwrap(), e.t_s))
        .collect()
}

/// The rig's true actuator's effective delay on the element (its dynamics and transport
/// over 1-20 Hz, `ActuatorPlant::effective_delay`) plus half a period of hold, s: the
/// truth the identified delay is checked against, from the plant, not the controller.
fn truth_delay_s(cfg: &HilConfig) -> f64 {
    let k = cfg
        .model
        .element
        .high_frequency_stiffness_n_per_m(cfg.scenario.preload_n);
    let plant = fastemu::rig::actuator::ActuatorPlant::from_config(&cfg.rig.actuator);
    plant.effective_delay(k).delay_s + 0.5 / RATE
}

/// The lead the controller sent last, s.
fn final_lead_s(run: &InProcessRun) -> f64 {
    run.controller
        .iter()
        .rev()
        .find(|r| r.mode == command_mode::LAW)
        .map(|r| r.lead_s)
        .unwrap()
}

/// From a guess of 0 (the default actuator needs ~0.25 ms) and from one 100 % too long,
/// declared or not, the run is faithful from its start, the lead settles within 2 s, and
/// the identified delay is the one a matched run identifies.
#[test]
fn a_wrong_initial_delay_is_learned_and_the_run_stays_faithful() {
    let matched = {
        let cfg = default_hil_config().unwrap();
        let run = run_in_process(&cfg, &script(4.0));
        assert!(faults(&run).is_empty());
        final_lead_s(&run)
    };
    // The default actuator: 122 us of hold + 50 us + 80 us, as seen at the samples.
    assert!((200e-6..330e-6).contains(&matched), "{matched}");
    // Declared (the plan may start elsewhere than the guess) and not (an external rig's:
    // the run starts at the guess).
    for (initial_s, declared) in [
        (0.0, true),
        (0.0, false),
        (2.0 * 252e-6, true),
        (2.0 * 252e-6, false),
    ] {
        let mut cfg = default_hil_config().unwrap();
        cfg.compensation.initial_delay_s = initial_s;
        cfg.compensation.plan_from_actuator = declared;
        let run = run_in_process(&cfg, &script(4.0));
        if !declared {
            assert!(run.plan.is_none());
        }
        assert!(faults(&run).is_empty(), "{initial_s}: {:?}", faults(&run));
        let error = displacement_error(&cfg, &run);
        assert!(error < 5e-3, "initial {initial_s}: error {error}");
        // Settled by 2 s: from then on within 5 % of the matched run's lead.
        for r in run
            .controller
            .iter()
            .filter(|r| r.t_s >= 2.0 && r.mode == command_mode::LAW)
        {
            assert!(
                (r.lead_s - matched).abs() < 0.05 * matched,
                "initial {initial_s}: lead {} at {} s vs {matched}",
                r.lead_s,
                r.t_s
            );
        }
    }
}

/// The limit cycle: the lead 100 us short, adaptation and guard off. The
/// emulator's stability monitor trips `loop-unstable`, the rig holds, and the specimen
/// moves less than 0.5 mm from where it was.
#[test]
fn a_lead_100_us_short_without_adaptation_or_guard_trips_loop_unstable_and_holds() {
    let mut cfg = default_hil_config().unwrap();
    cfg.compensation.initial_delay_s = 152e-6;
    cfg.compensation.adapt = false;
    cfg.compensation.passivity_guard = false;
    let run = run_in_process(&cfg, &script(4.0));
    let f = faults(&run);
    let trip = f
        .iter()
        .find(|(p, fault, _)| *p == process_id::EMULATOR && *fault == Fault::LoopUnstable)
        .unwrap_or_else(|| panic!("no loop-unstable: {f:?}"));
    // The rig held and ended at rest.
    let last = run.rig.last().unwrap();
    assert!(
        run.rig.iter().any(|r| r.state == rig_state::HOLD),
        "the rig never held"
    );
    assert!(last.t_s < 4.0 - 0.5, "the run did not end in the hold");
    // Excursion: every displacement from the start to the end within 0.5 mm of the
    // range before the instability grew (the preload's static position +- the load).
    let beyond = beyond_range_before(&run, trip.2 - 0.2);
    assert!(beyond < 0.5e-3, "excursion {} mm beyond", beyond * 1e3);
    // With the same lead, the guard alone keeps the loop stable and faithful.
    cfg.compensation.passivity_guard = true;
    let guarded = run_in_process(&cfg, &script(4.0));
    assert!(faults(&guarded).is_empty(), "{:?}", faults(&guarded));
    let error = displacement_error(&cfg, &guarded);
    assert!(error < 5e-3, "guarded: error {error}");
    assert!(guarded
        .controller
        .iter()
        .any(|r| r.guard_damping_ns_per_m > 0.0));
}

/// After a `loop-unstable` trip the report judges the lead at the trip against the leads
/// that hold the linearised loop in front of the rig's recorded actuator
/// (`check::after_trip`), at the preload and at the programme's loads. The limit
/// cycle (lead 100 us short, nothing adapting): the leads exist and hold 252 us, the lead
/// at the trip (152 us) is outside them. A `lag-delay` actuator of 738 + 552 us that
/// nothing declares, from the shipped guess: it trips, and the report says that no lead
/// holds it at every load of the programme (the leads at the preload alone, 1190-1350 us
/// by `hil --check`, do not hold the axles' 72 kN). Undeclared `slow-250kn`: it leaves the
/// displacement range, and its stable leads (from about 3.7 ms) lie far above the lead
/// at the trip.
#[test]
fn a_trips_report_says_whether_any_lead_would_have_held_the_loop() {
    use fastemu::hil::check::after_trip::{JudgedActuator, LeadVerdict};
    const DEFAULT: &str = include_str!("../../configs/hil-default.toml");
    let slow = DEFAULT
        .replace(
            "transport_delay_us = 50.0\n",
            "transport_delay_us = 738.8\n",
        )
        .replace("lag_us = 80.0\n", "lag_us = 551.8\n")
        .replace("plan_from_actuator = true", "plan_from_actuator = false");
    assert_ne!(slow, DEFAULT);
    let short = DEFAULT
        .replace("initial_delay_us = 252.0", "initial_delay_us = 152.0")
        .replace("adapt = true", "adapt = false")
        .replace("passivity_guard = true", "passivity_guard = false");
    let servo = DEFAULT
        .replace(
            "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0\n",
            "preset = \"slow-250kn\"\n",
        )
        .replace("plan_from_actuator = true", "plan_from_actuator = false");
    assert!(servo.contains("slow-250kn"));
    for (name, text) in [("short", short), ("slow", slow), ("servo", servo)] {
        let cfg = fastemu::hil::config::parse_hil_config(&text, "trip.toml", None).unwrap();
        let run = run_in_process(&cfg, &script(4.0));
        let dir = crate::common::TempDir::new(&format!("after-trip-{name}"));
        run.write_records(&dir.path, &cfg, &text).unwrap();
        let analysis = fastemu::hil::report::analyse_run(&cfg, &dir.path).unwrap();
        let trip = analysis
            .safety
            .faults
            .iter()
            .find(|f| f.leads_after_trip.is_some())
            .unwrap_or_else(|| panic!("{name}: nothing judged: {:?}", faults(&run)));
        let judged = trip.leads_after_trip.as_ref().expect("judged");
        assert_eq!(judged.judged, JudgedActuator::RecordedTruth, "{name}");
        // The lead at the trip is the last one the controller sent in force control.
        let last_law = law_commands(&run)
            .iter()
            .rev()
            .find(|r| r.t_s <= trip.detected_at_s)
            .map(|r| r.lead_s)
            .unwrap();
        assert!(
            (judged.lead_at_trip_us - last_law * 1e6).abs() < 1.0,
            "{name}: {} vs {}",
            judged.lead_at_trip_us,
            last_law * 1e6
        );
        match name {
            "short" => {
                assert_eq!(judged.verdict, LeadVerdict::LeadOutside, "{judged:?}");
                let (a, b) = judged.leads[0].at_every_load_us.unwrap();
                assert!(a > 152.0 && a <= 252.0 && b >= 252.0, "{a}-{b}");
            }
            // A servo-hydraulic force loop's stable leads lie above its load band's delay,
            // where neither the estimator nor the ring reader (below 27 Hz) takes it: it
            // leaves the displacement range at about 0.2 s, diverging at 20 Hz.
            "servo" => {
                assert_eq!(trip.fault, "displacement-out-of-range");
                assert_eq!(judged.verdict, LeadVerdict::LeadOutside, "{judged:?}");
                let (a, b) = judged.leads[0].at_every_load_us.unwrap();
                assert!((3500.0..4000.0).contains(&a) && b > 5000.0, "{a}-{b}");
                assert!(judged.lead_at_trip_us < a, "{judged:?}");
            }
            _ => {
                assert_eq!(trip.fault, "loop-unstable");
                assert!(
                    matches!(judged.verdict, LeadVerdict::NoLeadAtEveryLoad),
                    "{judged:?}"
                );
                let (a, b) = judged.leads[0].at_preload_us.unwrap();
                assert!(
                    (1100.0..1300.0).contains(&a) && (1300.0..1450.0).contains(&b),
                    "{a}-{b}"
                );
                assert!(
                    (judged.effective_delay_us - 1412.0).abs() < 10.0,
                    "{judged:?}"
                );
            }
        }
        // The other processes' faults (the controller's `emulator-tripped`, the rig's
        // `hold-requested`) are not judged again.
        assert_eq!(
            analysis
                .safety
                .faults
                .iter()
                .filter(|f| f.leads_after_trip.is_some())
                .count(),
            1,
            "{name}"
        );
    }
}

/// The run's law commands and how many of the first were sent with the guard armed (the
/// safe start).
fn safe_start(run: &InProcessRun) -> (Vec<&fastemu::hil::controller::ControllerRecord>, usize) {
    let law = law_commands(run);
    let start = law.iter().take_while(|r| r.guard_armed == 1).count();
    (law, start)
}

/// A passive loop gets no guard damping beyond the safe start: on the default run the
/// guard is armed from the first law command until the lead agrees with the identified
/// delay (the shipped guess is right: within 0.5 s), then never acts again.
#[test]
fn the_guard_adds_nothing_to_a_passive_loop() {
    let cfg = default_hil_config().unwrap();
    let run = run_in_process(&cfg, &script(4.0));
    let (law, start) = safe_start(&run);
    assert!(start > 0, "the guard did not arm");
    let end = law.get(start).expect("the guard was never disarmed").t_s;
    assert!(end < 0.5, "safe start until {end} s");
    assert!(
        law[start..]
            .iter()
            .all(|r| r.guard_armed == 0 && r.guard_damping_ns_per_m == 0.0),
        "the guard acted after the safe start"
    );
}

/// An emulator stall in an axle's passage (37 periods, 9 ms, at 2.35 and 2.4 s) rings the
/// specimen when the fresh law replaces the one the rig rode through on; the guard's
/// observer, restarted by the gap, reads that burst (more than four times its onset) and
/// excuses it: no damping is added after the safe start, and the run is as faithful as the
/// same run without the guard. No fault. (Until 2026-11-28 the guard answered it with 23
/// and 31 kN s/m, released over a second of axle passages.)
#[test]
fn an_emulator_stalls_burst_in_an_axles_passage_adds_no_damping() {
    for (at_s, periods) in [(2.35, 37), (2.4, 37)] {
        let run_with = |guard: bool| {
            let mut cfg = default_hil_config().unwrap();
            cfg.compensation.passivity_guard = guard;
            let mut s = script(3.5);
            s.emulator_stalls = vec![((at_s * RATE) as u64, periods)];
            let run = run_in_process(&cfg, &s);
            assert!(faults(&run).is_empty(), "{at_s} s: {:?}", faults(&run));
            (displacement_error(&cfg, &run), run)
        };
        let (error, run) = run_with(true);
        let (law, start) = safe_start(&run);
        let after: Vec<_> = law[start..].iter().filter(|r| r.t_s > at_s).collect();
        let burst = after
            .iter()
            .map(|r| r.guard_generated_j)
            .fold(0.0, f64::max);
        let onset = default_hil_config()
            .unwrap()
            .compensation
            .guard_onset_energy_j;
        assert!(burst > 4.0 * onset, "{at_s} s: the burst read {burst} J");
        assert!(
            law[start..].iter().all(|r| r.guard_damping_ns_per_m == 0.0),
            "{at_s} s: the guard damped the stall's burst"
        );
        // The guard's safe start makes the two runs differ from the start by a little:
        // 2 % of the error (an answered burst cost 65 % at 2.35 s: 0.076 % against 0.046 %).
        let (error_without, _) = run_with(false);
        assert!(
            (error - error_without).abs() < 0.02 * error_without,
            "{at_s} s: {error} with the guard, {error_without} without"
        );
    }
}

/// A loop only the guard keeps stable (the lead 100 us short, adaptation off: without the
/// guard, the limit cycle) stays stable under emulator stalls of 40 periods every
/// 0.3 s: each stall's burst is excused, and the energy the loop goes on generating after
/// it is answered. No fault, the guard damping all along, the error within 5 % of the same
/// run without the stalls.
#[test]
fn a_loop_the_guard_keeps_stable_stays_stable_under_emulator_stalls() {
    let run_with = |stalls: bool| {
        let mut cfg = default_hil_config().unwrap();
        cfg.compensation.initial_delay_s = 152e-6;
        cfg.compensation.adapt = false;
        let mut s = script(4.0);
        if stalls {
            s.emulator_stalls = (0..12)
                .map(|i| (((0.5 + 0.3 * f64::from(i)) * RATE) as u64, 40))
                .collect();
        }
        let run = run_in_process(&cfg, &s);
        assert!(
            faults(&run).is_empty(),
            "stalls {stalls}: {:?}",
            faults(&run)
        );
        (displacement_error(&cfg, &run), run)
    };
    let (calm, _) = run_with(false);
    let (stalled, run) = run_with(true);
    assert!(
        (stalled - calm).abs() < 0.05 * calm,
        "{stalled} with the stalls, {calm} without"
    );
    let law = law_commands(&run);
    let excused = law.iter().map(|r| r.guard_stall_bursts).max().unwrap_or(0);
    assert_eq!(excused, 12, "stall bursts excused");
    let after: Vec<_> = law.iter().filter(|r| r.t_s > 0.5).collect();
    let damped = after
        .iter()
        .filter(|r| r.guard_damping_ns_per_m > 0.0)
        .count();
    assert!(
        damped as f64 > 0.9 * after.len() as f64,
        "damped {damped} of {}",
        after.len()
    );
}

/// The safe start in front of an actuator slower than the guess: a guess of 0 before a
/// 722 us actuator (lag-delay 450 + 150 us) that nothing declares (an external rig's: with
/// the declaration the plan starts at a lead stable by itself, below). The loop starts
/// unstable at the resonance; before the safe start, the resonance rang up before the
/// guard's observer saw energy (0.32 % displacement error, a 20.7 um transient: not
/// clean). Armed from the first command until the lead is learned, the guard damps it from
/// the start.
#[test]
fn a_guess_of_zero_before_a_slow_actuator_is_made_safe_from_the_start() {
    let mut cfg = config_with_actuator(
        "kind = \"lag-delay\"\ntransport_delay_us = 450.0\nlag_us = 150.0\nforce_max_n = 150000.0",
        0.0,
        true,
        true,
    );
    cfg.compensation.plan_from_actuator = false;
    let run = run_in_process(&cfg, &script(4.0));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let (law, start) = safe_start(&run);
    assert!(
        start > 0 && start < law.len(),
        "safe start over {start} commands"
    );
    let truth = 0.5 / RATE + 450e-6 + 150e-6;
    let end = law[start];
    assert!(
        (end.lead_s / truth - 1.0).abs() < 0.12,
        "safe start ended at {} s with a lead of {} us",
        end.t_s,
        end.lead_s * 1e6
    );
    assert!(end.t_s < 1.5, "safe start until {} s", end.t_s);
    assert!(law[start..].iter().all(|r| r.guard_armed == 0));
    let error = displacement_error(&cfg, &run);
    assert!(error < 1e-3, "displacement error {:.3} %", 100.0 * error);
}

/// A guess far off before a declared actuator: 0 before `lag-delay` 500 + 500 us drawn by
/// `perturb = 0.3` seed 3 (truth 1137 us). The guess is stable for none of the actuators
/// the declaration allows, and the safe start's damping did not hold this one while the
/// lead was learned: `loop-unstable` at 0.08 s (`fastemu hil`; before 2026-11-28, twenty-seventh
/// session; seeds 4 and 6 alike). The plan now starts the run at the lead stable for all
/// of its draws nearest the guess, without the safe start's damping, and the adaptation
/// takes it on: no fault, no damping at all, the lead within 5 % of the truth, the run as
/// faithful as from the right guess.
#[test]
fn a_guess_far_off_before_a_declared_actuator_starts_where_the_declaration_is_stable() {
    let actuator = "kind = \"lag-delay\"\ntransport_delay_us = 500.0\nlag_us = 500.0\nforce_max_n = 150000.0\nperturb = 0.3\nperturb_seed = 3";
    let cfg = config_with_actuator(actuator, 0.0, true, true);
    let plan = fastemu::hil::check::compensation_plan(&cfg).expect("a plan");
    assert!(!plan.lead_fixed);
    assert_eq!(plan.start_moved_from_us, Some(0.0));
    assert_eq!(plan.lead_stable_for, plan.draws);
    let (lo, hi) = plan
        .scan
        .as_ref()
        .and_then(|s| s.common_us)
        .expect("leads stable for every draw");
    assert!((lo..=hi).contains(&plan.lead_us), "{} us", plan.lead_us);
    // Stable by itself at the start for the rig's truth and the declared actuator, on the
    // linearised loop.
    let plant = fastemu::rig::actuator::ActuatorPlant::from_config(&cfg.rig.actuator);
    let declared_nominal = {
        let mut c = cfg.clone();
        c.rig.actuator.perturb = 0.0;
        fastemu::rig::actuator::ActuatorPlant::from_config(&c.rig.actuator)
    };
    for p in [&plant, &declared_nominal] {
        assert!(
            fastemu::hil::check::LinearLoop::for_plant(&cfg, p, plan.lead_us * 1e-6, 1.0)
                .is_stable(0.0, 1.0),
            "{} us",
            plan.lead_us
        );
    }
    let run = run_in_process(&cfg, &script(6.0));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let law = law_commands(&run);
    assert!((law[0].lead_s * 1e6 - plan.lead_us).abs() < 1e-6);
    assert!(law.iter().all(|r| r.guard_damping_ns_per_m == 0.0));
    let truth = truth_delay_s(&cfg);
    assert!(
        (final_lead_s(&run) / truth - 1.0).abs() < 0.05,
        "{} us against {} us",
        final_lead_s(&run) * 1e6,
        truth * 1e6
    );
    let error = displacement_error(&cfg, &run);
    let right = config_with_actuator(actuator, truth * 1e6, true, true);
    let from_right = displacement_error(&right, &run_in_process(&right, &script(6.0)));
    assert!(
        error < 1.1 * from_right,
        "{:.4} % from 0, {:.4} % from the truth",
        100.0 * error,
        100.0 * from_right
    );
}

/// 0.81 ms actuator (lag-delay 554 + 135 us, the truth `perturb = 0.3` drew for seed 17
/// of 450 + 150 us). From a guess of 0 the resonance rings up faster than the safe start's
/// damping holds it: before the oscillation estimate, `loop-unstable` tripped at 0.106 s,
/// before the load band's estimator had warmed up. The ringing's own phase gives the lead:
/// it comes within 15 % of the truth while the ring is young, the safe start ends there
/// (its full damping at that lead would itself generate energy above 300 Hz), and the run
/// is faithful. Undeclared (an external rig's actuator): declared, the plan starts at a
/// lead stable by itself and nothing rings.
#[test]
fn a_loop_ringing_from_a_guess_of_zero_finds_its_lead_in_the_ringing() {
    let mut cfg = config_with_actuator(
        "kind = \"lag-delay\"\ntransport_delay_us = 554.0\nlag_us = 135.0\nforce_max_n = 150000.0",
        0.0,
        true,
        true,
    );
    cfg.compensation.plan_from_actuator = false;
    let run = run_in_process(&cfg, &script(3.0));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let truth = 0.5 / RATE + 554e-6 + 135e-6;
    let (law, _) = safe_start(&run);
    let reached = law
        .iter()
        .find(|r| (r.lead_s / truth - 1.0).abs() < 0.15)
        .unwrap_or_else(|| panic!("the lead never came within 15 % of {} us", truth * 1e6));
    assert!(
        reached.t_s < 0.1,
        "the lead came near the truth at {} s",
        reached.t_s
    );
    // It got there on the ringing: the guard's observer saw energy generated before.
    assert!(law
        .iter()
        .take_while(|r| r.t_s <= reached.t_s)
        .any(|r| r.guard_generated_j > cfg.compensation.guard_onset_energy_j));
    let (_, start) = safe_start(&run);
    assert!(
        law[start].t_s <= reached.t_s + 0.02,
        "the safe start ended at {} s",
        law[start].t_s
    );
    assert!((final_lead_s(&run) / truth - 1.0).abs() < 0.05);
    let error = displacement_error(&cfg, &run);
    assert!(error < 1e-3, "displacement error {:.3} %", 100.0 * error);
}

/// The guard's damping at a long lead (`compensation::DampingByLead`). An undeclared
/// `lag-delay` of 720 + 359 us (an actuator drawn at random; 1.2 ms with the hold) from
/// the shipped 252 us: the ring read at the start takes the lead to about 1.1 ms, inside
/// the loop's stable leads without damping (1000-1300 us by the linearised loop on this
/// actuator) but not with the guard's full damping (stable below 820 us with 40 kN s/m,
/// below 1060 us with 20). Uncapped, the guard answered the start's dying ring with 18-40
/// kN s/m there and `loop-unstable` tripped at 0.06 s. Now every damping the guard adds
/// after the safe start is one with which this actuator's linearised loop at that
/// command's lead is stable (judged here on the actuator itself, which the cap never saw),
/// and the run ends without a fault within 1 %.
#[test]
fn the_guards_damping_at_a_long_lead_is_one_the_loop_stays_stable_with() {
    use fastemu::hil::check::LinearLoop;
    let mut cfg = config_with_actuator(
        "kind = \"lag-delay\"\ntransport_delay_us = 720.0\nlag_us = 359.0\nforce_max_n = 150000.0",
        252.0,
        true,
        true,
    );
    cfg.compensation.plan_from_actuator = false;
    let run = run_in_process(&cfg, &script(3.0));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let plant = fastemu::rig::actuator::ActuatorPlant::from_config(&cfg.rig.actuator);
    let (law, start) = safe_start(&run);
    assert!(law[start].lead_s > 1e-3, "{}", law[start].lead_s);
    // One command in every 41 (10 ms) that added damping after the safe start.
    let damped: Vec<_> = law[start..]
        .iter()
        .step_by(41)
        .filter(|r| r.guard_damping_ns_per_m > 0.0)
        .collect();
    assert!(damped.len() >= 5, "{}", damped.len());
    for r in damped {
        let mut l = LinearLoop::for_plant(&cfg, &plant, r.lead_s, 1.0);
        l.guard_damping_ns_per_m = r.guard_damping_ns_per_m;
        assert!(
            l.is_stable(0.0, 1.0),
            "{} N s/m at {} us, {} s",
            r.guard_damping_ns_per_m,
            r.lead_s * 1e6,
            r.t_s
        );
    }
    let error = displacement_error(&cfg, &run);
    assert!(error < 1e-2, "displacement error {:.3} %", 100.0 * error);
}

/// A servo-hydraulic force loop the launcher makes no plan for (an external rig's actuator
/// is not declared: here `fatigue-150kn` with `plan_from_actuator = false`), from the
/// shipped guess of 252 us: the loop rings at 30-40 Hz at once (its stable leads are
/// 2220-3360 us) and tripped `loop-unstable` within 0.1 s before the lead was read from
/// the ringing. Now the ringing's phase takes the lead past 1.5 ms within 0.15 s, the
/// load band's estimator (which reads the 1-5 Hz delay, under 1 ms) may not lower it, and
/// the run is stable to its end. It is not faithful (a lead cannot make up a delay that
/// varies with frequency): more than 1 % error, not clean.
#[test]
fn an_undeclared_servo_hydraulic_loop_takes_its_lead_from_the_ringing_and_stays_stable() {
    let mut cfg = config_with_actuator("preset = \"fatigue-150kn\"", 252.0, true, true);
    cfg.compensation.plan_from_actuator = false;
    let run = run_in_process(&cfg, &script(6.0));
    assert!(run.plan.is_none() || !run.plan.as_ref().unwrap().lead_fixed);
    // Stable: what the passage left dies away, and nothing grows at the end (measured: 287
    // um before 4 s, 1.8 um in the last second; with the load band free to lower the lead
    // by 15 %, 41 um there, a 35 Hz ring growing).
    let error = ran_to_the_end_and_settled(&cfg, &run, "fatigue-150kn, no plan");
    let law = law_commands(&run);
    let early = law.iter().take_while(|r| r.t_s < 0.15).last().unwrap();
    assert!(
        early.lead_s > 1.5e-3,
        "lead {} us at {} s",
        early.lead_s * 1e6,
        early.t_s
    );
    let lowest = law
        .iter()
        .filter(|r| r.t_s >= 0.15)
        .map(|r| r.lead_s)
        .fold(f64::INFINITY, f64::min);
    assert!(
        lowest >= early.lead_s - 1e-9,
        "lead down to {} us from {} us",
        lowest * 1e6,
        early.lead_s * 1e6
    );
    assert!(error > 0.01, "displacement error {:.2} %", 100.0 * error);
}

/// The same undeclared `fatigue-150kn` from a guess above its stable leads (3500 us, a
/// third above its 2626 us effective delay; stable leads 2220-3360 us by `hil --check`):
/// the loop rings near 240 Hz, where the prediction over the lead amplifies (`w L` about 5),
/// and the phase read there is the servo-valve's, longer than the lead. Taken, it moved
/// the lead up to 4.2 ms and the run tripped within 0.1 s (a new user's trial, 2026-11-29);
/// such a ring now moves the lead down by a quarter, and the run is stable to its end
/// with its last lead inside the stable leads. Not faithful, as from 252 us. (From 3900 us
/// it tripped too with this rule alone; with the ring's follow-up, 2026-11-29, it runs to
/// its end on 2194 us, 3.3 %, in process.)
#[test]
fn a_ring_of_a_lead_too_long_moves_the_lead_down() {
    let mut cfg = config_with_actuator("preset = \"fatigue-150kn\"", 3500.0, true, true);
    cfg.compensation.plan_from_actuator = false;
    let run = run_in_process(&cfg, &script(6.0));
    let law = law_commands(&run);
    let first = law.first().unwrap().lead_s;
    assert!(
        (first - 3500e-6).abs() < 1e-9,
        "started at {} us",
        first * 1e6
    );
    let highest = law.iter().map(|r| r.lead_s).fold(0.0, f64::max);
    assert!(
        highest <= first + 1e-9,
        "lead up to {} us from {} us",
        highest * 1e6,
        first * 1e6
    );
    let error = ran_to_the_end_and_settled(&cfg, &run, "fatigue-150kn from 3500 us");
    let last = law.last().unwrap().lead_s;
    assert!(
        (2220e-6..=3360e-6).contains(&last),
        "last lead {} us",
        last * 1e6
    );
    assert!(error > 0.01, "displacement error {:.2} %", 100.0 * error);
}

/// An undeclared `rths-fast-150kn` (`perturb = 0.3`, seed 5; stable leads 1750-2660 us by
/// `hil --check`) from 0: its 48 Hz ring read 1399 us, the phase there, and the safe
/// start ended at that lead, where the guard can add no damping; nothing read the ring
/// again and it grew until `loop-unstable` at 0.18 s. A ring that grows on within 0.25 s
/// of the arrival now steps the lead up by a quarter: the run is stable to its end with
/// its last lead inside the stable leads. Not faithful (a servo-hydraulic loop's delay
/// varies with frequency).
#[test]
fn a_ring_that_grows_on_under_the_rings_lead_steps_the_lead_up() {
    let mut cfg = config_with_actuator(
        "preset = \"rths-fast-150kn\"\nperturb = 0.3\nperturb_seed = 5",
        0.0,
        true,
        true,
    );
    cfg.compensation.plan_from_actuator = false;
    let run = run_in_process(&cfg, &script(6.0));
    let law = law_commands(&run);
    // The ring's lead, where the safe start ended, then at least one step up within 0.25 s.
    let ended = law
        .iter()
        .find(|r| r.guard_armed == 0)
        .expect("the safe start ended");
    assert!(
        ended.t_s < 0.1 && (1000e-6..1750e-6).contains(&ended.lead_s),
        "safe start ended at {} s, lead {} us",
        ended.t_s,
        ended.lead_s * 1e6
    );
    let error = ran_to_the_end_and_settled(&cfg, &run, "rths-fast-150kn seed 5 from 0");
    let stepped = law
        .iter()
        .filter(|r| r.t_s <= ended.t_s + 0.3)
        .map(|r| r.lead_s)
        .fold(0.0, f64::max);
    assert!(
        stepped >= 1.2 * ended.lead_s,
        "lead up to {} us from {} us",
        stepped * 1e6,
        ended.lead_s * 1e6
    );
    let last = law.last().unwrap().lead_s;
    assert!(
        (1750e-6..=2660e-6).contains(&last),
        "last lead {} us",
        last * 1e6
    );
    assert!(error > 0.01, "displacement error {:.2} %", 100.0 * error);
}

/// An undeclared `fatigue-150kn` (`perturb = 0.3`, seed 5; effective delay 1.7 ms) from
/// a guess of 5250 us, about twice the preset's: the lead rings at 200-250 Hz, where `w L`
/// says it is too long, and the ring steps it down by a quarter. That step took 13 ms at
/// the ring's rate (0.1 s of lead per s), the ring grew meanwhile, and the run tripped
/// `loop-unstable` at 0.20 s. A step down is now taken at 1 s per s (244 us a sample):
/// within 3 ms, and the run is stable to its end on a lead at most 0.6 of the guess.
#[test]
fn a_lead_too_long_is_left_within_milliseconds() {
    let mut cfg = config_with_actuator(
        "preset = \"fatigue-150kn\"\nperturb = 0.3\nperturb_seed = 5",
        5250.0,
        true,
        true,
    );
    cfg.compensation.plan_from_actuator = false;
    let run = run_in_process(&cfg, &script(6.0));
    let law = law_commands(&run);
    let guess = law[0].lead_s;
    assert!(
        (guess - 5250e-6).abs() < 1e-9,
        "started at {} us",
        guess * 1e6
    );
    let left = law
        .iter()
        .find(|r| r.lead_s < guess - 1e-9)
        .expect("the lead left the guess");
    let down = law
        .iter()
        .find(|r| r.lead_s <= 0.75 * guess + 1e-9)
        .expect("the lead stepped down a quarter");
    assert!(
        left.t_s < 0.05 && down.t_s - left.t_s < 0.003,
        "left {} us at {} s, a quarter down at {} s",
        guess * 1e6,
        left.t_s,
        down.t_s
    );
    ran_to_the_end_and_settled(&cfg, &run, "fatigue-150kn seed 5 from 5250 us");
    let last = law.last().unwrap().lead_s;
    assert!(last <= 0.6 * guess, "last lead {} us", last * 1e6);
}

/// Same configuration, same input: the compensation (estimate, guard, the load band's
/// delay) is bit-identical.
#[test]
fn compensation_is_deterministic() {
    let mut cfg = default_hil_config().unwrap();
    cfg.compensation.initial_delay_s = 0.0;
    // Undeclared, so the run starts at the guess and the safe start's damping acts (a
    // declared actuator's plan would start where its loop is stable, without damping).
    cfg.compensation.plan_from_actuator = false;
    // 4 s: the load band's delay is identified from 3 s of force control on.
    let a = run_in_process(&cfg, &script(4.0));
    let b = run_in_process(&cfg, &script(4.0));
    assert!(a.controller.last().unwrap().load_band_delay_s.is_finite());
    assert_eq!(a.controller.len(), b.controller.len());
    for (x, y) in a.controller.iter().zip(&b.controller) {
        assert_eq!(x.lead_s.to_bits(), y.lead_s.to_bits());
        assert_eq!(x.actuator_gain.to_bits(), y.actuator_gain.to_bits());
        assert_eq!(
            x.guard_damping_ns_per_m.to_bits(),
            y.guard_damping_ns_per_m.to_bits()
        );
        assert_eq!(x.load_band_delay_s.to_bits(), y.load_band_delay_s.to_bits());
    }
    assert!(a.controller.iter().any(|r| r.guard_damping_ns_per_m > 0.0));
}

/// The default configuration's text with `[rig.actuator]` replaced by `actuator` (TOML
/// lines) and `[compensation]`'s three switches set.
fn config_with_actuator(
    actuator: &str,
    initial_delay_us: f64,
    adapt: bool,
    guard: bool,
) -> HilConfig {
    let text = include_str!("../../configs/hil-default.toml")
        .replace(
            "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0",
            actuator,
        )
        .replace(
            "initial_delay_us = 252.0",
            &format!("initial_delay_us = {initial_delay_us:.1}"),
        )
        .replace("adapt = true", &format!("adapt = {adapt}"))
        .replace("passivity_guard = true", &format!("passivity_guard = {guard}"));
    let cfg = fastemu::hil::config::parse_hil_config(&text, "actuator.toml", None).unwrap();
    assert_eq!(cfg.compensation.adapt, adapt);
    assert_eq!(cfg.compensation.passivity_guard, guard);
    cfg
}

/// A servo-hydraulic actuator (a perturbed preset) in front of a loop left without any
/// compensation goes unstable; after `loop-unstable` the rig's hold (stroke control, as
/// the actuator's own controller holds) keeps the specimen where it tripped: bounded
/// excursion, then at rest at the hold position under the load, to the end of the hold.
#[test]
fn a_servo_hydraulic_actuator_holds_in_stroke_control_after_loop_unstable() {
    let cfg = config_with_actuator(
        "preset = \"fatigue-150kn\"\nperturb = 0.3\nperturb_seed = 1",
        0.0,
        false,
        false,
    );
    let run = run_in_process(&cfg, &script(4.0));
    let f = faults(&run);
    let trip_t = f
        .iter()
        .find(|(p, fault, _)| *p == process_id::EMULATOR && *fault == Fault::LoopUnstable)
        .unwrap_or_else(|| panic!("no loop-unstable: {f:?}"))
        .2;
    let held: Vec<_> = run
        .rig
        .iter()
        .filter(|r| r.state == rig_state::HOLD)
        .collect();
    assert!(!held.is_empty(), "the rig never held");
    let hold_start = held[0].t_s;
    assert!(
        hold_start - trip_t < 0.05,
        "hold {hold_start} s, trip {trip_t} s"
    );
    let last = run.rig.last().unwrap();
    assert!(last.t_s < 4.0 - 0.5, "the run did not end in the hold");
    // From the hold on, the specimen stays within 0.5 mm of where it was then, and ends
    // at rest: the last 0.2 s within 5 um, under the load the actuator carries.
    let x_hold = held[0].x_m;
    let excursion = held
        .iter()
        .map(|r| (r.x_m - x_hold).abs())
        .fold(0.0f64, f64::max);
    assert!(excursion < 0.5e-3, "excursion {} mm", excursion * 1e3);
    let tail: Vec<_> = held.iter().filter(|r| r.t_s > last.t_s - 0.2).collect();
    let (lo, hi) = tail
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), r| {
            (a.min(r.x_m), b.max(r.x_m))
        });
    assert!(hi - lo < 5e-6, "not at rest: {} um", (hi - lo) * 1e6);
    let r = tail.last().unwrap();
    assert!(
        (r.actuator_force_n - r.external_force_n).abs() < 0.01 * r.external_force_n.abs(),
        "actuator {} N against load {} N",
        r.actuator_force_n,
        r.external_force_n
    );
}

/// The servo-hydraulic actuator's switches into stroke control (an operator hold) and
/// back (the resume) are bumpless: under a constant load, commanded the same force, the
/// actuator's force stays within 0.5 % of the load and the specimen within 2 um of where
/// it was, through force control, the hold and the blend back.
#[test]
fn a_servo_hydraulic_hold_and_resume_switch_control_without_a_bump() {
    use fastemu::ipc::messages::{command_mode, ActuatorCommand, Compensation, LocalLaw};
    use fastemu::rig::{RigPhysics, Servo};
    let cfg = config_with_actuator("preset = \"fatigue-150kn\"", 2500.0, false, false);
    let servo_cfg = cfg.servo_config();
    assert!(servo_cfg.stroke_hold);
    let load = 2.0e4;
    let x0 = 4.0e-4;
    let mut servo = Servo::new(servo_cfg, x0, load);
    let mut physics = RigPhysics::new(&cfg.rig, x0, load);
    let command = ActuatorCommand {
        sequence: 0,
        setpoint_sequence: 0,
        sample_sequence: 0,
        sample_publish_time_ns: 0,
        law: LocalLaw::constant(load),
        force_min_n: -5e3,
        force_max_n: 1.2e5,
        mode: command_mode::FORCE,
        controller_state: 1,
        fault_code: 0,
        reserved: 0,
        compensation: Compensation::NONE,
    };
    let dt = cfg.loop_.dt_s();
    let (hold_at, resume_at, end) = (4096u64, 2 * 4096, 3 * 4096);
    let (mut stroke_periods, mut worst_force, mut worst_x) = (0, 0.0f64, 0.0f64);
    for k in 0..end {
        if k == hold_at {
            servo.operator_hold(k);
        }
        if k == resume_at {
            servo.operator_resume(k);
        }
        // The controller goes on commanding through an operator hold.
        servo.on_command(&command, k);
        let (out, _) = servo.update(k, physics.x_m, load, physics.actuator_force_n);
        stroke_periods += usize::from(out.stroke_target_m.is_finite());
        physics.advance(
            k as f64 * dt,
            dt,
            out.command_n,
            out.stroke_target_m,
            load,
            load,
        );
        worst_force = worst_force.max((physics.actuator_force_n - load).abs());
        worst_x = worst_x.max((physics.x_m - x0).abs());
    }
    assert_eq!(stroke_periods as u64, resume_at - hold_at);
    assert!(worst_force < 0.005 * load, "force off by {worst_force} N");
    assert!(worst_x < 2e-6, "moved {} um", worst_x * 1e6);
}

/// The delay the lead's estimator identifies (the regression the lead follows) is the
/// actuator's effective delay as the rig's truth has it (its dynamics and transport over 1-20 Hz on the element, plus half a
/// period of zero-order hold), within 25 %, for the shipped lag-delay actuator and for the
/// electrodynamic shaker nominal and perturbed (the mass-like force its back-EMF puts in
/// the measured force once biased the estimate 40 % high through the force's curvature).
#[test]
fn the_identified_delay_is_the_actuators_effective_delay() {
    let cases = [
        ("kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0".to_string(), "lag-delay"),
        ("preset = \"shaker-150kn\"".to_string(), "shaker nominal"),
        ("preset = \"shaker-150kn\"\nperturb = 0.3\nperturb_seed = 3".to_string(), "shaker perturbed"),
    ];
    for (actuator, name) in cases {
        let cfg = config_with_actuator(&actuator, 252.0, true, true);
        // As in a process run on this machine: now and then the emulator misses a cycle
        // and takes two samples in the next (every 0.2 s here).
        let mut irregular = script(6.0);
        irregular.emulator_stalls = (1..20).map(|i| (i * 819, 1)).collect();
        let run = run_in_process(&cfg, &irregular);
        assert!(faults(&run).is_empty(), "{name}: {:?}", faults(&run));
        let truth_s = truth_delay_s(&cfg);
        let identified_s = run
            .controller
            .iter()
            .rev()
            .find(|r| r.identified_delay_s.is_finite())
            .map(|r| r.identified_delay_s)
            .expect("a delay was identified");
        eprintln!(
            "{name}: identified {:.1} us, truth {:.1} us",
            identified_s * 1e6,
            truth_s * 1e6
        );
        assert!(
            (identified_s - truth_s).abs() < 0.25 * truth_s,
            "{name}: identified {:.1} us, truth {:.1} us",
            identified_s * 1e6,
            truth_s * 1e6
        );
    }
}

/// A servo-hydraulic force loop's delay varies over the load band (`fatigue-150kn`: 0.7 ms
/// at 1 Hz, 3.3 ms at 20 Hz). The controller identifies it online as the truth defines it
/// (`LoadBandDelay`: each excited bin's phase delay of 1-20 Hz, the lead taken out, and their
/// mean), and the report's identified delay is that, within 25 % of the truth, for the
/// servo-hydraulic presets, a shaker and the shipped actuator alike; so is the record's
/// delay, read after the run from the emulator's records. The lead's own estimator, weighing
/// the band by the load's content, reads less than half of a servo loop's truth (measured:
/// identified 2656, 2487, 4242, 259 and 265 us against 2709, 2520, 4466, 248 and 252).
#[test]
fn the_identified_delay_is_the_truths_effective_delay_over_the_load_band() {
    for (actuator, planned) in [
        ("preset = \"fatigue-150kn\"\nperturb = 0.3\nperturb_seed = 3", true),
        ("preset = \"rths-fast-150kn\"\nperturb = 0.3\nperturb_seed = 2", true),
        ("preset = \"slow-250kn\"", true),
        ("preset = \"shaker-150kn\"", false),
        ("kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0", false),
    ] {
        let cfg = config_with_actuator(actuator, 252.0, true, true);
        let cell = fastemu::bench::compensation::fidelity_cell(&cfg, actuator, 6.0);
        assert_eq!(cell.fault, None, "{actuator}");
        assert_eq!(cell.planned_lead_us.is_some(), planned, "{actuator}");
        // The truth, independently: the plant's own response on the element.
        let truth_us = truth_delay_s(&cfg) * 1e6;
        let identified = cell.identified_delay_us.expect("an identified delay");
        assert_eq!(cell.identified_from, Some("load-band"), "{actuator}");
        let record = cell.record_delay_us.expect("a record delay");
        for (what, value) in [("identified", identified), ("record's", record)] {
            assert!(
                (value / truth_us - 1.0).abs() < 0.25,
                "{actuator}: the {what} {value:.0} us against the truth's {truth_us:.0} us"
            );
        }
        let lead_estimate = cell.lead_estimate_us.unwrap();
        if planned {
            assert!(
                lead_estimate < 0.5 * truth_us,
                "{actuator}: the lead's estimator {lead_estimate:.0} us"
            );
        }
    }
}

/// A perturbed electrodynamic shaker renders 0.74 of its command (seed 2: force constant
/// 222 N/A against 300). The simulated rig reports the force it commanded (rig ABI 4), so
/// the controller reads the gain from the rig's own equilibrium before its first command
/// and the specimen does not sink under a gain error: from the command answering the
/// second sample on (the first two samples agree: the actuator settled under the rig's
/// servo), every law command divides by the actuator's static gain (the plant's response on
/// the element at 0.5 Hz, an independent calculation, within 1 %), no fault, and the run
/// stays within 1 %. (Read
/// from the element's force once the specimen moved, the gain came out 0.817 and this run
/// ended 2.1 % off.)
#[test]
fn a_perturbed_shakers_gain_is_read_from_the_rigs_own_command() {
    let cfg = config_with_actuator(
        "preset = \"shaker-150kn\"\nperturb = 0.3\nperturb_seed = 2",
        252.0,
        true,
        true,
    );
    let run = run_in_process(&cfg, &script(6.0));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let k = cfg
        .model
        .element
        .high_frequency_stiffness_n_per_m(cfg.scenario.preload_n);
    let plant = fastemu::rig::actuator::ActuatorPlant::from_config(&cfg.rig.actuator);
    let static_gain = plant
        .response_on_element(2.0 * std::f64::consts::PI * 0.5, k)
        .norm();
    assert!((0.6..0.85).contains(&static_gain), "{static_gain}");
    let first = run
        .controller
        .iter()
        .find(|r| r.mode == command_mode::LAW && r.sample_seq >= 1)
        .expect("a law command");
    assert_eq!(first.sample_seq, 1, "the second sample was answered");
    assert!(
        (first.actuator_gain / static_gain - 1.0).abs() < 0.01,
        "the gain sent {} against the actuator's {static_gain}",
        first.actuator_gain
    );
    let error = displacement_error(&cfg, &run);
    assert!(error < 0.01, "displacement error {:.2} %", 100.0 * error);
}

/// An actuator of 722 us effective delay (lag-delay 450 + 150 us) started from a guess
/// twice that: the linearised loop is stable with 600-1320 us only, and the lead of the
/// guess itself diverged within 20 ms (`loop-unstable` before the estimator had seen
/// anything). The starting lead is capped for an actuator twice as fast as the guess
/// (`check::starting_lead_cap_s`), so the run starts inside the stable range, learns the
/// delay (the truth's effective delay within 5 %) and stays faithful, without a fault.
#[test]
fn a_guess_twice_a_slow_actuators_delay_starts_capped_and_is_learned() {
    let (cfg, run) = unfaulted_lag_delay_run(450.0, 150.0, 1444.0, 4.0);
    let first = run
        .controller
        .iter()
        .find(|r| r.mode == command_mode::LAW)
        .expect("a law command");
    // Inside the truth's stable leads (600-1320 us, `hil --check`), at most the guess.
    assert!(
        first.lead_s >= 600e-6 && first.lead_s < 1320e-6,
        "started at {} us",
        first.lead_s * 1e6
    );
    assert_learned_and_faithful(&cfg, &run, 0.5 / RATE + 450e-6 + 150e-6, 0.05);
}

/// The shipped configuration with a `lag-delay` actuator of `transport_us + lag_us` and the
/// starting guess `guess_us`, run in-process for `seconds`; asserts it ran without a fault.
fn unfaulted_lag_delay_run(
    transport_us: f64,
    lag_us: f64,
    guess_us: f64,
    seconds: f64,
) -> (HilConfig, InProcessRun) {
    let cfg = config_with_actuator(
        &format!(
            "kind = \"lag-delay\"\ntransport_delay_us = {transport_us:.1}\nlag_us = {lag_us:.1}\nforce_max_n = 150000.0"
        ),
        guess_us,
        true,
        true,
    );
    let run = run_in_process(&cfg, &script(seconds));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    assert_started_at_the_guess(&run);
    (cfg, run)
}

/// The run started where its guess put it (the plan did not move the start), so what a
/// test says of the start holds of the guess.
fn assert_started_at_the_guess(run: &InProcessRun) {
    assert!(
        run.plan
            .as_ref()
            .is_none_or(|p| p.start_moved_from_us.is_none()),
        "the plan moved the start: {:?}",
        run.plan
    );
}

/// The run's final lead within `tolerance` (relative) of the effective delay `truth_s`,
/// and its displacement error under 0.5 %.
fn assert_learned_and_faithful(cfg: &HilConfig, run: &InProcessRun, truth_s: f64, tolerance: f64) {
    let lead = final_lead_s(run);
    assert!(
        (lead / truth_s - 1.0).abs() < tolerance,
        "final lead {} us against {} us",
        lead * 1e6,
        truth_s * 1e6
    );
    let error = displacement_error(cfg, run);
    assert!(error < 0.005, "displacement error {:.3} %", 100.0 * error);
}

/// A transport delay of 500 us and a lag of 80 us (702 us of effective delay) from a guess
/// of 1160 us, capped to a starting lead of 742 us (`hil --check`: stable with 580-1280
/// us). Under the safe start's full damping the guard's band held almost nothing (0.4-0.5
/// mJ generated, most likely the sensor's noise through the damping), the observer saw its
/// onset energy (0.5 mJ), and the ring estimate read a phase delay of 1.85 ms there (fit
/// 0.99 at 70-100 Hz): the lead
/// went to 1.5 ms within 8 ms and the loop tripped `loop-unstable` at 0.18 s (2026-11-28).
/// A ring now moves the lead only beyond four times the onset: the lead stays inside the
/// stable range, is learned, and the run is faithful, without a fault.
#[test]
fn noise_under_the_safe_starts_damping_is_no_ring_to_take_a_lead_from() {
    let (cfg, run) = unfaulted_lag_delay_run(500.0, 80.0, 1160.0, 3.0);
    let highest = run
        .controller
        .iter()
        .filter(|r| r.mode == command_mode::LAW)
        .map(|r| r.lead_s)
        .fold(0.0, f64::max);
    assert!(highest < 1280e-6, "the lead went to {} us", highest * 1e6);
    assert_learned_and_faithful(&cfg, &run, 0.5 / RATE + 500e-6 + 80e-6, 0.1);
}

/// Emulator stalls of 1-8 periods, every 4-16 ms from 50 ms on (xorshift `seed`): the
/// controller bridges each gap for the guard, and `(first period, length)` per stall.
fn frequent_stalls(seed: u64, until: u64) -> Vec<(u64, u64)> {
    let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    };
    let mut stalls = Vec::new();
    let mut k = 200u64;
    while k < until {
        let len = 1 + next() % 8;
        stalls.push((k, len));
        k += len + 15 + next() % 50;
    }
    stalls
}

/// `seconds` of the in-process loop with `frequent_stalls(seed)` of the emulator through
/// all but its last 0.1 s; asserts it ran without a fault.
fn run_unfaulted_under_frequent_stalls(cfg: &HilConfig, seed: u64, seconds: f64) -> InProcessRun {
    let run = run_in_process(
        cfg,
        &InProcessScript {
            emulator_stalls: frequent_stalls(seed, ((seconds - 0.1) * RATE) as u64),
            ..script(seconds)
        },
    );
    assert!(faults(&run).is_empty(), "seed {seed}: {:?}", faults(&run));
    run
}

/// Bridged stretches are not evidence of a delay. Under emulator stalls of 1-8 periods
/// every 4-16 ms (a loaded machine; a UDP-link run in CI met the like), the straight lines
/// the controller bridges them with read, in the preload's near-static stretch, as a delay
/// of several ms with a small standard error: the lead walked from 252 to 1980 us and the
/// loop diverged into `displacement-out-of-range` (seed 2). With the estimator's standard
/// error counted honestly the lead does not follow them: no fault, the lead within a
/// factor 1.5 of the guess (which is right here), the error within 0.5 %. With the same
/// stalls only every 0.3 s it learns the delay between them.
#[test]
fn stalls_bridged_by_the_controller_are_not_read_as_a_delay() {
    let cfg = default_hil_config().unwrap();
    let guess = cfg.compensation.initial_delay_s;
    for seed in [2, 3, 12] {
        let run = run_unfaulted_under_frequent_stalls(&cfg, seed, 3.0);
        let leads: Vec<f64> = run
            .controller
            .iter()
            .filter(|r| r.mode == command_mode::LAW && r.repeat == 0)
            .map(|r| r.lead_s)
            .collect();
        let (lo, hi) = leads
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(a, b), &l| (a.min(l), b.max(l)));
        assert!(
            lo > 0.5 * guess && hi < 1.5 * guess,
            "seed {seed}: the lead went {:.0}-{:.0} us from the {:.0} us guess",
            lo * 1e6,
            hi * 1e6,
            guess * 1e6
        );
        let e = displacement_error(&cfg, &run);
        assert!(e < 0.005, "seed {seed}: displacement error {e}");
    }
    // The same stalls every 0.3 s leave room to learn: from a guess of 0 the lead reaches
    // the 252 us a run without stalls learns.
    let mut cfg0 = cfg.clone();
    cfg0.compensation.initial_delay_s = 0.0;
    // From the guess itself: undeclared (the plan would start where the loop is stable).
    cfg0.compensation.plan_from_actuator = false;
    let sparse: Vec<(u64, u64)> = frequent_stalls(2, 24_000).into_iter().step_by(25).collect();
    assert!(sparse.len() > 10 && sparse.iter().any(|s| s.1 > 2));
    let run = run_in_process(
        &cfg0,
        &InProcessScript {
            emulator_stalls: sparse,
            ..script(6.0)
        },
    );
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let lead = final_lead_s(&run);
    assert!(
        (lead - 252e-6).abs() < 30e-6,
        "the lead ended at {:.0} us",
        lead * 1e6
    );
}

/// A run that went to its end (`duration_s`) without a fault and without the rig ever
/// holding; returns the largest displacement error against the offline reference before
/// 4 s (the passage) and in the last second, m, and the relative RMS error.
/// The run's law commands (force control), in order.
fn law_commands(run: &InProcessRun) -> Vec<&ControllerRecord> {
    run.controller
        .iter()
        .filter(|r| r.mode == command_mode::LAW)
        .collect()
}

/// `ran_to_the_end_unheld`, and what the passage left died away: the largest error
/// against the reference in the last second under a tenth of the largest during the
/// passage. The displacement error.
fn ran_to_the_end_and_settled(cfg: &HilConfig, run: &InProcessRun, label: &str) -> f64 {
    let (during, after, error) = ran_to_the_end_unheld(cfg, run, label);
    assert!(
        after < 0.1 * during,
        "{label}: {} um after the passage, {} um during it",
        after * 1e6,
        during * 1e6
    );
    error
}

fn ran_to_the_end_unheld(cfg: &HilConfig, run: &InProcessRun, label: &str) -> (f64, f64, f64) {
    assert_eq!(run.rig.len(), 6 * RATE as usize, "{label}");
    assert!(faults(run).is_empty(), "{label}: {:?}", faults(run));
    assert!(
        run.rig.iter().all(|r| r.state != rig_state::HOLD),
        "{label}: the rig held"
    );
    let reference = reference_displacement_m(cfg, run.rig.len());
    let worst = |from: f64, to: f64| {
        run.rig
            .iter()
            .filter(|r| r.t_s >= from && r.t_s < to)
            .map(|r| (r.x_m - reference[r.step_idx as usize]).abs())
            .fold(0.0f64, f64::max)
    };
    (
        worst(0.0, 4.0),
        worst(5.0, 6.0),
        displacement_error(cfg, run),
    )
}

/// A servo controller without (or with half) the velocity compensation of the presets, as
/// a lab's force loop may be tuned (the external servo-hydraulic rig): the piston's
/// velocity reaches the oil column and the actuator damps the specimen, its rendered force
/// leading the element's by milliseconds in the load band. From the shipped guess, with
/// adaptation and guard as shipped, the run stays stable: no fault, the rig never holds,
/// and the specimen's error against the offline reference dies away once the passage is
/// over. It is not faithful (more than 1.5 % of displacement error), so its report cannot
/// call it clean. (Measured: 4.7, 8.6, 12.6 and 2.8 %.)
#[test]
fn a_servo_hydraulic_force_loop_without_velocity_compensation_stays_stable_and_is_not_clean() {
    let cases = [
        "preset = \"fatigue-150kn\"\nvelocity_compensation = 0.0",
        "preset = \"fatigue-150kn\"\nvelocity_compensation = 0.0\nforce_loop_bandwidth_hz = 20.0",
        "preset = \"slow-250kn\"\nvelocity_compensation = 0.0\nperturb = 0.3\nperturb_seed = 4",
        "preset = \"rths-fast-150kn\"\nvelocity_compensation = 0.5\nperturb = 0.3\nperturb_seed = 3",
    ];
    for actuator in cases {
        let cfg = config_with_actuator(actuator, 252.0, true, true);
        let run = run_in_process(&cfg, &script(6.0));
        let (during, after, error) = ran_to_the_end_unheld(&cfg, &run, actuator);
        assert!(
            after < 0.2 * during,
            "{actuator}: error {:.1} um in the last second, {:.1} um before 4 s",
            after * 1e6,
            during * 1e6
        );
        assert!(error > 0.015, "{actuator}: {:.3} %", error * 100.0);
    }
}

/// A servo loop that is unstable by itself (`rths-fast-150kn` without velocity
/// compensation, perturbed seed 5: its force loop, tuned on the nominal oil column, has a
/// pair of right-half-plane poles on the truth's stiffer one): the linearised loop on that
/// truth counts the actuator's own poles and finds no stable lead (counted as before, as if
/// the actuator were stable, it found every lead stable), and the time domain agrees: at
/// leads 0, 252 and 800 us, without adaptation or guard, the loop oscillates near 480 Hz,
/// grows, and trips `loop-unstable` within a second.
#[test]
fn an_actuator_unstable_by_itself_is_unstable_at_every_lead_in_the_check_and_in_time() {
    let actuator =
        "preset = \"rths-fast-150kn\"\nvelocity_compensation = 0.0\nperturb = 0.3\nperturb_seed = 5";
    let cfg = config_with_actuator(actuator, 252.0, false, false);
    let plant = fastemu::rig::actuator::ActuatorPlant::from_config(&cfg.rig.actuator);
    assert_eq!(plant.unstable_poles(), 2);
    let counted = fastemu::hil::check::LinearLoop::for_plant(&cfg, &plant, 0.0, 1.0);
    assert_eq!(counted.stable_leads(3e-3), None);
    let mut uncounted = counted.clone();
    uncounted.actuator_unstable_poles = 0;
    assert_eq!(uncounted.stable_leads(3e-3), Some((0.0, 3e-3)));
    for lead_us in [0.0, 252.0, 800.0] {
        let cfg = config_with_actuator(actuator, lead_us, false, false);
        let run = run_in_process(&cfg, &script(2.0));
        let trip = faults(&run)
            .into_iter()
            .find(|(p, f, _)| *p == process_id::EMULATOR && *f == Fault::LoopUnstable)
            .unwrap_or_else(|| panic!("lead {lead_us}: no loop-unstable: {:?}", faults(&run)));
        assert!(trip.2 < 1.0, "lead {lead_us}: tripped at {} s", trip.2);
        // The oscillation's frequency in the 50 ms before the trip, from its zero crossings.
        let window: Vec<_> = run
            .emulator
            .iter()
            .filter(|r| r.t_s > trip.2 - 0.1 && r.t_s <= trip.2 - 0.05)
            .collect();
        let crossings = window
            .windows(2)
            .filter(|p| p[0].oscillation_m.signum() != p[1].oscillation_m.signum())
            .count();
        let f_hz = crossings as f64 / 2.0 / 0.05;
        assert!((420.0..540.0).contains(&f_hz), "lead {lead_us}: {f_hz} Hz");
    }
}

/// The servo-hydraulic presets as shipped (full velocity compensation), perturbed, from the
/// shipped `[compensation]` (a guess of 252 us, adaptation and guard on): the adaptation
/// would settle on the load band's delay, where the loop is unstable for some actuators the
/// declared one's tolerance allows, so the plan (`check::compensation_plan`, judged on the
/// declared preset and its own draws, never the rig's) fixes the lead. Each run, on a
/// rig whose draw the plan never saw, is stable: no fault, the rig never holds, every law
/// command carries the plan's lead, or one the nudge stepped it to within the plan's range
/// (`compensation::LeadNudge`, at most 0.1 s of lead per s; the first command the plan's),
/// and no guard damping where the plan turned the guard off (its damping through the
/// actuator's lag generates energy); the error against the offline reference dies away
/// after the passage. None is faithful (over 1 % of displacement error): not clean. Without the plan
/// the same run trips `loop-unstable` within half a second.
#[test]
fn servo_hydraulic_presets_run_stable_on_the_planned_lead_and_are_not_clean() {
    let cases = [
        "preset = \"fatigue-150kn\"\nperturb = 0.3\nperturb_seed = 3",
        "preset = \"fatigue-150kn\"\nperturb = 0.3\nperturb_seed = 6",
        "preset = \"rths-fast-150kn\"\nperturb = 0.3\nperturb_seed = 2",
        "preset = \"slow-250kn\"\nperturb = 0.3\nperturb_seed = 5",
    ];
    for actuator in cases {
        let cfg = config_with_actuator(actuator, 252.0, true, true);
        let plan = fastemu::hil::check::compensation_plan(&cfg).expect("a plan");
        assert!(plan.lead_fixed, "{actuator}: {plan:?}");
        assert!(plan.destination_unstable_for > 0);
        let run = run_in_process(&cfg, &script(6.0));
        assert_eq!(run.plan.as_ref(), Some(&plan), "{actuator}");
        let (during, after, error) = ran_to_the_end_unheld(&cfg, &run, actuator);
        let law = law_commands(&run);
        assert!(law.len() > 20_000, "{actuator}: {} law commands", law.len());
        let range = plan.nudge.expect("a nudge range");
        assert!(
            (law[0].lead_s * 1e6 - plan.lead_us).abs() < 1e-6,
            "{actuator}"
        );
        let mut previous = (law[0].t_s, law[0].lead_s);
        for r in &law {
            // At most 0.1 s of lead per s of the samples between two commands.
            let allowed = 0.1 * ((r.t_s - previous.0) + 1.0 / RATE) + 1e-12;
            assert!(
                (range.low_s..=range.high_s).contains(&r.lead_s)
                    && (r.lead_s - previous.1).abs() <= allowed
                    && (plan.guard || r.guard_damping_ns_per_m == 0.0),
                "{actuator}: lead {} us, damping {} at {} s",
                r.lead_s * 1e6,
                r.guard_damping_ns_per_m,
                r.t_s
            );
            previous = (r.t_s, r.lead_s);
        }
        eprintln!(
            "{actuator}: lead {:.0} us, error {:.2} %, worst {:.1} um before 4 s, {:.1} um in the last second",
            plan.lead_us,
            error * 100.0,
            during * 1e6,
            after * 1e6
        );
        assert!(after < 0.1 * during, "{actuator}");
        assert!(error > 0.01, "{actuator}: {:.3} %", error * 100.0);
    }
    // A rig without the plan trips; with the plan it runs. `slow-250kn` seed 1: it rings
    // near 20 Hz, below the band the ring is read in. (`fatigue-150kn` seeds 1, 2 and 3
    // tripped here until 2026-11-28 and run to the end on their ring's lead since
    // `RING_PERIODS_AVERAGED`; seed 9, since the ring's follow-up, `RING_FOLLOW_UP_S`,
    // 2026-11-29: not clean, but no longer examples of a trip.)
    let unplanned_trips = "preset = \"slow-250kn\"\nperturb = 0.3\nperturb_seed = 1";
    let planned = config_with_actuator(unplanned_trips, 252.0, true, true);
    let run = run_in_process(&planned, &script(2.0));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let mut cfg = planned.clone();
    cfg.compensation.plan_from_actuator = false;
    assert_eq!(fastemu::hil::check::compensation_plan(&cfg), None);
    let run = run_in_process(&cfg, &script(2.0));
    let trip = faults(&run)
        .into_iter()
        .find(|(p, f, _)| *p == process_id::EMULATOR && *f == Fault::LoopUnstable)
        .unwrap_or_else(|| panic!("no loop-unstable without the plan: {:?}", faults(&run)));
    assert!(trip.2 < 0.5, "tripped at {} s", trip.2);
}

/// A draw the planned lead is a little too short for (`fatigue-150kn`, `perturb = 0.3` seed
/// 11: stable, by the linearised loop on its truth, for leads from 2890 us, and the plan
/// fixes 2850 us) runs quietly until the first axle (2.0 s), which starts an oscillation at
/// the force loop's crossover that keeps ±0.2 mm; until 2026-11-28 it went on for 2.6 s and
/// tripped `loop-unstable` at 4.65 s. The nudge (`compensation::LeadNudge`) reads it as a
/// lead too short (its frequency below the plan's split) and steps the lead up into the
/// truth's stable leads: no fault, and the error dies away.
#[test]
fn a_planned_lead_a_draw_keeps_oscillating_at_is_stepped_into_its_stable_leads() {
    use fastemu::hil::check::LinearLoop;
    use fastemu::rig::actuator::ActuatorPlant;
    let actuator = "preset = \"fatigue-150kn\"\nperturb = 0.3\nperturb_seed = 11";
    let cfg = config_with_actuator(actuator, 252.0, true, true);
    let plan = fastemu::hil::check::compensation_plan(&cfg).expect("a plan");
    let truth = ActuatorPlant::new(&cfg.rig.actuator.truth(), &cfg.rig.actuator.nominal);
    let (low, high) = LinearLoop::for_plant(&cfg, &truth, 0.0, 1.0)
        .stable_leads(0.01)
        .expect("stable leads");
    assert!(
        plan.lead_fixed && plan.lead_us * 1e-6 < low,
        "{plan:?} vs {low}"
    );
    let run = run_in_process(&cfg, &script(6.0));
    let (during, after, error) = ran_to_the_end_unheld(&cfg, &run, actuator);
    let law = law_commands(&run);
    // The plan's lead until the axle, then stepped up into the truth's stable leads.
    let first_move = law
        .iter()
        .find(|r| (r.lead_s * 1e6 - plan.lead_us).abs() > 1e-6)
        .expect("the lead moved");
    assert!(first_move.t_s > 2.0 && first_move.lead_s > plan.lead_us * 1e-6);
    let last = law.last().unwrap().lead_s;
    assert!((low..=high).contains(&last), "{last} not in {low}-{high}");
    eprintln!(
        "seed 11: stepped at {:.3} s, final lead {:.0} us, error {:.2} %, worst {:.0} um, {:.1} um in the last second",
        first_move.t_s,
        last * 1e6,
        error * 100.0,
        during * 1e6,
        after * 1e6
    );
    assert!(during > 100e-6, "{during}");
    assert!(after < 0.05 * during, "{after} vs {during}");
}

/// The safe start ends on a loaded machine. Under emulator stalls of 1-8 periods every
/// 4-16 ms the estimator restarted at every gap over 8 periods (faster than it warmed
/// up: no estimate), and the first estimates after a warm-up, resting on about one
/// independent residual, were followed (887 +- 125 us against 265: the lead went to
/// 348 us); either way the safe start's damping stayed on all run, 0.2-0.3 %
/// displacement error instead of 0.034 %. Now gaps up to 32 periods are bridged and an
/// estimate needs 3 independent residuals. Stall patterns of seeds nothing was tuned on.
#[test]
fn the_safe_start_ends_under_frequent_emulator_stalls() {
    let cfg = default_hil_config().unwrap();
    for seed in [21, 22] {
        let run = run_unfaulted_under_frequent_stalls(&cfg, seed, 4.0);
        let law = law_commands(&run);
        let armed_until = law
            .iter()
            .filter(|r| r.guard_armed == 1)
            .map(|r| r.t_s)
            .fold(0.0f64, f64::max);
        assert!(
            armed_until < 2.5,
            "seed {seed}: the safe start lasted to {armed_until} s"
        );
        assert!(
            law.iter().all(|r| (200e-6..300e-6).contains(&r.lead_s)),
            "seed {seed}: the lead left 200-300 us"
        );
        let e = displacement_error(&cfg, &run);
        assert!(e < 0.001, "seed {seed}: displacement error {e}");
    }
}

/// A perturbed lag-delay actuator (`perturb = 0.3`, `seed`) from `guess_us`, 3 s in
/// process: no fault, and the run's configuration, record and truth (`truth_delay_s`).
fn perturbed_lag_delay_run(
    transport_us: f64,
    lag_us: f64,
    seed: u64,
    guess_us: f64,
) -> (HilConfig, InProcessRun, f64) {
    let cfg = config_with_actuator(
        &format!(
            "kind = \"lag-delay\"\ntransport_delay_us = {transport_us:.1}\nlag_us = {lag_us:.1}\nforce_max_n = 150000.0\nperturb = 0.3\nperturb_seed = {seed}"
        ),
        guess_us,
        true,
        true,
    );
    let run = run_in_process(&cfg, &script(3.0));
    assert!(faults(&run).is_empty(), "seed {seed}: {:?}", faults(&run));
    assert_started_at_the_guess(&run);
    let truth_s = truth_delay_s(&cfg);
    (cfg, run, truth_s)
}

/// The time the safe start ended (the guard's last armed command), s.
fn safe_start_end_s(run: &InProcessRun) -> f64 {
    run.controller
        .iter()
        .filter(|r| r.mode == command_mode::LAW && r.guard_armed == 1)
        .map(|r| r.t_s)
        .fold(0.0, f64::max)
}

/// The safe start's full damping, on a lead a little shorter than the actuator's delay,
/// is itself what makes the loop ring: a `lag-delay` of 500 + 80 us drawn by seed 41
/// (815 us effective) from a guess of 1160 us, capped at 742 us (`hil --check`: stable at
/// that lead without the damping, unstable with any above ~5 kN s/m). A 400 Hz oscillation
/// grew under the damping while the observers read the loop as absorbing, and the
/// specimen left its range at 0.27-0.29 s (2026-11-28, in process and in one of two
/// `fastemu hil` runs). The guard now sees an oscillation grow under its own damping and
/// ends the safe start: no fault, the safe start over before the specimen could leave
/// its range, the lead learned and the run faithful.
#[test]
fn a_safe_start_whose_own_damping_rings_ends() {
    let (cfg, run, truth_s) = perturbed_lag_delay_run(500.0, 80.0, 41, 1160.0);
    let ended = safe_start_end_s(&run);
    assert!(ended > 0.0 && ended < 0.25, "safe start ended at {ended} s");
    assert_learned_and_faithful(&cfg, &run, truth_s, 0.1);
}

/// A lead a little too long under the safe start: a `lag-delay` of 300 + 100 us from a
/// guess of 800 us. The estimator read the delay precisely (445-545 us) by 0.15-0.3 s
/// while the lead crept down from 800 us at `adapt_time`'s pace under the full damping; a
/// 398-399 Hz ring then read 1.05-1.06 ms, the lead went there and seeds 9, 13 and 14
/// tripped `loop-unstable` (2026-11-28). Under the safe start the lead now goes to a
/// precise estimate near it at once, and a ring reading on the other side of such an
/// estimate is not taken: each runs faithfully, the safe start over within 0.5 s.
#[test]
fn a_lead_too_long_under_the_safe_start_goes_to_a_precise_estimate() {
    for seed in [9, 13, 14] {
        let (cfg, run, truth_s) = perturbed_lag_delay_run(300.0, 100.0, seed, 800.0);
        let ended = safe_start_end_s(&run);
        assert!(
            ended > 0.0 && ended < 0.5,
            "seed {seed}: safe start ended at {ended} s"
        );
        let highest = run
            .controller
            .iter()
            .filter(|r| r.mode == command_mode::LAW)
            .map(|r| r.lead_s)
            .fold(0.0, f64::max);
        assert!(
            highest <= 800e-6 + 1e-9,
            "seed {seed}: the lead went to {} us",
            highest * 1e6
        );
        assert_learned_and_faithful(&cfg, &run, truth_s, 0.1);
    }
}

/// The rendered force's amplitude against the element's at each whole hertz of 1-20 Hz
/// the element's force has content at (at least 2 % of the band's largest), over the
/// whole run: `(hz, |actuator force| / |element force|)`, from the rig's and the
/// emulator's records by a DFT of their own (not the report's rendering).
fn rendered_amplitude_1_20_hz(run: &InProcessRun) -> Vec<(u32, f64)> {
    let element: std::collections::HashMap<u64, f64> = run
        .emulator
        .iter()
        .map(|e| (e.step_idx, e.force_n))
        .collect();
    let pairs: Vec<(f64, f64, f64)> = run
        .rig
        .iter()
        .filter_map(|r| {
            element
                .get(&r.step_idx)
                .map(|&e| (r.t_s, r.actuator_force_n, e))
        })
        .collect();
    let dft = |hz: u32| {
        let w = 2.0 * std::f64::consts::PI * hz as f64;
        let (mut a, mut e) = ((0.0, 0.0), (0.0, 0.0));
        for &(t, fa, fe) in &pairs {
            let (s, c) = (w * t).sin_cos();
            a = (a.0 + fa * c, a.1 - fa * s);
            e = (e.0 + fe * c, e.1 - fe * s);
        }
        (a.0.hypot(a.1), e.0.hypot(e.1))
    };
    let bins: Vec<(u32, f64, f64)> = (1..=20)
        .map(|hz| {
            let (a, e) = dft(hz);
            (hz, a, e)
        })
        .collect();
    let largest = bins.iter().map(|b| b.2).fold(0.0, f64::max);
    bins.into_iter()
        .filter(|b| b.2 >= 0.02 * largest)
        .map(|(hz, a, e)| (hz, a / e))
        .collect()
}

/// `lag-delay` 1 ms + 1 ms (the check, `initial_delay_us` at the default): no lead
/// makes the loop stable with the configured quadratic prediction (`hil --check`), so
/// before 2026-11-28 `hil` refused it and in-process it tripped `loop-unstable`. The plan
/// raises the prediction to cubic, with which 1560-1670 us are stable for this actuator,
/// and fixes the lead there: the run ends without a fault, within 1 % of the offline
/// reference, its rendered amplitude within 1 % at every excited bin of 1-20 Hz, and the
/// delay identified over the load band within 25 % of the plant's effective delay. Measured
/// (`fastemu hil`, 3 runs): 0.648-0.649 %, amplitude 0.9916-1.0001, identified 2122 us
/// against 2120 us.
#[test]
fn a_lag_delay_of_1_plus_1_ms_runs_on_a_cubic_prediction_within_1_percent() {
    let cfg = config_with_actuator(
        "kind = \"lag-delay\"\ntransport_delay_us = 1000.0\nlag_us = 1000.0\nforce_max_n = 150000.0",
        252.0,
        true,
        true,
    );
    assert_eq!(cfg.compensation.lead_order, 2);
    let run = run_in_process(&cfg, &script(6.0));
    assert_on_the_planned_cubic(&run);
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let error = displacement_error(&cfg, &run);
    assert!(error < 0.01, "displacement error {:.3} %", 100.0 * error);
    let amplitude = rendered_amplitude_1_20_hz(&run);
    assert!(amplitude.len() >= 10, "{amplitude:?}");
    for (hz, ratio) in &amplitude {
        assert!((ratio - 1.0).abs() < 0.01, "{hz} Hz: amplitude {ratio:.4}");
    }
    let truth_s = truth_delay_s(&cfg);
    let identified_s = run
        .controller
        .iter()
        .rev()
        .find(|r| r.load_band_delay_s.is_finite())
        .map(|r| r.load_band_delay_s)
        .expect("a delay identified over the load band");
    assert!(
        (identified_s / truth_s - 1.0).abs() < 0.25,
        "identified {:.0} us, truth {:.0} us",
        identified_s * 1e6,
        truth_s * 1e6
    );
}

/// The run's plan raised the prediction to cubic and fixed the lead, and every law command
/// carried both; returns the plan.
fn assert_on_the_planned_cubic(run: &InProcessRun) -> &fastemu::hil::check::CompensationPlan {
    let plan = run.plan.as_ref().expect("a plan");
    assert_eq!(plan.raised_lead_order, Some(3));
    assert!(plan.lead_fixed);
    let law: Vec<&ControllerRecord> = law_commands(run);
    assert!(!law.is_empty());
    assert!(law
        .iter()
        .all(|r| r.lead_order == 3 && (r.lead_s * 1e6 - plan.lead_us).abs() < 1e-6));
    plan
}

/// `lag-delay` 700 + 900 us has stable leads at the configured quadratic prediction only
/// with all of the passivity guard's damping, and 1330-1570 us by itself at the cubic one.
/// Before 2026-11-28 (twenty-seventh session) the guard's damping counted as making the
/// quadratic renderable, so the plan did not raise the order, the run relied on the guard
/// and tripped `loop-unstable` from every guess (0, 252 and 3444 us). The plan now raises
/// the order, fixes the lead where the loop is stable by itself, and the run ends without
/// a fault within 1 % (measured: `fastemu hil` 0.396 % in 2 runs, in-process 0.396 %).
#[test]
fn a_loop_stable_only_under_the_guards_damping_at_the_configured_order_runs_at_the_raised_one() {
    let cfg = config_with_actuator(
        "kind = \"lag-delay\"\ntransport_delay_us = 700.0\nlag_us = 900.0\nforce_max_n = 150000.0",
        252.0,
        true,
        true,
    );
    assert_eq!(cfg.compensation.lead_order, 2);
    // The premise, on the linearised loop: at order 2 stable only with all of the damping.
    let plant = fastemu::rig::actuator::ActuatorPlant::from_config(&cfg.rig.actuator);
    let max = cfg.compensation.max_delay_s;
    let mut bare = fastemu::hil::check::LinearLoop::for_plant(&cfg, &plant, 0.0, 1.0);
    assert!(!bare.has_stable_lead(max));
    let mut damped = bare.clone();
    damped.guard_damping_ns_per_m = cfg.compensation.guard_max_damping_ns_per_m;
    assert!(damped.has_stable_lead(max));
    bare.lead_order = 3;
    assert!(bare.has_stable_lead(max));
    let run = run_in_process(&cfg, &script(6.0));
    let plan = assert_on_the_planned_cubic(&run);
    let mut at_plan =
        fastemu::hil::check::LinearLoop::for_plant(&cfg, &plant, plan.lead_us * 1e-6, 1.0);
    at_plan.lead_order = 3;
    assert!(at_plan.is_stable(0.0, 1.0), "{} us", plan.lead_us);
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let error = displacement_error(&cfg, &run);
    assert!(error < 0.01, "displacement error {:.3} %", 100.0 * error);
}

/// The element stiffens with its load (SPEC 2.1): `lag-delay` 1003 + 99 us, declared as it
/// is, has stable leads at the 20 kN preload (its plan fixes 1100 us inside them) but none
/// under the axle's 71.9 kN, and the plan says so. In time, the loop runs without a fault
/// until the first axle comes (2 s) and trips `loop-unstable` under it, and the rig holds
/// within the range the run had kept. The per-load judgement is checked against the loop
/// judged whole at that load as its preload.
#[test]
fn a_loop_stable_at_the_preload_and_not_under_the_axles_load_trips_at_the_first_axle() {
    let actuator =
        "kind = \"lag-delay\"\ntransport_delay_us = 1003.0\nlag_us = 99.0\nforce_max_n = 150000.0";
    let cfg = config_with_actuator(actuator, 252.0, true, true);
    let plan = fastemu::hil::check::compensation_plan(&cfg).expect("a plan");
    assert!(plan.lead_fixed, "{plan:?}");
    let (_, highest) = fastemu::hil::check::programme_load_range(&cfg);
    assert!(highest > 3.0 * cfg.scenario.preload_n, "{highest}");
    let over = plan
        .over_programme
        .clone()
        .expect("judged over the programme");
    assert_eq!(over.declared_unstable_loads_n, vec![highest]);
    assert!(fastemu::hil::check::describe_plan(&plan).contains("NOT stable under 71.9 kN"));
    let plant = fastemu::rig::actuator::ActuatorPlant::from_config(&cfg.rig.actuator);
    let lead_s = plan.lead_us * 1e-6;
    let lin = fastemu::hil::check::LinearLoop::for_plant(&cfg, &plant, lead_s, 1.0)
        .with_programme_loads(&cfg);
    assert!(lin.is_stable(0.0, 1.0));
    assert_eq!(lin.unstable_loads_n(), vec![highest]);
    let mut at_peak = cfg.clone();
    at_peak.scenario.preload_n = highest;
    let whole = fastemu::hil::check::LinearLoop::for_plant(&at_peak, &plant, lead_s, 1.0);
    assert!(!whole.is_stable(0.0, 1.0));
    assert_eq!(whole.stable_leads(10e-3), None);

    let run = run_in_process(&cfg, &script(3.0));
    let f = faults(&run);
    let first_axle_s = cfg.scenario.train_first_axle_s;
    let trip = f
        .iter()
        .find(|(p, fault, _)| *p == process_id::EMULATOR && *fault == Fault::LoopUnstable)
        .unwrap_or_else(|| panic!("no loop-unstable: {f:?}"));
    assert!(
        f.iter().all(|(_, _, t)| *t >= first_axle_s),
        "a fault before the first axle: {f:?}"
    );
    assert!(
        (first_axle_s..first_axle_s + 0.3).contains(&trip.2),
        "tripped at {} s",
        trip.2
    );
    assert!(run.rig.iter().any(|r| r.state == rig_state::HOLD));
    // Faithful before the axle: within 0.5 % of the offline reference up to 1.9 s.
    let error = displacement_error_before(&cfg, &run, first_axle_s - 0.1);
    assert!(error < 5e-3, "error before the axle {error}");
    // The hold keeps the specimen within 0.1 mm of the range the run had kept.
    let beyond = beyond_range_before(&run, trip.2 - 0.05);
    assert!(beyond < 0.1e-3, "excursion {} mm beyond", beyond * 1e3);
}

/// A guess 15-45 % too long before `lag-delay` 500 + 80 us (0.70 ms with the hold): the
/// safe start's full damping, predicted over such a lead, generates energy at the band's
/// top and the loop tripped `loop-unstable` within 0.1 s (guesses of 800-1000 us, nominal
/// and drawn). The launcher now starts with the largest fraction of it the starting lead
/// stays stable with in front of every actuator the guess allows
/// (`check::safe_start_damping_ns_per_m`): every run is fault-free and within 0.1 % of
/// the offline reference, its first law command carrying that damping.
#[test]
fn a_guess_somewhat_too_long_starts_with_the_damping_its_lead_stays_stable_with() {
    for (seed, guess_us) in [(0, 900.0), (3, 900.0), (4, 1000.0), (6, 800.0)] {
        let actuator = if seed == 0 {
            "kind = \"lag-delay\"\ntransport_delay_us = 500.0\nlag_us = 80.0\nforce_max_n = 150000.0".to_string()
        } else {
            format!("kind = \"lag-delay\"\ntransport_delay_us = 500.0\nlag_us = 80.0\nforce_max_n = 150000.0\nperturb = 0.3\nperturb_seed = {seed}")
        };
        let cfg = config_with_actuator(&actuator, guess_us, true, true);
        let start = fastemu::hil::check::starting_compensation(&cfg, None);
        let full = cfg.compensation.guard_max_damping_ns_per_m;
        assert!(
            start.safe_start_damping_ns_per_m < full,
            "seed {seed}, {guess_us} us: {}",
            start.safe_start_damping_ns_per_m
        );
        let run = run_in_process(&cfg, &script(3.0));
        assert!(faults(&run).is_empty(), "seed {seed}: {:?}", faults(&run));
        let first = law_commands(&run)[0];
        assert_eq!(
            first.guard_damping_ns_per_m,
            start.safe_start_damping_ns_per_m
        );
        let error = displacement_error(&cfg, &run);
        assert!(error < 1e-3, "seed {seed}, {guess_us} us: error {error}");
    }
}

/// A displacement sensor of 1 um (ten times the shipped rig's) in front of a declared
/// `lag-delay` of 600 + 150 us. The guard's observer reads the noise's own work above the
/// load band (the prediction and the actuator turn noise into force) as energy generated:
/// with the thresholds tuned at 0.1 um it damped on noise alone, the damping, delayed by
/// the actuator, made the loop ring, the ring's reading moved the lead out of its stable
/// range and `loop-unstable` tripped at 0.077 s (2026-11-28). The controller reads the
/// noise (within 15 %) and raises the thresholds with its variance: no fault, no damping
/// in any command, the run as faithful as the noise allows. A loop that does generate
/// energy (the lead 100 us short, adaptation off) under the same noise is still answered:
/// the guard damps it and the run ends without a fault.
#[test]
fn a_noisy_sensor_raises_the_guards_thresholds_and_a_generating_loop_is_still_damped() {
    let noisy = |mut cfg: HilConfig| {
        cfg.rig.sensor_noise_m = 1e-6;
        cfg
    };
    let actuator =
        "kind = \"lag-delay\"\ntransport_delay_us = 600.0\nlag_us = 150.0\nforce_max_n = 150000.0";
    let cfg = noisy(config_with_actuator(actuator, 252.0, true, true));
    let run = run_in_process(&cfg, &script(3.0));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let law = law_commands(&run);
    assert!(
        law.iter().all(|r| r.guard_damping_ns_per_m == 0.0),
        "damped on noise: largest {} N s/m",
        law.iter()
            .map(|r| r.guard_damping_ns_per_m)
            .fold(0.0, f64::max)
    );
    let last = law.last().unwrap();
    assert!(
        (last.sensor_noise_m / 1e-6 - 1.0).abs() < 0.15,
        "read {} m",
        last.sensor_noise_m
    );
    let onset = cfg.compensation.guard_onset_energy_j;
    let expected = onset * (last.sensor_noise_m / 0.25e-6).powi(2);
    assert!((last.guard_onset_j / expected - 1.0).abs() < 1e-9);
    assert!(
        last.guard_onset_j > 10.0 * onset,
        "{} J",
        last.guard_onset_j
    );
    let error = displacement_error(&cfg, &run);
    assert!(error < 0.005, "{:.3} %", 100.0 * error);

    let short = noisy(config_with_actuator(
        "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0",
        152.0,
        false,
        true,
    ));
    let run = run_in_process(&short, &script(3.0));
    assert!(faults(&run).is_empty(), "{:?}", faults(&run));
    let law = law_commands(&run);
    let damped = law
        .iter()
        .filter(|r| r.guard_damping_ns_per_m > 0.0)
        .count();
    assert!(
        damped > law.len() / 2,
        "damped {damped} of {} commands",
        law.len()
    );
}
