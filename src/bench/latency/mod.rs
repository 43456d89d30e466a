//! `fastemu bench latency`: what delay and jitter the loop's plumbing adds.
//!
//! Three measurements, one report:
//! - hop latency of five transports by two-process ping-pong (`transport`), interleaved
//!   in rounds (the transport order rotates every round) so machine drift hits all
//!   alike; one-way hop = round-trip / 2;
//! - wake-up jitter of the fixed-step scheduler (`jitter`) at 4096 Hz and 20 kHz;
//! - end-to-end latency of the real loop from a short `hil` run (`end_to_end`).
//!
//! Percentiles come from hdrhistogram (`stats`); every round is also written as one
//! interval of an HdrHistogram interval log (`hlog`), and a percentile-distribution PNG
//! is drawn. Timing never decides pass/fail here: the report states the numbers.

pub mod end_to_end;
pub mod hlog;
pub mod jitter;
pub mod stats;
pub mod transport;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};

use anyhow::Context;
use hdrhistogram::Histogram;

use crate::plot::{draw_png, Panel, Series};
use crate::rt::{apply_rt_setup, RtSetup, WaitMode};
use end_to_end::{measure_end_to_end, EndToEnd};
use hlog::{write_interval_log_file, LoggedInterval};
use jitter::{
    measure_wake_jitter, set_timer_slack_ns, thread_is_realtime, timer_slack_ns, JitterConfig,
};
use stats::{new_latency_histogram, percentile_curve, PercentileSummary};
use transport::{crossbeam_round, PeerSession, Transport, MESSAGE_BYTES, SOCKET_BYTES};

/// Everything one benchmark run needs.
#[derive(Debug, Clone)]
pub struct LatencyConfig {
    /// Measured ping-pongs per transport (summed over rounds).
    pub samples_per_transport: u64,
    /// Rounds the samples are split into; transports alternate within each round.
    pub rounds: u64,
    /// Unrecorded ping-pongs at the start of every round of every transport.
    pub warmup_per_round: u64,
    /// Wall time per scheduler configuration, s (split over the rounds).
    pub jitter_seconds: f64,
    /// Final spin of `WaitMode::SleepSpin`, ns.
    pub spin_ns: u64,
    /// Timer slack to set on the measuring thread before the jitter runs, ns
    /// (`None` keeps the kernel's; it only matters without SCHED_FIFO).
    pub timer_slack_ns: Option<u64>,
    /// Real-time setup of this process (pinger, scheduler jitter).
    pub main_rt: RtSetup,
    /// Real-time setup of the echo peer (process and crossbeam echo thread).
    pub peer_rt: RtSetup,
    /// Spinning receivers yield the CPU on every miss (both sides share one CPU).
    pub yield_while_spinning: bool,
    /// Length of the `hil` run for end-to-end latency, s; `None` skips it.
    pub hil_duration_s: Option<f64>,
    /// The executable to spawn for the peer and `hil` (normally the current one).
    pub exe: PathBuf,
    /// Where the `.hlog` and `.png` go.
    pub out_dir: PathBuf,
}

/// One transport's result.
#[derive(Debug, Clone)]
pub struct TransportResult {
    pub transport: Transport,
    pub summary: PercentileSummary,
    pub histogram: Histogram<u64>,
}

/// One scheduler configuration's result.
#[derive(Debug, Clone)]
pub struct JitterResult {
    pub config: JitterConfig,
    pub summary: PercentileSummary,
    pub missed_deadlines: u64,
    pub histogram: Histogram<u64>,
}

