//! Equivalent stiffness and damping (paper Eq. 2) and small-signal moduli of each form.
//!
//! The complex modulus `K(i W) = k_eq + i W c_eq` relates a small harmonic displacement
//! to the force around a preload `P`.

use super::params::{ElementModel, ZenerParams};

/// Equivalent stiffness (N/m) and damping (N s/m) at one preload and frequency.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Equivalent {
    pub k_eq_n_per_m: f64,
    pub c_eq_ns_per_m: f64,
}

/// Paper Eq. 2 for Zener parameters at preload `preload_n` and circular frequency `omega`.
pub fn zener_eq2(p: &ZenerParams, preload_n: f64, omega_rad_per_s: f64) -> Equivalent {
    let g = p.preload_factor(preload_n);
    let (k1, k2, c2) = (p.k1_0_n_per_m * g, p.k2_0_n_per_m * g, p.c2_0_ns_per_m * g);
    let a = (c2 * omega_rad_per_s / k2).powi(2);
    Equivalent {
        k_eq_n_per_m: k1 + k2 * a / (1.0 + a),
        c_eq_ns_per_m: c2 / (1.0 + a),
    }
}

/// Small-signal modulus of the paper form linearised at preload `P` (SPEC 2.1):
/// `[(k1+k2) s + a k1] / (s + a (1 - d))`, `a = k2/c2`, `d = chi P / (P0 + P)`.
pub fn paper_form_linearised(p: &ZenerParams, preload_n: f64, omega_rad_per_s: f64) -> Equivalent {
    let g = p.preload_factor(preload_n);
    let (k1, k2) = (p.k1_0_n_per_m * g, p.k2_0_n_per_m * g);
    let a = p.relaxation_rate_per_s();
    let d = p.chi * preload_n / (p.p0_n + preload_n);
    // (N_r + i N_i) / (D_r + i D_i) with s = i W.
    let (n_r, n_i) = (a * k1, (k1 + k2) * omega_rad_per_s);
    let (d_r, d_i) = (a * (1.0 - d), omega_rad_per_s);
    let den = d_r * d_r + d_i * d_i;
    let re = (n_r * d_r + n_i * d_i) / den;
    let im = (n_i * d_r - n_r * d_i) / den;
    Equivalent {
        k_eq_n_per_m: re,
        c_eq_ns_per_m: if omega_rad_per_s > 0.0 {
            im / omega_rad_per_s
        } else {
            f64::NAN
        },
    }
}

/// The equivalent stiffness and damping the model's *time-domain form* shows for small
/// oscillations around `preload_n`. For the consistent form and Kelvin-Voigt this is
/// Eq. 2 (resp. `k`, `c`); the paper form differs (see `paper_form_linearised`).
pub fn equivalent(model: &ElementModel, preload_n: f64, omega_rad_per_s: f64) -> Equivalent {
    match model {
        ElementModel::Consistent(p) => zener_eq2(p, preload_n, omega_rad_per_s),
        ElementModel::Paper(p) => paper_form_linearised(p, preload_n, omega_rad_per_s),
        ElementModel::KelvinVoigt(p) => Equivalent {
            k_eq_n_per_m: p.k_n_per_m,
            c_eq_ns_per_m: p.c_ns_per_m,
        },
    }
}

/// The paper's Table 2 grid: preloads (N) and frequencies (Hz).
pub const TABLE2_PRELOADS_N: [f64; 4] = [6e3, 18e3, 37e3, 55e3];
pub const TABLE2_FREQUENCIES_HZ: [f64; 5] = [1.0, 3.0, 5.0, 10.0, 20.0];
