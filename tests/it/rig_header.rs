//! `include/fastemu_rig.h` against the Rust types: compiles a C program with the system C
//! compiler (present wherever this crate builds: zstd-sys compiles C) that prints the size
//! of every struct and the offset of every field, and checks each against the Rust
//! message types (iceoryx2 payloads) and the link's encoder (UDP datagrams: the bytes at
//! the header's offset hold the field's value). Also checks the header's law and lead
//! helpers against the Rust ones, number for number.

use std::collections::BTreeMap;
use std::mem::{offset_of, size_of};
use std::path::PathBuf;
use std::process::Command;

use fastemu::ipc::messages::{
    command_mode, ActuatorCommand, Compensation, DisplacementSample, Heartbeat, LocalLaw,
    RunControl, ABI_VERSION,
};
use fastemu::link::protocol::{self, CommandDatagram, ControlDatagram, SampleDatagram};
use fastemu::rig::servo::lead_weights;

use crate::common::TempDir;

const FIELDS: &[(&str, &[&str])] = &[
    (
        "fastemu_displacement_sample",
        &[
            "sequence",
            "rig_time_ns",
            "publish_time_ns",
            "displacement_m",
            "actuator_force_n",
            "status",
            "rig_state",
            "rig_fault_code",
            "reserved",
            "commanded_force_n",
        ],
    ),
    (
        "fastemu_local_law",
        &[
            "force_n",
            "displacement_m",
            "velocity_m_per_s",
            "stiffness_n_per_m",
            "damping_ns_per_m",
            "force_rate_n_per_s",
            "stiffness_slope_n_per_m2",
        ],
    ),
    (
        "fastemu_actuator_command",
        &[
            "sequence",
            "setpoint_sequence",
            "sample_sequence",
            "sample_publish_time_ns",
            "law",
            "force_min_n",
            "force_max_n",
            "mode",
            "controller_state",
            "fault_code",
            "reserved",
            "compensation",
        ],
    ),
    (
        "fastemu_compensation",
        &[
            "lead_s",
            "added_damping_ns_per_m",
            "added_damping_corner_hz",
            "gain",
            "lead_order",
            "reserved",
        ],
    ),
    (
        "fastemu_heartbeat",
        &[
            "process",
            "state",
            "sequence",
            "time_ns",
            "fault_code",
            "reserved",
        ],
    ),
    (
        "fastemu_run_control",
        &[
            "sequence",
            "start_time_ns",
            "start_unix_ns",
            "command",
            "reserved",
        ],
    ),
    (
        "fastemu_link_header",
        &["magic", "version", "kind", "sequence", "sender_time_ns"],
    ),
    (
        "fastemu_link_sample",
        &[
            "header",
            "sample_sequence",
            "rig_time_ns",
            "displacement_m",
            "actuator_force_n",
            "status",
            "rig_state",
            "rig_fault_code",
            "reserved",
            "echo_command_time_ns",
            "echo_hold_ns",
            "commanded_force_n",
        ],
    ),
    (
        "fastemu_link_command",
        &[
            "header",
            "command_sequence",
            "setpoint_sequence",
            "sample_sequence",
            "law",
            "force_min_n",
            "force_max_n",
            "mode",
            "controller_state",
            "fault_code",
            "reserved",
            "echo_sample_time_ns",
            "compensation",
        ],
    ),
    (
        "fastemu_link_control",
        &[
            "header",
            "command",
            "reserved",
            "control_sequence",
            "start_delay_ns",
            "period_ns",
        ],
    ),
    (
        "fastemu_link_status",
        &["header", "rig_state", "rig_fault_code", "period_ns"],
    ),
];

