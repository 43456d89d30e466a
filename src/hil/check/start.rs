//! How a run starts: the starting lead's cap, the starting compensation and the safe
//! start's damping, judged on the linearised loop. Must not: run anything or touch the loop.

use super::*;

/// The longest lead the run may start with: the guess, or, when the linearised loop
/// in front of an actuator twice as fast as the guess (a pure delay of half the guessed
/// effective delay: the fastest the "off by 100 %" allows, and, without a lag's
/// roll-off, the most exposed to a lead too long) is not stable at the guess, the
/// longest shorter lead with which it is (in 2 % steps). Asymmetric on purpose: a lead
/// too long makes the prediction's gain near Nyquist diverge within milliseconds (lag-delay
/// 450 + 150 us, truth 722 us, started at 1500 us: `loop-unstable` after 20 ms, before
/// the estimator has seen anything), a lead too short leaves the resonance's negative
/// damping, which the guard takes out while the lead is learned. `INFINITY` (no cap) in
/// force mode, without adaptation (`adapt = false`: the lead is the user's), when the
/// guess is stable for that actuator, or when no lead below it is.
pub fn starting_lead_cap_s(cfg: &HilConfig) -> f64 {
    let guess = cfg.compensation.initial_delay_s;
    // A lead fixed by the plan (`adapt_lead` off) is the lead, judged on the actuator; a
    // lead the user fixes (`adapt = false`: no adaptation would take it on from a cap) is
    // the user's.
    if cfg.controller.command_mode != crate::hil::config::CommandMode::Law
        || guess <= 0.0
        || !cfg.compensation.adapt
        || !cfg.compensation.adapt_lead
        || cfg.compensation.start_planned
    {
        return f64::INFINITY;
    }
    let tau = (0.5 * guess - 0.5 * cfg.loop_.dt_s()).max(0.0);
    let mut probe = LinearLoop::new(cfg, delay_and_lag(tau, 0.0), guess, 1.0);
    // Judged with the guard's full damping, the most the safe start can carry; the
    // safe start's own damping is then chosen at the capped lead
    // (`safe_start_damping_ns_per_m`), and may be less.
    if cfg.compensation.adapt && cfg.compensation.passivity_guard {
        probe.guard_damping_ns_per_m = cfg.compensation.guard_max_damping_ns_per_m;
    }
    let step = (0.02 * guess).max(5e-6);
    let mut lead = guess;
    while lead > 0.0 {
        probe.lead_s = lead;
        if probe.is_stable(0.0, 1.0) {
            return if lead == guess { f64::INFINITY } else { lead };
        }
        lead -= step;
    }
    f64::INFINITY
}

/// `cfg`'s `[compensation]` with its starting lead capped (`starting_lead_cap_s`): what
/// the controller runs with, as `plan` (`compensation_plan`) sets it.
pub fn starting_compensation(
    cfg: &HilConfig,
    plan: Option<&CompensationPlan>,
) -> crate::hil::compensation::CompensationConfig {
    // Judged at the order the run predicts with: the plan's when it raised it, else the
    // configured one (without a plan, an external rig's say, nothing raises it).
    let at_order = match plan.and_then(|p| p.raised_lead_order) {
        Some(order) => {
            let mut raised = cfg.clone();
            raised.compensation.lead_order = order;
            std::borrow::Cow::Owned(raised)
        }
        None => std::borrow::Cow::Borrowed(cfg),
    };
    // A start the plan moves (`planned`) has neither cap nor safe start's damping.
    let capped = crate::hil::compensation::CompensationConfig {
        starting_lead_cap_s: starting_lead_cap_s(&at_order),
        safe_start_damping_ns_per_m: safe_start_damping_ns_per_m(&at_order),
        ..cfg.compensation
    };
    let mut c = planned(&capped, plan);
    c.guard_damping_by_lead = guard_damping_by_lead(&at_order, &c);
    c
}

