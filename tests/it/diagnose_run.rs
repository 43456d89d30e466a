//! `fastemu diagnose --run`: a run of the deterministic in-process loop with the rig's
//! law lead mis-set, written as a `fastemu hil` run writes its records and diagnosed from
//! them against the run's own model; the same with plain force commands and the
//! controller's compensation delay mis-set; the run with the lead right as the control.
//! (In process, so that the loop's delay is the configured one: a real run on a loaded
//! machine adds its own, which is the diagnosis' business to report but not this test's.)

use std::path::Path;
use std::process::Command;

use fastemu::hil::config::{parse_hil_config, HilConfig};
use fastemu::hil::inproc::{run_in_process, InProcessRun, InProcessScript};
use fastemu::records::event::event_kind;

use crate::common::TempDir;

const FASTEMU: &str = env!("CARGO_BIN_EXE_fastemu");
const DEFAULT: &str = include_str!("../../configs/hil-default.toml");
const KNOB: &str = "initial_delay_us = 252.0";

/// Runs the default passage in process with the controller's lead fixed at `lead_us`
/// (`[compensation] initial_delay_us`, adaptation off) and writes its records to
/// `run_dir`.
fn recorded_run(run_dir: &Path, lead_us: f64) -> Recorded {
    recorded_run_with(
        run_dir,
        &[
            (KNOB, &format!("initial_delay_us = {lead_us:.1}")),
            ("adapt = true", "adapt = false"),
        ],
    )
}

/// An in-process run with the configuration it ran.
struct Recorded {
    run: InProcessRun,
    cfg: HilConfig,
    text: String,
}

/// Runs the default passage in process with the given replacements of the default
/// configuration's text and writes its records to `run_dir`.
fn recorded_run_with(run_dir: &Path, replacements: &[(&str, &str)]) -> Recorded {
    let mut text = DEFAULT.to_string();
    for (from, to) in replacements {
        assert!(text.contains(from), "default config lacks `{from}`");
        text = text.replace(from, to);
    }
    let cfg = parse_hil_config(&text, "lead.toml", None).unwrap();
    let script = InProcessScript {
        // 6 s passage, then the end and the unload.
        max_steps: (8.0 * cfg.loop_.rate_hz) as u64,
        // The rig applies a command one period after it was sent: the 252 us the
        // default lead compensates at 4096 Hz (244 us) plus the actuator's few us.
        command_delay_periods: 1,
        ..InProcessScript::default()
    };
    let run = run_in_process(&cfg, &script);
    let faults: Vec<_> = run
        .events
        .iter()
        .filter(|e| e.kind == event_kind::FAULT)
        .collect();
    assert!(faults.is_empty(), "{faults:?}");
    run.write_records(run_dir, &cfg, &text).unwrap();
    Recorded { run, cfg, text }
}

fn diagnose(run_dir: &Path, out: &Path) -> serde_json::Value {
    let output = Command::new(FASTEMU)
        .args(["diagnose", "--json", "--run"])
        .arg(run_dir)
        .arg("--out")
        .arg(out)
        .output()
        .expect("run fastemu diagnose");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).expect("one JSON object")
}

fn effects(json: &serde_json::Value) -> Vec<String> {
    json["effects"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|e| e.as_str().map(str::to_string))
        .collect()
}

/// A named channel delay whose applied force leads by about 125 us (-160..-90 us), and
/// the advice that names `knob`.
fn named_lead_and_advice(json: &serde_json::Value, knob: &str) -> (f64, String) {
    eprintln!("{json:#}");
    assert!(effects(json).contains(&"channel-delay".into()), "{json}");
    let lag_s = json["force_lag_s"].as_f64().expect("a fitted lag");
    assert!((-160e-6..-90e-6).contains(&lag_s), "lag {lag_s}");
    let advice = json["advice"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|a| a.as_str())
        .find(|a| a.contains(knob))
        .unwrap_or_else(|| panic!("no advice on {knob}: {json}"));
    (lag_s, advice.to_string())
}

