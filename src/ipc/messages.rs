//! Fixed-size `#[repr(C)]` messages carried on the loop's publish-subscribe services.
//!
//! Times are `CLOCK_MONOTONIC` nanoseconds (the same base in every process), so a
//! timestamp set by the rig can be compared with the controller's clock for end-to-end
//! latency. Every message carries the sequence numbers it answers, so records from the
//! three processes can be joined.

use iceoryx2::prelude::ZeroCopySend;

/// Status of a displacement sample (`DisplacementSample::status`).
pub mod sample_status {
    /// Sensor reading valid.
    pub const OK: u32 = 0;
    /// The rig knows the sensor value is invalid (e.g. out of its measuring range).
    pub const SENSOR_FAULT: u32 = 1;
    /// The rig is stopping: last sample of the run.
    pub const END_OF_RUN: u32 = 2;
}

/// Rig -> emulator: one measured displacement sample.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::DisplacementSample")]
#[repr(C)]
pub struct DisplacementSample {
    /// Sample counter, strictly increasing from 0.
    pub sequence: u64,
    /// Rig time of the sample (its own clock, starting at 0), ns.
    pub rig_time_ns: u64,
    /// Monotonic time when the sample was published, ns (end-to-end latency start).
    pub publish_time_ns: u64,
    /// Measured displacement, m, positive in compression.
    pub displacement_m: f64,
    /// One of `sample_status`.
    pub status: u32,
    pub reserved: u32,
}

/// Emulator state carried in `ForceSetpoint::emulator_state` and heartbeats.
pub mod emulator_state {
    pub const STARTING: u32 = 0;
    pub const RUNNING: u32 = 1;
    /// Safe state: force setpoint held at the configured safe force; see the fault code.
    pub const TRIPPED: u32 = 2;
    pub const STOPPED: u32 = 3;
}

/// Emulator -> controller: the element force answering one displacement sample.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::ForceSetpoint")]
#[repr(C)]
pub struct ForceSetpoint {
    /// Setpoint counter (one per emulator cycle), from 0.
    pub sequence: u64,
    /// Sequence of the displacement sample the force was computed from.
    pub sample_sequence: u64,
    /// `publish_time_ns` of that sample (carried through for end-to-end latency).
    pub sample_publish_time_ns: u64,
    /// Emulator loop time of this cycle's deadline, ns since the loop started.
    pub loop_time_ns: u64,
    /// Element reaction force, N, positive in compression.
    pub force_n: f64,
    /// One of `emulator_state`.
    pub emulator_state: u32,
    /// Fault code when tripped (see the runtime's fault enum), else 0.
    pub fault_code: u32,
    /// Model step flags (`StepFlags` bits).
    pub model_flags: u32,
    pub reserved: u32,
}

/// Controller -> rig: the actuator force command.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::ActuatorCommand")]
#[repr(C)]
pub struct ActuatorCommand {
    pub sequence: u64,
    /// Setpoint this command answers.
    pub setpoint_sequence: u64,
    /// Displacement sample at the origin of the chain.
    pub sample_sequence: u64,
    /// `publish_time_ns` of that sample.
    pub sample_publish_time_ns: u64,
    /// Commanded actuator force, N, positive pushing the specimen into compression
    /// reaction (the rig applies `-force` to the specimen as the element's reaction).
    pub force_n: f64,
    /// Controller state (running, ramping to safe, faulted).
    pub controller_state: u32,
    /// Latched fault code, 0 if none.
    pub fault_code: u32,
}

/// Any process -> orchestrator: liveness and state.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::Heartbeat")]
#[repr(C)]
pub struct Heartbeat {
    /// Which process (0 rig, 1 emulator, 2 controller).
    pub process: u32,
    pub state: u32,
    pub sequence: u64,
    pub time_ns: u64,
    pub fault_code: u32,
    pub reserved: u32,
}

/// Controller state carried in `ActuatorCommand::controller_state` and heartbeats.
pub mod controller_state {
    pub const STARTING: u32 = 0;
    pub const RUNNING: u32 = 1;
    /// A fault is latched: the command ramps to the safe force.
    pub const RAMPING_TO_SAFE: u32 = 2;
    /// A fault is latched and the command has reached the safe force.
    pub const SAFE: u32 = 3;
    pub const STOPPED: u32 = 4;
}

/// Rig state carried in heartbeats.
pub mod rig_state {
    pub const STARTING: u32 = 0;
    pub const RUNNING: u32 = 1;
    /// The rig's own interlock ramped the actuator to the safe force (commands stale).
    pub const INTERLOCK: u32 = 2;
    pub const FINISHED: u32 = 3;
}

/// Process ids carried in `Heartbeat::process`.
pub mod process_id {
    pub const RIG: u32 = 0;
    pub const EMULATOR: u32 = 1;
    pub const CONTROLLER: u32 = 2;
}

/// Heartbeat state meaning "ports created, waiting for the start command" (all processes).
pub const HEARTBEAT_READY: u32 = 100;

/// Run-control commands (`RunControl::command`).
pub mod run_command {
    /// Start the loops: first deadline at `RunControl::start_time_ns`.
    pub const START: u32 = 1;
    /// Stop now: flush records and exit.
    pub const STOP: u32 = 2;
}

/// Orchestrator -> every process: start time and stop requests.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("fastemu::RunControl")]
#[repr(C)]
pub struct RunControl {
    pub sequence: u64,
    /// `CLOCK_MONOTONIC` time of the rig's first sample, ns; every loop's grid is
    /// `start_time_ns + k * period` (plus its own phase offset).
    pub start_time_ns: u64,
    /// One of `run_command`.
    pub command: u32,
    pub reserved: u32,
}
