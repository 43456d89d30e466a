//! The compensation plan from the declared actuator: the lead stable for most of the
//! actuators within `actuator_tolerance`, where the run starts, and the file the launcher
//! leaves it in for the controller. Must not: run anything or touch the loop.

use super::*;
use crate::hil::report::span;

/// The step of `LinearLoop::stable_leads`' scan, s.
pub const LEAD_STEP_S: f64 = 10e-6;

/// How many actuators the plan and the check draw: the declared one and the others.
pub const TOLERANCE_DRAWS: usize = 24;

/// The step of the plan's lead scan, s (a fifth of the narrowest servo-hydraulic window
/// of stable leads seen, 0.25 ms, and a quarter of the 10 us scans' cost).
pub const PLAN_LEAD_STEP_S: f64 = 50e-6;

/// The seed stream of the draws: its own, so that the scan describes the tolerance, not
/// the rig's one draw (`perturb_seed`), which fastemu is never told.
const TOLERANCE_SEED_BASE: u64 = 0x701E_5CA7_0000;

/// The declared actuator (`[rig.actuator]`, nominal) and `draws - 1` others with each
/// parameter within `[compensation] actuator_tolerance` of it (none when that is 0), each
/// with its controller tuned on the declared one, as the rig's is.
fn tolerance_draws(cfg: &HilConfig, draws: usize) -> Vec<ActuatorPlant> {
    let nominal = cfg.rig.actuator.nominal;
    let tolerance = cfg.compensation.actuator_tolerance;
    let draws = if tolerance > 0.0 { draws.max(1) } else { 1 };
    (0..draws)
        .map(|i| {
            let truth = if i == 0 {
                nominal
            } else {
                nominal.perturbed(tolerance, TOLERANCE_SEED_BASE + i as u64)
            };
            ActuatorPlant::new(&truth, &nominal)
        })
        .collect()
}

/// `f` over `items` on two threads, in order.
fn on_two_threads<T: Sync, R: Send>(items: &[T], f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    let half = items.len().div_ceil(2);
    std::thread::scope(|scope| {
        let second = scope.spawn(|| items[half..].iter().map(&f).collect::<Vec<_>>());
        let mut out: Vec<R> = items[..half].iter().map(&f).collect();
        out.extend(second.join().expect("a scan thread"));
        out
    })
}

/// The leads the linearised loop is stable with over the declared actuator and others
/// within its tolerance (`tolerance_draws`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ToleranceScan {
    /// The tolerance, a fraction of each parameter (`[compensation] actuator_tolerance`).
    pub tolerance: f64,
    /// The step of the scan, us.
    pub step_us: f64,
    /// Each drawn actuator's stable leads (first, last), us, the declared one first;
    /// `None`: no lead.
    pub windows_us: Vec<Option<(f64, f64)>>,
    /// The leads stable for every drawn actuator (first, last), us; `None`: no lead is.
    pub common_us: Option<(f64, f64)>,
    /// Among the leads stable for the declared actuator, the one stable for the most drawn
    /// actuators (the middle grid point of the first run of leads that tie), us, and for
    /// how many; `None` when no lead is stable for the declared one.
    pub most_widely_stable: Option<(f64, usize)>,
    /// How many drawn actuators the starting lead is stable for.
    pub starting_lead_stable_for: usize,
}

