//! Identification: Zener parameters from a campaign of harmonic tests (paper Sec. 3.1).
//!
//! Two objectives:
//! - `eq2` (the paper's, default for `--form paper`): per-metre k_eq in MN/m^2 and c_eq in
//!   MN s/m^2 from each test's single-bin DFT against paper Eq. 2, residuals
//!   `k_num - k_exp` and `sqrt(10) (c_num - c_exp)` (weight 10 on the squared damping
//!   error, as in the paper), P0 fixed.
//! - `force` (default for `--form consistent`): time-domain force residual. The chosen form
//!   is simulated over each test's measured steady-state displacement cycle and the
//!   simulated force is compared with the measured force cycle (harmonics 1-3, relative to
//!   each test's force amplitude, so every test weighs the same).
//!
//! Standard errors come from `sigma^2 (J^T J)^-1` in the fitted log/logit parameters and
//! are mapped to the physical ones (95 % intervals are transformed, hence asymmetric).

use std::path::{Path, PathBuf};

use serde_json::json;

use super::campaign::Campaign;
use super::fit::{fit_template, levenberg_marquardt, CycleData, LmFit, Template};
use super::fit::{relative_error, rms_gap};
use crate::model::effects::{AugmentedModel, DEFAULT_TEMPERATURE_C};
use crate::model::equiv::zener_eq2;
use crate::model::params::{ElementModel, Form, ZenerParams};

/// One identified parameter: value, standard error and 95 % interval, in file units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    pub value: f64,
    pub standard_error: Option<f64>,
    pub ci95: Option<(f64, f64)>,
}

