//! The effect library (SPEC 5) and `ModelStepper`, the element plus its effects.
//!
//! Owns: the `[[effect]]` tables of a model file (validation into `Effect`s and rendering
//! back), and a fixed-step force-from-displacement stepper that composes `ForceStepper`
//! (paper Eq. 1-3, consistent form) with the effects:
//!
//! - `preload-stiffening`: sets `chi` and `P0` of the Zener element (paper Eq. 1).
//! - `amplitude-friction`: an Iwan friction element in parallel: `IWAN_ELEMENTS` Jenkins
//!   elements (spring `k_f / N` in series with a Coulomb slider) whose slip forces follow
//!   a log-normal spread `s` around `F_slip / N` (normalised so the full-slip force is
//!   `F_slip`). `s = 0` is one Jenkins element (bilinear loop); `s ~ 1` is a smooth
//!   Berg-like transition. Rate-independent and exact for any step (a clamp each). Its
//!   loops obey Masing's rule (a branch is the first-loading curve scaled by two).
//!   Or, with `dahl_exponent` `n` instead of `slip_spread`, a generalised Dahl element
//!   `dF/dz = k_f |1 - F sgn(z')/F_slip|^n` (n = 1 Dahl's model, n -> 0 a Jenkins element,
//!   n = 2 hyperbolic): its branches restart the first-loading curve from the reversal
//!   point (not Masing). Integrated in closed form over each step's monotone increment.
//! - `fractional-damping`: a springpot `c_a s^alpha` in parallel, realised by a fixed bank
//!   of Maxwell branches (log-spaced relaxation rates, stiffnesses from the springpot's
//!   relaxation spectrum `c_a sin(pi alpha)/pi r^(alpha-1)`), plus a spring for the rates
//!   below the bank and a dashpot for those above, so `c_a (i W)^alpha` is matched to a
//!   few per mille between 0.1 Hz and 1 kHz.
//! - `temperature-shift`: at operating temperature T, moduli scale by
//!   `b_T = exp(-m (T - T_ref))` and relaxation times by `a_T = 10^(-s (T - T_ref))`
//!   (a local Arrhenius/WLF slope); applied to the Zener element and the springpot.
//! - `channel-delay`: the force channel lags the displacement channel by `tau`.
//! - `moving-mass`: `m z''` added to the force (mass between load cell and sample).
//! - `load-train-resonance`: the load cell reads the element force through the load
//!   train's own mode (fixture, load cell, frame): `F_meas = H F`,
//!   `H = w_n^2 / (s^2 + 2 zeta w_n s + w_n^2)` (a bilinear-transform filter in time).
//! - `specimen-drift`: the specimen's moduli change with a clock (test order, time or the
//!   energy it has dissipated): factor `1 + rate x (clock - clock at the reference
//!   instant)` on `k1`, `k2`, `c2`; the element parameters describe the reference instant.
//! - `self-heating`: the power the element dissipates heats it (`model::thermal`), and
//!   its temperature rise drives the temperature law (`temperature-shift`'s, else a stated
//!   default); offline the rise of each test comes from the campaign's schedule, in the
//!   stepper it is integrated step by step (Maxwell dashpots' power) and the element
//!   retuned whenever it has moved by `RETUNE_STEP_K`.
//! - `cyclic-softening` (the Mullins effect): the element's force is `eta F_v`, `F_v` the
//!   virgin element's, `eta = 1 - d tanh((M - F_v) / F_s)` with `M` the largest virgin
//!   force reached so far (an Ogden-Roxburgh-like damage of stress, in force): on the
//!   primary curve (`F_v = M`) nothing changes; below the largest load reached the element
//!   is softer, more so the further below; a new maximum moves `M` up for good.
//!
//! Channel delay, moving mass and the load-train resonance are artefacts of how a rig *measures* the element, not
//! properties of the elastomer. `StepperMode::Emulation` (what the HIL emulator runs)
//! leaves them out, so the emulated element force is the elastomer's own;
//! `StepperMode::Measurement` includes them, to simulate what a lab rig would record.
//!
//! Must not: allocate, read a clock or do I/O in `ModelStepper::step` (the delay line is
//! allocated once in `new`). Identical inputs give bit-identical outputs.

use super::element::{phi_functions, ForceStepper, StepFlags};
use super::equiv::equivalent;
use super::file::{render_model_toml, ModelFileError, ModelSpec};
use super::params::ElementModel;

/// The effect vocabulary of SPEC 5, in the order the library tries them.
pub const EFFECT_NAMES: [&str; 10] = [
    "preload-stiffening",
    "amplitude-friction",
    "fractional-damping",
    "temperature-shift",
    "channel-delay",
    "moving-mass",
    "load-train-resonance",
    "specimen-drift",
    "self-heating",
    "cyclic-softening",
];

/// What a `specimen-drift` runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DriftClock {
    /// Tests run so far (campaign order), per test.
    TestOrder,
    /// Clock time since the reference instant (`started_at`), per hour.
    Time,
    /// Energy the specimen dissipated since the reference instant, per kJ.
    DissipatedEnergy,
}

impl DriftClock {
    pub const ALL: [DriftClock; 3] = [
        DriftClock::TestOrder,
        DriftClock::Time,
        DriftClock::DissipatedEnergy,
    ];

    pub fn name(self) -> &'static str {
        match self {
            DriftClock::TestOrder => "test-order",
            DriftClock::Time => "time",
            DriftClock::DissipatedEnergy => "dissipated-energy",
        }
    }

    /// Unit of the clock (the rate is per this unit).
    pub fn unit(self) -> &'static str {
        match self {
            DriftClock::TestOrder => "test",
            DriftClock::Time => "h",
            DriftClock::DissipatedEnergy => "kJ",
        }
    }

    pub fn from_name(name: &str) -> Option<DriftClock> {
        DriftClock::ALL.into_iter().find(|c| c.name() == name)
    }
}

/// Largest relative change of the moduli a `specimen-drift` may describe over a campaign
/// (conditioning and ageing of an elastomer pad change it by a few per cent to tens).
pub const DRIFT_FACTOR_FLOOR: f64 = 0.05;

/// Temperature change after which a self-heating stepper retunes its element, K.
pub const RETUNE_STEP_K: f64 = 0.01;

/// The friction element's law and its shape parameter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FrictionLaw {
    /// Iwan element; log-normal spread of the Jenkins elements' slip forces (0: one
    /// slider), at most `SLIP_SPREAD_LIMIT`.
    Iwan { slip_spread: f64 },
    /// Generalised Dahl element; exponent in `DAHL_EXPONENT_RANGE`.
    Dahl { exponent: f64 },
}

/// Largest `slip_spread` a model file may state.
pub const SLIP_SPREAD_LIMIT: f64 = 5.0;
/// Range of `dahl_exponent` a model file may state.
pub const DAHL_EXPONENT_RANGE: (f64, f64) = (0.02, 4.0);

/// Temperature assumed when a model or test does not state one, degC.
pub const DEFAULT_TEMPERATURE_C: f64 = 23.0;

/// One effect with its parameters, per element (per-metre values times length).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Effect {
    PreloadStiffening {
        chi: f64,
        p0_n: f64,
    },
    AmplitudeFriction {
        /// Initial (sticking) stiffness of the friction element, N/m.
        stiffness_n_per_m: f64,
        /// Force at full slip, N.
        slip_force_n: f64,
        law: FrictionLaw,
    },
    FractionalDamping {
        /// Springpot coefficient `c_a` in `F = c_a d^alpha z / dt^alpha`, N s^alpha / m.
        coefficient_ns_alpha_per_m: f64,
        /// Springpot order, 0 < alpha < 1.
        alpha: f64,
    },
    TemperatureShift {
        reference_temperature_c: f64,
        /// Operating temperature of the stepper (the rig or test temperature), degC.
        operating_temperature_c: f64,
        /// `s` in `log10 a_T = -s (T - T_ref)`, 1/degC.
        log10_time_shift_per_c: f64,
        /// `m` in `ln b_T = -m (T - T_ref)`, 1/degC.
        ln_modulus_shift_per_c: f64,
    },
    ChannelDelay {
        /// Lag of the force channel behind the displacement channel, s (negative: lead).
        force_lag_s: f64,
    },
    MovingMass {
        mass_kg: f64,
    },
    LoadTrainResonance {
        natural_frequency_hz: f64,
        damping_ratio: f64,
    },
    SpecimenDrift {
        clock: DriftClock,
        /// Relative change of the moduli per unit of the clock.
        rate_per_unit: f64,
        /// Its standard error (from the fit; 0 when stated by hand).
        rate_standard_error: f64,
        /// Clock value of the state modelled, relative to the reference instant (0: the
        /// element as it was at the reference instant).
        clock_position: f64,
    },
    SelfHeating {
        heat_capacity_j_per_k: f64,
        heat_transfer_w_per_k: f64,
        /// Rise above the ambient (the operating temperature) of the state modelled, K.
        temperature_rise_k: f64,
    },
    CyclicSoftening {
        /// `d`: the largest relative softening, far below the largest load, 0..1.
        softening_limit: f64,
        /// `F_s`: the force scale over which the softening sets in below it, N.
        force_scale_n: f64,
        /// `M`: the largest virgin force the specimen has carried in the state modelled,
        /// N (0: a virgin specimen).
        max_force_n: f64,
    },
}

