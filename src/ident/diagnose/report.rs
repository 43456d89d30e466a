//! The diagnosis written out: `report.md`, the plots and the `--json` object (SPEC 5,
//! 5.1). Reads nothing; writes only under the output directory.

use std::fmt::Write as _;
use std::path::PathBuf;

use serde_json::json;

use super::verdict::{order_fraction, Unexplained};
use super::{effect_params, DiagnoseOptions, Diagnosis};
use crate::ident::fit::{predict_cycle, rms_gap, CycleData, EffectKind};
use crate::ident::plots::{
    distinct_levels, plot_equivalents, plot_histories, plot_loops, reconstruct,
};
use crate::model::effects::AugmentedModel;
use crate::plot::{draw_png, Panel, Series};

/// Where the inputs came from and where the outputs go.
pub struct ReportPaths {
    pub campaign: PathBuf,
    pub model: PathBuf,
    pub out: PathBuf,
}

/// What the gap measures, for `metric` in the JSON and the report.
pub fn metric(n_folds: usize) -> String {
    format!(
        "held-out relative RMS residual of the force at the test frequency in excess of measurement noise: sqrt(mean_w |F_sim,1 - F_meas,1|^2 / |F_meas,1|^2 - mean_w nu_i) over the held-out tests, mean_w a precision-weighted mean (weights 1 / max(nu~_i, median nu~ / 2), nu~_i the campaign's smoothed noise level), F_sim,1 from the steady-state force simulated from each test's measured displacement cycle by a model fitted without that test ({n_folds}-fold cross-validation), nu_i the noise share of that residual estimated from the DFT bins next to the test frequency (floored at a tenth of the noise RMS; raw_gap_* include the noise); a history test contributes its band's relative squared residual sum (F_sim - F_meas)^2 / sum (F_meas - mean)^2 and its noise share from the spectrum above the band"
    )
}

/// Latest evaluation of each candidate effect (the round it was named in, else its last).
fn latest_candidates(d: &Diagnosis) -> Vec<&super::CandidateResult> {
    let mut out: Vec<&super::CandidateResult> = Vec::new();
    for kind in EffectKind::ALL {
        let named_round = d
            .rounds
            .iter()
            .flatten()
            .find(|r| r.kind == kind && d.named.get(r.round - 1) == Some(&kind));
        let last = d.rounds.iter().flatten().rfind(|r| r.kind == kind);
        if let Some(r) = named_round.or(last) {
            out.push(r);
        }
    }
    out
}

pub fn json_summary(d: &Diagnosis, model_path: &std::path::Path) -> serde_json::Value {
    let candidates: Vec<serde_json::Value> = latest_candidates(d)
        .iter()
        .map(|r| {
            let params = params_json(&r.model, r.kind);
            json!({
                "effect": r.kind.name(),
                "score": r.score,
                "params": params,
                "round": r.round,
                "raw_held_out_residual": r.raw_gap,
                "gap_ratio": r.gap_ratio,
                "raw_ratio": r.raw_ratio,
                "wilcoxon_z": r.wilcoxon_z,
                "folds_improved": r.folds_improved,
                "history_evidence": r.history_evidence,
                "named": d.named.contains(&r.kind),
                // A named effect's parameters in the final model (refitted beside the
                // effects named after it), which the model file holds.
                "final_params": d.named.contains(&r.kind).then(|| params_json(&d.final_model, r.kind)),
                // Their 95 % intervals (the final fit's covariance joined with the folds'
                // jackknife), and whether the data determine each
                // (`ParamInterval::determined`).
                "final_param_intervals": d.named.contains(&r.kind).then(|| intervals_json(d, r.kind)),
                "would_qualify_but_for_range": r.would_qualify && r.out_of_range.is_some(),
                "out_of_range": r.out_of_range.map(|o| out_of_range_json(&o)),
                "law_broken": r.law_broken,
                "stand_in": r.stand_in,
                "law_note": r.law_note,
            })
        })
        .collect();
    let named: Vec<&str> = d.named.iter().map(|k| k.name()).collect();
    json!({
        "effect": named.first(),
        "effects": named,
        "replaced": d.replaced,
        "gap_before": d.gap_before,
        "gap_after": d.gap_after,
        "raw_gap_before": d.raw_gap_before,
        "raw_gap_after": d.raw_gap_after,
        "noise_floor": d.noise_floor,
        "metric": metric(n_folds(d)),
        "candidates": candidates,
        "not_identifiable": d.not_tried.iter().filter(|n| n.not_identifiable).map(|n| n.kind.name()).collect::<Vec<_>>(),
        "model_out": model_path.display().to_string(),
        "unexplained": unexplained_json(d.verdict.unexplained.as_ref()),
        "held_back_by_materiality": d.verdict.held_back_by_materiality.map(|ratio| json!({
            "gap": d.gap_after, "noise_floor": d.noise_floor, "ratio": ratio,
            "min_gap": super::verdict::MIN_GAP,
        })),
        "specimen_changed": d.verdict.specimen_changed(),
        "residual_wilcoxon_z": d.verdict.harmonic_z,
        "order_trend": d.verdict.trend.as_ref().map(|t| json!({
            "change": t.change, "t": t.t, "beats_design": t.beats_design,
            "by_clock": t.by_clock, "significant": t.significant(),
        })),
        "repeats": d.verdict.repeats.iter().map(|c| json!({
            "first": c.first_id, "last": c.last_id, "change": c.change, "z": c.z,
            "significant": c.significant(), "explained_by": c.explained_by,
        })).collect::<Vec<_>>(),
        "history_tests": d.history_ids,
        "first_cycles_used": d.first_cycles_used.iter().map(|u| json!({
            "test": u.test_id, "history_test": u.unit_id, "n_cycles": u.n_cycles,
            "n_whole_cycles": u.n_whole, "relative_change": u.relative_change,
            "noise_sigma": u.noise_sigma, "reason": u.reason(),
        })).collect::<Vec<_>>(),
    })
}

