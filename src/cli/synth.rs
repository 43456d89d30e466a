//! `fastemu synth-campaign`: argument handling (the generator is `crate::ident::synth`).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context};
use clap::Args;

use crate::ident::synth::{hidden_choices, valid_hidden, write_synthetic_campaign_with};

#[derive(Args)]
pub struct SynthArgs {
    /// Directory to write: campaign.toml, one CSV per test, baseline.toml, truth.toml.
    #[arg(long)]
    pub out: PathBuf,
    /// What the campaign hides: none, a library effect (preload-stiffening,
    /// amplitude-friction, fractional-damping, temperature-shift, channel-delay,
    /// moving-mass, load-train-resonance, specimen-drift, self-heating, cyclic-softening),
    /// friction-passages-only (one harmonic amplitude), or the older truths
    /// load-path-resonance and softening-specimen (other laws of the same causes); several
    /// joined by `+` (e.g. amplitude-friction+self-heating) hide them together.
    #[arg(long, default_value = "amplitude-friction")]
    pub hidden: String,
    /// Seed of the noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Harmonic records start from rest at the preload (start-up included) instead of
    /// after a lead-in: `diagnose` then uses the first cycles that differ from the steady
    /// ones.
    #[arg(long)]
    pub from_rest: bool,
}

pub fn run(args: SynthArgs) -> anyhow::Result<ExitCode> {
    let choices = hidden_choices();
    if !valid_hidden(&args.hidden) {
        bail!(
            "--hidden {}: expected one of {} (or several joined by +)",
            args.hidden,
            choices.join(", ")
        );
    }
    let n = write_synthetic_campaign_with(&args.out, &args.hidden, args.seed, args.from_rest)
        .with_context(|| format!("cannot write the campaign to {}", args.out.display()))?;
    eprintln!(
        "synth-campaign: {n} tests (hidden: {}) in {}; try\n  fastemu diagnose --campaign {} --model {} --out diagnosis\nthe truth is in {} (diagnose does not read it)",
        args.hidden,
        args.out.display(),
        args.out.display(),
        args.out.join("baseline.toml").display(),
        args.out.join("truth.toml").display()
    );
    Ok(ExitCode::SUCCESS)
}
