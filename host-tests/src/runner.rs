//! Runs many scenarios in parallel with one progress bar each.

use crate::sim::bench::Bench;
use crate::sim::scenario::Scenario;
use crate::sim::solver::{SimResult, SolverOptions};
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use rayon::prelude::*;
use std::path::Path;

/// The outcome of one scenario.
pub struct Outcome {
    /// The scenario.
    pub scenario: Scenario,
    /// Its result, or the error message.
    pub result: Result<SimResult, String>,
}

/// Runs `scenarios` on all cores. Progress bars go to stderr when it is a terminal and
/// `progress` is set.
pub fn run_all(
    bench: &Bench,
    scenarios: &[Scenario],
    solver: SolverOptions,
    progress: bool,
) -> Vec<Outcome> {
    let multi = MultiProgress::with_draw_target(if progress {
        ProgressDrawTarget::stderr()
    } else {
        ProgressDrawTarget::hidden()
    });
    let style =
        ProgressStyle::with_template("{prefix:>22} [{bar:30}] {pos:>7}/{len:7} ms sim  {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> ");
    let overall = multi.add(ProgressBar::new(scenarios.len() as u64));
    overall.set_style(
        ProgressStyle::with_template("{prefix:>22} {pos}/{len} scenarios  {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    overall.set_prefix("total");
    let out = scenarios
        .par_iter()
        .map(|s| {
            let pb = multi.add(ProgressBar::new((s.duration_s * 1000.0) as u64));
            pb.set_style(style.clone());
            pb.set_prefix(s.name.clone());
            let at = |t: f64| pb.set_position((t * 1000.0) as u64);
            let result = s
                .simulate(bench, Path::new("."), solver, Some(&at))
                .map(|(_, r)| r);
            pb.finish_and_clear();
            multi.remove(&pb);
            overall.inc(1);
            Outcome {
                scenario: s.clone(),
                result,
            }
        })
        .collect();
    overall.finish_and_clear();
    out
}
