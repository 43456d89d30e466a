//! The end of `fastemu hil`: the run's summary (`summary.json`), its verdict (clean or
//! why not), the console's report and the exit code. Must not: start or stop processes.

use super::*;

/// A first command later than this, s, is said in the console: it is due within a few
/// periods of the start (a default run's reaches the rig at about 1 ms).
const LATE_FIRST_COMMAND_S: f64 = 0.005;

/// Why a run is not clean (empty: clean).
pub(super) fn not_clean_because(
    cfg: &HilConfig,
    outcome: &RunOutcome,
    analysis: Option<&Analysis>,
    records_dropped: u64,
) -> Vec<String> {
    let mut why = Vec::new();
    if !outcome.faults.is_empty() {
        why.push(format!("faults: {}", outcome.faults.join("; ")));
    }
    match analysis {
        None => why.push("no analysis of the records".into()),
        Some(a) => {
            if !a.stability.stable {
                why.push("the loop was not stable (see stability)".into());
            }
            let error = a.fidelity.displacement_rel_rms;
            if error > cfg.safety.max_displacement_error {
                why.push(format!(
                    "displacement error {:.3} % > [safety] max_displacement_error = {:.3} %",
                    error * 100.0,
                    cfg.safety.max_displacement_error * 100.0
                ));
            }
            let dynamic = a.fidelity.displacement_dynamic_rel_rms;
            if dynamic > cfg.safety.max_dynamic_displacement_error {
                why.push(format!(
                    "dynamic displacement error {:.3} % > [safety] max_dynamic_displacement_error = {:.3} % (the error against the displacement's motion, the static deflection under the preload left out: the whole displacement's {:.3} % dilutes it)",
                    dynamic * 100.0,
                    cfg.safety.max_dynamic_displacement_error * 100.0,
                    error * 100.0
                ));
            }
            // A long run is judged by its worst stretch too: quiet ones dilute the rest.
            if let Some(w) = a.fidelity.dynamic_worst_window {
                if w.rel_rms > cfg.safety.max_dynamic_displacement_error {
                    why.push(format!(
                        "dynamic displacement error {:.3} % over the {:.0} s from {:.1} s > [safety] max_dynamic_displacement_error = {:.3} % (the worst {:.0} s stretch; over the whole run {:.3} %)",
                        w.rel_rms * 100.0,
                        w.window_s,
                        w.from_s,
                        cfg.safety.max_dynamic_displacement_error * 100.0,
                        w.window_s,
                        dynamic * 100.0
                    ));
                }
            }
            if a.loop_energy.not_passive() {
                why.push(a.loop_energy.describe());
            }
            if a.largest_transient_m > cfg.safety.max_transient_m {
                why.push(format!(
                    "largest resonant transient {:.1} um > [safety] max_transient_m = {:.1} um",
                    a.largest_transient_m * 1e6,
                    cfg.safety.max_transient_m * 1e6
                ));
            }
            if !a.records.truncated.is_empty() {
                why.push(format!(
                    "record files cut short: {}",
                    a.records.truncated.join("; ")
                ));
            }
        }
    }
    if records_dropped > 0 {
        why.push(format!(
            "{records_dropped} records dropped (record queue full)"
        ));
    }
    // Without an analysis whether they fired is unknown (and the run is not clean anyway).
    if let Some(missed) = analysis.and_then(|a| injections_not_fired(cfg, a.safety.injected.len()))
    {
        why.push(missed);
    }
    why
}

/// A fault test whose fault never came must not pass as a clean run: the configured
/// `[[inject]]` faults beyond those the records say were injected (`safety.injected`).
pub(super) fn injections_not_fired(cfg: &HilConfig, fired: usize) -> Option<String> {
    let configured = cfg.injections.len();
    (fired < configured).then(|| {
        let all: Vec<String> = cfg.injections.iter().map(|i| i.describe()).collect();
        format!(
            "{} of {configured} configured [[inject]] faults never fired (configured: {}; the run ended at {} s of programme)",
            configured - fired,
            all.join(", "),
            cfg.scenario.duration_s
        )
    })
}

