//! `bench_rig`: the simulated rig process (hardware stand-in), on iceoryx2 or as the far
//! end of the UDP rig link (`--link-bind`, `--link-peer`); started by `hil`, or by hand as
//! an external rig (`hil --rig external`). Physics, servo and process loop live in
//! `fastemu::rig`; this file only parses arguments.

use std::process::ExitCode;

use clap::Parser;
use fastemu::cli::loopproc::{run_rig_command, RigArgs};

#[derive(Parser)]
#[command(
    name = "bench_rig",
    about = "Simulated HIL rig: specimen mass, actuator with its servo controller, sensor"
)]
struct Cli {
    #[command(flatten)]
    args: RigArgs,
}

/// The loop threads' unavoidable small allocations (iceoryx2's block per publish) come
/// from a fixed lock-free pool; everything else from the system (`fastemu::rt::pool`).
#[global_allocator]
static ALLOCATOR: fastemu::rt::pool::RtPool<std::alloc::System> =
    fastemu::rt::pool::RtPool::new(std::alloc::System);

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
