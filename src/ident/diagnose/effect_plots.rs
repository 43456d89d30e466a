//! The plot that shows each named effect of what labs meet (`effects.png`): the
//! load-train's frequency response, the modulus against the drift's clock, the specimen's
//! temperature over the campaign, the softening envelope. Must not: decide anything (it
//! only draws the final model and the campaign's measured data).

use crate::ident::campaign::cdiv;
use crate::ident::fit::{predict_cycle, CycleData};
use crate::model::effects::{load_train_transfer, Effect};
use crate::model::thermal::campaign_temperature_rise_k;
use crate::plot::{Panel, Series};

use super::Diagnosis;

/// One panel per named effect that has a plot of its own (none for the older effects,
/// which the gap map and the loops show).
pub fn effect_panels(d: &Diagnosis, data: &[CycleData]) -> Vec<Panel> {
    let mut panels = Vec::new();
    for effect in &d.final_model.effects {
        match *effect {
            Effect::LoadTrainResonance {
                natural_frequency_hz,
                damping_ratio,
            } => panels.push(resonance_panel(natural_frequency_hz, damping_ratio, data)),
            Effect::SpecimenDrift {
                clock,
                rate_per_unit,
                ..
            } => panels.push(drift_panel(d, data, clock, rate_per_unit)),
            Effect::SelfHeating {
                heat_capacity_j_per_k,
                heat_transfer_w_per_k,
                ..
            } => panels.push(heating_panel(
                data,
                heat_capacity_j_per_k,
                heat_transfer_w_per_k,
                d.final_model
                    .effects
                    .iter()
                    .find_map(|e| match e {
                        Effect::ChannelDelay { force_lag_s } => Some(*force_lag_s),
                        _ => None,
                    })
                    .unwrap_or(0.0),
            )),
            Effect::CyclicSoftening {
                softening_limit,
                force_scale_n,
                ..
            } => panels.push(softening_panel(data, softening_limit, force_scale_n)),
            _ => {}
        }
    }
    panels
}

fn log_grid(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| lo * (hi / lo).powf(i as f64 / (n - 1) as f64))
        .collect()
}

fn resonance_panel(fn_hz: f64, zeta: f64, data: &[CycleData]) -> Panel {
    let f = log_grid(0.5, 2.0 * fn_hz, 200);
    let gain = |x: f64| {
        let h = load_train_transfer(fn_hz, zeta, 2.0 * std::f64::consts::PI * x);
        h.0.hypot(h.1)
    };
    let tested = super::harmonic_frequencies(data);
    Panel::new(
        format!("load-train-resonance: {fn_hz:.1} Hz, damping ratio {zeta:.3}"),
        "frequency (Hz)",
        "|F_measured / F_element|",
    )
    .log_x()
    .log_y()
    .with(Series::line(
        "load train",
        f.clone(),
        f.iter().map(|&x| gain(x)).collect(),
        1,
    ))
    .with(Series::points(
        "test frequencies",
        tested.clone(),
        tested.iter().map(|&x| gain(x)).collect(),
        2,
    ))
}

fn drift_panel(
    d: &Diagnosis,
    data: &[CycleData],
    clock: crate::model::effects::DriftClock,
    rate: f64,
) -> Panel {
    // Measured dynamic stiffness over the one the final model gives without its drift
    // (the specimen at the reference instant), per harmonic test, against the clock.
    let mut still = d.final_model.clone();
    still.effects.retain(|e| e.name() != "specimen-drift");
    let (x, y): (Vec<f64>, Vec<f64>) = data
        .iter()
        .filter(|c| !c.is_history())
        .map(|c| {
            let predicted = predict_cycle(&still, c)[0];
            let measured = cdiv(c.force_harmonics_n[0], c.displacement_harmonics_m[0]);
            let model = cdiv(predicted, c.displacement_harmonics_m[0]);
            (
                c.time.clock(clock),
                measured.0.hypot(measured.1) / model.0.hypot(model.1).max(1e-300),
            )
        })
        .unzip();
    let span = x.iter().copied().fold(0.0, f64::max).max(1e-9);
    Panel::new(
        format!(
            "specimen-drift: modulus against {} ({:+.2e} per {})",
            clock.name(),
            rate,
            clock.unit()
        ),
        format!("{} since the first test ({})", clock.name(), clock.unit()),
        "modulus / modulus at the first test",
    )
    .with(Series::points(
        "tests (measured / model at the first test)",
        x,
        y,
        2,
    ))
    .with(Series::line(
        "specimen-drift",
        vec![0.0, span],
        vec![1.0, 1.0 + rate * span],
        1,
    ))
}

fn heating_panel(
    data: &[CycleData],
    heat_capacity: f64,
    heat_transfer: f64,
    force_lag_s: f64,
) -> Panel {
    let Some(schedule) = data.iter().find_map(|c| c.time.schedule.clone()) else {
        return Panel::new("self-heating: no campaign times", "", "");
    };
    let t0 = schedule.first().map_or(0.0, |t| t.start_s);
    let (x, y): (Vec<f64>, Vec<f64>) = (0..schedule.len())
        .map(|i| {
            let t = schedule[i];
            (
                (t.start_s + t.probe_s - t0) / 3600.0,
                campaign_temperature_rise_k(
                    &schedule,
                    i,
                    heat_capacity,
                    heat_transfer,
                    force_lag_s,
                ),
            )
        })
        .unzip();
    Panel::new(
        format!(
            "self-heating: specimen temperature (time constant {:.0} s)",
            heat_capacity / heat_transfer
        ),
        "campaign time (h)",
        "temperature rise at each test's analysed data (K)",
    )
    .with(Series::line("", x.clone(), y.clone(), 1))
    .with(Series::points("tests", x, y, 1))
}

fn softening_panel(data: &[CycleData], limit: f64, scale_n: f64) -> Panel {
    let largest = data
        .iter()
        .map(|c| c.time.peak_force_n)
        .fold(0.0, f64::max)
        .max(1.0);
    let x: Vec<f64> = (0..=100).map(|i| largest * i as f64 / 100.0).collect();
    let eta: Vec<f64> = x
        .iter()
        .map(|&f| 1.0 - limit * ((largest - f) / scale_n).tanh())
        .collect();
    let (px, py): (Vec<f64>, Vec<f64>) = data
        .iter()
        .filter(|c| c.time.max_force_before_n > c.time.peak_force_n)
        .map(|c| {
            let m = c.time.max_force_before_n;
            (
                c.force_mean_n / 1e3,
                1.0 - limit * ((m - c.force_mean_n) / scale_n).tanh(),
            )
        })
        .unzip();
    Panel::new(
        format!(
            "cyclic-softening: force factor below the largest load ({:.0} kN)",
            largest / 1e3
        ),
        "force (kN)",
        "eta = F / F_virgin",
    )
    .with(Series::line(
        "after the campaign's largest load",
        x.iter().map(|f| f / 1e3).collect(),
        eta,
        1,
    ))
    .with(Series::points(
        "tests below a load reached before them (at their mean force)",
        px,
        py,
        2,
    ))
}
