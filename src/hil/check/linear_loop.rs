//! The linearised loop (`LinearLoop`): stability by the argument principle, margins, the
//! stable leads, the predicted rendering and its plot. Must not: run anything or touch the loop.
//!
//! The loop's characteristic function on the imaginary axis is
//! `D(jw) = -m w^2 + jw c + H_u(jw) P(jw) Z(jw) / g + jw H_v(jw)`, with `Z` the element's
//! complex modulus, `P` the rig's prediction (the Lagrange weights' response, and the
//! zero-order hold), `H_u` the actuator's force per command and `H_v` its force per
//! specimen velocity. `D` is a retarded quasi-polynomial of degree 2 whose open loop has no
//! right-half-plane pole, so (Stepan's argument principle) the loop is stable exactly when
//! the argument of `D(jw)` rises by `pi` from `w = 0` to `w -> inf`. The margins come from
//! bisection on that test: the extra actuator delay the loop tolerates (both ways) and the
//! gain factor; the thinnest frequency is where `|1 + L|` is smallest,
//! `L = (D - D_open) / D_open`, `D_open = -m w^2 + jw c + jw H_v`.

use super::*;

/// The report's faithful band: amplitude within 1 %, phase within 2 degrees, looked for
/// from 1 Hz up to 200 Hz (`hil::report::compensation`).
const FAITHFUL_AMPLITUDE: f64 = 0.01;
const FAITHFUL_PHASE_DEG: f64 = 2.0;
const FAITHFUL_TOP_HZ: f64 = 200.0;
/// The margins' bisections stop at 1 ns of delay error and 1e-6 of gain (they print to
/// the us and the hundredth).
const MARGIN_DELAY_RESOLUTION_S: f64 = 1e-9;
const MARGIN_GAIN_RESOLUTION: f64 = 1e-6;

/// The linearised loop.
#[derive(Debug, Clone)]
pub struct LinearLoop {
    pub mass_kg: f64,
    pub damping_ns_per_m: f64,
    pub period_s: f64,
    pub lead_s: f64,
    pub lead_order: u32,
    pub gain: f64,
    /// Damping the guard adds on the velocity high-passed at `guard_corner_hz`, N s/m.
    pub guard_damping_ns_per_m: f64,
    pub guard_corner_hz: f64,
    /// The actuator's own poles in the right half-plane (`ActuatorPlant::unstable_poles`):
    /// a servo loop unstable by itself; the stability count needs them.
    pub actuator_unstable_poles: usize,
    /// The element's modulus `k_eq(w) + j w c_eq(w)` at the preload, on the frequency grid.
    element: Vec<Complex64>,
    /// The same at the programme's lowest and highest load where they differ from the
    /// preload (`programme_load_range`): the element stiffens with its load, and an axle's
    /// load can take a loop stable at the preload past its edge (`unstable_loads_n`).
    other_elements: Vec<(f64, Vec<Complex64>)>,
    /// Actuator responses on the grid: force per command, force per specimen velocity.
    actuator_u: Vec<Complex64>,
    actuator_v: Vec<Complex64>,
    omega: Vec<f64>,
    /// Per grid point: `e^(-j w k T)` for the 4 newest samples, and the zero-order hold
    /// (computed once: the stability scans evaluate thousands of leads on the same grid).
    delays: Vec<[Complex64; 4]>,
    zoh: Vec<Complex64>,
}

/// A prediction's value and slope weights (`rig::servo::lead_weights`).
type Weights = ([f64; 4], [f64; 4]);

/// What `--check` reports.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Margins {
    pub stable: bool,
    /// The largest extra actuator delay the loop stays stable with (the actuator slower
    /// than the lead assumes), us; `null` in JSON when already unstable.
    pub delay_error_tolerated_slower_us: Option<f64>,
    /// The same with the actuator faster than the lead assumes, us.
    pub delay_error_tolerated_faster_us: Option<f64>,
    /// The factor on the rendered force at which the loop becomes unstable (above 1).
    pub gain_margin: Option<f64>,
    /// Where the loop comes nearest to instability: the frequency of the smallest
    /// `|1 + L|`, Hz, and that distance.
    pub thinnest_frequency_hz: f64,
    pub modulus_margin: f64,
}

