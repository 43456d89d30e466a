//! The real-time HIL runtime: configuration, faults, the emulator's and controller's loop
//! logic, the deterministic in-process loop, the loop processes, and the `hil`
//! orchestrator with its report.
//!
//! Must not: import iceoryx2 (only `ipc/` does); allocate, log or do I/O in the loop
//! iterations (`EmulatorCore::cycle`, `ControllerCore::on_*`).

pub mod check;
pub mod compensation;
pub mod config;
pub mod controller;
pub mod controller_process;
pub mod emulator;
pub mod emulator_process;
pub mod fault;
pub mod inproc;
pub mod orchestrator;
pub mod passivity;
pub mod process;
pub mod registry;
pub mod report;
