//! Identification and diagnosis: everything that fits models to measured data, offline.
//!
//! Map (data flows top to bottom):
//! - `campaign`: loads `campaign.toml` and its CSVs (SPEC 4), reduces each harmonic test to
//!   its steady cycle and estimates the noise of its fundamental.
//! - `first_cycles`: for `diagnose --campaign`, splits a harmonic record's first cycles
//!   off as a history test before it when they differ from its steady cycles beyond noise.
//! - `history`: history tests (any displacement programme, and the rig record of a HIL
//!   run) band-limited, decimated and with their noise estimated; the model's force
//!   predicted for them.
//! - `runrec`: the one reader of a `fastemu hil` run directory (`load_run_history`) and
//!   the sentence naming the loop's delay knob (`delay_knob_advice`).
//! - `fit`: `CycleData`, the cycle simulator `predict_cycle`, `Template` (free parameters
//!   of a baseline plus effects, with each effect's admissible range), Levenberg-Marquardt
//!   (`fit::lm`), `fit_template`, `cross_validate` over harmonic and history tests.
//! - `identify`: Zener parameters from a campaign (paper Sec. 3.1; `fastemu identify`).
//! - `diagnose`: the discrepancy workflow (SPEC 5, 5.1): calibration, naming rule,
//!   identifiability; `diagnose::verdict` tests what remains unexplained (noise floor,
//!   test order, repeated tests); `diagnose::run` diagnoses a HIL run's record;
//!   `diagnose::report` writes report.md, plots and the `--json` object.
//! - `plots`: k_eq/c_eq (paper Fig. 6 style), loops, history-test force plots.
//! - `synth`: seeded synthetic campaigns for a first run (`fastemu synth-campaign`).
//!
//! Must not: touch the real-time loop (`hil/`, `rig/`, `ipc/`, `rt/`): `runrec` only reads
//! the files a run left, and parses its config with `hil::config::parse_hil_config`. Only
//! `campaign`, `runrec`, `synth` and the writers (`diagnose::report`, `plots`) do I/O;
//! results never depend on the thread count.

pub mod campaign;
pub mod diagnose;
pub mod first_cycles;
pub mod fit;
pub mod history;
pub mod identify;
pub mod plots;
pub mod runrec;
pub mod synth;
