//! `pto perf`: wall time, real-time factor and accuracy of the reference runs: the stops as
//! events (the default) side by side with the stop spring and with the reference solver path,
//! their repeats interleaved, and the throughput of a batch of runs.

use crate::sim::bench::{BAR, Bench, Stops};
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
    /// Speed-up of the stops as events over the stop spring: Test III.
    pub const EVENTS_SPEEDUP_TEST3: f64 = 3.0;
    /// Speed-up of the stops as events over the stop spring: the irregular sea.
    pub const EVENTS_SPEEDUP_SEA: f64 = 1.5;
    /// Test III's accepted steps with the stops as events.
    pub const EVENTS_TEST3_STEPS: usize = 15_000;
    /// A batch of 1 000 Test III-length runs on every core, s.
    pub const BATCH_1000_WALL_S: f64 = 40.0;
}

/// A way of solving the same run: the stop model and the solver path.
#[derive(Debug, Clone, Copy)]
struct Variant {
    label: &'static str,
    stops: Stops,
    reference_path: bool,
}

/// The default (the stops as events, the default path), the stop spring on the default path,
/// and the stops as events on the reference path.
const VARIANTS: [Variant; 3] = [
    Variant {
        label: "events",
        stops: Stops::Events,
        reference_path: false,
    },
    Variant {
        label: "spring",
        stops: Stops::Spring,
        reference_path: false,
    },
    Variant {
        label: "events, reference path",
        stops: Stops::Events,
        reference_path: true,
    },
];

