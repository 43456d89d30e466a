//! The actuator's parameters: kinds, their keys (units in the names), presets, and the seeded perturbation; owns no dynamics and must not read files.

/// The physical kinds of force actuator the rig can simulate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ActuatorKind {
    /// First-order lag, transport delay, saturation.
    LagDelay,
    /// Servo-valve, oil column, force loop closed by the servo controller.
    ServoHydraulic,
    /// Current amplifier, coil, force constant, suspension.
    Electrodynamic,
}

/// How a key's value is validated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rule {
    Positive,
    NonNegative,
    /// A share, 0 to 1.
    Fraction,
}

/// One parameter key of a kind, as written in `[rig.actuator]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParamKey {
    /// The key, unit in its name.
    pub name: &'static str,
    /// Multiplies the configured value into SI (1e-6 for `_us`).
    pub to_si: f64,
    pub rule: Rule,
    /// Drawn by `perturb` (false: a controller setting, not hardware).
    pub physical: bool,
    /// Value when neither the preset nor the table gives it (configured units).
    pub default: Option<f64>,
}

const fn key(name: &'static str, to_si: f64, rule: Rule) -> ParamKey {
    ParamKey {
        name,
        to_si,
        rule,
        physical: true,
        default: None,
    }
}

/// Most parameters a kind has.
pub const MAX_PARAMS: usize = 10;

const TRANSPORT: ParamKey = key("transport_delay_us", 1e-6, Rule::NonNegative);
const FORCE_MAX: ParamKey = key("force_max_n", 1.0, Rule::Positive);

const LAG_DELAY_KEYS: [ParamKey; 3] =
    [TRANSPORT, FORCE_MAX, key("lag_us", 1e-6, Rule::NonNegative)];

const SERVO_HYDRAULIC_KEYS: [ParamKey; 10] = [
    TRANSPORT,
    FORCE_MAX,
    key("valve_frequency_hz", 1.0, Rule::Positive),
    key("valve_damping_ratio", 1.0, Rule::Positive),
    key("bulk_modulus_pa", 1.0, Rule::Positive),
    key("piston_area_m2", 1.0, Rule::Positive),
    key("oil_volume_m3", 1.0, Rule::Positive),
    ParamKey {
        physical: false,
        ..key("force_loop_bandwidth_hz", 1.0, Rule::Positive)
    },
    ParamKey {
        default: Some(0.0),
        ..key("leakage_m3_per_s_pa", 1.0, Rule::NonNegative)
    },
    // The servo controller's velocity compensation: the fraction of the measured piston
    // velocity fed forward into the valve command (1: full, the presets; 0: none, a force
    // loop that fights the oil column's natural velocity feedback with its gain alone).
    ParamKey {
        physical: false,
        default: Some(1.0),
        ..key("velocity_compensation", 1.0, Rule::Fraction)
    },
];

const ELECTRODYNAMIC_KEYS: [ParamKey; 9] = [
    TRANSPORT,
    FORCE_MAX,
    key("amplifier_bandwidth_hz", 1.0, Rule::Positive),
    key("coil_resistance_ohm", 1.0, Rule::Positive),
    key("coil_inductance_h", 1.0, Rule::Positive),
    key("force_constant_n_per_a", 1.0, Rule::Positive),
    key("suspension_stiffness_n_per_m", 1.0, Rule::NonNegative),
    key("suspension_damping_ns_per_m", 1.0, Rule::NonNegative),
    key("moving_mass_kg", 1.0, Rule::NonNegative),
];

impl ActuatorKind {
    pub const ALL: [ActuatorKind; 3] = [
        ActuatorKind::LagDelay,
        ActuatorKind::ServoHydraulic,
        ActuatorKind::Electrodynamic,
    ];

