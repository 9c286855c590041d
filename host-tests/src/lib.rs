//! The full, high-fidelity simulation of the hydraulic PTO test bench of a wave energy
//! converter, the paper's scenarios with their facts checked automatically, the fixed-point
//! model's validation against it, the firmware in the loop, the fit, and the `pto` tool behind
//! them.
//!
//! - [`sim`]: the simulation library (bench file, physics, plant, solver, motion, scenarios);
//!   it imports neither the model nor the firmware.
//! - [`paper`]: the paper's facts and figures, on the simulation.
//! - [`fit`]: bench parameters fitted to bench logs, on the simulation.
//! - [`model`]: the fixed-point model against the simulation (configuration from the bench,
//!   sensors, the f64 mirror, `pto validate`, golden vectors, code cost).
//! - [`hil`]: the firmware under QEMU, processor-in-the-loop, firmware cost.
//! - [`runner`]: scenarios run in parallel on all cores; [`perf`]: the solver's timing
//!   (`pto bench`).
//! - [`figures`] (the figures of a run and of the paper), [`plot`] (the plotting), [`output`]
//!   (outputs written whole).

pub mod figures;
pub mod fit;
pub mod hil;
pub mod model;
pub mod output;
pub mod paper;
pub mod perf;
pub mod plot;
pub mod runner;
pub mod sim;
