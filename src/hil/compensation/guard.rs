//! `PassivityGuard`: the passivity observer above the load band and the damper it drives,
//! with the safe start and a stall's burst. Must not: allocate, lock, log, read a clock or
//! do I/O (runs per setpoint).

use super::*;

/// The guard's state after a sample.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GuardState {
    /// Damping added now, N s/m.
    pub damping_ns_per_m: f64,
    /// Energy generated above the corner (the observer), J.
    pub generated_j: f64,
    /// Of it, the stall's burst the guard excuses (`STALL_BURST_S`), J, and the stall
    /// bursts excused so far.
    pub excused_j: f64,
    pub stall_bursts: u32,
    /// The safe start: its damping until the lead is learned.
    pub armed: bool,
    /// The energy the guard damps from now, J: `guard_onset_energy_j` times the sensor
    /// noise's scale (`noise::SensorNoise`); infinite before the noise is read.
    pub onset_j: f64,
}

/// Running totals of the guard's activity (for the report).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GuardActivity {
    /// Samples with damping added.
    pub active_samples: u64,
    /// Energy the added damping dissipated (its force times the high-passed velocity), J.
    pub dissipated_j: f64,
    /// Largest damping added, N s/m.
    pub max_damping_ns_per_m: f64,
    /// Largest energy the observer saw generated above the corner, J.
    pub max_generated_j: f64,
    /// Gaps in the setpoints after which the guard excused the stall's burst
    /// (`STALL_BURST_S`), and the largest burst it excused, J.
    pub stall_bursts: u32,
    pub max_stall_burst_j: f64,
    /// The largest factor the sensor's noise put on the guard's thresholds (1: none).
    pub max_energy_scale: f64,
}

/// The guard's damping, N s/m, by the levels it may take: the full damping
/// (`guard_max_damping_ns_per_m`) and its halves down to a sixteenth.
pub const DAMPING_LEVELS: usize = 5;

/// One actuator the guard's damping is judged in front of (`DampingByLead`): the longest
/// lead, s, up to which the linearised loop is stable with each damping level
/// (`DAMPING_LEVELS`) and without damping, when the actuator's effective delay is the lead.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DampingEdges {
    pub damped_s: [f64; DAMPING_LEVELS],
    pub undamped_s: f64,
}

/// The most damping the guard may add at the lead in effect (`check::guard_damping_by_lead`).
/// The guard damps the velocity predicted over the lead, and the prediction's gain at the
/// band's top grows with the lead: in front of an actuator as slow as the lead, damping
/// that holds a short lead's loop makes a long lead's generate energy. `lag-delay` 720 +
/// 359 us (a random draw, undeclared, from 252 us): the ring read at the start took the
/// lead to 1106 us, inside the loop's stable leads without damping (1000-1300 us); the
/// ring the start had grown was still dying, the guard answered it with 18-40 kN s/m, with
/// which the loop is stable only below 1060 (20 kN s/m) or 820 us (40), and
/// `loop-unstable` tripped 30 ms later. Judged in front of representative actuators
/// whose effective delay is the lead: a pure delay (the most exposed, no lag's roll-off)
/// and lags of a quarter and a half of it (`cap`). Where none is stable even undamped (a
/// lead beyond about 1.5 ms at the shipped specimen, a servo-hydraulic loop's) the
/// lag-and-delay picture says nothing and the full damping stays: a lag of three
/// quarters as a fourth representative capped the undeclared servo-hydraulic presets'
/// damping at their 1.7-2.5 ms leads, where their velocity feedback takes damping well,
/// and 10 of their 117 undeclared runs (nominal and `perturb = 0.3` seeds 1-12, three
/// guesses) tripped that had not (2026-11-28, thirtieth session).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DampingByLead {
    pub representatives: [DampingEdges; DAMPING_REPRESENTATIVES],
}

/// The representative actuators' lag, as a share of the effective delay (the rest is
/// transport delay), most exposed first.
pub const DAMPING_REPRESENTATIVE_LAGS: [f64; DAMPING_REPRESENTATIVES] = [0.0, 0.25, 0.5];
pub const DAMPING_REPRESENTATIVES: usize = 3;

