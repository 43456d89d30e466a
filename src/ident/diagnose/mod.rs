//! The discrepancy workflow (SPEC 5): calibrate the baseline, measure the held-out gap,
//! try each library effect, name one only on held-out evidence, repeat.
//!
//! The error of a model on a test is the relative residual of the force at the test
//! frequency: the steady-state force simulated from the measured displacement cycle
//! against the measured one, `e_i = |F_sim,1 - F_1|^2 / |F_1|^2` (single-bin DFT over
//! whole cycles, SPEC 4), with every `e_i` held out: K-fold cross-validation over tests,
//! folds dealt across the design. Each test also carries `nu_i`, the part of `e_i` that
//! measurement noise alone produces (estimated from the DFT bins next to the test
//! frequency, see `campaign::analyse_cycle`), and a precision weight `w_i` (inverse of the
//! campaign's smoothed noise level, `fit::assign_noise_weights`). The gap is the held-out
//! RMS residual in excess of noise, `sqrt(mean_w e_i - mean_w nu_i)` with weighted means,
//! floored at a tenth of the noise RMS (below that it is not measurable); the raw
//! `sqrt(mean_w e_i)` and the noise RMS are reported next to it.
//!
//! The weights matter: a test's realised noise scatters like an exponential variable
//! around `nu_i`, so in a plain mean the few noisiest tests (small amplitude, short
//! records) would decide the gap of the whole campaign by chance.
//!
//! Naming rule, per round of greedy forward selection: a candidate (current model plus one
//! effect, refitted on the training folds) is named only if
//! 1. its score, the held-out gap over the current model's, times 1 + 0.02 per extra
//!    parameter, is below 0.6,
//! 2. its raw held-out residual (noise included), penalised the same way, is below 0.95 x
//!    the current model's,
//! 3. the paired one-sided Wilcoxon signed-rank test of per-test held-out errors
//!    (current minus candidate, each times the test's precision weight) gives z > 2.3
//!    (p < 0.01), and
//! 4. it lowers the (weighted) held-out error in at least K - 1 of the K folds, and
//! 5. what it explains is material: `sqrt(gap_current^2 - gap_candidate^2)` exceeds 1e-3
//!    (0.1 % of the force at the test frequency). Below that, differences between
//!    integration schemes or model forms can be "explained" by any flexible effect.
//!
//! Held-out evidence does not assume white noise: coloured noise inflates the spread of
//! the per-test differences, not their sign, and an effect that only fits noise does not
//! predict held-out tests. Among qualifying candidates the lowest score wins. Effects
//! whose required variation is absent from the campaign are reported as not identifiable
//! and not tried.
//!
//! Must not: do I/O (`report` writes files; progress goes through a callback).

pub mod effect_plots;
pub mod report;
pub mod rivals;
pub mod run;
pub mod verdict;

use crate::ident::fit::{
    assign_folds, correlation, cross_validate, cross_validate_screened, in_sample_errors,
    run_parallel, CrossValidation, CycleData, EffectKind, OutOfRange, Template,
};
use crate::model::effects::{AugmentedModel, Effect};
use crate::model::params::ElementModel;
use rivals::{
    channel_delay_check, law_broken, resonance_in_pair_place, resonance_pair_note, springpot_check,
};
pub use rivals::{
    harmonic_frequencies, maxwell_rival, springpot_orders_by_band, BandOrders, MaxwellRival,
};
use verdict::{history_beyond_noise, verdict, Verdict};

/// Tunables of the naming rule (defaults documented in the module docs).
#[derive(Debug, Clone, Copy)]
pub struct DiagnoseOptions {
    pub n_folds: usize,
    pub max_iterations: usize,
    pub n_threads: usize,
    pub max_score: f64,
    pub max_raw_ratio: f64,
    pub penalty_per_param: f64,
    pub min_wilcoxon_z: f64,
    /// Smallest held-out gap an effect must explain, `sqrt(gap_before^2 - gap_after^2)`.
    pub min_explained_gap: f64,
    /// Test order is clock time (`started_at` on every test), else campaign order.
    pub order_is_clock: bool,
    /// Skip the fold refits of a candidate whose in-sample fit shows it cannot qualify.
    pub screen: bool,
}

/// How far the in-sample score of a screened-out candidate is above the naming score at
/// least (`score * SCREEN_MARGIN >= max_score`): held-out errors are larger than in-sample
/// ones, the candidate's (more parameters) usually more than the current model's.
pub const SCREEN_MARGIN: f64 = 0.8;

impl Default for DiagnoseOptions {
    fn default() -> DiagnoseOptions {
        DiagnoseOptions {
            n_folds: 5,
            max_iterations: 40,
            n_threads: 2,
            max_score: 0.6,
            max_raw_ratio: 0.95,
            penalty_per_param: 0.02,
            min_wilcoxon_z: 2.3,
            min_explained_gap: 1e-3,
            order_is_clock: false,
            screen: true,
        }
    }
}

/// One candidate evaluated in one round.
#[derive(Debug, Clone)]
pub struct CandidateResult {
    pub kind: EffectKind,
    pub round: usize,
    pub cv: CrossValidation,
    /// Raw held-out residual (noise included, precision-weighted).
    pub raw_gap: f64,
    /// Candidate's held-out gap (noise excluded) over the current model's.
    pub gap_ratio: f64,
    /// Same for the raw held-out residual (noise included).
    pub raw_ratio: f64,
    /// `gap_ratio (1 + penalty * n_params)`: the score (lower is better; < 1 is better).
    pub score: f64,
    pub wilcoxon_z: f64,
    pub folds_improved: usize,
    /// Whether the history tests alone show the improvement (see `Scoring::compare`).
    pub history_evidence: bool,
    pub qualifies: bool,
    /// The fit on all tests leaves the effect's physical range: never named.
    pub out_of_range: Option<OutOfRange>,
    /// Whether it would qualify but for its physical range (a finding worth reporting:
    /// the best fit of this effect is unphysical, so its cause is something else).
    pub would_qualify: bool,
    /// Its law does not hold across the tests (`law_broken`): never named, and,
    /// like a fit outside the range, a sign of a cause outside the library.
    pub law_broken: Option<String>,
    /// The candidate fitted on all tests.
    pub model: AugmentedModel,
    /// The template it was fitted with (the friction law chosen, for `amplitude-friction`).
    pub template: Template,
    /// How the law was chosen among its variants (a drift's clock), when it has several.
    pub law_note: Option<String>,
    /// Named alone, it shrank the gap it faced less than `MIN_STEP_SHRINK` and a residual
    /// beyond noise remained: taken back out as a likely stand-in for a cause outside the
    /// library (`take_back_stand_in`), with why.
    pub stand_in: Option<String>,
}

impl CandidateResult {
    /// Why its best fit cannot be the cause: outside its range, or a law that does not
    /// hold across the tests (empty when neither).
    pub fn unphysical_text(&self) -> String {
        match (&self.out_of_range, &self.law_broken) {
            (Some(o), _) => o.to_string(),
            (None, Some(b)) => b.clone(),
            (None, None) => String::new(),
        }
    }
}

/// Why an effect was not tried.
#[derive(Debug, Clone)]
pub struct NotTried {
    pub kind: EffectKind,
    pub reason: String,
    /// True when the campaign lacks the variation the effect needs (SPEC 5
    /// `not_identifiable`); false when the baseline already has the effect.
    pub not_identifiable: bool,
}

/// Everything a diagnosis found.
#[derive(Debug, Clone)]
pub struct Diagnosis {
    pub reference_temperature_c: f64,
    pub folds: Vec<usize>,
    pub baseline_template: Template,
    pub baseline_cv: CrossValidation,
    pub baseline_model: AugmentedModel,
    pub final_template: Template,
    pub final_cv: CrossValidation,
    pub final_model: AugmentedModel,
    pub named: Vec<EffectKind>,
    pub rounds: Vec<Vec<CandidateResult>>,
    /// Effects named and then replaced by a pair (`swap_last_named`), one sentence each.
    pub replaced: Vec<String>,
    pub not_tried: Vec<NotTried>,
    /// Held-out gaps in excess of noise (the SPEC 5 `gap_before` / `gap_after`).
    pub gap_before: f64,
    pub gap_after: f64,
    /// Raw held-out RMS residuals (noise included) and the noise floor RMS.
    pub raw_gap_before: f64,
    pub raw_gap_after: f64,
    pub noise_floor: f64,
    /// What remains unexplained, the trend with test order, repeated tests.
    pub verdict: Verdict,
    /// Ids of the history tests used.
    pub history_ids: Vec<String>,
    /// Harmonic tests whose first cycles were split off as history tests, and why (set by
    /// the caller that split them, `first_cycles::split_first_cycles`; empty otherwise).
    pub first_cycles_used: Vec<crate::ident::first_cycles::FirstCyclesUse>,
}

