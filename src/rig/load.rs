//! External load programme on the specimen: a constant preload plus a sequence of blocks
//! (each any mix of a harmonic load, an ETR 500 coach passage (paper Fig. 7, quasi-static
//! force on the sample's length), a step and a CSV segment, in block-local time), each
//! block repeated in a row, the whole sequence repeated for a durability test. A pure
//! function of programme time; no I/O and no allocation after construction.

use crate::hil::config::{BlockConfig, ProgrammeConfig};
use crate::track::{kmh_to_m_per_s, TrainPassage};

/// One block, ready to evaluate.
#[derive(Debug, Clone)]
struct Block {
    duration_s: f64,
    repeat: u64,
    harmonic_amplitude_n: f64,
    harmonic_omega_rad_per_s: f64,
    train: Option<(TrainPassage, f64)>,
    step_n: f64,
    step_at_s: f64,
    csv: Option<(f64, Vec<f64>)>,
}

impl Block {
    fn new(b: &BlockConfig) -> Block {
        Block {
            duration_s: b.duration_s,
            repeat: b.repeat.max(1),
            harmonic_amplitude_n: b.harmonic_amplitude_n,
            harmonic_omega_rad_per_s: 2.0 * std::f64::consts::PI * b.harmonic_frequency_hz,
            train: (b.train_speed_kmh > 0.0).then(|| {
                (
                    TrainPassage::etr500_coach(kmh_to_m_per_s(b.train_speed_kmh)),
                    b.train_first_axle_s,
                )
            }),
            step_n: b.step_n,
            step_at_s: b.step_at_s,
            csv: b.load_csv_samples.clone(),
        }
    }

    /// The block's force at block-local time `t_s` (without the preload), N.
    fn force_n(&self, t_s: f64, sample_length_m: f64) -> f64 {
        let mut f = self.harmonic_amplitude_n * (self.harmonic_omega_rad_per_s * t_s).sin();
        if let Some((train, t_first)) = &self.train {
            f += train.force_per_m_history(t_s, *t_first) * sample_length_m;
        }
        if self.step_n != 0.0 && t_s >= self.step_at_s {
            f += self.step_n;
        }
        if let Some((dt, values)) = &self.csv {
            let pos = t_s / dt;
            let i = pos.floor();
            if i >= 0.0 && (i as usize) + 1 < values.len() {
                let i = i as usize;
                let w = pos - i as f64;
                f += values[i] * (1.0 - w) + values[i + 1] * w;
            } else if let Some(last) = values.last().filter(|_| i >= 0.0) {
                f += *last;
            }
        }
        f
    }

    fn span_s(&self) -> f64 {
        self.duration_s * self.repeat as f64
    }
}

/// Where programme time falls: the sequence's repetition, the block, its repetition, and
/// the block-local time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProgrammePosition {
    /// Completed repetitions of the whole block sequence before this one (the durability
    /// cycle counter).
    pub cycle: u64,
    /// Index of the block in the sequence.
    pub block: u32,
    /// Completed repetitions of this block within this cycle.
    pub block_repeat: u64,
    /// Time into the block, s.
    pub local_s: f64,
}

/// External force on the specimen as a function of programme time, N (positive in
/// compression).
#[derive(Debug, Clone)]
pub struct LoadProgramme {
    preload_n: f64,
    sample_length_m: f64,
    blocks: Vec<Block>,
    /// Length of one pass through the block sequence, s.
    sequence_s: f64,
    /// Where the programme ends, s (its repeats done, or the run's length).
    end_s: f64,
}

impl LoadProgramme {
    /// The programme of `programme` on an element of length `sample_length_m`.
    pub fn new(programme: &ProgrammeConfig, sample_length_m: f64) -> LoadProgramme {
        let blocks: Vec<Block> = programme.blocks.iter().map(Block::new).collect();
        let sequence_s: f64 = blocks.iter().map(Block::span_s).sum();
        LoadProgramme {
            preload_n: programme.preload_n,
            sample_length_m,
            blocks,
            sequence_s,
            end_s: programme.end_s,
        }
    }

    /// Programme time at which the programme ends, s.
    pub fn end_s(&self) -> f64 {
        self.end_s
    }

    /// Length of one pass through the block sequence, s.
    pub fn sequence_s(&self) -> f64 {
        self.sequence_s
    }

    /// Where programme time `t_s` falls.
    pub fn position(&self, t_s: f64) -> ProgrammePosition {
        let t = t_s.max(0.0);
        if self.sequence_s <= 0.0 || self.blocks.is_empty() {
            return ProgrammePosition {
                cycle: 0,
                block: 0,
                block_repeat: 0,
                local_s: t,
            };
        }
        let cycle = (t / self.sequence_s).floor();
        let mut rest = t - cycle * self.sequence_s;
        let last = self.blocks.len() - 1;
        for (i, b) in self.blocks.iter().enumerate() {
            if rest < b.span_s() || i == last {
                let rep = (rest / b.duration_s)
                    .floor()
                    .min((b.repeat - 1) as f64)
                    .max(0.0);
                return ProgrammePosition {
                    cycle: cycle as u64,
                    block: i as u32,
                    block_repeat: rep as u64,
                    local_s: rest - rep * b.duration_s,
                };
            }
            rest -= b.span_s();
        }
        unreachable!("the last block takes the rest")
    }

    /// External force at programme time `t_s`, N.
    pub fn force_n(&self, t_s: f64) -> f64 {
        if self.blocks.is_empty() {
            return self.preload_n;
        }
        let p = self.position(t_s);
        self.preload_n + self.blocks[p.block as usize].force_n(p.local_s, self.sample_length_m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block(name: &str, duration_s: f64, repeat: u64, step_n: f64) -> BlockConfig {
        BlockConfig {
            name: name.into(),
            duration_s,
            repeat,
            harmonic_amplitude_n: 0.0,
            harmonic_frequency_hz: 0.0,
            train_speed_kmh: 0.0,
            train_first_axle_s: 0.0,
            step_n,
            step_at_s: 0.0,
            load_csv: None,
            load_csv_samples: None,
        }
    }

    #[test]
    fn blocks_repeat_in_a_row_and_the_sequence_repeats() {
        // A: 2 s x 3 (step +100 N), B: 1 s (step +200 N): a 7 s sequence.
        let p = LoadProgramme::new(
            &ProgrammeConfig {
                preload_n: 1000.0,
                blocks: vec![block("A", 2.0, 3, 100.0), block("B", 1.0, 1, 200.0)],
                repeat: 4,
                end_s: 28.0,
            },
            0.75,
        );
        assert_eq!(p.sequence_s(), 7.0);
        let at = |t: f64| {
            let q = p.position(t);
            (
                q.cycle,
                q.block,
                q.block_repeat,
                (q.local_s * 1e9).round() / 1e9,
            )
        };
        assert_eq!(at(0.5), (0, 0, 0, 0.5));
        assert_eq!(at(4.5), (0, 0, 2, 0.5));
        assert_eq!(at(6.25), (0, 1, 0, 0.25));
        assert_eq!(at(7.0), (1, 0, 0, 0.0));
        assert_eq!(at(20.5), (2, 1, 0, 0.5));
        assert_eq!(p.force_n(20.5), 1200.0);
        assert_eq!(p.force_n(15.0), 1100.0);
    }
}