/// Compiles and runs the layout probe; returns "struct" -> size and "struct.field" ->
/// offset, plus the helpers' numbers under "law" and "lead.*".
fn probe() -> BTreeMap<String, f64> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    // One directory per call: the tests calling this run in parallel.
    let temp = TempDir::new("header");
    let dir = temp.path.clone();
    let mut c = String::from(
        "#include <stdio.h>\n#include <stddef.h>\n#include \"fastemu_rig.h\"\nint main(void) {\n",
    );
    for (s, fields) in FIELDS {
        c.push_str(&format!("printf(\"{s} %zu\\n\", sizeof({s}));\n"));
        for f in *fields {
            c.push_str(&format!(
                "printf(\"{s}.{f} %zu\\n\", offsetof({s}, {f}));\n"
            ));
        }
    }
    c.push_str(
        "fastemu_local_law law = {2.0e4, 3.5e-4, -1.0e-3, 5.7e7, 75.0, -12.5, 1.0e10};\n\
         printf(\"law %.17g\\n\", fastemu_law_evaluate(&law, 3.7e-4, 2.0e-3, 0.004));\n\
         double v[4], s[4];\n\
         for (unsigned o = 0; o < 4; o++) {\n\
           fastemu_lead_weights(o, 1.0 / 4096.0, 252e-6, v, s);\n\
           for (int i = 0; i < 4; i++) printf(\"lead.%u.%d %.17g %.17g\\n\", o, i, v[i], s[i]);\n\
         }\n\
         printf(\"abi %u %u\\n\", FASTEMU_RIG_ABI_VERSION, FASTEMU_LINK_VERSION);\n\
         fastemu_actuator_command cmd = {0};\n\
         cmd.sample_sequence = 2; cmd.law = law; cmd.force_min_n = -5e3; cmd.force_max_n = 1.2e5;\n\
         cmd.mode = FASTEMU_MODE_LAW;\n\
         fastemu_compensation comp = {3.0e-4, 2.0e3, 60.0, 0.95, 2, 0};\n\
         cmd.compensation = comp;\n\
         fastemu_law_state st = {{3.5e-4, 3.5e-4, 3.5e-4, 3.5e-4}, {0}, {0}, -1.0, 0, 0.0};\n\
         for (unsigned k = 0; k < 8; k++) {\n\
           double z = 3.5e-4 + 2.0e-5 * k * k - 1.0e-6 * k * k * k;\n\
           printf(\"comp.%u %.17g\\n\", k, fastemu_compensated_force(&st, &cmd, z, k, 1.0 / 4096.0, 205.0 / 4096.0));\n\
         }\n\
         return 0;\n}\n",
    );
    let src = dir.join("probe.c");
    let exe = dir.join("probe");
    std::fs::write(&src, c).unwrap();
    let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
    let out = Command::new(&cc)
        .args(["-std=c11", "-Wall", "-Werror", "-O1", "-I"])
        .arg(root.join("include"))
        .arg(&src)
        .arg("-o")
        .arg(&exe)
        .output()
        .unwrap_or_else(|e| panic!("cannot run the C compiler `{cc}`: {e}"));
    assert!(
        out.status.success(),
        "the header does not compile: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = Command::new(&exe).output().unwrap();
    assert!(out.status.success());
    let mut map = BTreeMap::new();
    for line in String::from_utf8(out.stdout).unwrap().lines() {
        let mut words = line.split_whitespace();
        let key = words.next().unwrap().to_string();
        let values: Vec<f64> = words.map(|w| w.parse().unwrap()).collect();
        if key.starts_with("lead.") && values.len() == 2 {
            map.insert(format!("{key}.value"), values[0]);
            map.insert(format!("{key}.slope"), values[1]);
        } else if key == "abi" {
            map.insert("abi.rig".into(), values[0]);
            map.insert("abi.link".into(), values[1]);
        } else {
            map.insert(key, values[0]);
        }
    }
    map
}

fn at(map: &BTreeMap<String, f64>, key: &str) -> usize {
    *map.get(key).unwrap_or_else(|| panic!("{key} missing")) as usize
}

