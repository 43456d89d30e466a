//! Events: faults with their detection latency and action, injected faults, operator
//! actions, the hold's milestones. Fixed-size codes (no text), so the real-time loops can
//! push them; `describe` turns one into a sentence offline.

use super::Record;
use crate::hil::fault::fault_code_name;
use crate::record_type;

/// `EventRecord::kind`.
pub mod event_kind {
    /// A fault latched by the process that detected it.
    pub const FAULT: u32 = 1;
    /// An injected fault (`[[inject]]`) fired; `value` is its parameter (ms, count).
    pub const INJECTED: u32 = 2;
    /// Operator hold (`fastemu ctl hold`).
    pub const OPERATOR_HOLD: u32 = 3;
    /// Operator resume.
    pub const OPERATOR_RESUME: u32 = 4;
    /// Operator stop (orderly end: hold, unload, finish).
    pub const OPERATOR_STOP: u32 = 5;
    /// The specimen came to rest in a hold; `value` is the hold position, m.
    pub const AT_REST: u32 = 6;
    /// An unload reached zero external force.
    pub const UNLOADED: u32 = 7;
    /// The rig ended the run; `value` is the reason (0 scenario end, 1 after a hold).
    pub const FINISHED: u32 = 8;
}

/// Injection kinds carried in `EventRecord::fault_code` for `INJECTED` events.
pub mod injected_kind {
    pub const STALL: u32 = 1;
    pub const KILL: u32 = 2;
    pub const DROP_SAMPLES: u32 = 3;
    pub const NAN: u32 = 4;
    pub const OUT_OF_RANGE: u32 = 5;
    pub const CPU_STALL: u32 = 6;
}

/// `EventRecord::action` (`FaultAction` as a code; `NONE` for events without one).
pub mod action_code {
    use crate::hil::fault::FaultAction;

    pub const INDICATE: u32 = 0;
    pub const HOLD: u32 = 1;
    pub const HOLD_UNLOAD: u32 = 2;
    pub const NONE: u32 = u32::MAX;

    pub fn of(action: FaultAction) -> u32 {
        match action {
            FaultAction::Indicate => INDICATE,
            FaultAction::Hold => HOLD,
            FaultAction::HoldUnload => HOLD_UNLOAD,
        }
    }
}

record_type! {
    /// One event of a process (`/events`).
    pub struct EventRecord {
        topic: "/events",
        schema: "fastemu/EventRecord",
        log_time: |r| (r.t_s.max(0.0) * 1e9).round() as u64,
        fields: {
            /// time since the run's start, s
            t_s: f64,
            /// process that recorded it: 0 rig, 1 emulator, 2 controller, 3 orchestrator
            process: u32,
            /// event kind: 1 fault, 2 injected, 3 operator hold, 4 resume, 5 stop, 6 at rest, 7 unloaded, 8 finished
            kind: u32,
            /// fault code (fault events) or injection kind (injected events)
            fault_code: u32,
            /// the emulator's or controller's own fault code behind it, else 0
            remote_fault_code: u32,
            /// action: 0 indicate, 1 hold, 2 hold-unload, 4294967295 none
            action: u32,
            /// periods between the last good input and the detection
            detection_latency_periods: u64,
            /// the process's step or cycle index
            step_idx: u64,
            /// kind-specific value (hold position m, stall ms, sample count)
            value: f64,
        }
    }
}

const PROCESS_LABELS: [&str; 4] = ["bench_rig", "emulator", "controller", "hil"];

/// What a report calls the rig's slot when the rig is external (its own faults arrive in
/// its samples and carry the simulated rig's label).
pub const EXTERNAL_RIG_LABEL: &str = "external rig";

/// `text` (a fault line "bench_rig: ...", an event line "1.0 s bench_rig: ...", or the
/// bare label) with the rig's label, if it begins a line or follows a space, as an
/// external rig's.
pub fn external_rig_labelled(text: &str) -> String {
    let rig = PROCESS_LABELS[0];
    if text == rig {
        return EXTERNAL_RIG_LABEL.to_string();
    }
    if let Some(rest) = text.strip_prefix(&format!("{rig}: ")) {
        return format!("{EXTERNAL_RIG_LABEL}: {rest}");
    }
    text.replacen(&format!(" {rig}: "), &format!(" {EXTERNAL_RIG_LABEL}: "), 1)
}

impl EventRecord {
    /// Process label (`bench_rig`, `emulator`, ...).
    pub fn process_name(&self) -> &'static str {
        PROCESS_LABELS
            .get(self.process as usize)
            .copied()
            .unwrap_or("unknown")
    }

    pub fn action_name(&self) -> Option<&'static str> {
        match self.action {
            action_code::INDICATE => Some("indicate"),
            action_code::HOLD => Some("hold"),
            action_code::HOLD_UNLOAD => Some("hold-unload"),
            _ => None,
        }
    }

    /// One line: "1.234 s controller: setpoints-stale (after 102 periods) -> hold".
    pub fn describe(&self) -> String {
        let what = match self.kind {
            event_kind::FAULT => {
                let mut s = fault_code_name(self.fault_code);
                if self.remote_fault_code != 0 {
                    s.push_str(&format!(" ({})", fault_code_name(self.remote_fault_code)));
                }
                s.push_str(&format!(
                    " (detected after {} periods)",
                    self.detection_latency_periods
                ));
                if let Some(a) = self.action_name() {
                    s.push_str(&format!(" -> {a}"));
                }
                s
            }
            event_kind::INJECTED => match self.fault_code {
                injected_kind::STALL => format!("injected stall of {} ms", self.value),
                injected_kind::CPU_STALL => {
                    format!(
                        "injected CPU stall of {} ms (the loop thread's CPU)",
                        self.value
                    )
                }
                injected_kind::KILL => "injected kill".into(),
                injected_kind::DROP_SAMPLES => format!("injected drop of {} samples", self.value),
                injected_kind::NAN => "injected NaN sample".into(),
                injected_kind::OUT_OF_RANGE => "injected out-of-range sample".into(),
                k => format!("injected fault {k}"),
            },
            event_kind::OPERATOR_HOLD => "operator hold".into(),
            event_kind::OPERATOR_RESUME => "operator resume".into(),
            event_kind::OPERATOR_STOP => "operator stop".into(),
            event_kind::AT_REST => format!("at rest, held at {:.1} um", self.value * 1e6),
            event_kind::UNLOADED => "unloaded".into(),
            event_kind::FINISHED => "finished".into(),
            k => format!("event {k}"),
        };
        format!("{:.4} s {}: {what}", self.t_s, self.process_name())
    }

    /// Size check used by tests: the encoded record is fixed-size.
    pub const ENCODED_SIZE: usize = <EventRecord as Record>::SIZE;
}

#[cfg(test)]
mod label_tests {
    use super::*;

    /// The rig's label becomes an external rig's in a fault line, an event line and alone;
    /// other processes and words that merely contain it are left alone.
    #[test]
    fn the_rigs_label_is_an_external_rigs() {
        assert_eq!(external_rig_labelled("bench_rig"), "external rig");
        assert_eq!(
            external_rig_labelled("bench_rig: commands-stale"),
            "external rig: commands-stale"
        );
        assert_eq!(
            external_rig_labelled("1.2340 s bench_rig: hold-requested"),
            "1.2340 s external rig: hold-requested"
        );
        assert_eq!(external_rig_labelled("emulator"), "emulator");
        assert_eq!(
            external_rig_labelled("controller: emulator-tripped (bench_rig)"),
            "controller: emulator-tripped (bench_rig)"
        );
    }
}