impl DampingByLead {
    /// No cap: the full damping at every lead (a run without adaptation of the lead, the
    /// plan's fixed lead, or a unit test's guard).
    pub const NONE: DampingByLead = DampingByLead {
        representatives: [DampingEdges {
            damped_s: [f64::INFINITY; DAMPING_LEVELS],
            undamped_s: f64::INFINITY,
        }; DAMPING_REPRESENTATIVES],
    };

    /// The most damping at `lead_s`, N s/m, of `full`. Below the most exposed
    /// representative's undamped edge, its edges; between two representatives' undamped
    /// edges, the edges interpolated to the actuator whose undamped edge is the lead (the
    /// most exposed the lead can be stable for: edges rise with the lag's share); beyond
    /// the last, the full damping.
    #[inline]
    pub fn cap(&self, full: f64, lead_s: f64) -> f64 {
        let r = &self.representatives;
        let level = |edges: &dyn Fn(usize) -> f64| {
            let mut level = full;
            for k in 0..DAMPING_LEVELS {
                if lead_s <= edges(k) {
                    return level;
                }
                level *= 0.5;
            }
            0.0
        };
        if lead_s <= r[0].undamped_s {
            return level(&|k| r[0].damped_s[k]);
        }
        for i in 1..DAMPING_REPRESENTATIVES {
            let (a, b) = (&r[i - 1], &r[i]);
            if lead_s <= b.undamped_s {
                if !b.undamped_s.is_finite() {
                    return level(&|k| b.damped_s[k]);
                }
                let t = (lead_s - a.undamped_s) / (b.undamped_s - a.undamped_s);
                return level(&|k| {
                    let (ea, eb) = (a.damped_s[k], b.damped_s[k]);
                    if eb.is_finite() {
                        ea + t * (eb - ea)
                    } else {
                        eb
                    }
                });
            }
        }
        full
    }
}

/// Time-domain passivity controller above the load band.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PassivityGuard {
    observer: PassivityObserver,
    onset_energy_j: f64,
    full_energy_j: f64,
    /// The factor on both thresholds for the sensor's noise (`noise::SensorNoise`), >= 1.
    energy_scale: f64,
    max_damping: f64,
    /// The most damping by the lead in effect (`DampingByLead`).
    by_lead: DampingByLead,
    /// The safe start's damping (`safe_start_damping`).
    start_damping: f64,
    release: f64,
    damping: f64,
    last_z_hp_m: f64,
    dt_s: f64,
    /// The safe start (`disarm`).
    armed: bool,
    /// The safe start's ring check (`SAFE_START_RING_*`): the largest band displacement
    /// in the block being filled and in the last whole one, m; samples in the block; whole
    /// blocks in a row each beyond `SAFE_START_RING_GROWTH` times the one before.
    block_peak_m: f64,
    last_block_peak_m: f64,
    block_samples: u32,
    growing_blocks: u32,
    /// The stall's burst (`STALL_BURST_S`): the window in samples, samples of it left,
    /// samples since the last window began and the least between two (`STALL_BURST_SPACING_S`),
    /// and the energy excused, J; the observer's per-sample decay.
    burst_window: u32,
    burst_samples_left: u32,
    since_burst: u32,
    burst_spacing: u32,
    excused_j: f64,
    decay: f64,
    pub activity: GuardActivity,
}

/// The guard's observer's memory, s.
const GUARD_MEMORY_S: f64 = 0.1;

