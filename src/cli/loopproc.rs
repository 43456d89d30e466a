//! `fastemu emulator` and `fastemu controller`: the loop processes' command lines.
//! Parse arguments, load the config, run the process; no loop logic here.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::Args;

use crate::hil::config::{load_or_default, DEFAULT_CONFIG_TOML};
use crate::hil::process::{run_controller, run_emulator};
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
    /// Directory for this process's records.
    #[arg(long, default_value = ".")]
    pub out: PathBuf,
    /// Overrides `[scenario] duration_s`.
    #[arg(long)]
    pub duration_s: Option<f64>,
}

impl LoopProcessArgs {
    /// Loads the config; returns it with its text and base directory (for replay).
    pub fn load(&self) -> anyhow::Result<(crate::hil::config::HilConfig, String, Option<PathBuf>)> {
        let mut cfg = load_or_default(self.config.as_deref())?;
        if let Some(d) = self.duration_s {
            anyhow::ensure!(
                d > 0.0 && d.is_finite(),
                "--duration-s {d}: expected a number > 0"
            );
            cfg.scenario.duration_s = d;
        }
        let (text, base) = match &self.config {
            Some(p) => (
                std::fs::read_to_string(p)
                    .with_context(|| format!("cannot read {}", p.display()))?,
                p.canonicalize()
                    .ok()
                    .and_then(|c| c.parent().map(PathBuf::from)),
            ),
            None => (DEFAULT_CONFIG_TOML.to_string(), None),
        };
        Ok((cfg, text, base))
    }
}

pub fn run_emulator_command(args: LoopProcessArgs) -> anyhow::Result<ExitCode> {
    quiet_iceoryx2_logs();
    let (cfg, text, base) = args.load()?;
    let summary =
        run_emulator(&cfg, &text, base.as_deref(), &args.run_id, &args.out).context("emulator")?;
    eprintln!(
        "emulator: {} cycles, {} model steps, {} stale samples, {} missed deadlines, {} records dropped{}",
        summary.cycles,
        summary.model_steps,
        summary.stale_samples,
        summary.missed_deadlines,
        summary.records_dropped,
        summary.fault.as_ref().map_or(String::new(), |f| format!(", tripped: {f}"))
    );
    Ok(if summary.fault.is_some() {
        ExitCode::from(3)
    } else {
        ExitCode::SUCCESS
    })
}

pub fn run_controller_command(args: LoopProcessArgs) -> anyhow::Result<ExitCode> {
    quiet_iceoryx2_logs();
    let (cfg, _, _) = args.load()?;
    let summary = run_controller(&cfg, &args.run_id, &args.out).context("controller")?;
    eprintln!(
        "controller: {} commands, {} limited, {} records dropped{}",
        summary.commands,
        summary.limited_commands,
        summary.records_dropped,
        summary
            .fault
            .as_ref()
            .map_or(String::new(), |f| format!(", fault: {f}"))
    );
    Ok(if summary.fault.is_some() {
        ExitCode::from(3)
    } else {
        ExitCode::SUCCESS
    })
}

pub fn run_rig_command(args: LoopProcessArgs) -> anyhow::Result<ExitCode> {
    quiet_iceoryx2_logs();
    let (cfg, _, _) = args.load()?;
    let summary =
        crate::rig::process::run_rig(&cfg, &args.run_id, &args.out).context("bench_rig")?;
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
    Ok(if summary.fault.is_some() {
        ExitCode::from(3)
    } else {
        ExitCode::SUCCESS
    })
}
