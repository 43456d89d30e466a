//! `fastemu simulate force|rail`: the two offline simulation primitives (SPEC 2.3 contract).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context};
use clap::{Args, Subcommand};

use crate::csvio::{read_columns, uniform_step, write_columns};
use crate::model::element::simulate_force;
use crate::model::oscillator::{simulate_rail, StartCondition};
use crate::model::StepFlags;

#[derive(Subcommand)]
pub enum SimulateCommand {
    /// Force needed to impose a displacement history (input `t_s,displacement_m`).
    Force(ForceArgs),
    /// A mass on the element driven by an external force (input `t_s,force_n`).
    Rail(RailArgs),
}

#[derive(Args)]
pub struct ForceArgs {
    /// Model file (TOML, e.g. `configs/paper-sample-750mm.toml`; keys in the README).
    #[arg(long)]
    pub model: PathBuf,
    /// Displacement CSV: `t_s,displacement_m`, uniform step.
    #[arg(long)]
    pub input: PathBuf,
    /// Output CSV: `t_s,displacement_m,force_n`.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Args)]
pub struct RailArgs {
    /// Model file (TOML, e.g. `configs/paper-sample-750mm.toml`; keys in the README).
    #[arg(long)]
    pub model: PathBuf,
    /// Mass on the element, kg (60.21 for one metre of UIC60 rail).
    #[arg(long = "mass-kg", allow_negative_numbers = true)]
    pub mass_kg: f64,
    /// External force CSV: `t_s,force_n`, uniform step.
    #[arg(long)]
    pub input: PathBuf,
    /// Output CSV: `t_s,displacement_m,velocity_m_per_s,element_force_n`.
    #[arg(long)]
    pub out: PathBuf,
    /// Initial condition: `rest` (null) or `static` (equilibrium under the first force).
    #[arg(long, default_value = "rest")]
    pub start: String,
}

pub fn run(cmd: SimulateCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        SimulateCommand::Force(args) => run_force(args),
        SimulateCommand::Rail(args) => run_rail(args),
    }
}

fn warn_flags(flags: StepFlags) {
    if flags.contains(StepFlags::TENSION_CLAMPED) {
        eprintln!("fastemu: warning: tension beyond the model's domain: the power-law base was clamped (results there are not physical)");
    }
}

fn run_force(args: ForceArgs) -> anyhow::Result<ExitCode> {
    let spec = super::load_model(&args.model)?;
    let cols = read_columns(&args.input, &["t_s", "displacement_m"])?;
    let dt = uniform_step(
        &cols.data[0],
        &cols.lines,
        &args.input.display().to_string(),
        "t_s",
    )?;
    // A model file with [[effect]] tables runs through the effect library; the force is
    // what a rig would measure (channel-delay and moving-mass included).
    let (forces, flags) = if spec.effect_tables.is_empty() {
        simulate_force(spec.element, dt, &cols.data[1])
    } else {
        let model = crate::model::effects::AugmentedModel::from_spec(
            &spec,
            &args.model.display().to_string(),
        )?;
        crate::model::effects::simulate_model_force(
            &model,
            crate::model::effects::StepperMode::Measurement,
            dt,
            &cols.data[1],
        )
    };
    warn_flags(flags);
    super::ensure_parent_dir(&args.out)?;
    write_columns(
        &args.out,
        &["t_s", "displacement_m", "force_n"],
        &[&cols.data[0], &cols.data[1], &forces],
    )
    .with_context(|| format!("cannot write {}", args.out.display()))?;
    Ok(ExitCode::SUCCESS)
}

/// Validates the `--start` and `--mass-kg` arguments of the rail commands.
pub fn rail_start_and_mass(start: &str, mass_kg: f64) -> anyhow::Result<StartCondition> {
    let Some(start) = StartCondition::from_name(start) else {
        bail!("--start {start}: expected `rest` or `static`");
    };
    if !(mass_kg.is_finite() && mass_kg > 0.0) {
        bail!("--mass-kg {mass_kg}: must be a positive finite number");
    }
    Ok(start)
}

fn run_rail(args: RailArgs) -> anyhow::Result<ExitCode> {
    let start = rail_start_and_mass(&args.start, args.mass_kg)?;
    let spec = super::load_model(&args.model)?;
    if !spec.effect_tables.is_empty() {
        eprintln!(
            "fastemu: warning: {}: [[effect]] tables are not applied by `simulate rail` (only by `simulate force`)",
            args.model.display()
        );
    }
    let cols = read_columns(&args.input, &["t_s", "force_n"])?;
    let dt = uniform_step(
        &cols.data[0],
        &cols.lines,
        &args.input.display().to_string(),
        "t_s",
    )?;
    let (samples, flags) = simulate_rail(spec.element, args.mass_kg, dt, &cols.data[1], start);
    warn_flags(flags);
    let x: Vec<f64> = samples.iter().map(|s| s.displacement_m).collect();
    let v: Vec<f64> = samples.iter().map(|s| s.velocity_m_per_s).collect();
    let f: Vec<f64> = samples.iter().map(|s| s.element_force_n).collect();
    super::ensure_parent_dir(&args.out)?;
    write_columns(
        &args.out,
        &[
            "t_s",
            "displacement_m",
            "velocity_m_per_s",
            "element_force_n",
        ],
        &[&cols.data[0], &x, &v, &f],
    )
    .with_context(|| format!("cannot write {}", args.out.display()))?;
    Ok(ExitCode::SUCCESS)
}
