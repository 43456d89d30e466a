//! The project's synthetic-campaign generator (for the diagnose/identify tests).
//!
//! Independent of the crate's effect implementations where it reasonably can be:
//! - the nonlinear Zener element (consistent form) and the friction element are
//!   integrated with classical RK4 on a fine sub-step grid from analytic `z(t)`, `z'(t)`;
//! - friction is a Bouc-Wen element with exponent 2 (the library's is Dahl, exponent 1);
//! - fractional damping is an exact steady-state springpot `c (i h W)^alpha` per harmonic
//!   of the imposed displacement (the library's is a Maxwell bank in time domain);
//! - temperature follows WLF with a linear modulus factor (the library's law is
//!   exponential-linear);
//! - the channel delay is an exact time shift (interpolated on the fine grid) and the
//!   moving mass uses the analytic `z''`;
//! - self-heating: the power of each test is its noise-free record's `sum F dz` over its
//!   duration, the specimen's temperature is integrated by explicit Euler (0.05 s) through
//!   tests and rests, and the moduli fall linearly with it (the library's default law is
//!   exponential and also shifts relaxation times); each test runs at its mid-record
//!   temperature.
//!
//! Tests are "force-controlled style": the displacement is the harmonic that gives the
//! nominal force amplitude on the truth's linearised modulus, with a small 2nd harmonic
//! (imperfect control), so displacement amplitudes vary with stiffness, amplitude and
//! temperature. Both channels get white noise; the force also gets coloured noise (AR(1)
//! plus a slow drift).

use std::f64::consts::PI;
use std::fmt::Write as _;
use std::path::Path;

/// Deterministic SplitMix64 + Box-Muller normal generator.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(seed)
    }
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E3779B97F4A7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
        z ^ (z >> 31)
    }
    pub fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    pub fn normal(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (2.0 * PI * u2).cos()
    }
}

/// The truth behind a synthetic campaign (per element of `length_m`).
#[derive(Debug, Clone, Copy)]
pub struct Truth {
    pub length_m: f64,
    pub k1_0_n_per_m2: f64,
    pub k2_0_n_per_m2: f64,
    pub c2_0_ns_per_m2: f64,
    pub chi: f64,
    pub p0_n: f64,
    /// Bouc-Wen friction: initial stiffness (N/m^2) and slip force (N/m), per metre.
    pub friction: Option<(f64, f64)>,
    /// Bouc-Wen exponent (2 by default; large values approach a Jenkins element).
    pub friction_exponent: f64,
    /// Fractional Zener: the Maxwell dashpot replaced by a springpot of this order
    /// (Cole-Cole branch `k2 (i W tau)^a / (1 + (i W tau)^a)`, linear, at the preload).
    pub fractional_maxwell_order: Option<f64>,
    /// Springpot coefficient per metre (N s^alpha / m^2) and order.
    pub springpot: Option<(f64, f64)>,
    /// Out of the library: a second Maxwell branch in parallel, stiffness per metre
    /// (N/m^2) and relaxation time (s): `k (i W tau) / (1 + i W tau)` per harmonic (linear,
    /// harmonic tests only, like the springpot).
    pub second_maxwell: Option<(f64, f64)>,
    /// WLF C1, C2, reference temperature and modulus slope per degC.
    pub wlf: Option<(f64, f64, f64, f64)>,
    pub force_lag_s: f64,
    pub mass_kg: f64,
    /// Out of the library: the force reaches the load cell through a resonance of the
    /// load path (natural frequency Hz, damping ratio), `F_meas = H(s) F`,
    /// `H = w^2 / (s^2 + 2 zeta w s + w^2)`.
    pub load_path_resonance: Option<(f64, f64)>,
    /// Out of the library: the specimen's moduli fall linearly over the campaign by this
    /// fraction from the first test to the last (tests in campaign order).
    pub softening_over_campaign: f64,
    /// Out of the library: a cubic load-cell nonlinearity, `F_meas = F - c F^3 / (100 kN)^2`.
    pub force_sensor_cubic: f64,
    /// Self-heating: heat capacity (J/K), heat-transfer coefficient (W/K), linear modulus
    /// slope (1/K, moduli times `1 - slope dT`).
    pub self_heating: Option<(f64, f64, f64)>,
    /// Rest between the end of a test and the start of the next, s: when given, every test
    /// states `started_at`.
    pub rest_s: Option<f64>,
    /// Mullins softening (largest softening, force scale N): the recorded force times
    /// `1 - d (1 - exp(-(M - F) / F_s))`, `M` the largest force so far in the campaign
    /// (the library's law is a tanh and acts on the element's force alone).
    pub mullins: Option<(f64, f64)>,
    /// Out of the library: a cubic spring about a fixed displacement, coefficient N/m^3,
    /// displacement m and its drift over the campaign: `c (1 + drift u) (z - z_c)^3`, `u`
    /// from 0 at the first test to 1 at the last (harmonic tests only).
    pub cubic_spring: Option<(f64, f64, f64)>,
}

