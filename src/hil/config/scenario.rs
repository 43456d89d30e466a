//! `[scenario]` and `[programme]`: the run's length, preload and the load programme's blocks (with load CSVs).

use std::path::PathBuf;

use serde::Deserialize;

use super::{Check, ConfigError};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawProgramme {
    /// Passes through the block sequence; 0 = until the run's end.
    #[serde(default)]
    repeat: u64,
    block: Vec<RawBlock>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawBlock {
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
pub(super) struct RawScenario {
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

pub(super) fn parse_programme(
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

pub(super) fn parse_scenario(
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
