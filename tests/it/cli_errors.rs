//! The `fastemu` binary's error paths and output shapes (SPEC 2.3 contract), run as a
//! user would run it. Errors must exit non-zero and name the file and key or line.

use std::path::Path;
use std::process::{Command, Output};

use crate::common::{path_str, TempDir};

const CONSISTENT_MODEL: &str = "form = \"consistent\"\nlength_m = 0.75\nk1_0_n_per_m2 = 62e6\n\
k2_0_n_per_m2 = 9.6e6\nc2_0_ns_per_m2 = 0.7e6\nchi = 0.21\np0_n = 64e3\n";
const KV_MODEL: &str =
    "form = \"kelvin-voigt\"\nlength_m = 1.0\nk_n_per_m2 = 80e6\nc_ns_per_m2 = 1e3\n";

fn fastemu(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fastemu"))
        .args(args)
        .output()
        .expect("run fastemu")
}

/// Runs `fastemu` expecting failure; every `needles` entry must appear in stderr.
fn assert_fails(args: &[&str], needles: &[&str]) {
    let out = fastemu(args);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "{args:?} succeeded; stderr: {stderr}"
    );
    for needle in needles {
        assert!(
            stderr.contains(needle),
            "{args:?}: stderr lacks {needle:?}:\n{stderr}"
        );
    }
    // One-line errors (SPEC 2.3).
    assert_eq!(stderr.trim_end().lines().count(), 1, "{args:?}: {stderr}");
}

fn displacement_csv(rows: usize) -> String {
    let mut s = String::from("t_s,displacement_m\n");
    for i in 0..rows {
        s.push_str(&format!("{},{}\n", i as f64 * 1e-3, 1e-4 * i as f64));
    }
    s
}

fn load_csv(rows: usize) -> String {
    let mut s = String::from("t_s,force_n\n");
    for i in 0..rows {
        s.push_str(&format!("{},{}\n", i as f64 * 1e-4, 55e3));
    }
    s
}

fn simulate_force(model: &Path, input: &Path, out: &Path) -> Vec<String> {
    [
        "simulate",
        "force",
        "--model",
        path_str(model),
        "--input",
        path_str(input),
        "--out",
        path_str(out),
    ]
    .map(String::from)
    .to_vec()
}

fn as_strs(args: &[String]) -> Vec<&str> {
    args.iter().map(String::as_str).collect()
}

/// Each broken model file: (label, text, words stderr must contain besides the path).
fn broken_models() -> Vec<(&'static str, String, Vec<&'static str>)> {
    let replace = |from: &str, to: &str| CONSISTENT_MODEL.replace(from, to);
    vec![
        (
            "missing-chi",
            replace("chi = 0.21\n", ""),
            vec!["missing key `chi`"],
        ),
        (
            "missing-form",
            replace("form = \"consistent\"\n", ""),
            vec!["missing key `form`"],
        ),
        (
            "missing-kv-c",
            KV_MODEL.replace("c_ns_per_m2 = 1e3\n", ""),
            vec!["c_ns_per_m2"],
        ),
        (
            "unknown-key",
            format!("{CONSISTENT_MODEL}k3_n_per_m2 = 1.0\n"),
            vec!["unknown key `k3_n_per_m2`"],
        ),
        (
            "kv-key-in-zener",
            format!("{CONSISTENT_MODEL}k_n_per_m2 = 1.0\n"),
            vec!["unknown key `k_n_per_m2`"],
        ),
        (
            "zero-k1",
            replace("k1_0_n_per_m2 = 62e6", "k1_0_n_per_m2 = 0"),
            vec!["k1_0_n_per_m2", "positive"],
        ),
        (
            "negative-k2",
            replace("k2_0_n_per_m2 = 9.6e6", "k2_0_n_per_m2 = -9.6e6"),
            vec!["k2_0_n_per_m2", "positive"],
        ),
        (
            "zero-c2",
            replace("c2_0_ns_per_m2 = 0.7e6", "c2_0_ns_per_m2 = 0.0"),
            vec!["c2_0_ns_per_m2", "positive"],
        ),
        (
            "negative-p0",
            replace("p0_n = 64e3", "p0_n = -64e3"),
            vec!["p0_n", "positive"],
        ),
        (
            "zero-length",
            replace("length_m = 0.75", "length_m = 0.0"),
            vec!["length_m", "positive"],
        ),
        (
            "nan-length",
            replace("length_m = 0.75", "length_m = nan"),
            vec!["length_m", "positive"],
        ),
        (
            "kv-zero-k",
            KV_MODEL.replace("k_n_per_m2 = 80e6", "k_n_per_m2 = 0"),
            vec!["k_n_per_m2", "positive"],
        ),
        (
            "kv-negative-c",
            KV_MODEL.replace("c_ns_per_m2 = 1e3", "c_ns_per_m2 = -1"),
            vec!["c_ns_per_m2", "positive"],
        ),
        (
            "chi-one",
            replace("chi = 0.21", "chi = 1.0"),
            vec!["chi", "[0, 1)"],
        ),
        (
            "chi-negative",
            replace("chi = 0.21", "chi = -0.1"),
            vec!["chi", "[0, 1)"],
        ),
        (
            "chi-string",
            replace("chi = 0.21", "chi = \"0.21\""),
            vec!["chi", "number"],
        ),
        (
            "bad-form",
            replace("\"consistent\"", "\"maxwell\""),
            vec!["form", "maxwell", "kelvin-voigt"],
        ),
        ("form-number", replace("\"consistent\"", "3"), vec!["form"]),
        (
            "malformed-toml",
            replace("chi = 0.21", "chi = = 0.21"),
            vec!["not valid TOML", "line 6"],
        ),
    ]
}

