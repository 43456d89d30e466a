//! `fastemu bench ...`: benchmark commands.

use std::process::ExitCode;

use std::path::PathBuf;

use anyhow::bail;
use clap::{Args, Subcommand};

use crate::bench::model::time_all_forms;
use crate::bench::rail::time_simulate_rail;
use crate::csvio::{read_columns, uniform_step};
use crate::model::oscillator::StartCondition;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Nanoseconds per model step for each form (median of interleaved runs).
    Model(ModelBenchArgs),
    /// Seconds per `simulate rail` computation (no CSV I/O), median of repeated runs.
    Rail(RailBenchArgs),
}

#[derive(Args)]
pub struct RailBenchArgs {
    /// Model file (SPEC 2.3).
    #[arg(long)]
    pub model: PathBuf,
    /// Mass on the element, kg.
    #[arg(long = "mass-kg", allow_negative_numbers = true)]
    pub mass_kg: f64,
    /// External force CSV: `t_s,force_n`, uniform step (read once, outside the timing).
    #[arg(long)]
    pub input: PathBuf,
    /// Initial condition: `rest` or `static`.
    #[arg(long, default_value = "rest")]
    pub start: String,
    /// Timed runs.
    #[arg(long, default_value_t = 7)]
    pub runs: usize,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args)]
pub struct ModelBenchArgs {
    /// Print `{"ns_per_step": {...}, ...}` as JSON.
    #[arg(long)]
    pub json: bool,
    /// Interleaved rounds per form.
    #[arg(long, default_value_t = 15)]
    pub rounds: usize,
    /// Steps per timed run.
    #[arg(long, default_value_t = 2_000_000)]
    pub steps: usize,
}

pub fn run(cmd: BenchCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        BenchCommand::Model(args) => run_model(args),
        BenchCommand::Rail(args) => run_rail(args),
    }
}

fn run_rail(args: RailBenchArgs) -> anyhow::Result<ExitCode> {
    let Some(start) = StartCondition::from_name(&args.start) else {
        bail!("--start {}: expected `rest` or `static`", args.start);
    };
    if !(args.mass_kg.is_finite() && args.mass_kg > 0.0) {
        bail!(
            "--mass-kg {}: must be a positive finite number",
            args.mass_kg
        );
    }
    anyhow::ensure!(args.runs > 0, "--runs must be positive");
    let spec = super::load_model(&args.model)?;
    let cols = read_columns(&args.input, &["t_s", "force_n"])?;
    let dt = uniform_step(&cols.data[0], &args.input.display().to_string(), "t_s")?;
    let timing = time_simulate_rail(
        spec.element,
        args.mass_kg,
        dt,
        &cols.data[1],
        start,
        args.runs,
    );
    if args.json {
        println!("{}", serde_json::to_string(&timing)?);
    } else {
        println!(
            "{} form, {} samples at dt {:e} s, {} sub-step(s): median {:.6} s (min {:.6}, max {:.6}) over {} runs, {:.1} ns/step",
            timing.form,
            timing.n_samples,
            timing.dt_s,
            timing.substeps_per_step,
            timing.median_s,
            timing.min_s,
            timing.max_s,
            timing.runs,
            timing.median_ns_per_step
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn run_model(args: ModelBenchArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.rounds > 0 && args.steps > 0,
        "--rounds and --steps must be positive"
    );
    let timings = time_all_forms(args.rounds, args.steps);
    if args.json {
        let mut ns = serde_json::Map::new();
        for t in &timings {
            ns.insert(t.form.to_string(), serde_json::json!(t.median_ns_per_step));
        }
        let obj = serde_json::json!({"ns_per_step": ns, "detail": timings});
        println!("{}", serde_json::to_string(&obj)?);
    } else {
        println!(
            "{:<14} {:>12} {:>10} {:>10}   ({} rounds x {} steps)",
            "form", "median_ns", "min_ns", "max_ns", args.rounds, args.steps
        );
        for t in &timings {
            println!(
                "{:<14} {:>12.2} {:>10.2} {:>10.2}",
                t.form, t.median_ns_per_step, t.min_ns_per_step, t.max_ns_per_step
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
