//! What a named effect's law must hold against, off the naming rule itself: a
//! springpot's single order across the bands, a discrete relaxation fitted in a springpot's
//! or a channel lead's place (`maxwell_rival`), and the load-train mode a force lag and a
//! moving mass may be together (`resonance_pair_note`, `resonance_in_pair_place`).
//!
//! Must not: name or refuse effects itself (it returns reasons and notes for `diagnose`);
//! do I/O.

use super::{
    effect_params, excess_gap, out_of_range, raw_gap, CandidateResult, Reference, Scoring,
};
use crate::ident::fit::{
    cross_validate, run_parallel, CrossValidation, CycleData, EffectKind, Template,
};
use crate::model::effects::{AugmentedModel, Effect};

/// The distinct frequencies of the harmonic tests, ascending (equal within 1e-6).
pub fn harmonic_frequencies(data: &[CycleData]) -> Vec<f64> {
    let mut freqs: Vec<f64> = data
        .iter()
        .filter(|d| !d.is_history())
        .map(|d| d.frequency_hz)
        .collect();
    freqs.sort_by(f64::total_cmp);
    freqs.dedup_by(|a, b| (*a - *b).abs() <= 1e-6 * b.abs());
    freqs
}

/// The springpot's order on the lower and the upper half of the test frequencies.
#[derive(Debug, Clone, Copy)]
pub struct BandOrders {
    /// Each half's order (on the model's clamp, 0.001 or 0.999, when the band would take
    /// it further).
    pub alpha: [f64; 2],
    /// Each half's frequency range, Hz.
    pub bands: [(f64, f64); 2],
    /// What one order for both halves costs: the smallest rise of the two halves' summed
    /// squared residuals, with the order held at either half's or midway and everything
    /// else refitted, over their residual variance. A likelihood ratio: about chi-square
    /// with one degree of freedom when the order is the same, so 9 is 3 standard errors.
    pub common_order_cost: f64,
}

/// The element and `kind` as the only free parameters: `template`'s other effects held at
/// `fit`, `kind` last. Returns that template and its start (from `fit`). None without
/// `kind` in the template.
fn effect_alone(
    template: &Template,
    fit: &crate::ident::fit::LmFit,
    kind: EffectKind,
) -> Option<(Template, Vec<f64>)> {
    let k = template.added.iter().position(|k| *k == kind)?;
    let offset = template.n_params()
        - template.added[k..]
            .iter()
            .map(|k| k.n_params())
            .sum::<usize>();
    let mut fixed = template.model(&fit.params);
    fixed.effects.retain(|e| e.name() != kind.name());
    let mut alone = Template::new(fixed, template.reference_temperature_c);
    alone.fit_element = template.fit_element;
    alone.fit_chi = template.fit_chi;
    alone.clock_spans = template.clock_spans;
    alone.drift_clock = template.drift_clock;
    alone.added = vec![kind];
    let n_kind = kind.n_params();
    let ne = alone.n_params() - n_kind;
    let mut start: Vec<f64> = fit.params[..ne].to_vec();
    start.extend_from_slice(&fit.params[offset..offset + n_kind]);
    Some((alone, start))
}

