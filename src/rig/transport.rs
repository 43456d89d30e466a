//! `RigTransport`: the seam between the rig's loop and whatever carries its samples and commands; `rig/` owns the trait, its callers build the transport (iceoryx2 here in `process`, the UDP link's end in `link::rig_end`), and it must not import `link/`.

use crate::hil::process::{ControlRequests, ProcessError, StartInfo};
use crate::ipc::messages::{ActuatorCommand, DisplacementSample, Heartbeat};

/// Where the rig's samples go and where its commands, run control and start come from:
/// the run's iceoryx2 services, or the far end of the UDP rig link
/// (`crate::link::rig_end::UdpRigEnd`).
pub trait RigTransport {
    /// Announces readiness until the start; returns the time base on this machine's clock.
    fn wait_for_start(&mut self) -> Result<StartInfo, ProcessError>;
    /// Sends one sample (every period: must not allocate, lock or block).
    fn send_sample(&mut self, sample: &DisplacementSample);
    /// Hands over every command received since the last call, oldest first (every period).
    fn receive_commands(&mut self, on_command: &mut dyn FnMut(&ActuatorCommand));
    /// At heartbeat rate: reports the rig's state, returns the run control received.
    fn heartbeat(&mut self, heartbeat: &Heartbeat) -> ControlRequests;
    /// After the last period: the end-of-run sample and the final heartbeat.
    fn finish(&mut self, last: &DisplacementSample, heartbeat: &Heartbeat);
    /// What the transport counted, for the rig's summary (`RigSummary::link`).
    fn counts_json(&self) -> Option<serde_json::Value> {
        None
    }
}