/// `tolerance_draws` and the leads (`step_s` apart, up to `max_delay_us`) with which the
/// linearised loop is stable for each and for all; `starting_lead_s` is judged the same
/// way. Pure numbers, on two threads.
pub fn tolerance_scan(
    cfg: &HilConfig,
    starting_lead_s: f64,
    draws: usize,
    step_s: f64,
) -> ToleranceScan {
    let plants = tolerance_draws(cfg, draws);
    let max = cfg.compensation.max_delay_s;
    let n = (max / step_s).round() as usize;
    // (stable with the starting lead, stable with each lead of the scan), per draw.
    let scans = on_two_threads(&plants, |plant| {
        let lin = LinearLoop::for_plant(cfg, plant, starting_lead_s, 1.0);
        (lin.is_stable(0.0, 1.0), lin.stable_lead_map(max, step_s))
    });
    let draws = scans.len();
    let counts: Vec<usize> = (0..=n)
        .map(|i| scans.iter().filter(|(_, m)| m[i]).count())
        .collect();
    // Whole microseconds (the steps are), exact through the plan's JSON.
    let us = |i: usize| (i as f64 * step_s * 1e6).round();
    let window = |ok: &dyn Fn(usize) -> bool| {
        let first = (0..n + 1).position(ok)?;
        let last = (0..n + 1).rposition(ok)?;
        Some((us(first), us(last)))
    };
    let windows_us = scans.iter().map(|(_, m)| window(&|i| m[i])).collect();
    let common_us = window(&|i| counts[i] == draws);
    // Among the leads stable for the declared actuator (the first draw): the one stable
    // for most draws, the middle grid point of the first run of leads that tie.
    let declared = &scans[0].1;
    let eligible = |i: usize| if declared[i] { counts[i] } else { 0 };
    let best = (0..n + 1).map(eligible).max().unwrap_or(0);
    let most_widely_stable = (best > 0).then(|| {
        let first = (0..n + 1).position(|i| eligible(i) == best).unwrap_or(0);
        let run = (first..n + 1).take_while(|&i| eligible(i) == best).count();
        (us(first + (run - 1) / 2), best)
    });
    ToleranceScan {
        tolerance: cfg.compensation.actuator_tolerance,
        step_us: step_s * 1e6,
        windows_us,
        common_us,
        most_widely_stable,
        starting_lead_stable_for: scans.iter().filter(|(starts, _)| *starts).count(),
    }
}

/// What the controller runs with in front of the simulated rig's declared actuator
/// (`compensation_plan`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CompensationPlan {
    /// Actuators judged: the declared one and the others within the tolerance.
    pub draws: usize,
    pub tolerance: f64,
    /// The leads the adaptation may settle on, over all of them (the actuator's phase
    /// delay on the element from 1 Hz to the estimator's band, plus half a period of
    /// hold), us: lowest and highest.
    pub destinations_us: (f64, f64),
    /// How many of them are unstable at some lead of their own such range.
    pub destination_unstable_for: usize,
    /// True: the lead is fixed at `lead_us` and only the gain is learned.
    pub lead_fixed: bool,
    /// The lead the run starts with (fixed or not), us.
    pub lead_us: f64,
    /// How many drawn actuators `lead_us` is stable for.
    pub lead_stable_for: usize,
    /// Whether the passivity guard acts (false: its full damping at `lead_us` makes the
    /// declared actuator's loop unstable: through its lag the damping generates energy).
    pub guard: bool,
    /// The scan of leads, when the lead is fixed or the start moved (`start_moved_from_us`).
    pub scan: Option<ToleranceScan>,
    /// The lowest and highest effective delay (the mean phase delay over 1-20 Hz, plus half
    /// a period of hold, as the report identifies it) of the declared actuator and
    /// `DECLARATION_DRAWS` others within the tolerance, us: what the identified delay
    /// should lie near when the hardware is the declared actuator (`declaration_check`).
    #[serde(default)]
    pub effective_delays_us: Option<(f64, f64)>,
    /// With the lead fixed: where the controller may step it when the loop keeps
    /// oscillating (`compensation::LeadNudge`), from `nudge_range`; `None` when the
    /// frequencies a lead too short and one too long go unstable at do not separate.
    #[serde(default)]
    pub nudge: Option<NudgeRange>,
    /// The prediction order the run uses instead of `[compensation] lead_order`, which has
    /// no stable lead for the declared actuator (`raised_lead_order`); `None`: as
    /// configured.
    #[serde(default)]
    pub raised_lead_order: Option<u32>,
    /// With the lead fixed: for how many of the drawn actuators that lead is stable at the
    /// programme's lowest and highest load as well as at the preload (the element stiffens
    /// with its load; `LinearLoop::unstable_loads_n`), and the loads (N) at which it is
    /// not for the declared actuator.
    #[serde(default)]
    pub over_programme: Option<OverProgramme>,
    /// Without a fixed lead: the lead the run would have started at (the guess, capped),
    /// us, when that lead is stable for fewer than half of the drawn actuators and the plan
    /// starts the run at `lead_us` instead, the lead stable for most of them (and for the
    /// declared one); the adaptation takes the lead on from there. `None`: the run starts
    /// at the guess.
    #[serde(default)]
    pub start_moved_from_us: Option<f64>,
}

