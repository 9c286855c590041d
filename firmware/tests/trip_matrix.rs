//! The controller's safety functions driven on the host with made-up sensor sequences: each
//! combination of HP reading (valid, a jump, a ramp, a wire break after the trip), encoder
//! (turning, stuck) and motor reading (a high speed behind a closed valve), and host resets
//! while high → the trip state over time, asserted step by step; and the sensor-fault safe
//! mode, which a lost transducer reaches once the estimate's σ passes its bound.

use proptest::prelude::*;
use pto_firmware::control::{ControlConfig, Controller, NoClock, StepOut};
use pto_firmware::frontend::{LoopSpec, Transducer};
use pto_firmware::trip::TripLatch;
use pto_model::ModelConfig;
use pto_model::estimator::fault;
use pto_model::fx::{Aperture, Pressure, Rpm};
use pto_model::protocol::{SensorFrame, TripHold};
use pto_model::scheduler::{Mode, SchedulerConfig};

/// Steps per second (2^-10 s).
const HZ: u32 = 1024;

/// One step's sensors.
#[derive(Clone, Copy)]
struct Sensors {
    /// HP, bar; `None` = wire break (0 mA).
    hp_bar: Option<f32>,
    /// Encoder count.
    encoder: i32,
    /// Motor speed, rpm.
    rpm: f32,
}

struct Bench {
    c: Controller,
    hp: Transducer,
    lp: Transducer,
    tick: u32,
}

impl Bench {
    /// A controller started from known pressures, the valve at a fixed aperture.
    fn new(p2_bar: f32, aperture_pct: f32) -> Self {
        let mut c = Controller::new(
            &ModelConfig::reference(),
            &SchedulerConfig::default(),
            &ControlConfig::default(),
        )
        .unwrap();
        c.reset(Pressure::from_num(p2_bar), Pressure::from_num(8.0))
            .unwrap();
        c.set_mode(Mode::Fixed(Aperture::from_num(aperture_pct)));
        Bench {
            c,
            hp: Transducer::new(LoopSpec::HP).unwrap(),
            lp: Transducer::new(LoopSpec::LP).unwrap(),
            tick: 0,
        }
    }

    fn step(&mut self, s: Sensors) -> StepOut {
        let f = SensorFrame {
            tick: self.tick,
            encoder: s.encoder,
            hp_adc: s
                .hp_bar
                .map_or(self.hp.counts_at_ma(0.0), |p| self.hp.counts_at_bar(p)),
            lp_adc: self.lp.counts_at_bar(8.0),
            motor: Some(Rpm::from_num(s.rpm)),
        };
        self.tick += 1;
        self.c.sample(&f, &mut NoClock)
    }

    /// Runs `n` steps of `f(i)`; returns every output.
    fn run(&mut self, n: u32, f: impl Fn(u32) -> Sensors) -> Vec<StepOut> {
        (0..n).map(|i| self.step(f(i))).collect()
    }
}

fn still(hp_bar: Option<f32>) -> Sensors {
    Sensors {
        hp_bar,
        encoder: 0,
        rpm: 200.0,
    }
}

fn release_bar(c: &Controller) -> f32 {
    c.latch().release().to_f32()
}

#[test]
fn a_jump_trips_at_once_and_a_wire_break_after_it_holds_the_trip() {
    let mut b = Bench::new(100.0, 10.0);
    b.run(HZ, |_| still(Some(100.0)));
    let out = b.run(10, |_| still(Some(150.0)));
    assert!(out[0].dump, "tripped in the step that read 150 bar");
    assert_ne!(
        out[0].estimate.faults & fault::INNOVATION,
        0,
        "the jump is rejected by the gate, and flagged"
    );
    assert!(
        out[0].estimate.p2.to_f32() < 101.0,
        "the estimate stayed near 100 bar"
    );
    // Wire break for 10 s: the latch holds all through, whatever the estimate does.
    let out = b.run(10 * HZ, |_| still(None));
    let low = out
        .iter()
        .filter(|o| o.estimate.p2.to_f32() < 125.0)
        .count();
    assert!(out.iter().all(|o| o.dump), "a wire break released the trip");
    println!("wire break: 10 s tripped, estimate below the release in {low} steps");
    assert_eq!(
        b.c.reset(Pressure::from_num(100.0), Pressure::from_num(8.0)),
        Err(TripHold::HpMissing)
    );
    // Valid readings return at 100 bar: release only after the estimate too has been below the
    // release pressure for the hold time.
    let out = b.run(3 * HZ, |_| still(Some(100.0)));
    let first_free = out
        .iter()
        .position(|o| !o.dump)
        .expect("released once valid and low");
    let hold = usize::from(b.c.latch().hold_steps());
    let low_since = out
        .iter()
        .position(|o| o.estimate.p2.to_f32() < release_bar(&b.c))
        .unwrap();
    println!(
        "readings back at 100 bar: estimate below the release after {low_since} steps, \
         released after {first_free} (hold {hold})"
    );
    assert_eq!(
        first_free,
        low_since + hold - 1,
        "released exactly after the hold"
    );
    assert!(out[first_free..].iter().all(|o| !o.dump));
    assert_eq!(b.c.status.trips, 1);
}

