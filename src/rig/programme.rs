//! The load programme as the rig runs it: programme time that advances while running and
//! pauses on a hold (so a resume continues without a jump), and an unload that ramps the
//! external force to zero. Pure: no I/O, no clock, no allocation per period.

use super::load::LoadProgramme;

#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    Running,
    /// Paused at the programme's value when the hold began.
    Held,
    /// Ramping from the held value to zero at `rate_n_per_s`.
    Unloading {
        rate_n_per_s: f64,
    },
}

/// External load on the specimen, period by period.
#[derive(Debug, Clone)]
pub struct ProgrammeRunner {
    load: LoadProgramme,
    dt_s: f64,
    /// Programme time at the start of the current period, s.
    programme_time_s: f64,
    /// Periods run since the start (the programme's own clock: `programme_time = k dt`).
    programme_step: u64,
    state: State,
    /// External force at the start of the current period, N.
    value_n: f64,
}

impl ProgrammeRunner {
    pub fn new(load: LoadProgramme, dt_s: f64) -> ProgrammeRunner {
        let value_n = load.force_n(0.0);
        ProgrammeRunner {
            load,
            dt_s,
            programme_time_s: 0.0,
            programme_step: 0,
            state: State::Running,
            value_n,
        }
    }

    pub fn load(&self) -> &LoadProgramme {
        &self.load
    }

    /// External force now (start of the current period), N.
    pub fn force_n(&self) -> f64 {
        self.value_n
    }

    /// Programme time now, s (paused while held).
    pub fn programme_time_s(&self) -> f64 {
        self.programme_time_s
    }

    pub fn running(&self) -> bool {
        self.state == State::Running
    }

    /// Whether an unload reached zero.
    pub fn unloaded(&self) -> bool {
        matches!(self.state, State::Unloading { .. }) && self.value_n == 0.0
    }

    /// Pauses the programme at its current value.
    pub fn hold(&mut self) {
        if self.state == State::Running {
            self.state = State::Held;
        }
    }

    /// Continues a held programme from where it paused.
    pub fn resume(&mut self) {
        if self.state == State::Held {
            self.state = State::Running;
            self.value_n = self.load.force_n(self.programme_time_s);
        }
    }

    /// Ramps the external force to zero at `rate_n_per_s`.
    pub fn unload(&mut self, rate_n_per_s: f64) {
        if !matches!(self.state, State::Unloading { .. }) {
            self.state = State::Unloading { rate_n_per_s };
        }
    }

    /// Advances one period; returns the external force at its end, N.
    #[inline]
    pub fn advance(&mut self) -> f64 {
        match self.state {
            State::Running => {
                self.programme_step += 1;
                self.programme_time_s = self.programme_step as f64 * self.dt_s;
                self.value_n = self.load.force_n(self.programme_time_s);
            }
            State::Held => {}
            State::Unloading { rate_n_per_s } => {
                let step = rate_n_per_s * self.dt_s;
                self.value_n = if self.value_n.abs() <= step {
                    0.0
                } else {
                    self.value_n - step * self.value_n.signum()
                };
            }
        }
        self.value_n
    }
}