/// Precision-weighted mean `sum w_i x_i / sum w_i` (weights `CycleData::weight`).
fn weighted_mean(values: impl Iterator<Item = f64>, data: &[CycleData]) -> f64 {
    let (sum, weight) = values.zip(data).fold((0.0, 0.0), |(s, w), (x, d)| {
        (s + d.weight * x, w + d.weight)
    });
    sum / weight.max(1e-300)
}

/// Held-out gap in excess of noise: `sqrt(mean_w e_i - mean_w nu_i)` (precision-weighted
/// means), floored at a tenth of the noise RMS.
pub fn excess_gap(errors: &[f64], data: &[CycleData]) -> f64 {
    let mean_error = weighted_mean(errors.iter().copied(), data);
    let mean_noise = weighted_mean(data.iter().map(|d| d.noise_relative), data);
    (mean_error - mean_noise)
        .max(0.01 * mean_noise)
        .max(1e-300)
        .sqrt()
}

/// Raw held-out residual (noise included): `sqrt(mean_w e_i)`.
pub fn raw_gap(errors: &[f64], data: &[CycleData]) -> f64 {
    weighted_mean(errors.iter().copied(), data).sqrt()
}

/// RMS of the estimated noise floor `sqrt(mean_w nu_i)`.
pub fn noise_floor(data: &[CycleData]) -> f64 {
    weighted_mean(data.iter().map(|d| d.noise_relative), data).sqrt()
}

/// Distinct levels with a relative tolerance.
fn levels(values: impl Iterator<Item = f64>, tolerance: f64) -> Vec<f64> {
    let mut v: Vec<f64> = values.collect();
    v.sort_by(f64::total_cmp);
    let mut out: Vec<f64> = Vec::new();
    for x in v {
        if out
            .last()
            .is_none_or(|&l| (x - l).abs() > tolerance * l.abs().max(1.0))
        {
            out.push(x);
        }
    }
    out
}

/// Whether the campaign varies what an effect needs; `Err(reason)` if not.
///
/// A history test counts with what it spans: its force range (preloads from its lowest
/// to its highest force, amplitudes from nothing up to its half range) and its band
/// (frequencies from one over its duration up to the band edge).
pub fn identifiability(kind: EffectKind, data: &[CycleData]) -> Result<(), String> {
    let spans =
        |f: &dyn Fn(&CycleData) -> Vec<f64>| -> Vec<f64> { data.iter().flat_map(f).collect() };
    let freqs = levels(
        spans(&|d| match &d.history {
            Some(h) => vec![
                (1.0 / h.duration_s).max(0.05 * h.band_hz),
                h.frequency_centroid_hz,
                h.band_hz,
            ],
            None => vec![d.frequency_hz],
        })
        .into_iter(),
        0.02,
    );
    let f_span = freqs.last().unwrap_or(&1.0) / freqs.first().unwrap_or(&1.0);
    match kind {
        EffectKind::PreloadStiffening => {
            let preloads = levels(
                spans(&|d| match &d.history {
                    Some(h) => vec![h.force_min_n, h.force_max_n],
                    None => vec![d.force_mean_n],
                })
                .into_iter(),
                0.1,
            );
            if preloads.len() < 2 {
                return Err("all tests at one preload".into());
            }
        }
        EffectKind::AmplitudeFriction => {
            // The force amplitude is what the rig varies; displacement amplitudes also vary
            // with stiffness (preload, frequency), which does not separate friction.
            let force_amps = levels(
                spans(&|d| match &d.history {
                    Some(h) => vec![0.1 * h.swing_n(), h.swing_n()],
                    None => vec![d.amplitude_n],
                })
                .into_iter(),
                0.05,
            );
            let span =
                force_amps.last().unwrap_or(&1.0) / force_amps.first().unwrap_or(&1.0).max(1e-300);
            if force_amps.len() < 2 || span < 1.1 {
                return Err(
                    "no amplitude variation (one force amplitude, or levels within 10 %)".into(),
                );
            }
        }
        EffectKind::FractionalDamping => {
            if freqs.len() < 3 || f_span < 4.0 {
                return Err("fewer than three frequencies or less than a 4x frequency span".into());
            }
        }
        EffectKind::TemperatureShift => {
            let temps: Vec<f64> = data.iter().map(|d| d.temperature_c).collect();
            let lo = temps.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = temps.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            if hi - lo < 2.0 {
                return Err("no temperature variation (span below 2 degC)".into());
            }
        }
        EffectKind::ChannelDelay => {
            if freqs.len() < 2 || f_span < 2.0 {
                return Err("fewer than two frequencies or less than a 2x frequency span".into());
            }
        }
        EffectKind::MovingMass => {
            if freqs.len() < 3 || f_span < 3.0 {
                return Err("fewer than three frequencies or less than a 3x frequency span".into());
            }
        }
        EffectKind::LoadTrainResonance => {
            // Its low-frequency signature is a term in frequency squared proportional to
            // the force (a moving mass's is proportional to the displacement) plus a phase
            // lag (a channel delay's): it needs the frequency span of both, and the
            // force-to-displacement ratio to vary at one frequency (preloads or
            // temperatures) to be told from a mass.
            if freqs.len() < 3 || f_span < 4.0 {
                return Err("fewer than three frequencies or less than a 4x frequency span".into());
            }
            let harmonic: Vec<&CycleData> = data.iter().filter(|d| !d.is_history()).collect();
            let moduli = levels(
                harmonic
                    .iter()
                    .map(|d| d.force_mean_n + 1e5 * d.temperature_c),
                0.1,
            );
            if moduli.len() < 2 {
                return Err(
                    "one preload and one temperature: a resonance of the load train cannot be told from a moving mass"
                        .into(),
                );
            }
        }
        EffectKind::SpecimenDrift => {
            let harmonic: Vec<&CycleData> = data.iter().filter(|d| !d.is_history()).collect();
            if harmonic.len() < 8 {
                return Err("fewer than eight harmonic tests".into());
            }
            let order: Vec<f64> = harmonic.iter().map(|d| d.time.clocks[0]).collect();
            for (name, _, key) in verdict::DESIGN_KEYS {
                let values: Vec<f64> = harmonic.iter().map(|d| key(d)).collect();
                let r = correlation(&order, &values);
                if r.abs() > 0.9 {
                    return Err(format!(
                        "test order follows {name} (r = {r:.2}): a change of the specimen cannot be told from it"
                    ));
                }
            }
        }
        EffectKind::CyclicSoftening => {
            // Softening shows as tests below a load reached before them (softer) against
            // tests before that load was reached; tests that raise the maximum tell it from
            // a drift with time (which goes on whatever the load).
            let peaks: Vec<(f64, f64)> = data
                .iter()
                .filter(|d| d.time.schedule.is_some())
                .map(|d| (d.time.peak_force_n, d.time.max_force_before_n))
                .collect();
            let campaign_max = peaks.iter().map(|p| p.0).fold(0.0, f64::max);
            let below_after = peaks.iter().filter(|(p, m)| *p < 0.8 * m).count();
            let raising = peaks
                .iter()
                .filter(|(p, m)| *m > 0.0 && *p > 1.05 * m)
                .count();
            let below_before = peaks
                .iter()
                .filter(|(p, m)| *p < 0.8 * campaign_max && *m < 0.9 * campaign_max)
                .count();
            // Or the first cycles of harmonic records (split off as history tests because
            // they differ from the steady cycles beyond noise) that raise the largest
            // load: the virgin loading against the same record's steady cycles below it,
            // seconds apart, which a drift with time or tests cannot give.
            let first_raising = data
                .iter()
                .filter(|d| {
                    d.time.first_cycles
                        && d.time.schedule.is_some()
                        && d.time.peak_force_n > 1.05 * d.time.max_force_before_n
                })
                .count();
            if (below_after < 3 || raising < 2 || below_before < 3) && first_raising < 3 {
                return Err(format!(
                    "the load history does not show it: {below_after} tests below a load reached before them, {raising} raising the largest load, {below_before} at low load before the largest (3, 2 and 3 needed), {first_raising} records whose first cycles raise the largest load and differ from their steady cycles (or 3 needed)"
                ));
            }
        }
        EffectKind::SelfHeating => {
            // Power must vary at one chamber temperature (else temperature-shift), and not
            // with test order (else specimen-drift).
            let harmonic: Vec<&CycleData> = data
                .iter()
                .filter(|d| !d.is_history() && d.time.power_w() > 0.0)
                .collect();
            if harmonic.len() < 6 {
                return Err("fewer than six harmonic tests with a measured dissipated power (or no campaign times)".into());
            }
            let reference = reference_temperature_c(data);
            let powers: Vec<f64> = harmonic
                .iter()
                .filter(|d| (d.temperature_c - reference).abs() < 1.0)
                .map(|d| d.time.power_w())
                .collect();
            let lo = powers.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = powers.iter().copied().fold(0.0, f64::max);
            if powers.len() < 6 || hi < 5.0 * lo {
                return Err(
                    "dissipated power varies less than 5x at one chamber temperature".into(),
                );
            }
            let order: Vec<f64> = harmonic.iter().map(|d| d.time.clocks[0]).collect();
            let ln_power: Vec<f64> = harmonic.iter().map(|d| d.time.power_w().ln()).collect();
            let r = correlation(&order, &ln_power);
            if r.abs() > 0.9 {
                return Err(format!(
                    "dissipated power follows test order (r = {r:.2}): heating cannot be told from a drift"
                ));
            }
        }
    }
    Ok(())
}

