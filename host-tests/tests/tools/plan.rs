//! `pto plan`: the campaign planned from the reference bench for the four parameters
//! (`host-tests/data/campaign-four.toml`, what `pto plan` writes with its defaults) is what the
//! plan still gives, it meets its precisions and says what it cannot meet; and its predictions
//! hold — each parameter's fitted σ, and over noise seeds its scatter, within a factor 1.5 of
//! the σ the plan predicted.
//!
//! `the_predicted_sigma_is_the_fit_s_scatter` fits one noise seed in `cargo test` (each fit's
//! σ against the prediction, the truth inside 3σ); `PTO_PLAN_SEEDS=8` fits eight and compares
//! the scatter too (docs/fit.md, "Planning a calibration").

use pto_host::fit;
use pto_host::plan::{self, Campaign, Goal, Menu};
use pto_host::sim::bench::Bench;
use pto_host::sim::benchlog::BenchLog;
use std::path::Path;

const NAMES: [&str; 4] = ["trapped_air", "cd", "precharge", "leakage"];

fn committed() -> Campaign {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/campaign-four.toml");
    Campaign::load(&path, &Bench::reference()).unwrap()
}

/// The plan from the reference bench with `pto plan`'s defaults reproduces the committed
/// campaign (segments and predicted σ) and meets every precision within 45 min; asked for
/// precisions no candidate reaches within 3 min, it is not met, names each short parameter
/// with what blocks it, and stays within the budget.
#[test]
fn the_plan_meets_what_it_can_and_names_what_it_cannot() {
    let bench = Bench::reference();
    let params = fit::params(&NAMES.map(String::from), &bench.file).unwrap();
    let noise = fit::sensor_noise();
    let t0 = std::time::Instant::now();
    let scored = plan::score(
        &bench.file,
        &params,
        &noise,
        plan::candidates(&bench, &Menu::default()),
        None,
    )
    .unwrap();
    let scoring_s = t0.elapsed().as_secs_f64();
    let needed: Vec<f64> = params
        .iter()
        .map(|p| p.needed.at((p.get)(&bench.file)))
        .collect();
    let p = plan::plan(
        &scored,
        &params,
        &bench.file,
        &noise,
        &Goal {
            needed: needed.clone(),
            budget_min: 45.0,
        },
    );
    println!(
        "{} candidates scored in {scoring_s:.1} s: {} segments, {:.1} min, {} set-ups, met {}",
        p.candidates,
        p.campaign.segment.len(),
        p.minutes,
        p.interventions,
        p.met
    );
    let c = committed();
    for (q, k) in p.campaign.predicted.iter().zip(&c.predicted) {
        println!(
            "  {:<12} σ {:.3e} (committed {:.3e}), 3σ {:.3e} against {:.3e}",
            q.name,
            q.sigma,
            k.sigma,
            3.0 * q.sigma,
            q.needed
        );
        // A staleness check, not a precision: glibc picks its exp/pow code
        // path per CPU (FMA or not), so the last bits differ between
        // machines and grow through the adaptive solver and the finite
        // differences (2.3e-6 relative measured between this machine and
        // CI). With the rods' stops as located events the test build and
        // the release build that wrote the file differ far more: 4.4e-4
        // (trapped air), 9.3e-3 (Cd; with the stop spring < 1e-4), not
        // traced yet (the finite-difference columns through the events are
        // the suspect). The segments are compared exactly below; a change
        // to the model moves σ by percents (the events: trapped air 3.7 %,
        // Cd 5.0 %), which 2 % still catches.
        assert!(
            (q.sigma / k.sigma - 1.0).abs() < 2e-2,
            "{}: σ {} against the committed {}: rerun `pto plan --out \
             host-tests/data/campaign-four.toml`",
            q.name,
            q.sigma,
            k.sigma
        );
    }
    assert!(p.met && p.minutes <= 45.0, "{} min", p.minutes);
    assert_eq!(
        p.campaign.segment, c.segment,
        "the committed campaign is stale: rerun `pto plan --out host-tests/data/campaign-four.toml`"
    );
    // Every segment pulls its weight: without any one, some σ grows.
    for (k, without) in p.without.iter().enumerate() {
        assert!(
            without
                .iter()
                .zip(&p.campaign.predicted)
                .any(|(w, q)| *w > 1.01 * q.sigma),
            "segment {k} adds nothing"
        );
    }
    let tight: Vec<f64> = needed.iter().map(|n| n * 1e-3).collect();
    let q = plan::plan(
        &scored,
        &params,
        &bench.file,
        &noise,
        &Goal {
            needed: tight,
            budget_min: 3.0,
        },
    );
    assert!(
        !q.met && q.minutes <= 3.0,
        "{} min, met {}",
        q.minutes,
        q.met
    );
    assert_eq!(q.short.len(), 4, "each parameter is named");
    for s in &q.short {
        println!(
            "  short: {} 3σ {:.3e} > {:.3e}, blocked by {:?}; {}",
            s.name, s.three_sigma, s.needed, s.blocked_by, s.help
        );
        assert!(s.three_sigma > s.needed && s.blocked_by.is_some());
        assert!(!s.help.is_empty());
    }
}

