//! `DelayEstimator`: the actuator's effective delay and gain, learned online by exponentially
//! weighted least squares on the measured against the element's force (the lead's estimate).
//! Must not: allocate, lock, log, read a clock or do I/O (runs per setpoint).

use super::*;

/// The estimator's view after a sample.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct DelayEstimate {
    /// The actuator side's effective output delay (zero-order hold, transport, lag): how
    /// late the rendered force would follow the element's force without a lead, s; NaN when
    /// the data hold no rate (a static load: the gain alone is estimated).
    pub delay_s: f64,
    /// Its standard error, s.
    pub delay_sigma_s: f64,
    /// The actuator's force per commanded force in the load band.
    pub residual_gain: f64,
    /// Independent residuals behind it: the weighted samples beyond the fitted
    /// parameters over the samples per independent residual (`DelayEstimator::correlation`).
    pub independent: f64,
}

/// Exponentially weighted least squares on load-band signals. The rig renders the
/// element's force predicted over the lead `L` in effect, `d` late, with gain `g`:
/// `F_meas(t) = g F(t + L - d) ~ g (F + L dF/dt) - g d dF/dt`, so with the regressors
/// `x = F + L dF/dt` (the lead the rig used at that sample) and `dF/dt`,
/// `F_meas ~ a x + b dF/dt` gives `g = a` and the whole delay `d = -b/a` whatever leads
/// the window's samples were rendered with (exact to first order in `L - d`, so exact at
/// convergence).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DelayEstimator {
    /// Two cascaded second-order low-passes per signal (fourth order): the resonance's
    /// content, which the rate regressor would weigh by its frequency, is kept out.
    lp_element: [LowPass2; 2],
    lp_measured: [LowPass2; 2],
    forget: f64,
    dt_s: f64,
    last_x: f64,
    last_rate: f64,
    primed: bool,
    /// Samples to skip after a restart while the filters settle.
    warmup_left: u32,
    warmup: u32,
    /// Samples per independent residual: the residuals are the load band's, low-passed
    /// at `band_hz` and sampled far above it, so neighbours are not independent and the
    /// textbook variance, which counts each sample, is `1 / (2 band dt)` times too small.
    correlation: f64,
    /// Weighted sums: xx, xd, dd, xy, dy, yy, the weight, then xc, dc, cc, cy (`c` the
    /// force's curvature, `d^2F/dt^2`).
    s: [f64; 11],
}

impl DelayEstimator {
    pub fn new(band_hz: f64, memory_s: f64, dt_s: f64) -> DelayEstimator {
        DelayEstimator {
            lp_element: [LowPass2::low_pass(band_hz, dt_s); 2],
            lp_measured: [LowPass2::low_pass(band_hz, dt_s); 2],
            forget: (-dt_s / memory_s).exp(),
            dt_s,
            last_x: 0.0,
            last_rate: 0.0,
            primed: false,
            // Four time constants of the 4th-order low-pass.
            warmup_left: 0,
            warmup: (4.0 / (band_hz * dt_s)).ceil() as u32,
            correlation: (0.5 / (band_hz * dt_s)).max(1.0),
            s: [0.0; 11],
        }
    }

    /// Forgets the filters' state (a gap in the samples); the sums decay as usual.
    pub fn restart(&mut self) {
        self.primed = false;
    }

    /// One consecutive rig sample; `None` until the regression is determined.
    #[inline]
    pub fn update(
        &mut self,
        element_force_n: f64,
        measured_force_n: f64,
        lead_s: f64,
    ) -> Option<DelayEstimate> {
        if !(element_force_n.is_finite() && measured_force_n.is_finite()) {
            self.restart();
            return None;
        }
        if !self.primed {
            for f in &mut self.lp_element {
                f.reset(element_force_n);
            }
            for f in &mut self.lp_measured {
                f.reset(measured_force_n);
            }
            self.last_x = element_force_n;
            self.last_rate = 0.0;
            self.primed = true;
            self.warmup_left = self.warmup;
            return None;
        }
        let x = self.lp_element[0].step(element_force_n);
        let x = self.lp_element[1].step(x);
        let y = self.lp_measured[0].step(measured_force_n);
        let y = self.lp_measured[1].step(y);
        let d = (x - self.last_x) / self.dt_s;
        self.last_x = x;
        let c = (d - self.last_rate) / self.dt_s;
        self.last_rate = d;
        if self.warmup_left > 0 {
            self.warmup_left -= 1;
            return None;
        }
        let x = x + lead_s * d;
        let l = self.forget;
        let s = &mut self.s;
        add_to_sums(s, l, x, d, y);
        s[7] = l * s[7] + x * c;
        s[8] = l * s[8] + d * c;
        s[9] = l * s[9] + c * c;
        s[10] = l * s[10] + c * y;
        if let Some(estimate) = self.solve_with_curvature() {
            return Some(estimate);
        }
        let s = &self.s;
        let Some((a, b, det)) = solve_two(s, 1e-12).filter(|_| s[2] > 0.0) else {
            // No rate in the data (a static load): the gain alone, `y = a x`.
            if s[0] > 0.0 && s[3].is_finite() {
                return Some(DelayEstimate {
                    delay_s: f64::NAN,
                    delay_sigma_s: f64::NAN,
                    residual_gain: s[3] / s[0],
                    independent: (s[6] - 1.0).max(0.0) / self.correlation,
                });
            }
            return None;
        };
        if a.abs() < 1e-6 {
            return None;
        }
        // Residual sum of squares and the standard error of b (and so of -b/a).
        let rss = (s[5] - a * s[3] - b * s[4]).max(0.0);
        let dof = (s[6] - 2.0).max(1.0);
        let var_b = rss / dof * s[0] / det * self.correlation;
        Some(DelayEstimate {
            delay_s: -b / a,
            delay_sigma_s: var_b.sqrt() / a.abs(),
            residual_gain: a,
            independent: (s[6] - 2.0).max(0.0) / self.correlation,
        })
    }

