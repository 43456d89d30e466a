//! `bench_rig`: the simulated rig process (hardware stand-in). Physics and process loop
//! live in `fastemu::rig`; this file only parses arguments.

use std::process::ExitCode;

use clap::Parser;
use fastemu::cli::loopproc::LoopProcessArgs;

#[derive(Parser)]
#[command(
    name = "bench_rig",
    about = "Simulated HIL rig: specimen mass, actuator, sensor"
)]
struct Cli {
    #[command(flatten)]
    args: LoopProcessArgs,
}

fn main() -> ExitCode {
    fastemu::ipc::quiet_iceoryx2_logs();
    let cli = Cli::parse();
    let result = cli.args.load().and_then(|(cfg, _, _)| {
        fastemu::rig::process::run_rig(&cfg, &cli.args.run_id, &cli.args.out)
            .map_err(anyhow::Error::from)
    });
    match result {
        Ok(summary) => {
            eprintln!(
                "bench_rig: {} steps, {} missed deadlines, {} periods without a new command{}",
                summary.steps,
                summary.missed_deadlines,
                summary.held_commands,
                summary
                    .fault
                    .as_ref()
                    .map_or(String::new(), |f| format!(", interlock: {f}"))
            );
            if summary.fault.is_some() {
                ExitCode::from(3)
            } else {
                ExitCode::SUCCESS
            }
        }
        Err(e) => {
            eprintln!("bench_rig: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