/// Result of an identification.
#[derive(Debug, Clone)]
pub struct Identification {
    /// Per-metre parameters (k in N/m^2, c in N s/m^2).
    pub params_per_m: ZenerParams,
    pub estimates: Vec<(&'static str, Estimate)>,
    pub fit: LmFit,
}

fn log_estimate(theta: f64, se: Option<f64>, unit_scale: f64) -> Estimate {
    let value = theta.exp() * unit_scale;
    Estimate {
        value,
        standard_error: se.map(|s| value * s),
        ci95: se.map(|s| {
            (
                (theta - 1.96 * s).exp() * unit_scale,
                (theta + 1.96 * s).exp() * unit_scale,
            )
        }),
    }
}

fn logistic(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

fn chi_estimate(theta: f64, se: Option<f64>, chi_max: f64) -> Estimate {
    let value = chi_max * logistic(theta);
    let slope = value * (1.0 - logistic(theta));
    Estimate {
        value,
        standard_error: se.map(|s| slope * s),
        ci95: se.map(|s| {
            (
                chi_max * logistic(theta - 1.96 * s),
                chi_max * logistic(theta + 1.96 * s),
            )
        }),
    }
}

/// The model of a sample of `length_m` for per-metre parameters, in the chosen form.
fn sample_model(per_m: &ZenerParams, form: Form, length_m: f64) -> AugmentedModel {
    let element_params = ZenerParams {
        k1_0_n_per_m: per_m.k1_0_n_per_m * length_m,
        k2_0_n_per_m: per_m.k2_0_n_per_m * length_m,
        c2_0_ns_per_m: per_m.c2_0_ns_per_m * length_m,
        ..*per_m
    };
    AugmentedModel {
        element: match form {
            Form::Paper => ElementModel::Paper(element_params),
            _ => ElementModel::Consistent(element_params),
        },
        length_m,
        effects: Vec::new(),
    }
}

/// Start values from the measured k_eq/c_eq (per metre, SI).
fn start_params(campaign: &Campaign, p0_n: f64) -> ZenerParams {
    let eqs: Vec<_> = campaign
        .harmonic_tests()
        .filter_map(|t| campaign.equivalent(t))
        .collect();
    let k_min = eqs
        .iter()
        .map(|e| e.k_eq_n_per_m2)
        .fold(f64::INFINITY, f64::min)
        .max(1e3);
    let k_max = eqs.iter().map(|e| e.k_eq_n_per_m2).fold(0.0, f64::max);
    let c_max = eqs.iter().map(|e| e.c_eq_ns_per_m2).fold(0.0, f64::max);
    ZenerParams {
        k1_0_n_per_m: 0.9 * k_min,
        k2_0_n_per_m: (k_max - 0.9 * k_min).max(0.1 * k_min),
        c2_0_ns_per_m: c_max.max(1e-3 * k_min),
        chi: 0.2,
        p0_n,
    }
}

/// The paper's objective: Eq. 2 against per-metre k_eq (MN/m^2) and c_eq (MN s/m^2).
pub fn identify_eq2(campaign: &Campaign, p0_n: f64) -> Identification {
    const CHI_MAX: f64 = 0.95;
    let points: Vec<(f64, f64, f64, f64)> = campaign
        .harmonic_tests()
        .filter_map(|t| {
            let e = campaign.equivalent(t)?;
            Some((
                t.preload_n()?,
                2.0 * std::f64::consts::PI * t.frequency_hz()?,
                e.k_eq_n_per_m2 / 1e6,
                e.c_eq_ns_per_m2 / 1e6,
            ))
        })
        .collect();
    let to_params = |theta: &[f64]| ZenerParams {
        k1_0_n_per_m: theta[0].exp() * 1e6,
        k2_0_n_per_m: theta[1].exp() * 1e6,
        c2_0_ns_per_m: theta[2].exp() * 1e6,
        chi: CHI_MAX * logistic(theta[3]),
        p0_n,
    };
    let residuals = |theta: &[f64]| -> Vec<f64> {
        let p = to_params(theta);
        let weight = 10f64.sqrt();
        points
            .iter()
            .flat_map(|&(preload, omega, k_exp, c_exp)| {
                let eq = zener_eq2(&p, preload, omega);
                [
                    eq.k_eq_n_per_m / 1e6 - k_exp,
                    weight * (eq.c_eq_ns_per_m / 1e6 - c_exp),
                ]
            })
            .collect()
    };
    let s = start_params(campaign, p0_n);
    let mut best: Option<LmFit> = None;
    for chi in [0.05, 0.2, 0.5] {
        let start = [
            (s.k1_0_n_per_m / 1e6).ln(),
            (s.k2_0_n_per_m / 1e6).ln(),
            (s.c2_0_ns_per_m / 1e6).ln(),
            (chi / (CHI_MAX - chi)).ln(),
        ];
        let fit = levenberg_marquardt(residuals, &start, 200);
        if best.as_ref().is_none_or(|b| fit.sse < b.sse) {
            best = Some(fit);
        }
    }
    let fit = best.expect("three starts");
    let se = fit.standard_errors();
    let params_per_m = to_params(&fit.params);
    Identification {
        params_per_m,
        estimates: vec![
            ("k1_0_n_per_m2", log_estimate(fit.params[0], se[0], 1e6)),
            ("k2_0_n_per_m2", log_estimate(fit.params[1], se[1], 1e6)),
            ("c2_0_ns_per_m2", log_estimate(fit.params[2], se[2], 1e6)),
            ("chi", chi_estimate(fit.params[3], se[3], CHI_MAX)),
        ],
        fit,
    }
}

/// Time-domain force-residual fit of the chosen form (chi free, P0 fixed).
pub fn identify_force(
    campaign: &Campaign,
    data: &[CycleData],
    form: Form,
    p0_n: f64,
) -> Identification {
    let length = campaign.sample_length_m;
    let baseline = sample_model(&start_params(campaign, p0_n), form, length);
    let template = Template::new(baseline, DEFAULT_TEMPERATURE_C);
    let all: Vec<&CycleData> = data.iter().collect();
    let mut starts = template.starts(data);
    for chi in [0.05f64, 0.5] {
        let mut start = starts[0].clone();
        start[3] = (chi / (0.95 - chi)).ln();
        starts.push(start);
    }
    let fit = fit_template(&template, &all, &starts, 100);
    let se = fit.standard_errors();
    let model = template.model(&fit.params);
    let p = *model.element.zener().expect("Zener template");
    let params_per_m = ZenerParams {
        k1_0_n_per_m: p.k1_0_n_per_m / length,
        k2_0_n_per_m: p.k2_0_n_per_m / length,
        c2_0_ns_per_m: p.c2_0_ns_per_m / length,
        ..p
    };
    Identification {
        params_per_m,
        estimates: vec![
            (
                "k1_0_n_per_m2",
                log_estimate(fit.params[0], se[0], 1.0 / length),
            ),
            (
                "k2_0_n_per_m2",
                log_estimate(fit.params[1], se[1], 1.0 / length),
            ),
            (
                "c2_0_ns_per_m2",
                log_estimate(fit.params[2], se[2], 1.0 / length),
            ),
            ("chi", chi_estimate(fit.params[3], se[3], 0.95)),
        ],
        fit,
    }
}

/// What `identify` was asked to write.
pub struct IdentifyRequest {
    pub campaign: PathBuf,
    pub p0_n: f64,
    pub out: Option<PathBuf>,
    pub plot_dir: Option<PathBuf>,
}

/// Prints the estimates, writes the model file and plots asked for; returns the `--json`
/// summary.
pub fn write_identification(
    request: &IdentifyRequest,
    campaign: &Campaign,
    data: &[CycleData],
    identification: &Identification,
    form: Form,
    objective: &str,
) -> anyhow::Result<serde_json::Value> {
    use anyhow::Context;
    let length = campaign.sample_length_m;
    let model = sample_model(&identification.params_per_m, form, length);
    let errors: Vec<f64> = data.iter().map(|d| relative_error(&model, d)).collect();
    let residual = rms_gap(&errors);
    for (name, e) in &identification.estimates {
        let se = e
            .standard_error
            .map_or("n/a".to_string(), |s| format!("{s:.4e}"));
        let ci = e.ci95.map_or("n/a".to_string(), |(lo, hi)| {
            format!("[{lo:.4e}, {hi:.4e}]")
        });
        eprintln!(
            "identify: {name} = {:.6e} (standard error {se}, 95 % interval {ci})",
            e.value
        );
    }
    eprintln!("identify: in-sample relative RMS force residual {residual:.4e}");

    if let Some(out) = &request.out {
        if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create directory {}", parent.display()))?;
        }
        let header = format!(
            "Identified by `fastemu identify` from {} ({} harmonic tests), objective {objective}.\nStandard errors: {}",
            request.campaign.display(),
            data.len(),
            identification
                .estimates
                .iter()
                .map(|(n, e)| format!("{n} {}", e.standard_error.map_or("n/a".into(), |s| format!("{s:.3e}"))))
                .collect::<Vec<_>>()
                .join(", ")
        );
        std::fs::write(out, model.render_toml(&header))
            .with_context(|| format!("cannot write {}", out.display()))?;
    }
    let plot_dir: Option<PathBuf> = request.plot_dir.clone().or_else(|| {
        request
            .out
            .as_ref()
            .map(|o| o.parent().map_or(PathBuf::from("."), Path::to_path_buf))
    });
    let mut plots = Vec::new();
    if let Some(dir) = plot_dir {
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        let eq_path = dir.join("identify_keq_ceq.png");
        let label = format!("{form} ({objective})");
        crate::ident::plots::plot_equivalents(
            &eq_path,
            data,
            length,
            &[(&label, &model)],
            DEFAULT_TEMPERATURE_C,
        )?;
        let loop_path = dir.join("identify_loops.png");
        crate::ident::plots::plot_loops(
            &loop_path,
            data,
            &crate::ident::plots::loop_tests(data),
            &[(&label, &model)],
        )?;
        plots.push(eq_path.display().to_string());
        plots.push(loop_path.display().to_string());
    }
    let params: serde_json::Map<String, serde_json::Value> = identification
        .estimates
        .iter()
        .map(|(name, e)| {
            (
                name.to_string(),
                json!({"value": e.value, "standard_error": e.standard_error, "ci95": e.ci95.map(|c| [c.0, c.1])}),
            )
        })
        .collect();
    let tests: Vec<serde_json::Value> = data
        .iter()
        .zip(&errors)
        .map(|(d, e)| {
            let (k, c) = crate::ident::plots::equivalent_mn(
                d.force_harmonics_n[0],
                d.displacement_harmonics_m[0],
                d.frequency_hz,
                length,
            );
            let predicted = super::fit::predict_cycle(&model, d);
            let (km, cm) = crate::ident::plots::equivalent_mn(
                predicted[0],
                d.displacement_harmonics_m[0],
                d.frequency_hz,
                length,
            );
            json!({"id": d.id, "preload_n": d.preload_n, "frequency_hz": d.frequency_hz,
                "k_eq_mn_per_m2": k, "c_eq_mns_per_m2": c,
                "k_eq_model_mn_per_m2": km, "c_eq_model_mns_per_m2": cm,
                "relative_force_residual": e.sqrt()})
        })
        .collect();
    let summary = json!({
        "form": form.name(),
        "objective": objective,
        "p0_n": request.p0_n,
        "sample_length_m": length,
        "params": params,
        "relative_force_residual_rms": residual,
        "objective_sse": identification.fit.sse,
        "tests": tests,
        "model_out": request.out.as_ref().map(|o| o.display().to_string()),
        "plots": plots,
    });
    Ok(summary)
}