#[test]
fn broken_model_files_fail_naming_file_and_key() {
    let dir = TempDir::new("models");
    let input = dir.write("z.csv", &displacement_csv(10));
    let load = dir.write("load.csv", &load_csv(10));
    let out = dir.join("out.csv");
    for (label, text, needles) in broken_models() {
        let model = dir.write(&format!("{label}.toml"), &text);
        let mut expected = vec![path_str(&model)];
        expected.extend(&needles);
        assert_fails(&as_strs(&simulate_force(&model, &input, &out)), &expected);
        assert_fails(
            &[
                "simulate",
                "rail",
                "--model",
                path_str(&model),
                "--mass-kg",
                "60.21",
                "--input",
                path_str(&load),
                "--out",
                path_str(&out),
            ],
            &expected,
        );
        assert_fails(&["equiv", "--model", path_str(&model)], &expected);
        assert!(!out.exists(), "{label}: no output on error");
    }
    let missing = dir.join("no-such-model.toml");
    assert_fails(
        &["equiv", "--model", path_str(&missing)],
        &[path_str(&missing), "cannot read"],
    );
}

#[test]
fn broken_csv_inputs_fail_naming_file_line_and_column() {
    let dir = TempDir::new("csv");
    let model = dir.write("m.toml", CONSISTENT_MODEL);
    let out = dir.join("out.csv");
    let cases: Vec<(&str, String, Vec<String>)> = vec![
        (
            "not-a-number",
            displacement_csv(6).replace("0.0004\n", "0.0004x\n"),
            // Header is line 1, so the 5th data row (i = 4) is line 6, column 2.
            vec![":6:2:".into(), "displacement_m".into(), "0.0004x".into()],
        ),
        (
            "not-a-number-time",
            displacement_csv(6).replacen("0.002,", "abc,", 1),
            vec![":4:1:".into(), "t_s".into(), "not a number".into()],
        ),
        (
            "missing-column",
            displacement_csv(5).replace("displacement_m", "z_m"),
            vec![":1:".into(), "displacement_m".into()],
        ),
        (
            "short-row",
            displacement_csv(5).replacen("0.002,0.0002", "0.002", 1),
            vec![":4:".into()],
        ),
        (
            "non-uniform-step",
            displacement_csv(6).replacen("0.003,", "0.0031,", 1),
            vec![":5".into(), "uniform".into()],
        ),
        (
            "decreasing-time",
            displacement_csv(6).replacen("0.003,", "0.001,", 1),
            vec![":5".into(), "increase".into()],
        ),
        ("one-row", displacement_csv(1), vec!["at least two".into()]),
        (
            "header-only",
            displacement_csv(0),
            vec!["at least two".into()],
        ),
        ("empty", String::new(), vec!["empty".into()]),
        (
            "infinite",
            displacement_csv(4).replacen("0.0002", "inf", 1),
            vec![":4:2:".into(), "finite".into()],
        ),
        (
            "semicolons",
            displacement_csv(4).replace(',', ";"),
            vec![":1:".into(), "separated by `;`".into(), "commas".into()],
        ),
        (
            "tabs",
            displacement_csv(4).replace(',', "\t"),
            vec![":1:".into(), "separated by tab".into()],
        ),
        (
            "short-row-names-the-column",
            displacement_csv(5).replacen("0.002,0.0002", "0.002", 1),
            vec![":4:".into(), "lacks column `displacement_m`".into()],
        ),
        (
            // Blank lines do not shift the line named in the error (line 8 after two
            // blank lines, not line 6).
            "blank-lines-then-non-uniform",
            displacement_csv(6)
                .replacen("0.001,", "\n\n0.001,", 1)
                .replacen("0.004,", "0.0041,", 1),
            vec![":8".into(), "uniform".into()],
        ),
    ];
    for (label, text, needles) in cases {
        let input = dir.write(&format!("{label}.csv"), &text);
        let mut expected: Vec<&str> = vec![path_str(&input)];
        expected.extend(needles.iter().map(String::as_str));
        assert_fails(&as_strs(&simulate_force(&model, &input, &out)), &expected);
    }
    // The rail primitive reads `t_s,force_n` through the same reader.
    let input = dir.write("load-bad.csv", &load_csv(5).replacen("55000", "55 kN", 1));
    assert_fails(
        &[
            "simulate",
            "rail",
            "--model",
            path_str(&model),
            "--mass-kg",
            "60.21",
            "--input",
            path_str(&input),
            "--out",
            path_str(&out),
        ],
        &[path_str(&input), ":2:2:", "force_n"],
    );
    let input = dir.write("load-nocol.csv", "t_s,displacement_m\n0,0\n1,0\n");
    assert_fails(
        &[
            "simulate",
            "rail",
            "--model",
            path_str(&model),
            "--mass-kg",
            "60.21",
            "--input",
            path_str(&input),
            "--out",
            path_str(&out),
        ],
        &[path_str(&input), "force_n"],
    );
    let missing = dir.join("missing.csv");
    assert_fails(
        &as_strs(&simulate_force(&model, &missing, &out)),
        &[path_str(&missing)],
    );
}

