//! `actuator_truth`: the rig's actuator as it recorded it once per run (`/rig/actuator`, `/rig/actuator/param`); reads records only through the report's pass.

use serde::Serialize;

use crate::rig::actuator::{
    ActuatorKind, ActuatorParamRecord, ActuatorParams, ActuatorPlant, ActuatorTruthRecord, PRESETS,
};

/// One actuator parameter, in its key's unit.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ActuatorParameter {
    pub key: String,
    pub truth: f64,
    pub nominal: f64,
}

/// The rig's actuator truth (absent for an external rig).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ActuatorTruth {
    pub kind: String,
    pub preset: Option<String>,
    pub perturb: f64,
    pub perturb_seed: u64,
    /// The element's tangent stiffness at the configured preload, N/m.
    pub element_stiffness_n_per_m: f64,
    /// Effective delay from the rig's command, held over each loop period, to force over
    /// 1-20 Hz on that element, s: `actuator_delay_s + zero_order_hold_s`, the delay the
    /// controller identifies and its lead must make up for.
    pub effective_delay_s: f64,
    /// The actuator's own part (transport delay and dynamics, as recorded), s.
    pub actuator_delay_s: f64,
    /// Half a loop period: the command is held over each period, s.
    pub zero_order_hold_s: f64,
    pub amplitude_ratio: f64,
    /// The nominal parameters' `effective_delay_s` (hold included), s.
    pub nominal_effective_delay_s: f64,
    pub nominal_amplitude_ratio: f64,
    pub parameters: Vec<ActuatorParameter>,
}

impl ActuatorTruth {
    /// From the run's records; `None` without a `/rig/actuator` record.
    /// `period_s`: the loop period (the zero-order hold is half of it).
    pub fn from_records(
        truth: Option<&ActuatorTruthRecord>,
        params: &[ActuatorParamRecord],
        period_s: f64,
    ) -> Option<ActuatorTruth> {
        let t = truth?;
        let hold_s = 0.5 * period_s;
        let kind = ActuatorKind::from_code(t.kind)?;
        let keys = kind.keys();
        Some(ActuatorTruth {
            kind: kind.name().to_string(),
            preset: PRESETS
                .get(t.preset_index as usize)
                .map(|p| p.name.to_string()),
            perturb: t.perturb,
            perturb_seed: t.perturb_seed,
            element_stiffness_n_per_m: t.element_stiffness_n_per_m,
            effective_delay_s: t.effective_delay_s + hold_s,
            actuator_delay_s: t.effective_delay_s,
            zero_order_hold_s: hold_s,
            amplitude_ratio: t.amplitude_ratio,
            nominal_effective_delay_s: t.nominal_effective_delay_s + hold_s,
            nominal_amplitude_ratio: t.nominal_amplitude_ratio,
            parameters: params
                .iter()
                .filter(|p| p.kind == t.kind)
                .filter_map(|p| {
                    Some(ActuatorParameter {
                        key: keys.get(p.index as usize)?.name.to_string(),
                        truth: p.truth,
                        nominal: p.nominal,
                    })
                })
                .collect(),
        })
    }

    /// The recorded actuator as a plant (its truth, its controller tuned on the nominal),
    /// for the report's linearised judgements; `None` when a parameter is missing.
    pub fn plant(&self) -> Option<ActuatorPlant> {
        let kind = ActuatorKind::from_name(&self.kind)?;
        let values = |nominal: bool| -> Option<Vec<f64>> {
            kind.keys()
                .iter()
                .map(|k| {
                    // A key older records lack takes its default, as a configuration does.
                    match self.parameters.iter().find(|p| p.key == k.name) {
                        Some(p) => Some(if nominal { p.nominal } else { p.truth }),
                        None => k.default,
                    }
                })
                .collect()
        };
        let truth = ActuatorParams::from_config_units(kind, &values(false)?);
        let nominal = ActuatorParams::from_config_units(kind, &values(true)?);
        Some(ActuatorPlant::new(&truth, &nominal))
    }

    /// One line for the summary.
    pub fn describe(&self) -> String {
        format!(
            "actuator {}{}: effective delay {:.3} ms ({:.3} ms its own + {:.3} ms of hold; nominal {:.3} ms), amplitude ratio {:.3} over 1-20 Hz on {:.1} MN/m{}",
            self.kind,
            self.preset.as_ref().map_or(String::new(), |p| format!(" ({p})")),
            self.effective_delay_s * 1e3,
            self.actuator_delay_s * 1e3,
            self.zero_order_hold_s * 1e3,
            self.nominal_effective_delay_s * 1e3,
            self.amplitude_ratio,
            self.element_stiffness_n_per_m * 1e-6,
            if self.perturb > 0.0 {
                format!(", parameters perturbed +-{:.0} %", self.perturb * 100.0)
            } else {
                String::new()
            }
        )
    }
}