/// The planned lead over the programme's loads (`CompensationPlan::over_programme`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OverProgramme {
    pub stable_for: usize,
    pub declared_unstable_loads_n: Vec<f64>,
}

/// How far apart the frequencies of a lead too short and one too long must lie (the
/// highest of the first against the lowest of the second) for the nudge to tell them.
const NUDGE_SEPARATION: f64 = 2.0;

/// The planned fixed lead's nudge (`compensation::LeadNudge`) over `plants` and their
/// stable windows (`ToleranceScan::windows_us`): the leads from the lowest window's start
/// to the highest one's end, and the frequency between where a lead just below a window
/// and one just above it make the loop unstable (the linearised loop's thinnest
/// frequency there). `None` when those frequencies overlap (within `NUDGE_SEPARATION`) or
/// no window is known.
fn nudge_range(
    cfg: &HilConfig,
    plants: &[ActuatorPlant],
    windows_us: &[Option<(f64, f64)>],
    step_s: f64,
) -> Option<NudgeRange> {
    let edges = on_two_threads(
        &plants.iter().zip(windows_us).collect::<Vec<_>>(),
        |(plant, window)| {
            let (lo, hi) = window.map(|(a, b)| (a * 1e-6, b * 1e-6))?;
            let mut lin = LinearLoop::for_plant(cfg, plant, lo, 1.0);
            let short = (lo > step_s).then(|| {
                lin.lead_s = lo - step_s;
                lin.thinnest_frequency_hz()
            });
            let long = (hi + step_s <= cfg.compensation.max_delay_s).then(|| {
                lin.lead_s = hi + step_s;
                lin.thinnest_frequency_hz()
            });
            Some((lo, hi, short, long))
        },
    );
    let known: Vec<_> = edges.into_iter().flatten().collect();
    let low_s = known.iter().map(|e| e.0).fold(f64::INFINITY, f64::min);
    let high_s = known.iter().map(|e| e.1).fold(0.0, f64::max);
    let short_max = known.iter().filter_map(|e| e.2).fold(0.0, f64::max);
    let long_min = known
        .iter()
        .filter_map(|e| e.3)
        .fold(f64::INFINITY, f64::min);
    if known.is_empty() || !(short_max > 0.0 && long_min.is_finite()) {
        return None;
    }
    (long_min > NUDGE_SEPARATION * short_max).then(|| NudgeRange {
        low_s,
        high_s,
        split_hz: (short_max * long_min).sqrt(),
    })
}

/// How many actuators within the tolerance `declared_effective_delays_us` draws: the 24 of
/// the plan leave out much of the tolerance's spread (`fatigue-150kn`'s 24 span 1.8-3.6 ms
/// of effective delay, 3000 draws 1.5-7.2 ms, and the rig's own draw, seed 2, 5.1 ms).
const DECLARATION_DRAWS: u64 = 1000;

/// Its own seed stream.
const DECLARATION_SEED_BASE: u64 = 0xDEC1_A7ED_0000;