#[test]
fn bad_rail_arguments_fail() {
    let dir = TempDir::new("args");
    let model = dir.write("m.toml", CONSISTENT_MODEL);
    let load = dir.write("load.csv", &load_csv(10));
    let out = dir.join("out.csv");
    let rail = |extra: &[&str]| {
        let mut args = vec![
            "simulate",
            "rail",
            "--model",
            path_str(&model),
            "--input",
            path_str(&load),
            "--out",
            path_str(&out),
        ];
        args.extend(extra);
        args.into_iter().map(String::from).collect::<Vec<_>>()
    };
    assert_fails(
        &as_strs(&rail(&["--mass-kg", "60.21", "--start", "moving"])),
        &["--start", "moving", "rest", "static"],
    );
    for mass in ["0", "-60.21", "nan", "inf"] {
        assert_fails(
            &as_strs(&rail(&["--mass-kg", mass])),
            &["--mass-kg", "positive"],
        );
    }
    // clap's own parse error: not a number.
    let out_err = fastemu(&as_strs(&rail(&["--mass-kg", "heavy"])));
    assert!(!out_err.status.success());
    assert!(String::from_utf8_lossy(&out_err.stderr).contains("--mass-kg"));
    assert!(!out.exists());
}

fn read_lines(path: &Path) -> Vec<String> {
    std::fs::read_to_string(path)
        .expect("output written")
        .lines()
        .map(String::from)
        .collect()
}

