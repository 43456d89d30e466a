//! The HIL run configuration (one TOML file: loop, model, emulator, controller, rig,
//! safety, scenario, fault injections): parsed raw with `deny_unknown_fields`, then
//! validated section by section into typed structs.
//!
//! Every error is one line naming the file, the key, the value and what would be valid.
//! Must not: fill in physical constants silently (every physical key is required).

use crate::hil::compensation::CompensationConfig;
use crate::hil::passivity::StabilityBounds;
use crate::ipc::messages::Compensation;
use std::fmt;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::fault::{FaultAction, FaultActions, FaultClass};
use crate::model::effects::AugmentedModel;
use crate::model::file::{load_model_file, parse_model_toml, ModelSpec};
use crate::rig::servo::ServoConfig;
use crate::tomlerr;

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
    compensation: RawCompensation,
    safety: RawSafety,
    scenario: RawScenario,
    #[serde(default)]
    programme: Option<RawProgramme>,
    #[serde(default)]
    inject: Vec<RawInjection>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawProgramme {
    /// Passes through the block sequence; 0 = until the run's end.
    #[serde(default)]
    repeat: u64,
    block: Vec<RawBlock>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBlock {
    #[serde(default)]
    name: String,
    duration_s: f64,
    #[serde(default = "one")]
    repeat: u64,
    #[serde(default)]
    harmonic_amplitude_n: f64,
    #[serde(default)]
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

fn one() -> u64 {
    1
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
    #[serde(default)]
    controller_cpus: Vec<usize>,
    #[serde(default)]
    emulator_standby_cpus: Vec<usize>,
    #[serde(default)]
    emulator_standby_after_us: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawEmulator {
    displacement_min_m: f64,
    displacement_max_m: f64,
    law_frequency_hz: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawController {
    command_mode: String,
    compensation_order: u32,
    compensation_enabled: bool,
    compensation_delay_us: f64,
    force_min_n: f64,
    force_max_n: f64,
    force_rate_max_n_per_s: f64,
    limit_action: String,
    emulator_heartbeat_timeout_ms: f64,
    keepalive_periods: u32,
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
    hold_bandwidth_hz: f64,
    hold_damping_ratio: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCompensation {
    initial_delay_us: f64,
    #[serde(default = "yes")]
    adapt: bool,
    #[serde(default = "yes")]
    passivity_guard: bool,
    #[serde(default)]
    lead_order: Option<u32>,
    #[serde(default)]
    max_delay_us: Option<f64>,
    #[serde(default)]
    estimator_band_hz: Option<f64>,
    #[serde(default)]
    estimator_memory_ms: Option<f64>,
    #[serde(default)]
    adapt_time_ms: Option<f64>,
    #[serde(default)]
    guard_band_hz: Option<f64>,
    #[serde(default)]
    guard_onset_energy_j: Option<f64>,
    #[serde(default)]
    guard_full_energy_j: Option<f64>,
    #[serde(default)]
    guard_max_damping_ns_per_m: Option<f64>,
    #[serde(default)]
    guard_release_ms: Option<f64>,
}

fn yes() -> bool {
    true
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSafety {
    stall_limit_ms: f64,
    emulator_fault_action: String,
    controller_fault_action: String,
    limit_fault_action: String,
    orchestrator_lost_action: String,
    hold_min_s: f64,
    hold_max_s: f64,
    rest_band_m: f64,
    rest_window_ms: f64,
    unload_rate_n_per_s: f64,
    resume_blend_ms: f64,
    max_transient_m: f64,
    #[serde(default)]
    max_displacement_error: Option<f64>,
    #[serde(default)]
    stability_band_low_hz: Option<f64>,
    #[serde(default)]
    stability_band_high_hz: Option<f64>,
    #[serde(default)]
    stability_memory_ms: Option<f64>,
    #[serde(default)]
    max_generated_energy_j: Option<f64>,
    #[serde(default)]
    max_oscillation_m: Option<f64>,
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

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawInjection {
    process: String,
    kind: String,
    at_s: f64,
    #[serde(default)]
    duration_ms: Option<f64>,
    #[serde(default)]
    count: Option<u64>,
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
    /// The controller's thread (empty: any CPU the kernel picks).
    pub controller_cpus: Vec<usize>,
    /// The emulator's standby loop thread: `None` = no standby.
    pub emulator_standby: Option<Standby>,
}

/// A second loop thread of the emulator on other CPUs: it claims a cycle that the primary
/// has not begun `after_ns` past its deadline (`rt::CycleTurn`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Standby {
    pub cpus: Vec<usize>,
    pub after_ns: u64,
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
    /// Frequency at which the local law's stiffness and damping equal the element's
    /// small-signal modulus (the specimen's resonance on the element), Hz.
    pub law_frequency_hz: f64,
}

/// What the controller sends the actuator side.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CommandMode {
    /// The element's local linear law (evaluated by the actuator side every period).
    Law,
    /// Plain force commands, extrapolated over the loop delay.
    Force,
}

/// What the controller does when a setpoint exceeds the force or rate limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LimitAction {
    /// Clip to the limit and carry on.
    Saturate,
    /// Keep the last in-limit command while the setpoint is out of limits.
    Hold,
    /// Latch `force-limit-exceeded`; `[safety] limit_fault_action` applies.
    Fault,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControllerConfig {
    pub command_mode: CommandMode,
    pub compensation_order: u32,
    pub compensation_enabled: bool,
    pub compensation_delay_s: f64,
    pub force_min_n: f64,
    pub force_max_n: f64,
    pub force_rate_max_n_per_s: f64,
    pub limit_action: LimitAction,
    pub emulator_heartbeat_timeout_ns: u64,
    /// A command is repeated when none was sent for this long, ns.
    pub keepalive_ns: u64,
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
    pub hold_bandwidth_hz: f64,
    pub hold_damping_ratio: f64,
}

/// Fault actions, the hold and its end, and the report's transient bound.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SafetyConfig {
    /// Ride-through limit: a stall of the emulator or controller shorter than this is
    /// ridden through on the last local law; a longer one is a fault, s.
    pub stall_limit_s: f64,
    pub actions: FaultActions,
    pub hold_min_s: f64,
    pub hold_max_s: f64,
    pub rest_band_m: f64,
    pub rest_window_s: f64,
    pub unload_rate_n_per_s: f64,
    pub resume_blend_s: f64,
    /// A run whose largest resonant transient (HIL minus reference) exceeds this is not
    /// reported as clean, m.
    pub max_transient_m: f64,
    /// A run whose displacement error (relative RMS against the offline reference) exceeds
    /// this is not clean (default 0.01).
    pub max_displacement_error: f64,
    /// The online stability monitor's bounds (`loop-unstable`).
    pub stability: StabilityBounds,
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

/// One block of the load programme: load components in block-local time.
#[derive(Debug, Clone, PartialEq)]
pub struct BlockConfig {
    pub name: String,
    pub duration_s: f64,
    /// Times the block runs in a row.
    pub repeat: u64,
    pub harmonic_amplitude_n: f64,
    pub harmonic_frequency_hz: f64,
    /// 0 = no train passage.
    pub train_speed_kmh: f64,
    pub train_first_axle_s: f64,
    pub step_n: f64,
    pub step_at_s: f64,
    pub load_csv: Option<PathBuf>,
    pub load_csv_samples: Option<(f64, Vec<f64>)>,
}

/// The load programme: a preload and a block sequence, repeated.
#[derive(Debug, Clone, PartialEq)]
pub struct ProgrammeConfig {
    pub preload_n: f64,
    pub blocks: Vec<BlockConfig>,
    /// Passes through the block sequence (0: until `end_s`).
    pub repeat: u64,
    /// Programme time at which the programme ends, s.
    pub end_s: f64,
}

impl ProgrammeConfig {
    /// Length of one pass through the block sequence, s.
    pub fn sequence_s(&self) -> f64 {
        self.blocks
            .iter()
            .map(|b| b.duration_s * b.repeat as f64)
            .sum()
    }
}

/// A loop process, as named in `[[inject]] process`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoopProcess {
    Rig,
    Emulator,
    Controller,
}

impl LoopProcess {
    pub fn name(self) -> &'static str {
        match self {
            LoopProcess::Rig => "rig",
            LoopProcess::Emulator => "emulator",
            LoopProcess::Controller => "controller",
        }
    }
}

/// An injected fault (`[[inject]]`): deterministic, on the loop's own time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum InjectKind {
    /// The process's loop thread stops for this long, s.
    Stall { duration_s: f64 },
    /// The thread that runs the emulator's cycle is kept off its CPU for this long, s, as
    /// a hypervisor or an interrupt storm does to one CPU: the loop itself is not held,
    /// so a standby thread on another CPU goes on with it.
    CpuStall { duration_s: f64 },
    /// The process kills itself with SIGKILL.
    Kill,
    /// The rig publishes no sample for this many periods.
    DropSamples { count: u64 },
    /// The rig publishes one NaN sample.
    Nan,
    /// The rig publishes one sample far outside the emulator's range.
    OutOfRange,
}

impl InjectKind {
    pub fn name(self) -> &'static str {
        match self {
            InjectKind::Stall { .. } => "stall",
            InjectKind::CpuStall { .. } => "cpu-stall",
            InjectKind::Kill => "kill",
            InjectKind::DropSamples { .. } => "drop-samples",
            InjectKind::Nan => "nan",
            InjectKind::OutOfRange => "out-of-range",
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Injection {
    pub process: LoopProcess,
    pub kind: InjectKind,
    /// Loop time of the injection, s.
    pub at_s: f64,
}

impl Injection {
    /// "emulator stall 5 ms at 2.000 s" and the like.
    pub fn describe(&self) -> String {
        let what = match self.kind {
            InjectKind::Stall { duration_s } => format!("stall {} ms", duration_s * 1e3),
            InjectKind::CpuStall { duration_s } => format!("cpu-stall {} ms", duration_s * 1e3),
            InjectKind::DropSamples { count } => format!("drop-samples {count}"),
            k => k.name().to_string(),
        };
        format!("{} {what} at {:.3} s", self.process.name(), self.at_s)
    }
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
    /// `[compensation]`: what the controller sends the rig to compensate its actuator.
    pub compensation: CompensationConfig,
    pub safety: SafetyConfig,
    pub scenario: ScenarioConfig,
    /// The load programme (from `[programme]`, or the scenario's load keys as one block).
    pub programme: ProgrammeConfig,
    pub injections: Vec<Injection>,
}

impl HilConfig {
    /// The rig servo's settings.
    pub fn servo_config(&self) -> ServoConfig {
        let (hold_kp, hold_ki, hold_kd) = ServoConfig::hold_gains(
            self.rig.specimen_mass_kg,
            self.rig.hold_bandwidth_hz,
            self.rig.hold_damping_ratio,
        );
        ServoConfig {
            period_s: self.loop_.dt_s(),
            command_stale_periods: u64::from(self.rig.command_stale_periods),
            hold_kp,
            hold_ki,
            hold_kd,
            commands_stale_action: self.safety.actions.controller,
            orchestrator_lost_action: self.safety.actions.orchestrator,
            rest_band_m: self.safety.rest_band_m,
            rest_window_s: self.safety.rest_window_s,
            hold_min_s: self.safety.hold_min_s,
            hold_max_s: self.safety.hold_max_s,
            unload_rate_n_per_s: self.safety.unload_rate_n_per_s,
            resume_blend_s: self.safety.resume_blend_s,
        }
    }

    /// The ride-through limit in loop periods.
    pub fn stall_limit_periods(&self) -> u64 {
        (self.safety.stall_limit_s * self.loop_.rate_hz).round() as u64
    }

    /// Injections for one process, in time order.
    pub fn injections_for(&self, process: LoopProcess) -> Vec<Injection> {
        let mut v: Vec<Injection> = self
            .injections
            .iter()
            .filter(|i| i.process == process)
            .copied()
            .collect();
        v.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
        v
    }
}

/// Keys of earlier versions and what replaced them (a clearer error than "unknown key").
const REMOVED_KEYS: [(&str, &str); 8] = [
    (
        "law_lead_us",
        "moved: the controller owns the lead now, [compensation] initial_delay_us (a starting guess it refines during the run)",
    ),
    (
        "law_lead_order",
        "moved to [compensation] lead_order",
    ),
    (
        "safe_force_n",
        "removed: a constant force on a free mass is not a safe state; faults now hold the specimen's position (see [safety])",
    ),
    (
        "safe_ramp_n_per_s",
        "removed: faults now hold the specimen's position (see [safety])",
    ),
    (
        "stale_setpoint_periods",
        "removed: the ride-through limit is [safety] stall_limit_ms",
    ),
    (
        "fault",
        "removed from [rig]: inject faults with [[inject]] tables (process, kind, at_s)",
    ),
    (
        "fault_at_s",
        "removed from [rig]: inject faults with [[inject]] tables (process, kind, at_s)",
    ),
    (
        "ramp-to-zero",
        "removed as a limit_action: use \"fault\" (the [safety] limit_fault_action applies)",
    ),
];

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

/// Validation helpers bound to one file.
struct Check<'a> {
    origin: &'a str,
}

impl Check<'_> {
    fn err(&self, key: &str, message: String) -> ConfigError {
        ConfigError {
            origin: self.origin.to_string(),
            key: key.to_string(),
            message,
        }
    }
    fn positive(&self, key: &str, v: f64) -> Result<f64, ConfigError> {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(self.err(
                key,
                format!("{v} is not valid: expected a finite number > 0"),
            ))
        }
    }
    fn non_negative(&self, key: &str, v: f64) -> Result<f64, ConfigError> {
        if v.is_finite() && v >= 0.0 {
            Ok(v)
        } else {
            Err(self.err(
                key,
                format!("{v} is not valid: expected a finite number >= 0"),
            ))
        }
    }
    fn finite(&self, key: &str, v: f64) -> Result<f64, ConfigError> {
        if v.is_finite() {
            Ok(v)
        } else {
            Err(self.err(key, format!("{v} is not valid: expected a finite number")))
        }
    }
    fn at_least(&self, key: &str, v: u64, min: u64) -> Result<u64, ConfigError> {
        if v >= min {
            Ok(v)
        } else {
            Err(self.err(key, format!("{v} is not valid: expected >= {min}")))
        }
    }
    fn choice<T: Copy>(
        &self,
        key: &str,
        value: &str,
        options: &[(&str, T)],
    ) -> Result<T, ConfigError> {
        options
            .iter()
            .find(|(name, _)| *name == value)
            .map(|(_, v)| *v)
            .ok_or_else(|| {
                let names: Vec<String> = options.iter().map(|(n, _)| format!("\"{n}\"")).collect();
                let hint = REMOVED_KEYS
                    .iter()
                    .find(|(k, _)| *k == value)
                    .map_or(String::new(), |(_, h)| format!(" ({h})"));
                self.err(
                    key,
                    format!(
                        "\"{value}\" is not valid: expected {}{hint}",
                        names.join(", ")
                    ),
                )
            })
    }
}

/// Validates configuration text; relative paths resolve against `base_dir`.
pub fn parse_hil_config(
    text: &str,
    origin: &str,
    base_dir: Option<&Path>,
) -> Result<HilConfig, ConfigError> {
    let check = Check { origin };
    let raw: RawConfig = toml::from_str(text).map_err(|e| {
        let hint = REMOVED_KEYS
            .iter()
            .find(|(k, _)| e.message().contains(&format!("unknown field `{k}`")))
            .map_or(String::new(), |(k, h)| format!(" (`{k}` was {h})"));
        check.err(
            "",
            format!("invalid config {}{hint}", tomlerr::describe(text, &e)),
        )
    })?;
    let resolve = |p: &str| -> PathBuf {
        let p = PathBuf::from(p);
        match base_dir {
            Some(dir) if p.is_relative() => dir.join(p),
            _ => p,
        }
    };
    let loop_ = parse_loop(&check, &raw.loop_)?;
    let model = parse_model(&check, &raw.model, &resolve)?;
    let augmented = AugmentedModel::from_spec(&model, &format!("{origin} [model]"))
        .map_err(|e| check.err("model.effect", e.to_string()))?;
    let emulator = parse_emulator(&check, &raw.emulator)?;
    let controller = parse_controller(&check, &raw.controller, loop_.period_ns)?;
    let rig = parse_rig(&check, &raw.rig)?;
    let compensation = parse_compensation(&check, &raw.compensation)?;
    let safety = parse_safety(&check, &raw.safety)?;
    let scenario = parse_scenario(&check, &raw.scenario, &resolve)?;
    let programme = parse_programme(&check, raw.programme.as_ref(), &scenario, &resolve)?;
    let injections = raw
        .inject
        .iter()
        .enumerate()
        .map(|(i, r)| parse_injection(&check, i, r))
        .collect::<Result<Vec<_>, _>>()?;
    let stall_periods = (safety.stall_limit_s * loop_.rate_hz).round() as u64;
    if u64::from(loop_.trip_after_stale_samples) < stall_periods {
        return Err(check.err(
            "loop.trip_after_stale_samples",
            format!(
                "{} is not valid: expected at least the ride-through limit ([safety] stall_limit_ms = {} ms = {stall_periods} periods), or a short stall of the rig would trip the emulator",
                loop_.trip_after_stale_samples,
                safety.stall_limit_s * 1e3
            ),
        ));
    }
    if (controller.emulator_heartbeat_timeout_ns as f64) < safety.stall_limit_s * 1e9 {
        return Err(check.err(
            "controller.emulator_heartbeat_timeout_ms",
            format!(
                "{} is not valid: expected at least the ride-through limit ([safety] stall_limit_ms = {} ms), or a stall the loop rides through would trip it",
                controller.emulator_heartbeat_timeout_ns as f64 * 1e-6,
                safety.stall_limit_s * 1e3
            ),
        ));
    }
    Ok(HilConfig {
        origin: origin.to_string(),
        loop_,
        model,
        augmented,
        emulator,
        controller,
        rig,
        compensation,
        safety,
        scenario,
        programme,
        injections,
    })
}

fn parse_compensation(
    check: &Check,
    c: &RawCompensation,
) -> Result<CompensationConfig, ConfigError> {
    let mut out = CompensationConfig::with_initial_delay(0.0);
    let max_delay_s = match c.max_delay_us {
        Some(v) => check.positive("compensation.max_delay_us", v)? * 1e-6,
        None => out.max_delay_s,
    };
    if max_delay_s > Compensation::MAX_LEAD_S {
        return Err(check.err(
            "compensation.max_delay_us",
            format!(
                "{} is not valid: expected at most {} us (the longest lead a rig accepts)",
                max_delay_s * 1e6,
                Compensation::MAX_LEAD_S * 1e6
            ),
        ));
    }
    out.max_delay_s = max_delay_s;
    out.initial_delay_s =
        check.non_negative("compensation.initial_delay_us", c.initial_delay_us)? * 1e-6;
    if out.initial_delay_s > max_delay_s {
        return Err(check.err(
            "compensation.initial_delay_us",
            format!(
                "{} is not valid: expected at most max_delay_us = {} us",
                c.initial_delay_us,
                max_delay_s * 1e6
            ),
        ));
    }
    out.adapt = c.adapt;
    out.passivity_guard = c.passivity_guard;
    if let Some(order) = c.lead_order {
        if order > 3 {
            return Err(check.err(
                "compensation.lead_order",
                format!("{order} is not valid: expected 0, 1, 2 or 3"),
            ));
        }
        out.lead_order = order;
    }
    let pos = |key: &str, v: Option<f64>, scale: f64, default: f64| -> Result<f64, ConfigError> {
        match v {
            Some(v) => Ok(check.positive(&format!("compensation.{key}"), v)? * scale),
            None => Ok(default),
        }
    };
    out.estimator_band_hz = pos(
        "estimator_band_hz",
        c.estimator_band_hz,
        1.0,
        out.estimator_band_hz,
    )?;
    out.estimator_memory_s = pos(
        "estimator_memory_ms",
        c.estimator_memory_ms,
        1e-3,
        out.estimator_memory_s,
    )?;
    out.adapt_time_s = pos("adapt_time_ms", c.adapt_time_ms, 1e-3, out.adapt_time_s)?;
    out.guard_band_hz = pos("guard_band_hz", c.guard_band_hz, 1.0, out.guard_band_hz)?;
    out.guard_onset_energy_j = pos(
        "guard_onset_energy_j",
        c.guard_onset_energy_j,
        1.0,
        out.guard_onset_energy_j,
    )?;
    out.guard_full_energy_j = pos(
        "guard_full_energy_j",
        c.guard_full_energy_j,
        1.0,
        out.guard_full_energy_j,
    )?;
    if out.guard_full_energy_j <= out.guard_onset_energy_j {
        return Err(check.err(
            "compensation.guard_full_energy_j",
            format!(
                "{} is not valid: expected more than guard_onset_energy_j = {}",
                out.guard_full_energy_j, out.guard_onset_energy_j
            ),
        ));
    }
    out.guard_max_damping_ns_per_m = pos(
        "guard_max_damping_ns_per_m",
        c.guard_max_damping_ns_per_m,
        1.0,
        out.guard_max_damping_ns_per_m,
    )?;
    out.guard_release_s = pos(
        "guard_release_ms",
        c.guard_release_ms,
        1e-3,
        out.guard_release_s,
    )?;
    Ok(out)
}

impl HilConfig {
    /// Sets the run's length (`--duration-s`): the scenario's and the programme's end.
    pub fn set_duration_s(&mut self, duration_s: f64) {
        self.scenario.duration_s = duration_s;
        // The scenario's own load, as a single block, lasts the run.
        if self.programme.blocks.len() == 1 && self.programme.blocks[0].name == SCENARIO_BLOCK {
            self.programme.blocks[0].duration_s = duration_s;
        }
        let sequence = self.programme.sequence_s();
        self.programme.end_s = if self.programme.repeat > 0 {
            duration_s.min(sequence * self.programme.repeat as f64)
        } else {
            duration_s
        };
    }
}

/// Name of the block made from `[scenario]`'s load keys when there is no `[programme]`.
pub const SCENARIO_BLOCK: &str = "scenario";

/// A load CSV: its path and (time step, forces).
type LoadCsv = (Option<PathBuf>, Option<(f64, Vec<f64>)>);

fn load_csv(
    check: &Check,
    key: &str,
    file: &str,
    resolve: &dyn Fn(&str) -> PathBuf,
) -> Result<LoadCsv, ConfigError> {
    if file.is_empty() {
        return Ok((None, None));
    }
    let path = resolve(file);
    let cols = crate::csvio::read_columns(&path, &["t_s", "force_n"])
        .map_err(|e| check.err(key, e.to_string()))?;
    let step = crate::csvio::uniform_step(
        &cols.data[0],
        &cols.lines,
        &path.display().to_string(),
        "t_s",
    )
    .map_err(|e| check.err(key, e.to_string()))?;
    Ok((Some(path), Some((step, cols.data[1].clone()))))
}

fn parse_programme(
    check: &Check,
    raw: Option<&RawProgramme>,
    scenario: &ScenarioConfig,
    resolve: &dyn Fn(&str) -> PathBuf,
) -> Result<ProgrammeConfig, ConfigError> {
    let Some(raw) = raw else {
        let block = BlockConfig {
            name: SCENARIO_BLOCK.to_string(),
            duration_s: scenario.duration_s,
            repeat: 1,
            harmonic_amplitude_n: scenario.harmonic_amplitude_n,
            harmonic_frequency_hz: scenario.harmonic_frequency_hz,
            train_speed_kmh: scenario.train_speed_kmh,
            train_first_axle_s: scenario.train_first_axle_s,
            step_n: scenario.step_n,
            step_at_s: scenario.step_at_s,
            load_csv: scenario.load_csv.clone(),
            load_csv_samples: scenario.load_csv_samples.clone(),
        };
        return Ok(ProgrammeConfig {
            preload_n: scenario.preload_n,
            blocks: vec![block],
            repeat: 1,
            end_s: scenario.duration_s,
        });
    };
    let scenario_loads = scenario.harmonic_amplitude_n != 0.0
        || scenario.train_speed_kmh != 0.0
        || scenario.step_n != 0.0
        || scenario.load_csv.is_some();
    if scenario_loads {
        return Err(check.err(
            "programme",
            "[programme] blocks replace the load keys of [scenario] (harmonic_amplitude_n, train_speed_kmh, step_n, load_csv): set those to 0 or \"\", or drop [programme]".into(),
        ));
    }
    if raw.block.is_empty() {
        return Err(check.err(
            "programme.block",
            "missing: a [programme] needs at least one [[programme.block]]".into(),
        ));
    }
    let mut blocks = Vec::new();
    for (i, b) in raw.block.iter().enumerate() {
        let key = |k: &str| format!("programme.block[{i}].{k}");
        let (csv, samples) = load_csv(check, &key("load_csv"), &b.load_csv, resolve)?;
        blocks.push(BlockConfig {
            name: if b.name.is_empty() {
                format!("block {i}")
            } else {
                b.name.clone()
            },
            duration_s: check.positive(&key("duration_s"), b.duration_s)?,
            repeat: check.at_least(&key("repeat"), b.repeat, 1)?,
            harmonic_amplitude_n: check
                .non_negative(&key("harmonic_amplitude_n"), b.harmonic_amplitude_n)?,
            harmonic_frequency_hz: check
                .non_negative(&key("harmonic_frequency_hz"), b.harmonic_frequency_hz)?,
            train_speed_kmh: check.non_negative(&key("train_speed_kmh"), b.train_speed_kmh)?,
            train_first_axle_s: check.finite(&key("train_first_axle_s"), b.train_first_axle_s)?,
            step_n: check.finite(&key("step_n"), b.step_n)?,
            step_at_s: check.non_negative(&key("step_at_s"), b.step_at_s)?,
            load_csv: csv,
            load_csv_samples: samples,
        });
    }
    let mut programme = ProgrammeConfig {
        preload_n: scenario.preload_n,
        blocks,
        repeat: raw.repeat,
        end_s: scenario.duration_s,
    };
    let sequence = programme.sequence_s();
    if programme.repeat > 0 {
        programme.end_s = scenario.duration_s.min(sequence * programme.repeat as f64);
    }
    Ok(programme)
}

fn parse_loop(check: &Check, l: &RawLoop) -> Result<LoopConfig, ConfigError> {
    let rate_hz = check.positive("loop.rate_hz", l.rate_hz)?;
    if !(100.0..=50_000.0).contains(&rate_hz) {
        return Err(check.err(
            "loop.rate_hz",
            format!("{rate_hz} is not valid: expected 100 to 50000 Hz"),
        ));
    }
    let period_ns = (1e9 / rate_hz).round() as u64;
    let spin_ns = (check.non_negative("loop.spin_us", l.spin_us)? * 1e3) as u64;
    let emulator_phase_ns =
        (check.non_negative("loop.emulator_phase_us", l.emulator_phase_us)? * 1e3) as u64;
    if emulator_phase_ns >= period_ns {
        return Err(check.err(
            "loop.emulator_phase_us",
            format!(
                "{} is not valid: expected less than one period ({} us)",
                l.emulator_phase_us,
                period_ns as f64 / 1e3
            ),
        ));
    }
    check.at_least(
        "loop.trip_after_stale_samples",
        u64::from(l.trip_after_stale_samples),
        1,
    )?;
    check.at_least(
        "loop.record_queue_capacity",
        l.record_queue_capacity as u64,
        16,
    )?;
    if !(0..=99).contains(&l.fifo_priority) {
        return Err(check.err(
            "loop.fifo_priority",
            format!("{} is not valid: expected 0 (off) or 1-99", l.fifo_priority),
        ));
    }
    let emulator_standby = parse_standby(check, l, period_ns)?;
    Ok(LoopConfig {
        rate_hz,
        period_ns,
        spin_ns,
        emulator_phase_ns,
        sample_wait_ns: (check.non_negative("loop.sample_wait_us", l.sample_wait_us)? * 1e3) as u64,
        trip_after_stale_samples: l.trip_after_stale_samples,
        record_queue_capacity: l.record_queue_capacity,
        lock_memory: l.lock_memory,
        fifo_priority: (l.fifo_priority > 0).then_some(l.fifo_priority),
        emulator_cpus: l.emulator_cpus.clone(),
        rig_cpus: l.rig_cpus.clone(),
        controller_cpus: l.controller_cpus.clone(),
        emulator_standby,
    })
}

/// `[loop] emulator_standby_cpus` and `emulator_standby_after_us`: the standby must sit on
/// CPUs the primary does not use, and claim a cycle within its period.
fn parse_standby(
    check: &Check,
    l: &RawLoop,
    period_ns: u64,
) -> Result<Option<Standby>, ConfigError> {
    if l.emulator_standby_cpus.is_empty() {
        return Ok(None);
    }
    if let Some(cpu) = l
        .emulator_standby_cpus
        .iter()
        .find(|c| l.emulator_cpus.contains(c))
    {
        return Err(check.err(
            "loop.emulator_standby_cpus",
            format!(
                "{:?} is not valid: CPU {cpu} is also in emulator_cpus {:?}; the standby covers \
                 for the primary's CPU only from another one",
                l.emulator_standby_cpus, l.emulator_cpus
            ),
        ));
    }
    let after_us = l.emulator_standby_after_us.ok_or_else(|| {
        check.err(
            "loop.emulator_standby_after_us",
            "missing: with emulator_standby_cpus, how long after a deadline the standby \
             takes a cycle the primary has not begun, us"
                .into(),
        )
    })?;
    let after_ns = (check.positive("loop.emulator_standby_after_us", after_us)? * 1e3) as u64;
    if after_ns >= period_ns {
        return Err(check.err(
            "loop.emulator_standby_after_us",
            format!(
                "{after_us} is not valid: expected less than one period ({} us)",
                period_ns as f64 / 1e3
            ),
        ));
    }
    Ok(Some(Standby {
        cpus: l.emulator_standby_cpus.clone(),
        after_ns,
    }))
}

fn parse_model(
    check: &Check,
    model: &toml::Table,
    resolve: &dyn Fn(&str) -> PathBuf,
) -> Result<ModelSpec, ConfigError> {
    match model.get("path") {
        Some(toml::Value::String(p)) => {
            if model.len() > 1 {
                return Err(check.err(
                    "model.path",
                    "expected either `path` alone or the model-file keys inline, not both".into(),
                ));
            }
            load_model_file(&resolve(p)).map_err(|e| check.err("model.path", e.to_string()))
        }
        Some(other) => Err(check.err(
            "model.path",
            format!("{other} is not valid: expected a file path string"),
        )),
        None => {
            let inline = toml::to_string(model).map_err(|e| check.err("model", e.to_string()))?;
            parse_model_toml(&inline, &format!("{} [model]", check.origin))
                .map_err(|e| check.err("model", e.to_string()))
        }
    }
}

fn parse_emulator(check: &Check, e: &RawEmulator) -> Result<EmulatorConfig, ConfigError> {
    let displacement_min_m = check.finite("emulator.displacement_min_m", e.displacement_min_m)?;
    let displacement_max_m = check.finite("emulator.displacement_max_m", e.displacement_max_m)?;
    if displacement_min_m >= displacement_max_m {
        return Err(check.err(
            "emulator.displacement_max_m",
            format!("{displacement_max_m} is not valid: expected > displacement_min_m ({displacement_min_m})"),
        ));
    }
    Ok(EmulatorConfig {
        displacement_min_m,
        displacement_max_m,
        law_frequency_hz: check.positive("emulator.law_frequency_hz", e.law_frequency_hz)?,
    })
}

fn parse_controller(
    check: &Check,
    c: &RawController,
    period_ns: u64,
) -> Result<ControllerConfig, ConfigError> {
    if c.compensation_order > 3 {
        return Err(check.err(
            "controller.compensation_order",
            format!(
                "{} is not valid: expected 0, 1, 2 or 3",
                c.compensation_order
            ),
        ));
    }
    let command_mode = check.choice(
        "controller.command_mode",
        &c.command_mode,
        &[("law", CommandMode::Law), ("force", CommandMode::Force)],
    )?;
    let limit_action = check.choice(
        "controller.limit_action",
        &c.limit_action,
        &[
            ("saturate", LimitAction::Saturate),
            ("hold", LimitAction::Hold),
            ("fault", LimitAction::Fault),
        ],
    )?;
    let force_min_n = check.finite("controller.force_min_n", c.force_min_n)?;
    let force_max_n = check.finite("controller.force_max_n", c.force_max_n)?;
    if force_min_n >= force_max_n {
        return Err(check.err(
            "controller.force_max_n",
            format!("{force_max_n} is not valid: expected > force_min_n ({force_min_n})"),
        ));
    }
    let keepalive = check.at_least(
        "controller.keepalive_periods",
        u64::from(c.keepalive_periods),
        1,
    )?;
    Ok(ControllerConfig {
        command_mode,
        compensation_order: c.compensation_order,
        compensation_enabled: c.compensation_enabled,
        compensation_delay_s: check
            .non_negative("controller.compensation_delay_us", c.compensation_delay_us)?
            * 1e-6,
        force_min_n,
        force_max_n,
        force_rate_max_n_per_s: check.positive(
            "controller.force_rate_max_n_per_s",
            c.force_rate_max_n_per_s,
        )?,
        limit_action,
        emulator_heartbeat_timeout_ns: (check.positive(
            "controller.emulator_heartbeat_timeout_ms",
            c.emulator_heartbeat_timeout_ms,
        )? * 1e6) as u64,
        keepalive_ns: keepalive * period_ns,
    })
}

fn parse_rig(check: &Check, r: &RawRig) -> Result<RigConfig, ConfigError> {
    if r.internal_substeps == 0 || r.internal_substeps > 1000 {
        return Err(check.err(
            "rig.internal_substeps",
            format!("{} is not valid: expected 1 to 1000", r.internal_substeps),
        ));
    }
    check.at_least(
        "rig.command_stale_periods",
        u64::from(r.command_stale_periods),
        1,
    )?;
    let actuator_delay_s = check.non_negative("rig.actuator_delay_us", r.actuator_delay_us)? * 1e-6;
    if actuator_delay_s > 0.1 {
        return Err(check.err(
            "rig.actuator_delay_us",
            format!(
                "{} is not valid: expected <= 100000 us",
                r.actuator_delay_us
            ),
        ));
    }
    let hold_damping_ratio = check.positive("rig.hold_damping_ratio", r.hold_damping_ratio)?;
    Ok(RigConfig {
        specimen_mass_kg: check.positive("rig.specimen_mass_kg", r.specimen_mass_kg)?,
        damping_ns_per_m: check.non_negative("rig.damping_ns_per_m", r.damping_ns_per_m)?,
        actuator_lag_s: check.non_negative("rig.actuator_lag_us", r.actuator_lag_us)? * 1e-6,
        actuator_delay_s,
        actuator_force_max_n: check.positive("rig.actuator_force_max_n", r.actuator_force_max_n)?,
        sensor_noise_m: check.non_negative("rig.sensor_noise_m", r.sensor_noise_m)?,
        sensor_resolution_m: check
            .non_negative("rig.sensor_resolution_m", r.sensor_resolution_m)?,
        seed: r.seed,
        internal_substeps: r.internal_substeps,
        command_stale_periods: r.command_stale_periods,
        hold_bandwidth_hz: check.positive("rig.hold_bandwidth_hz", r.hold_bandwidth_hz)?,
        hold_damping_ratio,
    })
}

fn parse_action(check: &Check, class: FaultClass, value: &str) -> Result<FaultAction, ConfigError> {
    check.choice(
        &format!("safety.{}", class.config_key()),
        value,
        &[
            ("indicate", FaultAction::Indicate),
            ("hold", FaultAction::Hold),
            ("hold-unload", FaultAction::HoldUnload),
        ],
    )
}

fn parse_safety(check: &Check, s: &RawSafety) -> Result<SafetyConfig, ConfigError> {
    let actions = FaultActions {
        emulator: parse_action(check, FaultClass::Emulator, &s.emulator_fault_action)?,
        controller: parse_action(check, FaultClass::Controller, &s.controller_fault_action)?,
        limits: parse_action(check, FaultClass::Limits, &s.limit_fault_action)?,
        orchestrator: parse_action(check, FaultClass::Orchestrator, &s.orchestrator_lost_action)?,
    };
    let hold_min_s = check.non_negative("safety.hold_min_s", s.hold_min_s)?;
    let hold_max_s = check.positive("safety.hold_max_s", s.hold_max_s)?;
    if hold_max_s < hold_min_s {
        return Err(check.err(
            "safety.hold_max_s",
            format!("{hold_max_s} is not valid: expected >= hold_min_s ({hold_min_s})"),
        ));
    }
    let rest_window_ms = check.positive("safety.rest_window_ms", s.rest_window_ms)?;
    if rest_window_ms > 50.0 {
        return Err(check.err(
            "safety.rest_window_ms",
            format!("{rest_window_ms} is not valid: expected <= 50 ms"),
        ));
    }
    Ok(SafetyConfig {
        stall_limit_s: check.positive("safety.stall_limit_ms", s.stall_limit_ms)? * 1e-3,
        actions,
        hold_min_s,
        hold_max_s,
        rest_band_m: check.positive("safety.rest_band_m", s.rest_band_m)?,
        rest_window_s: rest_window_ms * 1e-3,
        unload_rate_n_per_s: check.positive("safety.unload_rate_n_per_s", s.unload_rate_n_per_s)?,
        resume_blend_s: check.non_negative("safety.resume_blend_ms", s.resume_blend_ms)? * 1e-3,
        max_transient_m: check.positive("safety.max_transient_m", s.max_transient_m)?,
        max_displacement_error: match s.max_displacement_error {
            Some(v) => check.positive("safety.max_displacement_error", v)?,
            None => 0.01,
        },
        stability: parse_stability(check, s)?,
    })
}

/// `[safety]` keys of the stability monitor (defaults: `StabilityBounds::DEFAULT`).
fn parse_stability(check: &Check, s: &RawSafety) -> Result<StabilityBounds, ConfigError> {
    let d = StabilityBounds::DEFAULT;
    let opt = |key: &str, v: Option<f64>, scale: f64, default: f64| -> Result<f64, ConfigError> {
        match v {
            Some(v) => Ok(check.positive(&format!("safety.{key}"), v)? * scale),
            None => Ok(default),
        }
    };
    let low = opt(
        "stability_band_low_hz",
        s.stability_band_low_hz,
        1.0,
        d.band_hz.0,
    )?;
    let high = opt(
        "stability_band_high_hz",
        s.stability_band_high_hz,
        1.0,
        d.band_hz.1,
    )?;
    if high <= low {
        return Err(check.err(
            "safety.stability_band_high_hz",
            format!("{high} is not valid: expected more than stability_band_low_hz = {low}"),
        ));
    }
    Ok(StabilityBounds {
        band_hz: (low, high),
        memory_s: opt(
            "stability_memory_ms",
            s.stability_memory_ms,
            1e-3,
            d.memory_s,
        )?,
        max_generated_energy_j: opt(
            "max_generated_energy_j",
            s.max_generated_energy_j,
            1.0,
            d.max_generated_energy_j,
        )?,
        max_oscillation_m: opt(
            "max_oscillation_m",
            s.max_oscillation_m,
            1.0,
            d.max_oscillation_m,
        )?,
    })
}

fn parse_scenario(
    check: &Check,
    s: &RawScenario,
    resolve: &dyn Fn(&str) -> PathBuf,
) -> Result<ScenarioConfig, ConfigError> {
    let duration_s = check.positive("scenario.duration_s", s.duration_s)?;
    let (load_csv, load_csv_samples) = load_csv(check, "scenario.load_csv", &s.load_csv, resolve)?;
    Ok(ScenarioConfig {
        duration_s,
        preload_n: check.finite("scenario.preload_n", s.preload_n)?,
        harmonic_amplitude_n: check
            .non_negative("scenario.harmonic_amplitude_n", s.harmonic_amplitude_n)?,
        harmonic_frequency_hz: check
            .non_negative("scenario.harmonic_frequency_hz", s.harmonic_frequency_hz)?,
        train_speed_kmh: check.non_negative("scenario.train_speed_kmh", s.train_speed_kmh)?,
        train_first_axle_s: check.finite("scenario.train_first_axle_s", s.train_first_axle_s)?,
        step_n: check.finite("scenario.step_n", s.step_n)?,
        step_at_s: check.non_negative("scenario.step_at_s", s.step_at_s)?,
        load_csv,
        load_csv_samples,
    })
}

fn parse_injection(
    check: &Check,
    index: usize,
    r: &RawInjection,
) -> Result<Injection, ConfigError> {
    let key = |k: &str| format!("inject[{index}].{k}");
    let process = check.choice(
        &key("process"),
        &r.process,
        &[
            ("rig", LoopProcess::Rig),
            ("emulator", LoopProcess::Emulator),
            ("controller", LoopProcess::Controller),
        ],
    )?;
    let at_s = check.non_negative(&key("at_s"), r.at_s)?;
    let kind = match r.kind.as_str() {
        "stall" => {
            let ms = r.duration_ms.ok_or_else(|| {
                check.err(&key("duration_ms"), "missing: a stall needs its duration in ms".into())
            })?;
            InjectKind::Stall {
                duration_s: check.positive(&key("duration_ms"), ms)? * 1e-3,
            }
        }
        "cpu-stall" => {
            let ms = r.duration_ms.ok_or_else(|| {
                check.err(&key("duration_ms"), "missing: a cpu-stall needs its duration in ms".into())
            })?;
            if process != LoopProcess::Emulator {
                return Err(check.err(
                    &key("process"),
                    format!("\"{}\" is not valid for kind \"cpu-stall\": only the emulator has a standby thread (process = \"emulator\")", r.process),
                ));
            }
            InjectKind::CpuStall {
                duration_s: check.positive(&key("duration_ms"), ms)? * 1e-3,
            }
        }
        "kill" => InjectKind::Kill,
        "drop-samples" => {
            let count = r.count.ok_or_else(|| {
                check.err(&key("count"), "missing: drop-samples needs a count of samples".into())
            })?;
            InjectKind::DropSamples {
                count: check.at_least(&key("count"), count, 1)?,
            }
        }
        "nan" => InjectKind::Nan,
        "out-of-range" => InjectKind::OutOfRange,
        other => {
            return Err(check.err(
                &key("kind"),
                format!("\"{other}\" is not valid: expected \"stall\", \"cpu-stall\", \"kill\", \"drop-samples\", \"nan\" or \"out-of-range\""),
            ))
        }
    };
    let sample_fault = matches!(
        kind,
        InjectKind::DropSamples { .. } | InjectKind::Nan | InjectKind::OutOfRange
    );
    if sample_fault && process != LoopProcess::Rig {
        return Err(check.err(
            &key("process"),
            format!(
                "\"{}\" is not valid for kind \"{}\": only the rig produces samples (process = \"rig\")",
                r.process,
                kind.name()
            ),
        ));
    }
    Ok(Injection {
        process,
        kind,
        at_s,
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
        assert_eq!(c.safety.actions, FaultActions::HOLD_ALL);
    }

    /// The error of the default configuration with `from` replaced by `to`.
    fn error_with(from: &str, to: &str) -> String {
        assert!(DEFAULT_CONFIG_TOML.contains(from), "default lacks `{from}`");
        let text = DEFAULT_CONFIG_TOML.replace(from, to);
        parse_hil_config(&text, "x.toml", None)
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn the_controller_sits_with_the_rig_and_the_standby_unless_left_to_the_kernel() {
        let c = default_hil_config().unwrap();
        let standby = c.loop_.emulator_standby.expect("the default has a standby");
        assert_eq!(c.loop_.controller_cpus, c.loop_.rig_cpus);
        assert_eq!(c.loop_.controller_cpus, standby.cpus);
        assert!(!c
            .loop_
            .controller_cpus
            .iter()
            .any(|cpu| c.loop_.emulator_cpus.contains(cpu)));
        let unpinned = DEFAULT_CONFIG_TOML.replace("controller_cpus = [0]", "");
        let c = parse_hil_config(&unpinned, "x.toml", None).unwrap();
        assert!(c.loop_.controller_cpus.is_empty());
        let misspelt = error_with("controller_cpus = [0]", "controller_cpu = [0]");
        assert!(
            misspelt.contains("controller_cpu") && misspelt.contains("controller_cpus"),
            "{misspelt}"
        );
    }

    #[test]
    fn the_standby_sits_on_another_cpu_and_claims_within_a_period() {
        let c = default_hil_config().unwrap();
        let standby = c.loop_.emulator_standby.expect("the default has a standby");
        assert!(!standby
            .cpus
            .iter()
            .any(|c0| c.loop_.emulator_cpus.contains(c0)));
        assert!(standby.after_ns > 0 && standby.after_ns < c.loop_.period_ns);
        let same_cpu = error_with("emulator_standby_cpus = [0]", "emulator_standby_cpus = [1]");
        assert!(
            same_cpu.contains("loop.emulator_standby_cpus") && same_cpu.contains("CPU 1"),
            "{same_cpu}"
        );
        let too_late = error_with(
            "emulator_standby_after_us = 100.0",
            "emulator_standby_after_us = 300.0",
        );
        assert!(
            too_late.contains("loop.emulator_standby_after_us")
                && too_late.contains("300")
                && too_late.contains("less than one period"),
            "{too_late}"
        );
        let missing = error_with("emulator_standby_after_us = 100.0", "");
        assert!(
            missing.contains("loop.emulator_standby_after_us") && missing.contains("missing"),
            "{missing}"
        );
        let none = DEFAULT_CONFIG_TOML
            .replace("emulator_standby_cpus = [0]", "emulator_standby_cpus = []");
        let c = parse_hil_config(&none, "x.toml", None).unwrap();
        assert_eq!(c.loop_.emulator_standby, None);
    }

    #[test]
    fn a_cpu_stall_is_injected_into_the_emulator_only() {
        let with = |process: &str| {
            let text = format!(
                "{DEFAULT_CONFIG_TOML}\n[[inject]]\nprocess = \"{process}\"\nkind = \"cpu-stall\"\nduration_ms = 80.0\nat_s = 1.0\n"
            );
            parse_hil_config(&text, "x.toml", None)
        };
        let c = with("emulator").unwrap();
        assert_eq!(
            c.injections[0].kind,
            InjectKind::CpuStall { duration_s: 0.08 }
        );
        let e = with("rig").unwrap_err().to_string();
        assert!(
            e.contains("inject[0].process") && e.contains("cpu-stall"),
            "{e}"
        );
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

    #[test]
    fn removed_key_says_what_replaced_it() {
        let text = DEFAULT_CONFIG_TOML.replace(
            "keepalive_periods = 8",
            "keepalive_periods = 8\nsafe_force_n = 20000.0",
        );
        let e = parse_hil_config(&text, "x.toml", None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("safe_force_n") && e.contains("[safety]"), "{e}");
    }

    #[test]
    fn injection_of_samples_must_target_the_rig() {
        let text = format!(
            "{DEFAULT_CONFIG_TOML}\n[[inject]]\nprocess = \"emulator\"\nkind = \"nan\"\nat_s = 1.0\n"
        );
        let e = parse_hil_config(&text, "x.toml", None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("inject[0].process") && e.contains("only the rig"),
            "{e}"
        );
    }
}