#[test]
fn a_law_lead_set_125_us_too_long_is_named_from_the_run_records() {
    let dir = TempDir::new("diagnose-run");
    let run_dir = dir.path.join("run");
    let recorded = recorded_run(&run_dir, 377.0);
    assert!(run_dir.join("records.mcap").is_file());
    let json = diagnose(&run_dir, &dir.path.join("diagnosis"));
    // The applied force leads by the 125 us the lead is too long (the law's extrapolation
    // is second order, so not exactly).
    let (lag_s, advice) = named_lead_and_advice(&json, "initial_delay_us");
    assert!(
        advice.starts_with("applied force leads the emulated force by")
            && advice.contains("[compensation] initial_delay_us (377 us) is about")
            && advice.ends_with("too long"),
        "{advice}"
    );
    assert!(
        json["record_used"]
            .as_str()
            .unwrap()
            .starts_with("all 24576 rig periods"),
        "{json}"
    );
    assert!(dir.path.join("diagnosis/histories.png").is_file());

    // The records exported as CSV (`fastemu export`) give the same diagnosis.
    export_csv(&run_dir, &dir.path.join("csv"));
    let from_csv = diagnose(&dir.path.join("csv"), &dir.path.join("diagnosis-csv"));
    assert_eq!(from_csv["effects"], json["effects"]);
    let lag_csv = from_csv["force_lag_s"].as_f64().unwrap();
    assert!((lag_csv - lag_s).abs() < 1e-6, "{lag_csv} vs {lag_s}");

    // The same session as an external rig's (no /rig records): the emulator's record of
    // its samples (measured displacement and force) tells the same, and the advice names
    // the rig's own lead.
    let external_dir = dir.path.join("external");
    let external = InProcessRun {
        rig: Vec::new(),
        ..recorded.run.clone()
    };
    external
        .write_records(&external_dir, &recorded.cfg, &recorded.text)
        .unwrap();
    let from_samples = diagnose(&external_dir, &dir.path.join("diagnosis-external"));
    assert_eq!(from_samples["effects"], json["effects"], "{from_samples}");
    let lag_ext = from_samples["force_lag_s"].as_f64().unwrap();
    assert!((lag_ext - lag_s).abs() < 2e-6, "{lag_ext} vs {lag_s}");
    assert!(
        from_samples["record_used"]
            .as_str()
            .unwrap()
            .contains("an external rig (no /rig records)"),
        "{from_samples}"
    );
    assert!(
        from_samples["advice"].as_array().unwrap().iter().any(|a| a
            .as_str()
            .unwrap()
            .contains("the lead the external rig applied")),
        "{from_samples}"
    );
}

#[test]
fn injected_bad_samples_end_the_stretch_that_is_diagnosed() {
    // A NaN sample injected at 3 s: the emulator trips and the rig holds; the diagnosis
    // uses the periods before the bad sample only, never the sample itself.
    let dir = TempDir::new("diagnose-run-nan");
    let run_dir = dir.path.join("run");
    let mut text = DEFAULT.to_string();
    text.push_str("\n[[inject]]\nprocess = \"rig\"\nkind = \"nan\"\nat_s = 3.0\n");
    let cfg = parse_hil_config(&text, "nan.toml", None).unwrap();
    let script = InProcessScript {
        max_steps: (8.0 * cfg.loop_.rate_hz) as u64,
        command_delay_periods: 1,
        ..InProcessScript::default()
    };
    let run = run_in_process(&cfg, &script);
    let bad = run
        .rig
        .iter()
        .position(|r| !r.z_measured_m.is_finite())
        .expect("the injected NaN in the rig's record");
    run.write_records(&run_dir, &cfg, &text).unwrap();
    let json = diagnose(&run_dir, &dir.path.join("diagnosis"));
    let used = json["record_used"].as_str().unwrap();
    assert!(
        used.starts_with(&format!("rig periods 0 to {} of ", bad - 1)),
        "{used} (bad sample at row {bad})"
    );
    assert!(json["gap_before"].as_f64().unwrap().is_finite(), "{json}");
}

#[test]
fn plain_force_commands_with_a_compensation_delay_125_us_too_long_are_named() {
    let dir = TempDir::new("diagnose-run-force");
    let run_dir = dir.path.join("run");
    recorded_run_with(
        &run_dir,
        &[
            ("command_mode = \"law\"", "command_mode = \"force\""),
            (
                "compensation_delay_us = 252.0",
                "compensation_delay_us = 377.0",
            ),
        ],
    );
    let json = diagnose(&run_dir, &dir.path.join("diagnosis"));
    // The controller's extrapolation (order 3) of the force over 125 us too many.
    let (_, advice) = named_lead_and_advice(&json, "compensation_delay_us");
    assert!(
        advice.contains("[controller] compensation_delay_us (377 us) is about")
            && advice.ends_with("too long"),
        "{advice}"
    );
}

