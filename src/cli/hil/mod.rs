//! `fastemu hil`: the product's main command. Validates the config, runs the three
//! processes through the orchestrator, analyses their records, writes the report
//! directory and prints one JSON object with `--json`. Progress goes to stderr.

mod check;
mod summary;

use check::{planned_config, stability_warning};
use summary::{order_faults, summarise};

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::Args;
use serde_json::json;

use crate::hil::config::{load_or_default, HilConfig, DEFAULT_CONFIG_TOML};
use crate::hil::orchestrator::{
    install_signal_handlers, lock_machine, new_run_id, run_processes, RigSetup, RunOutcome, RunPlan,
};
use crate::hil::report::{analyse_run, Analysis};
use crate::ipc::cleanup::clear_stale_runs;
use crate::ipc::quiet_iceoryx2_logs;
use crate::records::merge::merge_parts;

#[derive(Debug, Clone, Args)]
pub struct HilArgs {
    /// HIL configuration (TOML); the embedded `configs/hil-default.toml` when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Print one JSON object with the results on stdout.
    #[arg(long)]
    pub json: bool,
    /// Do not run: print the linearised loop's stability margin for the configured
    /// specimen, element, actuator and compensation, and write its Bode/Nyquist plot
    /// (`check.png` in `--out`, else in the current directory).
    #[arg(long)]
    pub check: bool,
    /// Report directory (default `out/hil-<UTC timestamp>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Overrides `[scenario] duration_s`: programme time, s (it stands still while the rig
    /// holds, so a run with an operator hold lasts longer in wall time).
    #[arg(long)]
    pub duration_s: Option<f64>,
    /// Also export the records as CSV (`rig.csv`, `emulator.csv`, `controller.csv`,
    /// `events.csv`) into the report directory (handy for short runs).
    #[arg(long)]
    pub csv: bool,
    /// Run the simulated rig although no lead makes the linearised loop stable (`hil
    /// --check`): the run then shows the trip (`loop-unstable`) and a hold that may move
    /// the specimen by millimetres. Without it such a run is refused before it starts.
    #[arg(long)]
    pub run_unstable: bool,
    /// Serve the run live over the Foxglove WebSocket protocol (open it in the Foxglove
    /// app with configs/foxglove-layout.json).
    #[arg(long)]
    pub live: bool,
    /// Address of the live view (`--live`); 127.0.0.1 keeps it on this machine.
    #[arg(long, default_value = "127.0.0.1:8765")]
    pub live_addr: String,
    /// Offer hold / resume / stop as services on the live view (whoever can reach it can
    /// then act on the run).
    #[arg(long)]
    pub live_control: bool,
    /// Messages per second of the live displacement and force channels.
    #[arg(long, default_value_t = 512.0)]
    pub live_rate_hz: f64,
    #[command(flatten)]
    pub rig: RigArgs,
}

/// Which rig, and how it connects (README "Connecting a rig").
#[derive(Debug, Clone, Args)]
pub struct RigArgs {
    /// `sim`: the simulated rig, started by hil; `external`: wait for a rig that fastemu
    /// did not start (hil prints where it must connect).
    #[arg(long = "rig", value_parser = ["sim", "external"], default_value = "sim")]
    pub kind: String,
    /// `ipc`: iceoryx2 shared memory; `udp`: the UDP rig link (with `--rig sim`, the
    /// simulated rig on the far side of a loopback link).
    #[arg(long = "rig-link", value_parser = ["ipc", "udp"], default_value = "ipc")]
    pub link: String,
    /// Run id for an external rig: the services are `fastemu/<NAME>/...` and the iceoryx2
    /// files `<NAME>_*` (letters, digits, `_`, `-`); default a fresh id, printed.
    #[arg(long, value_name = "NAME")]
    pub run_id: Option<String>,
    /// `--rig external --rig-link udp`: fastemu's end, the address of the interface that
    /// faces the rig (IP:PORT; never 0.0.0.0).
    #[arg(long, value_name = "IP:PORT")]
    pub link_bind: Option<String>,
    /// `--rig external --rig-link udp`: the rig's address; datagrams from anywhere else
    /// are rejected.
    #[arg(long, value_name = "IP:PORT")]
    pub link_peer: Option<String>,
    /// How long to wait for an external rig, s.
    #[arg(long, default_value_t = 120.0)]
    pub rig_wait_s: f64,
}

impl RigArgs {
    fn external(&self) -> bool {
        self.kind == "external"
    }
    fn udp(&self) -> bool {
        self.link == "udp"
    }
}

