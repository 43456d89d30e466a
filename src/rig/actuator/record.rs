//! The actuator's truth as the rig records it once per run (`/rig/actuator`, `/rig/actuator/param`); owns the record layouts and must not be written per period.

use super::{ActuatorConfig, ActuatorPlant, PRESETS};
use crate::record_type;

record_type! {
    /// The rig's actuator, once per run (`/rig/actuator`).
    pub struct ActuatorTruthRecord {
        topic: "/rig/actuator",
        schema: "fastemu/ActuatorTruthRecord",
        log_time: |_r| 0,
        fields: {
            /// kind: 0 lag-delay, 1 servo-hydraulic, 2 electrodynamic
            kind: u32,
            /// index of the preset in the preset table (u32::MAX none)
            preset_index: u32,
            /// fraction within which each physical parameter was drawn
            perturb: f64,
            /// seed of the draw
            perturb_seed: u64,
            /// element stiffness of the effective delay (tangent at the configured preload), N/m
            element_stiffness_n_per_m: f64,
            /// true effective delay from command to force over 1-20 Hz on that element, s
            effective_delay_s: f64,
            /// true mean amplitude ratio force/command over 1-20 Hz
            amplitude_ratio: f64,
            /// effective delay of the nominal parameters, s
            nominal_effective_delay_s: f64,
            /// amplitude ratio of the nominal parameters
            nominal_amplitude_ratio: f64,
        }
    }
}

record_type! {
    /// One actuator parameter, once per run (`/rig/actuator/param`), in its key's unit.
    pub struct ActuatorParamRecord {
        topic: "/rig/actuator/param",
        schema: "fastemu/ActuatorParamRecord",
        log_time: |_r| 0,
        fields: {
            /// kind, as in /rig/actuator
            kind: u32,
            /// index of the key in the kind's key list (docs/actuators.md)
            index: u32,
            /// the rig's true value (after perturbation), in the key's unit
            truth: f64,
            /// the configured (nominal) value, in the key's unit
            nominal: f64,
        }
    }
}

/// The records of an actuator configuration as the rig has it (`plant` built from it),
/// with the effective delay on an element of stiffness `element_stiffness_n_per_m`.
pub fn actuator_truth_records(
    cfg: &ActuatorConfig,
    plant: &ActuatorPlant,
    element_stiffness_n_per_m: f64,
) -> (ActuatorTruthRecord, Vec<ActuatorParamRecord>) {
    let truth = plant.effective_delay(element_stiffness_n_per_m);
    let nominal = cfg.nominal.effective_delay(element_stiffness_n_per_m);
    let kind = cfg.nominal.kind;
    let record = ActuatorTruthRecord {
        kind: kind.code(),
        preset_index: cfg
            .preset
            .and_then(|name| PRESETS.iter().position(|p| p.name == name))
            .map_or(u32::MAX, |i| i as u32),
        perturb: cfg.perturb,
        perturb_seed: cfg.perturb_seed,
        element_stiffness_n_per_m,
        effective_delay_s: truth.delay_s,
        amplitude_ratio: truth.amplitude_ratio,
        nominal_effective_delay_s: nominal.delay_s,
        nominal_amplitude_ratio: nominal.amplitude_ratio,
    };
    let params = (0..kind.keys().len())
        .map(|i| ActuatorParamRecord {
            kind: kind.code(),
            index: i as u32,
            truth: plant.truth.config_value(i),
            nominal: cfg.nominal.config_value(i),
        })
        .collect();
    (record, params)
}