/// The lowest and highest effective delay (plus half a period of hold, us) of the declared
/// actuator and `DECLARATION_DRAWS` others within `actuator_tolerance`, on the stiffness
/// the rig's truth is recorded on (`actuator_truth.effective_delay_s`).
fn declared_effective_delays_us(cfg: &HilConfig) -> Option<(f64, f64)> {
    let nominal = cfg.rig.actuator.nominal;
    let tolerance = cfg.compensation.actuator_tolerance;
    let k = cfg
        .model
        .element
        .high_frequency_stiffness_n_per_m(cfg.scenario.preload_n);
    let hold = 0.5 * cfg.loop_.dt_s();
    let draws = if tolerance > 0.0 {
        DECLARATION_DRAWS
    } else {
        0
    };
    (0..=draws)
        .map(|i| {
            let truth = if i == 0 {
                nominal
            } else {
                nominal.perturbed(tolerance, DECLARATION_SEED_BASE + i)
            };
            (ActuatorPlant::new(&truth, &nominal)
                .effective_delay(k)
                .delay_s
                + hold)
                * 1e6
        })
        .fold(None, |r: Option<(f64, f64)>, d| {
            Some(r.map_or((d, d), |(a, b)| (a.min(d), b.max(d))))
        })
}

/// How far beyond the declared actuators' effective delays an identified delay may lie
/// before the report says the actuator does not behave as declared: the load band's
/// estimate was within -29 to +9 % of the truth on the presets' draws
/// (docs/compensation.md).
pub const DECLARATION_MARGIN: f64 = 0.3;

/// The report's judgement of the declaration against the delay identified over the load
/// band (us): `None` when it is consistent or cannot be judged (no range, or a declared
/// range reaching zero or below: a force that leads its command is read at the lead in
/// effect, which cannot be negative); otherwise a warning naming both.
pub fn declaration_check(plan: &CompensationPlan, identified_us: f64) -> Option<String> {
    let (lo, hi) = plan.effective_delays_us?;
    if !(lo > 0.0 && identified_us.is_finite()) {
        return None;
    }
    let (low, high) = (
        lo * (1.0 - DECLARATION_MARGIN),
        hi * (1.0 + DECLARATION_MARGIN),
    );
    if (low..=high).contains(&identified_us) {
        return None;
    }
    Some(format!(
        "WARNING: the actuator does not behave as declared: its delay over the load band was identified at {identified_us:.0} us, where the declared actuator and {DECLARATION_DRAWS} others within actuator_tolerance = {} have {} us (more than {:.0} % {}): the plan was made for another actuator; check [rig.actuator] (or the rig's hardware) and [compensation] actuator_tolerance (fastemu hil --check)",
        plan.tolerance,
        span(lo, hi),
        DECLARATION_MARGIN * 100.0,
        if identified_us < low { "below" } else { "above" }
    ))
}

/// Leads judged between the ends of the adaptation's possible destinations.
const DESTINATION_POINTS: usize = 8;

/// The actuator's smallest and largest phase delay from command to force (with the
/// specimen on an element of stiffness `k`, `ActuatorPlant::response_on_element`) from 1 Hz
/// to `band_hz`, s: where the adaptation's estimate may settle, which weighs that band by
/// the programme's content (a programme of 1-2 Hz harmonics reads the low end, one of
/// axle passages more of the top).
fn phase_delay_range(plant: &ActuatorPlant, k: f64, band_hz: f64) -> (f64, f64) {
    const POINTS: usize = 24;
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut previous = 0.0;
    for i in 0..POINTS {
        // Log-spaced from 1 Hz to the band's corner.
        let f = band_hz.max(1.0).powf(i as f64 / (POINTS - 1) as f64);
        let w = 2.0 * PI * f;
        let mut phase = plant.response_on_element(w, k).arg();
        while phase - previous > PI {
            phase -= 2.0 * PI;
        }
        while phase - previous < -PI {
            phase += 2.0 * PI;
        }
        previous = phase;
        let delay = -phase / w;
        lo = lo.min(delay);
        hi = hi.max(delay);
    }
    (lo, hi)
}

