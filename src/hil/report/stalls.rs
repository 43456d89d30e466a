//! Stalls of the loop as the specimen felt them: episodes in which the rig's local law
//! stayed unchanged for at least `STALL_MIN_PERIODS` (the emulator, the controller or the
//! transport stalled; the rig rode through on the last law), each with its length, the
//! largest resonant transient in it and the 100 ms after, and the process that stalled
//! (from the emulator's cycle jumps, the controller's command gaps, the rig's catch-ups).

use serde::Serialize;

/// A law unchanged for this many periods is a stall (normal: 0-2).
pub const STALL_MIN_PERIODS: u64 = 4;
/// The transient of a stall is looked for until this long after it, s.
const TRANSIENT_WINDOW_S: f64 = 0.1;
/// Episodes listed in the report (the largest transients); all are counted.
const LISTED: usize = 20;

/// One stall.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct StallReport {
    pub at_s: f64,
    pub length_ms: f64,
    pub transient_m: f64,
    /// The largest >100 Hz residual in the 100 ms before the stall, m: what was there
    /// already (an oscillating loop's residual is not the stall's transient).
    pub before_m: f64,
    /// `emulator`, `controller`, `bench_rig`, or `unknown` (transport, or no record).
    pub source: String,
}

#[derive(Debug, Clone, Serialize, Default, PartialEq)]
pub struct Stalls {
    /// Stalls ridden through: the law came back before any hold.
    pub count: u64,
    /// Stalls the run did not ride through: still going when the law gave way to a hold
    /// (a fault's, usually the stall's own, or the programme's end), or when the records
    /// end. Not in `count`,
    /// `longest_ms` or `episodes`; the fault's hold is in the report's safety part.
    pub ended_in_hold: u64,
    pub longest_ms: f64,
    pub largest_transient_m: f64,
    /// The largest rise of an episode's transient over the residual before it, m (a stall
    /// in a limit cycle shows the cycle's amplitude as its transient, and no rise).
    pub largest_rise_m: f64,
    /// The episodes with the largest transients (at most 20).
    pub episodes: Vec<StallReport>,
}

/// A process's own gap: (start s, length s).
pub type Gap = (f64, f64);

#[derive(Debug, Clone)]
struct Episode {
    start_step: u64,
    end_step: u64,
    max_age: u64,
    transient: f64,
    before: f64,
    open: bool,
}

/// Finds stall episodes in the rig's records and measures their transients.
#[derive(Debug, Clone)]
pub struct StallTracker {
    dt_s: f64,
    window_periods: u64,
    episodes: Vec<Episode>,
    count: u64,
    longest_periods: u64,
    largest: f64,
    largest_rise: f64,
    finished: Vec<StallReport>,
    /// The last window's >100 Hz residual: (step, |residual|).
    recent: std::collections::VecDeque<(u64, f64)>,
}

impl StallTracker {
    pub fn new(rate_hz: f64) -> StallTracker {
        StallTracker {
            dt_s: 1.0 / rate_hz,
            window_periods: (TRANSIENT_WINDOW_S * rate_hz) as u64,
            episodes: Vec::new(),
            count: 0,
            longest_periods: 0,
            largest: 0.0,
            largest_rise: 0.0,
            finished: Vec::new(),
            recent: std::collections::VecDeque::new(),
        }
    }

    /// The rig's law age at `step` (before any hold).
    pub fn push_law_age(&mut self, step: u64, law_age_periods: u64) {
        let stalled = law_age_periods >= STALL_MIN_PERIODS;
        match self.episodes.last_mut() {
            Some(e) if e.open && stalled => {
                e.max_age = e.max_age.max(law_age_periods);
                e.end_step = step;
            }
            Some(e) if e.open => e.open = false,
            _ if stalled => {
                self.count += 1;
                let start_step = step.saturating_sub(law_age_periods);
                let from = start_step.saturating_sub(self.window_periods);
                let before = self
                    .recent
                    .iter()
                    .filter(|(s, _)| (from..start_step).contains(s))
                    .fold(0.0f64, |m, (_, x)| m.max(*x));
                self.episodes.push(Episode {
                    start_step,
                    end_step: step,
                    max_age: law_age_periods,
                    transient: 0.0,
                    before,
                    open: true,
                });
            }
            _ => {}
        }
    }

    /// The >100 Hz residual at `step` (arrives a little later than the law age).
    pub fn push_high_passed(&mut self, step: u64, hp: f64, sources: &[(&str, &[Gap])]) {
        let window = self.window_periods;
        for e in &mut self.episodes {
            if step >= e.start_step && step <= e.end_step + window {
                e.transient = e.transient.max(hp.abs());
            } else if step < e.start_step && step + window >= e.start_step {
                e.before = e.before.max(hp.abs());
            }
        }
        self.recent.push_back((step, hp.abs()));
        while self.recent.front().is_some_and(|(s, _)| s + window < step) {
            self.recent.pop_front();
        }
        // Episodes whose window has passed are final.
        let dt = self.dt_s;
        let mut i = 0;
        while i < self.episodes.len() {
            let e = &self.episodes[i];
            if !e.open && step > e.end_step + window {
                let e = self.episodes.remove(i);
                self.close(e, dt, sources);
            } else {
                i += 1;
            }
        }
    }

