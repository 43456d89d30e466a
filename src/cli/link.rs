//! The hidden `fastemu link`: fastemu's end of the UDP rig link (started by
//! `hil --rig-link udp`). Parses arguments, runs `link::process::run_link`.

use std::process::ExitCode;

use anyhow::Context;
use clap::Args;

use crate::cli::loopproc::LoopProcessArgs;
use crate::ipc::quiet_iceoryx2_logs;
use crate::link::process::{run_link, LinkPlan};
use crate::link::socket::parse_link_address;

#[derive(Debug, Clone, Args)]
pub struct LinkArgs {
    #[command(flatten)]
    pub process: LoopProcessArgs,
    /// Bind the link's UDP socket here: the address of the interface that faces the rig.
    #[arg(long)]
    pub bind: String,
    /// The rig's address: datagrams from anywhere else are rejected.
    #[arg(long)]
    pub peer: String,
    /// How long to wait for the rig's first status datagram, s.
    #[arg(long, default_value_t = 120.0)]
    pub rig_wait_s: f64,
}

pub fn run(args: LinkArgs) -> anyhow::Result<ExitCode> {
    quiet_iceoryx2_logs();
    anyhow::ensure!(
        args.rig_wait_s > 0.0 && args.rig_wait_s.is_finite(),
        "--rig-wait-s {}: expected a number of seconds > 0",
        args.rig_wait_s
    );
    let plan = LinkPlan {
        run_id: args.process.run_id.clone(),
        bind: parse_link_address("--bind", &args.bind)?,
        peer: parse_link_address("--peer", &args.peer)?,
        rig_wait: std::time::Duration::from_secs_f64(args.rig_wait_s),
    };
    let c = args.process.load()?;
    let s = run_link(&c.cfg, &plan, &args.process.out).context("link")?;
    // One write, so the line does not interleave with the other processes' last lines.
    let line =
        format!(
        "link: {} samples received, {} commands sent, {} datagrams rejected, {} samples lost{}\n",
        s.received.sample,
        s.sent.command,
        s.rejected_total,
        s.lost.sample,
        if s.rig_finished { "" } else { ", the rig did not finish" }
    );
    eprint!("{line}");
    Ok(ExitCode::SUCCESS)
}
