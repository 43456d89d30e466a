//! The UDP rig link and external rigs: datagrams that must be rejected are counted by
//! reason and never used (in process, on real loopback sockets, with loss, duplicates,
//! reordering and garbage scripted exactly); a cut link leaves the rig holding on stale
//! commands and trips the emulator on stale samples (the real cores behind real sockets);
//! `hil --rig-link udp` is clean and faithful while garbage is sent to every port it
//! listens on; the example rig, written from the C header alone, completes sessions over
//! iceoryx2 and over UDP that replay bit for bit; killing the link makes the far rig hold.
//! Assertions are on counts, states and physics, never on timings; no retries.

use std::net::{SocketAddr, UdpSocket};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::law_command;
use fastemu::child::ChildGuard;
use fastemu::hil::config::{default_hil_config, HilConfig};
use fastemu::hil::controller::ControllerCore;
use fastemu::hil::emulator::{EmulatorCore, EmulatorIo};
use fastemu::hil::fault::Fault;
use fastemu::ipc::messages::{rig_state, run_command, DisplacementSample, ForceSetpoint};
use fastemu::link::protocol::{
    encode_command, encode_sample, encode_status, CommandDatagram, ControlDatagram, Datagram,
    Reject, SampleDatagram, Side, StatusDatagram, MAX_DATAGRAM_BYTES, SAMPLE_BYTES,
};
use fastemu::link::rig_end::UdpRigEnd;
use fastemu::link::socket::{free_loopback_pair, open_link_socket, LinkReceiver, Receive};
use fastemu::rig::core::RigCore;
use fastemu::rig::process::RigTransport;
use fastemu::rt::CycleStats;

use super::hil_processes::{
    assert_hold_in_records, assert_nothing_left, ctl, export_csv, faults, scratch_dir,
    spawn_hil_with, the_child, write_config, Hil, Scratch, AXLE_S, FASTEMU, LOCK_WAIT, SERIAL,
};

const EXAMPLE_RIG: &str = env!("CARGO_BIN_EXE_example_rig");

fn sample_datagram(seq: u64) -> SampleDatagram {
    SampleDatagram {
        sample_sequence: seq,
        rig_time_ns: seq * 244_141,
        displacement_m: 4e-4,
        actuator_force_n: 2e4,
        status: 0,
        rig_state: rig_state::RUNNING,
        rig_fault_code: 0,
        echo_command_time_ns: 0,
        echo_hold_ns: 0,
        commanded_force_n: 2e4,
    }
}

/// Reads until nothing more comes for 100 ms; returns the accepted sample sequences.
fn drain_samples(rx: &mut LinkReceiver) -> Vec<u64> {
    let mut got = Vec::new();
    loop {
        match rx.receive() {
            Receive::Accepted(r) => {
                if let Datagram::Sample(d) = r.datagram {
                    got.push(d.sample_sequence);
                }
            }
            Receive::Rejected(_) => {}
            Receive::Nothing => return got,
        }
    }
}

#[test]
fn link_counts_loss_duplicates_reordering_and_garbage_by_reason_and_uses_none_of_them() {
    // Both ends bound here and kept: no other test can take a port in between.
    let fastemu_socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let fastemu_addr = fastemu_socket.local_addr().unwrap();
    let rig = UdpSocket::bind("127.0.0.1:0").unwrap();
    let rig_addr = rig.local_addr().unwrap();
    let (_tx, mut rx) = open_link_socket(
        fastemu_socket,
        rig_addr,
        Side::Fastemu,
        Some(Duration::from_millis(100)),
    )
    .unwrap();
    const PERIOD_NS: u64 = 244_141;
    rx.expect_period(PERIOD_NS);
    // The rig's address (`rig`), sending whatever the script says; and a stranger.
    let stranger = UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut buf = [0u8; MAX_DATAGRAM_BYTES];
    let mut send_sample = |seq: u64, from: &UdpSocket| {
        let n = encode_sample(&mut buf, seq, 1000 + seq, &sample_datagram(seq));
        from.send_to(&buf[..n], fastemu_addr).unwrap();
        buf[..n].to_vec()
    };
    // Sequence 3 lost, 4 duplicated, 5 after 6 (reordered), 100 from a stranger.
    for seq in [0, 1, 2, 4, 4, 6, 5, 7] {
        send_sample(seq, &rig);
    }
    let good = send_sample(100, &stranger);
    // Malformed datagrams from the peer's own address.
    let mut truncated = good.clone();
    truncated.truncate(SAMPLE_BYTES - 1);
    let mut oversized = good.clone();
    oversized.push(0);
    let mut bad_magic = good.clone();
    bad_magic[0] = b'X';
    let mut bad_version = good.clone();
    bad_version[4] = 1; // the previous link protocol
    let mut unknown_kind = good.clone();
    unknown_kind[6] = 9;
    let mut command = [0u8; MAX_DATAGRAM_BYTES];
    let n = encode_command(
        &mut command,
        0,
        0,
        &CommandDatagram {
            command: law_command(0),
            echo_sample_time_ns: 0,
        },
    );
    for d in [
        &truncated[..],
        &oversized[..],
        &bad_magic[..],
        &bad_version[..],
        &unknown_kind[..],
        &command[..n],
    ] {
        rig.send_to(d, fastemu_addr).unwrap();
    }
    // A status with another period is refused for its content; though its sequence number
    // is high, it moves no window: the good status after it, with a lower one, is taken.
    for (seq, period_ns) in [(50, 1), (1, PERIOD_NS)] {
        let n = encode_status(
            &mut buf,
            seq,
            0,
            &StatusDatagram {
                rig_state: 100,
                rig_fault_code: 0,
                period_ns,
            },
        );
        rig.send_to(&buf[..n], fastemu_addr).unwrap();
    }
    // Random garbage from the peer's address: every datagram rejected, none used.
    let mut x: u64 = 0x2545_f491_4f6c_dd1d;
    let mut random = |n: usize| -> Vec<u8> {
        (0..n)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                x as u8
            })
            .collect()
    };
    for i in 0..200usize {
        let len = [0, 1, 7, 23, 24, 40, 56, 87, 88, 89, 143, 144, 145, 1400][i % 14];
        rig.send_to(&random(len), fastemu_addr).unwrap();
    }
    let accepted = drain_samples(&mut rx);
    assert_eq!(
        accepted,
        vec![0, 1, 2, 4, 6, 7],
        "only new, well-formed samples"
    );
    let c = rx.counts;
    assert_eq!(c.lost.sample, 2, "3 and 5 never accepted");
    assert_eq!(c.accepted.status, 1, "the good status only");
    assert_eq!(rx.wrong_period_ns, 1);
    // The random garbage: lengths below 4 are truncated, the rest have no magic (of 200
    // datagrams cycling through 14 lengths, 30 have length 0 or 1).
    for (reason, n) in [
        (Reject::Duplicate, 1),
        (Reject::Reordered, 1),
        (Reject::ForeignSender, 1),
        (Reject::Truncated, 1 + 30),
        (Reject::Oversized, 1),
        (Reject::BadMagic, 1 + 170),
        (Reject::BadVersion, 1),
        (Reject::UnknownKind, 1),
        (Reject::WrongDirection, 1),
        (Reject::BadContent, 1),
    ] {
        assert_eq!(c.rejected_of(reason), n, "{reason}: {c:?}");
    }
    assert_eq!(c.rejected_total(), 10 + 200, "{c:?}");
}

