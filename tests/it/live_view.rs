//! The live view (`hil --live`): a client speaking the Foxglove WebSocket protocol
//! (subprotocol `foxglove.sdk.v1`: JSON `advertise`, `subscribe`; binary message data,
//! opcode 1) receives the run's channels while it runs, decimated as configured, and with
//! `--live-control` can hold the run (seen in the rig's records). Counts, not timings: the
//! rate is asserted as messages per second of *loop* time, from their own timestamps.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use fastemu::ipc::messages::rig_state;
use fastemu::records::RecordSet;
use fastemu::rig::core::RigRecord;
use tungstenite::client::IntoClientRequest;
use tungstenite::Message;

const FASTEMU: &str = env!("CARGO_BIN_EXE_fastemu");

#[test]
fn a_foxglove_client_receives_the_live_channels_and_can_hold_the_run() {
    let _serial = crate::hil_processes::serial();
    let dir = crate::common::TempDir::new("live");
    let report = dir.join("report");
    let (mut hil, guard, addr) = spawn_live_hil(&report, &["--live-control"], 6.0);
    let mut ws = connect(&addr, "foxglove.sdk.v1");
    let mut topics = std::collections::HashMap::new(); // subscription id -> topic
    let mut services = std::collections::HashMap::new();
    let mut schemas = std::collections::HashMap::<String, String>::new(); // topic -> JSON schema
    let mut displacement_t: Vec<f64> = Vec::new();
    let mut counts = std::collections::HashMap::<String, u64>::new();
    let mut held = false;
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(4) {
        let msg = match ws.read() {
            Ok(m) => m,
            Err(tungstenite::Error::Io(e))
                if e.kind() == std::io::ErrorKind::WouldBlock
                    || e.kind() == std::io::ErrorKind::TimedOut =>
            {
                continue
            }
            Err(e) => panic!("live view: {e}"),
        };
        match msg {
            Message::Text(text) => {
                let v: serde_json::Value = serde_json::from_str(&text).unwrap();
                match v["op"].as_str() {
                    Some("advertise") => {
                        let mut subs = Vec::new();
                        for c in v["channels"].as_array().unwrap() {
                            let sub = topics.len() as u64 + 1;
                            topics.insert(sub, c["topic"].as_str().unwrap().to_string());
                            schemas.insert(
                                c["topic"].as_str().unwrap().to_string(),
                                c["schema"].as_str().unwrap().to_string(),
                            );
                            subs.push(serde_json::json!({"id": sub, "channelId": c["id"]}));
                        }
                        ws.send(Message::text(
                            serde_json::json!({"op": "subscribe", "subscriptions": subs})
                                .to_string(),
                        ))
                        .unwrap();
                    }
                    Some("advertiseServices") => {
                        for s in v["services"].as_array().unwrap() {
                            services.insert(
                                s["name"].as_str().unwrap().to_string(),
                                s["id"].as_u64().unwrap(),
                            );
                        }
                    }
                    _ => {}
                }
            }
            Message::Binary(data) if data[0] == 1 => {
                let sub = u32::from_le_bytes(data[1..5].try_into().unwrap()) as u64;
                let topic = topics.get(&sub).cloned().unwrap_or_default();
                *counts.entry(topic.clone()).or_default() += 1;
                let v: serde_json::Value = serde_json::from_slice(&data[13..]).unwrap();
                if topic == "/live/displacement" {
                    assert!(v["measured_um"].is_number(), "{v}");
                    displacement_t.push(v["t_s"].as_f64().unwrap());
                }
                // Once the run is well under way, hold it from the live view.
                if !held && v["t_s"].as_f64().is_some_and(|t| t > 1.5) {
                    if let Some(&id) = services.get("/fastemu/hold") {
                        let mut frame = vec![2u8];
                        frame.extend((id as u32).to_le_bytes());
                        frame.extend(1u32.to_le_bytes());
                        frame.extend(4u32.to_le_bytes());
                        frame.extend(b"json{}");
                        ws.send(Message::binary(frame)).unwrap();
                        held = true;
                    }
                }
            }
            _ => {}
        }
    }
    assert!(held, "no hold service offered: {services:?}");
    for topic in [
        "/live/displacement",
        "/live/force",
        "/live/element",
        "/live/state",
        "/live/timing",
        "/live/fidelity",
    ] {
        assert!(
            counts.get(topic).copied().unwrap_or(0) > 0,
            "nothing on {topic}: {counts:?}"
        );
    }
    layout_names_only_what_the_server_offers(&schemas, &services);
    // >= 100 displacement messages per second of loop time, without gaps.
    let span = displacement_t.last().unwrap() - displacement_t.first().unwrap();
    let rate = displacement_t.len() as f64 / span;
    assert!(
        rate >= 100.0,
        "{} messages over {span} s of loop time",
        displacement_t.len()
    );
    assert!(displacement_t
        .windows(2)
        .all(|w| w[1] > w[0] && w[1] - w[0] < 0.05));
    // Stop the held run from the live view's stop, as an operator would.
    drop(ws);
    let out = Command::new(FASTEMU)
        .args(["ctl", "stop"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let status = hil.wait().unwrap();
    drop(guard);
    assert_eq!(status.code(), Some(0));
    let rig = RecordSet::open(&report)
        .unwrap()
        .read_all::<RigRecord>()
        .unwrap();
    assert!(
        rig.iter().any(|r| r.state == rig_state::OPERATOR_HOLD),
        "the live view's hold is not in the records"
    );
}

/// The shipped Foxglove layout (`configs/foxglove-layout.json`) plots, lists and calls only
/// what the live view advertised: every `/topic.field` path a field of that topic's
/// schema, every topic and service one the server offered.
fn layout_names_only_what_the_server_offers(
    schemas: &std::collections::HashMap<String, String>,
    services: &std::collections::HashMap<String, u64>,
) {
    let layout_path = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/foxglove-layout.json");
    let layout: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(layout_path).unwrap()).unwrap();
    let mut checked = 0;
    for (panel, config) in layout["configById"].as_object().unwrap() {
        let paths = config["paths"].as_array().into_iter().flatten();
        for path in paths.filter_map(|p| p["value"].as_str()) {
            let (topic, field) = path.split_once('.').expect("a /topic.field path");
            let schema: serde_json::Value = serde_json::from_str(
                schemas
                    .get(topic)
                    .unwrap_or_else(|| panic!("{panel}: {topic} is not advertised")),
            )
            .unwrap();
            assert!(
                schema["properties"][field].is_object(),
                "{panel}: {topic} has no field {field}: {schema}"
            );
            checked += 1;
        }
        if let Some(topic) = config["topicPath"].as_str() {
            assert!(
                schemas.contains_key(topic),
                "{panel}: {topic} not advertised"
            );
            checked += 1;
        }
        if let Some(service) = config["serviceName"].as_str() {
            assert!(
                services.contains_key(service),
                "{panel}: service {service} not offered: {services:?}"
            );
            checked += 1;
        }
    }
    // Every panel of the layout was looked at (18 plotted fields, a topic, 3 services).
    assert_eq!(checked, 22);
}

/// Starts `hil --live` on a port the OS picks; returns it, its guard and the address it
/// printed.
fn spawn_live_hil(
    report: &std::path::Path,
    extra: &[&str],
    duration_s: f64,
) -> (
    std::process::Child,
    crate::hil_processes::KillOnDrop,
    String,
) {
    let mut hil = Command::new(FASTEMU)
        .args(["hil", "--json", "--live", "--live-addr", "127.0.0.1:0"])
        .args(extra)
        .args(["--duration-s", &duration_s.to_string(), "--out"])
        .arg(report)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let guard = crate::hil_processes::KillOnDrop(hil.id());
    // The address comes from hil's own line (port 0: the OS chose one).
    let mut lines = BufReader::new(hil.stderr.take().unwrap()).lines();
    let addr = loop {
        let line = lines
            .next()
            .expect("hil ended before the live view started")
            .unwrap();
        if let Some(rest) = line.split("live view on ws://").nth(1) {
            break rest.split_whitespace().next().unwrap().to_string();
        }
    };
    std::thread::spawn(move || for _ in lines {});
    (hil, guard, addr)
}

type Socket = tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<std::net::TcpStream>>;

/// A WebSocket client offering `subprotocol`; checks the server chose it.
fn connect(addr: &str, subprotocol: &str) -> Socket {
    let mut request = format!("ws://{addr}").into_client_request().unwrap();
    request
        .headers_mut()
        .insert("Sec-WebSocket-Protocol", subprotocol.parse().unwrap());
    let (mut ws, response) = tungstenite::connect(request).expect("connect to the live view");
    assert_eq!(
        response.headers().get("sec-websocket-protocol").unwrap(),
        subprotocol
    );
    if let tungstenite::stream::MaybeTlsStream::Plain(s) = ws.get_mut() {
        s.set_read_timeout(Some(Duration::from_millis(200)))
            .unwrap();
    }
    ws
}

/// The Foxglove WebSocket protocol under its published name (`foxglove.websocket.v1`, the
/// specification's and older Foxglove apps') gets the same channels as under the SDK's;
/// a client offering neither is refused with the names to offer.
#[test]
fn a_client_offering_the_published_subprotocol_name_gets_in_and_one_offering_none_is_told_which() {
    let _serial = crate::hil_processes::serial();
    let dir = crate::common::TempDir::new("live-spec");
    let report = dir.join("report");
    let (mut hil, guard, addr) = spawn_live_hil(&report, &[], 3.0);
    let mut ws = connect(&addr, "foxglove.websocket.v1");
    let mut displacement = None;
    let mut received = 0u32;
    let t = Instant::now();
    while received < 50 && t.elapsed() < Duration::from_secs(20) {
        match ws.read() {
            Ok(Message::Text(text)) => {
                let v: serde_json::Value = serde_json::from_str(&text).unwrap();
                if v["op"] == "advertise" {
                    for c in v["channels"].as_array().unwrap() {
                        if c["topic"] == "/live/displacement" {
                            displacement = c["id"].as_u64();
                            ws.send(Message::text(
                                serde_json::json!({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": c["id"]}]})
                                    .to_string(),
                            ))
                            .unwrap();
                        }
                    }
                }
            }
            Ok(Message::Binary(data)) if data[0] == 1 => {
                assert_eq!(u32::from_le_bytes(data[1..5].try_into().unwrap()), 7);
                let v: serde_json::Value = serde_json::from_slice(&data[13..]).unwrap();
                assert!(v["measured_um"].is_number(), "{v}");
                received += 1;
            }
            Ok(_) => {}
            Err(tungstenite::Error::Io(e))
                if e.kind() == std::io::ErrorKind::WouldBlock
                    || e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => panic!("live view: {e}"),
        }
    }
    assert!(displacement.is_some(), "/live/displacement not advertised");
    assert_eq!(received, 50, "displacement messages received");
    drop(ws);
    // No subprotocol offered: an HTTP 400 that names the ones to offer.
    let mut plain = std::net::TcpStream::connect(&addr).unwrap();
    plain
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    std::io::Write::write_all(
        &mut plain,
        format!("GET / HTTP/1.1\r\nHost: {addr}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n").as_bytes(),
    )
    .unwrap();
    let mut answer = String::new();
    std::io::Read::read_to_string(&mut plain, &mut answer).unwrap();
    assert!(
        answer.starts_with("HTTP/1.1 400")
            && answer.contains("foxglove.sdk.v1")
            && answer.contains("foxglove.websocket.v1"),
        "{answer}"
    );
    let status = hil.wait().unwrap();
    drop(guard);
    assert_eq!(status.code(), Some(0));
}
