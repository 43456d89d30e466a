//! First cycles of harmonic records as history tests: owns the model-free test that a record's first whole cycle differs from its steady cycles beyond noise, and the campaign rewrite that splits those first cycles off as a history test before their parent; must not fit or run models, nor change a record whose first cycle is steady.

use std::f64::consts::PI;

use super::campaign::{analyse_cycle, cabs, cdiv, Campaign, Complex, Test, TestKind};

/// Whole cycles a record must hold for its first cycles to be compared and split.
pub const MIN_WHOLE_CYCLES: usize = 4;
/// Cycles split off (more when the history test needs more samples).
pub const FIRST_CYCLES: usize = 2;
/// Whole cycles the parent keeps.
pub const PARENT_MIN_CYCLES: usize = 2;
/// The first cycle's change must exceed this many standard deviations of noise...
pub const NOISE_SIGMAS: f64 = 5.0;
/// ... and this relative change of the dynamic stiffness.
pub const MIN_RELATIVE_CHANGE: f64 = 2e-3;
/// A start-up change is concentrated in the first cycle: its change against the second
/// cycle must be at least this share of its change against the steady cycles (a slow
/// change within the record, warming or drift, moves each cycle a little: a linear one
/// gives a share of `2 / n_whole`, 0.5 at 4 cycles).
pub const STEP_SHARE: f64 = 0.6;
/// Samples a history test needs (`history::prepare_history`).
const MIN_HISTORY_SAMPLES: usize = 256;

/// A harmonic test whose first cycles were used as a history test, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct FirstCyclesUse {
    /// The harmonic test's id and the history test's (`<id>#first-cycles`).
    pub test_id: String,
    pub unit_id: String,
    /// Whole cycles split off and whole cycles the record held.
    pub n_cycles: usize,
    pub n_whole: usize,
    /// `|K_first - K_steady| / |K_steady|` of the single-cycle dynamic stiffness
    /// `F_1 / Z_1`, `K_steady` the mean over the cycles after the first.
    pub relative_change: f64,
    /// One standard deviation of that change from noise.
    pub noise_sigma: f64,
}

impl FirstCyclesUse {
    /// One line: which test and why.
    pub fn reason(&self) -> String {
        format!(
            "{}: first cycle's dynamic stiffness {:.2} % from the steady cycles' ({:.1} sigma of noise); its first {} of {} cycles used as history test \"{}\"",
            self.test_id,
            100.0 * self.relative_change,
            self.relative_change / self.noise_sigma.max(1e-300),
            self.n_cycles,
            self.n_whole,
            self.unit_id
        )
    }
}

/// Single-bin dynamic stiffness `F_1 / Z_1` of samples `range` of a record, with a mean
/// and a linear trend fitted beside the fundamental (a creeping mean does not leak into it).
fn cycle_stiffness(test: &Test, frequency_hz: f64, range: std::ops::Range<usize>) -> Complex {
    let w = 2.0 * PI * frequency_hz;
    let n = range.len();
    let t_mid = 0.5 * (n as f64 - 1.0) * test.dt_s;
    let rows: Vec<[f64; 4]> = (0..n)
        .map(|i| {
            let t = i as f64 * test.dt_s;
            [1.0, t - t_mid, (w * t).cos(), (w * t).sin()]
        })
        .collect();
    let phasor = |x: &[f64]| -> Complex {
        let mut a = [[0.0; 4]; 4];
        let mut b = [0.0; 4];
        for (row, xi) in rows.iter().zip(x) {
            for r in 0..4 {
                b[r] += row[r] * xi;
                for c in 0..4 {
                    a[r][c] += row[r] * row[c];
                }
            }
        }
        let s = solve4(a, b);
        // x ~ c cos + s sin = Re((c - i s) e^{i w t}).
        (s[2], -s[3])
    };
    let z = phasor(&test.displacement_m[range.clone()]);
    let f = phasor(&test.force_n[range]);
    cdiv(f, z)
}

