//! The rig's force actuator: parameters (`params`), one plant per kind, their linear frequency responses and effective delay, and the truth record; owns the actuator's dynamics and must not do I/O or allocate per step.
//!
//! Every plant maps the command `u` (N, delayed by the transport delay and zero-order
//! held over each loop period by `RigPhysics`) and the specimen's velocity `v` (m/s,
//! positive in compression; the actuator moves with the specimen) to the force it applies
//! (positive: pushing back against compression). Linearised:
//! `F = H_u(jw) u + H_v(jw) v`, `H_u` including the transport delay.

pub mod electrodynamic;
pub mod lag_delay;
pub mod params;
pub mod record;
pub mod servo_hydraulic;

pub use electrodynamic::Electrodynamic;
pub use lag_delay::LagDelay;
pub use params::{
    preset, ActuatorConfig, ActuatorKind, ActuatorParams, ParamKey, Preset, Rule, MAX_PARAMS,
    PRESETS,
};
pub use realfft::num_complex::Complex64;
pub use record::{actuator_truth_records, ActuatorParamRecord, ActuatorTruthRecord};
pub use servo_hydraulic::ServoHydraulic;

/// A plant's internal states (unused ones stay 0).
pub type PlantState = [f64; 4];

/// The dynamics of one kind.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PlantKind {
    LagDelay(LagDelay),
    ServoHydraulic(ServoHydraulic),
    Electrodynamic(Electrodynamic),
}

/// An actuator plant: its true parameters, and a controller tuned on the nominal ones.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ActuatorPlant {
    pub truth: ActuatorParams,
    pub kind: PlantKind,
}

/// Effective delay and amplitude ratio over a band (`ActuatorPlant::effective_delay`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct EffectiveDelay {
    /// Mean of `-phase / omega` over the band, s.
    pub delay_s: f64,
    /// Mean of `|F / u|` over the band.
    pub amplitude_ratio: f64,
    /// Smallest and largest `|F / u|` over the band.
    pub amplitude_ratio_min: f64,
    pub amplitude_ratio_max: f64,
}

/// The band of `effective_delay`, Hz, and its points (0.5 Hz apart).
pub const DELAY_BAND_HZ: (f64, f64) = (1.0, 20.0);
const DELAY_BAND_POINTS: usize = 39;

impl ActuatorPlant {
    /// The plant of `truth` with its controller tuned on `nominal` (same kind).
    pub fn new(truth: &ActuatorParams, nominal: &ActuatorParams) -> ActuatorPlant {
        assert_eq!(truth.kind, nominal.kind, "truth and nominal of one kind");
        let kind = match truth.kind {
            ActuatorKind::LagDelay => PlantKind::LagDelay(LagDelay::new(truth)),
            ActuatorKind::ServoHydraulic => {
                PlantKind::ServoHydraulic(ServoHydraulic::new(truth, nominal))
            }
            ActuatorKind::Electrodynamic => {
                PlantKind::Electrodynamic(Electrodynamic::new(truth, nominal))
            }
        };
        ActuatorPlant {
            truth: *truth,
            kind,
        }
    }

    /// The plant of a configuration as the rig has it (the perturbed truth).
    pub fn from_config(cfg: &ActuatorConfig) -> ActuatorPlant {
        ActuatorPlant::new(&cfg.truth(), &cfg.nominal)
    }

    pub fn transport_delay_s(&self) -> f64 {
        self.truth.transport_delay_s()
    }

    pub fn force_max_n(&self) -> f64 {
        self.truth.force_max_n()
    }

    /// Mass that moves with the specimen (an electrodynamic armature), kg.
    pub fn moving_mass_kg(&self) -> f64 {
        match &self.kind {
            PlantKind::Electrodynamic(e) => e.moving_mass_kg,
            _ => 0.0,
        }
    }

    /// The states at rest under the command `force_n` (held since ever).
    pub fn rest_state(&self, force_n: f64) -> PlantState {
        match &self.kind {
            PlantKind::LagDelay(p) => p.rest_state(force_n),
            PlantKind::ServoHydraulic(p) => p.rest_state(force_n),
            PlantKind::Electrodynamic(p) => p.rest_state(force_n),
        }
    }