/// The SPEC 5.1 `unexplained` object (or null).
pub fn unexplained_json(u: Option<&Unexplained>) -> serde_json::Value {
    match u {
        Some(u) => json!({"gap": u.gap, "noise_floor": u.noise_floor, "where": u.where_}),
        None => serde_json::Value::Null,
    }
}

/// The headline sentence on what remains (SPEC 5.1): never "nothing beats the baseline"
/// when the gap is beyond noise.
pub fn unexplained_headline(u: &Unexplained) -> String {
    format!(
        "Unexplained residual: held-out gap {:.3e}, {:.1}x the noise floor {:.3e}, remains after the named effects; it concentrates in: {}",
        u.gap,
        u.gap / u.noise_floor.max(1e-300),
        u.noise_floor,
        u.where_.join("; ")
    )
}

/// Folds actually used (`--folds` is capped at the number of tests).
fn n_folds(d: &Diagnosis) -> usize {
    d.folds.iter().max().map_or(0, |m| m + 1)
}

/// RMS gap per level of a design variable: (level, gap before, gap after, n tests).
fn gap_by(
    d: &Diagnosis,
    data: &[CycleData],
    key: impl Fn(&CycleData) -> f64,
) -> Vec<(f64, f64, f64, usize)> {
    distinct_levels(data.iter().filter(|c| !c.is_history()).map(&key))
        .into_iter()
        .map(|level| {
            let idx: Vec<usize> = (0..data.len())
                .filter(|&i| !data[i].is_history())
                .filter(|&i| {
                    (key(&data[i]) - level).abs()
                        <= 0.01 * level.abs().max(key(&data[i]).abs()) + 1e-9
                })
                .collect();
            let before: Vec<f64> = idx
                .iter()
                .map(|&i| d.baseline_cv.held_out_error[i])
                .collect();
            let after: Vec<f64> = idx.iter().map(|&i| d.final_cv.held_out_error[i]).collect();
            (level, rms_gap(&before), rms_gap(&after), idx.len())
        })
        .collect()
}

/// Residual over the cycle phase (in-sample, full-data fits): RMS across tests of the
/// force residual relative to each test's force scale, at `n` phase points.
fn residual_over_cycle(model: &AugmentedModel, data: &[CycleData], n: usize) -> Vec<f64> {
    let mut sum = vec![0.0; n + 1];
    let data: Vec<&CycleData> = data.iter().filter(|d| !d.is_history()).collect();
    for d in &data {
        let predicted = predict_cycle(model, d);
        let mut diff = [(0.0, 0.0); crate::ident::campaign::N_HARMONICS];
        for h in 0..diff.len() {
            diff[h] = (
                (predicted[h].0 - d.force_harmonics_n[h].0) / d.scale_n,
                (predicted[h].1 - d.force_harmonics_n[h].1) / d.scale_n,
            );
        }
        for (s, r) in sum.iter_mut().zip(reconstruct(&diff, n)) {
            *s += r * r;
        }
    }
    sum.iter()
        .map(|s| (s / data.len().max(1) as f64).sqrt())
        .collect()
}

struct Plots {
    gap_map: PathBuf,
    loops: PathBuf,
    equivalents: PathBuf,
    histories: Option<PathBuf>,
    effects: Option<PathBuf>,
}

