//! The electrodynamic actuator: current amplifier, coil with back-EMF, force constant, suspension and moving mass; owns its states and must not allocate.
//!
//! States: `V` (amplifier output, V), `i` (coil current, A), `y` (armature travel from
//! rest, m, positive in compression), `J` (the current error's integral, A s). The
//! amplifier is a PI current loop (as current-mode amplifiers are: back-EMF rejected at
//! low frequency) whose voltage stage has the configured bandwidth `wa`:
//! `dV/dt = wa (Ga (e + wi J) - V)`, `e = c u(t - tau) - i`, `dJ/dt = e`,
//! `L di/dt = V - R i + Kf v` (back-EMF: the armature pushed in compression raises the
//! current), force on the specimen `F = Kf i + ks y + cs v`; the moving mass rides with
//! the specimen (added to its mass; `H_v` holds its `j w m`). From the nominal parameters:
//! `Ga` places the proportional loop's poles at damping 0.707 (natural frequency `wn`),
//! `wi = wn / 4`, and `c = 1 / Kf` (force per command 1 at DC).

use super::{params::ActuatorParams, Complex64, PlantState};

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Electrodynamic {
    pub amp_omega: f64,
    pub resistance_ohm: f64,
    pub inductance_h: f64,
    pub force_constant_n_per_a: f64,
    pub suspension_n_per_m: f64,
    pub damping_ns_per_m: f64,
    pub moving_mass_kg: f64,
    /// Amplifier current-loop gain, V/A.
    pub gain_v_per_a: f64,
    /// Integral corner of the current loop, rad/s.
    pub integral_omega: f64,
    /// Current command per force command, A/N.
    pub calibration_a_per_n: f64,
}

/// The amplifier gain giving the proportional current loop damping 0.707 (at least a
/// tenth of the coil's resistance), and that loop's natural frequency.
fn amplifier_gain(p: &ActuatorParams) -> (f64, f64) {
    let wa = 2.0 * std::f64::consts::PI * p.si[2];
    let (r, l) = (p.si[3], p.si[4]);
    let wn = (r / l + wa) / std::f64::consts::SQRT_2;
    ((wn * wn * l / wa - r).max(0.1 * r), wn)
}

impl Electrodynamic {
    pub fn new(truth: &ActuatorParams, nominal: &ActuatorParams) -> Electrodynamic {
        let (gain, wn) = amplifier_gain(nominal);
        Electrodynamic {
            amp_omega: 2.0 * std::f64::consts::PI * truth.si[2],
            resistance_ohm: truth.si[3],
            inductance_h: truth.si[4],
            force_constant_n_per_a: truth.si[5],
            suspension_n_per_m: truth.si[6],
            damping_ns_per_m: truth.si[7],
            moving_mass_kg: truth.si[8],
            gain_v_per_a: gain,
            integral_omega: wn / 4.0,
            calibration_a_per_n: 1.0 / nominal.si[5],
        }
    }

    /// At rest under the command `force_n` (the force it makes differs when the true
    /// force constant departs from the nominal one: no force feedback).
    pub fn rest_state(&self, force_n: f64) -> PlantState {
        let i = self.calibration_a_per_n * force_n;
        let v = self.resistance_ohm * i;
        [v, i, 0.0, v / (self.gain_v_per_a * self.integral_omega)]
    }

    #[inline]
    pub fn derivative(&self, s: &PlantState, u: f64, v: f64) -> PlantState {
        let e = self.calibration_a_per_n * u - s[1];
        [
            self.amp_omega * (self.gain_v_per_a * (e + self.integral_omega * s[3]) - s[0]),
            (s[0] - self.resistance_ohm * s[1] + self.force_constant_n_per_a * v)
                / self.inductance_h,
            v,
            e,
        ]
    }

    #[inline]
    pub fn force_n(&self, s: &PlantState, v: f64) -> f64 {
        self.force_constant_n_per_a * s[1]
            + self.suspension_n_per_m * s[2]
            + self.damping_ns_per_m * v
    }

    /// `(H_u, H_v)` without the transport delay; `H_v` includes the moving mass.
    pub fn response(&self, omega: f64) -> (Complex64, Complex64) {
        let s = Complex64::new(0.0, omega);
        let (l, r, wa, g, kf) = (
            self.inductance_h,
            self.resistance_ohm,
            self.amp_omega,
            self.gain_v_per_a,
            self.force_constant_n_per_a,
        );
        let wi = self.integral_omega;
        // s (L s + R)(s + wa) i = wa G (s + wi)(c u - i) + s (s + wa) Kf v
        let d = s * (l * s + r) * (s + wa) + wa * g * (s + wi);
        let h_u = kf * g * wa * (s + wi) * self.calibration_a_per_n / d;
        let h_v = kf * kf * s * (s + wa) / d
            + self.damping_ns_per_m
            + self.suspension_n_per_m / s
            + self.moving_mass_kg * s;
        (h_u, h_v)
    }
}