    /// The states' time derivative under command `u` and specimen velocity `v`.
    #[inline]
    pub fn derivative(&self, s: &PlantState, u: f64, v: f64) -> PlantState {
        match &self.kind {
            PlantKind::LagDelay(p) => p.derivative(s, u),
            PlantKind::ServoHydraulic(p) => p.derivative(s, u, v),
            PlantKind::Electrodynamic(p) => p.derivative(s, u, v),
        }
    }

    /// Whether the actuator can hold position itself (stroke control on its own
    /// displacement transducer): a servo-hydraulic actuator can; the others hold through
    /// a position loop on their force (`rig::servo`).
    pub fn has_stroke_control(&self) -> bool {
        matches!(self.kind, PlantKind::ServoHydraulic(_))
    }

    /// The states' time derivative in stroke control, `error_m` the displacement beyond
    /// the position to hold (m, positive in compression), `v` the specimen's velocity.
    /// Only for a plant with `has_stroke_control`; the others keep their last force.
    #[inline]
    pub fn stroke_derivative(&self, s: &PlantState, error_m: f64, v: f64) -> PlantState {
        match &self.kind {
            PlantKind::ServoHydraulic(p) => p.stroke_derivative(s, error_m, v),
            _ => [0.0; 4],
        }
    }

    /// Called when the plant switches between force control and stroke control
    /// (`stroke` true: into stroke control), so the switch is bumpless.
    pub fn switch_control(&self, s: &mut PlantState, stroke: bool) {
        if let PlantKind::ServoHydraulic(p) = &self.kind {
            p.switch_control(s, stroke);
        }
    }

    /// The force the states make (before saturation), N.
    #[inline]
    pub fn force_n(&self, s: &PlantState, v: f64) -> f64 {
        match &self.kind {
            PlantKind::Electrodynamic(p) => p.force_n(s, v),
            _ => s[0],
        }
    }

    /// The applied force: `force_n` within `+-force_max_n`.
    #[inline]
    pub fn applied_force_n(&self, s: &PlantState, v: f64) -> f64 {
        let f = self.truth.force_max_n();
        self.force_n(s, v).clamp(-f, f)
    }

    /// Before each RK4 sub-step, with the command held over it.
    #[inline]
    pub fn begin_substep(&self, s: &mut PlantState, u: f64) {
        if let PlantKind::LagDelay(p) = &self.kind {
            p.begin_substep(s, u);
        }
    }

    /// After each RK4 sub-step (limits on states).
    #[inline]
    pub fn end_substep(&self, s: &mut PlantState) {
        if let PlantKind::ServoHydraulic(p) = &self.kind {
            p.end_substep(s, self.truth.force_max_n());
        }
    }

    /// After each period (the lag-delay force state is clamped here, as it always was).
    #[inline]
    pub fn end_period(&self, s: &mut PlantState) {
        if let PlantKind::LagDelay(_) = &self.kind {
            let f = self.truth.force_max_n();
            s[0] = s[0].clamp(-f, f);
        }
    }

    /// How many of the plant's own poles lie in the right half-plane: the eigenvalues of
    /// its state matrix with the command and the specimen's velocity held at zero (the
    /// actuator on a blocked piston, its controller closed). `H_u` and `H_v` share these
    /// poles; a servo loop that is unstable by itself (a force loop tuned on nominal values
    /// the hardware does not have) has some, and the linearised loop's stability count
    /// must know them (`hil::check`). Poles on the axis (integrators) are not counted.
    pub fn unstable_poles(&self) -> usize {
        let column = |j: usize| {
            let mut e = [0.0; 4];
            e[j] = 1.0;
            self.derivative(&e, 0.0, 0.0)
        };
        let a = nalgebra::Matrix4::from_fn(|i, j| column(j)[i]);
        count_unstable(a.complex_eigenvalues().iter())
    }

    /// How many poles the actuator has in the right half-plane with a free specimen of
    /// `mass_kg` and `damping_ns_per_m` on it and a zero command (no element rendered):
    /// a force loop that the oil column's resonance with the specimen, say, makes unstable
    /// by itself. Poles on the axis (the free mass, integrators) are not counted.
    pub fn unstable_poles_on_mass(&self, mass_kg: f64, damping_ns_per_m: f64) -> usize {
        // States: specimen displacement, velocity, the plant's four.
        let m = mass_kg + self.moving_mass_kg();
        let derivative = |x: &[f64; 6]| -> [f64; 6] {
            let plant: PlantState = [x[2], x[3], x[4], x[5]];
            let d = self.derivative(&plant, 0.0, x[1]);
            let accel = (-damping_ns_per_m * x[1] - self.force_n(&plant, x[1])) / m;
            [x[1], accel, d[0], d[1], d[2], d[3]]
        };
        let a = nalgebra::Matrix6::from_fn(|i, j| {
            let mut e = [0.0; 6];
            e[j] = 1.0;
            derivative(&e)[i]
        });
        count_unstable(a.complex_eigenvalues().iter())
    }

