//! Links to rigs that fastemu did not start, beside `ipc/`: the UDP rig link for
//! real-time targets (Speedgoat/Simulink Real-Time, TwinCAT, VeriStand, a DAQ PC).
//!
//! - `protocol`: the datagrams (fixed little-endian layouts, magic, version, sequence
//!   numbers, the sender's clock), encode and decode, the reasons a datagram is rejected.
//! - `socket`: one end's UDP socket: bound to one interface, one peer, counts per reason.
//! - `process`: fastemu's end, the `fastemu link` process: the rig, as the loop sees it.
//! - `rig_end`: the rig's end, as the simulated rig runs it behind the link.
//!
//! Must not: import iceoryx2 (the loop's services are reached through `ipc/`); allocate,
//! lock or log per datagram.

pub mod process;
pub mod protocol;
pub mod rig_end;
pub mod socket;
