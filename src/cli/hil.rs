//! `fastemu hil`: the product's main command. Validates the config, runs the three
//! processes through the orchestrator, analyses their records, writes the report
//! directory and prints one JSON object with `--json`. Progress goes to stderr.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::Args;
use serde_json::json;

use crate::hil::config::{load_or_default, DEFAULT_CONFIG_TOML};
use crate::hil::orchestrator::{
    clear_stale_runs, install_signal_handlers, lock_machine, new_run_id, run_processes, RunPlan,
};
use crate::hil::report::{analyse_run, Analysis};
use crate::ipc::quiet_iceoryx2_logs;

#[derive(Debug, Clone, Args)]
pub struct HilArgs {
    /// HIL configuration (TOML); the embedded `configs/hil-default.toml` when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Print one JSON object with the results on stdout.
    #[arg(long)]
    pub json: bool,
    /// Report directory (default `out/hil-<UTC timestamp>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Overrides `[scenario] duration_s`.
    #[arg(long)]
    pub duration_s: Option<f64>,
}

/// `yyyymmddThhmmssZ` for a Unix time (UTC), without a date crate.
fn utc_timestamp(unix_s: u64) -> String {
    let days = (unix_s / 86_400) as i64;
    let secs = unix_s % 86_400;
    // Civil-from-days (H. Hinnant).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}{m:02}{d:02}T{:02}{:02}{:02}Z",
        secs / 3600,
        secs / 60 % 60,
        secs % 60
    )
}

fn read_json(path: &std::path::Path) -> serde_json::Value {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or(serde_json::Value::Null)
}

