//! `[compensation]`: the controller's compensation of the actuator (the starting lead,
//! adaptation, the passivity guard and their tuning). Must not: read the actuator's truth.

use serde::Deserialize;

use super::{Check, ConfigError};
use crate::hil::compensation::CompensationConfig;
use crate::ipc::messages::Compensation;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawCompensation {
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
    #[serde(default = "yes")]
    plan_from_actuator: bool,
    #[serde(default)]
    plan_for_external_rig: bool,
    #[serde(default)]
    actuator_tolerance: Option<f64>,
}

fn yes() -> bool {
    true
}

pub(super) fn parse_compensation(
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
                // As the key was written (the seconds' rounding left out).
                (max_delay_s * 1e6 * 1e6).round() / 1e6
            ),
        ));
    }
    out.adapt = c.adapt;
    out.passivity_guard = c.passivity_guard;
    out.plan_from_actuator = c.plan_from_actuator;
    out.plan_for_external_rig = c.plan_for_external_rig;
    if let Some(t) = c.actuator_tolerance {
        if !(0.0..=0.9).contains(&t) {
            return Err(check.err(
                "compensation.actuator_tolerance",
                format!("{t} is not valid: expected a fraction from 0 to 0.9 (0.3: each parameter within +-30 %)"),
            ));
        }
        out.actuator_tolerance = t;
    }
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