impl Truth {
    pub fn paper_like() -> Truth {
        Truth {
            length_m: 0.75,
            k1_0_n_per_m2: 60e6,
            k2_0_n_per_m2: 10e6,
            c2_0_ns_per_m2: 0.75e6,
            chi: 0.2,
            p0_n: 64e3,
            friction: None,
            friction_exponent: 2.0,
            fractional_maxwell_order: None,
            springpot: None,
            second_maxwell: None,
            wlf: None,
            force_lag_s: 0.0,
            mass_kg: 0.0,
            load_path_resonance: None,
            softening_over_campaign: 0.0,
            force_sensor_cubic: 0.0,
            self_heating: None,
            rest_s: None,
            mullins: None,
            cubic_spring: None,
        }
    }

    /// The truth with its moduli scaled by `factor` (a specimen that changed).
    fn scaled(&self, factor: f64) -> Truth {
        Truth {
            k1_0_n_per_m2: self.k1_0_n_per_m2 * factor,
            k2_0_n_per_m2: self.k2_0_n_per_m2 * factor,
            c2_0_ns_per_m2: self.c2_0_ns_per_m2 * factor,
            ..*self
        }
    }

    /// The truth warmed by `rise_k` above its chamber (self-heating's linear law).
    fn heated(&self, rise_k: f64) -> Truth {
        match self.self_heating {
            Some((_, _, slope)) if rise_k != 0.0 => self.scaled(1.0 - slope * rise_k),
            _ => *self,
        }
    }

    /// What the load path and the load cell make of the force on the fine grid (step `h`).
    fn measured_force(&self, fine: &[f64], h: f64) -> Vec<f64> {
        let mut out = fine.to_vec();
        if let Some((f_r, zeta)) = self.load_path_resonance {
            // Bilinear (Tustin) discretisation of H(s), started at rest at the first value.
            let w = 2.0 * PI * f_r;
            let k = 2.0 / h;
            let a0 = k * k + 2.0 * zeta * w * k + w * w;
            let b = [w * w / a0, 2.0 * w * w / a0, w * w / a0];
            let a = [
                2.0 * (w * w - k * k) / a0,
                (k * k - 2.0 * zeta * w * k + w * w) / a0,
            ];
            let (mut x1, mut x2, mut y1, mut y2) = (fine[0], fine[0], fine[0], fine[0]);
            for (o, &x) in out.iter_mut().zip(fine) {
                let y = b[0] * x + b[1] * x1 + b[2] * x2 - a[0] * y1 - a[1] * y2;
                (x2, x1, y2, y1) = (x1, x, y1, y);
                *o = y;
            }
        }
        if self.force_sensor_cubic != 0.0 {
            for o in out.iter_mut() {
                *o -= self.force_sensor_cubic * o.powi(3) / 1e10;
            }
        }
        out
    }

    /// Modulus factor and time factor at temperature `t_c`.
    fn temperature_factors(&self, t_c: f64) -> (f64, f64) {
        match self.wlf {
            Some((c1, c2, t_ref, slope)) => {
                let dt = t_c - t_ref;
                (1.0 - slope * dt, 10f64.powf(-c1 * dt / (c2 + dt)))
            }
            None => (1.0, 1.0),
        }
    }
}

/// Noise levels relative to the force amplitude / displacement amplitude.
#[derive(Debug, Clone, Copy)]
pub struct Noise {
    pub white_force: f64,
    pub white_displacement: f64,
    /// AR(1) coloured force noise: relative std and correlation per sample.
    pub coloured_force: f64,
    pub coloured_rho: f64,
    /// Slow drift of the force channel (relative amplitude, period 7 s).
    pub drift_force: f64,
}

impl Noise {
    pub fn typical() -> Noise {
        Noise {
            white_force: 0.01,
            white_displacement: 0.01,
            coloured_force: 0.01,
            coloured_rho: 0.98,
            drift_force: 0.01,
        }
    }
}

