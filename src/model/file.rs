//! Model files (SPEC 2.3): TOML parsed raw, then validated into an `ElementModel`.
//!
//! Every error is one line naming the file, the key, the value and what would be valid.
//! No silent defaults for physical constants: every parameter of the chosen form must
//! be present.

use std::fmt;
use std::path::Path;

use super::params::{ElementModel, Form, KelvinVoigtParams, ZenerParams};

/// A model file error: one line, naming the file.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelFileError {
    pub path: String,
    pub message: String,
}

impl fmt::Display for ModelFileError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.path, self.message)
    }
}

impl std::error::Error for ModelFileError {}

/// A validated model file.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelSpec {
    pub element: ElementModel,
    pub length_m: f64,
    /// `[[effect]]` tables, kept raw for the effect library to validate.
    pub effect_tables: Vec<toml::Table>,
}

const ZENER_KEYS: [&str; 5] = [
    "k1_0_n_per_m2",
    "k2_0_n_per_m2",
    "c2_0_ns_per_m2",
    "chi",
    "p0_n",
];
const KV_KEYS: [&str; 2] = ["k_n_per_m2", "c_ns_per_m2"];
const COMMON_KEYS: [&str; 4] = ["form", "length_m", "effect", "description"];

/// Reads and validates a model file.
pub fn load_model_file(path: &Path) -> Result<ModelSpec, ModelFileError> {
    let text = std::fs::read_to_string(path).map_err(|e| ModelFileError {
        path: path.display().to_string(),
        message: format!("cannot read model file: {e}"),
    })?;
    parse_model_toml(&text, &path.display().to_string())
}

/// Validates model-file text; `origin` names the file in errors.
pub fn parse_model_toml(text: &str, origin: &str) -> Result<ModelSpec, ModelFileError> {
    let err = |message: String| ModelFileError {
        path: origin.to_string(),
        message,
    };
    let table: toml::Table = text.parse().map_err(|e: toml::de::Error| {
        err(format!(
            "not valid TOML {}",
            crate::tomlerr::describe(text, &e)
        ))
    })?;

    let form_name = match table.get("form") {
        None => {
            return Err(err(
                "missing key `form`: expected \"consistent\", \"paper\" or \"kelvin-voigt\"".into(),
            ))
        }
        Some(toml::Value::String(s)) => s.clone(),
        Some(other) => {
            return Err(err(format!(
            "key `form` = {other}: expected a string \"consistent\", \"paper\" or \"kelvin-voigt\""
        )))
        }
    };
    let form = Form::from_name(&form_name).ok_or_else(|| {
        err(format!(
            "key `form` = \"{form_name}\": expected \"consistent\", \"paper\" or \"kelvin-voigt\""
        ))
    })?;
    let form_keys: &[&str] = match form {
        Form::Consistent | Form::Paper => &ZENER_KEYS,
        Form::KelvinVoigt => &KV_KEYS,
    };
    for key in table.keys() {
        if !COMMON_KEYS.contains(&key.as_str()) && !form_keys.contains(&key.as_str()) {
            let valid: Vec<&str> = COMMON_KEYS.iter().chain(form_keys).copied().collect();
            return Err(err(format!(
                "unknown key `{key}` for form \"{form_name}\": valid keys are {}",
                valid.join(", ")
            )));
        }
    }
    let number = |key: &str| -> Result<f64, ModelFileError> {
        match table.get(key) {
            None => Err(err(format!(
                "missing key `{key}` (required for form \"{form_name}\")"
            ))),
            Some(toml::Value::Float(x)) => Ok(*x),
            Some(toml::Value::Integer(i)) => Ok(*i as f64),
            Some(other) => Err(err(format!("key `{key}` = {other}: expected a number"))),
        }
    };
    let positive = |key: &str| -> Result<f64, ModelFileError> {
        let x = number(key)?;
        if x.is_finite() && x > 0.0 {
            Ok(x)
        } else {
            Err(err(format!(
                "key `{key}` = {x}: must be a positive finite number"
            )))
        }
    };

    let length_m = positive("length_m")?;
    let element = match form {
        Form::Consistent | Form::Paper => {
            let chi = number("chi")?;
            if !(0.0..1.0).contains(&chi) {
                return Err(err(format!("key `chi` = {chi}: must be in [0, 1)")));
            }
            let params = ZenerParams {
                k1_0_n_per_m: positive("k1_0_n_per_m2")? * length_m,
                k2_0_n_per_m: positive("k2_0_n_per_m2")? * length_m,
                c2_0_ns_per_m: positive("c2_0_ns_per_m2")? * length_m,
                chi,
                p0_n: positive("p0_n")?,
            };
            if form == Form::Consistent {
                ElementModel::Consistent(params)
            } else {
                ElementModel::Paper(params)
            }
        }
        Form::KelvinVoigt => ElementModel::KelvinVoigt(KelvinVoigtParams {
            k_n_per_m: positive("k_n_per_m2")? * length_m,
            c_ns_per_m: positive("c_ns_per_m2")? * length_m,
        }),
    };

    let effect_tables = match table.get("effect") {
        None => Vec::new(),
        Some(toml::Value::Array(items)) => items
            .iter()
            .enumerate()
            .map(|(i, item)| match item {
                toml::Value::Table(t) => Ok(t.clone()),
                other => Err(err(format!(
                    "`effect` entry {i} = {other}: expected an [[effect]] table"
                ))),
            })
            .collect::<Result<_, _>>()?,
        Some(other) => {
            return Err(err(format!(
                "key `effect` = {other}: expected [[effect]] tables"
            )))
        }
    };

    Ok(ModelSpec {
        element,
        length_m,
        effect_tables,
    })
}

/// Renders a model file (SPEC 2.3) for a Zener or Kelvin-Voigt element of `length_m`.
pub fn render_model_toml(element: &ElementModel, length_m: f64, header: &str) -> String {
    let mut out = String::new();
    for line in header.lines() {
        out.push_str(&format!("# {line}\n"));
    }
    out.push_str(&format!(
        "form = \"{}\"\nlength_m = {length_m:?}\n",
        element.form()
    ));
    match element {
        ElementModel::Consistent(p) | ElementModel::Paper(p) => {
            out.push_str(&format!(
                "k1_0_n_per_m2 = {:?}\nk2_0_n_per_m2 = {:?}\nc2_0_ns_per_m2 = {:?}\nchi = {:?}\np0_n = {:?}\n",
                p.k1_0_n_per_m / length_m,
                p.k2_0_n_per_m / length_m,
                p.c2_0_ns_per_m / length_m,
                p.chi,
                p.p0_n
            ));
        }
        ElementModel::KelvinVoigt(p) => {
            out.push_str(&format!(
                "k_n_per_m2 = {:?}\nc_ns_per_m2 = {:?}\n",
                p.k_n_per_m / length_m,
                p.c_ns_per_m / length_m
            ));
        }
    }
    out
}