#[test]
fn a_law_lead_that_matches_the_loop_names_no_delay() {
    let dir = TempDir::new("diagnose-run-control");
    let run_dir = dir.path.join("run");
    recorded_run(&run_dir, 252.0);
    let json = diagnose(&run_dir, &dir.path.join("diagnosis"));
    eprintln!("{json:#}");
    assert!(!effects(&json).contains(&"channel-delay".into()), "{json}");
    // The advice says nothing was found; it names no knob to turn.
    let advice = json["advice"].as_array().unwrap();
    assert_eq!(advice.len(), 1, "{json}");
    let advice = advice[0].as_str().unwrap();
    assert!(advice.starts_with("no loop artefact found"), "{advice}");
    assert!(!advice.contains("initial_delay_us") && !advice.contains("compensation_delay_us"));
}

#[test]
fn a_directory_without_run_records_is_refused_with_its_name() {
    let dir = TempDir::new("diagnose-run-empty");
    let output = Command::new(FASTEMU)
        .args(["diagnose", "--run"])
        .arg(&dir.path)
        .arg("--out")
        .arg(dir.path.join("out"))
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains(&dir.path.display().to_string()) && stderr.contains("no records"),
        "{stderr}"
    );
    // The --out directory it made for the analysis is gone again.
    assert!(!dir.path.join("out").exists());
}

/// A run whose model heats itself (`self-heating`, a small, poorly cooled pad): the
/// element's temperature rise is in the emulator's records, rises while the passage
/// dissipates, and `diagnose --run` replays it and names no loop artefact.
#[test]
fn a_self_heating_element_warms_in_the_records_and_no_loop_artefact_is_named() {
    let dir = TempDir::new("diagnose-run-heating");
    let run_dir = dir.path.join("run");
    let heating = "chi = 0.21\np0_n = 64e3\n\n[[model.effect]]\nname = \"self-heating\"\nheat_capacity_j_per_k = 1.0\nheat_transfer_w_per_k = 0.01\ntemperature_rise_k = 0.0\n";
    let recorded = recorded_run_with(
        &run_dir,
        &[
            ("chi = 0.21\np0_n = 64e3\n", heating),
            ("adapt = true", "adapt = false"),
        ],
    );
    let rises: Vec<f64> = recorded
        .run
        .emulator
        .iter()
        .map(|r| r.element_temperature_rise_k)
        .collect();
    let last = *rises.last().unwrap();
    assert!(rises.iter().all(|r| r.is_finite() && *r >= 0.0));
    // It warms: by the end of the run, and monotonically at the scale of a second (the
    // time constant is 100 s: it barely cools).
    assert!(last > 0.05, "rise at the end {last} K");
    let per_second = (recorded.cfg.loop_.rate_hz) as usize;
    for pair in rises.chunks(per_second).collect::<Vec<_>>().windows(2) {
        assert!(pair[1][0] >= pair[0][0] - 1e-9, "cooled within a second");
    }
    let json = diagnose(&run_dir, &dir.path.join("diagnosis"));
    assert!(effects(&json).is_empty(), "{json}");
    let max = json["element_temperature_rise_k"]["max"]
        .as_f64()
        .expect("recorded rise");
    assert!((max - rises.iter().copied().fold(0.0, f64::max)).abs() < 1e-9);
    let report = std::fs::read_to_string(dir.path.join("diagnosis/report.md")).unwrap();
    assert!(report.contains("Element temperature"), "{report}");
}

