//! A small Levenberg-Marquardt least-squares solver with a forward-difference Jacobian.
//!
//! Parameters are unbounded (callers fit log/logit/scaled parameters). Returns the final
//! Jacobian product `J^T J` so callers can form the covariance `sigma^2 (J^T J)^-1`.
//! Deterministic: no randomness, no threads.

use nalgebra::{DMatrix, DVector};

/// Result of a fit.
#[derive(Debug, Clone)]
pub struct LmFit {
    pub params: Vec<f64>,
    /// Sum of squared residuals at `params`.
    pub sse: f64,
    pub n_residuals: usize,
    /// `J^T J` at `params` (unscaled).
    pub jtj: DMatrix<f64>,
    pub iterations: usize,
}

impl LmFit {
    /// Standard errors of the parameters, `sqrt(diag(sigma^2 (J^T J)^-1))`, with
    /// `sigma^2 = SSE / (n - p)`. `None` where `J^T J` is singular.
    pub fn standard_errors(&self) -> Vec<Option<f64>> {
        let p = self.params.len();
        match self.covariance() {
            Some(cov) => (0..p)
                .map(|i| {
                    let v = cov[(i, i)];
                    (v.is_finite() && v >= 0.0).then(|| v.sqrt())
                })
                .collect(),
            None => vec![None; p],
        }
    }

    /// The parameters' covariance `sigma^2 (J^T J)^-1`, `sigma^2 = SSE / (n - p)` (p the
    /// parameters that move the residuals), over
    /// the parameters that move the residuals at all (a parameter held on a bound, whose
    /// column of `J` is zero, gets NaN in its row and column); `None` where the rest of
    /// `J^T J` is singular.
    pub fn covariance(&self) -> Option<DMatrix<f64>> {
        let p = self.params.len();
        let largest = (0..p).map(|i| self.jtj[(i, i)]).fold(0.0, f64::max);
        let moving: Vec<usize> = (0..p)
            .filter(|&i| self.jtj[(i, i)] > 1e-14 * largest)
            .collect();
        // The degrees of freedom count only the parameters that move the residuals.
        let dof = self.n_residuals.saturating_sub(moving.len()).max(1) as f64;
        let sigma2 = self.sse / dof;
        let reduced = DMatrix::from_fn(moving.len(), moving.len(), |a, b| {
            self.jtj[(moving[a], moving[b])]
        });
        let inverse = reduced.try_inverse()?;
        let mut covariance = DMatrix::from_element(p, p, f64::NAN);
        for (a, &i) in moving.iter().enumerate() {
            for (b, &j) in moving.iter().enumerate() {
                covariance[(i, j)] = inverse[(a, b)] * sigma2;
            }
        }
        Some(covariance)
    }
}

/// Relative decrease of the sum of squares below which an accepted step ends the fit.
pub const GAIN_CONVERGED: f64 = 1e-7;