    /// The name in `[rig.actuator] kind`.
    pub fn name(self) -> &'static str {
        match self {
            ActuatorKind::LagDelay => "lag-delay",
            ActuatorKind::ServoHydraulic => "servo-hydraulic",
            ActuatorKind::Electrodynamic => "electrodynamic",
        }
    }

    pub fn from_name(name: &str) -> Option<ActuatorKind> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }

    /// The code in the `/rig/actuator` record.
    pub fn code(self) -> u32 {
        match self {
            ActuatorKind::LagDelay => 0,
            ActuatorKind::ServoHydraulic => 1,
            ActuatorKind::Electrodynamic => 2,
        }
    }

    pub fn from_code(code: u32) -> Option<ActuatorKind> {
        Self::ALL.into_iter().find(|k| k.code() == code)
    }

    /// The kind's parameter keys, in the order of `ActuatorParams::si`.
    pub fn keys(self) -> &'static [ParamKey] {
        match self {
            ActuatorKind::LagDelay => &LAG_DELAY_KEYS,
            ActuatorKind::ServoHydraulic => &SERVO_HYDRAULIC_KEYS,
            ActuatorKind::Electrodynamic => &ELECTRODYNAMIC_KEYS,
        }
    }
}

/// One actuator's parameters, SI, in the order of `kind.keys()` (unused slots 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ActuatorParams {
    pub kind: ActuatorKind,
    pub si: [f64; MAX_PARAMS],
}

impl ActuatorParams {
    /// Parameters from values in configured units (`values[i]` for `kind.keys()[i]`; a key
    /// beyond `values` takes its default, e.g. a preset written before the key existed).
    pub fn from_config_units(kind: ActuatorKind, values: &[f64]) -> ActuatorParams {
        let mut si = [0.0; MAX_PARAMS];
        for (i, (slot, k)) in si.iter_mut().zip(kind.keys()).enumerate() {
            *slot = values.get(i).copied().or(k.default).unwrap_or(0.0) * k.to_si;
        }
        ActuatorParams { kind, si }
    }

    /// The SI value of `key` (its configured name), if the kind has it.
    pub fn get(&self, key: &str) -> Option<f64> {
        let i = self.kind.keys().iter().position(|k| k.name == key)?;
        Some(self.si[i])
    }

    /// The value of the kind's `i`th key in configured units.
    pub fn config_value(&self, i: usize) -> f64 {
        self.si[i] / self.kind.keys()[i].to_si
    }

    pub fn transport_delay_s(&self) -> f64 {
        self.si[0]
    }

    pub fn force_max_n(&self) -> f64 {
        self.si[1]
    }

    /// Each physical parameter drawn uniformly within `+-fraction` of its value from a
    /// splitmix64 stream seeded by `seed` (one draw per key, in key order).
    pub fn perturbed(&self, fraction: f64, seed: u64) -> ActuatorParams {
        let mut out = *self;
        let mut state = seed ^ 0xA076_1D64_78BD_642F;
        for (slot, k) in out.si.iter_mut().zip(self.kind.keys()) {
            let u = splitmix_uniform(&mut state);
            if k.physical {
                *slot *= 1.0 + fraction * (2.0 * u - 1.0);
            }
        }
        out
    }
}

/// A uniform deviate in (0, 1) from a splitmix64 stream.
fn splitmix_uniform(state: &mut u64) -> f64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
}

/// `[rig.actuator]`, validated: the nominal parameters (preset, then the table's keys) and
/// how the rig's truth departs from them. Only the rig calls `truth`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ActuatorConfig {
    pub nominal: ActuatorParams,
    /// The preset the nominal values started from.
    pub preset: Option<&'static str>,
    /// Fraction (0 to 0.9) within which each physical parameter is drawn.
    pub perturb: f64,
    pub perturb_seed: u64,
}