/// The guard's most damping by the lead in effect (`compensation::DampingByLead`), for a
/// run whose lead adapts and whose guard acts (`compensation` as the run has it; else no
/// cap): for each representative actuator (an effective delay of the lead less half a
/// period's hold, `DAMPING_REPRESENTATIVE_LAGS` of it a first-order lag, the rest a
/// transport delay), the longest lead with which the linearised loop in front of it is
/// stable with each damping level, and without damping. Each edge by bisection to
/// `DAMPING_EDGE_RESOLUTION_S` from the edge of the level above (less damping is stable
/// where more is: the damping acts on the velocity predicted over the lead, which
/// amplifies the band's top): about 200 evaluations of the loop, 0.2 s.
pub fn guard_damping_by_lead(
    cfg: &HilConfig,
    compensation: &crate::hil::compensation::CompensationConfig,
) -> DampingByLead {
    let c = compensation;
    if !(c.adapt && c.adapt_lead && c.passivity_guard)
        || cfg.controller.command_mode != crate::hil::config::CommandMode::Law
    {
        return DampingByLead::NONE;
    }
    let hold = 0.5 * cfg.loop_.dt_s();
    let mut probe = LinearLoop::new(cfg, delay_and_lag(0.0, 0.0), 0.0, 1.0);
    let mut out = DampingByLead::NONE;
    for (r, &lag_share) in DAMPING_REPRESENTATIVE_LAGS.iter().enumerate() {
        let mut stable = |lead: f64, damping: f64| {
            let effective = (lead - hold).max(0.0);
            probe.set_delay_and_lag(effective * (1.0 - lag_share), effective * lag_share);
            probe.lead_s = lead;
            probe.guard_damping_ns_per_m = damping;
            probe.is_stable(0.0, 1.0)
        };
        let mut from = 0.0;
        let mut edges = [f64::INFINITY; DAMPING_LEVELS + 1];
        for (k, edge) in edges.iter_mut().enumerate() {
            let damping = if k < DAMPING_LEVELS {
                c.guard_max_damping_ns_per_m / f64::from(1u32 << k)
            } else {
                0.0
            };
            *edge = longest_stable_lead(|lead| stable(lead, damping), from, c.max_delay_s);
            from = edge.min(c.max_delay_s);
        }
        let mut damped_s = [0.0; DAMPING_LEVELS];
        damped_s.copy_from_slice(&edges[..DAMPING_LEVELS]);
        out.representatives[r] = DampingEdges {
            damped_s,
            undamped_s: edges[DAMPING_LEVELS],
        };
    }
    out
}

/// The guard's most damping (`by.cap` of `full`, N s/m) over leads from 0 to `max_s`, as
/// steps: each `(up_to_s, damping)` holds from the step before it up to `up_to_s`, the last
/// to `max_s`. Read in `DAMPING_EDGE_RESOLUTION_S` steps, the resolution its edges were
/// found to (`hil --check` prints it).
pub fn damping_by_lead_steps(by: &DampingByLead, full: f64, max_s: f64) -> Vec<(f64, f64)> {
    let n = (max_s / DAMPING_EDGE_RESOLUTION_S).ceil().max(1.0) as usize;
    let mut steps: Vec<(f64, f64)> = Vec::new();
    for i in 0..=n {
        let lead = (i as f64 * DAMPING_EDGE_RESOLUTION_S).min(max_s);
        let d = by.cap(full, lead);
        match steps.last_mut() {
            Some((up_to, last)) if *last == d => *up_to = lead,
            _ => steps.push((lead, d)),
        }
    }
    steps
}