/// Orders the faults the processes reported (in the order their heartbeats or exits
/// reached `hil`, which varies between runs) as they happened: process deaths and a
/// failed link first (the cause), then by when the records say each was detected
/// (`safety.faults`), a fault the records do not date last; ties in text order. The same
/// faults print in the same order whatever order they arrived in.
pub(super) fn order_faults(
    faults: &mut [String],
    dated: &[crate::hil::report::safety::FaultReport],
) {
    let when = |f: &String| -> f64 {
        // "process: fault (detail)"; an external rig's own faults are labelled likewise.
        let (process, rest) = f.split_once(": ").unwrap_or(("", f.as_str()));
        let name = rest.split([' ', '(']).next().unwrap_or(rest);
        let earliest = |same_process: bool| {
            dated
                .iter()
                .filter(|d| d.fault == name && (!same_process || d.process == process))
                .map(|d| d.detected_at_s)
                .fold(None, |m: Option<f64>, t| Some(m.map_or(t, |m| m.min(t))))
        };
        earliest(true)
            .or_else(|| earliest(false))
            .unwrap_or(f64::INFINITY)
    };
    // Causes first: a process that died, or the link that failed (their reactions follow);
    // ties (undated faults) in text order, so that the same faults print the same way.
    faults.sort_by(|a, b| {
        let reaction = |f: &String| !(f.contains("process (pid") || f.starts_with("link: "));
        reaction(a)
            .cmp(&reaction(b))
            .then(when(a).total_cmp(&when(b)))
            .then(a.cmp(b))
    });
}