/// Letters, digits, `_` and `-`, 1 to 40 of them: a valid iceoryx2 file prefix and
/// service-name segment.
fn check_run_id(id: &str) -> anyhow::Result<()> {
    anyhow::ensure!(
        !id.is_empty()
            && id.len() <= 40
            && id
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-'),
        "--run-id `{id}` is not valid: expected 1 to 40 letters, digits, `_` or `-`"
    );
    Ok(())
}

/// The rig setup the arguments ask for (checked), and the sockets bound for the link ends
/// `hil` starts itself.
fn rig_setup(
    rig: &RigArgs,
) -> anyhow::Result<(RigSetup, Vec<std::sync::Arc<std::net::UdpSocket>>)> {
    use crate::link::socket::{bound_loopback_pair, parse_link_address};
    anyhow::ensure!(
        rig.rig_wait_s > 0.0 && rig.rig_wait_s.is_finite(),
        "--rig-wait-s {}: expected a number of seconds > 0",
        rig.rig_wait_s
    );
    let wait = std::time::Duration::from_secs_f64(rig.rig_wait_s);
    match (rig.external(), rig.udp()) {
        (false, false) | (true, false) => {
            anyhow::ensure!(
                rig.link_bind.is_none() && rig.link_peer.is_none(),
                "--link-bind and --link-peer need --rig-link udp"
            );
            Ok((
                if rig.external() {
                    RigSetup::External { wait }
                } else {
                    RigSetup::Simulated
                },
                vec![],
            ))
        }
        (false, true) => {
            anyhow::ensure!(
                rig.link_bind.is_none() && rig.link_peer.is_none(),
                "--rig sim --rig-link udp puts the simulated rig on a loopback link that hil sets up; --link-bind and --link-peer are for --rig external"
            );
            let (link, rig) = bound_loopback_pair()?;
            let setup = RigSetup::SimulatedUdp {
                link: link.local_addr()?,
                rig: rig.local_addr()?,
            };
            Ok((setup, vec![link.into(), rig.into()]))
        }
        (true, true) => {
            let (Some(bind), Some(peer)) = (&rig.link_bind, &rig.link_peer) else {
                anyhow::bail!("--rig external --rig-link udp needs --link-bind IP:PORT (this machine's interface facing the rig) and --link-peer IP:PORT (the rig)");
            };
            Ok((
                RigSetup::ExternalUdp {
                    link: parse_link_address("--link-bind", bind)?,
                    rig: parse_link_address("--link-peer", peer)?,
                    wait,
                },
                vec![],
            ))
        }
    }
}

/// Tells the operator where an external rig must connect.
fn print_rig_instructions(run_id: &str, setup: &RigSetup) {
    use crate::ipc::messages::ABI_VERSION;
    use crate::ipc::{IpcNode, Stream};
    match setup {
        RigSetup::External { wait } => {
            let service = |s| IpcNode::stream_service_name(run_id, s);
            eprintln!(
                "hil: waiting up to {} s for an external rig on iceoryx2 (rig ABI version {ABI_VERSION}, include/fastemu_rig.h):\n\
                 hil:   run id {run_id}: iceoryx2 config global.prefix = \"{run_id}_\"\n\
                 hil:   publish DisplacementSample on {} and Heartbeat on {}\n\
                 hil:   subscribe to ActuatorCommand on {} and RunControl on {}\n\
                 hil:   e.g. bench_rig --run-id {run_id} --config <this config> --out <dir>",
                wait.as_secs_f64(),
                service(Stream::Displacement),
                service(Stream::Heartbeat),
                service(Stream::Command),
                service(Stream::Control),
            );
        }
        RigSetup::ExternalUdp { link, rig, wait } => eprintln!(
            "hil: waiting up to {} s for an external rig on the UDP link (link protocol version {}, README \"UDP rig link\"): fastemu at {link}, the rig at {rig}; the rig sends status datagrams to {link} until it gets START",
            wait.as_secs_f64(),
            crate::link::protocol::LINK_VERSION
        ),
        RigSetup::SimulatedUdp { link, rig } => eprintln!(
            "hil: the simulated rig behind a loopback UDP link: fastemu's link at {link}, the rig at {rig}"
        ),
        RigSetup::Simulated => {}
    }
}

