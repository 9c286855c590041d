//! `pto bench`: wall time, real-time factor and accuracy of the reference runs, the default
//! solver path side by side with the reference path, and the throughput of a batch of runs.

use crate::sim::bench::{BAR, Bench};
use crate::sim::scenario::{self, RunError};
use crate::sim::solver::{SimResult, SolverOptions};
use rayon::prelude::*;
use serde::Serialize;
use std::time::Instant;

/// Targets of the simulation's speed.
pub mod target {
    /// Test III (400 s) wall time, s.
    pub const TEST3_WALL_S: f64 = 0.3;
    /// P2 error against a tight-tolerance run, bar.
    pub const TEST3_P2_ERR_BAR: f64 = 0.05;
    /// Speed-up of the default path over the reference path, on each run.
    pub const SPEEDUP: f64 = 2.0;
    /// A batch of 1 000 Test III-length runs on every core, s.
    pub const BATCH_1000_WALL_S: f64 = 120.0;
}

/// One benchmarked run on one solver path.
#[derive(Debug, Clone, Serialize)]
pub struct BenchRow {
    /// Scenario.
    pub scenario: String,
    /// `default` or `reference` (the finite-difference path that evaluates the motion and
    /// the levers at every call: the path before the speed work, kept for this comparison).
    pub path: String,
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

/// A batch of runs on every core.
#[derive(Debug, Clone, Serialize)]
pub struct Batch {
    /// Scenario.
    pub scenario: String,
    /// Runs.
    pub runs: usize,
    /// Worker threads.
    pub threads: usize,
    /// Wall time of the whole batch, s.
    pub wall_s: f64,
}

/// The report.
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    /// Rows: each scenario on the default path, then on the reference path.
    pub rows: Vec<BenchRow>,
    /// Wall-time ratio reference / default per scenario (medians).
    pub speedups: Vec<(String, f64)>,
    /// Max |P2 default − P2 reference| per scenario, bar.
    pub paths_p2_diff_bar: Vec<(String, f64)>,
    /// The batch, when asked for.
    pub batch: Option<Batch>,
    /// Every target met?
    pub pass: bool,
    /// Human-readable target lines.
    pub targets: Vec<String>,
}

fn run(bench: &Bench, name: &str, solver: SolverOptions) -> Result<SimResult, RunError> {
    let (s, base) = scenario::resolve(name)?;
    s.simulate(bench, &base, solver, None).map(|(_, r)| r)
}

fn row(name: &str, path: &str, walls: &mut [f64], r: &SimResult, err: Option<f64>) -> BenchRow {
    walls.sort_by(f64::total_cmp);
    let wall = walls[walls.len() / 2];
    let simulated = *r.trace.t_s.last().unwrap_or(&0.0);
    BenchRow {
        scenario: name.into(),
        path: path.into(),
        simulated_s: simulated,
        wall_s: wall,
        wall_min_s: walls[0],
        real_time_factor: simulated / wall,
        steps: r.stats.steps,
        rhs_evals: r.stats.rhs_evals,
        p2_max_err_bar: err,
    }
}

fn p2_err_bar(a: &SimResult, b: &SimResult) -> f64 {
    let err = a
        .trace
        .p2_pa
        .iter()
        .zip(&b.trace.p2_pa)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
    err / BAR
}

/// Both paths of one scenario, their repeats interleaved so that a change of the machine's load
/// falls on both alike, each compared with a tight run: (default row, reference row, max
/// |ΔP2| between the paths in bar).
fn side_by_side(
    bench: &Bench,
    name: &str,
    repeats: usize,
) -> Result<(BenchRow, BenchRow, f64), RunError> {
    let fast = SolverOptions::default();
    let slow = fast.reference_path();
    let (mut wf, mut ws) = (Vec::new(), Vec::new());
    let (mut rf, mut rs) = (None, None);
    for _ in 0..repeats.max(1) {
        let a = run(bench, name, fast)?;
        wf.push(a.stats.wall_s);
        rf = Some(a);
        let b = run(bench, name, slow)?;
        ws.push(b.stats.wall_s);
        rs = Some(b);
    }
    let (Some(rf), Some(rs)) = (rf, rs) else {
        unreachable!("at least one repeat ran");
    };
    let diff = p2_err_bar(&rf, &rs);
    let tight = run(bench, name, SolverOptions::tight().reference_path())?;
    let (ef, es) = (p2_err_bar(&rf, &tight), p2_err_bar(&rs, &tight));
    Ok((
        row(name, "default", &mut wf, &rf, Some(ef)),
        row(name, "reference", &mut ws, &rs, Some(es)),
        diff,
    ))
}

