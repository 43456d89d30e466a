//! Wake-up jitter of the fixed-step `rt::Scheduler`: how late each absolute-deadline
//! wake-up is (`CycleStats::wake_late_ns`) at the loop's rates, sleeping only
//! (`WaitMode::Sleep`) versus sleeping to `deadline - spin` and spinning the rest
//! (`WaitMode::SleepSpin`). Runs on the calling thread, which the caller has pinned
//! and prioritised as asked.

use hdrhistogram::Histogram;

use crate::rt::{MonotonicClock, Scheduler, WaitMode};

/// One scheduler configuration under test.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct JitterConfig {
    pub rate_hz: u64,
    pub mode: WaitMode,
}

impl JitterConfig {
    /// The four configurations the report lists: 4096 Hz and 20 kHz, each sleeping and
    /// sleeping plus a final `spin_ns` spin.
    pub fn standard_set(spin_ns: u64) -> Vec<JitterConfig> {
        let mut configs = Vec::new();
        for rate_hz in [4096, 20_000] {
            configs.push(JitterConfig {
                rate_hz,
                mode: WaitMode::Sleep,
            });
            configs.push(JitterConfig {
                rate_hz,
                mode: WaitMode::SleepSpin { spin_ns },
            });
        }
        configs
    }

    /// Key in the JSON report and hlog tag, e.g. `4096hz_sleep_spin`.
    pub fn key(&self) -> String {
        let mode = match self.mode {
            WaitMode::Sleep => "sleep",
            WaitMode::SleepSpin { .. } => "sleep_spin",
        };
        format!("{}hz_{mode}", self.rate_hz)
    }

    pub fn period_ns(&self) -> u64 {
        1_000_000_000 / self.rate_hz
    }
}

/// Runs `n_cycles` cycles of `config` starting one period from now; records each
/// cycle's wake lateness into `wake_late_ns` and returns the deadlines skipped.
pub fn measure_wake_jitter(
    config: JitterConfig,
    n_cycles: u64,
    wake_late_ns: &mut Histogram<u64>,
) -> u64 {
    let clock = MonotonicClock;
    let period_ns = config.period_ns();
    let start_ns = crate::rt::clock::monotonic_now_ns() + period_ns;
    let mut scheduler = Scheduler::new(period_ns, start_ns, config.mode);
    let mut missed_deadlines = 0;
    let mut cycles = 0;
    while cycles < n_cycles {
        let stats = scheduler.wait_next(&clock);
        wake_late_ns.saturating_record(stats.wake_late_ns);
        missed_deadlines += stats.missed_deadlines;
        // Skipped deadlines count as cycles: the run lasts n_cycles periods of time.
        cycles += 1 + stats.missed_deadlines;
    }
    missed_deadlines
}
