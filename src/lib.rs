//! fastemu: real-time hardware-in-the-loop emulation of the rail fastening elastomer of
//! Li et al. (Materials 2021), plus the offline tools around it. See ARCHITECTURE.md.

pub mod bench;
pub mod child;
pub mod cli;
pub mod csvio;
pub mod hil;
pub mod ident;
pub mod ipc;
pub mod link;
pub mod live;
pub mod model;
pub mod paper;
pub mod plot;
pub mod records;
pub mod rig;
pub mod rt;
pub mod tomlerr;
pub mod track;
pub mod utc;
