//! The full f64 simulation of the bench, apart from the tools that use it: it imports neither
//! the model nor the firmware, and knows no terminal (progress goes through callbacks).
//!
//! Layers: [`bench`](mod@bench) (the validated parameter file and its SI values) → [`physics`]
//! (component laws) → [`plant`] (the ODE) → [`solver`] (diffsol BDF driver, sampling, balances)
//! → [`scenario`] (named runs and scenario files, over [`motion`]) → [`trace`] (plant values at
//! an instant). [`benchlog`] is the bench-log format, [`runner`] runs scenarios in parallel,
//! [`perf`] times the solver.

pub mod bench;
pub mod benchlog;
pub mod motion;
pub mod perf;
pub mod physics;
pub mod plant;
pub mod runner;
pub mod scenario;
pub mod solver;
pub mod trace;