/// One-sided Wilcoxon signed-rank statistic (normal approximation with tie correction)
/// for `differences` being positive.
pub fn wilcoxon_z(differences: &[f64]) -> f64 {
    let mut nonzero: Vec<f64> = differences.iter().copied().filter(|d| *d != 0.0).collect();
    let n = nonzero.len();
    if n == 0 {
        return 0.0;
    }
    nonzero.sort_by(|a, b| a.abs().total_cmp(&b.abs()));
    let mut w_plus = 0.0;
    let mut tie_term = 0.0;
    let mut i = 0;
    while i < n {
        let mut j = i;
        while j + 1 < n && nonzero[j + 1].abs() == nonzero[i].abs() {
            j += 1;
        }
        let rank = (i + j) as f64 / 2.0 + 1.0;
        let t = (j - i + 1) as f64;
        tie_term += t * t * t - t;
        for d in &nonzero[i..=j] {
            if *d > 0.0 {
                w_plus += rank;
            }
        }
        i = j + 1;
    }
    let nf = n as f64;
    let mean = nf * (nf + 1.0) / 4.0;
    let var = nf * (nf + 1.0) * (2.0 * nf + 1.0) / 24.0 - tie_term / 48.0;
    (w_plus - mean) / var.max(1e-12).sqrt()
}

/// Reference temperature: the most common test temperature (ties: closest to 23 degC).
pub fn reference_temperature_c(data: &[CycleData]) -> f64 {
    let temps = levels(data.iter().map(|d| d.temperature_c), 0.005);
    let count = |t: f64| {
        data.iter()
            .filter(|d| (d.temperature_c - t).abs() <= 0.005 * t.abs().max(1.0))
            .count()
    };
    temps
        .iter()
        .copied()
        .max_by(|&a, &b| {
            count(a)
                .cmp(&count(b))
                .then(((b - 23.0).abs()).total_cmp(&(a - 23.0).abs()))
        })
        .unwrap_or(23.0)
}

/// A data-driven start for the baseline element (same structure, chi kept).
fn data_driven_element(element: &ElementModel, data: &[CycleData]) -> ElementModel {
    let data: Vec<&CycleData> = data.iter().filter(|d| !d.is_history()).collect();
    if data.is_empty() {
        return *element;
    }
    let ks: Vec<(f64, f64)> = data
        .iter()
        .map(|d| {
            let (re, im) =
                crate::ident::campaign::cdiv(d.force_harmonics_n[0], d.displacement_harmonics_m[0]);
            (re, im / (2.0 * std::f64::consts::PI * d.frequency_hz))
        })
        .collect();
    let k_min = ks
        .iter()
        .map(|k| k.0)
        .fold(f64::INFINITY, f64::min)
        .max(1.0);
    let k_max = ks.iter().map(|k| k.0).fold(0.0, f64::max);
    let c_max = ks.iter().map(|k| k.1).fold(0.0, f64::max).max(1e-3 * k_min);
    let mut out = *element;
    match &mut out {
        ElementModel::Consistent(p) | ElementModel::Paper(p) => {
            let g = p.preload_factor(
                data.iter().map(|d| d.force_mean_n).sum::<f64>() / data.len() as f64,
            );
            p.k1_0_n_per_m = 0.9 * k_min / g;
            p.k2_0_n_per_m = (k_max - 0.9 * k_min).max(0.1 * k_min) / g;
            p.c2_0_ns_per_m = c_max / g;
        }
        ElementModel::KelvinVoigt(p) => {
            p.k_n_per_m = 0.5 * (k_min + k_max);
            p.c_ns_per_m = c_max;
        }
    }
    out
}

/// The model a candidate is compared with: its per-test held-out errors and gaps.
struct Reference<'a> {
    errors: &'a [f64],
    gap: f64,
    raw: f64,
}

/// What the naming rule needs besides the two sets of held-out errors.
struct Scoring<'a> {
    data: &'a [CycleData],
    folds: &'a [usize],
    n_folds: usize,
    options: &'a DiagnoseOptions,
}

/// Naming-rule numbers of a candidate against a reference model.
struct Comparison {
    gap_ratio: f64,
    raw_ratio: f64,
    score: f64,
    z: f64,
    folds_improved: usize,
    history_evidence: bool,
    qualifies: bool,
    /// Every criterion but the size of what it explains (the materiality rule).
    qualifies_but_size: bool,
}

impl Scoring<'_> {
    /// The naming rule (module docs) for held-out `errors` (raw RMS `raw`) of a candidate
    /// with `n_extra` more parameters than `reference`.
    fn compare(
        &self,
        errors: &[f64],
        raw: f64,
        n_extra: usize,
        reference: &Reference<'_>,
    ) -> Comparison {
        let options = self.options;
        let penalty = 1.0 + options.penalty_per_param * n_extra as f64;
        let candidate_gap = excess_gap(errors, self.data);
        let gap_ratio = candidate_gap / reference.gap.max(1e-300);
        let raw_ratio = raw / reference.raw.max(1e-300);
        let score = gap_ratio * penalty;
        let differences: Vec<f64> = reference
            .errors
            .iter()
            .zip(errors)
            .zip(self.data)
            .map(|((b, c), d)| (b - c) * d.weight)
            .collect();
        let z = wilcoxon_z(&differences);
        let folds_improved = (0..self.n_folds)
            .filter(|&f| {
                let sum = |e: &[f64]| -> f64 {
                    e.iter()
                        .zip(self.folds)
                        .zip(self.data)
                        .filter(|((_, &g), _)| g == f)
                        .map(|((x, _), d)| x * d.weight)
                        .sum()
                };
                sum(errors) < sum(reference.errors)
            })
            .count();
        let explained = (reference.gap * reference.gap - candidate_gap * candidate_gap)
            .max(0.0)
            .sqrt();
        // A history test is a long record with many independent bins: each one whose
        // held-out residual is beyond its noise is evidence of its own. When every such
        // test (at least two) loses most of its excess with the candidate and the harmonic
        // tests do not get worse, the passages have shown the effect even where the
        // harmonic design cannot (e.g. one force amplitude).
        let history: Vec<usize> = (0..self.data.len())
            .filter(|&i| self.data[i].is_history())
            .collect();
        let harmonic_differences: Vec<f64> = differences
            .iter()
            .zip(self.data)
            .filter(|(_, d)| !d.is_history())
            .map(|(x, _)| *x)
            .collect();
        let history_evidence = history.len() >= 2
            && history.iter().all(|&i| {
                let d = &self.data[i];
                let dof = d.history.as_ref().map_or(1.0, |h| h.dof);
                let before = reference.errors[i] - d.noise_relative;
                let after = errors[i] - d.noise_relative;
                history_beyond_noise(reference.errors[i], d.noise_relative, dof)
                    && after < 0.6 * before
            })
            && (harmonic_differences.len() < 6 || wilcoxon_z(&harmonic_differences) > -1.0);
        let qualifies_but_size = score < options.max_score
            && raw_ratio * penalty < options.max_raw_ratio
            && ((z > options.min_wilcoxon_z && folds_improved + 1 >= self.n_folds)
                || history_evidence);
        let qualifies = qualifies_but_size && explained > options.min_explained_gap;
        Comparison {
            gap_ratio,
            raw_ratio,
            score,
            z,
            folds_improved,
            history_evidence,
            qualifies,
            qualifies_but_size,
        }
    }
}

