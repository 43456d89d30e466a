//! Fitting models to harmonic tests: the steady-state cycle simulator, parameterisations
//! of a baseline plus candidate effects, least-squares fits and cross-validation.
//!
//! Owns: `predict_cycle` (force harmonics a model gives for a measured displacement cycle,
//! by time-domain simulation with `ModelStepper` over warm-up cycles and one analysed
//! cycle), `Template` (which parameters are free and how they map to an `AugmentedModel`),
//! `fit_template` and `cross_validate`. The rig artefacts channel-delay and moving-mass are
//! linear and are applied exactly to the simulated harmonics (`F_meas = e^{-i h W tau}
//! (F + m (i h W)^2 Z)`), rather than through the stepper's discrete `z''` and delay line.
//!
//! Must not: do I/O. Everything is deterministic (threads only split independent work).

pub mod lm;

use std::f64::consts::PI;

use super::campaign::{cabs, Campaign, CampaignError, Complex, N_HARMONICS};
use super::history::{
    history_residuals, predict_history, prepare_history, HistoryData, SharedHistory,
};
use crate::model::effects::{
    AugmentedModel, DriftClock, Effect, FrictionLaw, ModelStepper, StepperMode,
};
use crate::model::params::ElementModel;
use crate::model::thermal::{campaign_temperature_rise_k, ThermalInterval};

pub use lm::{levenberg_marquardt, LmFit};

/// Harmonics compared in residuals and gaps: the fundamental only. Higher harmonics of the
/// force carry little signal and as much noise as the fundamental, so they would only
/// raise the noise floor of the gap; they still drive the simulation (measured `Z_2, Z_3`).
pub const FIT_HARMONICS: usize = 1;

/// Samples per simulated cycle.
pub const SAMPLES_PER_CYCLE: usize = 64;

/// One harmonic test as the fitting code sees it.
#[derive(Debug, Clone)]
pub struct CycleData {
    pub id: String,
    pub frequency_hz: f64,
    /// Nominal preload and force amplitude from `campaign.toml`, N.
    pub preload_n: f64,
    pub amplitude_n: f64,
    pub temperature_c: f64,
    /// Measured mean force over the analysed cycles (the operating point), N.
    pub force_mean_n: f64,
    pub displacement_harmonics_m: [Complex; N_HARMONICS],
    pub force_harmonics_n: [Complex; N_HARMONICS],
    /// `|F_1|`: residuals are relative to it, N.
    pub scale_n: f64,
    /// Estimated noise variance of the fundamental residual relative to `|F_1|^2`.
    pub noise_relative: f64,
    /// The same from the campaign's smoothed noise level (`assign_noise_weights`): one
    /// test's own estimate rests on two DFT bins and scatters like an exponential
    /// variable, so statistics that divide by a single test's noise use this; equal to
    /// `noise_relative` until assigned, and for history tests.
    pub noise_smoothed: f64,
    /// Duration of the analysed whole cycles, s.
    pub duration_s: f64,
    /// Precision weight of the test in held-out gaps, `1 / max(nu~_i, median nu~ / 2)`
    /// scaled to mean 1, with `nu~_i` the campaign's smoothed noise level (`assign_noise_weights`);
    /// 1 until assigned.
    pub weight: f64,
    /// Position in the campaign's time: `started_at` in seconds when every test states
    /// it, else the test's index in `campaign.toml`.
    pub order: f64,
    /// A history test (its `frequency_hz`, `preload_n`, `amplitude_n` and `force_mean_n`
    /// then stand for its force-weighted mean frequency, mean force and half force range;
    /// its harmonics are zero and unused).
    pub history: Option<SharedHistory>,
    /// Where the test sits in the campaign's time (`assign_campaign_time`).
    pub time: TestTime,
}

/// Where a test sits in the campaign's time, for `specimen-drift` and `self-heating`.
#[derive(Debug, Clone, Default)]
pub struct TestTime {
    /// Drift clocks at the test's analysed data, relative to the reference instant (the
    /// start of the campaign's first test), in `DriftClock::ALL` order: tests run before,
    /// hours, kJ dissipated.
    pub clocks: [f64; 3],
    /// The campaign's tests in time order as the thermal model sees them, and this test's
    /// place among them.
    pub schedule: Option<std::sync::Arc<Vec<ThermalInterval>>>,
    pub schedule_index: usize,
    /// Energy the specimen dissipated over the whole record (measured `sum F dz`), J.
    pub dissipated_j: f64,
    /// The largest force the specimen carried in the tests before this one (measured
    /// peaks), N: where `cyclic-softening`'s memory stands when the test starts.
    pub max_force_before_n: f64,
    /// This test's own peak force (measured), N.
    pub peak_force_n: f64,
    /// A history unit holding the first cycles of a harmonic record
    /// (`first_cycles::split_first_cycles`), sorted just before the rest of it.
    pub first_cycles: bool,
}

impl TestTime {
    pub fn clock(&self, clock: DriftClock) -> f64 {
        self.clocks[DriftClock::ALL
            .iter()
            .position(|c| *c == clock)
            .unwrap_or(0)]
    }

    /// Mean power dissipated over the record, W.
    pub fn power_w(&self) -> f64 {
        self.schedule
            .as_ref()
            .and_then(|s| s.get(self.schedule_index))
            .map_or(0.0, |t| t.power_w)
    }
}

impl CycleData {
    pub fn is_history(&self) -> bool {
        self.history.is_some()
    }

    /// A history test as a unit of the workflow.
    pub fn from_history(
        id: &str,
        history: HistoryData,
        temperature_c: f64,
        order: f64,
    ) -> CycleData {
        CycleData {
            id: id.to_string(),
            frequency_hz: history.frequency_centroid_hz,
            preload_n: history.force_mean_n(),
            amplitude_n: history.swing_n(),
            temperature_c,
            force_mean_n: history.force_mean_n(),
            displacement_harmonics_m: [(0.0, 0.0); N_HARMONICS],
            force_harmonics_n: [(0.0, 0.0); N_HARMONICS],
            scale_n: history.force_scale_n,
            noise_relative: history.noise_relative,
            noise_smoothed: history.noise_relative,
            duration_s: history.duration_s,
            weight: 1.0,
            order,
            history: Some(std::sync::Arc::new(history)),
            time: TestTime::default(),
        }
    }

    pub fn displacement_amplitude_m(&self) -> f64 {
        cabs(self.displacement_harmonics_m[0])
    }
}

/// The harmonic tests of a campaign, reduced to their steady-state cycles.
pub fn cycle_data(campaign: &Campaign) -> Vec<CycleData> {
    let mut data = harmonic_units(campaign);
    assign_noise_weights(&mut data);
    data
}

/// Every test of a campaign, harmonic and history, in campaign order, with weights.
pub fn test_data(campaign: &Campaign) -> Result<Vec<CycleData>, CampaignError> {
    let orders = campaign.test_orders();
    let harmonic = harmonic_units(campaign);
    let mut data = Vec::with_capacity(campaign.tests.len());
    let mut harmonic_iter = harmonic.into_iter();
    for (test, order) in campaign.tests.iter().zip(orders) {
        if test.cycle.is_some() {
            let mut d = harmonic_iter.next().expect("one unit per harmonic test");
            d.order = order;
            data.push(d);
        } else {
            let history =
                prepare_history(test.dt_s, &test.displacement_m, &test.force_n).map_err(|e| {
                    CampaignError {
                        path: test.file.display().to_string(),
                        message: format!("history test \"{}\": {e}", test.id),
                    }
                })?;
            data.push(CycleData::from_history(
                &test.id,
                history,
                test.temperature_c,
                order,
            ));
        }
    }
    assign_noise_weights(&mut data);
    assign_campaign_time(&mut data, campaign);
    Ok(data)
}

