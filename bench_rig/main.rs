//! `bench_rig`: the simulated rig process (hardware stand-in). Physics, servo and process
//! loop live in `fastemu::rig`; this file only parses arguments.

use std::process::ExitCode;

use clap::Parser;
use fastemu::cli::loopproc::{run_rig_command, LoopProcessArgs};

#[derive(Parser)]
#[command(
    name = "bench_rig",
    about = "Simulated HIL rig: specimen mass, actuator with its servo controller, sensor"
)]
struct Cli {
    #[command(flatten)]
    args: LoopProcessArgs,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run_rig_command(cli.args) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("bench_rig: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