fn write_plots(
    args: &ReportPaths,
    d: &Diagnosis,
    data: &[CycleData],
    length_m: f64,
) -> anyhow::Result<Plots> {
    let mut panels = Vec::new();
    type Key = fn(&CycleData) -> f64;
    let factors: [(&str, Key, bool); 4] = [
        ("preload (kN)", |c| c.preload_n / 1e3, false),
        ("frequency (Hz)", |c| c.frequency_hz, true),
        ("force amplitude (kN)", |c| c.amplitude_n / 1e3, false),
        ("temperature (degC)", |c| c.temperature_c, false),
    ];
    for (label, key, log_x) in factors {
        let rows = gap_by(d, data, key);
        let x: Vec<f64> = rows.iter().map(|r| r.0).collect();
        let mut panel = Panel::new(
            format!("held-out raw residual by {label}"),
            label,
            "relative RMS force residual (noise incl.)",
        )
        .log_y()
        .with(Series::line(
            "baseline (calibrated)",
            x.clone(),
            rows.iter().map(|r| r.1.max(1e-6)).collect(),
            1,
        ))
        .with(Series::points(
            "",
            x.clone(),
            rows.iter().map(|r| r.1.max(1e-6)).collect(),
            1,
        ))
        .with(Series::line(
            "augmented",
            x.clone(),
            rows.iter().map(|r| r.2.max(1e-6)).collect(),
            2,
        ))
        .with(Series::points(
            "",
            x,
            rows.iter().map(|r| r.2.max(1e-6)).collect(),
            2,
        ));
        if log_x {
            panel = panel.log_x();
        }
        panels.push(panel);
    }
    // Test order: each test's held-out residual (noise included) against its place in the
    // campaign, with the noise share; history tests drawn as their own series.
    let fractions = order_fraction(data);
    let pick = |history: bool, values: &[f64]| -> (Vec<f64>, Vec<f64>) {
        (0..data.len())
            .filter(|&i| data[i].is_history() == history)
            .map(|i| (fractions[i], values[i].max(1e-12).sqrt()))
            .unzip()
    };
    let noise: Vec<f64> = data.iter().map(|c| c.noise_relative).collect();
    let (xb, yb) = pick(false, &d.baseline_cv.held_out_error);
    let (xa, ya) = pick(false, &d.final_cv.held_out_error);
    let (xn, yn) = pick(false, &noise);
    let mut order_panel = Panel::new(
        if d.verdict.specimen_changed() {
            "held-out residual by test order: THE SPECIMEN CHANGED".to_string()
        } else if d.verdict.unexplained.is_some() {
            "held-out residual by test order (unexplained residual remains)".to_string()
        } else {
            "held-out residual by test order".to_string()
        },
        if d.verdict.trend.as_ref().is_some_and(|t| t.by_clock) {
            "started_at (0 = first test, 1 = last)"
        } else {
            "test order in campaign.toml (0 = first, 1 = last)"
        },
        "relative residual (noise incl.)",
    )
    .log_y()
    .with(Series::points("baseline (calibrated)", xb, yb, 1))
    .with(Series::points("augmented", xa, ya, 2))
    .with(Series::points("noise share", xn, yn, 0));
    if data.iter().any(CycleData::is_history) {
        let (xh, yh) = pick(true, &d.final_cv.held_out_error);
        order_panel = order_panel.with(Series::points("history tests (augmented)", xh, yh, 3));
    }
    panels.push(order_panel);
    let n = 64;
    let phase: Vec<f64> = (0..=n).map(|k| 360.0 * k as f64 / n as f64).collect();
    panels.push(
        Panel::new(
            "gap within the cycle (in-sample)",
            "phase of the fundamental (deg)",
            "RMS relative residual",
        )
        .with(Series::line(
            "baseline (calibrated)",
            phase.clone(),
            residual_over_cycle(&d.baseline_model, data, n),
            1,
        ))
        .with(Series::line(
            "augmented",
            phase,
            residual_over_cycle(&d.final_model, data, n),
            2,
        )),
    );
    let gap_map = args.out.join("gap_map.png");
    draw_png(&gap_map, 1500, 900, 3, &panels)?;
    let histories = args.out.join("histories.png");
    let has_history = data.iter().any(CycleData::is_history);
    if has_history {
        plot_histories(
            &histories,
            data,
            &[
                ("baseline (calibrated)", &d.baseline_model),
                ("augmented", &d.final_model),
            ],
        )?;
    }
    let effect_panels = super::effect_plots::effect_panels(d, data);
    let effects = (!effect_panels.is_empty())
        .then(|| args.out.join("effects.png"))
        .map(|path| {
            let rows = effect_panels.len().div_ceil(2) as u32;
            draw_png(&path, 1400, 500 * rows, 2, &effect_panels).map(|()| path)
        })
        .transpose()?;
    let loops = args.out.join("loops.png");
    // The four harmonic tests where the calibrated baseline misses most (held-out).
    let mut worst: Vec<usize> = (0..data.len()).filter(|&i| !data[i].is_history()).collect();
    worst.sort_by(|&a, &b| {
        d.baseline_cv.held_out_error[b].total_cmp(&d.baseline_cv.held_out_error[a])
    });
    worst.truncate(4);
    plot_loops(
        &loops,
        data,
        &worst,
        &[
            ("baseline (calibrated)", &d.baseline_model),
            ("augmented", &d.final_model),
        ],
    )?;
    let equivalents = args.out.join("keq_ceq.png");
    let harmonic: Vec<CycleData> = data.iter().filter(|c| !c.is_history()).cloned().collect();
    plot_equivalents(
        &equivalents,
        &harmonic,
        length_m,
        &[
            ("baseline (calibrated)", &d.baseline_model),
            ("augmented", &d.final_model),
        ],
        d.reference_temperature_c,
    )?;
    Ok(Plots {
        gap_map,
        loops,
        equivalents,
        histories: has_history.then_some(histories),
        effects,
    })
}