/// The emulator's transport for the in-process test: the link's receiver (waits, bounded,
/// for the sample it expects, as the process does); nothing arrives once `cut`.
struct LinkIo<'a> {
    rx: &'a mut LinkReceiver,
    setpoints: Vec<ForceSetpoint>,
    cut: bool,
}

impl EmulatorIo for LinkIo<'_> {
    fn receive_samples(&mut self, expected: u64, on_sample: &mut dyn FnMut(DisplacementSample)) {
        if self.cut {
            return;
        }
        let t = Instant::now();
        loop {
            match self.rx.receive() {
                Receive::Accepted(r) => {
                    if let Datagram::Sample(d) = r.datagram {
                        on_sample(d.to_sample(r.arrival_ns));
                        if d.sample_sequence >= expected {
                            return;
                        }
                    }
                }
                _ => assert!(
                    t.elapsed() < Duration::from_secs(5),
                    "sample {expected} lost"
                ),
            }
        }
    }
    fn publish_setpoint(&mut self, setpoint: ForceSetpoint) {
        self.setpoints.push(setpoint);
    }
}

#[test]
fn a_cut_link_leaves_the_rig_holding_and_trips_the_emulator() {
    let cfg: HilConfig = default_hil_config().unwrap();
    let period_ns = cfg.loop_.period_ns;
    let fastemu_socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let rig_socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let (fastemu_addr, rig_addr) = (
        fastemu_socket.local_addr().unwrap(),
        rig_socket.local_addr().unwrap(),
    );
    let (mut tx, mut rx) = open_link_socket(fastemu_socket, rig_addr, Side::Fastemu, None).unwrap();
    let mut rig_end =
        UdpRigEnd::open_socket(rig_socket, fastemu_addr, period_ns, Duration::from_secs(5))
            .unwrap();
    tx.send_control(&ControlDatagram {
        command: run_command::START,
        control_sequence: 1,
        start_delay_ns: 0,
        period_ns,
    });
    rig_end.wait_for_start().unwrap();
    let mut rig = RigCore::new(&cfg);
    let mut emulator = EmulatorCore::new(
        &cfg.augmented,
        &cfg.loop_,
        cfg.emulator,
        cfg.stall_limit_periods(),
    );
    let mut controller = ControllerCore::new(
        cfg.controller,
        cfg.safety.actions,
        period_ns,
        (cfg.safety.stall_limit_s * 1e9) as u64,
    );
    controller.set_start_time_ns(0);
    let cut_at = 2048u64; // 0.5 s
    let stale = u64::from(cfg.rig.command_stale_periods);
    let mut records = Vec::new();
    let mut emulator_trip_cycle = None;
    let mut last_command_period = 0;
    for k in 0..cut_at + 4096 {
        let cut = k >= cut_at;
        if let Some(s) = rig.measure(k * period_ns) {
            rig_end.send_sample(&s);
        }
        // fastemu's end: the emulator steps on the sample, the controller answers.
        let mut io = LinkIo {
            rx: &mut rx,
            setpoints: Vec::new(),
            cut,
        };
        let stats = CycleStats {
            cycle_idx: k,
            deadline_ns: k * period_ns,
            woke_ns: k * period_ns,
            wake_late_ns: 0,
            missed_deadlines: 0,
        };
        emulator.cycle(&stats, &mut io, &mut |_| {});
        if emulator.fault().is_some() && emulator_trip_cycle.is_none() {
            emulator_trip_cycle = Some(k);
        }
        // The controller answers from the rig's second sample on (it reads the gain from
        // the rig's own command first: `Compensator::ready_to_command`).
        let mut sent_now = false;
        if !cut {
            for sp in io.setpoints {
                if let Some((cmd, _)) = controller.on_setpoint(&sp, k * period_ns + 30_000) {
                    sent_now = true;
                    tx.send_command(&CommandDatagram {
                        command: cmd,
                        echo_sample_time_ns: 0,
                    });
                    // Loopback delivers at once; the rig reads it in the same period.
                    last_command_period = k;
                }
            }
        }
        let t = Instant::now();
        let mut got = false;
        while !cut && sent_now && !got {
            rig_end.receive_commands(&mut |c| {
                rig.on_command(c);
                got = true;
            });
            assert!(t.elapsed() < Duration::from_secs(5), "command {k} lost");
        }
        if cut {
            rig_end.receive_commands(&mut |c| rig.on_command(c));
        }
        records.push(rig.finish_period(0, false));
    }
    // Up to the cut: force control, nothing latched.
    assert!(records[..cut_at as usize]
        .iter()
        .all(|r| r.state == rig_state::RUNNING && r.fault_code == 0));
    // The rig holds on the stale commands, by itself, one stale limit after the last.
    let trip = rig.servo().trip().expect("the rig latched no fault");
    assert_eq!(trip.fault, Fault::CommandsStale);
    assert!(
        trip.step_idx > last_command_period + stale
            && trip.step_idx <= last_command_period + stale + 2,
        "tripped at period {}, last command at {last_command_period}",
        trip.step_idx
    );
    let after: Vec<_> = records[trip.step_idx as usize + 1..].iter().collect();
    assert!(after.iter().all(|r| r.state == rig_state::HOLD));
    let pre: Vec<f64> = records[..cut_at as usize].iter().map(|r| r.x_m).collect();
    let lo = pre.iter().cloned().fold(f64::INFINITY, f64::min);
    let hi = pre.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    assert!(
        after
            .iter()
            .all(|r| r.x_m > lo - 0.5e-3 && r.x_m < hi + 0.5e-3),
        "the held specimen left the pre-cut range"
    );
    // The emulator trips on the stale samples after its limit.
    assert_eq!(emulator.fault(), Some(Fault::TooManyStaleSamples));
    let trip_cycle = emulator_trip_cycle.unwrap();
    assert_eq!(
        trip_cycle - cut_at,
        u64::from(cfg.loop_.trip_after_stale_samples),
        "the emulator tripped {} cycles after the cut",
        trip_cycle - cut_at
    );
    // Nothing was lost or rejected on the way.
    assert_eq!(rx.counts.rejected_total(), 0);
    assert_eq!(rx.counts.lost.sample, 0);
}

