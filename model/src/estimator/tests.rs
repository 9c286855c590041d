//! The estimator's unit and property tests.

use super::*;
use proptest::prelude::*;

/// Increments below the Q16.16 LSB add up: 10 000 steps of 0.3 LSB each (a node at
/// 2 L/min whose change per step is 0.3 · 2^−16 bar) land within one LSB of the exact sum,
/// where rounding each step would have lost all of it.
#[test]
fn node_keeps_sub_lsb_increments() {
    let dtl = 10;
    let q = Fx::from_num(2.0);
    // dP/dV such that q · dP/dV · 2^−10 s = 0.3 · 2^−16 bar.
    let dp_per_flow = Fx::from_num(0.3 * 1024.0 / 65_536.0 / 2.0);
    let (mut p, mut lo) = (Fx::from_num(100.0), 0u16);
    for _ in 0..10_000 {
        node_step(&mut p, &mut lo, q, dp_per_flow, dtl);
    }
    let exact = 100.0 + 10_000.0 * q.to_num::<f64>() * dp_per_flow.to_num::<f64>() / 1024.0;
    let err_lsb = (p.to_num::<f64>() - exact).abs() * 65_536.0;
    println!("after 10 000 sub-LSB steps: {err_lsb:.3} LSB from the exact sum");
    assert!(err_lsb < 1.0);
}

/// The rotor's inertia: at full aperture (the valve's share of the pressure is ≈ 1 %) the
/// valve/motor flow rises toward its steady value with the rotor's time constant J/c (rad/s
/// units: 0.01 kg·m² / (0.00784 N·m/rpm × 60/2π) = 0.134 s on the reference bench), and a
/// closing valve stops it within the step (the gain is held to 1: no overshoot).
#[test]
fn motor_flow_lags_by_the_rotor_time_constant_and_stops_with_the_valve() {
    let cfg = crate::ModelConfig::reference();
    let k = cfg.coefficients().unwrap();
    let dt = 1.0 / f64::from(1u32 << k.dt_log2);
    // Just above the precharge the accumulator holds P2 (≈ 0.1 bar over the rise).
    let mut s = State::new(
        Pressure::from_num(30.0),
        Pressure::from_num(8.0),
        Pressure::ZERO,
    );
    s.branch.aperture = Fx::from_num(100);
    s.branch.started = true;
    let inp = Inputs {
        aperture_cmd: Aperture::from_num(100.0),
        ..Inputs::default()
    };
    let q_ss = f64::from(
        k.branch
            .valve_flow
            .at(s.branch.aperture, s.node.p2 - s.node.lp)
            .to_num::<f32>(),
    );
    let mut steps = 0u32;
    while f64::from(s.branch.q_motor.to_num::<f32>()) < (1.0 - (-1f64).exp()) * q_ss {
        step(&k, &mut s, &inp);
        steps += 1;
        assert!(steps < 10_000);
    }
    let tau = f64::from(steps) * dt;
    let c_rad = f64::from(cfg.load_nm_per_rpm) * 60.0 / (2.0 * core::f64::consts::PI);
    let tau_rotor = f64::from(cfg.motor_inertia_kg_m2) / c_rad;
    println!("flow reaches 63 % of {q_ss:.3} L/min after {tau:.4} s; rotor J/c = {tau_rotor:.4} s");
    assert!((tau / tau_rotor - 1.0).abs() < 0.05, "{tau} vs {tau_rotor}");
    // Close the valve at once (no spool lag in this state): the flow stops in one step.
    s.branch.aperture = ZERO;
    let inp = Inputs {
        aperture_cmd: Aperture::ZERO,
        ..Inputs::default()
    };
    let e = step(&k, &mut s, &inp);
    assert_eq!(s.branch.q_motor, ZERO);
    assert_eq!(e.motor_rpm.0, ZERO);
}

