//! Rig physics: specimen mass on guides with viscous damping, driven by the external
//! load programme and by the actuator, which applies the emulated element's reaction.
//!
//! `m x'' = F_ext(t) - c x' - F_act`, actuator `T dF_act/dt = u(t - tau) - F_act`
//! (first-order lag `T`, transport delay `tau`, saturation `|F_act| <= F_max`), `u` the
//! command held constant over each loop period (zero-order hold). Integrated with RK4
//! over `n_sub` sub-steps per period. Pure: no I/O, no clock, no allocation per step.

use crate::hil::config::RigConfig;

const DELAY_LINE_LEN: usize = 4096;

/// The rig's mechanical and actuator state.
#[derive(Debug, Clone)]
pub struct RigPhysics {
    mass_kg: f64,
    damping_ns_per_m: f64,
    lag_s: f64,
    delay_s: f64,
    force_max_n: f64,
    n_sub: u32,
    pub x_m: f64,
    pub v_m_per_s: f64,
    pub actuator_force_n: f64,
    /// Commands as (time they were issued, s; value, N), a ring.
    delay_line: Vec<(f64, f64)>,
    delay_head: usize,
    delay_len: usize,
}

impl RigPhysics {
    /// A rig at rest at `x0_m` with the actuator holding `force0_n`.
    pub fn new(cfg: &RigConfig, x0_m: f64, force0_n: f64) -> RigPhysics {
        let mut delay_line = vec![(0.0, 0.0); DELAY_LINE_LEN];
        delay_line[0] = (f64::NEG_INFINITY, force0_n);
        RigPhysics {
            mass_kg: cfg.specimen_mass_kg,
            damping_ns_per_m: cfg.damping_ns_per_m,
            lag_s: cfg.actuator_lag_s,
            delay_s: cfg.actuator_delay_s,
            force_max_n: cfg.actuator_force_max_n,
            n_sub: cfg.internal_substeps,
            x_m: x0_m,
            v_m_per_s: 0.0,
            actuator_force_n: force0_n.clamp(-cfg.actuator_force_max_n, cfg.actuator_force_max_n),
            delay_line,
            delay_head: 0,
            delay_len: 1,
        }
    }

    /// Command in effect at the actuator at time `t_s` (issued at or before `t_s - tau`).
    fn delayed_command_n(&self, t_s: f64) -> f64 {
        let t_issue = t_s - self.delay_s;
        for back in 0..self.delay_len {
            let idx = (self.delay_head + DELAY_LINE_LEN - back) % DELAY_LINE_LEN;
            let (t, u) = self.delay_line[idx];
            if t <= t_issue {
                return u;
            }
        }
        // Older than the line remembers: the oldest entry.
        self.delay_line[(self.delay_head + DELAY_LINE_LEN + 1 - self.delay_len) % DELAY_LINE_LEN].1
    }

    #[inline]
    fn derivative(&self, x: f64, v: f64, fa: f64, u: f64, f_ext: f64) -> (f64, f64, f64) {
        let _ = x;
        let applied = fa.clamp(-self.force_max_n, self.force_max_n);
        let dv = (f_ext - self.damping_ns_per_m * v - applied) / self.mass_kg;
        let dfa = if self.lag_s > 0.0 {
            (u - fa) / self.lag_s
        } else {
            0.0
        };
        (v, dv, dfa)
    }

    /// Advances one loop period from `t0_s` with command `command_n` issued at `t0_s`; the
    /// external force goes linearly from `f_ext_start_n` to `f_ext_end_n` over the period
    /// (as in the offline reference, so both see the same load).
    pub fn advance(
        &mut self,
        t0_s: f64,
        dt_s: f64,
        command_n: f64,
        f_ext_start_n: f64,
        f_ext_end_n: f64,
    ) {
        self.delay_head = (self.delay_head + 1) % DELAY_LINE_LEN;
        self.delay_line[self.delay_head] = (t0_s, command_n);
        self.delay_len = (self.delay_len + 1).min(DELAY_LINE_LEN);
        let n = self.n_sub;
        let h = dt_s / n as f64;
        let load = |tau: f64| f_ext_start_n + (f_ext_end_n - f_ext_start_n) * (tau / dt_s);
        let (mut x, mut v, mut fa) = (self.x_m, self.v_m_per_s, self.actuator_force_n);
        for i in 0..n {
            let ta = i as f64 * h;
            // The delayed command is taken at the sub-step's midpoint, constant over it.
            let u = self.delayed_command_n(t0_s + ta + 0.5 * h);
            if self.lag_s == 0.0 {
                fa = u;
            }
            let (fe0, fe_mid, fe1) = (load(ta), load(ta + 0.5 * h), load(ta + h));
            let k1 = self.derivative(x, v, fa, u, fe0);
            let k2 = self.derivative(
                x + 0.5 * h * k1.0,
                v + 0.5 * h * k1.1,
                fa + 0.5 * h * k1.2,
                u,
                fe_mid,
            );
            let k3 = self.derivative(
                x + 0.5 * h * k2.0,
                v + 0.5 * h * k2.1,
                fa + 0.5 * h * k2.2,
                u,
                fe_mid,
            );
            let k4 = self.derivative(x + h * k3.0, v + h * k3.1, fa + h * k3.2, u, fe1);
            x += h / 6.0 * (k1.0 + 2.0 * k2.0 + 2.0 * k3.0 + k4.0);
            v += h / 6.0 * (k1.1 + 2.0 * k2.1 + 2.0 * k3.1 + k4.1);
            fa += h / 6.0 * (k1.2 + 2.0 * k2.2 + 2.0 * k3.2 + k4.2);
        }
        self.x_m = x;
        self.v_m_per_s = v;
        self.actuator_force_n = fa.clamp(-self.force_max_n, self.force_max_n);
    }

    /// Kinetic energy of the specimen, J.
    pub fn kinetic_energy_j(&self) -> f64 {
        0.5 * self.mass_kg * self.v_m_per_s * self.v_m_per_s
    }
}

/// Displacement sensor: additive Gaussian noise from a seeded PRNG, then quantisation.
#[derive(Debug, Clone)]
pub struct Sensor {
    noise_m: f64,
    resolution_m: f64,
    state: u64,
    spare: Option<f64>,
}

impl Sensor {
    pub fn new(noise_m: f64, resolution_m: f64, seed: u64) -> Sensor {
        Sensor {
            noise_m,
            resolution_m,
            state: seed ^ 0x9E37_79B9_7F4A_7C15,
            spare: None,
        }
    }

    fn next_u64(&mut self) -> u64 {
        // splitmix64: small, fast, deterministic for a given seed.
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    /// A standard normal deviate (Box-Muller).
    pub fn gaussian(&mut self) -> f64 {
        if let Some(s) = self.spare.take() {
            return s;
        }
        let (u1, u2) = (self.uniform(), self.uniform());
        let r = (-2.0 * u1.ln()).sqrt();
        let phi = 2.0 * std::f64::consts::PI * u2;
        self.spare = Some(r * phi.sin());
        r * phi.cos()
    }

    /// Measures displacement `x_m`.
    pub fn measure(&mut self, x_m: f64) -> f64 {
        let noisy = x_m + self.noise_m * self.gaussian();
        if self.resolution_m > 0.0 {
            (noisy / self.resolution_m).round() * self.resolution_m
        } else {
            noisy
        }
    }
}
