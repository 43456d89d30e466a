//! Integration tests: one binary, one module per feature.

mod hil_core;
mod hil_processes;