/// `127.0.0.1:P` of `what` in the `hil` progress line naming the link's two ends.
fn port_in(stderr: &str, what: &str) -> Option<SocketAddr> {
    let line = stderr.lines().find(|l| l.contains("fastemu's link at"))?;
    let rest = &line[line.find(what)? + what.len()..];
    rest.split(|c: char| c == ',' || c.is_whitespace())
        .find(|w| !w.is_empty())?
        .parse()
        .ok()
}

/// `hil --rig-link udp` for 3 s of the default scenario (first axle at `AXLE_S`):
/// (scratch directory, report directory, the running `hil`).
fn spawn_udp_run(name: &str) -> (Scratch, std::path::PathBuf, Hil) {
    let dir = scratch_dir(name);
    let report = dir.join("report");
    let hil = spawn_hil_with(
        &write_config(&dir, &[], ""),
        &report,
        3.0,
        &["--rig-link", "udp"],
    );
    (dir, report, hil)
}

#[test]
fn udp_link_run_is_clean_and_faithful_under_garbage_and_replays() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (dir, report, mut hil) = spawn_udp_run("udp-link");
    hil.at(0.2);
    let stderr = hil.stderr();
    let link = port_in(&stderr, "fastemu's link at ").expect("link address printed");
    let rig = port_in(&stderr, "the rig at ").expect("rig address printed");
    // 2 s of garbage to both ends from a stranger: random bytes, right magic with a wrong
    // version, well-formed samples and commands, a jumbo datagram.
    let stranger = UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut sent = [0u64; 2];
    let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
    let mut buf = [0u8; MAX_DATAGRAM_BYTES];
    let t = Instant::now();
    let mut i = 0u64;
    while t.elapsed() < Duration::from_secs(2) {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        let datagram: Vec<u8> = match i % 5 {
            0 => (0..(x % 200) as usize)
                .map(|j| (x >> (j % 56)) as u8)
                .collect(),
            1 => {
                let n = encode_sample(&mut buf, i, 0, &sample_datagram(i));
                buf[4] = 7;
                buf[..n].to_vec()
            }
            2 => {
                let n = encode_sample(&mut buf, i, 0, &sample_datagram(i));
                buf[..n].to_vec()
            }
            3 => {
                let command = CommandDatagram {
                    command: law_command(0),
                    echo_sample_time_ns: 0,
                };
                let n = encode_command(&mut buf, i, 0, &command);
                buf[..n].to_vec()
            }
            _ => vec![0xA5; 1400],
        };
        for (j, to) in [link, rig].into_iter().enumerate() {
            if stranger.send_to(&datagram, to).is_ok() {
                sent[j] += 1;
            }
        }
        i += 1;
        std::thread::sleep(Duration::from_millis(2));
    }
    let (code, json) = hil.finish(Duration::from_secs(60));
    assert_eq!(code, 0, "hil failed: {json}\n{}", hil.stderr());
    assert_eq!(json["clean"], true, "{}", json["not_clean_because"]);
    let rel = json["fidelity"]["displacement_rel_rms"].as_f64().unwrap();
    assert!(rel < 0.02, "displacement relative RMS error {rel}");
    let l = &json["link"];
    assert_eq!(l["transport"], "udp");
    assert_eq!(
        l["rejected"]["foreign_sender"].as_u64(),
        Some(sent[0]),
        "{l}"
    );
    assert_eq!(l["rejected_total"].as_u64(), Some(sent[0]), "{l}");
    assert_eq!(
        l["rig_end"]["rejected"]["foreign_sender"].as_u64(),
        Some(sent[1]),
        "{l}"
    );
    let steps = json["steps"].as_u64().unwrap();
    assert!(l["received"]["sample"].as_u64().unwrap() >= steps);
    assert_eq!(l["lost"]["sample"], 0);
    assert_eq!(l["rig_finished"], true);
    for p in ["p50", "p99", "p999", "max"] {
        assert!(l["latency_ns"][p].is_u64(), "link.latency_ns.{p}: {l}");
    }
    replay_is_bit_for_bit(&report);
    assert_nothing_left(&json);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn killing_the_link_leaves_the_far_rig_holding() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (dir, report, mut hil) = spawn_udp_run("link-kill");
    let link = the_child(&hil, " link --bind");
    hil.at(AXLE_S);
    unsafe { libc::kill(link as i32, libc::SIGKILL) };
    let (code, json) = hil.finish(Duration::from_secs(60));
    assert_eq!(code, 2, "{json}");
    // The link's death is named, whichever came first in the list: on a loaded machine the
    // rig's own staleness (50 ms) was once reported before the orchestrator reaped the link.
    let f = faults(&json);
    assert!(
        f.iter()
            .any(|x| x.starts_with("link: ") && x.contains("signal 9")),
        "{f:?}"
    );
    let safety = json["safety"]["faults"].as_array().unwrap();
    assert!(
        safety
            .iter()
            .any(|s| s["fault"] == "commands-stale" && s["action"] == "hold"),
        "{safety:?}"
    );
    assert_hold_in_records(&report, AXLE_S, "link killed");
    assert_nothing_left(&json);
    std::fs::remove_dir_all(&dir).ok();
}

