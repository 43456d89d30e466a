//! `fastemu hil`: the product's main command. Validates the config, runs the three
//! processes through the orchestrator, analyses their records, writes the report
//! directory and prints one JSON object with `--json`. Progress goes to stderr.

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
    let days = (unix_s / 86_400) as i64;
    let secs = unix_s % 86_400;
    // Civil-from-days (H. Hinnant).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}{m:02}{d:02}T{:02}{:02}{:02}Z",
        secs / 3600,
        secs / 60 % 60,
        secs % 60
    )
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

/// Before a run on the simulated rig (whose actuator fastemu's config describes): a
/// warning when the linearised loop (`hil --check`) is not stable with the starting lead,
/// naming the leads that would be, or that none is. `None` when stable or in force mode.
fn stability_warning(cfg: &HilConfig) -> Option<String> {
    use crate::hil::check::{nominal_plant, LinearLoop};
    if cfg.controller.command_mode != crate::hil::config::CommandMode::Law {
        return None;
    }
    let cap_s = crate::hil::check::starting_lead_cap_s(cfg);
    let lead_s = cfg.compensation.initial_delay_s.min(cap_s);
    let lin = LinearLoop::for_plant(cfg, &nominal_plant(cfg), lead_s, 1.0);
    let safe_start = lin.safe_start_stable(cfg);
    if lin.margins().stable && safe_start != Some(false) {
        return None;
    }
    if lin.margins().stable {
        return Some(format!(
            "the linearised loop is stable with the starting lead of {:.0} us but not with the safe start's damping ({:.0} kN s/m above {:.0} Hz until the lead is learned; this actuator's lag there turns damping into energy): expect loop-unstable and a hold; with a lead you trust, adapt = false starts without it (fastemu hil --check)",
            lead_s * 1e6,
            crate::hil::check::safe_start_damping_ns_per_m(cfg) * 1e-3,
            cfg.compensation.guard_band_hz
        ));
    }
    let held = match safe_start {
        Some(true) => " The safe start's damping makes it stable while the lead is learned.",
        Some(false) => " Nor is it with the safe start's damping.",
        None => "",
    };
    let relies = match (cfg.compensation.adapt, cfg.compensation.passivity_guard) {
        (false, false) => "With adapt and passivity_guard off nothing makes up for it: expect loop-unstable and a hold",
        (true, false) => "The run relies on the adaptation, and ends in loop-unstable and a hold if it does not make up for it",
        (false, true) => "The run relies on the guard, and ends in loop-unstable and a hold if it does not make up for it",
        (true, true) => "The run relies on the adaptation and the guard, and ends in loop-unstable and a hold if they do not make up for it",
    };
    let whence = if cap_s.is_finite() {
        format!(
            "[compensation] initial_delay_us = {:.0} capped for an actuator twice as fast",
            cfg.compensation.initial_delay_s * 1e6
        )
    } else {
        "[compensation] initial_delay_us".to_string()
    };
    let max = cfg.compensation.max_delay_s;
    let nominal = if cfg.rig.actuator.perturb > 0.0 {
        format!(
            " [these figures are the actuator's nominal values; the rig draws its own within +-{:.0} %, which fastemu does not know]",
            cfg.rig.actuator.perturb * 100.0
        )
    } else {
        String::new()
    };
    let warning = match lin.stable_leads(max) {
        Some((lo, hi)) => format!(
            "the linearised loop is not stable with the starting lead of {:.0} us ({whence}); it is with {:.0}-{:.0} us.{held} {relies}{} (fastemu hil --check)",
            lead_s * 1e6,
            lo * 1e6,
            hi * 1e6,
            dispersive_hint(&lin, cfg.compensation.adapt)
        ),
        None => format!(
            "no lead from 0 to {:.0} us makes the linearised loop stable: {} (docs/compensation.md); expect loop-unstable and a hold (fastemu hil --check)",
            max * 1e6,
            crate::hil::check::why_no_stable_lead(cfg)
        ),
    };
    Some(format!("{warning}{nominal}"))
}

