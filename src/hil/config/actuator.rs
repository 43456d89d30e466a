//! `[rig.actuator]`: kind, preset, the kind's parameters (a preset's values overridden by the keys beside it), perturbation; the parameter tables and plants live in `rig::actuator`.

use super::{Check, ConfigError};
use crate::rig::actuator::{preset, ActuatorConfig, ActuatorKind, ActuatorParams, Rule, PRESETS};

/// Keys every kind takes besides its parameters.
const COMMON_KEYS: [&str; 4] = ["kind", "preset", "perturb", "perturb_seed"];

fn quoted(names: impl Iterator<Item = &'static str>) -> String {
    names
        .map(|n| format!("\"{n}\""))
        .collect::<Vec<_>>()
        .join(", ")
}

fn string<'t>(
    check: &Check,
    t: &'t toml::Table,
    key: &str,
) -> Result<Option<&'t str>, ConfigError> {
    match t.get(key) {
        None => Ok(None),
        Some(toml::Value::String(s)) => Ok(Some(s)),
        Some(other) => Err(check.err(
            &format!("rig.actuator.{key}"),
            format!("{other} is not valid: expected a string"),
        )),
    }
}

fn number(check: &Check, key: &str, v: &toml::Value) -> Result<f64, ConfigError> {
    match v {
        toml::Value::Float(f) => Ok(*f),
        toml::Value::Integer(i) => Ok(*i as f64),
        other => Err(check.err(key, format!("{other} is not valid: expected a number"))),
    }
}

/// Validates `[rig.actuator]`; `rig_seed` is the default `perturb_seed`.
pub(super) fn parse_actuator(
    check: &Check,
    t: &toml::Table,
    rig_seed: u64,
) -> Result<ActuatorConfig, ConfigError> {
    let kind_names = || quoted(ActuatorKind::ALL.into_iter().map(ActuatorKind::name));
    let kind = match string(check, t, "kind")? {
        Some(name) => Some(ActuatorKind::from_name(name).ok_or_else(|| {
            check.err(
                "rig.actuator.kind",
                format!("\"{name}\" is not valid: expected {}", kind_names()),
            )
        })?),
        None => None,
    };
    let preset = match string(check, t, "preset")? {
        Some(name) => {
            let valid = |k: Option<ActuatorKind>| {
                quoted(
                    PRESETS
                        .iter()
                        .filter(|p| k.is_none_or(|k| p.kind == k))
                        .map(|p| p.name),
                )
            };
            let p = preset(name).ok_or_else(|| {
                check.err(
                    "rig.actuator.preset",
                    format!("\"{name}\" is not valid: expected {}", valid(kind)),
                )
            })?;
            if let Some(k) = kind.filter(|k| *k != p.kind) {
                return Err(check.err(
                    "rig.actuator.preset",
                    format!(
                        "\"{name}\" is not valid for kind \"{}\" (it is a \"{}\" preset): expected {}",
                        k.name(),
                        p.kind.name(),
                        valid(Some(k))
                    ),
                ));
            }
            Some(p)
        }
        None => None,
    };
    let kind = kind.or(preset.map(|p| p.kind)).ok_or_else(|| {
        check.err(
            "rig.actuator.kind",
            format!("missing: expected one of {} (or a preset)", kind_names()),
        )
    })?;
    let keys = kind.keys();
    for (name, value) in t.iter() {
        if !COMMON_KEYS.contains(&name.as_str()) && !keys.iter().any(|k| k.name == name) {
            let valid: Vec<&str> = keys
                .iter()
                .map(|k| k.name)
                .chain(COMMON_KEYS.iter().copied())
                .collect();
            let guess = crate::tomlerr::closest_key(name, &valid)
                .map_or(String::new(), |g| format!(" (did you mean `{g}`?)"));
            return Err(check.err(
                &format!("rig.actuator.{name}"),
                format!(
                    "`{name} = {value}` is not a parameter of kind \"{}\": expected {} (and {}){guess}",
                    kind.name(),
                    keys.iter().map(|k| k.name).collect::<Vec<_>>().join(", "),
                    COMMON_KEYS.join(", ")
                ),
            ));
        }
    }
    let mut values = [0.0; crate::rig::actuator::MAX_PARAMS];
    for (i, k) in keys.iter().enumerate() {
        let full = format!("rig.actuator.{}", k.name);
        let value = match t.get(k.name) {
            Some(v) => number(check, &full, v)?,
            None => match preset.and_then(|p| p.values.get(i).copied()).or(k.default) {
                Some(v) => v,
                None => {
                    return Err(check.err(
                        &full,
                        format!(
                            "missing: kind \"{}\" needs it (or a preset that gives it)",
                            kind.name()
                        ),
                    ))
                }
            },
        };
        values[i] = match k.rule {
            Rule::Positive => check.positive(&full, value)?,
            Rule::NonNegative => check.non_negative(&full, value)?,
            Rule::Fraction if (0.0..=1.0).contains(&value) => value,
            Rule::Fraction => {
                return Err(check.err(
                    &full,
                    format!("{value} is not valid: expected a share from 0 to 1"),
                ))
            }
        };
    }
    let params = ActuatorParams::from_config_units(kind, &values[..keys.len()]);
    if params.transport_delay_s() > 0.1 {
        return Err(check.err(
            "rig.actuator.transport_delay_us",
            format!("{} is not valid: expected <= 100000 us", values[0]),
        ));
    }
    let perturb = match t.get("perturb") {
        Some(v) => number(check, "rig.actuator.perturb", v)?,
        None => 0.0,
    };
    if !(0.0..=0.9).contains(&perturb) {
        return Err(check.err(
            "rig.actuator.perturb",
            format!("{perturb} is not valid: expected 0 to 0.9 (a fraction of each value)"),
        ));
    }
    let perturb_seed = match t.get("perturb_seed") {
        None => rig_seed,
        Some(toml::Value::Integer(i)) if *i >= 0 => *i as u64,
        Some(other) => {
            return Err(check.err(
                "rig.actuator.perturb_seed",
                format!("{other} is not valid: expected an integer >= 0"),
            ))
        }
    };
    Ok(ActuatorConfig {
        nominal: params,
        preset: preset.map(|p| p.name),
        perturb,
        perturb_seed,
    })
}