/// A pad that heats strongly (the passage warms it by kelvins within seconds): the run's
/// report states the warming as the records hold it, and the offline reference warms the same way, so the
/// fidelity measures the loop and not the softening (against the plain element the
/// softening alone would be percent).
#[test]
fn a_strongly_self_heating_run_reports_its_warming_and_stays_faithful() {
    let dir = TempDir::new("hil-report-heating");
    let run_dir = dir.path.join("run");
    let heating = "chi = 0.21\np0_n = 64e3\n\n[[model.effect]]\nname = \"self-heating\"\nheat_capacity_j_per_k = 1.5\nheat_transfer_w_per_k = 0.015\ntemperature_rise_k = 0.0\n";
    let recorded = recorded_run_with(&run_dir, &[("chi = 0.21\np0_n = 64e3\n", heating)]);
    let rises: Vec<(f64, f64)> = recorded
        .run
        .emulator
        .iter()
        .map(|r| (r.t_s, r.element_temperature_rise_k))
        .collect();
    let analysis = fastemu::hil::report::analyse_run(&recorded.cfg, &run_dir).unwrap();
    let thermal = analysis
        .element_thermal
        .expect("self-heating in the report");
    let (t_max, max) =
        rises.iter().copied().fold(
            (0.0, f64::NEG_INFINITY),
            |a, b| if b.1 > a.1 { b } else { a },
        );
    assert_eq!(thermal.rise_end_k, rises.last().unwrap().1);
    assert_eq!((thermal.rise_max_at_s, thermal.rise_max_k), (t_max, max));
    assert!(max > 2.0, "the pad warmed only {max} K");
    // The thermal balance's power is what heated it: positive, and the steady rise it
    // implies (P / h) is above the largest rise reached (still warming, tau = 100 s).
    assert!(thermal.mean_power_w > 0.0);
    assert!(thermal.mean_power_w / thermal.heat_transfer_w_per_k > max);
    let expected = (-0.008 * (thermal.rise_end_k - thermal.rise_start_k)).exp();
    assert!((thermal.modulus_factor_end - expected).abs() < 1e-12);
    assert!(thermal.modulus_factor_end < 0.985);
    assert!(run_dir.join("element.png").exists());
    // The reference heats as the emulated element does: the loop's own error is left.
    let error = analysis.fidelity.displacement_rel_rms;
    assert!(error < 1e-3, "displacement error {error}, {thermal:?}");
}

/// `bench compensation --records` writes each fidelity run's records as a `fastemu hil`
/// run's: `export` reads them, and the lead the controller recorded last is the one the
/// bench's summary reports.
#[test]
fn bench_compensations_records_are_read_as_a_runs() {
    let dir = TempDir::new("bench-comp-records");
    let out = Command::new(FASTEMU)
        .args([
            "bench",
            "compensation",
            "--only-config",
            "--guess-us",
            "100",
            "--rounds",
            "1",
            "--duration-s",
            "1",
            "--json",
            "--records",
        ])
        .arg(dir.path.join("recs"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let cell = &json["fidelity"][0];
    let run_dir = dir.path.join("recs/config__lag-delay-100us");
    assert!(run_dir.join("records.mcap").is_file());
    export_csv(&run_dir, &dir.path.join("csv"));
    let text = std::fs::read_to_string(dir.path.join("csv/controller.csv")).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let lead_col = header.iter().position(|c| *c == "lead_s").unwrap();
    let rows: Vec<&str> = lines.collect();
    // One command per period of the 1 s programme at 4096 Hz (less the transport's few).
    assert!((4000..=4096).contains(&rows.len()), "{} rows", rows.len());
    let first: f64 = rows[0].split(',').nth(lead_col).unwrap().parse().unwrap();
    let last: f64 = rows[rows.len() - 1]
        .split(',')
        .nth(lead_col)
        .unwrap()
        .parse()
        .unwrap();
    // The run started at the guess (the plan keeps a guess the declaration finds stable
    // or moves it; either way it is what the summary says it started at) ...
    let started_us = cell["planned_start_us"].as_f64().unwrap_or(100.0);
    assert!((first * 1e6 - started_us).abs() < 1e-6, "{first} vs {cell}");
    // ... and ended at the lead the summary reports.
    let final_us = cell["final_lead_us"].as_f64().unwrap();
    assert!((last * 1e6 - final_us).abs() < 1e-3, "{last} vs {final_us}");
}

/// `fastemu export --record run_dir --out out`, which must succeed.
fn export_csv(run_dir: &std::path::Path, out: &std::path::Path) {
    let export = Command::new(FASTEMU)
        .args(["export", "--record"])
        .arg(run_dir)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(
        export.status.success(),
        "{}",
        String::from_utf8_lossy(&export.stderr)
    );
}
