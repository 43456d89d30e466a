//! The paper's tables and figures reproduced by simulation (`fastemu paper`, SPEC 3):
//! T3, F5, F7, F8, F10-F14 of Li et al. (Materials 2021), each as a CSV and a PNG, plus
//! `summary.json` / `summary.md` with the headline figures beside the published values.
//!
//! Owns: the scenario definitions and the post-processing (single-bin DFT, envelopes,
//! spectra). Uses the `model` steppers and `track` data as they are; never changes them.
//! Offline only: allocates, writes files and prints progress on stderr; nothing here
//! runs in the real-time loop.
//!
//! Sign convention (SPEC 2): displacement and force are positive in compression (rail
//! moving down into the elastomer). The paper plots the external force of Fig. 8 with
//! compression negative (its "valleys" are compression peaks); our F8 plot follows the
//! paper's sign so it can be laid over the published figure, and says so on its axis.
//! Every CSV uses the SPEC convention.
//!
//! Models: "nonlinear" is Table 3 in the paper form (paper Eq. 3 with P = F(t)), which
//! is what the published figures used; the consistent form (SPEC 2.1) is shown beside
//! it wherever it differs; "linear" is the Kelvin-Voigt model of paper Sec. 3.2
//! (80 MN/m^2, 1e-3 MN s/m^2). F10-F14 are per metre of ERS (rail mass 60.21 kg);
//! F5 and F8 are the 750 mm lab sample.

pub mod equivalent;
pub mod free_response;
pub mod harmonic;
pub mod loops;
pub mod passage;
pub mod summary;
pub mod train;

use std::path::{Path, PathBuf};

use anyhow::Context;
use realfft::num_complex::Complex64;

use crate::model::{ElementModel, KelvinVoigtParams, ZenerParams};
use crate::track::UIC60_MASS_KG_PER_M;

/// Length of the lab sample (paper Sec. 2), m.
pub const SAMPLE_LENGTH_M: f64 = 0.75;
/// Rail mass on one metre of ERS (UIC60), kg.
pub const RAIL_MASS_UNIT_LENGTH_KG: f64 = UIC60_MASS_KG_PER_M;

/// How much work `fastemu paper` does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PaperOptions {
    /// Coarse grids and short settling (for tests); the full run is the default.
    pub quick: bool,
}

/// The three element models of one length, in plotting order.
#[derive(Debug, Clone, Copy)]
pub struct ModelSet {
    pub paper: ElementModel,
    pub consistent: ElementModel,
    pub linear: ElementModel,
}

impl ModelSet {
    /// Table 3 (paper and consistent forms) and the linear Kelvin-Voigt model, scaled.
    pub fn paper_models(length_m: f64) -> ModelSet {
        let zener = ZenerParams::paper_table3(length_m);
        ModelSet {
            paper: ElementModel::Paper(zener),
            consistent: ElementModel::Consistent(zener),
            linear: ElementModel::KelvinVoigt(KelvinVoigtParams::paper_linear(length_m)),
        }
    }

    /// `(key, label, model)` for the three models; keys are used in CSV/JSON names.
    pub fn named(&self) -> [(&'static str, &'static str, ElementModel); 3] {
        [
            ("paper", "nonlinear, paper form (Eq. 3)", self.paper),
            ("consistent", "nonlinear, consistent form", self.consistent),
            ("linear", "linear Kelvin-Voigt", self.linear),
        ]
    }
}

/// Plot colours shared by all figures: one per model, one per preload.
pub const COLOR_PAPER: usize = 1;
pub const COLOR_CONSISTENT: usize = 2;
pub const COLOR_LINEAR: usize = 0;
pub const COLOR_PRELOAD: [usize; 4] = [0, 3, 2, 4];

/// Colour of a model key.
pub fn model_color(key: &str) -> usize {
    match key {
        "paper" => COLOR_PAPER,
        "consistent" => COLOR_CONSISTENT,
        _ => COLOR_LINEAR,
    }
}

