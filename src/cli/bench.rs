//! `fastemu bench ...`: benchmark commands.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Args, Subcommand};

use crate::bench::latency::transport::{serve_peer, PeerConfig};
use crate::bench::latency::{run_latency_bench, LatencyConfig};
use crate::bench::model::time_all_forms;
use crate::bench::rail::time_simulate_rail;
use crate::csvio::{read_columns, uniform_step};
use crate::rt::setup::parse_cpu_list;
use crate::rt::RtSetup;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Nanoseconds per model step for each form (median of interleaved runs).
    Model(ModelBenchArgs),
    /// Seconds per `simulate rail` computation (no CSV I/O), median of repeated runs.
    Rail(RailBenchArgs),
    /// Transport hop latency (iceoryx2, UDP, Unix socket, crossbeam), scheduler wake-up
    /// jitter and the loop's end-to-end latency, with hdrhistogram percentiles.
    Latency(LatencyArgs),
    /// What a stall of the emulator or controller does to the specimen (deterministic,
    /// in-process loop): largest transient per stall length, law vs force commands.
    RideThrough(RideThroughArgs),
    /// The controller's compensation: its added work per command (percentiles), and the
    /// fidelity per actuator and initial delay guess on the in-process loop.
    Compensation(CompensationBenchArgs),
    /// Echo peer of `bench latency` (spawned by it; not for direct use).
    #[command(hide = true)]
    LatencyPeer(LatencyPeerArgs),
}

#[derive(Args)]
pub struct LatencyArgs {
    /// Print one JSON object on stdout instead of the table (progress stays on stderr).
    #[arg(long)]
    pub json: bool,
    /// Measured ping-pongs per transport.
    #[arg(long, default_value_t = 100_000)]
    pub samples: u64,
    /// Rounds the samples are split into; transports alternate within each round.
    #[arg(long, default_value_t = 10)]
    pub rounds: u64,
    /// Unrecorded ping-pongs at the start of each round of each transport.
    #[arg(long, default_value_t = 200)]
    pub warmup: u64,
    /// CPUs to pin to, e.g. `2,3`: this process takes the first, the echo peer the
    /// rest (a single CPU is shared by both). Default: the machine's last two CPUs.
    #[arg(long, value_name = "CPUS")]
    pub pin: Option<String>,
    /// SCHED_FIFO priority (1-99) for both processes; also locks memory. Default: 50.
    #[arg(long, value_name = "P", allow_negative_numbers = true)]
    pub priority: Option<i32>,
    /// Measure under normal scheduling, unpinned, unless --pin/--priority say otherwise
    /// (by default the bench asks for the best real-time setup the OS permits, and
    /// reports a warning for each step it refuses).
    #[arg(long)]
    pub no_rt: bool,
    /// Output directory for latency.hlog and latency_percentiles.png.
    #[arg(long, value_name = "DIR", default_value = "out/latency")]
    pub out: PathBuf,
    /// Seconds of scheduler wake-up measurement per configuration.
    #[arg(long, default_value_t = 2.0)]
    pub jitter_s: f64,
    /// Final spin of the sleep+spin scheduler mode, us.
    #[arg(long, default_value_t = 100)]
    pub spin_us: u64,
    /// Timer slack for the thread measuring wake-up jitter, ns (kernel default 50000;
    /// ignored under SCHED_FIFO). Unset keeps the kernel's.
    #[arg(long, value_name = "NS")]
    pub timer_slack_ns: Option<u64>,
    /// Length of the `hil` run that gives the end-to-end latency, s.
    #[arg(long, default_value_t = 2.0)]
    pub hil_duration_s: f64,
    /// Do not run `hil` for the end-to-end latency.
    #[arg(long)]
    pub skip_hil: bool,
}

#[derive(Args)]
pub struct RideThroughArgs {
    /// HIL configuration (the embedded default when omitted).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Which process stalls.
    #[arg(long, default_value = "emulator", value_parser = ["emulator", "controller"])]
    pub process: String,
    /// Stall lengths, ms (comma-separated).
    #[arg(long, default_value = "2,5,10,15,20,24", value_delimiter = ',')]
    pub lengths_ms: Vec<f64>,
    /// Stall start times, s (default: around the default passage's first axle).
    #[arg(
        long,
        default_value = "1.5,1.95,2.0,2.02,2.05,2.1,2.2,2.35",
        value_delimiter = ','
    )]
    pub starts_s: Vec<f64>,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args)]
