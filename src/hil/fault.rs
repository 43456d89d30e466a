//! Named faults of the loop processes, carried as `u32` codes in messages and
//! heartbeats. `Copy` data only: reachable from the real-time loops.

use std::fmt;

/// A latched fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum Fault {
    /// Emulator: a NaN or infinite displacement sample.
    NonFiniteSample = 1,
    /// Emulator: a sample outside `[emulator] displacement_min_m..displacement_max_m`.
    DisplacementOutOfRange = 2,
    /// Emulator: a sample whose sequence is lower than one already used.
    SequenceBackwards = 3,
    /// Emulator: more consecutive late/missing samples than `trip_after_stale_samples`.
    TooManyStaleSamples = 4,
    /// Emulator: the rig flagged its sensor reading invalid.
    SensorFault = 5,
    /// Controller: no new setpoint for more than `stale_setpoint_periods`.
    SetpointsStale = 10,
    /// Controller: the emulator's heartbeat stopped.
    EmulatorHeartbeatLost = 11,
    /// Controller: the emulator reported itself tripped.
    EmulatorTripped = 12,
    /// Controller: a setpoint beyond the force limits with `limit_action = "ramp-to-zero"`.
    ForceLimitExceeded = 13,
    /// Rig: no new actuator command for more than `command_stale_periods` (interlock).
    CommandsStale = 20,
}

impl Fault {
    pub fn code(self) -> u32 {
        self as u32
    }

    pub fn from_code(code: u32) -> Option<Fault> {
        use Fault::*;
        [
            NonFiniteSample,
            DisplacementOutOfRange,
            SequenceBackwards,
            TooManyStaleSamples,
            SensorFault,
            SetpointsStale,
            EmulatorHeartbeatLost,
            EmulatorTripped,
            ForceLimitExceeded,
            CommandsStale,
        ]
        .into_iter()
        .find(|f| f.code() == code)
    }

    /// Kebab-case name used in reports and `--json` output.
    pub fn name(self) -> &'static str {
        match self {
            Fault::NonFiniteSample => "non-finite-sample",
            Fault::DisplacementOutOfRange => "displacement-out-of-range",
            Fault::SequenceBackwards => "sequence-backwards",
            Fault::TooManyStaleSamples => "too-many-stale-samples",
            Fault::SensorFault => "sensor-fault",
            Fault::SetpointsStale => "setpoints-stale",
            Fault::EmulatorHeartbeatLost => "emulator-heartbeat-lost",
            Fault::EmulatorTripped => "emulator-tripped",
            Fault::ForceLimitExceeded => "force-limit-exceeded",
            Fault::CommandsStale => "commands-stale",
        }
    }
}

impl fmt::Display for Fault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Name of a fault code, or `fault-<code>` for an unknown one.
pub fn fault_code_name(code: u32) -> String {
    Fault::from_code(code).map_or_else(|| format!("fault-{code}"), |f| f.name().to_string())
}
