//! Rig physics: specimen mass on guides with viscous damping, driven by the external
//! load programme and by the actuator, which applies the emulated element's reaction.
//!
//! `m x'' = F_ext(t) - c x' - F_act`, `F_act` the force of the actuator plant
//! (`rig::actuator`: lag-delay, servo-hydraulic or electrodynamic; saturated at its
//! `force_max_n`) driven by the command `u(t - tau)`: held constant over each loop period
//! (zero-order hold) and delayed by the transport delay `tau`, and by the specimen's
//! velocity (the actuator moves with it). The plant's states join `x, x'`; RK4 over
//! `n_sub` sub-steps per period. Pure: no I/O, no clock, no allocation per step.

use super::actuator::{ActuatorPlant, PlantState};
use crate::hil::config::RigConfig;

const DELAY_LINE_LEN: usize = 4096;

/// The rig's mechanical and actuator state.
#[derive(Debug, Clone)]
pub struct RigPhysics {
    /// Specimen mass plus whatever of the actuator moves with it, kg.
    mass_kg: f64,
    damping_ns_per_m: f64,
    plant: ActuatorPlant,
    delay_s: f64,
    n_sub: u32,
    pub x_m: f64,
    pub v_m_per_s: f64,
    pub actuator_force_n: f64,
    /// The actuator plant's states.
    actuator_state: PlantState,
    /// Whether the plant was in stroke control (position hold) last period.
    stroke_control: bool,
    /// Commands as (time they were issued, s; value, N), a ring.
    delay_line: Vec<(f64, f64)>,
    delay_head: usize,
    delay_len: usize,
}

impl RigPhysics {
    /// A rig at rest at `x0_m` with the actuator (the perturbed truth of `[rig.actuator]`)
    /// at rest under the command `force0_n`.
    pub fn new(cfg: &RigConfig, x0_m: f64, force0_n: f64) -> RigPhysics {
        RigPhysics::with_plant(
            cfg,
            ActuatorPlant::from_config(&cfg.actuator),
            x0_m,
            force0_n,
        )
    }

    /// As `new`, with the actuator plant given.
    pub fn with_plant(
        cfg: &RigConfig,
        plant: ActuatorPlant,
        x0_m: f64,
        force0_n: f64,
    ) -> RigPhysics {
        let mut delay_line = vec![(0.0, 0.0); DELAY_LINE_LEN];
        delay_line[0] = (f64::NEG_INFINITY, force0_n);
        let actuator_state = plant.rest_state(force0_n);
        RigPhysics {
            mass_kg: cfg.specimen_mass_kg + plant.moving_mass_kg(),
            damping_ns_per_m: cfg.damping_ns_per_m,
            delay_s: plant.transport_delay_s(),
            n_sub: cfg.internal_substeps,
            x_m: x0_m,
            v_m_per_s: 0.0,
            actuator_force_n: plant.applied_force_n(&actuator_state, 0.0),
            actuator_state,
            stroke_control: false,
            plant,
            delay_line,
            delay_head: 0,
            delay_len: 1,
        }
    }

    /// A rig at rest at `x0_m` whose actuator has been holding the specimen against the
    /// load `force0_n` (the servo controller held position before the run, so its command
    /// converged on whatever makes the actuator apply `force0_n`: with a gain error that
    /// is not `force0_n`). Returns the rig and that command.
    pub fn holding(cfg: &RigConfig, x0_m: f64, force0_n: f64) -> (RigPhysics, f64) {
        let plant = ActuatorPlant::from_config(&cfg.actuator);
        let probe = plant.applied_force_n(&plant.rest_state(force0_n), 0.0);
        let command_n = if probe.is_finite() && probe != 0.0 && force0_n != 0.0 {
            force0_n * (force0_n / probe)
        } else {
            force0_n
        };
        (
            RigPhysics::with_plant(cfg, plant, x0_m, command_n),
            command_n,
        )
    }

