//! Inter-process communication over iceoryx2: the only module that imports iceoryx2.
//!
//! Owns the shared-memory message types (`messages`), compiled once for every process so
//! their layouts cannot drift. Must not: allocate or log on the per-sample publish/receive
//! path beyond the one block iceoryx2 0.10 itself makes per publish (`transport`; on a loop
//! thread it comes from `rt::pool`).

pub mod cleanup;
pub mod messages;
pub mod transport;

pub use transport::{
    cleanup_dead_nodes, connect_all, count_nodes, file_prefix, quiet_iceoryx2_logs,
    service_settings, Connect, In, IpcError, IpcNode, Out, RigServices, Stream, Wake, WakeListener,
    MAX_NODES,
};
pub mod pingpong;
