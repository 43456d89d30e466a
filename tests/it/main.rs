//! The one integration-test binary (STYLE: one binary, shared helpers). Each module
//! checks a feature against an independent calculation written in the test itself.

mod alloc_counter;
mod campaign_loading;
mod cli_errors;
mod common;
mod compensation_inproc;
mod diagnose_campaigns;
mod diagnose_run;
mod diagnose_verdicts;
mod docs_links;
mod durability;
mod effects_model;
mod gen;
mod hil_core;
mod hil_processes;
mod identify_cli;
mod ipc_alloc;
mod latency_bench;
mod link_processes;
mod live_view;
mod model_alloc;
mod model_closed_form;
mod model_determinism;
mod model_modulus;
mod model_tension;
mod paper;
mod rig_header;
mod safety_inproc;
mod synth_cli;
