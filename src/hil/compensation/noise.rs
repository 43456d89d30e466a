//! The displacement sensor's noise, read online from the measured displacements, and the
//! scale it puts on the passivity guard's energy thresholds. Owns only the estimate; the
//! guard applies the scale.
//!
//! Why: the guard's observer integrates the work of the element's force less the measured
//! force on the measured displacement above the load band. A sensor's noise is not motion,
//! but the rig's prediction and the actuator turn it into force, and a residual phase error
//! at the band's top (50 us at 300 Hz) makes that work positive on average: a mean power
//! of about `K * error * var(velocity noise in the band)`, so the energy the observer reads
//! from noise alone grows with the noise's variance. With the default thresholds (onset
//! 0.5 mJ, full 5 mJ, tuned at the shipped rig's 0.1 um) a sensor of 0.5 um kept the guard
//! damping for the whole run (in-process, `lag-delay` 600 + 150 us, 2026-11-28: 5.9 s, up
//! to 5.6 kN s/m at 0.5 um, 20.8 kN s/m at 0.7 um), and at 0.7-1 um that damping, delayed
//! by the actuator, made the loop ring and the ring's reading moved the lead out of the
//! stable range: `loop-unstable` from every guess for 500 + 500 and 600 + 150 us, which
//! ran clean with the guard off. The thresholds therefore scale with the noise's variance
//! beyond `REFERENCE_NOISE_M` (`SensorNoise::energy_scale`).
//!
//! The estimate: the third difference of consecutive displacements, `z[n] - 3 z[n-1] + 3
//! z[n-2] - z[n-3]`, has variance `20 sigma^2` for white noise and is nearly blind to
//! motion (at the specimen's resonance on the element, 155 Hz at 4096 Hz, it passes 1.4 %
//! of the amplitude; a 2 Hz load, nothing). Its mean square per block of `BLOCK` samples,
//! the second least over the last `BLOCKS` blocks, corrected for that choice's bias
//! (before the first whole block, the block so far): a loop that starts to ring raises
//! the blocks after the quiet ones, which the second least does not follow, so the
//! estimate is one of the two quietest stretches of the last half second. Bridged or
//! missing samples are skipped (the
//! difference needs four consecutive measurements).
//!
//! Must not: allocate, lock, log, read a clock or do I/O (runs per rig sample in the
//! controller's loop); the same sample stream gives the same estimate bit for bit.

/// Samples per block (62 ms at 4096 Hz).
const BLOCK: u32 = 256;
/// Before the first whole block, the block so far stands from this many differences on (8
/// ms at 4096 Hz; its mean square within about 25 %): a sensor of 2 um drove the guard's
/// observer past its full energy in 30 ms.
const FIRST_READING: u32 = 32;
/// Blocks the estimate is taken over (0.5 s at 4096 Hz).
const BLOCKS: usize = 8;
/// The second least of `BLOCKS` blocks' mean squares, over the mean square itself, for
/// white noise (Monte Carlo, 200 draws: 0.884 Gaussian, 0.903 uniform); the estimate
/// divides by it.
const SECOND_LEAST_BIAS: f64 = 0.89;
/// The noise the guard's default thresholds were chosen at and hold for (the shipped
/// rig's sensor is 0.1 um; up to 0.3 um the thresholds kept the guard off the noise in
/// the runs above), m.
pub const REFERENCE_NOISE_M: f64 = 0.25e-6;

/// The online estimate (`SensorNoise::update`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorNoise {
    /// The last three consecutive displacements, newest first, and how many are valid.
    history: [f64; 3],
    valid: u32,
    /// The block being filled: the sum of squared third differences and their count.
    sum: f64,
    count: u32,
    /// The last `BLOCKS` blocks' noise variances (`mean square / 20`), m^2; NaN before.
    blocks: [f64; BLOCKS],
    next: usize,
    /// The current estimate's variance, m^2 (NaN before the first block).
    variance: f64,
}

impl Default for SensorNoise {
    fn default() -> Self {
        SensorNoise::new()
    }
}

impl SensorNoise {
    pub fn new() -> SensorNoise {
        SensorNoise {
            history: [0.0; 3],
            valid: 0,
            sum: 0.0,
            count: 0,
            blocks: [f64::NAN; BLOCKS],
            next: 0,
            variance: f64::NAN,
        }
    }

    /// One measured displacement; `consecutive` when it follows the previous one with no
    /// sample between (not bridged, not after a gap).
    #[inline]
    pub fn update(&mut self, z_m: f64, consecutive: bool) {
        if !z_m.is_finite() {
            // Never differenced, never kept: the next three samples start afresh.
            self.valid = 0;
            return;
        }
        if !consecutive {
            self.valid = 0;
        }
        if self.valid >= 3 {
            let [z1, z2, z3] = self.history;
            let d3 = z_m - 3.0 * z1 + 3.0 * z2 - z3;
            self.sum += d3 * d3;
            self.count += 1;
            if self.count >= BLOCK {
                self.blocks[self.next] = self.sum / (20.0 * self.count as f64);
                self.next = (self.next + 1) % BLOCKS;
                self.sum = 0.0;
                self.count = 0;
                let (mut least, mut second) = (f64::INFINITY, f64::INFINITY);
                for &v in self.blocks.iter().filter(|v| v.is_finite()) {
                    if v < least {
                        second = least;
                        least = v;
                    } else if v < second {
                        second = v;
                    }
                }
                self.variance = if second.is_finite() {
                    second / SECOND_LEAST_BIAS
                } else {
                    least
                };
            } else if self.count >= FIRST_READING && self.blocks[0].is_nan() {
                // Before the first whole block: the block so far.
                self.variance = self.sum / (20.0 * self.count as f64);
            }
        }
        self.history = [z_m, self.history[0], self.history[1]];
        self.valid = (self.valid + 1).min(3);
    }

