//! `fastemu bench latency`'s own machinery: percentile bookkeeping, the `.hlog` format,
//! the JSON shape of a tiny run, pinning/priority fallback, the `hil` output contract
//! and the child-process guard. Nothing here asserts on a timing.

use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, SystemTime};

use base64::Engine;
use hdrhistogram::serialization::interval_log::{IntervalLogIterator, LogEntry};
use hdrhistogram::serialization::Deserializer;
use hdrhistogram::Histogram;

use fastemu::bench::latency::end_to_end::parse_hil_output;
use fastemu::bench::latency::hlog::{write_interval_log, LoggedInterval};
use fastemu::bench::latency::split_into_rounds;
use fastemu::bench::latency::stats::{new_latency_histogram, percentile_curve, PercentileSummary};
use fastemu::bench::latency::transport::{Transport, SOCKET_BYTES};
use fastemu::child::ChildGuard;
use fastemu::ipc::messages::DisplacementSample;

/// A fresh directory for one test's outputs.
fn scratch_dir(name: &str) -> PathBuf {
    let nanos = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap()
        .as_nanos();
    let dir = std::env::temp_dir().join(format!(
        "fastemu-it-latency-{name}-{}-{nanos}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn histogram_of(values: impl IntoIterator<Item = u64>) -> Histogram<u64> {
    let mut h = new_latency_histogram();
    for v in values {
        h.record(v).unwrap();
    }
    h
}

#[test]
fn percentiles_of_known_values() {
    // Values below 2048 are stored exactly with 3 significant digits.
    let h = histogram_of(1..=1000);
    let s = PercentileSummary::from_histogram(&h);
    assert_eq!(
        s,
        PercentileSummary {
            p50_ns: 500,
            p90_ns: 900,
            p99_ns: 990,
            p999_ns: 999,
            p9999_ns: 1000,
            max_ns: 1000,
            samples: 1000,
        }
    );
}

#[test]
fn one_outlier_shows_only_in_the_tail() {
    let mut h = histogram_of(std::iter::repeat_n(700, 9_999));
    h.record(5_000_000).unwrap();
    let s = PercentileSummary::from_histogram(&h);
    assert_eq!((s.p50_ns, s.p99_ns, s.p999_ns), (700, 700, 700));
    // 5 ms is kept to 3 significant digits.
    assert!(s.max_ns.abs_diff(5_000_000) <= 5_000, "max {}", s.max_ns);
    assert_eq!(s.samples, 10_000);
}

#[test]
fn values_beyond_one_second_saturate_instead_of_failing() {
    let mut h = new_latency_histogram();
    h.saturating_record(5_000_000_000);
    assert_eq!(h.len(), 1);
    assert!(h.max() <= 1_001_000_000 && h.max() >= 999_000_000);
}

#[test]
fn percentile_curve_rises_on_the_inverse_tail_axis() {
    let curve = percentile_curve(&histogram_of(1..=10_000));
    assert!(curve.len() > 10);
    assert!(curve
        .windows(2)
        .all(|w| w[1].0 > w[0].0 && w[1].1 >= w[0].1));
    assert_eq!(curve[0].0, 1.0);
    assert!(curve.last().unwrap().1 >= 10_000.0);
    assert!(percentile_curve(&new_latency_histogram()).is_empty());
}

#[test]
fn rounds_split_the_samples_exactly() {
    for (total, rounds) in [(100_000, 10), (2_001, 10), (7, 10), (1, 1), (10, 3)] {
        let parts = split_into_rounds(total, rounds);
        assert_eq!(parts.iter().sum::<u64>(), total, "{total} in {rounds}");
        assert!(parts.len() as u64 <= rounds && parts.iter().all(|&p| p > 0));
        let (lo, hi) = (parts.iter().min().unwrap(), parts.iter().max().unwrap());
        assert!(hi - lo <= 1);
    }
}

#[test]
fn hlog_round_trips_through_the_standard_reader() {
    let intervals: Vec<LoggedInterval> = [
        ("iceoryx2", 0, 300u64),
        ("udp", 1, 200),
        ("iceoryx2", 2, 100),
    ]
    .into_iter()
    .map(|(tag, start_s, n)| LoggedInterval {
        tag: tag.to_string(),
        start_offset: Duration::from_secs(start_s),
        duration: Duration::from_millis(500),
        histogram: histogram_of((1..=n).map(|v| v * 1000)),
    })
    .collect();
    let mut buf = Vec::new();
    let base = SystemTime::UNIX_EPOCH + Duration::from_secs(1_700_000_000);
    write_interval_log(&mut buf, base, &["values are ns".to_string()], &intervals).unwrap();
    let text = String::from_utf8(buf.clone()).unwrap();
    assert!(text.contains("#[BaseTime: 1700000000.000"), "{text}");
    assert!(text.contains("#values are ns"));

    let mut deserializer = Deserializer::new();
    let mut read_back = Vec::new();
    for entry in IntervalLogIterator::new(&buf) {
        if let LogEntry::Interval(ilh) = entry.unwrap() {
            let bytes = base64::engine::general_purpose::STANDARD
                .decode(ilh.encoded_histogram())
                .unwrap();
            let h: Histogram<u64> = deserializer.deserialize(&mut bytes.as_slice()).unwrap();
            read_back.push((
                ilh.tag().map(|t| t.as_str().to_string()),
                ilh.start_timestamp(),
                h.len(),
                h.max(),
            ));
        }
    }
    let expected: Vec<_> = intervals
        .iter()
        .map(|i| {
            (
                Some(i.tag.clone()),
                i.start_offset,
                i.histogram.len(),
                i.histogram.max(),
            )
        })
        .collect();
    assert_eq!(read_back, expected);
}

#[test]
fn hlog_rejects_tags_the_format_cannot_carry() {
    let bad = LoggedInterval {
        tag: "has space".to_string(),
        start_offset: Duration::ZERO,
        duration: Duration::from_secs(1),
        histogram: histogram_of([1]),
    };
    let err = write_interval_log(&mut Vec::new(), SystemTime::now(), &[], &[bad]).unwrap_err();
    assert!(err.to_string().contains("has space"), "{err}");
}

#[test]
fn socket_rounds_carry_the_rig_links_datagrams_and_keys_round_trip() {
    use fastemu::link::protocol::{decode, encode_sample, Datagram, SampleDatagram, Side};
    let sample = DisplacementSample {
        sequence: u64::MAX - 3,
        rig_time_ns: 123_456_789,
        publish_time_ns: 987_654_321_000,
        displacement_m: -4.25e-4,
        actuator_force_n: 2.0e4,
        status: 2,
        rig_state: 1,
        rig_fault_code: 0,
        reserved: 0,
        commanded_force_n: 2.5e4,
    };
    let mut buf = [0u8; fastemu::link::protocol::MAX_DATAGRAM_BYTES];
    let n = encode_sample(&mut buf, 7, 8, &SampleDatagram::of(&sample, 0, 0));
    assert_eq!(n, SOCKET_BYTES.0);
    match decode(&buf[..n], Side::Fastemu).unwrap().1 {
        Datagram::Sample(d) => assert_eq!(d.to_sample(sample.publish_time_ns), sample),
        other => panic!("{other:?}"),
    }
    for t in Transport::ALL {
        assert_eq!(Transport::from_key(t.key()), Some(t));
    }
}

#[test]
fn hil_output_contract_is_read_and_gaps_are_reported() {
    let out = r#"{"latency_ns": {"end_to_end": {"p50": 1500, "p99": 4000.5, "p999": 9000, "max": 20000},
        "wake_jitter": {"p50": 10, "p99": 20, "p999": 30, "max": 40}}, "other": 1}"#;
    let (e2e, jitter) = parse_hil_output(out).unwrap();
    assert_eq!(
        (e2e.p50_ns, e2e.p99_ns, e2e.max_ns),
        (1500.0, 4000.5, 20000.0)
    );
    assert_eq!(jitter.unwrap().p999_ns, 30.0);
    // Progress lines before the object are skipped.
    let with_noise = format!("starting\n{}\n", out.replace('\n', " "));
    assert!(parse_hil_output(&with_noise).is_ok());
    assert!(parse_hil_output(r#"{"latency_ns": {"end_to_end": {"p50": 1}}}"#).is_err());
    assert!(parse_hil_output("not json").is_err());
}

#[test]
fn child_guard_kills_and_reaps_on_drop() {
    let child = Command::new("sleep").arg("30").spawn().unwrap();
    let pid = child.id() as libc::pid_t;
    drop(ChildGuard::new(child));
    // SAFETY: signal 0 only checks whether the pid exists.
    let alive = unsafe { libc::kill(pid, 0) } == 0;
    assert!(
        !alive,
        "child {pid} survived its guard (or is an unreaped zombie)"
    );
}

fn run_bench(args: &[&str]) -> serde_json::Value {
    // Tests run in parallel with the HIL process tests: no SCHED_FIFO spinners here
    // unless a test asks for pinning or priority itself (then `--no-rt` is moot).
    let explicit_rt = args.iter().any(|a| *a == "--pin" || *a == "--priority");
    let default_prefix_before = default_prefix_files();
    let child = Command::new(env!("CARGO_BIN_EXE_fastemu"))
        .args(["bench", "latency", "--json"])
        .args(if explicit_rt {
            &[][..]
        } else {
            &["--no-rt"][..]
        })
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id();
    let output = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "bench latency failed: {stderr}");
    // Every iceoryx2 file of the bench's ping-pong session (named with its prefix, which
    // begins with the bench's pid) is gone once it has exited.
    let left = fastemu::ipc::cleanup::files_with_prefix(&format!("fastemu_latency_{pid}_"));
    assert!(left.is_empty(), "the bench left iceoryx2 files: {left:?}");
    // Nor does it create any under iceoryx2's default prefix (no fastemu process does).
    let new: Vec<_> = default_prefix_files()
        .difference(&default_prefix_before)
        .cloned()
        .collect();
    assert!(
        new.is_empty(),
        "iceoryx2 files under the default prefix appeared: {new:?}"
    );
    let stdout = String::from_utf8(output.stdout).unwrap();
    assert_eq!(
        stdout.lines().count(),
        1,
        "one JSON object expected: {stdout}"
    );
    serde_json::from_str(&stdout).unwrap()
}

/// `/dev/shm/iox2_*`: iceoryx2's files under its default prefix.
fn default_prefix_files() -> std::collections::BTreeSet<String> {
    std::fs::read_dir("/dev/shm")
        .unwrap()
        .filter_map(Result::ok)
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("iox2_"))
        .collect()
}

