//! The fixed-point model against the full simulation (the `pto validate` harness, reduced to a
//! representative set so `cargo test` stays quick), and the scheduler in closed loop.
//!
//! Asserted here: every target of every selected run — P2 with and without the HP transducer,
//! motor speed, torque (RMS ≤ 5 % of the peak), fixed point vs f64 (0.05 bar, 0.5 N·m) — and
//! both closed-loop targets. The selection covers Test III, a torque run, Test II with all four
//! cylinders at the relief (the worst fixed-vs-f64 torque before the pressure nodes kept their
//! sub-LSB bits), a blocked input and the 71 bar discharge (both cross the HP precharge), the
//! experimental runs and the irregular sea; a blocked input at 25 % (P2 ends below the precharge
//! with the motor stopped, on the stiff empty node); and Test I with HC3.1 + HC3.4 in Config 3,
//! whose P2 crosses the precharge every wave (fixed vs f64 0.145 bar before the Kalman variance
//! kept its sub-LSB bits, 0.02–0.03 since). The other Test I runs with one or two cylinders
//! (HP accumulator empty) meet the P2, torque and motor-speed targets, and with one small
//! cylinder every target (the motor speed reading P2, the rod floating in its free play),
//! asserted on one of them below; the model-only P2 of the runs with HC3.4 is left to
//! `pto validate` (see `docs/model.md`), and why two of them cannot meet it with these sensors is
//! measured on the full simulation below.

use pto_host::sim::bench::Bench;
use pto_host::validation::{target, validate};

/// `pto validate`'s rows for the named built-in scenarios (every one must exist and run).
fn validate_named(names: &[&str]) -> Vec<validate::Row> {
    let sel: Vec<_> = pto_host::sim::scenario::builtin()
        .into_iter()
        .filter(|s| names.contains(&s.name.as_str()))
        .collect();
    assert_eq!(sel.len(), names.len());
    let rep = validate::run(&Bench::reference(), &sel, false);
    assert!(rep.errors.is_empty(), "{:?}", rep.errors);
    rep.rows
}

/// Every target of `pto validate` met, or the targets missed named.
fn assert_meets(r: &validate::Row) {
    assert!(
        r.pass && r.missed.is_empty(),
        "{}: missed {:?}",
        r.scenario,
        r.missed
    );
}

#[test]
fn model_tracks_the_full_simulation_on_representative_runs() {
    let names = [
        "test3-ap10",
        "test3-ap25",
        "torque-cfg3-c14",
        "exp-charge-67.2",
        "exp-discharge-84",
        "irregular-sea",
        "test2-cfg1-c1234",
        "blocked-ap10",
        "exp-discharge-71",
        "blocked-ap25",
        "test1-cfg3-c14",
    ];
    for r in &validate_named(&names) {
        println!(
            "{:<18} P2 RMS {:.3} bar, no-HP max {:.3} bar, torque {:?}, motor {:?}, fx-f64 {:.4} bar / {:.3} N·m",
            r.scenario,
            r.p2_rms_bar,
            r.p2_model_only_max_bar,
            r.torque_rms_of_peak,
            r.motor_rms_rel,
            r.fixed_vs_f64_bar,
            r.fixed_vs_f64_nm
        );
        assert_meets(r);
        // The telemetry's hydraulic power (P2 · valve flow): the valve flow is the motor's, so
        // it is held to the motor speed's 3 %.
        if let Some(pw) = r.valve_power_rms_of_mean {
            println!(
                "{:<18} valve power RMS error {:.2} % of its mean",
                r.scenario,
                pw * 100.0
            );
            assert!(pw <= target::MOTOR_RMS_REL, "{}: {pw}", r.scenario);
        }
        // Stricter than the harness, which judges it only where the estimate stays above the
        // precharge + 1 bar: these runs meet it throughout.
        assert!(
            r.p2_model_only_max_bar <= target::P2_MODEL_ONLY_MAX_BAR,
            "{}",
            r.scenario
        );
    }
}

