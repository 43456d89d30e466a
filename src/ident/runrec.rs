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

use crate::csvio::read_columns;
use crate::hil::config::{parse_hil_config, HilConfig};

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
        let message = if run_dir.join("records.mcap").is_file() {
            "no rig.csv: this reader does not read records.mcap yet; export the run's records as CSV first"
        } else {
            "no rig.csv: expected the report directory of a `fastemu hil` run"
        };
        return Err(RunRecordError {
            path: run_dir.display().to_string(),
            message: message.into(),
        });
    }
    let csv_err = |e: crate::csvio::CsvError| RunRecordError {
        path: e.path.clone(),
        message: e.message.clone(),
    };
    let cols = read_columns(&rig, &["t_s", "z_measured_m", "actuator_force_n"]).map_err(csv_err)?;
    let mut columns = cols.data.into_iter();
    let time_s = columns.next().unwrap_or_default();
    let (dt_s, displacement_m, applied_force_n) = uniform_series(
        &time_s,
        &columns.next().unwrap_or_default(),
        &columns.next().unwrap_or_default(),
    )
    .map_err(|message| RunRecordError {
        path: rig.display().to_string(),
        message,
    })?;
    let meta_path = run_dir.join("emulator-meta.json");
    let config_path = run_dir.join("config.toml");
    let (config_text, config_origin, config_base_dir) = if meta_path.is_file() {
        let text = std::fs::read_to_string(&meta_path).map_err(|e| RunRecordError {
            path: meta_path.display().to_string(),
            message: format!("cannot read: {e}"),
        })?;
        // Read as plain JSON (the keys `replay` uses), not through the loop's own type, so
        // that this reader does not move with the loop's record types.
        let meta: serde_json::Value = serde_json::from_str(&text).map_err(|e| RunRecordError {
            path: meta_path.display().to_string(),
            message: format!("not JSON: {e}"),
        })?;
        let config_text = meta["config_text"]
            .as_str()
            .ok_or_else(|| RunRecordError {
                path: meta_path.display().to_string(),
                message: "no `config_text` string".into(),
            })?
            .to_string();
        let origin = meta["config_origin"]
            .as_str()
            .map_or_else(|| meta_path.display().to_string(), str::to_string);
        let base_dir = meta["config_base_dir"].as_str().map(PathBuf::from);
        (config_text, origin, base_dir)
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

/// The record on a uniform grid at its nominal step (the median step). A loop that
/// missed deadlines skips periods, so some steps are whole multiples of the nominal one;
/// the gaps are filled by linear interpolation.
fn uniform_series(
    time_s: &[f64],
    a: &[f64],
    b: &[f64],
) -> Result<(f64, Vec<f64>, Vec<f64>), String> {
    if time_s.len() < 2 {
        return Err(format!("{} samples: too short a record", time_s.len()));
    }
    let mut steps: Vec<f64> = time_s.windows(2).map(|w| w[1] - w[0]).collect();
    steps.sort_by(f64::total_cmp);
    let dt_s = steps[steps.len() / 2];
    if dt_s.is_nan() || dt_s <= 0.0 {
        return Err("`t_s` does not increase".into());
    }
    for (i, w) in time_s.windows(2).enumerate() {
        let ratio = (w[1] - w[0]) / dt_s;
        if ratio < 0.5 || (ratio - ratio.round()).abs() > 0.01 || ratio > 1000.0 {
            return Err(format!(
                "`t_s` step {} s at row {} is no whole multiple of the nominal step {dt_s} s",
                w[1] - w[0],
                i + 2
            ));
        }
    }
    let n = ((time_s[time_s.len() - 1] - time_s[0]) / dt_s).round() as usize + 1;
    let (mut out_a, mut out_b) = (Vec::with_capacity(n), Vec::with_capacity(n));
    let mut j = 0;
    for k in 0..n {
        let t = time_s[0] + k as f64 * dt_s;
        while j + 2 < time_s.len() && time_s[j + 1] <= t + 1e-9 * dt_s {
            j += 1;
        }
        let span = (time_s[j + 1] - time_s[j]).max(1e-300);
        let u = ((t - time_s[j]) / span).clamp(0.0, 1.0);
        out_a.push(a[j] + u * (a[j + 1] - a[j]));
        out_b.push(b[j] + u * (b[j + 1] - b[j]));
    }
    Ok((dt_s, out_a, out_b))
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
