//! Named faults of the loop processes, their classes and the configurable actions, carried
//! as `u32` codes in messages and heartbeats. `Copy` data only: reachable from the
//! real-time loops.

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
    /// Emulator: more consecutive cycles without a new sample than `trip_after_stale_samples`.
    TooManyStaleSamples = 4,
    /// Emulator: the rig flagged its sensor reading invalid.
    SensorFault = 5,
    /// Emulator: its own loop woke later than the stall limit (it was stopped or starved).
    EmulatorStalled = 6,
    /// Emulator: the loop generates energy or oscillates beyond its bound
    /// (`StabilityMonitor`: the passivity observer's energy, the resonant oscillation).
    LoopUnstable = 7,
    /// Controller: no new setpoint for longer than the stall limit (emulator dead or stalled).
    SetpointsStale = 10,
    /// Controller: the emulator's heartbeat stopped.
    EmulatorHeartbeatLost = 11,
    /// Controller: the emulator reported itself tripped.
    EmulatorTripped = 12,
    /// Controller: a setpoint beyond the force limits with `limit_action = "fault"`.
    ForceLimitExceeded = 13,
    /// Controller: the emulator's local law was not finite or had a negative stiffness or
    /// damping.
    InvalidLaw = 14,
    /// Rig: no new actuator command for longer than its limit (controller dead or stalled).
    CommandsStale = 20,
    /// Rig: `fastemu hil` (the orchestrator) died.
    OrchestratorLost = 21,
    /// Rig: the controller asked for a hold (its own fault; see the controller's code).
    HoldRequested = 22,
}

/// Which configured action applies to a fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaultClass {
    /// The emulator tripped, stalled beyond its limit, died, or sent an invalid law.
    Emulator,
    /// Commands stopped reaching the rig (controller dead or stalled).
    Controller,
    /// A force beyond the controller's limits (`limit_action = "fault"`).
    Limits,
    /// The orchestrator died.
    Orchestrator,
}

impl FaultClass {
    /// The `[safety]` key that sets this class's action.
    pub fn config_key(self) -> &'static str {
        match self {
            FaultClass::Emulator => "emulator_fault_action",
            FaultClass::Controller => "controller_fault_action",
            FaultClass::Limits => "limit_fault_action",
            FaultClass::Orchestrator => "orchestrator_lost_action",
        }
    }
}

/// What the actuator side does on a fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaultAction {
    /// Record and report the fault; the loop goes on.
    Indicate,
    /// Interlock: position hold where it tripped, load programme held; the run ends once
    /// the specimen is at rest (after at least `[safety] hold_min_s`).
    Hold,
    /// As `Hold`, then unload the load programme to zero while holding position.
    HoldUnload,
}

impl FaultAction {
    pub fn name(self) -> &'static str {
        match self {
            FaultAction::Indicate => "indicate",
            FaultAction::Hold => "hold",
            FaultAction::HoldUnload => "hold-unload",
        }
    }

    pub fn from_name(name: &str) -> Option<FaultAction> {
        [
            FaultAction::Indicate,
            FaultAction::Hold,
            FaultAction::HoldUnload,
        ]
        .into_iter()
        .find(|a| a.name() == name)
    }
}

const ALL_FAULTS: [Fault; 15] = [
    Fault::NonFiniteSample,
    Fault::DisplacementOutOfRange,
    Fault::SequenceBackwards,
    Fault::TooManyStaleSamples,
    Fault::SensorFault,
    Fault::EmulatorStalled,
    Fault::LoopUnstable,
    Fault::SetpointsStale,
    Fault::EmulatorHeartbeatLost,
    Fault::EmulatorTripped,
    Fault::ForceLimitExceeded,
    Fault::InvalidLaw,
    Fault::CommandsStale,
    Fault::OrchestratorLost,
    Fault::HoldRequested,
];

impl Fault {
    pub fn code(self) -> u32 {
        self as u32
    }

    pub fn from_code(code: u32) -> Option<Fault> {
        ALL_FAULTS.into_iter().find(|f| f.code() == code)
    }

    /// The class whose configured action applies.
    pub fn class(self) -> FaultClass {
        match self {
            Fault::CommandsStale => FaultClass::Controller,
            Fault::ForceLimitExceeded => FaultClass::Limits,
            Fault::OrchestratorLost => FaultClass::Orchestrator,
            _ => FaultClass::Emulator,
        }
    }

    /// Kebab-case name used in reports and `--json` output.
    pub fn name(self) -> &'static str {
        match self {
            Fault::NonFiniteSample => "non-finite-sample",
            Fault::DisplacementOutOfRange => "displacement-out-of-range",
            Fault::SequenceBackwards => "sequence-backwards",
            Fault::TooManyStaleSamples => "too-many-stale-samples",
            Fault::SensorFault => "sensor-fault",
            Fault::EmulatorStalled => "emulator-stalled",
            Fault::LoopUnstable => "loop-unstable",
            Fault::SetpointsStale => "setpoints-stale",
            Fault::EmulatorHeartbeatLost => "emulator-heartbeat-lost",
            Fault::EmulatorTripped => "emulator-tripped",
            Fault::ForceLimitExceeded => "force-limit-exceeded",
            Fault::InvalidLaw => "invalid-law",
            Fault::CommandsStale => "commands-stale",
            Fault::OrchestratorLost => "orchestrator-lost",
            Fault::HoldRequested => "hold-requested",
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

/// The configured action per fault class (`[safety]`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FaultActions {
    pub emulator: FaultAction,
    pub controller: FaultAction,
    pub limits: FaultAction,
    pub orchestrator: FaultAction,
}

impl FaultActions {
    /// Hold on every class (the default).
    pub const HOLD_ALL: FaultActions = FaultActions {
        emulator: FaultAction::Hold,
        controller: FaultAction::Hold,
        limits: FaultAction::Hold,
        orchestrator: FaultAction::Hold,
    };

    pub fn for_fault(&self, fault: Fault) -> FaultAction {
        match fault.class() {
            FaultClass::Emulator => self.emulator,
            FaultClass::Controller => self.controller,
            FaultClass::Limits => self.limits,
            FaultClass::Orchestrator => self.orchestrator,
        }
    }
}
