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
    /// Run the closed loop: simulated rig, emulator and controller (the main command).
    Hil(cli::hil::HilArgs),
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
    /// Write a seeded synthetic campaign (a hidden effect, none, or one outside the
    /// library) to try `diagnose` on; the truth goes to a file diagnose never reads.
    SynthCampaign(cli::synth::SynthArgs),
    /// Benchmarks (model step speed, transport latency).
    #[command(subcommand)]
    Bench(cli::bench::BenchCommand),
    /// The emulator process (fixed-step loop; started by `hil`).
    Emulator(cli::loopproc::LoopProcessArgs),
    /// The actuator-controller process (event-driven; started by `hil`).
    Controller(cli::loopproc::LoopProcessArgs),
    /// The simulated rig in this binary (what `bench_rig` runs; used by `hil` when the
    /// `bench_rig` binary was not built, e.g. after `cargo run --release -- hil`).
    #[command(hide = true)]
    Rig(cli::loopproc::RigArgs),
    /// fastemu's end of the UDP rig link (started by `hil --rig-link udp`).
    #[command(hide = true)]
    Link(cli::link::LinkArgs),
    /// Re-run the emulator's model on a recorded input stream; verify bit-identical forces.
    Replay(cli::replay::ReplayArgs),
    /// Export a run's records (records.mcap) as CSV files.
    Export(cli::export::ExportArgs),
    /// Operator control of a running `hil` from another terminal: hold, resume, stop, status.
    Ctl(cli::ctl::CtlArgs),
}

/// The loop threads' unavoidable small allocations (iceoryx2's block per publish) come
/// from a fixed lock-free pool; everything else from the system (`fastemu::rt::pool`).
#[global_allocator]
static ALLOCATOR: fastemu::rt::pool::RtPool<std::alloc::System> =
    fastemu::rt::pool::RtPool::new(std::alloc::System);

fn main() -> std::process::ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            // A usage error is no verdict either: for `hil` 3, not clap's 2 (a fault).
            let _ = e.print();
            let hil = std::env::args().nth(1).as_deref() == Some("hil");
            return match e.exit_code() {
                0 => std::process::ExitCode::SUCCESS,
                _ if hil => std::process::ExitCode::from(3),
                code => std::process::ExitCode::from(code.clamp(1, 255) as u8),
            };
        }
    };
    // `hil` gives a verdict in its exit code (0 clean, 1 not clean, 2 a fault); an error is
    // no verdict (it did not run, or could not finish its report): 3, for scripts to tell.
    let failure = if matches!(cli.command, Command::Hil(_)) {
        std::process::ExitCode::from(3)
    } else {
        std::process::ExitCode::FAILURE
    };
    let result = match cli.command {
        Command::Simulate(cmd) => cli::simulate::run(cmd),
        Command::Equiv(args) => cli::equiv::run(args),
        Command::Paper(args) => cli::paper::run(args),
        Command::Bench(cmd) => cli::bench::run(cmd),
        Command::Identify(args) => cli::identify::run(args),
        Command::Diagnose(args) => cli::diagnose::run(args),
        Command::SynthCampaign(args) => cli::synth::run(args),
        Command::Hil(args) => cli::hil::run(args),
        Command::Emulator(args) => cli::loopproc::run_emulator_command(args),
        Command::Controller(args) => cli::loopproc::run_controller_command(args),
        Command::Replay(args) => cli::replay::run(args),
        Command::Export(args) => cli::export::run(args),
        Command::Ctl(args) => cli::ctl::run(args),
        Command::Rig(args) => cli::loopproc::run_rig_command(args),
        Command::Link(args) => cli::link::run(args),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("fastemu: error: {e:#}");
            failure
        }
    }
}
