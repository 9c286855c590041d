//! Full, high-fidelity simulation of the hydraulic PTO test bench of a wave energy converter,
//! the paper's scenarios with their facts checked automatically, and the `pto` tool behind it.
//!
//! Layers: [`bench`](mod@bench) (validated parameter file) → [`physics`] (component laws) → [`plant`]
//! (the ODE) → [`sim`] (diffsol BDF driver, sampling, balances) → [`scenario`] (named runs) →
//! [`paper`] (the paper's facts) → [`plot`] / [`figures`] (figures and tables).

pub mod bench;
pub mod benchlog;
pub mod estimation;
pub mod figures;
pub mod fit;
pub mod fw_cost;
pub mod golden;
pub mod model_cost;
pub mod motion;
pub mod output;
pub mod paper;
pub mod perf;
pub mod physics;
pub mod pil;
pub mod plant;
pub mod plot;
pub mod qemu;
pub mod runner;
pub mod scenario;
pub mod sim;
pub mod validate;
