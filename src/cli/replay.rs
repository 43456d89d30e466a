//! `fastemu replay --record R`: re-runs the emulator's model on a recorded input stream
//! (`emulator.csv` + `emulator-meta.json` beside it) and checks the forces bit for bit.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::Args;

use crate::csvio::read_columns;
use crate::hil::config::parse_hil_config;
use crate::hil::process::EmulatorMeta;
use crate::ipc::messages::emulator_state;
use crate::model::effects::{ModelStepper, StepperMode};

#[derive(Debug, Clone, Args)]
pub struct ReplayArgs {
    /// The emulator record (`emulator.csv` of a `hil` report directory).
    #[arg(long)]
    pub record: PathBuf,
    /// Its meta file (default: `emulator-meta.json` next to the record).
    #[arg(long)]
    pub meta: Option<PathBuf>,
}

/// Counts of a replay.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ReplayCounts {
    pub rows: usize,
    pub replayed: usize,
    pub mismatches: usize,
    pub first_mismatch_row: Option<usize>,
}

pub fn replay(args: &ReplayArgs) -> anyhow::Result<ReplayCounts> {
    let meta_path = args
        .meta
        .clone()
        .unwrap_or_else(|| args.record.with_file_name("emulator-meta.json"));
    let meta: EmulatorMeta = serde_json::from_str(
        &std::fs::read_to_string(&meta_path)
            .with_context(|| format!("cannot read {}", meta_path.display()))?,
    )
    .with_context(|| format!("{}: not an emulator meta file", meta_path.display()))?;
    let cfg = parse_hil_config(
        &meta.config_text,
        &meta.config_origin,
        meta.config_base_dir.as_deref(),
    )?;
    let cols = read_columns(&args.record, &["state", "z_used_m", "force_n"])?;
    let (state, z, force) = (&cols.data[0], &cols.data[1], &cols.data[2]);
    let mut stepper = ModelStepper::new(
        &cfg.augmented,
        StepperMode::Emulation,
        cfg.loop_.dt_s(),
        0.0,
    );
    let mut started = false;
    let mut counts = ReplayCounts {
        rows: z.len(),
        ..ReplayCounts::default()
    };
    for i in 0..z.len() {
        if state[i] as u32 != emulator_state::RUNNING {
            continue;
        }
        if !started {
            stepper.reset_static(z[i]);
            started = true;
        }
        let (f, _) = stepper.step(z[i]);
        counts.replayed += 1;
        if f.to_bits() != force[i].to_bits() {
            counts.mismatches += 1;
            counts.first_mismatch_row.get_or_insert(i);
        }
    }
    Ok(counts)
}

pub fn run(args: ReplayArgs) -> anyhow::Result<ExitCode> {
    let c = replay(&args)?;
    println!(
        "replay: {} rows, {} model steps replayed, {} forces differ{}",
        c.rows,
        c.replayed,
        c.mismatches,
        c.first_mismatch_row
            .map_or(String::new(), |r| format!(" (first at data row {r})"))
    );
    if c.mismatches > 0 || c.replayed == 0 {
        return Ok(ExitCode::FAILURE);
    }
    Ok(ExitCode::SUCCESS)
}
