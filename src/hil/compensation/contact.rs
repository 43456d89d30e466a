//! `ContactGain`: the actuator's gain read from the rig's own command before force control.
//! Must not: allocate, lock, log, read a clock or do I/O (runs per setpoint).

/// The gain read at the first contact: the first samples in force control give the
/// actuator's force per command at once, before the specimen sinks far under a gain error
/// (a perturbed electrodynamic shaker renders 0.73-0.86 of its command; the estimator
/// needs 0.13 s of warm-up, in which the specimen sank 160 um). Over the `CONTACT_LEN`
/// samples after the initial lead's periods (plus one) of the first stretch in force control:
/// when the element's force is a load (over 1 kN) and the ratio of the actuator's own to
/// the element's force stayed within `CONTACT_SPREAD` of its mean (no transient under way),
/// the gain jumps to that mean, once per run; the estimator refines it from there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct ContactGain {
    /// Samples skipped first: the actuator's response to the first command is still on
    /// its way (the initial lead's periods, plus one).
    skip: u32,
    samples: u32,
    /// The newest `CONTACT_LEN` ratios, a ring.
    recent: [f64; CONTACT_LEN],
    /// The last sample of a rig of ABI 4 (its sequence, measured-to-commanded ratio and
    /// commanded force; NaN none yet), and how many such samples came.
    rest_last: (u64, f64, f64),
    rest_samples: u32,
    /// The rig does not report its commanded force (a NaN came): no read before force
    /// control, nothing to wait for.
    unreported: bool,
    done: bool,
}

const CONTACT_LEN: usize = 3;
/// Give up after this many samples (about 10 ms at 4096 Hz).
const CONTACT_MAX_SAMPLES: u32 = 40;
/// The read before force control takes at most this many samples of a rig that reports
/// its commanded force; the controller sends no command until it is over
/// (`Compensator::ready_to_command`), so every sample it reads carries the rig's own
/// command. Without the wait the first command raced the rig's second sample: answered
/// within the rig's first period, it left one sample under the rig's servo, no pair to
/// read, and the read came from two samples of the transient that followed (a perturbed
/// `shaker-150kn`: 0.921 instead of 0.861 in 2 of 6 `fastemu hil` runs, 1.39 % error
/// instead of 0.40 %).
pub(super) const CONTACT_COMMANDED_SAMPLES: u32 = 4;
const CONTACT_MIN_FORCE_N: f64 = 1e3;
const CONTACT_SPREAD: f64 = 0.02;
/// Two consecutive measured-to-commanded ratios this close (relative) are a settled
/// actuator: its gain.
const CONTACT_REST_SPREAD: f64 = 0.005;

impl ContactGain {
    pub(super) fn new(initial_lead_s: f64, dt_s: f64) -> ContactGain {
        ContactGain {
            skip: (initial_lead_s / dt_s).ceil() as u32 + 1,
            samples: 0,
            recent: [f64::NAN; CONTACT_LEN],
            rest_last: (u64::MAX, f64::NAN, f64::NAN),
            rest_samples: 0,
            unreported: false,
            done: false,
        }
    }

    /// One of the first `CONTACT_COMMANDED_SAMPLES` samples of a rig that reports its
    /// commanded force (rig ABI 4), before the controller's first command: the measured
    /// over the commanded force is the actuator's own gain when the actuator has settled
    /// on a steady command, as under the rig's own servo before the run. Returns the gain
    /// to take, once: the mean of the ratios of the first two consecutive samples
    /// (sequence `k` and `k + 1`) whose commands and whose ratios each agree within
    /// `CONTACT_REST_SPREAD`, if in 0.5-2 and the command is a load (over 1 kN). A rig
    /// that does not report it (NaN), or whose samples do not agree, leaves the read to
    /// `observe` in force control.
    #[inline]
    pub(super) fn observe_commanded(
        &mut self,
        sample_seq: u64,
        measured_force_n: f64,
        commanded_force_n: f64,
    ) -> Option<f64> {
        if self.done || self.unreported || self.rest_samples >= CONTACT_COMMANDED_SAMPLES {
            return None;
        }
        if !commanded_force_n.is_finite() {
            self.unreported = true;
            return None;
        }
        // Counted even without a measured force, so that the wait is bounded.
        self.rest_samples += 1;
        if !measured_force_n.is_finite() {
            self.rest_last = (u64::MAX, f64::NAN, f64::NAN);
            return None;
        }
        let ratio = if commanded_force_n.abs() > CONTACT_MIN_FORCE_N {
            measured_force_n / commanded_force_n
        } else {
            f64::NAN
        };
        let (last_seq, last_ratio, last_command) =
            std::mem::replace(&mut self.rest_last, (sample_seq, ratio, commanded_force_n));
        let mean = 0.5 * (ratio + last_ratio);
        let steady_command = (commanded_force_n - last_command).abs()
            <= CONTACT_REST_SPREAD * commanded_force_n.abs();
        // NaN (no previous ratio, or no load) fails the comparisons.
        if last_seq.checked_add(1) == Some(sample_seq)
            && steady_command
            && (ratio - last_ratio).abs() <= CONTACT_REST_SPREAD * mean.abs()
            && (0.5..=2.0).contains(&mean)
        {
            self.done = true;
            return Some(mean);
        }
        None
    }

    /// Whether the read before force control is over: taken, given up
    /// (`CONTACT_COMMANDED_SAMPLES`), or impossible (the rig does not report its command).
    #[inline]
    pub(super) fn commanded_read_over(&self) -> bool {
        self.done || self.unreported || self.rest_samples >= CONTACT_COMMANDED_SAMPLES
    }

    /// One sample (`ratio`: the actuator's own force per element force); returns the gain
    /// to take, once: the mean of the first `CONTACT_LEN` consecutive ratios after the
    /// skip that agree within `CONTACT_SPREAD` (the actuator has settled on the command).
    #[inline]
    pub(super) fn observe(&mut self, ratio: f64, element_force_n: f64) -> Option<f64> {
        if self.done {
            return None;
        }
        self.samples += 1;
        if self.samples <= self.skip {
            return None;
        }
        if !(ratio.is_finite() && element_force_n.abs() > CONTACT_MIN_FORCE_N)
            || self.samples > self.skip + CONTACT_MAX_SAMPLES
        {
            self.done = true;
            return None;
        }
        self.recent[self.samples as usize % CONTACT_LEN] = ratio;
        let (mut lo, mut hi, mut sum) = (f64::INFINITY, f64::NEG_INFINITY, 0.0);
        for &r in &self.recent {
            lo = lo.min(r);
            hi = hi.max(r);
            sum += r;
        }
        let mean = sum / CONTACT_LEN as f64;
        // NaN (the ring not yet full) fails every comparison.
        let steady = hi - lo <= CONTACT_SPREAD * mean.abs();
        if steady && (0.5..=2.0).contains(&mean) {
            self.done = true;
            return Some(mean);
        }
        None
    }
}