    /// `(H_u(jw), H_v(jw))` of the linearised plant (no saturation); `H_u` includes the
    /// transport delay; `H_v` is zero for lag-delay.
    pub fn response(&self, omega: f64) -> (Complex64, Complex64) {
        let delay = Complex64::from_polar(1.0, -omega * self.transport_delay_s());
        let (h_u, h_v) = match &self.kind {
            PlantKind::LagDelay(p) => (p.response(omega), Complex64::new(0.0, 0.0)),
            PlantKind::ServoHydraulic(p) => p.response(omega),
            PlantKind::Electrodynamic(p) => p.response(omega),
        };
        (h_u * delay, h_v)
    }

    /// Force per command with the specimen on an element of stiffness `k` (quasi-static:
    /// `v = j w F / K`): `H_u / (1 - j w H_v / K)`. This is the delay a lead must make up
    /// for: with the element rendered faithfully the actuator's force is the element's,
    /// `F = K z`, and the rendering `H_u e^(j w L) + j w H_v / K` is 1 exactly when
    /// `e^(j w L) = (1 - j w H_v / K) / H_u`. (At another lead the force per command
    /// differs: the velocity term answers the displacement, not the command; at no lead it
    /// is `H_u + j w H_v / K`.)
    pub fn response_on_element(&self, omega: f64, element_stiffness_n_per_m: f64) -> Complex64 {
        let (h_u, h_v) = self.response(omega);
        h_u / (1.0 - Complex64::new(0.0, omega) * h_v / element_stiffness_n_per_m)
    }

    /// The effective delay from command to force and the amplitude ratio over 1-20 Hz
    /// with the specimen on an element of that stiffness (`response_on_element`).
    pub fn effective_delay(&self, element_stiffness_n_per_m: f64) -> EffectiveDelay {
        let (f0, f1) = DELAY_BAND_HZ;
        let mut previous_phase = 0.0;
        let (mut delay_sum, mut amp_sum) = (0.0, 0.0);
        let (mut amp_min, mut amp_max) = (f64::INFINITY, 0.0f64);
        for i in 0..DELAY_BAND_POINTS {
            let f = f0 + (f1 - f0) * i as f64 / (DELAY_BAND_POINTS - 1) as f64;
            let omega = 2.0 * std::f64::consts::PI * f;
            let h = self.response_on_element(omega, element_stiffness_n_per_m);
            // Unwrapped from the band's start (a continuous phase, small at 1 Hz).
            let mut phase = h.arg();
            while phase - previous_phase > std::f64::consts::PI {
                phase -= 2.0 * std::f64::consts::PI;
            }
            while phase - previous_phase < -std::f64::consts::PI {
                phase += 2.0 * std::f64::consts::PI;
            }
            previous_phase = phase;
            delay_sum += -phase / omega;
            let amp = h.norm();
            amp_sum += amp;
            amp_min = amp_min.min(amp);
            amp_max = amp_max.max(amp);
        }
        let n = DELAY_BAND_POINTS as f64;
        EffectiveDelay {
            delay_s: delay_sum / n,
            amplitude_ratio: amp_sum / n,
            amplitude_ratio_min: amp_min,
            amplitude_ratio_max: amp_max,
        }
    }
}

impl ActuatorParams {
    /// `effective_delay(element_stiffness_n_per_m)` of these parameters (controller tuned
    /// on them).
    pub fn effective_delay(&self, element_stiffness_n_per_m: f64) -> EffectiveDelay {
        ActuatorPlant::new(self, self).effective_delay(element_stiffness_n_per_m)
    }
}

#[cfg(test)]
mod tests;

/// Eigenvalues with a positive real part beyond round-off (a millionth of the largest).
fn count_unstable<'a>(eigen: impl Iterator<Item = &'a nalgebra::Complex<f64>> + Clone) -> usize {
    let scale = eigen.clone().map(|l| l.norm()).fold(0.0f64, f64::max);
    eigen.filter(|l| l.re > 1e-6 * scale.max(1.0)).count()
}