fn render_report(
    args: &ReportPaths,
    d: &Diagnosis,
    data: &[CycleData],
    plots: &Plots,
    model_path: &std::path::Path,
    elapsed_s: f64,
) -> String {
    let mut r = String::new();
    let named: Vec<&str> = d.named.iter().map(|k| k.name()).collect();
    let _ = writeln!(r, "# Discrepancy report\n");
    let n_history = data.iter().filter(|c| c.is_history()).count();
    if let Some(u) = &d.verdict.unexplained {
        let _ = writeln!(r, "**{}.**\n", unexplained_headline(u));
    }
    if d.verdict.specimen_changed() {
        let _ = writeln!(r, "**{}**\n", specimen_sentence(d));
    }
    let _ = writeln!(
        r,
        "- Campaign: `{}` ({} harmonic tests, {n_history} history tests)",
        args.campaign.display(),
        data.len() - n_history
    );
    if !d.first_cycles_used.is_empty() {
        let _ = writeln!(
            r,
            "- First cycles used as history tests ({} harmonic tests whose first cycle differs from their steady cycles beyond noise): {}",
            d.first_cycles_used.len(),
            d.first_cycles_used
                .iter()
                .map(|u| u.reason())
                .collect::<Vec<_>>()
                .join("; ")
        );
    }
    let _ = writeln!(r, "- Baseline model: `{}`", args.model.display());
    let _ = writeln!(
        r,
        "- **Named effects: {}**",
        if !named.is_empty() {
            named.join(", ")
        } else if d.verdict.unexplained.is_some() {
            "none: no library effect explains the gap within its physical range (see the unexplained residual above)".to_string()
        } else {
            "none (no library effect beats the calibrated baseline beyond noise; the residual: below)".to_string()
        }
    );
    for why in &d.replaced {
        let _ = writeln!(r, "- Replaced: {why}.");
    }
    if let (None, Some(ratio)) = (&d.verdict.unexplained, d.verdict.held_back_by_materiality) {
        let _ = writeln!(
            r,
            "- Unexplained residual: not reported, held back only by the materiality rule: the held-out gap after the named effects, {:.3e}, is {ratio:.1}x the noise floor and beyond noise, but below {:.0e} of the force (0.1 %), the smallest residual this workflow calls a discrepancy",
            d.gap_after,
            super::verdict::MIN_GAP
        );
    } else if d.verdict.unexplained.is_none() {
        let _ = writeln!(
            r,
            "- Unexplained residual: {}",
            residual_within_rules(
                d.gap_after / d.noise_floor.max(1e-300),
                d.verdict.harmonic_z
            )
        );
    }
    // Whether the specimen changed, in the opening lines whatever the answer (a change
    // is the bold headline above).
    if !d.verdict.specimen_changed() {
        let _ = writeln!(
            r,
            "- Specimen: {}",
            match &d.verdict.trend {
                Some(t) => format!(
                    "no change beyond noise during the campaign (in-phase residual {:+.3} % from the first to the last test, t = {:.2}; below: test order and repeated tests)",
                    100.0 * t.change,
                    t.t
                ),
                None => "too few tests to judge a change with test order".to_string(),
            }
        );
    }
    let unphysical: Vec<&super::CandidateResult> = d
        .rounds
        .iter()
        .flatten()
        .filter(|c| c.would_qualify && (c.out_of_range.is_some() || c.law_broken.is_some()))
        .collect();
    for c in &unphysical {
        if let Some(o) = c.out_of_range {
            let _ = writeln!(
                r,
                "- `{}` {o}: not named. This suggests {}.",
                c.kind.name(),
                o.suggestion()
            );
        } else if let Some(b) = &c.law_broken {
            let why = match c.kind {
                crate::ident::fit::EffectKind::ChannelDelay => "A lead of the force channel adds loss rising with frequency, as a relaxation with a time scale of its own (a second Maxwell branch) does below its corner; where the branch fits better the delay stood in for it, and the library does not hold such a relaxation.",
                _ => "A springpot has one order at every frequency and must beat a discrete relaxation in its place; an order that changes with the band, or a branch that fits better, suggests a relaxation with a time scale of its own (a second Maxwell branch), which the library does not hold.",
            };
            let _ = writeln!(r, "- `{}` {b}: not named. {why}", c.kind.name());
        }
    }
    for c in d.rounds.iter().flatten() {
        if let Some(why) = &c.stand_in {
            let _ = writeln!(r, "- `{}` {why}: not named.", c.kind.name());
        }
    }
    if !unphysical.is_empty() && !named.is_empty() && d.verdict.unexplained.is_some() {
        let _ = writeln!(
            r,
            "- The best fit of the library is unphysical and a residual remains: the named effects may stand in for a cause outside the library."
        );
    }
    let _ = writeln!(
        r,
        "- Held-out gap: **{:.4e} -> {:.4e}** ({:.1}x smaller)",
        d.gap_before,
        d.gap_after,
        d.gap_before / d.gap_after.max(1e-300)
    );
    let _ = writeln!(
        r,
        "- Raw held-out RMS residual (noise included): {:.4e} -> {:.4e}; estimated noise floor {:.4e}",
        d.raw_gap_before, d.raw_gap_after, d.noise_floor
    );
    let _ = writeln!(r, "- Gap metric: {}.", metric(n_folds(d)));
    for note in model_notes(d, data) {
        let _ = writeln!(r, "- {note}");
    }
    for c in d.rounds.iter().flatten() {
        // The note of the fit that was named (earlier rounds' fits of it were not).
        if let (Some(note), true) = (&c.law_note, c.qualifies && d.named.contains(&c.kind)) {
            let _ = writeln!(r, "- `{}` {note}", c.kind.name());
        }
    }
    for kind in &d.named {
        let intervals = d.final_template.effect_intervals(&d.final_cv, *kind);
        if intervals.is_empty() {
            continue;
        }
        let text: Vec<String> = intervals.iter().map(interval_text).collect();
        let _ = writeln!(
            r,
            "- `{}` fitted (95 % interval): {}",
            kind.name(),
            text.join(", ")
        );
        let loose: Vec<&str> = intervals
            .iter()
            .filter(|i| !i.determined())
            .map(|i| i.name)
            .collect();
        if !loose.is_empty() {
            let _ = writeln!(
                r,
                "- **`{}`: {} not determined by these data** (95 % interval wider than a factor of 10, or the value on the fit's bound): the effect is named because it lowers the held-out gap, but do not act on {} value{} without tests that pin it down.",
                kind.name(),
                loose.join(", "),
                if loose.len() == 1 { "that" } else { "those" },
                if loose.len() == 1 { "" } else { "s" }
            );
        }
    }
    let _ = writeln!(r, "- Augmented model: `{}`", model_path.display());
    let _ = writeln!(
        r,
        "- Reference temperature: {} degC; run time {elapsed_s:.1} s\n",
        d.reference_temperature_c
    );

    let _ = writeln!(r, "## Calibrated baseline (structure kept)\n");
    let se = d.baseline_cv.full_fit.standard_errors();
    let _ = writeln!(
        r,
        "| parameter (fitted scale) | value | standard error |\n| --- | --- | --- |"
    );
    for ((name, value), se) in d
        .baseline_template
        .param_names()
        .iter()
        .zip(&d.baseline_cv.full_fit.params)
        .zip(&se)
    {
        let _ = writeln!(
            r,
            "| {name} | {value:.5} | {} |",
            se.map_or("n/a".into(), |s| format!("{s:.2e}"))
        );
    }
    let _ = writeln!(
        r,
        "\nBaseline model file after calibration:\n\n```toml\n{}```\n",
        d.baseline_model.render_toml("")
    );

    let _ = writeln!(r, "## Candidates\n");
    let _ = writeln!(
        r,
        "Each candidate is the current model plus one effect, fitted on the training folds and scored on the held-out fold. \
         Score = held-out gap ratio (noise excluded) x (1 + 0.02 per extra parameter). Named only if score < {}, \
         the penalised raw-residual ratio < {}, the paired Wilcoxon z (per-test held-out errors, noise-normalised) > {}, \
         it is better in at least K-1 of K folds (or every history test beyond its noise loses most of its excess while the harmonic tests do not get worse), \
         it explains a held-out gap above {:.0e}, and its fitted parameters lie inside their physical range.\n",
        DiagnoseOptions::default().max_score,
        DiagnoseOptions::default().max_raw_ratio,
        DiagnoseOptions::default().min_wilcoxon_z,
        DiagnoseOptions::default().min_explained_gap
    );
    let _ = writeln!(r, "| round | effect | raw held-out residual | gap ratio | score | Wilcoxon z | folds better | qualifies | parameters |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for c in d.rounds.iter().flatten() {
        let params = params_text(&c.model, c.kind);
        let _ = writeln!(
            r,
            "| {} | {} | {:.4e} | {:.3} | {:.3} | {:.2} | {}/{} | {} | {params} |",
            c.round,
            c.kind.name(),
            c.raw_gap,
            c.gap_ratio,
            c.score,
            c.wilcoxon_z,
            c.folds_improved,
            d.folds.iter().max().map_or(0, |m| m + 1),
            match (c.qualifies, c.out_of_range, &c.law_broken) {
                _ if c.stand_in.is_some() => "no: a stand-in (below)".to_string(),
                (_, Some(o), _) => format!("no: {o}"),
                (_, None, Some(b)) => format!("no: {b}"),
                (true, None, None) if c.history_evidence => "yes (history tests)".to_string(),
                (true, None, None) => "yes".to_string(),
                (false, None, None) => "no".to_string(),
            }
        );
    }
    let _ = writeln!(r, "\n### Not tried\n");
    if d.not_tried.is_empty() {
        let _ = writeln!(r, "Every effect of the library was tried.");
    }
    for n in &d.not_tried {
        let _ = writeln!(
            r,
            "- `{}`: {}{}",
            n.kind.name(),
            if n.not_identifiable {
                "not identifiable: "
            } else {
                ""
            },
            n.reason
        );
    }

    let _ = writeln!(r, "\n## Where the gap lives (raw held-out residual per level, noise included, before -> after)\n");
    type Key = fn(&CycleData) -> f64;
    let factors: [(&str, Key); 4] = [
        ("preload (kN)", |c| c.preload_n / 1e3),
        ("frequency (Hz)", |c| c.frequency_hz),
        ("force amplitude (kN)", |c| c.amplitude_n / 1e3),
        ("temperature (degC)", |c| c.temperature_c),
    ];
    for (label, key) in factors {
        let _ = writeln!(
            r,
            "| {label} | tests | gap before | gap after |\n| --- | --- | --- | --- |"
        );
        for (level, before, after, n) in gap_by(d, data, key) {
            let _ = writeln!(r, "| {level:.4} | {n} | {before:.4e} | {after:.4e} |");
        }
        let _ = writeln!(r);
    }
    let _ = writeln!(r, "### Test order and repeated tests\n");
    match &d.verdict.trend {
        Some(t) => {
            let _ = writeln!(
                r,
                "In-phase residual against test order ({}): {:+.3} % from the first to the last test, t = {:.2}; order explains the residuals {} than any design variable. {}",
                if t.by_clock { "started_at" } else { "order in campaign.toml" },
                100.0 * t.change,
                t.t,
                if t.beats_design { "better" } else { "no better" },
                if t.significant() {
                    "**The specimen changed during the campaign.**"
                } else {
                    "No change of the specimen beyond noise."
                }
            );
        }
        None => {
            let _ = writeln!(r, "Too few tests for a trend with test order.");
        }
    }
    if d.verdict.repeats.is_empty() {
        let _ = writeln!(
            r,
            "\nNo test was repeated. A lab's habit that makes drift visible without any model: repeat the first test at the end of the campaign (same settings); diagnose compares repeated tests directly."
        );
    }
    for c in &d.verdict.repeats {
        let _ = writeln!(
            r,
            "\nRepeated test {} -> {}: measured dynamic stiffness {:+.3} % (z = {:.1}){}",
            c.first_id,
            c.last_id,
            100.0 * c.change,
            c.z,
            match (c.significant(), c.explained_by) {
                (true, Some(effect)) => format!(
                    ": beyond noise, but the named {effect} reproduces both tests (the repeat ran warmer): no change of the specimen"
                ),
                (true, None) => ": the specimen changed between them.".to_string(),
                _ => ": no change beyond noise.".to_string(),
            }
        );
    }
    let _ = writeln!(r);
    let _ = writeln!(r, "Per test (held-out relative residual at the test frequency, noise included, and the estimated noise share):\n\n| test | preload (kN) | f (Hz) | amplitude (kN) | T (degC) | before | after | noise |\n| --- | --- | --- | --- | --- | --- | --- | --- |");
    for (i, t) in data.iter().enumerate() {
        if t.is_history() {
            continue;
        }
        let _ = writeln!(
            r,
            "| {} | {:.1} | {} | {:.2} | {:.1} | {:.3e} | {:.3e} | {:.3e} |",
            t.id,
            t.preload_n / 1e3,
            t.frequency_hz,
            t.amplitude_n / 1e3,
            t.temperature_c,
            d.baseline_cv.held_out_error[i].sqrt(),
            d.final_cv.held_out_error[i].sqrt(),
            t.noise_relative.sqrt()
        );
    }
    if data.iter().any(CycleData::is_history) {
        let _ = writeln!(r, "\nHistory tests (held-out relative residual in the band, noise included, and the noise share):\n\n| test | band (Hz) | force range (kN) | T (degC) | before | after | noise | beyond noise after |\n| --- | --- | --- | --- | --- | --- | --- | --- |");
        for (i, t) in data.iter().enumerate() {
            let Some(h) = &t.history else { continue };
            let _ = writeln!(
                r,
                "| {} | {:.1} | {:.1}-{:.1} | {:.1} | {:.3e} | {:.3e} | {:.3e} | {} |",
                t.id,
                h.band_hz,
                h.force_min_n / 1e3,
                h.force_max_n / 1e3,
                t.temperature_c,
                d.baseline_cv.held_out_error[i].sqrt(),
                d.final_cv.held_out_error[i].sqrt(),
                t.noise_relative.sqrt(),
                if super::verdict::history_beyond_noise(
                    d.final_cv.held_out_error[i],
                    t.noise_relative,
                    h.dof
                ) {
                    "yes"
                } else {
                    "no"
                }
            );
        }
    }
    let _ = writeln!(r, "\n## Plots\n");
    let mut listed = vec![
        ("Gap map", &plots.gap_map),
        ("Loops", &plots.loops),
        ("k_eq and c_eq", &plots.equivalents),
    ];
    if let Some(h) = &plots.histories {
        listed.push(("History tests: measured, baseline and augmented force", h));
    }
    if let Some(e) = &plots.effects {
        listed.push(("The named effects of the campaign's time and the rig", e));
    }
    for (title, path) in listed {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        let _ = writeln!(r, "![{title}]({name})\n");
    }
    let _ = writeln!(
        r,
        "k_eq/c_eq curves are drawn at the reference temperature and each preload's median displacement amplitude; \
         points marked (at tests) are each model's prediction for the actual tests. Loops show the dynamic \
         (mean-removed) steady-state cycle."
    );
    r
}