#[test]
fn the_c_header_matches_the_rust_types_field_by_field() {
    let m = probe();
    assert_eq!(at(&m, "abi.rig"), ABI_VERSION as usize);
    assert_eq!(at(&m, "abi.link"), protocol::LINK_VERSION as usize);
    // iceoryx2 payloads: size and every offset against the #[repr(C)] Rust types.
    macro_rules! same_layout {
        ($c:literal, $t:ty, [$($f:ident),*]) => {{
            assert_eq!(at(&m, $c), size_of::<$t>(), "sizeof({})", $c);
            $( assert_eq!(
                at(&m, concat!($c, ".", stringify!($f))),
                offset_of!($t, $f),
                "{}.{}", $c, stringify!($f)
            ); )*
        }};
    }
    same_layout!(
        "fastemu_displacement_sample",
        DisplacementSample,
        [
            sequence,
            rig_time_ns,
            publish_time_ns,
            displacement_m,
            actuator_force_n,
            status,
            rig_state,
            rig_fault_code,
            reserved
        ]
    );
    same_layout!(
        "fastemu_local_law",
        LocalLaw,
        [
            force_n,
            displacement_m,
            velocity_m_per_s,
            stiffness_n_per_m,
            damping_ns_per_m,
            force_rate_n_per_s,
            stiffness_slope_n_per_m2
        ]
    );
    same_layout!(
        "fastemu_actuator_command",
        ActuatorCommand,
        [
            sequence,
            setpoint_sequence,
            sample_sequence,
            sample_publish_time_ns,
            law,
            force_min_n,
            force_max_n,
            mode,
            controller_state,
            fault_code,
            reserved
        ]
    );
    same_layout!(
        "fastemu_heartbeat",
        Heartbeat,
        [process, state, sequence, time_ns, fault_code, reserved]
    );
    same_layout!(
        "fastemu_run_control",
        RunControl,
        [sequence, start_time_ns, start_unix_ns, command, reserved]
    );

    // UDP datagrams: the encoder writes each field where the header says it is.
    let mut buf = [0u8; protocol::MAX_DATAGRAM_BYTES];
    let u64_at = |b: &[u8], o: usize| u64::from_le_bytes(b[o..o + 8].try_into().unwrap());
    let u32_at = |b: &[u8], o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
    let u16_at = |b: &[u8], o: usize| u16::from_le_bytes(b[o..o + 2].try_into().unwrap());
    let f64_at = |b: &[u8], o: usize| f64::from_le_bytes(b[o..o + 8].try_into().unwrap());
    let hdr = |b: &[u8], kind: u16, seq: u64, time: u64| {
        let h = at(&m, "fastemu_link_sample.header");
        assert_eq!(h, 0);
        assert_eq!(&b[at(&m, "fastemu_link_header.magic")..][..4], b"FEMU");
        assert_eq!(
            u16_at(b, at(&m, "fastemu_link_header.version")),
            protocol::LINK_VERSION
        );
        assert_eq!(u16_at(b, at(&m, "fastemu_link_header.kind")), kind);
        assert_eq!(u64_at(b, at(&m, "fastemu_link_header.sequence")), seq);
        assert_eq!(
            u64_at(b, at(&m, "fastemu_link_header.sender_time_ns")),
            time
        );
    };
    assert_eq!(at(&m, "fastemu_link_header"), protocol::HEADER_BYTES);

    let sample = SampleDatagram {
        sample_sequence: 11,
        rig_time_ns: 12,
        displacement_m: 13.5,
        actuator_force_n: 14.5,
        status: 15,
        rig_state: 16,
        rig_fault_code: 17,
        echo_command_time_ns: 18,
        echo_hold_ns: 19,
        commanded_force_n: 20.5,
    };
    let n = protocol::encode_sample(&mut buf, 1, 2, &sample);
    assert_eq!(n, at(&m, "fastemu_link_sample"));
    hdr(&buf, protocol::kind::SAMPLE, 1, 2);
    let s = |f: &str| at(&m, &format!("fastemu_link_sample.{f}"));
    assert_eq!(u64_at(&buf, s("sample_sequence")), 11);
    assert_eq!(u64_at(&buf, s("rig_time_ns")), 12);
    assert_eq!(f64_at(&buf, s("displacement_m")), 13.5);
    assert_eq!(f64_at(&buf, s("actuator_force_n")), 14.5);
    assert_eq!(u32_at(&buf, s("status")), 15);
    assert_eq!(u32_at(&buf, s("rig_state")), 16);
    assert_eq!(u32_at(&buf, s("rig_fault_code")), 17);
    assert_eq!(u32_at(&buf, s("reserved")), 0);
    assert_eq!(u64_at(&buf, s("echo_command_time_ns")), 18);
    assert_eq!(u64_at(&buf, s("echo_hold_ns")), 19);
    assert_eq!(f64_at(&buf, s("commanded_force_n")), 20.5);

    let law = LocalLaw {
        force_n: 21.5,
        displacement_m: 22.5,
        velocity_m_per_s: 23.5,
        stiffness_n_per_m: 24.5,
        damping_ns_per_m: 25.5,
        force_rate_n_per_s: 26.5,
        stiffness_slope_n_per_m2: 27.5,
    };
    let command = CommandDatagram {
        command: ActuatorCommand {
            sequence: 31,
            setpoint_sequence: 32,
            sample_sequence: 33,
            sample_publish_time_ns: 0,
            law,
            force_min_n: 34.5,
            force_max_n: 35.5,
            mode: 36,
            controller_state: 37,
            fault_code: 38,
            reserved: 0,
            compensation: Compensation {
                lead_s: 40.5,
                added_damping_ns_per_m: 41.5,
                added_damping_corner_hz: 42.5,
                gain: 43.5,
                lead_order: 44,
                reserved: 0,
            },
        },
        echo_sample_time_ns: 39,
    };
    let n = protocol::encode_command(&mut buf, 3, 4, &command);
    assert_eq!(n, at(&m, "fastemu_link_command"));
    hdr(&buf, protocol::kind::COMMAND, 3, 4);
    let c = |f: &str| at(&m, &format!("fastemu_link_command.{f}"));
    assert_eq!(u64_at(&buf, c("command_sequence")), 31);
    assert_eq!(u64_at(&buf, c("setpoint_sequence")), 32);
    assert_eq!(u64_at(&buf, c("sample_sequence")), 33);
    let l = |f: &str| c("law") + at(&m, &format!("fastemu_local_law.{f}"));
    assert_eq!(f64_at(&buf, l("force_n")), 21.5);
    assert_eq!(f64_at(&buf, l("displacement_m")), 22.5);
    assert_eq!(f64_at(&buf, l("velocity_m_per_s")), 23.5);
    assert_eq!(f64_at(&buf, l("stiffness_n_per_m")), 24.5);
    assert_eq!(f64_at(&buf, l("damping_ns_per_m")), 25.5);
    assert_eq!(f64_at(&buf, l("force_rate_n_per_s")), 26.5);
    assert_eq!(f64_at(&buf, l("stiffness_slope_n_per_m2")), 27.5);
    assert_eq!(f64_at(&buf, c("force_min_n")), 34.5);
    assert_eq!(f64_at(&buf, c("force_max_n")), 35.5);
    assert_eq!(u32_at(&buf, c("mode")), 36);
    assert_eq!(u32_at(&buf, c("controller_state")), 37);
    assert_eq!(u32_at(&buf, c("fault_code")), 38);
    assert_eq!(u64_at(&buf, c("echo_sample_time_ns")), 39);
    let k = |f: &str| c("compensation") + at(&m, &format!("fastemu_compensation.{f}"));
    assert_eq!(f64_at(&buf, k("lead_s")), 40.5);
    assert_eq!(f64_at(&buf, k("added_damping_ns_per_m")), 41.5);
    assert_eq!(f64_at(&buf, k("added_damping_corner_hz")), 42.5);
    assert_eq!(f64_at(&buf, k("gain")), 43.5);
    assert_eq!(u32_at(&buf, k("lead_order")), 44);

    let control = ControlDatagram {
        command: 41,
        control_sequence: 42,
        start_delay_ns: 43,
        period_ns: 44,
    };
    let n = protocol::encode_control(&mut buf, 5, 6, &control);
    assert_eq!(n, at(&m, "fastemu_link_control"));
    hdr(&buf, protocol::kind::CONTROL, 5, 6);
    let k = |f: &str| at(&m, &format!("fastemu_link_control.{f}"));
    assert_eq!(u32_at(&buf, k("command")), 41);
    assert_eq!(u64_at(&buf, k("control_sequence")), 42);
    assert_eq!(u64_at(&buf, k("start_delay_ns")), 43);
    assert_eq!(u64_at(&buf, k("period_ns")), 44);

    let status = protocol::StatusDatagram {
        rig_state: 51,
        rig_fault_code: 52,
        period_ns: 53,
    };
    let n = protocol::encode_status(&mut buf, 7, 8, &status);
    assert_eq!(n, at(&m, "fastemu_link_status"));
    hdr(&buf, protocol::kind::STATUS, 7, 8);
    let t = |f: &str| at(&m, &format!("fastemu_link_status.{f}"));
    assert_eq!(u32_at(&buf, t("rig_state")), 51);
    assert_eq!(u32_at(&buf, t("rig_fault_code")), 52);
    assert_eq!(u64_at(&buf, t("period_ns")), 53);
}