/// The springpot's order refitted on the lower and on the upper half of the test
/// frequencies (harmonic tests; the element refitted with it, every other effect held at
/// the fit on all tests; with an odd count of frequencies both halves hold the middle
/// one, which makes the comparison conservative). None without a springpot or with fewer
/// than four test frequencies.
pub fn springpot_orders_by_band(
    template: &Template,
    fit: &crate::ident::fit::LmFit,
    data: &[CycleData],
    max_iterations: usize,
) -> Option<BandOrders> {
    let (springpot, start) = effect_alone(template, fit, EffectKind::FractionalDamping)?;
    let n_params = springpot.n_params();
    let freqs = harmonic_frequencies(data);
    if freqs.len() < 4 {
        return None;
    }
    let n = freqs.len();
    let bands = [(freqs[0], freqs[(n - 1) / 2]), (freqs[n / 2], freqs[n - 1])];
    let subsets: Vec<Vec<&CycleData>> = bands
        .iter()
        .map(|&(lo, hi)| {
            data.iter()
                .filter(|d| {
                    !d.is_history()
                        && d.frequency_hz >= lo * (1.0 - 1e-6)
                        && d.frequency_hz <= hi * (1.0 + 1e-6)
                })
                .collect()
        })
        .collect();
    let free: Vec<crate::ident::fit::LmFit> = subsets
        .iter()
        .map(|subset| {
            crate::ident::fit::fit_template(
                &springpot,
                subset,
                std::slice::from_ref(&start),
                max_iterations,
            )
        })
        .collect();
    let order = |f: &crate::ident::fit::LmFit| {
        (1.0 / (1.0 + (-f.params[n_params - 1]).exp())).clamp(1e-3, 0.999)
    };
    let alpha = [order(&free[0]), order(&free[1])];
    // A half's sum of squares with the order held at `a` (the rest refitted from its own
    // free fit).
    let held = |half: usize, a: f64| {
        if (a - alpha[half]).abs() < 1e-9 {
            return free[half].sse;
        }
        let theta_a = (a / (1.0 - a)).ln();
        let subset = &subsets[half];
        crate::ident::fit::levenberg_marquardt(
            |theta: &[f64]| {
                let mut full = theta.to_vec();
                full.push(theta_a);
                springpot.residuals(&full, subset)
            },
            &free[half].params[..n_params - 1],
            max_iterations,
        )
        .sse
    };
    let separate = free[0].sse + free[1].sse;
    let common = [alpha[0], alpha[1], 0.5 * (alpha[0] + alpha[1])]
        .into_iter()
        .map(|a| held(0, a) + held(1, a))
        .fold(f64::INFINITY, f64::min);
    let dof = (free[0].n_residuals + free[1].n_residuals)
        .saturating_sub(2 * n_params)
        .max(1);
    let variance = separate / dof as f64;
    Some(BandOrders {
        alpha,
        bands,
        common_order_cost: (common - separate).max(0.0) / variance.max(1e-300),
    })
}

/// The discrete rival of an effect that adds loss rising with frequency (a springpot, a
/// force channel's lead): a second Maxwell branch (stiffness `k`, time constant `tau`) in
/// parallel with the element, fitted in its place on the harmonic tests.
#[derive(Debug, Clone, Copy)]
pub struct MaxwellRival {
    pub stiffness_n_per_m: f64,
    pub tau_s: f64,
    /// What the effect's fit is better by: the rival's sum of squares minus the effect's,
    /// over the effect's residual variance (negative: the rival fits better). A likelihood
    /// ratio between non-nested laws (the rival has as many or one more parameter): under
    /// 9 (3 standard errors) the data do not prefer the effect.
    pub advantage: f64,
    /// The same advantage on the fitted effect's own noise-free predictions (the rival
    /// fitted to them, over the same residual variance): what these tests would show were
    /// the effect the truth. Small: the design cannot tell the two apart.
    pub expected_advantage: f64,
}

