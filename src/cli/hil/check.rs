//! `hil --check` and the warning before a run: the linearised loop's margins, stable
//! leads, plan and predicted fidelity, printed and as JSON. Must not: start a run or
//! touch the loop.

use std::path::PathBuf;
use std::process::ExitCode;

use serde_json::json;

use super::HilArgs;
use crate::hil::config::HilConfig;
use crate::hil::report::json_us;

/// A lead the user fixed (`adapt = false`) with the guard on, where the loop is stable
/// and the guard's full damping makes it unstable (`LinearLoop::fixed_lead_guard_stable`).
fn fixed_lead_guard_warning(cfg: &HilConfig, lead_s: f64) -> String {
    format!(
        "the linearised loop is stable with the fixed lead of {:.0} us ([compensation] adapt = false) but not with the passivity guard's full damping ({:.0} kN s/m above {:.0} Hz, which it adds where it sees the loop generate energy: an axle, a stall): this actuator's lag there turns damping into energy, so the guard acting would trip loop-unstable; with a lead you trust, passivity_guard = false keeps it out (fastemu hil --check)",
        lead_s * 1e6,
        cfg.compensation.guard_max_damping_ns_per_m * 1e-3,
        cfg.compensation.guard_band_hz
    )
}

/// Before a run on the simulated rig (whose actuator fastemu's config describes): a
/// warning when the linearised loop (`hil --check`) is not stable with the starting lead,
/// naming the leads that would be, or that none is. `None` when stable or in force mode.
pub(super) fn stability_warning(cfg: &HilConfig) -> Option<String> {
    use crate::hil::check::{nominal_plant, LinearLoop};
    if cfg.controller.command_mode != crate::hil::config::CommandMode::Law {
        return None;
    }
    let cap_s = crate::hil::check::starting_lead_cap_s(cfg);
    let lead_s = cfg.compensation.initial_delay_s.min(cap_s);
    let lin = LinearLoop::for_plant(cfg, &nominal_plant(cfg), lead_s, 1.0);
    let safe_start = lin.safe_start_stable(cfg);
    if lin.margins().stable && lin.fixed_lead_guard_stable(cfg) == Some(false) {
        return Some(fixed_lead_guard_warning(cfg, lead_s));
    }
    if lin.margins().stable && safe_start != Some(false) {
        return None;
    }
    if lin.margins().stable {
        return Some(format!(
            "the linearised loop is stable with the starting lead of {:.0} us but not with the safe start's damping ({:.0} kN s/m above {:.0} Hz until the lead is learned; this actuator's lag there turns damping into energy): expect loop-unstable and a hold; with a lead you trust, adapt = false starts without it, and passivity_guard = false keeps the guard's damping out later too (fastemu hil --check)",
            lead_s * 1e6,
            crate::hil::check::safe_start_damping_ns_per_m(cfg) * 1e-3,
            cfg.compensation.guard_band_hz
        ));
    }
    let held = match safe_start {
        Some(true) => " The safe start's damping makes it stable while the lead is learned.",
        Some(false) => " Nor is it with the safe start's damping.",
        None => "",
    };
    let relies = match (cfg.compensation.adapt, cfg.compensation.passivity_guard) {
        (false, false) => "With adapt and passivity_guard off nothing makes up for it: expect loop-unstable and a hold",
        (true, false) => "The run relies on the adaptation, and ends in loop-unstable and a hold if it does not make up for it",
        (false, true) => "The run relies on the guard, and ends in loop-unstable and a hold if it does not make up for it",
        (true, true) => "The run relies on the adaptation and the guard, and ends in loop-unstable and a hold if they do not make up for it",
    };
    let whence = if cap_s.is_finite() {
        format!(
            "[compensation] initial_delay_us = {:.0} capped for an actuator twice as fast",
            cfg.compensation.initial_delay_s * 1e6
        )
    } else {
        "[compensation] initial_delay_us".to_string()
    };
    let max = cfg.compensation.max_delay_s;
    let nominal = if cfg.rig.actuator.perturb > 0.0 {
        format!(
            " [these figures are the actuator's nominal values; the rig draws its own within +-{:.0} %, which fastemu does not know]",
            cfg.rig.actuator.perturb * 100.0
        )
    } else {
        String::new()
    };
    let warning = match lin.stable_leads(max) {
        Some((lo, hi)) => format!(
            "the linearised loop is not stable with the starting lead of {:.0} us ({whence}); it is with {:.0}-{:.0} us.{held} {relies}{} (fastemu hil --check)",
            lead_s * 1e6,
            lo * 1e6,
            hi * 1e6,
            dispersive_hint(&lin, cfg.compensation.adapt)
        ),
        None => format!(
            "no lead from 0 to {:.0} us makes the linearised loop stable{}: {} (docs/compensation.md); expect loop-unstable and a hold (fastemu hil --check)",
            max * 1e6,
            crate::hil::check::lead_order_hint(cfg),
            crate::hil::check::why_no_stable_lead(cfg)
        ),
    };
    Some(format!("{warning}{nominal}"))
}

