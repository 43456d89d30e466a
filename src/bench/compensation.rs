//! `fastemu bench compensation`: what the controller's compensation costs and gives.
//!
//! - The controller's added work per command: `ControllerCore::on_setpoint` timed on the
//!   setpoints of an in-process run, with the compensation on (estimator and guard) and
//!   off, in alternating rounds; percentiles of each and of their difference of medians.
//! - Fidelity per actuator and initial guess: in-process runs of the configuration with
//!   each actuator variant and each starting lead, the displacement error against the
//!   offline reference, the identified delay, the faithful band, the guard's activity and
//!   whether a fault ended the run.
//!
//! Timings here are figures for reports, never pass/fail.

use std::time::Instant;

use hdrhistogram::Histogram;
use serde::Serialize;

use crate::hil::config::HilConfig;
use crate::hil::controller::ControllerCore;
use crate::hil::inproc::{run_in_process, InProcessRun, InProcessScript};
use crate::hil::report::compensation::CompensationAnalyser;
use crate::ipc::messages::{emulator_state, ForceSetpoint, LocalLaw};
use crate::records::event::event_kind;
use crate::rig::reference::reference_displacement_m;

/// Percentiles of one timing, ns.
#[derive(Debug, Clone, Serialize)]
pub struct Timing {
    pub p50_ns: u64,
    pub p99_ns: u64,
    pub p999_ns: u64,
    pub max_ns: u64,
}

fn timing(h: &Histogram<u64>) -> Timing {
    Timing {
        p50_ns: h.value_at_quantile(0.5),
        p99_ns: h.value_at_quantile(0.99),
        p999_ns: h.value_at_quantile(0.999),
        max_ns: h.max(),
    }
}

/// The controller's work per command.
#[derive(Debug, Clone, Serialize)]
pub struct ControllerWork {
    pub commands: u64,
    pub with_compensation: Timing,
    pub without: Timing,
}

/// One fidelity cell.
#[derive(Debug, Clone, Serialize)]
pub struct FidelityCell {
    pub actuator: String,
    pub initial_delay_us: f64,
    /// The lead the plan fixed instead (`check::compensation_plan`), us.
    pub planned_lead_us: Option<f64>,
    /// The lead the plan started the run at instead of the guess, us (`None`: the guess).
    pub planned_start_us: Option<f64>,
    pub fault: Option<String>,
    pub displacement_error_pct: f64,
    /// The report's identified delay (over the load band when the load excited it) and the
    /// lead's estimator's (`report::compensation::CompensationReport`), us.
    pub identified_delay_us: Option<f64>,
    /// `"load-band"` or `"lead-estimator"` (the report's `identified_from`).
    pub identified_from: Option<&'static str>,
    pub lead_estimate_us: Option<f64>,
    /// The actuator's mean phase delay over 1-20 Hz as the record shows it
    /// (`report::compensation::RecordDelay`), and the rig's truth of the same (its
    /// `actuator_truth.effective_delay_s`), us.
    pub record_delay_us: Option<f64>,
    pub truth_delay_us: f64,
    pub final_lead_us: f64,
    /// With the planned fixed lead: the nudge's steps (`CompensationReport::lead_nudges`).
    pub lead_nudges: Option<u32>,
    pub settled_at_s: Option<f64>,
    pub faithful_band_hz: Option<f64>,
    /// The band judged after the safe start only (`None`: the guard never armed).
    pub faithful_band_after_safe_start_hz: Option<f64>,
    pub guard_active_s: f64,
    pub guard_max_damping_ns_per_m: f64,
}

/// The setpoints the emulator of an in-process run published, rebuilt from its records
/// with the rig's measured force and state.
fn setpoints(run: &InProcessRun) -> Vec<ForceSetpoint> {
    run.emulator
        .iter()
        .enumerate()
        .map(|(i, e)| ForceSetpoint {
            sequence: i as u64,
            sample_sequence: e.sample_seq,
            sample_publish_time_ns: 0,
            loop_time_ns: 0,
            law: LocalLaw {
                force_n: e.force_n,
                displacement_m: e.z_used_m,
                stiffness_n_per_m: e.law_stiffness_n_per_m,
                damping_ns_per_m: e.law_damping_ns_per_m,
                force_rate_n_per_s: e.law_force_rate_n_per_s,
                ..LocalLaw::default()
            },
            emulator_state: emulator_state::RUNNING,
            fault_code: 0,
            model_flags: 0,
            rig_state: e.rig_state,
            measured_force_n: e.rig_force_n,
            // Not in the emulator's records: the first contact falls back to the ratio
            // of measured to element force (the timing is the same).
            commanded_force_n: f64::NAN,
        })
        .collect()
}