#[test]
fn simulate_force_and_rail_write_the_contracted_columns() {
    let dir = TempDir::new("happy");
    let model = dir.write("m.toml", CONSISTENT_MODEL);
    let input = dir.write("z.csv", &displacement_csv(50));
    let out = dir.join("sub/dir/f.csv");
    let result = fastemu(&as_strs(&simulate_force(&model, &input, &out)));
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let lines = read_lines(&out);
    assert_eq!(lines[0], "t_s,displacement_m,force_n");
    assert_eq!(lines.len(), 51);
    // The first row is the static equilibrium at the first displacement (0 m -> 0 N).
    assert_eq!(lines[1], "0.0,0.0,0.0");
    let last: Vec<f64> = lines[50].split(',').map(|s| s.parse().unwrap()).collect();
    assert_eq!(last.len(), 3);
    assert!(last[2] > 0.0);

    for start in ["rest", "static"] {
        let load = dir.write("load.csv", &load_csv(100));
        let out = dir.join(&format!("x-{start}.csv"));
        let result = fastemu(&[
            "simulate",
            "rail",
            "--model",
            path_str(&model),
            "--mass-kg",
            "45",
            "--input",
            path_str(&load),
            "--out",
            path_str(&out),
            "--start",
            start,
        ]);
        assert!(
            result.status.success(),
            "{}",
            String::from_utf8_lossy(&result.stderr)
        );
        let lines = read_lines(&out);
        assert_eq!(
            lines[0],
            "t_s,displacement_m,velocity_m_per_s,element_force_n"
        );
        assert_eq!(lines.len(), 101);
        let first: Vec<f64> = lines[1].split(',').map(|s| s.parse().unwrap()).collect();
        if start == "rest" {
            assert_eq!(first, [0.0, 0.0, 0.0, 0.0]);
        } else {
            // Static start: the element already carries the first force sample.
            assert!((first[3] - 55e3).abs() < 1e-6 * 55e3, "{first:?}");
        }
    }
}

#[test]
fn equiv_json_has_the_documented_shape() {
    let dir = TempDir::new("equiv");
    let model = dir.write("m.toml", &CONSISTENT_MODEL.replace("consistent", "paper"));
    let result = fastemu(&["equiv", "--model", path_str(&model), "--json"]);
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&result.stdout).expect("one JSON object");
    assert_eq!(json["form"], "paper");
    assert_eq!(json["length_m"], 0.75);
    assert_eq!(json["per_metre"], true);
    assert_eq!(json["model"], path_str(&model));
    let rows = json["rows"].as_array().expect("rows array");
    // Table 2 grid: 4 preloads x 5 frequencies.
    assert_eq!(rows.len(), 20);
    for row in rows {
        for key in [
            "preload_n",
            "frequency_hz",
            "k_eq_n_per_m2",
            "c_eq_ns_per_m2",
            "k_time_domain_n_per_m2",
            "c_time_domain_ns_per_m2",
        ] {
            assert!(row[key].is_f64(), "{key} in {row}");
        }
    }
    // Eq. 2 at 55 kN, 1 Hz (SPEC 2.1: 72.5 MN/m^2, 0.659 MN s/m^2), per metre even
    // though the sample is 0.75 m, and the paper form's own 78.9 / 0.215.
    let row = rows
        .iter()
        .find(|r| r["preload_n"] == 55e3 && r["frequency_hz"] == 1.0)
        .expect("55 kN, 1 Hz row");
    let get = |key: &str| row[key].as_f64().unwrap() / 1e6;
    assert!((get("k_eq_n_per_m2") - 72.5).abs() < 0.05);
    assert!((get("c_eq_ns_per_m2") - 0.659).abs() < 5e-4);
    assert!((get("k_time_domain_n_per_m2") - 78.9).abs() < 0.05);
    assert!((get("c_time_domain_ns_per_m2") - 0.215).abs() < 5e-4);

    let result = fastemu(&[
        "equiv",
        "--model",
        path_str(&model),
        "--json",
        "--preload-n",
        "6000",
        "--frequency-hz",
        "1,2,3",
    ]);
    let json: serde_json::Value = serde_json::from_slice(&result.stdout).unwrap();
    assert_eq!(json["rows"].as_array().unwrap().len(), 3);

    // A preload at or below -P0 is outside g(P)'s domain: an error, not clamped numbers.
    assert_fails(
        &["equiv", "--model", path_str(&model), "--preload-n=-70000"],
        &["--preload-n -70000", "domain", "-64000"],
    );
    // Tension above -P0 is inside the domain, and the linear model has no preload limit.
    let result = fastemu(&["equiv", "--model", path_str(&model), "--preload-n=-6000"]);
    assert!(result.status.success());
    let kv = dir.write("kv.toml", KV_MODEL);
    let result = fastemu(&["equiv", "--model", path_str(&kv), "--preload-n=-70000"]);
    assert!(result.status.success());
}

