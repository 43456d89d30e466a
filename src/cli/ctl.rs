//! `fastemu ctl [--run-id ID] hold|resume|stop|status`: operator control of a running
//! `hil` from another terminal (same user: it finds the run in the user's registry and
//! speaks to it over the run's own shared memory). `hold` puts the rig into a position
//! hold and pauses the programme; `resume` continues it without a jump; `stop` ends it in
//! an orderly unload; `status` prints each process's state. Every action lands in the
//! rig's records with its time. `ctl` speaks to the run's orchestrator only (its
//! operator services: requests in, the processes' heartbeats relayed out), never to a
//! loop's ports, so a `ctl` mid-run costs the loops nothing.

use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::{Args, Subcommand};

use crate::hil::fault::fault_code_name;
use crate::hil::registry::{running, RunEntry, Scan};
use crate::ipc::messages::{
    controller_state, emulator_state, process_id, rig_state, run_command, Heartbeat, RunControl,
    HEARTBEAT_READY,
};
use crate::ipc::{quiet_iceoryx2_logs, IpcNode};

#[derive(Debug, Clone, Args)]
pub struct CtlArgs {
    /// The run to control (default: the only run of this user; `status` lists them all).
    #[arg(long)]
    pub run_id: Option<String>,
    #[command(subcommand)]
    pub action: CtlAction,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Subcommand)]
pub enum CtlAction {
    /// Hold the specimen's position and pause the load programme.
    Hold,
    /// Continue the programme from where it paused (force control again, no jump).
    Resume,
    /// End the run in an orderly way: hold, unload the programme to zero, finish.
    Stop,
    /// The state of each process of the run.
    Status,
}

/// Says on stderr which registry entries could not be read, and why.
fn report_skipped(scan: &Scan) {
    for s in &scan.skipped {
        eprintln!("ctl: {s}");
    }
}

