//! `fastemu emulator`, `fastemu controller` and the hidden `fastemu rig` (on iceoryx2, or
//! as the far end of the UDP rig link): the loop
//! processes' command lines. Parse arguments, load the config, run the process; no loop
//! logic here.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::Args;

use crate::hil::config::{load_or_default, HilConfig, DEFAULT_CONFIG_TOML};
use crate::hil::controller_process::run_controller;
use crate::hil::emulator_process::run_emulator;
use crate::ipc::quiet_iceoryx2_logs;

/// Arguments shared by the loop processes (`bench_rig` takes the same).
#[derive(Debug, Clone, Args)]
pub struct LoopProcessArgs {
    /// HIL configuration (TOML); the embedded default when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Run id: names the iceoryx2 services (`fastemu/<id>/...`) and files (`<id>_*`).
    #[arg(long, default_value = "fedefault")]
    pub run_id: String,
    /// Report directory; this process's records go to `<out>/parts/`.
    #[arg(long, default_value = ".")]
    pub out: PathBuf,
    /// Overrides `[scenario] duration_s`.
    #[arg(long)]
    pub duration_s: Option<f64>,
    /// How long to wait for the start, s (a process started by hand, e.g. a rig that
    /// waits for `hil --rig external`, may wait longer than the 30 s default).
    #[arg(long, default_value_t = 30.0)]
    pub start_timeout_s: f64,
}

/// Arguments of the simulated rig (`bench_rig`, `fastemu rig`).
#[derive(Debug, Clone, Args)]
pub struct RigArgs {
    #[command(flatten)]
    pub process: LoopProcessArgs,
    /// Run as the far end of the UDP rig link instead of on iceoryx2: bind here (an
    /// interface address, e.g. 127.0.0.1:50001) ...
    #[arg(long, requires = "link_peer")]
    pub link_bind: Option<String>,
    /// ... and exchange datagrams with fastemu's link at this address only.
    #[arg(long, requires = "link_bind")]
    pub link_peer: Option<String>,
}

impl LoopProcessArgs {
    /// `--start-timeout-s` as a duration (checked).
    pub fn start_timeout(&self) -> anyhow::Result<std::time::Duration> {
        anyhow::ensure!(
            self.start_timeout_s > 0.0 && self.start_timeout_s.is_finite(),
            "--start-timeout-s {}: expected a number of seconds > 0",
            self.start_timeout_s
        );
        Ok(std::time::Duration::from_secs_f64(self.start_timeout_s))
    }
}

/// A loaded configuration with its text and base directory (recorded for replay).
pub struct LoadedConfig {
    pub cfg: HilConfig,
    pub text: String,
    pub base_dir: Option<PathBuf>,
}

impl LoopProcessArgs {
    /// Loads the config with its text and base directory.
    pub fn load(&self) -> anyhow::Result<LoadedConfig> {
        let mut cfg = load_or_default(self.config.as_deref())?;
        if let Some(d) = self.duration_s {
            anyhow::ensure!(
                d > 0.0 && d.is_finite(),
                "--duration-s {d}: expected a number > 0"
            );
            cfg.set_duration_s(d);
        }
        let (text, base_dir) = match &self.config {
            Some(p) => (
                std::fs::read_to_string(p)
                    .with_context(|| format!("cannot read {}", p.display()))?,
                p.canonicalize()
                    .ok()
                    .and_then(|c| c.parent().map(PathBuf::from)),
            ),
            None => (DEFAULT_CONFIG_TOML.to_string(), None),
        };
        Ok(LoadedConfig {
            cfg,
            text,
            base_dir,
        })
    }
}