/// The shaft tracker reads a shaft that is already turning when it starts (a Test I start:
/// 0.26 rad/s, 16 384 counts per revolution) from its first readings: with the
/// expanding-memory start-up gains its speed is within 3 % of the shaft's from 16 ms on
/// (1.2 %), where the fading-memory gains alone start from 0 and are still 82 % short at
/// 16 ms. After a 0.1 s encoder drop-out (the shaft turned on meanwhile) the tracker starts
/// again the same way.
#[test]
fn shaft_tracker_reads_a_turning_shaft_from_its_first_readings() {
    let cfg = crate::ModelConfig::reference();
    let k = cfg.coefficients().unwrap();
    let dt = 1.0 / f64::from(1u32 << k.dt_log2);
    let w = 0.2618;
    let settle = (0.016 / dt) as usize;
    // Largest relative speed error over 0.5 s from `settle` steps after the tracker
    // (re)starts at step `from`, the encoder missing for the 100 steps before `from` if
    // `from` > 0 (a drop-out: the shaft turns on and the readings resume).
    let run = |k: &Coefficients, from: usize| {
        let mut s = State::new(
            Pressure::from_num(25.0),
            Pressure::from_num(8.0),
            Pressure::from_num(1.0),
        );
        let mut worst = 0.0f64;
        for i in 0..from + 512 {
            let theta = 0.05 + w * i as f64 * dt;
            let mut inp = held_inputs(&cfg, theta, Pressure(s.node.p2), Pressure(s.node.lp), 0, 0);
            if i < from && i + 100 >= from {
                inp.encoder = None;
            }
            let e = step(k, &mut s, &inp);
            if i >= from + settle {
                worst = worst.max((f64::from(e.omega.0.to_num::<f32>()) / w - 1.0).abs());
            }
        }
        worst
    };
    let mut fading = k.clone();
    fading.tracker.tracker_startup_len = 0;
    let (with, without) = (run(&k, 0), run(&fading, 0));
    let after_dropout = run(&k, 400);
    println!(
        "speed error from {:.0} ms on: start-up gains {:.2} % ({} steps), fading-memory \
         gains alone {:.1} %; after a 0.1 s drop-out {:.2} %",
        settle as f64 * dt * 1e3,
        with * 100.0,
        k.tracker.tracker_startup_len,
        without * 100.0,
        after_dropout * 100.0
    );
    assert_eq!(k.tracker.tracker_startup_len, 53);
    assert!(with < 0.03, "{with}");
    assert!(after_dropout < 0.03, "{after_dropout}");
    assert!(without > 0.2, "{without}");
}

/// A step's readings with the lever at `theta` (rad, as the encoder counts it) and both
/// transducers reading `p2` and `lp`; valve at 10 %, no motor-speed reading.
fn held_inputs(
    cfg: &crate::ModelConfig,
    theta: f64,
    p2: Pressure,
    lp: Pressure,
    on_duty: u8,
    config: u8,
) -> Inputs {
    let count = theta / (2.0 * core::f64::consts::PI) * f64::from(cfg.encoder_counts_per_rev);
    Inputs {
        encoder: Some(count.round() as i32),
        hp: Some(p2),
        lp: Some(lp),
        motor: None,
        aperture_cmd: Aperture::from_num(10.0),
        on_duty,
        config,
    }
}

/// Runs `steps` steps without the HP reading: shaft still, no cylinder on duty, the valve
/// held at `aperture` %, the motor sensor reading `rpm` (or missing), from P2 = `p2` bar.
fn run_without_hp(k: &Coefficients, p2: f32, aperture: f32, rpm: Option<f32>, steps: usize) -> Fx {
    let lp = Pressure::from_num(8.0);
    let mut s = State::new(Pressure::from_num(p2), lp, Pressure::from_num(0.0));
    let inp = Inputs {
        hp: None,
        motor: rpm.map(Rpm::from_num),
        aperture_cmd: Aperture::from_num(aperture),
        ..held_inputs(&crate::ModelConfig::reference(), 0.0, lp, lp, 0, 0)
    };
    for _ in 0..steps {
        step(k, &mut s, &inp);
    }
    s.node.p2
}

