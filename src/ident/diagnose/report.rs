//! The diagnosis written out: `report.md`, the plots and the `--json` object (SPEC 5,
//! 5.1). Reads nothing; writes only under the output directory.

use std::fmt::Write as _;
use std::path::PathBuf;

use serde_json::json;

use super::{effect_params, DiagnoseOptions, Diagnosis};
use crate::ident::fit::{predict_cycle, rms_gap, CycleData, EffectKind};
use crate::ident::plots::{distinct_levels, plot_equivalents, plot_loops, reconstruct};
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
        "held-out relative RMS residual of the force at the test frequency in excess of measurement noise: sqrt(mean_w |F_sim,1 - F_meas,1|^2 / |F_meas,1|^2 - mean_w nu_i) over the harmonic tests, mean_w a precision-weighted mean (weights 1 / max(nu~_i, median nu~ / 2), nu~_i the campaign's smoothed noise level), F_sim,1 from the steady-state force simulated from each test's measured displacement cycle by a model fitted without that test ({n_folds}-fold cross-validation), nu_i the noise share of that residual estimated from the DFT bins next to the test frequency (floored at a tenth of the noise RMS; raw_gap_* include the noise)"
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
            let params: serde_json::Map<String, serde_json::Value> =
                effect_params(&r.model, r.kind)
                    .into_iter()
                    .map(|(k, v)| (k.to_string(), json!(v)))
                    .collect();
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
                "named": d.named.contains(&r.kind),
            })
        })
        .collect();
    let named: Vec<&str> = d.named.iter().map(|k| k.name()).collect();
    json!({
        "effect": named.first(),
        "effects": named,
        "gap_before": d.gap_before,
        "gap_after": d.gap_after,
        "raw_gap_before": d.raw_gap_before,
        "raw_gap_after": d.raw_gap_after,
        "noise_floor": d.noise_floor,
        "metric": metric(n_folds(d)),
        "candidates": candidates,
        "not_identifiable": d.not_tried.iter().filter(|n| n.not_identifiable).map(|n| n.kind.name()).collect::<Vec<_>>(),
        "model_out": model_path.display().to_string(),
    })
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
    distinct_levels(data.iter().map(&key))
        .into_iter()
        .map(|level| {
            let idx: Vec<usize> = (0..data.len())
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
    for d in data {
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
    let loops = args.out.join("loops.png");
    // The four tests where the calibrated baseline misses most (held-out).
    let mut worst: Vec<usize> = (0..data.len()).collect();
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
    plot_equivalents(
        &equivalents,
        data,
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
    let _ = writeln!(
        r,
        "- Campaign: `{}` ({} harmonic tests)",
        args.campaign.display(),
        data.len()
    );
    let _ = writeln!(r, "- Baseline model: `{}`", args.model.display());
    let _ = writeln!(
        r,
        "- **Named effects: {}**",
        if named.is_empty() {
            "none (nothing beats the calibrated baseline beyond noise)".to_string()
        } else {
            named.join(", ")
        }
    );
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
         it is better in at least K-1 of K folds, and it explains a held-out gap above {:.0e}.\n",
        DiagnoseOptions::default().max_score,
        DiagnoseOptions::default().max_raw_ratio,
        DiagnoseOptions::default().min_wilcoxon_z,
        DiagnoseOptions::default().min_explained_gap
    );
    let _ = writeln!(r, "| round | effect | raw held-out residual | gap ratio | score | Wilcoxon z | folds better | qualifies | parameters |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for c in d.rounds.iter().flatten() {
        let params = effect_params(&c.model, c.kind)
            .iter()
            .map(|(k, v)| format!("{k} = {v:.4e}"))
            .collect::<Vec<_>>()
            .join(", ");
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
            if c.qualifies { "yes" } else { "no" }
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
    let _ = writeln!(r, "Per test (held-out relative residual at the test frequency, noise included, and the estimated noise share):\n\n| test | preload (kN) | f (Hz) | amplitude (kN) | T (degC) | before | after | noise |\n| --- | --- | --- | --- | --- | --- | --- | --- |");
    for (i, t) in data.iter().enumerate() {
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
    let _ = writeln!(r, "\n## Plots\n");
    for (title, path) in [
        ("Gap map", &plots.gap_map),
        ("Loops", &plots.loops),
        ("k_eq and c_eq", &plots.equivalents),
    ] {
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
        "Augmented by `fastemu diagnose` from baseline {} and campaign {}.\nNamed effects: {}. Held-out gap {:.4e} -> {:.4e}.\nSet operating_temperature_c of temperature-shift to the rig temperature. channel-delay and moving-mass\nare rig artefacts: the emulator (StepperMode::Emulation) leaves them out.",
        args.model.display(),
        args.campaign.display(),
        if diagnosis.named.is_empty() { "none".to_string() } else { diagnosis.named.iter().map(|k| k.name()).collect::<Vec<_>>().join(", ") },
        diagnosis.gap_before,
        diagnosis.gap_after
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