/// The run to control. The skipped entries are reported when they matter: when no run is
/// chosen, or when one is chosen by elimination (a skipped entry may be another run).
fn find_run(scan: Scan, run_id: Option<&str>) -> anyhow::Result<RunEntry> {
    let found = match run_id {
        Some(id) => scan
            .runs
            .iter()
            .find(|r| r.run_id == id)
            .cloned()
            .ok_or_else(|| {
                anyhow::anyhow!(
                    "no running hil run `{id}` of this user (`fastemu ctl status` lists them)"
                )
            }),
        None => match scan.runs.len() {
            0 => Err(anyhow::anyhow!("no hil run of this user is running")),
            1 => Ok(scan.runs[0].clone()),
            _ => Err(anyhow::anyhow!(
                "{} hil runs are running ({}): choose one with --run-id",
                scan.runs.len(),
                scan.runs
                    .iter()
                    .map(|r| r.run_id.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )),
        },
    };
    if found.is_err() || run_id.is_none() {
        report_skipped(&scan);
    }
    found
}

fn state_name(hb: &Heartbeat) -> String {
    if hb.state == HEARTBEAT_READY {
        return "ready".into();
    }
    let name = match hb.process {
        process_id::RIG => match hb.state {
            rig_state::RUNNING => "running",
            rig_state::HOLD => "hold (fault)",
            rig_state::UNLOAD => "unloading",
            rig_state::OPERATOR_HOLD => "hold (operator)",
            rig_state::FINISHED => "finished",
            _ => "starting",
        },
        process_id::EMULATOR => match hb.state {
            emulator_state::RUNNING => "running",
            emulator_state::TRIPPED => "tripped",
            emulator_state::STOPPED => "stopped",
            _ => "starting",
        },
        _ => match hb.state {
            controller_state::RUNNING => "running",
            controller_state::FAULT_INDICATED => "fault indicated",
            controller_state::HOLDING => "holding",
            controller_state::STOPPED => "stopped",
            _ => "starting",
        },
    };
    let mut text = name.to_string();
    if hb.fault_code != 0 {
        text.push_str(&format!(", fault {}", fault_code_name(hb.fault_code)));
    }
    text
}

/// The newest heartbeat of each process within `window`.
fn heartbeats(node: &IpcNode, window: Duration) -> anyhow::Result<[Option<Heartbeat>; 3]> {
    let input = node.operator_status_in()?;
    let mut latest = [None; 3];
    let t = Instant::now();
    while t.elapsed() < window {
        input.receive_each(|hb| {
            if let Some(slot) = latest.get_mut(hb.process as usize) {
                *slot = Some(hb);
            }
        });
        std::thread::sleep(Duration::from_millis(5));
    }
    Ok(latest)
}

fn print_status(run: &RunEntry, node: &IpcNode) -> anyhow::Result<()> {
    let latest = heartbeats(node, Duration::from_millis(150))?;
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    println!(
        "run {} (hil pid {}), {} s since start, report in {}{}",
        run.run_id,
        run.pid,
        now.saturating_sub(run.started_unix_s),
        run.report_dir.display(),
        run.live_addr
            .as_ref()
            .map_or(String::new(), |a| format!(", live view ws://{a}"))
    );
    for (i, name) in ["bench_rig", "emulator", "controller"].iter().enumerate() {
        match &latest[i] {
            Some(hb) if i == 0 => println!(
                "  {name}: {} (t = {:.2} s)",
                state_name(hb),
                hb.sequence as f64 / run.rate_hz
            ),
            Some(hb) => println!("  {name}: {}", state_name(hb)),
            None => println!("  {name}: no heartbeat (not running, or stopped)"),
        }
    }
    Ok(())
}

pub fn run(args: CtlArgs) -> anyhow::Result<ExitCode> {
    quiet_iceoryx2_logs();
    let scan = running();
    if args.action == CtlAction::Status && args.run_id.is_none() && scan.runs.len() > 1 {
        report_skipped(&scan);
        for run in &scan.runs {
            let node = IpcNode::new(&run.run_id, "ctl")?;
            print_status(run, &node)?;
        }
        return Ok(ExitCode::SUCCESS);
    }
    let run = find_run(scan, args.run_id.as_deref())?;
    let node = IpcNode::new(&run.run_id, "ctl")?;
    let (command, wanted): (u32, &[u32]) = match args.action {
        CtlAction::Status => {
            print_status(&run, &node)?;
            return Ok(ExitCode::SUCCESS);
        }
        CtlAction::Hold => (
            run_command::HOLD,
            &[rig_state::OPERATOR_HOLD, rig_state::HOLD],
        ),
        CtlAction::Resume => (run_command::RESUME, &[rig_state::RUNNING]),
        CtlAction::Stop => (run_command::END, &[rig_state::UNLOAD, rig_state::FINISHED]),
    };
    // Subscribe first: a stop may finish the run quickly.
    let input = node.operator_status_in()?;
    let requests = node.operator_request_out()?;
    requests.publish(RunControl {
        sequence: std::process::id() as u64,
        start_time_ns: 0,
        start_unix_ns: 0,
        command,
        reserved: 0,
    });
    // Confirm from the rig's heartbeats, as the orchestrator relays them (it relays the
    // request and the heartbeats every 5 ms; the rig reads run control every 10 ms).
    let t = Instant::now();
    let mut last = None;
    while t.elapsed() < Duration::from_secs(2) {
        input.receive_each(|hb| {
            if hb.process == process_id::RIG {
                last = Some(hb);
            }
        });
        if last.is_some_and(|hb| wanted.contains(&hb.state)) {
            let hb = last.expect("checked");
            println!(
                "ctl {}: done; rig state {} at t = {:.3} s (run {})",
                format!("{:?}", args.action).to_lowercase(),
                state_name(&hb),
                hb.sequence as f64 / run.rate_hz,
                run.run_id
            );
            return Ok(ExitCode::SUCCESS);
        }
        // The run ended at the stop (it had not started: no unload to confirm).
        if args.action == CtlAction::Stop && crate::hil::registry::has_ended(&run) {
            println!("ctl stop: done; run {} ended", run.run_id);
            return Ok(ExitCode::SUCCESS);
        }
        // No rig heartbeat after 300 ms: no rig is there yet (an external rig awaited).
        // A stop then ends the run before it starts; the orchestrator waits for the
        // run's nodes to go before it clears the run, so leave it and wait for the end.
        if args.action == CtlAction::Stop
            && last.is_none()
            && t.elapsed() > Duration::from_millis(300)
        {
            drop(input);
            drop(requests);
            drop(node);
            return Ok(wait_for_the_end(&run));
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let seen = last.map_or("no heartbeat".to_string(), |hb| state_name(&hb));
    eprintln!(
        "ctl {}: sent to run {}, but the rig did not confirm within 2 s (its state: {seen})",
        format!("{:?}", args.action).to_lowercase(),
        run.run_id
    );
    Ok(ExitCode::from(2))
}

/// `ctl stop` of a run whose rig never came: waits up to 5 s for the run to end.
fn wait_for_the_end(run: &RunEntry) -> ExitCode {
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(5) {
        if crate::hil::registry::has_ended(run) {
            println!(
                "ctl stop: done; run {} ended before its rig started",
                run.run_id
            );
            return ExitCode::SUCCESS;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    eprintln!(
        "ctl stop: sent to run {}, which has no rig yet, but it did not end within 5 s",
        run.run_id
    );
    ExitCode::from(2)
}
