//! Monotonic time as data: the loop reads time only through a `Clock`, so tests can drive
//! it with a `MockClock` and the model never sees a clock at all.

use std::cell::Cell;

/// A monotonic clock in nanoseconds with absolute-deadline sleep.
pub trait Clock {
    fn now_ns(&self) -> u64;
    /// Sleeps until `deadline_ns` (absolute, on this clock) or returns at once if past.
    fn sleep_until_ns(&self, deadline_ns: u64);
}

/// `CLOCK_MONOTONIC`; the same time base in every process on the machine, so a
/// timestamp taken in one process can be compared with `now_ns` in another.
#[derive(Debug, Clone, Copy, Default)]
pub struct MonotonicClock;

/// Current `CLOCK_MONOTONIC` time, ns.
#[inline]
pub fn monotonic_now_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

impl Clock for MonotonicClock {
    #[inline]
    fn now_ns(&self) -> u64 {
        monotonic_now_ns()
    }

    fn sleep_until_ns(&self, deadline_ns: u64) {
        let ts = libc::timespec {
            tv_sec: (deadline_ns / 1_000_000_000) as libc::time_t,
            tv_nsec: (deadline_ns % 1_000_000_000) as libc::c_long,
        };
        loop {
            // SAFETY: valid timespec; a null remainder is allowed with TIMER_ABSTIME.
            let rc = unsafe {
                libc::clock_nanosleep(
                    libc::CLOCK_MONOTONIC,
                    libc::TIMER_ABSTIME,
                    &ts,
                    std::ptr::null_mut(),
                )
            };
            if rc != libc::EINTR {
                break;
            }
        }
    }
}

/// A clock that only moves when told to (tests): `sleep_until_ns` jumps to the deadline
/// plus a programmable lateness.
#[derive(Debug, Default)]
pub struct MockClock {
    now_ns: Cell<u64>,
    late_ns: Cell<u64>,
}

impl MockClock {
    pub fn new(start_ns: u64) -> MockClock {
        MockClock {
            now_ns: Cell::new(start_ns),
            late_ns: Cell::new(0),
        }
    }
    pub fn advance_ns(&self, by_ns: u64) {
        self.now_ns.set(self.now_ns.get() + by_ns);
    }
    /// Every following sleep wakes this much after its deadline.
    pub fn set_wake_lateness_ns(&self, late_ns: u64) {
        self.late_ns.set(late_ns);
    }
}

impl Clock for MockClock {
    fn now_ns(&self) -> u64 {
        self.now_ns.get()
    }
    fn sleep_until_ns(&self, deadline_ns: u64) {
        let target = deadline_ns + self.late_ns.get();
        if target > self.now_ns.get() {
            self.now_ns.set(target);
        }
    }
}