/// The `link` object of the report: fastemu's end (`link-summary.json`) and, with the
/// simulated rig, the rig's end (`rig-summary.json`).
fn link_report(out_dir: &std::path::Path, setup: &RigSetup) -> serde_json::Value {
    if matches!(setup, RigSetup::Simulated | RigSetup::External { .. }) {
        return serde_json::Value::Null;
    }
    let mut link = read_json(&out_dir.join("link-summary.json"));
    if link.is_null() {
        return json!({"transport": "udp", "error": "the link process wrote no summary"});
    }
    let one_way = link["sample_one_way_ns"].clone();
    let (latency, basis) = if one_way.is_object() {
        (
            one_way,
            "sample datagram, rig sent -> fastemu received (one clock: loopback)",
        )
    } else if link["round_trip_ns"].is_object() {
        let rtt = &link["round_trip_ns"];
        let half = |k: &str| rtt[k].as_u64().map(|v| v / 2);
        (
            json!({"p50": half("p50"), "p99": half("p99"), "p999": half("p999"), "max": half("max"), "count": rtt["count"]}),
            "round trip / 2 (command sent -> sample back, minus the rig's hold)",
        )
    } else {
        (serde_json::Value::Null, "no measurement")
    };
    link["latency_ns"] = latency;
    link["latency_basis"] = json!(basis);
    let rig_end = read_json(&out_dir.join("rig-summary.json"))["link"].clone();
    if rig_end.is_object() {
        link["rejected_total_both_ends"] = json!(
            link["rejected_total"].as_u64().unwrap_or(0)
                + rig_end["rejected_total"].as_u64().unwrap_or(0)
        );
        link["rig_end"] = rig_end;
    }
    link
}

/// `yyyymmddThhmmssZ` for a Unix time (UTC), without a date crate.
fn utc_timestamp(unix_s: u64) -> String {
    let [y, m, d, hh, mm, ss] = crate::utc::civil(unix_s as i64);
    format!("{y:04}{m:02}{d:02}T{hh:02}{mm:02}{ss:02}Z")
}

fn read_json(path: &std::path::Path) -> serde_json::Value {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or(serde_json::Value::Null)
}

/// The report directory: `--out`, or `out/hil-<UTC timestamp>`.
fn report_dir(args: &HilArgs) -> anyhow::Result<PathBuf> {
    let out_dir = match &args.out {
        Some(d) => d.clone(),
        None => {
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs());
            let mut dir = PathBuf::from("out").join(format!("hil-{}", utc_timestamp(now)));
            if dir.exists() {
                dir = PathBuf::from("out").join(format!(
                    "hil-{}-{}",
                    utc_timestamp(now),
                    std::process::id()
                ));
            }
            dir
        }
    };
    std::fs::create_dir_all(&out_dir)
        .with_context(|| format!("cannot create report directory {}", out_dir.display()))?;
    Ok(out_dir.canonicalize().unwrap_or(out_dir))
}

/// Loads the configuration with the command line's overrides.
fn load_config(args: &HilArgs) -> anyhow::Result<HilConfig> {
    let mut cfg = load_or_default(args.config.as_deref())?;
    if let Some(d) = args.duration_s {
        anyhow::ensure!(
            d > 0.0 && d.is_finite(),
            "--duration-s {d}: expected a number > 0"
        );
        cfg.set_duration_s(d);
    }
    Ok(cfg)
}

/// Merges the processes' parts into `records.mcap` (after a run; a crashed `hil` leaves
/// the parts, which every reader accepts).
fn merge_records(out_dir: &std::path::Path) -> serde_json::Value {
    if crate::records::reader::list_parts(&out_dir.join("parts")).is_empty() {
        // No process got as far as recording (e.g. no external rig connected): nothing
        // to merge, and no warning about it; the run's faults say why.
        return json!({"file": null, "messages": 0, "parts": 0});
    }
    match merge_parts(out_dir) {
        Ok(m) => {
            for (p, e) in &m.truncated {
                eprintln!("hil: warning: record part {} ends early ({e}); merged up to its last closed chunk, part kept", p.display());
            }
            json!({"file": m.output.display().to_string(), "messages": m.messages, "parts": m.parts,
                   "truncated_parts": m.truncated.iter().map(|(p, e)| format!("{}: {e}", p.display())).collect::<Vec<_>>()})
        }
        Err(e) => {
            eprintln!("hil: warning: records not merged: {e}");
            json!({"error": e.to_string()})
        }
    }
}