/// The example rig's programme in the configuration: no preload ramp, no train; the same
/// mass and damping.
const EXAMPLE_RIG_SCENARIO: &[(&str, &str)] = &[
    ("preload_n = 20000.0", "preload_n = 0.0"),
    ("train_speed_kmh = 200.0", "train_speed_kmh = 0.0"),
];

/// Runs the example rig for 2.5 s with `rig_args` to its end (killed and reaped on any
/// exit path); its exit status, `None` when it outlived 60 s, and its stderr (kept in
/// `dir`).
fn run_example_rig(dir: &Path, rig_args: &[&str]) -> (Option<std::process::ExitStatus>, String) {
    let path = dir.join("example_rig.stderr");
    let rig = Command::new(EXAMPLE_RIG)
        .args(rig_args)
        .args(["--duration-s", "2.5"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&path).unwrap())
        .spawn()
        .unwrap();
    let status = ChildGuard::new(rig)
        .wait_timeout(Duration::from_secs(60))
        .unwrap();
    (status, std::fs::read_to_string(&path).unwrap_or_default())
}

/// Runs `hil --rig external ...` and the example rig with `rig_args`; returns hil's JSON.
fn external_session(name: &str, hil_args: &[&str], rig_args: &[&str]) -> serde_json::Value {
    let dir = scratch_dir(name);
    let report = dir.join("report");
    let config = write_config(&dir, EXAMPLE_RIG_SCENARIO, "");
    let mut args = vec!["--rig", "external"];
    args.extend_from_slice(hil_args);
    let mut hil = spawn_hil_with(&config, &report, 2.5, &args);
    let (status, rig_stderr) = run_example_rig(&dir, rig_args);
    assert!(
        status.is_some_and(|s| s.success()),
        "example rig: {status:?}\n{rig_stderr}"
    );
    // Its loop allocates nothing of its own; over iceoryx2, iceoryx2 0.10 allocates one
    // block per publish (`ipc_alloc`), over UDP nothing does.
    let allocations: u64 = rig_stderr
        .lines()
        .find_map(|l| {
            l.rsplit("; ")
                .next()?
                .strip_suffix(" allocations in the loop")
        })
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{name}: no allocation count: {rig_stderr}"));
    if rig_args[0] == "--udp" {
        assert_eq!(allocations, 0, "{name}: {rig_stderr}");
    }
    let (code, json) = hil.finish(Duration::from_secs(60));
    assert_eq!(code, 0, "{name}: {json}\n{}", hil.stderr());
    assert_eq!(json["clean"], true, "{name}: {}", json["not_clean_because"]);
    let steps = json["steps"].as_u64().unwrap();
    assert!(
        steps >= (2.5 * 4096.0 * 0.99) as u64,
        "{name}: {steps} steps"
    );
    let rel = json["fidelity"]["displacement_rel_rms"].as_f64().unwrap();
    assert!(rel < 0.02, "{name}: displacement relative RMS error {rel}");
    assert!(json["rig"]["kind"] == "external");
    assert_eq!(
        json["safety"]["final_state"], "finished",
        "{}",
        json["safety"]
    );
    assert_eq!(json["deadline_misses_rig"], serde_json::Value::Null);
    // No loop of fastemu's allocated from the system: the emulator's and controller's, and
    // over UDP the link's two (their sections live: requests counted in them). A loop
    // may free a system block per port it shares with the rig (the controller's loop
    // has two: commands out, the rig's heartbeats in), at the session's end: when the rig (or the link) has
    // gone before STOP reaches the loop, iceoryx2 drops the port's connection to the
    // departed counterpart (its 32-byte block, allocated when the ports connected before
    // the loop) in the loop's next receive (traced 2026-11-29: `Receiver::receive` ->
    // `receive_from_to_be_removed_connections`, at the loop's last request; every
    // external session over iceoryx2 did it in the emulator's loop). The external rig's
    // loop is its own.
    let udp = !json["link"].is_null();
    for process in ["emulator", "controller", "link"] {
        let pool = &json["rt_pool"][process];
        if process == "link" && !udp {
            assert!(pool.is_null(), "{name}: {pool}");
            continue;
        }
        assert_eq!(
            pool["loop_system_allocations"], 0,
            "{name} {process}: {pool}"
        );
        assert!(
            pool["loop_system_frees"].as_u64().unwrap() <= 2,
            "{name} {process}: {pool}"
        );
        assert!(
            pool["loop_requests"].as_u64().unwrap() > 0,
            "{name} {process}: {pool}"
        );
    }
    replay_is_bit_for_bit(&report);
    assert_nothing_left(&json);
    std::fs::remove_dir_all(&dir).ok();
    json
}

fn replay_is_bit_for_bit(report: &Path) {
    let out = Command::new(FASTEMU)
        .arg("replay")
        .arg("--record")
        .arg(report.join("records.mcap"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains(" 0 forces differ"),
        "{text}"
    );
}

#[test]
fn an_external_rig_written_from_the_header_completes_sessions_over_iceoryx2_and_udp() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let run_id = format!("feit{}ext", std::process::id());
    let json = external_session("external-ipc", &["--run-id", &run_id], &["--ipc", &run_id]);
    assert_eq!(json["run_id"], run_id.as_str());
    assert!(json["link"].is_null());

    let (link, rig) = free_loopback_pair().unwrap();
    let (link, rig) = (link.to_string(), rig.to_string());
    let json = external_session(
        "external-udp",
        &[
            "--rig-link",
            "udp",
            "--link-bind",
            &link,
            "--link-peer",
            &rig,
        ],
        &["--udp", &rig, &link],
    );
    let l = &json["link"];
    assert_eq!(l["rejected_total"], 0, "{l}");
    assert_eq!(l["rig_finished"], true, "{l}");
    assert!(l["received"]["sample"].as_u64().unwrap() >= json["steps"].as_u64().unwrap());
}