/// Frequency grid: 0.05 Hz steps near 0 up to Nyquist, dense enough for the unwrapped
/// phase of a 20 ms delay (a step of 0.25 Hz turns it by 1.8 degrees).
fn grid(period_s: f64) -> Vec<f64> {
    let nyquist_hz = 0.5 / period_s;
    let mut f = Vec::new();
    let mut x = 0.05;
    while x < nyquist_hz {
        f.push(2.0 * PI * x);
        x += if x < 5.0 { 0.05 } else { 0.25 };
    }
    f
}

/// The responses `(H_u, H_v)` of an actuator that is a transport delay `tau_s` and a
/// first-order lag `lag_s` (a pure delay when `lag_s` is 0): the representatives the
/// checks judge where no plant is known (`LinearLoop::new`'s `actuator`).
pub fn delay_and_lag(tau_s: f64, lag_s: f64) -> impl Fn(f64) -> (Complex64, Complex64) + Copy {
    move |w| {
        (
            Complex64::from_polar(1.0, -w * tau_s) / Complex64::new(1.0, w * lag_s),
            Complex64::new(0.0, 0.0),
        )
    }
}

impl LinearLoop {
    /// The configured loop; `actuator(w)` gives `(H_u, H_v)` at circular frequency `w`.
    pub fn new(
        cfg: &HilConfig,
        actuator: impl Fn(f64) -> (Complex64, Complex64),
        lead_s: f64,
        gain: f64,
    ) -> LinearLoop {
        let omega = grid(cfg.loop_.dt_s());
        let preload = cfg.scenario.preload_n;
        let element = element_modulus(cfg, &omega, preload);
        let other_elements = Vec::new();
        let (actuator_u, actuator_v) = omega.iter().map(|&w| actuator(w)).unzip();
        let h = cfg.loop_.dt_s();
        let delays = omega
            .iter()
            .map(|&w| std::array::from_fn(|k| Complex64::from_polar(1.0, -w * k as f64 * h)))
            .collect();
        let zoh = omega
            .iter()
            .map(|&w| {
                if w * h > 1e-9 {
                    (Complex64::new(1.0, 0.0) - Complex64::from_polar(1.0, -w * h))
                        / Complex64::new(0.0, w * h)
                } else {
                    Complex64::new(1.0, 0.0)
                }
            })
            .collect();
        LinearLoop {
            mass_kg: cfg.rig.specimen_mass_kg,
            damping_ns_per_m: cfg.rig.damping_ns_per_m,
            period_s: cfg.loop_.dt_s(),
            lead_s,
            lead_order: cfg.compensation.lead_order,
            gain,
            guard_damping_ns_per_m: 0.0,
            guard_corner_hz: cfg.compensation.guard_band_hz,
            actuator_unstable_poles: 0,
            element,
            other_elements,
            actuator_u,
            actuator_v,
            omega,
            delays,
            zoh,
        }
    }

    /// The same loop judged also at `loads_n` (`programme_loads_n`): the element's
    /// modulus at each, for `unstable_loads_n` (the stability decisions stay at the
    /// preload, so the loops the plan and the cap scan by the thousand do without them).
    pub fn with_loads(mut self, cfg: &HilConfig, loads_n: &[f64]) -> Self {
        self.other_elements = loads_n
            .iter()
            .map(|&l| (l, element_modulus(cfg, &self.omega, l)))
            .collect();
        self
    }

    /// `with_loads` at the programme's lowest and highest load.
    pub fn with_programme_loads(self, cfg: &HilConfig) -> Self {
        let loads = programme_loads_n(cfg);
        self.with_loads(cfg, &loads)
    }

    /// The same loop in front of another actuator (`actuator(w)` as in `new`), on the same
    /// grid: the scans that judge many actuators need not recompute the element.
    pub fn set_actuator(&mut self, actuator: impl Fn(f64) -> (Complex64, Complex64)) {
        for (i, &w) in self.omega.iter().enumerate() {
            (self.actuator_u[i], self.actuator_v[i]) = actuator(w);
        }
        self.actuator_unstable_poles = 0;
    }

