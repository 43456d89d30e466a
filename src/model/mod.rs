//! The elastomer element model of Li et al. (Materials 2021, 14, 6968) in all its forms.
//!
//! Owns: parameters (paper Eq. 1 preload scaling), equivalent stiffness and damping
//! (paper Eq. 2), the fixed-step force-from-displacement stepper used by the emulator
//! (`ForceStepper`), the effect library composed on top of it (`effects::ModelStepper`),
//! the mass-on-element oscillator used offline and by the simulated rig
//! (`Oscillator`), and model files (SPEC 2.3).
//!
//! Must not: do I/O (except `file`, which only reads a model file), read a clock, or
//! allocate inside `ForceStepper::step` / `Oscillator::step`. Every step is a pure
//! function of its state and inputs, so identical inputs give bit-identical outputs.

pub mod effects;
pub mod element;
pub mod equiv;
pub mod file;
pub mod oscillator;
pub mod params;
pub mod thermal;

pub use effects::{AugmentedModel, Effect, ModelStepper, StepperMode};
pub use element::{ForceStepper, StepFlags};
pub use equiv::{equivalent, Equivalent};
pub use file::{load_model_file, parse_model_toml, ModelFileError};
pub use oscillator::{Oscillator, StartCondition};
pub use params::{ElementModel, Form, KelvinVoigtParams, ZenerParams};
