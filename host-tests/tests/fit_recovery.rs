//! `pto fit` recovers known parameters from synthetic bench logs (the reduced, fast case of the
//! full recovery run of `docs/fit.md`): five of the experimental runs at 5 Hz, made by the full
//! simulation from a bench with trapped air 4 %, Cd 0.17 and HP precharge 45 bar (reference:
//! 6 %, 0.154, 25 bar), with the sensor model's noise and quantisation; the fit starts from the
//! reference values.

use pto_host::fit;
use pto_host::sim::bench::{Bench, apply_override};
use pto_host::sim::benchlog::BenchLog;

#[test]
fn fit_recovers_trapped_air_cd_and_precharge() {
    let dir = std::env::temp_dir().join(format!("pto-fit-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut truth = Bench::reference().file;
    let shortcuts = fit::set_shortcuts();
    for kv in ["trapped_air=0.04", "cd=0.17", "precharge=45"] {
        apply_override(&mut truth, kv, &shortcuts).unwrap();
    }
    let truth = Bench::from_file(truth, "truth").unwrap();
    let mut logs = Vec::new();
    let runs = [
        "exp-charge-64.5",
        "exp-charge-72",
        "exp-9pct-101.5",
        "exp-discharge-102",
        "exp-discharge-71",
    ];
    for (i, run) in runs.iter().enumerate() {
        let log = fit::synth_log(&truth, run, 5.0, 1 + i as u64, &dir).unwrap();
        log.write().unwrap();
        // Through the file, as a user's log would come.
        logs.push(BenchLog::read(&log.path).unwrap());
    }
    let start = Bench::reference().file;
    let names: Vec<String> = ["trapped_air", "cd", "precharge"]
        .map(String::from)
        .to_vec();
    let o = fit::fit(&start, &names, logs, 1.0, 20, None).unwrap();
    let r = &o.report;
    for p in &r.params {
        println!(
            "{:<12} start {:.4} fitted {:.4} ± {:?}",
            p.name, p.start, p.value, p.sigma
        );
    }
    println!(
        "residual RMS {:.2} → {:.2} ({:.1}×), {} simulations, {:.1} s, {}",
        r.residual_rms.0, r.residual_rms.1, r.improvement, r.simulations, r.wall_s, r.termination
    );
    let v = |n: &str| r.params.iter().find(|p| p.name == n).unwrap().value;
    assert!((v("trapped_air") - 0.04).abs() <= 0.005, "trapped air");
    assert!((v("cd") - 0.17).abs() <= 0.03 * 0.17, "Cd");
    assert!((v("precharge") - 45.0).abs() <= 2.0, "precharge");
    assert!(r.improvement >= 10.0, "residual drops ≥ 10×");
    assert!(r.params.iter().all(|p| p.sigma.is_some_and(|s| s > 0.0)));
    let _ = std::fs::remove_dir_all(&dir);
}