    /// The same loop in front of a transport delay `tau_s` and a first-order lag `lag_s`
    /// (`delay_and_lag`).
    pub fn set_delay_and_lag(&mut self, tau_s: f64, lag_s: f64) {
        self.set_actuator(delay_and_lag(tau_s, lag_s));
    }

    /// The configured loop in front of `plant`: its responses and its own unstable poles.
    pub fn for_plant(cfg: &HilConfig, plant: &ActuatorPlant, lead_s: f64, gain: f64) -> Self {
        let p = *plant;
        let mut l = LinearLoop::new(cfg, move |w| p.response(w), lead_s, gain);
        l.actuator_unstable_poles = plant.unstable_poles();
        l
    }

    /// The rig's prediction and zero-order hold at grid point `i`: the displacement and
    /// velocity predicted over the lead from the newest samples, per displacement, held
    /// over the period.
    fn predicted(&self, i: usize, weights: &Weights) -> (Complex64, Complex64) {
        let (value, slope) = weights;
        let (mut p, mut v) = (Complex64::new(0.0, 0.0), Complex64::new(0.0, 0.0));
        for (k, z) in self.delays[i].iter().enumerate() {
            p += value[k] * z;
            v += slope[k] * z;
        }
        (p * self.zoh[i], v * self.zoh[i])
    }

    /// The guard's damping force per displacement at `w`: its damping on the predicted
    /// velocity less that velocity's first-order low-pass at the guard's corner, as the
    /// rig evaluates it (`rig::servo`, updated each period before the force).
    fn guard_force(&self, i: usize, velocity: Complex64) -> Complex64 {
        if self.guard_damping_ns_per_m == 0.0 {
            return Complex64::new(0.0, 0.0);
        }
        let a = 1.0 - (-2.0 * PI * self.guard_corner_hz * self.period_s).exp();
        let z1 = self.delays[i][1];
        let low = a / (Complex64::new(1.0, 0.0) - (1.0 - a) * z1);
        self.guard_damping_ns_per_m * velocity * (Complex64::new(1.0, 0.0) - low)
    }

    /// Open part and loop part of `D` at grid point `i` with an extra delay and a gain
    /// factor on the actuator's force per command.
    /// The prediction's weights for the lead in effect (once per sweep, not per point).
    fn weights(&self) -> Weights {
        lead_weights(self.lead_order as usize, self.period_s, self.lead_s)
    }

    fn parts(
        &self,
        i: usize,
        extra_delay_s: f64,
        gain_factor: f64,
        weights: &Weights,
    ) -> (Complex64, Complex64) {
        self.parts_on(&self.element, i, extra_delay_s, gain_factor, weights)
    }

    /// `parts` with the element's modulus `element` (at one of the judged loads).
    fn parts_on(
        &self,
        element: &[Complex64],
        i: usize,
        extra_delay_s: f64,
        gain_factor: f64,
        weights: &Weights,
    ) -> (Complex64, Complex64) {
        let w = self.omega[i];
        let jw = Complex64::new(0.0, w);
        let open = Complex64::new(-self.mass_kg * w * w, 0.0)
            + jw * self.damping_ns_per_m
            + jw * self.actuator_v[i];
        let delay = if extra_delay_s == 0.0 {
            Complex64::new(gain_factor, 0.0)
        } else {
            Complex64::from_polar(gain_factor, -w * extra_delay_s)
        };
        let (position, velocity) = self.predicted(i, weights);
        let rendered =
            self.actuator_u[i] * delay * (position * element[i] + self.guard_force(i, velocity))
                / self.gain;
        (open, rendered)
    }

    /// Stability by the argument principle (module doc), at the preload.
    pub fn is_stable(&self, extra_delay_s: f64, gain_factor: f64) -> bool {
        self.is_stable_on(&self.element, extra_delay_s, gain_factor, &self.weights())
    }

