//! The simulated rig (hardware stand-in) and the offline reference it is judged against:
//! specimen mass with the rig's own damping, external load programme, force actuator
//! (transport delay, first-order lag, saturation) with its servo controller (local law,
//! position-hold interlock), displacement sensor (noise, quantisation, seeded PRNG).
//! Physics and servo logic here are pure (no I/O, no clock); `process` runs them as the
//! `bench_rig` process on its own fixed-step clock.

pub mod actuator;
pub mod core;
pub mod load;
pub mod physics;
pub mod process;
pub mod programme;
pub mod reference;
pub mod servo;
pub mod transport;

pub use load::LoadProgramme;
pub use physics::{RigPhysics, Sensor};
pub use programme::ProgrammeRunner;
pub use servo::{Servo, ServoConfig};
pub use transport::RigTransport;
