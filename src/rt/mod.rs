//! Real-time primitives shared by the loop processes and the latency benchmark:
//! an injectable monotonic clock, the absolute-deadline fixed-step scheduler, and the
//! optional real-time process setup (mlockall, SCHED_FIFO, CPU affinity).
//!
//! Must not: allocate, lock or log inside `Scheduler::wait_next` or `Clock` calls.
//! `setup` runs once before a loop starts and returns its warnings as data.

pub mod clock;
pub mod scheduler;
pub mod setup;

pub use clock::{Clock, MockClock, MonotonicClock};
pub use scheduler::{CycleStats, Scheduler, WaitMode};
pub use setup::{apply_rt_setup, RtSetup};
