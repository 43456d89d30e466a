//! The one reader of a `fastemu hil` run directory for diagnosis, and the sentence that
//! names the loop's delay knob.
//!
//! Every read of a run goes through `load_run_history`, and every mention of the knob
//! that sets the loop's delay compensation through `delay_knob_advice`, so a new record
//! format or a new knob is one edit here.
//!
//! Reads the run's records (`records.mcap`, or the parts a run that did not finish left,
//! through `crate::records::RecordSet`): the rig's `/rig` stream (`t_s`, `z_measured_m`:
//! the displacement the emulator was given, `actuator_force_n`: the force applied to the
//! specimen, `state`) and the config text from the rig's (else the emulator's) `/meta`.
//! A directory written by `fastemu export` (`rig.csv` with `meta.json` or `config.toml`)
//! is read the same way. Only the run's first stretch in force control (rig state
//! RUNNING) is used: a hold restrains the specimen and says nothing about the element.
//!
//! Must not: write anything, or touch a running loop.

use std::fmt;
use std::path::{Path, PathBuf};

use crate::csvio::read_columns;
use crate::hil::config::{parse_hil_config, CommandMode, HilConfig};
use crate::hil::emulator::EmulatorRecord;
use crate::ipc::messages::rig_state;
use crate::records::RecordSet;
use crate::rig::core::RigRecord;

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
    /// Which part of the record was used, in words (for the report).
    pub used: String,
    /// The run's rig was external: its samples stand in for the rig's records, and the
    /// law lead is the rig's own.
    pub external_rig: bool,
    /// The element's self-heating rise over the run as the emulator recorded it (largest,
    /// last), K; `None` when it stayed 0 (no self-heating in the model) or was not recorded.
    pub element_temperature_rise_k: Option<(f64, f64)>,
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

/// Reads the rig record and the config of the run in `run_dir` (a report directory, its
/// `records.mcap`, or a directory written by `fastemu export`).
pub fn load_run_history(run_dir: &Path) -> Result<RunHistory, RunRecordError> {
    // The records when there are any (a report directory may also hold `hil --csv`'s
    // CSVs); an exported directory otherwise.
    let rig_csv = run_dir.join("rig.csv");
    let raw = match RecordSet::open(run_dir) {
        Ok(set) => read_records(&set)?,
        Err(_) if run_dir.is_dir() && rig_csv.is_file() => read_exported(run_dir, &rig_csv)?,
        Err(e) => {
            return Err(RunRecordError {
                path: run_dir.display().to_string(),
                message: format!(
                    "{}; expected the report directory of a `fastemu hil` run, its records.mcap, or a directory written by `fastemu export`",
                    e.message
                ),
            })
        }
    };
    let (first, last) = usable_stretch(&raw.usable).ok_or_else(|| RunRecordError {
        path: raw.origin.clone(),
        message: format!(
            "{} {}, none in force control (rig state RUNNING) with a finite, published sample and no fault: nothing to diagnose",
            raw.time_s.len(),
            raw.rows
        ),
    })?;
    let range = first..last + 1;
    let (dt_s, displacement_m, applied_force_n) = uniform_series(
        &raw.time_s[range.clone()],
        &raw.z_m[range.clone()],
        &raw.force_n[range.clone()],
    )
    .map_err(|message| RunRecordError {
        path: raw.origin.clone(),
        message,
    })?;
    let rows = raw.rows;
    let mut used = if first == 0 && last + 1 == raw.time_s.len() {
        format!(
            "all {} {rows} ({:.3} s to {:.3} s), in force control throughout",
            raw.time_s.len(),
            raw.time_s[first],
            raw.time_s[last]
        )
    } else {
        format!(
            "{rows} {first} to {last} of {} ({:.3} s to {:.3} s): the run's first stretch in force control on good samples (a hold, a fault, a bad or dropped sample, or the end follows)",
            raw.time_s.len(),
            raw.time_s[first],
            raw.time_s[last]
        )
    };
    if raw.external_rig {
        used.push_str(
            "; an external rig (no /rig records): its samples as the emulator recorded them (measured displacement, the rig's measured force, its state)",
        );
    }
    Ok(RunHistory {
        dt_s,
        displacement_m,
        applied_force_n,
        config_text: raw.config_text,
        config_origin: raw.config_origin,
        config_base_dir: raw.config_base_dir,
        used,
        external_rig: raw.external_rig,
        element_temperature_rise_k: raw.element_temperature_rise_k,
    })
}

