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
    controller_state, emulator_state, operator_answer, process_id, rig_state, run_command,
    Heartbeat, RunControl, HEARTBEAT_READY,
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
            drop(node);
            tidy_after(run);
        }
        return Ok(ExitCode::SUCCESS);
    }
    let run = find_run(scan, args.run_id.as_deref())?;
    let code = act(&args, &run);
    tidy_after(&run);
    code
}

/// A `ctl` that met a run in its last moments (its `hil` already cleared the run's
/// files) left the files its own node created; once the run has ended and no node of
/// it is left (an external rig still connected keeps its files), they are cleared.
fn tidy_after(run: &RunEntry) {
    if crate::hil::registry::has_ended(run)
        && crate::ipc::count_nodes(&run.run_id).is_ok_and(|n| n == 0)
    {
        crate::ipc::cleanup::clear_run(&run.run_id);
    }
}

/// Sends `args.action` to `run` and waits for its answer and the rig's confirmation.
fn act(args: &CtlArgs, run: &RunEntry) -> anyhow::Result<ExitCode> {
    let node = IpcNode::new(&run.run_id, "ctl")?;
    let (command, wanted): (u32, &[u32]) = match args.action {
        CtlAction::Status => {
            print_status(run, &node)?;
            return Ok(ExitCode::SUCCESS);
        }
        CtlAction::Hold => (
            run_command::HOLD,
            &[rig_state::OPERATOR_HOLD, rig_state::HOLD],
        ),
        CtlAction::Resume => (run_command::RESUME, &[rig_state::RUNNING]),
        CtlAction::Stop => (run_command::END, &[rig_state::UNLOAD, rig_state::FINISHED]),
    };
    // Subscribe first: a stop may finish the run quickly. The request goes to the run's
    // orchestrator, which answers it (`operator_answer`) and relays it to the rig; it is
    // sent again every 100 ms until answered (the orchestrator may not have subscribed
    // yet, or may have been busy), a repeat is answered, not relayed again.
    let input = node.operator_status_in()?;
    let requests = node.operator_request_out()?;
    let sequence = (u64::from(std::process::id()) << 32)
        | u64::from(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.subsec_nanos()),
        );
    let action = format!("{:?}", args.action).to_lowercase();
    let t = Instant::now();
    let mut sent_at: Option<Instant> = None;
    let mut answer = None;
    let mut last = None;
    while t.elapsed() < Duration::from_secs(2) {
        if answer.is_none() && sent_at.is_none_or(|s| s.elapsed() > Duration::from_millis(100)) {
            requests.publish(RunControl {
                sequence,
                start_time_ns: 0,
                start_unix_ns: 0,
                command,
                reserved: 0,
            });
            sent_at = Some(Instant::now());
        }
        input.receive_each(|hb| match hb.process {
            process_id::RIG => last = Some(hb),
            process_id::HIL if hb.sequence == sequence => answer = Some(hb.state),
            _ => {}
        });
        match answer {
            Some(operator_answer::RELAYED) => {
                // Confirmed by the rig's heartbeats as the orchestrator relays them (the
                // rig reads run control every 10 ms).
                if let Some(hb) = last.filter(|hb| wanted.contains(&hb.state)) {
                    println!(
                        "ctl {action}: done; rig state {} at t = {:.3} s (run {})",
                        state_name(&hb),
                        hb.sequence as f64 / run.rate_hz,
                        run.run_id
                    );
                    return Ok(ExitCode::SUCCESS);
                }
            }
            Some(operator_answer::ENDED_BEFORE_START) => {
                // Leave the run: an external run's clearing up waits for its nodes.
                drop(input);
                drop(requests);
                drop(node);
                return Ok(wait_for_the_end(run));
            }
            Some(operator_answer::IGNORED_BEFORE_START) => {
                eprintln!(
                    "ctl {action}: run {} has not started yet: nothing to {action} (`ctl stop` ends it)",
                    run.run_id
                );
                return Ok(ExitCode::from(2));
            }
            Some(operator_answer::IGNORED_ENDING) => {
                eprintln!(
                    "ctl {action}: run {} is ending (a stop was sent; a stop is not taken back): nothing to {action}",
                    run.run_id
                );
                return Ok(ExitCode::from(2));
            }
            Some(other) => {
                eprintln!(
                    "ctl {action}: run {}'s hil did not understand the request (answer {other}): is it another fastemu version?",
                    run.run_id
                );
                return Ok(ExitCode::from(2));
            }
            None => {}
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    if answer.is_none() {
        eprintln!(
            "ctl {action}: run {}'s hil did not answer within 2 s (it writes its report once the run is over, or it is stuck); the request may not have reached the rig",
            run.run_id
        );
    } else {
        let seen = last.map_or("no heartbeat".to_string(), |hb| state_name(&hb));
        eprintln!(
            "ctl {action}: relayed to run {}'s rig, but the rig did not confirm within 2 s (its state: {seen})",
            run.run_id
        );
    }
    Ok(ExitCode::from(2))
}

/// `ctl stop` of a run that had not started: waits up to 5 s for the run to end.
fn wait_for_the_end(run: &RunEntry) -> ExitCode {
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(5) {
        if crate::hil::registry::has_ended(run) {
            println!("ctl stop: done; run {} ended before it started", run.run_id);
            return ExitCode::SUCCESS;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    eprintln!(
        "ctl stop: run {} had not started and ends, but it did not end within 5 s",
        run.run_id
    );
    ExitCode::from(2)
}
