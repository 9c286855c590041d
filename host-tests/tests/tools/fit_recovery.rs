//! `pto fit` recovers known parameters from synthetic bench logs, or says it did not: never a
//! silent miss. Logs are made by the full simulation from a known bench with the sensor model's
//! noise and quantisation; the fit starts from the reference bench.
//!
//! `fit_recovers_trapped_air_cd_and_precharge`: one bench, three parameters (five of the
//! experimental runs at 5 Hz). `randomised_benches_are_recovered_or_refused`: benches drawn at
//! random (trapped air 0.02–0.10, Cd 0.12–0.20, HP precharge 15–60 bar, η_v 0.85–0.95), the
//! four fitted together from the seven experimental runs at 10 Hz; each fit either recovers all
//! four (trapped air ± 0.005, Cd ± 3 %, precharge ± 2 bar, η_v ± 0.01, the truth inside 3σ) or
//! fails a named check. One bench in `cargo test`; `PTO_FIT_BENCHES=8` runs the full set of
//! `docs/fit.md` and prints its table. `randomised_benches_from_a_planned_campaign_are_recovered`:
//! the same draws from the campaign `pto plan` gives for the reference bench
//! (`data/campaign-four.toml`), each also fitted from its truth (the χ²ᵣ the fit should end
//! at); two in `cargo test`, `PTO_FIT_CAMPAIGN_BENCHES=8` for the full set. `a_plant_the_model_does_not_match_…`:
//! an LP precharge or a seal friction other than the bench file's — within tolerance or refused.

use pto_host::fit;
use pto_host::plan::{self, Campaign};
use pto_host::sim::bench::{Bench, BenchFile, apply_override};
use pto_host::sim::benchlog::BenchLog;
use rand::{Rng, SeedableRng};
use std::path::Path;

fn bench_with(sets: &[String]) -> Bench {
    let mut f = Bench::reference().file;
    let shortcuts = fit::set_shortcuts();
    for kv in sets {
        apply_override(&mut f, kv, &shortcuts).unwrap();
    }
    Bench::from_file(f, "truth").unwrap()
}

/// Logs of `runs` from `truth` at `rate_hz`, written and read back as a user's would be.
fn logs_of(truth: &Bench, runs: &[&str], rate_hz: f64, seed: u64, dir: &Path) -> Vec<BenchLog> {
    std::fs::create_dir_all(dir).unwrap();
    runs.iter()
        .enumerate()
        .map(|(i, run)| {
            let log = fit::synth_log(truth, run, rate_hz, seed + i as u64, dir).unwrap();
            log.write().unwrap();
            BenchLog::read(&log.path).unwrap()
        })
        .collect()
}