impl Effect {
    pub fn name(&self) -> &'static str {
        match self {
            Effect::PreloadStiffening { .. } => EFFECT_NAMES[0],
            Effect::AmplitudeFriction { .. } => EFFECT_NAMES[1],
            Effect::FractionalDamping { .. } => EFFECT_NAMES[2],
            Effect::TemperatureShift { .. } => EFFECT_NAMES[3],
            Effect::ChannelDelay { .. } => EFFECT_NAMES[4],
            Effect::MovingMass { .. } => EFFECT_NAMES[5],
            Effect::LoadTrainResonance { .. } => EFFECT_NAMES[6],
            Effect::SpecimenDrift { .. } => EFFECT_NAMES[7],
            Effect::SelfHeating { .. } => EFFECT_NAMES[8],
            Effect::CyclicSoftening { .. } => EFFECT_NAMES[9],
        }
    }

    /// An artefact of the rig's measurement chain (never emulated, left out of the
    /// elastomer's own force): channel-delay, moving-mass, load-train-resonance.
    pub fn is_rig_artefact(&self) -> bool {
        matches!(
            self,
            Effect::ChannelDelay { .. }
                | Effect::MovingMass { .. }
                | Effect::LoadTrainResonance { .. }
        )
    }

    /// The parameters as they appear in a model file (per metre where stiffness-like).
    pub fn file_params(&self, length_m: f64) -> Vec<(&'static str, f64)> {
        match *self {
            Effect::PreloadStiffening { chi, p0_n } => vec![("chi", chi), ("p0_n", p0_n)],
            Effect::AmplitudeFriction {
                stiffness_n_per_m,
                slip_force_n,
                law,
            } => vec![
                ("stiffness_n_per_m2", stiffness_n_per_m / length_m),
                ("slip_force_n_per_m", slip_force_n / length_m),
                match law {
                    FrictionLaw::Iwan { slip_spread } => ("slip_spread", slip_spread),
                    FrictionLaw::Dahl { exponent } => ("dahl_exponent", exponent),
                },
            ],
            Effect::FractionalDamping {
                coefficient_ns_alpha_per_m,
                alpha,
            } => vec![
                (
                    "coefficient_ns_alpha_per_m2",
                    coefficient_ns_alpha_per_m / length_m,
                ),
                ("alpha", alpha),
            ],
            Effect::TemperatureShift {
                reference_temperature_c,
                operating_temperature_c,
                log10_time_shift_per_c,
                ln_modulus_shift_per_c,
            } => vec![
                ("reference_temperature_c", reference_temperature_c),
                ("operating_temperature_c", operating_temperature_c),
                ("log10_time_shift_per_c", log10_time_shift_per_c),
                ("ln_modulus_shift_per_c", ln_modulus_shift_per_c),
            ],
            Effect::ChannelDelay { force_lag_s } => vec![("force_lag_s", force_lag_s)],
            Effect::MovingMass { mass_kg } => vec![("mass_kg", mass_kg)],
            Effect::LoadTrainResonance {
                natural_frequency_hz,
                damping_ratio,
            } => vec![
                ("natural_frequency_hz", natural_frequency_hz),
                ("damping_ratio", damping_ratio),
            ],
            Effect::SpecimenDrift {
                rate_per_unit,
                rate_standard_error,
                clock_position,
                ..
            } => vec![
                ("rate_per_unit", rate_per_unit),
                ("rate_standard_error", rate_standard_error),
                ("clock_position", clock_position),
            ],
            Effect::SelfHeating {
                heat_capacity_j_per_k,
                heat_transfer_w_per_k,
                temperature_rise_k,
            } => vec![
                ("heat_capacity_j_per_k", heat_capacity_j_per_k),
                ("heat_transfer_w_per_k", heat_transfer_w_per_k),
                ("temperature_rise_k", temperature_rise_k),
            ],
            Effect::CyclicSoftening {
                softening_limit,
                force_scale_n,
                max_force_n,
            } => vec![
                ("softening_limit", softening_limit),
                ("force_scale_n", force_scale_n),
                ("max_force_n", max_force_n),
            ],
        }
    }

    /// The effect's text-valued keys in a model file.
    pub fn file_strings(&self) -> Vec<(&'static str, &'static str)> {
        match *self {
            Effect::SpecimenDrift { clock, .. } => vec![("clock", clock.name())],
            _ => Vec::new(),
        }
    }
}

/// Validates `[[effect]]` tables (`origin` names the file in errors).
pub fn parse_effects(
    tables: &[toml::Table],
    length_m: f64,
    origin: &str,
) -> Result<Vec<Effect>, ModelFileError> {
    let mut effects: Vec<Effect> = Vec::with_capacity(tables.len());
    for (index, table) in tables.iter().enumerate() {
        let effect = parse_effect(table, length_m, origin, index)?;
        if effects.iter().any(|e| e.name() == effect.name()) {
            return Err(ModelFileError {
                path: origin.to_string(),
                message: format!(
                    "[[effect]] {index}: effect \"{}\" appears twice",
                    effect.name()
                ),
            });
        }
        effects.push(effect);
    }
    Ok(effects)
}