/// One test of the design.
#[derive(Debug, Clone, Copy)]
pub struct TestPoint {
    pub preload_n: f64,
    pub amplitude_n: f64,
    pub frequency_hz: f64,
    pub temperature_c: f64,
}

/// The design used in every campaign: the paper grid at 5 kN and 23 degC, an amplitude
/// series and a temperature series (so no design leaks which effect is hidden).
pub fn standard_design() -> Vec<TestPoint> {
    let mut out = Vec::new();
    for p in [6e3, 18e3, 37e3, 55e3] {
        for f in [1.0, 3.0, 5.0, 10.0, 20.0] {
            out.push(TestPoint {
                preload_n: p,
                amplitude_n: 5e3,
                frequency_hz: f,
                temperature_c: 23.0,
            });
        }
    }
    for p in [18e3, 37e3] {
        for a in [2e3, 9e3] {
            for f in [3.0, 10.0] {
                out.push(TestPoint {
                    preload_n: p,
                    amplitude_n: a,
                    frequency_hz: f,
                    temperature_c: 23.0,
                });
            }
        }
        for t in [10.0, 35.0] {
            for f in [1.0, 5.0, 20.0] {
                out.push(TestPoint {
                    preload_n: p,
                    amplitude_n: 5e3,
                    frequency_hz: f,
                    temperature_c: t,
                });
            }
        }
    }
    out
}

/// Rates of the consistent-form element's elastic force `Fs` and Maxwell force `Fm`, and
/// of a Bouc-Wen friction force (beta = gamma = 1/2: it saturates at the slip force).
struct ElementRates {
    k1: f64,
    k2: f64,
    c2: f64,
    chi: f64,
    p0: f64,
    /// Friction stiffness (0: no friction) and slip force.
    kf: f64,
    ff_slip: f64,
    exponent: f64,
    /// Whether the Maxwell branch is there (a fractional branch replaces it).
    maxwell: bool,
}

impl ElementRates {
    fn at(&self, v: f64, s: &[f64; 3]) -> [f64; 3] {
        let gg = (1.0 + s[0] / self.p0).max(1e-6).powf(self.chi);
        let dfm = if self.maxwell {
            self.k2 * gg * v - (self.k2 / self.c2) * s[1]
        } else {
            0.0
        };
        let wn = s[2] / self.ff_slip;
        let dff = if self.kf > 0.0 {
            let pow = wn.abs().powf(self.exponent - 1.0);
            self.kf * (v - 0.5 * v.abs() * pow * wn - 0.5 * v * pow * wn.abs())
        } else {
            0.0
        };
        [self.k1 * gg * v, dfm, dff]
    }
}

/// One classical RK4 step of `state` from `t` over `h`.
fn rk4_step(deriv: &dyn Fn(f64, &[f64; 3]) -> [f64; 3], t: f64, h: f64, state: &mut [f64; 3]) {
    let k_1 = deriv(t, state);
    let s2 = std::array::from_fn(|i| state[i] + 0.5 * h * k_1[i]);
    let k_2 = deriv(t + 0.5 * h, &s2);
    let s3 = std::array::from_fn(|i| state[i] + 0.5 * h * k_2[i]);
    let k_3 = deriv(t + 0.5 * h, &s3);
    let s4 = std::array::from_fn(|i| state[i] + h * k_3[i]);
    let k_4 = deriv(t + h, &s4);
    for i in 0..3 {
        state[i] += h / 6.0 * (k_1[i] + 2.0 * k_2[i] + 2.0 * k_3[i] + k_4[i]);
    }
}

/// Static displacement of the consistent form under force `p` (per element params).
fn static_displacement(k1: f64, chi: f64, p0: f64, p: f64) -> f64 {
    ((1.0 + p / p0).powf(1.0 - chi) - 1.0) * p0 / ((1.0 - chi) * k1)
}

