//! `fastemu replay --record R`: re-runs the emulator's model on the recorded input stream
//! (the `/emulator` records of `records.mcap`, a report directory, a crashed run's parts,
//! or an exported `emulator.csv` with its `meta.json`) and checks every force and local
//! law bit for bit.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::Args;

use crate::csvio::read_columns;
use crate::hil::config::parse_hil_config;
use crate::hil::emulator::EmulatorRecord;
use crate::model::effects::{ModelStepper, StepperMode};
use crate::records::{RecordSet, RunMeta};

#[derive(Debug, Clone, Args)]
pub struct ReplayArgs {
    /// The records: `DIR/records.mcap`, a report directory, or an exported `emulator.csv`.
    #[arg(long)]
    pub record: PathBuf,
    /// The run's metadata for a CSV record (default: `meta.json` next to it).
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

/// The recorded steps: displacement, force and the law's stiffness, damping and rate.
type Steps = Vec<[f64; 5]>;

fn from_csv(path: &Path, meta: Option<&Path>) -> anyhow::Result<(RunMeta, Steps)> {
    let meta_path = meta.map_or_else(|| path.with_file_name("meta.json"), Path::to_path_buf);
    let meta: RunMeta = serde_json::from_str(
        &std::fs::read_to_string(&meta_path)
            .with_context(|| format!("cannot read {}", meta_path.display()))?,
    )
    .with_context(|| format!("{}: not a run meta file", meta_path.display()))?;
    let cols = read_columns(
        path,
        &[
            "z_used_m",
            "force_n",
            "law_stiffness_n_per_m",
            "law_damping_ns_per_m",
            "law_force_rate_n_per_s",
        ],
    )?;
    let steps = (0..cols.len())
        .map(|i| [0, 1, 2, 3, 4].map(|c| cols.data[c][i]))
        .collect();
    Ok((meta, steps))
}

fn from_records(path: &Path) -> anyhow::Result<(RunMeta, Steps)> {
    let set = RecordSet::open(path)?;
    let meta = set.meta_of("emulator")?;
    let mut steps = Vec::new();
    set.for_each::<EmulatorRecord>(|_, r| {
        steps.push([
            r.z_used_m,
            r.force_n,
            r.law_stiffness_n_per_m,
            r.law_damping_ns_per_m,
            r.law_force_rate_n_per_s,
        ])
    })?;
    Ok((meta, steps))
}

pub fn replay(args: &ReplayArgs) -> anyhow::Result<ReplayCounts> {
    let is_csv = args.record.extension().is_some_and(|e| e == "csv");
    let (meta, steps) = if is_csv {
        from_csv(&args.record, args.meta.as_deref())?
    } else {
        from_records(&args.record)?
    };
    let cfg = parse_hil_config(
        &meta.config_text,
        &meta.config_origin,
        meta.config_base_dir.as_deref(),
    )?;
    let mut stepper = ModelStepper::new(
        &cfg.augmented,
        StepperMode::Emulation,
        cfg.loop_.dt_s(),
        0.0,
    )
    .with_law_frequency(&cfg.augmented, cfg.emulator.law_frequency_hz);
    let mut counts = ReplayCounts {
        rows: steps.len(),
        ..ReplayCounts::default()
    };
    for (i, row) in steps.iter().enumerate() {
        if i == 0 {
            // The emulator starts in static equilibrium at its first sample.
            stepper.reset_static(row[0]);
        }
        let (force, _) = stepper.step(row[0]);
        let law = stepper.local_law();
        counts.replayed += 1;
        let got = [
            force,
            law.stiffness_n_per_m,
            law.damping_ns_per_m,
            law.force_rate_n_per_s,
        ];
        let same = got
            .iter()
            .zip(&row[1..])
            .all(|(a, b)| a.to_bits() == b.to_bits());
        if !same {
            counts.mismatches += 1;
            counts.first_mismatch_row.get_or_insert(i);
        }
    }
    Ok(counts)
}

pub fn run(args: ReplayArgs) -> anyhow::Result<ExitCode> {
    let c = replay(&args)?;
    println!(
        "replay: {} rows, {} model steps replayed, {} forces differ{} (each step's force and local law compared bit for bit)",
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
