//! `fastemu`: the command line. Each subcommand's arguments and handler live in
//! `fastemu::cli::<name>`; this file only dispatches. `anyhow` lives here, at the edge.

use clap::{Parser, Subcommand};
use fastemu::cli;

#[derive(Parser)]
#[command(
    name = "fastemu",
    version,
    about = "Real-time HIL emulator of rail fastening elastomers (Li et al., Materials 2021)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Offline simulation primitives (SPEC 2.3): force from displacement, mass on element.
    #[command(subcommand)]
    Simulate(cli::simulate::SimulateCommand),
    /// Equivalent stiffness and damping table (paper Eq. 2).
    Equiv(cli::equiv::EquivArgs),
    /// Reproduces the paper's tables and figures (CSV + PNG + summary.json/.md).
    Paper(cli::paper::PaperArgs),
    /// Identify Zener parameters from a campaign of harmonic tests (paper Sec. 3.1).
    Identify(cli::identify::IdentifyArgs),
    /// Find where model and campaign disagree, name the missing effect, show the gap shrink.
    Diagnose(cli::diagnose::DiagnoseArgs),
    /// Benchmarks (model step speed, transport latency).
    #[command(subcommand)]
    Bench(cli::bench::BenchCommand),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Simulate(cmd) => cli::simulate::run(cmd),
        Command::Equiv(args) => cli::equiv::run(args),
        Command::Paper(args) => cli::paper::run(args),
        Command::Bench(cmd) => cli::bench::run(cmd),
        Command::Identify(args) => cli::identify::run(args),
        Command::Diagnose(args) => cli::diagnose::run(args),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("fastemu: error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