/// Simulates one test; returns (t, z, F) without noise.
///
/// `from_rest`: the record begins where the loading begins, the specimen in static
/// equilibrium at the preload (`z = z_static`, Maxwell and friction forces zero), the
/// displacement `z_static + a1 sin(W t) + a2 sin(2 W t)` (imperfect control as in the
/// steady case); the start-up transient is in the record. Otherwise the record starts
/// after a 1.5 s lead-in. The springpot and Cole-Cole branches are steady-state formulas
/// either way.
pub fn simulate_test(
    truth: &Truth,
    point: &TestPoint,
    n_cycles: usize,
    samples_per_cycle: f64,
    min_rate_hz: f64,
    from_rest: bool,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let l = truth.length_m;
    let (b, a) = truth.temperature_factors(point.temperature_c);
    let k1 = truth.k1_0_n_per_m2 * l * b;
    let k2 = truth.k2_0_n_per_m2 * l * b;
    let c2 = truth.c2_0_ns_per_m2 * l * b * a;
    let (chi, p0) = (truth.chi, truth.p0_n);
    let w = 2.0 * PI * point.frequency_hz;
    let g = (1.0 + point.preload_n / p0).powf(chi);
    // Linearised modulus of the truth at the preload, for the displacement amplitude.
    let mut modulus = {
        let (k1g, k2g, c2g) = (k1 * g, k2 * g, c2 * g);
        let x = (c2g * w / k2g).powi(2);
        (k1g + k2g * x / (1.0 + x), w * c2g / (1.0 + x))
    };
    if let Some(order) = truth.fractional_maxwell_order {
        // Replace the Maxwell part by the Cole-Cole branch for the amplitude estimate.
        let x = (c2 * w / k2).powi(2);
        modulus.0 -= k2 * g * x / (1.0 + x);
        modulus.1 -= w * c2 * g / (1.0 + x);
        let mag = (w * c2 / k2).powf(order);
        modulus.0 += k2 * g * mag / (1.0 + mag);
        modulus.1 += k2 * g * mag * 0.5 / (1.0 + mag);
    }
    if let Some((kf, _)) = truth.friction {
        modulus.0 += 0.3 * kf * l;
    }
    if let Some((c, alpha)) = truth.springpot {
        let mag = c * l * b * (a * w).powf(alpha);
        modulus.0 += mag * (PI * alpha / 2.0).cos();
        modulus.1 += mag * (PI * alpha / 2.0).sin();
    }
    // A second Maxwell branch: k (i W tau) / (1 + i W tau), its time temperature-shifted.
    let maxwell2 = |w_h: f64| {
        truth.second_maxwell.map_or((0.0, 0.0), |(k, tau)| {
            let x = w_h * tau * a;
            let kk = k * l * b / (1.0 + x * x);
            (kk * x * x, kk * x)
        })
    };
    modulus.0 += maxwell2(w).0;
    modulus.1 += maxwell2(w).1;
    let z_amp = point.amplitude_n / modulus.0.hypot(modulus.1);
    let z_static = static_displacement(k1, chi, p0, point.preload_n);
    // Imperfect control: 2 % second harmonic.
    // From rest: sines, so the drive starts at the static displacement (phase -pi/2).
    let (a1, a2) = (z_amp, 0.02 * z_amp);
    let (phi1, phi2) = if from_rest {
        (-0.5 * PI, -0.5 * PI)
    } else {
        (0.0, 0.7)
    };
    let z_of = |t: f64| z_static + a1 * (w * t + phi1).cos() + a2 * (2.0 * w * t + phi2).cos();
    let v_of = |t: f64| -a1 * w * (w * t + phi1).sin() - 2.0 * a2 * w * (2.0 * w * t + phi2).sin();
    let acc_of =
        |t: f64| -a1 * w * w * (w * t + phi1).cos() - 4.0 * a2 * w * w * (2.0 * w * t + phi2).cos();

    let fs_hz = (samples_per_cycle * point.frequency_hz).max(min_rate_hz);
    let dt = 1.0 / fs_hz;
    let n = (n_cycles as f64 * fs_hz / point.frequency_hz).round() as usize;
    let sub = 16usize;
    let h = dt / sub as f64;
    // Settle: start 1.5 s early from the static state at z_static + a1 + a2 cos(phi2).
    let settle = if from_rest {
        0
    } else {
        (1.5 * fs_hz).round() as usize
    };
    let t0 = -(settle as f64) * dt;
    let z0 = z_of(t0);
    // Elastic force Fs of the consistent form at z0 (closed form), Fm = 0, friction 0.
    let fs0 = p0 * ((1.0 + (1.0 - chi) * k1 * (z0 - 0.0) / p0).powf(1.0 / (1.0 - chi)) - 1.0);
    let mut state = [fs0, 0.0, 0.0];
    let (kf, ff_slip) = truth.friction.map_or((0.0, 1.0), |(k, f)| (k * l, f * l));
    let rates = ElementRates {
        k1,
        k2,
        c2,
        chi,
        p0,
        kf,
        ff_slip,
        exponent: truth.friction_exponent,
        maxwell: truth.fractional_maxwell_order.is_none(),
    };
    let deriv = |t: f64, s: &[f64; 3]| rates.at(v_of(t), s);
    let total = settle + n;
    // Fine grid of the nonlinear force (elastic + Maxwell + friction).
    let mut fine = Vec::with_capacity(total * sub + 1);
    let mut t = t0;
    fine.push(state[0] + state[1] + state[2]);
    for _ in 0..total * sub {
        rk4_step(&deriv, t, h, &mut state);
        t += h;
        fine.push(state[0] + state[1] + state[2]);
    }
    let springpot = truth.springpot.map(|(c, alpha)| {
        let c_eff = c * l * b * a.powf(alpha);
        // c (i h W)^alpha per harmonic.
        let m1 = c_eff * w.powf(alpha);
        let m2 = c_eff * (2.0 * w).powf(alpha);
        (m1, m2, PI * alpha / 2.0)
    });
    // Cole-Cole Maxwell branch at the preload: k2 g (i h W tau)^a / (1 + (i h W tau)^a).
    let cole = truth.fractional_maxwell_order.map(|order| {
        let tau = c2 / k2;
        let branch = |w_h: f64| {
            let mag = (w_h * tau).powf(order);
            let (re, im) = (
                mag * (PI * order / 2.0).cos(),
                mag * (PI * order / 2.0).sin(),
            );
            // x / (1 + x)
            let (dr, di) = (1.0 + re, im);
            let den = dr * dr + di * di;
            let (qr, qi) = ((re * dr + im * di) / den, (im * dr - re * di) / den);
            (k2 * g * qr, k2 * g * qi)
        };
        (branch(w), branch(2.0 * w))
    });
    let force_at = |t: f64| -> f64 {
        let x = (t - t0) / h;
        let i = (x.floor() as usize).min(fine.len() - 2);
        let frac = x - i as f64;
        let mut f = fine[i] * (1.0 - frac) + fine[i + 1] * frac;
        if let Some((m1, m2, phase)) = springpot {
            f += m1 * a1 * (w * t + phi1 + phase).cos()
                + m2 * a2 * (2.0 * w * t + phi2 + phase).cos();
        }
        if truth.second_maxwell.is_some() {
            let (b1, b2) = (maxwell2(w), maxwell2(2.0 * w));
            let (p1, p2) = (w * t + phi1, 2.0 * w * t + phi2);
            f +=
                a1 * (b1.0 * p1.cos() - b1.1 * p1.sin()) + a2 * (b2.0 * p2.cos() - b2.1 * p2.sin());
        }
        if let Some((b1, b2)) = cole {
            // Re(K Z e^{i phase}) for z = a cos(W t + phi): a (K_r cos - K_i sin).
            let (p1, p2) = (w * t + phi1, 2.0 * w * t + phi2);
            f +=
                a1 * (b1.0 * p1.cos() - b1.1 * p1.sin()) + a2 * (b2.0 * p2.cos() - b2.1 * p2.sin());
        }
        let cubic = truth
            .cubic_spring
            .map_or(0.0, |(c, z_c, _)| c * (z_of(t) - z_c).powi(3));
        f + truth.mass_kg * acc_of(t) + cubic
    };
    // Load path and load cell (out-of-library truths) act on the whole fine record.
    let measured =
        (truth.load_path_resonance.is_some() || truth.force_sensor_cubic != 0.0).then(|| {
            let total: Vec<f64> = (0..fine.len())
                .map(|j| force_at(t0 + j as f64 * h))
                .collect();
            truth.measured_force(&total, h)
        });
    let mut ts = Vec::with_capacity(n);
    let mut zs = Vec::with_capacity(n);
    let mut fs = Vec::with_capacity(n);
    for i in 0..n {
        let t = i as f64 * dt;
        ts.push(t);
        zs.push(z_of(t));
        fs.push(match &measured {
            Some(m) => interpolate(m, t0, h, t - truth.force_lag_s),
            None => force_at(t - truth.force_lag_s),
        });
    }
    (ts, zs, fs)
}

