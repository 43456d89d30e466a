//! `fastemu synth-campaign`: the newcomer's first run, end to end through the CLI.

use std::process::Command;

use crate::common::TempDir;

const FASTEMU: &str = env!("CARGO_BIN_EXE_fastemu");

#[test]
fn a_synthetic_campaign_is_diagnosed_and_its_truth_kept_apart() {
    let _heavy = crate::common::cpu_heavy();
    let dir = TempDir::new("synth");
    let campaign = dir.path.join("demo");
    let status = Command::new(FASTEMU)
        .args([
            "synth-campaign",
            "--hidden",
            "moving-mass",
            "--seed",
            "3",
            "--out",
        ])
        .arg(&campaign)
        .status()
        .unwrap();
    assert!(status.success());
    let toml = std::fs::read_to_string(campaign.join("campaign.toml")).unwrap();
    assert!(!toml.contains("file = \"truth"), "a test reads the truth");
    assert_eq!(toml.matches("kind = \"history\"").count(), 3);
    assert_eq!(toml.matches("started_at").count(), 44);
    let truth = std::fs::read_to_string(campaign.join("truth.toml")).unwrap();
    assert!(truth.contains("name = \"moving-mass\""));
    let output = Command::new(FASTEMU)
        .args(["diagnose", "--json", "--campaign"])
        .arg(&campaign)
        .arg("--model")
        .arg(campaign.join("baseline.toml"))
        .arg("--out")
        .arg(dir.path.join("diagnosis"))
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(
        json["effects"],
        serde_json::json!(["moving-mass"]),
        "{json}"
    );
    assert!(json["unexplained"].is_null(), "{json}");
    assert_eq!(json["history_tests"].as_array().unwrap().len(), 3);
    assert!(dir.path.join("diagnosis/histories.png").is_file());
    // The report's opening lines (before its first section) say what was named, whether
    // a residual remains and whether the specimen changed, as the README promises.
    let report = std::fs::read_to_string(dir.path.join("diagnosis/report.md")).unwrap();
    let opening = report.split("\n## ").next().unwrap();
    assert_eq!(json["specimen_changed"], serde_json::json!(false), "{json}");
    for line in [
        "- **Named effects: moving-mass**",
        "- Unexplained residual: ",
        "- Specimen: no change beyond noise during the campaign",
    ] {
        assert!(opening.contains(line), "{line}\n{opening}");
    }
}

#[test]
fn an_unknown_hidden_effect_is_refused_with_the_choices() {
    let dir = TempDir::new("synth-bad");
    let output = Command::new(FASTEMU)
        .args(["synth-campaign", "--hidden", "gremlins", "--out"])
        .arg(dir.path.join("x"))
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("--hidden gremlins") && stderr.contains("load-path-resonance"),
        "{stderr}"
    );
}