/// Sets each test's `TestTime` from the campaign: start times from `started_at` when every
/// test states it, else the tests back to back in file order (no rests); each record's
/// duration and measured dissipated energy (`sum F dz`, trapezoid); the analysed data of a
/// harmonic test sit in the middle of its last analysed cycles, a history test's in its
/// middle. `data` must be `test_data`'s (one unit per test, campaign order).
pub fn assign_campaign_time(data: &mut [CycleData], campaign: &Campaign) {
    if data.len() != campaign.tests.len() || data.is_empty() {
        return;
    }
    let mut intervals: Vec<ThermalInterval> = Vec::with_capacity(data.len());
    let mut energies = Vec::with_capacity(data.len());
    let mut back_to_back_s = 0.0;
    let clocked = campaign.has_start_times();
    for (test, d) in campaign.tests.iter().zip(data.iter()) {
        let n = test.displacement_m.len();
        let duration_s = (n.max(1) as f64) * test.dt_s;
        // The energy the record shows dissipated, not clamped here: a force channel late
        // by more than the element's loss angle shows a negative one (0.3 ms at 20 Hz is
        // 2.2 degrees against about 0.8), and only with the lag's correction below
        // (`campaign_temperature_rise_k`) is it the element's. Clamped before the
        // correction, such tests heated the model by the correction alone: self-heating
        // beside a 0.3 ms lag was never named (2026-11-28). The drift's energy clock
        // takes it clamped, as before.
        let energy_j: f64 = test
            .displacement_m
            .windows(2)
            .zip(test.force_n.windows(2))
            .map(|(z, f)| 0.5 * (f[0] + f[1]) * (z[1] - z[0]))
            .sum::<f64>();
        // sum dF/dt dz: the energy's change per second of force lag corrected.
        let energy_per_lag_j_per_s: f64 = test
            .displacement_m
            .windows(2)
            .zip(test.force_n.windows(2))
            .map(|(z, f)| (f[1] - f[0]) / test.dt_s * (z[1] - z[0]))
            .sum();
        let probe_s = if d.is_history() {
            0.5 * duration_s
        } else {
            (duration_s - 0.5 * d.duration_s).clamp(0.0, duration_s)
        };
        let start_s = if clocked {
            test.started_at_s.unwrap_or(0.0)
        } else {
            back_to_back_s
        };
        back_to_back_s += duration_s;
        intervals.push(ThermalInterval {
            start_s,
            duration_s,
            power_w: energy_j / duration_s.max(1e-300),
            probe_s,
            power_per_lag_w_per_s: energy_per_lag_j_per_s / duration_s.max(1e-300),
        });
        energies.push(energy_j.max(0.0));
    }
    let mut order: Vec<usize> = (0..data.len()).collect();
    order.sort_by(|&a, &b| intervals[a].start_s.total_cmp(&intervals[b].start_s));
    let schedule: Vec<ThermalInterval> = order.iter().map(|&i| intervals[i]).collect();
    let reference_s = schedule[0].start_s;
    let shared = std::sync::Arc::new(schedule);
    let peaks: Vec<f64> = data
        .iter()
        .map(|d| match &d.history {
            Some(h) => h.force_max_n,
            None => d.force_mean_n + d.force_harmonics_n.iter().map(|f| cabs(*f)).sum::<f64>(),
        })
        .collect();
    let mut energy_before_j = 0.0;
    let mut max_before_n = 0.0f64;
    // The "tests run before" clock counts tests, not units: first cycles split off a
    // record (`first_cycles_of`, sorted just before their parent) take their parent's
    // count and do not advance it, so a drift per test sees the campaign the lab ran.
    let mut tests_before = 0usize;
    for (rank, &i) in order.iter().enumerate() {
        let t = intervals[i];
        let test_count = tests_before;
        if campaign.tests[i].first_cycles_of.is_none() {
            tests_before += 1;
        }
        let fraction = t.probe_s / t.duration_s.max(1e-300);
        data[i].time = TestTime {
            clocks: [
                test_count as f64,
                // Back-to-back times are not a clock: without `started_at` only order.
                if clocked {
                    (t.start_s + t.probe_s - reference_s) / 3600.0
                } else {
                    0.0
                },
                (energy_before_j + fraction * energies[i]) / 1e3,
            ],
            schedule: Some(shared.clone()),
            schedule_index: rank,
            dissipated_j: energies[i],
            max_force_before_n: max_before_n,
            peak_force_n: peaks[i],
            first_cycles: campaign.tests[i].first_cycles_of.is_some(),
        };
        energy_before_j += energies[i];
        max_before_n = max_before_n.max(peaks[i]);
    }
}

/// The model as it was during a test: its temperature, the self-heating rise the
/// campaign's schedule gives it, the drift clocks' positions.
pub fn model_for_test(model: &AugmentedModel, data: &CycleData) -> AugmentedModel {
    let mut out = model.at_temperature(data.temperature_c);
    let force_lag_s = out
        .effects
        .iter()
        .find_map(|e| match e {
            Effect::ChannelDelay { force_lag_s } => Some(*force_lag_s),
            _ => None,
        })
        .unwrap_or(0.0);
    for effect in &mut out.effects {
        match effect {
            Effect::SpecimenDrift {
                clock,
                clock_position,
                ..
            } => *clock_position = data.time.clock(*clock),
            // Without a schedule (a HIL run's record) the model's own rise is kept.
            Effect::SelfHeating {
                heat_capacity_j_per_k,
                heat_transfer_w_per_k,
                temperature_rise_k,
            } => {
                if let Some(s) = &data.time.schedule {
                    *temperature_rise_k = campaign_temperature_rise_k(
                        s,
                        data.time.schedule_index,
                        *heat_capacity_j_per_k,
                        *heat_transfer_w_per_k,
                        force_lag_s,
                    );
                }
            }
            // The specimen's memory of its largest load when the test starts (the test's
            // own first cycles raise it in the simulation).
            Effect::CyclicSoftening { max_force_n, .. } if data.time.schedule.is_some() => {
                *max_force_n = data.time.max_force_before_n;
            }
            _ => {}
        }
    }
    out
}

fn harmonic_units(campaign: &Campaign) -> Vec<CycleData> {
    campaign
        .harmonic_tests()
        .enumerate()
        .filter_map(|(index, test)| {
            let cycle = test.cycle.as_ref()?;
            let scale_n = cabs(cycle.force_harmonics_n[0]).max(1e-300);
            Some(CycleData {
                id: test.id.clone(),
                frequency_hz: cycle.frequency_hz,
                preload_n: test.preload_n().unwrap_or(cycle.force_mean_n),
                amplitude_n: test.amplitude_n().unwrap_or(0.0),
                temperature_c: test.temperature_c,
                force_mean_n: cycle.force_mean_n,
                displacement_harmonics_m: cycle.displacement_harmonics_m,
                force_harmonics_n: cycle.force_harmonics_n,
                scale_n,
                noise_relative: cycle.fundamental_noise_variance_n2 / (scale_n * scale_n),
                noise_smoothed: cycle.fundamental_noise_variance_n2 / (scale_n * scale_n),
                duration_s: cycle.n_cycles as f64 / cycle.frequency_hz,
                weight: 1.0,
                order: index as f64,
                history: None,
                time: TestTime::default(),
            })
        })
        .collect()
}

/// Sets each test's precision weight from a smoothed noise level.
///
/// A single test's noise estimate rests on two DFT bins, so it scatters like an
/// exponential variable; weighting by it would favour tests whose noise happens to be
/// underestimated. The smoothed level instead regresses the log noise spectral density
/// `ln(nu_i |F_1,i|^2 T_i)` on `ln f`, `(ln f)^2` and `ln |K_i|` (force noise is flat in
/// `|K|`, displacement noise grows as `|K|^2`) over the whole campaign and converts back:
/// `nu~_i = exp(fit_i) / (|F_1,i|^2 T_i)`. The weight is the inverse noise variance
/// `1 / max(nu~_i, median nu~ / 2)`: every test adds about as much noise to a weighted
/// mean, so a few tests with large noise (small amplitude, short records) no longer decide
/// the gap; the floor keeps the quietest tests from counting more than twice the median
/// test.
pub fn assign_noise_weights(data: &mut [CycleData]) {
    // Regressors: 1, ln f, (ln f)^2, ln |K|.
    let features = |d: &CycleData| -> [f64; 4] {
        let x = d.frequency_hz.ln();
        let stiffness =
            crate::ident::campaign::cdiv(d.force_harmonics_n[0], d.displacement_harmonics_m[0]);
        [1.0, x, x * x, cabs(stiffness).max(1e-300).ln()]
    };
    let rows: Vec<(f64, [f64; 4])> = data
        .iter()
        .filter(|d| !d.is_history() && d.noise_relative > 0.0 && d.duration_s > 0.0)
        .map(|d| {
            let y = (d.noise_relative * d.scale_n * d.scale_n * d.duration_s).ln();
            (y, features(d))
        })
        .collect();
    if rows.len() < 8 {
        return;
    }
    // Least squares with a small ridge (the columns are collinear when the campaign has
    // one preload or few frequencies); the intercept is not penalised.
    let mut ata = nalgebra::Matrix4::<f64>::zeros();
    let mut aty = nalgebra::Vector4::<f64>::zeros();
    for (y, a) in &rows {
        for i in 0..4 {
            aty[i] += a[i] * y;
            for j in 0..4 {
                ata[(i, j)] += a[i] * a[j];
            }
        }
    }
    for i in 1..4 {
        ata[(i, i)] += 1e-6 * ata[(i, i)].max(1.0);
    }
    let Some(coef) = ata.cholesky().map(|c| c.solve(&aty)) else {
        return;
    };
    // A history test's noise estimate rests on many bins: its own value is its level.
    let smoothed: Vec<f64> = data
        .iter()
        .map(|d| {
            if d.is_history() {
                return d.noise_relative;
            }
            let a = features(d);
            let density = (0..4).map(|i| coef[i] * a[i]).sum::<f64>().exp();
            density / (d.scale_n * d.scale_n * d.duration_s.max(1e-300))
        })
        .collect();
    let mut sorted: Vec<f64> = smoothed
        .iter()
        .zip(data.iter())
        .filter(|(_, d)| !d.is_history())
        .map(|(s, _)| *s)
        .collect();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    if !(median.is_finite() && median > 0.0) {
        return;
    }
    let raw: Vec<f64> = smoothed.iter().map(|s| 1.0 / s.max(0.5 * median)).collect();
    let mean = raw.iter().sum::<f64>() / raw.len() as f64;
    for ((d, w), s) in data.iter_mut().zip(raw).zip(&smoothed) {
        d.weight = w / mean;
        d.noise_smoothed = *s;
    }
}

/// Slowest relaxation time of the element, s (0 for Kelvin-Voigt).
fn relaxation_time_s(element: &ElementModel) -> f64 {
    element
        .zener()
        .map_or(0.0, |p| 1.0 / p.relaxation_rate_per_s())
}