pub struct CompensationBenchArgs {
    /// HIL configuration (the embedded default when omitted).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Alternating timing rounds (with and without compensation), each over a 4 s run's
    /// setpoints.
    #[arg(long, default_value_t = 5)]
    pub rounds: usize,
    /// Length of each fidelity run, s of programme.
    #[arg(long, default_value_t = 6.0)]
    pub duration_s: f64,
    /// Skip the fidelity table (timing only).
    #[arg(long)]
    pub timing_only: bool,
    /// The fidelity table for the configured actuator alone (not every preset).
    #[arg(long)]
    pub only_config: bool,
    /// Starting guesses to run, us (repeatable; default: 0, the configured guess and
    /// twice it).
    #[arg(long = "guess-us")]
    pub guesses_us: Vec<f64>,
    /// Print one JSON object instead of the tables.
    #[arg(long)]
    pub json: bool,
    /// Also write each fidelity run's records into DIR/<actuator>-<guess>us (as a
    /// `fastemu hil` run's `records.mcap`, for `export`, `replay` and `diagnose --run`).
    #[arg(long, value_name = "DIR")]
    pub records: Option<PathBuf>,
}

#[derive(Args)]
pub struct LatencyPeerArgs {
    #[arg(long)]
    pub control: PathBuf,
    #[arg(long)]
    pub iox_prefix: String,
    #[arg(long)]
    pub parent_udp_port: u16,
    #[arg(long)]
    pub peer_udp_port: u16,
    #[arg(long)]
    pub parent_uds: PathBuf,
    #[arg(long)]
    pub peer_uds: PathBuf,
    #[arg(long)]
    pub pin: Option<String>,
    #[arg(long)]
    pub priority: Option<i32>,
    #[arg(long)]
    pub lock_memory: bool,
    #[arg(long)]
    pub yield_spin: bool,
}

#[derive(Args)]
pub struct RailBenchArgs {
    /// Model file (TOML, e.g. `configs/paper-sample-750mm.toml`; keys in the README).
    #[arg(long)]
    pub model: PathBuf,
    /// Mass on the element, kg.
    #[arg(long = "mass-kg", allow_negative_numbers = true)]
    pub mass_kg: f64,
    /// External force CSV: `t_s,force_n`, uniform step (read once, outside the timing).
    #[arg(long)]
    pub input: PathBuf,
    /// Initial condition: `rest` or `static`.
    #[arg(long, default_value = "rest")]
    pub start: String,
    /// Timed runs.
    #[arg(long, default_value_t = 7)]
    pub runs: usize,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args)]
pub struct ModelBenchArgs {
    /// Print `{"ns_per_step": {...}, ...}` as JSON.
    #[arg(long)]
    pub json: bool,
    /// Interleaved rounds per form.
    #[arg(long, default_value_t = 15)]
    pub rounds: usize,
    /// Steps per timed run.
    #[arg(long, default_value_t = 2_000_000)]
    pub steps: usize,
}

pub fn run(cmd: BenchCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        BenchCommand::Model(args) => run_model(args),
        BenchCommand::Rail(args) => run_rail(args),
        BenchCommand::Latency(args) => run_latency(args),
        BenchCommand::RideThrough(args) => run_ride_through(args),
        BenchCommand::Compensation(args) => run_compensation(args),
        BenchCommand::LatencyPeer(args) => run_latency_peer(args),
    }
}

