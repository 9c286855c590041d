//! Runs many scenarios in parallel on all cores, reporting each one's progress through
//! [`RunProgress`] (the CLI draws progress bars with it; the library knows no terminal).

use crate::sim::bench::Bench;
use crate::sim::scenario::{RunError, Scenario};
use crate::sim::solver::{SimResult, SolverOptions};
use rayon::prelude::*;
use std::path::Path;

/// The outcome of one scenario.
pub struct Outcome {
    /// The scenario.
    pub scenario: Scenario,
    /// Its result, or why it failed (print it with [`crate::error_chain`]).
    pub result: Result<SimResult, RunError>,
}

/// What a parallel run reports, from any thread: a scenario started, reached a simulated time,
/// finished. `Sync`: the scenarios run on rayon's threads.
pub trait RunProgress: Sync {
    /// Scenario `index` (of `scenarios`) starts; it simulates `duration_s` seconds.
    fn start(&self, index: usize, name: &str, duration_s: f64);
    /// Scenario `index` reached `t_s` simulated seconds.
    fn at(&self, index: usize, t_s: f64);
    /// Scenario `index` finished (or failed).
    fn done(&self, index: usize);
}

/// Runs `scenarios` on all cores, telling `progress` (if any) how each one goes.
pub fn run_all(
    bench: &Bench,
    scenarios: &[Scenario],
    solver: SolverOptions,
    progress: Option<&dyn RunProgress>,
) -> Vec<Outcome> {
    scenarios
        .par_iter()
        .enumerate()
        .map(|(i, s)| {
            if let Some(p) = progress {
                p.start(i, &s.name, s.duration_s);
            }
            let at = |t: f64| {
                if let Some(p) = progress {
                    p.at(i, t);
                }
            };
            let result = s
                .simulate(bench, Path::new("."), solver, Some(&at))
                .map(|(_, r)| r);
            if let Some(p) = progress {
                p.done(i);
            }
            Outcome {
                scenario: s.clone(),
                result,
            }
        })
        .collect()
}