fn parse_effect(
    table: &toml::Table,
    length_m: f64,
    origin: &str,
    index: usize,
) -> Result<Effect, ModelFileError> {
    let err = |message: String| ModelFileError {
        path: origin.to_string(),
        message: format!("[[effect]] {index}: {message}"),
    };
    let name = match table.get("name") {
        Some(toml::Value::String(s)) => s.clone(),
        Some(other) => return Err(err(format!("key `name` = {other}: expected a string"))),
        None => {
            return Err(err(format!(
                "missing key `name`: expected one of {}",
                EFFECT_NAMES.join(", ")
            )))
        }
    };
    let keys: &[&str] = match name.as_str() {
        "preload-stiffening" => &["chi", "p0_n"],
        "amplitude-friction" => &[
            "stiffness_n_per_m2",
            "slip_force_n_per_m",
            "slip_spread",
            "dahl_exponent",
        ],
        "fractional-damping" => &["coefficient_ns_alpha_per_m2", "alpha"],
        "temperature-shift" => &[
            "reference_temperature_c",
            "operating_temperature_c",
            "log10_time_shift_per_c",
            "ln_modulus_shift_per_c",
        ],
        "channel-delay" => &["force_lag_s"],
        "moving-mass" => &["mass_kg"],
        "load-train-resonance" => &["natural_frequency_hz", "damping_ratio"],
        "specimen-drift" => &[
            "clock",
            "rate_per_unit",
            "rate_standard_error",
            "clock_position",
        ],
        "self-heating" => &[
            "heat_capacity_j_per_k",
            "heat_transfer_w_per_k",
            "temperature_rise_k",
        ],
        "cyclic-softening" => &["softening_limit", "force_scale_n", "max_force_n"],
        other => {
            return Err(err(format!(
                "key `name` = \"{other}\": expected one of {}",
                EFFECT_NAMES.join(", ")
            )))
        }
    };
    for key in table.keys() {
        if key != "name" && key != "description" && !keys.contains(&key.as_str()) {
            return Err(err(format!(
                "unknown key `{key}` for effect \"{name}\": valid keys are {}",
                keys.join(", ")
            )));
        }
    }
    let number = |key: &str| -> Result<f64, ModelFileError> {
        match table.get(key) {
            None => Err(err(format!(
                "missing key `{key}` (required for effect \"{name}\")"
            ))),
            Some(toml::Value::Float(x)) if x.is_finite() => Ok(*x),
            Some(toml::Value::Integer(i)) => Ok(*i as f64),
            Some(other) => Err(err(format!(
                "key `{key}` = {other}: expected a finite number"
            ))),
        }
    };
    let positive = |key: &str| -> Result<f64, ModelFileError> {
        let x = number(key)?;
        if x > 0.0 {
            Ok(x)
        } else {
            Err(err(format!("key `{key}` = {x}: must be positive")))
        }
    };
    Ok(match name.as_str() {
        "preload-stiffening" => {
            let chi = number("chi")?;
            if !(0.0..1.0).contains(&chi) {
                return Err(err(format!("key `chi` = {chi}: must be in [0, 1)")));
            }
            Effect::PreloadStiffening {
                chi,
                p0_n: positive("p0_n")?,
            }
        }
        "amplitude-friction" => {
            let law = match (table.contains_key("slip_spread"), table.contains_key("dahl_exponent")) {
                (true, true) | (false, false) => {
                    return Err(err(
                        "effect \"amplitude-friction\" needs exactly one of `slip_spread` (Iwan element) and `dahl_exponent` (generalised Dahl element)".into(),
                    ))
                }
                (true, false) => {
                    let slip_spread = number("slip_spread")?;
                    if !(0.0..=SLIP_SPREAD_LIMIT).contains(&slip_spread) {
                        return Err(err(format!(
                            "key `slip_spread` = {slip_spread}: must be in [0, {SLIP_SPREAD_LIMIT}]"
                        )));
                    }
                    FrictionLaw::Iwan { slip_spread }
                }
                (false, true) => {
                    let exponent = number("dahl_exponent")?;
                    let (lo, hi) = DAHL_EXPONENT_RANGE;
                    if !(lo..=hi).contains(&exponent) {
                        return Err(err(format!(
                            "key `dahl_exponent` = {exponent}: must be in [{lo}, {hi}]"
                        )));
                    }
                    FrictionLaw::Dahl { exponent }
                }
            };
            Effect::AmplitudeFriction {
                stiffness_n_per_m: positive("stiffness_n_per_m2")? * length_m,
                slip_force_n: positive("slip_force_n_per_m")? * length_m,
                law,
            }
        }
        "fractional-damping" => {
            let alpha = number("alpha")?;
            if !(alpha > 0.0 && alpha < 1.0) {
                return Err(err(format!("key `alpha` = {alpha}: must be in (0, 1)")));
            }
            Effect::FractionalDamping {
                coefficient_ns_alpha_per_m: positive("coefficient_ns_alpha_per_m2")? * length_m,
                alpha,
            }
        }
        "temperature-shift" => Effect::TemperatureShift {
            reference_temperature_c: number("reference_temperature_c")?,
            operating_temperature_c: number("operating_temperature_c")?,
            log10_time_shift_per_c: number("log10_time_shift_per_c")?,
            ln_modulus_shift_per_c: number("ln_modulus_shift_per_c")?,
        },
        "channel-delay" => Effect::ChannelDelay {
            force_lag_s: number("force_lag_s")?,
        },
        "load-train-resonance" => {
            let damping_ratio = positive("damping_ratio")?;
            Effect::LoadTrainResonance {
                natural_frequency_hz: positive("natural_frequency_hz")?,
                damping_ratio,
            }
        }
        "specimen-drift" => {
            let clock = match table.get("clock") {
                Some(toml::Value::String(c)) => DriftClock::from_name(c).ok_or_else(|| {
                    err(format!(
                        "key `clock` = \"{c}\": expected one of test-order, time, dissipated-energy"
                    ))
                })?,
                Some(other) => {
                    return Err(err(format!("key `clock` = {other}: expected a string")))
                }
                None => {
                    return Err(err(
                        "missing key `clock` (required for effect \"specimen-drift\"): one of test-order, time, dissipated-energy".into(),
                    ))
                }
            };
            let effect = Effect::SpecimenDrift {
                clock,
                rate_per_unit: number("rate_per_unit")?,
                rate_standard_error: if table.contains_key("rate_standard_error") {
                    number("rate_standard_error")?
                } else {
                    0.0
                },
                clock_position: if table.contains_key("clock_position") {
                    number("clock_position")?
                } else {
                    0.0
                },
            };
            if drift_factor(&effect) <= DRIFT_FACTOR_FLOOR {
                return Err(err(format!(
                    "rate_per_unit x clock_position leaves a modulus factor below {DRIFT_FACTOR_FLOOR}"
                )));
            }
            effect
        }
        "self-heating" => Effect::SelfHeating {
            heat_capacity_j_per_k: positive("heat_capacity_j_per_k")?,
            heat_transfer_w_per_k: positive("heat_transfer_w_per_k")?,
            temperature_rise_k: if table.contains_key("temperature_rise_k") {
                number("temperature_rise_k")?
            } else {
                0.0
            },
        },
        "cyclic-softening" => {
            let softening_limit = number("softening_limit")?;
            if !(0.0..1.0).contains(&softening_limit) {
                return Err(err(format!(
                    "key `softening_limit` = {softening_limit}: must be in [0, 1)"
                )));
            }
            Effect::CyclicSoftening {
                softening_limit,
                force_scale_n: positive("force_scale_n")?,
                max_force_n: if table.contains_key("max_force_n") {
                    number("max_force_n")?
                } else {
                    0.0
                },
            }
        }
        _ => Effect::MovingMass {
            mass_kg: number("mass_kg")?,
        },
    })
}

/// A baseline element plus effects: what a model file with `[[effect]]` tables describes.
#[derive(Debug, Clone, PartialEq)]
pub struct AugmentedModel {
    pub element: ElementModel,
    pub length_m: f64,
    pub effects: Vec<Effect>,
}

impl AugmentedModel {
    /// Validates the effect tables of a parsed model file.
    pub fn from_spec(spec: &ModelSpec, origin: &str) -> Result<AugmentedModel, ModelFileError> {
        let effects = parse_effects(&spec.effect_tables, spec.length_m, origin)?;
        let model = AugmentedModel {
            element: spec.element,
            length_m: spec.length_m,
            effects,
        };
        if model.element.zener().is_none() && model.find("preload-stiffening").is_some() {
            return Err(ModelFileError {
                path: origin.to_string(),
                message: "effect \"preload-stiffening\" needs a Zener element (form \"consistent\" or \"paper\")".into(),
            });
        }
        Ok(model)
    }

    pub fn find(&self, name: &str) -> Option<&Effect> {
        self.effects.iter().find(|e| e.name() == name)
    }

    /// The same model at another operating temperature (no-op without temperature-shift).
    pub fn at_temperature(&self, temperature_c: f64) -> AugmentedModel {
        let mut out = self.clone();
        for effect in &mut out.effects {
            if let Effect::TemperatureShift {
                operating_temperature_c,
                ..
            } = effect
            {
                *operating_temperature_c = temperature_c;
            }
        }
        out
    }

    /// Modulus factor `b_T` and time factor `a_T` at the operating temperature plus the
    /// self-heating rise.
    pub fn temperature_factors(&self) -> (f64, f64) {
        let rise_k = self.temperature_rise_k();
        let (dt_c, m, s) = self.temperature_law(rise_k);
        ((-m * dt_c).exp(), 10f64.powf(-s * dt_c))
    }

    /// Self-heating rise of the state modelled, K (0 without `self-heating`).
    pub fn temperature_rise_k(&self) -> f64 {
        match self.find("self-heating") {
            Some(&Effect::SelfHeating {
                temperature_rise_k, ..
            }) => temperature_rise_k,
            _ => 0.0,
        }
    }

    /// Temperature difference from the law's reference, and the law's modulus and time
    /// slopes: `temperature-shift`'s, else (self-heating alone) the stated default law.
    pub fn temperature_law(&self, rise_k: f64) -> (f64, f64, f64) {
        match self.find("temperature-shift") {
            Some(&Effect::TemperatureShift {
                reference_temperature_c,
                operating_temperature_c,
                log10_time_shift_per_c,
                ln_modulus_shift_per_c,
            }) => (
                operating_temperature_c - reference_temperature_c + rise_k,
                ln_modulus_shift_per_c,
                log10_time_shift_per_c,
            ),
            _ if self.find("self-heating").is_some() => (
                rise_k,
                super::thermal::DEFAULT_LN_MODULUS_SHIFT_PER_C,
                super::thermal::DEFAULT_LOG10_TIME_SHIFT_PER_C,
            ),
            _ => (0.0, 0.0, 0.0),
        }
    }

    /// The modulus factor of `specimen-drift` at its clock position (1 without it).
    pub fn drift_factor(&self) -> f64 {
        self.find("specimen-drift").map_or(1.0, drift_factor)
    }

