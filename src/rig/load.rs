//! External load programme on the specimen: preload + harmonic, a step, the ETR 500
//! coach passage (paper Fig. 7, quasi-static force on the sample's length) and an
//! optional CSV. Pure function of time; no I/O after construction.

use crate::hil::config::ScenarioConfig;
use crate::track::{kmh_to_m_per_s, TrainPassage};

/// External force on the specimen as a function of time, N (positive in compression).
#[derive(Debug, Clone)]
pub struct LoadProgramme {
    preload_n: f64,
    harmonic_amplitude_n: f64,
    harmonic_omega_rad_per_s: f64,
    train: Option<(TrainPassage, f64)>,
    sample_length_m: f64,
    step_n: f64,
    step_at_s: f64,
    csv: Option<(f64, Vec<f64>)>,
}

impl LoadProgramme {
    /// The programme of `scenario` on an element of length `sample_length_m`.
    pub fn new(scenario: &ScenarioConfig, sample_length_m: f64) -> LoadProgramme {
        LoadProgramme {
            preload_n: scenario.preload_n,
            harmonic_amplitude_n: scenario.harmonic_amplitude_n,
            harmonic_omega_rad_per_s: 2.0 * std::f64::consts::PI * scenario.harmonic_frequency_hz,
            train: (scenario.train_speed_kmh > 0.0).then(|| {
                (
                    TrainPassage::etr500_coach(kmh_to_m_per_s(scenario.train_speed_kmh)),
                    scenario.train_first_axle_s,
                )
            }),
            sample_length_m,
            step_n: scenario.step_n,
            step_at_s: scenario.step_at_s,
            csv: scenario.load_csv_samples.clone(),
        }
    }

    /// External force at `t_s`, N.
    pub fn force_n(&self, t_s: f64) -> f64 {
        let mut f = self.preload_n
            + self.harmonic_amplitude_n * (self.harmonic_omega_rad_per_s * t_s).sin();
        if let Some((train, t_first)) = &self.train {
            f += train.force_per_m_history(t_s, *t_first) * self.sample_length_m;
        }
        if self.step_n != 0.0 && t_s >= self.step_at_s {
            f += self.step_n;
        }
        if let Some((dt, values)) = &self.csv {
            let pos = t_s / dt;
            let i = pos.floor();
            if i >= 0.0 && (i as usize) + 1 < values.len() {
                let i = i as usize;
                let w = pos - i as f64;
                f += values[i] * (1.0 - w) + values[i + 1] * w;
            } else if let Some(last) = values.last().filter(|_| i >= 0.0) {
                f += *last;
            }
        }
        f
    }
}
