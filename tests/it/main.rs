//! The integration-test binary: one binary, one module per feature.

mod campaign_loading;
mod diagnose_campaigns;
mod effects_model;
mod gen;
mod identify_cli;