/// Minimises `sum r(theta)^2` from `start`.
pub fn levenberg_marquardt<F>(residuals: F, start: &[f64], max_iterations: usize) -> LmFit
where
    F: Fn(&[f64]) -> Vec<f64>,
{
    let p = start.len();
    let mut theta = start.to_vec();
    let mut r = residuals(&theta);
    let sanitize = |v: &mut Vec<f64>| {
        for x in v.iter_mut() {
            if !x.is_finite() {
                *x = 1e6;
            }
        }
    };
    sanitize(&mut r);
    let n = r.len();
    let mut sse: f64 = r.iter().map(|x| x * x).sum();
    let mut lambda = 1e-3;
    let mut jacobian = DMatrix::<f64>::zeros(n, p);
    let mut iterations = 0;
    let jacobian_at = |theta: &[f64], r: &[f64], jac: &mut DMatrix<f64>| {
        let mut shifted = theta.to_vec();
        for j in 0..p {
            let h = 1e-6 * theta[j].abs().max(1.0);
            shifted[j] = theta[j] + h;
            let mut rj = residuals(&shifted);
            sanitize(&mut rj);
            for i in 0..n {
                jac[(i, j)] = (rj[i] - r[i]) / h;
            }
            shifted[j] = theta[j];
        }
    };
    if p == 0 {
        return LmFit {
            params: theta,
            sse,
            n_residuals: n,
            jtj: DMatrix::zeros(0, 0),
            iterations,
        };
    }
    jacobian_at(&theta, &r, &mut jacobian);
    while iterations < max_iterations {
        iterations += 1;
        let jtj = jacobian.transpose() * &jacobian;
        let jtr = jacobian.transpose() * DVector::from_column_slice(&r);
        let mut improved = false;
        // Up to 8 damping increases (x 4^8 = 6.6e4) before the fit is taken as converged:
        // each try costs a full evaluation of the residuals.
        for _ in 0..8 {
            let mut a = jtj.clone();
            for i in 0..p {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
            }
            let Some(step) = a.cholesky().map(|c| c.solve(&(-&jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let trial: Vec<f64> = theta.iter().zip(step.iter()).map(|(t, s)| t + s).collect();
            if trial.iter().any(|t| !t.is_finite()) {
                lambda *= 10.0;
                continue;
            }
            let mut r_trial = residuals(&trial);
            sanitize(&mut r_trial);
            let sse_trial: f64 = r_trial.iter().map(|x| x * x).sum();
            if sse_trial < sse {
                let gain = (sse - sse_trial) / sse.max(1e-300);
                let step_size = step.amax();
                theta = trial;
                r = r_trial;
                sse = sse_trial;
                lambda = (lambda / 3.0).max(1e-9);
                improved = true;
                // A step that lowers the sum of squares by less than 1e-7 of it has
                // converged for every use here (held-out errors differ by far less than
                // their noise); tighter, fits crept on for dozens of full evaluations.
                if gain < GAIN_CONVERGED || step_size < 1e-9 {
                    iterations = max_iterations;
                }
                break;
            }
            lambda *= 4.0;
        }
        if !improved {
            break;
        }
        jacobian_at(&theta, &r, &mut jacobian);
    }
    let jtj = jacobian.transpose() * &jacobian;
    LmFit {
        params: theta,
        sse,
        n_residuals: n,
        jtj,
        iterations,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fits_an_exponential() {
        let t: Vec<f64> = (0..20).map(|i| i as f64 * 0.1).collect();
        let y: Vec<f64> = t.iter().map(|t| 3.0 * (-1.5 * t).exp()).collect();
        let fit = levenberg_marquardt(
            |p| {
                t.iter()
                    .zip(&y)
                    .map(|(t, y)| p[0].exp() * (-p[1] * t).exp() - y)
                    .collect()
            },
            &[0.0, 0.5],
            100,
        );
        assert!((fit.params[0].exp() - 3.0).abs() < 1e-6);
        assert!((fit.params[1] - 1.5).abs() < 1e-6);
    }

    /// A straight line `y = a x + b` plus a parameter that moves nothing: the covariance of
    /// `a` and `b` is the textbook one, `sigma^2 (X^T X)^-1`, and the dead parameter's row
    /// is NaN instead of making the whole matrix singular.
    #[test]
    fn covariance_is_the_textbook_one_and_skips_a_parameter_that_moves_nothing() {
        let x: Vec<f64> = (0..10).map(f64::from).collect();
        let wiggle = [0.3, -0.1, 0.2, -0.4, 0.1, 0.0, -0.2, 0.3, -0.1, -0.1];
        let y: Vec<f64> = x
            .iter()
            .zip(wiggle)
            .map(|(x, w)| 2.0 * x + 1.0 + w)
            .collect();
        let fit = levenberg_marquardt(
            |p| x.iter().zip(&y).map(|(x, y)| p[0] * x + p[1] - y).collect(),
            &[0.0, 0.0, 5.0],
            100,
        );
        let cov = fit.covariance().expect("covariance");
        // Independent: normal equations by hand.
        let n = x.len() as f64;
        let (sx, sxx) = (x.iter().sum::<f64>(), x.iter().map(|x| x * x).sum::<f64>());
        let det = n * sxx - sx * sx;
        // Two parameters move the residuals: n - 2 degrees of freedom.
        let sigma2 = fit.sse / (n - 2.0);
        assert!((cov[(0, 0)] - sigma2 * n / det).abs() < 1e-9 * cov[(0, 0)]);
        assert!((cov[(1, 1)] - sigma2 * sxx / det).abs() < 1e-9 * cov[(1, 1)]);
        assert!((cov[(0, 1)] + sigma2 * sx / det).abs() < 1e-9 * cov[(1, 1)]);
        assert!(cov[(2, 2)].is_nan() && cov[(0, 2)].is_nan());
        let se = fit.standard_errors();
        assert!(se[0].is_some() && se[1].is_some() && se[2].is_none());
    }
}
