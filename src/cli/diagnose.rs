//! `fastemu diagnose`: argument handling; the workflow, its verdicts and writers live in
//! `crate::ident::diagnose`, the run-directory reader in `crate::ident::runrec`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Args;

use crate::ident::campaign::load_campaign;
use crate::ident::diagnose::report::{write_outputs, write_run_outputs, ReportPaths};
use crate::ident::diagnose::run::{diagnose_run, operating_temperature_c};
use crate::ident::diagnose::{diagnose, DiagnoseOptions};
use crate::ident::first_cycles::split_first_cycles;
use crate::ident::fit::{test_data, CycleData};
use crate::ident::history::prepare_history;
use crate::ident::runrec::load_run_history;
use crate::model::effects::AugmentedModel;

#[derive(Args)]
pub struct DiagnoseArgs {
    /// Campaign directory: `campaign.toml` and one CSV per test (SPEC 4; see README).
    #[arg(long, required_unless_present = "run", conflicts_with = "run")]
    pub campaign: Option<PathBuf>,
    /// Report directory of a `fastemu hil` run: its rig record is diagnosed as one history
    /// test against the model the emulator ran (not recalibrated).
    #[arg(long)]
    pub run: Option<PathBuf>,
    /// Baseline model file (SPEC 2.3). With --campaign (required) its structure is kept and
    /// its parameters recalibrated; with --run it replaces the run's own model.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Output directory: report.md, PNG plots, augmented_model.toml.
    #[arg(long)]
    pub out: PathBuf,
    /// Print the SPEC 5 JSON object on stdout.
    #[arg(long)]
    pub json: bool,
    /// Cross-validation folds (at least 2; more than the tests gives leave-one-out).
    /// Campaigns only.
    #[arg(long, default_value_t = 5, conflicts_with = "run")]
    pub folds: usize,
    /// Worker threads. Campaigns only.
    #[arg(long, default_value_t = 2, conflicts_with = "run")]
    pub threads: usize,
}

fn load_model(path: &std::path::Path) -> anyhow::Result<AugmentedModel> {
    let spec = super::load_model(path)?;
    Ok(AugmentedModel::from_spec(
        &spec,
        &path.display().to_string(),
    )?)
}

pub fn run(args: DiagnoseArgs) -> anyhow::Result<ExitCode> {
    let started = Instant::now();
    if args.campaign.is_none() && args.run.is_none() {
        bail!("give --campaign DIR or --run RUNDIR");
    }
    // Fail on an unusable --out before the analysis, not after it; a directory made here
    // for an analysis that then fails is taken away again (only if still empty).
    let created = !args.out.exists();
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let summary = match (&args.campaign, &args.run) {
        (_, Some(run_dir)) => run_command(&args, run_dir, started),
        (Some(campaign), _) => campaign_command(&args, campaign, started),
        (None, None) => unreachable!("checked above"),
    };
    if summary.is_err() && created {
        let _ = std::fs::remove_dir(&args.out);
    }
    let summary = summary?;
    if args.json {
        println!("{summary}");
    }
    Ok(ExitCode::SUCCESS)
}

fn run_command(
    args: &DiagnoseArgs,
    run_dir: &std::path::Path,
    started: Instant,
) -> anyhow::Result<serde_json::Value> {
    let record = load_run_history(run_dir)?;
    let config = record.config()?;
    let model = match &args.model {
        Some(path) => load_model(path)?,
        None => config.augmented.clone(),
    };
    let history = prepare_history(record.dt_s, &record.displacement_m, &record.applied_force_n)
        .with_context(|| format!("{}: {}", run_dir.display(), record.used))?;
    let unit = CycleData::from_history(
        "the run's rig record",
        history,
        operating_temperature_c(&model),
        0.0,
    );
    let diagnosis = diagnose_run(&model, unit, &mut |msg| eprintln!("diagnose: {msg}"));
    let model_label = match &args.model {
        Some(p) => p.display().to_string(),
        None => format!("[model] of {}", record.config_origin),
    };
    write_run_outputs(
        run_dir,
        &model_label,
        &record,
        &args.out,
        &diagnosis,
        &config,
        started,
    )
}

fn campaign_command(
    args: &DiagnoseArgs,
    campaign_dir: &std::path::Path,
    started: Instant,
) -> anyhow::Result<serde_json::Value> {
    let Some(model_path) = &args.model else {
        bail!("--campaign needs --model MODEL.toml (the baseline to recalibrate)");
    };
    anyhow::ensure!(
        args.folds >= 2,
        "--folds {}: cross-validation needs at least 2 folds",
        args.folds
    );
    let campaign = load_campaign(campaign_dir)?;
    let mut baseline = load_model(model_path)?;
    if (baseline.length_m - campaign.sample_length_m).abs() > 1e-9 * campaign.sample_length_m {
        // Per-metre parameters are what the model file states: rescale to the sample.
        let scale = campaign.sample_length_m / baseline.length_m;
        eprintln!(
            "diagnose: model length_m {} differs from the campaign's sample_length_m {}: using the sample length",
            baseline.length_m, campaign.sample_length_m
        );
        baseline = rescale(&baseline, scale, campaign.sample_length_m);
    }
    // The first cycles of harmonic records that carry something (a Mullins effect's
    // virgin loading) become history tests; records starting in steady state are kept.
    let (campaign, first_cycles_used) = split_first_cycles(&campaign);
    for u in &first_cycles_used {
        eprintln!("diagnose: first cycles used: {}", u.reason());
    }
    let data = test_data(&campaign)?;
    let n_history = data.iter().filter(|d| d.is_history()).count();
    if data.len() < 6 {
        bail!(
            "{}: {} tests: diagnosis needs at least 6 (it holds tests out)",
            campaign_dir.display(),
            data.len()
        );
    }
    eprintln!(
        "diagnose: {} harmonic and {n_history} history tests from {}",
        data.len() - n_history,
        campaign_dir.display()
    );
    let options = DiagnoseOptions {
        n_folds: args.folds,
        n_threads: args.threads.max(1),
        order_is_clock: campaign.has_start_times(),
        ..DiagnoseOptions::default()
    };
    let mut diagnosis = diagnose(&baseline, &data, &options, &mut |msg| {
        eprintln!("diagnose: {msg}")
    });
    diagnosis.first_cycles_used = first_cycles_used;
    let paths = ReportPaths {
        campaign: campaign_dir.to_path_buf(),
        model: model_path.clone(),
        out: args.out.clone(),
    };
    write_outputs(&paths, &diagnosis, &data, campaign.sample_length_m, started)
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