/// Without the HP reading, the motor speed of a rotor held steady by P2 = 40 bar (LP 8, the
/// valve fully open) pulls a P2 estimate started 5 bar low to 40 bar less the reading's
/// band (2 % of ΔP) within a quarter of a second; the model alone stays 5 bar off. Near the
/// closed valve, and with the motor below its minimum speed, the reading is not used: P2
/// is bit for bit the model's own.
#[test]
fn motor_speed_reads_p2_without_the_hp_transducer() {
    let cfg = crate::ModelConfig::reference();
    let k = cfg.coefficients().unwrap();
    let (p_true, lp) = (40.0f32, 8.0f32);
    let q = k
        .branch
        .valve_flow
        .at(Fx::from_num(100.0), Fx::from_num(p_true - lp))
        .to_num::<f32>();
    let rpm = q * cfg.rpm_per_lpm();
    let steps = 256; // 0.25 s: ten time constants of 25 ms
    let with = run_without_hp(&k, p_true - 5.0, 100.0, Some(rpm), steps).to_num::<f32>();
    let alone = run_without_hp(&k, p_true - 5.0, 100.0, None, steps).to_num::<f32>();
    let band = 0.02 * (p_true - lp);
    let expect = p_true - band;
    std::println!(
        "steady rotor at {rpm:.1} rpm ({q:.3} L/min) for P2 = {p_true} bar: from {} bar, P2 \
         {with:.3} bar with the motor reading (expected {expect:.2} within 0.05), {alone:.3} \
         bar from the model alone",
        p_true - 5.0
    );
    assert!((with - expect).abs() < 0.05, "{with} vs {expect}");
    assert!(p_true - alone > 4.5, "{alone}");
    // Started at the right pressure, the reading keeps it there (inside its band).
    let held = run_without_hp(&k, p_true, 100.0, Some(rpm), steps).to_num::<f32>();
    assert!((held - p_true).abs() <= band + 0.1, "{held}");
    // Guards: valve near closed (dF/dQ above the limit), motor below its minimum speed.
    for (aperture, rpm) in [(1.0, rpm), (100.0, 0.5 * cfg.motor_reading_min_rpm)] {
        let a = run_without_hp(&k, p_true - 5.0, aperture, Some(rpm), steps);
        let b = run_without_hp(&k, p_true - 5.0, aperture, None, steps);
        assert_eq!(a, b, "aperture {aperture} %, {rpm} rpm");
    }
}

/// Behind a closed valve (commanded 0 %) a motor sensor reading 50 or 200 rpm moves P2 by
/// nothing — bit for bit the model alone — and is flagged as a contradiction once a real
/// rotor would have spun down (five of its time constants J/c, 0.67 s), not before. With the
/// valve open, a reading that implies a P2 above the relief is refused and flagged.
#[test]
fn contradicting_motor_readings_are_flagged_not_followed() {
    let cfg = crate::ModelConfig::reference();
    let k = cfg.coefficients().unwrap();
    let lp = Pressure::from_num(8.0);
    let run = |aperture: f32, rpm: Option<f32>, steps: usize| {
        let mut s = State::new(Pressure::from_num(50.0), lp, Pressure::from_num(1.0));
        let inp = Inputs {
            hp: None,
            motor: rpm.map(Rpm::from_num),
            aperture_cmd: Aperture::from_num(aperture),
            ..held_inputs(&cfg, 0.0, lp, lp, 0, 0)
        };
        let mut first = None;
        for i in 0..steps {
            if step(&k, &mut s, &inp).faults & fault::MOTOR_IMPLAUSIBLE != 0 {
                first = first.or(Some(i));
            }
        }
        (s.node.p2, first)
    };
    let steps = 3 << k.dt_log2;
    let (alone, none) = run(0.0, None, steps);
    assert_eq!(none, None);
    for rpm in [50.0, 200.0] {
        let (p2, first) = run(0.0, Some(rpm), steps);
        std::println!(
            "{rpm} rpm behind a closed valve: P2 {} bar after 3 s (model alone {}), flagged \
             from step {first:?} (spin-down {} steps)",
            p2.to_num::<f32>(),
            alone.to_num::<f32>(),
            k.branch.spin_down_steps
        );
        assert_eq!(p2, alone, "P2 followed the reading");
        assert_eq!(first, Some(usize::from(k.branch.spin_down_steps) - 1));
    }
    // The valve fully open, the motor reading the flow of ΔP = 160 bar: above the relief.
    let q = k
        .branch
        .valve_flow
        .at(Fx::from_num(100.0), Fx::from_num(160.0));
    let rpm = q.to_num::<f32>() * cfg.rpm_per_lpm();
    let (p2, first) = run(100.0, Some(rpm), steps);
    let (p2_alone, _) = run(100.0, None, steps);
    std::println!(
        "{rpm:.0} rpm at 100 % (ΔP 160 bar): flagged from step {first:?}, P2 {} bar (model \
         alone {})",
        p2.to_num::<f32>(),
        p2_alone.to_num::<f32>()
    );
    assert!(first.is_some(), "an impossible reading was taken");
    assert!(
        (p2.to_num::<f32>() - p2_alone.to_num::<f32>()).abs() < 0.01,
        "{p2} vs {p2_alone}"
    );
}