fn run_latency(args: LatencyArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(args.samples > 0, "--samples must be positive, got 0");
    anyhow::ensure!(args.rounds > 0, "--rounds must be positive, got 0");
    anyhow::ensure!(
        args.jitter_s > 0.0 && args.jitter_s.is_finite(),
        "--jitter-s must be a positive number of seconds, got {}",
        args.jitter_s
    );
    // By default, ask for what a real rig machine would use: two dedicated CPUs and
    // SCHED_FIFO. Busy-polling transports are otherwise preempted by any third task on
    // a small machine and their tails measure the scheduler, not the transport.
    let auto_rt = !args.no_rt && args.pin.is_none() && args.priority.is_none();
    let n_cpus = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) }.max(1) as usize;
    let mut args = args;
    if auto_rt && n_cpus >= 2 {
        args.pin = Some(format!("{},{}", n_cpus - 2, n_cpus - 1));
        args.priority = Some(50);
        eprintln!(
            "bench latency: pinning to CPUs {} with SCHED_FIFO 50 (the default; --no-rt measures under normal scheduling)",
            args.pin.as_deref().unwrap_or_default()
        );
    }
    let cpus = match &args.pin {
        Some(text) => parse_cpu_list(text).map_err(|e| anyhow::anyhow!("--pin {text}: {e}"))?,
        None => Vec::new(),
    };
    // This process takes the first CPU, the peer the rest; one CPU is shared.
    let (main_cpus, peer_cpus) = match cpus.split_first() {
        Some((&first, rest)) if !rest.is_empty() => (vec![first], rest.to_vec()),
        Some((&first, _)) => (vec![first], vec![first]),
        None => (Vec::new(), Vec::new()),
    };
    let yield_while_spinning = cpus.len() == 1;
    let setup = |cpus: Vec<usize>| RtSetup {
        lock_memory: args.priority.is_some(),
        fifo_priority: args.priority,
        cpus,
    };
    let config = LatencyConfig {
        samples_per_transport: args.samples,
        rounds: args.rounds,
        warmup_per_round: args.warmup,
        jitter_seconds: args.jitter_s,
        spin_ns: args.spin_us * 1000,
        timer_slack_ns: args.timer_slack_ns,
        main_rt: setup(main_cpus),
        peer_rt: setup(peer_cpus),
        yield_while_spinning,
        hil_duration_s: (!args.skip_hil).then_some(args.hil_duration_s),
        exe: std::env::current_exe().context("cannot locate the running executable")?,
        out_dir: args.out.clone(),
    };
    if yield_while_spinning {
        eprintln!(
            "bench latency: both sides share CPU {}: busy-polling receivers yield on every miss",
            cpus[0]
        );
    }
    let mut progress = |line: &str| eprintln!("bench latency: {line}");
    let report = run_latency_bench(&config, &mut progress)?;
    for w in &report.warnings {
        eprintln!("bench latency: warning: {w}");
    }
    if args.json {
        println!("{}", serde_json::to_string(&report.to_json())?);
    } else {
        print!("{}", report.table());
    }
    Ok(ExitCode::SUCCESS)
}