#[test]
fn fit_recovers_trapped_air_cd_and_precharge() {
    let dir = tmp!("three");
    let truth = bench_with(&["trapped_air=0.04", "cd=0.17", "precharge=45"].map(String::from));
    let runs = [
        "exp-charge-64.5",
        "exp-charge-72",
        "exp-9pct-101.5",
        "exp-discharge-102",
        "exp-discharge-71",
    ];
    let logs = logs_of(&truth, &runs, 5.0, 1, &dir);
    let opts = fit::FitOptions {
        spacing_s: 1.0,
        ..fit::FitOptions::new(&["trapped_air", "cd", "precharge"])
    };
    let o = fit::fit(&Bench::reference().file, logs, &opts).unwrap();
    let r = &o.report;
    for p in &r.params {
        println!(
            "{:<12} start {:.4} fitted {:.4} ± {:?}",
            p.name, p.start, p.value, p.sigma
        );
    }
    print!("{}", r.checks_table());
    println!(
        "residual RMS {:.2} → {:.2} ({:.1}×), {} simulations, {:.1} s",
        r.residual_rms.0, r.residual_rms.1, r.improvement, r.simulations, r.wall_s
    );
    let v = |n: &str| r.params.iter().find(|p| p.name == n).unwrap().value;
    assert!(r.passed, "every check holds");
    assert!((v("trapped_air") - 0.04).abs() <= 0.005, "trapped air");
    assert!((v("cd") - 0.17).abs() <= 0.03 * 0.17, "Cd");
    assert!((v("precharge") - 45.0).abs() <= 2.0, "precharge");
    assert!(r.improvement >= 10.0, "residual drops ≥ 10×");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `leakage` alone: the volumetric efficiency of a bench with η_v 0.88 (reference 0.92) from two
/// runs that turn the motor; the total efficiency follows at the bench's mechanical efficiency,
/// so no trial bench is invalid (the fit used to stop within a second, exit 2, at
/// η_total > η_v). Measured: 0.8800 ± 0.0007, reduced χ² 1.01, every check held (before the LP
/// start was fitted: 0.8843 ± 0.0040 with χ² 8.6).
#[test]
fn leakage_fits_alone() {
    let dir = tmp!("leakage");
    let truth = bench_with(&["leakage=0.88".to_string()]);
    let logs = logs_of(
        &truth,
        &["exp-9pct-101.5", "exp-discharge-71"],
        5.0,
        7,
        &dir,
    );
    let opts = fit::FitOptions {
        spacing_s: 1.0,
        ..fit::FitOptions::new(&["leakage"])
    };
    let o = fit::fit(&Bench::reference().file, logs, &opts).unwrap();
    let r = &o.report;
    let p = &r.params[0];
    println!(
        "leakage 0.92 → {:.4} ± {:?} (true 0.88), χ² {:.2}, {:.1} s",
        p.value, p.sigma, r.chi2_reduced, r.wall_s
    );
    for c in r.checks.iter().filter(|c| !c.passed) {
        println!("FAIL {}: {}", c.name, c.detail);
    }
    assert!(r.passed, "every check holds");
    assert!(
        (p.value - 0.88).abs() <= 0.01,
        "leakage recovered within 0.01"
    );
    assert!(
        (p.value - 0.88).abs() <= 3.0 * p.sigma.unwrap(),
        "the truth inside 3σ"
    );
    let f = &o.fitted.motor;
    assert!(
        (f.total_efficiency / f.volumetric_efficiency - 0.85 / 0.92).abs() < 1e-12,
        "mechanical efficiency held"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// One randomised bench's outcome.
struct Outcome {
    truth: [f64; 4],
    fitted: [(f64, f64); 4],
    passed: bool,
    failed: Vec<&'static str>,
    recovered: bool,
    chi2: f64,
    /// χ²ᵣ of the same fit started from the truth.
    chi2_truth: Option<f64>,
    wall_s: f64,
}

const NAMES: [&str; 4] = ["trapped_air", "cd", "precharge", "leakage"];

fn tolerance(k: usize, truth: f64) -> f64 {
    [0.005, 0.03 * truth, 2.0, 0.01][k]
}

/// The logs a randomised bench is fitted from.
enum Source<'a> {
    /// The paper's seven experimental runs at 10 Hz, a residual every 0.5 s.
    Paper,
    /// A campaign's segments at their rates (written with their sidecars: every sample).
    Campaign(&'a Campaign),
}

fn recover(k: u64, rng: &mut impl Rng, source: &Source) -> Outcome {
    let truth = [
        rng.random_range(0.02..0.10),
        rng.random_range(0.12..0.20),
        rng.random_range(15.0..60.0),
        rng.random_range(0.85..0.95),
    ];
    let sets: Vec<String> = NAMES
        .iter()
        .zip(truth)
        .map(|(n, v)| format!("{n}={v}"))
        .collect();
    // Apart per source: the two randomised tests run at once, and a campaign's sidecars are
    // read at fit time.
    let dir = tmp!(&format!(
        "random-{}-{k}",
        match source {
            Source::Paper => "paper",
            Source::Campaign(_) => "campaign",
        }
    ));
    let truth_bench = bench_with(&sets);
    let logs = match source {
        Source::Paper => logs_of(&truth_bench, &fit::EXPERIMENTAL_RUNS, 10.0, 100 * k, &dir),
        Source::Campaign(c) => campaign_logs(&truth_bench, c, 100 * k, &dir),
    };
    let start: BenchFile = Bench::reference().file;
    // Where the data say the fit should end: the same fit started from the truth.
    let chi2_truth = match source {
        Source::Paper => None,
        Source::Campaign(_) => Some(
            fit::fit(
                &truth_bench.file,
                logs.clone(),
                &fit::FitOptions::new(&NAMES),
            )
            .unwrap()
            .report
            .chi2_reduced,
        ),
    };
    let o = fit::fit(&start, logs, &fit::FitOptions::new(&NAMES)).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    let r = o.report;
    let fitted: Vec<(f64, f64)> = r
        .params
        .iter()
        .map(|p| (p.value, p.sigma.unwrap_or(f64::NAN)))
        .collect();
    let recovered = (0..4).all(|j| {
        let (v, s) = fitted[j];
        let err = (v - truth[j]).abs();
        err <= tolerance(j, truth[j]) && err <= 3.0 * s
    });
    Outcome {
        truth,
        fitted: [fitted[0], fitted[1], fitted[2], fitted[3]],
        passed: r.passed,
        failed: r
            .checks
            .iter()
            .filter(|c| !c.passed)
            .map(|c| c.name)
            .collect(),
        recovered,
        chi2: r.chi2_reduced,
        chi2_truth,
        wall_s: r.wall_s,
    }
}

/// A campaign's logs from `truth`, written with their sidecars and read back as `pto
/// synth-logs --campaign` writes them.
fn campaign_logs(truth: &Bench, c: &Campaign, seed: u64, dir: &Path) -> Vec<BenchLog> {
    std::fs::create_dir_all(dir).unwrap();
    c.segment
        .iter()
        .enumerate()
        .map(|(i, s)| {
            plan::synth_segment_log(truth, "planned", i, s, seed + i as u64, dir).unwrap()
        })
        .collect()
}

/// The paper's seven runs: each bench recovered or refused, never a silent miss (with four
/// parameters, refused on precision: docs/fit.md).
#[test]
fn randomised_benches_are_recovered_or_refused() {
    let n = benches("PTO_FIT_BENCHES", 1);
    let table = randomised(n, &Source::Paper);
    if n >= 8 {
        // The full set runs alone: its wall times are the fit's own.
        assert!(
            table.worst_wall <= 60.0,
            "a full fit takes ≤ 60 s on 2 cores"
        );
    }
}

/// The campaign `pto plan` gives from the reference bench (the four parameters at their
/// default precisions, 45 min; `host-tests/data/campaign-four.toml`): the drawn bench's logs
/// of it, the four fitted from the reference bench. On ≥ 7 of 8 every check holds with each
/// value within its tolerance, each fit ≤ 90 s; no silent miss on any; each passing fit's χ²ᵣ
/// within 0.1 of the same fit's from the truth. Two benches in `cargo test`, both recovered.
#[test]
fn randomised_benches_from_a_planned_campaign_are_recovered() {
    let n = benches("PTO_FIT_CAMPAIGN_BENCHES", 2);
    // `pto plan`'s campaign from the reference bench, as committed (tests/tools/plan.rs checks that
    // the plan still gives it).
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/campaign-four.toml");
    let c = Campaign::load(&path, &Bench::reference()).unwrap();
    println!(
        "campaign: {} ({:.0} min of bench time)",
        c.segment
            .iter()
            .map(|s| s.run.name.as_str())
            .collect::<Vec<_>>()
            .join(", "),
        c.minutes()
    );
    assert!(c.minutes() <= 45.0, "the campaign takes ≤ 45 min");
    let table = randomised(n, &Source::Campaign(&c));
    assert!(
        table.short_of_truth <= 0.1,
        "a fit ends where the data say: χ²ᵣ within 0.1 of the fit from the truth"
    );
    if n >= 8 {
        assert!(
            table.passed_recovered >= 7,
            "{} of {n} recovered with every check holding",
            table.passed_recovered
        );
        assert!(table.worst_wall <= 90.0, "each fit ≤ 90 s on 2 cores");
    } else {
        assert_eq!(
            table.passed_recovered, n as usize,
            "every bench of the short set recovered"
        );
    }
}

fn benches(var: &str, default: u64) -> u64 {
    std::env::var(var)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// What a randomised set came to.
struct Table {
    passed_recovered: usize,
    worst_wall: f64,
    /// The largest amount a passing fit's χ²ᵣ exceeds that of the fit from the truth.
    short_of_truth: f64,
}

/// `n` benches drawn (seeded) and fitted from `source`: prints the table, asserts no silent
/// miss and that a failed fit names its check.
fn randomised(n: u64, source: &Source) -> Table {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2026);
    println!(
        "| # | trapped air true → fitted ± σ | Cd | precharge (bar) | η_v | χ² | verdict | s |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    let mut silent = Vec::new();
    let mut worst_wall: f64 = 0.0;
    let mut passed_recovered = 0;
    let mut short_of_truth: f64 = f64::NEG_INFINITY;
    for k in 1..=n {
        let o = recover(k, &mut rng, source);
        let cell = |j: usize, d: usize| {
            format!(
                "{:.d$} → {:.d$} ± {:.d$}",
                o.truth[j], o.fitted[j].0, o.fitted[j].1
            )
        };
        let verdict = match (o.passed, o.recovered) {
            (true, true) => "passed, recovered".to_string(),
            (true, false) => "PASSED BUT MISSED".to_string(),
            (false, _) => format!(
                "failed: {}{}",
                o.failed.join(", "),
                if o.recovered {
                    " (values were within)"
                } else {
                    ""
                }
            ),
        };
        let chi2 = match o.chi2_truth {
            Some(t) => format!("{:.2} (from the truth {t:.2})", o.chi2),
            None => format!("{:.2}", o.chi2),
        };
        println!(
            "| {k} | {} | {} | {} | {} | {chi2} | {verdict} | {:.0} |",
            cell(0, 4),
            cell(1, 4),
            cell(2, 2),
            cell(3, 4),
            o.wall_s
        );
        if let Some(t) = o.chi2_truth
            && o.passed
        {
            short_of_truth = short_of_truth.max(o.chi2 - t);
        }
        worst_wall = worst_wall.max(o.wall_s);
        passed_recovered += usize::from(o.passed && o.recovered);
        if o.passed && !o.recovered {
            silent.push(k);
        }
        if !o.passed {
            assert!(!o.failed.is_empty(), "a failed fit names its check");
        }
    }
    println!("slowest fit {worst_wall:.1} s; {passed_recovered} of {n} passed and recovered");
    if short_of_truth.is_finite() {
        println!(
            "a passing fit's χ²ᵣ above the fit from the truth's by at most {short_of_truth:.3}"
        );
    }
    assert!(silent.is_empty(), "silent misses: benches {silent:?}");
    Table {
        passed_recovered,
        worst_wall,
        short_of_truth,
    }
}

/// A plant the model does not match stays honest: the planned campaign's logs from benches with
/// a field the fit holds at the bench file's value set otherwise (the four parameters changed
/// too), fitted from the reference bench: either every value within its tolerance, or a failed
/// check named — never exit 0 out of tolerance. LP precharge 6 bar for the file's 4 (the LP
/// accumulator's stiffness, which the LP channel follows) and seal friction 20 times the
/// file's (the rod's drift through the play).
///
/// Not among them: check valves cracking 2 bar above the file's. Its logs are fitted as well
/// as by the truth (χ²ᵣ 0.964 against 0.958) with trapped air 0.056 for 0.04 — a late suction
/// valve lets the chamber fall further below LP, where its air expands more: in P2, speed and
/// LP it is trapped air, and no check on the residuals can tell (docs/fit.md, "A plant the
/// model does not match"). What `pto plan` says of it instead is checked: the held fields'
/// leverage predicts that shift of trapped air within a factor 1.5. Three fits, 3–4 min: on
/// demand (`-- --ignored`).
#[test]
#[ignore = "three fits, 3–4 min: cargo test -p pto-host --test tools fit_recovery::a_plant_the_model_does_not_match -- --ignored"]
fn a_plant_the_model_does_not_match_is_fitted_within_tolerance_or_refused() {
    let truth = [0.04, 0.17, 40.0, 0.90];
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/campaign-four.toml");
    let c = Campaign::load(&path, &Bench::reference()).unwrap();
    let cases = [
        "lp_accumulator.precharge_bar=6",
        "cylinder_mounting.seal_friction_n_s_per_m=40000",
    ];
    let mut silent = Vec::new();
    for (k, effect) in cases.into_iter().enumerate() {
        let mut sets: Vec<String> = NAMES
            .iter()
            .zip(truth)
            .map(|(n, v)| format!("{n}={v}"))
            .collect();
        sets.push(effect.into());
        let dir = tmp!(&format!("mismatch{k}"));
        let logs = campaign_logs(&bench_with(&sets), &c, 7, &dir);
        let o = fit::fit(
            &Bench::reference().file,
            logs,
            &fit::FitOptions::new(&NAMES),
        )
        .unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        let r = &o.report;
        println!("plant with {effect}:");
        let mut within = true;
        for (j, p) in r.params.iter().enumerate() {
            let err = (p.value - truth[j]).abs();
            println!(
                "  {:<12} true {:.4} fitted {:.4} ± {:.4}: off by {err:.4} (tolerance {:.4})",
                p.name,
                truth[j],
                p.value,
                p.sigma.unwrap_or(f64::NAN),
                tolerance(j, truth[j])
            );
            within &= err <= tolerance(j, truth[j]);
        }
        print!("{}", r.checks_table());
        println!(
            "  χ²ᵣ {:.2}, passed {}, every value within tolerance {within}, {:.0} s",
            r.chi2_reduced, r.passed, r.wall_s
        );
        if r.passed && !within {
            silent.push(effect);
        }
        assert!(
            r.passed || r.checks.iter().any(|c| !c.passed),
            "a failure is named"
        );
    }
    assert!(silent.is_empty(), "passed out of tolerance: {silent:?}");
    // Check valves cracking 2 bar late: the shift of trapped air the plan predicts.
    let mut sets: Vec<String> = NAMES
        .iter()
        .zip(truth)
        .map(|(n, v)| format!("{n}={v}"))
        .collect();
    sets.push("check_valve.cracking_bar=2.5".into());
    sets.push("check_valve.full_open_bar=3.5".into());
    let reference = Bench::reference();
    let held = c
        .held_leverage(&reference.file, &fit::sensor_noise())
        .unwrap();
    let cracking = held
        .iter()
        .find(|h| h.field == "check_valve.cracking_bar")
        .unwrap();
    let predicted = 2.0 * cracking.shift_per_unit[0];
    let dir = tmp!("mismatch-cv");
    let logs = campaign_logs(&bench_with(&sets), &c, 7, &dir);
    let o = fit::fit(&reference.file, logs, &fit::FitOptions::new(&NAMES)).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    let shift = o.report.params[0].value - truth[0];
    println!(
        "check valves 2 bar late: trapped air {:.4} for {:.4} (shift {shift:+.4}; the plan's \
         leverage predicted {predicted:+.4}), χ²ᵣ {:.3}, passed {}",
        o.report.params[0].value, truth[0], o.report.chi2_reduced, o.report.passed
    );
    assert!(
        (1.0 / 1.5..=1.5).contains(&(shift / predicted)),
        "the plan's leverage predicts the shift: {shift} against {predicted}"
    );
}
