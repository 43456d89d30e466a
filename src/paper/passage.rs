//! F7 and F8: the static Winkler deflection of UIC60 under an ETR 500 coach (F7a), turned
//! into a deformation history at 200 km/h (F7b), and the force needed to impose that
//! history on the 750 mm sample (F8, paper Eq. 3 with P = F(t); SPEC 3).
//!
//! Deflection is positive downward (compression). F8's plot uses the paper's sign for
//! the external force (compression negative), so the two wheelsets of a bogie appear as
//! the paper's two "valleys" and the tension after them as positive force; the CSV keeps
//! the SPEC sign (compression positive).

use std::path::Path;

use serde_json::{json, Value};

use super::{model_color, out_path, write_csv, ModelSet, SAMPLE_LENGTH_M};
use crate::model::element::simulate_force;
use crate::plot::{draw_png, Panel, Series};
use crate::track::{kmh_to_m_per_s, TrainPassage};

/// Train speed of paper Fig. 7b/8, km/h.
pub const FIGURE8_SPEED_KMH: f64 = 200.0;
/// Track before the first axle and after the last one, m.
pub const PASSAGE_MARGIN_M: f64 = 15.0;
/// Time step of the F7b/F8 histories, s.
pub const PASSAGE_DT_S: f64 = 1e-4;

/// The F7b deformation history: times (s), deflection (m), and when the first axle passes.
pub fn deflection_history(speed_kmh: f64, dt_s: f64) -> (Vec<f64>, Vec<f64>, f64) {
    let train = TrainPassage::etr500_coach(kmh_to_m_per_s(speed_kmh));
    let duration_s = train.duration_s(PASSAGE_MARGIN_M);
    let t_first_s = PASSAGE_MARGIN_M / train.speed_m_per_s;
    let n = (duration_s / dt_s).round() as usize + 1;
    let time_s: Vec<f64> = (0..n).map(|i| i as f64 * dt_s).collect();
    let deflection_m = time_s
        .iter()
        .map(|&t| train.deflection_history_m(t, t_first_s))
        .collect();
    (time_s, deflection_m, t_first_s)
}

/// F7: deflection along the track (first axle at x = 0) and its history at 200 km/h.
/// Returns the peak deflection, m.
pub fn write_figure7(out_dir: &Path) -> anyhow::Result<f64> {
    let train = TrainPassage::etr500_coach(kmh_to_m_per_s(FIGURE8_SPEED_KMH));
    let x_m: Vec<f64> = (0..=4800).map(|i| -35.0 + 0.01 * i as f64).collect();
    let w_m: Vec<f64> = x_m.iter().map(|&x| train.deflection_at_m(x, 0.0)).collect();
    write_csv(
        &out_path(out_dir, "f7_static_deflection.csv"),
        &["x_m", "deflection_m"],
        &[&x_m, &w_m],
    )?;
    let (time_s, history_m, _) = deflection_history(FIGURE8_SPEED_KMH, PASSAGE_DT_S);
    write_csv(
        &out_path(out_dir, "f7_deflection_history.csv"),
        &["t_s", "displacement_m"],
        &[&time_s, &history_m],
    )?;
    let peak_m = w_m.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let axles_x: Vec<f64> = train.axle_offsets_m.iter().map(|d| -d).collect();
    let panels = [
        Panel::new(
            "(a) Static rail deflection, Winkler beam (k = 60 MN/m^2), ETR 500 coach, Q = 110 kN",
            "position along the track, first axle at 0 (m)",
            "deflection, downward positive (mm)",
        )
        .with(Series::line(
            "UIC60 on Winkler foundation",
            x_m.clone(),
            w_m.iter().map(|w| w * 1e3).collect(),
            0,
        ))
        .with(Series::points("axle positions", axles_x, vec![0.0; 4], 1)),
        Panel::new(
            "(b) Elastomer deformation history at 200 km/h",
            "time (s)",
            "deformation, compression positive (mm)",
        )
        .with(Series::line(
            "",
            time_s,
            history_m.iter().map(|w| w * 1e3).collect(),
            0,
        )),
    ];
    draw_png(
        &out_path(out_dir, "f7_static_deflection.png"),
        1200,
        900,
        1,
        &panels,
    )?;
    Ok(peak_m)
}