/// Complex amplitude `X` of the component of `signal` at `frequency_hz`, such that
/// `signal(t) ~ Re{X e^(i W t)}`, by a single-bin DFT over `signal` (sample `i` at time
/// `t0_s + i dt_s`). Exact (no leakage from DC or the harmonics of `frequency_hz`) only
/// when the window holds a whole number of cycles: callers make sure it does.
pub fn single_bin_dft(signal: &[f64], dt_s: f64, t0_s: f64, frequency_hz: f64) -> Complex64 {
    let omega = 2.0 * std::f64::consts::PI * frequency_hz;
    let mut sum = Complex64::new(0.0, 0.0);
    for (i, &x) in signal.iter().enumerate() {
        let phase = omega * (t0_s + i as f64 * dt_s);
        sum += Complex64::new(x * phase.cos(), -x * phase.sin());
    }
    sum * (2.0 / signal.len().max(1) as f64)
}

/// Prints one plain progress line on stderr (indicatif bars hide themselves when stderr
/// is not a terminal, so every stage also gets a line that survives in logs).
pub fn stage(message: &str) {
    eprintln!("fastemu paper: {message}");
}

/// `dir/name`, for output files.
pub fn out_path(dir: &Path, name: &str) -> PathBuf {
    dir.join(name)
}

/// Writes CSV columns, naming the file on failure.
pub fn write_csv(path: &Path, names: &[&str], columns: &[&[f64]]) -> anyhow::Result<()> {
    crate::csvio::write_columns(path, names, columns)
        .with_context(|| format!("cannot write {}", path.display()))
}

/// Every file `fastemu paper` writes, relative to the output directory.
pub const OUTPUT_FILES: [&str; 26] = [
    "t3_equivalent_table.csv",
    "t3_equivalent_table.png",
    "f5_force_displacement_loops.csv",
    "f5_force_displacement_loops.png",
    "f7_static_deflection.csv",
    "f7_deflection_history.csv",
    "f7_static_deflection.png",
    "f8_passage_force.csv",
    "f8_passage_force.png",
    "f10_equivalent_vs_frequency.csv",
    "f10_equivalent_vs_frequency.png",
    "f11_free_response.csv",
    "f11_envelope.csv",
    "f11_free_response.png",
    "f12a_harmonic_sweep.csv",
    "f12b_harmonic_sweep.csv",
    "f12_true_peaks.csv",
    "f12_peak_scans.csv",
    "f12a_harmonic_sweep.png",
    "f12b_harmonic_sweep.png",
    "f13_train_passage.csv",
    "f13_train_passage.png",
    "f14_spectra.csv",
    "f14_spectra.png",
    "summary.json",
    "summary.md",
];

/// Runs every scenario, writes all files into `out_dir` (plus `summary.md`), and
/// returns the summary object that was written to `summary.json`.
pub fn run_all(out_dir: &Path, options: &PaperOptions) -> anyhow::Result<serde_json::Value> {
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("cannot create directory {}", out_dir.display()))?;
    stage("T3 and F10: equivalent stiffness and damping (Eq. 2)");
    let t3 = equivalent::write_table3(out_dir)?;
    let f10 = equivalent::write_figure10(out_dir)?;
    stage("F5: force-controlled loops on the 750 mm sample");
    let f5 = loops::write_figure5(out_dir)?;
    stage("F7 and F8: Winkler deflection and passage force at 200 km/h");
    passage::write_figure7(out_dir)?;
    let f8 = passage::write_figure8(out_dir)?;
    stage("F11: free response to a 55 kN step");
    let f11 = free_response::write_figure11(out_dir, options)?;
    stage("F12: steady-state harmonic sweeps (the long part)");
    let f12 = harmonic::write_figure12(out_dir, options)?;
    stage("F13 and F14: train passage at 72 km/h with a 170 Hz force");
    let (f13, f14) = train::write_figures13_14(out_dir)?;
    let summary = serde_json::json!({
        "sign_convention": "displacement and force positive in compression (SPEC 2)",
        "quick": options.quick,
        "t3": t3,
        "f5": f5,
        "f8": f8,
        "f10": f10,
        "f11": f11,
        "f12": f12,
        "f13": f13,
        "f14": f14,
    });
    let json_path = out_path(out_dir, "summary.json");
    std::fs::write(&json_path, serde_json::to_string_pretty(&summary)? + "\n")
        .with_context(|| format!("cannot write {}", json_path.display()))?;
    let md_path = out_path(out_dir, "summary.md");
    std::fs::write(&md_path, summary::markdown(&summary))
        .with_context(|| format!("cannot write {}", md_path.display()))?;
    stage(&format!("done: files in {}", out_dir.display()));
    Ok(summary)
}
