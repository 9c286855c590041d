//! The paper's ten facts hold on the reference bench (every built-in scenario is run).

use pto_host::paper;
use pto_host::runner;
use pto_host::sim::bench::Bench;
use pto_host::sim::scenario;
use pto_host::sim::solver::SolverOptions;

#[test]
fn all_ten_facts_hold_on_the_reference_bench() {
    let bench = Bench::reference();
    let outcomes = runner::run_all(&bench, &scenario::builtin(), SolverOptions::default(), None);
    let facts = paper::check(&bench, &outcomes);
    for f in &facts {
        println!(
            "fact {:>2} {}: {}",
            f.id,
            if f.pass { "PASS" } else { "FAIL" },
            f.measured
        );
    }
    let failed: Vec<_> = facts.iter().filter(|f| !f.pass).map(|f| f.id).collect();
    assert!(failed.is_empty(), "facts failing: {failed:?}");
}
