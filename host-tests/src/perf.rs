//! `pto bench`: wall time, real-time factor and accuracy of the reference runs.

use crate::sim::bench::{BAR, Bench};
use crate::sim::scenario::{self, RunError};
use crate::sim::solver::{SimResult, SolverOptions};
use serde::Serialize;

/// Targets of the full-simulation issue.
pub mod target {
    /// Test III (400 s) wall time, s.
    pub const TEST3_WALL_S: f64 = 0.3;
    /// Real-time factor that implies.
    pub const TEST3_RTF: f64 = 1300.0;
    /// P2 error against a tight-tolerance run, bar.
    pub const TEST3_P2_ERR_BAR: f64 = 0.05;
}

/// One benchmarked run.
#[derive(Debug, Clone, Serialize)]
pub struct BenchRow {
    /// Scenario.
    pub scenario: String,
    /// Simulated time, s.
    pub simulated_s: f64,
    /// Median wall time over the repeats, s.
    pub wall_s: f64,
    /// Fastest wall time, s.
    pub wall_min_s: f64,
    /// Simulated / wall.
    pub real_time_factor: f64,
    /// Accepted solver steps.
    pub steps: usize,
    /// Right-hand-side evaluations.
    pub rhs_evals: usize,
    /// Max |P2 − P2_tight| over the run, bar (None when not compared).
    pub p2_max_err_bar: Option<f64>,
}

/// The report.
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    /// Rows.
    pub rows: Vec<BenchRow>,
    /// Every target met?
    pub pass: bool,
    /// Human-readable target lines.
    pub targets: Vec<String>,
}

fn run(bench: &Bench, name: &str, solver: SolverOptions) -> Result<SimResult, RunError> {
    let (s, base) = scenario::resolve(name)?;
    s.simulate(bench, &base, solver, None).map(|(_, r)| r)
}

fn timed(bench: &Bench, name: &str, repeats: usize, compare: bool) -> Result<BenchRow, RunError> {
    // At least one run; the last one's trace is compared.
    let mut r = run(bench, name, SolverOptions::default())?;
    let mut walls = vec![r.stats.wall_s];
    for _ in 1..repeats {
        r = run(bench, name, SolverOptions::default())?;
        walls.push(r.stats.wall_s);
    }
    walls.sort_by(f64::total_cmp);
    let wall = walls[walls.len() / 2];
    let p2_max_err_bar = if compare {
        let tight = run(bench, name, SolverOptions::tight())?;
        let err = r
            .trace
            .p2_pa
            .iter()
            .zip(&tight.trace.p2_pa)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        Some(err / BAR)
    } else {
        None
    };
    let simulated = *r.trace.t_s.last().unwrap_or(&0.0);
    Ok(BenchRow {
        scenario: name.into(),
        simulated_s: simulated,
        wall_s: wall,
        wall_min_s: walls[0],
        real_time_factor: simulated / wall,
        steps: r.stats.steps,
        rhs_evals: r.stats.rhs_evals,
        p2_max_err_bar,
    })
}

/// Runs the benchmark: Test III at 10 % (compared with a tight run) and the 1000 s irregular sea.
pub fn measure(bench: &Bench, repeats: usize) -> Result<BenchReport, RunError> {
    let t3 = timed(bench, "test3-ap10", repeats, true)?;
    let irr = timed(bench, "irregular-sea", repeats.min(3), false)?;
    let err = t3.p2_max_err_bar.unwrap_or(f64::INFINITY);
    let targets = vec![
        format!(
            "Test III wall {:.3} s <= {} s (real-time factor {:.0} >= {}): {}",
            t3.wall_s,
            target::TEST3_WALL_S,
            t3.real_time_factor,
            target::TEST3_RTF,
            if t3.wall_s <= target::TEST3_WALL_S {
                "met"
            } else {
                "MISSED"
            }
        ),
        format!(
            "Test III P2 error vs tight run {:.4} bar <= {} bar: {}",
            err,
            target::TEST3_P2_ERR_BAR,
            if err <= target::TEST3_P2_ERR_BAR {
                "met"
            } else {
                "MISSED"
            }
        ),
    ];
    let pass = t3.wall_s <= target::TEST3_WALL_S && err <= target::TEST3_P2_ERR_BAR;
    Ok(BenchReport {
        rows: vec![t3, irr],
        pass,
        targets,
    })
}
