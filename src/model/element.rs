//! Fixed-step force from imposed displacement (SPEC 2.2): the emulator's model step.
//!
//! Each step takes the displacement at the end of the step and returns the element force
//! there. Within a step `z` is taken linear in time and the preload-dependent parameters
//! frozen, and the Maxwell branch is integrated exactly (exponential integrator), so the
//! scheme is stable for any `dt`. `step` does not allocate, read a clock or do I/O.

use super::params::{consistent_static_force, paper_static_force, ElementModel, BASE_MIN};

/// Flags raised by a step. A bit set, `Copy`, so the loop can report it as data.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct StepFlags(pub u8);

impl StepFlags {
    pub const NONE: StepFlags = StepFlags(0);
    /// Tension beyond the model's domain: the power-law base was clamped at `BASE_MIN`.
    pub const TENSION_CLAMPED: StepFlags = StepFlags(1);
    /// The input was NaN or infinite: the state was held and the last force returned.
    pub const NONFINITE_INPUT: StepFlags = StepFlags(2);

    #[inline]
    pub fn contains(self, other: StepFlags) -> bool {
        self.0 & other.0 == other.0 && other.0 != 0
    }

    #[inline]
    pub fn is_empty(self) -> bool {
        self.0 == 0
    }
}

impl std::ops::BitOr for StepFlags {
    type Output = StepFlags;
    fn bitor(self, rhs: StepFlags) -> StepFlags {
        StepFlags(self.0 | rhs.0)
    }
}

impl std::ops::BitOrAssign for StepFlags {
    fn bitor_assign(&mut self, rhs: StepFlags) {
        self.0 |= rhs.0;
    }
}

/// `phi1(x) = (1 - e^-x)/x` and `phi2(x) = (1 - phi1(x))/x`, accurate for small `x`.
pub fn phi_functions(x: f64) -> (f64, f64) {
    if x < 1e-3 {
        // Taylor series: the closed forms cancel catastrophically for small x.
        let phi1 = 1.0 - x / 2.0 + x * x / 6.0 - x * x * x / 24.0;
        let phi2 = 0.5 - x / 6.0 + x * x / 24.0 - x * x * x / 120.0;
        (phi1, phi2)
    } else {
        let phi1 = -(-x).exp_m1() / x;
        (phi1, (1.0 - phi1) / x)
    }
}

#[derive(Debug, Clone, Copy)]
enum State {
    /// Consistent form: elastic part `Fs` and Maxwell branch force `Fm`.
    Consistent { fs_n: f64, fm_n: f64 },
    /// Paper form: the total force is the state.
    Paper { force_n: f64 },
    /// Kelvin-Voigt: stateless apart from the previous displacement.
    KelvinVoigt { force_n: f64 },
}

/// Force-from-displacement stepper for one element at a fixed step `dt`.
#[derive(Debug, Clone, Copy)]
pub struct ForceStepper {
    model: ElementModel,
    dt_s: f64,
    /// `e^{-a dt}` with `a = k2/c2`.
    decay: f64,
    /// `phi1(a dt)`.
    phi1: f64,
    /// `dt phi1(a dt)` and `dt phi2(a dt)`: weights of a linear input over the step.
    weight_0: f64,
    weight_1: f64,
    z_prev_m: f64,
    state: State,
}

impl ForceStepper {
    /// A stepper with step `dt_s`, starting in static equilibrium at `z0_m`.
    pub fn new(model: ElementModel, dt_s: f64, z0_m: f64) -> ForceStepper {
        assert!(dt_s > 0.0 && dt_s.is_finite(), "step must be positive");
        let rate = model.zener().map_or(0.0, |p| p.relaxation_rate_per_s());
        let x = rate * dt_s;
        let (phi1, phi2) = phi_functions(x);
        let mut stepper = ForceStepper {
            model,
            dt_s,
            decay: (-x).exp(),
            phi1,
            weight_0: dt_s * phi1,
            weight_1: dt_s * phi2,
            z_prev_m: 0.0,
            state: State::KelvinVoigt { force_n: 0.0 },
        };
        stepper.reset_static(z0_m);
        stepper
    }

    pub fn model(&self) -> &ElementModel {
        &self.model
    }

    pub fn dt_s(&self) -> f64 {
        self.dt_s
    }

    /// Puts the element at rest in static equilibrium at `z_m` (relaxed Maxwell branch).
    pub fn reset_static(&mut self, z_m: f64) {
        self.z_prev_m = z_m;
        self.state = match &self.model {
            ElementModel::Consistent(p) => State::Consistent {
                fs_n: consistent_static_force(p, z_m).0,
                fm_n: 0.0,
            },
            ElementModel::Paper(p) => State::Paper {
                force_n: paper_static_force(p, z_m),
            },
            ElementModel::KelvinVoigt(p) => State::KelvinVoigt {
                force_n: p.k_n_per_m * z_m,
            },
        };
    }

