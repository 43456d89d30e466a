//! Offline reference for fidelity: the same specimen mass, rig damping, element model (with
//! the material effects the emulator runs) and external load, simulated without any loop
//! (the element force acts on the mass exactly, as an ideal actuator would apply it).
//! Stepped one period at a time, so a report of any length holds no whole-run array.
//! Offline only.

use super::load::LoadProgramme;
use crate::hil::config::HilConfig;
use crate::model::oscillator::{Oscillator, StartCondition};
use crate::model::{ModelStepper, StepperMode};

/// Largest `omega h` of the augmented reference's leapfrog sub-steps (relative phase error
/// per cycle about `(omega h)^2 / 24`, under 2e-5).
const AUGMENTED_MAX_OMEGA_H: f64 = 0.02;

/// How the reference moves the mass.
enum Engine {
    /// The plain element: an ODE in the element's own state, RK4 sub-steps.
    Plain(Oscillator),
    /// A model with material effects (friction, springpot, self-heating, softening...):
    /// the emulator's own `ModelStepper` at a sub-step, coupled to the mass by leapfrog.
    Augmented(Box<AugmentedMass>),
}

/// The mass on the augmented model: `x` at the sub-step grid, `v` half a sub-step behind.
struct AugmentedMass {
    stepper: ModelStepper,
    mass_kg: f64,
    damping_ns_per_m: f64,
    h_s: f64,
    n_sub: u32,
    x_m: f64,
    v_m_per_s: f64,
}

impl AugmentedMass {
    /// Advances one period, the load going linearly from `f0_n` to `f1_n`.
    fn step(&mut self, f0_n: f64, f1_n: f64) {
        let n = f64::from(self.n_sub);
        for i in 0..self.n_sub {
            let external = f0_n + (f1_n - f0_n) * f64::from(i) / n;
            let element = self.stepper.force_n();
            let a = (external - element - self.damping_ns_per_m * self.v_m_per_s) / self.mass_kg;
            self.v_m_per_s += self.h_s * a;
            self.x_m += self.h_s * self.v_m_per_s;
            self.stepper.step(self.x_m);
        }
    }

    /// Restarts at a measured state, the element relaxed there (its branches' loads and
    /// the friction sliders' are not known from a record).
    fn set_state(&mut self, x_m: f64, v_m_per_s: f64) {
        self.x_m = x_m;
        self.v_m_per_s = v_m_per_s;
        self.stepper.reset_static(x_m);
    }
}

/// The reference displacement at `t_k = k dt`, k = 0, 1, 2, ... (`Iterator`).
pub struct ReferenceStepper {
    engine: Engine,
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
        let emulated = cfg.augmented.effects.iter().any(|e| !e.is_rig_artefact());
        let engine = if emulated {
            // The rig starts where the plain element is in static equilibrium under the
            // first load, at rest, and the emulator relaxes its model there: so does this.
            let x0 = osc.displacement_m();
            let stiffness = cfg
                .augmented
                .effective_element()
                .high_frequency_stiffness_n_per_m(2.0 * max_force);
            let omega = (stiffness / cfg.rig.specimen_mass_kg).sqrt();
            let n_sub = ((omega * dt_s / AUGMENTED_MAX_OMEGA_H).ceil() as u32).max(1);
            let h_s = dt_s / f64::from(n_sub);
            Engine::Augmented(Box::new(AugmentedMass {
                stepper: ModelStepper::new(&cfg.augmented, StepperMode::Emulation, h_s, x0),
                mass_kg: cfg.rig.specimen_mass_kg,
                damping_ns_per_m: cfg.rig.damping_ns_per_m,
                h_s,
                n_sub,
                x_m: x0,
                v_m_per_s: 0.0,
            }))
        } else {
            Engine::Plain(osc)
        };
        ReferenceStepper {
            engine,
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
            let f0 = self.load.force_n(self.k as f64 * self.dt_s);
            let f1 = self.load.force_n((self.k + 1) as f64 * self.dt_s);
            match &mut self.engine {
                Engine::Plain(osc) => {
                    osc.step(f0, f1);
                }
                Engine::Augmented(mass) => mass.step(f0, f1),
            }
            self.k += 1;
        }
        match &self.engine {
            Engine::Plain(osc) => osc.displacement_m(),
            Engine::Augmented(mass) => mass.x_m,
        }
    }

    /// Restarts the reference from a measured state at programme step `m` (after an
    /// operator hold the rig resumes from where it was held, not where the reference
    /// would be). The element exerts `element_force_n` there when it is known (the force
    /// the actuator applies once the rig is back on the element's law: moving, the
    /// element's relaxing branch is loaded); otherwise it starts relaxed, as after a hold.
    /// A model with material effects always restarts relaxed.
    pub fn resync(&mut self, x_m: f64, v_m_per_s: f64, element_force_n: Option<f64>, m: u64) {
        match (&mut self.engine, element_force_n) {
            (Engine::Plain(osc), Some(f)) if f.is_finite() => {
                osc.set_state_with_element_force(x_m, v_m_per_s, f)
            }
            (Engine::Plain(osc), _) => osc.set_state(x_m, v_m_per_s),
            (Engine::Augmented(mass), _) => mass.set_state(x_m, v_m_per_s),
        }
        self.k = m;
    }
}

