//! The actuator's phase delay at the frequency the loop oscillates at, from the ringing
//! itself: the safe start's way to a lead when the starting guess leaves the loop
//! unstable (at the specimen's resonance, or at a servo-hydraulic loop's 30-40 Hz). Owns only the band-passed regression; the compensator decides when to use it.
//!
//! Must not: allocate, lock, log, read a clock or do I/O (runs per rig sample in the
//! controller's loop); the same sample stream gives the same estimate bit for bit.

use super::estimator::{add_to_sums, solve_two};
use crate::hil::passivity::{HighPass2, LowPass2};

/// The estimate after a sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OscillationEstimate {
    /// How much later than the element's force the rendered force follows it at the
    /// oscillation's frequency, beyond the leads the window was rendered with, s: the
    /// lead must grow by this much to cancel the phase there.
    pub residual_s: f64,
    /// The lead in effect over the window, weighted as the fit weighs its samples (by the
    /// force's square: a ring that grew under one lead and decays under another reads as
    /// the first), s.
    pub window_lead_s: f64,
    /// The oscillation's frequency (the band-passed force's rate over its value), Hz.
    pub frequency_hz: f64,
    /// The window holds a memory's worth of samples since it was last cleared.
    pub window_full: bool,
    /// The share of the measured force's band power the fit explains (0-1): near 1 when
    /// one oscillation dominates the band, low for noise or several modes.
    pub fit: f64,
}

/// Exponentially weighted least squares on band-passed forces. In the band, the element's
/// force `F` is one oscillation (the loop ringing at its crossover) and the rendered force
/// is `F` at gain `g` and phase lag `phi`: `F_meas = g cos(phi) F - g sin(phi) / w dF/dt`.
/// Regressed on `F` and `dF/dt` (`a`, `b`), `phi = atan2(-b w, a)` with `w` from the
/// band power of the rate against that of the force, and the residual delay is `phi / w`:
/// exact at any phase (the load band's estimator linearises `F(t - d)` in `d`, which at
/// 155 Hz and 0.8 ms reads 27 % long). The rate is a central difference, so that `F`,
/// `dF/dt` and `F_meas` describe the same instant (a backward difference lags half a
/// sample: 7 degrees at 155 Hz). Both forces pass the same filters, so their phase cancels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OscillationDelay {
    hp_element: HighPass2,
    lp_element: LowPass2,
    hp_measured: HighPass2,
    lp_measured: LowPass2,
    forget: f64,
    dt_s: f64,
    /// The two previous band-passed element forces and the previous measured one.
    prev: (f64, f64, f64),
    primed: u32,
    /// Samples in the window since it was last cleared, and a memory's worth.
    window_samples: u32,
    memory_samples: u32,
    /// Weighted sums: xx, xd, dd, xy, dy, yy, weight, lead (weighted by xx), and xc (`c` the second
    /// difference).
    s: [f64; 9],
}

/// Samples to let the filters and the central difference settle after a restart.
const WARMUP: u32 = 8;

impl OscillationDelay {
    /// Band `(low, high)` Hz, memory `memory_s`, sample period `dt_s`.
    pub fn new(band_hz: (f64, f64), memory_s: f64, dt_s: f64) -> OscillationDelay {
        OscillationDelay {
            hp_element: HighPass2::high_pass(band_hz.0, dt_s),
            lp_element: LowPass2::low_pass(band_hz.1, dt_s),
            hp_measured: HighPass2::high_pass(band_hz.0, dt_s),
            lp_measured: LowPass2::low_pass(band_hz.1, dt_s),
            forget: (-dt_s / memory_s).exp(),
            dt_s,
            prev: (0.0, 0.0, 0.0),
            primed: 0,
            window_samples: 0,
            memory_samples: (memory_s / dt_s).ceil() as u32,
            s: [0.0; 9],
        }
    }

    /// Forgets the filters and the sums (a gap in the samples).
    pub fn restart(&mut self) {
        self.primed = 0;
        self.clear_window();
    }

    /// Forgets the sums, keeps the filters: the next estimates describe what comes now.
    pub fn clear_window(&mut self) {
        self.s = [0.0; 9];
        self.window_samples = 0;
    }

