//! `element`: the emulated element's own state over a run (self-heating's temperature rise and the softening it causes), from the emulator's records; offline, never in a loop.

use serde::Serialize;

use super::decimate::Decimator;
use crate::model::effects::{AugmentedModel, Effect};

/// The element's self-heating over the run (only with `self-heating` in the model).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ElementThermal {
    pub heat_capacity_j_per_k: f64,
    pub heat_transfer_w_per_k: f64,
    /// `C / h`, s.
    pub time_constant_s: f64,
    /// Rise above the operating temperature at the first record, K.
    pub rise_start_k: f64,
    pub rise_max_k: f64,
    pub rise_max_at_s: f64,
    pub rise_end_k: f64,
    /// Mean power the element dissipated over the recorded time, from the thermal balance
    /// of its records (`C * (rise_end - rise_start) + h * integral(rise dt)`, over the
    /// time), W.
    pub mean_power_w: f64,
    /// The temperature law's modulus factor at the end relative to the start
    /// (`exp(-ln_modulus_shift_per_c * (rise_end - rise_start))`): below 1 when it softened.
    pub modulus_factor_end: f64,
    pub ln_modulus_shift_per_c: f64,
}

/// A decimated series for a plot: times and values.
pub type PlotSeries = (Vec<f64>, Vec<f64>);

/// Follows the emulator's records of the element's temperature rise.
pub struct ElementTracker {
    heat_capacity_j_per_k: f64,
    heat_transfer_w_per_k: f64,
    ln_modulus_shift_per_c: f64,
    first: Option<(f64, f64)>,
    last: (f64, f64),
    max: (f64, f64),
    /// Trapezoidal integral of the rise over time, K s.
    integral_k_s: f64,
    rise: Decimator,
}

impl ElementTracker {
    /// `None` when the model does not heat itself.
    pub fn new(model: &AugmentedModel) -> Option<ElementTracker> {
        let Some(&Effect::SelfHeating {
            heat_capacity_j_per_k,
            heat_transfer_w_per_k,
            temperature_rise_k,
        }) = model.find("self-heating")
        else {
            return None;
        };
        let (_, ln_modulus_shift_per_c, _) = model.temperature_law(temperature_rise_k);
        Some(ElementTracker {
            heat_capacity_j_per_k,
            heat_transfer_w_per_k,
            ln_modulus_shift_per_c,
            first: None,
            last: (0.0, 0.0),
            max: (0.0, f64::NEG_INFINITY),
            integral_k_s: 0.0,
            rise: Decimator::new(0.0, 1e-3, super::PLOT_BUCKETS),
        })
    }

    /// One emulator record: its time and the element's rise.
    pub fn push(&mut self, t_s: f64, rise_k: f64) {
        if !rise_k.is_finite() {
            return;
        }
        match self.first {
            None => self.first = Some((t_s, rise_k)),
            Some(_) => {
                let (t0, r0) = self.last;
                if t_s > t0 {
                    self.integral_k_s += 0.5 * (r0 + rise_k) * (t_s - t0);
                }
            }
        }
        if rise_k > self.max.1 {
            self.max = (t_s, rise_k);
        }
        self.last = (t_s, rise_k);
        self.rise.push(t_s, rise_k);
    }

    /// The summary, and the decimated rise (t, K) for the plot; `None` without records.
    pub fn finish(self) -> Option<(ElementThermal, PlotSeries)> {
        let (t0, r0) = self.first?;
        let (t1, r1) = self.last;
        let span_s = t1 - t0;
        let mean_power_w = if span_s > 0.0 {
            (self.heat_capacity_j_per_k * (r1 - r0)
                + self.heat_transfer_w_per_k * self.integral_k_s)
                / span_s
        } else {
            0.0
        };
        let summary = ElementThermal {
            heat_capacity_j_per_k: self.heat_capacity_j_per_k,
            heat_transfer_w_per_k: self.heat_transfer_w_per_k,
            time_constant_s: self.heat_capacity_j_per_k / self.heat_transfer_w_per_k,
            rise_start_k: r0,
            rise_max_k: self.max.1,
            rise_max_at_s: self.max.0,
            rise_end_k: r1,
            mean_power_w,
            modulus_factor_end: (-self.ln_modulus_shift_per_c * (r1 - r0)).exp(),
            ln_modulus_shift_per_c: self.ln_modulus_shift_per_c,
        };
        Some((summary, self.rise.points(1.0)))
    }
}

impl ElementThermal {
    /// One line for the console.
    pub fn describe(&self) -> String {
        format!(
            "element self-heating: {:.3} K above ambient at the start, {:.3} K at the end (largest {:.3} K at {:.1} s; time constant {:.0} s), {:.2} W dissipated on average; modulus {:+.3} % by the end",
            self.rise_start_k,
            self.rise_end_k,
            self.rise_max_k,
            self.rise_max_at_s,
            self.time_constant_s,
            self.mean_power_w,
            (self.modulus_factor_end - 1.0) * 100.0
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::thermal::ThermalState;

    /// The tracker's thermal balance gives back the power that heated a thermal state it
    /// did not see, and the modulus factor follows the default temperature law.
    #[test]
    fn the_mean_power_is_recovered_from_the_recorded_rise() {
        let (c, h, dt) = (2.0, 0.05, 1e-3);
        let plain = AugmentedModel {
            element: crate::model::params::ElementModel::Consistent(
                crate::model::params::ZenerParams::paper_table3(0.75),
            ),
            length_m: 0.75,
            effects: Vec::new(),
        };
        let mut model = plain.clone();
        model.effects.push(Effect::SelfHeating {
            heat_capacity_j_per_k: c,
            heat_transfer_w_per_k: h,
            temperature_rise_k: 0.0,
        });
        let mut tracker = ElementTracker::new(&model).expect("self-heating");
        let mut state = ThermalState::new(c, h, dt, 0.0);
        // 3 W for 20 s, then 1 W for 20 s: 2 W on average.
        for i in 0..=40_000u32 {
            let t = f64::from(i) * dt;
            tracker.push(t, state.rise_k);
            state.step(if t < 20.0 { 3.0 } else { 1.0 });
        }
        let (s, (ts, rs)) = tracker.finish().expect("records");
        assert!((s.mean_power_w - 2.0).abs() < 2e-3, "{}", s.mean_power_w);
        assert!(s.rise_max_k > s.rise_end_k && s.rise_end_k > 0.0);
        let expected =
            (-crate::model::thermal::DEFAULT_LN_MODULUS_SHIFT_PER_C * s.rise_end_k).exp();
        assert!((s.modulus_factor_end - expected).abs() < 1e-12);
        assert!(!ts.is_empty() && ts.len() == rs.len());
        assert!(ElementTracker::new(&plain).is_none());
    }
}
