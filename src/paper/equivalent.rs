//! T3 and F10: equivalent stiffness and damping of the element per metre (paper Eq. 2),
//! on the Table 2 grid (T3) and over 0-250 Hz against the linear model (F10).
//!
//! Eq. 2 is the small-signal modulus of the consistent form; the paper form's own
//! small-signal values (SPEC 2.1, `paper_form_linearised`) differ and are shown dashed.

use std::path::Path;

use serde_json::{json, Value};

use super::{out_path, write_csv, ModelSet, COLOR_PRELOAD};

/// The linear model's colour here: the preloads already use the model colours.
const LINEAR_COLOR: usize = 5;
use crate::model::equiv::{
    equivalent, paper_form_linearised, zener_eq2, Equivalent, TABLE2_FREQUENCIES_HZ,
    TABLE2_PRELOADS_N,
};
use crate::model::ZenerParams;
use crate::plot::{draw_png, Panel, Series};

const TWO_PI: f64 = 2.0 * std::f64::consts::PI;

/// One row of an equivalent-property table, per metre of ERS.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EquivalentRow {
    pub preload_n: f64,
    pub frequency_hz: f64,
    /// Paper Eq. 2 (= consistent form's small-signal modulus).
    pub eq2: Equivalent,
    /// The paper form's small-signal modulus, linearised at the preload.
    pub paper_form: Equivalent,
}

/// Eq. 2 and the paper form's linearised values per metre for each preload and frequency.
pub fn equivalent_rows(preloads_n: &[f64], frequencies_hz: &[f64]) -> Vec<EquivalentRow> {
    let zener = ZenerParams::paper_table3(1.0);
    let mut rows = Vec::with_capacity(preloads_n.len() * frequencies_hz.len());
    for &preload_n in preloads_n {
        for &frequency_hz in frequencies_hz {
            let omega = TWO_PI * frequency_hz;
            rows.push(EquivalentRow {
                preload_n,
                frequency_hz,
                eq2: zener_eq2(&zener, preload_n, omega),
                paper_form: paper_form_linearised(&zener, preload_n, omega),
            });
        }
    }
    rows
}

/// The F10 frequency grid: 0.5 Hz steps from 0.5 to 250 Hz (Eq. 2's damping is finite at
/// 0 Hz but the paper form's linearised damping is a ratio Im/W, undefined there).
pub fn figure10_frequencies_hz() -> Vec<f64> {
    (1..=500).map(|i| 0.5 * i as f64).collect()
}

fn write_rows(path: &Path, rows: &[EquivalentRow]) -> anyhow::Result<()> {
    let col = |f: &dyn Fn(&EquivalentRow) -> f64| rows.iter().map(f).collect::<Vec<f64>>();
    write_csv(
        path,
        &[
            "preload_n",
            "frequency_hz",
            "k_eq_eq2_n_per_m2",
            "c_eq_eq2_ns_per_m2",
            "k_eq_paper_form_n_per_m2",
            "c_eq_paper_form_ns_per_m2",
        ],
        &[
            &col(&|r| r.preload_n),
            &col(&|r| r.frequency_hz),
            &col(&|r| r.eq2.k_eq_n_per_m),
            &col(&|r| r.eq2.c_eq_ns_per_m),
            &col(&|r| r.paper_form.k_eq_n_per_m),
            &col(&|r| r.paper_form.c_eq_ns_per_m),
        ],
    )
}