    /// The element with preload-stiffening and temperature-shift folded into its parameters.
    pub fn effective_element(&self) -> ElementModel {
        let (modulus_factor, time_factor) = self.temperature_factors();
        let mut element = self.element;
        match &mut element {
            ElementModel::Consistent(p) | ElementModel::Paper(p) => {
                if let Some(&Effect::PreloadStiffening { chi, p0_n }) =
                    self.find("preload-stiffening")
                {
                    p.chi = chi;
                    p.p0_n = p0_n;
                }
                let drift = self.drift_factor();
                p.k1_0_n_per_m *= modulus_factor * drift;
                p.k2_0_n_per_m *= modulus_factor * drift;
                p.c2_0_ns_per_m *= modulus_factor * time_factor * drift;
                // P0 is a force scale: with softer moduli the same preload strains more,
                // but the paper's Eq. 1 is in force, so it stays.
            }
            ElementModel::KelvinVoigt(p) => {
                let drift = self.drift_factor();
                p.k_n_per_m *= modulus_factor * drift;
                p.c_ns_per_m *= modulus_factor * time_factor * drift;
            }
        }
        element
    }

    /// Model file text (SPEC 2.3) with one `[[effect]]` table per effect.
    pub fn render_toml(&self, header: &str) -> String {
        let mut out = render_model_toml(&self.element, self.length_m, header);
        for effect in &self.effects {
            out.push_str(&format!("\n[[effect]]\nname = \"{}\"\n", effect.name()));
            for (key, value) in effect.file_strings() {
                out.push_str(&format!("{key} = \"{value}\"\n"));
            }
            for (key, value) in effect.file_params(self.length_m) {
                out.push_str(&format!("{key} = {value:?}\n"));
            }
        }
        out
    }
}

/// The rig artefacts of a model, applied to force spectra: `F_meas(w) = e^{-i w tau}
/// H(i w) (F(w) - m w^2 Z(w))` (channel delay, load-train resonance, moving mass).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RigArtefacts {
    pub mass_kg: f64,
    pub lag_s: f64,
    /// Natural frequency (Hz) and damping ratio of the load train.
    pub resonance: Option<(f64, f64)>,
}

impl RigArtefacts {
    pub fn is_none(&self) -> bool {
        self.mass_kg == 0.0 && self.lag_s == 0.0 && self.resonance.is_none()
    }

    /// The measured force component at `w` rad/s for the element's `force` and the
    /// displacement `z` there (complex amplitudes as (re, im)).
    pub fn measured(&self, w: f64, force: (f64, f64), z: (f64, f64)) -> (f64, f64) {
        let mut f = (
            force.0 - self.mass_kg * w * w * z.0,
            force.1 - self.mass_kg * w * w * z.1,
        );
        if let Some((fn_hz, zeta)) = self.resonance {
            let h = load_train_transfer(fn_hz, zeta, w);
            f = (f.0 * h.0 - f.1 * h.1, f.0 * h.1 + f.1 * h.0);
        }
        if self.lag_s != 0.0 {
            let (s, c) = (-w * self.lag_s).sin_cos();
            f = (f.0 * c - f.1 * s, f.0 * s + f.1 * c);
        }
        f
    }
}

impl AugmentedModel {
    /// The model's rig artefacts.
    pub fn rig_artefacts(&self) -> RigArtefacts {
        let mut out = RigArtefacts::default();
        for effect in &self.effects {
            match *effect {
                Effect::MovingMass { mass_kg } => out.mass_kg = mass_kg,
                Effect::ChannelDelay { force_lag_s } => out.lag_s = force_lag_s,
                Effect::LoadTrainResonance {
                    natural_frequency_hz,
                    damping_ratio,
                } => out.resonance = Some((natural_frequency_hz, damping_ratio)),
                _ => {}
            }
        }
        out
    }
}

/// Which effects a `ModelStepper` includes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StepperMode {
    /// The elastomer's own force: channel-delay and moving-mass are left out.
    Emulation,
    /// What a lab rig records: every effect.
    Measurement,
}

/// Number of Maxwell branches realising the springpot (4 per decade, 1e-2 .. 1e4 Hz).
pub const SPRINGPOT_BRANCHES: usize = 25;
const SPRINGPOT_LOWEST_RATE_HZ: f64 = 1e-2;
const SPRINGPOT_BRANCHES_PER_DECADE: f64 = 4.0;

/// Maxwell-bank realisation of a springpot `c (i W)^alpha`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpringpotBank {
    pub rates_per_s: [f64; SPRINGPOT_BRANCHES],
    pub stiffnesses_n_per_m: [f64; SPRINGPOT_BRANCHES],
    /// Spring standing in for the relaxation rates below the bank, N/m.
    pub low_tail_stiffness_n_per_m: f64,
    /// Dashpot standing in for the rates above the bank, N s/m.
    pub high_tail_damping_ns_per_m: f64,
}

impl SpringpotBank {
    pub fn new(coefficient: f64, alpha: f64) -> SpringpotBank {
        let du = std::f64::consts::LN_10 / SPRINGPOT_BRANCHES_PER_DECADE;
        let density = coefficient * (std::f64::consts::PI * alpha).sin() / std::f64::consts::PI;
        let mut rates = [0.0; SPRINGPOT_BRANCHES];
        let mut stiffnesses = [0.0; SPRINGPOT_BRANCHES];
        let r0 = 2.0 * std::f64::consts::PI * SPRINGPOT_LOWEST_RATE_HZ;
        for j in 0..SPRINGPOT_BRANCHES {
            let r = r0 * (j as f64 * du).exp();
            rates[j] = r;
            // c s^alpha = int_0^inf density r^(alpha-1) s/(s+r) dr, with dr = r d(ln r).
            stiffnesses[j] = density * r.powf(alpha) * du;
        }
        let r_low = r0 * (-0.5 * du).exp();
        let r_high = r0 * ((SPRINGPOT_BRANCHES as f64 - 0.5) * du).exp();
        SpringpotBank {
            rates_per_s: rates,
            stiffnesses_n_per_m: stiffnesses,
            low_tail_stiffness_n_per_m: density * r_low.powf(alpha) / alpha,
            high_tail_damping_ns_per_m: density * r_high.powf(alpha - 1.0) / (1.0 - alpha),
        }
    }

    /// Complex modulus of the bank at circular frequency `omega` (for checks and plots).
    pub fn modulus(&self, omega_rad_per_s: f64) -> (f64, f64) {
        let mut re = self.low_tail_stiffness_n_per_m;
        let mut im = self.high_tail_damping_ns_per_m * omega_rad_per_s;
        for (r, k) in self.rates_per_s.iter().zip(&self.stiffnesses_n_per_m) {
            // k i W / (r + i W)
            let den = r * r + omega_rad_per_s * omega_rad_per_s;
            re += k * omega_rad_per_s * omega_rad_per_s / den;
            im += k * omega_rad_per_s * r / den;
        }
        (re, im)
    }
}

/// A linear state jumps to its periodic solution only when a period takes at least this
/// much off it (`1 - decay^period`); slower ones keep their state.
const MIN_PERIODIC_DECAY: f64 = 1e-6;

/// A stepper's linear states at one instant (`ModelStepper::linear_state`).
#[derive(Debug, Clone, Copy)]
pub struct LinearState {
    maxwell_n: f64,
    bank_n: [f64; SPRINGPOT_BRANCHES],
}

#[derive(Debug, Clone, Copy)]
struct BankState {
    rates_per_s: [f64; SPRINGPOT_BRANCHES],
    decay: [f64; SPRINGPOT_BRANCHES],
    /// `k_j phi1(r_j dt)`: branch force per unit displacement increment over a step.
    gain: [f64; SPRINGPOT_BRANCHES],
    force_n: [f64; SPRINGPOT_BRANCHES],
    /// `1 / c_j = r_j / k_j`: a branch dissipates `F_j^2 / c_j`.
    inverse_damping: [f64; SPRINGPOT_BRANCHES],
    low_tail_stiffness_n_per_m: f64,
    high_tail_damping_ns_per_m: f64,
    /// The springpot's order.
    alpha: f64,
    /// Its coefficient now over the one it was built with (self-heating retunes it).
    scale: f64,
}

impl BankState {
    /// Scales every branch's stiffness (and the tails) by `ratio` without a force jump:
    /// the branch forces are kept, and the low tail's spring is re-anchored so it carries
    /// the same force at `z_m`. Returns the new anchor.
    fn rescale(&mut self, ratio: f64, z_m: f64, anchor_m: f64) -> f64 {
        for j in 0..SPRINGPOT_BRANCHES {
            self.gain[j] *= ratio;
            self.inverse_damping[j] /= ratio;
        }
        self.low_tail_stiffness_n_per_m *= ratio;
        self.high_tail_damping_ns_per_m *= ratio;
        self.scale *= ratio;
        z_m - (z_m - anchor_m) / ratio
    }
}

