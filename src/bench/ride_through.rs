//! `fastemu bench ride-through`: what a stall of the emulator or the controller does to the
//! specimen, on the deterministic in-process loop (no OS timing: the figures depend on the
//! configuration only). For each stall length and start, the largest resonant transient
//! (the >100 Hz part of the true displacement minus the offline reference) with
//! local-law commands and with plain force commands, and whether the stall became a fault.

use serde::Serialize;

use crate::hil::config::{CommandMode, HilConfig};
use crate::hil::inproc::{run_in_process, InProcessRun, InProcessScript};
use crate::hil::report::fidelity::CentredHighPass;
use crate::records::event::event_kind;
use crate::rig::reference::ReferenceStepper;

/// One cell: a stall of `length_ms` from `start_s`.
#[derive(Debug, Clone, Serialize)]
pub struct RideThroughCell {
    pub start_s: f64,
    pub length_ms: f64,
    /// Largest transient after the stall's start, um, with local-law commands.
    pub law_transient_um: f64,
    /// The same with plain force commands (extrapolated by the controller).
    pub force_transient_um: f64,
    /// Whether the stall became a fault (beyond the ride-through limit).
    pub law_fault: bool,
    pub force_fault: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct RideThrough {
    /// `emulator` or `controller`.
    pub process: String,
    pub stall_limit_ms: f64,
    pub cells: Vec<RideThroughCell>,
}

fn transient_after(cfg: &HilConfig, run: &InProcessRun, from_s: f64) -> f64 {
    let mut reference = ReferenceStepper::new(cfg, cfg.scenario.duration_s);
    let mut hp = CentredHighPass::new(cfg.loop_.rate_hz);
    let from_idx = (from_s * cfg.loop_.rate_hz) as usize;
    let mut peak = 0.0f64;
    let mut k = 0u64;
    let mut x_ref = 0.0;
    // Only while the rig runs in force control (a hold leaves the reference behind).
    for r in run
        .rig
        .iter()
        .take_while(|r| r.state == crate::ipc::messages::rig_state::RUNNING)
    {
        while k <= r.step_idx {
            x_ref = reference.next().unwrap_or(f64::NAN);
            k += 1;
        }
        if let Some((i, y)) = hp.push(r.x_m - x_ref) {
            if i >= from_idx {
                peak = peak.max(y.abs());
            }
        }
    }
    peak
}

fn faulted(run: &InProcessRun) -> bool {
    run.events.iter().any(|e| e.kind == event_kind::FAULT)
}

/// Runs the study; `emulator` chooses which process stalls.
pub fn ride_through(
    cfg: &HilConfig,
    emulator: bool,
    starts_s: &[f64],
    lengths_ms: &[f64],
) -> RideThrough {
    let rate = cfg.loop_.rate_hz;
    let mut force_cfg = cfg.clone();
    force_cfg.controller.command_mode = CommandMode::Force;
    let mut law_cfg = cfg.clone();
    law_cfg.controller.command_mode = CommandMode::Law;
    let mut cells = Vec::new();
    for &start_s in starts_s {
        for &length_ms in lengths_ms {
            let stall = vec![(
                (start_s * rate) as u64,
                (length_ms * 1e-3 * rate).round() as u64,
            )];
            let horizon = start_s + length_ms * 1e-3 + 0.3;
            let script = InProcessScript {
                max_steps: (horizon * rate) as u64,
                command_delay_periods: 1,
                emulator_stalls: if emulator { stall.clone() } else { vec![] },
                controller_stalls: if emulator { vec![] } else { stall },
                ..InProcessScript::default()
            };
            let law = run_in_process(&law_cfg, &script);
            let force = run_in_process(&force_cfg, &script);
            cells.push(RideThroughCell {
                start_s,
                length_ms,
                law_transient_um: transient_after(&law_cfg, &law, start_s) * 1e6,
                force_transient_um: transient_after(&force_cfg, &force, start_s) * 1e6,
                law_fault: faulted(&law),
                force_fault: faulted(&force),
            });
        }
    }
    RideThrough {
        process: if emulator { "emulator" } else { "controller" }.into(),
        stall_limit_ms: cfg.safety.stall_limit_s * 1e3,
        cells,
    }
}

impl RideThrough {
    /// A table: one row per stall length, the worst over the starts.
    pub fn table(&self) -> String {
        let mut lengths: Vec<f64> = self.cells.iter().map(|c| c.length_ms).collect();
        lengths.sort_by(f64::total_cmp);
        lengths.dedup();
        let mut out = format!(
            "{} stall (ride-through limit {} ms); largest resonant transient over {} start times, um\n",
            self.process,
            self.stall_limit_ms,
            self.cells.len() / lengths.len().max(1)
        );
        out.push_str(
            "| stall (ms) | local-law commands | plain force commands |\n| --- | --- | --- |\n",
        );
        for l in lengths {
            let row: Vec<&RideThroughCell> =
                self.cells.iter().filter(|c| c.length_ms == l).collect();
            let worst = |f: fn(&RideThroughCell) -> f64, fault: fn(&RideThroughCell) -> bool| {
                let m = row.iter().map(|c| f(c)).fold(0.0f64, f64::max);
                let faults = row.iter().filter(|c| fault(c)).count();
                if faults > 0 {
                    format!("{m:.1} (fault in {faults} of {})", row.len())
                } else {
                    format!("{m:.1}")
                }
            };
            out.push_str(&format!(
                "| {l} | {} | {} |\n",
                worst(|c| c.law_transient_um, |c| c.law_fault),
                worst(|c| c.force_transient_um, |c| c.force_fault)
            ));
        }
        out
    }
}