/// The sea family (`pto validate`'s group `sea-family`: 18 JONSWAP seas over Hs 20–60 mm of
/// rack, Tp 6–14 s, two seeds each, 300 s, and two starts from an empty HP node with the lever
/// moving): in every run the torque RMS error is within 5 % of the peak, P2 within 0.3 bar RMS
/// with the transducer, the model-only P2 within 2 bar where it applies, σ covers the error and
/// fixed point follows f64. Small and partial strokes leave the rods standing in their free play
/// (a stroke shorter than the play, a reversal that comes before the rod engaged, a tracker
/// speed flickering about zero at a slow reversal); without the eye's position in its play
/// carried from one reversal to the next (`CylState::gap`) the Hs 20 mm seas run 5–10 % of
/// peak, with 4 s events of up to 54 % of peak.
///
/// Motor speed is not asserted here: it is judged (and reported as missed where it is) by
/// `pto validate`. In two runs the valve opens at 100 bar only in the run's last 30–40 s, and
/// ≈ 94 % of the motor's squared error sits in the 0.2 s spin-up after the opening, where the
/// full simulation's motor line (oil with trapped air, pressurised from LP) delays the rotor by
/// ≈ 70 ms and overshoots, which the reduced model (no motor-line node) does not carry; see
/// `docs/model.md`.
#[test]
fn model_tracks_the_full_simulation_over_the_sea_family() {
    let sel = pto_host::sim::scenario::sea_family();
    assert!(sel.len() >= 12);
    let rep = validate::run(&Bench::reference(), &sel, false);
    assert!(rep.errors.is_empty(), "{:?}", rep.errors);
    let spread = rep.sea_family.as_ref().expect("the family's spread");
    println!(
        "sea family over {} runs, worst / median: torque RMS {:.2} / {:.2} % of peak, worst 4 s \
         {:.1} / {:.1} % of peak, P2 RMS {:.3} / {:.3} bar, motor {:.2} / {:.2} %",
        spread.runs,
        spread.torque_rms_of_peak.0 * 100.0,
        spread.torque_rms_of_peak.1 * 100.0,
        spread.torque_worst_4s_of_peak.0 * 100.0,
        spread.torque_worst_4s_of_peak.1 * 100.0,
        spread.p2_rms_bar.0,
        spread.p2_rms_bar.1,
        spread.motor_rms_rel.0 * 100.0,
        spread.motor_rms_rel.1 * 100.0,
    );
    assert_eq!(spread.runs, sel.len());
    for r in &rep.rows {
        let others: Vec<_> = r
            .missed
            .iter()
            .filter(|m| !m.starts_with("motor "))
            .collect();
        assert!(others.is_empty(), "{}: missed {others:?}", r.scenario);
        let tq = r.torque_rms_of_peak.expect("the lever moves");
        assert!(
            tq <= target::TORQUE_RMS_OF_PEAK,
            "{}: torque {tq}",
            r.scenario
        );
        assert!(r.p2_rms_bar <= target::P2_RMS_BAR, "{}", r.scenario);
        assert!(r.cover_2s >= target::COVER_2S && r.cover_3s >= target::COVER_3S);
    }
}

/// Test I with one cylinder: the HP accumulator is empty and P2 follows the motor, whose rotor
/// inertia the model carries (the quasi-static valve/motor law missed the speed by 10–13 %).
/// Without the HP transducer the motor speed reads P2 (the model alone was 4.4 bar off). At
/// P2 ≈ 10 bar the small rod runs ahead of its eye on the annulus stroke and is pushed at once
/// when the lever turns back (the torque was 6.8 % of peak off while the model had the eye cross
/// its play first).
#[test]
fn model_tracks_p2_and_motor_speed_with_the_hp_accumulator_empty() {
    let rows = validate_named(&["test1-cfg1-c1"]);
    let r = &rows[0];
    let motor = r.motor_rms_rel.expect("Test I runs the motor");
    let torque = r.torque_rms_of_peak.expect("Test I moves the lever");
    println!(
        "{}: P2 RMS {:.3} bar (target {}), no-HP max {:.3} bar (target {}), torque {:.2} % \
         (target {} %), motor {:.2} % (target {} %), fx-f64 {:.4} bar (target {})",
        r.scenario,
        r.p2_rms_bar,
        target::P2_RMS_BAR,
        r.p2_model_only_max_bar,
        target::P2_MODEL_ONLY_MAX_BAR,
        100.0 * torque,
        100.0 * target::TORQUE_RMS_OF_PEAK,
        100.0 * motor,
        100.0 * target::MOTOR_RMS_REL,
        r.fixed_vs_f64_bar,
        target::FIXED_VS_F64_BAR
    );
    assert_meets(r);
    assert!(r.p2_model_only_max_bar <= target::P2_MODEL_ONLY_MAX_BAR);
}