/// The whole run.
#[derive(Debug, Clone)]
pub struct LatencyReport {
    pub transports: Vec<TransportResult>,
    pub wake_jitter: Vec<JitterResult>,
    pub end_to_end: EndToEnd,
    /// The same loop with the simulated rig behind the UDP rig link.
    pub end_to_end_udp_link: EndToEnd,
    pub rounds: u64,
    pub warmup_per_round: u64,
    pub spin_ns: u64,
    /// Timer slack of the thread that measured wake-up jitter, ns.
    pub timer_slack_ns: u64,
    /// Whether that thread ran under SCHED_FIFO/RR (which ignores timer slack).
    pub jitter_thread_realtime: bool,
    pub main_cpus: Vec<usize>,
    pub peer_cpus: Vec<usize>,
    pub fifo_priority: Option<i32>,
    /// Setup steps refused by the OS and other things the reader should know.
    pub warnings: Vec<String>,
    pub out_dir: PathBuf,
    pub hlog_path: PathBuf,
    pub png_path: PathBuf,
    pub elapsed_s: f64,
}

/// Splits `total` samples into `rounds` near-equal parts that sum to `total`.
pub fn split_into_rounds(total: u64, rounds: u64) -> Vec<u64> {
    let rounds = rounds.clamp(1, total.max(1));
    (0..rounds)
        .map(|r| total / rounds + u64::from(r < total % rounds))
        .collect()
}

/// `/dev/shm` entries written by iceoryx2, to check the run leaves none behind.
fn iceoryx2_shm_entries() -> BTreeSet<String> {
    std::fs::read_dir("/dev/shm")
        .map(|dir| {
            dir.filter_map(Result::ok)
                .map(|e| e.file_name().to_string_lossy().into_owned())
                // The bench's own files carry its prefix and are removed with the session;
                // anything under iceoryx2's default prefix is another user's, or a leak.
                .filter(|n| n.starts_with("iox2_") || n.starts_with("fastemu_latency_"))
                .collect()
        })
        .unwrap_or_default()
}