/// Force harmonics the model gives when driven by the test's displacement cycle around
/// the static point of the measured mean force (so a displacement offset in the data does
/// not matter, and the operating point is the measured preload). Also returns one
/// simulated cycle of force and displacement (`SAMPLES_PER_CYCLE` samples, rig artefacts
/// excluded from the force).
pub fn predict_cycle_with_waveform(
    model: &AugmentedModel,
    data: &CycleData,
) -> ([Complex; N_HARMONICS], Vec<f64>, Vec<f64>) {
    let m = SAMPLES_PER_CYCLE;
    let model_t = model_for_test(model, data);
    let element = model_t.effective_element();
    let z_mean = element.static_displacement_m(data.force_mean_n);
    let omega = 2.0 * PI * data.frequency_hz;
    let period_s = 1.0 / data.frequency_hz;
    let dt_s = period_s / m as f64;
    let mut n_warm = (5.0 * relaxation_time_s(&element) * data.frequency_hz).ceil() as usize;
    n_warm = n_warm.clamp(1, 40);
    if model_t.find("amplitude-friction").is_some() || model_t.find("fractional-damping").is_some()
    {
        n_warm += 2;
    }
    // Start where the fundamental crosses its mean on the way up, so slow branches start
    // close to their periodic state.
    let z1 = data.displacement_harmonics_m[0];
    let t_start = (-0.5 * PI - z1.1.atan2(z1.0)).rem_euclid(2.0 * PI) / omega;
    let mut z_cycle = vec![0.0; m];
    let mut basis = vec![[(0.0, 0.0); N_HARMONICS]; m];
    // Each harmonic's phasor at the first sample, advanced sample by sample by a rotation
    // (64 samples: the recurrence's rounding stays near 1e-15).
    let mut phasor = [(0.0, 0.0); N_HARMONICS];
    let mut rotation = [(0.0, 0.0); N_HARMONICS];
    for h in 0..N_HARMONICS {
        let (s, c) = ((h + 1) as f64 * omega * t_start).sin_cos();
        phasor[h] = (c, s);
        let (s, c) = ((h + 1) as f64 * omega * dt_s).sin_cos();
        rotation[h] = (c, s);
    }
    for (z, b) in z_cycle.iter_mut().zip(basis.iter_mut()) {
        *z = z_mean;
        for (h, (bh, zh)) in b.iter_mut().zip(&data.displacement_harmonics_m).enumerate() {
            let (c, s) = phasor[h];
            *z += zh.0 * c - zh.1 * s;
            *bh = (c, -s);
            let (rc, rs) = rotation[h];
            phasor[h] = (c * rc - s * rs, s * rc + c * rs);
        }
    }
    // The static force of the consistent form at each sample of the cycle, once: the
    // warm-up steps the same 64 displacements over and over.
    let static_forces: Vec<Option<(f64, bool)>> = match &element {
        ElementModel::Consistent(p) => z_cycle
            .iter()
            .map(|&z| Some(crate::model::params::consistent_static_force(p, z)))
            .collect(),
        _ => vec![None; m],
    };
    let mut stepper = ModelStepper::new(&model_t, StepperMode::Emulation, dt_s, z_cycle[0])
        .with_frozen_temperature();
    let warm_cycle = |stepper: &mut ModelStepper| {
        for k in 1..=m {
            let idx = k % m;
            stepper.step_with_static_force(z_cycle[idx], static_forces[idx]);
        }
    };
    // The linear states (Maxwell branch, springpot branches) need 5 relaxation times to
    // forget the start, but their periodic state follows from one cycle: after it they
    // jump there, and the nonlinear states (friction, the Mullins maximum) settle over
    // `settle` more cycles. Fewer cycles when the relaxation is slow against the test's
    // period, and closer to the periodic state (the long warm-up kept e^-5 of the start's
    // transient, e^-4 and more where it hit its 40 cycles; test
    // `the_predicted_cycle_is_the_periodic_one`).
    let friction = model_t.find("amplitude-friction").is_some();
    let settle = if friction { 3 } else { 2 };
    match stepper.linear_state() {
        Some(start) if n_warm > 1 + settle => {
            warm_cycle(&mut stepper);
            stepper.jump_to_periodic(&start, m);
            for _ in 0..settle {
                warm_cycle(&mut stepper);
            }
        }
        _ => {
            for _ in 0..n_warm {
                warm_cycle(&mut stepper);
            }
        }
    }
    let mut harmonics = [(0.0, 0.0); N_HARMONICS];
    let mut waveform = vec![0.0; m];
    for k in 1..=m {
        let idx = k % m;
        let (force, _) = stepper.step_with_static_force(z_cycle[idx], static_forces[idx]);
        waveform[idx] = force;
        for h in 0..N_HARMONICS {
            harmonics[h].0 += force * basis[idx][h].0 * 2.0 / m as f64;
            harmonics[h].1 += force * basis[idx][h].1 * 2.0 / m as f64;
        }
    }
    let artefacts = model_t.rig_artefacts();
    if !artefacts.is_none() {
        for (h, fh) in harmonics.iter_mut().enumerate() {
            let w = (h + 1) as f64 * omega;
            *fh = artefacts.measured(w, *fh, data.displacement_harmonics_m[h]);
        }
    }
    (harmonics, waveform, z_cycle)
}

/// Force harmonics the model predicts for a test (see `predict_cycle_with_waveform`).
pub fn predict_cycle(model: &AugmentedModel, data: &CycleData) -> [Complex; N_HARMONICS] {
    predict_cycle_with_waveform(model, data).0
}

/// Relative squared residual of one test: `|F_sim,1 - F_1|^2 / |F_1|^2` (harmonic), the
/// band's relative squared residual (history, see `history`).
pub fn relative_error(model: &AugmentedModel, data: &CycleData) -> f64 {
    test_residuals(model, data).iter().map(|r| r * r).sum()
}

/// Residual terms of one test; their squares sum to its relative squared residual.
pub fn test_residuals(model: &AugmentedModel, data: &CycleData) -> Vec<f64> {
    match &data.history {
        Some(history) => history_residuals(
            &predict_history(
                &model_for_test(model, data),
                history,
                data.temperature_c,
                data.time.schedule.is_some(),
            ),
            history,
        ),
        None => residual_terms(&predict_cycle(model, data), data).to_vec(),
    }
}

fn residual_terms(
    predicted: &[Complex; N_HARMONICS],
    data: &CycleData,
) -> [f64; 2 * FIT_HARMONICS] {
    let mut out = [0.0; 2 * FIT_HARMONICS];
    for h in 0..FIT_HARMONICS {
        out[2 * h] = (predicted[h].0 - data.force_harmonics_n[h].0) / data.scale_n;
        out[2 * h + 1] = (predicted[h].1 - data.force_harmonics_n[h].1) / data.scale_n;
    }
    out
}

/// An effect the library can add.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum EffectKind {
    PreloadStiffening,
    AmplitudeFriction,
    FractionalDamping,
    TemperatureShift,
    ChannelDelay,
    MovingMass,
    LoadTrainResonance,
    SpecimenDrift,
    SelfHeating,
    CyclicSoftening,
}

impl EffectKind {
    pub const ALL: [EffectKind; 10] = [
        EffectKind::PreloadStiffening,
        EffectKind::AmplitudeFriction,
        EffectKind::FractionalDamping,
        EffectKind::TemperatureShift,
        EffectKind::ChannelDelay,
        EffectKind::MovingMass,
        EffectKind::LoadTrainResonance,
        EffectKind::SpecimenDrift,
        EffectKind::SelfHeating,
        EffectKind::CyclicSoftening,
    ];

    /// Rig artefacts: how the rig measures, not the elastomer (never emulated).
    pub fn is_rig_artefact(self) -> bool {
        matches!(
            self,
            EffectKind::ChannelDelay | EffectKind::MovingMass | EffectKind::LoadTrainResonance
        )
    }

    pub fn name(self) -> &'static str {
        crate::model::effects::EFFECT_NAMES[self as usize]
    }

    pub fn n_params(self) -> usize {
        match self {
            EffectKind::PreloadStiffening
            | EffectKind::ChannelDelay
            | EffectKind::MovingMass
            | EffectKind::SpecimenDrift => 1,
            EffectKind::AmplitudeFriction => 3,
            _ => 2,
        }
    }

    /// Where a fitted effect's parameters leave the range its physics allows, the first
    /// such parameter. Parameters mapped through `exp` or a logistic (stiffnesses, slip
    /// forces, exponents, chi) stay inside by construction; the linear ones are checked.
    pub fn out_of_range(self, effect: &Effect) -> Option<OutOfRange> {
        let check = |param: &'static str, value: f64, range: (f64, f64), unit: &'static str| {
            (!(range.0..=range.1).contains(&value)).then_some(OutOfRange {
                kind: self,
                param,
                value,
                range,
                unit,
            })
        };
        match *effect {
            Effect::MovingMass { mass_kg } => check("mass_kg", mass_kg, MOVING_MASS_RANGE_KG, "kg"),
            Effect::ChannelDelay { force_lag_s } => {
                check("force_lag_s", force_lag_s, CHANNEL_DELAY_RANGE_S, "s")
            }
            Effect::TemperatureShift {
                log10_time_shift_per_c,
                ln_modulus_shift_per_c,
                ..
            } => check(
                "log10_time_shift_per_c",
                log10_time_shift_per_c,
                TIME_SHIFT_RANGE_PER_C,
                "1/degC",
            )
            .or_else(|| {
                check(
                    "ln_modulus_shift_per_c",
                    ln_modulus_shift_per_c,
                    MODULUS_SHIFT_RANGE_PER_C,
                    "1/degC",
                )
            }),
            Effect::LoadTrainResonance {
                natural_frequency_hz,
                damping_ratio,
            } => check(
                "natural_frequency_hz",
                natural_frequency_hz,
                LOAD_TRAIN_FREQUENCY_RANGE_HZ,
                "Hz",
            )
            .or_else(|| check("damping_ratio", damping_ratio, LOAD_TRAIN_DAMPING_RANGE, "")),
            Effect::CyclicSoftening { force_scale_n, .. } => check(
                "force_scale_n",
                force_scale_n,
                SOFTENING_FORCE_SCALE_RANGE_N,
                "N",
            ),
            Effect::SelfHeating {
                heat_capacity_j_per_k,
                heat_transfer_w_per_k,
                ..
            } => check(
                "heat_transfer_w_per_k",
                heat_transfer_w_per_k,
                crate::model::thermal::HEAT_TRANSFER_RANGE_W_PER_K,
                "W/K",
            )
            .or_else(|| {
                check(
                    "heat_capacity_j_per_k",
                    heat_capacity_j_per_k,
                    crate::model::thermal::HEAT_CAPACITY_RANGE_J_PER_K,
                    "J/K",
                )
            }),
            _ => None,
        }
    }
}

