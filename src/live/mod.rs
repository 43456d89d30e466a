//! The live view of a running `hil` (`--live`): a Foxglove WebSocket server (the official
//! `foxglove` SDK) serving the run's streams decimated for display, fed by following the
//! processes' record parts as they are written (`records::tail`), so the loops never touch
//! it: data leaves them through their bounded record queues, as it always does. With
//! `--live-control` the server also offers hold / resume / stop services, relayed to the
//! rig by the orchestrator like `fastemu ctl`. Clients reach it through `front`.
//!
//! Must not: run in a loop process, or block the orchestrator's supervision.

pub mod feed;
pub mod front;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use foxglove::websocket::service::{Service, ServiceSchema};
use foxglove::{ChannelBuilder, PartialMetadata, RawChannel, Schema, WebSocketServer};

use crate::hil::config::HilConfig;
use crate::ipc::messages::run_command;
use crate::records::tail::PartTail;
use crate::records::META_TOPIC;
use feed::{topic, LiveFeed, LiveMessage};

/// How the live view is served.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveOptions {
    /// Messages per second of the displacement and force channels.
    pub rate_hz: f64,
    /// Offer hold / resume / stop services.
    pub control: bool,
}

/// The running live view.
pub struct LiveHandle {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    front: Option<JoinHandle<()>>,
    /// An operator request from a service call (`run_command`), 0 when none; the
    /// orchestrator takes it.
    pub requests: Arc<AtomicU32>,
    /// The address the server listens on.
    pub addr: String,
}

impl LiveHandle {
    /// Takes a pending operator request (`run_command::HOLD`, ...), if any.
    pub fn take_request(&self) -> Option<u32> {
        match self.requests.swap(0, Ordering::AcqRel) {
            0 => None,
            c => Some(c),
        }
    }

    /// Stops following the records and the server.
    pub fn stop(self) {
        drop(self);
    }
}

impl Drop for LiveHandle {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        for t in [self.thread.take(), self.front.take()]
            .into_iter()
            .flatten()
        {
            let _ = t.join();
        }
    }
}

/// JSON schema of a live topic (for Foxglove's panels): its fields with units in names.
fn schema(topic: &str) -> Schema {
    let fields: &[&str] = match topic {
        topic::DISPLACEMENT => &["t_s", "measured_um", "true_um", "reference_um"],
        topic::FORCE => &["t_s", "command_kn", "actuator_kn", "external_kn"],
        topic::ELEMENT => &[
            "t_s",
            "force_kn",
            "displacement_um",
            "law_stiffness_mn_per_m",
        ],
        topic::STATE => &[
            "t_s",
            "rig",
            "mode",
            "fault",
            "programme_time_s",
            "cycle",
            "block",
            "block_name",
        ],
        topic::TIMING => &[
            "t_s",
            "deadline_misses",
            "end_to_end_p50_us",
            "end_to_end_p99_us",
            "end_to_end_p999_us",
            "end_to_end_max_us",
            "stalls",
            "longest_stall_ms",
        ],
        topic::FIDELITY => &[
            "t_s",
            "displacement_rel_rms_last_s",
            "displacement_rel_rms",
            "resonant_peak_um_last_s",
            "comparing",
        ],
        _ => &["t_s", "text"],
    };
    let properties: serde_json::Map<String, serde_json::Value> = fields
        .iter()
        .map(|f| {
            let ty = match *f {
                "rig" | "mode" | "fault" | "block_name" | "text" => {
                    serde_json::json!({"type": ["string", "null"]})
                }
                "comparing" => serde_json::json!({"type": "boolean"}),
                _ => serde_json::json!({"type": ["number", "null"]}),
            };
            (f.to_string(), ty)
        })
        .collect();
    let schema = serde_json::json!({"type": "object", "properties": properties});
    Schema::new(
        format!("fastemu{topic}"),
        "jsonschema",
        serde_json::to_vec(&schema).unwrap_or_default(),
    )
}

fn control_service(name: &str, command: u32, requests: &Arc<AtomicU32>) -> Service {
    let requests = requests.clone();
    let empty = || Schema::new("fastemu.Empty", "jsonschema", &br#"{"type":"object"}"#[..]);
    let schema = ServiceSchema::new("fastemu.OperatorAction")
        .with_request("json", empty())
        .with_response("json", empty());
    Service::builder(name, schema).handler_fn(move |_req| {
        requests.store(command, Ordering::Release);
        Ok::<_, String>(b"{\"accepted\": true}".to_vec())
    })
}

/// Starts the server behind `front` (the listener on `--live-addr`) and the thread that
/// follows the records in `report_dir/parts`.
pub fn start(
    cfg: &HilConfig,
    report_dir: &Path,
    front: front::Front,
    options: &LiveOptions,
) -> anyhow::Result<LiveHandle> {
    let requests = Arc::new(AtomicU32::new(0));
    // The SDK's server listens on a private loopback port; clients come through `front`.
    let mut server = WebSocketServer::new()
        .name("fastemu hil")
        .bind("127.0.0.1", 0);
    if options.control {
        server = server.services([
            control_service("/fastemu/hold", run_command::HOLD, &requests),
            control_service("/fastemu/resume", run_command::RESUME, &requests),
            control_service("/fastemu/stop", run_command::END, &requests),
        ]);
    }
    let handle = server
        .start_blocking()
        .map_err(|e| anyhow::anyhow!("live view server: {e}"))?;
    let upstream = std::net::SocketAddr::from(([127, 0, 0, 1], handle.port()));
    let addr = front.addr().to_string();
    let channels: Vec<(&'static str, Arc<RawChannel>)> = topic::ALL
        .iter()
        .map(|t| {
            ChannelBuilder::new(*t)
                .message_encoding("json")
                .schema(schema(t))
                .build_raw()
                .map(|c| (*t, c))
                .map_err(|e| anyhow::anyhow!("live channel {t}: {e}"))
        })
        .collect::<Result<_, _>>()?;
    let stop = Arc::new(AtomicBool::new(false));
    let front = front.serve(upstream, stop.clone())?;
    let thread_stop = stop.clone();
    let parts: PathBuf = report_dir.join("parts");
    let mut feed = LiveFeed::new(cfg, options.rate_hz);
    let thread = std::thread::Builder::new()
        .name("live-view".into())
        .spawn(move || {
            let mut tails: Vec<PartTail> = ["rig", "emulator", "controller"]
                .iter()
                .map(|p| PartTail::new(parts.clone(), p))
                .collect();
            let mut start_unix_ns: Option<u64> = None;
            let mut out: Vec<LiveMessage> = Vec::new();
            while !thread_stop.load(Ordering::Acquire) {
                for tail in &mut tails {
                    tail.poll(|m| {
                        if m.topic == META_TOPIC {
                            start_unix_ns.get_or_insert(m.log_time_ns);
                        } else {
                            feed.push(&m.topic, &m.data, &mut out);
                        }
                    });
                }
                for m in out.drain(..) {
                    if let Some((_, channel)) = channels.iter().find(|(t, _)| *t == m.topic) {
                        let bytes = serde_json::to_vec(&m.value).unwrap_or_default();
                        let log_time = start_unix_ns.map(|t0| t0 + (m.t_s.max(0.0) * 1e9) as u64);
                        channel.log_with_meta(&bytes, PartialMetadata { log_time });
                    }
                }
                std::thread::sleep(Duration::from_millis(10));
            }
            drop(handle.stop());
        })?;
    Ok(LiveHandle {
        stop,
        thread: Some(thread),
        front: Some(front),
        requests,
        addr,
    })
}