/// An external rig holds after the emulator's own fault (a 300 ms stall of the emulator
/// at 1 s: the controller commands the hold on stale setpoints, the emulator trips
/// `emulator-stalled` when it runs again). fastemu has no records of the rig itself; the
/// emulator goes on recording the rig's samples after its fault without stepping the
/// model, so the hold is in the records and the report: the run ends in the hold, held
/// from the first sample that carried it to the end, and the samples recorded after the
/// fault say the rig held.
#[test]
fn an_external_rigs_hold_after_the_emulators_fault_is_in_the_records_and_the_report() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (dir, code, json, stderr) = external_run_with(
        "external-hold",
        "\n[[inject]]\nprocess = \"emulator\"\nkind = \"stall\"\nat_s = 1.0\nduration_ms = 300\n",
    );
    assert_ne!(code, 0, "{stderr}");
    let faults = json["safety"]["faults"].as_array().unwrap();
    let emulator = faults
        .iter()
        .find(|f| f["process"] == "emulator")
        .unwrap_or_else(|| panic!("no emulator fault: {json}"));
    assert_eq!(emulator["fault"], "emulator-stalled", "{emulator}");
    assert_eq!(json["safety"]["final_state"], "hold", "{}", json["safety"]);
    let held_s = json["safety"]["held_s"].as_f64().unwrap();
    // From the first sample that carried the hold (after the stalled emulator missed some) to the end.
    assert!(held_s > 0.5, "held {held_s} s");
    // The records after the fault: the rig's samples, in its hold, to the end of the run.
    let rows: Vec<(f64, u32)> =
        exported_columns(&dir, "emulator_after_fault.csv", ["t_s", "rig_state"])
            .into_iter()
            .map(|[t, state]| (t, state as u32))
            .collect();
    let emulator_trip = emulator["detected_at_s"].as_f64().unwrap();
    assert!(rows.len() > 2048, "{} samples after the fault", rows.len());
    assert!(
        rows.iter().all(|r| r.0 >= emulator_trip - 0.3),
        "{:?}",
        rows.first()
    );
    assert!(
        rows.iter().all(|r| r.1 == 2),
        "not all in the hold: {:?}",
        rows.iter().find(|r| r.1 != 2)
    );
    assert_nothing_left(&json);
}

/// A first command late (a loaded machine once delayed it to 7.6 ms: 1.6 % error, a 20 um
/// transient, not clean): here the controller stalls 12 ms at the start. Until the command
/// comes the example rig holds its start with the programme's change fed forward (header
/// 2c), so the specimen waits at rest; that wait is the rig's, not the rendering's, so the
/// comparison starts where the rig first applies a command, the reference from the state
/// measured there. Before: 6.35 % error and a 58 um transient on this case.
#[test]
fn an_external_rigs_wait_for_a_late_first_command_is_at_rest_and_not_compared() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (dir, _code, json, stderr) = external_run_with(
        "ext-late-first",
        "\n[[inject]]\nprocess = \"controller\"\nkind = \"stall\"\nat_s = 0.0005\nduration_ms = 12\n",
    );
    assert_eq!(json["safety"]["faults"], serde_json::json!([]), "{stderr}");
    let from = json["fidelity"]["compared_from_s"].as_f64().unwrap();
    assert!(from >= 0.010, "compared from {from} s");
    // The wait, as the emulator recorded the rig's samples: at rest where it started.
    let waited: Vec<f64> = exported_columns(&dir, "emulator.csv", ["t_s", "z_used_m"])
        .into_iter()
        .filter(|[t, _]| *t < from)
        .map(|[_, z]| z)
        .collect();
    assert!(
        waited.len() >= 40,
        "{} samples before the first command",
        waited.len()
    );
    let moved = waited.iter().fold(0.0f64, |m, z| m.max(z.abs()));
    assert!(
        moved < 1e-7,
        "the specimen moved {moved} m before the first command"
    );
    let rel = json["fidelity"]["displacement_rel_rms"].as_f64().unwrap();
    assert!(rel < 0.03, "displacement relative RMS error {rel}");
}

/// An external rig whose loop trips (the example rig declared, its lead fixed at 0 with
/// nothing to make up for it): its hold stays where it tripped, the report reads its rest
/// from its measured displacement, and the trip is judged on the declared actuator. A
/// lab's trial (2026-11-29) found the example rig holding its last force as the
/// equilibrium: mid-swing in a tripped loop, 2 kN off the load, and the specimen went 0.93
/// mm into the hold; every fault line said "never at rest".
#[test]
fn an_external_rigs_trip_holds_where_it_tripped_comes_to_rest_and_is_judged_on_the_declaration() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = scratch_dir("ext-trip");
    let report = dir.join("report");
    let mut replacements = EXAMPLE_RIG_SCENARIO.to_vec();
    replacements.extend([
        ("initial_delay_us = 252.0", "initial_delay_us = 0.0"),
        ("adapt = true", "adapt = false"),
        ("passivity_guard = true", "passivity_guard = false"),
        (
            "plan_for_external_rig = false",
            "plan_for_external_rig = true",
        ),
    ]);
    let config = write_config(&dir, &replacements, "");
    let run_id = format!("feit{}exttrip", std::process::id());
    let mut hil = spawn_hil_with(
        &config,
        &report,
        2.5,
        &["--rig", "external", "--run-id", &run_id, "--run-unstable"],
    );
    let (status, rig_stderr) = run_example_rig(&dir, &["--ipc", &run_id]);
    assert!(
        status.is_some(),
        "the example rig did not end: {rig_stderr}"
    );
    let (code, json) = hil.finish(Duration::from_secs(60));
    let stderr = hil.stderr();
    assert_nothing_left(&json);
    assert_eq!(code, 2, "{stderr}");
    let faults = json["safety"]["faults"].as_array().unwrap();
    let trip = faults
        .iter()
        .find(|f| f["process"] == "emulator")
        .unwrap_or_else(|| panic!("no emulator fault: {stderr}"));
    assert_eq!(trip["fault"], "loop-unstable", "{trip}");
    let judged = &trip["leads_after_trip"];
    assert_eq!(judged["judged"], "declared", "{judged}");
    assert_eq!(judged["verdict"], "lead-outside", "{judged}");
    assert!(stderr.contains("the declared actuator"), "{stderr}");
    // The rig's hold, from its samples: near where it tripped, and at rest.
    let rig = faults
        .iter()
        .find(|f| f["process"] == "external rig")
        .unwrap_or_else(|| panic!("no external rig fault: {stderr}"));
    assert_eq!(rig["fault"], "hold-requested", "{rig}");
    // The swing at the trip carries on into the hold (18-117 um on this machine, by when
    // the trip came), but the hold ends where it latched: before, 0.91 mm away.
    let excursion = rig["largest_excursion_m"].as_f64().unwrap();
    assert!(excursion < 500e-6, "{} um into the hold", excursion * 1e6);
    let latched = rig["position_at_fault_m"].as_f64().unwrap();
    let held = exported_columns(&dir, "emulator_after_fault.csv", ["z_measured_m"]);
    let end = held.last().expect("samples after the fault")[0];
    assert!(
        (end - latched).abs() < 50e-6,
        "held at {} um, latched at {} um",
        end * 1e6,
        latched * 1e6
    );
    let rest = rig["time_to_rest_s"].as_f64();
    assert!(rest.is_some_and(|t| t < 1.0), "{rig}");
    assert_eq!(json["safety"]["at_rest"], true, "{}", json["safety"]);
    assert!(!stderr.contains("never at rest"), "{stderr}");
}

