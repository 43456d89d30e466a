//! `fastemu export --record R --out DIR [--format csv]`: a run's records as CSV files (one
//! per record stream, the record types' fields as columns, described in `columns.txt`)
//! plus the run's metadata (`meta.json`, `config.toml`), for MATLAB, pandas and the CSV tools. Reads
//! `records.mcap`, a report directory, or the parts a crashed run left.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::{Args, ValueEnum};

use crate::hil::controller::ControllerRecord;
use crate::hil::emulator::{AfterFaultSampleRecord, EmulatorRecord};
use crate::records::export::{export_csv, CsvOf};
use crate::records::{EventRecord, RecordSet};
use crate::rig::core::RigRecord;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ExportFormat {
    Csv,
}

#[derive(Debug, Clone, Args)]
pub struct ExportArgs {
    /// The records: `DIR/records.mcap`, a report directory, or its `parts/` directory.
    #[arg(long)]
    pub record: PathBuf,
    /// Output directory (created if needed).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, value_enum, default_value = "csv")]
    pub format: ExportFormat,
}

/// Exports the records at `record` as CSV into `out`; returns (file, rows) per file.
pub fn export_dir(record: &Path, out: &Path) -> anyhow::Result<Vec<(PathBuf, u64)>> {
    let set = RecordSet::open(record)?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let sinks = vec![
        CsvOf::<RigRecord>::create(&out.join("rig.csv"))?,
        CsvOf::<EmulatorRecord>::create(&out.join("emulator.csv"))?,
        CsvOf::<AfterFaultSampleRecord>::create(&out.join("emulator_after_fault.csv"))?,
        CsvOf::<ControllerRecord>::create(&out.join("controller.csv"))?,
        CsvOf::<EventRecord>::create(&out.join("events.csv"))?,
    ];
    let (written, stats) = export_csv(&set, sinks)?;
    let columns = out.join("columns.txt");
    std::fs::write(&columns, columns_text())
        .with_context(|| format!("cannot write {}", columns.display()))?;
    for (p, e) in &stats.truncated {
        eprintln!(
            "export: {} ends early ({e}): exported up to its last closed chunk",
            p.display()
        );
    }
    let metas = set.metas()?;
    if let Some(meta) = metas
        .iter()
        .find(|m| m.process == "emulator")
        .or(metas.first())
    {
        std::fs::write(out.join("meta.json"), serde_json::to_string_pretty(meta)?)?;
        std::fs::write(out.join("config.toml"), &meta.config_text)?;
    }
    Ok(written)
}

/// What each CSV's columns hold (type, name, unit and codes), one section per file: the
/// records' own schema, so a CSV reader needs nothing else to read `kind = 8`.
fn columns_text() -> String {
    use crate::records::Record;
    let mut text = String::from(
        "# Columns of the exported CSV files: type, name (units in the name), what it holds.\n",
    );
    for (file, schema) in [
        ("rig.csv", RigRecord::schema_text()),
        ("emulator.csv", EmulatorRecord::schema_text()),
        (
            "emulator_after_fault.csv",
            AfterFaultSampleRecord::schema_text(),
        ),
        ("controller.csv", ControllerRecord::schema_text()),
        ("events.csv", EventRecord::schema_text()),
    ] {
        text.push_str(&format!("\n[{file}]\n{schema}"));
    }
    text.push_str("\n[fault codes] (fault_code, remote_fault_code, rig_fault_code)\n");
    for code in 1..64 {
        if let Some(f) = crate::hil::fault::Fault::from_code(code) {
            text.push_str(&format!("{code} {}\n", f.name()));
        }
    }
    text
}

pub fn run(args: ExportArgs) -> anyhow::Result<ExitCode> {
    let written = export_dir(&args.record, &args.out)?;
    for (path, rows) in &written {
        println!("export: {} ({rows} rows)", path.display());
    }
    println!(
        "export: {} (what each column holds: units, codes)",
        args.out.join("columns.txt").display()
    );
    Ok(ExitCode::SUCCESS)
}
