//! Element parameters for one modelled element (already multiplied by its length).
//!
//! Paper Eq. 1: `g(P) = (1 + P/P0)^chi`, `k1 = k1_0 g`, `k2 = k2_0 g`, `c2 = c2_0 g`.
//! Values here are per element, i.e. the per-metre values of the paper times `length_m`.

use std::fmt;

/// Smallest allowed base of the preload power law (`1 + P/P0`, or the base of `Fs`).
///
/// Below it the model is outside its domain (deep tension); the steppers clamp the base
/// here, keep going, and raise `StepFlags::TENSION_CLAMPED`. Not zero, so that powers
/// with negative exponents stay finite.
pub const BASE_MIN: f64 = 1e-6;

/// Which time-domain form of the element is integrated (SPEC 2.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Form {
    /// Tangent-stiffness form: `F = Fs(z) + Fm`; small-signal modulus equals Eq. 2 exactly.
    Consistent,
    /// Paper Eq. 3 with the preload replaced by the instantaneous force.
    Paper,
    /// Linear spring and dashpot in parallel (paper Sec. 3.2 comparison model).
    KelvinVoigt,
}

impl Form {
    pub const ALL: [Form; 3] = [Form::Consistent, Form::Paper, Form::KelvinVoigt];

    pub fn name(self) -> &'static str {
        match self {
            Form::Consistent => "consistent",
            Form::Paper => "paper",
            Form::KelvinVoigt => "kelvin-voigt",
        }
    }

    pub fn from_name(name: &str) -> Option<Form> {
        Form::ALL.into_iter().find(|form| form.name() == name)
    }
}

impl fmt::Display for Form {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Zener parameters of one element (per-metre values times length).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ZenerParams {
    /// Reference stiffness of the parallel spring, N/m.
    pub k1_0_n_per_m: f64,
    /// Reference stiffness of the Maxwell spring, N/m.
    pub k2_0_n_per_m: f64,
    /// Reference damping of the Maxwell dashpot, N s/m.
    pub c2_0_ns_per_m: f64,
    /// Preload exponent (0 gives the linear Zener model).
    pub chi: f64,
    /// Reference preload, N.
    pub p0_n: f64,
}

impl ZenerParams {
    /// Table 3 of the paper, per metre, scaled to `length_m`.
    pub fn paper_table3(length_m: f64) -> ZenerParams {
        ZenerParams {
            k1_0_n_per_m: 62e6 * length_m,
            k2_0_n_per_m: 9.6e6 * length_m,
            c2_0_ns_per_m: 0.7e6 * length_m,
            chi: 0.21,
            p0_n: 64e3,
        }
    }

    /// Preload factor `g(P) = (1 + P/P0)^chi` (Eq. 1), with the base clamped at `BASE_MIN`.
    #[inline]
    pub fn preload_factor(&self, preload_n: f64) -> f64 {
        (1.0 + preload_n / self.p0_n).max(BASE_MIN).powf(self.chi)
    }

    /// Inverse relaxation time `k2/c2` in 1/s; independent of preload (same factor).
    #[inline]
    pub fn relaxation_rate_per_s(&self) -> f64 {
        self.k2_0_n_per_m / self.c2_0_ns_per_m
    }
}

/// Kelvin-Voigt parameters of one element.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KelvinVoigtParams {
    pub k_n_per_m: f64,
    pub c_ns_per_m: f64,
}

impl KelvinVoigtParams {
    /// The paper's linear comparison model (Sec. 3.2), scaled to `length_m`.
    pub fn paper_linear(length_m: f64) -> KelvinVoigtParams {
        KelvinVoigtParams {
            k_n_per_m: 80e6 * length_m,
            c_ns_per_m: 1e3 * length_m,
        }
    }
}

/// One element: a form and its parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ElementModel {
    Consistent(ZenerParams),
    Paper(ZenerParams),
    KelvinVoigt(KelvinVoigtParams),
}

impl ElementModel {
    pub fn form(&self) -> Form {
        match self {
            ElementModel::Consistent(_) => Form::Consistent,
            ElementModel::Paper(_) => Form::Paper,
            ElementModel::KelvinVoigt(_) => Form::KelvinVoigt,
        }
    }