/// Writes `augmented_model.toml`, the plots and `report.md` under `paths.out`; returns the
/// `--json` object.
pub fn write_outputs(
    paths: &ReportPaths,
    diagnosis: &Diagnosis,
    data: &[CycleData],
    length_m: f64,
    started: std::time::Instant,
) -> anyhow::Result<serde_json::Value> {
    use anyhow::Context;
    let args = paths;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let model_path = args.out.join("augmented_model.toml");
    let header = format!(
        "Augmented by `fastemu diagnose` from baseline {} and campaign {}.\nNamed effects: {}. Held-out gap {:.4e} -> {:.4e}.\nSet operating_temperature_c of temperature-shift to the rig temperature. channel-delay, moving-mass and\nload-train-resonance are rig artefacts: the emulator (StepperMode::Emulation) leaves them out.{}",
        args.model.display(),
        args.campaign.display(),
        if diagnosis.named.is_empty() { "none".to_string() } else { diagnosis.named.iter().map(|k| k.name()).collect::<Vec<_>>().join(", ") },
        diagnosis.gap_before,
        diagnosis.gap_after,
        model_notes(diagnosis, data)
            .iter()
            .map(|n| format!("\n{n}"))
            .collect::<String>()
    );
    std::fs::write(&model_path, diagnosis.final_model.render_toml(&header))
        .with_context(|| format!("cannot write {}", model_path.display()))?;
    eprintln!("diagnose: writing plots");
    let plots = write_plots(args, diagnosis, data, length_m)?;
    let elapsed_s = started.elapsed().as_secs_f64();
    let report = render_report(args, diagnosis, data, &plots, &model_path, elapsed_s);
    let report_path = args.out.join("report.md");
    std::fs::write(&report_path, report)
        .with_context(|| format!("cannot write {}", report_path.display()))?;
    eprintln!(
        "diagnose: named [{}], held-out gap {:.4e} -> {:.4e}; report {} ({elapsed_s:.1} s)",
        diagnosis
            .named
            .iter()
            .map(|k| k.name())
            .collect::<Vec<_>>()
            .join(", "),
        diagnosis.gap_before,
        diagnosis.gap_after,
        report_path.display()
    );
    Ok(json_summary(diagnosis, &model_path))
}