const SUMMARY_KEYS: [&str; 7] = [
    "p50_ns", "p90_ns", "p99_ns", "p999_ns", "p9999_ns", "max_ns", "samples",
];

#[test]
fn tiny_run_reports_every_transport_and_writes_its_files() {
    let dir = scratch_dir("json");
    let out = dir.join("out");
    let report = run_bench(&[
        "--samples",
        "2000",
        "--rounds",
        "2",
        "--jitter-s",
        "0.05",
        "--out",
        out.to_str().unwrap(),
    ]);
    let transports = report["transports"].as_object().unwrap();
    let keys: Vec<&str> = transports.keys().map(String::as_str).collect();
    let mut expected = vec!["iceoryx2", "iceoryx2_event", "udp", "uds", "crossbeam"];
    expected.sort();
    assert_eq!(keys, expected);
    for (name, summary) in transports {
        for key in SUMMARY_KEYS {
            assert!(summary[key].is_u64(), "{name}.{key} in {summary}");
        }
        assert_eq!(summary["samples"], 2000, "{name}");
        let p = |k: &str| summary[k].as_u64().unwrap();
        assert!(
            p("p50_ns") <= p("p99_ns") && p("p99_ns") <= p("max_ns"),
            "{name}"
        );
    }
    let jitter = report["loop"]["wake_jitter"].as_object().unwrap();
    for key in [
        "4096hz_sleep",
        "4096hz_sleep_spin",
        "20000hz_sleep",
        "20000hz_sleep_spin",
    ] {
        let j = &jitter[key];
        for k in SUMMARY_KEYS {
            assert!(j[k].is_u64(), "{key}.{k}");
        }
        assert!(j["samples"].as_u64().unwrap() > 0);
        assert!(j["missed_deadlines"].is_u64());
    }
    // On a binary without `hil` this is null with a note; with it, an object.
    let e2e = &report["loop"]["end_to_end"];
    if e2e.is_null() {
        assert!(report["loop"]["end_to_end_note"]
            .as_str()
            .unwrap()
            .starts_with("unavailable"));
    } else {
        for k in ["p50_ns", "p99_ns", "p999_ns", "max_ns"] {
            assert!(e2e[k].is_number(), "end_to_end.{k}");
        }
        // The `hil` runs report under the bench's own directory, not in ./out.
        for run in ["hil-iceoryx2", "hil-udp-link"] {
            assert!(out.join(run).join("summary.json").is_file(), "{run}");
        }
    }
    assert!(report["ratio_udp_over_iceoryx2_p99"].is_number());
    assert_eq!(report["message_bytes"], 64);
    assert_eq!(
        report["socket_datagram_bytes"],
        serde_json::json!([96, 184])
    );
    assert!(report["loop"]["end_to_end_udp_link"]["note"].is_string());
    assert_eq!(report["out_dir"], out.to_str().unwrap());

    // One interval per round per transport and per scheduler configuration.
    let hlog = std::fs::read(out.join("latency.hlog")).unwrap();
    let mut per_tag = std::collections::BTreeMap::<String, (usize, u64)>::new();
    let mut deserializer = Deserializer::new();
    for entry in IntervalLogIterator::new(&hlog) {
        if let LogEntry::Interval(ilh) = entry.unwrap() {
            let bytes = base64::engine::general_purpose::STANDARD
                .decode(ilh.encoded_histogram())
                .unwrap();
            let h: Histogram<u64> = deserializer.deserialize(&mut bytes.as_slice()).unwrap();
            let e = per_tag
                .entry(ilh.tag().unwrap().as_str().to_string())
                .or_default();
            e.0 += 1;
            e.1 += h.len();
        }
    }
    for t in expected {
        assert_eq!(per_tag[t], (2, 2000), "{t}");
    }
    assert_eq!(per_tag.len(), 5 + 4);
    assert!(per_tag["jitter_20000hz_sleep_spin"].0 == 2);
    let png = std::fs::read(out.join("latency_percentiles.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn impossible_pinning_and_priority_are_warnings_not_failures() {
    let dir = scratch_dir("fallback");
    let report = run_bench(&[
        "--samples",
        "200",
        "--rounds",
        "1",
        "--jitter-s",
        "0.01",
        "--skip-hil",
        "--pin",
        "900,901",
        "--priority",
        "150",
        "--out",
        dir.to_str().unwrap(),
    ]);
    let warnings: Vec<&str> = report["warnings"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| w.as_str().unwrap())
        .collect();
    let has = |prefix: &str, needle: &str| {
        warnings
            .iter()
            .any(|w| w.starts_with(prefix) && w.contains(needle))
    };
    assert!(has("main:", "CPU 900 does not exist"), "{warnings:?}");
    assert!(has("peer:", "CPU 901 does not exist"), "{warnings:?}");
    assert!(has("main:", "priority 150 outside 1-99"), "{warnings:?}");
    assert!(has("peer:", "priority 150 outside 1-99"), "{warnings:?}");
    assert_eq!(report["transports"]["udp"]["samples"], 200);
    assert_eq!(report["cpus"]["main"], serde_json::json!([900]));
    assert_eq!(report["cpus"]["peer"], serde_json::json!([901]));
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn rt_setup_can_move_a_thread_off_an_inherited_one_cpu_mask() {
    // A peer process or echo thread inherits its parent's CPU mask; asking it for
    // another CPU must work, not be refused as "CPU does not exist".
    // SAFETY: sysconf with a constant name has no preconditions.
    let n_cpus = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) }.max(1) as usize;
    let last_cpu = n_cpus - 1;
    let warnings = std::thread::spawn(move || {
        let setup = |cpus: Vec<usize>| fastemu::rt::RtSetup {
            lock_memory: false,
            fifo_priority: None,
            cpus,
        };
        let mut warnings = fastemu::rt::apply_rt_setup(&setup(vec![0]));
        warnings.extend(fastemu::rt::apply_rt_setup(&setup(vec![last_cpu])));
        // SAFETY: cpu_set_t is plain data; pid 0 is this thread.
        let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
        unsafe { libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) };
        assert!(unsafe { libc::CPU_ISSET(last_cpu, &set) });
        warnings
    })
    .join()
    .unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
}