/// What the report says of an external rig's hold that only its heartbeat told.
fn external_hold_not_recorded(h: crate::hil::orchestrator::RigHoldSeen) -> String {
    let fault = crate::hil::fault::Fault::from_code(h.fault_code)
        .map_or_else(|| format!("fault code {}", h.fault_code), |f| f.to_string());
    let at = h.at_s.map_or("before the start".to_string(), |t| {
        format!("from about {t:.2} s")
    });
    format!(
        "the external rig reported a {} ({fault}) in its heartbeat {at}, but none of its samples from then on reached the records (the emulator records an external rig's samples: it had ended, or the link was silent), so held_s, the excursions and at_rest cover only what was recorded; the rig's own records hold the rest",
        crate::hil::report::safety::rig_state_name(h.state),
    )
}

/// Checks the live view's options and binds its address when asked, before anything of
/// the run exists (a bad or busy address fails here, leaving nothing behind).
fn bind_live(args: &HilArgs) -> anyhow::Result<Option<crate::live::front::Front>> {
    if !args.live {
        anyhow::ensure!(
            !args.live_control,
            "--live-control needs --live (the services are offered on the live view)"
        );
        return Ok(None);
    }
    anyhow::ensure!(
        args.live_rate_hz.is_finite() && args.live_rate_hz > 0.0,
        "--live-rate-hz {}: expected a number > 0",
        args.live_rate_hz
    );
    crate::live::front::bind(&args.live_addr).map(Some)
}

/// Starts the live view behind its bound address (before the run, so a client can
/// connect early).
fn start_live(
    args: &HilArgs,
    cfg: &HilConfig,
    out_dir: &std::path::Path,
    front: Option<crate::live::front::Front>,
) -> anyhow::Result<Option<crate::live::LiveHandle>> {
    let Some(front) = front else {
        return Ok(None);
    };
    let loopback = front.addr().ip().is_loopback();
    let live = crate::live::start(
        cfg,
        out_dir,
        front,
        &crate::live::LiveOptions {
            rate_hz: args.live_rate_hz,
            control: args.live_control,
        },
    )?;
    eprintln!(
        "hil: live view on ws://{} (Foxglove WebSocket protocol, subprotocol foxglove.sdk.v1 or foxglove.websocket.v1; in the Foxglove app open a connection to it, layout configs/foxglove-layout.json){}",
        live.addr,
        if args.live_control { "; hold/resume/stop offered as services" } else { "" }
    );
    if !loopback {
        eprintln!(
            "hil: warning: the live view listens on {}: anyone who can reach this address can watch the run{}",
            live.addr,
            if args.live_control { " and hold, resume or stop it" } else { "" }
        );
    }
    Ok(Some(live))
}

/// Writes the run's configuration to `out_dir/config.toml` (the embedded default, or a
/// copy of `--config`) and returns the path the processes load it from: the copy for the
/// default, the given file itself otherwise (paths in it stay relative to where it lives).
fn write_report_config(args: &HilArgs, out_dir: &Path) -> anyhow::Result<PathBuf> {
    let copy = out_dir.join("config.toml");
    let Some(given) = &args.config else {
        std::fs::write(&copy, DEFAULT_CONFIG_TOML)
            .with_context(|| format!("cannot write {}", copy.display()))?;
        return Ok(copy);
    };
    let given = given
        .canonicalize()
        .with_context(|| format!("cannot resolve {}", given.display()))?;
    if copy.canonicalize().ok().as_ref() != Some(&given) {
        std::fs::copy(&given, &copy)
            .with_context(|| format!("cannot copy {} to {}", given.display(), copy.display()))?;
    }
    Ok(given)
}