    /// `F_meas ~ a x + b dF/dt + e d2F/dt2`: the curvature term takes what rises with
    /// frequency squared (a moving mass's inertia in the measured force, the second-order
    /// term of a lag), which in a transient (an axle passage) correlates with the rate and
    /// would otherwise bias `b` (an electrodynamic actuator's back-EMF, mass-like: +40 % on
    /// its delay). `None` when the three regressors are not determined (then the rate
    /// alone is fitted).
    #[inline]
    fn solve_with_curvature(&self) -> Option<DelayEstimate> {
        let s = &self.s;
        let (xx, xd, dd, xy, dy, yy, w) = (s[0], s[1], s[2], s[3], s[4], s[5], s[6]);
        let (xc, dc, cc, cy) = (s[7], s[8], s[9], s[10]);
        // Cofactors of the symmetric normal matrix [[xx xd xc] [xd dd dc] [xc dc cc]].
        let c00 = dd * cc - dc * dc;
        let c01 = xc * dc - xd * cc;
        let c02 = xd * dc - dd * xc;
        let c11 = xx * cc - xc * xc;
        let c12 = xd * xc - xx * dc;
        let c22 = xx * dd - xd * xd;
        let det = xx * c00 + xd * c01 + xc * c02;
        // Determined: a determinant clear of rounding (false for NaN too).
        let determined = det > 1e-9 * xx * dd * cc;
        if !determined {
            return None;
        }
        let a = (c00 * xy + c01 * dy + c02 * cy) / det;
        let b = (c01 * xy + c11 * dy + c12 * cy) / det;
        let e = (c02 * xy + c12 * dy + c22 * cy) / det;
        if a.abs() < 1e-6 {
            return None;
        }
        let rss = (yy - a * xy - b * dy - e * cy).max(0.0);
        let dof = (w - 3.0).max(1.0);
        let var_b = rss / dof * c11 / det * self.correlation;
        Some(DelayEstimate {
            delay_s: -b / a,
            delay_sigma_s: var_b.sqrt() / a.abs(),
            residual_gain: a,
            independent: (w - 3.0).max(0.0) / self.correlation,
        })
    }
}

/// Adds a sample to the exponentially weighted sums of the regression `y ~ a x + b d`
/// (both estimators'): `s[0..7]` are xx, xd, dd, xy, dy, yy and the weight, each decayed by
/// `forget` first.
#[inline]
pub(super) fn add_to_sums(s: &mut [f64], forget: f64, x: f64, d: f64, y: f64) {
    for (sum, term) in s[..7]
        .iter_mut()
        .zip([x * x, x * d, d * d, x * y, d * y, y * y, 1.0])
    {
        *sum = forget * *sum + term;
    }
}

/// `(a, b, det)` of `y ~ a x + b d` from `add_to_sums`' sums; `None` unless the
/// determinant is clear of rounding by `tolerance` of `xx dd` (false for NaN too).
#[inline]
pub(super) fn solve_two(s: &[f64], tolerance: f64) -> Option<(f64, f64, f64)> {
    let (xx, xd, dd, xy, dy) = (s[0], s[1], s[2], s[3], s[4]);
    let det = xx * dd - xd * xd;
    (det > tolerance * xx * dd).then(|| ((dd * xy - xd * dy) / det, (xx * dy - xd * xy) / det, det))
}
