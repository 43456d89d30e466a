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

/// The calling thread's timer slack, ns (`PR_GET_TIMERSLACK`): how much the kernel may
/// delay a normal-priority thread's timer expiry to batch wake-ups (50 us by default).
/// SCHED_FIFO/RR threads get no slack whatever this says.
pub fn timer_slack_ns() -> u64 {
    // SAFETY: PR_GET_TIMERSLACK takes no pointers and only reads the calling thread.
    let slack = unsafe { libc::prctl(libc::PR_GET_TIMERSLACK, 0, 0, 0, 0) };
    slack.max(0) as u64
}

/// Sets the calling thread's timer slack (`PR_SET_TIMERSLACK`); 0 is refused because
/// the kernel reads it as "reset to the default".
pub fn set_timer_slack_ns(slack_ns: u64) -> Result<(), String> {
    if slack_ns == 0 {
        return Err("timer slack 0 means \"default\" to the kernel: use 1 ns".to_string());
    }
    // SAFETY: PR_SET_TIMERSLACK takes a value, no pointers; it affects this thread only.
    let rc = unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, slack_ns as libc::c_ulong, 0, 0, 0) };
    if rc != 0 {
        return Err(format!(
            "timer slack {slack_ns} ns refused ({})",
            std::io::Error::last_os_error()
        ));
    }
    Ok(())
}

/// Whether the calling thread runs under a real-time policy (SCHED_FIFO or SCHED_RR).
pub fn thread_is_realtime() -> bool {
    // SAFETY: pid 0 is the calling thread; no pointers.
    let policy = unsafe { libc::sched_getscheduler(0) };
    policy == libc::SCHED_FIFO || policy == libc::SCHED_RR
}