    /// The programme's loads (N) other than the preload at which the loop as it stands
    /// is unstable: its lowest and highest where they differ from the preload. The
    /// element stiffens with its load, so an axle's peak can take a loop stable at the
    /// preload past its edge: `lag-delay` 1003 + 99 us with a lead of 1100 us is stable at
    /// 20 kN and not at 71.9 kN, and tripped `loop-unstable` at the first axle. The
    /// decisions (the plan, the cap, the margins) stay at the preload: an axle's peak is
    /// brief, and the plan's leads judged there ran the servo-hydraulic presets with less
    /// error than those judged at the peak as well (docs/compensation.md).
    pub fn unstable_loads_n(&self) -> Vec<f64> {
        let weights = self.weights();
        self.other_elements
            .iter()
            .filter(|(_, e)| !self.is_stable_on(e, 0.0, 1.0, &weights))
            .map(|(l, _)| *l)
            .collect()
    }

    /// The programme's loads (N) judged besides the preload.
    pub fn other_loads_n(&self) -> Vec<f64> {
        self.other_elements.iter().map(|(l, _)| *l).collect()
    }

    /// The leads (10 us steps up to `max_lead_s`) stable at the preload and at every one
    /// of the programme's other judged loads, as the first and last; `None` when none is.
    pub fn stable_leads_over_programme(&self, max_lead_s: f64) -> Option<(f64, f64)> {
        let mut probe = self.clone();
        let n = (max_lead_s / LEAD_STEP_S).round() as usize;
        let ok: Vec<bool> = (0..=n)
            .map(|i| {
                probe.lead_s = i as f64 * LEAD_STEP_S;
                probe.is_stable(0.0, 1.0) && probe.unstable_loads_n().is_empty()
            })
            .collect();
        let first = ok.iter().position(|&s| s)?;
        let last = ok.iter().rposition(|&s| s)?;
        Some((first as f64 * LEAD_STEP_S, last as f64 * LEAD_STEP_S))
    }

    fn is_stable_on(
        &self,
        element: &[Complex64],
        extra_delay_s: f64,
        gain_factor: f64,
        weights: &Weights,
    ) -> bool {
        let mut last = f64::NAN;
        let mut unwrapped = 0.0;
        for i in 0..self.omega.len() {
            let (open, rendered) = self.parts_on(element, i, extra_delay_s, gain_factor, weights);
            let arg = (open + rendered).arg();
            if last.is_nan() {
                unwrapped = arg;
            } else {
                let mut d = arg - last;
                while d > PI {
                    d -= 2.0 * PI;
                }
                while d < -PI {
                    d += 2.0 * PI;
                }
                unwrapped += d;
            }
            last = arg;
        }
        // From 0 (a positive static stiffness) to pi (the mass dominates): one half turn,
        // plus one per right-half-plane pole of the actuator's own responses (the
        // argument principle on the positive half of the imaginary axis counts
        // `pi (1 + P_R - Z_R)` for a function two orders above its poles; stable: Z_R = 0).
        let turns = 1.0 + self.actuator_unstable_poles as f64;
        (unwrapped - turns * PI).abs() < 0.5 * PI
    }

    /// Where the loop comes nearest to instability: the frequency of the smallest
    /// `|1 + L|`, Hz (`Margins::thinnest_frequency_hz`, without the bisections).
    pub fn thinnest_frequency_hz(&self) -> f64 {
        self.thinnest().0
    }

    /// The frequency of the smallest `|1 + L|` (Hz) and that distance.
    fn thinnest(&self) -> (f64, f64) {
        let weights = self.weights();
        let (mut thin_i, mut thin) = (0, f64::INFINITY);
        for i in 0..self.omega.len() {
            let (open, rendered) = self.parts(i, 0.0, 1.0, &weights);
            let d = ((open + rendered) / open).norm();
            if d < thin {
                thin = d;
                thin_i = i;
            }
        }
        (self.omega[thin_i] / (2.0 * PI), thin)
    }