/// Linear interpolation of a series on the grid `t0 + j h`.
fn interpolate(series: &[f64], t0: f64, h: f64, t: f64) -> f64 {
    let x = ((t - t0) / h).max(0.0);
    let i = (x.floor() as usize).min(series.len() - 2);
    let frac = x - i as f64;
    series[i] * (1.0 - frac) + series[i + 1] * frac
}

/// A recorded passage (history test): a train of axle pulses on a preload.
#[derive(Debug, Clone, Copy)]
pub struct Passage {
    pub preload_n: f64,
    /// Peak force above the preload of each axle pulse, N.
    pub peak_n: f64,
    pub temperature_c: f64,
    pub duration_s: f64,
    pub rate_hz: f64,
    /// Axle pulses: count, first at, spacing, width (s) of the Gaussian pulses.
    pub n_axles: usize,
    pub pulse_width_s: f64,
}

impl Passage {
    /// Three passages of rising size on a 20 kN preload.
    pub fn rising(n: usize) -> Vec<Passage> {
        (0..n)
            .map(|i| Passage {
                preload_n: 20e3,
                peak_n: 8e3 + 16e3 * i as f64 / (n.max(2) - 1) as f64,
                temperature_c: 23.0,
                duration_s: 4.0,
                rate_hz: 1000.0,
                n_axles: 4,
                pulse_width_s: 0.06,
            })
            .collect()
    }
}