    /// The sensor's noise (standard deviation), m; None before the first block.
    pub fn sigma_m(&self) -> Option<f64> {
        self.variance.is_finite().then(|| self.variance.sqrt())
    }

    /// The factor on the guard's energy thresholds: the noise's variance over the
    /// reference's, never below 1; infinite before the first reading (`FIRST_READING`
    /// differences, 8 ms), when the energy the observer reads cannot be told from the
    /// noise's (a sensor of 3 um drove it past the full energy within those 8 ms).
    #[inline]
    pub fn energy_scale(&self) -> f64 {
        if self.variance.is_finite() {
            (self.variance / (REFERENCE_NOISE_M * REFERENCE_NOISE_M)).max(1.0)
        } else {
            f64::INFINITY
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic uniform noise of standard deviation `sigma` (xorshift).
    fn noise(seed: &mut u64, sigma: f64) -> f64 {
        *seed ^= *seed << 13;
        *seed ^= *seed >> 7;
        *seed ^= *seed << 17;
        let u = (*seed >> 11) as f64 / (1u64 << 53) as f64;
        (u - 0.5) * sigma * 12f64.sqrt()
    }

    /// White noise on a 2 Hz load of 0.2 mm: the estimate is the noise within 10 %, and the
    /// scale is its variance over the reference's (1 below it).
    #[test]
    fn the_estimate_reads_the_noise_under_a_moving_load() {
        let dt = 1.0 / 4096.0;
        for &sigma in &[0.1e-6, 0.5e-6, 1.0e-6] {
            let mut n = SensorNoise::new();
            let mut seed = 0x1234_5678_9abc_def1u64;
            assert_eq!(n.sigma_m(), None);
            assert_eq!(n.energy_scale(), f64::INFINITY);
            for i in 0..4096 {
                let t = i as f64 * dt;
                let z = 0.4e-3 + 0.2e-3 * (2.0 * std::f64::consts::PI * 2.0 * t).sin();
                n.update(z + noise(&mut seed, sigma), true);
            }
            let s = n.sigma_m().unwrap();
            assert!((s / sigma - 1.0).abs() < 0.1, "{sigma}: {s}");
            let expected = (s * s / (REFERENCE_NOISE_M * REFERENCE_NOISE_M)).max(1.0);
            assert!((n.energy_scale() / expected - 1.0).abs() < 1e-12);
            if sigma < REFERENCE_NOISE_M {
                assert_eq!(n.energy_scale(), 1.0);
            } else {
                assert!(n.energy_scale() > 3.0, "{}", n.energy_scale());
            }
        }
    }

    /// A ring that grows after a quiet start does not raise the estimate: the second least
    /// block over the last half second is a quiet one. A ring of 30 um at 155 Hz throughout
    /// raises it by less than a fifth at 0.1 um of noise.
    #[test]
    fn a_growing_ring_does_not_raise_the_estimate() {
        let dt = 1.0 / 4096.0;
        let sigma = 0.1e-6;
        let mut quiet_then_ring = SensorNoise::new();
        let mut ringing = SensorNoise::new();
        let mut seed = 7u64;
        for i in 0..2048 {
            let t = i as f64 * dt;
            let ring = (2.0 * std::f64::consts::PI * 155.0 * t).sin();
            let e = noise(&mut seed, sigma);
            let growing = if i < 512 {
                0.0
            } else {
                1e-6 * (20.0 * (t - 0.125)).exp()
            };
            quiet_then_ring.update(growing * ring + e, true);
            ringing.update(30e-6 * ring + e, true);
        }
        // Two quiet blocks of eight: the second least is the larger of the two, over the
        // bias correction for eight: a little high, never the ring's.
        let q = quiet_then_ring.sigma_m().unwrap();
        assert!((q / sigma - 1.0).abs() < 0.2, "{q}");
        let r = ringing.sigma_m().unwrap();
        assert!(r < 1.2 * sigma, "{r}");
    }

    /// A sample that is not finite (a sensor's fault) is skipped, not differenced, not
    /// kept: the estimate stays finite and at the noise.
    #[test]
    fn a_sample_that_is_not_finite_is_skipped() {
        let mut n = SensorNoise::new();
        let mut seed = 5u64;
        for i in 0..2048 {
            let z = if i % 300 == 17 {
                f64::NAN
            } else {
                noise(&mut seed, 0.2e-6)
            };
            n.update(z, true);
        }
        let s = n.sigma_m().unwrap();
        assert!((s / 0.2e-6 - 1.0).abs() < 0.1, "{s}");
    }

    /// Samples that are not consecutive are not differenced: steps of 50 um every 100
    /// samples, each after a gap, leave the estimate at the noise; the same steps without
    /// the gaps (differenced across) raise it far beyond.
    #[test]
    fn a_gap_is_not_differenced() {
        let run = |gaps: bool| {
            let mut n = SensorNoise::new();
            let mut seed = 99u64;
            for i in 0..2048 {
                let offset = if (i / 100) % 2 == 0 { 0.0 } else { 50e-6 };
                n.update(offset + noise(&mut seed, 0.2e-6), !(gaps && i % 100 == 0));
            }
            n.sigma_m().unwrap()
        };
        let s = run(true);
        assert!((s / 0.2e-6 - 1.0).abs() < 0.1, "{s}");
        assert!(run(false) > 10.0 * 0.2e-6, "{}", run(false));
    }
}
