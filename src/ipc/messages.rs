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
