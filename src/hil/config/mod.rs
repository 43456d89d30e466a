//! The HIL run configuration (one TOML file: loop, model, emulator, controller, rig,
//! safety, scenario, fault injections): parsed raw with `deny_unknown_fields`, then
//! validated section by section into typed structs.
//!
//! Every error is one line naming the file, the key, the value and what would be valid.
//! Must not: fill in physical constants silently (every physical key is required).

use std::fmt;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::model::effects::AugmentedModel;
use crate::model::file::ModelSpec;
use crate::rig::servo::ServoConfig;
use crate::tomlerr;

mod actuator;
mod compensation;
mod controller;
mod emulator;
mod injections;
mod loop_;
mod rig;
mod safety;
mod scenario;

pub use controller::{CommandMode, ControllerConfig, LimitAction};
pub use emulator::EmulatorConfig;
pub use injections::{InjectKind, Injection, LoopProcess};
pub use loop_::{LoopConfig, Standby};
pub use rig::RigConfig;
pub use safety::SafetyConfig;
pub use scenario::{BlockConfig, ProgrammeConfig, ScenarioConfig, SCENARIO_BLOCK};

use compensation::{parse_compensation, RawCompensation};
use controller::{parse_controller, RawController};
use emulator::{parse_emulator, parse_model, RawEmulator};
use injections::{parse_injection, RawInjection};
use loop_::{parse_loop, RawLoop};
use rig::{parse_rig, RawRig};
use safety::{parse_safety, RawSafety};
use scenario::{parse_programme, parse_scenario, RawProgramme, RawScenario};

/// The default configuration, embedded so `fastemu hil` runs from any directory.
pub const DEFAULT_CONFIG_TOML: &str = include_str!("../../../configs/hil-default.toml");
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
    pub compensation: crate::hil::compensation::CompensationConfig,
    pub safety: SafetyConfig,
    pub scenario: ScenarioConfig,
    /// The load programme (from `[programme]`, or the scenario's load keys as one block).
    pub programme: ProgrammeConfig,
    pub injections: Vec<Injection>,
}

impl HilConfig {
    /// The rig servo's settings.
    pub fn servo_config(&self) -> ServoConfig {
        // The hold moves the specimen and whatever of the actuator rides with it (an
        // electrodynamic shaker's armature: 100 kg against a 60 kg rail segment); a servo
        // controller is tuned for its own actuator, so the rig places the poles on both.
        let moved_kg = self.rig.specimen_mass_kg
            + crate::rig::actuator::ActuatorPlant::from_config(&self.rig.actuator).moving_mass_kg();
        let (hold_kp, hold_ki, hold_kd) = ServoConfig::hold_gains(
            moved_kg,
            self.hold_bandwidth_hz(),
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
            stroke_hold: crate::rig::actuator::ActuatorPlant::from_config(&self.rig.actuator)
                .has_stroke_control(),
        }
    }

