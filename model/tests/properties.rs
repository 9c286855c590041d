//! Invariants of the fixed-point model over the documented input ranges.

use proptest::prelude::*;
use pto_model::estimator::{self, Inputs, State};
use pto_model::fx::{Aperture, Fx, Pressure, Rpm};
use pto_model::scheduler::{self, Mode, SchedulerConfig, SchedulerState, aperture_for_flow};
use pto_model::{Coefficients, ModelConfig};
use std::sync::OnceLock;

fn coeffs() -> &'static Coefficients {
    static C: OnceLock<Coefficients> = OnceLock::new();
    C.get_or_init(|| ModelConfig::reference().coefficients().unwrap())
}

fn opt<T: std::fmt::Debug + Clone>(
    s: impl Strategy<Value = T>,
) -> impl Strategy<Value = Option<T>> {
    prop_oneof![1 => Just(None), 4 => s.prop_map(Some)]
}

prop_compose! {
    fn inputs()(encoder in opt(prop_oneof![4 => -100_000i32..100_000, 1 => any::<i32>()]),
                hp in opt(-50.0f32..500.0), lp in opt(-50.0f32..200.0), motor in opt(-100.0f32..20_000.0),
                ap in -20.0f32..150.0, on_duty in 0u8..=255, config in 0u8..6) -> Inputs {
        Inputs {
            encoder,
            hp: hp.map(Pressure::from_num),
            lp: lp.map(Pressure::from_num),
            motor: motor.map(Rpm::from_num),
            aperture_cmd: Aperture::from_num(ap),
            on_duty,
            config,
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Any sequence of readings, in range or not (the encoder's drop-outs restart the shaft
    /// tracker's start-up), from any phase of the tracker, never panics (overflow checks are
    /// on) and keeps the state inside its physical limits.
    #[test]
    fn estimator_and_scheduler_never_panic(seq in prop::collection::vec(inputs(), 1..300),
                                           p0 in 0.0f32..140.0, mode_sel in 0u8..4, set in 0.0f32..150.0,
                                           enc_phase in any::<u8>()) {
        let k = coeffs();
        let sc = SchedulerConfig::default().coefficients(k).unwrap();
        let mut s = State::new(Pressure::from_num(p0), Pressure::from_num(8.0), Pressure::from_num(1.0));
        // Any phase of the shaft tracker, even one it never takes (past its start-up length).
        s.tracker.phase = enc_phase;
        let mut st = SchedulerState::default();
        let mode = match mode_sel {
            0 => Mode::Fixed(Aperture::from_num(set.min(100.0))),
            1 => Mode::HoldPressure(Pressure::from_num(set)),
            2 => Mode::HoldSpeed(Rpm::from_num(set * 3.0)),
            _ => Mode::MaxAutonomy(Rpm::from_num(set)),
        };
        for inp in &seq {
            let e = estimator::step(k, &mut s, inp);
            prop_assert!(e.p2.to_f32() >= -1.0 && e.p2.to_f32() <= 400.0);
            prop_assert!(e.p2_var.to_f32() >= 0.0);
            let c = scheduler::step(k, &sc, &mut st, mode, &e, inp.motor);
            prop_assert!((0.0..=100.0).contains(&c.aperture.to_f32()));
        }
    }

    /// Without the HP reading, with the spool held (so the motor-speed reading runs every step),
    /// any motor speed in the sensor's range and any lever motion never panic and keep P2
    /// inside its physical limits.
    #[test]
    fn motor_reading_never_panics(motor in prop::collection::vec(0.0f32..3000.0, 1..400),
                                  enc_step in -200i32..200, ap in 0.0f32..100.0,
                                  p0 in 0.0f32..140.0, lp in 0.0f32..30.0, on_duty in 0u8..16) {
        let k = coeffs();
        let mut s = State::new(Pressure::from_num(p0), Pressure::from_num(lp), Pressure::from_num(1.0));
        for (i, m) in motor.iter().enumerate() {
            let inp = Inputs {
                encoder: Some(enc_step.saturating_mul(i as i32)),
                hp: None,
                lp: Some(Pressure::from_num(lp)),
                motor: Some(Rpm::from_num(*m)),
                aperture_cmd: Aperture::from_num(ap),
                on_duty,
                config: 0,
            };
            let e = estimator::step(k, &mut s, &inp);
            prop_assert!(e.p2.to_f32() >= -1.0 && e.p2.to_f32() <= 400.0);
        }
    }

    /// Valve flow grows with aperture and with pressure difference.
    #[test]
    fn valve_table_is_monotone(a in 0.0f32..99.0, da in 0.01f32..20.0, dp in 0.0f32..150.0, ddp in 0.01f32..20.0) {
        let k = coeffs();
        let f = |a: f32, dp: f32| k.branch.valve_flow.at(Fx::from_num(a), Fx::from_num(dp));
        prop_assert!(f((a + da).min(100.0), dp) >= f(a, dp));
        prop_assert!(f(a, dp + ddp) >= f(a, dp));
    }

    /// The inverse valve table round-trips: flow(aperture_for_flow(q)) = q.
    #[test]
    fn inverse_valve_table_round_trips(a in 2.0f32..100.0, dp in 20.0f32..150.0) {
        let k = coeffs();
        let (a, dp) = (Fx::from_num(a), Fx::from_num(dp));
        let q = k.branch.valve_flow.at(a, dp);
        let back = aperture_for_flow(k, q, dp);
        let q_back = k.branch.valve_flow.at(back, dp);
        prop_assert!((q_back - q).abs() < Fx::from_num(0.002), "q {} back {}", q, q_back);
        prop_assert!((back - a).abs() < Fx::from_num(0.05));
    }
}

#[test]
fn config_errors_name_the_field() {
    let mut c = ModelConfig::reference();
    c.dt_log2 = 3;
    assert_eq!(
        c.coefficients().unwrap_err().to_string(),
        "dt_log2: 3 outside [6, 12]"
    );
    let mut c = ModelConfig::reference();
    c.valve_area_mm2[4] = 1.0;
    assert_eq!(c.validate().unwrap_err().field, "valve_area_mm2");
    // The motor reading: 0 switches it off; a time constant below 1 ms, a band beyond 50 % of
    // ΔP or a minimum speed above the sensor's full scale is an error naming the field.
    let mut c = ModelConfig::reference();
    c.motor_reading_time_constant_ms = 0.0;
    let k = c.coefficients().unwrap();
    assert_eq!(k.reading.gain, Fx::ZERO);
    c.motor_reading_time_constant_ms = 0.5;
    assert_eq!(
        c.validate().unwrap_err().field,
        "motor_reading_time_constant_ms"
    );
    let mut c = ModelConfig::reference();
    c.motor_reading_band_pct = 60.0;
    assert_eq!(c.validate().unwrap_err().field, "motor_reading_band_pct");
    let mut c = ModelConfig::reference();
    c.motor_reading_min_rpm = c.motor_sensor_max_rpm + 1.0;
    assert_eq!(c.validate().unwrap_err().field, "motor_reading_min_rpm");
}

#[test]
fn state_is_small() {
    let n = std::mem::size_of::<State>() + std::mem::size_of::<SchedulerState>();
    println!("estimator + scheduler state: {n} bytes");
    assert!(n <= 1024);
}

/// A step that spent stroke-reversal work holds the feed-forward of the last refresh: its
/// command is the one the old pump flow would have given; the next free step refreshes it.
#[test]
fn feed_forward_is_held_while_a_reversal_is_worked_on() {
    use pto_model::estimator::Estimate;
    use pto_model::fx::Flow;
    let k = coeffs();
    let sc = SchedulerConfig::default().coefficients(k).unwrap();
    let mode = Mode::HoldPressure(Pressure::from_num(100.0));
    let est = |q: f32, units: u8| Estimate {
        p2: Pressure::from_num(100.0),
        lp: Pressure::from_num(3.0),
        q_pump_mean: Flow::from_num(q),
        background_units: units,
        ..Default::default()
    };
    let mut st = SchedulerState::default();
    // Settle on the rate limit: P2 at the set-point, the aperture at the feed-forward.
    for _ in 0..10_000 {
        scheduler::step(k, &sc, &mut st, mode, &est(3.0, 0), None);
    }
    let (mut held, mut fresh_old, mut fresh_new) = (st, st, st);
    let a_held = scheduler::step(k, &sc, &mut held, mode, &est(4.0, 1), None).aperture;
    let a_old = scheduler::step(k, &sc, &mut fresh_old, mode, &est(3.0, 0), None).aperture;
    let a_new = scheduler::step(k, &sc, &mut fresh_new, mode, &est(4.0, 0), None).aperture;
    println!(
        "aperture: held {}, refreshed at 3 L/min {}, at 4 L/min {} %",
        a_held.to_f32(),
        a_old.to_f32(),
        a_new.to_f32()
    );
    assert_eq!(a_held, a_old);
    assert!(a_new > a_old);
}

/// A fixed aperture is the aperture asked, whatever mode ran before: after holding a pressure
/// above its set-point (the integral term wound up), `Fixed(0)` closes the valve within the
/// rate limit's time (it held 15 % on the twin: the hold's integral carried over).
#[test]
fn a_fixed_aperture_after_a_hold_is_the_aperture_asked() {
    use pto_model::estimator::Estimate;
    use pto_model::fx::{Aperture, Flow};
    let k = coeffs();
    let cfg = SchedulerConfig::default();
    let sc = cfg.coefficients(k).unwrap();
    let est = Estimate {
        p2: Pressure::from_num(70.0),
        lp: Pressure::from_num(8.0),
        q_pump_mean: Flow::from_num(3.0),
        ..Default::default()
    };
    let mut st = SchedulerState::default();
    let hold = Mode::HoldPressure(Pressure::from_num(60.0));
    for _ in 0..20_000 {
        scheduler::step(k, &sc, &mut st, hold, &est, None);
    }
    let held = st;
    let steps_per_s = 1u32 << k.dt_log2;
    let mut a = Aperture::ZERO;
    // The slew from 100 % at the rate limit, and a step more.
    let n = (100.0 / cfg.rate_limit_pct_per_s * steps_per_s as f32) as u32 + 2;
    for _ in 0..n {
        a = scheduler::step(k, &sc, &mut st, Mode::Fixed(Aperture::ZERO), &est, None).aperture;
    }
    println!(
        "aperture after holding 60 bar at 70: {} %; {n} steps of fixed 0 %: {} %",
        scheduler::step(k, &sc, &mut held.clone(), hold, &est, None)
            .aperture
            .to_f32(),
        a.to_f32()
    );
    assert_eq!(a, Aperture::ZERO);
    let b = scheduler::step(
        k,
        &sc,
        &mut st,
        Mode::Fixed(Aperture::from_num(12.0)),
        &est,
        None,
    );
    assert!(b.aperture <= Aperture::from_num(12.0));
}