/// What the written model describes for effects that depend on the campaign's time: the
/// instant a drift's element parameters describe, a self-heating's thermal state and law,
/// what a load train's participating mass would need. One line each.
pub fn model_notes(d: &Diagnosis, data: &[CycleData]) -> Vec<String> {
    use crate::model::effects::Effect;
    let mut notes = Vec::new();
    for effect in &d.final_model.effects {
        match *effect {
            Effect::SpecimenDrift {
                clock,
                rate_per_unit,
                rate_standard_error,
                clock_position,
            } => {
                let reference = data
                    .iter()
                    .find(|c| c.time.schedule.is_some() && c.time.schedule_index == 0)
                    .map_or("the campaign's first test".to_string(), |c| {
                        format!("the start of the campaign's first test, `{}`", c.id)
                    });
                notes.push(format!(
                    "specimen-drift: the element parameters describe the specimen at the reference instant, {reference} (clock_position = {clock_position} there); its moduli change by {:+.3e} +- {:.1e} per {} of {} (1 sigma).",
                    rate_per_unit,
                    rate_standard_error,
                    clock.unit(),
                    clock.name()
                ));
            }
            Effect::SelfHeating {
                heat_capacity_j_per_k,
                heat_transfer_w_per_k,
                temperature_rise_k,
            } => {
                let law = if d.final_model.find("temperature-shift").is_some() {
                    "the temperature law of temperature-shift".to_string()
                } else {
                    format!(
                        "the default temperature law ({:.1} %/degC modulus, relaxation times {:.3} decades/degC; no temperature-shift was named)",
                        -100.0 * crate::model::thermal::DEFAULT_LN_MODULUS_SHIFT_PER_C,
                        -crate::model::thermal::DEFAULT_LOG10_TIME_SHIFT_PER_C
                    )
                };
                notes.push(format!(
                    "self-heating: thermal time constant C/h = {:.0} s, {:.3} K per W dissipated at steady state; temperature_rise_k = {temperature_rise_k} (the specimen at its ambient when the model starts); its temperature drives {law}.",
                    heat_capacity_j_per_k / heat_transfer_w_per_k,
                    1.0 / heat_transfer_w_per_k
                ));
            }
            Effect::CyclicSoftening { max_force_n, .. } => notes.push(format!(
                "cyclic-softening: max_force_n = {max_force_n} is a state, not a fitted parameter: the largest virgin force the element carried before the model starts (0: the virgin specimen); it rises as the element is loaded beyond it."
            )),
            Effect::LoadTrainResonance {
                natural_frequency_hz,
                ..
            } => notes.push(format!(
                "load-train-resonance: a rig artefact (never emulated); its participating mass is the load train's stiffness k over (2 pi {natural_frequency_hz:.1} Hz)^2, which force and displacement records alone do not give: m = k x {:.3e} kg per N/m.",
                1.0 / (2.0 * std::f64::consts::PI * natural_frequency_hz).powi(2)
            )),
            _ => {}
        }
    }
    notes
}

