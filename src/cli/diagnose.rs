//! `fastemu diagnose`: the discrepancy workflow of SPEC 5 (logic and writers in
//! `crate::ident::diagnose`); this module handles the arguments.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Args;

use crate::ident::campaign::load_campaign;
use crate::ident::diagnose::report::{write_outputs, ReportPaths};
use crate::ident::diagnose::{diagnose, DiagnoseOptions};
use crate::ident::fit::cycle_data;
use crate::model::effects::AugmentedModel;

#[derive(Args)]
pub struct DiagnoseArgs {
    /// Campaign directory: `campaign.toml` and one CSV per test (SPEC 4; see README).
    #[arg(long)]
    pub campaign: PathBuf,
    /// Baseline model file (SPEC 2.3); its structure is kept, its parameters recalibrated.
    #[arg(long)]
    pub model: PathBuf,
    /// Output directory: report.md, PNG plots, augmented_model.toml.
    #[arg(long)]
    pub out: PathBuf,
    /// Print the SPEC 5 JSON object on stdout.
    #[arg(long)]
    pub json: bool,
    /// Cross-validation folds (at least 2; more than the tests gives leave-one-out).
    #[arg(long, default_value_t = 5)]
    pub folds: usize,
    /// Worker threads.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

pub fn run(args: DiagnoseArgs) -> anyhow::Result<ExitCode> {
    let started = Instant::now();
    let campaign = load_campaign(&args.campaign)?;
    let spec = super::load_model(&args.model)?;
    let baseline = AugmentedModel::from_spec(&spec, &args.model.display().to_string())?;
    let mut baseline = baseline;
    if (baseline.length_m - campaign.sample_length_m).abs() > 1e-9 * campaign.sample_length_m {
        // Per-metre parameters are what the model file states: rescale to the sample.
        let scale = campaign.sample_length_m / baseline.length_m;
        eprintln!(
            "diagnose: model length_m {} differs from the campaign's sample_length_m {}: using the sample length",
            baseline.length_m, campaign.sample_length_m
        );
        baseline = rescale(&baseline, scale, campaign.sample_length_m);
    }
    let data = cycle_data(&campaign);
    if data.len() < 6 {
        bail!(
            "{}: {} harmonic tests: diagnosis needs at least 6 (it holds tests out)",
            args.campaign.display(),
            data.len()
        );
    }
    let n_history = campaign.tests.len() - data.len();
    eprintln!(
        "diagnose: {} harmonic tests{} from {}",
        data.len(),
        if n_history > 0 {
            format!(" ({n_history} history tests not used)")
        } else {
            String::new()
        },
        args.campaign.display()
    );
    anyhow::ensure!(
        args.folds >= 2,
        "--folds {}: cross-validation needs at least 2 folds",
        args.folds
    );
    // Fail on an unusable --out before the analysis, not after it.
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let options = DiagnoseOptions {
        n_folds: args.folds,
        n_threads: args.threads.max(1),
        ..DiagnoseOptions::default()
    };
    let diagnosis = diagnose(&baseline, &data, &options, &mut |msg| {
        eprintln!("diagnose: {msg}")
    });
    let paths = ReportPaths {
        campaign: args.campaign.clone(),
        model: args.model.clone(),
        out: args.out.clone(),
    };
    let summary = write_outputs(&paths, &diagnosis, &data, campaign.sample_length_m, started)?;
    if args.json {
        println!("{summary}");
    }
    Ok(ExitCode::SUCCESS)
}

fn rescale(model: &AugmentedModel, scale: f64, length_m: f64) -> AugmentedModel {
    use crate::model::params::ElementModel;
    let mut out = model.clone();
    match &mut out.element {
        ElementModel::Consistent(p) | ElementModel::Paper(p) => {
            p.k1_0_n_per_m *= scale;
            p.k2_0_n_per_m *= scale;
            p.c2_0_ns_per_m *= scale;
        }
        ElementModel::KelvinVoigt(p) => {
            p.k_n_per_m *= scale;
            p.c_ns_per_m *= scale;
        }
    }
    out.length_m = length_m;
    out
}
