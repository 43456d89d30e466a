//! The integration-test binary: one binary, one module per feature.

mod diagnose_campaigns;
mod gen;
