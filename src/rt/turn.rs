//! The turn of a fixed-step loop that two threads on two CPUs may run, a primary and a
//! standby: whoever claims a cycle first runs it, the other skips it. A CPU held off by
//! the hypervisor or an interrupt storm then costs the loop no deadline while the other
//! CPU runs (on this 2-core VM nine in ten late wake-ups hit one CPU alone).
//!
//! Must not: allocate, lock, block or read a clock (callers pass the time). The claim is
//! the only synchronisation of the state the two threads share: a cycle's body runs
//! between a successful `try_claim` (acquire) and `release` (release), by one thread.

use std::sync::atomic::{AtomicU64, Ordering};

use super::CycleStats;

/// The turn's state once the loop has ended: odd (busy), so no claim can succeed.
const FINISHED: u64 = u64::MAX;

/// Which cycle of a deadline grid `start + k * period` runs next, and whether a thread
/// is running one now.
#[derive(Debug)]
pub struct CycleTurn {
    period_ns: u64,
    start_ns: u64,
    /// `(next cycle index << 1) | busy`, or `FINISHED`.
    state: AtomicU64,
}

impl CycleTurn {
    /// A turn whose first cycle (index 0) is due at `start_ns`.
    pub fn new(period_ns: u64, start_ns: u64) -> CycleTurn {
        assert!(period_ns > 0, "period must be positive");
        CycleTurn {
            period_ns,
            start_ns,
            state: AtomicU64::new(0),
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

    /// The cycle a thread should wait for: the next one, or while another thread runs a
    /// cycle, the one after it; `None` once the loop has ended.
    #[inline]
    pub fn next_idx(&self) -> Option<u64> {
        let state = self.state.load(Ordering::Acquire);
        (state != FINISHED).then_some((state >> 1) + (state & 1))
    }

    /// Claims cycle `idx` at `now_ns` (after its deadline): the cycle's statistics, late
    /// relative to its deadline, the deadlines that passed meanwhile skipped (as
    /// `Scheduler::wait_next` counts them); `None` when another thread runs it or ran it,
    /// or the loop has ended.
    #[inline]
    pub fn try_claim(&self, idx: u64, now_ns: u64) -> Option<CycleStats> {
        let free = idx << 1;
        self.state
            .compare_exchange(free, free | 1, Ordering::Acquire, Ordering::Relaxed)
            .ok()?;
        let deadline = self.deadline_ns(idx);
        let late = now_ns.saturating_sub(deadline);
        Some(CycleStats {
            cycle_idx: idx,
            deadline_ns: deadline,
            woke_ns: now_ns,
            wake_late_ns: late,
            missed_deadlines: late / self.period_ns,
        })
    }

    /// Ends the claimed cycle `stats`: the next is the first deadline after it that was
    /// not skipped.
    #[inline]
    pub fn release(&self, stats: &CycleStats) {
        let next = stats.cycle_idx + 1 + stats.missed_deadlines;
        self.state.store(next << 1, Ordering::Release);
    }

    /// Ends the loop from the claimed cycle: no thread claims another.
    #[inline]
    pub fn finish(&self) {
        self.state.store(FINISHED, Ordering::Release);
    }

    pub fn finished(&self) -> bool {
        self.state.load(Ordering::Acquire) == FINISHED
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_thread_claims_each_cycle_the_other_skips_it() {
        let turn = CycleTurn::new(250, 1_000);
        assert_eq!(turn.next_idx(), Some(0));
        let stats = turn.try_claim(0, 1_010).expect("cycle 0 is free");
        assert_eq!((stats.cycle_idx, stats.wake_late_ns), (0, 10));
        // While it runs, the other thread can have neither it nor the next.
        assert_eq!(turn.try_claim(0, 1_100), None);
        assert_eq!(turn.try_claim(1, 1_260), None);
        assert_eq!(
            turn.next_idx(),
            Some(1),
            "the other thread waits for the next cycle"
        );
        turn.release(&stats);
        assert_eq!(turn.try_claim(0, 1_270), None, "cycle 0 is done");
        assert_eq!(turn.next_idx(), Some(1));
        assert!(turn.try_claim(1, 1_260).is_some());
    }

    #[test]
    fn a_late_claim_skips_the_deadlines_that_passed() {
        let turn = CycleTurn::new(250, 1_000);
        // The primary was held off; the standby claims cycle 0 at 1_000 + 3.2 periods.
        let stats = turn.try_claim(0, 1_800).unwrap();
        assert_eq!((stats.missed_deadlines, stats.wake_late_ns), (3, 800));
        turn.release(&stats);
        assert_eq!(turn.next_idx(), Some(4));
        // The primary wakes for cycle 0 (or any skipped one): gone.
        for idx in 0..4 {
            assert_eq!(turn.try_claim(idx, 1_900), None);
        }
        let next = turn.try_claim(4, 2_000).unwrap();
        assert_eq!((next.cycle_idx, next.missed_deadlines), (4, 0));
    }

    #[test]
    fn after_finish_no_cycle_is_claimed() {
        let turn = CycleTurn::new(250, 0);
        assert!(turn.try_claim(0, 0).is_some());
        turn.finish();
        assert!(turn.finished());
        assert_eq!(turn.next_idx(), None);
        for idx in [0, 1, 2, u64::MAX >> 1] {
            assert_eq!(turn.try_claim(idx, 10_000), None);
        }
    }

    #[test]
    fn two_threads_run_every_cycle_exactly_once() {
        // Two threads race for 20 000 cycles on a clock that is never late: each cycle
        // index is run by exactly one of them (whatever the interleaving).
        let turn = CycleTurn::new(1, 0);
        let runs: Vec<AtomicU64> = (0..20_000).map(|_| AtomicU64::new(0)).collect();
        let work = |_: usize| loop {
            let Some(idx) = turn.next_idx() else {
                return;
            };
            if let Some(stats) = turn.try_claim(idx, idx) {
                runs[idx as usize].fetch_add(1, Ordering::Relaxed);
                if idx + 1 == runs.len() as u64 {
                    turn.finish();
                } else {
                    turn.release(&stats);
                }
            }
        };
        std::thread::scope(|s| {
            s.spawn(|| work(1));
            work(0);
        });
        assert!(runs.iter().all(|r| r.load(Ordering::Relaxed) == 1));
    }
}