#[test]
fn the_c_headers_law_and_lead_helpers_give_the_rust_numbers() {
    let m = probe();
    let law = LocalLaw {
        force_n: 2.0e4,
        displacement_m: 3.5e-4,
        velocity_m_per_s: -1.0e-3,
        stiffness_n_per_m: 5.7e7,
        damping_ns_per_m: 75.0,
        force_rate_n_per_s: -12.5,
        stiffness_slope_n_per_m2: 1.0e10,
    };
    let rust = law.evaluate(3.7e-4, 2.0e-3, 0.004);
    let c = m["law"];
    assert!(
        (c - rust).abs() <= 1e-9 * rust.abs(),
        "C {c} vs Rust {rust}"
    );
    for order in 0..4usize {
        let (value, slope) = lead_weights(order, 1.0 / 4096.0, 252e-6);
        for i in 0..4 {
            for (what, rust) in [("value", value[i]), ("slope", slope[i])] {
                let c = m[&format!("lead.{order}.{i}.{what}")];
                assert!(
                    (c - rust).abs() <= 1e-9 * rust.abs().max(1.0),
                    "lead order {order} weight {i} {what}: C {c} vs Rust {rust}"
                );
            }
        }
    }
}

/// The header's `fastemu_compensated_force` (what an external rig runs every period) gives
/// the simulated rig's servo's numbers: prediction over the command's lead, the guard's
/// damping on the high-passed velocity, the limits, the gain.
#[test]
fn the_c_headers_compensated_force_is_the_servos() {
    use fastemu::hil::config::default_hil_config;
    use fastemu::rig::servo::Servo;
    let m = probe();
    let cfg = default_hil_config().unwrap();
    let servo_cfg = fastemu::rig::servo::ServoConfig {
        period_s: 1.0 / 4096.0,
        command_stale_periods: 205,
        ..cfg.servo_config()
    };
    let mut servo = Servo::new(servo_cfg, 3.5e-4, 2.0e4);
    let cmd = ActuatorCommand {
        sequence: 0,
        setpoint_sequence: 0,
        sample_sequence: 2,
        sample_publish_time_ns: 0,
        law: LocalLaw {
            force_n: 2.0e4,
            displacement_m: 3.5e-4,
            velocity_m_per_s: -1.0e-3,
            stiffness_n_per_m: 5.7e7,
            damping_ns_per_m: 75.0,
            force_rate_n_per_s: -12.5,
            stiffness_slope_n_per_m2: 1.0e10,
        },
        force_min_n: -5e3,
        force_max_n: 1.2e5,
        mode: command_mode::LAW,
        controller_state: 1,
        fault_code: 0,
        reserved: 0,
        compensation: Compensation {
            lead_s: 3.0e-4,
            added_damping_ns_per_m: 2.0e3,
            added_damping_corner_hz: 60.0,
            gain: 0.95,
            lead_order: 2,
            reserved: 0,
        },
    };
    servo.on_command(&cmd, 0);
    for k in 0..8u64 {
        let kf = k as f64;
        let z = 3.5e-4 + 2.0e-5 * kf * kf - 1.0e-6 * kf * kf * kf;
        let (out, _) = servo.update(k, z, 2.0e4, f64::NAN);
        let c = m[&format!("comp.{k}")];
        assert!(
            (out.command_n - c).abs() <= 1e-9 * c.abs().max(1.0),
            "period {k}: servo {} vs header {c}",
            out.command_n
        );
    }
}