/// The plan for the simulated rig's declared actuator (`[rig.actuator]`'s nominal values;
/// never the rig's perturbed truth), with `[compensation] plan_from_actuator` and `adapt`
/// (`None` otherwise, and in force mode). The adaptation learns the load band's delay; in
/// front of an actuator whose stable leads lie elsewhere (a servo-hydraulic force loop:
/// its phase delay grows with frequency and its velocity feedback moves the loop's
/// crossover, docs/compensation.md) that walks the loop into `loop-unstable`. So when the
/// loop is unstable at that destination for any of the declared actuator and the others
/// within `actuator_tolerance`, the lead is fixed at the lead stable for most of them
/// (`tolerance_scan`), only the gain is learned, and the guard acts only if its damping
/// keeps the declared actuator's loop stable there. Otherwise the compensation stays as
/// configured.
pub fn compensation_plan(cfg: &HilConfig) -> Option<CompensationPlan> {
    if !(cfg.compensation.plan_from_actuator && cfg.compensation.adapt)
        || cfg.controller.command_mode != crate::hil::config::CommandMode::Law
    {
        return None;
    }
    // Everything below is judged at the order the run will predict with.
    let (raised_lead_order, cfg) = with_raised_order(cfg);
    let cfg = cfg.as_ref();
    let c = &cfg.compensation;
    let plants = tolerance_draws(cfg, TOLERANCE_DRAWS);
    let preload = cfg.scenario.preload_n;
    let k = equivalent(
        &cfg.model.element,
        preload,
        2.0 * PI * cfg.emulator.law_frequency_hz,
    )
    .k_eq_n_per_m;
    let hold = 0.5 * cfg.loop_.dt_s();
    // Per draw: (the range of leads the adaptation may settle on, stable over all of it).
    let judged = on_two_threads(&plants, |plant| {
        let (lo, hi) = phase_delay_range(plant, k, c.estimator_band_hz);
        let (lo, hi) = (
            (lo + hold).clamp(0.0, c.max_delay_s),
            (hi + hold).clamp(0.0, c.max_delay_s),
        );
        let mut lin = LinearLoop::for_plant(cfg, plant, lo, 1.0);
        let stable = (0..=DESTINATION_POINTS).all(|i| {
            lin.lead_s = lo + (hi - lo) * i as f64 / DESTINATION_POINTS as f64;
            lin.is_stable(0.0, 1.0)
        });
        ((lo, hi), stable)
    });
    let destinations_us = judged
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), ((lo, hi), _)| {
            (a.min(lo * 1e6), b.max(hi * 1e6))
        });
    let destination_unstable_for = judged.iter().filter(|(_, ok)| !ok).count();
    let effective_delays_us = declared_effective_delays_us(cfg);
    let starting = c.initial_delay_s.min(starting_lead_cap_s(cfg));
    let mut plan = CompensationPlan {
        draws: plants.len(),
        tolerance: c.actuator_tolerance,
        destinations_us,
        destination_unstable_for,
        lead_fixed: false,
        lead_us: starting * 1e6,
        lead_stable_for: 0,
        guard: c.passivity_guard,
        scan: None,
        effective_delays_us,
        nudge: None,
        raised_lead_order,
        over_programme: None,
        start_moved_from_us: None,
    };
    // How many of the draws the loop is stable for at a lead, s.
    let stable_for = |lead_s: f64| {
        on_two_threads(&plants, |plant| {
            LinearLoop::for_plant(cfg, plant, lead_s, 1.0).is_stable(0.0, 1.0)
        })
        .iter()
        .filter(|&&ok| ok)
        .count()
    };
    if destination_unstable_for == 0 {
        plan.lead_stable_for = stable_for(starting);
        // A guess far off (0 before a `lag-delay` of 500 + 500 us, whose stable leads
        // start near 900 us) starts the loop unstable for most of the actuators the
        // declaration allows, and the safe start's damping does not hold every one while
        // the lead is learned (perturbed seeds 3, 4 and 6 of 0.3 tripped `loop-unstable`
        // from 0). The declaration knows better than the guess where to start.
        if 2 * plan.lead_stable_for < plan.draws {
            // The lead stable for all of them nearest the guess, two steps inside their
            // common leads where they are that wide (the guess is the user's knowledge:
            // the middle of a wide window, 180-1530 us for the shipped actuator, would
            // start far from it); else the most widely stable one.
            let scan = tolerance_scan(cfg, starting, TOLERANCE_DRAWS, PLAN_LEAD_STEP_S);
            // The common leads are the first and last the scan found stable for all of
            // them; the lead chosen inside is counted again (a draw's stable leads may
            // have a hole).
            let nearest = scan.common_us.map(|(lo, hi)| {
                let margin = (2.0 * PLAN_LEAD_STEP_S * 1e6).min(0.5 * (hi - lo));
                let lead_us = (starting * 1e6).clamp(lo + margin, hi - margin);
                (lead_us, stable_for(lead_us * 1e-6))
            });
            let start = match (nearest, scan.most_widely_stable) {
                (Some((lead_us, count)), _) if count == plan.draws => Some((lead_us, count)),
                (_, best) => best,
            };
            if let Some((lead_us, count)) = start {
                if count > plan.lead_stable_for {
                    plan.start_moved_from_us = Some(starting * 1e6);
                    plan.lead_us = (lead_us * 1e3).round() / 1e3;
                    plan.lead_stable_for = count;
                    plan.scan = Some(scan);
                }
            }
        }
        return Some(plan);
    }
    let scan = tolerance_scan(cfg, starting, TOLERANCE_DRAWS, PLAN_LEAD_STEP_S);
    if let Some((lead_us, count)) = scan.most_widely_stable {
        plan.lead_fixed = true;
        // The scan's steps are whole microseconds (its sums leave 2849.9999999999995).
        plan.lead_us = (lead_us * 1e3).round() / 1e3;
        plan.lead_stable_for = count;
        if c.passivity_guard {
            let mut lin = LinearLoop::for_plant(cfg, &plants[0], lead_us * 1e-6, 1.0);
            lin.guard_damping_ns_per_m = c.guard_max_damping_ns_per_m;
            plan.guard = lin.is_stable(0.0, 1.0);
        }
        plan.nudge = nudge_range(cfg, &plants, &scan.windows_us, PLAN_LEAD_STEP_S);
        let loads = programme_loads_n(cfg);
        let judged = on_two_threads(&plants, |plant| {
            let lin =
                LinearLoop::for_plant(cfg, plant, plan.lead_us * 1e-6, 1.0).with_loads(cfg, &loads);
            (lin.is_stable(0.0, 1.0), lin.unstable_loads_n())
        });
        plan.over_programme = Some(OverProgramme {
            stable_for: judged
                .iter()
                .filter(|(stable, unstable)| *stable && unstable.is_empty())
                .count(),
            declared_unstable_loads_n: judged[0].1.clone(),
        });
    }
    plan.scan = Some(scan);
    Some(plan)
}

