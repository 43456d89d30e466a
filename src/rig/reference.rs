//! Offline reference for fidelity: the same specimen mass, rig damping, element model and
//! external load, simulated without any loop (the element force acts on the mass exactly,
//! as an ideal actuator would apply it). Stepped one period at a time, so a report of any
//! length holds no whole-run array. Offline only.

use super::load::LoadProgramme;
use crate::hil::config::HilConfig;
use crate::model::oscillator::{Oscillator, StartCondition};

/// The reference displacement at `t_k = k dt`, k = 0, 1, 2, ... (`Iterator`).
pub struct ReferenceStepper {
    osc: Oscillator,
    load: LoadProgramme,
    dt_s: f64,
    /// Programme step of the oscillator's state.
    k: u64,
    /// Steps handed out by the iterator.
    emitted: u64,
}

impl ReferenceStepper {
    /// Sub-stepping is sized for the largest force the programme reaches within
    /// `horizon_s` (scanned at the loop rate over one pass through its block sequence at
    /// most: the programme repeats).
    pub fn new(cfg: &HilConfig, horizon_s: f64) -> ReferenceStepper {
        let dt_s = cfg.loop_.dt_s();
        let load = LoadProgramme::new(&cfg.programme, cfg.model.length_m);
        let scan_s = if load.sequence_s() > 0.0 {
            horizon_s.min(load.sequence_s())
        } else {
            horizon_s
        };
        let n = (scan_s / dt_s).ceil() as u64;
        let max_force = (0..=n)
            .map(|k| load.force_n(k as f64 * dt_s).abs())
            .fold(0.0, f64::max);
        let mut osc = Oscillator::new(
            cfg.model.element,
            cfg.rig.specimen_mass_kg,
            dt_s,
            2.0 * max_force,
        )
        .with_extra_damping(cfg.rig.damping_ns_per_m);
        osc.start(StartCondition::Static, load.force_n(0.0));
        ReferenceStepper {
            osc,
            load,
            dt_s,
            k: 0,
            emitted: 0,
        }
    }
}

impl ReferenceStepper {
    /// The displacement at programme step `m` (`t = m dt`), stepping forward to it.
    pub fn advance_to(&mut self, m: u64) -> f64 {
        while self.k < m {
            self.osc.step(
                self.load.force_n(self.k as f64 * self.dt_s),
                self.load.force_n((self.k + 1) as f64 * self.dt_s),
            );
            self.k += 1;
        }
        self.osc.displacement_m()
    }

    /// Restarts the reference from a measured state at programme step `m` (after an
    /// operator hold the rig resumes from where it was held, not where the reference
    /// would be); the element starts relaxed there, as it is after a hold.
    pub fn resync(&mut self, x_m: f64, v_m_per_s: f64, m: u64) {
        self.osc.set_state(x_m, v_m_per_s);
        self.k = m;
    }
}

impl Iterator for ReferenceStepper {
    type Item = f64;

    /// The displacement at the next grid instant (the first call gives `t = 0`).
    fn next(&mut self) -> Option<f64> {
        let x = self.advance_to(self.emitted);
        self.emitted += 1;
        Some(x)
    }
}

/// Reference displacement at `t_k = k dt`, k = 0..=n_steps, m (short runs and tests).
pub fn reference_displacement_m(cfg: &HilConfig, n_steps: usize) -> Vec<f64> {
    ReferenceStepper::new(cfg, n_steps as f64 * cfg.loop_.dt_s())
        .take(n_steps + 1)
        .collect()
}