    /// The consistent form's Maxwell-branch force (its only state not a function of the
    /// displacement), `None` for the other forms.
    pub fn maxwell_force_n(&self) -> Option<f64> {
        match self.state {
            State::Consistent { fm_n, .. } => Some(fm_n),
            _ => None,
        }
    }

    /// Puts the consistent form's Maxwell branch on its periodic state, given its force
    /// `start_n` one period of `period_steps` steps ago: over a period of a periodic input
    /// the branch maps `fm -> D fm + c` with `D = decay^period_steps` (it is linear in
    /// `fm` with a constant step), so its fixed point is `(fm_now - D start_n) / (1 - D)`.
    /// No-op for the other forms (the paper form's force is not linear in its state), and
    /// when a period takes less than `min_decay` off the branch (`1 - D` would amplify the
    /// rounding of its increment).
    pub fn jump_maxwell_to_periodic(&mut self, start_n: f64, period_steps: usize, min_decay: f64) {
        let d = self.decay.powi(period_steps as i32);
        if let State::Consistent { fm_n, .. } = &mut self.state {
            if d < 1.0 - min_decay {
                *fm_n = (*fm_n - d * start_n) / (1.0 - d);
            }
        }
    }

    /// Replaces the element's parameters mid-run (self-heating: the same element at another
    /// temperature) without a force jump from re-parameterisation: the elastic force is
    /// re-evaluated at the current displacement and the Maxwell branch's force scaled with
    /// its spring. No allocation; the form must stay the same.
    pub fn retune(&mut self, model: ElementModel) {
        let old_k2 = self.model.zener().map_or(1.0, |p| p.k2_0_n_per_m);
        let rate = model.zener().map_or(0.0, |p| p.relaxation_rate_per_s());
        let x = rate * self.dt_s;
        let (phi1, phi2) = phi_functions(x);
        self.decay = (-x).exp();
        self.phi1 = phi1;
        self.weight_0 = self.dt_s * phi1;
        self.weight_1 = self.dt_s * phi2;
        let z = self.z_prev_m;
        match (&model, &mut self.state) {
            (ElementModel::Consistent(p), State::Consistent { fs_n, fm_n }) => {
                *fs_n = consistent_static_force(p, z).0;
                *fm_n *= p.k2_0_n_per_m / old_k2.max(1e-300);
            }
            (ElementModel::Paper(p), State::Paper { force_n }) => {
                *force_n *= p.k1_0_n_per_m / self.model.zener().map_or(1.0, |q| q.k1_0_n_per_m);
            }
            _ => {}
        }
        self.model = model;
    }

    /// Power dissipated in the element's dashpot now, W: `Fm^2 / c2` (consistent form,
    /// `c2 = c2_0 g(Fs)`), `c v^2` (Kelvin-Voigt), 0 for the paper form (its Maxwell
    /// branch is not a state of its own).
    #[inline]
    pub fn dashpot_power_w(&self, velocity_m_per_s: f64) -> f64 {
        match (&self.model, self.state) {
            (ElementModel::Consistent(p), State::Consistent { fs_n, fm_n }) => {
                let c2 = p.c2_0_ns_per_m * p.preload_factor(fs_n);
                fm_n * fm_n / c2.max(1e-300)
            }
            (ElementModel::KelvinVoigt(p), _) => p.c_ns_per_m * velocity_m_per_s * velocity_m_per_s,
            _ => 0.0,
        }
    }

    /// Current element force, N.
    #[inline]
    pub fn force_n(&self) -> f64 {
        match self.state {
            State::Consistent { fs_n, fm_n } => fs_n + fm_n,
            State::Paper { force_n } | State::KelvinVoigt { force_n } => force_n,
        }
    }

    /// Displacement of the last accepted step, m.
    pub fn displacement_m(&self) -> f64 {
        self.z_prev_m
    }

    /// Drift of the force at fixed displacement now (the Maxwell branch relaxing), N/s:
    /// `-a Fm` in the consistent form, `a (k1 z - F)` in the paper form (Eq. 3 with
    /// `dz/dt = 0`), 0 for Kelvin-Voigt.
    #[inline]
    pub fn relaxation_rate_n_per_s(&self) -> f64 {
        match (&self.model, self.state) {
            (ElementModel::Consistent(p), State::Consistent { fm_n, .. }) => {
                -p.relaxation_rate_per_s() * fm_n
            }
            (ElementModel::Paper(p), State::Paper { force_n }) => {
                let (g, _) = paper_factor(p.chi, p.p0_n, force_n);
                p.relaxation_rate_per_s() * (p.k1_0_n_per_m * g * self.z_prev_m - force_n)
            }
            _ => 0.0,
        }
    }

    /// The force that sets the element's preload factor now: the elastic force `Fs` in the
    /// consistent form, the total force in the paper form, the force for Kelvin-Voigt, N.
    #[inline]
    pub fn operating_force_n(&self) -> f64 {
        match self.state {
            State::Consistent { fs_n, .. } => fs_n,
            State::Paper { force_n } | State::KelvinVoigt { force_n } => force_n,
        }
    }