/// Whether `[rig.actuator]` and `[rig]` describe the run's rig: always for the simulated
/// rig (they configure it); for an external rig only with `[compensation]
/// plan_for_external_rig`, by which the lab declares its actuator and specimen. Where they
/// do, the launcher refuses, warns and plans (`compensation_plan`) from them.
pub fn declares_the_rig(cfg: &HilConfig, external_rig: bool) -> bool {
    !external_rig || cfg.compensation.plan_for_external_rig
}

/// `compensation_plan` for the run's rig: `None` where the configuration does not declare
/// it (`declares_the_rig`).
pub fn plan_for_rig(cfg: &HilConfig, external_rig: bool) -> Option<CompensationPlan> {
    if declares_the_rig(cfg, external_rig) {
        compensation_plan(cfg)
    } else {
        None
    }
}

/// `cfg`'s `[compensation]` as the plan (`compensation_plan`) sets it.
pub fn planned(
    cfg: &crate::hil::compensation::CompensationConfig,
    plan: Option<&CompensationPlan>,
) -> crate::hil::compensation::CompensationConfig {
    let lead_order = plan
        .and_then(|p| p.raised_lead_order)
        .unwrap_or(cfg.lead_order);
    match plan {
        Some(p) if p.lead_fixed => crate::hil::compensation::CompensationConfig {
            initial_delay_s: p.lead_us * 1e-6,
            starting_lead_cap_s: f64::INFINITY,
            adapt_lead: false,
            passivity_guard: p.guard,
            nudge: p.nudge,
            lead_order,
            ..*cfg
        },
        // A start stable by itself for the actuators the declaration allows: no safe
        // start's damping there. Damping acts on the velocity predicted over the lead, and
        // at a long lead even a quarter of it made a loop unstable that is stable without
        // it (`lag-delay` 600 + 300 us, perturbed seed 11 of 0.3, started at 1150 us with
        // 10 kN s/m: `loop-unstable` at 0.07 s; 0.045 % without). The guard still answers
        // energy generated.
        Some(p) if p.start_moved_from_us.is_some() => {
            crate::hil::compensation::CompensationConfig {
                initial_delay_s: p.lead_us * 1e-6,
                starting_lead_cap_s: f64::INFINITY,
                safe_start_damping_ns_per_m: 0.0,
                start_planned: true,
                lead_order,
                ..*cfg
            }
        }
        _ => crate::hil::compensation::CompensationConfig { lead_order, ..*cfg },
    }
}