    /// One consecutive rig sample: the element's force, the actuator's own force (the
    /// measured force times the gain in effect) and the lead in effect; `None` until the
    /// regression is determined.
    #[inline]
    pub fn update(
        &mut self,
        element_force_n: f64,
        own_force_n: f64,
        lead_s: f64,
    ) -> Option<OscillationEstimate> {
        if !(element_force_n.is_finite() && own_force_n.is_finite() && lead_s.is_finite()) {
            self.restart();
            return None;
        }
        if self.primed == 0 {
            self.hp_element.reset(element_force_n);
            self.lp_element.reset(0.0);
            self.hp_measured.reset(own_force_n);
            self.lp_measured.reset(0.0);
        }
        let x = self.lp_element.step(self.hp_element.step(element_force_n));
        let y = self.lp_measured.step(self.hp_measured.step(own_force_n));
        let (x1, x2, y1) = self.prev;
        self.prev = (x, x1, y);
        if self.primed < WARMUP {
            self.primed += 1;
            return None;
        }
        // The previous sample's force, rate (central difference) and measured force.
        let d = (x - x2) / (2.0 * self.dt_s);
        let c = (x - 2.0 * x1 + x2) / (self.dt_s * self.dt_s);
        let (x, y) = (x1, y1);
        let l = self.forget;
        let s = &mut self.s;
        add_to_sums(s, l, x, d, y);
        s[7] = l * s[7] + x * x * lead_s;
        s[8] = l * s[8] + x * c;
        self.window_samples = self.window_samples.saturating_add(1);
        let (xx, xy, dy, yy) = (s[0], s[3], s[4], s[5]);
        let (a, b, _) = solve_two(s, 1e-9).filter(|_| yy > 0.0)?;
        // The frequency from the second difference, which is `-(2 sin(w dt / 2) / dt)^2`
        // times a sinusoid at every sample (exact whatever the window's phase; the rate's
        // power over the force's swings by a few % with it). The central difference's
        // gain is `sin(w dt) / (w dt)`: `-b w_d` with its own `w_d` is `g sin(phi)`.
        let ratio = (-s[8] / xx).max(0.0).sqrt() * 0.5 * self.dt_s;
        let w = 2.0 * ratio.min(1.0).asin() / self.dt_s;
        let w_d = (w * self.dt_s).sin() / self.dt_s;
        let phi = (-b * w_d).atan2(a);
        Some(OscillationEstimate {
            residual_s: phi / w,
            window_lead_s: s[7] / xx,
            frequency_hz: w / (2.0 * std::f64::consts::PI),
            window_full: self.window_samples >= self.memory_samples,
            fit: ((a * xy + b * dy) / yy).clamp(0.0, 1.0),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    const DT: f64 = 1.0 / 4096.0;

    /// An oscillation at `f_hz` growing at `growth_per_s`, rendered `delay_s` late at gain
    /// `gain`, with the lead `lead_s` in effect.
    fn ring(
        f_hz: f64,
        growth_per_s: f64,
        delay_s: f64,
        gain: f64,
        lead_s: f64,
    ) -> OscillationEstimate {
        let mut est = OscillationDelay::new((60.0, 400.0), 0.025, DT);
        let force = |t: f64| 20e3 + 3e3 * (growth_per_s * t).exp() * (2.0 * PI * f_hz * t).sin();
        let mut last = None;
        for k in 0..600 {
            let t = k as f64 * DT;
            // The rig rendered the element's force predicted over the lead, `delay_s` late.
            let own = gain * force(t + lead_s - delay_s);
            last = est.update(force(t), own, lead_s).or(last);
        }
        last.unwrap()
    }

    /// The residual is the delay at the ringing's frequency less the lead, at phases far
    /// beyond the linear range (0.8 ms at 155 Hz is 45 degrees, 2.5 ms at 120 Hz 108):
    /// exact for a steady oscillation; one growing by e in 50 ms (the monitor's bound
    /// reached from a slight ring in 0.1 s) biases it by its growth over its frequency.
    #[test]
    fn the_residual_is_the_phase_delay_at_the_ringing_frequency() {
        for (growth, tolerance) in [(0.0, 2e-6), (20.0, 0.03)] {
            for (f, delay, gain, lead) in [
                (155.0, 811e-6, 1.0, 0.0),
                (155.0, 811e-6, 0.8, 300e-6),
                (120.0, 2.5e-3, 1.1, 0.0),
                (200.0, 250e-6, 1.0, 400e-6),
            ] {
                let e = ring(f, growth, delay, gain, lead);
                let expected = delay - lead;
                let allowed = if growth == 0.0 {
                    tolerance
                } else {
                    tolerance * expected.abs()
                };
                assert!(
                    (e.residual_s - expected).abs() < allowed,
                    "{f} Hz growing {growth}/s, {delay} s late, lead {lead} s: residual {} us, expected {} us",
                    e.residual_s * 1e6,
                    expected * 1e6
                );
                assert!(
                    (e.frequency_hz / f - 1.0).abs() < 0.01,
                    "{}",
                    e.frequency_hz
                );
                assert!(e.fit > 0.99, "fit {}", e.fit);
                assert!((e.window_lead_s - lead).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn noise_alone_fits_nothing() {
        let mut est = OscillationDelay::new((60.0, 400.0), 0.025, DT);
        let mut state = 1u64;
        let mut noise = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 100.0
        };
        let mut last = None;
        for _ in 0..2000 {
            let (a, b) = (noise(), noise());
            last = est.update(20e3 + a, 20e3 + b, 0.0).or(last);
        }
        assert!(last.unwrap().fit < 0.1, "{:?}", last);
    }
}