/// Admissible first mode of a load train (fixture, load cell, frame) seen through the
/// force channel: above the slowest test frequencies a lab runs, below which the mode would
/// be the test; beyond 5 kHz it plays no part in tests up to a few hundred Hz.
pub const LOAD_TRAIN_FREQUENCY_RANGE_HZ: (f64, f64) = (10.0, 5000.0);
/// Admissible damping ratio of that mode: bolted steel (a few 0.1 %) to rubber-mounted
/// fixtures (30 %). Above, the "mode" is a low-pass filter of another kind.
pub const LOAD_TRAIN_DAMPING_RANGE: (f64, f64) = (0.001, 0.3);
/// Force scale of the Mullins softening below the largest load (a sample's forces: tens
/// of newtons to a meganewton).
pub const SOFTENING_FORCE_SCALE_RANGE_N: (f64, f64) = (10.0, 1e6);
/// Largest relative softening of a filled elastomer far below its largest load (the
/// Mullins effect reaches tens of per cent in carbon-black-filled rubber).
pub const SOFTENING_LIMIT_MAX: f64 = 0.6;
/// Largest relative change of the moduli over a campaign a `specimen-drift` may have.
pub const DRIFT_CHANGE_LIMIT: f64 = 0.5;

/// Admissible moving mass between load cell and sample: not negative; a tonne is far more
/// than any loading head or fixture.
pub const MOVING_MASS_RANGE_KG: (f64, f64) = (0.0, 1000.0);
/// Admissible skew between force and displacement channels (either sign), s.
pub const CHANNEL_DELAY_RANGE_S: (f64, f64) = (-5e-3, 5e-3);
/// Time shift `s` in `log10 a_T = -s (T - T_ref)`: relaxation speeds up as the elastomer
/// warms (s >= 0), at most a decade per 2 degC.
pub const TIME_SHIFT_RANGE_PER_C: (f64, f64) = (0.0, 0.5);
/// Modulus shift `m` in `ln b_T = -m (T - T_ref)`: elastomers soften as they warm; a
/// slight entropic stiffening (m down to -0.02) is allowed, and the factor `exp(-m dT)`
/// stays positive for any `m`.
pub const MODULUS_SHIFT_RANGE_PER_C: (f64, f64) = (-0.02, 0.2);

/// A fitted parameter outside its physical range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutOfRange {
    pub kind: EffectKind,
    pub param: &'static str,
    pub value: f64,
    pub range: (f64, f64),
    pub unit: &'static str,
}

impl OutOfRange {
    /// What a best fit outside the range suggests about the data.
    pub fn suggestion(&self) -> &'static str {
        match (self.kind, self.value < self.range.0) {
            (EffectKind::MovingMass, true) => {
                "a negative mass is no mass: the measured force grows with frequency squared in proportion to the force itself, which points at the load train's own dynamics (a resonance of fixture, load cell or frame above the test frequencies), not at a moving mass"
            }
            (EffectKind::MovingMass, false) => {
                "a frequency-squared term too large for any moving part: a resonance of the load path close to the test frequencies"
            }
            (EffectKind::ChannelDelay, _) => {
                "a phase error beyond any acquisition skew: a phase that grows with frequency, e.g. dynamics of the load path or the actuator"
            }
            (EffectKind::SelfHeating, true) => {
                "heat that is never carried away accumulates over the whole campaign: the specimen changed with the energy it dissipated or with time, which specimen-drift describes"
            }
            (EffectKind::LoadTrainResonance, false) => {
                "a mode far above every test frequency: no load-train resonance shows in these tests"
            }
            (EffectKind::TemperatureShift, _) => {
                "no thermorheological law explains the tests at other temperatures: they differ for another reason (were they run late in the campaign? see test order)"
            }
            _ => "the effect's physics does not explain this discrepancy",
        }
    }
}

impl OutOfRange {
    /// Whether the fit left its range towards another effect of the library (a
    /// self-heating that never cools is a drift; a load-train mode beyond every test
    /// frequency is no mode): such a fit is not a sign of a cause outside the library.
    pub fn degenerates(&self) -> bool {
        matches!(
            (self.kind, self.value < self.range.0),
            (EffectKind::SelfHeating, true) | (EffectKind::LoadTrainResonance, false)
        )
    }
}

/// A fitted value this far from 1 (or this close to 0) is a map's numerical limit, not a
/// value: every effect's range lies well inside it.
const RUNAWAY_MAGNITUDE: f64 = 1e20;

impl std::fmt::Display for OutOfRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let bound = if self.value < self.range.0 {
            format!(">= {}", self.range.0)
        } else {
            format!("<= {}", self.range.1)
        };
        // A log- or logistic-mapped parameter run off to its map's numerical limit
        // (e^50 = 5.18e21, e^-50): no finite value fits; its number is no result.
        let magnitude = self.value.abs();
        if magnitude >= RUNAWAY_MAGNITUDE
            || (magnitude > 0.0 && magnitude <= 1.0 / RUNAWAY_MAGNITUDE)
        {
            return write!(
                f,
                "fits only with {} running off to {} (the fit stopped at its numerical limit, {:.1e}), outside its range ({bound} {})",
                self.param,
                if magnitude >= 1.0 { "infinity" } else { "zero" },
                self.value,
                self.unit
            );
        }
        write!(
            f,
            "fits only with {} = {:.4e}, outside its range ({bound} {})",
            self.param, self.value, self.unit
        )
    }
}

/// A fitted effect parameter (file units) with its 95 % interval.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamInterval {
    pub name: &'static str,
    pub value: f64,
    pub ci95: Option<(f64, f64)>,
    /// The parameter's change per unit of the fitted coordinate that sets it (NaN when
    /// several do): the scale an interval across zero is judged on.
    pub unit: f64,
    /// Pinned on its map's bound (a clamp): the data do not move it, no interval.
    pub on_bound: bool,
}

impl ParamInterval {
    /// Whether the data determine it: a finite 95 % interval that, away from zero, spans
    /// at most a factor of 10; an interval across zero determines the value as about zero
    /// (a shift the data show absent, `consistent_with_zero`) only when it is no wider
    /// than one unit of the fitted coordinate either way (`unit`: a moving mass of -50 to
    /// +400 kg is no measurement; a temperature slope within +-8e-4 per degC is).
    pub fn determined(&self) -> bool {
        self.ci95.is_some_and(|(lo, hi)| {
            lo.is_finite()
                && hi.is_finite()
                && if lo * hi <= 0.0 {
                    lo.abs().max(hi.abs()) <= self.unit
                } else {
                    lo.abs().max(hi.abs()) <= 10.0 * lo.abs().min(hi.abs())
                }
        })
    }

    /// Whether its 95 % interval holds zero.
    pub fn consistent_with_zero(&self) -> bool {
        self.ci95.is_some_and(|(lo, hi)| lo <= 0.0 && hi >= 0.0)
    }
}

/// Which parameters are free: the baseline's own (structure kept) plus added effects.
#[derive(Debug, Clone)]
pub struct Template {
    /// The baseline: element structure and any effects it already has (held fixed).
    pub baseline: AugmentedModel,
    /// Whether the baseline's `chi` is fitted (only when it is non-zero: chi = 0 stays 0).
    pub fit_chi: bool,
    /// Whether the element's own parameters are fitted at all.
    pub fit_element: bool,
    pub added: Vec<EffectKind>,
    pub reference_temperature_c: f64,
    /// Start values for the leading parameters (e.g. the fit this template extends).
    pub start_prefix: Option<Vec<f64>>,
    /// Law of an added `amplitude-friction`: generalised Dahl (true) or Iwan (false).
    pub friction_dahl: bool,
    /// An added `temperature-shift` with its relaxation-time shift held on its range's
    /// lower bound, 0 (the parameter stays in the vector but does nothing): the variant
    /// tried beside the free one, for a fit that would leave the range just below it.
    pub time_shift_on_bound: bool,
    /// Clock of an added `specimen-drift`.
    pub drift_clock: DriftClock,
    /// Each drift clock's span over the campaign (`DriftClock::ALL` order; 0: the campaign
    /// lacks that clock): the drift's fitted parameter is its change over the campaign,
    /// `rate x span`.
    pub clock_spans: [f64; 3],
    /// Clocks left out because they are proportional to test order in this campaign
    /// (evenly spaced tests; tests that dissipate alike): the data cannot tell them apart.
    pub clocks_like_order: Vec<DriftClock>,
}

const CHI_MAX: f64 = 0.95;
/// Largest log-normal spread of the friction sliders' slip forces.
const SLIP_SPREAD_MAX: f64 = 3.0;
/// Fitted generalised-Dahl exponent range (a logistic map onto it).
const DAHL_EXPONENT_FIT: (f64, f64) = (0.05, 3.0);

fn dahl_exponent(theta: f64) -> f64 {
    DAHL_EXPONENT_FIT.0 + (DAHL_EXPONENT_FIT.1 - DAHL_EXPONENT_FIT.0) * logistic(theta)
}

fn dahl_theta(exponent: f64) -> f64 {
    logit((exponent - DAHL_EXPONENT_FIT.0) / (DAHL_EXPONENT_FIT.1 - DAHL_EXPONENT_FIT.0))
}

/// Pearson correlation (0 when either side is constant).
pub fn correlation(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len().min(y.len()) as f64;
    if n < 2.0 {
        return 0.0;
    }
    let mx = x.iter().sum::<f64>() / n;
    let my = y.iter().sum::<f64>() / n;
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (a, b) in x.iter().zip(y) {
        sxy += (a - mx) * (b - my);
        sxx += (a - mx) * (a - mx);
        syy += (b - my) * (b - my);
    }
    if sxx <= 0.0 || syy <= 0.0 {
        return 0.0;
    }
    sxy / (sxx * syy).sqrt()
}

/// Fitted damping ratio of a load train: a logistic map onto (0, 0.3].
fn damping_ratio(theta: f64) -> f64 {
    LOAD_TRAIN_DAMPING_RANGE.1 * logistic(theta)
}