pub fn run_emulator_command(args: LoopProcessArgs) -> anyhow::Result<ExitCode> {
    quiet_iceoryx2_logs();
    let c = args.load()?;
    let s = run_emulator(
        &c.cfg,
        &c.text,
        c.base_dir.as_deref(),
        &args.run_id,
        &args.out,
    )
    .context("emulator")?;
    say_line(format!(
        "emulator: {} cycles, {} model steps, {} stale cycles, {} missing samples, {} missed deadlines (longest stall {:.1} ms){}, {} records dropped{}",
        s.cycles,
        s.model_steps,
        s.stale_cycles,
        s.missing_samples,
        s.missed_deadlines,
        s.longest_stall_ms,
        if s.standby_cpus.is_empty() {
            String::new()
        } else {
            format!(
                ", {} cycles run by the standby thread on CPU {:?}",
                s.standby_cycles, s.standby_cpus
            )
        },
        s.records.dropped,
        s.fault.as_ref().map_or(String::new(), |f| format!(", tripped: {f}"))
    ));
    Ok(exit_code(s.fault.is_some()))
}

pub fn run_controller_command(args: LoopProcessArgs) -> anyhow::Result<ExitCode> {
    quiet_iceoryx2_logs();
    let c = args.load()?;
    let s = run_controller(
        &c.cfg,
        &c.text,
        c.base_dir.as_deref(),
        &args.run_id,
        &args.out,
    )
    .context("controller")?;
    say_line(format!(
        "controller: {} commands ({} keep-alive repeats), {} limited, {} records dropped{}",
        s.commands,
        s.repeated_commands,
        s.limited_commands,
        s.records.dropped,
        s.fault
            .as_ref()
            .map_or(String::new(), |f| format!(", fault: {f}"))
    ));
    Ok(exit_code(s.fault.is_some()))
}

pub fn run_rig_command(args: RigArgs) -> anyhow::Result<ExitCode> {
    use crate::link::socket::parse_link_address;
    quiet_iceoryx2_logs();
    let link = match (&args.link_bind, &args.link_peer) {
        (Some(bind), Some(peer)) => Some((
            parse_link_address("--link-bind", bind)?,
            parse_link_address("--link-peer", peer)?,
        )),
        _ => None,
    };
    let start_timeout = args.process.start_timeout()?;
    let args = args.process;
    let c = args.load()?;
    // The rig's loop takes its transport from here: iceoryx2 inside `rig`, or the far
    // end of the UDP rig link from `link` (so `rig/` never imports `link/`).
    let s = match link {
        None => crate::rig::process::run_rig_ipc(
            &c.cfg,
            &c.text,
            c.base_dir.as_deref(),
            &args.run_id,
            &args.out,
            start_timeout,
        ),
        Some((bind, peer)) => {
            let mut transport = crate::link::rig_end::UdpRigEnd::open(
                bind,
                peer,
                c.cfg.loop_.period_ns,
                start_timeout,
            )
            .context("bench_rig: the UDP rig link")?;
            crate::rig::process::run_rig(
                &c.cfg,
                &c.text,
                c.base_dir.as_deref(),
                &args.run_id,
                &args.out,
                &mut transport,
            )
        }
    }
    .context("bench_rig")?;
    say_line(format!(
        "bench_rig: {} steps, {} missed deadlines, {} periods without a new command{}{}",
        s.steps,
        s.missed_deadlines,
        s.periods_without_command,
        if s.rejected_commands > 0 {
            format!(
                ", {} commands dropped for their content",
                s.rejected_commands
            )
        } else {
            String::new()
        },
        s.fault.as_ref().map_or(String::new(), |f| format!(
            ", interlock: {f} (held{})",
            if s.at_rest {
                ", at rest"
            } else {
                ", not at rest"
            }
        ))
    ));
    Ok(exit_code(s.fault.is_some()))
}

/// 3 when the process ended on a fault, else 0.
fn exit_code(faulted: bool) -> ExitCode {
    if faulted {
        ExitCode::from(3)
    } else {
        ExitCode::SUCCESS
    }
}

/// Writes one line to stderr in a single write: the three loop processes end at the same
/// moment and share `hil`'s stderr, and `eprintln!` writes piece by piece (their lines
/// came out interleaved).
fn say_line(line: String) {
    use std::io::Write;
    let _ = std::io::stderr().write_all(format!("{line}\n").as_bytes());
}
