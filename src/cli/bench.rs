//! `fastemu bench ...`: benchmark commands.

use std::process::ExitCode;

use clap::{Args, Subcommand};

use crate::bench::model::time_all_forms;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Nanoseconds per model step for each form (median of interleaved runs).
    Model(ModelBenchArgs),
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
    }
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