/// Number of Jenkins elements of the Iwan friction element.
pub const IWAN_ELEMENTS: usize = 12;

/// Iwan element: per-slider stiffness (N/m), slip forces (N) and current forces (N).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IwanElement {
    pub slider_stiffness_n_per_m: f64,
    pub slip_forces_n: [f64; IWAN_ELEMENTS],
    pub forces_n: [f64; IWAN_ELEMENTS],
}

impl IwanElement {
    /// At rest (all sliders unloaded).
    pub fn new(stiffness_n_per_m: f64, slip_force_n: f64, slip_spread: f64) -> IwanElement {
        // Slider j sits at the standard-normal quantile (j + 1/2) / N of the spread.
        let mut weights = [0.0; IWAN_ELEMENTS];
        for (j, w) in weights.iter_mut().enumerate() {
            let p = (j as f64 + 0.5) / IWAN_ELEMENTS as f64;
            *w = (slip_spread * normal_quantile(p)).exp();
        }
        let total: f64 = weights.iter().sum();
        let mut slip_forces_n = [0.0; IWAN_ELEMENTS];
        for (f, w) in slip_forces_n.iter_mut().zip(&weights) {
            *f = slip_force_n * w / total;
        }
        IwanElement {
            slider_stiffness_n_per_m: stiffness_n_per_m / IWAN_ELEMENTS as f64,
            slip_forces_n,
            forces_n: [0.0; IWAN_ELEMENTS],
        }
    }

    /// Advances by a displacement increment; returns the total friction force.
    #[inline]
    pub fn step(&mut self, dz_m: f64) -> f64 {
        let mut total = 0.0;
        for (f, limit) in self.forces_n.iter_mut().zip(&self.slip_forces_n) {
            // max/min rather than clamp: never panics, whatever the parameters.
            *f = (*f + self.slider_stiffness_n_per_m * dz_m)
                .min(*limit)
                .max(-limit);
            total += *f;
        }
        total
    }

    pub fn force_n(&self) -> f64 {
        self.forces_n.iter().sum()
    }
}

/// Generalised Dahl element: `dF/dz = k |1 - F sgn(dz) / F_s|^n`, integrated exactly over
/// a monotone step: with `u = 1 - F sgn(dz) / F_s` and `x = k |dz| / F_s`,
/// `u' = u e^-x` (n = 1), `u'^(1-n) = u^(1-n) + (n - 1) x` (n > 1), and
/// `u'^(1-n) = max(u^(1-n) - (1 - n) x, 0)` (n < 1: full slip within a finite step).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DahlElement {
    pub stiffness_n_per_m: f64,
    pub slip_force_n: f64,
    pub exponent: f64,
    pub force_n: f64,
    /// `u^(1-n)` after the last step, the direction it was taken in and the force it
    /// gave: while the direction holds, the next step needs no power to recover it.
    carried: (f64, f64, f64),
}

impl DahlElement {
    pub fn new(stiffness_n_per_m: f64, slip_force_n: f64, exponent: f64) -> DahlElement {
        DahlElement {
            stiffness_n_per_m,
            slip_force_n,
            exponent,
            force_n: 0.0,
            carried: (0.0, 0.0, f64::NAN),
        }
    }

    #[inline]
    pub fn step(&mut self, dz_m: f64) -> f64 {
        if dz_m == 0.0 || self.slip_force_n <= 0.0 {
            return self.force_n;
        }
        let sign = dz_m.signum();
        let x = self.stiffness_n_per_m * dz_m.abs() / self.slip_force_n;
        let n = self.exponent;
        let u = if n == 1.0 {
            let u0 = (1.0 - sign * self.force_n / self.slip_force_n).max(0.0);
            u0 * (-x).exp()
        } else {
            let (v_last, sign_last, force_last) = self.carried;
            let v0 = if sign == sign_last && self.force_n == force_last {
                v_last
            } else {
                // u0 = 0 with n > 1: 0^(1-n) = inf, and inf^(1/(1-n)) = 0 stays 0.
                (1.0 - sign * self.force_n / self.slip_force_n)
                    .max(0.0)
                    .powf(1.0 - n)
            };
            let v = if n > 1.0 {
                v0 + (n - 1.0) * x
            } else {
                (v0 - (1.0 - n) * x).max(0.0)
            };
            self.carried = (v, sign, f64::NAN);
            v.powf(1.0 / (1.0 - n))
        };
        self.force_n = sign * self.slip_force_n * (1.0 - u);
        if n != 1.0 {
            self.carried.2 = self.force_n;
        }
        self.force_n
    }
}

/// The friction element a `ModelStepper` runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FrictionElement {
    Iwan(IwanElement),
    Dahl(DahlElement),
}

impl FrictionElement {
    pub fn new(stiffness_n_per_m: f64, slip_force_n: f64, law: FrictionLaw) -> FrictionElement {
        match law {
            FrictionLaw::Iwan { slip_spread } => FrictionElement::Iwan(IwanElement::new(
                stiffness_n_per_m,
                slip_force_n,
                slip_spread,
            )),
            FrictionLaw::Dahl { exponent } => {
                FrictionElement::Dahl(DahlElement::new(stiffness_n_per_m, slip_force_n, exponent))
            }
        }
    }

    #[inline]
    pub fn step(&mut self, dz_m: f64) -> f64 {
        match self {
            FrictionElement::Iwan(e) => e.step(dz_m),
            FrictionElement::Dahl(e) => e.step(dz_m),
        }
    }

    pub fn force_n(&self) -> f64 {
        match self {
            FrictionElement::Iwan(e) => e.force_n(),
            FrictionElement::Dahl(e) => e.force_n,
        }
    }

    /// Unloads the element (no allocation).
    pub fn unload(&mut self) {
        match self {
            FrictionElement::Iwan(e) => e.forces_n = [0.0; IWAN_ELEMENTS],
            FrictionElement::Dahl(e) => e.force_n = 0.0,
        }
    }
}

/// The modulus factor a `specimen-drift` gives at its clock position (floored).
pub fn drift_factor(effect: &Effect) -> f64 {
    match *effect {
        Effect::SpecimenDrift {
            rate_per_unit,
            clock_position,
            ..
        } => (1.0 + rate_per_unit * clock_position).max(DRIFT_FACTOR_FLOOR),
        _ => 1.0,
    }
}

/// Load-train transfer `H(i w) = 1 / (1 - r^2 + 2 i zeta r)`, `r = w / w_n`.
pub fn load_train_transfer(natural_frequency_hz: f64, damping_ratio: f64, w: f64) -> (f64, f64) {
    let r = w / (2.0 * std::f64::consts::PI * natural_frequency_hz);
    let (re, im) = (1.0 - r * r, 2.0 * damping_ratio * r);
    let den = re * re + im * im;
    (re / den.max(1e-300), -im / den.max(1e-300))
}

/// Second-order section (bilinear transform, prewarped at the natural frequency) of the
/// load-train resonance, in measurement mode.
#[derive(Debug, Clone, Copy)]
struct ResonanceFilter {
    b: [f64; 3],
    a: [f64; 2],
    x: [f64; 2],
    y: [f64; 2],
}

impl ResonanceFilter {
    /// `None` when the resonance is too close to or above the step's Nyquist frequency to
    /// be represented (it then plays no part in what the step can resolve).
    fn new(natural_frequency_hz: f64, damping_ratio: f64, dt_s: f64) -> Option<ResonanceFilter> {
        let w = 2.0 * std::f64::consts::PI * natural_frequency_hz;
        if w * dt_s >= 2.5 {
            return None;
        }
        let k = w / (0.5 * w * dt_s).tan();
        let a0 = k * k + 2.0 * damping_ratio * w * k + w * w;
        Some(ResonanceFilter {
            b: [w * w / a0, 2.0 * w * w / a0, w * w / a0],
            a: [
                2.0 * (w * w - k * k) / a0,
                (k * k - 2.0 * damping_ratio * w * k + w * w) / a0,
            ],
            x: [0.0; 2],
            y: [0.0; 2],
        })
    }

    fn fill(&mut self, force_n: f64) {
        self.x = [force_n; 2];
        self.y = [force_n; 2];
    }

    #[inline]
    fn step(&mut self, x: f64) -> f64 {
        let y = self.b[0] * x + self.b[1] * self.x[0] + self.b[2] * self.x[1]
            - self.a[0] * self.y[0]
            - self.a[1] * self.y[1];
        self.x = [x, self.x[0]];
        self.y = [y, self.y[0]];
        y
    }
}

/// Mullins state of a stepper: the law's constants and the largest virgin force so far.
#[derive(Debug, Clone, Copy)]
struct SofteningState {
    limit: f64,
    scale_n: f64,
    max_force_n: f64,
}