/// One line on `tolerance_scan`'s result: whether one lead serves every actuator the
/// tolerance allows.
pub fn describe_tolerance(t: &ToleranceScan, starting_lead_s: f64) -> String {
    let draws = t.windows_us.len();
    let each: Vec<String> = t
        .windows_us
        .iter()
        .map(|w| match w {
            Some((a, b)) => format!("{a:.0}-{b:.0}"),
            None => "none".into(),
        })
        .collect();
    let common = match (t.common_us, t.most_widely_stable) {
        (Some((a, b)), _) => format!("leads stable for all of them: {a:.0}-{b:.0} us"),
        (None, Some((lead, count))) => format!(
            "NO lead is stable for all of them (the most widely stable, {lead:.0} us, for {count})"
        ),
        (None, None) => "no lead is stable for any of them".into(),
    };
    format!(
        "over the declared actuator and {} others within [compensation] actuator_tolerance = {} (a seed stream of the check's own, not the rig's draw), stable leads in {:.0} us steps: {}; {common}; the configured starting lead ({:.0} us, [compensation] initial_delay_us) is stable for {} of {draws}",
        draws - 1,
        t.tolerance,
        t.step_us,
        each.join(", "),
        starting_lead_s * 1e6,
        t.starting_lead_stable_for
    )
}