    /// The margins (bisection on `is_stable`).
    pub fn margins(&self) -> Margins {
        let stable = self.is_stable(0.0, 1.0);
        let (slower, faster, gain) = if stable {
            let max_delay = 0.02;
            let slower = if self.is_stable(max_delay, 1.0) {
                max_delay
            } else {
                bisect_edge(
                    |d| self.is_stable(d, 1.0),
                    0.0,
                    max_delay,
                    MARGIN_DELAY_RESOLUTION_S,
                )
            };
            // Faster: an actuator quicker than the lead by up to the lead and a period.
            let most_faster = self.lead_s + self.period_s;
            let faster = if self.is_stable(-most_faster, 1.0) {
                most_faster
            } else {
                bisect_edge(
                    |d| self.is_stable(-d, 1.0),
                    0.0,
                    most_faster,
                    MARGIN_DELAY_RESOLUTION_S,
                )
            };
            let gain = if self.is_stable(0.0, 100.0) {
                100.0
            } else {
                bisect_edge(
                    |g| self.is_stable(0.0, g),
                    1.0,
                    100.0,
                    MARGIN_GAIN_RESOLUTION,
                )
            };
            (Some(slower * 1e6), Some(faster * 1e6), Some(gain))
        } else {
            (None, None, None)
        };
        let (thinnest_frequency_hz, modulus_margin) = self.thinnest();
        Margins {
            stable,
            delay_error_tolerated_slower_us: slower,
            delay_error_tolerated_faster_us: faster,
            gain_margin: gain,
            thinnest_frequency_hz,
            modulus_margin,
        }
    }

    /// The force the rig renders per element force at grid point `i`, as the report's
    /// rendering measures it: the actuator's response to the law evaluated on the
    /// displacement predicted over the lead (held over the period), divided by the gain,
    /// plus its own force on the specimen's velocity (a servo-valve's residual flow, a
    /// shaker's back-EMF) per element force.
    fn rendering(&self, i: usize, weights: &Weights) -> Complex64 {
        let w = self.omega[i];
        self.actuator_u[i] * self.predicted(i, weights).0 / self.gain
            + Complex64::new(0.0, w) * self.actuator_v[i] / self.element[i]
    }

    /// The predicted faithful band: the highest frequency from 1 Hz up to which the
    /// rendering stays within `FAITHFUL_AMPLITUDE` and `FAITHFUL_PHASE_DEG` (the report's
    /// tolerances), looked for up to `FAITHFUL_TOP_HZ`; 0 when it is not faithful at 1 Hz.
    pub fn faithful_band_hz(&self) -> f64 {
        let mut band = 0.0;
        let weights = self.weights();
        for i in 0..self.omega.len() {
            let f = self.omega[i] / (2.0 * PI);
            if f < 1.0 - 1e-9 {
                continue;
            }
            if f > FAITHFUL_TOP_HZ {
                break;
            }
            let r = self.rendering(i, &weights);
            if (r.norm() - 1.0).abs() > FAITHFUL_AMPLITUDE
                || r.arg().to_degrees().abs() > FAITHFUL_PHASE_DEG
            {
                break;
            }
            band = f;
        }
        band
    }

    /// Whether the loop is stable as the run starts: with the safe start's damping when
    /// `cfg`'s compensation arms it (`adapt` and `passivity_guard`), else as it is.
    /// `None` without a safe start.
    pub fn safe_start_stable(&self, cfg: &HilConfig) -> Option<bool> {
        let c = &cfg.compensation;
        // A start the plan moved carries no safe start (`planned`).
        (c.adapt && c.adapt_lead && c.passivity_guard && !c.start_planned).then(|| {
            let mut armed = self.clone();
            armed.guard_damping_ns_per_m = safe_start_damping_ns_per_m(cfg);
            armed.is_stable(0.0, 1.0)
        })
    }

    /// The actuator at `f_hz` (the grid point at or above it): its phase delay (s) and
    /// amplitude ratio in answer to a command (no lead), and its own force on the
    /// specimen's velocity per element force (magnitude).
    pub fn actuator_at(&self, f_hz: f64) -> (f64, f64, f64) {
        let w = 2.0 * PI * f_hz;
        let i = self
            .omega
            .iter()
            .position(|&x| x >= w - 1e-9)
            .unwrap_or(self.omega.len() - 1);
        let w = self.omega[i];
        (
            -self.actuator_u[i].arg() / w,
            self.actuator_u[i].norm(),
            (Complex64::new(0.0, w) * self.actuator_v[i] / self.element[i]).norm(),
        )
    }