impl SofteningState {
    /// `eta` and `d eta / d F_v` at virgin force `f`, after raising the maximum to it.
    #[inline]
    fn factor(&mut self, f: f64) -> (f64, f64) {
        if f > self.max_force_n {
            self.max_force_n = f;
        }
        self.eval(f)
    }

    /// `eta` and `d eta / d F_v` at virgin force `f` (at most the maximum).
    #[inline]
    fn eval(&self, f: f64) -> (f64, f64) {
        // tanh(x) for x >= 0 through one `exp` (`f64::tanh` goes through `expm1`, over
        // a fifth of `diagnose`'s time on a Mullins campaign): near x = 0 the difference
        // loses relative but not absolute precision (~1e-16), and `eta` needs only that.
        let e = (-2.0 * (self.max_force_n - f).max(0.0) / self.scale_n).exp();
        let t = (1.0 - e) / (1.0 + e);
        (
            1.0 - self.limit * t,
            self.limit * (1.0 - t * t) / self.scale_n,
        )
    }
}

/// Self-heating state of a stepper: the thermal state, the element at the rise it was
/// built for, the temperature law's slopes and the rise the element is tuned to.
#[derive(Debug, Clone, Copy)]
struct SelfHeatingRuntime {
    state: super::thermal::ThermalState,
    base_element: ElementModel,
    base_rise_k: f64,
    tuned_rise_k: f64,
    ln_modulus_shift_per_c: f64,
    log10_time_shift_per_c: f64,
    /// False offline (a campaign's schedule sets the rise per test).
    dynamic: bool,
}

impl SelfHeatingRuntime {
    /// The element at `rise_k` (relative factors from the base element's rise).
    fn element_at(&self, rise_k: f64) -> ElementModel {
        let d = rise_k - self.base_rise_k;
        let modulus = (-self.ln_modulus_shift_per_c * d).exp();
        let time = 10f64.powf(-self.log10_time_shift_per_c * d);
        let mut element = self.base_element;
        match &mut element {
            ElementModel::Consistent(p) | ElementModel::Paper(p) => {
                p.k1_0_n_per_m *= modulus;
                p.k2_0_n_per_m *= modulus;
                p.c2_0_ns_per_m *= modulus * time;
            }
            ElementModel::KelvinVoigt(p) => {
                p.k_n_per_m *= modulus;
                p.c_ns_per_m *= modulus * time;
            }
        }
        element
    }

    /// A springpot's coefficient at `rise_k` over its coefficient at the base rise:
    /// `c (a_T s)^alpha b_T` with the law's modulus and time factors.
    fn springpot_scale_at(&self, rise_k: f64, alpha: f64) -> f64 {
        let d = rise_k - self.base_rise_k;
        (-self.ln_modulus_shift_per_c * d).exp()
            * 10f64.powf(-self.log10_time_shift_per_c * d).powf(alpha)
    }
}

/// Standard normal quantile (Acklam's rational approximation, |error| < 1.2e-9).
fn normal_quantile(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969683028665376e1,
        2.209460984245205e2,
        -2.759285104469687e2,
        1.38357751867269e2,
        -3.066479806614716e1,
        2.506628277459239,
    ];
    const B: [f64; 5] = [
        -5.447609879822406e1,
        1.615858368580409e2,
        -1.556989798598866e2,
        6.680131188771972e1,
        -1.328068155288572e1,
    ];
    const C: [f64; 6] = [
        -7.784894002430293e-3,
        -3.223964580411365e-1,
        -2.400758277161838,
        -2.549732539343734,
        4.374664141464968,
        2.938163982698783,
    ];
    const D: [f64; 4] = [
        7.784695709041462e-3,
        3.224671290700398e-1,
        2.445134137142996,
        3.754408661907416,
    ];
    let p_low = 0.02425;
    if p < p_low {
        let q = (-2.0 * p.ln()).sqrt();
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    } else if p <= 1.0 - p_low {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    } else {
        -normal_quantile(1.0 - p)
    }
}

/// The springpot coefficient at the model's temperature: `c (a_T s)^alpha b_T`, the
/// temperature shift scaling the coefficient (`factors` = (modulus, time) factors).
fn shifted_springpot_coefficient(coefficient: f64, alpha: f64, factors: (f64, f64)) -> f64 {
    coefficient * factors.0 * factors.1.powf(alpha)
}

/// A model's local linear law (see `ModelStepper::local_law`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LocalLinearLaw {
    pub force_n: f64,
    pub displacement_m: f64,
    pub velocity_m_per_s: f64,
    pub stiffness_n_per_m: f64,
    pub damping_ns_per_m: f64,
    pub force_rate_n_per_s: f64,
    pub stiffness_slope_n_per_m2: f64,
}

/// Force-from-displacement stepper of an augmented model at a fixed step `dt`.
#[derive(Debug, Clone)]
pub struct ModelStepper {
    base: ForceStepper,
    dt_s: f64,
    friction: Option<FrictionElement>,
    bank: Option<BankState>,
    /// Moving mass in the force (0 in emulation mode), kg.
    mass_kg: f64,
    /// Starting displacement (the springpot's low-tail spring acts about it), m.
    z_start_m: f64,
    /// Last four displacements, newest first (for a second-order backward `z''`).
    z_history_m: [f64; 4],
    /// Force lag in steps (0 in emulation mode).
    lag_steps: f64,
    /// Ring buffer of past forces before the channel delay (allocated in `new` only).
    delay_line: Vec<f64>,
    delay_head: usize,
    force_n: f64,
    /// Circular frequency of the local law (`with_law_frequency`), rad/s.
    law_omega_rad_per_s: f64,
    /// Stiffness and damping the linear effects (friction sliders sticking, springpot
    /// bank) add to the local law at that frequency.
    law_effects_n_per_m: f64,
    law_effects_ns_per_m: f64,
    /// The springpot bank's share of those (retuned with it).
    law_bank_n_per_m: f64,
    law_bank_ns_per_m: f64,
    /// Load-train resonance (measurement mode only).
    resonance: Option<ResonanceFilter>,
    self_heating: Option<SelfHeatingRuntime>,
    softening: Option<SofteningState>,
}

impl ModelStepper {
    /// A stepper with step `dt_s`, starting at rest in static equilibrium at `z0_m`.
    pub fn new(model: &AugmentedModel, mode: StepperMode, dt_s: f64, z0_m: f64) -> ModelStepper {
        let base = ForceStepper::new(model.effective_element(), dt_s, z0_m);
        let (modulus_factor, time_factor) = model.temperature_factors();
        let mut friction = None;
        let mut bank = None;
        let mut mass_kg = 0.0;
        let mut lag_s = 0.0;
        let mut resonance = None;
        let mut self_heating = None;
        let mut softening = None;
        for effect in &model.effects {
            match *effect {
                Effect::AmplitudeFriction {
                    stiffness_n_per_m,
                    slip_force_n,
                    law,
                } => friction = Some(FrictionElement::new(stiffness_n_per_m, slip_force_n, law)),
                Effect::FractionalDamping {
                    coefficient_ns_alpha_per_m,
                    alpha,
                } => {
                    let coefficient = shifted_springpot_coefficient(
                        coefficient_ns_alpha_per_m,
                        alpha,
                        (modulus_factor, time_factor),
                    );
                    let springpot = SpringpotBank::new(coefficient, alpha);
                    let mut state = BankState {
                        rates_per_s: springpot.rates_per_s,
                        decay: [0.0; SPRINGPOT_BRANCHES],
                        gain: [0.0; SPRINGPOT_BRANCHES],
                        force_n: [0.0; SPRINGPOT_BRANCHES],
                        inverse_damping: [0.0; SPRINGPOT_BRANCHES],
                        low_tail_stiffness_n_per_m: springpot.low_tail_stiffness_n_per_m,
                        high_tail_damping_ns_per_m: springpot.high_tail_damping_ns_per_m,
                        alpha,
                        scale: 1.0,
                    };
                    for j in 0..SPRINGPOT_BRANCHES {
                        let x = springpot.rates_per_s[j] * dt_s;
                        state.decay[j] = (-x).exp();
                        state.gain[j] = springpot.stiffnesses_n_per_m[j] * phi_functions(x).0;
                        state.inverse_damping[j] =
                            springpot.rates_per_s[j] / springpot.stiffnesses_n_per_m[j].max(1e-300);
                    }
                    bank = Some(state);
                }
                Effect::MovingMass { mass_kg: m } if mode == StepperMode::Measurement => {
                    mass_kg = m
                }
                Effect::ChannelDelay { force_lag_s } if mode == StepperMode::Measurement => {
                    lag_s = force_lag_s
                }
                Effect::LoadTrainResonance {
                    natural_frequency_hz,
                    damping_ratio,
                } if mode == StepperMode::Measurement => {
                    resonance = ResonanceFilter::new(natural_frequency_hz, damping_ratio, dt_s)
                }
                Effect::SelfHeating {
                    heat_capacity_j_per_k,
                    heat_transfer_w_per_k,
                    temperature_rise_k,
                } => {
                    let (_, m, s) = model.temperature_law(temperature_rise_k);
                    self_heating = Some(SelfHeatingRuntime {
                        state: super::thermal::ThermalState::new(
                            heat_capacity_j_per_k,
                            heat_transfer_w_per_k,
                            dt_s,
                            temperature_rise_k,
                        ),
                        base_element: model.effective_element(),
                        base_rise_k: temperature_rise_k,
                        tuned_rise_k: temperature_rise_k,
                        ln_modulus_shift_per_c: m,
                        log10_time_shift_per_c: s,
                        dynamic: true,
                    })
                }
                Effect::CyclicSoftening {
                    softening_limit,
                    force_scale_n,
                    max_force_n,
                } => {
                    softening = Some(SofteningState {
                        limit: softening_limit,
                        scale_n: force_scale_n.max(1e-9),
                        max_force_n,
                    })
                }
                _ => {}
            }
        }
        let lag_steps = lag_s / dt_s;
        let capacity = if lag_steps > 0.0 {
            lag_steps.ceil() as usize + 2
        } else {
            2
        };
        let mut stepper = ModelStepper {
            base,
            dt_s,
            friction,
            bank,
            mass_kg,
            z_start_m: z0_m,
            z_history_m: [z0_m; 4],
            lag_steps,
            delay_line: vec![0.0; capacity],
            delay_head: 0,
            force_n: 0.0,
            law_omega_rad_per_s: 0.0,
            law_effects_n_per_m: 0.0,
            law_effects_ns_per_m: 0.0,
            law_bank_n_per_m: 0.0,
            law_bank_ns_per_m: 0.0,
            resonance,
            self_heating,
            softening,
        };
        let f0 = stepper.undelayed_force_n(z0_m);
        stepper.delay_line.fill(f0);
        if let Some(filter) = &mut stepper.resonance {
            filter.fill(f0);
        }
        stepper.force_n = f0;
        stepper
    }

