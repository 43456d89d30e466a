//! `[safety]`: fault actions, the ride-through limit, the hold and its end, the report's transient bound.

use serde::Deserialize;

use super::{Check, ConfigError};
use crate::hil::fault::{FaultAction, FaultActions, FaultClass};
use crate::hil::passivity::StabilityBounds;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSafety {
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
    max_dynamic_displacement_error: Option<f64>,
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
    #[serde(default)]
    stability_persist_ms: Option<f64>,
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
    /// A run whose dynamic displacement error (the same with the means removed: the
    /// static deflection under the preload left out) exceeds this is not clean (default
    /// 0.04). On the shipped programme the dynamic error is about 4 times the whole one
    /// (0.135 against 0.034 % on the shipped actuator; 3.2 against 0.82 % on a
    /// `shaker-150kn` draw), so the two bounds agree there; a higher preload or a long
    /// quiet stretch dilutes the whole displacement's error and not this one as much
    /// (`fatigue-150kn` at a 60 kN preload: 0.70 % whole, 8.0 % dynamic, faithful to 1 Hz).
    pub max_dynamic_displacement_error: f64,
    /// The online stability monitor's bounds (`loop-unstable`).
    pub stability: StabilityBounds,
}

pub(super) fn parse_action(
    check: &Check,
    class: FaultClass,
    value: &str,
) -> Result<FaultAction, ConfigError> {
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

pub(super) fn parse_safety(check: &Check, s: &RawSafety) -> Result<SafetyConfig, ConfigError> {
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
        max_dynamic_displacement_error: match s.max_dynamic_displacement_error {
            Some(v) => check.positive("safety.max_dynamic_displacement_error", v)?,
            None => 0.04,
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
        persist_s: opt(
            "stability_persist_ms",
            s.stability_persist_ms,
            1e-3,
            d.persist_s,
        )?,
    })
}