/// One-step lookahead when no single candidate qualifies: the best single candidate (if it
/// improves on the current model with held-out evidence, Wilcoxon z above the naming
/// threshold) paired with each other candidate. Returns the index of the first member in
/// `results` and the second member's result (fitted with the first, compared with the
/// first alone) of the best qualifying pair.
fn lookahead_pair(
    results: &[CandidateResult],
    forced_first: Option<usize>,
    reference: &Reference<'_>,
    scoring: &Scoring<'_>,
    progress: &mut dyn FnMut(&str),
) -> Option<(usize, CandidateResult)> {
    let options = scoring.options;
    let (first_index, first) = results
        .iter()
        .enumerate()
        .filter(|(i, _)| forced_first.is_none_or(|f| f == *i))
        .filter(|(i, r)| {
            forced_first == Some(*i)
                || !r.cv.screened
                    && r.score < 1.0
                    && r.wilcoxon_z > options.min_wilcoxon_z
                    && r.out_of_range.is_none()
                    && r.law_broken.is_none()
        })
        .min_by(|a, b| a.1.score.total_cmp(&b.1.score))?;
    let others: Vec<&CandidateResult> = results.iter().filter(|r| r.kind != first.kind).collect();
    if others.is_empty() {
        return None;
    }
    let round = first.round + 1;
    let first_template = &first.template;
    let first_reference = Reference {
        errors: &first.cv.held_out_error,
        gap: excess_gap(&first.cv.held_out_error, scoring.data),
        raw: raw_gap(&first.cv.held_out_error, scoring.data),
    };
    // The screen of the single candidates, on the pair against the first alone (in
    // sample both): a pair that cannot beat its first member there cannot qualify held
    // out, and its fold refits are skipped (a third round's six pairs beside a Mullins
    // law took 8 s of an 18 s diagnosis).
    let first_in_sample = in_sample_errors(
        &first.template.model(&first.cv.full_fit.params),
        scoring.data,
    );
    let first_in_sample_reference = Reference {
        errors: &first_in_sample,
        gap: excess_gap(&first_in_sample, scoring.data),
        raw: raw_gap(&first_in_sample, scoring.data),
    };
    let evaluated = run_parallel(&others, options.n_threads, |other| {
        let mut pair_template =
            first_template.with_effect(other.kind, Some(&first.cv.full_fit.params));
        if other.kind == EffectKind::AmplitudeFriction {
            pair_template.friction_dahl = other.template.friction_dahl;
        }
        if other.kind == EffectKind::TemperatureShift {
            pair_template.time_shift_on_bound = other.template.time_shift_on_bound;
        }
        let screen = |in_sample: &[f64]| {
            let m = scoring.compare(
                in_sample,
                raw_gap(in_sample, scoring.data),
                other.kind.n_params(),
                &first_in_sample_reference,
            );
            m.score * SCREEN_MARGIN >= options.max_score
                && m.z <= options.min_wilcoxon_z
                && !m.history_evidence
        };
        let cv = cross_validate_screened(
            &pair_template,
            scoring.data,
            scoring.folds,
            scoring.n_folds,
            options.max_iterations,
            options.n_threads,
            options
                .screen
                .then_some(&screen as &crate::ident::fit::Screen<'_>),
        );
        let joint = scoring.compare(
            &cv.held_out_error,
            raw_gap(&cv.held_out_error, scoring.data),
            first.kind.n_params() + other.kind.n_params(),
            reference,
        );
        let given_first = scoring.compare(
            &cv.held_out_error,
            raw_gap(&cv.held_out_error, scoring.data),
            other.kind.n_params(),
            &first_reference,
        );
        // A screened candidate's errors are in sample: its held-out ones are needed here
        // (not when the pair itself was screened out: it cannot qualify).
        let other_cv = if other.cv.screened && !cv.screened {
            cross_validate(
                &other.template,
                scoring.data,
                scoring.folds,
                scoring.n_folds,
                options.max_iterations,
                options.n_threads,
            )
        } else {
            other.cv.clone()
        };
        let other_reference = Reference {
            errors: &other_cv.held_out_error,
            gap: excess_gap(&other_cv.held_out_error, scoring.data),
            raw: raw_gap(&other_cv.held_out_error, scoring.data),
        };
        let given_other = scoring.compare(
            &cv.held_out_error,
            raw_gap(&cv.held_out_error, scoring.data),
            first.kind.n_params(),
            &other_reference,
        );
        let model = pair_template.model_with_errors(&cv.full_fit);
        let out_of_range = out_of_range(&model, &[first.kind, other.kind]);
        let would =
            !cv.screened && joint.qualifies && given_first.qualifies && given_other.qualifies;
        let law_broken = (would && out_of_range.is_none())
            .then(|| {
                law_broken(
                    &pair_template,
                    &cv.full_fit,
                    scoring.data,
                    &[first.kind, other.kind],
                    options.max_iterations,
                )
            })
            .flatten();
        let result = CandidateResult {
            law_note: other.law_note.clone(),
            kind: other.kind,
            round,
            raw_gap: raw_gap(&cv.held_out_error, scoring.data),
            cv,
            gap_ratio: given_first.gap_ratio,
            raw_ratio: given_first.raw_ratio,
            score: given_first.score,
            wilcoxon_z: given_first.z,
            folds_improved: given_first.folds_improved,
            history_evidence: given_first.history_evidence,
            qualifies: would && out_of_range.is_none() && law_broken.is_none(),
            would_qualify: would,
            out_of_range,
            law_broken,
            model,
            template: pair_template,
            stand_in: None,
        };
        (result, joint.score, given_other.score)
    });
    for (r, joint_score, other_score) in &evaluated {
        progress(&format!(
            "round {}: lookahead {} + {:<20} joint score {:.3}, score given {} {:.3}, given {} alone {:.3}{}",
            first.round,
            first.kind.name(),
            r.kind.name(),
            joint_score,
            first.kind.name(),
            r.score,
            r.kind.name(),
            other_score,
            if r.qualifies {
                " qualifies"
            } else if r.cv.screened {
                " (screened out in sample: folds not refitted)"
            } else {
                ""
            }
        ));
    }
    evaluated
        .into_iter()
        .filter(|(r, _, _)| r.qualifies)
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(r, _, _)| (first_index, r))
}

/// When a round's best description fits only outside its range beside the effect named
/// alone in the round before (a load-train resonance pushed to zero damping by a springpot
/// that took the phase a channel skew put there), that effect may have stood in for half
/// of a pair. From the model before it, the unphysical candidate `x` is fitted beside each
/// other candidate of that round; a pair replaces the last named effect only if it lies
/// inside every range, passes the naming rule against the model before (penalised for both
/// effects), each member passes it against the other alone, and it passes it against the
/// current model too. Returns `x` and the partner, both carrying the pair's fit (the
/// partner's comparison is against `x` alone), best joint score first.
#[allow(clippy::too_many_arguments)]
fn swap_last_named(
    x: &CandidateResult,
    last: EffectKind,
    before_template: &Template,
    before_cv: &CrossValidation,
    before_results: &[CandidateResult],
    current: &Reference<'_>,
    scoring: &Scoring<'_>,
    progress: &mut dyn FnMut(&str),
) -> Option<(CandidateResult, CandidateResult)> {
    let options = scoring.options;
    let data = scoring.data;
    let held_out = |r: &CandidateResult| {
        if r.cv.screened {
            cross_validate(
                &r.template,
                data,
                scoring.folds,
                scoring.n_folds,
                options.max_iterations,
                options.n_threads,
            )
        } else {
            r.cv.clone()
        }
    };
    let x_alone = held_out(before_results.iter().find(|r| r.kind == x.kind)?);
    let before = Reference {
        errors: &before_cv.held_out_error,
        gap: excess_gap(&before_cv.held_out_error, data),
        raw: raw_gap(&before_cv.held_out_error, data),
    };
    let x_reference = Reference {
        errors: &x_alone.held_out_error,
        gap: excess_gap(&x_alone.held_out_error, data),
        raw: raw_gap(&x_alone.held_out_error, data),
    };
    let others: Vec<&CandidateResult> =
        before_results.iter().filter(|r| r.kind != x.kind).collect();
    let evaluated = run_parallel(&others, options.n_threads, |other| {
        let mut t = before_template.with_effect(x.kind, Some(&before_cv.full_fit.params));
        t.added.push(other.kind);
        for source in [&x.template, &other.template] {
            match source.added.last() {
                Some(EffectKind::AmplitudeFriction) => t.friction_dahl = source.friction_dahl,
                Some(EffectKind::TemperatureShift) => {
                    t.time_shift_on_bound = source.time_shift_on_bound
                }
                Some(EffectKind::SpecimenDrift) => t.drift_clock = source.drift_clock,
                _ => {}
            }
        }
        let cv = cross_validate(
            &t,
            data,
            scoring.folds,
            scoring.n_folds,
            options.max_iterations,
            options.n_threads,
        );
        let raw = raw_gap(&cv.held_out_error, data);
        let (n_x, n_other) = (x.kind.n_params(), other.kind.n_params());
        let joint = scoring.compare(&cv.held_out_error, raw, n_x + n_other, &before);
        let other_alone = held_out(other);
        let other_reference = Reference {
            errors: &other_alone.held_out_error,
            gap: excess_gap(&other_alone.held_out_error, data),
            raw: raw_gap(&other_alone.held_out_error, data),
        };
        let given_other = scoring.compare(&cv.held_out_error, raw, n_x, &other_reference);
        let given_x = scoring.compare(&cv.held_out_error, raw, n_other, &x_reference);
        let against_current = scoring.compare(&cv.held_out_error, raw, n_x + n_other, current);
        let model = t.model_with_errors(&cv.full_fit);
        let out_of_range = out_of_range(&model, &[x.kind, other.kind]);
        let ok = joint.qualifies
            && given_other.qualifies
            && given_x.qualifies
            && against_current.qualifies
            && out_of_range.is_none();
        let law_broken = ok
            .then(|| {
                law_broken(
                    &t,
                    &cv.full_fit,
                    data,
                    &[x.kind, other.kind],
                    options.max_iterations,
                )
            })
            .flatten();
        let ok = ok && law_broken.is_none();
        let result = |kind: EffectKind, round: usize, m: &Comparison, law_note: &Option<String>| {
            CandidateResult {
                kind,
                round,
                raw_gap: raw,
                cv: cv.clone(),
                gap_ratio: m.gap_ratio,
                raw_ratio: m.raw_ratio,
                score: m.score,
                wilcoxon_z: m.z,
                folds_improved: m.folds_improved,
                history_evidence: m.history_evidence,
                qualifies: ok,
                out_of_range,
                law_broken: law_broken.clone(),
                would_qualify: ok,
                model: model.clone(),
                template: t.clone(),
                law_note: law_note.clone(),
                stand_in: None,
            }
        };
        let round = other.round;
        (
            result(x.kind, round, &joint, &x.law_note),
            result(other.kind, round + 1, &given_x, &other.law_note),
            joint.score,
            against_current.score,
        )
    });
    for (xr, yr, joint_score, current_score) in &evaluated {
        progress(&format!(
            "swap: {} + {:<20} from the model before {}: joint score {:.3}, against the current model {:.3}{}{}",
            xr.kind.name(),
            yr.kind.name(),
            last.name(),
            joint_score,
            current_score,
            yr.out_of_range.map_or(String::new(), |o| format!(" {o}")),
            if yr.qualifies { " qualifies" } else { "" }
        ));
    }
    evaluated
        .into_iter()
        .filter(|(_, y, _, _)| y.qualifies)
        .min_by(|a, b| a.2.total_cmp(&b.2))
        .map(|(x, y, _, _)| (x, y))
}

