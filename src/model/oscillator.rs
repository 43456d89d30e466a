//! A mass on the element driven by an external force (paper Fig. 9): offline simulation
//! (`simulate rail`, the paper's Figs. 11-14) and the simulated rig's specimen.
//!
//! State: displacement `x`, velocity `v`, and the element's internal force (`Fm` for the
//! consistent form, `F` for the paper form). The external force is linear in time over
//! an input step. Each input step is split into `n_sub` equal sub-steps integrated with
//! the classical 4th-order Runge-Kutta scheme; `n_sub` keeps `omega_max * h_sub <= 0.1`
//! (phase error ~1e-6 per cycle, so long free responses keep their phase), and the
//! relaxation rate `k2/c2` is far below it. `step` does not allocate.

use super::element::StepFlags;
use super::params::{consistent_static_force, paper_static_force, ElementModel, BASE_MIN};

/// Largest `omega h` allowed in one Runge-Kutta sub-step.
pub const MAX_OMEGA_H: f64 = 0.1;

/// Initial condition of an oscillator simulation (SPEC 2.3 `--start`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StartCondition {
    /// Null initial conditions: x = 0, v = 0, element force 0 (paper Fig. 11).
    Rest,
    /// Static equilibrium under the first external force sample.
    Static,
}

impl StartCondition {
    pub fn from_name(name: &str) -> Option<StartCondition> {
        match name {
            "rest" => Some(StartCondition::Rest),
            "static" => Some(StartCondition::Static),
            _ => None,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Derivative {
    dx: f64,
    dv: f64,
    dq: f64,
}

/// Mass on one element, integrated at a fixed input step.
#[derive(Debug, Clone, Copy)]
pub struct Oscillator {
    model: ElementModel,
    dt_s: f64,
    n_sub: u32,
    x_m: f64,
    v_m_per_s: f64,
    /// Internal element state: `Fm` (consistent), `F` (paper), unused (Kelvin-Voigt).
    q_n: f64,
    /// Constants of the derivative, computed once so a stage needs no division but one.
    coef: Coefficients,
    /// Viscous damping to ground in parallel with the element (the HIL rig's own
    /// damping in the offline reference), N s/m; 0 by default.
    extra_damping_ns_per_m: f64,
}

/// Per-oscillator constants of the right-hand side (see `Oscillator::derivative`).
#[derive(Debug, Clone, Copy, Default)]
struct Coefficients {
    inv_mass_per_kg: f64,
    /// Consistent: `(1 - chi) k1_0 / P0`; paper: `1 / P0`.
    base_slope: f64,
    /// Consistent: `1 / (1 - chi)`; paper: `chi`.
    exponent: f64,
    /// `k2/c2`, 1/s.
    rate_per_s: f64,
    /// Consistent: `k2_0 / k1_0 * k1_0 = k2_0` (tangent Maxwell stiffness factor).
    maxwell_n_per_m: f64,
    /// Paper: `k1_0 + k2_0`.
    k12_n_per_m: f64,
    /// Paper: `a k1_0`.
    a_k1_n_per_m_s: f64,
}

impl Coefficients {
    fn of(model: &ElementModel, mass_kg: f64) -> Coefficients {
        let inv_mass_per_kg = 1.0 / mass_kg;
        match model {
            ElementModel::Consistent(p) => Coefficients {
                inv_mass_per_kg,
                base_slope: (1.0 - p.chi) * p.k1_0_n_per_m / p.p0_n,
                exponent: 1.0 / (1.0 - p.chi),
                rate_per_s: p.relaxation_rate_per_s(),
                maxwell_n_per_m: p.k2_0_n_per_m,
                ..Coefficients::default()
            },
            ElementModel::Paper(p) => Coefficients {
                inv_mass_per_kg,
                base_slope: 1.0 / p.p0_n,
                exponent: p.chi,
                rate_per_s: p.relaxation_rate_per_s(),
                k12_n_per_m: p.k1_0_n_per_m + p.k2_0_n_per_m,
                a_k1_n_per_m_s: p.relaxation_rate_per_s() * p.k1_0_n_per_m,
                ..Coefficients::default()
            },
            ElementModel::KelvinVoigt(_) => Coefficients {
                inv_mass_per_kg,
                ..Coefficients::default()
            },
        }
    }
}

impl Oscillator {
    /// An oscillator stepping at `dt_s`, sub-stepped for forces up to `max_force_n`.
    pub fn new(model: ElementModel, mass_kg: f64, dt_s: f64, max_force_n: f64) -> Oscillator {
        assert!(
            mass_kg > 0.0 && dt_s > 0.0,
            "mass and step must be positive"
        );
        let stiffness = model.high_frequency_stiffness_n_per_m(max_force_n.abs());
        let omega = (stiffness / mass_kg).sqrt();
        let n_sub = ((omega * dt_s / MAX_OMEGA_H).ceil() as u32).max(1);
        Oscillator {
            model,
            dt_s,
            n_sub,
            x_m: 0.0,
            v_m_per_s: 0.0,
            q_n: 0.0,
            coef: Coefficients::of(&model, mass_kg),
            extra_damping_ns_per_m: 0.0,
        }
    }

    /// Adds a viscous damper to ground in parallel with the element, N s/m.
    pub fn with_extra_damping(mut self, damping_ns_per_m: f64) -> Oscillator {
        self.extra_damping_ns_per_m = damping_ns_per_m;
        self
    }

    pub fn substeps(&self) -> u32 {
        self.n_sub
    }

    /// Sets the initial condition; `force_n` is the external force at the start.
    pub fn start(&mut self, start: StartCondition, force_n: f64) {
        self.v_m_per_s = 0.0;
        match start {
            StartCondition::Rest => {
                self.x_m = 0.0;
                self.q_n = 0.0;
            }
            StartCondition::Static => {
                self.x_m = self.model.static_displacement_m(force_n);
                self.q_n = match &self.model {
                    ElementModel::Paper(p) => paper_static_force(p, self.x_m),
                    _ => 0.0,
                };
            }
        }
    }

    /// Sets position, velocity and a relaxed element (for the rig's own start-up).
    pub fn set_state(&mut self, x_m: f64, v_m_per_s: f64) {
        self.x_m = x_m;
        self.v_m_per_s = v_m_per_s;
        self.q_n = match &self.model {
            ElementModel::Paper(p) => paper_static_force(p, x_m),
            _ => 0.0,
        };
    }

    pub fn displacement_m(&self) -> f64 {
        self.x_m
    }

    pub fn velocity_m_per_s(&self) -> f64 {
        self.v_m_per_s
    }

    /// Force the element exerts on the mass (positive in compression), N.
    pub fn element_force_n(&self) -> f64 {
        self.element_force_at(self.x_m, self.v_m_per_s, self.q_n).0
    }

    /// Sets position, velocity and the element's internal state such that it exerts
    /// `element_force_n` there (an element caught moving, its relaxing branch loaded). A
    /// Kelvin-Voigt element has no such state.
    pub fn set_state_with_element_force(&mut self, x_m: f64, v_m_per_s: f64, element_force_n: f64) {
        self.x_m = x_m;
        self.v_m_per_s = v_m_per_s;
        self.q_n = match &self.model {
            ElementModel::Consistent(_) | ElementModel::Paper(_) => {
                element_force_n - self.element_force_at(x_m, v_m_per_s, 0.0).0
            }
            ElementModel::KelvinVoigt(_) => 0.0,
        };
    }

    #[inline]
    fn element_force_at(&self, x: f64, v: f64, q: f64) -> (f64, bool) {
        match &self.model {
            ElementModel::Consistent(p) => {
                let (fs, clamped) = consistent_static_force(p, x);
                (fs + q, clamped)
            }
            ElementModel::Paper(_) => (q, false),
            ElementModel::KelvinVoigt(p) => (p.k_n_per_m * x + p.c_ns_per_m * v, false),
        }
    }

    #[inline]
    fn derivative(&self, x: f64, v: f64, q: f64, external_n: f64) -> (Derivative, bool) {
        let c = &self.coef;
        let external_n = external_n - self.extra_damping_ns_per_m * v;
        match &self.model {
            ElementModel::Consistent(p) => {
                // Fs = P0 (base^(1/(1-chi)) - 1) and dFs/dz = k1_0 g(Fs) = k1_0 base^(1/(1-chi)) / base;
                // the Maxwell spring's stiffness is k2_0 g(Fs) = k2_0 base^(1/(1-chi)) / base.
                let raw_base = 1.0 + c.base_slope * x;
                let clamped = raw_base.is_nan() || raw_base < BASE_MIN;
                let base = if clamped { BASE_MIN } else { raw_base };
                let power = base.powf(c.exponent);
                let fs = p.p0_n * (power - 1.0);
                let maxwell = if clamped {
                    0.0
                } else {
                    c.maxwell_n_per_m * power / base
                };
                let d = Derivative {
                    dx: v,
                    dv: (external_n - fs - q) * c.inv_mass_per_kg,
                    dq: maxwell * v - c.rate_per_s * q,
                };
                (d, clamped)
            }
            ElementModel::Paper(_) => {
                let raw_base = 1.0 + q * c.base_slope;
                let clamped = raw_base.is_nan() || raw_base < BASE_MIN;
                let g = if clamped { BASE_MIN } else { raw_base }.powf(c.exponent);
                let u = c.k12_n_per_m * v + c.a_k1_n_per_m_s * x;
                let d = Derivative {
                    dx: v,
                    dv: (external_n - q) * c.inv_mass_per_kg,
                    dq: g * u - c.rate_per_s * q,
                };
                (d, clamped)
            }
            ElementModel::KelvinVoigt(p) => {
                let d = Derivative {
                    dx: v,
                    dv: (external_n - p.k_n_per_m * x - p.c_ns_per_m * v) * c.inv_mass_per_kg,
                    dq: 0.0,
                };
                (d, false)
            }
        }
    }

    /// Advances one input step with the external force going linearly from `f0_n` to
    /// `f1_n`. Returns flags raised during the step.
    #[inline]
    pub fn step(&mut self, f0_n: f64, f1_n: f64) -> StepFlags {
        if !(f0_n.is_finite() && f1_n.is_finite()) {
            return StepFlags::NONFINITE_INPUT;
        }
        let n = self.n_sub;
        let inv_n = 1.0 / n as f64;
        let h = self.dt_s * inv_n;
        let mut clamped = false;
        let (mut x, mut v, mut q) = (self.x_m, self.v_m_per_s, self.q_n);
        for i in 0..n {
            let s0 = i as f64 * inv_n;
            let s_half = (i as f64 + 0.5) * inv_n;
            let s1 = (i + 1) as f64 * inv_n;
            let fa = f0_n + (f1_n - f0_n) * s0;
            let fm = f0_n + (f1_n - f0_n) * s_half;
            let fb = f0_n + (f1_n - f0_n) * s1;
            let (k1, c1) = self.derivative(x, v, q, fa);
            let (k2, c2) = self.derivative(
                x + 0.5 * h * k1.dx,
                v + 0.5 * h * k1.dv,
                q + 0.5 * h * k1.dq,
                fm,
            );
            let (k3, c3) = self.derivative(
                x + 0.5 * h * k2.dx,
                v + 0.5 * h * k2.dv,
                q + 0.5 * h * k2.dq,
                fm,
            );
            let (k4, c4) = self.derivative(x + h * k3.dx, v + h * k3.dv, q + h * k3.dq, fb);
            clamped |= c1 || c2 || c3 || c4;
            x += h / 6.0 * (k1.dx + 2.0 * k2.dx + 2.0 * k3.dx + k4.dx);
            v += h / 6.0 * (k1.dv + 2.0 * k2.dv + 2.0 * k3.dv + k4.dv);
            q += h / 6.0 * (k1.dq + 2.0 * k2.dq + 2.0 * k3.dq + k4.dq);
            if let ElementModel::Paper(p) = &self.model {
                q = q.max(-p.p0_n * (1.0 - BASE_MIN));
            }
        }
        self.x_m = x;
        self.v_m_per_s = v;
        self.q_n = q;
        // The end state is out of the domain if its power-law base is (no power needed).
        let end_base = match &self.model {
            ElementModel::Consistent(_) => 1.0 + self.coef.base_slope * x,
            ElementModel::Paper(_) => 1.0 + self.coef.base_slope * q,
            ElementModel::KelvinVoigt(_) => 1.0,
        };
        if clamped || end_base.is_nan() || end_base < BASE_MIN {
            StepFlags::TENSION_CLAMPED
        } else {
            StepFlags::NONE
        }
    }
}

/// One sample of an oscillator simulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RailSample {
    pub displacement_m: f64,
    pub velocity_m_per_s: f64,
    pub element_force_n: f64,
}

/// Simulates a mass on the element under an external force history at a uniform step.
pub fn simulate_rail(
    model: ElementModel,
    mass_kg: f64,
    dt_s: f64,
    external_force_n: &[f64],
    start: StartCondition,
) -> (Vec<RailSample>, StepFlags) {
    let mut out = Vec::with_capacity(external_force_n.len());
    let Some(&f_first) = external_force_n.first() else {
        return (out, StepFlags::NONE);
    };
    let max_force = external_force_n.iter().fold(0.0f64, |m, f| m.max(f.abs()));
    // Overshoot of a suddenly applied load reaches twice the load: size sub-steps for it.
    let mut osc = Oscillator::new(model, mass_kg, dt_s, 2.0 * max_force);
    osc.start(start, f_first);
    let sample = |o: &Oscillator| RailSample {
        displacement_m: o.displacement_m(),
        velocity_m_per_s: o.velocity_m_per_s(),
        element_force_n: o.element_force_n(),
    };
    out.push(sample(&osc));
    let mut all_flags = StepFlags::NONE;
    for pair in external_force_n.windows(2) {
        all_flags |= osc.step(pair[0], pair[1]);
        out.push(sample(&osc));
    }
    (out, all_flags)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hil::config::default_hil_config;

    #[test]
    fn a_state_set_with_an_element_force_exerts_that_force() {
        let element = default_hil_config().unwrap().model.element;
        let mut osc = Oscillator::new(element, 200.0, 1.0 / 4096.0, 1e5);
        let (x, v) = (5.0e-4, 0.02);
        osc.set_state(x, v);
        let relaxed = osc.element_force_n();
        assert!(relaxed > 0.0, "compressed: {relaxed} N");
        osc.set_state_with_element_force(x, v, relaxed + 3000.0);
        assert!((osc.element_force_n() - (relaxed + 3000.0)).abs() < 1e-9);
        assert_eq!((osc.displacement_m(), osc.velocity_m_per_s()), (x, v));
        // The loaded branch is state: stepping with the force that balances the relaxed
        // element leaves the mass with 3 kN to spare, towards extension.
        let mut relaxed_osc = osc;
        relaxed_osc.set_state(x, v);
        osc.step(relaxed, relaxed);
        relaxed_osc.step(relaxed, relaxed);
        assert!(osc.velocity_m_per_s() < relaxed_osc.velocity_m_per_s());
    }
}