/// Writes `summary.json`, prints the one-line result (and `--json`), returns the exit code.
#[allow(clippy::too_many_arguments)]
pub(super) fn summarise(
    cfg: &HilConfig,
    args: &HilArgs,
    out_dir: &std::path::Path,
    run_id: &str,
    outcome: &RunOutcome,
    analysis: Option<&Analysis>,
    records: serde_json::Value,
    effect_names: &[&str],
    rig_setup: &RigSetup,
    configured: &crate::hil::compensation::CompensationConfig,
) -> anyhow::Result<ExitCode> {
    let emu = read_json(&out_dir.join("emulator-summary.json"));
    let rig = read_json(&out_dir.join("rig-summary.json"));
    let ctl = read_json(&out_dir.join("controller-summary.json"));
    let u =
        |v: &serde_json::Value, k: &str| v.get(k).and_then(serde_json::Value::as_u64).unwrap_or(0);
    let dropped = |v: &serde_json::Value| {
        v["records"]["dropped"].as_u64().unwrap_or(0) + v["events"]["dropped"].as_u64().unwrap_or(0)
    };
    let records_dropped = dropped(&emu) + dropped(&ctl) + dropped(&rig);
    // The product's fixed-step loop is the emulator's; the rig's misses (the simulated
    // hardware's own timing) are reported separately.
    let deadline_misses = u(&emu, "missed_deadlines");
    let stable = outcome.faults.is_empty() && analysis.is_some_and(|a| a.stability.stable);
    let why = not_clean_because(cfg, outcome, analysis, records_dropped);
    let clean = why.is_empty();
    let value = |v: Option<serde_json::Value>| v.unwrap_or(serde_json::Value::Null);
    let mut summary = json!({
        "rate_hz": cfg.loop_.rate_hz,
        "duration_s": cfg.scenario.duration_s,
        "steps": analysis.map_or(u(&emu, "model_steps"), |a| a.steps),
        "deadline_misses": deadline_misses,
        "deadline_misses_emulator": deadline_misses,
        // An external rig's own timing is not known to fastemu: null, not 0.
        "deadline_misses_rig": if args.rig.external() {
            serde_json::Value::Null
        } else {
            json!(u(&rig, "missed_deadlines"))
        },
        "emulator_standby_cycles": u(&emu, "standby_cycles"),
        "stale_samples": u(&emu, "stale_cycles"),
        "missing_samples": u(&emu, "missing_samples"),
        "records_dropped": records_dropped,
        // What each process's threads marked real-time took from the fixed pool, and how
        // often a loop reached the system allocator (`rt::pool`; null for a process that
        // did not run here, an external rig).
        "rt_pool": {
            "emulator": emu["rt_pool"],
            "controller": ctl["rt_pool"],
            "rig": rig["rt_pool"],
            "link": read_json(&out_dir.join("link-summary.json"))["rt_pool"],
        },
        "stable": stable,
        "clean": clean,
        "not_clean_because": why,
        "faults": outcome.faults,
        "operator_stop": outcome.operator_stop
            || analysis.is_some_and(|a| a.safety.operator_actions.iter().any(|x| x.ends_with("operator stop"))),
        "safety": value(analysis.map(|a| serde_json::to_value(&a.safety).unwrap_or_default())),
        "loop_energy": value(analysis.map(|a| serde_json::to_value(a.loop_energy).unwrap_or_default())),
        "stalls": value(analysis.map(|a| json!({
            "count": a.stalls.count,
            "ended_in_hold": a.stalls.ended_in_hold,
            "longest_ms": a.stalls.longest_ms,
            "largest_transient_um": a.stalls.largest_transient_m * 1e6,
            "largest_rise_um": a.stalls.largest_rise_m * 1e6,
            "episodes": a.stalls.episodes.iter().map(|e| json!({
                "at_s": e.at_s, "length_ms": e.length_ms, "transient_um": e.transient_m * 1e6,
                "before_um": e.before_m * 1e6, "source": e.source,
            })).collect::<Vec<_>>(),
        }))),
        "programme": value(analysis.map(|a| serde_json::to_value(&a.programme).unwrap_or_default())),
        "largest_transient_um": value(analysis.map(|a| json!(a.largest_transient_m * 1e6))),
        "max_transient_um": cfg.safety.max_transient_m * 1e6,
        "fidelity": value(analysis.map(|a| serde_json::to_value(&a.fidelity).unwrap_or_default())),
        "stability": value(analysis.map(|a| serde_json::to_value(&a.stability).unwrap_or_default())),
        "compensation": value(analysis.map(|a| serde_json::to_value(&a.compensation).unwrap_or_default())),
        "latency_ns": value(analysis.map(|a| serde_json::to_value(&a.latency_ns).unwrap_or_default())),
        "events": value(analysis.map(|a| json!(a.events))),
        "actuator_truth": value(analysis.and_then(|a| a.actuator_truth.as_ref()).map(|t| serde_json::to_value(t).unwrap_or_default())),
        "element_thermal": value(analysis.and_then(|a| a.element_thermal.as_ref()).map(|t| serde_json::to_value(t).unwrap_or_default())),
        "model": {
            "form": cfg.model.element.form().name(),
            "length_m": cfg.model.length_m,
            "effects": effect_names,
        },
        "commands": {
            "mode": match cfg.controller.command_mode {
                crate::hil::config::CommandMode::Law => "law",
                crate::hil::config::CommandMode::Force => "force",
            },
            // As configured; what the plan made of them: `compensation.plan`.
            "initial_delay_us": configured.initial_delay_s * 1e6,
            "lead_order": configured.lead_order,
            "adapt": configured.adapt,
            "passivity_guard": configured.passivity_guard,
        },
        "force_mode_compensation": {
            "enabled": cfg.controller.compensation_enabled,
            "order": cfg.controller.compensation_order,
            "delay_us": cfg.controller.compensation_delay_s * 1e6,
        },
        "records": records,
        "processes": {"bench_rig": rig, "emulator": emu, "controller": ctl, "exit": outcome.exit_statuses},
        "leftover_files_removed": outcome.leftover_files.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "run_id": run_id,
        "report_dir": out_dir.display().to_string(),
    });
    summary["rig"] = json!({"kind": args.rig.kind, "link": args.rig.link});
    // The launcher's plan for the declared actuator (none: as configured).
    if let Some(c) = summary
        .get_mut("compensation")
        .and_then(|c| c.as_object_mut())
    {
        let plan = crate::hil::check::read_plan(out_dir).unwrap_or(None);
        // The declaration against what the load band identified (not the lead's own
        // estimator, which reads a servo loop short).
        let identified = analysis
            .map(|a| &a.compensation)
            .filter(|c| c.identified_from == Some("load-band"))
            .and_then(|c| c.identified_delay_us);
        let warning = plan
            .as_ref()
            .zip(identified)
            .and_then(|(p, d)| crate::hil::check::declaration_check(p, d));
        let warned = warning.is_some();
        c.insert("declaration_warning".into(), warning.into());
        c.insert("plan".into(), serde_json::to_value(plan)?);
        // A trip judged on the declaration says when the run found the rig unlike it.
        if let Some(faults) = summary["safety"]["faults"].as_array_mut() {
            for l in faults
                .iter_mut()
                .filter_map(|f| f.get_mut("leads_after_trip"))
                .filter(|l| l["judged"] == "declared")
                .filter_map(|l| l.as_object_mut())
            {
                l.insert("declaration_warned".into(), warned.into());
            }
        }
    }
    summary["link"] = link_report(out_dir, rig_setup);
    let text = serde_json::to_string_pretty(&summary)?;
    std::fs::write(out_dir.join("summary.json"), &text)?;
    if args.json {
        // Stdout stays one compact line: the compensation's per-frequency rendering and
        // its trajectory are in summary.json only.
        let mut compact = summary.clone();
        if let Some(c) = compact
            .get_mut("compensation")
            .and_then(|c| c.as_object_mut())
        {
            for key in ["rendering", "trajectory"] {
                if let Some(v) = c.remove(key) {
                    let n = v.as_array().map_or(0, Vec::len);
                    c.insert(format!("{key}_points"), n.into());
                }
            }
        }
        println!("{}", serde_json::to_string(&compact)?);
    }
    if let Some(a) = analysis {
        // An external rig reports no timing of its own (its misses are its own business).
        let rig_timing = match rig_setup {
            RigSetup::External { .. } | RigSetup::ExternalUdp { .. } => {
                "the rig is external: its own timing is not known".to_string()
            }
            _ => format!(
                "the simulated rig's own timing: {} missed",
                summary["deadline_misses_rig"].as_u64().unwrap_or(0)
            ),
        };
        eprintln!(
            "hil: {} steps, {deadline_misses} emulator deadline misses ({:.1e}; {rig_timing}), {} stalls ridden through (longest {:.1} ms{}), largest transient {:.2} um of {:.1} um allowed ({:.2} um after a stall, {:.2} um above the residual before it), displacement rel. RMS error {:.3} % (dynamic, means removed: {:.3} %{}), stable {}, end-to-end p50 {} us p99 {} us",
            a.steps,
            deadline_misses as f64 / a.steps.max(1) as f64,
            a.stalls.count,
            a.stalls.longest_ms,
            // Every run's law ends in a hold (the programme's end too): said only when a
            // fault's hold ended a stall.
            match a.stalls.ended_in_hold {
                n if n > 0 && summary["faults"].as_array().is_some_and(|f| !f.is_empty()) => {
                    format!("; {n} more ended in the fault's hold")
                }
                _ => String::new(),
            },
            a.largest_transient_m * 1e6,
            cfg.safety.max_transient_m * 1e6,
            a.stalls.largest_transient_m * 1e6,
            a.stalls.largest_rise_m.max(0.0) * 1e6,
            a.fidelity.displacement_rel_rms * 100.0,
            a.fidelity.displacement_dynamic_rel_rms * 100.0,
            a.fidelity.dynamic_worst_window.map_or(String::new(), |w| format!(
                "; the worst {:.0} s, from {:.1} s: {:.3} %",
                w.window_s,
                w.from_s,
                w.rel_rms * 100.0
            )),
            // As summary.json's `stable`: a fault makes a run not stable, whatever the
            // residual before it showed (`stability.stable`).
            match (summary["stable"] == true, a.stability.stable) {
                (true, _) => "true",
                (false, true) => "false (a fault; before it the residual did not grow)",
                (false, false) => "false",
            },
            a.latency_ns.end_to_end.p50 / 1000,
            a.latency_ns.end_to_end.p99 / 1000
        );
        // The first command is due within a few periods; a late one is said (the wait is
        // the rig's own hold and not compared, but its load change is a step at the switch).
        if let Some(from) = a
            .fidelity
            .compared_from_s
            .filter(|&t| t > LATE_FIRST_COMMAND_S)
        {
            eprintln!(
                "hil: the first command reached the rig at {:.1} ms; until then its own servo held the start (not compared), and the load's change over that wait met the element as a step",
                from * 1e3
            );
        }
        if let Some(t) = &a.actuator_truth {
            eprintln!("hil: {}", t.describe());
        }
        if cfg.controller.command_mode == crate::hil::config::CommandMode::Law {
            eprintln!("hil: {}", a.compensation.describe());
            if let Some(w) = summary["compensation"]["declaration_warning"].as_str() {
                eprintln!("hil: {w}");
            }
        }
        if let Some(e) = &a.element_thermal {
            eprintln!("hil: {}", e.describe());
        }
        print_programme_and_operator(a, summary["operator_stop"] == true);
        for f in &a.safety.faults {
            eprintln!(
                "hil: fault {}: {}{} at {:.3} s (after {} periods) -> {}{}; largest excursion {} from where it tripped; {} beyond the range it kept before the fault{}; {}",
                f.process,
                f.fault,
                f.cause.as_ref().map_or(String::new(), |c| format!(" ({c})")),
                f.detected_at_s,
                f.detection_latency_periods,
                f.action.as_deref().unwrap_or("the controller acts"),
                f.already_held_since_s.map_or(String::new(), |t| format!(
                    " (the rig already held the specimen, since {t:.3} s)"
                )),
                micrometres(f.largest_excursion_m),
                micrometres(f.beyond_prefault_range_m),
                // Tripped already outside that range: the two measures differ in origin.
                match (f.position_at_fault_m, f.prefault_range_m) {
                    (Some(x), [lo, hi]) if lo.is_finite() && (x > hi || x < lo) => format!(
                        " (it tripped {} outside it)",
                        micrometres(Some((x - hi).max(lo - x)))
                    ),
                    _ => String::new(),
                },
                match f.time_to_rest_s {
                    None => "never at rest".to_string(),
                    Some(t) if t == 0.0 && f.already_held_since_s.is_some() => "already at rest".to_string(),
                    Some(t) => format!("at rest after {t:.3} s"),
                }
            );
            if let Some(seen) = &f.instability {
                eprintln!("hil:   it tripped on {}", seen.describe());
            }
            if let Some(l) = &f.leads_after_trip {
                let unlike = l.judged == crate::hil::check::after_trip::JudgedActuator::Declared
                    && summary["compensation"]["declaration_warning"].is_string();
                eprintln!(
                    "hil:   {}{}",
                    l.describe(),
                    if unlike {
                        " (judged on the declaration, which the run found this rig does not match: see the WARNING above)"
                    } else {
                        ""
                    }
                );
            }
        }
        if let Some(note) = &a.safety.hold_not_recorded {
            eprintln!("hil: {note}");
        }
    }
    // Allocations and frees apart: a free at the end (a counterpart that left before the
    // loops stopped, its connection dropped in a loop's last receive) is iceoryx2's
    // cleanup; an allocation is a port that appeared during the run.
    let count = |key: &str| -> Vec<String> {
        ["emulator", "controller", "rig", "link"]
            .iter()
            .filter_map(|p| {
                let n = summary["rt_pool"][p][key].as_u64()?;
                (n > 0).then(|| format!("{p} {n}"))
            })
            .collect()
    };
    let allocated = count("loop_system_allocations");
    if !allocated.is_empty() {
        eprintln!(
            "hil: a loop allocated from the system allocator ({} times; `rt_pool` in summary.json): beyond the real-time pool (iceoryx2 connecting a port that appeared on a loop's service during the run does)",
            allocated.join(", ")
        );
    }
    let freed = count("loop_system_frees");
    if !freed.is_empty() {
        eprintln!(
            "hil: a loop freed system memory ({} times; `rt_pool` in summary.json): iceoryx2 dropping its connection to a port that left, such as a rig's that ended before the loops stopped",
            freed.join(", ")
        );
    }
    if !outcome.faults.is_empty() {
        eprintln!("hil: FAULT: {}", outcome.faults.join("; "));
        eprintln!("hil: report in {}", out_dir.display());
        // Faults before the loop ever ran (no rig connected, a rig of another link
        // protocol, a process that died while setting up): nothing was loaded or held,
        // so there is no verdict on a run.
        if !outcome.started {
            eprintln!("hil: no verdict: the loop never started");
            return Ok(ExitCode::from(3));
        }
        return Ok(ExitCode::from(2));
    }
    if !clean {
        eprintln!("hil: NOT CLEAN: {}", summary["not_clean_because"]);
        eprintln!("hil: report in {}", out_dir.display());
        return Ok(ExitCode::from(1));
    }
    eprintln!("hil: clean run; report in {}", out_dir.display());
    Ok(ExitCode::SUCCESS)
}