/// `equiv` shows the base element's values; a model with `[[effect]]` tables says that the
/// effects are not in them (stderr and JSON) instead of passing silently.
#[test]
fn equiv_names_the_effects_it_leaves_out() {
    let dir = TempDir::new("equiv-effects");
    let text = format!("{CONSISTENT_MODEL}\n[[effect]]\nname = \"moving-mass\"\nmass_kg = 40.0\n");
    let model = dir.write("m.toml", &text);
    let result = fastemu(&["equiv", "--model", path_str(&model), "--json"]);
    assert!(result.status.success());
    let json: serde_json::Value = serde_json::from_slice(&result.stdout).expect("one JSON object");
    assert_eq!(
        json["effects_not_included"],
        serde_json::json!(["moving-mass"])
    );
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(
        stderr.contains("moving-mass") && stderr.contains("not included"),
        "{stderr}"
    );
}

/// What spreadsheets and other tools write: a UTF-8 byte-order mark, CRLF line endings,
/// quoted fields, spaces and trailing blank lines. All read as the plain file does.
#[test]
fn csv_inputs_from_spreadsheets_read_like_plain_ones() {
    let dir = TempDir::new("csv-dialects");
    let model = dir.write("m.toml", CONSISTENT_MODEL);
    let plain = displacement_csv(20);
    let reference_in = dir.write("plain.csv", &plain);
    let reference_out = dir.join("plain-out.csv");
    let result = fastemu(&as_strs(&simulate_force(
        &model,
        &reference_in,
        &reference_out,
    )));
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let reference = std::fs::read_to_string(&reference_out).unwrap();
    let quoted: String = plain
        .lines()
        .map(|l| {
            let f: Vec<String> = l.split(',').map(|x| format!("\"{x}\"")).collect();
            f.join(",") + "\n"
        })
        .collect();
    let variants = [
        ("bom", format!("\u{feff}{plain}")),
        ("crlf", plain.replace('\n', "\r\n")),
        (
            "bom-crlf",
            format!("\u{feff}{}", plain.replace('\n', "\r\n")),
        ),
        ("quoted", quoted),
        ("spaces", plain.replace(',', " , ")),
        (
            "blank-lines",
            format!("\n{}\n\n", plain.replacen("0.005,", "\n0.005,", 1)),
        ),
    ];
    for (label, text) in variants {
        let input = dir.write(&format!("{label}.csv"), &text);
        let out = dir.join(&format!("{label}-out.csv"));
        let result = fastemu(&as_strs(&simulate_force(&model, &input, &out)));
        assert!(
            result.status.success(),
            "{label}: {}",
            String::from_utf8_lossy(&result.stderr)
        );
        assert_eq!(std::fs::read_to_string(&out).unwrap(), reference, "{label}");
    }
}

#[test]
fn a_misspelt_hil_config_key_fails_before_anything_starts_naming_line_table_and_the_key_meant() {
    let dir = TempDir::new("hil-typo");
    let default = fastemu::hil::config::DEFAULT_CONFIG_TOML;
    let line = default
        .lines()
        .position(|l| l.starts_with("specimen_mass_kg"))
        .expect("the default config sets specimen_mass_kg")
        + 1;
    let config = dir.write(
        "typo.toml",
        &default.replacen("specimen_mass_kg", "specimen_mas_kg", 1),
    );
    let out = dir.join("report");
    assert_fails(
        &[
            "hil",
            "--config",
            path_str(&config),
            "--out",
            path_str(&out),
        ],
        &[
            path_str(&config),
            &format!("at line {line} in [rig]"),
            "unknown field `specimen_mas_kg`",
            "(did you mean `specimen_mass_kg`?)",
        ],
    );
    assert!(
        !out.exists(),
        "a report directory for a run that never started"
    );
}