/// Fits `kind`'s discrete rival (`MaxwellRival`): the template with `kind` taken out and a
/// Maxwell branch's force `k j w tau / (1 + j w tau) X` added to each harmonic test's
/// first harmonic, the element refitted with it, every other effect held at `fit`. Both
/// laws are fitted on the harmonic tests only. None without `kind` or with fewer than four
/// test frequencies.
pub fn maxwell_rival(
    template: &Template,
    fit: &crate::ident::fit::LmFit,
    data: &[CycleData],
    kind: EffectKind,
    max_iterations: usize,
) -> Option<MaxwellRival> {
    let freqs = harmonic_frequencies(data);
    if freqs.len() < 4 {
        return None;
    }
    let (alone, start) = effect_alone(template, fit, kind)?;
    let n_params = alone.n_params();
    let ne = n_params - kind.n_params();
    let harmonic: Vec<&CycleData> = data.iter().filter(|d| !d.is_history()).collect();
    let ef = crate::ident::fit::fit_template(
        &alone,
        &harmonic,
        std::slice::from_ref(&start),
        max_iterations,
    );
    let mut bare = alone.clone();
    bare.added.clear();
    // The fitted effect's own predictions, noise-free, as data.
    let ef_model = alone.model(&ef.params);
    let ideal: Vec<CycleData> = harmonic
        .iter()
        .map(|d| CycleData {
            force_harmonics_n: crate::ident::fit::predict_cycle(&ef_model, d),
            ..(*d).clone()
        })
        .collect();
    let ideal: Vec<&CycleData> = ideal.iter().collect();
    let branch_on = |tests: &[&CycleData], theta: &[f64]| -> Vec<f64> {
        let model = bare.model(&theta[..ne]);
        let (kb, tau) = (theta[ne].exp(), theta[ne + 1].exp());
        let mut out = Vec::with_capacity(tests.len() * 2);
        for d in tests {
            let mut r = crate::ident::fit::test_residuals(&model, d);
            let wt = 2.0 * std::f64::consts::PI * d.frequency_hz * tau;
            // k j wt / (1 + j wt) = k (wt^2 + j wt) / (1 + wt^2)
            let (mr, mi) = (kb * wt * wt / (1.0 + wt * wt), kb * wt / (1.0 + wt * wt));
            let (xr, xi) = d.displacement_harmonics_m[0];
            r[0] += (mr * xr - mi * xi) / d.scale_n;
            r[1] += (mr * xi + mi * xr) / d.scale_n;
            out.extend(r);
        }
        out
    };
    // Starts: the corner below, within and above the tested band, the branch's loss at the
    // band's middle matched to the effect's there (its first harmonic with and without it,
    // per displacement).
    let (f_lo, f_hi) = (freqs[0], freqs[freqs.len() - 1]);
    let f_mid = (f_lo * f_hi).sqrt();
    let w_mid = 2.0 * std::f64::consts::PI * f_mid;
    let bare_model = bare.model(&ef.params[..ne]);
    let loss_mid = harmonic
        .iter()
        .min_by(|a, b| {
            (a.frequency_hz / f_mid)
                .ln()
                .abs()
                .total_cmp(&(b.frequency_hz / f_mid).ln().abs())
        })
        .map_or(1.0, |d| {
            let (with, without) = (
                crate::ident::fit::predict_cycle(&ef_model, d)[0],
                crate::ident::fit::predict_cycle(&bare_model, d)[0],
            );
            let (dr, di) = (with.0 - without.0, with.1 - without.1);
            let (xr, xi) = d.displacement_harmonics_m[0];
            // Im(dF / X)
            ((di * xr - dr * xi) / (xr * xr + xi * xi)).abs()
        })
        .max(1.0);
    let fit_rival = |tests: &[&CycleData]| {
        let mut best: Option<crate::ident::fit::LmFit> = None;
        for corner_hz in [0.5 * f_lo, f_mid, 2.0 * f_hi, 8.0 * f_hi] {
            let tau = 1.0 / (2.0 * std::f64::consts::PI * corner_hz);
            let wt = w_mid * tau;
            let kb = loss_mid * (1.0 + wt * wt) / wt;
            let mut s0 = ef.params[..ne].to_vec();
            s0.extend_from_slice(&[kb.ln(), tau.ln()]);
            let f = crate::ident::fit::levenberg_marquardt(
                |theta: &[f64]| branch_on(tests, theta),
                &s0,
                max_iterations,
            );
            if best.as_ref().is_none_or(|b| f.sse < b.sse) {
                best = Some(f);
            }
        }
        best
    };
    let rival = fit_rival(&harmonic)?;
    let on_ideal = fit_rival(&ideal)?;
    let variance = ef.sse / ef.n_residuals.saturating_sub(n_params).max(1) as f64;
    Some(MaxwellRival {
        stiffness_n_per_m: rival.params[ne].exp(),
        tau_s: rival.params[ne + 1].exp(),
        advantage: (rival.sse - ef.sse) / variance.max(1e-300),
        expected_advantage: on_ideal.sse / variance.max(1e-300),
    })
}

