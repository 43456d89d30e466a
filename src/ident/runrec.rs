//! The one reader of a `fastemu hil` run directory for diagnosis, and the sentence that
//! names the loop's delay knob.
//!
//! A run's records are changing format (CSV today, `records.mcap` later): every read of
//! a run directory goes through `load_run_history`, and every mention of the knob that
//! sets the loop's delay compensation through `delay_knob_advice`, so a new format or a
//! new knob is one edit here.
//!
//! Reads today: `rig.csv` (columns `t_s`, `z_measured_m`: the displacement the emulator
//! was given, `actuator_force_n`: the force applied to the specimen) and the config text
//! from `emulator-meta.json` (`config_text`, as `replay` reads it), else `config.toml` in
//! the run directory.
//!
//! Must not: write anything, or touch a running loop.

use std::fmt;
use std::path::{Path, PathBuf};

use crate::csvio::{read_columns, uniform_step};
use crate::hil::config::{parse_hil_config, HilConfig};
use crate::hil::process::EmulatorMeta;

/// What diagnosis needs from a run: the record as a history test, and the config it ran.
#[derive(Debug, Clone)]
pub struct RunHistory {
    pub dt_s: f64,
    /// Displacement the emulator was given (the rig's measurement), m.
    pub displacement_m: Vec<f64>,
    /// Force the actuator applied to the specimen, N.
    pub applied_force_n: Vec<f64>,
    /// The HIL config text the run used, and where it came from.
    pub config_text: String,
    pub config_origin: String,
    pub config_base_dir: Option<PathBuf>,
}

impl RunHistory {
    /// The run's validated config (its `[model]` is what the emulator ran).
    pub fn config(&self) -> Result<HilConfig, RunRecordError> {
        parse_hil_config(
            &self.config_text,
            &self.config_origin,
            self.config_base_dir.as_deref(),
        )
        .map_err(|e| RunRecordError {
            path: self.config_origin.clone(),
            message: e.to_string(),
        })
    }
}

/// A run directory that cannot be read: names the file.
#[derive(Debug, Clone, PartialEq)]
pub struct RunRecordError {
    pub path: String,
    pub message: String,
}

impl fmt::Display for RunRecordError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.path, self.message)
    }
}

impl std::error::Error for RunRecordError {}

/// Reads the rig record and the config of the run in `run_dir`.
pub fn load_run_history(run_dir: &Path) -> Result<RunHistory, RunRecordError> {
    let rig = run_dir.join("rig.csv");
    if !rig.is_file() {
        return Err(RunRecordError {
            path: run_dir.display().to_string(),
            message: "no rig.csv: expected the report directory of a `fastemu hil` run".into(),
        });
    }
    let csv_err = |e: crate::csvio::CsvError| RunRecordError {
        path: e.path.clone(),
        message: e.message.clone(),
    };
    let cols = read_columns(&rig, &["t_s", "z_measured_m", "actuator_force_n"]).map_err(csv_err)?;
    let origin = rig.display().to_string();
    let dt_s = uniform_step(&cols.data[0], &cols.lines, &origin, "t_s").map_err(csv_err)?;
    let mut columns = cols.data.into_iter().skip(1);
    let displacement_m = columns.next().unwrap_or_default();
    let applied_force_n = columns.next().unwrap_or_default();
    let meta_path = run_dir.join("emulator-meta.json");
    let config_path = run_dir.join("config.toml");
    let (config_text, config_origin, config_base_dir) = if meta_path.is_file() {
        let text = std::fs::read_to_string(&meta_path).map_err(|e| RunRecordError {
            path: meta_path.display().to_string(),
            message: format!("cannot read: {e}"),
        })?;
        let meta: EmulatorMeta = serde_json::from_str(&text).map_err(|e| RunRecordError {
            path: meta_path.display().to_string(),
            message: format!("not an emulator meta file: {e}"),
        })?;
        (meta.config_text, meta.config_origin, meta.config_base_dir)
    } else if config_path.is_file() {
        let text = std::fs::read_to_string(&config_path).map_err(|e| RunRecordError {
            path: config_path.display().to_string(),
            message: format!("cannot read: {e}"),
        })?;
        (
            text,
            config_path.display().to_string(),
            Some(run_dir.to_path_buf()),
        )
    } else {
        return Err(RunRecordError {
            path: run_dir.display().to_string(),
            message:
                "neither emulator-meta.json nor config.toml: cannot tell which model the run used"
                    .into(),
        });
    };
    Ok(RunHistory {
        dt_s,
        displacement_m,
        applied_force_n,
        config_text,
        config_origin,
        config_base_dir,
    })
}

/// What a fitted channel delay between emulated and applied force means for the loop,
/// in the words of the run's config. `force_lag_s` > 0: the applied force lags.
pub fn delay_knob_advice(config: &HilConfig, force_lag_s: f64) -> String {
    let us = (force_lag_s * 1e6).abs();
    let knob_us = config.controller.compensation_delay_s * 1e6;
    if force_lag_s < 0.0 {
        format!(
            "applied force leads the emulated force by {us:.0} us: the controller's compensation_delay_us ({knob_us:.0} us) is about {us:.0} us too long"
        )
    } else {
        format!(
            "applied force lags the emulated force by {us:.0} us: the controller's compensation_delay_us ({knob_us:.0} us) is about {us:.0} us too short (or the loop's delay grew)"
        )
    }
}