/// After a gap in the setpoints longer than the compensator bridges (`MAX_BRIDGED_GAP`: the
/// emulator stalled), the energy the observer reads in this long (16 ms, 64 samples at 4096
/// Hz, two and a half periods of the specimen's resonance on the element) is the stall's
/// burst, excused up to `guard_full_energy_j`: that much is never answered, in the window
/// or after it. After the window the excused energy follows the observer's down, never
/// up, so that energy generated beyond the burst counts from the lowest level the burst
/// fell to (as if the observer had restarted there). While the emulator stalls the rig
/// renders the last law, a linearisation that drifts from the element (100-200 N over 9 ms
/// in an axle's passage, a few um); the fresh law corrects it at once and the step rings
/// the specimen's resonance; and the observer, restarted by the gap on a specimen the load
/// moves, reads the restart's own transient too. In-process, default run, one emulator
/// stall of 33-37 periods at 2.33-2.4 s (2026-11-28): 0.8-4.0 mJ read within 2-8 ms of the
/// gap, then gone (the loop is stable), answered with 2.9-31 kN s/m released over a second
/// of axle passages: 0.040-0.076 % displacement error against 0.038-0.046 % with the guard
/// off; with the burst excused (and so not damped) it read 1.2-5.1 mJ. A loop that is
/// unstable keeps generating after the window, and the guard answers it then; the damping
/// it had before the gap keeps being released as before. The emulator's monitor, which
/// sees every sample, is not excused. (Tried and not kept: restarting the observer on the
/// ramp through its first two samples instead of on a constant. Those samples carry the
/// stale law's error dying away (-197 and -104 N), and the ramp through them read 12 mJ in
/// `fastemu hil`.)
pub(super) const STALL_BURST_S: f64 = 0.016;
/// At most one stall's burst is excused in this long (0.25 s, the default
/// `guard_release_ms`, counted in the guard's samples): however often the emulator stalls,
/// the guard is blind for at most 16 ms, and to at most `guard_full_energy_j`, in 250 ms.
pub(super) const STALL_BURST_SPACING_S: f64 = 0.25;

/// The safe start's full damping can itself be what makes the loop ring. It acts on the
/// displacement predicted over the lead, whose prediction amplifies the band's top (twice
/// at 400 Hz over 742 us, order 2), so an actuator a little slower than the lead turns it
/// into energy there: `lag-delay` 630 + 63 us (`perturb = 0.3` seed 41 of 500 + 80 us)
/// started at its capped 742 us is stable without the damping and unstable with any
/// above about 5 kN s/m (`hil --check`), and a 400 Hz oscillation grew from the first 20
/// ms by 1.1-2 times per 16 ms while both observers read the loop as absorbing (at
/// the band's top a fraction of a sample's skew between force and displacement flips the
/// sign of their work), until the specimen left its range at 0.27 s (2026-11-28). A
/// damping that answers energy it generated would never do that: under the safe start,
/// an oscillation in the guard's band growing by `SAFE_START_RING_GROWTH` per block of
/// `SAFE_START_RING_BLOCK` samples (16 ms at 4096 Hz) for `SAFE_START_RING_BLOCKS` blocks
/// in a row, beyond `SAFE_START_RING_FLOOR_M` (four times the sensor's noise), while the
/// observer reads no energy generated beyond its onset, ends the safe start: from then on
/// the damping follows the energy generated, as after any safe start. In-process,
/// `perturb = 0.3` seeds 1-20, 2026-11-28: `lag-delay` 500 + 80 us from a guess of 1160 us
/// (capped at 742 us), seeds 11, 15, 17 and 41 tripped `displacement-out-of-range` at
/// 0.27-0.31 s (now 0.05-0.07 %, no fault) and seed 3 ran at 0.21 % (now 0.05 %); 300 +
/// 100 us from 800 us, seeds 11, 15 and 17 ran at 0.9-3.2 % with the damping on for 2-4.6
/// s (now 0.05-0.06 %). The block peaks of seed 41's ring: 0.35, 0.52, 1.05, 1.83, 2.03,
/// 3.17 um (the sensor's noise alone about 0.35 um); with 1.2 per block and 3 um the check
/// caught it at 0.14 s, 25-32 um, beyond `max_transient_m` (`fastemu hil`: not clean);
/// with 1.1 and 1.5 um at 0.078 s (clean, 0.06 %). (A lead too short rings at the
/// specimen's resonance, where the observer reads the energy generated and the ring's
/// own reading moves the lead: `follow_oscillation`.)
const SAFE_START_RING_BLOCK: u32 = 64;
const SAFE_START_RING_BLOCKS: u32 = 3;
const SAFE_START_RING_GROWTH: f64 = 1.1;
const SAFE_START_RING_FLOOR_M: f64 = 1.5e-6;