/// The sentence for a specimen that changed during the campaign.
pub fn specimen_sentence(d: &Diagnosis) -> String {
    let mut parts = Vec::new();
    if let Some(t) = d.verdict.trend.as_ref().filter(|t| t.significant()) {
        parts.push(format!(
            "the residual trends with test order: the measured force fell {:.2} % against the model from the first to the last test (t = {:.1}){}",
            100.0 * t.change,
            t.t,
            if t.by_clock { ", by started_at" } else { ", in campaign order" }
        ));
    }
    for c in d.verdict.repeats.iter().filter(|c| c.shows_a_change()) {
        parts.push(format!(
            "repeated test {} -> {} changed its dynamic stiffness by {:+.2} % (z = {:.1})",
            c.first_id,
            c.last_id,
            100.0 * c.change,
            c.z
        ));
    }
    if let Some(crate::model::effects::Effect::SpecimenDrift {
        clock,
        rate_per_unit,
        rate_standard_error,
        ..
    }) = d.final_model.find("specimen-drift")
    {
        parts.push(format!(
            "named as specimen-drift: the moduli change by {:+.3e} +- {:.1e} per {} of {} (the element parameters describe the first test)",
            rate_per_unit,
            rate_standard_error,
            clock.unit(),
            clock.name()
        ));
        return format!(
            "The specimen changed during the campaign: {}.",
            parts.join("; ")
        );
    }
    if d.final_model.find("cyclic-softening").is_some() {
        parts.push(
            "named as cyclic-softening: below the largest load it had carried the specimen was softer (the element parameters describe the virgin specimen)".into(),
        );
        return format!(
            "The specimen changed during the campaign: {}.",
            parts.join("; ")
        );
    }
    format!(
        "The specimen changed during the campaign: {}. Effects named from such a campaign may stand in for the change; repeat the first test at the end to check.",
        parts.join("; ")
    )
}

/// Writes the run diagnosis (`report.md`, `histories.png`, `augmented_model.toml`) under
/// `out`; returns the `--json` object (SPEC 5 keys, `unexplained`, and `advice`).
pub fn write_run_outputs(
    run_dir: &std::path::Path,
    model_label: &str,
    record: &crate::ident::runrec::RunHistory,
    out: &std::path::Path,
    d: &super::run::RunDiagnosis,
    config: &crate::hil::config::HilConfig,
    started: std::time::Instant,
) -> anyhow::Result<serde_json::Value> {
    use anyhow::Context;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let advice = run_advice(d, config, record.external_rig);
    let record_used = record.used.as_str();
    let named: Vec<&str> = d.named.iter().map(|k| k.name()).collect();
    let model_path = out.join("augmented_model.toml");
    let header = format!(
        "Rig artefacts of run {} fitted by `fastemu diagnose --run` to the model {model_label} (not recalibrated).\nNamed: {}. The emulator (StepperMode::Emulation) leaves channel-delay, moving-mass and load-train-resonance out.",
        run_dir.display(),
        if named.is_empty() { "none".to_string() } else { named.join(", ") }
    );
    std::fs::write(&model_path, d.final_model.render_toml(&header))
        .with_context(|| format!("cannot write {}", model_path.display()))?;
    let plot_path = out.join("histories.png");
    plot_histories(
        &plot_path,
        std::slice::from_ref(&d.unit),
        &[
            ("run's model", &d.model),
            ("with named artefacts", &d.final_model),
        ],
    )?;
    let elapsed_s = started.elapsed().as_secs_f64();
    let mut r = String::new();
    let _ = writeln!(r, "# Loop diagnosis of a HIL run\n");
    for a in &advice {
        let _ = writeln!(r, "**{a}.**\n");
    }
    if let Some(u) = &d.unexplained {
        let _ = writeln!(r, "**{}.**\n", unexplained_headline(u));
    }
    let _ = writeln!(
        r,
        "- Run: `{}`; model: {model_label} (as the emulator ran it, not recalibrated)",
        run_dir.display()
    );
    let _ = writeln!(r, "- Record used: {record_used}");
    if let Some((max_k, last_k)) = record.element_temperature_rise_k {
        let _ = writeln!(
            r,
            "- Element temperature (self-heating, the emulator's `/emulator` records, `element_temperature_rise_k`): rose up to {max_k:.3} K above its ambient, {last_k:.3} K at the end; the model replays it step by step"
        );
    }
    let _ = writeln!(
        r,
        "- **Named rig artefacts: {}**",
        if named.is_empty() {
            "none".to_string()
        } else {
            named.join(", ")
        }
    );
    let _ = writeln!(
        r,
        "- Relative RMS residual of the applied force against the emulated model (band to {:.0} Hz, noise included): **{:.4e} -> {:.4e}**; estimated noise floor {:.4e}",
        d.unit.history.as_ref().map_or(0.0, |h| h.band_hz),
        d.gap_before,
        d.gap_after,
        d.noise_floor
    );
    let _ = writeln!(r, "- Run time {elapsed_s:.2} s\n");
    let _ = writeln!(r, "| round | artefact | relative residual | parameters | qualifies |\n| --- | --- | --- | --- | --- |");
    for c in &d.candidates {
        let params = params_text(&c.model, c.kind);
        let _ = writeln!(
            r,
            "| {} | {} | {:.4e} | {params} | {} |",
            c.round,
            c.kind.name(),
            c.error.sqrt(),
            match c.out_of_range {
                Some(o) => format!("no: {o}; {}", o.suggestion()),
                None if c.qualifies => "yes".into(),
                None => "no".into(),
            }
        );
    }
    let _ = writeln!(r, "\n![measured vs emulated force](histories.png)");
    let report_path = out.join("report.md");
    std::fs::write(&report_path, r)
        .with_context(|| format!("cannot write {}", report_path.display()))?;
    eprintln!(
        "diagnose: run record: named [{}], residual {:.4e} -> {:.4e}; report {} ({elapsed_s:.2} s)",
        named.join(", "),
        d.gap_before,
        d.gap_after,
        report_path.display()
    );
    for a in &advice {
        eprintln!("diagnose: {a}");
    }
    let candidates: Vec<serde_json::Value> = d
        .candidates
        .iter()
        .map(|c| {
            let params = params_json(&c.model, c.kind);
            json!({
                "effect": c.kind.name(),
                "score": c.gap / d.gap_before.max(1e-300),
                "params": params,
                "round": c.round,
                "named": d.named.contains(&c.kind) && c.qualifies,
                "out_of_range": c.out_of_range.map(|o| out_of_range_json(&o)),
            })
        })
        .collect();
    Ok(json!({
        "effect": named.first(),
        "effects": named,
        "gap_before": d.gap_before,
        "gap_after": d.gap_after,
        "noise_floor": d.noise_floor,
        "metric": "relative RMS residual of the applied (actuator) force against the force of the run's own model driven by the measured displacement, inside the record's signal band (noise included; noise_floor is the noise share estimated from the spectrum above the band)",
        "candidates": candidates,
        "not_identifiable": Vec::<&str>::new(),
        "model_out": model_path.display().to_string(),
        "unexplained": unexplained_json(d.unexplained.as_ref()),
        "advice": advice,
        "element_temperature_rise_k": record.element_temperature_rise_k.map(|(max_k, last_k)| json!({"max": max_k, "last": last_k})),
        "force_lag_s": d.force_lag_s(),
        "record_used": record_used,
    }))
}