    /// The actuator plant (its true parameters).
    pub fn plant(&self) -> &ActuatorPlant {
        &self.plant
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

    /// Derivatives of `(x, v, plant states)`.
    #[inline]
    fn derivative(
        &self,
        (x, v): (f64, f64),
        s: &PlantState,
        u: f64,
        stroke_target_m: f64,
        f_ext: f64,
    ) -> (f64, f64, PlantState) {
        let applied = self.plant.applied_force_n(s, v);
        let dv = (f_ext - self.damping_ns_per_m * v - applied) / self.mass_kg;
        let ds = if stroke_target_m.is_finite() {
            self.plant.stroke_derivative(s, x - stroke_target_m, v)
        } else {
            self.plant.derivative(s, u, v)
        };
        (v, dv, ds)
    }

    /// Advances one loop period from `t0_s` with command `command_n` issued at `t0_s`; the
    /// external force goes linearly from `f_ext_start_n` to `f_ext_end_n` over the period
    /// (as in the offline reference, so both see the same load). With `stroke_target_m`
    /// finite the actuator holds that position in stroke control instead (its own
    /// position loop, `ActuatorPlant::stroke_derivative`; only a plant that has one,
    /// `ActuatorPlant::has_stroke_control`, is asked to); the command still enters the
    /// transport delay line, so force control resumes from it.
    pub fn advance(
        &mut self,
        t0_s: f64,
        dt_s: f64,
        command_n: f64,
        stroke_target_m: f64,
        f_ext_start_n: f64,
        f_ext_end_n: f64,
    ) {
        debug_assert!(!stroke_target_m.is_finite() || self.plant.has_stroke_control());
        let stroke = stroke_target_m.is_finite();
        if stroke != self.stroke_control {
            self.plant.switch_control(&mut self.actuator_state, stroke);
            self.stroke_control = stroke;
        }
        self.delay_head = (self.delay_head + 1) % DELAY_LINE_LEN;
        self.delay_line[self.delay_head] = (t0_s, command_n);
        self.delay_len = (self.delay_len + 1).min(DELAY_LINE_LEN);
        let n = self.n_sub;
        let h = dt_s / n as f64;
        let load = |tau: f64| f_ext_start_n + (f_ext_end_n - f_ext_start_n) * (tau / dt_s);
        let (mut x, mut v, mut s) = (self.x_m, self.v_m_per_s, self.actuator_state);
        let step = |s: &PlantState, k: &PlantState, f: f64| -> PlantState {
            [
                s[0] + f * k[0],
                s[1] + f * k[1],
                s[2] + f * k[2],
                s[3] + f * k[3],
            ]
        };
        for i in 0..n {
            let ta = i as f64 * h;
            // The delayed command is taken at the sub-step's midpoint, constant over it.
            let u = self.delayed_command_n(t0_s + ta + 0.5 * h);
            self.plant.begin_substep(&mut s, u);
            let (fe0, fe_mid, fe1) = (load(ta), load(ta + 0.5 * h), load(ta + h));
            let st = stroke_target_m;
            let k1 = self.derivative((x, v), &s, u, st, fe0);
            let mid1 = (x + 0.5 * h * k1.0, v + 0.5 * h * k1.1);
            let k2 = self.derivative(mid1, &step(&s, &k1.2, 0.5 * h), u, st, fe_mid);
            let mid2 = (x + 0.5 * h * k2.0, v + 0.5 * h * k2.1);
            let k3 = self.derivative(mid2, &step(&s, &k2.2, 0.5 * h), u, st, fe_mid);
            let end = (x + h * k3.0, v + h * k3.1);
            let k4 = self.derivative(end, &step(&s, &k3.2, h), u, st, fe1);
            x += h / 6.0 * (k1.0 + 2.0 * k2.0 + 2.0 * k3.0 + k4.0);
            v += h / 6.0 * (k1.1 + 2.0 * k2.1 + 2.0 * k3.1 + k4.1);
            for (j, sj) in s.iter_mut().enumerate() {
                *sj += h / 6.0 * (k1.2[j] + 2.0 * k2.2[j] + 2.0 * k3.2[j] + k4.2[j]);
            }
            self.plant.end_substep(&mut s);
        }
        self.plant.end_period(&mut s);
        self.x_m = x;
        self.v_m_per_s = v;
        self.actuator_state = s;
        self.actuator_force_n = self.plant.applied_force_n(&s, v);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::actuator::{preset, ActuatorConfig, ActuatorParams};

    /// The physics before the actuator plants (lag-delay only), kept to show the default
    /// runs bit-identically.
    #[derive(Debug, Clone)]
    pub struct LegacyPhysics {
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

    impl LegacyPhysics {
        /// A rig at rest at `x0_m` with the actuator holding `force0_n`.
        pub fn new(cfg: &RigConfig, x0_m: f64, force0_n: f64) -> LegacyPhysics {
            let mut delay_line = vec![(0.0, 0.0); DELAY_LINE_LEN];
            delay_line[0] = (f64::NEG_INFINITY, force0_n);
            LegacyPhysics {
                mass_kg: cfg.specimen_mass_kg,
                damping_ns_per_m: cfg.damping_ns_per_m,
                lag_s: cfg.actuator.nominal.si[2],
                delay_s: cfg.actuator.nominal.si[0],
                force_max_n: cfg.actuator.nominal.si[1],
                n_sub: cfg.internal_substeps,
                x_m: x0_m,
                v_m_per_s: 0.0,
                actuator_force_n: force0_n
                    .clamp(-cfg.actuator.nominal.si[1], cfg.actuator.nominal.si[1]),
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
            self.delay_line
                [(self.delay_head + DELAY_LINE_LEN + 1 - self.delay_len) % DELAY_LINE_LEN]
                .1
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
    }

    fn rig_with(actuator: ActuatorConfig) -> RigConfig {
        let mut rig = crate::hil::config::default_hil_config().unwrap().rig;
        rig.actuator = actuator;
        rig
    }

    /// A command and load that wander: a slow sine, a fast one, steps.
    fn drive(k: usize) -> (f64, f64) {
        let t = k as f64 / 4096.0;
        let f = 20e3
            + 5e3 * (2.0 * std::f64::consts::PI * 7.0 * t).sin()
            + if k % 500 < 250 { 2e3 } else { 0.0 };
        (
            f + 300.0 * (2.0 * std::f64::consts::PI * 170.0 * t).sin(),
            f,
        )
    }

    #[test]
    fn the_default_lag_delay_runs_bit_identically_to_the_physics_before_the_plants() {
        for (delay, lag) in [(50e-6, 80e-6), (50e-6, 0.0), (0.0, 80e-6)] {
            let cfg = rig_with(ActuatorConfig::lag_delay(delay, lag, 150e3));
            let mut new = RigPhysics::new(&cfg, 3.5e-4, 20e3);
            let mut old = LegacyPhysics::new(&cfg, 3.5e-4, 20e3);
            let dt = 1.0 / 4096.0;
            for k in 0..4096 {
                let (u, f_ext) = drive(k);
                let (u2, f_ext2) = drive(k + 1);
                let _ = u2;
                new.advance(k as f64 * dt, dt, u, f64::NAN, f_ext, f_ext2);
                old.advance(k as f64 * dt, dt, u, f_ext, f_ext2);
                assert_eq!(new.x_m.to_bits(), old.x_m.to_bits(), "step {k}");
                assert_eq!(new.v_m_per_s.to_bits(), old.v_m_per_s.to_bits(), "step {k}");
                assert_eq!(
                    new.actuator_force_n.to_bits(),
                    old.actuator_force_n.to_bits(),
                    "step {k}"
                );
            }
        }
        let default = crate::hil::config::default_hil_config()
            .unwrap()
            .rig
            .actuator;
        // As the configuration always converted it: us times 1e-6.
        assert_eq!(
            default.nominal,
            ActuatorConfig::lag_delay(50.0 * 1e-6, 80.0 * 1e-6, 150e3).nominal
        );
    }

    fn preset_config(name: &str) -> ActuatorConfig {
        let p = preset(name).unwrap();
        ActuatorConfig {
            nominal: ActuatorParams::from_config_units(p.kind, p.values),
            preset: Some(p.name),
            perturb: 0.0,
            perturb_seed: 0,
        }
    }

    /// A rig that held its specimen before the run starts in equilibrium whatever its
    /// actuator's gain: a perturbed shaker (force constant off its nominal) is commanded
    /// what makes it apply the load, and nothing moves.
    #[test]
    fn a_rig_that_held_before_the_run_starts_in_equilibrium_with_a_gain_error() {
        let mut actuator = preset_config("shaker-150kn");
        actuator.perturb = 0.3;
        actuator.perturb_seed = 2;
        let cfg = rig_with(actuator);
        let (mut p, command) = RigPhysics::holding(&cfg, 3.5e-4, 20e3);
        let gain = p.plant().applied_force_n(&p.plant().rest_state(1e3), 0.0) / 1e3;
        assert!(
            (gain - 1.0).abs() > 0.05,
            "the draw must put the gain off: {gain}"
        );
        assert!(
            (command * gain - 20e3).abs() < 1e-6 * 20e3,
            "{command} x {gain}"
        );
        assert!((p.actuator_force_n - 20e3).abs() < 1e-6 * 20e3);
        let dt = 1.0 / 4096.0;
        for k in 0..4096 {
            p.advance(k as f64 * dt, dt, command, f64::NAN, 20e3, 20e3);
        }
        assert!((p.x_m - 3.5e-4).abs() < 1e-9, "moved to {}", p.x_m);
        // The plain constructor rests under the command, not the load: it sinks.
        let mut q = RigPhysics::new(&cfg, 3.5e-4, 20e3);
        for k in 0..64 {
            q.advance(k as f64 * dt, dt, 20e3, f64::NAN, 20e3, 20e3);
        }
        assert!((q.x_m - 3.5e-4).abs() > 1e-6, "{}", q.x_m);
    }

    #[test]
    fn every_kind_holds_a_constant_command_and_saturates_at_its_limit() {
        for name in [
            "this-rig",
            "fatigue-150kn",
            "slow-250kn",
            "shaker-10kn",
            "shaker-150kn",
        ] {
            let cfg = rig_with(preset_config(name));
            let dt = 1.0 / 4096.0;
            // At rest in equilibrium: the load equals the command.
            let mut p = RigPhysics::new(&cfg, 3.5e-4, 8e3);
            for k in 0..4096 {
                p.advance(k as f64 * dt, dt, 8e3, f64::NAN, 8e3, 8e3);
            }
            assert!(
                (p.actuator_force_n - 8e3).abs() < 1e-6 * 8e3,
                "{name}: {}",
                p.actuator_force_n
            );
            assert!(p.v_m_per_s.abs() < 1e-9, "{name}: {}", p.v_m_per_s);
            // A step of the load, the command following it: the force settles on it.
            for k in 4096..8192 {
                p.advance(k as f64 * dt, dt, 9e3, f64::NAN, 9e3, 9e3);
            }
            assert!(
                (p.actuator_force_n - 9e3).abs() < 1e-3 * 9e3,
                "{name}: {}",
                p.actuator_force_n
            );
            // A command beyond the limit: the force stops at it.
            let f_max = p.plant().force_max_n();
            let mut p = RigPhysics::new(&cfg, 3.5e-4, 8e3);
            // (The load pushes the specimen into the actuator, as a test would.)
            let mut largest = 0.0f64;
            for k in 0..40 {
                p.advance(
                    k as f64 * dt,
                    dt,
                    10.0 * f_max,
                    f64::NAN,
                    2.0 * f_max,
                    2.0 * f_max,
                );
                assert!(p.actuator_force_n.abs() <= f_max, "{name}");
                largest = largest.max(p.actuator_force_n);
            }
            assert_eq!(largest, f_max, "{name}");
        }
    }
}