    /// The states that are linear in themselves under a given input (the consistent form's
    /// Maxwell branch, the springpot's branches): what `jump_to_periodic` needs from one
    /// period earlier. `None` when the element has no such state to jump (paper form,
    /// Kelvin-Voigt) or the temperature moves (self-heating not frozen: the decays change).
    pub fn linear_state(&self) -> Option<LinearState> {
        if self.self_heating.is_some_and(|h| h.dynamic) {
            return None;
        }
        Some(LinearState {
            maxwell_n: self.base.maxwell_force_n()?,
            bank_n: self.bank.map_or([0.0; SPRINGPOT_BRANCHES], |b| b.force_n),
        })
    }

    /// After one period of `period_steps` steps of a periodic input begun at `start`
    /// (`linear_state`), puts the linear states on their periodic solution (each maps
    /// `f -> decay^period_steps f + c` over a period). The nonlinear states (friction,
    /// the Mullins maximum) are left to settle over further periods; the force output
    /// changes only from the next step on.
    pub fn jump_to_periodic(&mut self, start: &LinearState, period_steps: usize) {
        self.base
            .jump_maxwell_to_periodic(start.maxwell_n, period_steps, MIN_PERIODIC_DECAY);
        if let Some(bank) = &mut self.bank {
            for j in 0..SPRINGPOT_BRANCHES {
                let d = bank.decay[j].powi(period_steps as i32);
                // A branch too slow to move over a period keeps its state: `1 - d` would
                // amplify the rounding of its increment.
                if d < 1.0 - MIN_PERIODIC_DECAY {
                    bank.force_n[j] = (bank.force_n[j] - d * start.bank_n[j]) / (1.0 - d);
                }
            }
        }
    }

    /// Holds the self-heating rise at the model's `temperature_rise_k` (offline, where a
    /// campaign's schedule gives each test its rise).
    pub fn with_frozen_temperature(mut self) -> ModelStepper {
        if let Some(heating) = &mut self.self_heating {
            heating.dynamic = false;
        }
        self
    }

    /// The largest virgin force the element has carried (`cyclic-softening`), N (0
    /// without it).
    pub fn max_force_n(&self) -> f64 {
        self.softening.map_or(0.0, |s| s.max_force_n)
    }

    /// Self-heating rise of the element above its ambient now, K (0 without it).
    pub fn temperature_rise_k(&self) -> f64 {
        self.self_heating.map_or(0.0, |h| h.state.rise_k)
    }

    /// Power dissipated in the element's dashpots now (the Maxwell branch and the
    /// springpot bank; friction's is not counted), W.
    pub fn dissipated_power_w(&self, velocity_m_per_s: f64) -> f64 {
        let mut power = self.base.dashpot_power_w(velocity_m_per_s);
        if let Some(bank) = &self.bank {
            for j in 0..SPRINGPOT_BRANCHES {
                power += bank.force_n[j] * bank.force_n[j] * bank.inverse_damping[j];
            }
            power += bank.high_tail_damping_ns_per_m * velocity_m_per_s * velocity_m_per_s;
        }
        power
    }

    pub fn dt_s(&self) -> f64 {
        self.dt_s
    }

    /// Sets the frequency at which `local_law` matches the model's small-signal modulus
    /// (for a HIL rig: the specimen's resonance on the element, where a stall's transient
    /// rings). Computes the linear effects' share once; allocation-free afterwards.
    pub fn with_law_frequency(mut self, model: &AugmentedModel, frequency_hz: f64) -> ModelStepper {
        let omega = 2.0 * std::f64::consts::PI * frequency_hz;
        let (modulus_factor, time_factor) = model.temperature_factors();
        let (mut k, mut c) = (0.0, 0.0);
        for effect in &model.effects {
            match *effect {
                // Small oscillations about any state reverse every slider: all stick.
                Effect::AmplitudeFriction {
                    stiffness_n_per_m, ..
                } => k += stiffness_n_per_m,
                Effect::FractionalDamping {
                    coefficient_ns_alpha_per_m,
                    alpha,
                } => {
                    let coefficient = shifted_springpot_coefficient(
                        coefficient_ns_alpha_per_m,
                        alpha,
                        (modulus_factor, time_factor),
                    );
                    // At the bank's present scale (a self-heated element's retuned bank).
                    let scale = self.bank.map_or(1.0, |b| b.scale);
                    let (re, im) = SpringpotBank::new(coefficient * scale, alpha).modulus(omega);
                    k += re;
                    self.law_bank_n_per_m = re;
                    if omega > 0.0 {
                        c += im / omega;
                        self.law_bank_ns_per_m = im / omega;
                    }
                }
                _ => {}
            }
        }
        self.law_omega_rad_per_s = omega;
        self.law_effects_n_per_m = k;
        self.law_effects_ns_per_m = c;
        self
    }

    /// The model's local linear law at its current state: force, displacement, velocity,
    /// stiffness, damping and force rate such that the force near that state is
    /// `F + k (z - z0) + c (v - v0) + r (t - t0)`. Stiffness and damping are the
    /// small-signal equivalent of the element at its current preload (paper Eq. 2 for the
    /// consistent form) at the law frequency, plus the linear effects' share; the rate is
    /// the relaxation of the Maxwell branches at fixed displacement. No allocation, no clock.
    #[inline]
    pub fn local_law(&self) -> LocalLinearLaw {
        let eq = equivalent(
            self.base.model(),
            self.base.operating_force_n(),
            self.law_omega_rad_per_s,
        );
        let [z0, z1, _, _] = self.z_history_m;
        let mut rate = self.base.relaxation_rate_n_per_s();
        if let Some(bank) = &self.bank {
            for j in 0..SPRINGPOT_BRANCHES {
                rate -= bank.rates_per_s[j] * bank.force_n[j];
            }
        }
        let mut c = if eq.c_eq_ns_per_m.is_finite() {
            eq.c_eq_ns_per_m
        } else {
            0.0
        };
        // Cyclic softening scales the element's force by eta(F_v): its stiffness by
        // `eta + F_v d eta / d F_v`, its damping and relaxation by eta.
        let mut k_eq = eq.k_eq_n_per_m;
        if let Some(softening) = &self.softening {
            let f = self.base.force_n();
            let (eta, slope) = softening.eval(f);
            k_eq *= eta + f * slope;
            c *= eta;
            rate *= eta;
        }
        // d k_eq / dz = k_eq chi dFs/dz / (P0 + Fs) in the consistent form (g(Fs) scales
        // every coefficient and dFs/dz = k1 g); other forms: left at 0 (linear law).
        let slope = match self.base.model() {
            ElementModel::Consistent(p) => {
                let fs = self.base.operating_force_n();
                let g = p.preload_factor(fs);
                eq.k_eq_n_per_m * p.chi * p.k1_0_n_per_m * g / (p.p0_n + fs).max(p.p0_n * 1e-6)
            }
            _ => 0.0,
        };
        LocalLinearLaw {
            stiffness_slope_n_per_m2: slope,
            force_n: self.force_n,
            displacement_m: z0,
            velocity_m_per_s: (z0 - z1) / self.dt_s,
            stiffness_n_per_m: k_eq + self.law_effects_n_per_m,
            damping_ns_per_m: c + self.law_effects_ns_per_m,
            force_rate_n_per_s: rate,
        }
    }