/// What the named artefacts mean for the run, in the words of its config.
fn run_advice(
    d: &super::run::RunDiagnosis,
    config: &crate::hil::config::HilConfig,
    external_rig: bool,
) -> Vec<String> {
    let mut out = Vec::new();
    for effect in &d.final_model.effects {
        match *effect {
            crate::model::effects::Effect::ChannelDelay { force_lag_s }
                if d.named.contains(&EffectKind::ChannelDelay) =>
            {
                out.push(crate::ident::runrec::delay_knob_advice(
                    config,
                    force_lag_s,
                    external_rig,
                ));
            }
            crate::model::effects::Effect::MovingMass { mass_kg }
                if d.named.contains(&EffectKind::MovingMass) =>
            {
                out.push(format!(
                    "the applied force carries {mass_kg:.1} kg times the measured acceleration beyond the emulated force: a mass the loop does not account for (the rig's moving parts between actuator and specimen)"
                ));
            }
            _ => {}
        }
    }
    if out.is_empty() && d.unexplained.is_none() {
        out.push(format!(
            "no loop artefact found: neither a delay nor a mass lowers the residual of the applied force ({:.2e}) consistently",
            d.gap_after
        ));
    }
    out
}

/// An effect's parameters as `name = value, ...` (file units).
fn params_text(model: &AugmentedModel, kind: EffectKind) -> String {
    effect_params(model, kind)
        .iter()
        .map(|(k, v)| match *k {
            // States the model starts from, not fitted (a lab read a 0 as a fit).
            "max_force_n" | "temperature_rise_k" => format!("{k} = {v:.4e} (state)"),
            _ => format!("{k} = {v:.4e}"),
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// `name = value (lo .. hi)`, or `(interval n/a)` when the covariance is singular.
fn interval_text(i: &crate::ident::fit::ParamInterval) -> String {
    if i.on_bound {
        return format!(
            "{} = {:.3e} (on the fit's bound: no interval)",
            i.name, i.value
        );
    }
    match i.ci95 {
        Some((lo, hi)) => format!(
            "{} = {:.3e} ({lo:.2e} .. {hi:.2e}{})",
            i.name,
            i.value,
            if i.consistent_with_zero() {
                ": about 0"
            } else {
                ""
            }
        ),
        None => format!("{} = {:.3e} (interval n/a: singular fit)", i.name, i.value),
    }
}

/// A named effect's parameter intervals in the final model, as a JSON object.
fn intervals_json(d: &Diagnosis, kind: crate::ident::fit::EffectKind) -> serde_json::Value {
    d.final_template
        .effect_intervals(&d.final_cv, kind)
        .into_iter()
        .map(|i| {
            (
                i.name.to_string(),
                json!({"value": i.value, "ci95": i.ci95.map(|(lo, hi)| [lo, hi]), "determined": i.determined(), "consistent_with_zero": i.consistent_with_zero(), "on_bound": i.on_bound}),
            )
        })
        .collect::<serde_json::Map<String, serde_json::Value>>()
        .into()
}

/// An effect's parameters as a JSON object (file units).
fn params_json(model: &AugmentedModel, kind: EffectKind) -> serde_json::Value {
    effect_params(model, kind)
        .into_iter()
        .map(|(k, v)| (k.to_string(), json!(v)))
        .collect::<serde_json::Map<String, serde_json::Value>>()
        .into()
}

fn out_of_range_json(o: &crate::ident::fit::OutOfRange) -> serde_json::Value {
    json!({
        "param": o.param, "value": o.value, "range": [o.range.0, o.range.1],
        "text": o.to_string(), "suggests": o.suggestion(),
    })
}

/// Why no residual is reported when neither the noise nor materiality explains it away:
/// within noise, or beyond noise by the harmonic tests' Wilcoxon z but under the ratio to
/// the noise floor from which the workflow reports one (`verdict::MIN_RATIO`).
fn residual_within_rules(ratio: f64, harmonic_z: f64) -> String {
    use super::verdict::{MIN_RATIO, MIN_Z};
    if harmonic_z > MIN_Z && ratio < MIN_RATIO {
        format!(
            "none reported: the held-out gap after the named effects is {ratio:.1}x the noise floor, beyond noise by the harmonic tests' Wilcoxon z ({harmonic_z:.1} > {MIN_Z}), but under the {MIN_RATIO:.0}x the noise floor from which this workflow reports a residual"
        )
    } else {
        format!(
            "none (the held-out gap after the named effects is {ratio:.1}x the noise floor, within noise: Wilcoxon z {harmonic_z:.1})"
        )
    }
}

#[cfg(test)]
mod residual_wording_tests {
    /// A gap 1.6x the floor with z 3.6 is said to be beyond noise and held back by the
    /// 2x rule, not "at the noise floor"; a gap within noise is said to be within noise.
    #[test]
    fn a_residual_beyond_noise_under_the_ratio_rule_says_so() {
        let held = super::residual_within_rules(1.6, 3.58);
        assert!(
            held.contains("1.6x the noise floor, beyond noise")
                && held.contains("Wilcoxon z (3.6 > 2.33)")
                && held.contains("under the 2x"),
            "{held}"
        );
        let within = super::residual_within_rules(0.9, 0.4);
        assert!(
            within.contains("0.9x the noise floor, within noise"),
            "{within}"
        );
        assert!(!within.contains("beyond"), "{within}");
    }
}