/// Times `on_setpoint` with and without compensation over `rounds` alternating rounds.
pub fn controller_work(cfg: &HilConfig, rounds: usize) -> ControllerWork {
    let run = run_in_process(
        cfg,
        &InProcessScript {
            max_steps: (4.0 * cfg.loop_.rate_hz) as u64,
            command_delay_periods: 1,
            ..InProcessScript::default()
        },
    );
    let sps = setpoints(&run);
    let period_ns = cfg.loop_.period_ns;
    let mut with = Histogram::<u64>::new_with_bounds(1, 1_000_000_000, 3).expect("bounds");
    let mut without = with.clone();
    let mut off = cfg.compensation;
    off.adapt = false;
    off.passivity_guard = false;
    for round in 0..rounds.max(1) * 2 {
        let on = round % 2 == 0;
        let mut core = ControllerCore::new(
            cfg.controller,
            cfg.safety.actions,
            period_ns,
            (cfg.safety.stall_limit_s * 1e9) as u64,
        )
        .with_compensation(if on { cfg.compensation } else { off });
        for (k, sp) in sps.iter().enumerate() {
            let now = k as u64 * period_ns;
            let t0 = Instant::now();
            let out = core.on_setpoint(sp, now);
            let ns = t0.elapsed().as_nanos() as u64;
            std::hint::black_box(out);
            let h = if on { &mut with } else { &mut without };
            h.saturating_record(ns.max(1));
        }
    }
    ControllerWork {
        commands: sps.len() as u64,
        with_compensation: timing(&with),
        without: timing(&without),
    }
}

/// One in-process run of `cfg` for `duration_s`, summarised.
pub fn fidelity_cell(cfg: &HilConfig, actuator: &str, duration_s: f64) -> FidelityCell {
    fidelity_cell_recorded(cfg, actuator, duration_s, None)
        .expect("a run without records cannot fail to write them")
}

/// As [`fidelity_cell`], and with `records = Some((dir, config_text))` the run's records
/// written to `dir` as a `fastemu hil` run's (`records.mcap`, for `export`, `replay`,
/// `diagnose --run`).
pub fn fidelity_cell_recorded(
    cfg: &HilConfig,
    actuator: &str,
    duration_s: f64,
    records: Option<(&std::path::Path, &str)>,
) -> anyhow::Result<FidelityCell> {
    let run = run_in_process(
        cfg,
        &InProcessScript {
            max_steps: (duration_s * cfg.loop_.rate_hz) as u64,
            command_delay_periods: 1,
            ..InProcessScript::default()
        },
    );
    if let Some((dir, text)) = records {
        std::fs::create_dir_all(dir)
            .map_err(|e| anyhow::anyhow!("cannot create {}: {e}", dir.display()))?;
        run.write_records(dir, cfg, text)
            .map_err(|e| anyhow::anyhow!("{}: {}", e.path, e.message))?;
    }
    let fault = run
        .events
        .iter()
        .find(|e| e.kind == event_kind::FAULT)
        .map(|e| crate::hil::fault::fault_code_name(e.fault_code));
    // The displacement error up to the first hold (the reference has none).
    let reference = reference_displacement_m(cfg, run.rig.len());
    let (mut e2, mut r2) = (0.0, 0.0);
    for r in run
        .rig
        .iter()
        .take_while(|r| r.state == crate::ipc::messages::rig_state::RUNNING)
    {
        let x_ref = reference[r.step_idx as usize];
        e2 += (r.x_m - x_ref).powi(2);
        r2 += x_ref * x_ref;
    }
    let mut analyser = CompensationAnalyser::new(cfg.loop_.dt_s(), duration_s);
    for r in &run.controller {
        analyser.controller(r);
    }
    for r in &run.emulator {
        analyser.emulator(r);
    }
    // Judged as planned, as `fastemu hil` judges a run (the plan's fixed lead and nudge).
    let mut as_planned = cfg.clone();
    as_planned.compensation = crate::hil::check::planned(&cfg.compensation, run.plan.as_ref());
    let mut c = analyser.finish(&as_planned);
    if let Some(mut settled) = crate::hil::report::compensation::SettledRendering::after(&c) {
        for r in &run.emulator {
            settled.emulator(r);
        }
        settled.finish(cfg.loop_.dt_s(), &mut c);
    }
    Ok(FidelityCell {
        actuator: actuator.to_string(),
        initial_delay_us: cfg.compensation.initial_delay_s * 1e6,
        planned_lead_us: run
            .plan
            .as_ref()
            .filter(|p| p.lead_fixed)
            .map(|p| p.lead_us),
        planned_start_us: run
            .plan
            .as_ref()
            .filter(|p| !p.lead_fixed && p.start_moved_from_us.is_some())
            .map(|p| p.lead_us),
        fault,
        displacement_error_pct: if r2 > 0.0 {
            (e2 / r2).sqrt() * 100.0
        } else {
            f64::NAN
        },
        identified_delay_us: c.identified_delay_us,
        identified_from: c.identified_from,
        lead_estimate_us: c.lead_estimate_us,
        record_delay_us: c.record_delay.map(|d| d.mean_us),
        truth_delay_us: {
            let k = cfg
                .model
                .element
                .high_frequency_stiffness_n_per_m(cfg.scenario.preload_n);
            let plant = crate::rig::actuator::ActuatorPlant::from_config(&cfg.rig.actuator);
            (plant.effective_delay(k).delay_s + 0.5 * cfg.loop_.dt_s()) * 1e6
        },
        final_lead_us: c.final_lead_us,
        lead_nudges: c.lead_nudges,
        settled_at_s: c.settled_at_s,
        faithful_band_hz: c.faithful_band_hz,
        faithful_band_after_safe_start_hz: c.faithful_band_after_safe_start_hz,
        guard_active_s: c.guard.active_s,
        guard_max_damping_ns_per_m: c.guard.max_damping_ns_per_m,
    })
}

