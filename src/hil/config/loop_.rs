//! `[loop]`: the fixed-step loop's rate, phases, CPUs and the emulator's standby thread.

use serde::Deserialize;

use super::{Check, ConfigError};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawLoop {
    rate_hz: f64,
    spin_us: f64,
    emulator_phase_us: f64,
    sample_wait_us: f64,
    trip_after_stale_samples: u32,
    record_queue_capacity: usize,
    #[serde(default)]
    lock_memory: bool,
    #[serde(default)]
    fifo_priority: i32,
    #[serde(default)]
    emulator_cpus: Vec<usize>,
    #[serde(default)]
    rig_cpus: Vec<usize>,
    #[serde(default)]
    controller_cpus: Vec<usize>,
    #[serde(default)]
    emulator_standby_cpus: Vec<usize>,
    #[serde(default)]
    emulator_standby_after_us: Option<f64>,
}

/// Fixed-step loop settings shared by the rig and the emulator.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopConfig {
    pub rate_hz: f64,
    pub period_ns: u64,
    pub spin_ns: u64,
    pub emulator_phase_ns: u64,
    pub sample_wait_ns: u64,
    pub trip_after_stale_samples: u32,
    pub record_queue_capacity: usize,
    pub lock_memory: bool,
    /// `None` = normal scheduling.
    pub fifo_priority: Option<i32>,
    pub emulator_cpus: Vec<usize>,
    pub rig_cpus: Vec<usize>,
    /// The controller's thread (empty: any CPU the kernel picks).
    pub controller_cpus: Vec<usize>,
    /// The emulator's standby loop thread: `None` = no standby.
    pub emulator_standby: Option<Standby>,
}

/// A second loop thread of the emulator on other CPUs: it claims a cycle that the primary
/// has not begun `after_ns` past its deadline (`rt::CycleTurn`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Standby {
    pub cpus: Vec<usize>,
    pub after_ns: u64,
}

impl LoopConfig {
    /// The model step, s (one loop period; the same expression everywhere for replay).
    pub fn dt_s(&self) -> f64 {
        1.0 / self.rate_hz
    }
}

pub(super) fn parse_loop(check: &Check, l: &RawLoop) -> Result<LoopConfig, ConfigError> {
    let rate_hz = check.positive("loop.rate_hz", l.rate_hz)?;
    if !(100.0..=50_000.0).contains(&rate_hz) {
        return Err(check.err(
            "loop.rate_hz",
            format!("{rate_hz} is not valid: expected 100 to 50000 Hz"),
        ));
    }
    let period_ns = (1e9 / rate_hz).round() as u64;
    let spin_ns = (check.non_negative("loop.spin_us", l.spin_us)? * 1e3) as u64;
    let emulator_phase_ns =
        (check.non_negative("loop.emulator_phase_us", l.emulator_phase_us)? * 1e3) as u64;
    if emulator_phase_ns >= period_ns {
        return Err(check.err(
            "loop.emulator_phase_us",
            format!(
                "{} is not valid: expected less than one period ({} us)",
                l.emulator_phase_us,
                period_ns as f64 / 1e3
            ),
        ));
    }
    check.at_least(
        "loop.trip_after_stale_samples",
        u64::from(l.trip_after_stale_samples),
        1,
    )?;
    check.at_least(
        "loop.record_queue_capacity",
        l.record_queue_capacity as u64,
        16,
    )?;
    if l.fifo_priority != 0 && !(2..=98).contains(&l.fifo_priority) {
        return Err(check.err(
            "loop.fifo_priority",
            format!(
                "{} is not valid: expected 0 (off) or 2-98 (the loops' SCHED_FIFO priority; the controller runs one above it, the emulator's standby one below)",
                l.fifo_priority
            ),
        ));
    }
    let emulator_standby = parse_standby(check, l, period_ns)?;
    Ok(LoopConfig {
        rate_hz,
        period_ns,
        spin_ns,
        emulator_phase_ns,
        sample_wait_ns: (check.non_negative("loop.sample_wait_us", l.sample_wait_us)? * 1e3) as u64,
        trip_after_stale_samples: l.trip_after_stale_samples,
        record_queue_capacity: l.record_queue_capacity,
        lock_memory: l.lock_memory,
        fifo_priority: (l.fifo_priority > 0).then_some(l.fifo_priority),
        emulator_cpus: l.emulator_cpus.clone(),
        rig_cpus: l.rig_cpus.clone(),
        controller_cpus: l.controller_cpus.clone(),
        emulator_standby,
    })
}

/// `[loop] emulator_standby_cpus` and `emulator_standby_after_us`: the standby must sit on
/// CPUs the primary does not use, and claim a cycle within its period.
pub(super) fn parse_standby(
    check: &Check,
    l: &RawLoop,
    period_ns: u64,
) -> Result<Option<Standby>, ConfigError> {
    if l.emulator_standby_cpus.is_empty() {
        return Ok(None);
    }
    if let Some(cpu) = l
        .emulator_standby_cpus
        .iter()
        .find(|c| l.emulator_cpus.contains(c))
    {
        return Err(check.err(
            "loop.emulator_standby_cpus",
            format!(
                "{:?} is not valid: CPU {cpu} is also in emulator_cpus {:?}; the standby covers \
                 for the primary's CPU only from another one",
                l.emulator_standby_cpus, l.emulator_cpus
            ),
        ));
    }
    let after_us = l.emulator_standby_after_us.ok_or_else(|| {
        check.err(
            "loop.emulator_standby_after_us",
            "missing: with emulator_standby_cpus, how long after a deadline the standby \
             takes a cycle the primary has not begun, us"
                .into(),
        )
    })?;
    let after_ns = (check.positive("loop.emulator_standby_after_us", after_us)? * 1e3) as u64;
    if after_ns >= period_ns {
        return Err(check.err(
            "loop.emulator_standby_after_us",
            format!(
                "{after_us} is not valid: expected less than one period ({} us)",
                period_ns as f64 / 1e3
            ),
        ));
    }
    Ok(Some(Standby {
        cpus: l.emulator_standby_cpus.clone(),
        after_ns,
    }))
}