/// For an actuator whose phase delay grows with frequency (a servo-hydraulic force loop):
/// the adaptation learns the load band's delay, which for such actuators lies below the
/// stable leads, so a lead the user trusts is kept only with `adapt = false`; empty when
/// the adaptation is off or the delay is nearly the same over the band.
fn dispersive_hint(lin: &crate::hil::check::LinearLoop, adapt: bool) -> String {
    // Over the band the rendering is judged on (1-20 Hz), as `hil --check` quotes it.
    let (at_1, at_20) = (lin.actuator_at(1.0).0, lin.actuator_at(20.0).0);
    let dispersive = at_1 > 0.0 && at_20 > 1.5 * at_1;
    if !adapt || !dispersive {
        return String::new();
    }
    format!(
        ". This actuator's phase delay runs from {:.0} us at 1 Hz to {:.0} us at 20 Hz: the adaptation learns the load band's delay and walks such leads out of the stable range (docs/compensation.md, \"What does not work yet\"); with a lead you trust inside it, adapt = false keeps it there, though no lead makes up for a delay that varies with frequency (expect a run that is not clean)",
        at_1 * 1e6,
        at_20 * 1e6
    )
}

/// `cfg` with its `[compensation]` as `plan` sets it.
pub(super) fn planned_config(
    cfg: &HilConfig,
    plan: Option<&crate::hil::check::CompensationPlan>,
) -> HilConfig {
    let mut planned = cfg.clone();
    planned.compensation = crate::hil::check::planned(&cfg.compensation, plan);
    planned
}