/// Without the HP transducer, P2's σ is at least `precharge_sigma_bar` once the estimate
/// is within `precharge_band_bar` of the precharge or below it (the accumulator may run
/// empty at any moment, or has), and grows freely above; the empty flag stands below the
/// precharge plus `hp_empty_margin_bar`.
#[test]
fn model_only_sigma_is_wide_where_the_accumulator_empties() {
    let cfg = crate::ModelConfig::reference();
    let k = cfg.coefficients().unwrap();
    let lp = Pressure::from_num(8.0);
    for (p2, want_floor, empty) in [
        (20.0, true, true),
        (25.05, true, true),
        (25.5, true, false),
        (27.0, false, false),
        (100.0, false, false),
    ] {
        let mut s = State::new(Pressure::from_num(p2), lp, Pressure::from_num(0.1));
        let inp = Inputs {
            hp: None,
            ..held_inputs(&cfg, 0.0, lp, lp, 0, 0)
        };
        let e = step(&k, &mut s, &inp);
        let sigma = e.p2_sigma().to_f32();
        std::println!(
            "P2 {p2} bar without HP: σ {sigma:.3} bar, empty {}",
            e.hp_empty
        );
        assert_eq!(sigma >= cfg.precharge_sigma_bar - 0.01, want_floor, "{p2}");
        assert_eq!(e.hp_empty, empty, "{p2}");
    }
}

/// The Kalman variance follows its f64 recursion var ← (var + q)·(1 − g(var)) (the same
/// tables, interpolated in f64) over 4 s of HP readings at 100 bar from σ = 1 bar: within
/// 10^−4 all the way down, its bits below the LSB counted (the gain is looked up with them,
/// `ObserverCoeffs::gain_q32`; read at the Q16.16 value, near the steady ≈ 130 LSBs, one LSB
/// was 0.8 %). Floored to its Q16.16 LSB, the shrink lost up to 1 LSB a step on the way
/// down and the variance ran up to 17 % below the f64 one (in `pto validate`, after each
/// crossing of the precharge, 20 %: P2 up to 0.15 bar away from the f64 model). The process
/// noise q is at its floor of one LSB per step here.
#[test]
fn kalman_variance_keeps_its_sub_lsb_bits() {
    let cfg = crate::ModelConfig::reference();
    let k = cfg.coefficients().unwrap();
    let r = k.observer.r.to_num::<f64>();
    let (p2, lp) = (Pressure::from_num(100.0), Pressure::from_num(8.0));
    let mut s = State::new(p2, lp, Pressure::from_num(1.0));
    let inp = held_inputs(&cfg, 0.0, p2, lp, 0, 0);
    let mut var = 1.0f64;
    let mut worst = 0.0f64;
    // The variance with its bits below the LSB (the step's gain reads them too).
    let fixed = |s: &State| s.node.var.to_num::<f64>() + f64::from(s.node.var_lo) / 4_294_967_296.0;
    for _ in 0..4 << k.dt_log2 {
        step(&k, &mut s, &inp);
        var += k.observer.q_step.at_ext(s.node.p2) as f64 / 4_294_967_296.0;
        let g = if var < r {
            k.observer.gain_fine.at_f64(var)
        } else {
            k.observer.gain_coarse.at_f64(var).clamp(0.0, 1.0)
        };
        var *= 1.0 - g;
        worst = worst.max((fixed(&s) / var - 1.0).abs());
    }
    let last = (fixed(&s) / var - 1.0).abs();
    std::println!(
        "P2 100 bar: variance after 4 s {:.6} bar² (f64 {var:.6}: {:.4} % apart, allowed \
         0.01 %), {:.4} % apart at worst on the way (allowed 0.01 %)",
        fixed(&s),
        100.0 * last,
        100.0 * worst
    );
    assert!(last < 1e-4, "{last}");
    assert!(worst < 1e-4, "{worst}");
}

