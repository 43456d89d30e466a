//! The real-time HIL runtime: configuration, the emulator's and controller's loop logic,
//! records, the loop processes, and the `hil` orchestrator with its report.
//!
//! Must not: import iceoryx2 (only `ipc/` does); allocate, log or do I/O in the loop
//! iterations (`EmulatorCore::cycle`, `ControllerCore::on_*`).

pub mod config;
pub mod controller;
pub mod emulator;
pub mod fault;
pub mod orchestrator;
pub mod process;
pub mod records;
pub mod report;