/// One timed run on one solver path (`pto perf`).
#[derive(Debug, Clone, Serialize)]
pub struct PerfRow {
    /// Scenario.
    pub scenario: String,
    /// `events` (the default: the rods' stops as located events, the default solver path),
    /// `spring` (the stop spring, the default path) or `events, reference path` (the path that
    /// evaluates the motion and the levers at every call, kept for this comparison).
    pub variant: String,
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
    /// Max |P2 − P2_tight| over the run against a tight run of its own stop model, bar.
    pub p2_max_err_bar: f64,
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
pub struct PerfReport {
    /// Rows: each scenario in each variant (events, spring, events on the reference path).
    pub rows: Vec<PerfRow>,
    /// Per scenario: wall-time ratio spring / events (medians).
    pub events_speedups: Vec<(String, f64)>,
    /// Per scenario: wall-time ratio reference path / default path, both with events.
    pub path_speedups: Vec<(String, f64)>,
    /// Per scenario: max |P2 events − P2 spring|, bar.
    pub stops_p2_diff_bar: Vec<(String, f64)>,
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

fn with_stops(bench: &Bench, stops: Stops) -> Bench {
    let mut b = bench.clone();
    b.stops = stops;
    b
}

fn row(name: &str, variant: &str, walls: &mut [f64], r: &SimResult, err: f64) -> PerfRow {
    walls.sort_by(f64::total_cmp);
    let wall = walls[walls.len() / 2];
    let simulated = *r.trace.t_s.last().unwrap_or(&0.0);
    PerfRow {
        scenario: name.into(),
        variant: variant.into(),
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

/// Every variant of one scenario, their repeats interleaved so that a change of the machine's
/// load falls on all alike, each compared with a tight run of its own stop model: one row per
/// variant (in `VARIANTS`' order: events, spring, events on the reference path) and the max
/// |ΔP2| between events and spring in bar.
fn side_by_side(
    bench: &Bench,
    name: &str,
    repeats: usize,
) -> Result<([PerfRow; 3], f64), RunError> {
    let benches = VARIANTS.map(|v| with_stops(bench, v.stops));
    let solver = |v: &Variant| {
        let o = SolverOptions::default();
        if v.reference_path {
            o.reference_path()
        } else {
            o
        }
    };
    let mut walls = VARIANTS.map(|_| Vec::new());
    let mut last: [Option<SimResult>; 3] = [None, None, None];
    for _ in 0..repeats.max(1) {
        for (k, v) in VARIANTS.iter().enumerate() {
            let r = run(&benches[k], name, solver(v))?;
            walls[k].push(r.stats.wall_s);
            last[k] = Some(r);
        }
    }
    let last = last.map(|r| r.expect("at least one repeat ran"));
    let tight = |stops| {
        run(
            &with_stops(bench, stops),
            name,
            SolverOptions::tight().reference_path(),
        )
    };
    let (tight_events, tight_spring) = (tight(Stops::Events)?, tight(Stops::Spring)?);
    let rows = std::array::from_fn(|k| {
        let (v, r, w) = (&VARIANTS[k], &last[k], &mut walls[k]);
        let t = match v.stops {
            Stops::Events => &tight_events,
            Stops::Spring => &tight_spring,
        };
        row(name, v.label, w, r, p2_err_bar(r, t))
    });
    Ok((rows, p2_err_bar(&last[0], &last[1])))
}

/// `runs` runs of `name` with the stops as events on the default path, spread over every core.
pub fn batch(bench: &Bench, name: &str, runs: usize) -> Result<Batch, RunError> {
    let bench = with_stops(bench, Stops::Events);
    let t0 = Instant::now();
    (0..runs)
        .into_par_iter()
        .try_for_each(|_| run(&bench, name, SolverOptions::default()).map(drop))?;
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

/// `row`'s P2 error against its tight run is within `against`'s + max(10 %, `floor_bar`): the
/// default path's accuracy unchanged from the reference path's (floor 1e-4 bar), the stops as
/// events no worse than the spring, each against its own tight run (floor 1e-5 bar, for a
/// spring error near zero).
fn within_10pct(row: &PerfRow, against: &PerfRow, floor_bar: f64) -> bool {
    let (a, b) = (row.p2_max_err_bar, against.p2_max_err_bar);
    a <= b + (0.1 * b).max(floor_bar)
}

fn yes_no(ok: bool) -> &'static str {
    if ok { "yes" } else { "NO" }
}

/// Runs the benchmark: Test III at 10 % and the 1000 s irregular sea, each in every variant and
/// against tight runs; with `batch_runs`, that many Test III runs (stops as events) on every
/// core.
pub fn measure(
    bench: &Bench,
    repeats: usize,
    batch_runs: Option<usize>,
) -> Result<PerfReport, RunError> {
    let (t3, t3_diff) = side_by_side(bench, "test3-ap10", repeats)?;
    let (irr, irr_diff) = side_by_side(bench, "irregular-sea", repeats.min(3))?;
    let [ev, sp, _] = &t3;
    let err = ev.p2_max_err_bar;
    let mut targets = vec![
        format!(
            "Test III wall {:.3} s <= {} s (real-time factor {:.0}): {}",
            ev.wall_s,
            target::TEST3_WALL_S,
            ev.real_time_factor,
            verdict(ev.wall_s <= target::TEST3_WALL_S)
        ),
        format!(
            "Test III P2 error vs tight run {err:.4} bar <= {} bar: {}",
            target::TEST3_P2_ERR_BAR,
            verdict(err <= target::TEST3_P2_ERR_BAR)
        ),
        format!(
            "Test III steps with the stops as events {} <= {} (spring {}): {}",
            ev.steps,
            target::EVENTS_TEST3_STEPS,
            sp.steps,
            verdict(ev.steps <= target::EVENTS_TEST3_STEPS)
        ),
    ];
    let mut pass = ev.wall_s <= target::TEST3_WALL_S
        && err <= target::TEST3_P2_ERR_BAR
        && ev.steps <= target::EVENTS_TEST3_STEPS;
    let mut events_speedups = Vec::new();
    let mut path_speedups = Vec::new();
    let mut stops_p2_diff_bar = Vec::new();
    for ([ev, sp, rf], diff, events_target) in [
        (&t3, t3_diff, target::EVENTS_SPEEDUP_TEST3),
        (&irr, irr_diff, target::EVENTS_SPEEDUP_SEA),
    ] {
        let name = &ev.scenario;
        stops_p2_diff_bar.push((name.clone(), diff));
        let x = sp.wall_s / ev.wall_s;
        let ok = x >= events_target;
        pass &= ok;
        targets.push(format!(
            "{name}: stops as events {x:.2}x faster than the spring >= {events_target}x: {}",
            verdict(ok)
        ));
        events_speedups.push((name.clone(), x));
        let ok = within_10pct(ev, sp, 1e-5);
        pass &= ok;
        targets.push(format!(
            "{name}: P2 error vs its own tight run {:.2e} bar with events, {:.2e} with the spring \
             (the models differ by <= {diff:.2} bar): no worse: {}",
            ev.p2_max_err_bar,
            sp.p2_max_err_bar,
            yes_no(ok)
        ));
        let ok = within_10pct(ev, rf, 1e-4);
        pass &= ok;
        targets.push(format!(
            "{name}: P2 error vs tight run {:.2e} bar on the default path, {:.2e} on the \
             reference path: accuracy unchanged: {}",
            ev.p2_max_err_bar,
            rf.p2_max_err_bar,
            yes_no(ok)
        ));
        let x = rf.wall_s / ev.wall_s;
        let ok = x >= target::SPEEDUP;
        pass &= ok;
        targets.push(format!(
            "{name}: default path {x:.2}x faster than the reference path >= {}x: {}",
            target::SPEEDUP,
            verdict(ok)
        ));
        path_speedups.push((name.clone(), x));
    }
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
    let mut rows = Vec::from(t3);
    rows.extend(irr);
    Ok(PerfReport {
        rows,
        events_speedups,
        path_speedups,
        stops_p2_diff_bar,
        batch,
        pass,
        targets,
    })
}