/// The transformed parameter of a load-train damping ratio (a fit's start).
pub fn damping_theta(ratio: f64) -> f64 {
    logit(ratio / LOAD_TRAIN_DAMPING_RANGE.1)
}

fn logit(x: f64) -> f64 {
    (x / (1.0 - x)).ln()
}

fn logistic(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

impl Template {
    pub fn new(baseline: AugmentedModel, reference_temperature_c: f64) -> Template {
        let fit_chi = baseline.element.zener().is_some_and(|p| p.chi > 0.0);
        Template {
            baseline,
            fit_chi,
            fit_element: true,
            added: Vec::new(),
            reference_temperature_c,
            start_prefix: None,
            friction_dahl: false,
            time_shift_on_bound: false,
            drift_clock: DriftClock::TestOrder,
            clock_spans: [0.0; 3],
            clocks_like_order: Vec::new(),
        }
    }

    /// Sets the drift clocks' spans from the campaign's tests.
    pub fn with_clock_spans(mut self, data: &[CycleData]) -> Template {
        for (k, span) in self.clock_spans.iter_mut().enumerate() {
            *span = data.iter().map(|d| d.time.clocks[k]).fold(0.0, f64::max);
        }
        let order: Vec<f64> = data.iter().map(|d| d.time.clocks[0]).collect();
        self.clocks_like_order.clear();
        for k in 1..3 {
            let clock: Vec<f64> = data.iter().map(|d| d.time.clocks[k]).collect();
            if self.clock_spans[k] > 0.0 && correlation(&order, &clock) > 0.999 {
                self.clock_spans[k] = 0.0;
                self.clocks_like_order.push(DriftClock::ALL[k]);
            }
        }
        self
    }

    fn drift_span(&self) -> f64 {
        self.clock_spans[DriftClock::ALL
            .iter()
            .position(|c| *c == self.drift_clock)
            .unwrap_or(0)]
        .max(1e-300)
    }

    /// The model for the parameters of `fit`, with the standard errors the fit gives
    /// where an effect states one (a drift's rate).
    pub fn model_with_errors(&self, fit: &LmFit) -> AugmentedModel {
        let mut model = self.model(&fit.params);
        let errors = fit.standard_errors();
        let mut i = self.n_element_params();
        for kind in &self.added {
            if *kind == EffectKind::SpecimenDrift {
                let span = self.drift_span();
                for effect in &mut model.effects {
                    if let Effect::SpecimenDrift {
                        rate_standard_error,
                        ..
                    } = effect
                    {
                        *rate_standard_error = errors
                            .get(i)
                            .copied()
                            .flatten()
                            .map_or(f64::NAN, |e| e / span);
                    }
                }
            }
            i += kind.n_params();
        }
        model
    }

    /// The 95 % interval of each fitted parameter of the added effect `kind` (file
    /// units), from the covariance of `fit` (every parameter's correlation included).
    /// A parameter set by one fitted coordinate (a log or logistic map) maps that
    /// coordinate's interval `theta +- 1.96 se` through its map, so an interval reaches a
    /// range's bound where the data allow it; one set by several coordinates takes the
    /// delta method on its logarithm. Parameters no coordinate moves (a state such as
    /// `temperature_rise_k`, or a shift held on its bound) are left out; `ci95` is `None`
    /// when the covariance is singular (the data do not determine the fit at all).
    pub fn effect_intervals(&self, cv: &CrossValidation, kind: EffectKind) -> Vec<ParamInterval> {
        let fit = &cv.full_fit;
        let Some(position) = self.added.iter().position(|k| *k == kind) else {
            return Vec::new();
        };
        let offset = self.n_element_params()
            + self.added[..position]
                .iter()
                .map(|k| k.n_params())
                .sum::<usize>();
        let coords = offset..offset + kind.n_params();
        let params_at = |theta: &[f64]| -> Vec<(&'static str, f64)> {
            let model = self.model(theta);
            model
                .effects
                .iter()
                .find(|e| e.name() == kind.name())
                .map(|e| e.file_params(model.length_m))
                .unwrap_or_default()
        };
        let base = params_at(&fit.params);
        // Two covariances: the fit's own (noise, given the law), and the jackknife of the
        // fold refits, `(K - 1) / K sum (theta_k - mean)(theta_k - mean)^T`, which also
        // sees how far the fit moves when a fold's tests are left out (a law that fits
        // the data only roughly); each interval is the union of the two.
        let jackknife = (cv.fold_params.len() >= 3).then(|| {
            let k = cv.fold_params.len() as f64;
            let n = fit.params.len();
            let mean: Vec<f64> = (0..n)
                .map(|i| cv.fold_params.iter().map(|p| p[i]).sum::<f64>() / k)
                .collect();
            nalgebra::DMatrix::from_fn(n, n, |a, b| {
                (k - 1.0) / k
                    * cv.fold_params
                        .iter()
                        .map(|p| (p[a] - mean[a]) * (p[b] - mean[b]))
                        .sum::<f64>()
            })
        });
        let own = fit.covariance();
        let has_own = own.is_some();
        let covariances: Vec<nalgebra::DMatrix<f64>> = own.into_iter().chain(jackknife).collect();
        const H: f64 = 1e-4;
        const Z95: f64 = 1.96;
        // Derivative of every file parameter along each of the effect's coordinates.
        let gradients: Vec<Vec<f64>> = coords
            .clone()
            .map(|k| {
                let mut up = fit.params.clone();
                let mut down = fit.params.clone();
                up[k] += H;
                down[k] -= H;
                let (pu, pd) = (params_at(&up), params_at(&down));
                (0..base.len())
                    .map(|j| (pu[j].1 - pd[j].1) / (2.0 * H))
                    .collect()
            })
            .collect();
        let mut out = Vec::new();
        for (j, &(name, value)) in base.iter().enumerate() {
            let moving: Vec<usize> = (0..gradients.len())
                .filter(|&c| gradients[c][j].abs() > 1e-9 * value.abs().max(1e-300))
                .collect();
            if moving.is_empty() {
                // A state (no coordinate moves it at all) is left out; a parameter that a
                // coordinate moves once it is a unit away, or at the middle of its map, is
                // pinned on its map's bound (a springpot's order on its clamp): no
                // interval, and no measurement.
                let moves_further = coords.clone().any(|k| {
                    [fit.params[k] - 1.0, fit.params[k] + 1.0, 0.0]
                        .iter()
                        .any(|&at| {
                            let mut theta = fit.params.clone();
                            theta[k] = at;
                            (params_at(&theta)[j].1 - value).abs() > 1e-9 * value.abs().max(1e-300)
                        })
                });
                if moves_further {
                    out.push(ParamInterval {
                        name,
                        value,
                        ci95: None,
                        unit: f64::NAN,
                        on_bound: true,
                    });
                }
                continue;
            }
            let interval = |cov: &nalgebra::DMatrix<f64>| -> Option<(f64, f64)> {
                if let [c] = moving[..] {
                    let k = offset + c;
                    let se = cov[(k, k)];
                    if !(se.is_finite() && se >= 0.0) {
                        return None;
                    }
                    // Far beyond any map's useful range: the bound or infinity.
                    let half = (Z95 * se.sqrt()).min(60.0);
                    let mut ends = [f64::NAN; 2];
                    for (end, sign) in ends.iter_mut().zip([-1.0, 1.0]) {
                        let mut theta = fit.params.clone();
                        theta[k] += sign * half;
                        *end = params_at(&theta)[j].1;
                    }
                    Some((ends[0].min(ends[1]), ends[0].max(ends[1])))
                } else if value != 0.0 {
                    let mut variance = 0.0;
                    for &a in &moving {
                        for &b in &moving {
                            variance +=
                                gradients[a][j] * gradients[b][j] * cov[(offset + a, offset + b)];
                        }
                    }
                    let se_ln = variance.max(0.0).sqrt() / value.abs();
                    se_ln.is_finite().then(|| {
                        let factor = (Z95 * se_ln).min(60.0).exp();
                        let (a, b) = (value / factor, value * factor);
                        (a.min(b), a.max(b))
                    })
                } else {
                    None
                }
            };
            // The fit's own covariance must exist (else the fit is singular: no interval);
            // the union of the intervals the two covariances give.
            let ci95 = if !has_own {
                None
            } else {
                covariances
                    .iter()
                    .filter_map(interval)
                    .reduce(|(lo, hi), (a, b)| (lo.min(a), hi.max(b)))
            };
            // A parameter set by one coordinate: its change per unit of that coordinate
            // (the fit's natural unit of it: 10 kg of a moving mass, 0.1 ms of a delay,
            // 0.01 per degC of a temperature slope, a factor e of a log-mapped one).
            let unit = match moving[..] {
                [c] => gradients[c][j].abs(),
                _ => f64::NAN,
            };
            out.push(ParamInterval {
                name,
                value,
                ci95,
                unit,
                on_bound: false,
            });
        }
        out
    }

    /// The law variants to try when adding `kind`: both friction laws for
    /// `amplitude-friction` (an Iwan element obeys Masing's rule, a Dahl element does not;
    /// neither imitates the other closely), else the one template.
    pub fn variants_with_effect(&self, kind: EffectKind, fitted: Option<&[f64]>) -> Vec<Template> {
        let plain = self.with_effect(kind, fitted);
        match kind {
            EffectKind::AmplitudeFriction => {
                let mut dahl = plain.clone();
                dahl.friction_dahl = true;
                vec![plain, dahl]
            }
            EffectKind::TemperatureShift => {
                let mut on_bound = plain.clone();
                on_bound.time_shift_on_bound = true;
                vec![plain, on_bound]
            }
            // Every clock the campaign has (time only with `started_at`, energy only when
            // dissipated energy was measured); the data pick one.
            EffectKind::SpecimenDrift => DriftClock::ALL
                .iter()
                .enumerate()
                .filter(|(k, _)| self.clock_spans[*k] > 0.0)
                .map(|(_, &clock)| {
                    let mut t = plain.clone();
                    t.drift_clock = clock;
                    t
                })
                .collect(),
            _ => vec![plain],
        }
    }

    /// This template plus one effect, starting from `fitted` (this template's fit).
    pub fn with_effect(&self, kind: EffectKind, fitted: Option<&[f64]>) -> Template {
        let mut out = self.clone();
        out.added.push(kind);
        out.start_prefix = fitted.map(<[f64]>::to_vec);
        out
    }

    fn n_element_params(&self) -> usize {
        if !self.fit_element {
            return 0;
        }
        match self.baseline.element {
            ElementModel::KelvinVoigt(_) => 2,
            _ => 3 + usize::from(self.fit_chi),
        }
    }

    pub fn n_params(&self) -> usize {
        self.n_element_params() + self.added.iter().map(|k| k.n_params()).sum::<usize>()
    }

    /// Index in the transformed parameters of the first parameter of `added[index]`.
    pub fn effect_param_offset(&self, index: usize) -> usize {
        self.n_element_params()
            + self.added[..index.min(self.added.len())]
                .iter()
                .map(|k| k.n_params())
                .sum::<usize>()
    }

    /// Names of the fitted (transformed) parameters.
    pub fn param_names(&self) -> Vec<String> {
        let mut names: Vec<String> = Vec::new();
        if self.fit_element {
            match self.baseline.element {
                ElementModel::KelvinVoigt(_) => {
                    names.extend(["ln_k_n_per_m".into(), "ln_c_ns_per_m".into()])
                }
                _ => {
                    names.extend([
                        "ln_k1_0_n_per_m".into(),
                        "ln_k2_0_n_per_m".into(),
                        "ln_c2_0_ns_per_m".into(),
                    ]);
                    if self.fit_chi {
                        names.push("logit_chi".into());
                    }
                }
            }
        }
        for kind in &self.added {
            match kind {
                EffectKind::PreloadStiffening => names.push("logit_chi".into()),
                EffectKind::AmplitudeFriction => names.extend([
                    "ln_friction_stiffness".into(),
                    "ln_slip_force".into(),
                    if self.friction_dahl {
                        "logit_dahl_exponent".into()
                    } else {
                        "logit_slip_spread".into()
                    },
                ]),
                EffectKind::FractionalDamping => {
                    names.extend(["ln_springpot_coefficient".into(), "logit_alpha".into()])
                }
                EffectKind::TemperatureShift => {
                    names.extend(["100_log10_time_shift".into(), "100_ln_modulus_shift".into()])
                }
                EffectKind::ChannelDelay => names.push("force_lag_0.1ms".into()),
                EffectKind::MovingMass => names.push("mass_10kg".into()),
                EffectKind::LoadTrainResonance => names.extend([
                    "ln_natural_frequency_hz".into(),
                    "logit_damping_ratio".into(),
                ]),
                EffectKind::SpecimenDrift => names.push("drift_change_over_campaign".into()),
                EffectKind::SelfHeating => names.extend([
                    "ln_heat_transfer_w_per_k".into(),
                    "ln_thermal_time_constant_s".into(),
                ]),
                EffectKind::CyclicSoftening => {
                    names.extend(["logit_softening_limit".into(), "ln_force_scale_n".into()])
                }
            }
        }
        names
    }

    /// Start points: the baseline's values, and a few for the nonlinear effect parameters.
    pub fn starts(&self, data: &[CycleData]) -> Vec<Vec<f64>> {
        let mut base = Vec::new();
        let k_ref = match self.baseline.element {
            ElementModel::KelvinVoigt(p) => {
                if self.fit_element {
                    base.extend([p.k_n_per_m.ln(), p.c_ns_per_m.ln()]);
                }
                p.k_n_per_m
            }
            ElementModel::Consistent(p) | ElementModel::Paper(p) => {
                if self.fit_element {
                    base.extend([
                        p.k1_0_n_per_m.ln(),
                        p.k2_0_n_per_m.ln(),
                        p.c2_0_ns_per_m.ln(),
                    ]);
                    if self.fit_chi {
                        base.push(logit(p.chi / CHI_MAX));
                    }
                }
                p.k1_0_n_per_m
            }
        };
        let mut amplitudes: Vec<f64> = data
            .iter()
            .filter(|d| !d.is_history())
            .map(|d| d.displacement_amplitude_m())
            .collect();
        amplitudes.sort_by(f64::total_cmp);
        let z_amp = amplitudes
            .get(amplitudes.len() / 2)
            .copied()
            .unwrap_or(1e-4);
        let mut freqs: Vec<f64> = data.iter().map(|d| d.frequency_hz).collect();
        freqs.sort_by(f64::total_cmp);
        let omega_mid = 2.0 * PI * freqs.get(freqs.len() / 2).copied().unwrap_or(5.0);
        let f_max = freqs.last().copied().unwrap_or(20.0);
        let force_max_n = data
            .iter()
            .map(|d| d.time.peak_force_n)
            .fold(0.0, f64::max)
            .max(1e3);
        let power_max_w = data
            .iter()
            .map(|d| d.time.power_w())
            .fold(0.0, f64::max)
            .max(1e-3);
        let mut n_prefix_effects = 0;
        let mut prefix_start = None;
        if let Some(prefix) = &self.start_prefix {
            let mut n = self.n_element_params();
            for kind in &self.added {
                if n + kind.n_params() > prefix.len() {
                    break;
                }
                n += kind.n_params();
                n_prefix_effects += 1;
            }
            prefix_start = Some(prefix[..n].to_vec());
        }
        let options_of = |kind: &EffectKind| -> Vec<Vec<f64>> {
            match kind {
                EffectKind::PreloadStiffening => vec![vec![logit(0.2 / CHI_MAX)]],
                EffectKind::AmplitudeFriction if self.friction_dahl => {
                    let stiffness = 0.3 * k_ref;
                    vec![
                        vec![
                            stiffness.ln(),
                            (stiffness * 0.2 * z_amp).ln(),
                            dahl_theta(1.0),
                        ],
                        vec![
                            stiffness.ln(),
                            (stiffness * 0.6 * z_amp).ln(),
                            dahl_theta(0.3),
                        ],
                        vec![
                            stiffness.ln(),
                            (stiffness * 0.6 * z_amp).ln(),
                            dahl_theta(2.0),
                        ],
                    ]
                }
                EffectKind::AmplitudeFriction => {
                    let stiffness = 0.3 * k_ref;
                    let spread = |sigma: f64| logit(sigma / SLIP_SPREAD_MAX);
                    vec![
                        vec![stiffness.ln(), (stiffness * 0.2 * z_amp).ln(), spread(1.0)],
                        vec![stiffness.ln(), (stiffness * 0.6 * z_amp).ln(), spread(0.3)],
                        vec![stiffness.ln(), (stiffness * 0.6 * z_amp).ln(), spread(1.5)],
                    ]
                }
                EffectKind::FractionalDamping => [0.3, 0.7]
                    .iter()
                    .map(|&alpha: &f64| {
                        vec![(0.05 * k_ref / omega_mid.powf(alpha)).ln(), logit(alpha)]
                    })
                    .collect(),
                EffectKind::TemperatureShift => vec![vec![0.0, 0.0]],
                EffectKind::ChannelDelay => vec![vec![0.0]],
                EffectKind::MovingMass => vec![vec![0.0]],
                EffectKind::LoadTrainResonance => [3.0, 8.0]
                    .iter()
                    .map(|&x: &f64| vec![(x * f_max).clamp(20.0, 4000.0).ln(), damping_theta(0.05)])
                    .collect(),
                EffectKind::SpecimenDrift => vec![vec![0.0]],
                // A rise of about 1 K and of 10 K at the most dissipative test, short and
                // long memory. (From 1 K alone, a weak heating beside friction settled on a
                // 1.3 s memory and a tenth of its rise, which held out worse than the truth.)
                EffectKind::SelfHeating => [(1.0, 60.0), (1.0, 1000.0), (10.0, 200.0)]
                    .iter()
                    .map(|&(rise_k, tau): &(f64, f64)| vec![(power_max_w / rise_k).ln(), tau.ln()])
                    .collect(),
                // A few per cent, setting in over a fifth and over half the largest load.
                EffectKind::CyclicSoftening => [0.2, 0.5]
                    .iter()
                    .map(|&x: &f64| {
                        vec![
                            logit(0.05 / SOFTENING_LIMIT_MAX),
                            (x * force_max_n).max(100.0).ln(),
                        ]
                    })
                    .collect(),
            }
        };
        // `first_only`: the first start option of each kind (an effect started afresh
        // beside a fit that already holds it needs one start, not its whole grid).
        let extend_with = |starts: Vec<Vec<f64>>, kinds: &[EffectKind], first_only: bool| {
            let mut starts = starts;
            for kind in kinds {
                let mut options = options_of(kind);
                if first_only {
                    options.truncate(1);
                }
                starts = starts
                    .iter()
                    .flat_map(|s| {
                        options.iter().map(move |o| {
                            let mut v = s.clone();
                            v.extend(o);
                            v
                        })
                    })
                    .collect();
            }
            starts
        };
        let extend =
            |starts: Vec<Vec<f64>>, kinds: &[EffectKind]| extend_with(starts, kinds, false);
        match prefix_start {
            None => extend(vec![base], &self.added),
            Some(prefix) => {
                let mut starts = extend(vec![prefix], &self.added[n_prefix_effects..]);
                if n_prefix_effects > 0 {
                    // The previous fit can sit on a bound of an effect parameter (a
                    // springpot exponent at 1 standing in for a force-channel lead that is
                    // added now) where the transformed gradient vanishes; also start every
                    // effect afresh so such a fit can be left (the effects already fitted
                    // from their first start only: their whole grids multiplied out made
                    // a third round's fit 14 starts long).
                    let afresh = extend_with(vec![base], &self.added[..n_prefix_effects], true);
                    starts.extend(extend(afresh, &self.added[n_prefix_effects..]));
                }
                starts
            }
        }
    }

    /// The model for transformed parameters `theta`.
    pub fn model(&self, theta: &[f64]) -> AugmentedModel {
        let mut model = self.baseline.clone();
        let mut i = 0;
        if self.fit_element {
            match &mut model.element {
                ElementModel::KelvinVoigt(p) => {
                    p.k_n_per_m = theta[0].exp();
                    p.c_ns_per_m = theta[1].exp();
                    i = 2;
                }
                ElementModel::Consistent(p) | ElementModel::Paper(p) => {
                    p.k1_0_n_per_m = theta[0].exp();
                    p.k2_0_n_per_m = theta[1].exp();
                    p.c2_0_ns_per_m = theta[2].exp();
                    i = 3;
                    if self.fit_chi {
                        p.chi = CHI_MAX * logistic(theta[3]);
                        i = 4;
                    }
                }
            }
        }
        for kind in &self.added {
            let effect = match kind {
                EffectKind::PreloadStiffening => Effect::PreloadStiffening {
                    chi: CHI_MAX * logistic(theta[i]),
                    p0_n: model.element.zener().map_or(64e3, |p| p.p0_n),
                },
                EffectKind::AmplitudeFriction => Effect::AmplitudeFriction {
                    stiffness_n_per_m: theta[i].exp(),
                    slip_force_n: theta[i + 1].exp(),
                    law: if self.friction_dahl {
                        FrictionLaw::Dahl {
                            exponent: dahl_exponent(theta[i + 2]),
                        }
                    } else {
                        FrictionLaw::Iwan {
                            slip_spread: SLIP_SPREAD_MAX * logistic(theta[i + 2]),
                        }
                    },
                },
                EffectKind::FractionalDamping => Effect::FractionalDamping {
                    coefficient_ns_alpha_per_m: theta[i].exp(),
                    alpha: logistic(theta[i + 1]).clamp(1e-3, 0.999),
                },
                EffectKind::TemperatureShift => Effect::TemperatureShift {
                    reference_temperature_c: self.reference_temperature_c,
                    operating_temperature_c: self.reference_temperature_c,
                    log10_time_shift_per_c: if self.time_shift_on_bound {
                        0.0
                    } else {
                        theta[i] / 100.0
                    },
                    ln_modulus_shift_per_c: theta[i + 1] / 100.0,
                },
                EffectKind::ChannelDelay => Effect::ChannelDelay {
                    force_lag_s: theta[i] * 1e-4,
                },
                EffectKind::MovingMass => Effect::MovingMass {
                    mass_kg: theta[i] * 10.0,
                },
                EffectKind::LoadTrainResonance => Effect::LoadTrainResonance {
                    natural_frequency_hz: theta[i].clamp(-50.0, 50.0).exp(),
                    damping_ratio: damping_ratio(theta[i + 1]),
                },
                EffectKind::SpecimenDrift => Effect::SpecimenDrift {
                    clock: self.drift_clock,
                    rate_per_unit: theta[i] / self.drift_span(),
                    rate_standard_error: 0.0,
                    clock_position: 0.0,
                },
                EffectKind::CyclicSoftening => Effect::CyclicSoftening {
                    softening_limit: SOFTENING_LIMIT_MAX * logistic(theta[i]),
                    force_scale_n: theta[i + 1].clamp(-50.0, 50.0).exp(),
                    max_force_n: 0.0,
                },
                EffectKind::SelfHeating => {
                    let h = theta[i].clamp(-50.0, 50.0).exp();
                    Effect::SelfHeating {
                        heat_transfer_w_per_k: h,
                        heat_capacity_j_per_k: h * theta[i + 1].clamp(-50.0, 50.0).exp(),
                        temperature_rise_k: 0.0,
                    }
                }
            };
            i += kind.n_params();
            model.effects.retain(|e| e.name() != effect.name());
            model.effects.push(effect);
        }
        model
    }

    /// Residual vector over `data`.
    pub fn residuals(&self, theta: &[f64], data: &[&CycleData]) -> Vec<f64> {
        let model = self.model(theta);
        let mut out = Vec::with_capacity(data.len() * 2 * FIT_HARMONICS);
        for d in data {
            out.extend(test_residuals(&model, d));
        }
        out
    }
}

/// Fits a template on `data` from each of `starts`; returns the best fit.
pub fn fit_template(
    template: &Template,
    data: &[&CycleData],
    starts: &[Vec<f64>],
    max_iterations: usize,
) -> LmFit {
    let mut best: Option<LmFit> = None;
    for start in starts {
        let fit = levenberg_marquardt(
            |theta| template.residuals(theta, data),
            start,
            max_iterations,
        );
        if best.as_ref().is_none_or(|b| fit.sse < b.sse) {
            best = Some(fit);
        }
    }
    best.expect("at least one start")
}

/// Cross-validated errors of a template.
#[derive(Debug, Clone)]
pub struct CrossValidation {
    /// Fit on all tests (used for the model file and in-sample numbers).
    pub full_fit: LmFit,
    /// Held-out relative squared residual of each test (fit without its fold); for a
    /// screened candidate, the in-sample residual of the full fit instead.
    pub held_out_error: Vec<f64>,
    /// The fold refits were skipped: the full fit's in-sample residuals (optimistic)
    /// already showed it cannot qualify.
    pub screened: bool,
    /// Each fold's refit (without that fold's tests), in fold order; empty when screened.
    pub fold_params: Vec<Vec<f64>>,
}

impl CrossValidation {
    /// Raw held-out residual (noise included): `sqrt(mean_i e_i)`.
    pub fn gap(&self) -> f64 {
        rms_gap(&self.held_out_error)
    }
}

pub fn rms_gap(errors: &[f64]) -> f64 {
    (errors.iter().sum::<f64>() / errors.len().max(1) as f64).sqrt()
}

/// Fold of each test: tests sorted by (temperature, preload, amplitude, frequency) and
/// dealt round-robin, so every fold spans the design.
pub fn assign_folds(data: &[CycleData], n_folds: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..data.len()).collect();
    order.sort_by(|&a, &b| {
        let key = |d: &CycleData| [d.temperature_c, d.preload_n, d.amplitude_n, d.frequency_hz];
        key(&data[a])
            .iter()
            .zip(key(&data[b]).iter())
            .map(|(x, y)| x.total_cmp(y))
            .find(|o| o.is_ne())
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    let mut folds = vec![0; data.len()];
    for (rank, &i) in order.iter().enumerate() {
        folds[i] = rank % n_folds.max(1);
    }
    folds
}

/// Runs `work` on every item with up to `n_threads` threads, items handed out one at a
/// time (so one slow item does not hold a whole share back). Results are in item order and
/// do not depend on the thread count.
pub fn run_parallel<T: Sync, R: Send>(
    items: &[T],
    n_threads: usize,
    work: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Mutex;
    let next = AtomicUsize::new(0);
    let results: Vec<Mutex<Option<R>>> = items.iter().map(|_| Mutex::new(None)).collect();
    let n_workers = n_threads.clamp(1, items.len().max(1));
    std::thread::scope(|scope| {
        for _ in 0..n_workers {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(item) = items.get(i) else { break };
                let result = work(item);
                *results[i]
                    .lock()
                    .expect("no worker panics while holding it") = Some(result);
            });
        }
    });
    results
        .into_iter()
        .map(|m| {
            m.into_inner()
                .expect("no worker panicked")
                .expect("every item was processed")
        })
        .collect()
}

