//! `[controller]`: command mode, delay compensation, force and rate limits, keep-alive.

use serde::Deserialize;

use super::{Check, ConfigError};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawController {
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

pub(super) fn parse_controller(
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