#[test]
fn a_ramp_trips_where_it_crosses_and_a_wire_break_after_the_trip_holds_it() {
    let mut b = Bench::new(100.0, 10.0);
    // 100 → 150 bar over 1 s, the motor at 200 rpm.
    let out = b.run(HZ, |i| still(Some(100.0 + 50.0 * i as f32 / HZ as f32)));
    let k = out.iter().position(|o| o.dump).expect("the ramp trips");
    let crossing = (HZ as f32 * 40.0 / 50.0) as usize;
    println!("ramp: tripped at step {k}, the reading crossed 140 bar at step {crossing}");
    assert!(
        k <= crossing + 2,
        "tripped {k} steps in, the reading crossed at {crossing}"
    );
    let out = b.run(5 * HZ, |_| still(None));
    assert!(out.iter().all(|o| o.dump), "released during the wire break");
    assert!(b.c.status.hp_loop_faults >= 5 * HZ);
}

#[test]
fn a_stuck_encoder_neither_hides_nor_releases_a_trip() {
    let mut b = Bench::new(100.0, 10.0);
    // The encoder does not move while P2 rises past the trip (the pump flow is invisible).
    let out = b.run(4 * HZ, |i| {
        still(Some(100.0 + 45.0 * i as f32 / (4 * HZ) as f32))
    });
    assert!(out.last().unwrap().dump, "tripped on the reading");
    assert!(
        out.iter()
            .any(|o| o.estimate.faults & fault::ENCODER_STUCK != 0),
        "the stuck encoder is flagged"
    );
    let out = b.run(2 * HZ, |_| still(Some(130.0)));
    assert!(
        out.iter().all(|o| o.dump),
        "130 bar is above the release pressure"
    );
}

#[test]
fn an_estimate_above_the_trip_trips_and_holds_until_it_falls() {
    let mut b = Bench::new(100.0, 10.0);
    b.run(10, |_| still(Some(100.0)));
    b.c.reset(Pressure::from_num(150.0), Pressure::from_num(8.0))
        .unwrap();
    let out = b.run(3 * HZ, |_| still(Some(100.0)));
    assert!(out[0].dump, "the estimate alone trips");
    let rel = release_bar(&b.c);
    let free = out.iter().position(|o| !o.dump).expect("released");
    let low = out
        .iter()
        .position(|o| o.estimate.p2.to_f32() < rel)
        .unwrap();
    println!(
        "estimate 150 bar, reading 100: estimate below the release after {low} steps, released after {free}"
    );
    assert!(free >= low + usize::from(b.c.latch().hold_steps()) - 1);
}

#[test]
fn a_reset_while_high_is_refused_with_its_reason() {
    let mut b = Bench::new(100.0, 10.0);
    b.run(5, |_| still(Some(145.0)));
    assert!(b.c.status.tripped);
    let e =
        b.c.reset(Pressure::from_num(100.0), Pressure::from_num(8.0))
            .unwrap_err();
    assert!(
        matches!(e, TripHold::HpHigh(p) if (p.to_f32() - 145.0).abs() < 0.2),
        "{e:?}"
    );
    println!("reset while high: refused ({e})");
    // Still tripped, the estimator untouched.
    let out = b.run(HZ, |_| still(Some(145.0)));
    assert!(out.iter().all(|o| o.dump));
    // Back below the release: the reset is taken, the trip still runs its hold.
    // (The estimate, rejecting the 45 bar innovation, takes the reading after 250 ms.)
    b.run(300, |_| still(Some(100.0)));
    assert!(b.c.status.tripped);
    b.c.reset(Pressure::from_num(100.0), Pressure::from_num(8.0))
        .unwrap();
    let out = b.run(1, |_| still(Some(100.0)));
    assert!(out[0].dump, "a reset never releases the trip itself");
}