fn run_rail(args: RailBenchArgs) -> anyhow::Result<ExitCode> {
    let start = super::simulate::rail_start_and_mass(&args.start, args.mass_kg)?;
    anyhow::ensure!(args.runs > 0, "--runs must be positive");
    let spec = super::load_model(&args.model)?;
    let cols = read_columns(&args.input, &["t_s", "force_n"])?;
    let dt = uniform_step(
        &cols.data[0],
        &cols.lines,
        &args.input.display().to_string(),
        "t_s",
    )?;
    let timing = time_simulate_rail(
        spec.element,
        args.mass_kg,
        dt,
        &cols.data[1],
        start,
        args.runs,
    );
    if args.json {
        println!("{}", serde_json::to_string(&timing)?);
    } else {
        println!(
            "{} form, {} samples at dt {:e} s, {} sub-step(s): median {:.6} s (min {:.6}, max {:.6}) over {} runs, {:.1} ns/step",
            timing.form,
            timing.n_samples,
            timing.dt_s,
            timing.substeps_per_step,
            timing.median_s,
            timing.min_s,
            timing.max_s,
            timing.runs,
            timing.median_ns_per_step
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn run_latency_peer(args: LatencyPeerArgs) -> anyhow::Result<ExitCode> {
    let cpus = match &args.pin {
        Some(text) => parse_cpu_list(text).map_err(|e| anyhow::anyhow!("--pin {text}: {e}"))?,
        None => Vec::new(),
    };
    let config = PeerConfig {
        control_path: args.control,
        iox_prefix: args.iox_prefix,
        parent_udp_port: args.parent_udp_port,
        peer_udp_port: args.peer_udp_port,
        parent_uds_path: args.parent_uds,
        peer_uds_path: args.peer_uds,
        rt: RtSetup {
            lock_memory: args.lock_memory,
            fifo_priority: args.priority,
            cpus,
        },
        yield_while_spinning: args.yield_spin,
    };
    serve_peer(&config)?;
    Ok(ExitCode::SUCCESS)
}

fn run_model(args: ModelBenchArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.rounds > 0 && args.steps > 0,
        "--rounds and --steps must be positive"
    );
    let timings = time_all_forms(args.rounds, args.steps);
    if args.json {
        let mut ns = serde_json::Map::new();
        for t in &timings {
            ns.insert(t.form.to_string(), serde_json::json!(t.median_ns_per_step));
        }
        let obj = serde_json::json!({"ns_per_step": ns, "detail": timings});
        println!("{}", serde_json::to_string(&obj)?);
    } else {
        println!(
            "{:<14} {:>12} {:>10} {:>10}   ({} rounds x {} steps)",
            "form", "median_ns", "min_ns", "max_ns", args.rounds, args.steps
        );
        for t in &timings {
            println!(
                "{:<14} {:>12.2} {:>10.2} {:>10.2}",
                t.form, t.median_ns_per_step, t.min_ns_per_step, t.max_ns_per_step
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn run_ride_through(args: RideThroughArgs) -> anyhow::Result<ExitCode> {
    let cfg = crate::hil::config::load_or_default(args.config.as_deref())?;
    anyhow::ensure!(
        args.lengths_ms
            .iter()
            .chain(&args.starts_s)
            .all(|v| v.is_finite() && *v > 0.0),
        "--lengths-ms and --starts-s: expected numbers > 0"
    );
    let study = crate::bench::ride_through::ride_through(
        &cfg,
        args.process == "emulator",
        &args.starts_s,
        &args.lengths_ms,
    );
    if args.json {
        println!("{}", serde_json::to_string(&study)?);
    } else {
        print!("{}", study.table());
    }
    Ok(ExitCode::SUCCESS)
}

fn run_compensation(args: CompensationBenchArgs) -> anyhow::Result<ExitCode> {
    use crate::bench::compensation::{controller_work, fidelity_cell_recorded, fidelity_table};
    let cfg = crate::hil::config::load_or_default(args.config.as_deref())?;
    let config_text = match &args.config {
        Some(p) => std::fs::read_to_string(p)
            .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", p.display()))?,
        None => crate::hil::config::DEFAULT_CONFIG_TOML.to_string(),
    };
    anyhow::ensure!(
        args.duration_s > 0.0 && args.duration_s.is_finite(),
        "--duration-s must be a positive number of seconds, got {}",
        args.duration_s
    );
    eprintln!(
        "bench compensation: timing on_setpoint, {} rounds each way",
        args.rounds
    );
    let work = controller_work(&cfg, args.rounds);
    let mut cells = Vec::new();
    if !args.timing_only {
        let initial = cfg.compensation.initial_delay_s;
        let guesses: Vec<f64> = if args.guesses_us.is_empty() {
            vec![0.0, initial, 2.0 * initial]
        } else {
            args.guesses_us.iter().map(|g| g * 1e-6).collect()
        };
        for g in &guesses {
            anyhow::ensure!(
                g.is_finite() && *g >= 0.0,
                "--guess-us must be a delay of 0 us or more, got {}",
                g * 1e6
            );
        }
        let mut variants = crate::bench::compensation::actuator_variants(&cfg);
        if args.only_config {
            variants.truncate(1);
        }
        for (name, variant) in variants {
            // As `hil` refuses it: an actuator that cannot carry the load cannot hold.
            if let Some(why) = crate::hil::check::actuator_cannot_hold(&variant) {
                eprintln!("bench compensation: {name} skipped: {why}");
                continue;
            }
            for &guess in &guesses {
                let mut c = variant.clone();
                c.compensation.initial_delay_s = guess.min(c.compensation.max_delay_s);
                eprintln!(
                    "bench compensation: {name}, initial delay {:.0} us",
                    guess * 1e6
                );
                let dir = args.records.as_ref().map(|d| {
                    let safe: String = name
                        .chars()
                        .map(|ch| {
                            if ch.is_ascii_alphanumeric() || ch == '-' {
                                ch
                            } else {
                                '_'
                            }
                        })
                        .collect();
                    d.join(format!("{safe}-{:.0}us", guess * 1e6))
                });
                let records = dir.as_deref().map(|d| (d, config_text.as_str()));
                cells.push(fidelity_cell_recorded(&c, &name, args.duration_s, records)?);
            }
        }
    }
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "controller_work": work,
                "fidelity": cells,
            }))?
        );
    } else {
        let t = |x: &crate::bench::compensation::Timing| {
            format!(
                "p50 {:.2} us, p99 {:.2} us, p99.9 {:.2} us, max {:.1} us",
                x.p50_ns as f64 * 1e-3,
                x.p99_ns as f64 * 1e-3,
                x.p999_ns as f64 * 1e-3,
                x.max_ns as f64 * 1e-3
            )
        };
        println!(
            "controller on_setpoint over {} setpoints x {} rounds:\n  with compensation:    {}\n  without compensation: {}",
            work.commands,
            args.rounds,
            t(&work.with_compensation),
            t(&work.without)
        );
        if !cells.is_empty() {
            print!("\n{}", fidelity_table(&cells));
        }
    }
    Ok(ExitCode::SUCCESS)
}