/// A springpot is a law of every frequency: its loss angle is `alpha pi / 2` at each, so
/// its order fitted on the lower test frequencies and on the upper ones must agree. When
/// the two differ by more than `SPRINGPOT_ORDER_MATERIAL` and one order for both costs more
/// than `SPRINGPOT_ORDER_COST` residual variances, the springpot imitates something with a
/// time scale of its own (a discrete relaxation, a second Maxwell branch): it is not
/// named. Nor is it when that rival, fitted in its place, fits the harmonic tests better
/// (by `RIVAL_ADVANTAGE`): a relaxation whose corner lies above the tested band
/// looks like a springpot of high order within it. Returns why.
fn springpot_law_broken(
    template: &Template,
    fit: &crate::ident::fit::LmFit,
    data: &[CycleData],
    max_iterations: usize,
) -> Option<String> {
    springpot_check(template, fit, data, max_iterations).0
}

/// Why the first of `kinds` whose law has a check fails it in `template` (a springpot:
/// `springpot_law_broken`; a channel delay: `channel_delay_check`), or None: the check
/// every path that names an effect applies, alone or in a pair.
pub(super) fn law_broken(
    template: &Template,
    fit: &crate::ident::fit::LmFit,
    data: &[CycleData],
    kinds: &[EffectKind],
    max_iterations: usize,
) -> Option<String> {
    kinds.iter().find_map(|&kind| {
        let why = match kind {
            EffectKind::FractionalDamping => {
                springpot_law_broken(template, fit, data, max_iterations)
            }
            EffectKind::ChannelDelay => channel_delay_check(template, fit, data, max_iterations).0,
            _ => None,
        };
        why.map(|w| format!("`{}` {w}", kind.name()))
    })
}

/// `springpot_law_broken`'s verdict and, when the springpot stands but its discrete rival
/// fits about as well, the note a named springpot carries (what these tests cannot tell).
pub(super) fn springpot_check(
    template: &Template,
    fit: &crate::ident::fit::LmFit,
    data: &[CycleData],
    max_iterations: usize,
) -> (Option<String>, Option<String>) {
    let Some(b) = springpot_orders_by_band(template, fit, data, max_iterations) else {
        return (None, None);
    };
    let [lo, hi] = b.alpha;
    let [(f0, f1), (f2, f3)] = b.bands;
    let cost = b.common_order_cost;
    if (lo - hi).abs() > SPRINGPOT_ORDER_MATERIAL && cost > SPRINGPOT_ORDER_COST {
        return (Some(format!(
            "has no single order: alpha = {lo:.3} on the tests at {f0}-{f1} Hz, {hi:.3} on those at {f2}-{f3} Hz, and one order for both costs {cost:.1} residual variances (a likelihood ratio; 9 is 3 standard errors)"
        )), None);
    }
    rival_check(
        template,
        fit,
        data,
        EffectKind::FractionalDamping,
        RIVAL_POWER,
        max_iterations,
    )
}

/// A rival's corner above this many times the highest harmonic test frequency is a
/// dashpot to every test (its loss within 1 % of `k tau omega` up to 1/10 of the corner).
const DASHPOT_CORNER_FACTOR: f64 = 10.0;

/// A force channel's delay is named only if it beats its discrete rival: a lead of the
/// force channel adds loss rising with frequency, as a second Maxwell branch (a relaxation
/// beyond the library) does below its corner. `rival_check` for `channel-delay`.
pub(super) fn channel_delay_check(
    template: &Template,
    fit: &crate::ident::fit::LmFit,
    data: &[CycleData],
    max_iterations: usize,
) -> (Option<String>, Option<String>) {
    // A force lag takes loss away, which a branch (positive stiffness) cannot imitate.
    let lag = template
        .model(&fit.params)
        .effects
        .iter()
        .find_map(|e| match *e {
            Effect::ChannelDelay { force_lag_s } => Some(force_lag_s),
            _ => None,
        });
    if lag.is_none_or(|l| l >= 0.0) {
        return (None, None);
    }
    rival_check(
        template,
        fit,
        data,
        EffectKind::ChannelDelay,
        CHANNEL_DELAY_RIVAL_POWER,
        max_iterations,
    )
}

