//! Diagnose's honest verdicts (SPEC 5.1) on the project's generator: effects only passages
//! reveal, what labs meet (a load-train resonance, a specimen that changed during the
//! campaign, self-heating), a truth outside the library (a load-cell nonlinearity), and
//! null campaigns.

use std::path::PathBuf;

use fastemu::ident::campaign::load_campaign;
use fastemu::ident::diagnose::{diagnose, DiagnoseOptions, Diagnosis};
use fastemu::ident::first_cycles::{split_first_cycles, FirstCyclesUse};
use fastemu::ident::fit::{test_data, EffectKind};
use fastemu::model::effects::{AugmentedModel, DriftClock, Effect};
use fastemu::model::file::parse_model_toml;

use crate::gen::{
    off_baseline_toml, standard_design, write_campaign_full, Acquisition, Noise, Passage,
    TestPoint, Truth,
};

fn scratch_dir(name: &str) -> PathBuf {
    if let Some(keep) = std::env::var_os("FASTEMU_KEEP_CAMPAIGNS") {
        let dir = PathBuf::from(keep).join(name);
        let _ = std::fs::remove_dir_all(&dir);
        return dir;
    }
    let dir = std::env::temp_dir().join(format!("fastemu-it-{}-v-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// Writes the campaign, diagnoses it (campaign order is test order), cleans up.
pub fn diagnose_case(
    name: &str,
    truth: &Truth,
    design: &[TestPoint],
    passages: &[Passage],
    noise: &Noise,
    seed: u64,
) -> Diagnosis {
    diagnose_case_with(
        name,
        truth,
        design,
        passages,
        noise,
        seed,
        &Acquisition::typical(),
    )
}

/// `diagnose_case` with records of another length. Like `diagnose --campaign` it uses
/// the first cycles of records that carry something; records that start in steady state
/// must have none split off.
pub fn diagnose_case_with(
    name: &str,
    truth: &Truth,
    design: &[TestPoint],
    passages: &[Passage],
    noise: &Noise,
    seed: u64,
    acquisition: &Acquisition,
) -> Diagnosis {
    let (diagnosis, used) = diagnose_case_split(
        name,
        truth,
        design,
        passages,
        noise,
        seed,
        acquisition,
        true,
    );
    if !acquisition.from_rest {
        assert!(used.is_empty(), "[{name}] first cycles split: {used:?}");
    }
    diagnosis
}

/// `diagnose_case_with`, the first cycles split off (`split_first_cycles`) or not, and
/// which were.
#[allow(clippy::too_many_arguments)]
pub fn diagnose_case_split(
    name: &str,
    truth: &Truth,
    design: &[TestPoint],
    passages: &[Passage],
    noise: &Noise,
    seed: u64,
    acquisition: &Acquisition,
    use_first_cycles: bool,
) -> (Diagnosis, Vec<FirstCyclesUse>) {
    let dir = scratch_dir(name);
    write_campaign_full(&dir, truth, design, passages, noise, seed, acquisition);
    let campaign = load_campaign(&dir).expect("campaign loads");
    let (campaign, used) = if use_first_cycles {
        split_first_cycles(&campaign)
    } else {
        (campaign, Vec::new())
    };
    for u in &used {
        eprintln!("[{name}] first cycles used: {}", u.reason());
    }
    let data = test_data(&campaign).expect("tests reduce");
    let spec = parse_model_toml(&off_baseline_toml(0.3), "baseline.toml").unwrap();
    let baseline = AugmentedModel::from_spec(&spec, "baseline.toml").unwrap();
    let quiet = std::env::var_os("FASTEMU_VERBOSE").is_none();
    let diagnosis = diagnose(&baseline, &data, &DiagnoseOptions::default(), &mut |m| {
        if !quiet {
            eprintln!("[{name}] {m}")
        }
    });
    if std::env::var_os("FASTEMU_KEEP_CAMPAIGNS").is_none() {
        let _ = std::fs::remove_dir_all(&dir);
    } else {
        std::fs::write(dir.join("baseline.toml"), off_baseline_toml(0.3)).unwrap();
    }
    eprintln!(
        "[{name}] named {:?}, gap {:.3e} -> {:.3e}, noise floor {:.3e}, harmonic z {:.2}, unexplained {:?}, trend {:?}, out of range {:?}",
        names(&diagnosis),
        diagnosis.gap_before,
        diagnosis.gap_after,
        diagnosis.noise_floor,
        diagnosis.verdict.harmonic_z,
        diagnosis.verdict.unexplained.as_ref().map(|u| (u.gap, &u.where_)),
        diagnosis.verdict.trend.as_ref().map(|t| (t.change, t.t, t.beats_design)),
        out_of_range(&diagnosis),
    );
    (diagnosis, used)
}

pub fn names(d: &Diagnosis) -> Vec<&'static str> {
    d.named.iter().map(|k| k.name()).collect()
}

fn out_of_range(d: &Diagnosis) -> Vec<String> {
    d.rounds
        .iter()
        .flatten()
        .filter_map(|c| c.out_of_range.map(|o| format!("{}: {o}", c.kind.name())))
        .collect()
}

/// The paper's 20-test design: four preloads x five frequencies, one amplitude.
fn paper_design() -> Vec<TestPoint> {
    standard_design().into_iter().take(20).collect()
}

#[test]
fn friction_that_only_passages_reveal_is_named() {
    let truth = Truth {
        friction: Some((20e6, 1.0e3)),
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "passages-friction",
        &truth,
        &paper_design(),
        &Passage::rising(3),
        &Noise::typical(),
        21,
    );
    assert!(
        d.named.contains(&EffectKind::AmplitudeFriction),
        "named {:?}",
        names(&d)
    );
    assert!(
        d.gap_before >= 3.0 * d.gap_after,
        "gap {:.3e} -> {:.3e}",
        d.gap_before,
        d.gap_after
    );
}

#[test]
fn without_passages_the_same_friction_is_not_identifiable() {
    // The counterpart of the case above: one force amplitude and no passage.
    let truth = Truth {
        friction: Some((20e6, 1.0e3)),
        ..Truth::paper_like()
    };
    let friction_identifiable = |name: &str, passages: &[Passage]| {
        let dir = scratch_dir(name);
        write_campaign_full(
            &dir,
            &truth,
            &paper_design(),
            passages,
            &Noise::typical(),
            21,
            &Acquisition::typical(),
        );
        let data = test_data(&load_campaign(&dir).unwrap()).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        fastemu::ident::diagnose::identifiability(EffectKind::AmplitudeFriction, &data).is_ok()
    };
    assert!(!friction_identifiable("no-passages", &[]));
    assert!(friction_identifiable("with-passages", &Passage::rising(1)));
}

#[test]
fn a_load_train_resonance_is_named_with_its_mode_and_no_negative_mass() {
    // The generator's resonance: Tustin filter of the force at its fine step, 70 Hz, 5 %.
    let truth = Truth {
        load_path_resonance: Some((70.0, 0.05)),
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "resonance",
        &truth,
        &standard_design(),
        &[],
        &Noise::typical(),
        22,
    );
    assert_named_alone(&d, "load-train-resonance");
    let params =
        fastemu::ident::diagnose::effect_params(&d.final_model, EffectKind::LoadTrainResonance);
    let value = |key: &str| params.iter().find(|(k, _)| *k == key).unwrap().1;
    let (fn_hz, zeta) = (value("natural_frequency_hz"), value("damping_ratio"));
    assert!((fn_hz - 70.0).abs() < 3.5, "natural frequency {fn_hz}");
    assert!((0.025..0.1).contains(&zeta), "damping ratio {zeta}");
    // What a moving mass would need is still reported: a negative mass.
    let mass = d
        .rounds
        .iter()
        .flatten()
        .find(|c| c.kind == EffectKind::MovingMass)
        .expect("moving-mass was tried");
    let o = mass.out_of_range.expect("the mass fits only negative");
    assert!(o.value < 0.0, "{o}");
}

#[test]
fn a_specimen_that_softens_during_the_campaign_is_named_as_a_drift_with_its_rate() {
    let truth = Truth {
        softening_over_campaign: 0.06,
        ..Truth::paper_like()
    };
    let design = standard_design();
    let d = diagnose_case("softening", &truth, &design, &[], &Noise::typical(), 23);
    assert_named_alone(&d, "specimen-drift");
    let Some(&Effect::SpecimenDrift {
        clock,
        rate_per_unit,
        rate_standard_error,
        clock_position,
    }) = d.final_model.find("specimen-drift")
    else {
        panic!("no drift in {:?}", d.final_model.effects)
    };
    // No started_at: test order or dissipated energy; the generator's law is linear in
    // the test index, 6 % from the first test to the last.
    let change = rate_per_unit * (design.len() - 1) as f64;
    assert_eq!(clock, DriftClock::TestOrder, "{clock:?}");
    assert!(
        (change + 0.06).abs() < 0.01,
        "change over the campaign {change}"
    );
    assert!(rate_standard_error > 0.0 && rate_standard_error < 0.2 * rate_per_unit.abs());
    assert_eq!(clock_position, 0.0, "the model describes the first test");
}

#[test]
fn a_self_heating_specimen_is_named_with_a_physical_thermal_circuit() {
    // 6 J/K on 0.05 W/K: a two-minute time constant; 60-cycle records with 10 s rests, so
    // heat carries from test to test; moduli -1 %/K (the library's default law: -0.8 %/K,
    // exponential; the generator has no relaxation-time shift either).
    let truth = Truth {
        self_heating: Some((6.0, 0.05, 0.01)),
        rest_s: Some(10.0),
        ..Truth::paper_like()
    };
    let dir_name = "self-heating";
    let acquisition = long_records();
    let d = diagnose_case_with(
        dir_name,
        &truth,
        &standard_design(),
        &[],
        &Noise::typical(),
        24,
        &acquisition,
    );
    assert_named_alone(&d, "self-heating");
    let Some(&Effect::SelfHeating {
        heat_capacity_j_per_k,
        heat_transfer_w_per_k,
        ..
    }) = d.final_model.find("self-heating")
    else {
        panic!()
    };
    // The laws differ (linear vs exponential, no time shift in the truth): within 2x.
    assert!(
        (0.025..0.1).contains(&heat_transfer_w_per_k),
        "h = {heat_transfer_w_per_k}"
    );
    let tau = heat_capacity_j_per_k / heat_transfer_w_per_k;
    assert!((40.0..400.0).contains(&tau), "tau = {tau}");
    // Heat carried between tests: the heat capacity is identified, no caveat.
    let named = d
        .rounds
        .iter()
        .flatten()
        .find(|c| c.qualifies && c.kind == EffectKind::SelfHeating)
        .expect("the fit named");
    assert_eq!(named.law_note, None);
}

/// The first test repeated at the end of a heating campaign runs warmer: its stiffness
/// differs beyond noise, but the named self-heating reproduces both, so the report does
/// not say the specimen changed (a drift's repeat still does:
/// `a_repeated_first_test_checks_drift_directly`).
#[test]
fn a_warmer_repeat_is_explained_by_self_heating_not_a_changed_specimen() {
    let truth = Truth {
        self_heating: Some((6.0, 0.05, 0.01)),
        rest_s: Some(10.0),
        ..Truth::paper_like()
    };
    let mut design = standard_design();
    design.push(design[0]);
    let d = diagnose_case_with(
        "self-heating-repeat",
        &truth,
        &design,
        &[],
        &Noise::typical(),
        26,
        &long_records(),
    );
    assert_named_set(&d, &["self-heating"]);
    let repeat = d
        .verdict
        .repeats
        .iter()
        .find(|r| r.significant())
        .expect("the warmer repeat differs beyond noise");
    assert!(repeat.change < 0.0, "{repeat:?}");
    assert_eq!(repeat.explained_by, Some("self-heating"));
    assert!(!d.verdict.specimen_changed());
}

#[test]
fn cyclic_softening_is_named_from_the_load_history_with_passages() {
    // Mullins: up to 8 % softer well below the largest load, over 25 kN (the generator's
    // law is exponential, the library's a tanh). The design raises the load preload by
    // preload, then runs lower loads; the rising passages at the end raise it again.
    let truth = Truth {
        mullins: Some((0.08, 25e3)),
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "mullins",
        &truth,
        &standard_design(),
        &Passage::rising(3),
        &Noise::typical(),
        27,
    );
    assert_named_alone(&d, "cyclic-softening");
    let Some(&Effect::CyclicSoftening {
        softening_limit,
        force_scale_n,
        max_force_n,
    }) = d.final_model.find("cyclic-softening")
    else {
        panic!()
    };
    assert!(
        (0.04..0.16).contains(&softening_limit),
        "d = {softening_limit}"
    );
    assert!(
        (10e3..60e3).contains(&force_scale_n),
        "F_s = {force_scale_n}"
    );
    assert_eq!(max_force_n, 0.0, "the model describes the virgin specimen");
}

/// The standard design in the order of its largest load (preload + amplitude, ascending):
/// no test runs below a load reached before it, so the load history across tests cannot
/// show a Mullins effect.
fn rising_load_design() -> Vec<TestPoint> {
    let mut design = standard_design();
    design.sort_by(|a, b| (a.preload_n + a.amplitude_n).total_cmp(&(b.preload_n + b.amplitude_n)));
    design
}

/// A fifth of the typical noise: a single cycle's dynamic stiffness to about 0.2 %
/// (with the typical noise, about 1 %, the first cycle's 1-2 % change under this Mullins
/// truth is not 5 sigma in any one record).
fn quiet_noise() -> Noise {
    scaled_noise(0.2)
}

/// The typical noise, every level times `factor`.
fn scaled_noise(factor: f64) -> Noise {
    let n = Noise::typical();
    Noise {
        white_force: factor * n.white_force,
        white_displacement: factor * n.white_displacement,
        coloured_force: factor * n.coloured_force,
        drift_force: factor * n.drift_force,
        ..n
    }
}

/// A named effect's parameter in the final model (its model-file key).
fn final_param(d: &Diagnosis, kind: EffectKind, key: &str) -> f64 {
    fastemu::ident::diagnose::effect_params(&d.final_model, kind)
        .iter()
        .find(|(k, _)| *k == key)
        .unwrap_or_else(|| panic!("{} has no {key}", kind.name()))
        .1
}

/// Records from rest at the preload, start-up included.
fn from_rest() -> Acquisition {
    Acquisition {
        from_rest: true,
        ..Acquisition::typical()
    }
}

#[test]
fn cyclic_softening_is_named_from_the_first_cycles_of_records_from_rest() {
    // Every test raises the largest load: only the first cycles of each record, its virgin
    // loading, against its steady cycles below it show the softening.
    let truth = Truth {
        mullins: Some((0.08, 25e3)),
        ..Truth::paper_like()
    };
    let design = rising_load_design();
    let (without, none) = diagnose_case_split(
        "mullins-rest-steady-only",
        &truth,
        &design,
        &[],
        &quiet_noise(),
        27,
        &from_rest(),
        false,
    );
    assert!(none.is_empty());
    // Without the first cycles the load history cannot show it: not identifiable.
    assert!(
        !names(&without).contains(&"cyclic-softening"),
        "without first cycles: {:?}",
        names(&without)
    );
    let reason = without
        .not_tried
        .iter()
        .find(|n| n.kind == EffectKind::CyclicSoftening && n.not_identifiable)
        .map(|n| n.reason.clone());
    eprintln!("[mullins-rest-steady-only] cyclic-softening: {reason:?}");
    assert!(
        reason.is_some(),
        "cyclic-softening not listed as not identifiable"
    );
    let (d, used) = diagnose_case_split(
        "mullins-rest",
        &truth,
        &design,
        &[],
        &quiet_noise(),
        27,
        &from_rest(),
        true,
    );
    assert!(names(&d).contains(&"cyclic-softening"), "{:?}", names(&d));
    assert!(used.len() >= 3, "first cycles used: {used:?}");
    assert!(
        used.iter().all(|u| u.relative_change > 5.0 * u.noise_sigma),
        "{used:?}"
    );
    assert!(
        d.gap_before >= 3.0 * d.gap_after,
        "gap {:.3e} -> {:.3e}",
        d.gap_before,
        d.gap_after
    );
    let Some(&Effect::CyclicSoftening {
        softening_limit,
        force_scale_n,
        ..
    }) = d.final_model.find("cyclic-softening")
    else {
        panic!()
    };
    eprintln!("[mullins-rest] d = {softening_limit}, F_s = {force_scale_n}");
    assert!(
        (0.04..0.16).contains(&softening_limit),
        "d = {softening_limit}"
    );
    assert!(
        (10e3..60e3).contains(&force_scale_n),
        "F_s = {force_scale_n}"
    );
}

#[test]
fn records_from_rest_without_a_hidden_effect_name_nothing() {
    // The start-up transient of the Maxwell branch is the model's own: whether or not the
    // first cycles are split off, it must not raise an alarm.
    let (d, used) = diagnose_case_split(
        "null-rest",
        &Truth::paper_like(),
        &rising_load_design(),
        &[],
        &quiet_noise(),
        31,
        &from_rest(),
        true,
    );
    eprintln!("[null-rest] {} records' first cycles used", used.len());
    assert!(d.named.is_empty(), "named {:?}", names(&d));
    assert!(
        d.verdict.unexplained.is_none(),
        "unexplained {:?}",
        d.verdict.unexplained
    );
}

/// Two at once, new effects beside older ones: self-heating beside amplitude friction (both
/// grow with amplitude; heat also with frequency and with the tests before) and a
/// load-train resonance beside a temperature shift. (Beside a channel delay or a moving
/// mass a resonance well above the test band is not separable: its phase is a delay's and
/// its frequency-squared term a mass's to first order; see docs/diagnose.md.)
#[test]
fn self_heating_beside_friction_and_a_resonance_beside_a_temperature_shift_are_both_named() {
    let acquisition = long_records();
    let heating = Truth {
        self_heating: Some((6.0, 0.05, 0.01)),
        rest_s: Some(10.0),
        friction: Some((20e6, 1.0e3)),
        ..Truth::paper_like()
    };
    let d = diagnose_case_with(
        "heating-friction",
        &heating,
        &standard_design(),
        &[],
        &Noise::typical(),
        28,
        &acquisition,
    );
    assert_named_set(&d, &["amplitude-friction", "self-heating"]);
    // The heating's parameters come with 95 % intervals the data determine, and its
    // memory is the truth's (C / h = 120 s) within 2x: a 1 K start alone once settled on
    // a memory of a second beside friction (the blind weak-heating campaign).
    let heat = heating_intervals(&d);
    let tau = heat[0].value / heat[1].value;
    assert!(heat.iter().all(|i| i.determined()), "{heat:?}");
    assert!((60.0..240.0).contains(&tau), "tau {tau} s: {heat:?}");
    let resonance = Truth {
        load_path_resonance: Some((90.0, 0.04)),
        wlf: Some((2.0, 80.0, 23.0, 0.005)),
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "resonance-temperature",
        &resonance,
        &standard_design(),
        &[],
        &Noise::typical(),
        29,
    );
    assert_named_set(&d, &["load-train-resonance", "temperature-shift"]);
}

/// The named `self-heating`'s parameter intervals (heat capacity, heat transfer), each
/// checked to exist (the fit is not singular).
fn heating_intervals(d: &Diagnosis) -> Vec<fastemu::ident::fit::ParamInterval> {
    let heat = d
        .final_template
        .effect_intervals(&d.final_cv, EffectKind::SelfHeating);
    let names: Vec<&str> = heat.iter().map(|i| i.name).collect();
    assert_eq!(names, ["heat_capacity_j_per_k", "heat_transfer_w_per_k"]);
    for i in &heat {
        assert!(i.ci95.is_some(), "no interval: {i:?}");
    }
    heat
}

/// A thermal memory far shorter than a record (2 s against 20 s records), where a rule of
/// thumb would say only `h` can be measured: the warming within each record shows `C`
/// too, and both 95 % intervals hold the truth (as the fit's default law, -0.8 %/K, sees
/// the truth's -1 %/K: `C` and `h` times 0.8), each within a factor of 10, so the report
/// claims no parameter is undetermined.
#[test]
fn a_short_thermal_memory_is_measured_with_intervals_that_hold_the_truth() {
    let truth = Truth {
        self_heating: Some((2.0, 1.0, 0.01)),
        rest_s: Some(10.0),
        ..Truth::paper_like()
    };
    let d = diagnose_case_with(
        "short-thermal-memory",
        &truth,
        &standard_design(),
        &[],
        &Noise::typical(),
        32,
        &long_records(),
    );
    assert_named_set(&d, &["self-heating"]);
    let heat = heating_intervals(&d);
    for (interval, truth) in heat.iter().zip([2.0 * 0.8, 1.0 * 0.8]) {
        let (lo, hi) = interval.ci95.expect("interval");
        assert!(lo <= truth && truth <= hi, "truth {truth}: {interval:?}");
        assert!(interval.determined(), "{interval:?}");
    }
    let named = d
        .rounds
        .iter()
        .flatten()
        .find(|c| c.kind == EffectKind::SelfHeating && c.qualifies)
        .expect("the named self-heating's candidate");
    assert_eq!(named.law_note, None, "no claim that C is unmeasured");
}

/// Self-heating beside a chamber-temperature law that moves the modulus only (no
/// relaxation-time shift: the edge of its range). The free fit of `temperature-shift`
/// lands just below 0 there; the variant held on the bound is physical and is kept, so
/// both are named and the model file says the relaxation times do not shift.
#[test]
fn self_heating_beside_a_modulus_only_temperature_law_is_named_with_the_shift_on_its_bound() {
    let truth = Truth {
        self_heating: Some((5.0, 0.025, 0.015)),
        rest_s: Some(10.0),
        wlf: Some((0.0, 80.0, 23.0, 0.015)),
        ..Truth::paper_like()
    };
    let d = diagnose_case_with(
        "heating-modulus-only-temperature",
        &truth,
        &standard_design(),
        &[],
        &Noise::typical(),
        31,
        &long_records(),
    );
    assert_named_set(&d, &["self-heating", "temperature-shift"]);
    let Some(&Effect::TemperatureShift {
        log10_time_shift_per_c,
        ln_modulus_shift_per_c,
        ..
    }) = d.final_model.find("temperature-shift")
    else {
        panic!("no temperature-shift in {:?}", d.final_model.effects)
    };
    let shift = (log10_time_shift_per_c, ln_modulus_shift_per_c);
    assert_eq!(shift.0, 0.0);
    assert!((shift.1 - 0.015).abs() < 0.003, "{shift:?}");
}

#[test]
fn a_repeated_first_test_checks_drift_directly() {
    let truth = Truth {
        softening_over_campaign: 0.03,
        ..Truth::paper_like()
    };
    let mut design = standard_design();
    design.push(design[7]);
    let d = diagnose_case("repeat", &truth, &design, &[], &Noise::typical(), 24);
    let repeat = d.verdict.repeats.first().expect("one repeated test");
    assert!(repeat.significant() && repeat.change < 0.0, "{repeat:?}");
    assert!(d.verdict.specimen_changed());
}

#[test]
fn a_load_cell_nonlinearity_is_not_passed_off_as_explained() {
    let truth = Truth {
        force_sensor_cubic: 0.15,
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "sensor",
        &truth,
        &standard_design(),
        &Passage::rising(2),
        &Noise::typical(),
        25,
    );
    // Whatever the library names, its parameters are physical, and what it cannot
    // explain is said.
    assert_physical(&d);
    assert!(d.verdict.unexplained.is_some(), "named {:?}", names(&d));
}

/// A cubic spring whose coefficient drifts over the campaign (stiffening turning into
/// softening: beyond the library) is partly described by several library effects: an
/// independent check saw `cyclic-softening` named at a 2.1x gap shrink beside a residual
/// 2.2x the noise floor. Whatever describes only part of it is not named: the residual is
/// reported unexplained with nothing named, and the take-back says why (at typical noise
/// and at a third of it, so that both of its conditions act).
#[test]
fn a_drifting_cubic_spring_is_reported_unexplained_not_named_after_a_stand_in() {
    let truth = Truth {
        cubic_spring: Some((1.5e12, 4e-4, -2.0)),
        rest_s: Some(10.0),
        ..Truth::paper_like()
    };
    let mut why = Vec::new();
    // At typical noise the stand-in leaves nothing beyond noise (it is taken back as the
    // only effect named); at a third of it, a residual beyond noise stays beside it.
    for (noise, seed) in [
        (Noise::typical(), 61),
        (Noise::typical(), 62),
        (scaled_noise(0.3), 61),
    ] {
        let d = diagnose_case(
            "cubic-drift",
            &truth,
            &standard_design(),
            &Passage::rising(3),
            &noise,
            seed,
        );
        let stand_ins: Vec<&str> = d
            .rounds
            .iter()
            .flatten()
            .filter(|c| c.stand_in.is_some())
            .map(|c| c.kind.name())
            .collect();
        eprintln!(
            "[cubic-drift {seed}] named {:?}, stand-ins {stand_ins:?}, gap {:.3e} -> {:.3e}, unexplained {}",
            names(&d),
            d.gap_before,
            d.gap_after,
            d.verdict.unexplained.is_some()
        );
        assert!(names(&d).is_empty(), "seed {seed}: named {:?}", names(&d));
        assert!(d.verdict.unexplained.is_some(), "seed {seed}");
        why.extend(d.rounds.iter().flatten().filter_map(|c| c.stand_in.clone()));
    }
    // The rule acted, by both of its conditions: without it a stand-in would have been
    // named.
    assert!(
        why.iter().any(|w| w.contains("was the only effect named")),
        "{why:?}"
    );
    assert!(why.iter().any(|w| w.contains("left a residual")), "{why:?}");
}

/// Every effect of the final model inside what physics allows (checked here from the
/// physics, not with the library's own ranges): no negative mass, stiffness, slip force
/// or damping; exponents in (0, 1]; a delay of at most a few ms; relaxation that speeds
/// up as the elastomer warms.
/// `name` is the one effect named, with physical parameters, the gap at least 3x smaller
/// and nothing left unexplained.
fn assert_named_alone(d: &Diagnosis, name: &str) {
    assert_named_set(d, &[name]);
    assert!(d.verdict.unexplained.is_none());
}

/// Exactly the effects `expected` (sorted) are named, with physical parameters, and the gap
/// is at least 3x smaller.
fn assert_named_set(d: &Diagnosis, expected: &[&str]) {
    let mut named = names(d);
    named.sort();
    assert_eq!(named, expected);
    assert_physical(d);
    assert!(
        d.gap_before / d.gap_after >= 3.0,
        "{} -> {}",
        d.gap_before,
        d.gap_after
    );
}

/// Records long enough for a specimen to warm within them: 20 cycles below 2 Hz, 60 above.
fn long_records() -> Acquisition {
    Acquisition {
        cycles_below_2_hz: 20,
        cycles_above_2_hz: 60,
        ..Acquisition::typical()
    }
}

fn assert_physical(d: &Diagnosis) {
    for e in &d.final_model.effects {
        let ok = match *e {
            Effect::MovingMass { mass_kg } => mass_kg >= 0.0,
            Effect::ChannelDelay { force_lag_s } => force_lag_s.abs() <= 5e-3,
            Effect::AmplitudeFriction {
                stiffness_n_per_m,
                slip_force_n,
                ..
            } => stiffness_n_per_m >= 0.0 && slip_force_n >= 0.0,
            Effect::FractionalDamping {
                coefficient_ns_alpha_per_m,
                alpha,
                ..
            } => coefficient_ns_alpha_per_m >= 0.0 && alpha > 0.0 && alpha <= 1.0,
            Effect::TemperatureShift {
                log10_time_shift_per_c,
                ..
            } => log10_time_shift_per_c >= 0.0,
            Effect::PreloadStiffening { chi, p0_n } => chi >= 0.0 && p0_n.is_finite(),
            // Independent of the library's ranges: a load train's first mode above the test
            // band's slowest tests and below 5 kHz, damped like a structure (< 30 %).
            Effect::LoadTrainResonance {
                natural_frequency_hz,
                damping_ratio,
            } => {
                (10.0..=5000.0).contains(&natural_frequency_hz)
                    && damping_ratio > 0.0
                    && damping_ratio <= 0.3
            }
            Effect::SpecimenDrift { rate_per_unit, .. } => rate_per_unit.is_finite(),
            // A pad's heat capacity (grams to a 100 kg block) and heat transfer (still air to
            // water-cooled steel).
            Effect::SelfHeating {
                heat_capacity_j_per_k,
                heat_transfer_w_per_k,
                ..
            } => {
                (1.0..=1e6).contains(&heat_capacity_j_per_k)
                    && (1e-3..=1e3).contains(&heat_transfer_w_per_k)
            }
            // Mullins softening of a filled elastomer: below 60 % far under its largest
            // load, setting in over tens of newtons to a meganewton.
            Effect::CyclicSoftening {
                softening_limit,
                force_scale_n,
                ..
            } => (0.0..=0.6).contains(&softening_limit) && (10.0..=1e6).contains(&force_scale_n),
        };
        assert!(ok, "unphysical {e:?}");
    }
}

#[test]
fn null_campaigns_with_passages_name_nothing_and_leave_nothing_unexplained() {
    let d = diagnose_case(
        "null-passages",
        &Truth::paper_like(),
        &standard_design(),
        &Passage::rising(3),
        &Noise::typical(),
        26,
    );
    assert!(d.named.is_empty(), "named {:?}", names(&d));
    assert!(d.verdict.unexplained.is_none());
    assert!(!d.verdict.specimen_changed());
}

/// The false-alarm rate of the verdicts on null campaigns (the library explains the truth:
/// only the baseline's parameters are off): 60 campaigns, white noise alone, the typical
/// white + coloured + drifting noise, and loud coloured noise, half of them with passages.
/// A false alarm is any named effect, an unexplained residual, or a changed specimen.
/// No alarm in 59 or more campaigns bounds the rate below 5 % at 95 % confidence
/// (0.95^59 < 0.05). About 100 s on two cores (measured 98 s with another build running).
#[test]
fn null_campaigns_false_alarm_rate_below_5_percent_at_95_percent_confidence() {
    let white = Noise {
        coloured_force: 0.0,
        drift_force: 0.0,
        ..Noise::typical()
    };
    let loud = Noise {
        white_force: 0.02,
        white_displacement: 0.02,
        coloured_force: 0.03,
        coloured_rho: 0.99,
        drift_force: 0.02,
    };
    let mut alarms = Vec::new();
    let n = 60;
    for k in 0..n {
        let (label, noise) = match k % 3 {
            0 => ("white", white),
            1 => ("typical", Noise::typical()),
            _ => ("loud", loud),
        };
        let passages = if k % 2 == 0 {
            Passage::rising(3)
        } else {
            Vec::new()
        };
        let name = format!("null-{label}-{k}");
        let d = diagnose_case(
            &name,
            &Truth::paper_like(),
            &standard_design(),
            &passages,
            &noise,
            5000 + k as u64,
        );
        if !d.named.is_empty() || d.verdict.unexplained.is_some() || d.verdict.specimen_changed() {
            alarms.push(name);
        }
    }
    eprintln!("FALSE ALARMS {}/{n}: {alarms:?}", alarms.len());
    assert!(
        alarms.is_empty(),
        "false alarms {}/{n}: {alarms:?} (none allowed for the 5 % bound at 95 %)",
        alarms.len()
    );
}

/// A rig artefact beside another effect, where greedy selection once went wrong: the
/// springpot took the phase of a displacement channel 0.5 ms late, and the resonance beside
/// it then fitted only with zero damping (nothing more named); the skew's apparent loop area
/// was taken for heat, so self-heating beside it fitted a wrong thermal circuit and was not
/// named. Each pair must be named, with the skew, the mode and the circuit physical.
#[test]
fn a_channel_skew_beside_a_resonance_or_self_heating_is_named_with_it() {
    let resonance = Truth {
        load_path_resonance: Some((90.0, 0.04)),
        force_lag_s: -0.5e-3,
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "resonance-skew",
        &resonance,
        &standard_design(),
        &Passage::rising(3),
        &Noise::typical(),
        31,
    );
    assert_named_set(&d, &["channel-delay", "load-train-resonance"]);
    let fn_hz = final_param(&d, EffectKind::LoadTrainResonance, "natural_frequency_hz");
    let zeta = final_param(&d, EffectKind::LoadTrainResonance, "damping_ratio");
    let lag = final_param(&d, EffectKind::ChannelDelay, "force_lag_s");
    // The mode's phase below it (2 zeta / w_n, 0.14 ms here) trades against the skew: the
    // two are told apart by the history tests' band, within a fifth of the skew.
    assert!((fn_hz - 90.0).abs() < 4.5, "natural frequency {fn_hz}");
    assert!(
        (0.02..0.1).contains(&zeta),
        "damping ratio {zeta} (lag {lag})"
    );
    assert!(
        (lag + 0.5e-3).abs() < 0.1e-3,
        "force lag {lag} (damping ratio {zeta})"
    );

    let heating = Truth {
        self_heating: Some((6.0, 0.05, 0.01)),
        rest_s: Some(10.0),
        force_lag_s: -0.5e-3,
        ..Truth::paper_like()
    };
    let d = diagnose_case_with(
        "heating-skew",
        &heating,
        &standard_design(),
        &[],
        &Noise::typical(),
        32,
        &long_records(),
    );
    assert_named_set(&d, &["channel-delay", "self-heating"]);

    // The force channel late instead, by more than the element's loss angle at the top
    // of the band (0.3 ms is 2.2 degrees at 20 Hz): those records show a negative loop
    // area, which was clamped to zero before the lag's correction, so the model heated by
    // the correction alone and self-heating was never named beside it (2026-11-28, a
    // helper's blind campaigns and `synth-campaign --hidden self-heating+channel-delay`).
    let heating = Truth {
        force_lag_s: 0.3e-3,
        ..heating
    };
    let d = diagnose_case_with(
        "heating-lag",
        &heating,
        &standard_design(),
        &[],
        &Noise::typical(),
        33,
        &long_records(),
    );
    assert_named_set(&d, &["channel-delay", "self-heating"]);
    let lag = final_param(&d, EffectKind::ChannelDelay, "force_lag_s");
    assert!((lag - 0.3e-3).abs() < 0.03e-3, "force lag {lag}");
}

/// A moving mass beside a load-train resonance: below the mode both add a force rising
/// with frequency squared, so once the resonance is named what the mass leaves is under
/// the 0.1 % materiality floor, yet without it the mode comes out 15 % too high. A
/// candidate that passes every other part of the naming rule and moves a named effect's
/// parameters by more than 5 % is named, and the report says why.
#[test]
fn a_small_moving_mass_that_moves_a_named_resonance_is_named_with_it() {
    let truth = Truth {
        load_path_resonance: Some((90.0, 0.04)),
        mass_kg: 40.0,
        ..Truth::paper_like()
    };
    // A lab's good acquisition (the blind generator's level, noise floor ~1e-5): with the
    // typical noise here the mass's remainder is at the noise floor and nothing more can
    // be said.
    let very_quiet = scaled_noise(0.02);
    let d = diagnose_case(
        "resonance-mass",
        &truth,
        &standard_design(),
        &Passage::rising(3),
        &very_quiet,
        33,
    );
    assert_named_set(&d, &["load-train-resonance", "moving-mass"]);
    let fn_hz = final_param(&d, EffectKind::LoadTrainResonance, "natural_frequency_hz");
    let mass = final_param(&d, EffectKind::MovingMass, "mass_kg");
    assert!(
        (fn_hz - 90.0).abs() < 4.5,
        "natural frequency {fn_hz} (mass {mass})"
    );
    assert!(
        (30.0..50.0).contains(&mass),
        "mass {mass} (natural frequency {fn_hz})"
    );
}

/// A stiff load train with a heavy participating mass (180 Hz, 3 %, 60 kg: an independent
/// check's case): within 1-20 Hz it is, to second order in f / f_n, a force lag of
/// 2 zeta / omega_n (53 us) and a mass of 60 kg less K / omega_n^2. Named as the mode with
/// its mass, or as that lag and mass with the doubt said on the second of the pair (the
/// mode family the pair stands for, containing the truth, and the mode refitted in the
/// pair's place with how it compares); never the pair in silence.
#[test]
fn a_heavy_load_train_is_named_or_its_lag_and_mass_say_they_may_be_one() {
    let truth = Truth {
        load_path_resonance: Some((180.0, 0.03)),
        mass_kg: 60.0,
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "heavy-load-train",
        &truth,
        &standard_design(),
        &Passage::rising(3),
        &Noise::typical(),
        34,
    );
    let named = names(&d);
    if named.contains(&"load-train-resonance") {
        let fn_hz = final_param(&d, EffectKind::LoadTrainResonance, "natural_frequency_hz");
        assert!((fn_hz - 180.0).abs() < 18.0, "natural frequency {fn_hz}");
        return;
    }
    assert_named_set(&d, &["channel-delay", "moving-mass"]);
    let note = d
        .rounds
        .iter()
        .flatten()
        .filter(|c| c.qualifies)
        .filter_map(|c| c.law_note.clone())
        .find(|n| n.contains("not told from a load-train resonance"))
        .unwrap_or_else(|| {
            let qualified: Vec<_> = d
                .rounds
                .iter()
                .flatten()
                .filter(|c| c.qualifies)
                .map(|c| (c.round, c.kind.name(), c.law_note.clone()))
                .collect();
            panic!(
                "the pair named without the doubt: {named:?}, lag {} s, mass {} kg; {qualified:?}",
                final_param(&d, EffectKind::ChannelDelay, "force_lag_s"),
                final_param(&d, EffectKind::MovingMass, "mass_kg")
            )
        });
    // The family: f_n from zeta / (pi tau) over zeta 0.001-0.3, above 3x the highest test
    // frequency; it must hold the truth's 180 Hz.
    let lag = final_param(&d, EffectKind::ChannelDelay, "force_lag_s");
    let f_at_3pct = 0.03 / (std::f64::consts::PI * lag);
    assert!(
        (140.0..230.0).contains(&f_at_3pct),
        "the lag {lag} s puts a 3 % mode at {f_at_3pct} Hz: {note}"
    );
    // The mode refitted in the pair's place (started at 140 and 460 Hz of the family) and
    // what it says of the two: the truth's mode within a fifth.
    eprintln!("[heavy-load-train] {note}");
    let refitted = note
        .split("refitted in the pair's place, a mode at ")
        .nth(1)
        .unwrap_or_else(|| panic!("no refit in the note: {note}"));
    let f_n: f64 = refitted
        .split(" Hz")
        .next()
        .and_then(|x| x.parse().ok())
        .unwrap_or_else(|| panic!("refit: {refitted}"));
    assert!(
        (144.0..216.0).contains(&f_n),
        "refitted mode {f_n} Hz: {note}"
    );
    assert!(
        refitted.contains("cannot tell the two apart") || refitted.contains("point at the mode"),
        "{refitted}"
    );
}

/// A springpot has one order at every frequency. At a noise floor of about 1e-4 (the
/// issue's blind campaigns), a second, discrete Maxwell branch (outside the library) fits
/// as a springpot of order near 1 on the low test frequencies and 0.7 on the high ones,
/// and one order for both costs beyond 3 standard errors: it is not named
/// `fractional-damping` (nothing stands in for it), and the residual is reported as
/// unexplained. A springpot beside a channel skew is named with the skew, and a springpot
/// alone as before.
#[test]
fn a_discrete_relaxation_is_not_named_a_springpot_but_a_springpot_is() {
    let branch = Truth {
        second_maxwell: Some((6e6, 2e-3)),
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "maxwell2",
        &branch,
        &standard_design(),
        &[],
        &scaled_noise(0.05),
        41,
    );
    assert!(
        !names(&d).contains(&"fractional-damping"),
        "named {:?}",
        names(&d)
    );
    assert!(d.verdict.unexplained.is_some(), "named {:?}", names(&d));
    let broken = d
        .rounds
        .iter()
        .flatten()
        .find(|c| c.kind == EffectKind::FractionalDamping && c.law_broken.is_some());
    assert!(broken.is_some(), "the springpot's law was not found broken");

    let springpot_skew = Truth {
        springpot: Some((7e5, 0.3)),
        force_lag_s: -0.4e-3,
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "springpot-skew",
        &springpot_skew,
        &standard_design(),
        &[],
        &scaled_noise(0.05),
        42,
    );
    assert_named_set(&d, &["channel-delay", "fractional-damping"]);
    let alpha = final_param(&d, EffectKind::FractionalDamping, "alpha");
    assert!((alpha - 0.3).abs() < 0.05, "alpha {alpha}");

    let springpot = Truth {
        springpot: Some((7e5, 0.45)),
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "springpot-45",
        &springpot,
        &standard_design(),
        &[],
        &scaled_noise(0.05),
        43,
    );
    assert_named_alone(&d, "fractional-damping");
}

/// A weak second Maxwell branch whose corner (80 Hz) lies above the tested band looks
/// like a springpot of order ~0.8 within it, and its one order holds across the band (the
/// order test passes). Its discrete rival, a Maxwell branch fitted in the springpot's
/// place, fits better, so nothing is named, the residual is reported unexplained, and the
/// reason names the branch with its time constant (the truth's 2 ms within 15 %). (Before
/// the rival, both were named `fractional-damping`, 0.79 and 0.77.) A springpot of order
/// 0.55 is still named: its rival fits it far worse. With 20 times the noise the data do
/// not tell the two apart: a springpot is named with a note that says so.
#[test]
fn a_weak_discrete_relaxation_is_told_from_a_springpot_by_its_rival() {
    for (k, seed) in [(1e6, 108), (2e6, 109)] {
        let truth = Truth {
            second_maxwell: Some((k, 2e-3)),
            ..Truth::paper_like()
        };
        let d = diagnose_case(
            "weak-maxwell2",
            &truth,
            &standard_design(),
            &[],
            &scaled_noise(0.05),
            seed,
        );
        assert!(names(&d).is_empty(), "{k}: named {:?}", names(&d));
        assert!(d.verdict.unexplained.is_some(), "{k}: nothing unexplained");
        let why = d
            .rounds
            .iter()
            .flatten()
            .filter(|c| c.kind == EffectKind::FractionalDamping)
            .find_map(|c| c.law_broken.clone())
            .expect("the springpot's rival reported");
        let tau_ms: f64 = why
            .split(" N/m, ")
            .nth(1)
            .and_then(|t| t.split(" ms").next())
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("{why}"));
        assert!(why.contains("discrete relaxation"), "{why}");
        assert!((tau_ms / 2.0 - 1.0).abs() < 0.15, "{k}: {why}");
    }
    let springpot = Truth {
        springpot: Some((1e5, 0.55)),
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "springpot-055",
        &springpot,
        &standard_design(),
        &[],
        &scaled_noise(0.05),
        110,
    );
    assert_named_alone(&d, "fractional-damping");
    let alpha = final_param(&d, EffectKind::FractionalDamping, "alpha");
    assert!((alpha - 0.55).abs() < 0.05, "{alpha}");
    let noisy = Truth {
        springpot: Some((7e5, 0.3)),
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "springpot-noisy",
        &noisy,
        &standard_design(),
        &[],
        &scaled_noise(1.0),
        104,
    );
    assert_named_alone(&d, "fractional-damping");
    let note = d
        .rounds
        .iter()
        .flatten()
        .find(|c| c.kind == EffectKind::FractionalDamping && c.qualifies)
        .and_then(|c| c.law_note.clone())
        .unwrap_or_default();
    assert!(
        note.contains("not told from a discrete relaxation"),
        "note: {note}"
    );
}

/// A lead of the force channel adds loss rising with frequency, as a second Maxwell branch
/// (beyond the library) does below its corner: at typical noise a 2 MN/m, 2 ms branch was
/// named `channel-delay` on two seeds of three, with nothing said. The delay now meets the
/// branch fitted in its place: refused where the branch fits better (a 6 MN/m branch),
/// else named with the note that these tests do not tell the two apart (2 MN/m), or taken
/// back as a stand-in where it was the only effect named and shrank the gap less than 3x
/// (since 2026-11-27; one 2 MN/m seed). A true channel lead (preload-dependent, as the
/// element's modulus is) is named without any of these.
#[test]
fn a_channel_lead_a_discrete_relaxation_imitates_is_refused_or_named_with_the_doubt() {
    let mut refused = 0;
    let mut noted = 0;
    let mut taken_back = 0;
    for (k, seed) in [(2e6, 201), (2e6, 204), (6e6, 108)] {
        let truth = Truth {
            second_maxwell: Some((k, 2e-3)),
            ..Truth::paper_like()
        };
        let d = diagnose_case(
            "maxwell2-typical",
            &truth,
            &standard_design(),
            &[],
            &Noise::typical(),
            seed,
        );
        let delay = d
            .rounds
            .iter()
            .flatten()
            .find(|c| c.kind == EffectKind::ChannelDelay && c.would_qualify)
            .unwrap_or_else(|| panic!("seed {seed}: the delay did not stand in"));
        if names(&d).contains(&"channel-delay") {
            let note = delay.law_note.clone().unwrap_or_default();
            assert!(
                note.contains("not told from a discrete relaxation"),
                "seed {seed}: named without the doubt: {note:?}"
            );
            noted += 1;
        } else if let Some(why) = &delay.law_broken {
            assert!(
                why.contains("discrete relaxation rather"),
                "seed {seed}: {why}"
            );
            refused += 1;
        } else if let Some(why) = &delay.stand_in {
            assert!(why.contains("do not establish"), "seed {seed}: {why}");
            taken_back += 1;
        }
    }
    assert_eq!((noted + taken_back, refused), (2, 1));

    let lead = Truth {
        force_lag_s: -0.5e-3,
        ..Truth::paper_like()
    };
    let d = diagnose_case(
        "channel-lead",
        &lead,
        &standard_design(),
        &[],
        &Noise::typical(),
        33,
    );
    assert_named_alone(&d, "channel-delay");
    let lag = final_param(&d, EffectKind::ChannelDelay, "force_lag_s");
    assert!((lag + 0.5e-3).abs() < 0.05e-3, "force lag {lag}");
    let delay = d
        .rounds
        .iter()
        .flatten()
        .find(|c| c.kind == EffectKind::ChannelDelay && c.qualifies)
        .expect("the delay qualified");
    assert!(
        delay.law_broken.is_none() && delay.law_note.is_none(),
        "{:?}",
        delay.law_note
    );
}
