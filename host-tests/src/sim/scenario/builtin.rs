//! The paper's 62 runs as built-in scenarios: Test I (valve open), Test II (valve closed to the
//! relief), Test III (apertures), the torque runs, the blocked input, the experimental runs of
//! Section 4.2 and an irregular sea.

use super::{Scenario, ValveSpec};
use crate::sim::motion::MotionSpec;

fn sine() -> MotionSpec {
    MotionSpec::Sine {
        amplitude_mm: 40.0,
        frequency_hz: 0.1,
    }
}

/// Cylinder sets of the paper's figures, with short tags.
pub const SETS: [(&str, &[&str]); 4] = [
    ("c1", &["HC3.1"]),
    ("c4", &["HC3.4"]),
    ("c14", &["HC3.1", "HC3.4"]),
    ("c1234", &["HC3.1", "HC3.2", "HC3.3", "HC3.4"]),
];

/// Test III apertures, %.
pub const TEST3_APERTURES: [f64; 6] = [5.0, 8.0, 10.0, 15.0, 20.0, 25.0];
/// Blocked-input apertures, %.
pub const BLOCKED_APERTURES: [f64; 5] = [10.0, 12.0, 15.0, 20.0, 25.0];

#[allow(clippy::too_many_arguments)]
fn scenario(
    name: String,
    group: &str,
    description: String,
    config: usize,
    cylinders: &[&str],
    motion: MotionSpec,
    valve: ValveSpec,
    duration_s: f64,
    sample_interval_s: f64,
    initial_hp_bar: Option<f64>,
) -> Scenario {
    Scenario {
        name,
        description,
        group: group.into(),
        config: format!("Config {config}"),
        cylinders: cylinders.iter().map(|s| s.to_string()).collect(),
        motion,
        valve,
        duration_s,
        sample_interval_s,
        initial_hp_bar,
        initial_lp_bar: 8.0,
    }
}

/// Every built-in scenario, in the order of the paper.
pub fn builtin() -> Vec<Scenario> {
    let mut v = Vec::new();
    let open = ValveSpec::Constant {
        aperture_pct: 100.0,
    };
    let closed = ValveSpec::Constant { aperture_pct: 0.0 };
    // Test I: valve fully open, periodic steady state. {HC3.1, HC3.3} added for fact 7.
    for config in [1, 2, 3] {
        for (tag, set) in SETS
            .iter()
            .copied()
            .chain([("c13", &["HC3.1", "HC3.3"][..])])
        {
            v.push(scenario(
                format!("test1-cfg{config}-{tag}"),
                "test1",
                format!(
                    "Test I: valve 100 %, Config {config}, {} on duty",
                    set.join(" + ")
                ),
                config,
                set,
                sine(),
                open.clone(),
                150.0,
                0.01,
                None,
            ));
        }
    }
    // Test II: valve closed from 30 bar until the relief holds P2.
    for config in 1..=4 {
        for (tag, set) in SETS {
            v.push(scenario(
                format!("test2-cfg{config}-{tag}"),
                "test2",
                format!(
                    "Test II: valve closed, Config {config}, {} on duty, from 30 bar",
                    set.join(" + ")
                ),
                config,
                set,
                sine(),
                closed.clone(),
                1200.0,
                0.05,
                Some(30.0),
            ));
        }
    }
    // Restraining torque (Figs. 15/16): valve closed near 100 bar, three wave periods.
    for config in 1..=3 {
        for (tag, set) in SETS {
            v.push(scenario(
                format!("torque-cfg{config}-{tag}"),
                "torque",
                format!(
                    "Restraining torque: valve closed from 100 bar, Config {config}, {}",
                    set.join(" + ")
                ),
                config,
                set,
                sine(),
                closed.clone(),
                30.0,
                0.005,
                Some(100.0),
            ));
        }
    }
    // Test III: HC3.1 + HC3.4, Config 1, valve opens at 100 bar.
    for ap in TEST3_APERTURES {
        v.push(scenario(
            format!("test3-ap{ap}"),
            "test3",
            format!("Test III: HC3.1 + HC3.4, Config 1, from 60 bar, valve to {ap} % at 100 bar"),
            1,
            &["HC3.1", "HC3.4"],
            sine(),
            ValveSpec::Threshold {
                threshold_bar: 100.0,
                aperture_pct: ap,
            },
            400.0,
            0.01,
            Some(60.0),
        ));
    }
    // Blocked input from 102 bar (Fig. 19).
    for ap in BLOCKED_APERTURES {
        v.push(scenario(
            format!("blocked-ap{ap}"),
            "blocked",
            format!("Blocked input from 102 bar, valve {ap} %"),
            1,
            &["HC3.1", "HC3.4"],
            MotionSpec::Blocked { angle_deg: 0.0 },
            ValveSpec::Constant { aperture_pct: ap },
            600.0,
            0.05,
            Some(102.0),
        ));
    }
    // The experimental runs of Section 4.2 (Config 1).
    // (name, cylinders, initial P2 bar, aperture %, input blocked, duration s)
    type ExpRun<'a> = (&'a str, &'a [&'a str], f64, f64, bool, f64);
    let exp: [ExpRun; 7] = [
        (
            "exp-charge-64.5",
            &["HC3.1", "HC3.3"],
            64.5,
            0.0,
            false,
            200.0,
        ),
        ("exp-charge-67.2", &["HC3.2"], 67.2, 0.0, false, 200.0),
        ("exp-charge-72", &["HC3.4"], 72.0, 0.0, false, 200.0),
        (
            "exp-9pct-101.5",
            &["HC3.1", "HC3.3"],
            101.5,
            9.0,
            false,
            300.0,
        ),
        (
            "exp-discharge-102",
            &["HC3.1", "HC3.4"],
            102.0,
            12.0,
            true,
            200.0,
        ),
        (
            "exp-discharge-84",
            &["HC3.1", "HC3.4"],
            84.0,
            15.0,
            true,
            200.0,
        ),
        (
            "exp-discharge-71",
            &["HC3.1", "HC3.4"],
            71.0,
            25.0,
            true,
            200.0,
        ),
    ];
    for (name, set, p0, ap, blocked, dur) in exp {
        v.push(scenario(
            name.into(),
            "experimental",
            format!(
                "Experimental run: {}, {} from {p0} bar, valve {ap} %",
                if blocked {
                    "input blocked"
                } else {
                    "±40 mm at 0.1 Hz"
                },
                set.join(" + ")
            ),
            1,
            set,
            if blocked {
                MotionSpec::Blocked { angle_deg: 0.0 }
            } else {
                sine()
            },
            ValveSpec::Constant { aperture_pct: ap },
            dur,
            0.02,
            Some(p0),
        ));
    }
    // Irregular sea: the performance case and the estimator's validation input.
    v.push(scenario(
        "irregular-sea".into(),
        "irregular",
        "Irregular sea: JONSWAP Hs 50 mm of rack, Tp 10 s, HC3.1 + HC3.4, Config 1, valve 10 % at 100 bar".into(),
        1,
        &["HC3.1", "HC3.4"],
        MotionSpec::Irregular {
            significant_mm: 50.0,
            peak_period_s: 10.0,
            gamma: 3.3,
            components: 64,
            seed: 1,
        },
        ValveSpec::Threshold {
            threshold_bar: 100.0,
            aperture_pct: 10.0,
        },
        1000.0,
        0.02,
        Some(60.0),
    ));
    v
}

