//! Campaign loading (SPEC 4): every malformed input gives a one-line error naming the file.

use std::path::{Path, PathBuf};

use fastemu::ident::campaign::load_campaign;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("fastemu-campaign-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn harmonic_csv(n: usize, dt: f64, f_hz: f64) -> String {
    let mut s = String::from("t_s,displacement_m,force_n\n");
    for i in 0..n {
        let t = i as f64 * dt;
        let w = 2.0 * std::f64::consts::PI * f_hz;
        s.push_str(&format!(
            "{t},{},{}\n",
            1e-4 * (w * t).cos(),
            5e3 + 4e3 * (w * t - 0.2).cos()
        ));
    }
    s
}

const TEST_ENTRY: &str = "[[test]]\nid = \"a\"\nfile = \"a.csv\"\nkind = \"harmonic\"\npreload_n = 6000.0\namplitude_n = 5000.0\nfrequency_hz = 2.0\n";

fn write(dir: &Path, toml: &str, csv: &str) {
    std::fs::write(
        dir.join("campaign.toml"),
        format!("sample_length_m = 0.75\n{toml}"),
    )
    .unwrap();
    std::fs::write(dir.join("a.csv"), csv).unwrap();
}

/// Loads a campaign that must fail; checks the message is one line and names `file` and `needle`.
fn check_error(name: &str, toml: &str, csv: &str, file: &str, needle: &str) {
    let dir = scratch(name);
    write(&dir, toml, csv);
    let err = load_campaign(&dir).expect_err(name).to_string();
    let _ = std::fs::remove_dir_all(&dir);
    assert!(!err.contains('\n'), "{name}: multi-line error: {err}");
    assert!(
        err.contains(file),
        "{name}: error does not name {file}: {err}"
    );
    assert!(
        err.contains(needle),
        "{name}: error lacks `{needle}`: {err}"
    );
}

#[test]
fn a_valid_campaign_loads_with_its_equivalents() {
    let dir = scratch("valid");
    write(&dir, TEST_ENTRY, &harmonic_csv(1000, 1e-3, 2.0));
    let campaign = load_campaign(&dir).unwrap();
    // The path of the campaign file itself names the same campaign.
    let via_file = load_campaign(&dir.join("campaign.toml")).unwrap();
    assert_eq!(via_file.dir, dir);
    assert_eq!(via_file.tests.len(), campaign.tests.len());
    let _ = std::fs::remove_dir_all(&dir);
    let test = &campaign.tests[0];
    assert_eq!(test.temperature_c, 23.0);
    let eq = campaign.equivalent(test).unwrap();
    // F_1 / Z_1 = 4e7 e^{-0.2 i}: k = 4e7 cos 0.2 / 0.75, c = -4e7 sin 0.2 / (W 0.75).
    assert!((eq.k_eq_n_per_m2 - 4e7 * 0.2f64.cos() / 0.75).abs() < 1e-6 * 4e7);
    let w = 4.0 * std::f64::consts::PI;
    assert!((eq.c_eq_ns_per_m2 + 4e7 * 0.2f64.sin() / (w * 0.75)).abs() < 1e-6 * 4e7 / w);
}

#[test]
fn malformed_campaigns_give_one_line_errors_naming_the_file() {
    let csv = harmonic_csv(1000, 1e-3, 2.0);
    check_error("missing-toml", "", &csv, "campaign.toml", "no [[test]]");
    check_error(
        "missing-file",
        &TEST_ENTRY.replace("a.csv", "b.csv"),
        &csv,
        "campaign.toml",
        "no such file",
    );
    check_error(
        "bad-header",
        TEST_ENTRY,
        &csv.replacen("force_n", "force", 1),
        "a.csv",
        "lacks column `force_n`",
    );
    let mut nonuniform: Vec<String> = csv.lines().map(String::from).collect();
    nonuniform[10] = format!("0.0095,{}", nonuniform[10].split_once(',').unwrap().1);
    check_error(
        "non-uniform",
        TEST_ENTRY,
        &nonuniform.join("\n"),
        "a.csv",
        "uniform",
    );
    let mut decreasing = nonuniform.clone();
    decreasing[10] = format!("0.0,{}", decreasing[10].split_once(',').unwrap().1);
    check_error(
        "non-increasing",
        TEST_ENTRY,
        &decreasing.join("\n"),
        "a.csv",
        "does not increase",
    );
    let mut nan = csv.lines().map(String::from).collect::<Vec<_>>();
    nan[20] = "0.019,NaN,5000".into();
    check_error("nan", TEST_ENTRY, &nan.join("\n"), "a.csv", "finite");
    check_error(
        "short",
        TEST_ENTRY,
        &harmonic_csv(700, 1e-3, 2.0),
        "a.csv",
        "two whole cycles",
    );
    check_error(
        "kind",
        &TEST_ENTRY.replace("\"harmonic\"", "\"sweep\""),
        &csv,
        "campaign.toml",
        "\"sweep\"",
    );
    check_error(
        "duplicate",
        &format!("{TEST_ENTRY}{TEST_ENTRY}"),
        &csv,
        "campaign.toml",
        "duplicate id \"a\"",
    );
    check_error(
        "missing-key",
        &TEST_ENTRY.replace("frequency_hz = 2.0\n", ""),
        &csv,
        "campaign.toml",
        "missing key `frequency_hz`",
    );
    check_error(
        "unknown-key",
        &format!("{TEST_ENTRY}frequncy_hz = 3.0\n"),
        &csv,
        "campaign.toml",
        "unknown key `frequncy_hz`",
    );
}

#[test]
fn a_missing_campaign_directory_is_named() {
    let dir = std::env::temp_dir().join("fastemu-no-such-campaign");
    let err = load_campaign(&dir).unwrap_err().to_string();
    assert!(
        err.contains("fastemu-no-such-campaign") && err.contains("cannot read"),
        "{err}"
    );
}

#[test]
fn started_at_orders_the_tests_when_every_test_states_it() {
    let dir = scratch("started-at");
    let entry = |id: &str, when: &str| {
        format!(
            "[[test]]\nid = \"{id}\"\nfile = \"a.csv\"\nkind = \"harmonic\"\npreload_n = 6000.0\namplitude_n = 5000.0\nfrequency_hz = 2.0\nstarted_at = {when}\n"
        )
    };
    let toml = format!(
        "{}{}",
        entry("late", "\"2026-03-14T10:00:00Z\""),
        // A TOML date-time (unquoted) is taken as well, with its offset.
        entry("early", "2026-03-14T10:30:00+01:00")
    );
    write(&dir, &toml, &harmonic_csv(2000, 1e-3, 2.0));
    let campaign = load_campaign(&dir).unwrap();
    assert!(campaign.has_start_times());
    let orders = campaign.test_orders();
    assert_eq!(orders[0] - orders[1], 1800.0, "{orders:?}");
    // Without started_at on every test, the order is the file's.
    let partial = format!(
        "{}{}",
        entry("late", "\"2026-03-14T10:00:00Z\""),
        TEST_ENTRY
    );
    write(&dir, &partial, &harmonic_csv(2000, 1e-3, 2.0));
    let campaign = load_campaign(&dir).unwrap();
    assert!(!campaign.has_start_times());
    assert_eq!(campaign.test_orders(), vec![0.0, 1.0]);
    let _ = std::fs::remove_dir_all(&dir);
    check_error(
        "started-at-bad",
        &entry("a", "\"14/03/2026\""),
        &harmonic_csv(2000, 1e-3, 2.0),
        "campaign.toml",
        "key `started_at` = \"14/03/2026\": expected an ISO 8601 date and time",
    );
}
