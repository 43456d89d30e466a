//! Shared helpers: parameter sets, a single-bin DFT, independent closed forms,
//! temporary directories and the loop's messages as the rig and the controller send them.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard};

/// Held by the CPU-heavy diagnosis tests (each uses both cores), so that they run one at a
/// time on this two-core machine.
static CPU_HEAVY: Mutex<()> = Mutex::new(());

pub fn cpu_heavy() -> MutexGuard<'static, ()> {
    CPU_HEAVY.lock().unwrap_or_else(|e| e.into_inner())
}

use fastemu::model::ZenerParams;
use nalgebra::Complex;

pub const PI: f64 = std::f64::consts::PI;

/// Table 3 values with `chi = 0`: the linear Zener model, whose closed forms are known.
pub fn linear_zener(length_m: f64) -> ZenerParams {
    ZenerParams {
        chi: 0.0,
        ..ZenerParams::paper_table3(length_m)
    }
}

/// Complex modulus of the linear Zener model, written out independently of the crate:
/// `K(iW) = k1 + k2 (iW tau) / (1 + iW tau)`, `tau = c2/k2`.
pub fn zener_modulus(k1: f64, k2: f64, c2: f64, omega: f64) -> Complex<f64> {
    let iwt = Complex::new(0.0, omega * c2 / k2);
    Complex::new(k1, 0.0) + Complex::new(k2, 0.0) * iwt / (Complex::new(1.0, 0.0) + iwt)
}

/// Single-bin DFT at `omega` of samples taken at `t0 + n dt` covering whole cycles:
/// returns the phasor `A` with `x(t) ~ Re(A e^{i omega t})` (mean and other harmonics
/// drop out when the window holds an integer number of cycles).
pub fn phasor(samples: &[f64], t0_s: f64, dt_s: f64, omega: f64) -> Complex<f64> {
    let mut sum = Complex::new(0.0, 0.0);
    for (n, &x) in samples.iter().enumerate() {
        let phase = omega * (t0_s + n as f64 * dt_s);
        sum += Complex::new(x * phase.cos(), -x * phase.sin());
    }
    sum * (2.0 / samples.len() as f64)
}

pub fn rel_err(value: f64, reference: f64) -> f64 {
    (value - reference).abs() / reference.abs()
}

/// A directory under the system temp dir, unique per test, removed on drop.
pub struct TempDir {
    pub path: PathBuf,
}

impl TempDir {
    pub fn new(label: &str) -> TempDir {
        static COUNTER: AtomicUsize = AtomicUsize::new(0);
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let path =
            std::env::temp_dir().join(format!("fastemu-it-{}-{label}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).expect("create temp dir");
        TempDir { path }
    }

    /// Writes `contents` to `name` inside the directory and returns its path.
    pub fn write(&self, name: &str, contents: &str) -> PathBuf {
        let path = self.path.join(name);
        std::fs::write(&path, contents).expect("write temp file");
        path
    }

    pub fn join(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

pub fn path_str(path: &Path) -> &str {
    path.to_str().expect("utf-8 temp path")
}

/// A rig sample of displacement `z` (m), sequence `seq`, no force measured or reported.
pub fn sample(seq: u64, z: f64) -> fastemu::ipc::messages::DisplacementSample {
    fastemu::ipc::messages::DisplacementSample {
        sequence: seq,
        rig_time_ns: seq * 244_141,
        publish_time_ns: 0,
        displacement_m: z,
        actuator_force_n: f64::NAN,
        status: fastemu::ipc::messages::sample_status::OK,
        rig_state: 1,
        rig_fault_code: 0,
        reserved: 0,
        commanded_force_n: f64::NAN,
    }
}

/// A law command as the controller sends one: a constant 20 kN law, limits -5/120 kN, the
/// shipped lead (252 us, order 2).
pub fn law_command(seq: u64) -> fastemu::ipc::messages::ActuatorCommand {
    use fastemu::ipc::messages::{command_mode, ActuatorCommand, Compensation, LocalLaw};
    ActuatorCommand {
        sequence: seq,
        setpoint_sequence: seq,
        sample_sequence: seq,
        sample_publish_time_ns: 0,
        law: LocalLaw::constant(2e4),
        force_min_n: -5e3,
        force_max_n: 1.2e5,
        mode: command_mode::LAW,
        controller_state: 1,
        fault_code: 0,
        reserved: 0,
        compensation: Compensation::lead(2.52e-4, 2),
    }
}
