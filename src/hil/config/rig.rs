//! `[rig]`: the simulated rig's specimen, sensor, servo lead and position hold.

use serde::Deserialize;

use super::actuator::parse_actuator;
use super::{Check, ConfigError};
use crate::rig::actuator::ActuatorConfig;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawRig {
    specimen_mass_kg: f64,
    damping_ns_per_m: f64,
    actuator: toml::Table,
    sensor_noise_m: f64,
    sensor_resolution_m: f64,
    seed: u64,
    internal_substeps: u32,
    command_stale_periods: u32,
    hold_bandwidth_hz: f64,
    hold_damping_ratio: f64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigConfig {
    pub specimen_mass_kg: f64,
    pub damping_ns_per_m: f64,
    /// `[rig.actuator]`: the actuator's kind and nominal parameters.
    pub actuator: ActuatorConfig,
    pub sensor_noise_m: f64,
    pub sensor_resolution_m: f64,
    pub seed: u64,
    pub internal_substeps: u32,
    pub command_stale_periods: u32,
    pub hold_bandwidth_hz: f64,
    pub hold_damping_ratio: f64,
}

pub(super) fn parse_rig(check: &Check, r: &RawRig) -> Result<RigConfig, ConfigError> {
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
    let actuator = parse_actuator(check, &r.actuator, r.seed)?;
    let hold_damping_ratio = check.positive("rig.hold_damping_ratio", r.hold_damping_ratio)?;
    Ok(RigConfig {
        specimen_mass_kg: check.positive("rig.specimen_mass_kg", r.specimen_mass_kg)?,
        damping_ns_per_m: check.non_negative("rig.damping_ns_per_m", r.damping_ns_per_m)?,
        actuator,
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