/// `kind` against its discrete rival (`maxwell_rival`): why it is not named when the rival
/// fits better (by more than `RIVAL_ADVANTAGE`, or at all where `kind`, were it the truth,
/// would have shown an advantage of `power` or more), else the note a named `kind` carries
/// when the two fit about as well (what these tests cannot tell). Each parameter the rival
/// has beyond `kind`'s counts as one residual variance in `kind`'s favour.
fn rival_check(
    template: &Template,
    fit: &crate::ident::fit::LmFit,
    data: &[CycleData],
    kind: EffectKind,
    power: f64,
    max_iterations: usize,
) -> (Option<String>, Option<String>) {
    let Some(mut r) = maxwell_rival(template, fit, data, kind, max_iterations) else {
        return (None, None);
    };
    r.advantage += 2.0 - kind.n_params() as f64;
    let what = match kind {
        EffectKind::FractionalDamping => "a springpot",
        EffectKind::ChannelDelay => "a channel delay",
        _ => kind.name(),
    };
    let f_hi = data
        .iter()
        .filter(|d| !d.is_history())
        .map(|d| d.frequency_hz)
        .fold(0.0, f64::max);
    let (branch, telling) = rival_branch_text(r.stiffness_n_per_m, r.tau_s, f_hi);
    if r.advantage < -RIVAL_ADVANTAGE || (r.advantage < 0.0 && r.expected_advantage >= power) {
        return (Some(format!(
            "is a discrete relaxation rather (beyond the library): {branch} fits the harmonic tests better by {:.1} residual variances, where {what} would have fitted them better by about {:.1}",
            -r.advantage,
            r.expected_advantage
        )), None);
    }
    let note = (r.advantage < RIVAL_ADVANTAGE).then(|| {
        format!(
            "not told from a discrete relaxation by these tests: {branch} fits the harmonic tests about as well ({} by {:.1} residual variances; 9 is 3 standard errors); {telling}",
            if r.advantage < 0.0 { "the branch better".to_string() } else { format!("{what} better") },
            r.advantage.abs(),
        )
    });
    (None, note)
}

/// How a fitted rival branch (`stiffness`, `tau`) is described, and which tests would tell
/// it from the effect, given the highest harmonic test frequency `f_hi`. A corner far above
/// every test (the fit ran its relaxation time towards zero) leaves a plain dashpot `k tau`:
/// no test "around the corner" can be proposed (a helper's blind campaigns, 2026-11-28:
/// "corner 298146968 Hz", tests "from 149073484 Hz").
fn rival_branch_text(stiffness_n_per_m: f64, tau_s: f64, f_hi: f64) -> (String, String) {
    let corner_hz = 1.0 / (2.0 * std::f64::consts::PI * tau_s);
    if corner_hz > DASHPOT_CORNER_FACTOR * f_hi {
        (
            format!(
                "a dashpot of {:.3e} N s/m beside the element (a second Maxwell branch whose corner ran far above every test) in its place",
                stiffness_n_per_m * tau_s
            ),
            "tests where the element's stiffness differs most (preloads, temperatures: a channel's lead adds loss in proportion to the element's stiffness, a dashpot the same at every operating point) would tell them apart".to_string(),
        )
    } else {
        (
            format!(
                "a second Maxwell branch ({:.3e} N/m, {:.3} ms, corner {:.0} Hz) in its place",
                stiffness_n_per_m,
                tau_s * 1e3,
                corner_hz
            ),
            format!(
                "tests from {:.0} to {:.0} Hz, around that corner, would tell them apart",
                0.5 * corner_hz,
                2.0 * corner_hz
            ),
        )
    }
}

