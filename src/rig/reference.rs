//! Offline reference for fidelity: the same specimen mass, rig damping, element model and
//! external load, simulated without any loop (the element force acts on the mass exactly,
//! as an ideal actuator would apply it). Allocates its output; offline only.

use super::load::LoadProgramme;
use crate::hil::config::HilConfig;
use crate::model::oscillator::{Oscillator, StartCondition};

/// Reference displacement at `t_k = k dt`, k = 0..n_steps, m.
pub fn reference_displacement_m(cfg: &HilConfig, n_steps: usize) -> Vec<f64> {
    let dt = cfg.loop_.dt_s();
    let load = LoadProgramme::new(&cfg.scenario, cfg.model.length_m);
    let max_force = (0..=n_steps)
        .map(|k| load.force_n(k as f64 * dt).abs())
        .fold(0.0, f64::max);
    let mut osc = Oscillator::new(
        cfg.model.element,
        cfg.rig.specimen_mass_kg,
        dt,
        2.0 * max_force,
    )
    .with_extra_damping(cfg.rig.damping_ns_per_m);
    osc.start(StartCondition::Static, load.force_n(0.0));
    let mut out = Vec::with_capacity(n_steps + 1);
    out.push(osc.displacement_m());
    for k in 0..n_steps {
        osc.step(
            load.force_n(k as f64 * dt),
            load.force_n((k + 1) as f64 * dt),
        );
        out.push(osc.displacement_m());
    }
    out
}
