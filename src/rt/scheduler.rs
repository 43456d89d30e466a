//! Absolute-deadline fixed-step scheduling.
//!
//! Deadlines lie on a fixed grid `start + k * period`; a late wake-up never shifts the
//! grid. If a wake-up is later than a whole period, the skipped deadlines are counted as
//! misses and the cycle index jumps over them, so the loop's notion of time stays on the
//! grid (deterministic handling: the skipped cycles are reported, not silently absorbed).
//! Waiting is a coarse sleep to `deadline - spin` followed by a busy spin to the deadline
//! (`WaitMode::SleepSpin`), or sleep only (`WaitMode::Sleep`).

use super::clock::Clock;

/// How the scheduler waits for a deadline.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WaitMode {
    /// `clock_nanosleep` to the deadline.
    Sleep,
    /// Sleep to `deadline - spin_ns`, then spin on the clock.
    SleepSpin { spin_ns: u64 },
}

/// Per-cycle scheduling statistics, reported as data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CycleStats {
    /// Index of this cycle on the deadline grid (jumps over missed cycles).
    pub cycle_idx: u64,
    /// The deadline this cycle was scheduled for, ns on the loop's clock.
    pub deadline_ns: u64,
    /// When the loop actually woke, ns.
    pub woke_ns: u64,
    /// `woke - deadline`, ns (0 if on time or early).
    pub wake_late_ns: u64,
    /// Deadlines skipped since the previous cycle because the loop was late by more
    /// than a period (0 normally).
    pub missed_deadlines: u64,
}

/// Waits until `deadline_ns` on `clock` as `mode` says (returns at once if it has passed).
#[inline]
pub fn wait_until<C: Clock>(clock: &C, deadline_ns: u64, mode: WaitMode) {
    match mode {
        WaitMode::Sleep => clock.sleep_until_ns(deadline_ns),
        WaitMode::SleepSpin { spin_ns } => {
            if deadline_ns > spin_ns {
                let coarse = deadline_ns - spin_ns;
                if clock.now_ns() < coarse {
                    clock.sleep_until_ns(coarse);
                }
            }
            while clock.now_ns() < deadline_ns {
                std::hint::spin_loop();
            }
        }
    }
}

/// Fixed-step scheduler on an absolute deadline grid.
#[derive(Debug, Clone)]
pub struct Scheduler {
    period_ns: u64,
    start_ns: u64,
    next_idx: u64,
    mode: WaitMode,
}

impl Scheduler {
    /// A scheduler whose first deadline is `start_ns`.
    pub fn new(period_ns: u64, start_ns: u64, mode: WaitMode) -> Scheduler {
        assert!(period_ns > 0, "period must be positive");
        Scheduler {
            period_ns,
            start_ns,
            next_idx: 0,
            mode,
        }
    }

    pub fn period_ns(&self) -> u64 {
        self.period_ns
    }

    /// Deadline of cycle `idx`, ns.
    #[inline]
    pub fn deadline_ns(&self, idx: u64) -> u64 {
        self.start_ns + idx * self.period_ns
    }

    /// Waits for the next deadline and returns the cycle's statistics.
    #[inline]
    pub fn wait_next<C: Clock>(&mut self, clock: &C) -> CycleStats {
        let idx = self.next_idx;
        let deadline = self.deadline_ns(idx);
        wait_until(clock, deadline, self.mode);
        let woke = clock.now_ns();
        let late = woke.saturating_sub(deadline);
        // Deadlines that passed entirely while we were late are skipped, not replayed.
        let skipped = late / self.period_ns;
        self.next_idx = idx + 1 + skipped;
        CycleStats {
            cycle_idx: idx,
            deadline_ns: deadline,
            woke_ns: woke,
            wake_late_ns: late,
            missed_deadlines: skipped,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rt::clock::MockClock;

    #[test]
    fn on_time_cycles_follow_the_grid() {
        let clock = MockClock::new(1_000);
        let mut s = Scheduler::new(250, 2_000, WaitMode::Sleep);
        for k in 0..5 {
            let st = s.wait_next(&clock);
            assert_eq!(st.cycle_idx, k);
            assert_eq!(st.deadline_ns, 2_000 + 250 * k);
            assert_eq!(st.wake_late_ns, 0);
            assert_eq!(st.missed_deadlines, 0);
        }
    }

    #[test]
    fn lateness_beyond_a_period_skips_and_counts_deadlines() {
        let clock = MockClock::new(0);
        let mut s = Scheduler::new(100, 100, WaitMode::Sleep);
        clock.set_wake_lateness_ns(250);
        let st = s.wait_next(&clock);
        assert_eq!(
            (st.cycle_idx, st.wake_late_ns, st.missed_deadlines),
            (0, 250, 2)
        );
        clock.set_wake_lateness_ns(0);
        let st = s.wait_next(&clock);
        // Deadlines 1 and 2 were skipped; the grid is unchanged.
        assert_eq!((st.cycle_idx, st.deadline_ns), (3, 400));
    }
}
