//! Command-line handlers: argument structs and `run` functions, one module per command.
//! Handlers may do I/O and allocate; they never run inside the real-time loop.

pub mod bench;
pub mod ctl;
pub mod diagnose;
pub mod equiv;
pub mod export;
pub mod hil;
pub mod identify;
pub mod link;
pub mod loopproc;
pub mod paper;
pub mod replay;
pub mod simulate;
pub mod synth;

use anyhow::Context;
use std::path::Path;

use crate::model::file::{load_model_file, ModelSpec};

/// Loads a model file for a command (error already names the file).
pub fn load_model(path: &Path) -> anyhow::Result<ModelSpec> {
    Ok(load_model_file(path)?)
}

/// Creates the parent directory of an output file if needed.
pub fn ensure_parent_dir(path: &Path) -> anyhow::Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("cannot create directory {}", parent.display()))?;
    }
    Ok(())
}