/// The rig's columns and the run's config, as read.
struct RawRun {
    origin: String,
    /// What a row is, in words ("rig periods", "samples of the external rig").
    rows: &'static str,
    external_rig: bool,
    /// Largest and last self-heating rise the emulator recorded, K (None: none recorded).
    element_temperature_rise_k: Option<(f64, f64)>,
    time_s: Vec<f64>,
    z_m: Vec<f64>,
    force_n: Vec<f64>,
    /// Per row: the rig in force control (RUNNING), no fault latched, the sample
    /// published and finite, the force finite.
    usable: Vec<bool>,
    config_text: String,
    config_origin: String,
    config_base_dir: Option<PathBuf>,
}

/// Whether a row may enter the diagnosis (see `RawRun::usable`).
fn usable_row(state: u32, fault_code: u32, published: bool, z_m: f64, force_n: f64) -> bool {
    state == rig_state::RUNNING
        && fault_code == 0
        && published
        && z_m.is_finite()
        && force_n.is_finite()
}

/// First and last index of the first run of usable rows.
fn usable_stretch(usable: &[bool]) -> Option<(usize, usize)> {
    let first = usable.iter().position(|&u| u)?;
    let len = usable[first..].iter().take_while(|&&u| u).count();
    Some((first, first + len - 1))
}

fn read_records(set: &RecordSet) -> Result<RawRun, RunRecordError> {
    let rec_err = |e: crate::records::reader::RecordsError| RunRecordError {
        path: e.path,
        message: e.message,
    };
    let origin = set.files[0].display().to_string();
    let (mut time_s, mut z_m, mut force_n, mut usable) = (vec![], vec![], vec![], vec![]);
    let mut stats = set
        .for_each::<RigRecord>(|_, r| {
            time_s.push(r.t_s);
            z_m.push(r.z_measured_m);
            force_n.push(r.actuator_force_n);
            usable.push(usable_row(
                r.state,
                r.fault_code,
                r.published != 0,
                r.z_measured_m,
                r.actuator_force_n,
            ));
        })
        .map_err(rec_err)?;
    // An external rig's own records are not fastemu's: the emulator recorded what its
    // samples said (measured displacement and force, state, fault). Interpolated steps
    // stand for a missing sample and are not data.
    let external_rig = time_s.is_empty();
    let (mut rise_max_k, mut rise_last_k) = (0.0f64, 0.0f64);
    set.for_each::<EmulatorRecord>(|_, r| {
        if r.element_temperature_rise_k.is_finite() {
            rise_max_k = rise_max_k.max(r.element_temperature_rise_k);
            rise_last_k = r.element_temperature_rise_k;
        }
    })
    .map_err(rec_err)?;
    let mut measured_force = false;
    if external_rig {
        stats = set
            .for_each::<EmulatorRecord>(|_, r| {
                time_s.push(r.t_s);
                z_m.push(r.z_used_m);
                force_n.push(r.rig_force_n);
                measured_force |= r.rig_force_n.is_finite();
                usable.push(usable_row(
                    r.rig_state,
                    r.rig_fault_code,
                    r.interpolated == 0,
                    r.z_used_m,
                    r.rig_force_n,
                ));
            })
            .map_err(rec_err)?;
        if !time_s.is_empty() && !measured_force {
            return Err(RunRecordError {
                path: origin,
                message: format!(
                    "an external rig's session (no /rig records): of its {} samples none carried a measured actuator force (actuator_force_n NaN throughout), so there is no applied force to compare the emulated one with",
                    time_s.len()
                ),
            });
        }
    }
    for (path, e) in &stats.truncated {
        eprintln!(
            "diagnose: {} ends early ({e}): read up to its last closed chunk",
            path.display()
        );
    }
    let metas = set.metas().map_err(rec_err)?;
    let meta = metas
        .iter()
        .find(|m| m.process == "rig")
        .or_else(|| metas.iter().find(|m| m.process == "emulator"))
        .ok_or_else(|| RunRecordError {
            path: origin.clone(),
            message:
                "no /meta message of the rig or the emulator: cannot tell which model the run used"
                    .into(),
        })?;
    Ok(RawRun {
        origin,
        rows: if external_rig {
            "samples of the external rig"
        } else {
            "rig periods"
        },
        external_rig,
        element_temperature_rise_k: (rise_max_k > 0.0).then_some((rise_max_k, rise_last_k)),
        time_s,
        z_m,
        force_n,
        usable,
        config_text: meta.config_text.clone(),
        config_origin: meta.config_origin.clone(),
        config_base_dir: meta.config_base_dir.clone(),
    })
}