/// Why model-only P2 misses its 2 bar target in Test I with HC3.1 + HC3.4 in Configs 1–2 (`docs/model.md`,
/// "Known limits"): each time the plant's HP accumulator runs empty, P2 falls 2 bar below where it
/// hovered within 7–13 ms, and by then the motor speed, the only sensor left that sees the fall,
/// has moved ≤ 1.4 rpm from its course against a noise of 2 rpm per sample. Even a matched filter
/// that knew the instant and the shape of the deviation would reach a detectability d′ of only
/// 0.5–1.2 by the time the error is 2 bar (d′ = √Σδ²/σ over the 2^−10 s samples, δ the speed's
/// deviation from its straight-line course over the 40 ms before), so no estimator on these
/// sensors can follow the fall within 2 bar. With HC3.4 alone or HC3.1 + HC3.3 the fall is
/// slower (2 bar in 17–39 ms) and the speed has seen more of it (d′ 1.9–5.9, above every
/// HC3.1 + HC3.4 event's; with the accumulator's lift-off band holding the gas law's oil, one
/// HC3.1 + HC3.3 event in Config 1 is at 1.9): there the 2 bar is a matter of the detector. The
/// model on the two runs: P2 off by more than 2 bar without the transducer, the error covered by
/// its σ, the empty flag in time.
#[test]
fn where_the_hp_accumulator_runs_empty_the_motor_speed_sees_its_fall_too_late() {
    let bench = Bench::reference();
    let sigma = pto_host::validation::sensors::SensorSpec::default().motor_noise_rpm;
    let p0 = bench.hp_acc.precharge_pa / pto_host::sim::bench::BAR;
    let dt = 1.0 / 1024.0;
    // (fastest 2 bar fall in ms, smallest d′, largest d′) over a run's emptying events.
    let events = |name: &str| {
        let mut s = pto_host::sim::scenario::builtin_named(name).expect("built-in scenario");
        s.sample_interval_s = dt;
        let (_, res) = s
            .simulate(
                &bench,
                std::path::Path::new("."),
                pto_host::sim::solver::SolverOptions::default(),
                None,
            )
            .unwrap();
        let tr = &res.trace;
        // P2 (bar) and the motor speed (rpm) at each sample, as the validation reads the plant.
        let (p, w): (Vec<f64>, Vec<f64>) = tr
            .t_s
            .iter()
            .map(|&t| {
                let v = pto_host::sim::trace::truth_at(tr, t);
                (v.p2_bar, v.motor_rpm)
            })
            .unzip();
        let fit = 40;
        let (mut n, mut fastest, mut d_lo, mut d_hi) = (0, f64::MAX, f64::MAX, 0.0f64);
        let mut off = 0.0f64;
        let mut i = fit;
        while i + 1 < p.len() {
            if !(p[i] >= p0 && p[i + 1] < p0 && tr.t_s[i] > 0.5) {
                i += 1;
                continue;
            }
            // The first sample 2 bar below the level P2 left (within 0.3 s).
            let Some(j) = (i..p.len().min(i + 300)).find(|&j| p[j] <= p[i] - 2.0) else {
                i += 1;
                continue;
            };
            // The rotor's course: a least-squares line through the 40 ms before.
            let (xs, ys) = (&tr.t_s[i - fit..=i], &w[i - fit..=i]);
            let m = xs.len() as f64;
            let (mx, my) = (xs.iter().sum::<f64>() / m, ys.iter().sum::<f64>() / m);
            let b = xs
                .iter()
                .zip(ys)
                .map(|(x, y)| (x - mx) * (y - my))
                .sum::<f64>()
                / xs.iter().map(|x| (x - mx).powi(2)).sum::<f64>();
            let ss: f64 = (i + 1..=j)
                .map(|k| (w[k] - my - b * (tr.t_s[k] - mx)).powi(2))
                .sum();
            let d = ss.sqrt() / sigma;
            off = off.max((w[j] - my - b * (tr.t_s[j] - mx)).abs());
            n += 1;
            fastest = fastest.min((tr.t_s[j] - tr.t_s[i]) * 1e3);
            (d_lo, d_hi) = (d_lo.min(d), d_hi.max(d));
            i = j;
        }
        println!(
            "{name}: {n} emptyings, P2 2 bar down within {fastest:.1} ms at the fastest, \
             the speed ≤ {off:.2} rpm off its course and d′ {d_lo:.2}–{d_hi:.2} by then"
        );
        assert!(n >= 10, "{name}: the accumulator runs empty in every wave");
        (d_lo, d_hi)
    };
    // The model on these runs: without the transducer its P2 misses 2 bar where the
    // measurement says any estimator on these sensors must, and it says so: σ covers the error
    // and the empty flag follows the bench's accumulator (the targets `pto validate` judges
    // these runs by).
    for r in &validate_named(&["test1-cfg1-c14", "test1-cfg2-c14"]) {
        println!(
            "{}: model-only P2 max error {:.2} bar, within 2σ {:.2} %, within 3σ {:.2} %, \
             empty flag ≤ {:?} ms after the bench",
            r.scenario,
            r.p2_model_only_max_bar,
            100.0 * r.cover_2s_model_only,
            100.0 * r.cover_3s_model_only,
            r.empty_flag_delay_ms
        );
        assert!(r.p2_model_only_max_bar > target::P2_MODEL_ONLY_MAX_BAR);
        assert!(
            r.model_only_min_p2_bar < bench.hp_acc.precharge_pa / pto_host::sim::bench::BAR + 1.0
        );
        // The one miss allowed, reported by `pto validate` when it happens: in Config 1 the
        // fixed-point model and its f64 twin part at one instant of a model-only dive through
        // the precharge cell, where P2 falls ≈ 250 bar/s and trajectories a few LSBs apart
        // separate exponentially: 0.181 bar (target 0.2) with the stops as events, 0.216 with
        // the stop spring (0.8 of a 1 ms step apart in time). Every other target holds; a new
        // miss fails here.
        let known = |m: &String| r.scenario == "test1-cfg1-c14" && m.starts_with("fixed vs f64");
        let others: Vec<&String> = r.missed.iter().filter(|m| !known(m)).collect();
        assert!(others.is_empty(), "{}: missed {others:?}", r.scenario);
    }
    for cfg in [1, 2] {
        let (_, hi) = events(&format!("test1-cfg{cfg}-c14"));
        assert!(hi < 1.5, "HC3.1 + HC3.4, Config {cfg}: d′ up to {hi}");
        for cyl in ["c4", "c13"] {
            let (lo, _) = events(&format!("test1-cfg{cfg}-{cyl}"));
            // Every slower fall more detectable than the fastest runs' best, and ≥ 1.8.
            assert!(lo > hi && lo > 1.8, "{cyl}, Config {cfg}: d′ from {lo}");
        }
    }
}

