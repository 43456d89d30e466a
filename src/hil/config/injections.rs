//! `[[inject]]`: deterministic fault injections on the loop's own time.

use serde::Deserialize;

use super::{Check, ConfigError};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawInjection {
    process: String,
    kind: String,
    at_s: f64,
    #[serde(default)]
    duration_ms: Option<f64>,
    #[serde(default)]
    count: Option<u64>,
}

/// A loop process, as named in `[[inject]] process`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoopProcess {
    Rig,
    Emulator,
    Controller,
}

impl LoopProcess {
    pub fn name(self) -> &'static str {
        match self {
            LoopProcess::Rig => "rig",
            LoopProcess::Emulator => "emulator",
            LoopProcess::Controller => "controller",
        }
    }
}

/// An injected fault (`[[inject]]`): deterministic, on the loop's own time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum InjectKind {
    /// The process's loop thread stops for this long, s.
    Stall { duration_s: f64 },
    /// The thread that runs the emulator's cycle is kept off its CPU for this long, s, as
    /// a hypervisor or an interrupt storm does to one CPU: the loop itself is not held,
    /// so a standby thread on another CPU goes on with it.
    CpuStall { duration_s: f64 },
    /// The process kills itself with SIGKILL.
    Kill,
    /// The rig publishes no sample for this many periods.
    DropSamples { count: u64 },
    /// The rig publishes one NaN sample.
    Nan,
    /// The rig publishes one sample far outside the emulator's range.
    OutOfRange,
}

impl InjectKind {
    pub fn name(self) -> &'static str {
        match self {
            InjectKind::Stall { .. } => "stall",
            InjectKind::CpuStall { .. } => "cpu-stall",
            InjectKind::Kill => "kill",
            InjectKind::DropSamples { .. } => "drop-samples",
            InjectKind::Nan => "nan",
            InjectKind::OutOfRange => "out-of-range",
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Injection {
    pub process: LoopProcess,
    pub kind: InjectKind,
    /// Loop time of the injection, s.
    pub at_s: f64,
}

impl Injection {
    /// "emulator stall 5 ms at 2.000 s" and the like.
    pub fn describe(&self) -> String {
        let what = match self.kind {
            InjectKind::Stall { duration_s } => format!("stall {} ms", duration_s * 1e3),
            InjectKind::CpuStall { duration_s } => format!("cpu-stall {} ms", duration_s * 1e3),
            InjectKind::DropSamples { count } => format!("drop-samples {count}"),
            k => k.name().to_string(),
        };
        format!("{} {what} at {:.3} s", self.process.name(), self.at_s)
    }
}

pub(super) fn parse_injection(
    check: &Check,
    index: usize,
    r: &RawInjection,
) -> Result<Injection, ConfigError> {
    let key = |k: &str| format!("inject[{index}].{k}");
    let process = check.choice(
        &key("process"),
        &r.process,
        &[
            ("rig", LoopProcess::Rig),
            ("emulator", LoopProcess::Emulator),
            ("controller", LoopProcess::Controller),
        ],
    )?;
    let at_s = check.non_negative(&key("at_s"), r.at_s)?;
    let kind = match r.kind.as_str() {
        "stall" => {
            let ms = r.duration_ms.ok_or_else(|| {
                check.err(&key("duration_ms"), "missing: a stall needs its duration in ms".into())
            })?;
            InjectKind::Stall {
                duration_s: check.positive(&key("duration_ms"), ms)? * 1e-3,
            }
        }
        "cpu-stall" => {
            let ms = r.duration_ms.ok_or_else(|| {
                check.err(&key("duration_ms"), "missing: a cpu-stall needs its duration in ms".into())
            })?;
            if process != LoopProcess::Emulator {
                return Err(check.err(
                    &key("process"),
                    format!("\"{}\" is not valid for kind \"cpu-stall\": only the emulator has a standby thread (process = \"emulator\")", r.process),
                ));
            }
            InjectKind::CpuStall {
                duration_s: check.positive(&key("duration_ms"), ms)? * 1e-3,
            }
        }
        "kill" => InjectKind::Kill,
        "drop-samples" => {
            let count = r.count.ok_or_else(|| {
                check.err(&key("count"), "missing: drop-samples needs a count of samples".into())
            })?;
            InjectKind::DropSamples {
                count: check.at_least(&key("count"), count, 1)?,
            }
        }
        "nan" => InjectKind::Nan,
        "out-of-range" => InjectKind::OutOfRange,
        other => {
            return Err(check.err(
                &key("kind"),
                format!("\"{other}\" is not valid: expected \"stall\", \"cpu-stall\", \"kill\", \"drop-samples\", \"nan\" or \"out-of-range\""),
            ))
        }
    };
    let sample_fault = matches!(
        kind,
        InjectKind::DropSamples { .. } | InjectKind::Nan | InjectKind::OutOfRange
    );
    if sample_fault && process != LoopProcess::Rig {
        return Err(check.err(
            &key("process"),
            format!(
                "\"{}\" is not valid for kind \"{}\": only the rig produces samples (process = \"rig\")",
                r.process,
                kind.name()
            ),
        ));
    }
    Ok(Injection {
        process,
        kind,
        at_s,
    })
}