/// Fits on all data (multi-start), then refits without each fold (starting from the full
/// fit, folds in parallel) and predicts the fold.
pub fn cross_validate(
    template: &Template,
    data: &[CycleData],
    folds: &[usize],
    n_folds: usize,
    max_iterations: usize,
    n_threads: usize,
) -> CrossValidation {
    cross_validate_screened(
        template,
        data,
        folds,
        n_folds,
        max_iterations,
        n_threads,
        None,
    )
}

/// In-sample relative squared residual of each test under `model`.
pub fn in_sample_errors(model: &AugmentedModel, data: &[CycleData]) -> Vec<f64> {
    data.iter().map(|d| relative_error(model, d)).collect()
}

/// A screen on a candidate's in-sample errors: true when it cannot qualify held out.
pub type Screen<'a> = dyn Fn(&[f64]) -> bool + 'a;

/// `cross_validate`, but after the full fit `cannot_qualify` (when given) sees its
/// in-sample errors; when it says so, the fold refits are skipped and the in-sample errors
/// stand in (`screened`).
pub fn cross_validate_screened(
    template: &Template,
    data: &[CycleData],
    folds: &[usize],
    n_folds: usize,
    max_iterations: usize,
    n_threads: usize,
    cannot_qualify: Option<&Screen<'_>>,
) -> CrossValidation {
    let all: Vec<&CycleData> = data.iter().collect();
    let full_fit = fit_template(template, &all, &template.starts(data), max_iterations);
    if let Some(cannot_qualify) = cannot_qualify {
        let in_sample = in_sample_errors(&template.model(&full_fit.params), data);
        if cannot_qualify(&in_sample) {
            return CrossValidation {
                full_fit,
                held_out_error: in_sample,
                screened: true,
                fold_params: Vec::new(),
            };
        }
    }
    let fold_ids: Vec<usize> = (0..n_folds).collect();
    let fold_errors = run_parallel(&fold_ids, n_threads, |&fold| {
        let train: Vec<&CycleData> = data
            .iter()
            .zip(folds)
            .filter(|(_, &f)| f != fold)
            .map(|(d, _)| d)
            .collect();
        if train.len() == data.len() {
            return (Vec::new(), None);
        }
        // From the full fit, a fold's optimum is a short way off: half the iterations.
        let fit = fit_template(
            template,
            &train,
            std::slice::from_ref(&full_fit.params),
            (max_iterations / 2).max(10),
        );
        let model = template.model(&fit.params);
        let errors = data
            .iter()
            .enumerate()
            .filter(|(i, _)| folds[*i] == fold)
            .map(|(i, d)| (i, relative_error(&model, d)))
            .collect::<Vec<_>>();
        (errors, Some(fit.params))
    });
    let mut held_out_error = vec![0.0; data.len()];
    let mut fold_params = Vec::new();
    for (errors, params) in fold_errors {
        for (i, e) in errors {
            held_out_error[i] = e;
        }
        fold_params.extend(params);
    }
    CrossValidation {
        full_fit,
        held_out_error,
        screened: false,
        fold_params,
    }
}

