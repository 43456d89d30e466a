//! A HIL run as a campaign of one history test (SPEC 5.1): the rig's record (measured
//! displacement, applied force) against the model the emulator ran, not recalibrated.
//! What disagrees is the loop, so only the rig artefacts are tried: `channel-delay`
//! (applied force early or late against the emulated force: delay compensation) and
//! `moving-mass` (an acceleration term: a mass the loop does not account for).
//!
//! With one test there is nothing to hold out; each artefact has one parameter against
//! hundreds of independent bins, so the in-sample improvement is the evidence, judged
//! by the lack-of-fit F test against what the residual itself leaves (not against the
//! noise estimate: a loop's record holds broadband disturbances above the band, missed
//! deadlines and the specimen's resonance, that make an extrapolated noise level
//! unreliable): an artefact is named when `F = (e0 - e1) / (e1 / (dof - 1)) > MIN_F`, or,
//! as a record's disturbances (a loop's missed deadlines) are sparse in time and inflate
//! `e1` everywhere in the F test, when it lowers the residual in at least 7 of 8
//! consecutive stretches of the record and explains at least `MIN_EXPLAINED_SHARE` of the
//! relative RMS residual; it must also explain a relative residual
//! `sqrt(e0 - e1)` above the naming rule's 1e-3 and fit inside its physical range. Gaps
//! here are relative RMS residuals, noise included.
//!
//! Must not: do I/O.

use super::verdict::{history_beyond_noise, Unexplained, MIN_GAP, MIN_RATIO};
use crate::ident::fit::{
    fit_template, relative_error, test_residuals, CycleData, EffectKind, OutOfRange, Template,
};
use crate::model::effects::{AugmentedModel, Effect, DEFAULT_TEMPERATURE_C};

/// Lack-of-fit F (one parameter) an artefact must reach; far beyond p = 0.001 (~11), as
/// neighbouring bins of a deterministic residual are not independent.
pub const MIN_F: f64 = 25.0;

/// Segments of the record compared one by one, and how many must improve when the F test
/// does not pass (a one-sided sign test, p = 0.035).
pub const N_SEGMENTS: usize = 8;
pub const MIN_SEGMENTS_IMPROVED: usize = 7;
/// Share of the relative RMS residual an artefact must explain on the stretch path.
pub const MIN_EXPLAINED_SHARE: f64 = 0.2;

/// In how many of `N_SEGMENTS` consecutive stretches of the record the candidate's
/// squared residual `after` is below the current model's `before`.
fn segments_improved(before: &[f64], after: &[f64]) -> usize {
    let n = before.len().min(after.len());
    (0..N_SEGMENTS)
        .filter(|&k| {
            let (a, b) = (k * n / N_SEGMENTS, (k + 1) * n / N_SEGMENTS);
            let sum = |r: &[f64]| r[a..b].iter().map(|x| x * x).sum::<f64>();
            sum(after) < sum(before)
        })
        .count()
}

/// The artefacts tried on a run.
pub const RUN_ARTEFACTS: [EffectKind; 2] = [EffectKind::ChannelDelay, EffectKind::MovingMass];

/// One artefact tried in one round.
#[derive(Debug, Clone)]
pub struct RunCandidate {
    pub kind: EffectKind,
    pub round: usize,
    /// Model with the artefact fitted (and the ones named before it).
    pub model: AugmentedModel,
    /// Relative squared residual with it, and its square root.
    pub error: f64,
    pub gap: f64,
    pub out_of_range: Option<OutOfRange>,
    pub qualifies: bool,
}

/// What a run's record says about the loop.
#[derive(Debug, Clone)]
pub struct RunDiagnosis {
    /// The model the emulator ran (rig artefacts of its file left out, as the emulator does).
    pub model: AugmentedModel,
    pub unit: CycleData,
    pub error_before: f64,
    pub gap_before: f64,
    pub candidates: Vec<RunCandidate>,
    pub named: Vec<EffectKind>,
    pub final_model: AugmentedModel,
    pub error_after: f64,
    pub gap_after: f64,
    pub noise_floor: f64,
    pub unexplained: Option<Unexplained>,
}

impl RunDiagnosis {
    /// Fitted force lag of the applied force behind the emulated one, s (if named).
    pub fn force_lag_s(&self) -> Option<f64> {
        self.final_model.effects.iter().find_map(|e| match e {
            Effect::ChannelDelay { force_lag_s } => Some(*force_lag_s),
            _ => None,
        })
    }
}

fn excess(error: f64, noise: f64) -> f64 {
    (error - noise).max(0.01 * noise).max(1e-300).sqrt()
}