/// Runs the workflow. `progress` receives one-line messages.
pub fn diagnose(
    baseline: &AugmentedModel,
    data: &[CycleData],
    options: &DiagnoseOptions,
    progress: &mut dyn FnMut(&str),
) -> Diagnosis {
    let n_folds = options.n_folds.clamp(2, data.len().max(2));
    let folds = assign_folds(data, n_folds);
    let reference_temperature_c = reference_temperature_c(data);
    let mut not_tried = Vec::new();
    let mut candidates: Vec<EffectKind> = Vec::new();
    for kind in EffectKind::ALL {
        if baseline.find(kind.name()).is_some() {
            not_tried.push(NotTried {
                kind,
                reason: "already in the baseline model".into(),
                not_identifiable: false,
            });
            continue;
        }
        if kind == EffectKind::PreloadStiffening {
            match baseline.element {
                ElementModel::KelvinVoigt(_) => {
                    not_tried.push(NotTried {
                        kind,
                        reason: "needs a Zener baseline".into(),
                        not_identifiable: false,
                    });
                    continue;
                }
                _ if baseline.element.zener().is_some_and(|p| p.chi > 0.0) => {
                    not_tried.push(NotTried {
                        kind,
                        reason: "the baseline already has chi > 0 (re-calibrated with it)".into(),
                        not_identifiable: false,
                    });
                    continue;
                }
                _ => {}
            }
        }
        match identifiability(kind, data) {
            Ok(()) => candidates.push(kind),
            Err(reason) => {
                progress(&format!("{}: not identifiable: {reason}", kind.name()));
                not_tried.push(NotTried {
                    kind,
                    reason,
                    not_identifiable: true,
                })
            }
        }
    }

    // Calibrate the baseline: from the file's values and from a data-driven start.
    let mut template =
        Template::new(baseline.clone(), reference_temperature_c).with_clock_spans(data);
    let all: Vec<&CycleData> = data.iter().collect();
    let mut alternative = template.clone();
    alternative.baseline.element = data_driven_element(&baseline.element, data);
    let starts = [
        template.starts(data)[0].clone(),
        alternative.starts(data)[0].clone(),
    ];
    let calibration = crate::ident::fit::fit_template(&template, &all, &starts, 100);
    template.baseline = template.model(&calibration.params);
    let baseline_template = template.clone();
    let baseline_cv = cross_validate(
        &template,
        data,
        &folds,
        n_folds,
        options.max_iterations,
        options.n_threads,
    );
    let baseline_model = template.model(&baseline_cv.full_fit.params);
    progress(&format!(
        "baseline calibrated on {} tests: held-out gap {:.4e} (raw {:.4e}, noise floor {:.4e}; {n_folds}-fold)",
        data.len(),
        excess_gap(&baseline_cv.held_out_error, data),
        raw_gap(&baseline_cv.held_out_error, data),
        noise_floor(data)
    ));

    let mut current_template = template;
    let mut current_cv = baseline_cv.clone();
    let mut named = Vec::new();
    let mut rounds: Vec<Vec<CandidateResult>> = Vec::new();
    // The model before the effect last named alone and the index of its round, for a
    // swap (`swap_last_named`); one swap per diagnosis.
    let mut before_last: Option<(Template, CrossValidation, usize)> = None;
    let mut swapped = false;
    let mut replaced: Vec<String> = Vec::new();
    loop {
        let remaining: Vec<EffectKind> = candidates
            .iter()
            .copied()
            .filter(|k| !named.contains(k))
            .collect();
        if remaining.is_empty() {
            break;
        }
        let round = rounds.len() + 1;
        let prefix = current_cv.full_fit.params.clone();
        let current_errors = current_cv.held_out_error.clone();
        let current_gap = excess_gap(&current_errors, data);
        let current_raw = raw_gap(&current_cv.held_out_error, data);
        let reference = Reference {
            errors: &current_errors,
            gap: current_gap,
            raw: current_raw,
        };
        let scoring = Scoring {
            data,
            folds: &folds,
            n_folds,
            options,
        };
        // Every variant of every candidate is one work item, so the two friction laws run
        // side by side rather than one after the other in one worker.
        let items: Vec<(EffectKind, Template)> = remaining
            .iter()
            .flat_map(|&kind| {
                current_template
                    .variants_with_effect(kind, Some(&prefix))
                    .into_iter()
                    .map(move |t| (kind, t))
            })
            .collect();
        // The screen: a candidate whose full fit, in sample (optimistic for it), neither
        // comes within `SCREEN_MARGIN` of the naming score nor shows a Wilcoxon or history
        // signal against the current model in sample cannot qualify held out, nor lead a
        // pair: its fold refits are skipped.
        let current_model = current_template.model(&current_cv.full_fit.params);
        let current_in_sample = in_sample_errors(&current_model, data);
        let in_sample_reference = Reference {
            errors: &current_in_sample,
            gap: excess_gap(&current_in_sample, data),
            raw: raw_gap(&current_in_sample, data),
        };
        let fitted = run_parallel(&items, options.n_threads, |(kind, t)| {
            let screen = |in_sample: &[f64]| {
                let m = scoring.compare(
                    in_sample,
                    raw_gap(in_sample, data),
                    kind.n_params(),
                    &in_sample_reference,
                );
                m.score * SCREEN_MARGIN >= options.max_score
                    && m.z <= options.min_wilcoxon_z
                    && !m.history_evidence
            };
            let started = std::time::Instant::now();
            let cv = cross_validate_screened(
                t,
                data,
                &folds,
                n_folds,
                options.max_iterations,
                options.n_threads,
                options
                    .screen
                    .then_some(&screen as &crate::ident::fit::Screen<'_>),
            );
            (cv, started.elapsed().as_secs_f64())
        });
        let mut seconds: Vec<(EffectKind, f64)> = Vec::new();
        let fitted: Vec<CrossValidation> = items
            .iter()
            .zip(fitted)
            .map(|((kind, _), (cv, s))| {
                match seconds.iter_mut().find(|(k, _)| k == kind) {
                    Some(entry) => entry.1 += s,
                    None => seconds.push((*kind, s)),
                }
                cv
            })
            .collect();
        let mut by_kind: Vec<(EffectKind, Template, CrossValidation)> = Vec::new();
        let outside = |template: &Template, cv: &CrossValidation| {
            out_of_range(&template.model(&cv.full_fit.params), &template.added).is_some()
        };
        let mut drift_fits: Vec<(crate::model::effects::DriftClock, f64, usize)> = Vec::new();
        for ((kind, template), cv) in items.into_iter().zip(fitted) {
            if kind == EffectKind::SpecimenDrift {
                drift_fits.push((
                    template.drift_clock,
                    cv.full_fit.sse,
                    cv.full_fit.n_residuals.saturating_sub(template.n_params()),
                ));
            }
            match by_kind.iter_mut().find(|(k, _, _)| *k == kind) {
                // The choice between laws with equally many parameters is made on the
                // in-sample fit, never on held-out errors; a fit inside the effect's
                // physical range beats one outside it (the relaxation-time shift held on
                // its bound beside a free fit just below it).
                Some(entry)
                    if (outside(&template, &cv), cv.full_fit.sse)
                        < (outside(&entry.1, &entry.2), entry.2.full_fit.sse) =>
                {
                    *entry = (kind, template, cv)
                }
                Some(_) => {}
                None => by_kind.push((kind, template, cv)),
            }
        }
        let mut results: Vec<CandidateResult> = by_kind
            .into_iter()
            .map(|(kind, candidate, cv)| {
                let m = scoring.compare(
                    &cv.held_out_error,
                    raw_gap(&cv.held_out_error, scoring.data),
                    kind.n_params(),
                    if cv.screened {
                        &in_sample_reference
                    } else {
                        &reference
                    },
                );
                let m = Comparison {
                    qualifies: m.qualifies && !cv.screened,
                    ..m
                };
                let model = candidate.model_with_errors(&cv.full_fit);
                let out_of_range = out_of_range(&model, &[kind]);
                // Too small to name by the materiality rule, but it moves what is named:
                // the named effects' parameters are results too.
                let moves_named = (!m.qualifies && m.qualifies_but_size && !cv.screened)
                    .then(|| moved_named_parameter(&current_model, &model, &named))
                    .flatten();
                let m = Comparison {
                    qualifies: m.qualifies || moves_named.is_some(),
                    ..m
                };
                let (law_broken, rival_note) = match kind {
                    _ if !m.qualifies || out_of_range.is_some() => (None, None),
                    EffectKind::FractionalDamping => {
                        springpot_check(&candidate, &cv.full_fit, data, options.max_iterations)
                    }
                    EffectKind::ChannelDelay => {
                        channel_delay_check(&candidate, &cv.full_fit, data, options.max_iterations)
                    }
                    _ => (None, None),
                };
                let law_note = match kind {
                    EffectKind::FractionalDamping => rival_note,
                    EffectKind::ChannelDelay => rival_note,
                    EffectKind::SpecimenDrift => Some(drift_clock_note(
                        &drift_fits,
                        &candidate.clocks_like_order,
                        data,
                    )),
                    EffectKind::SelfHeating => heating_note(
                        &model,
                        data,
                        candidate
                            .effect_intervals(&cv, kind)
                            .iter()
                            .find(|i| i.name == "heat_capacity_j_per_k")
                            .is_none_or(|i| i.determined()),
                    ),
                    _ => None,
                };
                let law_note = match (law_note, moves_named) {
                    (note, Some(moved)) => Some(match note {
                        Some(n) => format!("{n}; {moved}"),
                        None => moved,
                    }),
                    (note, None) => note,
                };
                CandidateResult {
                    law_note,
                    kind,
                    round,
                    raw_gap: raw_gap(&cv.held_out_error, scoring.data),
                    cv,
                    gap_ratio: m.gap_ratio,
                    raw_ratio: m.raw_ratio,
                    score: m.score,
                    wilcoxon_z: m.z,
                    folds_improved: m.folds_improved,
                    history_evidence: m.history_evidence,
                    qualifies: m.qualifies && out_of_range.is_none() && law_broken.is_none(),
                    would_qualify: m.qualifies,
                    out_of_range,
                    law_broken,
                    model,
                    template: candidate,
                    stand_in: None,
                }
            })
            .collect();
        for r in &results {
            progress(&format!(
                "round {round}: {:<20} held-out gap {:.4e} (raw {:.4e}) ratio {:.3} raw ratio {:.3} score {:.3} z {:.2} folds {}/{}{}{}{}{} [{:.1} s]",
                r.kind.name(),
                excess_gap(&r.cv.held_out_error, data),
                raw_gap(&r.cv.held_out_error, data),
                r.gap_ratio,
                r.raw_ratio,
                r.score,
                r.wilcoxon_z,
                r.folds_improved,
                n_folds,
                if r.history_evidence { " (history evidence)" } else { "" },
                r.out_of_range.map_or(String::new(), |o| format!(" {o}")),
                r.law_broken.as_ref().map_or(String::new(), |b| format!(" {b}")),
                if r.qualifies { " qualifies" } else if r.cv.screened { " (screened out in sample: folds not refitted)" } else { "" },
                seconds
                    .iter()
                    .find(|(k, _)| *k == r.kind)
                    .map_or(0.0, |(_, s)| *s)
            ));
        }
        // When the candidate that describes the discrepancy best would qualify but fits
        // only outside its physical range, the strongest pattern in the data is not any
        // library effect: the physical candidates that still qualify are stand-ins for it
        // (a delay and a springpot imitating a load-path resonance), so none is named.
        let best_would = results
            .iter()
            .filter(|r| r.would_qualify && !r.out_of_range.is_some_and(|o| o.degenerates()))
            .min_by(|a, b| a.score.total_cmp(&b.score));
        // A springpot that is the best description but has no single order across the
        // tests may be half of a pair (a channel skew bends its apparent order): it is
        // fitted beside each other candidate, and the pair is named if the springpot's law
        // holds there and the pair passes the lookahead's rule. Else nothing is named.
        let broken_law_pair = best_would
            .filter(|b| {
                b.kind == EffectKind::FractionalDamping
                    && b.out_of_range.is_none()
                    && b.law_broken.is_some()
            })
            .and_then(|b| results.iter().position(|r| r.kind == b.kind))
            .and_then(|i| lookahead_pair(&results, Some(i), &reference, &scoring, progress));
        // The springpot's partner may pair better with something else (a skew beside a
        // load-train resonance, for which the springpot stood in): the partner is fitted
        // beside each other candidate too, and a qualifying pair without the springpot
        // whose joint score is better is named instead.
        let joint_score = |first: EffectKind, pair: &CandidateResult| {
            scoring
                .compare(
                    &pair.cv.held_out_error,
                    raw_gap(&pair.cv.held_out_error, data),
                    first.n_params() + pair.kind.n_params(),
                    &reference,
                )
                .score
        };
        let broken_law_pair = broken_law_pair.map(|(first_index, second)| {
            let springpot_score = joint_score(results[first_index].kind, &second);
            let alternative = results
                .iter()
                .position(|r| r.kind == second.kind)
                .and_then(|i| lookahead_pair(&results, Some(i), &reference, &scoring, progress))
                .filter(|(i, alt)| {
                    alt.kind != EffectKind::FractionalDamping
                        && joint_score(results[*i].kind, alt) < springpot_score
                });
            match alternative {
                Some((i, alt)) => Some((i, alt, false)),
                // A springpot whose law held only beside a partner is named with it only
                // when the pair leaves nothing material: its broken law alone, and a
                // residual beside its partner, say it stands in for a cause outside the
                // library.
                None => (excess_gap(&second.cv.held_out_error, data) < verdict::MIN_GAP)
                    .then_some((first_index, second, true)),
            }
        });
        let broken_law_pair = broken_law_pair.flatten();
        if let Some((first_index, second, with_springpot)) = broken_law_pair {
            let first = &mut results[first_index];
            if with_springpot {
                let why = first.law_broken.take().unwrap_or_default();
                first.law_note = Some(format!(
                    "alone it {why}; beside `{}` its order holds across the tests",
                    second.kind.name()
                ));
            }
            first.qualifies = true;
            let first = first.kind;
            progress(&format!(
                "round {round}: named {} and {} (jointly: the springpot alone has no single order)",
                first.name(),
                second.kind.name()
            ));
            (current_template, current_cv) =
                name_pair(&mut rounds, &mut named, results, first, second);
            before_last = None;
            continue;
        }
        if let Some(best) =
            best_would.filter(|b| b.out_of_range.is_some() || b.law_broken.is_some())
        {
            let swap = match (&before_last, named.last()) {
                (Some((before_template, before_cv, k)), Some(&last)) if !swapped => {
                    swap_last_named(
                        best,
                        last,
                        before_template,
                        before_cv,
                        &rounds[*k],
                        &reference,
                        &scoring,
                        progress,
                    )
                    .map(|pair| (pair, last, *k))
                }
                _ => None,
            };
            if let Some(((x, y), last, k)) = swap {
                let why = format!(
                    "`{}`, named in round {}, was replaced by `{}` and `{}`: beside it `{}` {}; from the model before it the pair fits inside every range, each member is needed beside the other, and its held-out errors beat `{}`'s by the naming rule",
                    last.name(),
                    k + 1,
                    x.kind.name(),
                    y.kind.name(),
                    best.kind.name(),
                    best.unphysical_text(),
                    last.name()
                );
                progress(&format!("round {round}: {why}"));
                replaced.push(why);
                named.pop();
                rounds.truncate(k + 1);
                let round_k = &mut rounds[k];
                for r in round_k.iter_mut().filter(|r| r.kind == last) {
                    r.qualifies = false;
                }
                current_template = y.template.clone();
                current_cv = y.cv.clone();
                match round_k.iter_mut().find(|r| r.kind == x.kind) {
                    Some(entry) => *entry = x.clone(),
                    None => round_k.push(x.clone()),
                }
                named.push(x.kind);
                named.push(y.kind);
                rounds.push(vec![y]);
                swapped = true;
                before_last = None;
                continue;
            }
            progress(&format!(
                "round {round}: the best description, {}, is unphysical: nothing named",
                best.kind.name()
            ));
            rounds.push(results);
            break;
        }
        let winner = results
            .iter()
            .filter(|r| r.qualifies)
            .filter(|r| !held_back_by_simpler_artefact(r, &results, &scoring))
            .filter(|r| !held_back_on_bound(r, &results, &scoring))
            .min_by(|a, b| a.score.total_cmp(&b.score))
            .map(|r| (r.kind, r.cv.clone(), r.template.clone()));
        if let Some((kind, cv, template)) = winner {
            before_last = Some((current_template.clone(), current_cv.clone(), rounds.len()));
            rounds.push(results);
            progress(&format!("round {round}: named {}", kind.name()));
            current_template = template;
            current_cv = cv;
            named.push(kind);
            continue;
        }
        // No single effect qualifies. Two effects can mask each other (a force-channel
        // delay cancels part of the loss a springpot adds, a moving mass part of the
        // stiffening...), so greedy selection would stop with both hidden. Look one step
        // ahead: the best single candidate, if it already shows held-out evidence, plus
        // each other candidate. The pair is named only if it passes the naming rule
        // against the current model (penalised for both effects) and each member passes
        // it against the other member alone (neither is redundant).
        let pair = lookahead_pair(&results, None, &reference, &scoring, progress);
        match pair {
            Some((first_index, second)) => {
                let first = results[first_index].kind;
                results[first_index].qualifies = true;
                progress(&format!(
                    "round {round}: named {} and {} (jointly: neither qualifies alone)",
                    first.name(),
                    second.kind.name()
                ));
                (current_template, current_cv) =
                    name_pair(&mut rounds, &mut named, results, first, second);
                before_last = None;
            }
            None => {
                rounds.push(results);
                progress(&format!(
                    "round {round}: nothing beats the current model beyond noise"
                ));
                break;
            }
        }
    }
    if let Some((template, cv)) = take_back_stand_in(
        &mut rounds,
        &mut named,
        before_last.as_ref(),
        (&current_template, &current_cv),
        data,
        options.order_is_clock,
    ) {
        progress(&format!(
            "{} taken back: it shrank the gap less than {MIN_STEP_SHRINK}x and a residual beyond noise remains",
            rounds.iter().flatten().find(|c| c.stand_in.is_some()).map_or("", |c| c.kind.name())
        ));
        (current_template, current_cv) = (template, cv);
    }
    let final_model = current_template.model_with_errors(&current_cv.full_fit);
    // A named force lag beside a named moving mass may be one load-train resonance above
    // the band: said on the later-named of the two (however the pair came to be named).
    let refit = resonance_in_pair_place(
        &current_template,
        &current_cv,
        &Scoring {
            data,
            folds: &folds,
            n_folds,
            options,
        },
        progress,
    );
    if let Some(note) = resonance_pair_note(&final_model, data, refit.as_ref()) {
        if let Some(c) = rounds
            .iter_mut()
            .flatten()
            .filter(|c| {
                c.qualifies && matches!(c.kind, EffectKind::ChannelDelay | EffectKind::MovingMass)
            })
            .max_by_key(|c| c.round)
        {
            c.law_note = Some(match c.law_note.take() {
                Some(n) => format!("{n}; {note}"),
                None => note,
            });
        }
    }
    let gap_after = excess_gap(&current_cv.held_out_error, data);
    let mut verdict = verdict(
        &final_model,
        data,
        &current_cv.held_out_error,
        gap_after,
        noise_floor(data),
        options.order_is_clock,
    );
    verdict.drift_named = named.contains(&EffectKind::SpecimenDrift);
    if named.contains(&EffectKind::SelfHeating) {
        verdict::mark_explained_repeats(
            &mut verdict.repeats,
            data,
            &current_cv.held_out_error,
            "self-heating",
        );
    }
    Diagnosis {
        verdict,
        first_cycles_used: Vec::new(),
        history_ids: data
            .iter()
            .filter(|d| d.is_history())
            .map(|d| d.id.clone())
            .collect(),
        gap_before: excess_gap(&baseline_cv.held_out_error, data),
        gap_after,
        raw_gap_before: raw_gap(&baseline_cv.held_out_error, data),
        raw_gap_after: raw_gap(&current_cv.held_out_error, data),
        noise_floor: noise_floor(data),
        reference_temperature_c,
        folds,
        baseline_template,
        baseline_cv,
        baseline_model,
        final_template: current_template,
        final_cv: current_cv,
        final_model,
        named,
        rounds,
        replaced,
        not_tried,
    }
}

/// The gap shrink (gap before over gap after, noise excluded) an effect named alone must
/// bring when a residual beyond noise remains after it: the naming bar of SPEC 5.1's
/// workflow (the gap shown to shrink at least 3x).
pub const MIN_STEP_SHRINK: f64 = 3.0;

/// Takes the last-named effect back out when it was named alone, shrank the gap it faced
/// less than `MIN_STEP_SHRINK`, and either the final model still leaves a residual beyond
/// noise (`verdict::verdict`'s unexplained residual) or it is the only effect named (its
/// shrink is then the campaign's: an independent check's drifting cubic spring was named
/// `cyclic-softening` at 2.5x, nothing left beyond the noise). Such an effect describes part of a
/// pattern it cannot describe whole, which is what a library effect standing in for a
/// cause outside the library does (an independent check: a cubic spring whose coefficient
/// drifted over the campaign was named `cyclic-softening`, 2.1x shrink, beside a residual
/// 2.2x the noise floor). An effect that is the truth leaves no such residual, or removes
/// most of the gap it faced. Marks its result (`stand_in`, no longer qualifying), drops
/// its later rounds (fitted beside it), and returns the model before it.
fn take_back_stand_in(
    rounds: &mut Vec<Vec<CandidateResult>>,
    named: &mut Vec<EffectKind>,
    before_last: Option<&(Template, CrossValidation, usize)>,
    (current_template, current_cv): (&Template, &CrossValidation),
    data: &[CycleData],
    order_is_clock: bool,
) -> Option<(Template, CrossValidation)> {
    let (before_template, before_cv, k) = before_last?;
    let last = *named.last()?;
    let step = rounds
        .get(*k)?
        .iter()
        .find(|c| c.kind == last && c.qualifies)?;
    let shrink = 1.0 / step.gap_ratio.max(1e-300);
    if shrink >= MIN_STEP_SHRINK {
        return None;
    }
    let gap = excess_gap(&current_cv.held_out_error, data);
    let model = current_template.model_with_errors(&current_cv.full_fit);
    let remains = verdict(
        &model,
        data,
        &current_cv.held_out_error,
        gap,
        noise_floor(data),
        order_is_clock,
    )
    .unexplained;
    let left = match remains {
        Some(u) => format!(
            "left a residual {:.1}x the noise floor",
            u.gap / u.noise_floor.max(1e-300)
        ),
        // The only effect named: its shrink is the campaign's, which the workflow must
        // show to name it.
        None if named.len() == 1 => "was the only effect named".to_string(),
        None => return None,
    };
    rounds.truncate(k + 1);
    let step = rounds[*k].iter_mut().find(|c| c.kind == last)?;
    step.qualifies = false;
    step.stand_in = Some(format!(
        "named alone it made the gap only {shrink:.1}x smaller (the workflow asks {MIN_STEP_SHRINK}x of an effect it names) and {left}: the data do not establish it; it may be a true effect too weak against this campaign's noise to show, or describe part of a cause outside the library it stands in for"
    ));
    named.pop();
    Some((before_template.clone(), before_cv.clone()))
}

/// Names a pair in one round: the round's `results` (the first member's marked as
/// qualifying by the caller), then the second member's result, which carries the pair's
/// fit; returns the pair's template and cross-validation, the new current model.
fn name_pair(
    rounds: &mut Vec<Vec<CandidateResult>>,
    named: &mut Vec<EffectKind>,
    results: Vec<CandidateResult>,
    first: EffectKind,
    second: CandidateResult,
) -> (Template, CrossValidation) {
    rounds.push(results);
    named.push(first);
    named.push(second.kind);
    let current = (second.template.clone(), second.cv.clone());
    rounds.push(vec![second]);
    current
}

/// A load-train resonance can imitate a channel delay (its phase) or a moving mass (its
/// frequency-squared term): when one of those one-parameter artefacts qualifies too, the
/// resonance is named only if its held-out errors beat that artefact's by the naming
/// rule's Wilcoxon threshold (parsimony: the simpler artefact explains as much otherwise).
fn held_back_by_simpler_artefact(
    candidate: &CandidateResult,
    results: &[CandidateResult],
    scoring: &Scoring<'_>,
) -> bool {
    if candidate.kind != EffectKind::LoadTrainResonance {
        return false;
    }
    results
        .iter()
        .filter(|r| {
            r.qualifies && matches!(r.kind, EffectKind::ChannelDelay | EffectKind::MovingMass)
        })
        .any(|simpler| !beats(candidate, simpler, scoring))
}

/// Whether `candidate`'s held-out errors beat `other`'s by the naming rule's Wilcoxon
/// threshold (paired, precision-weighted).
fn beats(candidate: &CandidateResult, other: &CandidateResult, scoring: &Scoring<'_>) -> bool {
    let differences: Vec<f64> = other
        .cv
        .held_out_error
        .iter()
        .zip(&candidate.cv.held_out_error)
        .zip(scoring.data)
        .map(|((o, c), d)| (o - c) * d.weight)
        .collect();
    wilcoxon_z(&differences) > scoring.options.min_wilcoxon_z
}

/// How far a named effect's parameters move when `candidate` is fitted beside it: the
/// sentence for the report when one moves by more than `MATERIAL_PARAMETER_CHANGE`
/// (relative; parameters at 0 in the current model are left out).
fn moved_named_parameter(
    current: &AugmentedModel,
    candidate: &AugmentedModel,
    named: &[EffectKind],
) -> Option<String> {
    let mut worst: Option<(f64, String)> = None;
    for &kind in named {
        let before = effect_params(current, kind);
        let after = effect_params(candidate, kind);
        for ((key, b), (_, a)) in before.iter().zip(&after) {
            if *b == 0.0 || !b.is_finite() || !a.is_finite() {
                continue;
            }
            let change = (a - b) / b.abs();
            if change.abs() > MATERIAL_PARAMETER_CHANGE
                && worst.as_ref().is_none_or(|(w, _)| change.abs() > *w)
            {
                worst = Some((
                    change.abs(),
                    format!(
                        "named though it explains under 0.1 % of the force: without it `{}`'s {key} is {b:.4e}, with it {a:.4e} ({:+.0} %)",
                        kind.name(),
                        100.0 * change
                    ),
                ));
            }
        }
    }
    worst.map(|(_, s)| s)
}

/// A named effect's parameter moving by more than this (relative) when a candidate too
/// small for the materiality rule is fitted beside it makes that candidate material.
const MATERIAL_PARAMETER_CHANGE: f64 = 0.05;

/// A springpot whose order sits on its upper bound (alpha at 1) is a plain dashpot: a
/// damping that grows with frequency in proportion to the element's force, which is what a
/// force-channel lead does too. Such a fit is named only if its held-out errors beat every
/// other qualifying candidate's by the naming rule's Wilcoxon threshold (a cause inside
/// its range is preferred to a law pinned on its bound when the data cannot tell them
/// apart).
fn held_back_on_bound(
    candidate: &CandidateResult,
    results: &[CandidateResult],
    scoring: &Scoring<'_>,
) -> bool {
    if !pinned_on_bound(&candidate.model, candidate.kind) {
        return false;
    }
    results
        .iter()
        .filter(|r| r.qualifies && r.kind != candidate.kind)
        .filter(|r| !pinned_on_bound(&r.model, r.kind))
        .any(|other| !beats(candidate, other, scoring))
}

/// Whether a fitted effect sits on a bound of its transformed range (`pinned_on_bound`
/// of `held_back_on_bound`): today the springpot order at its upper clamp.
fn pinned_on_bound(model: &AugmentedModel, kind: EffectKind) -> bool {
    kind == EffectKind::FractionalDamping
        && model.effects.iter().any(|e| {
            matches!(e, Effect::FractionalDamping { alpha, .. } if *alpha >= FRACTIONAL_ORDER_PINNED)
        })
}

/// A springpot order at or above this is on the fit's clamp (0.999): a dashpot.
const FRACTIONAL_ORDER_PINNED: f64 = 0.99;

/// What a self-heating fit cannot say, when its heat capacity's 95 % interval spans more
/// than a factor of 10 (`capacity_determined` false) and its time constant is under a fifth
/// of the median record: every test reaches its steady rise `P / h` within its record and
/// nothing is carried between tests. (A short memory alone says nothing: the warming within
/// a record can still show it.)
fn heating_note(
    model: &AugmentedModel,
    data: &[CycleData],
    capacity_determined: bool,
) -> Option<String> {
    if capacity_determined {
        return None;
    }
    let Some(&Effect::SelfHeating {
        heat_capacity_j_per_k,
        heat_transfer_w_per_k,
        ..
    }) = model.find("self-heating")
    else {
        return None;
    };
    let tau_s = heat_capacity_j_per_k / heat_transfer_w_per_k;
    let mut durations: Vec<f64> = data
        .iter()
        .find_map(|d| d.time.schedule.clone())?
        .iter()
        .map(|i| i.duration_s)
        .collect();
    durations.sort_by(f64::total_cmp);
    let median_s = *durations.get(durations.len() / 2)?;
    (tau_s < median_s / 5.0).then(|| {
        format!(
            "time constant {tau_s:.1} s, under a fifth of the median record ({median_s:.0} s): each test reaches its steady rise P / h within its record and no heat is carried to the next, so the data identify h ({heat_transfer_w_per_k:.3} W/K) but not the heat capacity ({heat_capacity_j_per_k:.2} J/K is no measurement of it)"
        )
    })
}

/// Which clock a drift runs on, as the data say: the in-sample fits of each clock the
/// campaign has, told apart when the worse one's sum of squares exceeds the best one's by
/// more than 4 noise variances (a likelihood-ratio test at about 95 %), else "cannot tell".
fn drift_clock_note(
    fits: &[(crate::model::effects::DriftClock, f64, usize)],
    like_order: &[crate::model::effects::DriftClock],
    data: &[CycleData],
) -> String {
    let Some(&(best, best_sse, dof)) = fits.iter().min_by(|a, b| a.1.total_cmp(&b.1)) else {
        return String::new();
    };
    let sigma2 = best_sse / dof.max(1) as f64;
    let mut told = Vec::new();
    let mut untold = Vec::new();
    for &(clock, sse, _) in fits {
        if clock == best {
            continue;
        }
        if (sse - best_sse) / sigma2.max(1e-300) > 4.0 {
            told.push(clock.name());
        } else {
            untold.push(clock.name());
        }
    }
    let mut note = format!("clock: {}", best.name());
    if !told.is_empty() {
        note.push_str(&format!("; the data prefer it to {}", told.join(" and ")));
    }
    if !untold.is_empty() {
        note.push_str(&format!(
            "; the data cannot tell it from {} (in-sample fits within noise)",
            untold.join(" and ")
        ));
    }
    if !like_order.is_empty() {
        // Named, not "that clock": beside "prefer it to X" a pronoun read as X.
        let names = like_order
            .iter()
            .map(|c| c.name())
            .collect::<Vec<_>>()
            .join(" and ");
        note.push_str(&format!(
            "; {names} {} proportional to test order in this campaign, so the data cannot tell {names} from test-order",
            if like_order.len() == 1 { "is" } else { "are" }
        ));
    }
    let has_time = data.iter().any(|d| d.time.clocks[1] > 0.0);
    if !has_time {
        note.push_str("; time not tried (no `started_at` on every test)");
    }
    note
}

/// The first of `kinds` whose fitted parameters in `model` leave their physical range.
fn out_of_range(model: &AugmentedModel, kinds: &[EffectKind]) -> Option<OutOfRange> {
    kinds.iter().find_map(|&kind| {
        model
            .effects
            .iter()
            .find(|e| e.name() == kind.name())
            .and_then(|e| kind.out_of_range(e))
    })
}

/// Physical parameters of an effect in a model, per metre as in the model file.
pub fn effect_params(model: &AugmentedModel, kind: EffectKind) -> Vec<(&'static str, f64)> {
    model
        .effects
        .iter()
        .find(|e| e.name() == kind.name())
        .map(|e: &Effect| e.file_params(model.length_m))
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilcoxon_is_large_for_consistent_improvement_and_small_for_noise() {
        let improving: Vec<f64> = (1..=30).map(|i| i as f64).collect();
        assert!(wilcoxon_z(&improving) > 4.0);
        let mixed: Vec<f64> = (1..=30)
            .map(|i| if i % 2 == 0 { i as f64 } else { -(i as f64) })
            .collect();
        assert!(wilcoxon_z(&mixed).abs() < 1.0);
    }
}