#[cfg(test)]
mod tests {
    use super::{CrossValidation, EffectKind, LmFit, ParamInterval, Template};
    use crate::model::effects::AugmentedModel;
    use crate::model::params::{ElementModel, ZenerParams};

    /// The cycle `predict_cycle_with_waveform` returns is the periodic one: a plain stepper
    /// driven by the same displacement cycle for 600 cycles (30 s, 60 relaxation times;
    /// the prediction's warm-up with its jump is 4 cycles) gives the same force, for an
    /// element whose relaxation is slow against the period (0.5 s at 20 Hz, where the
    /// 40 cycles the warm-up used before left e^-4 of the start's transient), alone and
    /// with each effect that has states of its own.
    #[test]
    fn the_predicted_cycle_is_the_periodic_one() {
        use super::{model_for_test, predict_cycle_with_waveform, CycleData, TestTime};
        use crate::model::effects::{Effect, FrictionLaw, ModelStepper, StepperMode};
        let mut element = ZenerParams::paper_table3(0.75);
        element.c2_0_ns_per_m = 0.5 * element.k2_0_n_per_m;
        let m = super::SAMPLES_PER_CYCLE;
        let mut harmonics = [(0.0, 0.0); super::N_HARMONICS];
        harmonics[0] = (60e-6, 10e-6);
        harmonics[1] = (3e-6, 0.0);
        let data = CycleData {
            id: "T".into(),
            frequency_hz: 20.0,
            preload_n: 20e3,
            amplitude_n: 4e3,
            temperature_c: 23.0,
            force_mean_n: 20e3,
            displacement_harmonics_m: harmonics,
            force_harmonics_n: [(0.0, 0.0); super::N_HARMONICS],
            scale_n: 4e3,
            noise_relative: 1e-8,
            noise_smoothed: 1e-8,
            duration_s: 1.0,
            weight: 1.0,
            order: 0.0,
            history: None,
            time: TestTime::default(),
        };
        let cases = [
            None,
            Some(Effect::CyclicSoftening {
                softening_limit: 0.2,
                force_scale_n: 2e3,
                max_force_n: 0.0,
            }),
            Some(Effect::FractionalDamping {
                coefficient_ns_alpha_per_m: 2e6,
                alpha: 0.3,
            }),
            Some(Effect::AmplitudeFriction {
                stiffness_n_per_m: 20e6,
                slip_force_n: 800.0,
                law: FrictionLaw::Iwan { slip_spread: 0.5 },
            }),
        ];
        for effect in cases {
            let model = AugmentedModel {
                element: ElementModel::Consistent(element),
                length_m: 0.75,
                effects: effect.into_iter().collect(),
            };
            let (_, waveform, z_cycle) = predict_cycle_with_waveform(&model, &data);
            let model_t = model_for_test(&model, &data);
            let dt_s = 1.0 / (20.0 * m as f64);
            let mut reference =
                ModelStepper::new(&model_t, StepperMode::Emulation, dt_s, z_cycle[0])
                    .with_frozen_temperature();
            for _ in 0..600 {
                for k in 1..=m {
                    reference.step(z_cycle[k % m]);
                }
            }
            let swing = waveform.iter().cloned().fold(f64::MIN, f64::max)
                - waveform.iter().cloned().fold(f64::MAX, f64::min);
            assert!(swing > 1e3, "{swing}");
            // The springpot's slowest branches (a period takes under 1e-6 off them) keep
            // their state and are still moving after 30 s: 9e-6 of the swing here (the
            // 40-cycle warm-up before the jump: 2.1e-4; the other cases 3e-5 to 9e-5).
            let tolerance = if matches!(effect, Some(Effect::FractionalDamping { .. })) {
                2e-5
            } else {
                1e-9
            };
            for k in 1..=m {
                let idx = k % m;
                let (f, _) = reference.step(z_cycle[idx]);
                assert!(
                    (f - waveform[idx]).abs() < tolerance * swing,
                    "{:?} sample {idx}: {f} against {} (swing {swing})",
                    model.effects.first().map(|e| e.name()),
                    waveform[idx]
                );
            }
        }
    }