/// What a named force lag `tau` beside a named moving mass `m` cannot rule out: within
/// the tests' band (far below the mode, to second order in `f / f_n`) a load-train
/// resonance `1 / (1 - r^2 + 2 i zeta r)` renders the force `2 zeta / omega_n` late and
/// larger by `K (omega / omega_n)^2`, as a negative mass `-K / omega_n^2` would; so the
/// pair is also a resonance with `zeta = tau omega_n / 2` and a participating mass
/// `m + K / omega_n^2` (`K` the element's median dynamic stiffness over the harmonic
/// tests). The note gives the modes within the library's ranges above 3x the highest test
/// frequency, and one example at zeta 0.03. None when no such mode exists.
pub(super) fn resonance_pair_note(
    model: &AugmentedModel,
    data: &[CycleData],
    refit: Option<&CandidateResult>,
) -> Option<String> {
    use crate::ident::fit::LOAD_TRAIN_DAMPING_RANGE;
    let (tau, mass) = lag_and_mass(model)?;
    let k = median_dynamic_stiffness(data)?;
    let (lo, hi) = pair_mode_family(tau, data)?;
    let f_of = |zeta: f64| zeta / (std::f64::consts::PI * tau);
    let participating = |f_n: f64| mass + k / (2.0 * std::f64::consts::PI * f_n).powi(2);
    let example = f_of(0.03).clamp(lo, hi);
    let refitted = refit.map_or(String::new(), |r| {
        let p = effect_params(&r.model, EffectKind::LoadTrainResonance);
        let m = effect_params(&r.model, EffectKind::MovingMass);
        let get = |v: &[(&str, f64)], name: &str| {
            v.iter().find(|(n, _)| *n == name).map_or(f64::NAN, |x| x.1)
        };
        let verdict = if r.qualifies {
            "fits them better by the naming rule: the data point at the mode"
        } else if r.out_of_range.is_some() {
            "fits only outside the mode's range"
        } else {
            "fits them no better (one parameter more): these tests cannot tell the two apart"
        };
        format!(
            "; refitted in the pair's place, a mode at {:.0} Hz, zeta {:.3}, with {:.1} kg {verdict} (held-out gap ratio to the pair {:.3}, z {:.2})",
            get(&p, "natural_frequency_hz"),
            get(&p, "damping_ratio"),
            get(&m, "mass_kg"),
            r.gap_ratio,
            r.wilcoxon_z
        )
    });
    Some(format!(
        "with the force lag of {:.3} ms named beside it, not told from a load-train resonance above the tests' band by these tests: a mode at {lo:.0}-{hi:.0} Hz (damping ratio {:.3}-{:.2}, 2 zeta / omega_n = the lag) with a participating mass of {:.1}-{:.1} kg (this mass plus K / omega_n^2, K = {:.3e} N/m the element's median dynamic stiffness) gives the same force within them to second order in f / f_n (e.g. {example:.0} Hz, zeta {:.3}, {:.1} kg); content near such a mode (history tests whose passages reach it, or tests at 50-150 Hz) tells them apart{refitted}",
        tau * 1e3,
        (lo * std::f64::consts::PI * tau).max(LOAD_TRAIN_DAMPING_RANGE.0),
        (hi * std::f64::consts::PI * tau).min(LOAD_TRAIN_DAMPING_RANGE.1),
        participating(hi),
        participating(lo),
        k,
        example * std::f64::consts::PI * tau,
        participating(example),
    ))
}

/// A positive force lag (s) and a positive moving mass (kg) among `model`'s effects, both
/// or none: the pair a load-train mode above the band looks like.
fn lag_and_mass(model: &AugmentedModel) -> Option<(f64, f64)> {
    let tau = model.effects.iter().find_map(|e| match *e {
        Effect::ChannelDelay { force_lag_s } if force_lag_s > 0.0 => Some(force_lag_s),
        _ => None,
    })?;
    let mass = model.effects.iter().find_map(|e| match *e {
        Effect::MovingMass { mass_kg } if mass_kg > 0.0 => Some(mass_kg),
        _ => None,
    })?;
    Some((tau, mass))
}

/// The element's median dynamic stiffness over the harmonic tests, N/m.
fn median_dynamic_stiffness(data: &[CycleData]) -> Option<f64> {
    let mut stiffness: Vec<f64> = data
        .iter()
        .filter(|d| !d.is_history())
        .map(|d| {
            let k =
                crate::ident::campaign::cdiv(d.force_harmonics_n[0], d.displacement_harmonics_m[0]);
            k.0.hypot(k.1)
        })
        .filter(|k| k.is_finite() && *k > 0.0)
        .collect();
    stiffness.sort_by(f64::total_cmp);
    stiffness.get(stiffness.len() / 2).copied()
}

