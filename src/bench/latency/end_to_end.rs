//! End-to-end latency of the real three-process loop (rig sample published -> actuator
//! command published), taken from a short `fastemu hil --json --duration-s S` run of the
//! same executable, on iceoryx2 and with the simulated rig behind the UDP rig link
//! (`--rig-link udp`: the sample's time is when the rig sent its datagram, so the link's
//! hop is included; the link's own latency comes from `link.latency_ns`). Its contract: one JSON object on stdout with
//! `latency_ns.end_to_end` and `latency_ns.wake_jitter`, each holding `p50`, `p99`,
//! `p999`, `max` in ns. If this binary has no `hil` subcommand, or the run fails, the
//! result is "unavailable" with the reason, never an error of the benchmark.

use std::io::Read;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use crate::child::ChildGuard;

/// p50/p99/p99.9/max as the `hil` command reports them, ns.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct LoopLatency {
    pub p50_ns: f64,
    pub p99_ns: f64,
    pub p999_ns: f64,
    pub max_ns: f64,
}

/// What the `hil` run gave.
#[derive(Debug, Clone, PartialEq)]
pub enum EndToEnd {
    Measured {
        end_to_end: LoopLatency,
        /// The loop's own wake-up jitter during that run, if reported.
        wake_jitter: Option<LoopLatency>,
        /// The UDP rig link's latency (`link.latency_ns`) when the run used the link.
        link: Option<LoopLatency>,
        command: String,
    },
    Unavailable {
        reason: String,
        command: String,
    },
}

/// Parses `{"p50": .., "p99": .., "p999": .., "max": ..}`.
fn parse_loop_latency(value: &serde_json::Value) -> Option<LoopLatency> {
    let field = |k: &str| value.get(k).and_then(serde_json::Value::as_f64);
    Some(LoopLatency {
        p50_ns: field("p50")?,
        p99_ns: field("p99")?,
        p999_ns: field("p999")?,
        max_ns: field("max")?,
    })
}

/// Reads the `hil --json` output (last JSON object line on stdout).
pub fn parse_hil_output(stdout: &str) -> Result<(LoopLatency, Option<LoopLatency>), String> {
    let object: serde_json::Value = stdout
        .lines()
        .rev()
        .find_map(|line| serde_json::from_str(line.trim()).ok())
        .or_else(|| serde_json::from_str(stdout.trim()).ok())
        .ok_or_else(|| "no JSON object on `hil --json` stdout".to_string())?;
    let latency = object
        .get("latency_ns")
        .ok_or_else(|| "`hil --json` output has no `latency_ns`".to_string())?;
    let end_to_end = latency
        .get("end_to_end")
        .and_then(parse_loop_latency)
        .ok_or_else(|| {
            "`latency_ns.end_to_end` missing or lacks p50/p99/p999/max numbers".to_string()
        })?;
    let wake_jitter = latency.get("wake_jitter").and_then(parse_loop_latency);
    Ok((end_to_end, wake_jitter))
}

/// Reads `link.latency_ns` of a `hil --json --rig-link udp` output, if there.
pub fn parse_link_latency(stdout: &str) -> Option<LoopLatency> {
    let object: serde_json::Value = stdout
        .lines()
        .rev()
        .find_map(|line| serde_json::from_str(line.trim()).ok())?;
    parse_loop_latency(&object["link"]["latency_ns"])
}

/// Runs `exe hil --json --duration-s duration_s [extra]`, killing it after `timeout`.
pub fn measure_end_to_end(
    exe: &Path,
    duration_s: f64,
    timeout: Duration,
    extra: &[&str],
) -> EndToEnd {
    let mut args = vec![
        "hil".to_string(),
        "--json".to_string(),
        "--duration-s".to_string(),
        format!("{duration_s}"),
    ];
    args.extend(extra.iter().map(|a| a.to_string()));
    let command = format!("{} {}", exe.display(), args.join(" "));
    let unavailable = |reason: String| EndToEnd::Unavailable {
        reason,
        command: command.clone(),
    };
    let child = Command::new(exe)
        .args(&args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn();
    let mut child = match child {
        Ok(c) => c,
        Err(e) => return unavailable(format!("cannot spawn: {e}")),
    };
    // Drain both pipes on threads so a chatty child cannot block on a full pipe.
    let drain = |pipe: Option<Box<dyn Read + Send>>| {
        std::thread::spawn(move || {
            let mut text = String::new();
            if let Some(mut p) = pipe {
                let _ = p.read_to_string(&mut text);
            }
            text
        })
    };
    let stdout_reader = drain(
        child
            .stdout
            .take()
            .map(|p| Box::new(p) as Box<dyn Read + Send>),
    );
    let stderr_reader = drain(
        child
            .stderr
            .take()
            .map(|p| Box::new(p) as Box<dyn Read + Send>),
    );
    let mut guard = ChildGuard::new(child);
    let status = guard.wait_timeout(timeout);
    drop(guard); // kills it if still running, so the pipe readers finish
    let stdout = stdout_reader.join().unwrap_or_default();
    let stderr = stderr_reader.join().unwrap_or_default();
    let status = match status {
        Ok(Some(s)) => s,
        Ok(None) => return unavailable(format!("`hil` did not finish within {timeout:?}; killed")),
        Err(e) => return unavailable(format!("waiting for `hil`: {e}")),
    };
    if !status.success() {
        if stderr.contains("unrecognized subcommand") {
            return unavailable(
                "this fastemu binary has no `hil` subcommand (HIL runtime not built in)"
                    .to_string(),
            );
        }
        let tail: String = stderr.lines().rev().take(3).collect::<Vec<_>>().join(" | ");
        return unavailable(format!("`hil` failed ({status}): {tail}"));
    }
    match parse_hil_output(&stdout) {
        Ok((end_to_end, wake_jitter)) => EndToEnd::Measured {
            end_to_end,
            wake_jitter,
            link: parse_link_latency(&stdout),
            command,
        },
        Err(reason) => unavailable(reason),
    }
}