/// Two panels (k_eq, c_eq in MN units) with one colour per preload: Eq. 2 in `eq2_style`,
/// the paper form dashed, and the linear model if `linear` is given.
fn equivalent_panels(
    rows: &[EquivalentRow],
    preloads_n: &[f64],
    points: bool,
    linear: Option<Equivalent>,
    title_suffix: &str,
) -> Vec<Panel> {
    let mut k_panel = Panel::new(
        format!("Equivalent stiffness per metre{title_suffix}"),
        "frequency (Hz)",
        "k_eq (MN/m^2)",
    );
    let mut c_panel = Panel::new(
        format!("Equivalent damping per metre{title_suffix}"),
        "frequency (Hz)",
        "c_eq (MN s/m^2)",
    )
    .log_y();
    for (i, &p) in preloads_n.iter().enumerate() {
        let sel: Vec<&EquivalentRow> = rows.iter().filter(|r| r.preload_n == p).collect();
        let f: Vec<f64> = sel.iter().map(|r| r.frequency_hz).collect();
        let k2: Vec<f64> = sel.iter().map(|r| r.eq2.k_eq_n_per_m * 1e-6).collect();
        let c2: Vec<f64> = sel.iter().map(|r| r.eq2.c_eq_ns_per_m * 1e-6).collect();
        let kp: Vec<f64> = sel
            .iter()
            .map(|r| r.paper_form.k_eq_n_per_m * 1e-6)
            .collect();
        let cp: Vec<f64> = sel
            .iter()
            .map(|r| r.paper_form.c_eq_ns_per_m * 1e-6)
            .collect();
        let color = COLOR_PRELOAD[i % COLOR_PRELOAD.len()];
        let label = format!("{:.0} kN, Eq. 2", p * 1e-3);
        if points {
            k_panel = k_panel.with(Series::points(label.clone(), f.clone(), k2.clone(), color));
            c_panel = c_panel.with(Series::points(label, f.clone(), c2.clone(), color));
        }
        k_panel = k_panel.with(Series::line(
            if points {
                String::new()
            } else {
                format!("{:.0} kN, Eq. 2", p * 1e-3)
            },
            f.clone(),
            k2,
            color,
        ));
        c_panel = c_panel.with(Series::line(
            if points {
                String::new()
            } else {
                format!("{:.0} kN, Eq. 2", p * 1e-3)
            },
            f.clone(),
            c2,
            color,
        ));
        let dashed_label = if i == 0 {
            "dashed: paper form, linearised"
        } else {
            ""
        };
        k_panel = k_panel.with(Series::dashed(dashed_label, f.clone(), kp, color));
        c_panel = c_panel.with(Series::dashed(dashed_label, f, cp, color));
    }
    if let Some(lin) = linear {
        let f: Vec<f64> = rows.iter().map(|r| r.frequency_hz).collect();
        let (lo, hi) = f
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        k_panel = k_panel.with(Series::line(
            "linear Kelvin-Voigt",
            vec![lo, hi],
            vec![lin.k_eq_n_per_m * 1e-6; 2],
            LINEAR_COLOR,
        ));
        c_panel = c_panel.with(Series::line(
            "linear Kelvin-Voigt",
            vec![lo, hi],
            vec![lin.c_eq_ns_per_m * 1e-6; 2],
            LINEAR_COLOR,
        ));
    }
    vec![k_panel, c_panel]
}

/// T3: k_eq and c_eq per metre on the paper's Table 2 grid. Returns the table as JSON.
pub fn write_table3(out_dir: &Path) -> anyhow::Result<Value> {
    let rows = equivalent_rows(&TABLE2_PRELOADS_N, &TABLE2_FREQUENCIES_HZ);
    write_rows(&out_path(out_dir, "t3_equivalent_table.csv"), &rows)?;
    let mut panels = equivalent_panels(&rows, &TABLE2_PRELOADS_N, true, None, " (Table 2 grid)");
    // Headroom keeps the legend (upper right) off the 55 kN curve.
    panels[0] = panels[0].clone().y_range(64.0, 88.0);
    draw_png(
        &out_path(out_dir, "t3_equivalent_table.png"),
        1400,
        550,
        2,
        &panels,
    )?;
    let table: Vec<Value> = rows
        .iter()
        .map(|r| {
            json!({
                "preload_n": r.preload_n,
                "frequency_hz": r.frequency_hz,
                "k_eq_n_per_m2": r.eq2.k_eq_n_per_m,
                "c_eq_ns_per_m2": r.eq2.c_eq_ns_per_m,
            })
        })
        .collect();
    Ok(json!({ "rows": table }))
}

/// F10: k_eq and c_eq per metre over 0.5-250 Hz at the four preloads vs the linear model.
pub fn write_figure10(out_dir: &Path) -> anyhow::Result<Value> {
    let freqs = figure10_frequencies_hz();
    let rows = equivalent_rows(&TABLE2_PRELOADS_N, &freqs);
    write_rows(&out_path(out_dir, "f10_equivalent_vs_frequency.csv"), &rows)?;
    let linear = equivalent(&ModelSet::paper_models(1.0).linear, 0.0, 1.0);
    let panels = equivalent_panels(&rows, &TABLE2_PRELOADS_N, false, Some(linear), "");
    draw_png(
        &out_path(out_dir, "f10_equivalent_vs_frequency.png"),
        1000,
        1000,
        1,
        &panels,
    )?;
    let c_range = |p: f64| {
        let sel: Vec<&EquivalentRow> = rows.iter().filter(|r| r.preload_n == p).collect();
        (
            sel.first().map_or(f64::NAN, |r| r.eq2.c_eq_ns_per_m),
            sel.last().map_or(f64::NAN, |r| r.eq2.c_eq_ns_per_m),
        )
    };
    let per_preload: Vec<Value> = TABLE2_PRELOADS_N
        .iter()
        .map(|&p| {
            let (c_lo, c_hi) = c_range(p);
            json!({
                "preload_n": p,
                "c_eq_at_0_5_hz_ns_per_m2": c_lo,
                "c_eq_at_250_hz_ns_per_m2": c_hi,
            })
        })
        .collect();
    Ok(json!({
        "linear_k_n_per_m2": linear.k_eq_n_per_m,
        "linear_c_ns_per_m2": linear.c_eq_ns_per_m,
        "eq2_by_preload": per_preload,
    }))
}
