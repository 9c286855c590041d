//! The full f64 simulation of the bench, apart from the tools that use it: it imports neither
//! the model nor the firmware, and knows no terminal (progress goes through callbacks).
//!
//! Layers: [`bench`](mod@bench) (the validated parameter file and its SI values) → [`physics`]
//! (component laws) → [`plant`] (the ODE) → [`solver`] (diffsol BDF driver, over the valve's
//! [`schedule`]) → its [`trace`] (sampled outputs, plant values at an instant), [`balance`] and
//! [`power`] → [`scenario`] (named runs and scenario files, over [`motion`]). [`benchlog`] is the
//! bench-log format.
//!
//! A run of a built-in scenario, shortened to 20 s:
//!
//! ```
//! use pto_host::sim::bench::{BAR, Bench};
//! use pto_host::sim::scenario;
//! use pto_host::sim::solver::SolverOptions;
//!
//! let bench = Bench::reference();
//! // Test III: HC3.1 + HC3.4 in Config 1, the valve at 10 %, P2 from 60 bar.
//! let mut s = scenario::builtin_named("test3-ap10").expect("a built-in scenario");
//! s.duration_s = 20.0;
//! let here = std::path::Path::new(".");
//! let (_, run) = s.simulate(&bench, here, SolverOptions::default(), None)?;
//! let p2_bar = run.trace.p2_pa.last().copied().unwrap_or_default() / BAR;
//! println!("P2 after 20 s: {p2_bar:.1} bar, balances within {:.1e}", run.balance.worst());
//! // The valve stays shut until 100 bar: the pumps raise P2 from its 60 bar start.
//! assert!(p2_bar > 60.0 && p2_bar < 100.0, "{p2_bar}");
//! assert!(run.balance.worst() <= 1e-4);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

/// The bench parameter file (its own crate, `pto-bench`, which the firmware's build script uses
/// too).
pub use pto_bench as bench;
pub mod balance;
pub mod benchlog;
pub mod motion;
pub mod physics;
pub mod plant;
pub mod power;
pub mod scenario;
pub mod schedule;
pub mod solver;
pub mod trace;
