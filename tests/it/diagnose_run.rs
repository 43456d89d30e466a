//! `fastemu diagnose --run`: a real `fastemu hil` run with the controller's delay
//! compensation mis-set (100 us too long), diagnosed from its records against the run's
//! own model.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::TempDir;

const FASTEMU: &str = env!("CARGO_BIN_EXE_fastemu");

/// Kills the child on drop (a failed assertion must not leave a loop running).
struct Guard(Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Runs `fastemu hil`; `Err` with its stderr when the run failed (a loop that tripped).
fn run_hil(config: &Path, out: &Path, duration_s: f64) -> Result<(), String> {
    let child = Command::new(FASTEMU)
        .args(["hil", "--config"])
        .arg(config)
        .arg("--out")
        .arg(out)
        .args(["--duration-s", &duration_s.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn fastemu hil");
    let mut guard = Guard(child);
    // The machine lock may make it wait for another run.
    let started = Instant::now();
    let status = loop {
        if let Some(status) = guard.0.try_wait().unwrap() {
            break status;
        }
        assert!(
            started.elapsed() < Duration::from_secs(400),
            "hil did not end"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut stderr = String::new();
    if let Some(mut pipe) = guard.0.stderr.take() {
        use std::io::Read;
        let _ = pipe.read_to_string(&mut stderr);
    }
    if status.success() {
        Ok(())
    } else {
        Err(format!("hil failed: {status:?}\n{stderr}"))
    }
}

fn diagnose_run(run_dir: &Path, out: &Path) -> serde_json::Value {
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

#[test]
fn a_compensation_delay_set_100_us_too_long_is_found_in_the_run_records() {
    let dir = TempDir::new("diagnose-run");
    let default = include_str!("../../configs/hil-default.toml");
    let knob = "compensation_delay_us = 252.0";
    assert!(default.contains(knob), "default config lacks `{knob}`");
    let config = dir.path.join("mis-set.toml");
    std::fs::write(
        &config,
        default.replace(knob, "compensation_delay_us = 352.0"),
    )
    .unwrap();
    // The loop's realised delay is what the records show: a run whose commands arrived
    // late (a loaded machine: held commands, stale samples) has a longer delay than the
    // one the compensation was tuned for, and diagnose rightly says so. The assertion on
    // the mis-set knob needs a run that kept its timing; up to three runs are made.
    let _heavy = crate::common::cpu_heavy();
    let mut quiet_run = None;
    for attempt in 0..4 {
        if attempt > 0 {
            // Whatever loaded the machine may pass.
            std::thread::sleep(Duration::from_secs(15));
        }
        let run_dir = dir.path.join(format!("run-{attempt}"));
        // 6 s holds the whole coach passage of the default scenario (a record cut in the
        // middle of it compares badly at its ends).
        if let Err(e) = run_hil(&config, &run_dir, 6.0) {
            // A loop 100 us over-compensated on a loaded machine can trip; the trip is
            // the loop's business (hil_processes tests it), not the diagnosis'.
            eprintln!("run {attempt}: {e}");
            continue;
        }
        let summary = |file: &str, key: &str| -> u64 {
            let text = std::fs::read_to_string(run_dir.join(file)).unwrap();
            let json: serde_json::Value = serde_json::from_str(&text).unwrap();
            json[key].as_u64().unwrap()
        };
        let held = summary("rig-summary.json", "held_commands");
        let stale = summary("emulator-summary.json", "stale_samples");
        // The run's own fidelity (hil's summary): quiet runs here keep 0.3-1 %; runs that
        // shared the cores with another test binary reached 1.5-1.7 % and their records
        // were dominated by the disturbances (a 3-4 % residual that no delay explains).
        let text = std::fs::read_to_string(run_dir.join("summary.json")).unwrap();
        let run_summary: serde_json::Value = serde_json::from_str(&text).unwrap();
        let fidelity = run_summary["fidelity"]["displacement_rel_rms"]
            .as_f64()
            .unwrap_or(f64::INFINITY);
        eprintln!(
            "run {attempt}: {held} held commands, {stale} stale samples, displacement error {fidelity:.4}"
        );
        if held < 200 && stale < 200 && fidelity < 0.012 {
            quiet_run = Some(run_dir);
            break;
        }
    }
    let run_dir =
        quiet_run.expect("no run kept its timing (below 1 % held commands) in three tries");
    let json = diagnose_run(&run_dir, &dir.path.join("diagnosis"));
    eprintln!("{json:#}");
    let effects: Vec<&str> = json["effects"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|e| e.as_str())
        .collect();
    assert!(effects.contains(&"channel-delay"), "{json}");
    let lag_s = json["force_lag_s"].as_f64().expect("a fitted lag");
    // On main the applied force leads by 85 us at +100 us and 135 us at +150 us.
    // A loaded machine lengthens the loop and shortens the lead: the range is wide.
    assert!((-200e-6..-30e-6).contains(&lag_s), "lag {lag_s}");
    let advice = json["advice"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|a| a.as_str())
        .find(|a| a.contains("compensation_delay_us"))
        .expect("advice on the delay knob");
    assert!(
        advice.starts_with("applied force leads the emulated force by")
            && advice.contains("compensation_delay_us (352 us) is about")
            && advice.ends_with("too long"),
        "{advice}"
    );
    assert!(dir.path.join("diagnosis/histories.png").is_file());
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
        stderr.contains(&dir.path.display().to_string()) && stderr.contains("no rig.csv"),
        "{stderr}"
    );
}