/// The safe start's damping: as `check::starting_compensation` chose it, never above the
/// guard's largest.
pub(super) fn safe_start_damping(cfg: &CompensationConfig) -> f64 {
    cfg.safe_start_damping_ns_per_m
        .min(cfg.guard_max_damping_ns_per_m)
}

impl PassivityGuard {
    pub fn new(cfg: &CompensationConfig, dt_s: f64) -> PassivityGuard {
        PassivityGuard {
            observer: PassivityObserver::new(
                (cfg.guard_band_hz, cfg.guard_band_top_hz),
                GUARD_MEMORY_S,
                dt_s,
            ),
            onset_energy_j: cfg.guard_onset_energy_j,
            full_energy_j: cfg.guard_full_energy_j,
            energy_scale: 1.0,
            max_damping: cfg.guard_max_damping_ns_per_m,
            by_lead: cfg.guard_damping_by_lead,
            start_damping: safe_start_damping(cfg),
            release: (-dt_s / cfg.guard_release_s).exp(),
            damping: 0.0,
            last_z_hp_m: 0.0,
            dt_s,
            armed: cfg.adapt && cfg.adapt_lead && cfg.passivity_guard,
            block_peak_m: 0.0,
            last_block_peak_m: f64::INFINITY,
            block_samples: 0,
            growing_blocks: 0,
            burst_window: (STALL_BURST_S / dt_s).round() as u32,
            burst_samples_left: 0,
            since_burst: u32::MAX,
            burst_spacing: (STALL_BURST_SPACING_S / dt_s).round() as u32,
            excused_j: 0.0,
            decay: (-dt_s / GUARD_MEMORY_S).exp(),
            activity: GuardActivity {
                max_energy_scale: 1.0,
                ..GuardActivity::default()
            },
        }
    }

    /// The safe start's ring check (`SAFE_START_RING_BLOCK`): true when its damping rings.
    #[inline]
    fn damping_rings(&mut self, s: &crate::hil::passivity::EnergyState) -> bool {
        self.block_peak_m = self.block_peak_m.max(s.oscillation_m.abs());
        self.block_samples += 1;
        if self.block_samples < SAFE_START_RING_BLOCK {
            return false;
        }
        if self.block_peak_m >= SAFE_START_RING_GROWTH * self.last_block_peak_m {
            self.growing_blocks += 1;
        } else {
            self.growing_blocks = 0;
        }
        self.last_block_peak_m = self.block_peak_m;
        self.block_peak_m = 0.0;
        self.block_samples = 0;
        self.growing_blocks >= SAFE_START_RING_BLOCKS
            && self.last_block_peak_m >= SAFE_START_RING_FLOOR_M * self.energy_scale.sqrt()
            && s.generated_high_j <= self.onset_j()
    }

    /// The energy the guard starts to damp from, J: `guard_onset_energy_j` times the
    /// sensor noise's scale.
    #[inline]
    pub fn onset_j(&self) -> f64 {
        self.onset_energy_j * self.energy_scale
    }

    /// The energy of full damping, J: `guard_full_energy_j` times the noise's scale.
    #[inline]
    fn full_j(&self) -> f64 {
        self.full_energy_j * self.energy_scale
    }

    /// Scales both thresholds for the sensor's noise (`noise::SensorNoise::energy_scale`;
    /// infinite: not read yet, no answer to energy).
    #[inline]
    pub fn set_energy_scale(&mut self, scale: f64) {
        self.energy_scale = scale.max(1.0);
        if self.energy_scale.is_finite() {
            let a = &mut self.activity;
            a.max_energy_scale = a.max_energy_scale.max(self.energy_scale);
        }
    }