impl ActuatorConfig {
    /// Today's default: 50 us transport delay, 80 us lag, 150 kN.
    pub fn lag_delay(transport_delay_s: f64, lag_s: f64, force_max_n: f64) -> ActuatorConfig {
        let mut si = [0.0; MAX_PARAMS];
        si[0] = transport_delay_s;
        si[1] = force_max_n;
        si[2] = lag_s;
        ActuatorConfig {
            nominal: ActuatorParams {
                kind: ActuatorKind::LagDelay,
                si,
            },
            preset: None,
            perturb: 0.0,
            perturb_seed: 0,
        }
    }

    /// The parameters the rig's hardware has (the nominal ones when `perturb` is 0).
    pub fn truth(&self) -> ActuatorParams {
        if self.perturb == 0.0 {
            self.nominal
        } else {
            self.nominal.perturbed(self.perturb, self.perturb_seed)
        }
    }
}

/// A named parameter set (`[rig.actuator] preset`); `docs/actuators.md` gives the sources.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Preset {
    pub name: &'static str,
    pub kind: ActuatorKind,
    /// Values in configured units, in the order of `kind.keys()`.
    pub values: &'static [f64],
    /// One line: what hardware it stands for.
    pub source: &'static str,
}

/// The presets, per kind.
pub const PRESETS: &[Preset] = &[
    Preset {
        name: "this-rig",
        kind: ActuatorKind::LagDelay,
        values: &[50.0, 150_000.0, 80.0],
        source: "the shipped configs' actuator: 50 us transport delay, 80 us lag, 150 kN",
    },
    Preset {
        // 150 kN at 21 MPa: A = 7.14e-3 m2; 250 mm stroke (both chambers 1.8e-3 m3) plus
        // manifold and hoses: V = 2.0e-3 m3; a two-stage valve with its -90 deg point near
        // 100 Hz; force loop at 60 Hz.
        name: "fatigue-150kn",
        kind: ActuatorKind::ServoHydraulic,
        values: &[
            500.0, 150_000.0, 100.0, 0.7, 1.5e9, 7.14e-3, 2.0e-3, 60.0, 0.0,
        ],
        source:
            "a 150 kN fatigue actuator at 21 MPa with a two-stage servo-valve (Moog G761 class)",
    },
    Preset {
        // Faster: a three-stage valve near 150 Hz, 150 mm stroke, a faster controller.
        name: "rths-fast-150kn",
        kind: ActuatorKind::ServoHydraulic,
        values: &[
            300.0, 150_000.0, 150.0, 0.7, 1.6e9, 7.14e-3, 1.2e-3, 100.0, 0.0,
        ],
        source: "a 150 kN dynamic actuator with a high-response valve, as in RTHS labs",
    },
    Preset {
        // Slower: 250 kN at 21 MPa, 300 mm stroke plus hoses, a large valve near 60 Hz, a
        // soft loop, some leakage across the piston.
        name: "slow-250kn",
        kind: ActuatorKind::ServoHydraulic,
        values: &[
            800.0, 250_000.0, 60.0, 0.8, 1.4e9, 1.19e-2, 4.0e-3, 40.0, 1.0e-12,
        ],
        source: "a 250 kN structural actuator with a large two-stage valve",
    },
    Preset {
        name: "shaker-10kn",
        kind: ActuatorKind::Electrodynamic,
        values: &[
            100.0, 10_000.0, 1500.0, 0.2, 3.0e-4, 60.0, 60_000.0, 300.0, 12.0,
        ],
        source: "a 10 kN-sine air-cooled electrodynamic shaker with a current-mode amplifier",
    },
    Preset {
        name: "shaker-150kn",
        kind: ActuatorKind::Electrodynamic,
        values: &[
            100.0, 150_000.0, 1000.0, 0.05, 2.0e-4, 300.0, 300_000.0, 2000.0, 100.0,
        ],
        source: "a large water-cooled electrodynamic shaker (the 150-300 kN class)",
    },
];

/// The preset `name`, if it exists.
pub fn preset(name: &str) -> Option<&'static Preset> {
    PRESETS.iter().find(|p| p.name == name)
}