fn read_exported(dir: &Path, rig_csv: &Path) -> Result<RawRun, RunRecordError> {
    let csv_err = |e: crate::csvio::CsvError| RunRecordError {
        path: e.path.clone(),
        message: e.message.clone(),
    };
    let cols = read_columns(
        rig_csv,
        &[
            "t_s",
            "z_measured_m",
            "actuator_force_n",
            "state",
            "fault_code",
            "published",
        ],
    )
    .map_err(csv_err)?;
    let mut columns = cols.data.into_iter();
    let mut next = || columns.next().unwrap_or_default();
    let (time_s, z_m, force_n) = (next(), next(), next());
    let (state, fault_code, published) = (next(), next(), next());
    let usable = (0..time_s.len())
        .map(|i| {
            usable_row(
                state[i] as u32,
                fault_code[i] as u32,
                published[i] != 0.0,
                z_m[i],
                force_n[i],
            )
        })
        .collect();
    let meta_path = dir.join("meta.json");
    let config_path = dir.join("config.toml");
    let read = |path: &Path| {
        std::fs::read_to_string(path).map_err(|e| RunRecordError {
            path: path.display().to_string(),
            message: format!("cannot read: {e}"),
        })
    };
    let (config_text, config_origin, config_base_dir) = if meta_path.is_file() {
        let meta: crate::records::RunMeta =
            serde_json::from_str(&read(&meta_path)?).map_err(|e| RunRecordError {
                path: meta_path.display().to_string(),
                message: format!("not the run's metadata as `fastemu export` writes it: {e}"),
            })?;
        (meta.config_text, meta.config_origin, meta.config_base_dir)
    } else if config_path.is_file() {
        (
            read(&config_path)?,
            config_path.display().to_string(),
            Some(dir.to_path_buf()),
        )
    } else {
        return Err(RunRecordError {
            path: dir.display().to_string(),
            message: "rig.csv but neither meta.json nor config.toml: cannot tell which model the run used".into(),
        });
    };
    Ok(RawRun {
        origin: rig_csv.display().to_string(),
        rows: "rig periods",
        external_rig: false,
        element_temperature_rise_k: None,
        time_s,
        z_m,
        force_n,
        usable,
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
/// in the words of the run's config. `force_lag_s` > 0: the applied force lags. The knob
/// is the lead the controller sends in law mode (`[compensation] initial_delay_us`, the
/// default, which the controller refines during the run when `adapt` is on), the
/// controller's compensation delay in force mode (`[controller] compensation_delay_us`).
pub fn delay_knob_advice(config: &HilConfig, force_lag_s: f64, external_rig: bool) -> String {
    let us = (force_lag_s * 1e6).abs();
    // The launcher's plan is a function of the configuration: a lead it fixed is the knob.
    let planned = crate::hil::check::plan_for_rig(config, external_rig).filter(|p| p.lead_fixed);
    let knob = match config.controller.command_mode {
        CommandMode::Law if planned.is_some() => format!(
            "the lead the launcher fixed from the declared actuator ({:.0} us; [compensation] plan_from_actuator and actuator_tolerance, the report's compensation.plan)",
            planned.map_or(f64::NAN, |p| p.lead_us)
        ),
        CommandMode::Law => format!(
            "{}[compensation] initial_delay_us ({:.0} us{})",
            if external_rig {
                "the lead the external rig applied (it follows the commands' compensation.lead_s): "
            } else {
                ""
            },
            config.compensation.initial_delay_s * 1e6,
            if config.compensation.adapt {
                "; adapt = true refined it during the run, see the report's compensation"
            } else {
                ""
            }
        ),
        CommandMode::Force => format!(
            "[controller] compensation_delay_us ({:.0} us)",
            config.controller.compensation_delay_s * 1e6
        ),
    };
    if force_lag_s < 0.0 {
        format!(
            "applied force leads the emulated force by {us:.0} us: {knob} is about {us:.0} us too long"
        )
    } else {
        format!(
            "applied force lags the emulated force by {us:.0} us: {knob} is about {us:.0} us too short (or the loop's delay grew)"
        )
    }
}
