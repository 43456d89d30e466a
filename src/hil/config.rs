//! The HIL run configuration (one TOML file: loop, model, emulator, controller, rig,
//! scenario): parsed raw with `deny_unknown_fields`, then validated into typed structs.
//!
//! Every error is one line naming the file, the key, the value and what would be valid.
//! Must not: fill in physical constants silently (every physical key is required).

use std::fmt;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::model::effects::AugmentedModel;
use crate::model::file::{load_model_file, parse_model_toml, ModelSpec};

/// The default configuration, embedded so `fastemu hil` runs from any directory.
pub const DEFAULT_CONFIG_TOML: &str = include_str!("../../configs/hil-default.toml");
/// Name used for the embedded default in messages.
pub const DEFAULT_CONFIG_ORIGIN: &str = "<embedded configs/hil-default.toml>";

/// A configuration error: file, key and what is wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct ConfigError {
    pub origin: String,
    pub key: String,
    pub message: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.key.is_empty() {
            write!(f, "{}: {}", self.origin, self.message)
        } else {
            write!(f, "{}: `{}`: {}", self.origin, self.key, self.message)
        }
    }
}

impl std::error::Error for ConfigError {}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    #[serde(rename = "loop")]
    loop_: RawLoop,
    model: toml::Table,
    emulator: RawEmulator,
    controller: RawController,
    rig: RawRig,
    scenario: RawScenario,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLoop {
    rate_hz: f64,
    spin_us: f64,
    emulator_phase_us: f64,
    sample_wait_us: f64,
    trip_after_stale_samples: u32,
    record_queue_capacity: usize,
    #[serde(default)]
    lock_memory: bool,
    #[serde(default)]
    fifo_priority: i32,
    #[serde(default)]
    emulator_cpus: Vec<usize>,
    #[serde(default)]
    rig_cpus: Vec<usize>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawEmulator {
    displacement_min_m: f64,
    displacement_max_m: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawController {
    compensation_order: u32,
    compensation_enabled: bool,
    compensation_delay_us: f64,
    force_min_n: f64,
    force_max_n: f64,
    force_rate_max_n_per_s: f64,
    limit_action: String,
    stale_setpoint_periods: u32,
    emulator_heartbeat_timeout_ms: f64,
    safe_force_n: f64,
    safe_ramp_n_per_s: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRig {
    specimen_mass_kg: f64,
    damping_ns_per_m: f64,
    actuator_lag_us: f64,
    actuator_delay_us: f64,
    actuator_force_max_n: f64,
    sensor_noise_m: f64,
    sensor_resolution_m: f64,
    seed: u64,
    internal_substeps: u32,
    command_stale_periods: u32,
    safe_force_n: f64,
    safe_ramp_n_per_s: f64,
    #[serde(default = "default_fault")]
    fault: String,
    #[serde(default)]
    fault_at_s: f64,
}

fn default_fault() -> String {
    "none".into()
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawScenario {
    duration_s: f64,
    preload_n: f64,
    harmonic_amplitude_n: f64,
    harmonic_frequency_hz: f64,
    #[serde(default)]
    train_speed_kmh: f64,
    #[serde(default)]
    train_first_axle_s: f64,
    #[serde(default)]
    step_n: f64,
    #[serde(default)]
    step_at_s: f64,
    #[serde(default)]
    load_csv: String,
}

/// Fixed-step loop settings shared by the rig and the emulator.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopConfig {
    pub rate_hz: f64,
    pub period_ns: u64,
    pub spin_ns: u64,
    pub emulator_phase_ns: u64,
    pub sample_wait_ns: u64,
    pub trip_after_stale_samples: u32,
    pub record_queue_capacity: usize,
    pub lock_memory: bool,
    /// `None` = normal scheduling.
    pub fifo_priority: Option<i32>,
    pub emulator_cpus: Vec<usize>,
    pub rig_cpus: Vec<usize>,
}

impl LoopConfig {
    /// The model step, s (one loop period; the same expression everywhere for replay).
    pub fn dt_s(&self) -> f64 {
        1.0 / self.rate_hz
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EmulatorConfig {
    pub displacement_min_m: f64,
    pub displacement_max_m: f64,
}

/// What the controller does when a setpoint exceeds the force or rate limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LimitAction {
    /// Clip to the limit and carry on.
    Saturate,
    /// Keep the last in-limit command while the setpoint is out of limits.
    Hold,
    /// Latch a fault and ramp the command to zero.
    RampToZero,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControllerConfig {
    pub compensation_order: u32,
    pub compensation_enabled: bool,
    pub compensation_delay_s: f64,
    pub force_min_n: f64,
    pub force_max_n: f64,
    pub force_rate_max_n_per_s: f64,
    pub limit_action: LimitAction,
    pub stale_setpoint_periods: u32,
    pub emulator_heartbeat_timeout_ns: u64,
    pub safe_force_n: f64,
    pub safe_ramp_n_per_s: f64,
}

/// Fault injected by the rig into its displacement samples (tests).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RigFault {
    None,
    /// A NaN sample.
    Nan,
    /// A sample far outside the emulator's displacement range.
    OutOfRange,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigConfig {
    pub specimen_mass_kg: f64,
    pub damping_ns_per_m: f64,
    pub actuator_lag_s: f64,
    pub actuator_delay_s: f64,
    pub actuator_force_max_n: f64,
    pub sensor_noise_m: f64,
    pub sensor_resolution_m: f64,
    pub seed: u64,
    pub internal_substeps: u32,
    pub command_stale_periods: u32,
    pub safe_force_n: f64,
    pub safe_ramp_n_per_s: f64,
    pub fault: RigFault,
    pub fault_at_s: f64,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ScenarioConfig {
    pub duration_s: f64,
    pub preload_n: f64,
    pub harmonic_amplitude_n: f64,
    pub harmonic_frequency_hz: f64,
    /// 0 = no train passage.
    pub train_speed_kmh: f64,
    pub train_first_axle_s: f64,
    pub step_n: f64,
    pub step_at_s: f64,
    /// Extra external load `t_s,force_n` added to the programme (uniform step, linear
    /// interpolation), loaded at validation.
    pub load_csv: Option<PathBuf>,
    pub load_csv_samples: Option<(f64, Vec<f64>)>,
}

/// A validated HIL configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct HilConfig {
    pub origin: String,
    pub loop_: LoopConfig,
    pub model: ModelSpec,
    /// The model with its `[[effect]]` tables validated: what the emulator steps.
    pub augmented: AugmentedModel,
    pub emulator: EmulatorConfig,
    pub controller: ControllerConfig,
    pub rig: RigConfig,
    pub scenario: ScenarioConfig,
}

/// Reads and validates a configuration file.
pub fn load_hil_config(path: &Path) -> Result<HilConfig, ConfigError> {
    let origin = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| ConfigError {
        origin: origin.clone(),
        key: String::new(),
        message: format!("cannot read config file: {e}"),
    })?;
    parse_hil_config(&text, &origin, path.parent())
}

/// The embedded default configuration.
pub fn default_hil_config() -> Result<HilConfig, ConfigError> {
    parse_hil_config(DEFAULT_CONFIG_TOML, DEFAULT_CONFIG_ORIGIN, None)
}

/// Validates configuration text; relative paths resolve against `base_dir`.
pub fn parse_hil_config(
    text: &str,
    origin: &str,
    base_dir: Option<&Path>,
) -> Result<HilConfig, ConfigError> {
    let err = |key: &str, message: String| ConfigError {
        origin: origin.to_string(),
        key: key.to_string(),
        message,
    };
    let raw: RawConfig = toml::from_str(text).map_err(|e| {
        let line = e
            .span()
            .map(|span| text[..span.start].matches('\n').count() + 1)
            .map_or(String::new(), |l| format!(" at line {l}"));
        err(
            "",
            format!("invalid config{line}: {}", e.message().replace('\n', " ")),
        )
    })?;
    let resolve = |p: &str| -> PathBuf {
        let p = PathBuf::from(p);
        match base_dir {
            Some(dir) if p.is_relative() => dir.join(p),
            _ => p,
        }
    };

    let positive = |key: &str, v: f64| -> Result<f64, ConfigError> {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(err(
                key,
                format!("{v} is not valid: expected a finite number > 0"),
            ))
        }
    };
    let non_negative = |key: &str, v: f64| -> Result<f64, ConfigError> {
        if v.is_finite() && v >= 0.0 {
            Ok(v)
        } else {
            Err(err(
                key,
                format!("{v} is not valid: expected a finite number >= 0"),
            ))
        }
    };
    let finite = |key: &str, v: f64| -> Result<f64, ConfigError> {
        if v.is_finite() {
            Ok(v)
        } else {
            Err(err(
                key,
                format!("{v} is not valid: expected a finite number"),
            ))
        }
    };

    // [loop]
    let l = &raw.loop_;
    let rate_hz = positive("loop.rate_hz", l.rate_hz)?;
    if !(100.0..=50_000.0).contains(&rate_hz) {
        return Err(err(
            "loop.rate_hz",
            format!("{rate_hz} is not valid: expected 100 to 50000 Hz"),
        ));
    }
    let period_ns = (1e9 / rate_hz).round() as u64;
    let spin_ns = (non_negative("loop.spin_us", l.spin_us)? * 1e3) as u64;
    let emulator_phase_ns =
        (non_negative("loop.emulator_phase_us", l.emulator_phase_us)? * 1e3) as u64;
    if emulator_phase_ns >= period_ns {
        return Err(err(
            "loop.emulator_phase_us",
            format!(
                "{} is not valid: expected less than one period ({} us)",
                l.emulator_phase_us,
                period_ns as f64 / 1e3
            ),
        ));
    }
    if l.trip_after_stale_samples == 0 {
        return Err(err(
            "loop.trip_after_stale_samples",
            "0 is not valid: expected >= 1".into(),
        ));
    }
    if l.record_queue_capacity < 16 {
        return Err(err(
            "loop.record_queue_capacity",
            format!("{} is not valid: expected >= 16", l.record_queue_capacity),
        ));
    }
    if !(0..=99).contains(&l.fifo_priority) {
        return Err(err(
            "loop.fifo_priority",
            format!("{} is not valid: expected 0 (off) or 1-99", l.fifo_priority),
        ));
    }
    let loop_ = LoopConfig {
        rate_hz,
        period_ns,
        spin_ns,
        emulator_phase_ns,
        sample_wait_ns: (non_negative("loop.sample_wait_us", l.sample_wait_us)? * 1e3) as u64,
        trip_after_stale_samples: l.trip_after_stale_samples,
        record_queue_capacity: l.record_queue_capacity,
        lock_memory: l.lock_memory,
        fifo_priority: (l.fifo_priority > 0).then_some(l.fifo_priority),
        emulator_cpus: l.emulator_cpus.clone(),
        rig_cpus: l.rig_cpus.clone(),
    };

    // [model]
    let model = match raw.model.get("path") {
        Some(toml::Value::String(p)) => {
            if raw.model.len() > 1 {
                return Err(err(
                    "model.path",
                    "expected either `path` alone or the model-file keys inline, not both".into(),
                ));
            }
            load_model_file(&resolve(p)).map_err(|e| err("model.path", e.to_string()))?
        }
        Some(other) => {
            return Err(err(
                "model.path",
                format!("{other} is not valid: expected a file path string"),
            ))
        }
        None => {
            let inline = toml::to_string(&raw.model).map_err(|e| err("model", e.to_string()))?;
            parse_model_toml(&inline, &format!("{origin} [model]"))
                .map_err(|e| err("model", e.to_string()))?
        }
    };

    let augmented = AugmentedModel::from_spec(&model, &format!("{origin} [model]"))
        .map_err(|e| err("model.effect", e.to_string()))?;

    // [emulator]
    let e = &raw.emulator;
    let displacement_min_m = finite("emulator.displacement_min_m", e.displacement_min_m)?;
    let displacement_max_m = finite("emulator.displacement_max_m", e.displacement_max_m)?;
    if displacement_min_m >= displacement_max_m {
        return Err(err("emulator.displacement_max_m", format!("{displacement_max_m} is not valid: expected > displacement_min_m ({displacement_min_m})")));
    }
    let emulator = EmulatorConfig {
        displacement_min_m,
        displacement_max_m,
    };

    // [controller]
    let c = &raw.controller;
    if c.compensation_order > 3 {
        return Err(err(
            "controller.compensation_order",
            format!(
                "{} is not valid: expected 0, 1, 2 or 3",
                c.compensation_order
            ),
        ));
    }
    let limit_action = match c.limit_action.as_str() {
        "saturate" => LimitAction::Saturate,
        "hold" => LimitAction::Hold,
        "ramp-to-zero" => LimitAction::RampToZero,
        other => {
            return Err(err(
                "controller.limit_action",
                format!(
                    "\"{other}\" is not valid: expected \"saturate\", \"hold\" or \"ramp-to-zero\""
                ),
            ))
        }
    };
    let force_min_n = finite("controller.force_min_n", c.force_min_n)?;
    let force_max_n = finite("controller.force_max_n", c.force_max_n)?;
    if force_min_n >= force_max_n {
        return Err(err(
            "controller.force_max_n",
            format!("{force_max_n} is not valid: expected > force_min_n ({force_min_n})"),
        ));
    }
    if c.stale_setpoint_periods == 0 {
        return Err(err(
            "controller.stale_setpoint_periods",
            "0 is not valid: expected >= 1".into(),
        ));
    }
    let controller = ControllerConfig {
        compensation_order: c.compensation_order,
        compensation_enabled: c.compensation_enabled,
        compensation_delay_s: non_negative(
            "controller.compensation_delay_us",
            c.compensation_delay_us,
        )? * 1e-6,
        force_min_n,
        force_max_n,
        force_rate_max_n_per_s: positive(
            "controller.force_rate_max_n_per_s",
            c.force_rate_max_n_per_s,
        )?,
        limit_action,
        stale_setpoint_periods: c.stale_setpoint_periods,
        emulator_heartbeat_timeout_ns: (positive(
            "controller.emulator_heartbeat_timeout_ms",
            c.emulator_heartbeat_timeout_ms,
        )? * 1e6) as u64,
        safe_force_n: finite("controller.safe_force_n", c.safe_force_n)?,
        safe_ramp_n_per_s: positive("controller.safe_ramp_n_per_s", c.safe_ramp_n_per_s)?,
    };

    // [rig]
    let r = &raw.rig;
    let fault = match r.fault.as_str() {
        "none" => RigFault::None,
        "nan" => RigFault::Nan,
        "out-of-range" => RigFault::OutOfRange,
        other => {
            return Err(err(
                "rig.fault",
                format!("\"{other}\" is not valid: expected \"none\", \"nan\" or \"out-of-range\""),
            ))
        }
    };
    if r.internal_substeps == 0 || r.internal_substeps > 1000 {
        return Err(err(
            "rig.internal_substeps",
            format!("{} is not valid: expected 1 to 1000", r.internal_substeps),
        ));
    }
    if r.command_stale_periods == 0 {
        return Err(err(
            "rig.command_stale_periods",
            "0 is not valid: expected >= 1".into(),
        ));
    }
    let rig = RigConfig {
        specimen_mass_kg: positive("rig.specimen_mass_kg", r.specimen_mass_kg)?,
        damping_ns_per_m: non_negative("rig.damping_ns_per_m", r.damping_ns_per_m)?,
        actuator_lag_s: non_negative("rig.actuator_lag_us", r.actuator_lag_us)? * 1e-6,
        actuator_delay_s: non_negative("rig.actuator_delay_us", r.actuator_delay_us)? * 1e-6,
        actuator_force_max_n: positive("rig.actuator_force_max_n", r.actuator_force_max_n)?,
        sensor_noise_m: non_negative("rig.sensor_noise_m", r.sensor_noise_m)?,
        sensor_resolution_m: non_negative("rig.sensor_resolution_m", r.sensor_resolution_m)?,
        seed: r.seed,
        internal_substeps: r.internal_substeps,
        command_stale_periods: r.command_stale_periods,
        safe_force_n: finite("rig.safe_force_n", r.safe_force_n)?,
        safe_ramp_n_per_s: positive("rig.safe_ramp_n_per_s", r.safe_ramp_n_per_s)?,
        fault,
        fault_at_s: non_negative("rig.fault_at_s", r.fault_at_s)?,
    };
    if rig.actuator_delay_s > 0.1 {
        return Err(err(
            "rig.actuator_delay_us",
            format!(
                "{} is not valid: expected <= 100000 us",
                r.actuator_delay_us
            ),
        ));
    }

    // [scenario]
    let s = &raw.scenario;
    let duration_s = positive("scenario.duration_s", s.duration_s)?;
    if duration_s > 3600.0 {
        return Err(err(
            "scenario.duration_s",
            format!("{duration_s} is not valid: expected <= 3600 s"),
        ));
    }
    let (load_csv, load_csv_samples) = if s.load_csv.is_empty() {
        (None, None)
    } else {
        let path = resolve(&s.load_csv);
        let cols = crate::csvio::read_columns(&path, &["t_s", "force_n"])
            .map_err(|e| err("scenario.load_csv", e.to_string()))?;
        let step = crate::csvio::uniform_step(
            &cols.data[0],
            &cols.lines,
            &path.display().to_string(),
            "t_s",
        )
        .map_err(|e| err("scenario.load_csv", e.to_string()))?;
        (Some(path), Some((step, cols.data[1].clone())))
    };
    let scenario = ScenarioConfig {
        duration_s,
        preload_n: finite("scenario.preload_n", s.preload_n)?,
        harmonic_amplitude_n: non_negative(
            "scenario.harmonic_amplitude_n",
            s.harmonic_amplitude_n,
        )?,
        harmonic_frequency_hz: non_negative(
            "scenario.harmonic_frequency_hz",
            s.harmonic_frequency_hz,
        )?,
        train_speed_kmh: non_negative("scenario.train_speed_kmh", s.train_speed_kmh)?,
        train_first_axle_s: finite("scenario.train_first_axle_s", s.train_first_axle_s)?,
        step_n: finite("scenario.step_n", s.step_n)?,
        step_at_s: non_negative("scenario.step_at_s", s.step_at_s)?,
        load_csv,
        load_csv_samples,
    };

    Ok(HilConfig {
        origin: origin.to_string(),
        loop_,
        model,
        augmented,
        emulator,
        controller,
        rig,
        scenario,
    })
}

/// Loads `path`, or the embedded default when `None`.
pub fn load_or_default(path: Option<&Path>) -> Result<HilConfig, ConfigError> {
    match path {
        Some(p) => load_hil_config(p),
        None => default_hil_config(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_default_validates() {
        let c = default_hil_config().unwrap();
        assert_eq!(c.loop_.rate_hz, 4096.0);
    }

    #[test]
    fn misspelt_key_names_the_key() {
        let text = DEFAULT_CONFIG_TOML.replace("spin_us", "spin_usec");
        let e = parse_hil_config(&text, "x.toml", None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("x.toml") && e.contains("spin_usec"), "{e}");
    }

    #[test]
    fn bad_value_names_key_value_and_valid_range() {
        let text = DEFAULT_CONFIG_TOML.replace("compensation_order = 3", "compensation_order = 7");
        let e = parse_hil_config(&text, "x.toml", None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("controller.compensation_order")
                && e.contains('7')
                && e.contains("0, 1, 2 or 3"),
            "{e}"
        );
    }
}