/// An actuator that cannot carry the programme's peak load (`shaker-10kn`, 10 kN, under
/// the default programme's 20 kN preload and axle pulses): `hil` refuses before anything
/// starts, naming the file, the key and its value, and `hil --check` exits 1 with it.
#[test]
fn an_actuator_that_cannot_hold_the_load_is_refused_before_anything_starts() {
    let dir = TempDir::new("hil-weak-actuator");
    let default = fastemu::hil::config::DEFAULT_CONFIG_TOML;
    let block =
        "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0";
    assert!(
        default.contains(block),
        "the default's [rig.actuator] changed"
    );
    let config = dir.write(
        "weak.toml",
        &default.replacen(block, "preset = \"shaker-10kn\"", 1),
    );
    let out = dir.join("report");
    let args = [
        "hil",
        "--config",
        path_str(&config),
        "--out",
        path_str(&out),
    ];
    assert_fails(
        &args,
        &[
            path_str(&config),
            "rig.actuator.force_max_n = 10000 N",
            "below the programme's peak load",
        ],
    );
    assert!(
        !out.exists(),
        "a report directory for a run that never started"
    );
    let check = fastemu(&[
        "hil",
        "--check",
        "--config",
        path_str(&config),
        "--out",
        path_str(&dir.join("check")),
    ]);
    assert_eq!(check.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&check.stderr);
    assert!(
        stderr.contains("ERROR: ") && stderr.contains("rig.actuator.force_max_n = 10000 N"),
        "{stderr}"
    );
}

#[test]
fn a_bad_or_busy_live_address_fails_before_anything_starts_naming_the_reason() {
    let dir = TempDir::new("live-addr");
    let out = dir.join("report");
    let busy = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let busy_addr = busy.local_addr().unwrap().to_string();
    for (addr, says) in [
        ("127.0.0.1:99999", "port 99999 is out of range (0-65535)"),
        ("127.0.0.1", "expected HOST:PORT"),
        (busy_addr.as_str(), "cannot listen on"),
    ] {
        assert_fails(
            &[
                "hil",
                "--live",
                "--live-addr",
                addr,
                "--out",
                path_str(&out),
            ],
            &[&format!("--live-addr `{addr}`"), says],
        );
        assert!(
            !out.exists(),
            "{addr}: a report directory for a run that never started"
        );
    }
}