/// Where the comparison with the reference stands around operator holds: it pauses at
/// the hold (the rig restrains the specimen, the programme waits) and restarts from the
/// measured state once the rig is wholly back on the element's law, i.e. after the resume
/// blend (the servo's first period after a resume still applies the hold's force, and a
/// blend mixes the two for `resume_blend_ms`: a reference released at once would not
/// match a specimen still partly held).
#[derive(Debug, Clone)]
pub struct OperatorPause {
    /// Running periods after a resume before the rig is wholly on the law.
    handover_periods: u64,
    paused: bool,
    /// Running periods seen since the resume.
    resumed_for: u64,
}

/// What to do with one rig record ([`OperatorPause::push`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PauseStep {
    /// Compare it with the reference.
    Compare,
    /// The first record of an operator hold: the segment compared before it is complete.
    HoldBegins,
    /// Held, or still handing back to the law: not compared.
    Paused,
    /// The rig is wholly back on the law: restart the reference from this record's state
    /// and compare from here.
    Restart,
}

impl OperatorPause {
    /// `resume_blend_s` as configured (the simulated rig); 0 for an external rig, whose
    /// own handover is unknown here and whose velocity is not recorded (it restarts at
    /// rest where the rig held it).
    pub fn new(resume_blend_s: f64, dt_s: f64) -> OperatorPause {
        OperatorPause {
            handover_periods: (resume_blend_s.max(dt_s) / dt_s).round().max(1.0) as u64,
            paused: false,
            resumed_for: 0,
        }
    }

    /// An external rig's: restarts on its first running record after a hold.
    pub fn immediate() -> OperatorPause {
        OperatorPause {
            handover_periods: 0,
            paused: false,
            resumed_for: 0,
        }
    }

    /// Feeds the rig state of the next record.
    pub fn push(&mut self, state: u32) -> PauseStep {
        use crate::ipc::messages::rig_state;
        if state == rig_state::OPERATOR_HOLD {
            let begins = !self.paused;
            self.paused = true;
            self.resumed_for = 0;
            return if begins {
                PauseStep::HoldBegins
            } else {
                PauseStep::Paused
            };
        }
        if !self.paused {
            return PauseStep::Compare;
        }
        if state != rig_state::RUNNING {
            return PauseStep::Paused;
        }
        if self.resumed_for < self.handover_periods {
            self.resumed_for += 1;
            return PauseStep::Paused;
        }
        self.paused = false;
        PauseStep::Restart
    }

    /// Whether the comparison is paused.
    pub fn paused(&self) -> bool {
        self.paused
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ipc::messages::rig_state::{HOLD, OPERATOR_HOLD, RUNNING};

    /// The augmented engine (the emulator's stepper coupled to the mass by leapfrog) on a
    /// model whose only effect changes nothing agrees with the plain element's RK4
    /// oscillator: the default passage's displacement to within 1e-4 of its range.
    #[test]
    fn the_augmented_reference_agrees_with_the_plain_one_on_a_neutral_effect() {
        use crate::model::effects::{DriftClock, Effect};
        let plain_cfg = crate::hil::config::default_hil_config().unwrap();
        let mut cfg = plain_cfg.clone();
        cfg.augmented.effects.push(Effect::SpecimenDrift {
            clock: DriftClock::TestOrder,
            rate_per_unit: 0.0,
            rate_standard_error: 0.0,
            clock_position: 0.0,
        });
        let n = (3.0 * cfg.loop_.rate_hz) as usize;
        let plain = reference_displacement_m(&plain_cfg, n);
        let augmented_stepper = ReferenceStepper::new(&cfg, n as f64 * cfg.loop_.dt_s());
        assert!(matches!(augmented_stepper.engine, Engine::Augmented(_)));
        let augmented: Vec<f64> = augmented_stepper.take(n + 1).collect();
        let (lo, hi) = plain
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        let worst = plain
            .iter()
            .zip(&augmented)
            .map(|(p, a)| (p - a).abs())
            .fold(0.0, f64::max);
        assert!(hi - lo > 1e-4, "the passage moves the specimen");
        assert!(
            worst < 1e-4 * (hi - lo),
            "worst {worst} of range {}",
            hi - lo
        );
    }

    fn steps(mut pause: OperatorPause, states: &[u32]) -> Vec<PauseStep> {
        states.iter().map(|&s| pause.push(s)).collect()
    }

    #[test]
    fn the_comparison_restarts_only_once_the_resume_blend_is_over() {
        use PauseStep::*;
        // 3 periods of blend at dt = 1: the 4th running record is the first on the law.
        let got = steps(
            OperatorPause::new(3.0, 1.0),
            &[
                RUNNING,
                OPERATOR_HOLD,
                OPERATOR_HOLD,
                RUNNING,
                RUNNING,
                RUNNING,
                RUNNING,
                RUNNING,
            ],
        );
        assert_eq!(
            got,
            [Compare, HoldBegins, Paused, Paused, Paused, Paused, Restart, Compare]
        );
        // No blend: the servo's first period after the resume still holds.
        let got = steps(
            OperatorPause::new(0.0, 1.0),
            &[OPERATOR_HOLD, RUNNING, RUNNING],
        );
        assert_eq!(got, [HoldBegins, Paused, Restart]);
        // A hold again during the handover starts over; an external rig restarts at once.
        let got = steps(
            OperatorPause::new(2.0, 1.0),
            &[
                OPERATOR_HOLD,
                RUNNING,
                OPERATOR_HOLD,
                RUNNING,
                RUNNING,
                RUNNING,
            ],
        );
        assert_eq!(got, [HoldBegins, Paused, Paused, Paused, Paused, Restart]);
        let got = steps(OperatorPause::immediate(), &[OPERATOR_HOLD, RUNNING, HOLD]);
        assert_eq!(got, [HoldBegins, Restart, Compare]);
    }
}