    #[test]
    fn a_fit_run_off_to_its_numerical_limit_is_said_so_not_quoted() {
        use super::{OutOfRange, LOAD_TRAIN_DAMPING_RANGE, LOAD_TRAIN_FREQUENCY_RANGE_HZ};
        let runaway = OutOfRange {
            kind: EffectKind::LoadTrainResonance,
            param: "natural_frequency_hz",
            value: 50f64.exp(),
            range: LOAD_TRAIN_FREQUENCY_RANGE_HZ,
            unit: "Hz",
        };
        let text = runaway.to_string();
        assert!(text.contains("running off to infinity"), "{text}");
        assert!(!text.contains("5.1847e21"), "{text}");
        let to_zero = OutOfRange {
            param: "damping_ratio",
            value: 3.4e-285,
            range: LOAD_TRAIN_DAMPING_RANGE,
            unit: "",
            ..runaway
        };
        assert!(to_zero.to_string().contains("running off to zero"));
        let finite = OutOfRange {
            value: 7000.0,
            ..runaway
        };
        assert_eq!(
            finite.to_string(),
            "fits only with natural_frequency_hz = 7.0000e3, outside its range (<= 5000 Hz)"
        );
    }

    /// A springpot whose order sits on its clamp (0.999: the logistic coordinate far out)
    /// is reported on its bound, with no interval and not determined; its coefficient gets
    /// the interval its coordinate's standard error maps to (`exp(theta +- 1.96 se)`).
    #[test]
    fn an_order_on_its_clamp_is_on_its_bound_and_its_coefficient_has_an_interval() {
        let baseline = AugmentedModel {
            element: ElementModel::Consistent(ZenerParams::paper_table3(0.75)),
            length_m: 0.75,
            effects: Vec::new(),
        };
        let mut template = Template::new(baseline, 23.0);
        template.added = vec![EffectKind::FractionalDamping];
        let n = template.n_params();
        let mut params = vec![0.0; n];
        params[..4].copy_from_slice(&[62e6f64.ln(), 9.6e6f64.ln(), 0.7e6f64.ln(), 0.0]);
        params[n - 2] = 1e5f64.ln();
        params[n - 1] = 30.0; // logistic(30) = 1 - 1e-13: clamped at 0.999
                              // Unit J^T J and sigma^2 = SSE / (n_residuals - n) = 1 / 100: the coefficient's
                              // coordinate has se = 0.1.
        let n_residuals = 100 + n;
        let fit = LmFit {
            params,
            sse: 1.0,
            n_residuals,
            jtj: nalgebra::DMatrix::identity(n, n),
            iterations: 1,
        };
        let cv = CrossValidation {
            full_fit: fit,
            held_out_error: Vec::new(),
            screened: false,
            fold_params: Vec::new(),
        };
        let intervals = template.effect_intervals(&cv, EffectKind::FractionalDamping);
        let alpha = intervals
            .iter()
            .find(|i| i.name == "alpha")
            .expect("alpha listed");
        assert!(
            alpha.on_bound && alpha.ci95.is_none() && !alpha.determined(),
            "{alpha:?}"
        );
        let coefficient = intervals
            .iter()
            .find(|i| i.name != "alpha")
            .expect("the coefficient");
        let (lo, hi) = coefficient.ci95.expect("an interval");
        let half: f64 = 1.96 * 0.1; // se = sqrt(1 / 100)
        assert!(
            (hi / coefficient.value - half.exp()).abs() < 1e-6,
            "{coefficient:?}"
        );
        assert!(
            (coefficient.value / lo - half.exp()).abs() < 1e-6,
            "{coefficient:?}"
        );
        assert!(coefficient.determined() && !coefficient.on_bound);
    }

    fn interval(value: f64, lo: f64, hi: f64) -> ParamInterval {
        ParamInterval {
            name: "x",
            value,
            ci95: Some((lo, hi)),
            unit: 0.01,
            on_bound: false,
        }
    }

    #[test]
    fn an_interval_is_determined_within_a_decade_or_about_zero() {
        assert!(interval(1.0, 0.5, 4.9).determined());
        assert!(!interval(1.0, 0.5, 5.1).determined());
        assert!(interval(-1.0, -4.9, -0.5).determined());
        assert!(!interval(-1.0, -5.1, -0.5).determined());
        let about_zero = interval(1e-6, -8e-4, 8e-4);
        assert!(about_zero.determined() && about_zero.consistent_with_zero());
        // Across zero and wider than a unit of its coordinate (a mass of -50 to 400 kg,
        // fitted in units of 10 kg): not determined.
        let mass = ParamInterval {
            unit: 10.0,
            ..interval(170.0, -50.0, 400.0)
        };
        assert!(!mass.determined() && mass.consistent_with_zero());
        assert!(!interval(1.0, 0.5, 2.0).consistent_with_zero());
        assert!(!interval(1.0, 0.5, f64::INFINITY).determined());
        let singular = ParamInterval {
            ci95: None,
            ..interval(1.0, 0.0, 0.0)
        };
        assert!(!singular.determined());
    }
}