/// Significant rack displacements of the sea family, mm (4σ).
pub const FAMILY_HS_MM: [f64; 3] = [20.0, 40.0, 60.0];
/// Peak periods of the sea family, s.
pub const FAMILY_TP_S: [f64; 3] = [6.0, 10.0, 14.0];
/// Phase seeds of each sea state of the family.
pub const FAMILY_SEEDS: [u64; 2] = [11, 12];
/// Length of a family run, s.
pub const FAMILY_DURATION_S: f64 = 300.0;

/// The estimator's family of irregular seas (group `sea-family`): JONSWAP seas over
/// [`FAMILY_HS_MM`] × [`FAMILY_TP_S`] × [`FAMILY_SEEDS`], 300 s each, HC3.1 + HC3.4 in
/// Config 1 from 60 bar with the valve opening to 10 % at 100 bar (the irregular-sea run's
/// set-up), 128 spectral components so that a run does not repeat itself within 300 s; and
/// two starts from an empty HP node (P2 = LP = 8 bar) with the lever moving: the irregular
/// sea at Hs 40 mm, and the paper's sine, which starts at its full speed.
pub fn sea_family() -> Vec<Scenario> {
    let mut v = Vec::new();
    let threshold = ValveSpec::Threshold {
        threshold_bar: 100.0,
        aperture_pct: 10.0,
    };
    let sea = |hs: f64, tp: f64, seed: u64| MotionSpec::Irregular {
        significant_mm: hs,
        peak_period_s: tp,
        gamma: 3.3,
        components: 128,
        seed,
    };
    for hs in FAMILY_HS_MM {
        for tp in FAMILY_TP_S {
            for seed in FAMILY_SEEDS {
                v.push(scenario(
                    format!("sea-hs{hs:.0}-tp{tp:.0}-s{seed}"),
                    "sea-family",
                    format!(
                        "Irregular sea: JONSWAP Hs {hs:.0} mm of rack, Tp {tp:.0} s, seed \
                         {seed}, HC3.1 + HC3.4, Config 1, from 60 bar, valve 10 % at 100 bar"
                    ),
                    1,
                    &["HC3.1", "HC3.4"],
                    sea(hs, tp, seed),
                    threshold.clone(),
                    FAMILY_DURATION_S,
                    0.02,
                    Some(60.0),
                ));
            }
        }
    }
    v.push(scenario(
        "sea-empty-start".into(),
        "sea-family",
        "Irregular sea Hs 40 mm, Tp 10 s, from an empty HP node (P2 = LP = 8 bar), HC3.1 + \
         HC3.4, Config 1, valve 10 % at 100 bar"
            .into(),
        1,
        &["HC3.1", "HC3.4"],
        sea(40.0, 10.0, 11),
        threshold.clone(),
        FAMILY_DURATION_S,
        0.02,
        Some(8.0),
    ));
    v.push(scenario(
        "sine-empty-start".into(),
        "sea-family",
        "Sine ±40 mm at 0.1 Hz starting at full speed, from an empty HP node (P2 = LP = 8 bar), \
         HC3.1 + HC3.4, Config 1, valve 10 % at 100 bar"
            .into(),
        1,
        &["HC3.1", "HC3.4"],
        sine(),
        threshold,
        120.0,
        0.02,
        Some(8.0),
    ));
    v
}

/// Every built-in scenario: the paper's runs ([`builtin`]) and the sea family ([`sea_family`]).
pub fn every_builtin() -> Vec<Scenario> {
    let mut v = builtin();
    v.extend(sea_family());
    v
}

/// The built-in scenario called `name` (the paper's runs and the sea family).
pub fn builtin_named(name: &str) -> Option<Scenario> {
    every_builtin().into_iter().find(|s| s.name == name)
}