    /// The position hold's bandwidth the rig's servo uses: `[rig] hold_bandwidth_hz`, at
    /// most `0.05 / d` for an actuator of effective delay `d` (its phase lag at the hold's
    /// crossover stays under 18 degrees). A servo controller is tuned for its own
    /// actuator: a 50 Hz position loop through a servo-hydraulic actuator milliseconds
    /// late is itself unstable, and the interlock must hold whatever the actuator. Only
    /// the rig calls this (it knows its actuator's truth; the controller never does).
    pub fn hold_bandwidth_hz(&self) -> f64 {
        let k = self
            .model
            .element
            .high_frequency_stiffness_n_per_m(self.scenario.preload_n);
        let delay_s = self
            .rig
            .actuator
            .truth()
            .effective_delay(k)
            .delay_s
            .max(0.0);
        let limit_hz = if delay_s > 0.0 {
            0.05 / delay_s
        } else {
            f64::INFINITY
        };
        self.rig.hold_bandwidth_hz.min(limit_hz)
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
const REMOVED_KEYS: [(&str, &str); 11] = [
    (
        "law_lead_us",
        "moved: the controller owns the lead now, [compensation] initial_delay_us (a starting guess it refines during the run)",
    ),
    (
        "law_lead_order",
        "moved to [compensation] lead_order",
    ),
    (
        "actuator_lag_us",
        "moved: [rig.actuator] kind = \"lag-delay\", lag_us",
    ),
    (
        "actuator_delay_us",
        "moved: [rig.actuator] transport_delay_us",
    ),
    (
        "actuator_force_max_n",
        "moved: [rig.actuator] force_max_n",
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
    use crate::hil::fault::FaultActions;

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

    /// The loops' priority leaves room for the controller one above and the standby one
    /// below: 1 and 99 are refused, naming the key; 0 (off), 2 and 98 are taken.
    #[test]
    fn the_fifo_priority_leaves_a_level_above_and_below_the_loops() {
        for bad in ["1", "99", "100"] {
            let e = error_with("fifo_priority = 80", &format!("fifo_priority = {bad}"));
            assert!(
                e.contains("loop.fifo_priority") && e.contains("2-98"),
                "{bad}: {e}"
            );
        }
        for good in ["0", "2", "98"] {
            let text = DEFAULT_CONFIG_TOML
                .replace("fifo_priority = 80", &format!("fifo_priority = {good}"));
            assert!(parse_hil_config(&text, "x.toml", None).is_ok(), "{good}");
        }
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
        // A guess beyond the longest lead: the bound as the key was written.
        let text = DEFAULT_CONFIG_TOML.replace(
            "initial_delay_us = 252.0",
            "initial_delay_us = 252.0\nmax_delay_us = 100",
        );
        let e = parse_hil_config(&text, "x.toml", None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("compensation.initial_delay_us")
                && e.contains("252 is not valid: expected at most max_delay_us = 100 us"),
            "{e}"
        );
        // The dynamic error's bound is a key of its own, checked as the others.
        let text = DEFAULT_CONFIG_TOML.replace(
            "max_transient_m = 20.0e-6",
            "max_transient_m = 20.0e-6\nmax_dynamic_displacement_error = -0.04",
        );
        let e = parse_hil_config(&text, "x.toml", None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("safety.max_dynamic_displacement_error"), "{e}");
        let text = DEFAULT_CONFIG_TOML.replace(
            "max_transient_m = 20.0e-6",
            "max_transient_m = 20.0e-6\nmax_dynamic_displacement_error = 0.02",
        );
        let c = parse_hil_config(&text, "x.toml", None).unwrap();
        assert_eq!(c.safety.max_dynamic_displacement_error, 0.02);
        assert_eq!(
            default_hil_config()
                .unwrap()
                .safety
                .max_dynamic_displacement_error,
            0.04
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

    /// The default configuration with its `[rig.actuator]` table replaced by `table`.
    fn with_actuator(table: &str) -> Result<HilConfig, ConfigError> {
        let start = DEFAULT_CONFIG_TOML.find("[rig.actuator]").unwrap();
        let end = start
            + DEFAULT_CONFIG_TOML[start..]
                .find("\n[compensation]")
                .unwrap();
        let text = format!(
            "{}[rig.actuator]\n{table}\n{}",
            &DEFAULT_CONFIG_TOML[..start],
            &DEFAULT_CONFIG_TOML[end..]
        );
        parse_hil_config(&text, "x.toml", None)
    }

    #[test]
    fn actuator_kinds_presets_overrides_and_perturbation_parse() {
        use crate::rig::actuator::ActuatorKind;
        let c = with_actuator("preset = \"fatigue-150kn\"")
            .unwrap()
            .rig
            .actuator;
        assert_eq!(c.nominal.kind, ActuatorKind::ServoHydraulic);
        assert_eq!(c.preset, Some("fatigue-150kn"));
        assert_eq!(c.nominal.get("valve_frequency_hz"), Some(100.0));
        assert_eq!(c.perturb_seed, 1, "defaults to [rig] seed");
        let c = with_actuator(
            "kind = \"servo-hydraulic\"\npreset = \"fatigue-150kn\"\nvalve_frequency_hz = 120\ntransport_delay_us = 700.0\nperturb = 0.3\nperturb_seed = 9",
        )
        .unwrap()
        .rig
        .actuator;
        assert_eq!(c.nominal.get("valve_frequency_hz"), Some(120.0));
        assert_eq!(c.nominal.transport_delay_s(), 700.0 * 1e-6);
        assert_eq!((c.perturb, c.perturb_seed), (0.3, 9));
        assert_eq!(c.truth(), c.truth());
        assert_ne!(c.truth(), c.nominal);
        let e = with_actuator(
            "kind = \"electrodynamic\"\ntransport_delay_us = 100.0\nforce_max_n = 1e4\namplifier_bandwidth_hz = 1500.0\ncoil_resistance_ohm = 0.2\ncoil_inductance_h = 3e-4\nforce_constant_n_per_a = 60.0\nsuspension_stiffness_n_per_m = 6e4\nsuspension_damping_ns_per_m = 300.0\nmoving_mass_kg = 12.0",
        )
        .unwrap();
        assert_eq!(e.rig.actuator.nominal.kind, ActuatorKind::Electrodynamic);
    }

    #[test]
    fn actuator_errors_name_the_key_and_what_is_valid() {
        let e = with_actuator("kind = \"pneumatic\"")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("rig.actuator.kind")
                && e.contains("pneumatic")
                && e.contains("\"servo-hydraulic\""),
            "{e}"
        );
        let e = with_actuator("kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 1e5\nvalve_frequency_hz = 100.0")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("rig.actuator.valve_frequency_hz")
                && e.contains("`valve_frequency_hz = 100.0`")
                && e.contains("lag-delay")
                && e.contains("lag_us")
                && !e.contains("did you mean"),
            "{e}"
        );
        // A misspelt key: its value and the key meant.
        let e = with_actuator(
            "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_uss = 80.0\nforce_max_n = 1e5",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("x.toml")
                && e.contains("rig.actuator.lag_uss")
                && e.contains("`lag_uss = 80.0`")
                && e.ends_with("(did you mean `lag_us`?)"),
            "{e}"
        );
        let e = with_actuator("kind = \"lag-delay\"\ntransport_delay_us = 50.0\nforce_max_n = 1e5")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("rig.actuator.lag_us") && e.contains("missing"),
            "{e}"
        );
        // A share: the servo controller's velocity compensation, 0 to 1.
        let e = with_actuator("preset = \"fatigue-150kn\"\nvelocity_compensation = 1.5")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("rig.actuator.velocity_compensation")
                && e.contains("1.5 is not valid: expected a share from 0 to 1"),
            "{e}"
        );
        assert!(with_actuator("preset = \"fatigue-150kn\"\nvelocity_compensation = 0.5").is_ok());
        let e = with_actuator("preset = \"fatigue-150kn\"\nbulk_modulus_pa = -1.0")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("x.toml") && e.contains("rig.actuator.bulk_modulus_pa") && e.contains("-1"),
            "{e}"
        );
        let e = with_actuator("kind = \"electrodynamic\"\npreset = \"fatigue-150kn\"")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("rig.actuator.preset") && e.contains("shaker-10kn"),
            "{e}"
        );
        let e = with_actuator("preset = \"fatigue-150kn\"\nperturb = 1.5")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("rig.actuator.perturb") && e.contains("1.5"),
            "{e}"
        );
        let old = DEFAULT_CONFIG_TOML.replace("seed = 1\n", "seed = 1\nactuator_lag_us = 80.0\n");
        let e = parse_hil_config(&old, "x.toml", None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("actuator_lag_us") && e.contains("[rig.actuator]"),
            "{e}"
        );
    }
}
