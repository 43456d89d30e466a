//! `summary.md`: the headline figures of `summary.json` beside the paper's published
//! values, with one line on each difference. Pure formatting: reads the JSON object that
//! `run_all` built, returns Markdown; no simulation and no I/O here.

use std::fmt::Write as _;

use serde_json::Value;

/// The number at `path` in `summary` (NaN if absent or null).
fn num(summary: &Value, path: &[&str]) -> f64 {
    path.iter()
        .try_fold(summary, |v, key| v.get(*key))
        .and_then(Value::as_f64)
        .unwrap_or(f64::NAN)
}

/// The F12 peak entry for a model and preload.
fn peak<'a>(summary: &'a Value, model: &str, preload_n: f64) -> Option<&'a Value> {
    summary["f12"]["peaks"]
        .as_array()?
        .iter()
        .find(|p| p["model"].as_str() == Some(model) && p["preload_n"].as_f64() == Some(preload_n))
}

fn pnum(entry: Option<&Value>, key: &str) -> f64 {
    entry.and_then(|e| e[key].as_f64()).unwrap_or(f64::NAN)
}

/// The Markdown summary for a `summary.json` object.
pub fn markdown(s: &Value) -> String {
    let mut md = String::new();
    let w = &mut md;
    let _ = writeln!(
        w,
        "# `fastemu paper`: headline figures beside the paper's\n"
    );
    if s["quick"].as_bool() == Some(true) {
        let _ = writeln!(
            w,
            "**Quick run (`--quick`): coarse grids and short settling; numbers are rough.**\n"
        );
    }
    let _ = writeln!(
        w,
        "Models: *paper form* = Table 3 integrated as paper Eq. 3 with P replaced by the \
         instantaneous force (what the published figures used); *consistent form* = SPEC 2.1 \
         (small-signal modulus exactly Eq. 2); *linear* = Kelvin-Voigt 80 MN/m^2, \
         1e-3 MN s/m^2. F10-F14 per metre of ERS (rail 60.21 kg/m); F5 and F8 on the 750 mm \
         sample. Sign: displacement and force positive in compression (SPEC 2). The paper \
         draws Fig. 8's external force with compression negative: our F8 plot does the same \
         (axis says so) and the F8 values below are in that paper sign; all CSVs use the \
         SPEC sign.\n"
    );

    // F10 / T3.
    let _ = writeln!(w, "## T3, F10: equivalent stiffness and damping (Eq. 2)\n");
    let c_lo = num(
        s,
        &["f10", "eq2_by_preload", "0", "c_eq_at_0_5_hz_ns_per_m2"],
    );
    let by_preload = s["f10"]["eq2_by_preload"].as_array();
    let c_first = by_preload
        .and_then(|a| a.first())
        .and_then(|e| e["c_eq_at_0_5_hz_ns_per_m2"].as_f64())
        .unwrap_or(c_lo);
    let c_last = by_preload
        .and_then(|a| a.first())
        .and_then(|e| e["c_eq_at_250_hz_ns_per_m2"].as_f64())
        .unwrap_or(f64::NAN);
    let _ = writeln!(
        w,
        "| quantity | ours | paper |\n|---|---|---|\n\
         | c_eq at 6 kN, 0.5 Hz -> 250 Hz | {:.2} -> {:.1e} MN s/m^2 | ~1 -> ~1e-4 MN s/m^2 |\n\
         | linear model | 80 MN/m^2, 1e-3 MN s/m^2 | same |\n",
        c_first * 1e-6,
        c_last * 1e-6
    );
    let _ = writeln!(
        w,
        "Eq. 2 evaluated exactly (T3 CSV holds the Table 2 grid). The dashed curves are the \
         paper form's own small-signal values (SPEC 2.1): up to 70 % less damping at 55 kN, \
         which explains most differences below.\n"
    );

    // F5.
    let _ = writeln!(w, "## F5: force-controlled loops (750 mm sample)\n");
    let _ = writeln!(
        w,
        "| case | model | k_eq per m (MN/m^2) | c_eq per m (MN s/m^2) |"
    );
    let _ = writeln!(w, "|---|---|---|---|");
    if let Some(loops) = s["f5"]["loops"].as_array() {
        for l in loops {
            let _ = writeln!(
                w,
                "| {:.0} kN, {:.0} Hz | {} | {:.1} | {:.3} |",
                num(l, &["preload_n"]) * 1e-3,
                num(l, &["frequency_hz"]),
                l["model"].as_str().unwrap_or("?"),
                num(l, &["k_eq_per_metre_n_per_m2"]) * 1e-6,
                num(l, &["c_eq_per_metre_ns_per_m2"]) * 1e-6
            );
        }
    }
    let _ = writeln!(
        w,
        "\nThe paper shows the loops only as plots beside measured ones. The consistent \
         form's loops reproduce Eq. 2 (5 kN is a small amplitude); the paper form's are \
         stiffer and less damped, as its linearisation predicts.\n"
    );

    // F8.
    let _ = writeln!(
        w,
        "## F8: force imposing the 200 km/h passage (750 mm sample)\n"
    );
    let _ = writeln!(
        w,
        "| model | 1st valley (kN) | 2nd valley (kN) | positive overshoot after (kN) |\n|---|---|---|---|"
    );
    for model in ["paper", "consistent", "linear"] {
        let _ = writeln!(
            w,
            "| {model} | {:.1} | {:.1} | {:+.2} |",
            num(s, &["f8", model, "first_valley_paper_sign_n"]) * 1e-3,
            num(s, &["f8", model, "second_valley_paper_sign_n"]) * 1e-3,
            num(s, &["f8", model, "overshoot_paper_sign_n"]) * 1e-3
        );
    }
    let _ = writeln!(
        w,
        "\nPaper: the 2nd valley is smaller than the 1st and the force goes positive after \
         the valleys; no numbers are printed. Both Zener forms reproduce both features (the \
         Maxwell branch relaxes during compression, so unloading leaves it in tension); the \
         linear model gives equal valleys and only the small positive force of the Winkler \
         uplift.\n"
    );

    // F11.
    let _ = writeln!(
        w,
        "## F11: free response to a 55 kN step (null initial conditions)\n"
    );
    let _ = writeln!(
        w,
        "| model | natural frequency (Hz) | 90 % decay (s) | damping ratio | paper |\n|---|---|---|---|---|"
    );
    let paper_f11 = [
        (
            "paper",
            "shorter period, larger amplitude, 90 % decay 7.6 s",
        ),
        ("consistent", "(not in the paper)"),
        ("linear", "~185 Hz (0.0054 s period), 90 % decay ~0.3 s"),
    ];
    for (model, published) in paper_f11 {
        let decay = s["f11"][model]["decay_90_percent_s"].as_f64();
        let _ = writeln!(
            w,
            "| {model} | {:.1} | {} | {:.5} | {published} |",
            num(s, &["f11", model, "natural_frequency_hz"]),
            decay.map_or("not reached".to_string(), |d| format!("{d:.2}")),
            num(s, &["f11", model, "damping_ratio"])
        );
    }
    let _ = writeln!(
        w,
        "\nLinear: 183.4 Hz, zeta 0.0072 and 0.277 s, as the closed form gives; the paper \
         rounds to 185 Hz and 0.3 s. As published, the paper form oscillates faster than the \
         linear model (shorter period) with a larger first swing ({:.3} vs {:.3} mm). Paper form: {:.1} s instead of 7.6 s. Our decay rate \
         ({:.3} 1/s) matches the paper form's linearised damping at 55 kN and ~185 Hz \
         (~31 N s/m, 0.255 1/s, 9.0 s): the paper's 7.6 s needs ~20 % more damping than its \
         own equations give, plausibly from its integrator's numerical dissipation or a \
         different reading of the envelope; we cannot check either. The consistent form \
         decays in {:.1} s (damping = Eq. 2's c_eq, ~111 N s/m).\n",
        num(s, &["f11", "paper", "first_amplitude_m"]) * 1e3,
        num(s, &["f11", "linear", "first_amplitude_m"]) * 1e3,
        num(s, &["f11", "paper", "decay_90_percent_s"]),
        num(s, &["f11", "paper", "fitted_decay_rate_per_s"]),
        num(s, &["f11", "consistent", "decay_90_percent_s"])
    );

    // F12.
    let _ = writeln!(w, "## F12: steady-state harmonic response (F1 = 1 kN)\n");
    let lin_peak = num(s, &["f12", "linear", "peak_amplitude_ratio_m_per_n"]);
    let lin_peak_f = num(s, &["f12", "linear", "peak_frequency_hz"]);
    let _ = writeln!(
        w,
        "Linear model: exact peak {:.2} Hz, {:.3e} m/N (grid peak {:.0} Hz, {:.3e} m/N).\n",
        lin_peak_f,
        lin_peak,
        num(s, &["f12", "linear", "grid_peak_frequency_hz"]),
        num(s, &["f12", "linear", "grid_peak_amplitude_ratio_m_per_n"])
    );
    let _ = writeln!(
        w,
        "| model | P (kN) | grid peak (Hz) | grid peak / linear grid peak | true peak (Hz) | true peak / linear peak | shift from linear peak (Hz) | small-signal peak / linear peak |\n|---|---|---|---|---|---|---|---|"
    );
    for model in ["paper", "consistent"] {
        for preload in [6e3, 18e3, 37e3, 55e3] {
            let e = peak(s, model, preload);
            let _ = writeln!(
                w,
                "| {model} | {:.0} | {:.0} | {:.2} | {:.2} | {:.2} | {:+.1} | {:.1} |",
                preload * 1e-3,
                pnum(e, "grid_peak_frequency_hz"),
                pnum(e, "grid_peak_over_linear_grid_peak"),
                pnum(e, "true_peak_frequency_hz"),
                pnum(e, "true_peak_over_linear_peak"),
                pnum(e, "frequency_shift_from_linear_peak_hz"),
                pnum(e, "small_signal_peak_over_linear_peak")
            );
        }
    }
    let peaks: Vec<&Value> = s["f12"]["peaks"]
        .as_array()
        .map(|a| a.iter().collect())
        .unwrap_or_default();
    let range = |key: &str| {
        peaks
            .iter()
            .filter_map(|p| p[key].as_f64())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(v), hi.max(v))
            })
    };
    let (true_lo, true_hi) = range("true_peak_over_linear_peak");
    let (grid_lo, grid_hi) = range("grid_peak_over_linear_grid_peak");
    let (shift_lo, shift_hi) = range("frequency_shift_from_linear_peak_hz");
    let (ss_lo, ss_hi) = range("small_signal_peak_over_linear_peak");
    let _ = writeln!(
        w,
        "\nPaper: nonlinear peaks ~3x the linear one, peak frequency shifted by ~4 Hz, higher \
         preload -> higher peak and frequency. We get the ordering and a shift of {shift_lo:+.1} \
         to {shift_hi:+.1} Hz (smallest at high preload), but peaks only {grid_lo:.1}-{grid_hi:.1}x \
         the linear one on the grid and {true_lo:.1}-{true_hi:.1}x at the true peaks. Why: at resonance a 1 kN force would need displacement \
         amplitudes of several mm (the small-signal peaks are {ss_lo:.0}-{ss_hi:.0}x linear, last \
         column), i.e. element forces far below -P0 = -64 kN where Eq. 1's factor \
         (1 + F/P0)^chi goes to zero. Runs at or next to each peak leave the model's domain \
         (tension clamped and flagged: `true_peak_tension_clamped`, and on the grid \
         `grid_tension_clamped_band_hz`, the 0-2 points nearest the peak), so the peak is \
         set by that softening, not by damping. The paper's ~3x depends on how its code \
         handled the same out-of-domain region, which it does not say. The shift: at 6 kN \
         Eq. 2 gives k_eq ~72.9 MN/m^2 near 175 Hz against the linear 80 MN/m^2, which alone \
         puts the small-signal resonance ~8 Hz below the linear one (175.1 vs 183.4 Hz); the \
         1 kN softening adds a few Hz more. A ~4 Hz shift at 6 kN would need k_eq ~76.6 \
         MN/m^2, which Table 3 does not give; our shift is ~4 Hz only at 37 kN. The \
         response near the peak jumps (softening): each run starts from static equilibrium, \
         so the curves are that branch, and the true peak sits at a jump edge (see the \
         0.25 Hz scan dots and `f12_peak_scans.csv`). Max settling change between the last \
         two windows: {:.1e} (runs had settled).\n",
        num(s, &["f12", "max_settle_change"])
    );

    // F13.
    let _ = writeln!(w, "## F13: coach at 72 km/h + 20 N at 170 Hz (per metre)\n");
    let _ = writeln!(
        w,
        "| quantity | paper form / linear | consistent / linear | paper |\n|---|---|---|---|"
    );
    let ratio = |model: &str, key: &str| num(s, &["f13", &format!("{model}_over_linear"), key]);
    let _ = writeln!(
        w,
        "| max low-frequency displacement | {:.3} | {:.3} | ~1.11 |",
        ratio("paper", "low_frequency_displacement_ratio"),
        ratio("consistent", "low_frequency_displacement_ratio")
    );
    let v_ratio = |model: &str| {
        num(s, &["f14", model, "velocity_170_hz_m_per_s"])
            / num(s, &["f14", "linear", "velocity_170_hz_m_per_s"])
    };
    let _ = writeln!(
        w,
        "| 170 Hz line of the rail velocity over the 3 s window (F14) | {:.2} | {:.2} | ~2.5-3 |",
        v_ratio("paper"),
        v_ratio("consistent")
    );
    let _ = writeln!(
        w,
        "| 170 Hz half swing in 1.7-1.8 s (Fig. 13b window) | {:.1} | {:.1} | ~3 |",
        ratio("paper", "ripple_half_swing_ratio"),
        ratio("consistent", "ripple_half_swing_ratio")
    );
    let _ = writeln!(
        w,
        "\nLow frequency: the paper form gives {:.1} % more displacement than linear, the \
         consistent form {:.1} %, against the paper's ~11 %; the Zener forms differ in their \
         static branch (secant vs tangent use of k1(P)), which brackets the published value. \
         170 Hz: over the whole passage the 170 Hz line is ~3x linear, as published. In the \
         1.7-1.8 s window alone the ratio is larger because the element is nearly unloaded \
         there: the nonlinear natural frequency drops to 173.5 Hz (linear 183.4 Hz), so \
         170 Hz is 4x closer to resonance, and the start-up transient at 173.5 Hz still rings \
         (beats with 170 Hz); the paper's Fig. 13b likely shows a different phase of that beat.\n",
        (ratio("paper", "low_frequency_displacement_ratio") - 1.0) * 100.0,
        (ratio("consistent", "low_frequency_displacement_ratio") - 1.0) * 100.0
    );

    // F14.
    let _ = writeln!(w, "## F14: spectra over 0-3 s (Hann window)\n");
    let _ = writeln!(
        w,
        "| model | velocity peak in 171-180 Hz (Hz) | its amplitude / 170 Hz line | prominence over the trough |\n|---|---|---|---|"
    );
    for model in ["paper", "consistent", "linear"] {
        let p = &s["f14"][model]["velocity_peak_171_to_180_hz"];
        let _ = writeln!(
            w,
            "| {model} | {:.2} | {:.2} | {:.1} |",
            num(p, &["frequency_hz"]),
            num(p, &["amplitude"]) / num(s, &["f14", model, "velocity_170_hz_m_per_s"]),
            num(p, &["prominence"])
        );
    }
    let _ = writeln!(
        w,
        "\nPaper: a peak near 173 Hz only for the nonlinear model (transient response). Ours: \
         the Zener forms show a clear peak at ~173.7 Hz (their natural frequency near zero \
         preload); the linear model has only the Hann side lobes of the 170 Hz line there \
         (prominence ~1), since its transient dies within 0.3 s where the window is ~0.\n"
    );
    md
}