    /// Ends the safe start: from the next sample on, the damping follows the energy
    /// generated. The start's damping was a precaution, not an answer to energy seen, so
    /// it goes at once (its slow release cost the resonance band's fidelity for 2-3 s:
    /// a faithful band of 176 Hz instead of 194 on the default run).
    pub fn disarm(&mut self) {
        if self.armed {
            self.armed = false;
            self.damping = 0.0;
        }
    }

    pub fn armed(&self) -> bool {
        self.armed
    }

    pub fn restart(&mut self) {
        self.observer.restart();
        self.block_peak_m = 0.0;
        self.last_block_peak_m = f64::INFINITY;
        self.block_samples = 0;
        self.growing_blocks = 0;
        self.burst_samples_left = 0;
        self.excused_j = 0.0;
    }

    /// Restarts after a gap in the setpoints (a stall of the emulator): the energy read in
    /// the next `STALL_BURST_S` is the stall's burst, unless the last window began less
    /// than `STALL_BURST_SPACING_S` ago.
    pub fn restart_after_stall(&mut self) {
        self.restart();
        if self.since_burst >= self.burst_spacing {
            self.burst_samples_left = self.burst_window;
            self.since_burst = 0;
            self.activity.stall_bursts += 1;
        }
    }

    /// The energy generated beyond the stall's burst (`STALL_BURST_S`), J.
    #[inline]
    fn beyond_stall_burst(&mut self, generated_j: f64) -> f64 {
        self.since_burst = self.since_burst.saturating_add(1);
        if self.burst_samples_left > 0 {
            self.burst_samples_left -= 1;
            self.excused_j = self.excused_j.max(generated_j).min(self.full_j());
            let a = &mut self.activity;
            a.max_stall_burst_j = a.max_stall_burst_j.max(self.excused_j);
        } else {
            self.excused_j = (self.excused_j * self.decay).min(generated_j.max(0.0));
        }
        generated_j - self.excused_j
    }

    /// One consecutive rig sample in force control, with the lead in effect.
    #[inline]
    pub fn update(
        &mut self,
        z_m: f64,
        element_force_n: f64,
        measured_force_n: f64,
        lead_s: f64,
    ) -> GuardState {
        let s = self.observer.update(z_m, element_force_n, measured_force_n);
        if self.armed && self.damping_rings(&s) {
            self.disarm();
        }
        // Damping in proportion to the energy generated (none while the loop absorbs it),
        // at once when it rises, released slowly when it falls.
        let generated_j = self.beyond_stall_burst(s.generated_high_j);
        // (None before the sensor's noise is read: `energy_scale` infinite.)
        let onset = self.onset_j();
        let most = self.by_lead.cap(self.max_damping, lead_s);
        let answer = if onset.is_finite() {
            let span = (self.full_j() - onset).max(1e-12);
            most * ((generated_j - onset) / span).clamp(0.0, 1.0)
        } else {
            0.0
        };
        // Armed: at least the safe start's damping (judged at the starting lead), more as
        // energy is seen; released, never above what the lead in effect stays stable with.
        self.damping = if self.armed {
            self.start_damping
                .max(answer)
                .max(self.damping * self.release)
        } else {
            answer.max(self.damping * self.release).min(most)
        };
        if self.damping < 1.0 {
            self.damping = 0.0;
        }
        let v_hp = (s.oscillation_m - self.last_z_hp_m) / self.dt_s;
        self.last_z_hp_m = s.oscillation_m;
        let a = &mut self.activity;
        if self.damping > 0.0 {
            a.active_samples += 1;
            a.dissipated_j += self.damping * v_hp * v_hp * self.dt_s;
        }
        a.max_damping_ns_per_m = a.max_damping_ns_per_m.max(self.damping);
        a.max_generated_j = a.max_generated_j.max(s.generated_high_j);
        GuardState {
            damping_ns_per_m: self.damping,
            generated_j: s.generated_high_j,
            excused_j: self.excused_j,
            stall_bursts: self.activity.stall_bursts,
            armed: self.armed,
            onset_j: self.onset_j(),
        }
    }
}