pub fn run(args: HilArgs) -> anyhow::Result<ExitCode> {
    install_signal_handlers();
    quiet_iceoryx2_logs();
    let cfg = load_config(&args)?;
    if args.check {
        return check::run(&args, &cfg);
    }
    // The rig's actuator (the simulated one, or an external one the configuration
    // declares) must be able to hold what the programme loads it with.
    if crate::hil::check::declares_the_rig(&cfg, args.rig.external()) {
        if let Some(why) = crate::hil::check::actuator_cannot_hold(&cfg) {
            anyhow::bail!("{why} (fastemu hil --check)");
        }
        // Nor is a loop that no lead makes stable started, unless asked for.
        if let Some(why) = crate::hil::check::no_stable_lead(&cfg) {
            anyhow::ensure!(args.run_unstable, "{why} (fastemu hil --check)");
            eprintln!("hil: --run-unstable: running a loop that no lead makes stable; expect loop-unstable and a hold");
        }
    }
    let live_front = bind_live(&args)?;
    let out_dir = report_dir(&args)?;
    let config_path = write_report_config(&args, &out_dir)?;
    let _machine_lock = lock_machine(std::time::Duration::from_secs(300), || {
        eprintln!("hil: waiting for another hil run on this machine to finish")
    })?;
    let stale = clear_stale_runs();
    if !stale.is_empty() {
        eprintln!(
            "hil: cleared stale state of crashed runs: {}",
            stale.join(", ")
        );
    }
    let (rig_setup, handed_sockets) = rig_setup(&args.rig)?;
    let run_id = match &args.rig.run_id {
        Some(id) => {
            check_run_id(id)?;
            // A crashed earlier run of this id may have left dead nodes.
            let _ = crate::ipc::cleanup_dead_nodes(id);
            id.clone()
        }
        None => new_run_id(),
    };
    let bin_dir = std::env::current_exe()?
        .parent()
        .map(PathBuf::from)
        .unwrap_or_default();
    let plan = RunPlan {
        run_id: run_id.clone(),
        config_path,
        out_dir: out_dir.clone(),
        duration_s: cfg.scenario.duration_s,
        duration_override_s: args.duration_s,
        bin_dir,
        hold_max_s: cfg.safety.hold_max_s,
        rig: rig_setup.clone(),
        handed_sockets,
    };
    eprintln!(
        "hil: run {run_id}: {} s at {} Hz, {} commands, report in {}",
        cfg.scenario.duration_s,
        cfg.loop_.rate_hz,
        match cfg.controller.command_mode {
            crate::hil::config::CommandMode::Law => "local-law",
            crate::hil::config::CommandMode::Force => "plain force",
        },
        out_dir.display()
    );
    print_rig_instructions(&run_id, &rig_setup);
    // The plan for the declared actuator (the simulated rig's, or an external rig's with
    // plan_for_external_rig), left for the controller; the report judges the run as planned.
    let compensation_plan = crate::hil::check::plan_for_rig(&cfg, args.rig.external());
    // What the configuration asked for, reported as such beside what the plan set.
    let configured = cfg.compensation;
    let cfg = planned_config(&cfg, compensation_plan.as_ref());
    // The controller reads the plan from the report directory: one left there by an
    // earlier run in the same directory must not stand for this one.
    if let Some(p) = &compensation_plan {
        let whose = if args.rig.external() {
            "for the external rig's actuator as [rig.actuator] declares it ([compensation] plan_for_external_rig): "
        } else {
            ""
        };
        eprintln!("hil: {whose}{}", crate::hil::check::describe_plan(p));
    } else if args.rig.external() && !cfg.compensation.plan_for_external_rig {
        eprintln!("hil: the external rig's actuator is unknown to fastemu, which learns its delay and gain during the run (adapt); a lab that knows its actuator and specimen can declare them in [rig.actuator] and [rig] with [compensation] plan_for_external_rig = true, and the launcher plans the compensation for them (docs/compensation.md, \"An external rig's declared actuator\")");
    }
    crate::hil::check::leave_plan(&out_dir, compensation_plan.as_ref())?;
    let cap_s = crate::hil::check::starting_lead_cap_s(&cfg);
    if cap_s < cfg.compensation.initial_delay_s {
        eprintln!(
            "hil: the run starts at a lead of {:.0} us, not at [compensation] initial_delay_us = {:.0} us: that lead would make the loop diverge within milliseconds in front of an actuator twice as fast as the guess; the adaptation takes the lead on from there (docs/compensation.md, \"Adaptation\")",
            cap_s * 1e6,
            cfg.compensation.initial_delay_s * 1e6
        );
    }
    if crate::hil::check::declares_the_rig(&cfg, args.rig.external()) {
        if let Some(warning) = stability_warning(&cfg) {
            eprintln!("hil: WARNING: {warning}");
        }
    }
    for inj in &cfg.injections {
        eprintln!("hil: injected fault configured: {}", inj.describe());
        if inj.at_s >= cfg.scenario.duration_s {
            eprintln!(
                "hil: WARNING: it comes at or after the run's end ({} s of programme, [scenario] duration_s or --duration-s): it fires only if holds stretch the run, and a run it does not fire in is not clean",
                cfg.scenario.duration_s
            );
        }
    }
    let effect_names: Vec<&str> = cfg.augmented.effects.iter().map(|e| e.name()).collect();
    if !effect_names.is_empty() {
        eprintln!(
            "hil: the emulator runs the model's effects [{}] (rig artefacts channel-delay and moving-mass are left out); the fidelity reference integrates the base element only",
            effect_names.join(", ")
        );
    }
    let live = start_live(&args, &cfg, &out_dir, live_front)?;
    let _registration = crate::hil::registry::register(&crate::hil::registry::RunEntry {
        run_id: run_id.clone(),
        pid: std::process::id(),
        report_dir: out_dir.clone(),
        config_origin: cfg.origin.clone(),
        rate_hz: cfg.loop_.rate_hz,
        started_unix_s: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
        live_addr: live.as_ref().map(|l| l.addr.clone()),
    })
    .map_err(|e| eprintln!("hil: warning: run not registered for `fastemu ctl`: {e}"))
    .ok();
    let mut outcome = run_processes(&plan, true, live.as_ref())?;
    if let Some(l) = live {
        l.stop();
    }
    // Process deaths first: they are the cause; the others' reactions follow from them.
    outcome.faults.sort_by_key(|f| !f.contains("process (pid"));
    if args.rig.external() {
        // The rig's slot carries an external rig's own faults (from its samples).
        for f in &mut outcome.faults {
            *f = crate::records::event::external_rig_labelled(f);
        }
    }
    let records = merge_records(&out_dir);
    if args.csv && records["parts"].as_u64() != Some(0) {
        if let Err(e) = crate::cli::export::export_dir(&out_dir, &out_dir) {
            eprintln!("hil: warning: CSV export failed: {e:#}");
        }
    }
    let recorded = records["parts"].as_u64() != Some(0);
    let analysis: Option<Analysis> = match analyse_run(&cfg, &out_dir) {
        Ok(a) => Some(a),
        Err(_) if !recorded => {
            eprintln!("hil: no records and no analysis: the loop never started");
            None
        }
        Err(e) => {
            eprintln!("hil: no analysis: {e:#}");
            None
        }
    };
    // An external rig says it finished in its heartbeat (or the link's finished
    // datagrams), not in the samples the report reads: a session it ended at the
    // programme's end while running says "finished", as the simulated rig's does.
    let analysis = analysis.map(|mut a| {
        match outcome.rig_hold_seen {
            // The rig held, but its samples from then on were not recorded (the emulator,
            // which records an external rig's samples, was dead, or the link silent).
            // (The records end in force control, the heartbeat in a hold.)
            Some(h) if args.rig.external() && a.safety.final_state == "running" => {
                a.safety.final_state =
                    crate::hil::report::safety::rig_state_name(h.state).to_string();
                a.safety.hold_not_recorded = Some(external_hold_not_recorded(h));
            }
            _ if args.rig.external() && a.safety.final_state == "running" => {
                // A rig that said it finished, in a run without faults, finished (its own
                // duration may be shorter than the programme's, or a resume shortened it).
                if outcome.rig_finished && (a.programme.completed || outcome.faults.is_empty()) {
                    a.safety.final_state = "finished".into();
                } else if !a.programme.completed {
                    // The samples stop while it ran: what the rig did then is its own.
                    a.safety.final_state = "unknown".into();
                    a.safety.hold_not_recorded = Some(format!(
                        "the external rig's samples stop at {:.3} s while it was in force control, before the programme's end ({:.1} s), and its heartbeat told no hold: how it ended (a hold on stale commands, as the protocol asks of it) is not in fastemu's records, so held_s, the excursions and at_rest cover only what was recorded; the rig's own records hold the rest",
                        a.rig_steps as f64 * cfg.loop_.dt_s(),
                        a.programme.end_s
                    ));
                }
            }
            _ => {}
        }
        // The guess as configured; `starting_lead_us` is the lead the run started with.
        a.compensation.initial_delay_us = configured.initial_delay_s * 1e6;
        a
    });
    if let Some(a) = &analysis {
        order_faults(&mut outcome.faults, &a.safety.faults);
    }
    summarise(
        &cfg,
        &args,
        &out_dir,
        &run_id,
        &outcome,
        analysis.as_ref(),
        records,
        &effect_names,
        &rig_setup,
        &configured,
    )
}

#[cfg(test)]
mod tests {
    #[test]
    fn timestamp_is_utc_civil_time() {
        assert_eq!(super::utc_timestamp(0), "19700101T000000Z");
        assert_eq!(super::utc_timestamp(1_700_000_000), "20231114T221320Z");
    }
}
