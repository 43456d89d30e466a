//! `fastemu identify` and `fastemu diagnose` end to end: Table 3 from Eq. 2 data, the
//! consistent-form force fit, and the SPEC 5 JSON shape.

use std::f64::consts::PI;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

use fastemu::ident::campaign::load_campaign;
use fastemu::ident::identify::identify_eq2;
use fastemu::model::equiv::{zener_eq2, TABLE2_FREQUENCIES_HZ, TABLE2_PRELOADS_N};
use fastemu::model::params::ZenerParams;

use crate::gen::{off_baseline_toml, standard_design, write_campaign, Noise, TestPoint, Truth};

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("fastemu-idcli-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A campaign whose k_eq/c_eq are exactly paper Eq. 2 with Table 3 on the Table 2 grid.
fn write_eq2_campaign(dir: &Path) {
    let length = 0.75;
    let per_metre = ZenerParams::paper_table3(1.0);
    let mut toml = format!("sample_length_m = {length}\n");
    for (i, &p) in TABLE2_PRELOADS_N.iter().enumerate() {
        for (j, &f) in TABLE2_FREQUENCIES_HZ.iter().enumerate() {
            let w = 2.0 * PI * f;
            let eq = zener_eq2(&per_metre, p, w);
            let (k, c) = (eq.k_eq_n_per_m * length, eq.c_eq_ns_per_m * length);
            let z_amp = 5e3 / k.hypot(w * c);
            let dt = 1.0 / (64.0 * f);
            let id = format!("P{i}F{j}");
            let mut csv = String::from("t_s,displacement_m,force_n\n");
            for n in 0..(4 * 64) {
                let t = n as f64 * dt;
                let z = z_amp * (w * t).cos();
                let force = p + k * z - c * z_amp * w * (w * t).sin();
                let _ = writeln!(csv, "{t:?},{:?},{force:?}", 1e-3 + z);
            }
            std::fs::write(dir.join(format!("{id}.csv")), csv).unwrap();
            let _ = write!(toml, "\n[[test]]\nid = \"{id}\"\nfile = \"{id}.csv\"\nkind = \"harmonic\"\npreload_n = {p:?}\namplitude_n = 5000.0\nfrequency_hz = {f:?}\n");
        }
    }
    std::fs::write(dir.join("campaign.toml"), toml).unwrap();
}

#[test]
fn the_paper_objective_on_eq2_data_recovers_table_3() {
    let dir = scratch("table3");
    write_eq2_campaign(&dir);
    let campaign = load_campaign(&dir).unwrap();
    let id = identify_eq2(&campaign, 64e3);
    let p = id.params_per_m;
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-4 * b.abs();
    assert!(close(p.k1_0_n_per_m, 62e6), "k1_0 {}", p.k1_0_n_per_m);
    assert!(close(p.k2_0_n_per_m, 9.6e6), "k2_0 {}", p.k2_0_n_per_m);
    assert!(close(p.c2_0_ns_per_m, 0.7e6), "c2_0 {}", p.c2_0_ns_per_m);
    assert!((p.chi - 0.21).abs() < 1e-4, "chi {}", p.chi);

    // The CLI: paper form, JSON summary, model file and plots.
    let out = dir.join("out");
    let output = Command::new(env!("CARGO_BIN_EXE_fastemu"))
        .args(["identify", "--form", "paper", "--json", "--campaign"])
        .arg(&dir)
        .arg("--out")
        .arg(out.join("m.toml"))
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let k1 = json["params"]["k1_0_n_per_m2"]["value"].as_f64().unwrap();
    assert!(close(k1, 62e6), "{k1}");
    assert!(json["params"]["chi"]["ci95"].is_array());
    let model = std::fs::read_to_string(out.join("m.toml")).unwrap();
    assert!(model.contains("form = \"paper\""));
    assert!(out.join("identify_keq_ceq.png").is_file() && out.join("identify_loops.png").is_file());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_force_fit_recovers_consistent_form_parameters_from_noisy_tests() {
    let dir = scratch("force-fit");
    let truth = Truth::paper_like();
    let design: Vec<TestPoint> = standard_design()
        .into_iter()
        .filter(|p| p.temperature_c == 23.0)
        .collect();
    write_campaign(&dir, &truth, &design, &Noise::typical(), 5);
    let output = Command::new(env!("CARGO_BIN_EXE_fastemu"))
        .args(["identify", "--json", "--campaign"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let value = |k: &str| json["params"][k]["value"].as_f64().unwrap();
    let se = |k: &str| json["params"][k]["standard_error"].as_f64().unwrap();
    for (key, expected) in [
        ("k1_0_n_per_m2", truth.k1_0_n_per_m2),
        ("k2_0_n_per_m2", truth.k2_0_n_per_m2),
        ("c2_0_ns_per_m2", truth.c2_0_ns_per_m2),
        ("chi", truth.chi),
    ] {
        let (v, s) = (value(key), se(key));
        assert!(
            (v - expected).abs() < 0.05 * expected,
            "{key}: {v} vs {expected}"
        );
        assert!(s > 0.0 && s < 0.05 * expected, "{key}: standard error {s}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn diagnose_json_follows_spec_5_and_says_what_is_not_identifiable() {
    let dir = scratch("diagnose-json");
    // The paper grid only: one amplitude and no temperature variation.
    let design: Vec<TestPoint> = standard_design().into_iter().take(20).collect();
    let truth = Truth {
        force_lag_s: 2e-4,
        ..Truth::paper_like()
    };
    write_campaign(&dir.join("campaign"), &truth, &design, &Noise::typical(), 3);
    std::fs::write(dir.join("baseline.toml"), off_baseline_toml(0.3)).unwrap();
    // A recorded passage rides along (a history test: SPEC 5.1 uses it in the gap).
    let (t, z, f) = crate::gen::simulate_passage(&truth, &crate::gen::Passage::rising(1)[0]);
    let mut history = String::from("t_s,displacement_m,force_n,extra\n");
    for i in 0..t.len() {
        let _ = writeln!(history, "{:?},{:?},{:?},0", t[i], z[i], f[i]);
    }
    std::fs::write(dir.join("campaign").join("passage.csv"), history).unwrap();
    let toml_path = dir.join("campaign").join("campaign.toml");
    let mut toml = std::fs::read_to_string(&toml_path).unwrap();
    toml.push_str("\n[[test]]\nid = \"passage\"\nfile = \"passage.csv\"\nkind = \"history\"\n");
    std::fs::write(&toml_path, toml).unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_fastemu"))
        .arg("diagnose")
        .arg("--campaign")
        .arg(dir.join("campaign"))
        .arg("--model")
        .arg(dir.join("baseline.toml"))
        .arg("--out")
        .arg(dir.join("out"))
        .arg("--json")
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    for key in [
        "effect",
        "effects",
        "gap_before",
        "gap_after",
        "metric",
        "candidates",
        "not_identifiable",
        "model_out",
        "unexplained",
    ] {
        assert!(json.get(key).is_some(), "missing {key}");
    }
    assert_eq!(json["history_tests"], serde_json::json!(["passage"]));
    assert_eq!(json["effect"], "channel-delay");
    assert_eq!(json["effects"], serde_json::json!(["channel-delay"]));
    let not_identifiable: Vec<&str> = json["not_identifiable"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    // One harmonic amplitude, but the passage spans amplitudes (SPEC 5.1).
    assert!(
        !not_identifiable.contains(&"amplitude-friction")
            && not_identifiable.contains(&"temperature-shift"),
        "{not_identifiable:?}"
    );
    for c in json["candidates"].as_array().unwrap() {
        assert!(c["effect"].is_string() && c["score"].is_f64() && c["params"].is_object());
    }
    let model_out = PathBuf::from(json["model_out"].as_str().unwrap());
    let spec = fastemu::model::file::load_model_file(&model_out).unwrap();
    let model = fastemu::model::effects::AugmentedModel::from_spec(&spec, "augmented").unwrap();
    assert!(model.find("channel-delay").is_some());
    for file in ["report.md", "gap_map.png", "loops.png", "keq_ceq.png"] {
        assert!(dir.join("out").join(file).is_file(), "{file}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn diagnose_checks_folds_and_out_before_the_analysis_and_reports_the_folds_used() {
    let dir = scratch("diag-args");
    write_eq2_campaign(&dir);
    let model = dir.join("base.toml");
    std::fs::write(
        &model,
        "form = \"consistent\"\nlength_m = 0.75\nk1_0_n_per_m2 = 62e6\nk2_0_n_per_m2 = 9.6e6\n\
         c2_0_ns_per_m2 = 0.7e6\nchi = 0.21\np0_n = 64e3\n",
    )
    .unwrap();
    let run = |out: &Path, folds: &str| {
        Command::new(env!("CARGO_BIN_EXE_fastemu"))
            .args(["diagnose", "--campaign"])
            .arg(&dir)
            .arg("--model")
            .arg(&model)
            .arg("--out")
            .arg(out)
            .args(["--folds", folds, "--json"])
            .output()
            .unwrap()
    };
    // One fold holds nothing out: an error, not a silent two.
    let out = run(&dir.join("d1"), "1");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("--folds 1"),
        "{stderr}"
    );
    // An --out that cannot be a directory fails before the analysis runs.
    let file = dir.join("taken");
    std::fs::write(&file, "").unwrap();
    let out = run(&file, "5");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("taken") && !stderr.contains("round"),
        "{stderr}"
    );
    // The metric names the folds used.
    let out = run(&dir.join("d3"), "3");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(
        json["metric"].as_str().unwrap().contains("3-fold"),
        "{}",
        json["metric"]
    );
    let _ = std::fs::remove_dir_all(&dir);
}