#[test]
fn scheduler_holds_p2_and_motor_speed_in_closed_loop_with_the_full_simulation() {
    for row in pto_host::validation::closed_loop::closed_loop_rows(&Bench::reference()) {
        let row = row.unwrap();
        println!(
            "{}: max deviation {:.4} (target {})",
            row.name, row.max_deviation, row.target
        );
        assert!(row.pass, "{}", row.name);
    }
}

/// Fixed point vs f64 one step at a time: at every step of 20 s of nine runs (Test I with one
/// or two cylinders crossing the precharge every wave, Test II on the relief, the irregular sea,
/// the 71 bar discharge, a blocked input ending on the empty node, Test III at 25 %), with and
/// without the HP transducer, the f64 reference is set to the
/// fixed-point estimator's state exactly (`Reference::from_state`) and both take the same
/// inputs: P2 must agree to 2 LSB (2^−15 bar) after the step where the HP node is on its
/// accumulator (P2 at or above the precharge before and after the step). Below the precharge
/// the node is the lines' oil alone, 244× stiffer (14.8 against 0.061 bar per L at 25 bar): a
/// step there moves P2 by up to 0.6 bar (40 000 LSB) and the two arithmetics' roundings of the
/// flows, multiplied by that stiffness, part by more than 2 LSB (2.28 LSB on a 6 400 LSB step
/// of Test I since the accumulators hold the gas law's oil); there the bound is 2 LSB + 1e-4 of
/// the step. Over whole runs the two drift apart where the dynamics are unstable (the precharge
/// cell), which this isolates from the arithmetic's own error.
#[test]
fn fixed_point_and_f64_agree_to_two_lsb_from_an_identical_state() {
    use pto_host::sim::solver::SolverOptions;
    use pto_host::sim::trace::truth_at;
    use pto_host::validation::reference::Reference;
    use pto_host::validation::sensors::{SensorSpec, SensorSynth};
    use pto_host::validation::{commanded_aperture_pct, duty_mask, model_config};
    use pto_model::estimator::{self, State};
    use pto_model::fx::Pressure;
    let bench = Bench::reference();
    let mcfg = model_config(&bench).unwrap();
    let k = mcfg.coefficients().unwrap();
    let lsb = 1.0 / 65_536.0;
    let precharge = f64::from(mcfg.hp_accumulator.precharge_bar);
    let mut worst_all = 0.0f64;
    // Below the precharge: the worst error beyond 2 LSB as a share of the step.
    let mut worst_stiff = 0.0f64;
    for name in [
        "test1-cfg1-c14",
        "test1-cfg2-c4",
        "test1-cfg3-c14",
        "test1-cfg1-c1",
        "test2-cfg1-c1234",
        "irregular-sea",
        "exp-discharge-71",
        "blocked-ap25",
        "test3-ap25",
    ] {
        let mut s = pto_host::sim::scenario::builtin_named(name).unwrap();
        s.sample_interval_s = 1.0 / 128.0;
        s.duration_s = s.duration_s.min(120.0);
        let (prep, res) = s
            .simulate(
                &bench,
                std::path::Path::new("."),
                SolverOptions::default(),
                None,
            )
            .unwrap();
        let motion = prep.plant.motion();
        let duty = duty_mask(&prep.on_duty);
        let dt = 2f64.powi(-i32::from(mcfg.dt_log2));
        // Test II reaches the relief after ≈ 90 s: judge its last 20 s.
        let t_from = (s.duration_s - 20.0).max(0.0);
        for with_hp in [true, false] {
            let t0 = truth_at(&res.trace, t_from);
            let mut st = State::new(
                Pressure::from_num(t0.p2_bar as f32),
                Pressure::from_num(t0.lp_bar as f32),
                Pressure::from_num(1.0),
            );
            let mut synth = SensorSynth::new(SensorSpec::default(), 5);
            let (mut worst, mut worst_t, mut n) = (0.0f64, 0.0, 0usize);
            for i in 0..(20.0 / dt) as usize {
                let t = t_from + i as f64 * dt;
                let truth = truth_at(&res.trace, t);
                let ap = commanded_aperture_pct(&s, &res, t);
                let r = synth.read(motion.at(t).0, &truth);
                let mut inp = r.to_inputs(ap, duty, prep.config as u8);
                if !with_hp {
                    inp.hp = None;
                }
                let mut rf = Reference::from_state(&mcfg, &k, &st);
                let before = f64::from(st.node.p2.to_num::<f32>());
                let e = estimator::step(&k, &mut st, &inp);
                let r = rf.step(&inp);
                let after = f64::from(e.p2.to_f32());
                let d = (after - r.p2_bar).abs();
                if before >= precharge && after >= precharge {
                    if d > worst {
                        (worst, worst_t) = (d, t);
                    }
                } else {
                    let step = (after - before).abs().max(lsb);
                    worst_stiff = worst_stiff.max((d - 2.0 * lsb).max(0.0) / step);
                }
                n += 1;
            }
            println!(
                "{name:<18} {}: one-step |P2 fixed − f64| max {:.2} LSB at t = {worst_t:.3} s \
                 over {n} steps, P2 on the accumulator (allowed 2)",
                if with_hp { "with HP   " } else { "model only" },
                worst / lsb
            );
            worst_all = worst_all.max(worst);
        }
    }
    println!(
        "below the precharge: the error beyond 2 LSB is at most {worst_stiff:.1e} of the step \
         (allowed 1e-4)"
    );
    assert!(worst_all <= 2.0 * lsb, "{:.2} LSB", worst_all / lsb);
    assert!(worst_stiff <= 1e-4, "{worst_stiff:e} of the step");
}