/// Valleys and overshoot of one bogie's force history, in the paper's sign
/// (compression negative).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BogieForceFeatures {
    /// Paper-sign force at the first wheelset (negative: compression), N.
    pub first_valley_n: f64,
    /// Paper-sign force at the second wheelset, N.
    pub second_valley_n: f64,
    /// Largest paper-sign force (tension) after the second wheelset, before the next
    /// bogie approaches, N.
    pub overshoot_n: f64,
}

/// Finds the features of the first bogie (axles at `t_first_s` and `t_first_s + 3 m / v`).
pub fn bogie_features(
    time_s: &[f64],
    force_n: &[f64],
    t_first_s: f64,
    speed_m_per_s: f64,
) -> BogieForceFeatures {
    let window_max = |t0: f64, t1: f64, f: &dyn Fn(f64) -> f64| {
        time_s
            .iter()
            .zip(force_n)
            .filter(|(t, _)| **t >= t0 && **t <= t1)
            .map(|(_, &x)| f(x))
            .fold(f64::NEG_INFINITY, f64::max)
    };
    let at = |x_m: f64| t_first_s + x_m / speed_m_per_s;
    BogieForceFeatures {
        first_valley_n: -window_max(at(-1.5), at(1.5), &|f| f),
        second_valley_n: -window_max(at(1.5), at(4.5), &|f| f),
        // Halfway between the bogies (11 m after the first axle) the next one takes over.
        overshoot_n: window_max(at(3.0), at(11.0), &|f| -f),
    }
}

/// F8: the force to impose the F7b history on the 750 mm sample, for the three models.
pub fn write_figure8(out_dir: &Path) -> anyhow::Result<Value> {
    let speed_m_per_s = kmh_to_m_per_s(FIGURE8_SPEED_KMH);
    let (time_s, displacement_m, t_first_s) = deflection_history(FIGURE8_SPEED_KMH, PASSAGE_DT_S);
    let models = ModelSet::paper_models(SAMPLE_LENGTH_M);
    let mut forces = Vec::new();
    let mut features = serde_json::Map::new();
    let mut whole = Panel::new(
        "Force imposing the 200 km/h passage on the 750 mm sample (whole coach)",
        "time (s)",
        "external force, compression negative as in paper Fig. 8 (kN)",
    )
    .y_range(-75.0, 25.0);
    let t_bogie_end = t_first_s + 11.0 / speed_m_per_s;
    let t_bogie_start = t_first_s - 6.0 / speed_m_per_s;
    let mut bogie = Panel::new(
        "First bogie: two valleys (wheelsets) then tension (paper Fig. 8)",
        "time (s)",
        "external force, compression negative as in paper Fig. 8 (kN)",
    )
    .y_range(-75.0, 25.0);
    let (b0, b1) = (
        (t_bogie_start / PASSAGE_DT_S).round() as usize,
        (t_bogie_end / PASSAGE_DT_S).round() as usize,
    );
    for (key, label, model) in models.named() {
        let (force_n, _flags) = simulate_force(model, PASSAGE_DT_S, &displacement_m);
        let f = bogie_features(&time_s, &force_n, t_first_s, speed_m_per_s);
        features.insert(
            key.to_string(),
            json!({
                "first_valley_paper_sign_n": f.first_valley_n,
                "second_valley_paper_sign_n": f.second_valley_n,
                "overshoot_paper_sign_n": f.overshoot_n,
            }),
        );
        let paper_sign_kn: Vec<f64> = force_n.iter().map(|f| -f * 1e-3).collect();
        whole = whole.with(Series::line(
            label,
            time_s.clone(),
            paper_sign_kn.clone(),
            model_color(key),
        ));
        bogie = bogie.with(Series::line(
            label,
            time_s[b0..b1].to_vec(),
            paper_sign_kn[b0..b1].to_vec(),
            model_color(key),
        ));
        forces.push(force_n);
    }
    write_csv(
        &out_path(out_dir, "f8_passage_force.csv"),
        &[
            "t_s",
            "displacement_m",
            "force_paper_n",
            "force_consistent_n",
            "force_linear_n",
        ],
        &[&time_s, &displacement_m, &forces[0], &forces[1], &forces[2]],
    )?;
    draw_png(
        &out_path(out_dir, "f8_passage_force.png"),
        1200,
        900,
        1,
        &[bogie, whole],
    )?;
    features.insert("speed_kmh".into(), json!(FIGURE8_SPEED_KMH));
    features.insert("sample_length_m".into(), json!(SAMPLE_LENGTH_M));
    Ok(Value::Object(features))
}