/// The programme's progress and how it ended, and every operator action with its time.
fn print_programme_and_operator(a: &Analysis, operator_stop: bool) {
    let p = &a.programme;
    let ended = if operator_stop {
        "ended by an operator stop (orderly unload)".to_string()
    } else if p.completed {
        "ran to its end".to_string()
    } else if !a.safety.faults.is_empty() {
        "ended by a fault hold".to_string()
    } else {
        format!(
            "stopped at the run's duration ({:.1} s of {:.1} s)",
            p.programme_time_s, p.end_s
        )
    };
    eprintln!(
        "hil: programme: {:.1} s, cycles completed {}, last block {} `{}`; {ended}",
        p.programme_time_s, p.cycles_completed, p.last_block, p.last_block_name
    );
    if !a.safety.operator_actions.is_empty() {
        eprintln!("hil: operator: {}", a.safety.operator_actions.join("; "));
    }
}

/// "12.3 um", or "unknown" when the rig recorded nothing after the fault.
fn micrometres(m: Option<f64>) -> String {
    m.map_or("unknown".into(), |m| {
        if m.abs() >= 0.1 {
            format!("{m:.2} m")
        } else if m.abs() >= 1e-3 {
            format!("{:.2} mm", m * 1e3)
        } else {
            format!("{:.1} um", m * 1e6)
        }
    })
}