/// Mid-stroke (the shaft at full speed), every cylinder on duty has one chamber at
/// P2 + drop delivering and the other at LP − drop sucking, in both directions, every
/// geometry and around several lever positions: the rod's travel counts on until the old
/// chamber reaches LP, also where (the rod off centre) that chamber is the longer one and
/// needs more travel than the new one does to reach P2. (The travel used to stop at
/// delivery, and such an old chamber stayed above LP for the rest of the stroke, passing no
/// flow.)
#[test]
fn both_chambers_reach_their_check_valves_by_mid_stroke() {
    let cfg = crate::ModelConfig::reference();
    let k = cfg.coefficients().unwrap();
    let n = 1u32 << k.dt_log2;
    let (p2, lp) = (Pressure::from_num(100.0), Pressure::from_num(8.0));
    let (mut worst, mut checked) = (0.0f32, 0);
    // ±8° at 0.1 Hz around three lever positions, P2 held at 100 bar by its transducer.
    let (amp, f) = (8f64.to_radians(), 0.1);
    for offset_deg in [-15.0f64, 0.0, 15.0] {
        for config in 0..4u8 {
            let mut s = State::new(p2, lp, Pressure::ZERO);
            // Two periods; the shaft at full speed at t = j/(2f): 10 s and 15 s are
            // mid-stroke after a reversal each way.
            for i in 0..=(15 * n) {
                let t = f64::from(i) / f64::from(n);
                let theta =
                    offset_deg.to_radians() + amp * (2.0 * core::f64::consts::PI * f * t).sin();
                let inp = held_inputs(&cfg, theta, p2, lp, 0b1111, config);
                let e = step(&k, &mut s, &inp);
                if i == 10 * n || i == 15 * n {
                    let (lo, hi) = (
                        e.lp.0 - k.pump.check_drop_bar,
                        e.p2.0 + k.pump.check_drop_bar,
                    );
                    for cs in &s.cyl {
                        let (p_hi, p_lo) = if cs.p_cap > cs.p_rod {
                            (cs.p_cap, cs.p_rod)
                        } else {
                            (cs.p_rod, cs.p_cap)
                        };
                        worst = worst
                            .max((p_hi - hi).abs().to_num())
                            .max((p_lo - lo).abs().to_num());
                        checked += 1;
                    }
                }
            }
        }
    }
    println!("{checked} chamber pairs mid-stroke: worst {worst:.4} bar from P2 + drop / LP − drop");
    assert_eq!(checked, 96);
    assert!(worst < 0.01, "{worst}");
}