/// Sensors failing at plausible values, in closed loop with the firmware's own controller on
/// the full simulation (`model::faults`): every case of the table, from four onsets across the
/// HP check's window, is flagged within its bound (5 s; a drift within the time it takes to
/// drift 5 bar, plus 5 s; a motor reading stuck where the speed was within 5 s of the speed
/// leaving it, or never if it never left), the right sensor named, and the controller in its
/// safe state from then on; the fault-free loops hold no sensor faulted.
#[test]
fn sensors_failing_at_plausible_values_are_caught_named_and_made_safe() {
    use pto_host::validation::faults::{self, Detection};
    use rayon::prelude::*;
    let bench = Bench::reference();
    // Each case from four onsets across the HP check's 4 s window (20 s starts one).
    let runs: Vec<faults::Case> = faults::cases()
        .into_iter()
        .flat_map(|c| {
            [0.0, 1.0, 2.5, 3.9].map(|dt| {
                let mut c = c;
                c.fault.from_s += dt;
                c
            })
        })
        .collect();
    let rows: Vec<Detection> = faults::detect_all(&bench, &runs, 11).unwrap();
    println!(
        "{:<48} {:>6} {:>9} {:>9} {:<8} {:>9} {:>15} {:>7} safe",
        "case", "from", "after s", "bound s", "held", "P2 then", "P2 after", "silent"
    );
    for d in &rows {
        println!(
            "{:<48} {:>6.1} {:>9} {:>9.1} {:<8} {:>9} {:>6.1}–{:<6.1} {:>7.1} {}",
            d.case.name,
            d.case.fault.from_s,
            d.after_s.map_or("never".into(), |t| format!("{t:.2}")),
            d.bound_s,
            d.held.join(","),
            d.p2_at_detection_bar
                .map_or("-".into(), |p| format!("{p:.1}")),
            d.p2_after_bar.0,
            d.p2_after_bar.1,
            d.p2_silent_bar,
            d.safe_after
        );
    }
    let failed: Vec<String> = rows
        .iter()
        .filter(|d| !d.pass)
        .map(|d| format!("{} from {} s", d.case.name, d.case.fault.from_s))
        .collect();
    assert!(failed.is_empty(), "missed: {failed:?}");
    let fa: Vec<usize> = faults::fault_free_loops()
        .par_iter()
        .map(|(m, p0)| faults::false_alarms(&bench, *m, *p0, 12).unwrap())
        .collect();
    println!("false alarms in the fault-free loops (steps): {fa:?}");
    assert!(fa.iter().all(|&n| n == 0), "{fa:?}");
}
