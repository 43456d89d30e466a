//! `fastemu identify`: argument handling and output (the fit is `crate::ident::identify`).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::bail;
use clap::Args;

use crate::ident::campaign::load_campaign;
use crate::ident::fit::cycle_data;
use crate::ident::identify::{identify_eq2, identify_force, write_identification, IdentifyRequest};
use crate::model::params::Form;

#[derive(Args)]
pub struct IdentifyArgs {
    /// Campaign directory: `campaign.toml` and one CSV per test (SPEC 4; see README).
    #[arg(long)]
    pub campaign: PathBuf,
    /// Time-domain form of the identified model: `consistent` or `paper`.
    #[arg(long, default_value = "consistent")]
    pub form: String,
    /// Objective: `force` (time-domain force residual) or `eq2` (paper: k_eq/c_eq, weight 10
    /// on damping). Default: `force` for the consistent form, `eq2` for the paper form.
    #[arg(long)]
    pub objective: Option<String>,
    /// Reference preload P0 of paper Eq. 1, N (held fixed, as in the paper).
    #[arg(long = "p0-n", default_value_t = 64e3)]
    pub p0_n: f64,
    /// Model file to write (SPEC 2.3).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Directory for the PNG plots (default: next to `--out`, else none).
    #[arg(long = "plot-dir")]
    pub plot_dir: Option<PathBuf>,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
}
pub fn run(args: IdentifyArgs) -> anyhow::Result<ExitCode> {
    let Some(form) = Form::from_name(&args.form).filter(|f| *f != Form::KelvinVoigt) else {
        bail!("--form {}: expected `consistent` or `paper`", args.form);
    };
    let objective = args
        .objective
        .clone()
        .unwrap_or_else(|| if form == Form::Paper { "eq2" } else { "force" }.to_string());
    if objective != "eq2" && objective != "force" {
        bail!("--objective {objective}: expected `force` or `eq2`");
    }
    if !(args.p0_n.is_finite() && args.p0_n > 0.0) {
        bail!("--p0-n {}: must be a positive number", args.p0_n);
    }
    let campaign = load_campaign(&args.campaign)?;
    let data = cycle_data(&campaign);
    if data.len() < 4 {
        bail!(
            "{}: {} harmonic tests: identification needs at least 4",
            args.campaign.display(),
            data.len()
        );
    }
    eprintln!(
        "identify: {} harmonic tests, form {form}, objective {objective}",
        data.len()
    );
    let identification = if objective == "eq2" {
        identify_eq2(&campaign, args.p0_n)
    } else {
        identify_force(&campaign, &data, form, args.p0_n)
    };
    let request = IdentifyRequest {
        campaign: args.campaign.clone(),
        p0_n: args.p0_n,
        out: args.out.clone(),
        plot_dir: args.plot_dir.clone(),
    };
    let summary = write_identification(
        &request,
        &campaign,
        &data,
        &identification,
        form,
        &objective,
    )?;
    if args.json {
        println!("{summary}");
    }
    Ok(ExitCode::SUCCESS)
}