/// One line on the plan: what the controller runs with and why.
pub fn describe_plan(p: &CompensationPlan) -> String {
    let judged = if p.draws > 1 {
        format!(
            "the declared actuator and {} others within actuator_tolerance = {}",
            p.draws - 1,
            p.tolerance
        )
    } else {
        "the declared actuator (actuator_tolerance = 0)".to_string()
    };
    let raised = p.raised_lead_order.map_or(String::new(), |o| {
        format!("the prediction's order raised to {o} (at [compensation] lead_order no lead makes the declared actuator's loop stable); ")
    });
    if !p.lead_fixed {
        let unstable = if p.destination_unstable_for == 0 {
            "stable for all of them".to_string()
        } else {
            format!(
                "unstable somewhere for {} of them, and no lead is stable for the declared actuator",
                p.destination_unstable_for
            )
        };
        if let Some(from_us) = p.start_moved_from_us {
            return format!(
                "compensation planned from the declared actuator: {raised}over {judged}, the leads the adaptation may settle on ({} us: the actuator's phase delay from 1 Hz to the estimator's band plus half a period) are {unstable}; the lead the guess would start at ({from_us:.0} us: [compensation] initial_delay_us, capped where it would diverge in front of an actuator twice as fast) is stable for fewer than half of them, so the run starts at {:.0} us, stable for {} of {}, and the adaptation takes the lead on from there; [compensation] plan_from_actuator = false (with an external rig, also plan_for_external_rig = false) starts at the guess",
                span(p.destinations_us.0, p.destinations_us.1), p.lead_us, p.lead_stable_for, p.draws
            );
        }
        return format!(
            "compensation as configured: {raised}over {judged}, the leads the adaptation may settle on ({} us: the actuator's phase delay from 1 Hz to the estimator's band plus half a period) are {unstable}; the starting lead ({:.0} us) is stable for {} of {}",
            span(p.destinations_us.0, p.destinations_us.1), p.lead_us, p.lead_stable_for, p.draws
        );
    }
    let nudge = p.nudge.map_or(String::new(), |n| {
        format!(
            "; a loop that keeps oscillating steps it by 5 % within {:.0}-{:.0} us (up below {:.0} Hz, where a lead too short goes unstable, down above)",
            n.low_s * 1e6,
            n.high_s * 1e6,
            n.split_hz
        )
    });
    // A lead stable for few of them: an actuator as far from the declaration as the
    // tolerance allows may well trip (lag-delay 1 + 1 ms, 8 of 24: perturbed seeds 4 and 6
    // of 0.3 tripped loop-unstable at 0.30 s and held 0.67 mm beyond where they ran).
    let few = if 2 * p.lead_stable_for < p.draws {
        format!(
            ". WARNING: that lead is stable for only {} of the {} actuators judged: an actuator as far from the declaration as actuator_tolerance allows may trip loop-unstable and hold, the forces in flight moving the specimen by up to about a millimetre; declare the actuator as closely as it is known (a smaller actuator_tolerance judges fewer far ones)",
            p.lead_stable_for, p.draws
        )
    } else {
        String::new()
    };
    let over = p.over_programme.as_ref().map_or(String::new(), |o| {
        let declared = if o.declared_unstable_loads_n.is_empty() {
            String::new()
        } else {
            format!(
                ". WARNING: the declared actuator's loop with that lead is NOT stable under {} (the element stiffens with its load): expect it to ring or trip loop-unstable and hold while the load is there (an axle's peak)",
                o.declared_unstable_loads_n
                    .iter()
                    .map(|l| format!("{:.1} kN", l / 1e3))
                    .collect::<Vec<_>>()
                    .join(" and ")
            )
        };
        format!(
            "; at the programme's lowest and highest load as well, stable for {} of {}{declared}",
            o.stable_for, p.draws
        )
    });
    format!(
        "compensation planned from the declared actuator: {raised}over {judged}, the leads the adaptation may settle on ({} us: the actuator's phase delay from 1 Hz to the estimator's band plus half a period) are unstable somewhere for {} of them, so the lead is fixed at {:.0} us, stable for {} of {} (the adaptation learns the gain only){over}{nudge}{}{few}; such an actuator is rendered stable but maybe not faithful (a fixed lead makes up neither for a delay that varies with frequency nor for the part of one it falls short of: expect a run that may not be clean); [compensation] plan_from_actuator = false (with an external rig, also plan_for_external_rig = false) runs as configured",
        span(p.destinations_us.0, p.destinations_us.1),
        p.destination_unstable_for,
        p.lead_us,
        p.lead_stable_for,
        p.draws,
        if p.guard {
            ""
        } else {
            "; the passivity guard is off: its damping, through this actuator's lag above its corner, makes the declared actuator's loop unstable at this lead"
        }
    )
}

/// Where the launcher leaves the plan for the controller (in the report directory).
pub const PLAN_FILE: &str = "compensation-plan.json";

/// Leaves `plan` in `out_dir` for the controller (`PLAN_FILE`), or, without one, removes
/// a plan an earlier run in the same directory left there: it must not stand for this run.
pub fn leave_plan(
    out_dir: &std::path::Path,
    plan: Option<&CompensationPlan>,
) -> anyhow::Result<()> {
    let path = out_dir.join(PLAN_FILE);
    match plan {
        Some(p) => std::fs::write(&path, serde_json::to_string_pretty(p)?)
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display())),
        None => match std::fs::remove_file(&path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                Err(anyhow::anyhow!("cannot remove {}: {e}", path.display()))
            }
            _ => Ok(()),
        },
    }
}

/// The plan the launcher left in `out_dir` (`PLAN_FILE`), if any.
pub fn read_plan(out_dir: &std::path::Path) -> anyhow::Result<Option<CompensationPlan>> {
    let path = out_dir.join(PLAN_FILE);
    match std::fs::read_to_string(&path) {
        Ok(text) => serde_json::from_str(&text)
            .map(Some)
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(anyhow::anyhow!("{}: {e}", path.display())),
    }
}