    /// Puts the model at rest in static equilibrium at `z_m` (relaxed branches, unloaded
    /// friction sliders, a filled delay line). Does not allocate: the emulator calls it
    /// on its first sample, inside the loop.
    pub fn reset_static(&mut self, z_m: f64) {
        self.base.reset_static(z_m);
        if let Some(friction) = &mut self.friction {
            friction.unload();
        }
        if let Some(bank) = &mut self.bank {
            bank.force_n = [0.0; SPRINGPOT_BRANCHES];
        }
        self.z_start_m = z_m;
        self.z_history_m = [z_m; 4];
        let f0 = self.undelayed_force_n(z_m);
        self.delay_line.fill(f0);
        self.delay_head = 0;
        if let Some(filter) = &mut self.resonance {
            filter.fill(f0);
        }
        self.force_n = f0;
    }

    /// Force of the last step (as returned by `step`), N.
    pub fn force_n(&self) -> f64 {
        self.force_n
    }

    fn undelayed_force_n(&mut self, z_m: f64) -> f64 {
        let mut force = self.base.force_n();
        if let Some(softening) = &mut self.softening {
            force *= softening.factor(force).0;
        }
        if let Some(friction) = &self.friction {
            force += friction.force_n();
        }
        if let Some(bank) = &self.bank {
            force += bank.low_tail_stiffness_n_per_m * (z_m - self.z_start_m);
            force += bank.force_n.iter().sum::<f64>();
        }
        force
    }

    /// Advances one step to displacement `z_m`; returns the force at the step's end.
    #[inline]
    pub fn step(&mut self, z_m: f64) -> (f64, StepFlags) {
        self.step_with_static_force(z_m, None)
    }

    /// `step` with the element's static force given (see
    /// `ForceStepper::step_with_static_force`): offline, for a periodic input.
    #[inline]
    pub fn step_with_static_force(
        &mut self,
        z_m: f64,
        static_force: Option<(f64, bool)>,
    ) -> (f64, StepFlags) {
        if !z_m.is_finite() {
            return (self.force_n, StepFlags::NONFINITE_INPUT);
        }
        let (mut force, flags) = self.base.step_with_static_force(z_m, static_force);
        if let Some(softening) = &mut self.softening {
            force *= softening.factor(force).0;
        }
        let z_prev = self.z_history_m[0];
        let dz = z_m - z_prev;
        if let Some(friction) = &mut self.friction {
            force += friction.step(dz);
        }
        if let Some(bank) = &mut self.bank {
            let mut branch_sum = 0.0;
            for j in 0..SPRINGPOT_BRANCHES {
                bank.force_n[j] = bank.decay[j] * bank.force_n[j] + bank.gain[j] * dz;
                branch_sum += bank.force_n[j];
            }
            // The low tail is a spring about the starting point (a springpot holds no
            // static force); the high tail is a dashpot on the step's mean velocity.
            force += branch_sum
                + bank.low_tail_stiffness_n_per_m * (z_m - self.z_start_m)
                + bank.high_tail_damping_ns_per_m * dz / self.dt_s;
        }
        self.z_history_m = [
            z_m,
            self.z_history_m[0],
            self.z_history_m[1],
            self.z_history_m[2],
        ];
        if self.mass_kg != 0.0 {
            force += self.mass_kg * self.acceleration_m_per_s2();
        }
        if let Some(filter) = &mut self.resonance {
            force = filter.step(force);
        }
        if self.lag_steps != 0.0 {
            force = self.delay(force);
        }
        self.force_n = force;
        if self.self_heating.is_some_and(|h| h.dynamic) {
            let power = self.dissipated_power_w(dz / self.dt_s);
            if let Some(heating) = &mut self.self_heating {
                let rise = heating.state.step(power);
                if (rise - heating.tuned_rise_k).abs() >= RETUNE_STEP_K {
                    heating.tuned_rise_k = rise;
                    self.base.retune(heating.element_at(rise));
                    // The springpot follows the same temperature law (as offline, where
                    // each test's rise shifts its coefficient).
                    if let Some(bank) = &mut self.bank {
                        let ratio = heating.springpot_scale_at(rise, bank.alpha) / bank.scale;
                        self.z_start_m = bank.rescale(ratio, z_m, self.z_start_m);
                        self.law_effects_n_per_m += self.law_bank_n_per_m * (ratio - 1.0);
                        self.law_effects_ns_per_m += self.law_bank_ns_per_m * (ratio - 1.0);
                        self.law_bank_n_per_m *= ratio;
                        self.law_bank_ns_per_m *= ratio;
                    }
                }
            }
        }
        (force, flags)
    }

    /// Second-order backward difference of the displacement history.
    fn acceleration_m_per_s2(&self) -> f64 {
        let [z0, z1, z2, z3] = self.z_history_m;
        (2.0 * z0 - 5.0 * z1 + 4.0 * z2 - z3) / (self.dt_s * self.dt_s)
    }

    fn delay(&mut self, force: f64) -> f64 {
        let n = self.delay_line.len();
        let previous = self.delay_line[self.delay_head];
        self.delay_head = (self.delay_head + 1) % n;
        self.delay_line[self.delay_head] = force;
        if self.lag_steps < 0.0 {
            // A lead cannot be realised causally: linear extrapolation over the lead.
            return force + (-self.lag_steps) * (force - previous);
        }
        let whole = self.lag_steps.floor();
        let frac = self.lag_steps - whole;
        let i0 = (self.delay_head + n - whole as usize) % n;
        let i1 = (i0 + n - 1) % n;
        (1.0 - frac) * self.delay_line[i0] + frac * self.delay_line[i1]
    }
}

/// Simulates the force of an augmented model for a displacement history (offline helper).
pub fn simulate_model_force(
    model: &AugmentedModel,
    mode: StepperMode,
    dt_s: f64,
    displacement_m: &[f64],
) -> (Vec<f64>, StepFlags) {
    let mut forces = Vec::with_capacity(displacement_m.len());
    let Some(&z0) = displacement_m.first() else {
        return (forces, StepFlags::NONE);
    };
    let mut stepper = ModelStepper::new(model, mode, dt_s, z0);
    let mut all_flags = StepFlags::NONE;
    forces.push(stepper.force_n());
    for &z in &displacement_m[1..] {
        let (force, flags) = stepper.step(z);
        all_flags |= flags;
        forces.push(force);
    }
    (forces, all_flags)
}

#[cfg(test)]
mod tests {
    use super::SofteningState;

    /// The Mullins factor's `tanh` through `exp` against `f64::tanh` (an independent
    /// implementation), from the virgin curve (x = 0) to deep below the maximum, and its
    /// slope against the analytic `d (1 - d tanh) / d F`.
    #[test]
    fn softening_factor_matches_tanh() {
        let s = SofteningState {
            limit: 0.2,
            scale_n: 5e3,
            max_force_n: 40e3,
        };
        let below = [0.0, 1e-9, 1e-3, 1.0].into_iter();
        for d in below.chain((1..=2000).map(|i| i as f64 * 60.0)) {
            let f = 40e3 - d;
            let x = (40e3 - f).max(0.0) / 5e3;
            let t = x.tanh();
            let (eta, slope) = s.eval(f);
            assert!((eta - (1.0 - 0.2 * t)).abs() < 1e-15, "{f} {eta}");
            assert!(
                (slope - 0.2 * (1.0 - t * t) / 5e3).abs() < 1e-19,
                "{f} {slope}"
            );
        }
        // Above the maximum (not reached through `eval`): the virgin curve.
        assert_eq!(s.eval(41e3), (1.0, 0.2 / 5e3));
    }
}
