//! The simulated rig (hardware stand-in) and the offline reference it is judged against:
//! specimen mass with the rig's own damping, external load programme, force actuator
//! (transport delay, first-order lag, saturation), displacement sensor (noise,
//! quantisation, seeded PRNG). Physics here is pure (no I/O, no clock); `process` runs
//! it as the `bench_rig` process on its own fixed-step clock.

pub mod load;
pub mod physics;
pub mod process;
pub mod reference;

pub use load::LoadProgramme;
pub use physics::{RigPhysics, Sensor};
