//! Min/max decimation of a series for plots: at most `capacity` buckets over a time axis
//! that grows with the run (full buckets merge in pairs), so a plot of an hour-long run
//! holds a few thousand points and still shows every excursion's extremes.

/// One bucket: first time, min and max with their times.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Bucket {
    t_min: f64,
    min: f64,
    t_max: f64,
    max: f64,
}

/// A decimated series.
#[derive(Debug, Clone)]
pub struct Decimator {
    t0_s: f64,
    width_s: f64,
    capacity: usize,
    buckets: Vec<Option<Bucket>>,
}

impl Decimator {
    /// Buckets of `initial_width_s` starting at `t0_s`, at most `capacity` of them.
    pub fn new(t0_s: f64, initial_width_s: f64, capacity: usize) -> Decimator {
        Decimator {
            t0_s,
            width_s: initial_width_s.max(1e-9),
            capacity: capacity.max(2) & !1,
            buckets: Vec::new(),
        }
    }

    pub fn push(&mut self, t_s: f64, y: f64) {
        if !y.is_finite() {
            return;
        }
        let mut idx = ((t_s - self.t0_s) / self.width_s).floor().max(0.0) as usize;
        while idx >= self.capacity {
            self.merge_pairs();
            idx = ((t_s - self.t0_s) / self.width_s).floor().max(0.0) as usize;
        }
        if self.buckets.len() <= idx {
            self.buckets.resize(idx + 1, None);
        }
        let b = &mut self.buckets[idx];
        match b {
            None => {
                *b = Some(Bucket {
                    t_min: t_s,
                    min: y,
                    t_max: t_s,
                    max: y,
                })
            }
            Some(b) => {
                if y < b.min {
                    b.min = y;
                    b.t_min = t_s;
                }
                if y > b.max {
                    b.max = y;
                    b.t_max = t_s;
                }
            }
        }
    }

    fn merge_pairs(&mut self) {
        let merged: Vec<Option<Bucket>> = self
            .buckets
            .chunks(2)
            .map(|pair| {
                let mut out: Option<Bucket> = None;
                for b in pair.iter().flatten() {
                    out = Some(match out {
                        None => *b,
                        Some(o) => Bucket {
                            t_min: if b.min < o.min { b.t_min } else { o.t_min },
                            min: o.min.min(b.min),
                            t_max: if b.max > o.max { b.t_max } else { o.t_max },
                            max: o.max.max(b.max),
                        },
                    });
                }
                out
            })
            .collect();
        self.buckets = merged;
        self.width_s *= 2.0;
    }

    /// The series as points in time order (each bucket's min and max), scaled by `scale`.
    pub fn points(&self, scale: f64) -> (Vec<f64>, Vec<f64>) {
        let mut t = Vec::with_capacity(2 * self.buckets.len());
        let mut y = Vec::with_capacity(2 * self.buckets.len());
        for b in self.buckets.iter().flatten() {
            let pair = if b.t_min <= b.t_max {
                [(b.t_min, b.min), (b.t_max, b.max)]
            } else {
                [(b.t_max, b.max), (b.t_min, b.min)]
            };
            for (ti, yi) in pair {
                if t.last() != Some(&ti) {
                    t.push(ti);
                    y.push(yi * scale);
                }
            }
        }
        (t, y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_the_extremes_of_a_long_series_in_bounded_points() {
        let mut d = Decimator::new(0.0, 0.001, 100);
        for k in 0..1_000_000 {
            let t = k as f64 * 1e-4;
            let spike = if k == 777_777 { 5.0 } else { 0.0 };
            d.push(t, (t * 3.0).sin() + spike);
        }
        let (t, y) = d.points(1.0);
        assert!(t.len() <= 200, "{} points", t.len());
        assert!(t.windows(2).all(|w| w[0] < w[1]));
        let max = y.iter().fold(f64::MIN, |m, v| m.max(*v));
        assert!((max - (77.7777f64 * 3.0).sin() - 5.0).abs() < 1e-9, "{max}");
    }
}