/// The columns `names` of `file` (e.g. `emulator.csv`) in the CSV export of the run whose
/// report is in `dir/report`, row by row.
fn exported_columns<const N: usize>(dir: &Path, file: &str, names: [&str; N]) -> Vec<[f64; N]> {
    let csv = dir.join("csv");
    export_csv(&dir.join("report").join("records.mcap"), &csv);
    let text = std::fs::read_to_string(csv.join(file)).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let cols = names.map(|name| {
        header
            .iter()
            .position(|h| *h == name)
            .unwrap_or_else(|| panic!("{file} has no column {name}"))
    });
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            cols.map(|c| f[c].parse().unwrap())
        })
        .collect()
}

/// Runs the example rig over iceoryx2 under `hil --rig external` with `inject` appended to
/// the configuration; returns the scratch directory (the report in `report/`), hil's exit
/// code, JSON and stderr.
fn external_run_with(name: &str, inject: &str) -> (Scratch, i32, serde_json::Value, String) {
    let dir = scratch_dir(name);
    let report = dir.join("report");
    let config = write_config(&dir, EXAMPLE_RIG_SCENARIO, inject);
    let run_id = format!("feit{}{name}", std::process::id());
    let mut hil = spawn_hil_with(
        &config,
        &report,
        2.5,
        &["--rig", "external", "--run-id", &run_id],
    );
    let (status, rig_stderr) = run_example_rig(&dir, &["--ipc", &run_id]);
    assert!(
        status.is_some(),
        "{name}: the example rig did not end: {rig_stderr}"
    );
    let (code, json) = hil.finish(Duration::from_secs(60));
    let stderr = hil.stderr();
    assert_nothing_left(&json);
    (dir, code, json, stderr)
}

/// fastemu records an external rig's samples in the emulator. A new user's rig (UDP,
/// 2026-11-28) held on the controller's hold command after the emulator was killed, and
/// the report said `final_state` "finished", `held_s` 0: nothing recorded the hold. The
/// rig's heartbeat says it held: the report now ends in "hold" and says that the records
/// miss it and why. With the controller killed the emulator lives and records the rig's
/// own `commands-stale` and its hold: that fault's action is the rig's hold (it read "the
/// controller acts", the controller dead), and the programme time stops at the hold (it
/// counted the hold's 1 s as programme).
#[test]
fn an_external_rigs_hold_the_records_miss_is_told_from_its_heartbeat() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (_dir, code, json, stderr) = external_run_with(
        "ext-emu-kill",
        "\n[[inject]]\nprocess = \"emulator\"\nkind = \"kill\"\nat_s = 1.0\n",
    );
    assert_eq!(code, 2, "{stderr}");
    let safety = &json["safety"];
    assert_eq!(safety["final_state"], "hold", "{safety}");
    let note = safety["hold_not_recorded"].as_str().unwrap_or_default();
    assert!(
        note.contains("reported a hold (hold-requested) in its heartbeat from about 1."),
        "{safety}"
    );
    assert!(stderr.contains(note), "{stderr}");

    let (_dir, code, json, stderr) = external_run_with(
        "ext-ctl-kill",
        "\n[[inject]]\nprocess = \"controller\"\nkind = \"kill\"\nat_s = 1.0\n",
    );
    assert_eq!(code, 2, "{stderr}");
    let safety = &json["safety"];
    let rig = safety["faults"]
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["fault"] == "commands-stale")
        .unwrap_or_else(|| panic!("no commands-stale: {safety}"));
    assert_eq!(rig["action"], "hold", "{rig}");
    assert_eq!(safety["final_state"], "hold", "{safety}");
    assert!(safety["hold_not_recorded"].is_null(), "{safety}");
    assert!(safety["held_s"].as_f64().unwrap() > 0.5, "{safety}");
    // The programme stopped at the hold: 1 s and the stale commands' 50 ms, not the 2.5 s
    // of samples.
    let programme_s = json["programme"]["programme_time_s"].as_f64().unwrap();
    assert!(
        (1.0..1.2).contains(&programme_s),
        "programme time {programme_s} s"
    );
}

#[test]
fn an_external_rig_that_never_connects_is_a_named_fault_that_leaves_nothing() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = scratch_dir("external-none");
    let config = write_config(&dir, &[], "");
    let run_id = format!("feit{}none", std::process::id());
    let mut hil = spawn_hil_with(
        &config,
        &dir.join("report"),
        2.0,
        &[
            "--rig",
            "external",
            "--run-id",
            &run_id,
            "--rig-wait-s",
            "1",
        ],
    );
    let (code, json) = hil.finish(Duration::from_secs(30));
    let stderr = hil.stderr();
    // No verdict: the loop never ran.
    assert_eq!(code, 3, "{stderr}");
    assert_eq!(json["clean"], false, "{json}");
    assert!(stderr.contains("no rig connected within 1 s"), "{stderr}");
    // Nothing was recorded, and that is said once, without a warning about merging.
    assert!(stderr.contains("the loop never started"), "{stderr}");
    assert!(!stderr.contains("not merged"), "{stderr}");
    assert_eq!(json["records"]["parts"], 0, "{json}");
    assert_eq!(json["run_id"], run_id.as_str());
    assert_nothing_left(&json);
}