/// Gaussian elimination with partial pivoting of a 4x4 system.
fn solve4(mut a: [[f64; 4]; 4], mut b: [f64; 4]) -> [f64; 4] {
    for col in 0..4 {
        let pivot = (col..4)
            .max_by(|&p, &q| a[p][col].abs().total_cmp(&a[q][col].abs()))
            .unwrap_or(col);
        a.swap(col, pivot);
        b.swap(col, pivot);
        let d = a[col][col];
        if d == 0.0 {
            continue;
        }
        let pivot_row = a[col];
        for r in col + 1..4 {
            let factor = a[r][col] / d;
            for (x, p) in a[r].iter_mut().zip(pivot_row.iter()).skip(col) {
                *x -= factor * p;
            }
            b[r] -= factor * b[col];
        }
    }
    let mut x = [0.0; 4];
    for r in (0..4).rev() {
        let rest: f64 = (r + 1..4).map(|c| a[r][c] * x[c]).sum();
        x[r] = if a[r][r] == 0.0 {
            0.0
        } else {
            (b[r] - rest) / a[r][r]
        };
    }
    x
}

/// Whether a harmonic test's first cycles carry something its steady cycles do not, and
/// how many to split off: `Some(use)` when the record holds `MIN_WHOLE_CYCLES` whole
/// cycles, the first cycle's `F_1 / Z_1` differs from the later cycles' mean by more than
/// `NOISE_SIGMAS` sigma and `MIN_RELATIVE_CHANGE`, the change is concentrated in the first
/// cycle (`STEP_SHARE`), and the parent keeps `PARENT_MIN_CYCLES` whole cycles.
///
/// Noise: one cycle's `F_1 - K Z_1` has the variance the harmonic analysis estimated over
/// its `n` analysed cycles times `n`; the scatter of the cycles after the first about their
/// mean is taken instead when larger (it also holds any slow change within the record).
pub fn first_cycles_change(test: &Test) -> Option<FirstCyclesUse> {
    let TestKind::Harmonic { frequency_hz, .. } = test.kind else {
        return None;
    };
    if test.first_cycles_of.is_some() {
        return None;
    }
    let cycle = test.cycle.as_ref()?;
    let samples_per_cycle = 1.0 / (frequency_hz * test.dt_s);
    let n = test.displacement_m.len().min(test.force_n.len());
    let n_whole = (n as f64 / samples_per_cycle + 1e-6).floor() as usize;
    if n_whole < MIN_WHOLE_CYCLES {
        return None;
    }
    let bound = |k: usize| ((k as f64 * samples_per_cycle).round() as usize).min(n);
    let stiffness: Vec<Complex> = (0..n_whole)
        .map(|k| cycle_stiffness(test, frequency_hz, bound(k)..bound(k + 1)))
        .collect();
    // The steady cycles: all after the first, averaged.
    let later = &stiffness[1..];
    let m = later.len() as f64;
    let steady = later
        .iter()
        .fold((0.0, 0.0), |a, k| (a.0 + k.0 / m, a.1 + k.1 / m));
    let scale = cabs(steady);
    if !scale.is_finite() || scale <= 0.0 {
        return None;
    }
    let diff = |a: Complex, b: Complex| cabs((a.0 - b.0, a.1 - b.1)) / scale;
    let relative_change = diff(stiffness[0], steady);
    let step = diff(stiffness[0], stiffness[1]);

    // Noise of one cycle's K relative to |K|: |F_1 - K Z_1| / |F_1|.
    let f1 = cabs(cycle.force_harmonics_n[0]).max(1e-300);
    let analysed = cycle.fundamental_noise_variance_n2 * cycle.n_cycles as f64 / (f1 * f1);
    let scatter = later.iter().map(|k| diff(*k, steady).powi(2)).sum::<f64>() / (m - 1.0).max(1.0);
    // One cycle against the mean of the m others: (1 + 1/m) times one cycle's variance.
    let noise_sigma = ((1.0 + 1.0 / m) * analysed.max(scatter)).sqrt();
    if !(relative_change > NOISE_SIGMAS * noise_sigma
        && relative_change > MIN_RELATIVE_CHANGE
        && step >= STEP_SHARE * relative_change)
    {
        return None;
    }
    let n_cycles =
        FIRST_CYCLES.max((MIN_HISTORY_SAMPLES as f64 / samples_per_cycle).ceil() as usize);
    if n_whole < n_cycles + PARENT_MIN_CYCLES {
        return None;
    }
    Some(FirstCyclesUse {
        test_id: test.id.clone(),
        unit_id: format!("{}#first-cycles", test.id),
        n_cycles,
        n_whole,
        relative_change,
        noise_sigma,
    })
}

