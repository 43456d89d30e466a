//! The lag-delay actuator: first-order lag after the transport delay, saturation; owns its one state and must not allocate.

use super::{params::ActuatorParams, Complex64, PlantState};

/// `T dF/dt = u(t - tau) - F`; `T = 0`: the force follows the delayed command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LagDelay {
    pub lag_s: f64,
}

impl LagDelay {
    pub fn new(truth: &ActuatorParams) -> LagDelay {
        LagDelay { lag_s: truth.si[2] }
    }

    pub fn rest_state(&self, force_n: f64) -> PlantState {
        [force_n, 0.0, 0.0, 0.0]
    }

    #[inline]
    pub fn derivative(&self, s: &PlantState, u: f64) -> PlantState {
        let dfa = if self.lag_s > 0.0 {
            (u - s[0]) / self.lag_s
        } else {
            0.0
        };
        [dfa, 0.0, 0.0, 0.0]
    }

    /// Without a lag the force is the delayed command, set at each sub-step's start.
    #[inline]
    pub fn begin_substep(&self, s: &mut PlantState, u: f64) {
        if self.lag_s == 0.0 {
            s[0] = u;
        }
    }

    /// `H_u` without the transport delay (`H_v` is zero).
    pub fn response(&self, omega: f64) -> Complex64 {
        Complex64::new(1.0, 0.0) / Complex64::new(1.0, omega * self.lag_s)
    }
}