/// The play the eye crosses after a reversal follows the sign of the chambers' net force on
/// the rod when the lever turns, computed here in f64 from the bores and rods: every
/// cylinder, both directions, chamber pressures over LP − drop … P2 + drop; inside the band a
/// quarter of the play after a stroke that delivered (the rod floated), all of it after one
/// that had not.
#[test]
fn the_play_to_cross_follows_the_rods_net_force_at_the_reversal() {
    let cfg = crate::ModelConfig::reference();
    let k = cfg.coefficients().unwrap();
    let (lo, hi) = (7.5f64, 30.5f64);
    let play: f64 = k.pump.play_mm.to_num();
    let band: f64 = FLOAT_BAND.to_num();
    let mut count = [0u32; 3]; // none, within the band, all of it
    let mut worst = 0.0f64;
    for (c, cc) in k.pump.cyl.iter().zip(cfg.cylinders.iter()) {
        let a_cap = core::f64::consts::PI / 4.0 * f64::from(cc.bore_mm).powi(2);
        let a_ann = a_cap - core::f64::consts::PI / 4.0 * f64::from(cc.rod_mm).powi(2);
        for (dir, delivered) in [(1i8, true), (-1, true), (1, false), (-1, false)] {
            let float = if delivered { 0.25 * play } else { play };
            for i in 0..=62 {
                for j in 0..=62 {
                    let (p_cap, p_rod) = (lo + 0.37 * f64::from(i), lo + 0.37 * f64::from(j));
                    // The force pushing the rod the new way, per unit area of the old
                    // chamber (the one that delivered on the last stroke).
                    let (assist, a_old) = if dir > 0 {
                        (p_cap * a_cap - p_rod * a_ann, a_cap)
                    } else {
                        (p_rod * a_ann - p_cap * a_cap, a_ann)
                    };
                    let net = assist / a_old;
                    let cs = CylState {
                        dir,
                        delivered,
                        p_cap: Fx::from_num(p_cap),
                        p_rod: Fx::from_num(p_rod),
                        ..CylState::default()
                    };
                    let got: f64 =
                        play_to_cross(&k.pump, c, &cs, Fx::from_num(lo), Fx::from_num(hi)).to_num();
                    let ramp: f64 = FLOAT_RAMP.to_num();
                    let (expected, class) = if net <= -band {
                        (0.0, 0)
                    } else if net >= band {
                        (play, 2)
                    } else if net < ramp - band {
                        (float * (net + band) / ramp, 1)
                    } else if net > band - ramp {
                        (float + (play - float) * (net - (band - ramp)) / ramp, 1)
                    } else {
                        (float, 1)
                    };
                    // Q16.16 area ratio (±7.6e-6 relative) times ≤ 30 bar: the net force
                    // is off by ≤ 2.3e-4 bar, the play on the steeper ramp by
                    // ≤ 0.75·play/ramp × that = 0.0028·play.
                    let err = (got - expected).abs();
                    worst = worst.max(err);
                    assert!(
                        err <= 0.003 * play,
                        "p_cap {p_cap}, p_rod {p_rod}, dir {dir}: {got} vs {expected}"
                    );
                    count[class] += 1;
                }
            }
        }
    }
    println!("worst play error {worst:.5} mm of {play} mm");
    println!(
        "reversals: {} with no play to cross, {} floating (within the band), {} the whole play",
        count[0], count[1], count[2]
    );
    assert!(count.iter().all(|&n| n > 100), "{count:?}");
}

/// Seal friction: every rod on duty adds c·d²·θ̇ to the restraining torque (a force c·v
/// against its speed v = d·θ̇ on the arm d); an idle rod, bypassed and pushed out by LP,
/// adds none. Two estimators, with and without friction, on the same readings, mid-stroke
/// in every geometry.
#[test]
fn seal_friction_adds_c_d2_omega_per_rod_on_duty() {
    let cfg = crate::ModelConfig::reference();
    let k = cfg.coefficients().unwrap();
    let k0 = crate::ModelConfig {
        seal_friction_n_s_per_m: 0.0,
        ..cfg
    }
    .coefficients()
    .unwrap();
    let n = 1u32 << k.dt_log2;
    let (p2, lp) = (Pressure::from_num(60.0), Pressure::from_num(8.0));
    let c = f64::from(cfg.seal_friction_n_s_per_m) * 1e-6; // kN per mm/s
    let (mut worst, mut checked) = (0.0f64, 0);
    for config in 0..4u8 {
        let (mut s, mut s0) = (
            State::new(p2, lp, Pressure::ZERO),
            State::new(p2, lp, Pressure::ZERO),
        );
        for i in 0..=(10 * n) {
            let t = f64::from(i) / f64::from(n);
            let theta = 20f64.to_radians() * (2.0 * core::f64::consts::PI * 0.1 * t).sin();
            let inp = held_inputs(&cfg, theta, p2, lp, 0b0101, config);
            let (e, e0) = (step(&k, &mut s, &inp), step(&k0, &mut s0, &inp));
            if i == 5 * n || i == 10 * n {
                let omega: f64 = e.omega.0.to_num();
                for (j, cyl) in k.pump.cyl.iter().enumerate() {
                    let sth = if cyl.side < ZERO {
                        -e.theta.0
                    } else {
                        e.theta.0
                    };
                    let d: f64 = k.pump.arm[usize::from(config)].at(sth).to_num();
                    let expected = if inp.on_duty & (1 << j) != 0 {
                        c * d * d * omega
                    } else {
                        0.0
                    };
                    let got: f64 = (e.torque_cyl[j].0 - e0.torque_cyl[j].0).to_num();
                    worst = worst.max((got - expected).abs() / (c * d * d * omega).abs());
                    checked += 1;
                }
            }
        }
    }
    println!(
        "{checked} rods mid-stroke: seal torque within {:.3} % of c·d²·θ̇",
        100.0 * worst
    );
    assert_eq!(checked, 32);
    assert!(worst < 0.01, "{worst}");
}