/// `hil`'s exit code is its verdict (0 clean, 1 not clean, 2 a fault): a run that never
/// starts, from a usage error or a configuration error, is no verdict, 3; `--help` is 0.
#[test]
fn hil_without_a_verdict_exits_3() {
    let dir = TempDir::new("hil-exit3");
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, "[loop]\nrat_hz = 4096.0\n").unwrap();
    for args in [
        vec!["hil", "--duration-s", "abc"],
        vec!["hil", "--no-such-option"],
        vec!["hil", "--config", path_str(&bad)],
    ] {
        let out = fastemu(&args);
        assert_eq!(
            out.status.code(),
            Some(3),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    assert_eq!(fastemu(&["hil", "--help"]).status.code(), Some(0));
    // Other commands keep the usual codes.
    assert_eq!(
        fastemu(&["equiv", "--no-such-option"]).status.code(),
        Some(2)
    );
}

/// `hil --check --json` on the shipped configuration: stable as the run starts (exit 0),
/// where the specimen starts (the element's static displacement under the programme's
/// first force, checked here by the consistent form's static law forward, SPEC 2.1:
/// `F = P0 [(1 + (1 - chi) k1_0 z / P0)^(1/(1-chi)) - 1]`), and the programme's loads it
/// judges the loop at besides the preload. A `lag-delay` of 1003 + 99 us, stable at the
/// preload with its planned lead and not under the axle's peak, says so and still exits 0
/// (it starts stable).
#[test]
fn hil_check_json_says_where_the_specimen_starts_and_the_programmes_loads() {
    let dir = TempDir::new("hil-check-json");
    let out = dir.join("check");
    let run = fastemu(&["hil", "--check", "--json", "--out", path_str(&out)]);
    assert_eq!(run.status.code(), Some(0));
    let j: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(j["margins"]["stable"], true);
    let z = j["start_displacement_m"].as_f64().unwrap();
    let (k1_0, chi, p0) = (62e6 * 0.75, 0.21, 64e3);
    let force = p0 * ((1.0 + (1.0 - chi) * k1_0 * z / p0).powf(1.0 / (1.0 - chi)) - 1.0);
    assert!((force - 20e3).abs() < 1e-6, "{force} N at {z} m");
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains(&format!("the specimen starts at rest at {:.6} mm", z * 1e3)),
        "{stderr}"
    );
    let loads = &j["programme_loads"];
    let (lowest, highest) = (
        loads["lowest_n"].as_f64().unwrap(),
        loads["highest_n"].as_f64().unwrap(),
    );
    // The harmonic's 4 kN below the preload at least, and the axles well above it.
    assert!(
        lowest <= 16e3 + 1e-6 && highest > 60e3,
        "{lowest} {highest}"
    );
    assert_eq!(loads["judged_n"], serde_json::json!([lowest, highest]));
    assert_eq!(loads["unstable_at_n"], serde_json::json!([]));
    let over = loads["stable_leads_us"].as_array().unwrap();
    let at_preload = j["stable_leads_us"].as_array().unwrap();
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    assert!(f(&over[0]) >= f(&at_preload[0]) && f(&over[1]) <= f(&at_preload[1]));
    assert_eq!(
        j["safe_start_damping_ns_per_m"].as_f64(),
        Some(40e3),
        "the shipped guess keeps all of the guard's damping"
    );
    // The guard's most damping by the lead: the full damping at the shipped lead, halved
    // step by step as the lead grows, none, then the full again beyond the leads any
    // lag-and-delay actuator as slow as the lead is stable at; the last step to the
    // adaptation's longest lead.
    let steps = j["guard_damping_by_lead"].as_array().unwrap();
    let step = |i: usize| (f(&steps[i]["up_to_us"]), f(&steps[i]["damping_ns_per_m"]));
    assert!(step(0).0 > 252.0 && step(0).1 == 40e3, "{steps:?}");
    assert_eq!(step(steps.len() - 1), (10000.0, 40e3), "{steps:?}");
    let none = steps.len() - 2;
    assert_eq!(step(none).1, 0.0, "{steps:?}");
    for i in 1..=none {
        assert!(step(i).0 > step(i - 1).0, "{steps:?}");
        assert!(step(i).1 < step(i - 1).1, "{steps:?}");
    }
    assert!(
        stderr.contains("the passivity guard's most damping by the lead in effect")
            && stderr.contains("at this lead 40.0 kN s/m"),
        "{stderr}"
    );
    // The slowest actuator some lead holds: as a pure delay beyond the shipped 252 us and
    // below the 1224 us (1003 + 99 us and the hold) of the next case (stable at the
    // preload, not at the axles' peak); a lag makes a slower one holdable.
    let slowest = j["slowest_held_actuator"].as_array().unwrap();
    assert_eq!(slowest.len(), 3, "{slowest:?}");
    let limit = |i: usize| f(&slowest[i]["effective_delay_us"]);
    assert_eq!(f(&slowest[0]["lag_share"]), 0.0);
    assert!(
        limit(0) > 252.0 && limit(0) < 1003.0 + 99.0 + 122.0,
        "{slowest:?}"
    );
    assert!(limit(0) <= limit(1) && limit(1) <= limit(2), "{slowest:?}");
    assert!(
        stderr.contains(&format!("{:.0} us as a pure delay", limit(0))),
        "{stderr}"
    );
    assert!(out.join("check.png").exists());

    let edge = dir.write(
        "edge.toml",
        &include_str!("../../configs/hil-default.toml").replace(
            "transport_delay_us = 50.0\nlag_us = 80.0",
            "transport_delay_us = 1003.0\nlag_us = 99.0",
        ),
    );
    let run = fastemu(&[
        "hil",
        "--check",
        "--json",
        "--config",
        path_str(&edge),
        "--out",
        path_str(&out),
    ]);
    assert_eq!(run.status.code(), Some(0));
    let j: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert!(
        (j["lead_us"].as_f64().unwrap() - 1100.0).abs() < 1e-6,
        "{}",
        j["lead_us"]
    );
    assert_eq!(
        j["programme_loads"]["unstable_at_n"],
        serde_json::json!([highest])
    );
    assert_eq!(
        j["programme_loads"]["stable_leads_us"],
        serde_json::Value::Null
    );
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("NOT stable with this lead under 71.9 kN")
            && stderr.contains(
                "the declared actuator's loop with that lead is NOT stable under 71.9 kN"
            ),
        "{stderr}"
    );
}