/// The natural frequencies (Hz, low and high) of the load-train modes a force lag `tau`
/// stands for within the tests' band: `f_n = zeta / (pi tau)` over the library's damping
/// range, above 3x the highest harmonic test frequency and within the frequency range.
fn pair_mode_family(tau: f64, data: &[CycleData]) -> Option<(f64, f64)> {
    use crate::ident::fit::{LOAD_TRAIN_DAMPING_RANGE, LOAD_TRAIN_FREQUENCY_RANGE_HZ};
    let f_max = data
        .iter()
        .filter(|d| !d.is_history())
        .map(|d| d.frequency_hz)
        .fold(0.0, f64::max);
    let f_of = |zeta: f64| zeta / (std::f64::consts::PI * tau);
    let lo = f_of(LOAD_TRAIN_DAMPING_RANGE.0)
        .max(3.0 * f_max)
        .max(LOAD_TRAIN_FREQUENCY_RANGE_HZ.0);
    let hi = f_of(LOAD_TRAIN_DAMPING_RANGE.1).min(LOAD_TRAIN_FREQUENCY_RANGE_HZ.1);
    (lo < hi).then_some((lo, hi))
}

/// A named force lag beside a named moving mass refitted as what they may be together
/// (`resonance_pair_note`): a load-train resonance in the lag's place, the mass kept as
/// the mode's participating mass, started at two members of the family the pair stands
/// for. The two descriptions agree within the band to second order in `f / f_n`; they
/// differ where the element's stiffness varies (a mode's apparent mass `-K / omega_n^2`
/// follows the preload's stiffness, a moving mass does not) and in content near the mode.
/// Returns the resonance's result (its comparison against the pair, one parameter more),
/// `qualifies` when it passes the naming rule against the pair within every range.
pub(super) fn resonance_in_pair_place(
    template: &Template,
    cv: &CrossValidation,
    scoring: &Scoring<'_>,
    progress: &mut dyn FnMut(&str),
) -> Option<CandidateResult> {
    use crate::ident::fit::{damping_theta, LOAD_TRAIN_DAMPING_RANGE};
    let data = scoring.data;
    let options = scoring.options;
    let delay_at = template
        .added
        .iter()
        .position(|k| *k == EffectKind::ChannelDelay)?;
    let model = template.model(&cv.full_fit.params);
    let (tau, mass) = lag_and_mass(&model)?;
    let k = median_dynamic_stiffness(data)?;
    let (lo, hi) = pair_mode_family(tau, data)?;
    let mut base = template.clone();
    base.added.remove(delay_at);
    base.added.push(EffectKind::LoadTrainResonance);
    let mass_at = base
        .added
        .iter()
        .position(|k| *k == EffectKind::MovingMass)?;
    let mut theta = cv.full_fit.params.clone();
    theta.remove(template.effect_param_offset(delay_at));
    let mass_offset = base.effect_param_offset(mass_at);
    let templates: Vec<Template> = [0.25, 0.6]
        .iter()
        .map(|&x| {
            let f_n = lo * (hi / lo).powf(x);
            let zeta = (std::f64::consts::PI * f_n * tau)
                .clamp(LOAD_TRAIN_DAMPING_RANGE.0, LOAD_TRAIN_DAMPING_RANGE.1);
            let mut start = theta.clone();
            start[mass_offset] = (mass + k / (2.0 * std::f64::consts::PI * f_n).powi(2)) / 10.0;
            start.extend([f_n.ln(), damping_theta(zeta)]);
            let mut t = base.clone();
            t.start_prefix = Some(start);
            t
        })
        .collect();
    let fitted = run_parallel(&templates, options.n_threads, |t| {
        cross_validate(
            t,
            data,
            scoring.folds,
            scoring.n_folds,
            options.max_iterations,
            options.n_threads,
        )
    });
    let (t, fit) = templates
        .into_iter()
        .zip(fitted)
        .min_by(|a, b| a.1.full_fit.sse.total_cmp(&b.1.full_fit.sse))?;
    let reference = Reference {
        errors: &cv.held_out_error,
        gap: excess_gap(&cv.held_out_error, data),
        raw: raw_gap(&cv.held_out_error, data),
    };
    let raw = raw_gap(&fit.held_out_error, data);
    let m = scoring.compare(&fit.held_out_error, raw, 1, &reference);
    let model = t.model_with_errors(&fit.full_fit);
    let out_of_range = out_of_range(&model, &[EffectKind::LoadTrainResonance]);
    progress(&format!(
        "the force lag and moving mass refitted as a load-train resonance with its mass: held-out gap {:.4e} against the pair's {:.4e}, ratio {:.3}, z {:.2}, folds {}/{}{}{}",
        excess_gap(&fit.held_out_error, data),
        reference.gap,
        m.gap_ratio,
        m.z,
        m.folds_improved,
        scoring.n_folds,
        out_of_range.map_or(String::new(), |o| format!(" {o}")),
        if m.qualifies { " qualifies" } else { "" }
    ));
    Some(CandidateResult {
        kind: EffectKind::LoadTrainResonance,
        round: 0,
        raw_gap: raw,
        cv: fit,
        gap_ratio: m.gap_ratio,
        raw_ratio: m.raw_ratio,
        score: m.score,
        wilcoxon_z: m.z,
        folds_improved: m.folds_improved,
        history_evidence: m.history_evidence,
        qualifies: m.qualifies && out_of_range.is_none(),
        would_qualify: m.qualifies,
        out_of_range,
        law_broken: None,
        model,
        template: t,
        law_note: None,
        stand_in: None,
    })
}