/// `damping_by_lead_steps` in words: "40 kN s/m up to 730 us, 20 up to 940 us, ...".
pub fn describe_damping_by_lead(steps: &[(f64, f64)]) -> String {
    steps
        .iter()
        .enumerate()
        .map(|(i, &(up_to, d))| {
            let amount = if d > 0.0 {
                format!("{:.1} kN s/m", d * 1e-3)
            } else {
                "none".to_string()
            };
            if i + 1 == steps.len() {
                if i == 0 {
                    format!("{amount} at every lead")
                } else {
                    format!("{amount} beyond (no actuator as slow as the lead is stable there even undamped: the cap does not apply)")
                }
            } else {
                format!("{amount} up to {:.0} us", up_to * 1e6)
            }
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// How closely `guard_damping_by_lead` finds each edge, s.
const DAMPING_EDGE_RESOLUTION_S: f64 = 10e-6;

/// The longest lead in `[from, max]` with which `stable` holds, by bisection (`from` when
/// it does not hold there, infinite when it holds at `max`).
fn longest_stable_lead(mut stable: impl FnMut(f64) -> bool, from: f64, max: f64) -> f64 {
    if !stable(from) {
        return from;
    }
    if stable(max) {
        return f64::INFINITY;
    }
    bisect_edge(stable, from, max, DAMPING_EDGE_RESOLUTION_S)
}

/// The edge of `holds` between `lo`, where it holds, and `hi`, where it does not, by
/// bisection to `resolution`: the last point found to hold (`holds` assumed to hold
/// below its edge and not above it).
pub fn bisect_edge(
    mut holds: impl FnMut(f64) -> bool,
    mut lo: f64,
    mut hi: f64,
    resolution: f64,
) -> f64 {
    while hi - lo > resolution {
        let mid = 0.5 * (lo + hi);
        if holds(mid) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    lo
}

/// The safe start's damping: the largest of `[compensation] guard_max_damping_ns_per_m`
/// and its halves down to a sixteenth with which the linearised loop at the starting lead
/// (`starting_lead_cap_s`) is stable in front of every actuator the guess allows, pure
/// delays from half the guess to the guess (`SAFE_START_DRAWS` of them, half a period
/// of hold less); the full damping when none is, or without a safe start or a guess.
/// The damping acts on the velocity predicted over the lead, whose prediction amplifies
/// the band's top, so in front of an actuator a little faster than a long lead the full
/// damping itself generates energy: `lag-delay` 500 + 80 us (0.70 ms) from a guess of 800-
/// 1000 us (the start capped at 774 us for 900) tripped `loop-unstable` within 0.1 s,
/// stable there without the damping, unstable with 40 kN s/m and stable with 20 kN s/m
/// (`hil --check` on the truth). A damping of its own size costs nothing when the lead is
/// too short: the guard's answer to energy seen goes up to the full damping.
pub fn safe_start_damping_ns_per_m(cfg: &HilConfig) -> f64 {
    let c = &cfg.compensation;
    let full = c.guard_max_damping_ns_per_m;
    let guess = c.initial_delay_s;
    if c.start_planned {
        return 0.0;
    }
    if !(c.adapt && c.adapt_lead && c.passivity_guard)
        || cfg.controller.command_mode != crate::hil::config::CommandMode::Law
        || guess <= 0.0
    {
        return full;
    }
    let lead = guess.min(starting_lead_cap_s(cfg)).min(c.max_delay_s);
    let hold = 0.5 * cfg.loop_.dt_s();
    let loops: Vec<LinearLoop> = (0..SAFE_START_DRAWS)
        .map(|i| {
            let f = 0.5 + 0.5 * i as f64 / (SAFE_START_DRAWS - 1) as f64;
            let tau = (f * guess - hold).max(0.0);
            LinearLoop::new(cfg, delay_and_lag(tau, 0.0), lead, 1.0)
        })
        .collect();
    (0..SAFE_START_HALVINGS)
        .map(|k| full / f64::from(1u32 << k))
        .find(|&d| {
            loops.iter().all(|l| {
                let mut damped = l.clone();
                damped.guard_damping_ns_per_m = d;
                damped.is_stable(0.0, 1.0)
            })
        })
        .unwrap_or(full)
}

/// The actuators the safe start's damping is judged in front of (`safe_start_damping_ns_per_m`).
const SAFE_START_DRAWS: usize = 6;
/// The full damping and its halves tried: 1, 1/2, 1/4, 1/8, 1/16.
const SAFE_START_HALVINGS: u32 = 5;