#[test]
fn a_high_motor_reading_behind_a_closed_valve_moves_nothing_and_is_flagged() {
    for rpm in [50.0, 200.0] {
        let mut b = Bench::new(50.0, 0.0);
        // The HP transducer lost, the valve commanded closed, the lever still, the motor
        // sensor reading `rpm`.
        let out = b.run(3 * HZ, |_| Sensors {
            hp_bar: None,
            encoder: 0,
            rpm,
        });
        let p2_max = out
            .iter()
            .map(|o| o.estimate.p2.to_f32())
            .fold(0.0, f32::max);
        let sigma_end = out.last().unwrap().estimate.p2_sigma().to_f32();
        let flagged = out
            .iter()
            .position(|o| o.estimate.faults & fault::MOTOR_IMPLAUSIBLE != 0);
        println!(
            "{rpm} rpm behind a closed valve, no HP: P2 max {p2_max:.3} bar over 3 s, σ {sigma_end:.3} \
             bar, contradiction flagged from step {flagged:?}"
        );
        assert!(p2_max < 50.5, "P2 followed the motor reading: {p2_max}");
        assert!(out.iter().all(|o| !o.dump), "false trip");
        // Flagged once a real rotor would have spun down (5 time constants, 0.67 s).
        let k = flagged.expect("the contradiction is flagged");
        assert!((600..=800).contains(&k), "flagged at step {k}");
    }
}

#[test]
fn a_lost_transducer_drives_the_valve_to_its_safe_aperture_once_sigma_passes_its_bound() {
    use pto_model::scheduler::Override;
    let bound = SchedulerConfig::default().sensor_fault_sigma_bar;
    let safe = SchedulerConfig::default().sensor_fault_aperture_pct;
    // The HP accumulator empty (15 bar, precharge 25), the valve closed, no motor reading: the
    // stiff node's variance grows at ≈ 0.08 bar² a step.
    let mut b = Bench::new(15.0, 0.0);
    let out = b.run(HZ / 2, |_| Sensors {
        hp_bar: None,
        encoder: 0,
        rpm: 0.0,
    });
    let k = out
        .iter()
        .position(|o| o.command.safety == Override::SensorFault)
        .expect("the sensor-fault safe mode engages");
    let sigma = out[k].estimate.p2_sigma().to_f32();
    println!(
        "empty HP node, transducer lost: σ {sigma:.2} bar > {bound} bar at step {k}, valve to \
         {:.1} %",
        out[k].applied.to_f32()
    );
    assert!(
        sigma > bound && k < (HZ / 4) as usize,
        "within 0.25 s: step {k}, σ {sigma}"
    );
    assert!(
        out[k..]
            .iter()
            .all(|o| o.command.safety == Override::SensorFault)
    );
    assert_eq!(out[k].applied.to_f32(), safe, "the safe aperture at once");
    // With gas in the accumulator (100 bar) the model alone stays good for minutes: 10 s
    // without the transducer leave σ near its start and the mode alone.
    let mut b = Bench::new(100.0, 10.0);
    let out = b.run(10 * HZ, |_| Sensors {
        hp_bar: None,
        encoder: 0,
        rpm: 0.0,
    });
    let sigma = out.last().unwrap().estimate.p2_sigma().to_f32();
    println!("100 bar, transducer lost for 10 s: σ {sigma:.2} bar");
    assert!(out.iter().all(|o| o.command.safety == Override::None));
    assert!(sigma < 1.2);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// For any sequence of readings and estimates the latch never releases while any valid
    /// HP reading within the last hold time was at or above the release pressure.
    #[test]
    fn the_latch_never_releases_while_a_recent_valid_reading_was_high(
        seq in prop::collection::vec(
            (prop::option::weighted(0.8, 0.0f32..200.0), 0.0f32..200.0),
            1..600,
        ),
        hold in 1u16..50,
    ) {
        let mut l = TripLatch::new(Pressure::from_num(140.0), Pressure::from_num(125.0), hold);
        let mut last_high: Option<usize> = None;
        let mut was = false;
        for (i, (hp, est)) in seq.iter().enumerate() {
            let hp = hp.map(Pressure::from_num);
            if hp.is_some_and(|p| p.to_f32() >= 125.0) {
                last_high = Some(i);
            }
            let now = l.step(hp, Pressure::from_num(*est));
            if was && !now {
                prop_assert!(
                    last_high.is_none_or(|k| i - k >= usize::from(hold)),
                    "released at step {i}, a valid reading was high at step {last_high:?}"
                );
            }
            was = now;
        }
    }
}