/// The fidelity table as text.
pub fn fidelity_table(cells: &[FidelityCell]) -> String {
    let mut s = String::from(
        "| actuator | initial delay, us | fault | displacement error, % | identified delay, us | the lead's estimate, us | the record's delay, us | truth, us | settled at, s | faithful band, Hz | after the safe start, Hz | guard active, s | guard max, kN s/m |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
    );
    let opt =
        |v: Option<f64>, digits: usize| v.map_or("-".to_string(), |x| format!("{x:.digits$}"));
    for c in cells {
        s.push_str(&format!(
            "| {} | {} | {} | {:.3} | {} | {} | {} | {:.0} | {} | {} | {} | {:.2} | {:.1} |\n",
            c.actuator,
            match (c.planned_lead_us, c.lead_nudges) {
                (Some(lead), Some(n)) if n > 0 => format!(
                    "{:.0} (planned: fixed {lead:.0}, stepped {n}x to {:.0})",
                    c.initial_delay_us, c.final_lead_us
                ),
                (Some(lead), _) => format!("{:.0} (planned: fixed {lead:.0})", c.initial_delay_us),
                (None, _) => match c.planned_start_us {
                    Some(start) => format!("{:.0} (planned: start {start:.0})", c.initial_delay_us),
                    None => format!("{:.0}", c.initial_delay_us),
                },
            },
            c.fault.as_deref().unwrap_or("none"),
            c.displacement_error_pct,
            match (c.identified_delay_us, c.identified_from) {
                (Some(d), Some("lead-estimator")) => format!("{d:.0} (the lead's: no load band)"),
                (d, _) => opt(d, 0),
            },
            opt(c.lead_estimate_us, 0),
            opt(c.record_delay_us, 0),
            c.truth_delay_us,
            opt(c.settled_at_s, 2),
            opt(c.faithful_band_hz, 0),
            opt(c.faithful_band_after_safe_start_hz, 0),
            c.guard_active_s,
            c.guard_max_damping_ns_per_m * 1e-3,
        ));
    }
    s
}

/// The actuators to compare: the configuration's own, then every preset of the
/// simulated rig (`[rig.actuator] preset`, nominal values).
pub fn actuator_variants(cfg: &HilConfig) -> Vec<(String, HilConfig)> {
    use crate::rig::actuator::{ActuatorParams, PRESETS};
    let own = format!(
        "config: {}",
        cfg.rig
            .actuator
            .preset
            .unwrap_or(cfg.rig.actuator.nominal.kind.name())
    );
    let mut out = vec![(own, cfg.clone())];
    for p in PRESETS {
        if Some(p.name) == cfg.rig.actuator.preset {
            continue;
        }
        let mut c = cfg.clone();
        c.rig.actuator.nominal = ActuatorParams::from_config_units(p.kind, p.values);
        c.rig.actuator.preset = Some(p.name);
        c.rig.actuator.perturb = 0.0;
        out.push((format!("{} ({})", p.name, p.kind.name()), c));
    }
    out
}