    pub fn zener(&self) -> Option<&ZenerParams> {
        match self {
            ElementModel::Consistent(p) | ElementModel::Paper(p) => Some(p),
            ElementModel::KelvinVoigt(_) => None,
        }
    }

    /// The same Zener parameters in another Zener form (no-op for Kelvin-Voigt).
    pub fn with_form(&self, form: Form) -> ElementModel {
        match (self.zener(), form) {
            (Some(p), Form::Consistent) => ElementModel::Consistent(*p),
            (Some(p), Form::Paper) => ElementModel::Paper(*p),
            _ => *self,
        }
    }

    /// Static force at displacement `z_m` (the force the element holds at rest there).
    pub fn static_force_n(&self, z_m: f64) -> f64 {
        match self {
            ElementModel::Consistent(p) => consistent_static_force(p, z_m).0,
            ElementModel::Paper(p) => paper_static_force(p, z_m),
            ElementModel::KelvinVoigt(p) => p.k_n_per_m * z_m,
        }
    }

    /// Static displacement under force `force_n` (inverse of `static_force_n`).
    pub fn static_displacement_m(&self, force_n: f64) -> f64 {
        match self {
            ElementModel::Consistent(p) => {
                let base = (1.0 + force_n / p.p0_n).max(BASE_MIN).powf(1.0 - p.chi);
                (base - 1.0) * p.p0_n / ((1.0 - p.chi) * p.k1_0_n_per_m)
            }
            ElementModel::Paper(p) => force_n / (p.k1_0_n_per_m * p.preload_factor(force_n)),
            ElementModel::KelvinVoigt(p) => force_n / p.k_n_per_m,
        }
    }

    /// Small-signal (tangent) stiffness bound at force `force_n`: `k1 + k2` (or `k`), N/m.
    pub fn high_frequency_stiffness_n_per_m(&self, force_n: f64) -> f64 {
        match self {
            ElementModel::Consistent(p) | ElementModel::Paper(p) => {
                (p.k1_0_n_per_m + p.k2_0_n_per_m) * p.preload_factor(force_n)
            }
            ElementModel::KelvinVoigt(p) => p.k_n_per_m,
        }
    }
}

/// `Fs(z)` of the consistent form and whether the base had to be clamped.
///
/// `Fs(z) = P0 [(1 + (1 - chi) k1_0 z / P0)^(1/(1-chi)) - 1]`, so `dFs/dz = k1_0 g(Fs)`.
#[inline]
pub fn consistent_static_force(p: &ZenerParams, z_m: f64) -> (f64, bool) {
    let one_minus_chi = 1.0 - p.chi;
    let raw_base = 1.0 + one_minus_chi * p.k1_0_n_per_m * z_m / p.p0_n;
    // NaN counts as clamped too, so a NaN base can never reach `powf`.
    let clamped = raw_base.is_nan() || raw_base < BASE_MIN;
    let base = if clamped { BASE_MIN } else { raw_base };
    (p.p0_n * (base.powf(1.0 / one_minus_chi) - 1.0), clamped)
}

/// Static equilibrium of the paper form: the `F` solving `F = k1_0 g(F) z`.
///
/// Newton iterations on `h(F) = F - k1_0 g(F) z`; converges in a few steps in compression
/// and in moderate tension. In tension beyond the domain the result is clamped at
/// `-P0 (1 - BASE_MIN)`.
pub fn paper_static_force(p: &ZenerParams, z_m: f64) -> f64 {
    let floor_n = -p.p0_n * (1.0 - BASE_MIN);
    let mut force_n = p.k1_0_n_per_m * z_m;
    for _ in 0..100 {
        let base = (1.0 + force_n / p.p0_n).max(BASE_MIN);
        let g = base.powf(p.chi);
        let h = force_n - p.k1_0_n_per_m * g * z_m;
        let dh = 1.0 - p.k1_0_n_per_m * z_m * p.chi * g / (base * p.p0_n);
        let next = (force_n - h / dh).max(floor_n);
        if (next - force_n).abs() <= 1e-12 * (1.0 + force_n.abs()) {
            return next;
        }
        force_n = next;
    }
    force_n
}
