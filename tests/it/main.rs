//! One integration-test binary (STYLE.md): each module tests one feature.

mod paper;
