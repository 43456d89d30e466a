//! Durability programmes: a block sequence repeated (in process: cycle and block counters,
//! block-local loads, the programme's end; over processes: the shipped durability config
//! counts its cycles and stays clean), and the configuration's errors.

use fastemu::hil::config::{default_hil_config, parse_hil_config, DEFAULT_CONFIG_TOML};
use fastemu::hil::inproc::{run_in_process, InProcessScript};
use fastemu::rig::reference::reference_displacement_m;

const PROGRAMME: &str = r#"
[programme]
repeat = 3
[[programme.block]]
name = "harmonic"
duration_s = 0.5
repeat = 2
harmonic_amplitude_n = 2000.0
harmonic_frequency_hz = 4.0
[[programme.block]]
name = "step"
duration_s = 0.25
step_n = 3000.0
"#;

fn without_scenario_loads(text: &str) -> String {
    text.replace(
        "harmonic_amplitude_n = 4000.0",
        "harmonic_amplitude_n = 0.0",
    )
    .replace("train_speed_kmh = 200.0", "train_speed_kmh = 0.0")
}

#[test]
fn a_block_sequence_repeats_with_its_counters_and_ends_the_run() {
    let text = format!("{}{PROGRAMME}", without_scenario_loads(DEFAULT_CONFIG_TOML));
    let mut cfg = parse_hil_config(&text, "test.toml", None).unwrap();
    cfg.set_duration_s(100.0);
    // 3 passes of (0.5 s x 2 + 0.25 s) = 3.75 s.
    assert_eq!(cfg.programme.end_s, 3.75);
    let run = run_in_process(
        &cfg,
        &InProcessScript {
            max_steps: 100_000,
            command_delay_periods: 1,
            ..InProcessScript::default()
        },
    );
    let rate = cfg.loop_.rate_hz;
    assert_eq!(
        run.rig.len() as f64,
        3.75 * rate,
        "the run ends with the programme"
    );
    for r in &run.rig {
        let t = r.programme_time_s;
        let (cycle, in_cycle) = ((t / 1.25).floor() as u64, t % 1.25);
        assert_eq!(r.programme_cycle, cycle, "at {t} s");
        let block = u32::from(in_cycle >= 1.0);
        assert_eq!(r.programme_block, block, "at {t} s");
        let expected = if block == 1 {
            20_000.0 + 3000.0
        } else {
            20_000.0 + 2000.0 * (2.0 * std::f64::consts::PI * 4.0 * (in_cycle % 0.5)).sin()
        };
        assert!(
            (r.external_force_n - expected).abs() < 1e-6,
            "at {t} s: {} vs {expected}",
            r.external_force_n
        );
    }
    // The loop follows the reference through the block changes (within 1 %: each 3 kN
    // step rings the specimen's resonance, ~50 um, the band where the loop is least exact;
    // smooth loads give ~0.03 %).
    let reference = reference_displacement_m(&cfg, run.rig.len());
    let (mut e2, mut r2) = (0.0, 0.0);
    for r in &run.rig {
        let x = reference[r.step_idx as usize];
        e2 += (r.x_m - x).powi(2);
        r2 += x * x;
    }
    assert!((e2 / r2).sqrt() < 1e-2, "rel {}", (e2 / r2).sqrt());
}

#[test]
fn programme_configuration_errors_name_the_key() {
    let both = format!("{DEFAULT_CONFIG_TOML}{PROGRAMME}");
    let e = parse_hil_config(&both, "x.toml", None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("x.toml") && e.contains("[programme]") && e.contains("harmonic_amplitude_n"),
        "{e}"
    );
    let bad = format!(
        "{}\n[programme]\n[[programme.block]]\nduration_s = -1.0\n",
        without_scenario_loads(DEFAULT_CONFIG_TOML)
    );
    let e = parse_hil_config(&bad, "x.toml", None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("programme.block[0].duration_s") && e.contains("-1"),
        "{e}"
    );
    let none = format!(
        "{}\n[programme]\nblock = []\n",
        without_scenario_loads(DEFAULT_CONFIG_TOML)
    );
    let e = parse_hil_config(&none, "x.toml", None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("programme.block") && e.contains("at least one"),
        "{e}"
    );
    assert_eq!(default_hil_config().unwrap().programme.blocks.len(), 1);
}

#[test]
fn the_shipped_durability_config_counts_its_cycles_over_processes() {
    let _serial = crate::hil_processes::serial();
    let dir = crate::common::TempDir::new("durability");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_fastemu"))
        .args([
            "hil",
            "--json",
            "--config",
            concat!(env!("CARGO_MANIFEST_DIR"), "/configs/hil-durability.toml"),
            "--duration-s",
            "12",
            "--out",
        ])
        .arg(dir.join("report"))
        .output()
        .unwrap();
    let json: serde_json::Value =
        serde_json::from_slice(&out.stdout).unwrap_or(serde_json::Value::Null);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{json}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        json["programme"]["cycles_completed"], 2,
        "{}",
        json["programme"]
    );
    assert_eq!(json["programme"]["completed"], true);
    assert!(json["fidelity"]["displacement_rel_rms"].as_f64().unwrap() < 0.02);
}
