//! `fastemu emulator`, `fastemu controller` and the hidden `fastemu rig`: the loop
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
    eprintln!(
        "emulator: {} cycles, {} model steps, {} stale cycles, {} missing samples, {} missed deadlines (longest stall {:.1} ms), {} records dropped{}",
        s.cycles,
        s.model_steps,
        s.stale_cycles,
        s.missing_samples,
        s.missed_deadlines,
        s.longest_stall_ms,
        s.records.dropped,
        s.fault.as_ref().map_or(String::new(), |f| format!(", tripped: {f}"))
    );
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
    eprintln!(
        "controller: {} commands ({} keep-alive repeats), {} limited, {} records dropped{}",
        s.commands,
        s.repeated_commands,
        s.limited_commands,
        s.records.dropped,
        s.fault
            .as_ref()
            .map_or(String::new(), |f| format!(", fault: {f}"))
    );
    Ok(exit_code(s.fault.is_some()))
}

pub fn run_rig_command(args: LoopProcessArgs) -> anyhow::Result<ExitCode> {
    quiet_iceoryx2_logs();
    let c = args.load()?;
    let s = crate::rig::process::run_rig(
        &c.cfg,
        &c.text,
        c.base_dir.as_deref(),
        &args.run_id,
        &args.out,
    )
    .context("bench_rig")?;
    eprintln!(
        "bench_rig: {} steps, {} missed deadlines, {} periods without a new command{}",
        s.steps,
        s.missed_deadlines,
        s.periods_without_command,
        s.fault.as_ref().map_or(String::new(), |f| format!(
            ", interlock: {f} (held{})",
            if s.at_rest {
                ", at rest"
            } else {
                ", not at rest"
            }
        ))
    );
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
