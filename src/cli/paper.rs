//! `fastemu paper`: reproduces the paper's tables and figures (SPEC 3) into a directory.
//! Argument handling only; the science is in `crate::paper`.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;

use crate::paper::{run_all, PaperOptions};

#[derive(Args)]
pub struct PaperArgs {
    /// Output directory (created if missing): CSV + PNG per figure, summary.json/.md.
    #[arg(long)]
    pub out: PathBuf,
    /// Coarse grids and short settling (seconds instead of about a minute; for tests).
    #[arg(long)]
    pub quick: bool,
}

pub fn run(args: PaperArgs) -> anyhow::Result<ExitCode> {
    run_all(&args.out, &PaperOptions { quick: args.quick })?;
    Ok(ExitCode::SUCCESS)
}
