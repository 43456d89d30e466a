//! Self-heating: the specimen's temperature rise from the power it dissipates (a lumped
//! heat capacity `C` cooled through a heat-transfer coefficient `h` to the ambient, time
//! constant `C / h`), over a campaign's schedule of tests and rests or step by step.
//! Must not: allocate, do I/O or read a clock in `ThermalState::step`.

/// Temperature law used by `self-heating` when the model has no `temperature-shift`: the
/// dynamic modulus of a typical filled rubber near room temperature, -0.8 %/degC, and no
/// shift of relaxation times (that needs tests at several chamber temperatures to be
/// calibrated: `temperature-shift`). Stated in the report when used.
pub const DEFAULT_LN_MODULUS_SHIFT_PER_C: f64 = 0.008;
pub const DEFAULT_LOG10_TIME_SHIFT_PER_C: f64 = 0.0;

/// Physical range of the heat capacity of a specimen (a few grams of rubber to a 100 kg
/// block with its steel plates), J/K.
pub const HEAT_CAPACITY_RANGE_J_PER_K: (f64, f64) = (1.0, 1e6);
/// Physical range of the heat-transfer coefficient to the surroundings (still air on a
/// small pad to water-cooled steel plates), W/K.
pub const HEAT_TRANSFER_RANGE_W_PER_K: (f64, f64) = (1e-3, 1e3);

/// One test of a campaign as the thermal model sees it: when it started (s, any origin),
/// how long it ran, the mean power the specimen dissipated and when in it the test's
/// analysed data sit (s after its start).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThermalInterval {
    pub start_s: f64,
    pub duration_s: f64,
    /// Mean power dissipated, W (from the measured records).
    pub power_w: f64,
    pub probe_s: f64,
    /// Change of `power_w` per second of force-channel lag corrected (`mean(dF/dt dz/dt)`,
    /// W/s): a skew between the channels inflates or shrinks the measured loop's area,
    /// which is no heat (`campaign_temperature_rise_k`'s `force_lag_s`).
    pub power_per_lag_w_per_s: f64,
}

/// Temperature rise of the specimen at the probe time of test `index` of `schedule`
/// (tests in time order, starting cold; rests between tests cool it, an overlap counts as
/// no rest). Exact for piecewise-constant power: `dT/dt = (P - h T) / C`. `force_lag_s` is
/// the force channel's lag behind the displacement's (a named `channel-delay`, else 0):
/// each test's measured power is corrected for it, to first order.
pub fn campaign_temperature_rise_k(
    schedule: &[ThermalInterval],
    index: usize,
    heat_capacity_j_per_k: f64,
    heat_transfer_w_per_k: f64,
    force_lag_s: f64,
) -> f64 {
    let tau_s = heat_capacity_j_per_k / heat_transfer_w_per_k.max(1e-300);
    let relax = |rise: f64, target: f64, t_s: f64| target + (rise - target) * (-t_s / tau_s).exp();
    let mut rise = 0.0;
    let mut end_s = f64::NEG_INFINITY;
    for (i, test) in schedule.iter().enumerate().take(index + 1) {
        if end_s.is_finite() {
            rise = relax(rise, 0.0, (test.start_s - end_s).max(0.0));
        }
        let power_w = test.power_w + force_lag_s * test.power_per_lag_w_per_s;
        let target = power_w.max(0.0) / heat_transfer_w_per_k.max(1e-300);
        if i == index {
            return relax(rise, target, test.probe_s.clamp(0.0, test.duration_s));
        }
        rise = relax(rise, target, test.duration_s);
        end_s = test.start_s + test.duration_s;
    }
    rise
}

/// Per-element thermal state for a fixed-step stepper: the rise above ambient, advanced
/// exactly over each step for the step's power (no allocation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThermalState {
    pub rise_k: f64,
    /// `exp(-dt / tau)`.
    decay: f64,
    heat_transfer_w_per_k: f64,
}

impl ThermalState {
    pub fn new(
        heat_capacity_j_per_k: f64,
        heat_transfer_w_per_k: f64,
        dt_s: f64,
        rise_k: f64,
    ) -> ThermalState {
        let tau_s = heat_capacity_j_per_k / heat_transfer_w_per_k.max(1e-300);
        ThermalState {
            rise_k,
            decay: (-dt_s / tau_s.max(1e-300)).exp(),
            heat_transfer_w_per_k: heat_transfer_w_per_k.max(1e-300),
        }
    }

    /// Advances one step with the power dissipated over it, W; returns the new rise, K.
    #[inline]
    pub fn step(&mut self, power_w: f64) -> f64 {
        let target = if power_w.is_finite() {
            power_w.max(0.0) / self.heat_transfer_w_per_k
        } else {
            0.0
        };
        self.rise_k = target + (self.rise_k - target) * self.decay;
        self.rise_k
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_test_reaches_p_over_h_and_a_rest_cools_by_its_time_constant() {
        // C = 2000 J/K, h = 4 W/K: tau = 500 s; 10 W gives a 2.5 K steady rise.
        let schedule = [
            ThermalInterval {
                start_s: 0.0,
                duration_s: 10_000.0,
                power_w: 10.0,
                probe_s: 10_000.0,
                power_per_lag_w_per_s: 0.0,
            },
            ThermalInterval {
                start_s: 10_500.0,
                duration_s: 100.0,
                power_w: 0.0,
                probe_s: 0.0,
                power_per_lag_w_per_s: 0.0,
            },
        ];
        let first = campaign_temperature_rise_k(&schedule, 0, 2000.0, 4.0, 0.0);
        assert!((first - 2.5).abs() < 1e-6, "{first}");
        // One time constant of rest: 2.5 / e.
        let second = campaign_temperature_rise_k(&schedule, 1, 2000.0, 4.0, 0.0);
        assert!((second - 2.5 * (-1.0f64).exp()).abs() < 1e-6, "{second}");
    }

    #[test]
    fn stepping_matches_the_closed_form_heating_curve() {
        let mut state = ThermalState::new(300.0, 3.0, 0.01, 0.0);
        for _ in 0..10_000 {
            state.step(6.0);
        }
        // 100 s = one time constant: 2 K (1 - 1/e).
        let expected = 2.0 * (1.0 - (-1.0f64).exp());
        assert!((state.rise_k - expected).abs() < 1e-9, "{}", state.rise_k);
    }
}
