//! `fastemu identify`: argument handling and output (the fit is `crate::ident::identify`).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context};
use clap::Args;
use serde_json::json;

use crate::ident::campaign::load_campaign;
use crate::ident::fit::{cycle_data, relative_error, rms_gap};
use crate::ident::identify::{identify_eq2, identify_force};
use crate::ident::plots;
use crate::model::effects::{AugmentedModel, DEFAULT_TEMPERATURE_C};
use crate::model::params::{ElementModel, Form, ZenerParams};

#[derive(Args)]
pub struct IdentifyArgs {
    /// Campaign directory: `campaign.toml` and one CSV per test (SPEC 4; see README).
    #[arg(long)]
    pub campaign: PathBuf,
    /// Time-domain form of the identified model: `consistent` or `paper`.
    #[arg(long, default_value = "consistent")]
    pub form: String,
    /// Objective: `force` (time-domain force residual) or `eq2` (paper: k_eq/c_eq, weight 10
    /// on damping). Default: `force` for the consistent form, `eq2` for the paper form.
    #[arg(long)]
    pub objective: Option<String>,
    /// Reference preload P0 of paper Eq. 1, N (held fixed, as in the paper).
    #[arg(long = "p0-n", default_value_t = 64e3)]
    pub p0_n: f64,
    /// Model file to write (SPEC 2.3).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Directory for the PNG plots (default: next to `--out`, else none).
    #[arg(long = "plot-dir")]
    pub plot_dir: Option<PathBuf>,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
}
pub fn run(args: IdentifyArgs) -> anyhow::Result<ExitCode> {
    let Some(form) = Form::from_name(&args.form).filter(|f| *f != Form::KelvinVoigt) else {
        bail!("--form {}: expected `consistent` or `paper`", args.form);
    };
    let objective = args
        .objective
        .clone()
        .unwrap_or_else(|| if form == Form::Paper { "eq2" } else { "force" }.to_string());
    if objective != "eq2" && objective != "force" {
        bail!("--objective {objective}: expected `force` or `eq2`");
    }
    if !(args.p0_n.is_finite() && args.p0_n > 0.0) {
        bail!("--p0-n {}: must be a positive number", args.p0_n);
    }
    let campaign = load_campaign(&args.campaign)?;
    let data = cycle_data(&campaign);
    if data.len() < 4 {
        bail!(
            "{}: {} harmonic tests: identification needs at least 4",
            args.campaign.display(),
            data.len()
        );
    }
    eprintln!(
        "identify: {} harmonic tests, form {form}, objective {objective}",
        data.len()
    );
    let identification = if objective == "eq2" {
        identify_eq2(&campaign, args.p0_n)
    } else {
        identify_force(&campaign, &data, form, args.p0_n)
    };
    let length = campaign.sample_length_m;
    let p = identification.params_per_m;
    let element_params = ZenerParams {
        k1_0_n_per_m: p.k1_0_n_per_m * length,
        k2_0_n_per_m: p.k2_0_n_per_m * length,
        c2_0_ns_per_m: p.c2_0_ns_per_m * length,
        ..p
    };
    let element = match form {
        Form::Paper => ElementModel::Paper(element_params),
        _ => ElementModel::Consistent(element_params),
    };
    let model = AugmentedModel {
        element,
        length_m: length,
        effects: Vec::new(),
    };
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

    if let Some(out) = &args.out {
        super::ensure_parent_dir(out)?;
        let header = format!(
            "Identified by `fastemu identify` from {} ({} harmonic tests), objective {objective}.\nStandard errors: {}",
            args.campaign.display(),
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
    let plot_dir: Option<PathBuf> = args.plot_dir.clone().or_else(|| {
        args.out
            .as_ref()
            .map(|o| o.parent().map_or(PathBuf::from("."), Path::to_path_buf))
    });
    let mut plots = Vec::new();
    if let Some(dir) = plot_dir {
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        let eq_path = dir.join("identify_keq_ceq.png");
        let label = format!("{form} ({objective})");
        plots::plot_equivalents(
            &eq_path,
            &data,
            length,
            &[(&label, &model)],
            DEFAULT_TEMPERATURE_C,
        )?;
        let loop_path = dir.join("identify_loops.png");
        plots::plot_loops(
            &loop_path,
            &data,
            &plots::loop_tests(&data),
            &[(&label, &model)],
        )?;
        plots.push(eq_path.display().to_string());
        plots.push(loop_path.display().to_string());
    }
    if args.json {
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
                let (k, c) = plots::equivalent_mn(
                    d.force_harmonics_n[0],
                    d.displacement_harmonics_m[0],
                    d.frequency_hz,
                    length,
                );
                let predicted = crate::ident::fit::predict_cycle(&model, d);
                let (km, cm) = plots::equivalent_mn(
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
            "p0_n": args.p0_n,
            "sample_length_m": length,
            "params": params,
            "relative_force_residual_rms": residual,
            "objective_sse": identification.fit.sse,
            "tests": tests,
            "model_out": args.out.as_ref().map(|o| o.display().to_string()),
            "plots": plots,
        });
        println!("{summary}");
    }
    Ok(ExitCode::SUCCESS)
}
