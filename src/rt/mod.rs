//! Real-time primitives shared by the loop processes and the latency benchmark:
//! an injectable monotonic clock, the absolute-deadline fixed-step scheduler, the turn of
//! a loop that a standby thread on another CPU may run, and the optional real-time
//! process setup (mlockall, SCHED_FIFO, CPU affinity), and the pool the threads marked
//! real-time take their unavoidable small allocations from (`pool`).
//!
//! Must not: allocate, lock or log inside `Scheduler::wait_next`, `CycleTurn` or `Clock`
//! calls.
//! `setup` runs once before a loop starts and returns its warnings as data.

pub mod clock;
pub mod pool;
pub mod scheduler;
pub mod setup;
pub mod turn;

pub use clock::{Clock, MockClock, MonotonicClock};
pub use scheduler::{wait_until, CycleStats, Scheduler, WaitMode};
pub use setup::{apply_rt_setup, RtSetup};
pub use turn::CycleTurn;