/// The held fields' leverage under the committed campaign names what the four fitted
/// parameters cannot be told from: the check valves' cracking and the HP accumulator's volume
/// move trapped air (a 2 bar cracking error, or 1 % of the volume, beyond its precision); an
/// LP precharge off by its whole value moves none past its precision (it shows in the
/// residuals instead: `fit_recovery`'s mismatch test), nor does a seal friction off by twice
/// its value in this linear reading. (With the stops as events a free rod crosses its play at
/// a speed ∝ 1/friction, so the step at the file's value overstates a large error: linearly
/// ± 14 700 N·s/m on η_v, yet `fit_recovery`'s plant with 20× the friction fits η_v within
/// 0.0006.)
#[test]
fn the_held_fields_that_move_a_fitted_parameter_are_named() {
    let bench = Bench::reference();
    let t0 = std::time::Instant::now();
    let held = committed()
        .held_leverage(&bench.file, &fit::sensor_noise())
        .unwrap();
    println!(
        "{} held fields in {:.1} s",
        held.len(),
        t0.elapsed().as_secs_f64()
    );
    assert_eq!(held.len(), 6, "every held field of the reference bench");
    let within = |field: &str| {
        let h = held.iter().find(|h| h.field == field).unwrap();
        println!(
            "  {field:<42} {} {}: keep within {:?}; shifts per unit {:?}",
            h.value, h.unit, h.keep_within, h.shift_per_unit
        );
        h.keep_within.clone()
    };
    let cracking = within("check_valve.cracking_bar").unwrap();
    assert!(
        cracking.error < 2.0 && cracking.limited_by == "trapped_air",
        "{cracking:?}"
    );
    let volume = within("hp_accumulator.volume_l").unwrap();
    assert!(
        volume.error < 0.1 && volume.limited_by == "trapped_air",
        "{volume:?}"
    );
    // Off by their whole value (LP 4 bar) or twice it (friction, 4 000 N·s/m), neither moves
    // a fitted value past its precision.
    let lp = within("lp_accumulator.precharge_bar").unwrap();
    assert!(lp.error > 4.0, "{lp:?}");
    let friction = within("cylinder_mounting.seal_friction_n_s_per_m").unwrap();
    assert!(friction.error > 4_000.0, "{friction:?}");
    within("oil.liquid_bulk_modulus_mpa");
    within("cylinder_mounting.dead_volume_cm3");
}

/// The committed campaign's logs from the reference bench over noise seeds, the four fitted
/// from it: each fit passes with the truth inside 3σ, its σ within a factor 1.5 of the plan's;
/// over ≥ 8 seeds, each parameter's scatter within a factor 1.5 of the plan's σ.
#[test]
fn the_predicted_sigma_is_the_fit_s_scatter() {
    let seeds: u64 = std::env::var("PTO_PLAN_SEEDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1);
    let c = committed();
    let truth = Bench::reference();
    let dir = std::env::temp_dir().join(format!("pto-plan-test-{}", std::process::id()));
    let mut values: Vec<Vec<f64>> = vec![Vec::new(); NAMES.len()];
    for seed in 0..seeds {
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let logs: Vec<BenchLog> = c
            .segment
            .iter()
            .enumerate()
            .map(|(i, s)| {
                plan::synth_segment_log(
                    &truth,
                    "campaign-four.toml",
                    i,
                    s,
                    100 * seed + i as u64,
                    &dir,
                )
                .unwrap()
            })
            .collect();
        let out = fit::fit(&truth.file, logs, &fit::FitOptions::new(&NAMES)).unwrap();
        let r = &out.report;
        println!(
            "seed {seed}: χ²ᵣ {:.3}, {} simulations, {:.1} s, passed {}",
            r.chi2_reduced, r.simulations, r.wall_s, r.passed
        );
        assert!(r.passed, "seed {seed}: every check holds");
        for ((f, q), v) in r.params.iter().zip(&c.predicted).zip(&mut values) {
            let sigma = f.sigma.unwrap();
            let truth_value = f.start;
            println!(
                "  {:<12} {:.5} ± {:.2e} (truth {truth_value:.5}; predicted σ {:.2e}, ratio {:.2})",
                f.name,
                f.value,
                sigma,
                q.sigma,
                sigma / q.sigma
            );
            assert!(
                (1.0 / 1.5..=1.5).contains(&(sigma / q.sigma)),
                "{}: the fit's σ {sigma:.2e} against the predicted {:.2e}",
                f.name,
                q.sigma
            );
            assert!(
                (f.value - truth_value).abs() <= 3.0 * sigma,
                "{}: the truth inside 3σ",
                f.name
            );
            v.push(f.value);
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    if seeds >= 8 {
        let n = seeds as f64;
        for ((v, q), name) in values.iter().zip(&c.predicted).zip(NAMES) {
            let mean = v.iter().sum::<f64>() / n;
            let scatter = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
            println!(
                "{name:<12} over {seeds} seeds: mean {mean:.5}, scatter {scatter:.2e}, predicted \
                 {:.2e}: ratio {:.2}",
                q.sigma,
                scatter / q.sigma
            );
            assert!(
                (1.0 / 1.5..=1.5).contains(&(scatter / q.sigma)),
                "{name}: scatter {scatter:.2e} against the predicted {:.2e}",
                q.sigma
            );
        }
    }
}