/// `runs` runs of `name` on the default path, spread over every core.
pub fn batch(bench: &Bench, name: &str, runs: usize) -> Result<Batch, RunError> {
    let t0 = Instant::now();
    (0..runs)
        .into_par_iter()
        .try_for_each(|_| run(bench, name, SolverOptions::default()).map(drop))?;
    Ok(Batch {
        scenario: name.into(),
        runs,
        threads: rayon::current_num_threads(),
        wall_s: t0.elapsed().as_secs_f64(),
    })
}

fn verdict(ok: bool) -> &'static str {
    if ok { "met" } else { "MISSED" }
}

/// Accuracy of the default path is unchanged when its P2 error against the tight run is within
/// the reference path's + max(10 %, 1e-4 bar).
fn unchanged(default: &BenchRow, reference: &BenchRow) -> bool {
    let (a, b) = (
        default.p2_max_err_bar.unwrap_or(f64::INFINITY),
        reference.p2_max_err_bar.unwrap_or(f64::INFINITY),
    );
    a <= b + (0.1 * b).max(1e-4)
}

/// Runs the benchmark: Test III at 10 % and the 1000 s irregular sea, each on both paths and
/// against a tight run; with `batch_runs`, that many Test III runs on every core.
pub fn measure(
    bench: &Bench,
    repeats: usize,
    batch_runs: Option<usize>,
) -> Result<BenchReport, RunError> {
    let (t3, t3_ref, t3_diff) = side_by_side(bench, "test3-ap10", repeats)?;
    let (irr, irr_ref, irr_diff) = side_by_side(bench, "irregular-sea", repeats.min(3))?;
    let err = t3.p2_max_err_bar.unwrap_or(f64::INFINITY);
    let speedups = vec![
        (t3.scenario.clone(), t3_ref.wall_s / t3.wall_s),
        (irr.scenario.clone(), irr_ref.wall_s / irr.wall_s),
    ];
    let mut targets = vec![
        format!(
            "Test III wall {:.3} s <= {} s (real-time factor {:.0}): {}",
            t3.wall_s,
            target::TEST3_WALL_S,
            t3.real_time_factor,
            verdict(t3.wall_s <= target::TEST3_WALL_S)
        ),
        format!(
            "Test III P2 error vs tight run {err:.4} bar <= {} bar: {}",
            target::TEST3_P2_ERR_BAR,
            verdict(err <= target::TEST3_P2_ERR_BAR)
        ),
    ];
    let mut pass = t3.wall_s <= target::TEST3_WALL_S && err <= target::TEST3_P2_ERR_BAR;
    for (d, r, diff) in [(&t3, &t3_ref, t3_diff), (&irr, &irr_ref, irr_diff)] {
        let ok = unchanged(d, r);
        pass &= ok;
        targets.push(format!(
            "{}: P2 error vs tight run {:.2e} bar on the default path, {:.2e} on the reference \
             path (paths differ by ≤ {diff:.1e} bar): accuracy unchanged: {}",
            d.scenario,
            d.p2_max_err_bar.unwrap_or(f64::NAN),
            r.p2_max_err_bar.unwrap_or(f64::NAN),
            if ok { "yes" } else { "NO" }
        ));
    }
    for (name, x) in &speedups {
        let ok = *x >= target::SPEEDUP;
        pass &= ok;
        targets.push(format!(
            "{name}: default path {x:.2}x faster than the reference path >= {}x: {}",
            target::SPEEDUP,
            verdict(ok)
        ));
    }
    let paths_p2_diff_bar = vec![
        (t3.scenario.clone(), t3_diff),
        (irr.scenario.clone(), irr_diff),
    ];
    let batch = match batch_runs {
        Some(n) => {
            let b = batch(bench, "test3-ap10", n)?;
            // The target is for 1 000 runs; a smaller batch is judged pro rata.
            let limit = target::BATCH_1000_WALL_S * n as f64 / 1000.0;
            let ok = b.wall_s <= limit;
            pass &= ok;
            targets.push(format!(
                "{n} Test III runs on {} threads: {:.1} s <= {limit:.1} s: {}",
                b.threads,
                b.wall_s,
                verdict(ok)
            ));
            Some(b)
        }
        None => None,
    };
    Ok(BenchReport {
        rows: vec![t3, t3_ref, irr, irr_ref],
        speedups,
        paths_p2_diff_bar,
        batch,
        pass,
        targets,
    })
}