    /// With a lead the user fixed (`adapt = false`) and the guard on, in law mode: whether
    /// the loop stays stable with the guard's full damping at that lead (the guard still
    /// adds it where it sees energy); `None` otherwise.
    pub fn fixed_lead_guard_stable(&self, cfg: &HilConfig) -> Option<bool> {
        let c = &cfg.compensation;
        if c.adapt
            || !c.passivity_guard
            || cfg.controller.command_mode != crate::hil::config::CommandMode::Law
        {
            return None;
        }
        let mut damped = self.clone();
        damped.guard_damping_ns_per_m = c.guard_max_damping_ns_per_m;
        Some(damped.is_stable(0.0, 1.0))
    }

    /// Among the stable leads (10 us steps up to `max_lead_s`), the one with the widest
    /// predicted faithful band (the middle of those that tie), and that band; `None` when
    /// no lead is stable. Stable at the preload; `most_faithful_lead_over_programme` at the
    /// judged loads too.
    pub fn most_faithful_stable_lead(&self, max_lead_s: f64) -> Option<(f64, f64)> {
        self.most_faithful_lead(max_lead_s, false)
    }

    /// `most_faithful_stable_lead` among the leads stable at the preload and at every
    /// judged load (`with_loads`; the same without them).
    pub fn most_faithful_lead_over_programme(&self, max_lead_s: f64) -> Option<(f64, f64)> {
        self.most_faithful_lead(max_lead_s, true)
    }

    fn most_faithful_lead(&self, max_lead_s: f64, at_every_load: bool) -> Option<(f64, f64)> {
        // (first lead, last lead, band) of the widest band so far.
        let mut best: Option<(f64, f64, f64)> = None;
        let mut probe = self.clone();
        let n = (max_lead_s / 10e-6).round() as usize;
        for i in 0..=n {
            probe.lead_s = i as f64 * 10e-6;
            if probe.is_stable(0.0, 1.0) && (!at_every_load || probe.unstable_loads_n().is_empty())
            {
                let band = probe.faithful_band_hz();
                best = match best {
                    Some((first, _, b)) if band == b => Some((first, probe.lead_s, b)),
                    Some((_, _, b)) if band < b => best,
                    _ => Some((probe.lead_s, probe.lead_s, band)),
                };
            }
        }
        best.map(|(first, last, band)| (0.5 * (first + last), band))
    }

    /// Whether some lead (10 us steps up to `max_lead_s`) makes the loop stable; stops at
    /// the first.
    pub fn has_stable_lead(&self, max_lead_s: f64) -> bool {
        let mut probe = self.clone();
        let n = (max_lead_s / 10e-6).round() as usize;
        (0..=n).any(|i| {
            probe.lead_s = i as f64 * 10e-6;
            probe.is_stable(0.0, 1.0)
        })
    }

    /// The leads (10 us steps up to `max_lead_s`) with which the loop is stable, as the
    /// first and last of the stable range, or `None` when no lead makes it stable.
    pub fn stable_leads(&self, max_lead_s: f64) -> Option<(f64, f64)> {
        let map = self.stable_lead_map(max_lead_s, LEAD_STEP_S);
        let first = map.iter().position(|&s| s)?;
        let last = map.iter().rposition(|&s| s)?;
        Some((first as f64 * LEAD_STEP_S, last as f64 * LEAD_STEP_S))
    }

    /// Whether the loop is stable with each lead `i * step_s` up to `max_lead_s`.
    pub fn stable_lead_map(&self, max_lead_s: f64, step_s: f64) -> Vec<bool> {
        let mut probe = self.clone();
        let n = (max_lead_s / step_s).round() as usize;
        (0..=n)
            .map(|i| {
                probe.lead_s = i as f64 * step_s;
                probe.is_stable(0.0, 1.0)
            })
            .collect()
    }