    fn close(&mut self, e: Episode, dt: f64, sources: &[(&str, &[Gap])]) {
        self.longest_periods = self.longest_periods.max(e.max_age);
        self.largest = self.largest.max(e.transient);
        self.largest_rise = self.largest_rise.max(e.transient - e.before);
        let (t0, t1) = (e.start_step as f64 * dt, e.end_step as f64 * dt);
        // The source whose own gap overlaps the episode most.
        let mut best = ("unknown", 0.0);
        for (name, gaps) in sources {
            for &(g0, len) in gaps.iter() {
                let overlap = (t1.min(g0 + len) - t0.max(g0 - 2.0 * dt)).max(0.0);
                if overlap > best.1 {
                    best = (name, overlap);
                }
            }
        }
        let report = StallReport {
            at_s: t0,
            length_ms: e.max_age as f64 * dt * 1e3,
            transient_m: e.transient,
            before_m: e.before,
            source: best.0.to_string(),
        };
        self.finished.push(report);
        if self.finished.len() > 4 * LISTED {
            self.trim();
        }
    }

    fn trim(&mut self) {
        self.finished
            .sort_by(|a, b| b.transient_m.total_cmp(&a.transient_m));
        self.finished.truncate(LISTED);
    }

    pub fn finish(mut self, sources: &[(&str, &[Gap])]) -> Stalls {
        let dt = self.dt_s;
        let mut ended_in_hold = 0;
        for e in std::mem::take(&mut self.episodes) {
            if e.open {
                // The law ages end at the hold (or the records do): never ridden through.
                self.count -= 1;
                ended_in_hold += 1;
            } else {
                self.close(e, dt, sources);
            }
        }
        self.trim();
        self.finished.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
        Stalls {
            count: self.count,
            ended_in_hold,
            longest_ms: self.longest_periods as f64 * dt * 1e3,
            largest_transient_m: self.largest,
            largest_rise_m: self.largest_rise,
            episodes: self.finished,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 8000 steps at 4096 Hz with one stall of 20 periods from step 4096, the >100 Hz
    /// residual `hp(step)`.
    fn one_stall(sources: &[(&str, &[Gap])], hp: impl Fn(u64) -> f64) -> Stalls {
        let mut t = StallTracker::new(4096.0);
        let start = 4096;
        for step in 0..8000u64 {
            let age = if (start..start + 20).contains(&step) {
                step - start
            } else {
                1
            };
            t.push_law_age(step, age);
            t.push_high_passed(step, hp(step), sources);
        }
        t.finish(sources)
    }

    #[test]
    fn an_episode_is_counted_measured_and_attributed() {
        let emulator_gaps: Vec<Gap> = vec![(1.0, 0.005)];
        let sources: Vec<(&str, &[Gap])> = vec![("emulator", &emulator_gaps)];
        let s = one_stall(&sources, |step| if step == 4096 + 30 { 7e-6 } else { 1e-7 });
        assert_eq!(s.count, 1);
        assert!((s.longest_ms - 19.0 / 4.096).abs() < 1e-9, "{s:?}");
        assert_eq!(s.largest_transient_m, 7e-6);
        assert_eq!(s.episodes[0].before_m, 1e-7);
        assert!((s.largest_rise_m - (7e-6 - 1e-7)).abs() < 1e-15, "{s:?}");
        assert_eq!(s.episodes[0].source, "emulator");
        assert_eq!(s.ended_in_hold, 0);
    }

    /// A stall inside a limit cycle: its "transient" is the cycle's amplitude, which was
    /// there before it; the rise says the stall added nothing.
    #[test]
    fn a_stall_in_an_oscillation_is_not_its_transient() {
        // 84 um at 155 Hz, the lead-100-us-short limit cycle's size.
        let s = one_stall(&[], |step| {
            84e-6 * (2.0 * std::f64::consts::PI * 155.0 * step as f64 / 4096.0).sin()
        });
        assert_eq!(s.count, 1);
        assert!(s.largest_transient_m > 80e-6, "{s:?}");
        assert!(s.episodes[0].before_m > 80e-6, "{s:?}");
        assert!(s.largest_rise_m.abs() < 1e-6, "{s:?}");
    }

    /// A stall still going when the law ages end (the hold came during it: a kill's
    /// gap that tripped `setpoints-stale`) is not counted as ridden through, nor in the
    /// longest; the one before it is.
    #[test]
    fn a_stall_the_hold_ended_is_not_ridden_through() {
        let mut t = StallTracker::new(4096.0);
        let sources: Vec<(&str, &[Gap])> = Vec::new();
        for step in 0..6000u64 {
            let age = match step {
                1000..=1019 => step - 1000,
                5800.. => step - 5800,
                _ => 1,
            };
            t.push_law_age(step, age);
            t.push_high_passed(step, 1e-7, &sources);
        }
        let s = t.finish(&sources);
        assert_eq!((s.count, s.ended_in_hold), (1, 1), "{s:?}");
        assert!((s.longest_ms - 19.0 / 4.096).abs() < 1e-9, "{s:?}");
        assert_eq!(s.episodes.len(), 1);
    }
}