#[cfg(test)]
mod tests {
    /// The faults as reported in any order come out deaths and a failed link first, then
    /// by when the records dated them, an undated one last, ties in text order.
    #[test]
    fn faults_are_ordered_as_they_happened() {
        let dated = |process: &str, fault: &str, at: f64| crate::hil::report::safety::FaultReport {
            process: process.into(),
            fault: fault.into(),
            cause: None,
            detected_at_s: at,
            detection_latency_periods: 0,
            action: None,
            hold_started_at_s: None,
            position_at_fault_m: None,
            largest_excursion_m: None,
            prefault_range_m: [0.0; 2],
            beyond_prefault_range_m: None,
            time_to_rest_s: None,
            already_held_since_s: None,
            instability: None,
            leads_after_trip: None,
        };
        let records = [
            dated("emulator", "emulator-stalled", 2.4),
            dated("controller", "setpoints-stale", 2.1005),
            dated("bench_rig", "commands-stale", 2.3),
        ];
        let expected = vec![
            "controller: process (pid 9) killed by signal 9".to_string(),
            "emulator: process (pid 7) killed by signal 9".to_string(),
            "link: the rig went silent".to_string(),
            "controller: setpoints-stale (emulator: emulator-stalled)".to_string(),
            "bench_rig: commands-stale".to_string(),
            "emulator: emulator-stalled".to_string(),
        ];
        // In whatever order they arrived.
        for turn in 0..expected.len() {
            for reversed in [false, true] {
                let mut faults = expected.clone();
                faults.rotate_left(turn);
                if reversed {
                    faults.reverse();
                }
                super::order_faults(&mut faults, &records);
                assert_eq!(faults, expected, "turn {turn}, reversed {reversed}");
            }
        }
    }

    /// A configured injection the records do not show (the run ended first) makes the run
    /// not clean, naming it; none configured, or all fired, says nothing.
    #[test]
    fn an_injection_that_never_fired_is_named() {
        use crate::hil::config::{InjectKind, Injection, LoopProcess};
        let mut cfg = crate::hil::config::default_hil_config().unwrap();
        assert_eq!(super::injections_not_fired(&cfg, 0), None);
        cfg.injections.push(Injection {
            process: LoopProcess::Emulator,
            kind: InjectKind::Stall { duration_s: 0.1 },
            at_s: 9.0,
        });
        assert_eq!(super::injections_not_fired(&cfg, 1), None);
        let why = super::injections_not_fired(&cfg, 0).expect("named");
        assert!(
            why.starts_with("1 of 1 configured [[inject]] faults never fired")
                && why.contains("emulator stall 100 ms at 9.000 s"),
            "{why}"
        );
    }
}
