//! The servo-hydraulic actuator in force control: servo-valve, oil column, PI force loop, the piston's velocity in the flow; owns its states and gains and must not allocate.
//!
//! States: `F` (force = piston area x load pressure), `q` (valve flow over piston area,
//! m/s), `q'`, `I` (the force error's integral). With `e = u(t - tau) - F`:
//! `q_c = Kp e + Ki I - g_v v`, `q'' = wv^2 (q_c - q) - 2 zeta wv q'`,
//! `dF/dt = k_h (q + v) - lambda F`, `k_h = 4 beta A^2 / V`, `lambda = 4 beta C_L / V`,
//! `v` the specimen's (= the piston's) velocity, positive in compression: a specimen
//! pushing into the actuator compresses the oil and raises the force.
//!
//! The controller is tuned on the nominal parameters (the truth may differ): `Kp =
//! w_c / k_h` puts the crossover of the P loop `Kp k_h / s` (flow integrates into force)
//! at the configured bandwidth `w_c`; `Ki = Kp w_c / 10` (the integral's corner a decade
//! below) removes the steady-state error leakage would leave. The measured piston velocity
//! is fed forward into the valve command (`- g_v v`, `g_v = 1` unless
//! `velocity_compensation` says otherwise: the flow that lets the piston follow the
//! specimen without compressing the oil), the velocity compensation that force control of
//! servo-hydraulic actuators needs against their natural velocity feedback (Dyke et al.
//! 1995; Dimig et al. 1999 and Shield et al. 2001, effective force testing). It acts
//! through the valve, so the valve's lag leaves a residual `H_v = P (1 - g_v G) / (1 + P G
//! C)`; `g_v = 0` is a force loop without it, whose natural velocity feedback damps the
//! specimen heavily and lags the rendered force by milliseconds in the load band.
//!
//! Stroke control (the interlock's position hold, as a servo-hydraulic controller holds
//! on its own displacement transducer): `q_c = Kx (x - x_hold)`, the piston following the
//! flow through the oil column (`x = F / k_h - int q`, quasi-statically), so the hold is
//! as stiff as the oil column at once and the flow removes the offset. `Kx = wv / 10`
//! (nominal valve), far below the valve and the oil column's resonance with the specimen
//! (a gain margin near 9 at the presets). A force-loop hold through a servo-hydraulic
//! actuator milliseconds slow on a free specimen (the element gone) diverged.

use super::{params::ActuatorParams, Complex64, PlantState};

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServoHydraulic {
    /// Hydraulic stiffness `4 beta A^2 / V`, N/m.
    pub k_h_n_per_m: f64,
    /// Leakage decay rate `4 beta C_L / V`, 1/s.
    pub leak_per_s: f64,
    pub valve_omega: f64,
    pub valve_zeta: f64,
    /// Proportional gain, (m/s) per N.
    pub kp: f64,
    /// Integral gain, (m/s) per N s.
    pub ki: f64,
    /// Stroke control's gain, (m/s) per m.
    pub kx_per_s: f64,
    /// The fraction of the piston's velocity fed forward into the valve command.
    pub velocity_compensation: f64,
}

/// Hydraulic stiffness and leakage rate of a parameter set.
fn column(p: &ActuatorParams) -> (f64, f64) {
    let (beta, area, volume, leakage) = (p.si[4], p.si[5], p.si[6], p.si[8]);
    (
        4.0 * beta * area * area / volume,
        4.0 * beta * leakage / volume,
    )
}

impl ServoHydraulic {
    pub fn new(truth: &ActuatorParams, nominal: &ActuatorParams) -> ServoHydraulic {
        let (k_h, leak) = column(truth);
        let (k_h_nominal, _) = column(nominal);
        let omega_c = 2.0 * std::f64::consts::PI * nominal.si[7];
        let kp = omega_c / k_h_nominal;
        ServoHydraulic {
            k_h_n_per_m: k_h,
            leak_per_s: leak,
            valve_omega: 2.0 * std::f64::consts::PI * truth.si[2],
            valve_zeta: truth.si[3],
            kp,
            ki: kp * omega_c / 10.0,
            kx_per_s: 2.0 * std::f64::consts::PI * nominal.si[2] / 10.0,
            velocity_compensation: nominal.si[9],
        }
    }

    /// At rest holding `force_n` (with leakage, the valve's flow that makes it up).
    pub fn rest_state(&self, force_n: f64) -> PlantState {
        let q = self.leak_per_s * force_n / self.k_h_n_per_m;
        [force_n, q, 0.0, q / self.ki]
    }

    #[inline]
    pub fn derivative(&self, s: &PlantState, u: f64, v: f64) -> PlantState {
        let e = u - s[0];
        let q_c = self.kp * e + self.ki * s[3] - self.velocity_compensation * v;
        let w = self.valve_omega;
        [
            self.k_h_n_per_m * (s[1] + v) - self.leak_per_s * s[0],
            s[2],
            w * w * (q_c - s[1]) - 2.0 * self.valve_zeta * w * s[2],
            e,
        ]
    }

    /// In stroke control: the valve commanded from the position error (no force loop,
    /// its integral frozen).
    #[inline]
    pub fn stroke_derivative(&self, s: &PlantState, error_m: f64, v: f64) -> PlantState {
        let q_c = self.kx_per_s * error_m;
        let w = self.valve_omega;
        [
            self.k_h_n_per_m * (s[1] + v) - self.leak_per_s * s[0],
            s[2],
            w * w * (q_c - s[1]) - 2.0 * self.valve_zeta * w * s[2],
            0.0,
        ]
    }

    /// Back to force control: the integral is set as at rest under the force carried now,
    /// so the force loop starts without a step (its command is that force, `rig::servo`).
    pub fn switch_control(&self, s: &mut PlantState, stroke: bool) {
        if !stroke {
            s[3] = self.rest_state(s[0])[3];
        }
    }

    /// The pressure limit (relief valves): the force state stays within `force_max_n`.
    #[inline]
    pub fn end_substep(&self, s: &mut PlantState, force_max_n: f64) {
        s[0] = s[0].clamp(-force_max_n, force_max_n);
    }

    /// `(H_u, H_v)` without the transport delay.
    pub fn response(&self, omega: f64) -> (Complex64, Complex64) {
        let s = Complex64::new(0.0, omega);
        let w = self.valve_omega;
        let plant = self.k_h_n_per_m / (s + self.leak_per_s);
        let valve = w * w / (s * s + 2.0 * self.valve_zeta * w * s + w * w);
        let controller = self.kp + self.ki / s;
        let open = plant * valve * controller;
        (
            open / (1.0 + open),
            plant * (1.0 - self.velocity_compensation * valve) / (1.0 + open),
        )
    }
}