proptest! {
    /// A relaxation never overshoots its target (the fraction bits may carry it less than
    /// one LSB past it), for any flows and gains in range.
    #[test]
    fn relaxation_never_overshoots(
        x in 0i32..(1000 << 16), lo in any::<u16>(), t in 0i32..(1000 << 16),
        g in 0i32..=65_536,
    ) {
        let (mut xx, mut ll) = (Fx::from_bits(x), lo);
        relax(&mut xx, &mut ll, Fx::from_bits(g), Fx::from_bits(t));
        let (a, b) = (x.min(t), x.max(t));
        prop_assert!(xx.to_bits() >= a && xx.to_bits() <= b, "{} not in [{a}, {b}]", xx.to_bits());
    }

    /// An observer correction lands between the estimate and the reading (the fraction
    /// bits may carry it less than one LSB past the reading) and inside the pressure range,
    /// for readings outside it too.
    #[test]
    fn correction_stays_between_estimate_and_reading(
        p in -65_536i32..(400 << 16), lo in any::<u16>(), z in (-10i32 << 16)..(500 << 16),
        g in 0i32..=65_536,
    ) {
        let (mut pp, mut ll) = (Fx::from_bits(p), lo);
        correct(&mut pp, &mut ll, Fx::from_bits(g), Fx::from_bits(z));
        let zc = z.clamp(P_MIN.to_bits(), P_MAX.to_bits());
        let (a, b) = (p.min(zc), p.max(zc));
        prop_assert!(pp.to_bits() >= a && pp.to_bits() <= b, "{} not in [{a}, {b}]", pp.to_bits());
    }

    /// A node step never leaves the physical pressure range, for any flow and dP/dV.
    #[test]
    fn node_step_stays_in_range(
        p in -65_536i32..(400 << 16), lo in any::<u16>(), q in any::<i32>(),
        dpdv in 0i32..i32::MAX, dtl in 6u8..=12,
    ) {
        let (mut pp, mut ll) = (Fx::from_bits(p), lo);
        node_step(&mut pp, &mut ll, Fx::from_bits(q), Fx::from_bits(dpdv), dtl);
        prop_assert!(pp >= P_MIN && pp <= P_MAX);
    }
}

#[test]
fn hydraulic_power_is_p2_times_valve_flow_in_watts() {
    // 1 bar · 1 L/min = 5/3 W; each Q16.16 product rounds by ≤ 1 LSB and the constant is 3.1e-6
    // high.
    let mut worst = 0.0f64;
    for p2 in [0.0f32, 8.0, 60.0, 100.0, 129.5, 130.0, 400.0] {
        for q in [0.0f32, 0.01, 1.53, 2.61, 7.9, 11.0] {
            let (p2, q) = (Fx::from_num(p2), Fx::from_num(q));
            let w = hydraulic_power(p2, q).0.to_num::<f64>();
            // Against the product of the Q16.16 inputs (their own rounding is the caller's).
            let want = (p2.to_num::<f64>() * q.to_num::<f64>() * 5.0 / 3.0).min(32_767.999);
            // In LSB beyond the constant's 3.1e-6.
            let lsb = 2f64.powi(-16);
            worst = worst.max(((w - want).abs() - 3.1e-6 * want).max(0.0) / lsb);
        }
    }
    println!("hydraulic power: worst error {worst:.2} LSB beyond the constant's 3.1e-6");
    assert!(worst <= 2.0, "{worst}");
    // Saturation and the floor.
    let max = hydraulic_power(Fx::from_num(400), Fx::from_num(1000));
    assert_eq!(max.0, Fx::MAX);
    assert_eq!(hydraulic_power(Fx::from_num(-0.5), Fx::from_num(2)).0, ZERO);
    assert_eq!(hydraulic_power(Fx::from_num(100), Fx::from_num(-1)).0, ZERO);
}
