//! Solver accuracy: the default tolerance against a tight reference, and conservation.

use pto_host::bench::{BAR, Bench};
use pto_host::scenario;
use pto_host::sim::SolverOptions;
use std::path::Path;

/// P2 accuracy target of the full-simulation issue, bar.
const P2_TOL_BAR: f64 = 0.05;

#[test]
fn test3_default_tolerance_tracks_a_tight_run_within_0_05_bar() {
    let bench = Bench::reference();
    let (s, _) = scenario::resolve("test3-ap15").unwrap();
    let p = s.prepare(&bench, Path::new(".")).unwrap();
    let fast = p.run(SolverOptions::default(), None).unwrap();
    let tight = p.run(SolverOptions::tight(), None).unwrap();
    let (mut max, mut sq) = (0.0f64, 0.0);
    for (a, b) in fast.trace.p2.iter().zip(&tight.trace.p2) {
        let e = (a - b).abs() / BAR;
        max = max.max(e);
        sq += e * e;
    }
    let rms = (sq / fast.trace.len() as f64).sqrt();
    println!(
        "P2 vs tight: max {max:.2e} bar, RMS {rms:.2e} bar (tol {P2_TOL_BAR}); steps {} vs {}",
        fast.stats.steps, tight.stats.steps
    );
    assert!(max <= P2_TOL_BAR);
    println!(
        "balances: default {:.1e}, tight {:.1e}",
        fast.balance.worst(),
        tight.balance.worst()
    );
    assert!(fast.balance.worst() <= 1e-4 && tight.balance.worst() <= 1e-6);
}
