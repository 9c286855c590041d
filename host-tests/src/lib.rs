//! The full, high-fidelity simulation of the hydraulic PTO test bench of a wave energy
//! converter, the paper's scenarios with their facts checked automatically, the fixed-point
//! model's validation against it, the firmware in the loop, the fit, and the `pto` tool behind
//! them.
//!
//! - [`sim`]: the simulation library (bench file, physics, plant, solver, motion, scenarios);
//!   it imports neither the model nor the firmware.
//! - [`paper`]: the paper's facts and figures, on the simulation.
//! - [`fit`]: bench parameters fitted to bench logs, on the simulation.
//! - [`validation`]: the fixed-point model (`pto-model`) validated against the simulation: its
//!   configuration from the bench, the sensor model, the f64 mirror, `pto validate`, the
//!   closed loop and the sensor faults, golden vectors, code cost. (Named for what it does:
//!   "model" is the crate.)
//! - [`hil`]: the firmware built from the host, run under QEMU, processor-in-the-loop, firmware cost.
//! - [`runner`]: scenarios run in parallel on all cores; [`perf`]: the solver's timing
//!   (`pto perf`); [`sweep`]: a design matrix over bench, scenario and controller fields, one
//!   row per run (`pto sweep`).
//! - [`figures`] (the figures of a run and of the paper), [`plot`] (the plotting), [`output`]
//!   (outputs written whole).

pub mod figures;
pub mod fit;
pub mod hil;
pub mod output;
pub mod paper;
pub mod perf;
pub mod plan;
pub mod plot;
pub mod runner;
pub mod sim;
pub mod sweep;
pub mod validation;

/// An error and its causes on one line, `error: cause: cause's cause` (what `anyhow` prints
/// for `{:#}`), for reports that keep errors as text.
///
/// The library's errors follow one rule: a wrapped error is either part of the wrapper's
/// message or its [`source`](std::error::Error::source), never both. A wrapper that adds
/// context (`cannot write out/a.csv`) leaves the cause (`Permission denied (os error 13)`) to
/// `source()`: print errors with this function or `anyhow`'s `{:#}`, not with `{}` alone.
pub fn error_chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut s = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cause = c.source();
    }
    s
}