/// Residual variances beyond which one of an effect and its discrete rival
/// (`maxwell_rival`) fits the harmonic tests better: 3 standard errors. A rival better by
/// more keeps the effect from being named; within it either way, a named effect says these
/// tests do not tell the two apart.
const RIVAL_ADVANTAGE: f64 = 9.0;
/// Advantage a springpot would show over its rival, were it the truth, from which the
/// design counts as able to tell them apart: then a rival that fits better at all keeps it
/// from being named. Between non-nested laws the advantage's spread is about `2 sqrt(E)`
/// for an expected `E`, so at 4 a true springpot still loses about one time in six; the
/// weak branches this refuses (docs/diagnose.md) were measured with it.
const RIVAL_POWER: f64 = 4.0;
/// The same for a channel delay: 16, two spreads (a true lead refused about one time in
/// forty): a true lead is told from the branch by the preload, which scales it.
const CHANNEL_DELAY_RIVAL_POWER: f64 = 16.0;

/// Likelihood ratio (residual variances) beyond which the two band orders disagree: 3
/// standard errors of one degree of freedom.
const SPRINGPOT_ORDER_COST: f64 = 9.0;
/// Smallest difference of the band orders that counts (a tenth of the order's range).
const SPRINGPOT_ORDER_MATERIAL: f64 = 0.1;

#[cfg(test)]
mod tests {
    use super::*;

    /// A branch with its corner near the tests is named by its corner and the band that
    /// would tell it apart; one whose corner ran far above every test (0.5 ns: 318 MHz) is
    /// the dashpot `k tau` it is to every test, with no band beyond them proposed.
    #[test]
    fn a_rival_whose_corner_ran_away_is_described_as_the_dashpot_it_is() {
        let (branch, telling) = rival_branch_text(2e6, 2e-3, 20.0);
        assert!(branch.contains("corner 80 Hz"), "{branch}");
        assert!(telling.contains("from 40 to 159 Hz"), "{telling}");
        let (branch, telling) = rival_branch_text(3.2e13, 0.5e-9, 20.0);
        assert!(branch.contains("dashpot of 1.600e4 N s/m"), "{branch}");
        assert!(!telling.contains("Hz"), "{telling}");
        assert!(!branch.contains("Hz"), "{branch}");
    }
}