/// Simulates a passage (friction, preload stiffening, mass, delay, load path and load
/// cell as in harmonic tests; springpots and fractional branches are harmonic-only here).
pub fn simulate_passage(truth: &Truth, passage: &Passage) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    assert!(
        truth.springpot.is_none()
            && truth.fractional_maxwell_order.is_none()
            && truth.second_maxwell.is_none(),
        "passages simulate time-domain truths only"
    );
    let l = truth.length_m;
    let (b, a) = truth.temperature_factors(passage.temperature_c);
    let k1 = truth.k1_0_n_per_m2 * l * b;
    let k2 = truth.k2_0_n_per_m2 * l * b;
    let c2 = truth.c2_0_ns_per_m2 * l * b * a;
    let (chi, p0) = (truth.chi, truth.p0_n);
    let g = (1.0 + passage.preload_n / p0).powf(chi);
    let k_fast = (k1 + 0.5 * k2) * g + truth.friction.map_or(0.0, |(kf, _)| 0.3 * kf * l);
    let amp = passage.peak_n / k_fast;
    let z_static = static_displacement(k1, chi, p0, passage.preload_n);
    let spacing = (passage.duration_s - 1.0) / passage.n_axles as f64;
    let centres: Vec<f64> = (0..passage.n_axles)
        .map(|k| 0.6 + spacing * k as f64)
        .collect();
    let s = passage.pulse_width_s;
    let pulse = |t: f64, order: u32| -> f64 {
        centres
            .iter()
            .map(|&c| {
                let u = (t - c) / s;
                let e = (-u * u).exp();
                match order {
                    0 => amp * e,
                    1 => amp * e * (-2.0 * u / s),
                    _ => amp * e * (4.0 * u * u - 2.0) / (s * s),
                }
            })
            .sum()
    };
    let dt = 1.0 / passage.rate_hz;
    let n = (passage.duration_s * passage.rate_hz).round() as usize;
    let sub = 8usize;
    let h = dt / sub as f64;
    let fs0 = passage.preload_n;
    let mut state = [fs0, 0.0, 0.0];
    let (kf, ff_slip) = truth.friction.map_or((0.0, 1.0), |(k, f)| (k * l, f * l));
    let rates = ElementRates {
        k1,
        k2,
        c2,
        chi,
        p0,
        kf,
        ff_slip,
        exponent: truth.friction_exponent,
        maxwell: true,
    };
    let deriv = |t: f64, st: &[f64; 3]| rates.at(pulse(t, 1), st);
    let mut fine = Vec::with_capacity(n * sub + 1);
    let mut t = 0.0;
    fine.push(state[0] + state[1] + state[2]);
    for _ in 0..n * sub {
        rk4_step(&deriv, t, h, &mut state);
        t += h;
        fine.push(state[0] + state[1] + state[2] + truth.mass_kg * pulse(t, 2));
    }
    let measured = truth.measured_force(&fine, h);
    let ts: Vec<f64> = (0..n).map(|i| i as f64 * dt).collect();
    let zs: Vec<f64> = ts.iter().map(|&t| z_static + pulse(t, 0)).collect();
    let fs: Vec<f64> = ts
        .iter()
        .map(|&t| interpolate(&measured, 0.0, h, t - truth.force_lag_s))
        .collect();
    (ts, zs, fs)
}