/// `hil --check`: the linearised loop's margins, printed, as JSON with `--json`, and its
/// plot. Exit 0 when the loop is stable, 1 when not.
pub(super) fn run(args: &HilArgs, cfg: &HilConfig) -> anyhow::Result<ExitCode> {
    use crate::hil::check::{describe_actuator, nominal_plant, LinearLoop};
    anyhow::ensure!(
        cfg.controller.command_mode == crate::hil::config::CommandMode::Law,
        "{}: [controller] command_mode = \"force\": --check models local-law commands (the rig's prediction over the controller's lead) only",
        cfg.origin
    );
    // The plan for the simulated rig's declared actuator; the rest is judged as planned.
    let declared = crate::hil::check::declares_the_rig(cfg, args.rig.external());
    let plan = crate::hil::check::plan_for_rig(cfg, args.rig.external());
    // What the controller starts with: the guard's most damping by the lead among it.
    let starting = crate::hil::check::starting_compensation(cfg, plan.as_ref());
    let damping_steps =
        (starting.adapt && starting.adapt_lead && starting.passivity_guard).then(|| {
            crate::hil::check::damping_by_lead_steps(
                &starting.guard_damping_by_lead,
                starting.guard_max_damping_ns_per_m,
                starting.max_delay_s,
            )
        });
    let original_lead_s = cfg
        .compensation
        .initial_delay_s
        .min(crate::hil::check::starting_lead_cap_s(cfg));
    // The configured guess, reported as such (the plan may start elsewhere: `lead_us`).
    let guess_s = cfg.compensation.initial_delay_s;
    let planned = planned_config(cfg, plan.as_ref());
    let cfg = &planned;
    let cap_s = crate::hil::check::starting_lead_cap_s(cfg);
    let lead_s = cfg.compensation.initial_delay_s.min(cap_s);
    // The programme is scanned once (a durability block takes seconds).
    let load_range = crate::hil::check::programme_load_range(cfg);
    let lin = LinearLoop::for_plant(cfg, &nominal_plant(cfg), lead_s, 1.0).with_loads(
        cfg,
        &crate::hil::check::loads_beside_the_preload(cfg, load_range),
    );
    let m = lin.margins();
    let dir = args.out.clone().unwrap_or_else(|| PathBuf::from("."));
    std::fs::create_dir_all(&dir).map_err(|e| anyhow::anyhow!("--out {}: {e}", dir.display()))?;
    let plot = dir.join("check.png");
    lin.plot(&plot, "linearised loop")?;
    let element = crate::model::equiv::equivalent(
        &cfg.model.element,
        cfg.scenario.preload_n,
        2.0 * std::f64::consts::PI * cfg.emulator.law_frequency_hz,
    );
    let band_hz = lin.faithful_band_hz();
    // The safe start: the run's first commands carry its damping
    // (`check::safe_start_damping_ns_per_m`).
    let safe_start = lin.safe_start_stable(cfg);
    // As the run starts: with the safe start's damping when it arms.
    let starts_stable = safe_start.unwrap_or(m.stable);
    // Among the leads stable at every judged load; else at the preload (said so).
    let best_over_programme = lin.most_faithful_lead_over_programme(cfg.compensation.max_delay_s);
    let best_at_preload_only = best_over_programme.is_none();
    let best =
        best_over_programme.or_else(|| lin.most_faithful_stable_lead(cfg.compensation.max_delay_s));
    // The actuator must carry the programme's peak load, or a fault's hold cannot hold.
    // (Not for an external rig's undeclared actuator: [rig.actuator] is not its actuator.)
    let cannot_hold = if args.rig.external() && !declared {
        None
    } else {
        crate::hil::check::actuator_cannot_hold(cfg)
    };
    // hil refuses a loop no lead makes stable on the simulated rig (unless --run-unstable).
    let no_stable_lead = if declared {
        crate::hil::check::no_stable_lead(cfg)
    } else {
        None
    };
    let [(delay_1_s, amplitude_1, _), (delay_20_s, amplitude_20, velocity_20)] =
        [1.0, 20.0].map(|f| lin.actuator_at(f));
    // Where the specimen starts: at rest under the programme's first force.
    let start_force_n =
        crate::rig::load::LoadProgramme::new(&cfg.programme, cfg.model.length_m).force_n(0.0);
    let start_m = cfg.model.element.static_displacement_m(start_force_n);
    // How slow an actuator the specimen and programme allow at all (for a rig nothing
    // declares, the limit the run's actuator must be within).
    let slowest = crate::hil::check::after_trip::slowest_held_s(
        cfg,
        &lin.other_loads_n(),
        cfg.compensation.max_delay_s,
    );
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({
                "margins": m,
                "start_displacement_m": start_m,
                "start_force_n": start_force_n,
                "stable_leads_us": lin.stable_leads(cfg.compensation.max_delay_s).map(|(a, b)| [json_us(a), json_us(b)]),
                "safe_start_damping_ns_per_m": crate::hil::check::safe_start_damping_ns_per_m(cfg),
                "programme_loads": {
                    "lowest_n": load_range.0,
                    "highest_n": load_range.1,
                    "judged_n": lin.other_loads_n(),
                    "unstable_at_n": lin.unstable_loads_n(),
                    "stable_leads_us": lin
                        .stable_leads_over_programme(cfg.compensation.max_delay_s)
                        .map(|(a, b)| [json_us(a), json_us(b)]),
                },
                "lead_us": json_us(lead_s),
                "initial_delay_us": json_us(guess_s),
                "starting_lead_capped": cap_s.is_finite(),
                "lead_order": cfg.compensation.lead_order,
                "safe_start_stable": safe_start,
                "guard_damping_by_lead": damping_steps.as_ref().map(|steps| steps
                    .iter()
                    .map(|&(up_to, d)| json!({"up_to_us": (up_to * 1e6).round(), "damping_ns_per_m": d}))
                    .collect::<Vec<_>>()),
                "starts_stable": starts_stable,
                "actuator_cannot_hold": cannot_hold,
                "no_stable_lead": no_stable_lead,
                // As the console: none for a loop that is not stable as it starts (the
                // rendering's own band stays in `rendering_faithful_band_hz`).
                "predicted_faithful_band_hz": starts_stable.then_some(band_hz),
                "rendering_faithful_band_hz": band_hz,
                "fixed_lead_guard_stable": lin.fixed_lead_guard_stable(cfg),
                "most_faithful_stable_lead": best.map(|(l, b)| json!({"lead_us": json_us(l), "faithful_band_hz": b, "stable_at_every_load": !best_at_preload_only})),
                "actuator_phase_delay_us": {"1_hz": json_us(delay_1_s), "20_hz": json_us(delay_20_s)},
                "actuator_amplitude_ratio": {"1_hz": amplitude_1, "20_hz": amplitude_20},
                "actuator_velocity_force_share_20_hz": velocity_20,
                "actuator": describe_actuator(cfg),
                "slowest_held_actuator": slowest
                    .iter()
                    .map(|&(share, d)| json!({"lag_share": share, "effective_delay_us": d.map(|d| (d * 1e6).round())}))
                    .collect::<Vec<_>>(),
                "plan": plan,
                "plot": plot.display().to_string(),
            }))?
        );
    }
    eprintln!("hil --check: {}", cfg.origin);
    eprintln!(
        "  specimen {:.2} kg, rig damping {:.0} N s/m; element at {:.0} kN preload: {:.1} MN/m, {:.0} N s/m at {:.0} Hz; the specimen starts at rest at {:.6} mm (the element's static displacement under the programme's first force, {:.3} kN: where a rig of its own starts too)",
        cfg.rig.specimen_mass_kg,
        cfg.rig.damping_ns_per_m,
        cfg.scenario.preload_n * 1e-3,
        element.k_eq_n_per_m * 1e-6,
        element.c_eq_ns_per_m,
        cfg.emulator.law_frequency_hz,
        start_m * 1e3,
        start_force_n * 1e-3
    );
    eprintln!(
        "  actuator: {} ({})",
        describe_actuator(cfg),
        match (args.rig.external(), declared) {
            (false, _) => "the simulated rig's [rig.actuator]; a rig of its own is unknown to fastemu, which learns it with adapt = true, unless [compensation] plan_for_external_rig declares it",
            (true, true) => "the external rig's actuator as [rig.actuator] declares it, with [compensation] plan_for_external_rig; [rig] gives its specimen",
            (true, false) => "[rig.actuator], which describes the simulated rig, not this external one: fastemu learns the external rig's actuator with adapt = true ([compensation] plan_for_external_rig = true declares it)",
        }
    );
    if let Some(why) = &cannot_hold {
        eprintln!("  ERROR: {why}");
    }
    if cap_s.is_finite() {
        eprintln!(
            "  starting lead capped at {:.0} us: the guess ({:.0} us) would diverge within milliseconds in front of an actuator twice as fast as it (a lead too long; one too short is what the guard makes up for)",
            cap_s * 1e6,
            cfg.compensation.initial_delay_s * 1e6
        );
    }
    eprintln!(
        "  compensation: starting lead {:.0} us ({}), prediction order {}",
        lead_s * 1e6,
        if !cfg.compensation.adapt_lead {
            "planned, fixed"
        } else if cfg.compensation.start_planned {
            "planned from the declared actuator, not the guess; the adaptation takes it on from there, without a safe start's damping"
        } else if cap_s.is_finite() {
            "[compensation] initial_delay_us, capped"
        } else {
            "[compensation] initial_delay_us"
        },
        cfg.compensation.lead_order
    );
    if m.stable {
        // The faster side is searched down to the lead plus one period earlier: reaching
        // that bound means any faster actuator, however fast.
        let faster_us = m.delay_error_tolerated_faster_us.unwrap_or(f64::NAN);
        let faster = if faster_us >= (lead_s + cfg.loop_.dt_s()) * 1e6 - 1e-3 {
            "any faster one".to_string()
        } else {
            format!("one up to {faster_us:.0} us faster")
        };
        eprintln!(
            "  linearised loop: stable; it tolerates an actuator up to {:.0} us slower than the lead and {faster}; gain margin {:.2}; thinnest at {:.0} Hz (|1 + L| = {:.3})",
            m.delay_error_tolerated_slower_us.unwrap_or(f64::NAN),
            m.gain_margin.unwrap_or(f64::NAN),
            m.thinnest_frequency_hz,
            m.modulus_margin
        );
    } else {
        eprintln!(
            "  linearised loop: NOT STABLE with this lead (nearest to -1 at {:.0} Hz, |1 + L| = {:.3}): the run would end in loop-unstable{}",
            m.thinnest_frequency_hz,
            m.modulus_margin,
            match (
                cfg.compensation.adapt && cfg.compensation.adapt_lead,
                cfg.compensation.passivity_guard
            ) {
                (true, true) => " unless the controller's adaptation and guard make up for it",
                (true, false) => " unless the controller's adaptation makes up for it",
                (false, true) => " unless the passivity guard's damping makes up for it",
                (false, false) => " (adaptation and passivity guard are off)",
            }
        );
    }
    match lin.stable_leads(cfg.compensation.max_delay_s) {
        Some((lo, hi)) => eprintln!(
            "  leads with which the linearised loop is stable: {:.0}-{:.0} us ({})",
            lo * 1e6,
            hi * 1e6,
            if cfg.compensation.adapt && cfg.compensation.adapt_lead {
                format!(
                    "the adaptation keeps the lead within [0, {:.0}] us",
                    cfg.compensation.max_delay_s * 1e6
                )
            } else {
                "the lead stays where it starts".to_string()
            }
        ),
        None => eprintln!(
            "  no lead from 0 to {:.0} us makes the linearised loop stable{}: {}; {}",
            cfg.compensation.max_delay_s * 1e6,
            crate::hil::check::lead_order_hint(cfg),
            crate::hil::check::why_no_stable_lead(cfg),
            if no_stable_lead.is_some() {
                "`fastemu hil` refuses to run it (--run-unstable runs it anyway: expect loop-unstable and a hold that may move the specimen by millimetres)"
            } else {
                "with this actuator, expect loop-unstable and a hold"
            }
        ),
    }
    let loads = lin.other_loads_n();
    if !loads.is_empty() {
        let (lowest, highest) = load_range;
        let unstable = lin.unstable_loads_n();
        let kn = |l: &[f64]| -> String {
            l.iter()
                .map(|x| format!("{:.1} kN", x / 1e3))
                .collect::<Vec<_>>()
                .join(" and ")
        };
        let over = match lin.stable_leads_over_programme(cfg.compensation.max_delay_s) {
            Some((lo, hi)) => format!(
                "leads stable at all three: {:.0}-{:.0} us",
                lo * 1e6,
                hi * 1e6
            ),
            None => "no lead is stable at all three".to_string(),
        };
        eprintln!(
            "  at the programme's lowest and highest load ({:.1} and {:.1} kN; the element stiffens with its load): {}; {over}",
            lowest.max(0.0) / 1e3,
            highest / 1e3,
            if !m.stable {
                "(the loop is not stable at the preload)".to_string()
            } else if unstable.is_empty() {
                "stable with this lead too".to_string()
            } else {
                format!(
                    "NOT stable with this lead under {}: the loop may ring or trip loop-unstable and hold while the load is there (an axle's peak)",
                    kn(&unstable)
                )
            }
        );
    }
    eprintln!(
        "  {}",
        crate::hil::check::after_trip::describe_slowest_held(
            &slowest,
            cfg.compensation.max_delay_s
        )
    );
    if let Some(p) = &plan {
        eprintln!("  {}", crate::hil::check::describe_plan(p));
        if let Some(t) = &p.scan {
            eprintln!(
                "  {}",
                crate::hil::check::describe_tolerance(
                    t,
                    // The lead the scan judged: the guess's start, which the plan moved.
                    p.start_moved_from_us
                        .map_or(original_lead_s, |us| us * 1e-6)
                )
            );
        }
    }
    if let Some(stable) = safe_start {
        let start_damping = crate::hil::check::safe_start_damping_ns_per_m(cfg);
        eprintln!(
            "  safe start (the guard's {:.0} kN s/m above {:.0} Hz from the first command until the lead is learned{}): the linearised loop is {} with it at this lead{}",
            start_damping * 1e-3,
            cfg.compensation.guard_band_hz,
            if start_damping < cfg.compensation.guard_max_damping_ns_per_m {
                format!(
                    "; less than guard_max_damping_ns_per_m = {:.0} kN s/m, with which the loop at this lead is unstable in front of some actuator between half the guess and the guess",
                    cfg.compensation.guard_max_damping_ns_per_m * 1e-3
                )
            } else {
                String::new()
            },
            if stable { "stable" } else { "NOT stable" },
            match (stable, m.stable) {
                (true, false) => ": it holds the loop while the lead is learned",
                (false, true) => ": the actuator's lag there turns damping into energy; with a lead you trust, adapt = false starts without it (and passivity_guard = false keeps the guard's damping out later too)",
                _ => "",
            }
        );
    }
    if m.stable && lin.fixed_lead_guard_stable(cfg) == Some(false) {
        eprintln!("  WARNING: {}", fixed_lead_guard_warning(cfg, lead_s));
    }
    if let Some(steps) = &damping_steps {
        let at = |lead: f64| {
            starting
                .guard_damping_by_lead
                .cap(starting.guard_max_damping_ns_per_m, lead)
                * 1e-3
        };
        eprintln!(
            "  the passivity guard's most damping by the lead in effect (more would turn into energy in front of an actuator as slow as the lead: a pure delay, or a lag of a quarter or half of it): {}; at this lead {:.1} kN s/m{}",
            crate::hil::check::describe_damping_by_lead(steps),
            at(lead_s),
            match best {
                Some((lead, _)) => format!(", at the most faithful stable lead ({:.0} us) {:.1} kN s/m", lead * 1e6, at(lead)),
                None => String::new(),
            }
        );
    }
    if starts_stable {
        eprintln!(
            "  predicted faithful band with this lead: {band_hz:.1} Hz (the rendered force within 1 % and 2 degrees of the element's from 1 Hz up; the run's report measures it on the bins the load excites)"
        );
    } else {
        // A band of a loop that diverges is no promise: said as what it is.
        eprintln!(
            "  predicted faithful band with this lead: none (the loop is not stable as it starts; a stable loop with this rendering would be faithful up to {band_hz:.1} Hz)"
        );
    }
    match best {
        Some((lead, band)) if band < 20.0 => {
            // What a lead and a gain cannot make up for: a delay that changes over the
            // band, an amplitude that does, the actuator's own force on the velocity.
            let mut causes = Vec::new();
            if (delay_20_s - delay_1_s).abs() > 0.1 * delay_1_s.abs().max(delay_20_s.abs()) {
                causes.push(format!(
                    "its phase delay runs from {:.0} us at 1 Hz to {:.0} us at 20 Hz",
                    delay_1_s * 1e6,
                    delay_20_s * 1e6
                ));
            }
            if (amplitude_20 - amplitude_1).abs() > 0.01 {
                causes.push(format!(
                    "its amplitude ratio from {amplitude_1:.3} to {amplitude_20:.3}"
                ));
            }
            if velocity_20 > 0.01 {
                causes.push(format!(
                    "its own force on the specimen's velocity (a servo-valve's residual flow, a shaker's back-EMF) is {:.1} % of the element's at 20 Hz",
                    100.0 * velocity_20
                ));
            }
            eprintln!(
                "  WARNING: no stable lead renders 1-20 Hz within 1 % and 2 degrees (the most faithful, {:.0} us, up to {band:.1} Hz): {}; a lead and a gain do not make up for that. Whether the run is clean is judged on its displacement error ([safety] max_displacement_error); its report's faithful band says how far it was faithful (docs/compensation.md)",
                lead * 1e6,
                if causes.is_empty() { "the prediction's own error".to_string() } else { causes.join(", ") }
            )
        }
        Some((lead, band)) => eprintln!(
            "  most faithful stable lead: {:.0} us (predicted faithful band {band:.1} Hz){}",
            lead * 1e6,
            if best_at_preload_only && !lin.other_loads_n().is_empty() {
                "; stable at the preload only: no lead is stable at every load of the programme"
            } else {
                ""
            }
        ),
        None => {}
    }
    eprintln!("  plot: {}", plot.display());
    Ok(if starts_stable && cannot_hold.is_none() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

#[cfg(test)]
mod tests {
    /// The pre-run warning: none on the default configuration; the leads that would be
    /// stable when the starting lead is far off, and that the safe start holds it there;
    /// a lead stable alone but not with the safe start's damping (a servo-hydraulic force
    /// loop lags too much above 60 Hz), and why the adaptation does not keep such a loop's
    /// lead; "no lead" for an actuator too slow.
    #[test]
    fn a_run_is_warned_when_its_linearised_loop_is_not_stable() {
        use crate::hil::config::{default_hil_config, parse_hil_config, DEFAULT_CONFIG_TOML};
        assert_eq!(
            super::stability_warning(&default_hil_config().unwrap()),
            None
        );
        let mut far = default_hil_config().unwrap();
        far.compensation.initial_delay_s = 0.0;
        let w = super::stability_warning(&far).expect("a lead of 0 is unstable");
        assert!(
            w.contains("starting lead of 0 us")
                && w.contains("it is with")
                && w.contains("The safe start's damping makes it stable")
                && !w.contains("phase delay runs from"),
            "{w}"
        );
        // A servo-hydraulic force loop from the shipped guess: the stable leads, and why
        // the adaptation will not keep a lead there (its delay grows with frequency).
        let servo_guess = DEFAULT_CONFIG_TOML.replace(
            "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0",
            "preset = \"fatigue-150kn\"",
        );
        let servo_guess = parse_hil_config(&servo_guess, "servo.toml", None).unwrap();
        let w = super::stability_warning(&servo_guess).expect("252 us is unstable there");
        assert!(
            w.contains("starting lead of 252 us")
                && w.contains("it is with 2220-3360 us")
                && w.contains("phase delay runs from 566 us at 1 Hz to 2996 us at 20 Hz")
                && w.contains("adapt = false keeps it there"),
            "{w}"
        );
        let servo = DEFAULT_CONFIG_TOML
            .replace(
                "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0",
                "preset = \"fatigue-150kn\"",
            )
            .replace("initial_delay_us = 252.0", "initial_delay_us = 2790.0");
        let servo = parse_hil_config(&servo, "servo.toml", None).unwrap();
        let w = super::stability_warning(&servo).expect("the safe start is not stable there");
        assert!(
            w.contains(
                "is stable with the starting lead of 2790 us but not with the safe start's damping"
            ),
            "{w}"
        );
        // A lead the user trusts: no safe start, but the guard would still act where it
        // sees energy, and its damping is as harmful there; without the guard, no warning.
        let mut trusted = servo.clone();
        trusted.compensation.adapt = false;
        let w = super::stability_warning(&trusted).expect("the guard's damping is not stable");
        assert!(
            w.contains("stable with the fixed lead of 2790 us")
                && w.contains("passivity_guard = false keeps it out"),
            "{w}"
        );
        trusted.compensation.passivity_guard = false;
        assert_eq!(super::stability_warning(&trusted), None);
        // A lead 100 us short with nothing to make up for it says so.
        let mut bare = default_hil_config().unwrap();
        bare.compensation.initial_delay_s = 152e-6;
        bare.compensation.adapt = false;
        bare.compensation.passivity_guard = false;
        let w = super::stability_warning(&bare).expect("152 us is unstable");
        assert!(w.contains("nothing makes up for it"), "{w}");
        let slow = DEFAULT_CONFIG_TOML
            .replace("transport_delay_us = 50.0", "transport_delay_us = 3000.0")
            .replace("lag_us = 80.0", "lag_us = 2000.0");
        let slow = parse_hil_config(&slow, "slow.toml", None).unwrap();
        let w = super::stability_warning(&slow).expect("3 ms + 2 ms is unstable");
        assert!(w.contains("no lead from 0 to"), "{w}");
    }
}