/// For an actuator whose phase delay grows with frequency (a servo-hydraulic force loop):
/// the adaptation learns the load band's delay, which for such actuators lies below the
/// stable leads, so a lead the user trusts is kept only with `adapt = false`; empty when
/// the adaptation is off or the delay is nearly the same over the band.
fn dispersive_hint(lin: &crate::hil::check::LinearLoop, adapt: bool) -> String {
    let (at_2, at_40) = (lin.actuator_at(2.0).0, lin.actuator_at(40.0).0);
    let dispersive = at_2 > 0.0 && at_40 > 1.5 * at_2;
    if !adapt || !dispersive {
        return String::new();
    }
    format!(
        ". This actuator's phase delay runs from {:.0} us at 2 Hz to {:.0} us at 40 Hz: the adaptation learns the load band's delay and walks such leads out of the stable range (docs/compensation.md, \"What does not work yet\"); with a lead you trust inside it, adapt = false keeps it there, though no lead makes up for a delay that varies with frequency (expect a run that is not clean)",
        at_2 * 1e6,
        at_40 * 1e6
    )
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

/// `cfg` with its `[compensation]` as `plan` sets it.
fn planned_config(
    cfg: &HilConfig,
    plan: Option<&crate::hil::check::CompensationPlan>,
) -> HilConfig {
    let mut planned = cfg.clone();
    planned.compensation = crate::hil::check::planned(&cfg.compensation, plan);
    planned
}

/// `hil --check`: the linearised loop's margins, printed, as JSON with `--json`, and its
/// plot. Exit 0 when the loop is stable, 1 when not.
fn check(args: &HilArgs, cfg: &HilConfig) -> anyhow::Result<ExitCode> {
    use crate::hil::check::{describe_actuator, nominal_plant, LinearLoop};
    anyhow::ensure!(
        cfg.controller.command_mode == crate::hil::config::CommandMode::Law,
        "{}: [controller] command_mode = \"force\": --check models local-law commands (the rig's prediction over the controller's lead) only",
        cfg.origin
    );
    // The plan for the simulated rig's declared actuator; the rest is judged as planned.
    let declared = crate::hil::check::declares_the_rig(cfg, args.rig.external());
    let plan = crate::hil::check::plan_for_rig(cfg, args.rig.external());
    // What the controller starts with: the guard's most damping by the lead among it.
    let starting = crate::hil::check::starting_compensation(cfg, plan.as_ref());
    let damping_steps =
        (starting.adapt && starting.adapt_lead && starting.passivity_guard).then(|| {
            crate::hil::check::damping_by_lead_steps(
                &starting.guard_damping_by_lead,
                starting.guard_max_damping_ns_per_m,
                starting.max_delay_s,
            )
        });
    let original_lead_s = cfg
        .compensation
        .initial_delay_s
        .min(crate::hil::check::starting_lead_cap_s(cfg));
    // The configured guess, reported as such (the plan may start elsewhere: `lead_us`).
    let guess_s = cfg.compensation.initial_delay_s;
    let planned = planned_config(cfg, plan.as_ref());
    let cfg = &planned;
    let cap_s = crate::hil::check::starting_lead_cap_s(cfg);
    let lead_s = cfg.compensation.initial_delay_s.min(cap_s);
    // The programme is scanned once (a durability block takes seconds).
    let load_range = crate::hil::check::programme_load_range(cfg);
    let lin = LinearLoop::for_plant(cfg, &nominal_plant(cfg), lead_s, 1.0).with_loads(
        cfg,
        &crate::hil::check::loads_beside_the_preload(cfg, load_range),
    );
    let m = lin.margins();
    let dir = args.out.clone().unwrap_or_else(|| PathBuf::from("."));
    std::fs::create_dir_all(&dir).map_err(|e| anyhow::anyhow!("--out {}: {e}", dir.display()))?;
    let plot = dir.join("check.png");
    lin.plot(&plot, "linearised loop")?;
    let element = crate::model::equiv::equivalent(
        &cfg.model.element,
        cfg.scenario.preload_n,
        2.0 * std::f64::consts::PI * cfg.emulator.law_frequency_hz,
    );
    let band_hz = lin.faithful_band_hz();
    // The safe start: the run's first commands carry its damping
    // (`check::safe_start_damping_ns_per_m`).
    let safe_start = lin.safe_start_stable(cfg);
    // As the run starts: with the safe start's damping when it arms.
    let starts_stable = safe_start.unwrap_or(m.stable);
    let best = lin.most_faithful_stable_lead(cfg.compensation.max_delay_s);
    // The actuator must carry the programme's peak load, or a fault's hold cannot hold.
    let cannot_hold = crate::hil::check::actuator_cannot_hold(cfg);
    // hil refuses a loop no lead makes stable on the simulated rig (unless --run-unstable).
    let no_stable_lead = if declared {
        crate::hil::check::no_stable_lead(cfg)
    } else {
        None
    };
    let [(delay_1_s, amplitude_1, _), (delay_20_s, amplitude_20, velocity_20)] =
        [1.0, 20.0].map(|f| lin.actuator_at(f));
    // Where the specimen starts: at rest under the programme's first force.
    let start_force_n =
        crate::rig::load::LoadProgramme::new(&cfg.programme, cfg.model.length_m).force_n(0.0);
    let start_m = cfg.model.element.static_displacement_m(start_force_n);
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({
                "margins": m,
                "start_displacement_m": start_m,
                "start_force_n": start_force_n,
                "stable_leads_us": lin.stable_leads(cfg.compensation.max_delay_s).map(|(a, b)| [a * 1e6, b * 1e6]),
                "safe_start_damping_ns_per_m": crate::hil::check::safe_start_damping_ns_per_m(cfg),
                "programme_loads": {
                    "lowest_n": load_range.0,
                    "highest_n": load_range.1,
                    "judged_n": lin.other_loads_n(),
                    "unstable_at_n": lin.unstable_loads_n(),
                    "stable_leads_us": lin
                        .stable_leads_over_programme(cfg.compensation.max_delay_s)
                        .map(|(a, b)| [a * 1e6, b * 1e6]),
                },
                "lead_us": lead_s * 1e6,
                "initial_delay_us": guess_s * 1e6,
                "starting_lead_capped": cap_s.is_finite(),
                "lead_order": cfg.compensation.lead_order,
                "safe_start_stable": safe_start,
                "guard_damping_by_lead": damping_steps.as_ref().map(|steps| steps
                    .iter()
                    .map(|&(up_to, d)| json!({"up_to_us": (up_to * 1e6).round(), "damping_ns_per_m": d}))
                    .collect::<Vec<_>>()),
                "starts_stable": starts_stable,
                "actuator_cannot_hold": cannot_hold,
                "no_stable_lead": no_stable_lead,
                "predicted_faithful_band_hz": band_hz,
                "most_faithful_stable_lead": best.map(|(l, b)| json!({"lead_us": l * 1e6, "faithful_band_hz": b})),
                "actuator_phase_delay_us": {"1_hz": delay_1_s * 1e6, "20_hz": delay_20_s * 1e6},
                "actuator_amplitude_ratio": {"1_hz": amplitude_1, "20_hz": amplitude_20},
                "actuator_velocity_force_share_20_hz": velocity_20,
                "actuator": describe_actuator(cfg),
                "plan": plan,
                "plot": plot.display().to_string(),
            }))?
        );
    }
    eprintln!("hil --check: {}", cfg.origin);
    eprintln!(
        "  specimen {:.2} kg, rig damping {:.0} N s/m; element at {:.0} kN preload: {:.1} MN/m, {:.0} N s/m at {:.0} Hz; the specimen starts at rest at {:.6} mm (the element's static displacement under the programme's first force, {:.3} kN: where a rig of its own starts too)",
        cfg.rig.specimen_mass_kg,
        cfg.rig.damping_ns_per_m,
        cfg.scenario.preload_n * 1e-3,
        element.k_eq_n_per_m * 1e-6,
        element.c_eq_ns_per_m,
        cfg.emulator.law_frequency_hz,
        start_m * 1e3,
        start_force_n * 1e-3
    );
    eprintln!(
        "  actuator: {} ({})",
        describe_actuator(cfg),
        match (args.rig.external(), declared) {
            (false, _) => "the simulated rig's [rig.actuator]; a rig of its own is unknown to fastemu, which learns it with adapt = true, unless [compensation] plan_for_external_rig declares it",
            (true, true) => "the external rig's actuator as [rig.actuator] declares it, with [compensation] plan_for_external_rig; [rig] gives its specimen",
            (true, false) => "[rig.actuator], which describes the simulated rig, not this external one: fastemu learns the external rig's actuator with adapt = true ([compensation] plan_for_external_rig = true declares it)",
        }
    );
    if let Some(why) = &cannot_hold {
        eprintln!("  ERROR: {why}");
    }
    if cap_s.is_finite() {
        eprintln!(
            "  starting lead capped at {:.0} us: the guess ({:.0} us) would diverge within milliseconds in front of an actuator twice as fast as it (a lead too long; one too short is what the guard makes up for)",
            cap_s * 1e6,
            cfg.compensation.initial_delay_s * 1e6
        );
    }
    eprintln!(
        "  compensation: starting lead {:.0} us ({}), prediction order {}",
        lead_s * 1e6,
        if !cfg.compensation.adapt_lead {
            "planned, fixed"
        } else if cfg.compensation.start_planned {
            "planned from the declared actuator, not the guess; the adaptation takes it on from there, without a safe start's damping"
        } else if cap_s.is_finite() {
            "[compensation] initial_delay_us, capped"
        } else {
            "[compensation] initial_delay_us"
        },
        cfg.compensation.lead_order
    );
    if m.stable {
        // The faster side is searched down to the lead plus one period earlier: reaching
        // that bound means any faster actuator, however fast.
        let faster_us = m.delay_error_tolerated_faster_us.unwrap_or(f64::NAN);
        let faster = if faster_us >= (lead_s + cfg.loop_.dt_s()) * 1e6 - 1e-3 {
            "any faster one".to_string()
        } else {
            format!("one up to {faster_us:.0} us faster")
        };
        eprintln!(
            "  linearised loop: stable; it tolerates an actuator up to {:.0} us slower than the lead and {faster}; gain margin {:.2}; thinnest at {:.0} Hz (|1 + L| = {:.3})",
            m.delay_error_tolerated_slower_us.unwrap_or(f64::NAN),
            m.gain_margin.unwrap_or(f64::NAN),
            m.thinnest_frequency_hz,
            m.modulus_margin
        );
    } else {
        eprintln!(
            "  linearised loop: NOT STABLE with this lead (nearest to -1 at {:.0} Hz, |1 + L| = {:.3}): the run would end in loop-unstable{}",
            m.thinnest_frequency_hz,
            m.modulus_margin,
            match (
                cfg.compensation.adapt && cfg.compensation.adapt_lead,
                cfg.compensation.passivity_guard
            ) {
                (true, true) => " unless the controller's adaptation and guard make up for it",
                (true, false) => " unless the controller's adaptation makes up for it",
                (false, true) => " unless the passivity guard's damping makes up for it",
                (false, false) => " (adaptation and passivity guard are off)",
            }
        );
    }
    match lin.stable_leads(cfg.compensation.max_delay_s) {
        Some((lo, hi)) => eprintln!(
            "  leads with which the linearised loop is stable: {:.0}-{:.0} us ({})",
            lo * 1e6,
            hi * 1e6,
            if cfg.compensation.adapt && cfg.compensation.adapt_lead {
                format!(
                    "the adaptation keeps the lead within [0, {:.0}] us",
                    cfg.compensation.max_delay_s * 1e6
                )
            } else {
                "the lead stays where it starts".to_string()
            }
        ),
        None => eprintln!(
            "  no lead from 0 to {:.0} us makes the linearised loop stable: {}; {}",
            cfg.compensation.max_delay_s * 1e6,
            crate::hil::check::why_no_stable_lead(cfg),
            if no_stable_lead.is_some() {
                "`fastemu hil` refuses to run it (--run-unstable runs it anyway: expect loop-unstable and a hold that may move the specimen by millimetres)"
            } else {
                "with this actuator, expect loop-unstable and a hold"
            }
        ),
    }
    let loads = lin.other_loads_n();
    if !loads.is_empty() {
        let (lowest, highest) = load_range;
        let unstable = lin.unstable_loads_n();
        let kn = |l: &[f64]| -> String {
            l.iter()
                .map(|x| format!("{:.1} kN", x / 1e3))
                .collect::<Vec<_>>()
                .join(" and ")
        };
        let over = match lin.stable_leads_over_programme(cfg.compensation.max_delay_s) {
            Some((lo, hi)) => format!(
                "leads stable at all three: {:.0}-{:.0} us",
                lo * 1e6,
                hi * 1e6
            ),
            None => "no lead is stable at all three".to_string(),
        };
        eprintln!(
            "  at the programme's lowest and highest load ({:.1} and {:.1} kN; the element stiffens with its load): {}; {over}",
            lowest.max(0.0) / 1e3,
            highest / 1e3,
            if !m.stable {
                "(the loop is not stable at the preload)".to_string()
            } else if unstable.is_empty() {
                "stable with this lead too".to_string()
            } else {
                format!(
                    "NOT stable with this lead under {}: the loop may ring or trip loop-unstable and hold while the load is there (an axle's peak)",
                    kn(&unstable)
                )
            }
        );
    }
    if let Some(p) = &plan {
        eprintln!("  {}", crate::hil::check::describe_plan(p));
        if let Some(t) = &p.scan {
            eprintln!(
                "  {}",
                crate::hil::check::describe_tolerance(
                    t,
                    // The lead the scan judged: the guess's start, which the plan moved.
                    p.start_moved_from_us
                        .map_or(original_lead_s, |us| us * 1e-6)
                )
            );
        }
    }
    if let Some(stable) = safe_start {
        let start_damping = crate::hil::check::safe_start_damping_ns_per_m(cfg);
        eprintln!(
            "  safe start (the guard's {:.0} kN s/m above {:.0} Hz from the first command until the lead is learned{}): the linearised loop is {} with it at this lead{}",
            start_damping * 1e-3,
            cfg.compensation.guard_band_hz,
            if start_damping < cfg.compensation.guard_max_damping_ns_per_m {
                format!(
                    "; less than guard_max_damping_ns_per_m = {:.0} kN s/m, with which the loop at this lead is unstable in front of some actuator between half the guess and the guess",
                    cfg.compensation.guard_max_damping_ns_per_m * 1e-3
                )
            } else {
                String::new()
            },
            if stable { "stable" } else { "NOT stable" },
            match (stable, m.stable) {
                (true, false) => ": it holds the loop while the lead is learned",
                (false, true) => ": the actuator's lag there turns damping into energy; with a lead you trust, adapt = false starts without it",
                _ => "",
            }
        );
    }
    if let Some(steps) = &damping_steps {
        let at = |lead: f64| {
            starting
                .guard_damping_by_lead
                .cap(starting.guard_max_damping_ns_per_m, lead)
                * 1e-3
        };
        eprintln!(
            "  the passivity guard's most damping by the lead in effect (more would turn into energy in front of an actuator as slow as the lead: a pure delay, or a lag of a quarter or half of it): {}; at this lead {:.1} kN s/m{}",
            crate::hil::check::describe_damping_by_lead(steps),
            at(lead_s),
            match best {
                Some((lead, _)) => format!(", at the most faithful stable lead ({:.0} us) {:.1} kN s/m", lead * 1e6, at(lead)),
                None => String::new(),
            }
        );
    }
    if starts_stable {
        eprintln!(
            "  predicted faithful band with this lead: {band_hz:.1} Hz (the rendered force within 1 % and 2 degrees of the element's from 1 Hz up; the run's report measures it on the bins the load excites)"
        );
    } else {
        // A band of a loop that diverges is no promise: said as what it is.
        eprintln!(
            "  predicted faithful band with this lead: none (the loop is not stable as it starts; a stable loop with this rendering would be faithful up to {band_hz:.1} Hz)"
        );
    }
    match best {
        Some((lead, band)) if band < 20.0 => {
            // What a lead and a gain cannot make up for: a delay that changes over the
            // band, an amplitude that does, the actuator's own force on the velocity.
            let mut causes = Vec::new();
            if (delay_20_s - delay_1_s).abs() > 0.1 * delay_1_s.abs().max(delay_20_s.abs()) {
                causes.push(format!(
                    "its phase delay runs from {:.0} us at 1 Hz to {:.0} us at 20 Hz",
                    delay_1_s * 1e6,
                    delay_20_s * 1e6
                ));
            }
            if (amplitude_20 - amplitude_1).abs() > 0.01 {
                causes.push(format!(
                    "its amplitude ratio from {amplitude_1:.3} to {amplitude_20:.3}"
                ));
            }
            if velocity_20 > 0.01 {
                causes.push(format!(
                    "its own force on the specimen's velocity (a servo-valve's residual flow, a shaker's back-EMF) is {:.1} % of the element's at 20 Hz",
                    100.0 * velocity_20
                ));
            }
            eprintln!(
                "  WARNING: no stable lead renders 1-20 Hz within 1 % and 2 degrees (the most faithful, {:.0} us, up to {band:.1} Hz): {}; a lead and a gain do not make up for that. Whether the run is clean is judged on its displacement error ([safety] max_displacement_error); its report's faithful band says how far it was faithful (docs/compensation.md)",
                lead * 1e6,
                if causes.is_empty() { "the prediction's own error".to_string() } else { causes.join(", ") }
            )
        }
        Some((lead, band)) => eprintln!(
            "  most faithful stable lead: {:.0} us (predicted faithful band {band:.1} Hz)",
            lead * 1e6
        ),
        None => {}
    }
    eprintln!("  plot: {}", plot.display());
    Ok(if starts_stable && cannot_hold.is_none() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// Why a run is not clean (empty: clean).
fn not_clean_because(
    cfg: &HilConfig,
    outcome: &RunOutcome,
    analysis: Option<&Analysis>,
    records_dropped: u64,
) -> Vec<String> {
    let mut why = Vec::new();
    if !outcome.faults.is_empty() {
        why.push(format!("faults: {}", outcome.faults.join("; ")));
    }
    match analysis {
        None => why.push("no analysis of the records".into()),
        Some(a) => {
            if !a.stability.stable {
                why.push("the loop was not stable (see stability)".into());
            }
            let error = a.fidelity.displacement_rel_rms;
            if error > cfg.safety.max_displacement_error {
                why.push(format!(
                    "displacement error {:.3} % > [safety] max_displacement_error = {:.3} %",
                    error * 100.0,
                    cfg.safety.max_displacement_error * 100.0
                ));
            }
            if a.loop_energy.not_passive() {
                why.push(a.loop_energy.describe());
            }
            if a.largest_transient_m > cfg.safety.max_transient_m {
                why.push(format!(
                    "largest resonant transient {:.1} um > [safety] max_transient_m = {:.1} um",
                    a.largest_transient_m * 1e6,
                    cfg.safety.max_transient_m * 1e6
                ));
            }
            if !a.records.truncated.is_empty() {
                why.push(format!(
                    "record files cut short: {}",
                    a.records.truncated.join("; ")
                ));
            }
        }
    }
    if records_dropped > 0 {
        why.push(format!(
            "{records_dropped} records dropped (record queue full)"
        ));
    }
    // Without an analysis whether they fired is unknown (and the run is not clean anyway).
    if let Some(missed) = analysis.and_then(|a| injections_not_fired(cfg, a.safety.injected.len()))
    {
        why.push(missed);
    }
    why
}

/// A fault test whose fault never came must not pass as a clean run: the configured
/// `[[inject]]` faults beyond those the records say were injected (`safety.injected`).
fn injections_not_fired(cfg: &HilConfig, fired: usize) -> Option<String> {
    let configured = cfg.injections.len();
    (fired < configured).then(|| {
        let all: Vec<String> = cfg.injections.iter().map(|i| i.describe()).collect();
        format!(
            "{} of {configured} configured [[inject]] faults never fired (configured: {}; the run ended at {} s of programme)",
            configured - fired,
            all.join(", "),
            cfg.scenario.duration_s
        )
    })
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
        return check(&args, &cfg);
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

/// Orders the faults the processes reported (in the order their heartbeats or exits
/// reached `hil`, which varies between runs) as they happened: process deaths and a
/// failed link first (the cause), then by when the records say each was detected
/// (`safety.faults`), a fault the records do not date last; ties in text order. The same
/// faults print in the same order whatever order they arrived in.
fn order_faults(faults: &mut [String], dated: &[crate::hil::report::safety::FaultReport]) {
    let when = |f: &String| -> f64 {
        // "process: fault (detail)"; an external rig's own faults are labelled likewise.
        let (process, rest) = f.split_once(": ").unwrap_or(("", f.as_str()));
        let name = rest.split([' ', '(']).next().unwrap_or(rest);
        let earliest = |same_process: bool| {
            dated
                .iter()
                .filter(|d| d.fault == name && (!same_process || d.process == process))
                .map(|d| d.detected_at_s)
                .fold(None, |m: Option<f64>, t| Some(m.map_or(t, |m| m.min(t))))
        };
        earliest(true)
            .or_else(|| earliest(false))
            .unwrap_or(f64::INFINITY)
    };
    // Causes first: a process that died, or the link that failed (their reactions follow);
    // ties (undated faults) in text order, so that the same faults print the same way.
    faults.sort_by(|a, b| {
        let reaction = |f: &String| !(f.contains("process (pid") || f.starts_with("link: "));
        reaction(a)
            .cmp(&reaction(b))
            .then(when(a).total_cmp(&when(b)))
            .then(a.cmp(b))
    });
}

/// Writes `summary.json`, prints the one-line result (and `--json`), returns the exit code.
#[allow(clippy::too_many_arguments)]
fn summarise(
    cfg: &HilConfig,
    args: &HilArgs,
    out_dir: &std::path::Path,
    run_id: &str,
    outcome: &RunOutcome,
    analysis: Option<&Analysis>,
    records: serde_json::Value,
    effect_names: &[&str],
    rig_setup: &RigSetup,
    configured: &crate::hil::compensation::CompensationConfig,
) -> anyhow::Result<ExitCode> {
    let emu = read_json(&out_dir.join("emulator-summary.json"));
    let rig = read_json(&out_dir.join("rig-summary.json"));
    let ctl = read_json(&out_dir.join("controller-summary.json"));
    let u =
        |v: &serde_json::Value, k: &str| v.get(k).and_then(serde_json::Value::as_u64).unwrap_or(0);
    let dropped = |v: &serde_json::Value| {
        v["records"]["dropped"].as_u64().unwrap_or(0) + v["events"]["dropped"].as_u64().unwrap_or(0)
    };
    let records_dropped = dropped(&emu) + dropped(&ctl) + dropped(&rig);
    // The product's fixed-step loop is the emulator's; the rig's misses (the simulated
    // hardware's own timing) are reported separately.
    let deadline_misses = u(&emu, "missed_deadlines");
    let stable = outcome.faults.is_empty() && analysis.is_some_and(|a| a.stability.stable);
    let why = not_clean_because(cfg, outcome, analysis, records_dropped);
    let clean = why.is_empty();
    let value = |v: Option<serde_json::Value>| v.unwrap_or(serde_json::Value::Null);
    let mut summary = json!({
        "rate_hz": cfg.loop_.rate_hz,
        "duration_s": cfg.scenario.duration_s,
        "steps": analysis.map_or(u(&emu, "model_steps"), |a| a.steps),
        "deadline_misses": deadline_misses,
        "deadline_misses_emulator": deadline_misses,
        // An external rig's own timing is not known to fastemu: null, not 0.
        "deadline_misses_rig": if args.rig.external() {
            serde_json::Value::Null
        } else {
            json!(u(&rig, "missed_deadlines"))
        },
        "emulator_standby_cycles": u(&emu, "standby_cycles"),
        "stale_samples": u(&emu, "stale_cycles"),
        "missing_samples": u(&emu, "missing_samples"),
        "records_dropped": records_dropped,
        "stable": stable,
        "clean": clean,
        "not_clean_because": why,
        "faults": outcome.faults,
        "operator_stop": outcome.operator_stop
            || analysis.is_some_and(|a| a.safety.operator_actions.iter().any(|x| x.ends_with("operator stop"))),
        "safety": value(analysis.map(|a| serde_json::to_value(&a.safety).unwrap_or_default())),
        "loop_energy": value(analysis.map(|a| serde_json::to_value(a.loop_energy).unwrap_or_default())),
        "stalls": value(analysis.map(|a| json!({
            "count": a.stalls.count,
            "ended_in_hold": a.stalls.ended_in_hold,
            "longest_ms": a.stalls.longest_ms,
            "largest_transient_um": a.stalls.largest_transient_m * 1e6,
            "largest_rise_um": a.stalls.largest_rise_m * 1e6,
            "episodes": a.stalls.episodes.iter().map(|e| json!({
                "at_s": e.at_s, "length_ms": e.length_ms, "transient_um": e.transient_m * 1e6,
                "before_um": e.before_m * 1e6, "source": e.source,
            })).collect::<Vec<_>>(),
        }))),
        "programme": value(analysis.map(|a| serde_json::to_value(&a.programme).unwrap_or_default())),
        "largest_transient_um": value(analysis.map(|a| json!(a.largest_transient_m * 1e6))),
        "max_transient_um": cfg.safety.max_transient_m * 1e6,
        "fidelity": value(analysis.map(|a| serde_json::to_value(&a.fidelity).unwrap_or_default())),
        "stability": value(analysis.map(|a| serde_json::to_value(&a.stability).unwrap_or_default())),
        "compensation": value(analysis.map(|a| serde_json::to_value(&a.compensation).unwrap_or_default())),
        "latency_ns": value(analysis.map(|a| serde_json::to_value(&a.latency_ns).unwrap_or_default())),
        "events": value(analysis.map(|a| json!(a.events))),
        "actuator_truth": value(analysis.and_then(|a| a.actuator_truth.as_ref()).map(|t| serde_json::to_value(t).unwrap_or_default())),
        "element_thermal": value(analysis.and_then(|a| a.element_thermal.as_ref()).map(|t| serde_json::to_value(t).unwrap_or_default())),
        "model": {
            "form": cfg.model.element.form().name(),
            "length_m": cfg.model.length_m,
            "effects": effect_names,
        },
        "commands": {
            "mode": match cfg.controller.command_mode {
                crate::hil::config::CommandMode::Law => "law",
                crate::hil::config::CommandMode::Force => "force",
            },
            // As configured; what the plan made of them: `compensation.plan`.
            "initial_delay_us": configured.initial_delay_s * 1e6,
            "lead_order": configured.lead_order,
            "adapt": configured.adapt,
            "passivity_guard": configured.passivity_guard,
        },
        "force_mode_compensation": {
            "enabled": cfg.controller.compensation_enabled,
            "order": cfg.controller.compensation_order,
            "delay_us": cfg.controller.compensation_delay_s * 1e6,
        },
        "records": records,
        "processes": {"bench_rig": rig, "emulator": emu, "controller": ctl, "exit": outcome.exit_statuses},
        "leftover_files_removed": outcome.leftover_files.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "run_id": run_id,
        "report_dir": out_dir.display().to_string(),
    });
    summary["rig"] = json!({"kind": args.rig.kind, "link": args.rig.link});
    // The launcher's plan for the declared actuator (none: as configured).
    if let Some(c) = summary
        .get_mut("compensation")
        .and_then(|c| c.as_object_mut())
    {
        let plan = crate::hil::check::read_plan(out_dir).unwrap_or(None);
        // The declaration against what the load band identified (not the lead's own
        // estimator, which reads a servo loop short).
        let identified = analysis
            .map(|a| &a.compensation)
            .filter(|c| c.identified_from == Some("load-band"))
            .and_then(|c| c.identified_delay_us);
        let warning = plan
            .as_ref()
            .zip(identified)
            .and_then(|(p, d)| crate::hil::check::declaration_check(p, d));
        c.insert("declaration_warning".into(), warning.into());
        c.insert("plan".into(), serde_json::to_value(plan)?);
    }
    summary["link"] = link_report(out_dir, rig_setup);
    let text = serde_json::to_string_pretty(&summary)?;
    std::fs::write(out_dir.join("summary.json"), &text)?;
    if args.json {
        // Stdout stays one compact line: the compensation's per-frequency rendering and
        // its trajectory are in summary.json only.
        let mut compact = summary.clone();
        if let Some(c) = compact
            .get_mut("compensation")
            .and_then(|c| c.as_object_mut())
        {
            for key in ["rendering", "trajectory"] {
                if let Some(v) = c.remove(key) {
                    let n = v.as_array().map_or(0, Vec::len);
                    c.insert(format!("{key}_points"), n.into());
                }
            }
        }
        println!("{}", serde_json::to_string(&compact)?);
    }
    if let Some(a) = analysis {
        // An external rig reports no timing of its own (its misses are its own business).
        let rig_timing = match rig_setup {
            RigSetup::External { .. } | RigSetup::ExternalUdp { .. } => {
                "the rig is external: its own timing is not known".to_string()
            }
            _ => format!(
                "the simulated rig's own timing: {} missed",
                summary["deadline_misses_rig"].as_u64().unwrap_or(0)
            ),
        };
        eprintln!(
            "hil: {} steps, {deadline_misses} emulator deadline misses ({:.1e}; {rig_timing}), {} stalls ridden through (longest {:.1} ms{}), largest transient {:.2} um of {:.1} um allowed ({:.2} um after a stall, {:.2} um above the residual before it), displacement rel. RMS error {:.3} %, stable {}, end-to-end p50 {} us p99 {} us",
            a.steps,
            deadline_misses as f64 / a.steps.max(1) as f64,
            a.stalls.count,
            a.stalls.longest_ms,
            // Every run's law ends in a hold (the programme's end too): said only when a
            // fault's hold ended a stall.
            match a.stalls.ended_in_hold {
                n if n > 0 && summary["faults"].as_array().is_some_and(|f| !f.is_empty()) => {
                    format!("; {n} more ended in the fault's hold")
                }
                _ => String::new(),
            },
            a.largest_transient_m * 1e6,
            cfg.safety.max_transient_m * 1e6,
            a.stalls.largest_transient_m * 1e6,
            a.stalls.largest_rise_m.max(0.0) * 1e6,
            a.fidelity.displacement_rel_rms * 100.0,
            // As summary.json's `stable`: a fault makes a run not stable, whatever the
            // residual before it showed (`stability.stable`).
            match (summary["stable"] == true, a.stability.stable) {
                (true, _) => "true",
                (false, true) => "false (a fault; before it the residual did not grow)",
                (false, false) => "false",
            },
            a.latency_ns.end_to_end.p50 / 1000,
            a.latency_ns.end_to_end.p99 / 1000
        );
        if let Some(t) = &a.actuator_truth {
            eprintln!("hil: {}", t.describe());
        }
        if cfg.controller.command_mode == crate::hil::config::CommandMode::Law {
            eprintln!("hil: {}", a.compensation.describe());
            if let Some(w) = summary["compensation"]["declaration_warning"].as_str() {
                eprintln!("hil: {w}");
            }
        }
        if let Some(e) = &a.element_thermal {
            eprintln!("hil: {}", e.describe());
        }
        print_programme_and_operator(a, summary["operator_stop"] == true);
        for f in &a.safety.faults {
            eprintln!(
                "hil: fault {}: {}{} at {:.3} s (after {} periods) -> {}{}; largest excursion {} ({} beyond the pre-fault range), {}",
                f.process,
                f.fault,
                f.cause.as_ref().map_or(String::new(), |c| format!(" ({c})")),
                f.detected_at_s,
                f.detection_latency_periods,
                f.action.as_deref().unwrap_or("the controller acts"),
                f.already_held_since_s.map_or(String::new(), |t| format!(
                    " (the rig already held the specimen, since {t:.3} s)"
                )),
                micrometres(f.largest_excursion_m),
                micrometres(f.beyond_prefault_range_m),
                match f.time_to_rest_s {
                    None => "never at rest".to_string(),
                    Some(t) if t == 0.0 && f.already_held_since_s.is_some() => "already at rest".to_string(),
                    Some(t) => format!("at rest after {t:.3} s"),
                }
            );
            if let Some(seen) = &f.instability {
                eprintln!("hil:   it tripped on {}", seen.describe());
            }
        }
        if let Some(note) = &a.safety.hold_not_recorded {
            eprintln!("hil: {note}");
        }
    }
    if !outcome.faults.is_empty() {
        eprintln!("hil: FAULT: {}", outcome.faults.join("; "));
        eprintln!("hil: report in {}", out_dir.display());
        // Faults before the loop ever ran (no rig connected, a rig of another link
        // protocol, a process that died while setting up): nothing was loaded or held,
        // so there is no verdict on a run.
        if !outcome.started {
            eprintln!("hil: no verdict: the loop never started");
            return Ok(ExitCode::from(3));
        }
        return Ok(ExitCode::from(2));
    }
    if !clean {
        eprintln!("hil: NOT CLEAN: {}", summary["not_clean_because"]);
        eprintln!("hil: report in {}", out_dir.display());
        return Ok(ExitCode::from(1));
    }
    eprintln!("hil: clean run; report in {}", out_dir.display());
    Ok(ExitCode::SUCCESS)
}

/// The programme's progress and how it ended, and every operator action with its time.
fn print_programme_and_operator(a: &Analysis, operator_stop: bool) {
    let p = &a.programme;
    let ended = if operator_stop {
        "ended by an operator stop (orderly unload)".to_string()
    } else if p.completed {
        "ran to its end".to_string()
    } else if !a.safety.faults.is_empty() {
        "ended by a fault hold".to_string()
    } else {
        format!(
            "stopped at the run's duration ({:.1} s of {:.1} s)",
            p.programme_time_s, p.end_s
        )
    };
    eprintln!(
        "hil: programme: {:.1} s, cycles completed {}, last block {} `{}`; {ended}",
        p.programme_time_s, p.cycles_completed, p.last_block, p.last_block_name
    );
    if !a.safety.operator_actions.is_empty() {
        eprintln!("hil: operator: {}", a.safety.operator_actions.join("; "));
    }
}

/// "12.3 um", or "unknown" when the rig recorded nothing after the fault.
fn micrometres(m: Option<f64>) -> String {
    m.map_or("unknown".into(), |m| {
        if m.abs() >= 0.1 {
            format!("{m:.2} m")
        } else if m.abs() >= 1e-3 {
            format!("{:.2} mm", m * 1e3)
        } else {
            format!("{:.1} um", m * 1e6)
        }
    })
}

#[cfg(test)]
mod tests {
    /// The faults as reported in any order come out deaths and a failed link first, then
    /// by when the records dated them, an undated one last, ties in text order.
    #[test]
    fn faults_are_ordered_as_they_happened() {
        let dated = |process: &str, fault: &str, at: f64| crate::hil::report::safety::FaultReport {
            process: process.into(),
            fault: fault.into(),
            cause: None,
            detected_at_s: at,
            detection_latency_periods: 0,
            action: None,
            hold_started_at_s: None,
            position_at_fault_m: None,
            largest_excursion_m: None,
            prefault_range_m: [0.0; 2],
            beyond_prefault_range_m: None,
            time_to_rest_s: None,
            already_held_since_s: None,
            instability: None,
        };
        let records = [
            dated("emulator", "emulator-stalled", 2.4),
            dated("controller", "setpoints-stale", 2.1005),
            dated("bench_rig", "commands-stale", 2.3),
        ];
        let expected = vec![
            "controller: process (pid 9) killed by signal 9".to_string(),
            "emulator: process (pid 7) killed by signal 9".to_string(),
            "link: the rig went silent".to_string(),
            "controller: setpoints-stale (emulator: emulator-stalled)".to_string(),
            "bench_rig: commands-stale".to_string(),
            "emulator: emulator-stalled".to_string(),
        ];
        // In whatever order they arrived.
        for turn in 0..expected.len() {
            for reversed in [false, true] {
                let mut faults = expected.clone();
                faults.rotate_left(turn);
                if reversed {
                    faults.reverse();
                }
                super::order_faults(&mut faults, &records);
                assert_eq!(faults, expected, "turn {turn}, reversed {reversed}");
            }
        }
    }

    /// A configured injection the records do not show (the run ended first) makes the run
    /// not clean, naming it; none configured, or all fired, says nothing.
    #[test]
    fn an_injection_that_never_fired_is_named() {
        use crate::hil::config::{InjectKind, Injection, LoopProcess};
        let mut cfg = crate::hil::config::default_hil_config().unwrap();
        assert_eq!(super::injections_not_fired(&cfg, 0), None);
        cfg.injections.push(Injection {
            process: LoopProcess::Emulator,
            kind: InjectKind::Stall { duration_s: 0.1 },
            at_s: 9.0,
        });
        assert_eq!(super::injections_not_fired(&cfg, 1), None);
        let why = super::injections_not_fired(&cfg, 0).expect("named");
        assert!(
            why.starts_with("1 of 1 configured [[inject]] faults never fired")
                && why.contains("emulator stall 100 ms at 9.000 s"),
            "{why}"
        );
    }

    #[test]
    fn timestamp_is_utc_civil_time() {
        assert_eq!(super::utc_timestamp(0), "19700101T000000Z");
        assert_eq!(super::utc_timestamp(1_700_000_000), "20231114T221320Z");
    }

    /// The pre-run warning: none on the default configuration; the leads that would be
    /// stable when the starting lead is far off, and that the safe start holds it there;
    /// a lead stable alone but not with the safe start's damping (a servo-hydraulic force
    /// loop lags too much above 60 Hz), and why the adaptation does not keep such a loop's
    /// lead; "no lead" for an actuator too slow.
    #[test]
    fn a_run_is_warned_when_its_linearised_loop_is_not_stable() {
        use crate::hil::config::{default_hil_config, parse_hil_config, DEFAULT_CONFIG_TOML};
        assert_eq!(
            super::stability_warning(&default_hil_config().unwrap()),
            None
        );
        let mut far = default_hil_config().unwrap();
        far.compensation.initial_delay_s = 0.0;
        let w = super::stability_warning(&far).expect("a lead of 0 is unstable");
        assert!(
            w.contains("starting lead of 0 us")
                && w.contains("it is with")
                && w.contains("The safe start's damping makes it stable")
                && !w.contains("phase delay runs from"),
            "{w}"
        );
        // A servo-hydraulic force loop from the shipped guess: the stable leads, and why
        // the adaptation will not keep a lead there (its delay grows with frequency).
        let servo_guess = DEFAULT_CONFIG_TOML.replace(
            "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0",
            "preset = \"fatigue-150kn\"",
        );
        let servo_guess = parse_hil_config(&servo_guess, "servo.toml", None).unwrap();
        let w = super::stability_warning(&servo_guess).expect("252 us is unstable there");
        assert!(
            w.contains("starting lead of 252 us")
                && w.contains("it is with 2220-3360 us")
                && w.contains("phase delay runs from 745 us at 2 Hz to 3399 us at 40 Hz")
                && w.contains("adapt = false keeps it there"),
            "{w}"
        );
        let servo = DEFAULT_CONFIG_TOML
            .replace(
                "kind = \"lag-delay\"\ntransport_delay_us = 50.0\nlag_us = 80.0\nforce_max_n = 150000.0",
                "preset = \"fatigue-150kn\"",
            )
            .replace("initial_delay_us = 252.0", "initial_delay_us = 2790.0");
        let servo = parse_hil_config(&servo, "servo.toml", None).unwrap();
        let w = super::stability_warning(&servo).expect("the safe start is not stable there");
        assert!(
            w.contains(
                "is stable with the starting lead of 2790 us but not with the safe start's damping"
            ),
            "{w}"
        );
        let mut trusted = servo.clone();
        trusted.compensation.adapt = false;
        assert_eq!(super::stability_warning(&trusted), None);
        // A lead 100 us short with nothing to make up for it says so.
        let mut bare = default_hil_config().unwrap();
        bare.compensation.initial_delay_s = 152e-6;
        bare.compensation.adapt = false;
        bare.compensation.passivity_guard = false;
        let w = super::stability_warning(&bare).expect("152 us is unstable");
        assert!(w.contains("nothing makes up for it"), "{w}");
        let slow = DEFAULT_CONFIG_TOML
            .replace("transport_delay_us = 50.0", "transport_delay_us = 3000.0")
            .replace("lag_us = 80.0", "lag_us = 2000.0");
        let slow = parse_hil_config(&slow, "slow.toml", None).unwrap();
        let w = super::stability_warning(&slow).expect("3 ms + 2 ms is unstable");
        assert!(w.contains("no lead from 0 to"), "{w}");
    }
}