/// Writes a campaign directory for `truth` over `design`.
/// How tests are sampled: samples per cycle (at least `min_rate_hz`), cycles recorded
/// below and above 2 Hz, and white noise on the displacement relative to the force's.
#[derive(Debug, Clone, Copy)]
pub struct Acquisition {
    pub samples_per_cycle: f64,
    pub min_rate_hz: f64,
    pub cycles_below_2_hz: usize,
    pub cycles_above_2_hz: usize,
    /// Harmonic records start from rest at the preload, start-up included (see
    /// `simulate_test`), instead of after a lead-in.
    pub from_rest: bool,
}

impl Acquisition {
    pub fn typical() -> Acquisition {
        Acquisition {
            samples_per_cycle: 64.0,
            min_rate_hz: 500.0,
            cycles_below_2_hz: 4,
            cycles_above_2_hz: 8,
            from_rest: false,
        }
    }
}

pub fn write_campaign(dir: &Path, truth: &Truth, design: &[TestPoint], noise: &Noise, seed: u64) {
    write_campaign_with(dir, truth, design, noise, seed, &Acquisition::typical());
}

pub fn write_campaign_with(
    dir: &Path,
    truth: &Truth,
    design: &[TestPoint],
    noise: &Noise,
    seed: u64,
    acquisition: &Acquisition,
) {
    write_campaign_full(dir, truth, design, &[], noise, seed, acquisition);
}

/// A campaign of harmonic tests (`design`, in order) followed by recorded passages.
pub fn write_campaign_full(
    dir: &Path,
    truth: &Truth,
    design: &[TestPoint],
    passages: &[Passage],
    noise: &Noise,
    seed: u64,
    acquisition: &Acquisition,
) {
    std::fs::create_dir_all(dir).unwrap();
    let n_tests = design.len() + passages.len();
    // A specimen that changes over the campaign: its moduli at test `index`.
    let truth_at = |index: usize| -> Truth {
        let fraction = index as f64 / (n_tests.max(2) - 1) as f64;
        let mut at = truth.scaled(1.0 - truth.softening_over_campaign * fraction);
        at.cubic_spring = truth
            .cubic_spring
            .map(|(c, z_c, drift)| (c * (1.0 + drift * fraction), z_c, 0.0));
        at
    };
    let mut rng = Rng::new(seed);
    let mut toml = format!("sample_length_m = {:?}\n", truth.length_m);
    // Campaign clock (s from the first start) and the specimen's temperature rise.
    let mut clock_s = 0.0;
    let mut rise_k = 0.0;
    let mut largest_n = 0.0f64;
    let mut soften = |f: &mut [f64]| {
        if let Some((d, scale)) = truth.mullins {
            for fi in f.iter_mut() {
                largest_n = largest_n.max(*fi);
                *fi *= 1.0 - d * (1.0 - (-(largest_n - *fi) / scale).exp());
            }
        }
    };
    let mut started_at = |duration_s: f64| -> String {
        let Some(rest) = truth.rest_s else {
            return String::new();
        };
        let start = clock_s;
        clock_s += duration_s + rest;
        // Whole seconds after 2026-03-14T09:00:00Z (minutes and seconds written out).
        let s = start.round() as i64;
        format!(
            "started_at = \"2026-03-14T{:02}:{:02}:{:02}Z\"\n",
            9 + s / 3600,
            (s / 60) % 60,
            s % 60
        )
    };
    for (idx, point) in design.iter().enumerate() {
        let id = format!(
            "T{idx:02}-P{:02}-F{}-A{}-T{}",
            (point.preload_n / 1e3).round(),
            point.frequency_hz,
            point.amplitude_n / 1e3,
            point.temperature_c
        );
        let n_cycles = if point.frequency_hz < 2.0 {
            acquisition.cycles_below_2_hz
        } else {
            acquisition.cycles_above_2_hz
        };
        let mut specimen = truth_at(idx);
        let (mut t, mut z, mut f) = simulate_test(
            &specimen.heated(rise_k),
            point,
            n_cycles,
            acquisition.samples_per_cycle,
            acquisition.min_rate_hz,
            acquisition.from_rest,
        );
        if let Some((heat_capacity, heat_transfer, _)) = truth.self_heating {
            // Power of the record, the temperature through the test (Euler), and the test
            // again at its mid-record temperature.
            let duration = t.last().copied().unwrap_or(0.0) + t.get(1).copied().unwrap_or(0.0);
            let energy: f64 = z
                .windows(2)
                .zip(f.windows(2))
                .map(|(zz, ff)| 0.5 * (ff[0] + ff[1]) * (zz[1] - zz[0]))
                .sum();
            let power = energy.max(0.0) / duration;
            let h = 0.05;
            let mut time = 0.0;
            let mut mid_rise = rise_k;
            while time < duration {
                rise_k += h * (power - heat_transfer * rise_k) / heat_capacity;
                time += h;
                if time <= 0.5 * duration {
                    mid_rise = rise_k;
                }
            }
            specimen = specimen.heated(mid_rise);
            (t, z, f) = simulate_test(
                &specimen,
                point,
                n_cycles,
                acquisition.samples_per_cycle,
                acquisition.min_rate_hz,
                acquisition.from_rest,
            );
            // The rest cools it.
            let mut time = 0.0;
            while time < truth.rest_s.unwrap_or(0.0) {
                rise_k -= h * heat_transfer * rise_k / heat_capacity;
                time += h;
            }
        }
        soften(&mut f);
        let record_s = t.last().copied().unwrap_or(0.0) + t.get(1).copied().unwrap_or(0.0);
        let start_line = started_at(record_s);
        let drift_phase = rng.uniform() * 2.0 * PI;
        let drift = |t: f64| noise.drift_force * (2.0 * PI * t / 7.0 + drift_phase).sin();
        add_noise(
            &t,
            &mut z,
            &mut f,
            point.amplitude_n,
            noise,
            &drift,
            &mut rng,
        );
        write_record(dir, &id, &t, &z, &f);
        let _ = write!(
            toml,
            "\n[[test]]\nid = \"{id}\"\nfile = \"{id}.csv\"\nkind = \"harmonic\"\npreload_n = {:?}\namplitude_n = {:?}\nfrequency_hz = {:?}\ntemperature_c = {:?}\n{start_line}",
            point.preload_n, point.amplitude_n, point.frequency_hz, point.temperature_c
        );
    }
    for (k, passage) in passages.iter().enumerate() {
        let id = format!("H{k}-passage-{:.0}kN", passage.peak_n / 1e3);
        let (t, mut z, mut f) =
            simulate_passage(&truth_at(design.len() + k).heated(rise_k), passage);
        soften(&mut f);
        let start_line = started_at(t.last().copied().unwrap_or(0.0));
        // Passages get no slow drift (their records are short).
        add_noise(
            &t,
            &mut z,
            &mut f,
            0.5 * passage.peak_n,
            noise,
            &|_| 0.0,
            &mut rng,
        );
        write_record(dir, &id, &t, &z, &f);
        let _ = write!(
            toml,
            "\n[[test]]\nid = \"{id}\"\nfile = \"{id}.csv\"\nkind = \"history\"\ntemperature_c = {:?}\n{start_line}",
            passage.temperature_c
        );
    }
    std::fs::write(dir.join("campaign.toml"), toml).unwrap();
}