/// `fastemu ctl stop` while `hil` waits for an external rig ends the run at once (not
/// at the end of its wait), as an operator stop with nothing left; `ctl` says the run
/// ended before it started and does not hold the run's clearing up (its own node is one
/// of the run's). A `hold` before the start is answered as refused.
#[test]
fn ctl_stop_ends_a_run_that_waits_for_its_external_rig() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = scratch_dir("external-ctl-stop");
    let config = write_config(&dir, &[], "");
    let run_id = format!("feit{}wait", std::process::id());
    let mut hil = spawn_hil_with(
        &config,
        &dir.join("report"),
        2.0,
        &[
            "--rig",
            "external",
            "--run-id",
            &run_id,
            "--rig-wait-s",
            "60",
        ],
    );
    // Registered as soon as it waits.
    let t = Instant::now();
    while !ctl(&["--run-id", &run_id, "status"]).0 {
        assert!(t.elapsed() < Duration::from_secs(20), "never registered");
        std::thread::sleep(Duration::from_millis(100));
    }
    // A hold before the start is refused by the run's hil, which answers it.
    let (ok, text) = ctl(&["--run-id", &run_id, "hold"]);
    assert!(!ok && text.contains("has not started yet"), "{text}");
    let (ok, text) = ctl(&["--run-id", &run_id, "stop"]);
    assert!(ok && text.contains("ended before it started"), "{text}");
    let (code, json) = hil.finish(Duration::from_secs(30));
    // Ended by the stop, not by the wait's end (that fault is "no rig connected").
    let stderr = hil.stderr();
    assert_eq!(code, 3, "{stderr}");
    assert!(
        stderr.contains("stopped by fastemu ctl before the start"),
        "{stderr}"
    );
    assert_eq!(json["operator_stop"], true, "{json}");
    assert_eq!(json["records"]["parts"], 0, "{json}");
    assert_nothing_left(&json);
}

/// A rig of the previous link protocol (1: commands without the compensation) is named at
/// once with its version and fastemu's, instead of waiting out the rig's time-out.
#[test]
fn a_rig_of_the_previous_link_protocol_is_named_with_its_version() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = scratch_dir("link-old-version");
    let config = write_config(&dir, &[], "");
    let (link, rig) = free_loopback_pair().unwrap();
    let mut hil = spawn_hil_with(
        &config,
        &dir.join("report"),
        2.0,
        &[
            "--rig",
            "external",
            "--rig-link",
            "udp",
            "--link-bind",
            &link.to_string(),
            "--link-peer",
            &rig.to_string(),
            "--rig-wait-s",
            "20",
        ],
    );
    // The old rig announces itself: READY status datagrams whose header says version 2,
    // every 10 ms until hil has ended.
    let socket = UdpSocket::bind(rig).unwrap();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let sender = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut buf = [0u8; MAX_DATAGRAM_BYTES];
            let status = StatusDatagram {
                rig_state: 100,
                rig_fault_code: 0,
                period_ns: 244_141,
            };
            let mut seq = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                let n = encode_status(&mut buf, seq, 0, &status);
                buf[4] = 2; // the previous protocol's version
                let _ = socket.send_to(&buf[..n], link);
                seq += 1;
                std::thread::sleep(Duration::from_millis(10));
            }
        })
    };
    // Named at once: well before the 20 s the rig was given.
    let (code, json) = hil.finish(Duration::from_secs(15));
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    sender.join().unwrap();
    let stderr = hil.stderr();
    // No verdict: the loop never ran (a new user's rig of protocol 2 got exit 2 before).
    assert_eq!(code, 3, "{stderr}");
    assert!(
        stderr.contains("speaks link protocol 2; this fastemu speaks 3"),
        "{stderr}"
    );
    assert_nothing_left(&json);
}

const BENCH_RIG: &str = env!("CARGO_BIN_EXE_bench_rig");

const LAG_DELAY_LINES: &str =
    "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0";
const SLOW_LAG_DELAY_LINES: &str =
    "kind = \"lag-delay\"\ntransport_delay_us = 450.0\nlag_us = 150.0\nforce_max_n = 150000.0";

/// fastemu's simulated rig started by hand as an external rig over iceoryx2 with the
/// `[rig.actuator]` lines `rig_actuator` (the rig draws nothing: `perturb = 0`), and
/// `hil --rig external` on
/// a configuration whose `[rig.actuator]` is `declared_preset` (the shipped lag-delay when
/// `None`) and which declares it for the external rig with `declared` (`[compensation]
/// plan_for_external_rig`); hil's exit code and JSON.
fn external_servo_session(
    name: &str,
    declared_preset: Option<&str>,
    rig_actuator: &str,
    declared: bool,
    duration_s: f64,
) -> (i32, serde_json::Value) {
    let dir = scratch_dir(name);
    let report = dir.join("report");
    let preset_line = |p: &str| format!("preset = \"{p}\"");
    let actuator = declared_preset.map_or(LAG_DELAY_LINES.to_string(), preset_line);
    let config = write_config(
        &dir,
        &[
            (LAG_DELAY_LINES, actuator.as_str()),
            (
                "plan_for_external_rig = false",
                &format!("plan_for_external_rig = {declared}"),
            ),
        ],
        "",
    );
    let rig_config = dir.join("rig.toml");
    std::fs::write(
        &rig_config,
        std::fs::read_to_string(&config)
            .unwrap()
            .replace(&actuator, rig_actuator),
    )
    .unwrap();
    let run_id = format!("feit{}{name}", std::process::id());
    let mut hil = spawn_hil_with(
        &config,
        &report,
        duration_s,
        &["--rig", "external", "--run-id", &run_id],
    );
    let rig = Command::new(BENCH_RIG)
        .args(["--run-id", &run_id, "--out"])
        .arg(&report)
        .arg("--config")
        .arg(&rig_config)
        .args(["--duration-s", &duration_s.to_string()])
        // hil may wait for the machine's lock (another test's run) before it starts.
        .args([
            "--start-timeout-s",
            &(LOCK_WAIT + Duration::from_secs(60)).as_secs().to_string(),
        ])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let status = ChildGuard::new(rig)
        .wait_timeout(LOCK_WAIT + Duration::from_secs(120))
        .unwrap();
    assert!(status.is_some(), "{name}: the rig did not end");
    let (code, json) = hil.finish(Duration::from_secs(60));
    assert!(
        json["rig"]["kind"] == "external",
        "{name}: exit {code}, {json}\n{}",
        hil.stderr()
    );
    assert_nothing_left(&json);
    (code, json)
}