/// Runs the benchmark; `progress` receives human-readable lines (for stderr).
pub fn run_latency_bench(
    config: &LatencyConfig,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<LatencyReport> {
    anyhow::ensure!(
        config.samples_per_transport > 0,
        "--samples must be positive"
    );
    let run_start = Instant::now();
    let base_time = SystemTime::now();
    crate::ipc::pingpong::quiet_iceoryx2_logging();
    std::fs::create_dir_all(&config.out_dir)
        .with_context(|| format!("cannot create {}", config.out_dir.display()))?;

    let mut warnings: Vec<String> = apply_rt_setup(&config.main_rt)
        .into_iter()
        .map(|w| format!("main: {w}"))
        .collect();
    let unique = format!(
        "{}_{}",
        std::process::id(),
        base_time
            .duration_since(SystemTime::UNIX_EPOCH)
            .unwrap_or_default()
            .as_nanos()
    );
    let shm_before = iceoryx2_shm_entries();

    // --- transports -------------------------------------------------------------
    let per_round = split_into_rounds(config.samples_per_transport, config.rounds);
    let rounds = per_round.len() as u64;
    let mut totals: Vec<Histogram<u64>> = Transport::ALL
        .iter()
        .map(|_| new_latency_histogram())
        .collect();
    let mut intervals: Vec<LoggedInterval> = Vec::new();
    {
        let mut session = PeerSession::start(
            &config.exe,
            &unique,
            &config.peer_rt,
            config.yield_while_spinning,
        )?;
        warnings.extend(session.peer_warnings.iter().map(|w| format!("peer: {w}")));
        progress(&format!(
            "transports: {} rounds x ~{} samples each of {}, message {MESSAGE_BYTES} bytes (sockets: link datagrams {} out, {} back)",
            rounds,
            per_round[0],
            Transport::ALL.map(Transport::key).join(", "),
            SOCKET_BYTES.0,
            SOCKET_BYTES.1
        ));
        for (round_idx, &n_measured) in per_round.iter().enumerate() {
            let mut line = format!("  round {}/{rounds}:", round_idx + 1);
            for k in 0..Transport::ALL.len() {
                // Rotate the order every round so no transport always runs first.
                let t_idx = (k + round_idx) % Transport::ALL.len();
                let transport = Transport::ALL[t_idx];
                let mut hist = new_latency_histogram();
                let started = Instant::now();
                if transport == Transport::Crossbeam {
                    let echo_warnings = crossbeam_round(
                        config.warmup_per_round,
                        n_measured,
                        &mut hist,
                        &config.peer_rt,
                        config.yield_while_spinning,
                    )?;
                    if round_idx == 0 {
                        warnings.extend(
                            echo_warnings
                                .into_iter()
                                .map(|w| format!("crossbeam echo: {w}")),
                        );
                    }
                } else {
                    session
                        .round(transport, config.warmup_per_round, n_measured, &mut hist)
                        .with_context(|| format!("{} round {}", transport.key(), round_idx + 1))?;
                }
                line.push_str(&format!(
                    " {} p99 {:.1} us;",
                    transport.key(),
                    hist.value_at_quantile(0.99) as f64 / 1e3
                ));
                totals[t_idx].add(&hist).context("adding histograms")?;
                intervals.push(LoggedInterval {
                    tag: transport.key().to_string(),
                    start_offset: started.duration_since(run_start),
                    duration: started.elapsed(),
                    histogram: hist,
                });
            }
            progress(&line);
        }
        if let Err(e) = session.finish() {
            warnings.push(format!("peer shutdown: {e:#}"));
        }
    }
    let transports: Vec<TransportResult> = Transport::ALL
        .iter()
        .zip(totals)
        .map(|(&transport, histogram)| TransportResult {
            transport,
            summary: PercentileSummary::from_histogram(&histogram),
            histogram,
        })
        .collect();

    // --- scheduler wake-up jitter ---------------------------------------------------
    if let Some(slack_ns) = config.timer_slack_ns {
        if let Err(e) = set_timer_slack_ns(slack_ns) {
            warnings.push(format!("main: {e}"));
        }
    }
    let timer_slack_ns = timer_slack_ns();
    let jitter_thread_realtime = thread_is_realtime();
    if !jitter_thread_realtime && timer_slack_ns > 1_000 {
        warnings.push(format!(
            "wake jitter measured under normal scheduling with {} us timer slack: every \
             sleep may end up to that much late (SCHED_FIFO via --priority, or \
             --timer-slack-ns 1, removes it)",
            timer_slack_ns / 1000
        ));
    }
    let jitter_configs = JitterConfig::standard_set(config.spin_ns);
    let mut jitter_totals: Vec<(Histogram<u64>, u64)> = jitter_configs
        .iter()
        .map(|_| (new_latency_histogram(), 0))
        .collect();
    progress(&format!(
        "wake jitter: {} configurations x {:.1} s, {} rounds, spin {} us",
        jitter_configs.len(),
        config.jitter_seconds,
        rounds,
        config.spin_ns / 1000
    ));
    for _ in 0..rounds {
        for (i, jc) in jitter_configs.iter().enumerate() {
            let cycles =
                ((jc.rate_hz as f64 * config.jitter_seconds / rounds as f64).ceil() as u64).max(1);
            let mut hist = new_latency_histogram();
            let started = Instant::now();
            let missed = measure_wake_jitter(*jc, cycles, &mut hist);
            jitter_totals[i].0.add(&hist).context("adding histograms")?;
            jitter_totals[i].1 += missed;
            intervals.push(LoggedInterval {
                tag: format!("jitter_{}", jc.key()),
                start_offset: started.duration_since(run_start),
                duration: started.elapsed(),
                histogram: hist,
            });
        }
    }
    let wake_jitter: Vec<JitterResult> = jitter_configs
        .into_iter()
        .zip(jitter_totals)
        .map(|(config, (histogram, missed_deadlines))| JitterResult {
            config,
            summary: PercentileSummary::from_histogram(&histogram),
            missed_deadlines,
            histogram,
        })
        .collect();

    // --- end-to-end from the real loop, on iceoryx2 and behind the UDP rig link ------
    // Each run's report directory goes under the bench's own output directory.
    let hil_run = |extra: &[&str], report: &str, progress: &mut dyn FnMut(&str)| match config
        .hil_duration_s
    {
        Some(duration_s) => {
            let report_dir = config.out_dir.join(report).display().to_string();
            let mut extra = extra.to_vec();
            extra.extend(["--out", &report_dir]);
            progress(&format!(
                "end-to-end: `hil --json --duration-s {duration_s} {}`",
                extra.join(" ")
            ));
            measure_end_to_end(
                &config.exe,
                duration_s,
                Duration::from_secs_f64(duration_s + 60.0),
                &extra,
            )
        }
        None => EndToEnd::Unavailable {
            reason: "skipped (--skip-hil)".to_string(),
            command: String::new(),
        },
    };
    let end_to_end = hil_run(&[], "hil-iceoryx2", &mut *progress);
    let end_to_end_udp_link = hil_run(&["--rig-link", "udp"], "hil-udp-link", &mut *progress);

    let leftovers: Vec<String> = iceoryx2_shm_entries()
        .difference(&shm_before)
        .cloned()
        .collect();
    if !leftovers.is_empty() {
        warnings.push(format!(
            "{} new /dev/shm/iox2_* entries after the run (another iceoryx2 user on this \
             machine, or a leak of this run): {}",
            leftovers.len(),
            leftovers.join(" ")
        ));
    }

    // --- files -------------------------------------------------------------------
    let hlog_path = config.out_dir.join("latency.hlog");
    let png_path = config.out_dir.join("latency_percentiles.png");
    let comments = vec![
        "fastemu bench latency: values are ns".to_string(),
        "transport tags: one-way hop latency = round-trip time / 2".to_string(),
        "jitter_* tags: scheduler wake-up lateness (woke - deadline)".to_string(),
    ];
    write_interval_log_file(&hlog_path, base_time, &comments, &intervals)?;
    let mut report = LatencyReport {
        transports,
        wake_jitter,
        end_to_end,
        end_to_end_udp_link,
        rounds,
        warmup_per_round: config.warmup_per_round,
        spin_ns: config.spin_ns,
        timer_slack_ns,
        jitter_thread_realtime,
        main_cpus: config.main_rt.cpus.clone(),
        peer_cpus: config.peer_rt.cpus.clone(),
        fifo_priority: config.main_rt.fifo_priority,
        warnings,
        out_dir: config.out_dir.clone(),
        hlog_path,
        png_path,
        elapsed_s: 0.0,
    };
    draw_percentile_plot(&report, &report.png_path)?;
    report.elapsed_s = run_start.elapsed().as_secs_f64();
    Ok(report)
}

fn draw_percentile_plot(report: &LatencyReport, path: &Path) -> anyhow::Result<()> {
    let x_label = "percentile, 1/(1-p): 10 = p90, 100 = p99, 1000 = p99.9";
    let curve_us = |hist: &Histogram<u64>| -> (Vec<f64>, Vec<f64>) {
        percentile_curve(hist)
            .into_iter()
            .map(|(x, ns)| (x, ns / 1e3))
            .unzip()
    };
    let mut hop = Panel::new(
        "One-way hop latency (RTT/2), 40-byte DisplacementSample",
        x_label,
        "latency, us",
    )
    .log_x()
    .log_y();
    for (i, t) in report.transports.iter().enumerate() {
        let (x, y) = curve_us(&t.histogram);
        hop = hop.with(Series::line(t.transport.key(), x, y, i));
    }
    let mut jitter = Panel::new(
        "Scheduler wake-up lateness (woke - deadline)",
        x_label,
        "lateness, us",
    )
    .log_x()
    .log_y();
    for (i, j) in report.wake_jitter.iter().enumerate() {
        let (x, y) = curve_us(&j.histogram);
        jitter = jitter.with(Series::line(j.config.key(), x, y, i));
    }
    draw_png(path, 1600, 650, 2, &[hop, jitter])
}

fn summary_json(s: &PercentileSummary) -> serde_json::Value {
    serde_json::to_value(s).expect("plain struct serialises")
}

impl LatencyReport {
    /// The transport's summary, if measured.
    pub fn transport(&self, transport: Transport) -> Option<&PercentileSummary> {
        self.transports
            .iter()
            .find(|t| t.transport == transport)
            .map(|t| &t.summary)
    }

    /// UDP p99 / iceoryx2 (busy polling) p99: the SPEC 7 target is >= 3.
    pub fn ratio_udp_over_iceoryx2_p99(&self) -> Option<f64> {
        let udp = self.transport(Transport::Udp)?.p99_ns as f64;
        let iox = self.transport(Transport::Iceoryx2)?.p99_ns as f64;
        (iox > 0.0).then(|| udp / iox)
    }

    /// The `--json` object.
    pub fn to_json(&self) -> serde_json::Value {
        let mut transports = serde_json::Map::new();
        for t in &self.transports {
            transports.insert(t.transport.key().to_string(), summary_json(&t.summary));
        }
        let mut wake_jitter = serde_json::Map::new();
        for j in &self.wake_jitter {
            let mut value = summary_json(&j.summary);
            value["missed_deadlines"] = serde_json::json!(j.missed_deadlines);
            value["period_ns"] = serde_json::json!(j.config.period_ns());
            if let WaitMode::SleepSpin { spin_ns } = j.config.mode {
                value["spin_ns"] = serde_json::json!(spin_ns);
            }
            wake_jitter.insert(j.config.key(), value);
        }
        let (end_to_end, end_to_end_note, hil_wake_jitter) = match &self.end_to_end {
            EndToEnd::Measured {
                end_to_end,
                wake_jitter,
                command,
                ..
            } => (
                serde_json::to_value(end_to_end).expect("plain struct"),
                format!("from `{command}`"),
                serde_json::to_value(wake_jitter).expect("plain struct"),
            ),
            EndToEnd::Unavailable { reason, .. } => (
                serde_json::Value::Null,
                format!("unavailable: {reason}"),
                serde_json::Value::Null,
            ),
        };
        serde_json::json!({
            "hop": "one-way hop latency = round-trip time / 2, ns, 2 processes (crossbeam: 2 threads)",
            "message_bytes": MESSAGE_BYTES,
            "socket_datagram_bytes": [SOCKET_BYTES.0, SOCKET_BYTES.1],
            "rounds": self.rounds,
            "warmup_per_round": self.warmup_per_round,
            "transports": transports,
            "loop": {
                "wake_jitter": wake_jitter,
                "timer_slack_ns": self.timer_slack_ns,
                "jitter_thread_realtime": self.jitter_thread_realtime,
                "end_to_end": end_to_end,
                "end_to_end_note": end_to_end_note,
                "end_to_end_udp_link": self.udp_link_json(),
                "hil_wake_jitter": hil_wake_jitter,
            },
            "ratio_udp_over_iceoryx2_p99": self.ratio_udp_over_iceoryx2_p99(),
            "cpus": {"main": self.main_cpus, "peer": self.peer_cpus},
            "fifo_priority": self.fifo_priority,
            "warnings": self.warnings,
            "out_dir": self.out_dir.display().to_string(),
            "hlog": self.hlog_path.display().to_string(),
            "png": self.png_path.display().to_string(),
            "elapsed_s": self.elapsed_s,
        })
    }

    /// `loop.end_to_end_udp_link`: the loop's end-to-end latency and the link's own
    /// latency with the simulated rig behind the UDP rig link.
    fn udp_link_json(&self) -> serde_json::Value {
        match &self.end_to_end_udp_link {
            EndToEnd::Measured {
                end_to_end,
                link,
                command,
                ..
            } => serde_json::json!({
                "end_to_end": end_to_end,
                "link": link,
                "note": format!("from `{command}`"),
            }),
            EndToEnd::Unavailable { reason, .. } => {
                serde_json::json!({"note": format!("unavailable: {reason}")})
            }
        }
    }

    /// The terminal table.
    pub fn table(&self) -> String {
        let us = |ns: u64| format!("{:.2}", ns as f64 / 1e3);
        let mut out = String::new();
        let header = format!(
            "{:<22} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9}\n",
            "", "p50_us", "p90_us", "p99_us", "p99.9_us", "p99.99_us", "max_us", "samples"
        );
        let row = |name: &str, s: &PercentileSummary| {
            format!(
                "{:<22} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9}\n",
                name,
                us(s.p50_ns),
                us(s.p90_ns),
                us(s.p99_ns),
                us(s.p999_ns),
                us(s.p9999_ns),
                us(s.max_ns),
                s.samples
            )
        };
        out.push_str(&format!(
            "One-way hop latency = RTT/2 ({MESSAGE_BYTES}-byte DisplacementSample; udp/uds: the rig link's {}-byte sample and {}-byte command datagrams; {} rounds interleaved)\n",
            SOCKET_BYTES.0,
            SOCKET_BYTES.1,
            self.rounds
        ));
        out.push_str(&header);
        for t in &self.transports {
            out.push_str(&row(t.transport.key(), &t.summary));
        }
        if let Some(ratio) = self.ratio_udp_over_iceoryx2_p99() {
            // Below 1 (a preempted spinner) one decimal would print 0.0.
            let shown = if ratio >= 1.0 {
                format!("{ratio:.1}")
            } else {
                format!("{ratio:.2e}")
            };
            out.push_str(&format!("UDP p99 / iceoryx2 p99 = {shown} (target >= 3)\n"));
        }
        out.push_str(&format!(
            "\nScheduler wake-up lateness (sleep_spin spins the last {} us; {}, timer slack {} us)\n",
            self.spin_ns / 1000,
            if self.jitter_thread_realtime { "SCHED_FIFO" } else { "normal scheduling" },
            self.timer_slack_ns as f64 / 1e3
        ));
        out.push_str(header.trim_end());
        out.push_str("  missed\n");
        for j in &self.wake_jitter {
            out.push_str(row(&j.config.key(), &j.summary).trim_end());
            out.push_str(&format!("  {:>6}\n", j.missed_deadlines));
        }
        out.push_str("\nEnd-to-end (rig sample published -> actuator command received): ");
        match &self.end_to_end {
            EndToEnd::Measured {
                end_to_end: e,
                command,
                ..
            } => out.push_str(&format!(
                "p50 {:.2} us, p99 {:.2} us, p99.9 {:.2} us, max {:.2} us\n  (from `{command}`)\n",
                e.p50_ns / 1e3,
                e.p99_ns / 1e3,
                e.p999_ns / 1e3,
                e.max_ns / 1e3
            )),
            EndToEnd::Unavailable { reason, .. } => {
                out.push_str(&format!("unavailable: {reason}\n"))
            }
        }
        out.push_str(
            "End-to-end, simulated rig behind the UDP rig link (rig sent -> command published): ",
        );
        match &self.end_to_end_udp_link {
            EndToEnd::Measured {
                end_to_end: e,
                link,
                command,
                ..
            } => {
                out.push_str(&format!(
                    "p50 {:.2} us, p99 {:.2} us, p99.9 {:.2} us, max {:.2} us\n",
                    e.p50_ns / 1e3,
                    e.p99_ns / 1e3,
                    e.p999_ns / 1e3,
                    e.max_ns / 1e3
                ));
                if let Some(l) = link {
                    out.push_str(&format!(
                        "  the link's sample datagram alone: p50 {:.2} us, p99 {:.2} us, p99.9 {:.2} us, max {:.2} us\n",
                        l.p50_ns / 1e3,
                        l.p99_ns / 1e3,
                        l.p999_ns / 1e3,
                        l.max_ns / 1e3
                    ));
                }
                out.push_str(&format!("  (from `{command}`)\n"));
            }
            EndToEnd::Unavailable { reason, .. } => {
                out.push_str(&format!("unavailable: {reason}\n"))
            }
        }
        for w in &self.warnings {
            out.push_str(&format!("warning: {w}\n"));
        }
        out.push_str(&format!(
            "\nFiles: {} (HdrHistogram interval log, one interval per round, tagged), {}\n",
            self.hlog_path.display(),
            self.png_path.display()
        ));
        out
    }
}