    /// Advances one step to displacement `z_m`; returns the force at the step's end.
    #[inline]
    pub fn step(&mut self, z_m: f64) -> (f64, StepFlags) {
        self.step_with_static_force(z_m, None)
    }

    /// `step`, with the consistent form's static force `Fs(z_m)` (and whether it was
    /// clamped) given by the caller when it has it already (a periodic input evaluated
    /// once per period); it must be `consistent_static_force(model, z_m)`.
    #[inline]
    pub fn step_with_static_force(
        &mut self,
        z_m: f64,
        static_force: Option<(f64, bool)>,
    ) -> (f64, StepFlags) {
        if !z_m.is_finite() {
            return (self.force_n(), StepFlags::NONFINITE_INPUT);
        }
        let z0 = self.z_prev_m;
        self.z_prev_m = z_m;
        let mut flags = StepFlags::NONE;
        match (&self.model, &mut self.state) {
            (ElementModel::Consistent(p), State::Consistent { fs_n, fm_n }) => {
                let (fs1, clamped) =
                    static_force.unwrap_or_else(|| consistent_static_force(p, z_m));
                if clamped {
                    flags |= StepFlags::TENSION_CLAMPED;
                }
                // dFm/dt = k2 dz/dt - a Fm with k2 = k2_0 g(Fs) = (k2_0/k1_0) dFs/dt:
                // the Maxwell spring sees the increment of Fs scaled by k2_0/k1_0, taken
                // linear in time over the step and integrated exactly.
                let ratio = p.k2_0_n_per_m / p.k1_0_n_per_m;
                *fm_n = self.decay * *fm_n + ratio * (fs1 - *fs_n) * self.phi1;
                *fs_n = fs1;
            }
            (ElementModel::Paper(p), State::Paper { force_n }) => {
                // dF/dt = -a F + g(F) u(t), u = (k1_0 + k2_0) dz/dt + a k1_0 z (Eq. 3).
                let a = p.relaxation_rate_per_s();
                let velocity = (z_m - z0) / self.dt_s;
                let u0 = (p.k1_0_n_per_m + p.k2_0_n_per_m) * velocity + a * p.k1_0_n_per_m * z0;
                let u1 = u0 + a * p.k1_0_n_per_m * (z_m - z0);
                let forcing = u0 * self.weight_0 + (u1 - u0) * self.weight_1;
                let f0 = *force_n;
                // Predictor with g at the step start, corrector with g at the midpoint.
                let (g0, clamped0) = paper_factor(p.chi, p.p0_n, f0);
                let f_pred = self.decay * f0 + g0 * forcing;
                let (g_mid, clamped_mid) = paper_factor(p.chi, p.p0_n, 0.5 * (f0 + f_pred));
                let f1 = self.decay * f0 + g_mid * forcing;
                let (_, clamped1) = paper_factor(p.chi, p.p0_n, f1);
                if clamped0 || clamped_mid || clamped1 {
                    flags |= StepFlags::TENSION_CLAMPED;
                }
                *force_n = f1.max(-p.p0_n * (1.0 - BASE_MIN));
            }
            (ElementModel::KelvinVoigt(p), State::KelvinVoigt { force_n }) => {
                let velocity = (z_m - z0) / self.dt_s;
                *force_n = p.k_n_per_m * z_m + p.c_ns_per_m * velocity;
            }
            _ => unreachable!("state always matches the model's form"),
        }
        (self.force_n(), flags)
    }
}

/// `g(F) = (1 + F/P0)^chi` and whether the base was clamped.
#[inline]
pub(crate) fn paper_factor(chi: f64, p0_n: f64, force_n: f64) -> (f64, bool) {
    let raw = 1.0 + force_n / p0_n;
    // NaN counts as clamped too, so a NaN base can never reach `powf`.
    let clamped = raw.is_nan() || raw < BASE_MIN;
    (if clamped { BASE_MIN } else { raw }.powf(chi), clamped)
}

/// Simulates the force for a whole displacement history at a uniform step.
///
/// The element starts in static equilibrium at the first sample. Returns forces and the
/// union of flags raised. (Offline helper: allocates the output once.)
pub fn simulate_force(
    model: ElementModel,
    dt_s: f64,
    displacement_m: &[f64],
) -> (Vec<f64>, StepFlags) {
    let mut forces = Vec::with_capacity(displacement_m.len());
    let Some(&z0) = displacement_m.first() else {
        return (forces, StepFlags::NONE);
    };
    let mut stepper = ForceStepper::new(model, dt_s, z0);
    let mut all_flags = StepFlags::NONE;
    forces.push(stepper.force_n());
    for &z in &displacement_m[1..] {
        let (force, flags) = stepper.step(z);
        all_flags |= flags;
        forces.push(force);
    }
    (forces, all_flags)
}