/// The campaign with the first cycles of every harmonic test that carries something in
/// them (`first_cycles_change`) split off as a history test `<id>#first-cycles`, placed
/// immediately before its parent, at its parent's temperature and start; the parent keeps
/// the rest of its record (starting that much later) and is analysed again. A campaign
/// whose records start in steady state comes back unchanged.
pub fn split_first_cycles(campaign: &Campaign) -> (Campaign, Vec<FirstCyclesUse>) {
    let mut tests = Vec::with_capacity(campaign.tests.len());
    let mut used = Vec::new();
    for test in &campaign.tests {
        let Some(found) = first_cycles_change(test) else {
            tests.push(test.clone());
            continue;
        };
        let TestKind::Harmonic { frequency_hz, .. } = test.kind else {
            unreachable!("first_cycles_change takes harmonic tests only");
        };
        let samples_per_cycle = 1.0 / (frequency_hz * test.dt_s);
        let n = test.displacement_m.len().min(test.force_n.len());
        let cut = ((found.n_cycles as f64 * samples_per_cycle).round() as usize).min(n);
        let first = Test {
            id: found.unit_id.clone(),
            file: test.file.clone(),
            kind: TestKind::History,
            temperature_c: test.temperature_c,
            dt_s: test.dt_s,
            time_s: test.time_s[..cut].to_vec(),
            displacement_m: test.displacement_m[..cut].to_vec(),
            force_n: test.force_n[..cut].to_vec(),
            cycle: None,
            started_at_s: test.started_at_s,
            first_cycles_of: Some(test.id.clone()),
        };
        let displacement_m = test.displacement_m[cut..n].to_vec();
        let force_n = test.force_n[cut..n].to_vec();
        let parent = Test {
            cycle: Some(analyse_cycle(
                test.dt_s,
                frequency_hz,
                &displacement_m,
                &force_n,
            )),
            time_s: test.time_s[cut..n].to_vec(),
            displacement_m,
            force_n,
            // The rest of the record starts when the first cycles end.
            started_at_s: test.started_at_s.map(|s| s + cut as f64 * test.dt_s),
            ..test.clone()
        };
        tests.push(first);
        tests.push(parent);
        used.push(found);
    }
    (
        Campaign {
            dir: campaign.dir.clone(),
            sample_length_m: campaign.sample_length_m,
            tests,
        },
        used,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ident::fit::test_data;
    use std::path::PathBuf;

    /// A 2 Hz harmonic record of `n_cycles` cycles on a 20 kN preload, 500 samples per
    /// second, its force `k z` (a stiffness `first_k` over the first cycle), with a small
    /// deterministic "noise".
    fn record(id: &str, n_cycles: usize, first_k: f64, started_at_s: f64) -> Test {
        let (f_hz, dt) = (2.0, 2e-3);
        let n = (n_cycles as f64 / (f_hz * dt)).round() as usize;
        let per_cycle = n / n_cycles;
        let k = 5e7;
        let mut z = Vec::with_capacity(n);
        let mut f = Vec::with_capacity(n);
        for i in 0..n {
            let t = i as f64 * dt;
            let zi = 1e-4 * (2.0 * PI * f_hz * t).sin();
            let wobble = 1.0 + 1e-4 * ((i * 7919 % 101) as f64 / 50.0 - 1.0);
            let ki = if i < per_cycle { first_k } else { k };
            z.push(4e-4 + zi);
            f.push(20e3 + ki * zi * wobble);
        }
        Test {
            id: id.into(),
            file: PathBuf::from(format!("{id}.csv")),
            kind: TestKind::Harmonic {
                preload_n: 20e3,
                amplitude_n: 5e3,
                frequency_hz: f_hz,
            },
            temperature_c: 23.0,
            dt_s: dt,
            time_s: (0..n).map(|i| i as f64 * dt).collect(),
            cycle: Some(analyse_cycle(dt, f_hz, &z, &f)),
            displacement_m: z,
            force_n: f,
            started_at_s: Some(started_at_s),
            first_cycles_of: None,
        }
    }

    fn campaign(tests: Vec<Test>) -> Campaign {
        Campaign {
            dir: PathBuf::from("."),
            sample_length_m: 1.0,
            tests,
        }
    }

    #[test]
    fn a_steady_record_is_kept_and_a_changed_first_cycle_is_split_before_its_parent() {
        let steady = campaign(vec![record("A", 6, 5e7, 0.0), record("B", 6, 5e7, 100.0)]);
        let (same, used) = split_first_cycles(&steady);
        assert!(used.is_empty(), "{used:?}");
        assert_eq!(same.tests.len(), 2);

        // B's first cycle 3 % stiffer: split off, 2 of 6 cycles, before B, at B's start.
        let changed = campaign(vec![
            record("A", 6, 5e7, 0.0),
            record("B", 6, 5.15e7, 100.0),
        ]);
        let (split, used) = split_first_cycles(&changed);
        assert_eq!(used.len(), 1, "{used:?}");
        assert_eq!(used[0].test_id, "B");
        assert!((used[0].relative_change - 0.03).abs() < 0.01, "{used:?}");
        let ids: Vec<&str> = split.tests.iter().map(|t| t.id.as_str()).collect();
        assert_eq!(ids, ["A", "B#first-cycles", "B"]);
        let (first, parent) = (&split.tests[1], &split.tests[2]);
        assert_eq!(first.kind, TestKind::History);
        assert_eq!(first.first_cycles_of.as_deref(), Some("B"));
        assert_eq!(first.started_at_s, Some(100.0));
        assert_eq!(first.force_n.len(), 500);
        assert_eq!(parent.force_n.len(), 1000);
        assert!((parent.started_at_s.unwrap() - 101.0).abs() < 1e-9);
        assert_eq!(parent.cycle.as_ref().unwrap().n_cycles, 4);

        // Units: the first cycles count as their parent's test on the test-order clock and
        // raise the largest force the steady cycles start from.
        let data = test_data(&split).unwrap();
        assert_eq!(data.len(), 3);
        assert_eq!(data[1].time.clocks[0], 1.0);
        assert_eq!(data[2].time.clocks[0], 1.0);
        assert!(data[1].time.first_cycles && !data[2].time.first_cycles);
        assert!(data[2].time.max_force_before_n >= data[1].time.peak_force_n);
        assert_eq!(split.test_orders(), vec![0.0, 100.0, 101.0]);
    }

    #[test]
    fn a_record_too_short_or_a_slow_change_is_not_split() {
        // 3 whole cycles: too few to compare.
        let short = campaign(vec![record("S", 3, 5.15e7, 0.0)]);
        assert!(split_first_cycles(&short).1.is_empty());
        // A stiffness rising 6 % over the record (warming, drift): not a start-up.
        let mut slow = record("W", 8, 5e7, 0.0);
        let n = slow.force_n.len() as f64;
        for (i, f) in slow.force_n.iter_mut().enumerate() {
            *f = 20e3 + (*f - 20e3) * (1.0 + 0.06 * i as f64 / n);
        }
        slow.cycle = Some(analyse_cycle(
            slow.dt_s,
            2.0,
            &slow.displacement_m,
            &slow.force_n,
        ));
        assert!(split_first_cycles(&campaign(vec![slow])).1.is_empty());
        // Without start times the split unit takes its parent's index.
        let mut a = record("A", 6, 5e7, 0.0);
        let mut b = record("B", 6, 5.15e7, 0.0);
        let mut c = record("C", 6, 5e7, 0.0);
        for t in [&mut a, &mut b, &mut c] {
            t.started_at_s = None;
        }
        let (split, _) = split_first_cycles(&campaign(vec![a, b, c]));
        assert_eq!(split.test_orders(), vec![0.0, 1.0, 1.0, 2.0]);
    }
}