pub fn run(args: HilArgs) -> anyhow::Result<ExitCode> {
    install_signal_handlers();
    quiet_iceoryx2_logs();
    let mut cfg = load_or_default(args.config.as_deref())?;
    if let Some(d) = args.duration_s {
        anyhow::ensure!(
            d > 0.0 && d.is_finite(),
            "--duration-s {d}: expected a number > 0"
        );
        cfg.scenario.duration_s = d;
    }
    let out_dir = match &args.out {
        Some(d) => d.clone(),
        None => {
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs());
            let mut dir = PathBuf::from("out").join(format!("hil-{}", utc_timestamp(now)));
            if dir.exists() {
                dir = PathBuf::from("out").join(format!(
                    "hil-{}-{}",
                    utc_timestamp(now),
                    std::process::id()
                ));
            }
            dir
        }
    };
    std::fs::create_dir_all(&out_dir)
        .with_context(|| format!("cannot create report directory {}", out_dir.display()))?;
    let out_dir = out_dir.canonicalize().unwrap_or(out_dir);
    let config_path = match &args.config {
        Some(p) => p
            .canonicalize()
            .with_context(|| format!("cannot resolve {}", p.display()))?,
        None => {
            let p = out_dir.join("config.toml");
            std::fs::write(&p, DEFAULT_CONFIG_TOML)
                .with_context(|| format!("cannot write {}", p.display()))?;
            p
        }
    };
    let _machine_lock = lock_machine(std::time::Duration::from_secs(300), || {
        eprintln!("hil: waiting for another hil run on this machine to finish")
    })?;
    let stale = clear_stale_runs();
    if !stale.is_empty() {
        eprintln!(
            "hil: cleared stale state of crashed runs: {}",
            stale.join(", ")
        );
    }
    let run_id = new_run_id();
    let bin_dir = std::env::current_exe()?
        .parent()
        .map(PathBuf::from)
        .unwrap_or_default();
    let plan = RunPlan {
        run_id: run_id.clone(),
        config_path,
        out_dir: out_dir.clone(),
        duration_s: cfg.scenario.duration_s,
        duration_override_s: args.duration_s,
        bin_dir,
    };
    eprintln!(
        "hil: run {run_id}: {} s at {} Hz, report in {}",
        cfg.scenario.duration_s,
        cfg.loop_.rate_hz,
        out_dir.display()
    );
    let effect_names: Vec<&str> = cfg.augmented.effects.iter().map(|e| e.name()).collect();
    if !effect_names.is_empty() {
        eprintln!(
            "hil: the emulator runs the model's effects [{}] (rig artefacts channel-delay and moving-mass are left out); the fidelity reference integrates the base element only",
            effect_names.join(", ")
        );
    }
    let mut outcome = run_processes(&plan, true)?;
    // Process deaths first: they are the cause; the others' safe states follow from them.
    outcome.faults.sort_by_key(|f| !f.contains("process (pid"));

    let emu = read_json(&out_dir.join("emulator-summary.json"));
    let rig = read_json(&out_dir.join("rig-summary.json"));
    let ctl = read_json(&out_dir.join("controller-summary.json"));
    let analysis: Option<Analysis> = match analyse_run(&cfg, &out_dir) {
        Ok(a) => Some(a),
        Err(e) => {
            eprintln!("hil: no analysis: {e:#}");
            None
        }
    };
    let u =
        |v: &serde_json::Value, k: &str| v.get(k).and_then(serde_json::Value::as_u64).unwrap_or(0);
    // The product's fixed-step loop is the emulator's; the rig's misses (the simulated
    // hardware's own timing) are reported separately.
    let deadline_misses = u(&emu, "missed_deadlines");
    let steps = u(&emu, "model_steps");
    let stable = outcome.faults.is_empty() && analysis.as_ref().is_some_and(|a| a.stability.stable);
    let summary = json!({
        "rate_hz": cfg.loop_.rate_hz,
        "duration_s": cfg.scenario.duration_s,
        "steps": steps,
        "deadline_misses": deadline_misses,
        "deadline_misses_emulator": u(&emu, "missed_deadlines"),
        "deadline_misses_rig": u(&rig, "missed_deadlines"),
        "stale_samples": u(&emu, "stale_samples"),
        "records_dropped": u(&emu, "records_dropped") + u(&ctl, "records_dropped"),
        "stable": stable,
        "faults": outcome.faults,
        "fidelity": analysis.as_ref().map(|a| serde_json::to_value(&a.fidelity).unwrap_or_default()),
        "stability": analysis.as_ref().map(|a| serde_json::to_value(&a.stability).unwrap_or_default()),
        "latency_ns": analysis.as_ref().map(|a| serde_json::to_value(&a.latency_ns).unwrap_or_default()),
        "model": {
            "form": cfg.model.element.form().name(),
            "length_m": cfg.model.length_m,
            "effects": effect_names,
        },
        "compensation": {
            "enabled": cfg.controller.compensation_enabled,
            "order": cfg.controller.compensation_order,
            "delay_us": cfg.controller.compensation_delay_s * 1e6,
        },
        "processes": {"bench_rig": rig, "emulator": emu, "controller": ctl, "exit": outcome.exit_statuses},
        "leftover_files_removed": outcome.leftover_files.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "run_id": run_id,
        "report_dir": out_dir.display().to_string(),
    });
    let text = serde_json::to_string_pretty(&summary)?;
    std::fs::write(out_dir.join("summary.json"), &text)?;
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    }
    if let Some(a) = &analysis {
        eprintln!(
            "hil: {steps} steps, {deadline_misses} deadline misses, {} stale samples, displacement rel. RMS error {:.3} %, stable {}, end-to-end p50 {} us p99 {} us",
            u(&emu, "stale_samples"),
            a.fidelity.displacement_rel_rms * 100.0,
            a.stability.stable,
            a.latency_ns.end_to_end.p50 / 1000,
            a.latency_ns.end_to_end.p99 / 1000
        );
    }
    if !outcome.faults.is_empty() {
        eprintln!("hil: FAILED: {}", outcome.faults.join("; "));
        return Ok(ExitCode::from(2));
    }
    if !stable {
        eprintln!("hil: FAILED: the loop was not stable (see stability in summary.json)");
        return Ok(ExitCode::from(1));
    }
    eprintln!("hil: report in {}", out_dir.display());
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    #[test]
    fn timestamp_is_utc_civil_time() {
        assert_eq!(super::utc_timestamp(0), "19700101T000000Z");
        assert_eq!(super::utc_timestamp(1_700_000_000), "20231114T221320Z");
    }
}