    /// Bode (|L|, phase of L) and Nyquist of the loop transfer `L = rendered / open`.
    pub fn plot(&self, path: &std::path::Path, title: &str) -> anyhow::Result<()> {
        let mut f = Vec::new();
        let (mut mag, mut phase, mut re, mut im) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let weights = self.weights();
        for i in 0..self.omega.len() {
            let (open, rendered) = self.parts(i, 0.0, 1.0, &weights);
            let l = rendered / open;
            f.push(self.omega[i] / (2.0 * PI));
            mag.push(20.0 * l.norm().log10());
            phase.push(l.arg().to_degrees());
            if l.norm() < 4.0 {
                re.push(l.re);
                im.push(l.im);
            }
        }
        let bode_mag = Panel::new(
            format!("{title}: loop gain |L|"),
            "frequency, Hz",
            "|L|, dB",
        )
        .log_x()
        .with(Series::line("|L|", f.clone(), mag, 0))
        .with(Series::dashed(
            "0 dB",
            vec![f[0], *f.last().unwrap()],
            vec![0.0, 0.0],
            3,
        ));
        let bode_phase = Panel::new("phase of L", "frequency, Hz", "degrees")
            .log_x()
            .with(Series::line("arg L", f.clone(), phase, 1))
            .with(Series::dashed(
                "-180",
                vec![f[0], *f.last().unwrap()],
                vec![-180.0, -180.0],
                3,
            ));
        let circle_t: Vec<f64> = (0..=200).map(|k| 2.0 * PI * k as f64 / 200.0).collect();
        let nyquist = Panel::new("Nyquist of L near -1 (|L| < 4)", "Re L", "Im L")
            .x_range(-2.0, 0.5)
            .y_range(-1.0, 1.0)
            .with(Series::points("L(jw)", re, im, 0))
            .with(Series::dashed(
                "unit circle",
                circle_t.iter().map(|t| t.cos()).collect(),
                circle_t.iter().map(|t| t.sin()).collect(),
                3,
            ))
            .with(Series::points("-1", vec![-1.0], vec![0.0], 2));
        // The rendering the faithful band judges, from 1 Hz to its top, and its limits.
        let (mut fr, mut amp, mut ph) = (Vec::new(), Vec::new(), Vec::new());
        for i in 0..self.omega.len() {
            let hz = self.omega[i] / (2.0 * PI);
            if !(1.0 - 1e-9..=FAITHFUL_TOP_HZ).contains(&hz) {
                continue;
            }
            let r = self.rendering(i, &weights);
            fr.push(hz);
            amp.push(100.0 * (r.norm() - 1.0));
            ph.push(r.arg().to_degrees());
        }
        let limits = |panel: Panel, limit: f64, unit: &str| {
            let ends = vec![1.0, FAITHFUL_TOP_HZ];
            panel
                .with(Series::dashed(
                    format!("faithful: within +-{limit} {unit}"),
                    ends.clone(),
                    vec![limit, limit],
                    3,
                ))
                .with(Series::dashed("", ends, vec![-limit, -limit], 3))
        };
        let band = self.faithful_band_hz();
        let rendered_amp = limits(
            Panel::new(
                format!(
                    "rendered force per element force: amplitude (faithful up to {band:.1} Hz; clipped at +-10 %)"
                ),
                "frequency, Hz",
                "amplitude error, %",
            )
            .log_x()
            .y_range(-10.0, 10.0)
            .with(Series::line("|F/F_element| - 1", fr.clone(), amp, 0)),
            100.0 * FAITHFUL_AMPLITUDE,
            "%",
        );
        let rendered_phase = limits(
            Panel::new(
                "rendered force per element force: phase (clipped at +-20 degrees)",
                "frequency, Hz",
                "phase error, degrees",
            )
            .log_x()
            .y_range(-20.0, 20.0)
            .with(Series::line("arg F/F_element", fr, ph, 1)),
            FAITHFUL_PHASE_DEG,
            "degrees",
        );
        draw_png(
            path,
            1000,
            1900,
            1,
            &[bode_mag, bode_phase, nyquist, rendered_amp, rendered_phase],
        )
    }
}
