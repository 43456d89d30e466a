//! `fastemu equiv`: equivalent stiffness and damping table (paper Eq. 2).

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;

use crate::model::equiv::{equivalent, zener_eq2, TABLE2_FREQUENCIES_HZ, TABLE2_PRELOADS_N};
use crate::model::params::BASE_MIN;
use crate::model::ElementModel;

#[derive(Args)]
pub struct EquivArgs {
    /// Model file (TOML, e.g. `configs/paper-sample-750mm.toml`; keys in the README).
    #[arg(long)]
    pub model: PathBuf,
    /// Preloads, N (comma-separated; default: the paper's Table 2 grid 6, 18, 37, 55 kN).
    #[arg(
        long = "preload-n",
        value_delimiter = ',',
        allow_negative_numbers = true
    )]
    pub preload_n: Vec<f64>,
    /// Frequencies, Hz (comma-separated; default: 1, 3, 5, 10, 20 Hz).
    #[arg(
        long = "frequency-hz",
        value_delimiter = ',',
        allow_negative_numbers = true
    )]
    pub frequency_hz: Vec<f64>,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: EquivArgs) -> anyhow::Result<ExitCode> {
    let spec = super::load_model(&args.model)?;
    let preloads = if args.preload_n.is_empty() {
        TABLE2_PRELOADS_N.to_vec()
    } else {
        args.preload_n
    };
    let freqs = if args.frequency_hz.is_empty() {
        TABLE2_FREQUENCIES_HZ.to_vec()
    } else {
        args.frequency_hz
    };
    for &p in &preloads {
        anyhow::ensure!(p.is_finite(), "--preload-n {p}: must be a finite number");
        // g(P) = (1 + P/P0)^chi needs P > -P0: below, the model clamps and the table
        // would show numbers that mean nothing.
        if let ElementModel::Consistent(z) | ElementModel::Paper(z) = &spec.element {
            anyhow::ensure!(
                1.0 + p / z.p0_n > BASE_MIN,
                "--preload-n {p}: outside the model's domain: the preload (compression \
                 positive) must be greater than -p0_n = {} N",
                -z.p0_n
            );
        }
    }
    for &f in &freqs {
        anyhow::ensure!(
            f.is_finite() && f >= 0.0,
            "--frequency-hz {f}: must be a finite number >= 0"
        );
    }
    // k_eq/c_eq are the element's (paper Eq. 2 / small-signal); [[effect]] tables are not
    // in them: say so rather than print numbers that look like the augmented model's.
    let effect_names: Vec<String> = spec
        .effect_tables
        .iter()
        .map(|t| {
            t.get("name")
                .and_then(|v| v.as_str())
                .unwrap_or("?")
                .to_string()
        })
        .collect();
    if !effect_names.is_empty() {
        eprintln!(
            "equiv: {}: the values are the base element's; its [[effect]] tables ({}) are not included (`fastemu diagnose` plots k_eq/c_eq with them)",
            args.model.display(),
            effect_names.join(", ")
        );
    }
    let per_metre = 1.0 / spec.length_m;
    let mut rows = Vec::new();
    for &p in &preloads {
        for &f in &freqs {
            let omega = 2.0 * std::f64::consts::PI * f;
            // Eq. 2 is the model's identified k_eq/c_eq; the paper form's time-domain
            // small-signal values differ from it (SPEC 2.1), so show both for that form.
            let eq2 = match &spec.element {
                ElementModel::Consistent(z) | ElementModel::Paper(z) => zener_eq2(z, p, omega),
                ElementModel::KelvinVoigt(_) => equivalent(&spec.element, p, omega),
            };
            let td = equivalent(&spec.element, p, omega);
            rows.push((
                p,
                f,
                eq2.k_eq_n_per_m * per_metre,
                eq2.c_eq_ns_per_m * per_metre,
                td.k_eq_n_per_m * per_metre,
                td.c_eq_ns_per_m * per_metre,
            ));
        }
    }
    if args.json {
        let rows_json: Vec<_> = rows
            .iter()
            .map(|&(p, f, k, c, k_td, c_td)| {
                serde_json::json!({"preload_n": p, "frequency_hz": f, "k_eq_n_per_m2": k, "c_eq_ns_per_m2": c,
                    "k_time_domain_n_per_m2": k_td, "c_time_domain_ns_per_m2": c_td})
            })
            .collect();
        let obj = serde_json::json!({
            "model": args.model.display().to_string(),
            "form": spec.element.form().name(),
            "length_m": spec.length_m,
            "per_metre": true,
            "effects_not_included": effect_names,
            "rows": rows_json,
        });
        println!("{}", serde_json::to_string_pretty(&obj)?);
    } else {
        println!(
            "# {} ({} form, length {} m); values per metre of element",
            args.model.display(),
            spec.element.form(),
            spec.length_m
        );
        let paper = matches!(spec.element, ElementModel::Paper(_));
        print!(
            "{:>11} {:>9} {:>15} {:>16}",
            "preload_kN", "freq_Hz", "k_eq_MN_per_m2", "c_eq_MNs_per_m2"
        );
        if paper {
            print!(
                " {:>22} {:>23}",
                "k_paper_form_MN_per_m2", "c_paper_form_MNs_per_m2"
            );
        }
        println!();
        for (p, f, k, c, k_td, c_td) in rows {
            print!(
                "{:>11.3} {:>9.3} {:>15.4} {:>16.6}",
                p / 1e3,
                f,
                k / 1e6,
                c / 1e6
            );
            if paper {
                print!(" {:>22.4} {:>23.6}", k_td / 1e6, c_td / 1e6);
            }
            println!();
        }
        if paper {
            println!("# k_eq/c_eq: paper Eq. 2; *_paper_form: what the paper-form ODE shows for small oscillations (SPEC 2.1)");
        }
    }
    Ok(ExitCode::SUCCESS)
}
