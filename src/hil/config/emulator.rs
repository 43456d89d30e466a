//! `[model]` and `[emulator]`: the element model (inline or a model file) and the emulator's range and law frequency.

use std::path::PathBuf;

use serde::Deserialize;

use super::{Check, ConfigError};
use crate::model::file::{load_model_file, parse_model_toml, ModelSpec};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawEmulator {
    displacement_min_m: f64,
    displacement_max_m: f64,
    law_frequency_hz: f64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EmulatorConfig {
    pub displacement_min_m: f64,
    pub displacement_max_m: f64,
    /// Frequency at which the local law's stiffness and damping equal the element's
    /// small-signal modulus (the specimen's resonance on the element), Hz.
    pub law_frequency_hz: f64,
}

pub(super) fn parse_model(
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

pub(super) fn parse_emulator(
    check: &Check,
    e: &RawEmulator,
) -> Result<EmulatorConfig, ConfigError> {
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