/// The operating temperature the run's model states (temperature-shift), else 23 degC.
pub fn operating_temperature_c(model: &AugmentedModel) -> f64 {
    model
        .effects
        .iter()
        .find_map(|e| match e {
            Effect::TemperatureShift {
                operating_temperature_c,
                ..
            } => Some(*operating_temperature_c),
            _ => None,
        })
        .unwrap_or(DEFAULT_TEMPERATURE_C)
}

/// Diagnoses a run's record `unit` (a history unit) against `model`.
pub fn diagnose_run(
    model: &AugmentedModel,
    unit: CycleData,
    progress: &mut dyn FnMut(&str),
) -> RunDiagnosis {
    let mut model = model.clone();
    model.effects.retain(|e| {
        !matches!(
            e,
            Effect::ChannelDelay { .. }
                | Effect::MovingMass { .. }
                | Effect::LoadTrainResonance { .. }
        )
    });
    let dof = unit.history.as_ref().map_or(1.0, |h| h.dof);
    let noise = unit.noise_relative;
    let error_before = relative_error(&model, &unit);
    progress(&format!(
        "run record: relative residual {:.4e} against the run's model (noise {:.4e}, band to {:.0} Hz)",
        error_before.sqrt(),
        noise.sqrt(),
        unit.history.as_ref().map_or(0.0, |h| h.band_hz)
    ));
    let mut current = model.clone();
    let mut current_error = error_before;
    let mut named: Vec<EffectKind> = Vec::new();
    let mut candidates = Vec::new();
    let units = [&unit];
    for round in 1..=RUN_ARTEFACTS.len() {
        let mut best: Option<RunCandidate> = None;
        for kind in RUN_ARTEFACTS.iter().copied().filter(|k| !named.contains(k)) {
            let mut template = Template::new(current.clone(), unit.temperature_c);
            template.fit_element = false;
            template.fit_chi = false;
            let template = template.with_effect(kind, None);
            let fit = fit_template(&template, &units, &template.starts(&[]), 60);
            let fitted = template.model(&fit.params);
            let error = relative_error(&fitted, &unit);
            let out_of_range = fitted
                .effects
                .iter()
                .find(|e| e.name() == kind.name())
                .and_then(|e| kind.out_of_range(e));
            let gap = error.sqrt();
            let explained = (current_error - error).max(0.0).sqrt();
            let f_statistic = (current_error - error) / (error / (dof - 1.0).max(1.0)).max(1e-300);
            let segments = segments_improved(
                &test_residuals(&current, &unit),
                &test_residuals(&fitted, &unit),
            );
            // The stretch-by-stretch path also asks for a material share of the residual:
            // a consistent but tiny improvement is a fit to the disturbances' pattern.
            let qualifies = out_of_range.is_none()
                && explained > MIN_GAP
                && (f_statistic > MIN_F
                    || (segments >= MIN_SEGMENTS_IMPROVED
                        && explained > MIN_EXPLAINED_SHARE * current_error.sqrt()));
            progress(&format!(
                "round {round}: {:<14} residual {:.4e}{}{}",
                kind.name(),
                error.sqrt(),
                out_of_range.map_or(String::new(), |o| format!(" {o}")),
                if qualifies { " qualifies" } else { "" }
            ));
            let candidate = RunCandidate {
                kind,
                round,
                model: fitted,
                error,
                gap,
                out_of_range,
                qualifies,
            };
            if qualifies && best.as_ref().is_none_or(|b| candidate.error < b.error) {
                best = Some(candidate.clone());
            }
            candidates.push(candidate);
        }
        match best {
            Some(b) => {
                progress(&format!("round {round}: named {}", b.kind.name()));
                named.push(b.kind);
                current = b.model;
                current_error = b.error;
            }
            None => break,
        }
    }
    let gap_before = error_before.sqrt();
    let gap_after = current_error.sqrt();
    let noise_floor = noise.sqrt();
    let unexplained = (history_beyond_noise(current_error, noise, dof)
        && excess(current_error, noise) >= MIN_RATIO * noise_floor
        && gap_after >= MIN_GAP)
        .then(|| Unexplained {
            gap: excess(current_error, noise),
            noise_floor,
            where_: vec![unit.id.clone()],
            harmonic_z: 0.0,
            history_ids: vec![unit.id.clone()],
        });
    RunDiagnosis {
        model,
        unit,
        error_before,
        gap_before,
        candidates,
        named,
        final_model: current,
        error_after: current_error,
        gap_after,
        noise_floor,
        unexplained,
    }
}