/// An external rig whose actuator the configuration declares (`[compensation]
/// plan_for_external_rig = true`: `[rig.actuator]` and `[rig]` describe it) is planned for
/// as the simulated rig is. Undeclared, `slow-250kn` from the shipped guess (252 us; the
/// linearised loop is stable only from about 3.7 ms) rings up and trips into the hold
/// within the first second (`loop-unstable` at 0.25 s until 2026-11-28, since
/// `displacement-out-of-range` at 0.21 s: 0.22-0.24 mm, then 0.35-0.36 mm beyond the
/// range the run had kept, three runs each; the hold's own excursion 0.41-0.42 mm in four
/// runs with both cores loaded on 2026-11-28, 0.54 mm once in CI, after a ring of +-1.4
/// mm), its excursion bounded by the ring's (the bound was 0.5 mm, a figure observed, not
/// derived: CI crossed it); declared, the launcher
/// fixes the lead at the plan's (stable for all 24 actuators it judged), the loop is stable
/// to the end without a fault, and, since a lead does not render this actuator within 1 %,
/// the run is not clean.
#[test]
fn an_external_rigs_declared_actuator_is_planned_for_and_runs_stable() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (code, json) = external_servo_session(
        "ext-undeclared",
        Some("slow-250kn"),
        "preset = \"slow-250kn\"",
        false,
        3.0,
    );
    assert_ne!(code, 0, "{json}");
    assert!(
        json["compensation"]["plan"].is_null(),
        "{}",
        json["compensation"]
    );
    // It rings below 27 Hz, where no lead is read from the ringing (`OSCILLATION_LOW_HZ`):
    // the safe start's damping alone, and the trip.
    assert_eq!(json["safety"]["final_state"], "hold", "{}", json["safety"]);
    let trip = &json["safety"]["faults"][0];
    assert!(
        ["loop-unstable", "displacement-out-of-range"].contains(&trip["fault"].as_str().unwrap()),
        "{trip}"
    );
    assert!(trip["detected_at_s"].as_f64().unwrap() < 1.0, "{trip}");
    // The hold restrains: through this 4.3 ms actuator it cannot stop the ring at once,
    // but it takes the specimen no further from where it tripped than half the range the
    // ring itself swept before (about 1.4 mm), and brings it to rest within 0.5 s.
    let range = trip["prefault_range_m"].as_array().unwrap();
    let half_range = 0.5 * (range[1].as_f64().unwrap() - range[0].as_f64().unwrap());
    assert!(
        trip["largest_excursion_m"].as_f64().unwrap() < half_range,
        "{trip}"
    );
    assert!(trip["time_to_rest_s"].as_f64().unwrap() < 0.5, "{trip}");

    let (code, json) = external_servo_session(
        "ext-declared",
        Some("slow-250kn"),
        "preset = \"slow-250kn\"",
        true,
        3.0,
    );
    let c = &json["compensation"];
    let plan = &c["plan"];
    assert_eq!(plan["lead_fixed"], true, "{plan}");
    assert_eq!(plan["lead_stable_for"], plan["draws"], "{plan}");
    let lead_us = plan["lead_us"].as_f64().unwrap();
    assert!((3000.0..8000.0).contains(&lead_us), "{plan}");
    assert_eq!(c["starting_lead_us"].as_f64(), Some(lead_us), "{c}");
    // The plan's lead, or where the nudge stepped it (`compensation::LeadNudge`: this
    // actuator's axles ring on at the force loop's crossover, a lead on the short side,
    // so up), within the plan's range.
    let final_us = c["final_lead_us"].as_f64().unwrap();
    let high_us = plan["nudge"]["high_s"].as_f64().unwrap() * 1e6;
    match c["lead_nudges"].as_u64() {
        Some(0) => assert_eq!(final_us, lead_us, "{c}"),
        Some(_) => assert!(lead_us < final_us && final_us <= high_us, "{c}"),
        None => panic!("no lead_nudges with a fixed lead: {c}"),
    }
    // The rig is the declared actuator: nothing to warn about.
    assert!(c["declaration_warning"].is_null(), "{c}");
    assert!(faults(&json).is_empty(), "{:?}", faults(&json));
    assert_eq!(
        json["safety"]["final_state"], "finished",
        "{}",
        json["safety"]
    );
    assert_eq!(json["stable"], true, "{}", json["stability"]);
    assert_eq!(json["clean"], false);
    assert_eq!(code, 1, "{json}");
    let steps = json["steps"].as_u64().unwrap();
    assert!(steps >= (3.0 * 4096.0 * 0.99) as u64, "{steps} steps");
}

/// A declaration the hardware does not match is said: the shipped lag-delay actuator
/// declared (about 0.25 ms of effective delay), a slower one on the external rig (450 us
/// transport delay and a 150 us lag, about 0.8 ms). The plan keeps the compensation as
/// configured (the declared actuator's adaptation is stable), the loop adapts its lead
/// and runs to the end, and the report warns that the delay identified over the load band
/// lies far outside what the declared actuator within its tolerance could have.
///
/// (A servo-hydraulic rig behind this declaration is no test of the warning: from the
/// declared 252 us lead, `fatigue-150kn` sometimes rings up before the lead has adapted and
/// trips `loop-unstable`, as an undeclared one may, and a run that ends in the hold
/// identifies nothing over the load band.)
#[test]
fn an_external_rig_that_does_not_match_its_declaration_is_warned_about() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (_, json) = external_servo_session("ext-mismatch", None, SLOW_LAG_DELAY_LINES, true, 5.0);
    let c = &json["compensation"];
    assert_eq!(c["plan"]["lead_fixed"], false, "{}", c["plan"]);
    let (lo, hi) = (
        c["plan"]["effective_delays_us"][0].as_f64().unwrap(),
        c["plan"]["effective_delays_us"][1].as_f64().unwrap(),
    );
    assert!(lo > 100.0 && hi < 500.0, "{}", c["plan"]);
    assert!(faults(&json).is_empty(), "{:?}", faults(&json));
    assert_eq!(c["identified_from"], "load-band", "{c}");
    let identified = c["identified_delay_us"].as_f64().unwrap();
    assert!(identified > 2.0 * hi, "{identified} against {lo}-{hi}");
    let warning = c["declaration_warning"]
        .as_str()
        .unwrap_or_else(|| panic!("{c}"));
    assert!(
        warning.contains("does not behave as declared")
            && warning.contains(&format!("{identified:.0} us")),
        "{warning}"
    );
}