/// Adds the campaign's noise to a record: white and AR(1) force noise and the slow
/// `drift(t)` (relative to `force_scale_n`), white displacement noise relative to the
/// displacement's half range.
fn add_noise(
    t: &[f64],
    z: &mut [f64],
    f: &mut [f64],
    force_scale_n: f64,
    noise: &Noise,
    drift: &dyn Fn(f64) -> f64,
    rng: &mut Rng,
) {
    let z_amp = {
        let lo = z.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = z.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (hi - lo)
    };
    let mut ar = 0.0;
    let innovation = (1.0 - noise.coloured_rho * noise.coloured_rho).sqrt();
    for i in 0..t.len() {
        ar = noise.coloured_rho * ar + innovation * rng.normal();
        f[i] += force_scale_n
            * (noise.white_force * rng.normal() + noise.coloured_force * ar + drift(t[i]));
        z[i] += z_amp * noise.white_displacement * rng.normal();
    }
}

fn write_record(dir: &Path, id: &str, t: &[f64], z: &[f64], f: &[f64]) {
    let mut csv = String::from("t_s,displacement_m,force_n\n");
    for i in 0..t.len() {
        let _ = writeln!(csv, "{:?},{:?},{:?}", t[i], z[i], f[i]);
    }
    std::fs::write(dir.join(format!("{id}.csv")), csv).unwrap();
}

/// A baseline model file whose parameters are off (and chi as given).
pub fn off_baseline_toml(chi: f64) -> String {
    format!(
        "form = \"consistent\"\nlength_m = 0.75\nk1_0_n_per_m2 = 75e6\nk2_0_n_per_m2 = 7e6\nc2_0_ns_per_m2 = 0.5e6\nchi = {chi:?}\np0_n = 64e3\n"
    )
}
