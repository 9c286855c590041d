//! The controller's safety functions driven on the host with made-up sensor sequences: each
//! combination of HP reading (valid, a jump, a ramp, a wire break after the trip), encoder
//! (turning, stuck) and motor reading (a high speed behind a closed valve), and host resets
//! while high → the trip state over time, asserted step by step; and the sensor-fault safe
//! mode, which a lost transducer reaches once the estimate's σ passes its bound.

use proptest::prelude::*;
use pto_firmware::control::{ControlConfig, Controller, NoClock, StepOut};
use pto_firmware::frontend::{LoopSpec, Transducer};
use pto_firmware::trip::{TripLatch, TripSample};
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
    /// The ADC reference the board reports, mV.
    supply_mv: Option<u16>,
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
            supply_mv: Some(3300),
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
            supply_mv: self.supply_mv,
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

/// Sensors of a bench at rest: the lever still, the motor stopped.
fn rest(hp_bar: Option<f32>) -> Sensors {
    Sensors {
        hp_bar,
        encoder: 0,
        rpm: 0.0,
    }
}

fn release_bar(c: &Controller) -> f32 {
    c.latch().release().to_f32()
}

/// A failed measurement of the ADC's reference (VREFINT reading as 1.5 V, or not at all): no
/// loop reading can be trusted. They count as missing: the estimate runs on the model with the
/// HP sensor fault, a trip that holds keeps holding, and a high reading taken with it does not
/// release anything.
#[test]
fn an_implausible_supply_makes_the_readings_missing_and_the_trip_holds() {
    let mut b = Bench::new(100.0, 10.0);
    b.run(HZ, |_| still(Some(100.0)));
    b.supply_mv = Some(1500);
    let out = b.run(HZ, |_| still(Some(100.0)));
    assert!(
        out.iter()
            .all(|o| o.estimate.faults & fault::HP_SENSOR != 0)
    );
    assert!(
        out.iter().all(|o| !o.dump),
        "no trip from a missing reading alone"
    );
    assert_eq!(b.c.status.supply_faults, HZ);
    assert_eq!(b.c.status.hp_loop_faults, HZ);
    // Trip on a real reading, then the supply measurement fails: the trip holds, and the host
    // cannot reset it away.
    b.supply_mv = Some(3300);
    let out = b.run(10, |_| still(Some(150.0)));
    assert!(out.iter().all(|o| o.dump));
    b.supply_mv = Some(0);
    let out = b.run(5 * HZ, |_| still(Some(60.0)));
    assert!(
        out.iter().all(|o| o.dump),
        "released on an untrusted reading"
    );
    assert_eq!(
        b.c.reset(Pressure::from_num(60.0), Pressure::from_num(8.0)),
        Err(TripHold::HpMissing)
    );
    // The measurement back: readings count again.
    b.supply_mv = Some(3290);
    let out = b.run(10, |_| still(Some(60.0)));
    let last = out.last().unwrap();
    assert_eq!(
        last.estimate.faults & fault::HP_SENSOR,
        0,
        "{:?}",
        last.estimate
    );
    assert_eq!(b.c.status.supply_faults, HZ + 5 * HZ);
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
    // Valid readings return at 100 bar. The model, its valve wide open (the safe state) and
    // no transducer, has drained its P2 meanwhile: the reading disagrees, the gate rejects it,
    // and the estimator resets P2 to it — a contradiction, which holds the trip until the host
    // acknowledges it (a reset, taken once the reading and the estimate are both low).
    let p2_after = out.last().unwrap().estimate.p2.to_f32();
    let out = b.run(HZ, |_| still(Some(100.0)));
    assert!(
        out.iter().all(|o| o.dump),
        "released while reading and model disagreed"
    );
    let snapped = out
        .iter()
        .position(|o| o.estimate.faults & fault::INNOVATION_RESET != 0);
    println!(
        "readings back at 100 bar (the estimate at {p2_after:.1} bar after the wire break): P2 \
         reset to the reading after {snapped:?} steps; still tripped 1 s later"
    );
    assert!(b.c.latch().contradicted());
    b.c.reset(Pressure::from_num(100.0), Pressure::from_num(8.0))
        .expect("acknowledged once both read low");
    let out = b.run(2 * HZ, |_| still(Some(100.0)));
    let first_free = out
        .iter()
        .position(|o| !o.dump)
        .expect("released after the hold");
    let hold = usize::from(b.c.latch().hold_steps());
    println!(
        "acknowledged: released after {} steps (hold {hold})",
        first_free + 1
    );
    assert_eq!(first_free + 1, hold, "released exactly after the hold");
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
fn an_estimate_above_the_trip_trips_and_holds_until_the_host_acknowledges() {
    let mut b = Bench::new(100.0, 10.0);
    b.run(10, |_| still(Some(100.0)));
    b.c.reset(Pressure::from_num(150.0), Pressure::from_num(8.0))
        .unwrap();
    let out = b.run(3 * HZ, |_| still(Some(100.0)));
    assert!(out[0].dump, "the estimate alone trips");
    let rel = release_bar(&b.c);
    let low = out
        .iter()
        .position(|o| o.estimate.p2.to_f32() < rel)
        .unwrap();
    println!(
        "estimate 150 bar, reading 100: the estimate reset to the reading after {low} steps; \
         tripped 3 s later: {}",
        out.last().unwrap().dump
    );
    assert!(
        out.iter().all(|o| o.dump),
        "a contradiction released the trip"
    );
    b.c.reset(Pressure::from_num(100.0), Pressure::from_num(8.0))
        .unwrap();
    let out = b.run(HZ, |_| still(Some(100.0)));
    let free = out.iter().position(|o| !o.dump).expect("released");
    assert_eq!(free + 1, usize::from(b.c.latch().hold_steps()));
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
    // Still tripped, the estimator untouched: it steps on exactly as a twin never asked.
    let mut twin = Bench {
        supply_mv: Some(3300),
        c: b.c.clone(),
        hp: b.hp,
        lp: b.lp,
        tick: b.tick,
    };
    assert!(
        twin.c
            .reset(Pressure::from_num(100.0), Pressure::from_num(8.0))
            .is_err()
    );
    let (x, y) = (
        b.run(HZ, |_| still(Some(145.0))),
        twin.run(HZ, |_| still(Some(145.0))),
    );
    assert!(x.iter().all(|o| o.dump));
    assert_eq!(x, y, "a refused reset changed the controller");
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
        // The valve commanded closed, the lever still; the HP transducer confirms 50 bar for
        // 0.2 s, then its wire breaks and the motor sensor reads `rpm`.
        let confirm = HZ / 5;
        b.run(confirm, |_| Sensors {
            hp_bar: Some(50.0),
            encoder: 0,
            rpm: 0.0,
        });
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
            .position(|o| o.estimate.faults & fault::MOTOR_IMPLAUSIBLE != 0)
            .map(|k| k + confirm as usize);
        println!(
            "{rpm} rpm behind a closed valve, no HP: P2 max {p2_max:.3} bar over 3 s, σ {sigma_end:.3} \
             bar, contradiction flagged from step {flagged:?} of the closure"
        );
        assert!(p2_max < 50.5, "P2 followed the motor reading: {p2_max}");
        assert!(out.iter().all(|o| !o.dump), "false trip");
        // Flagged once a real rotor would have spun down (5 time constants J/c, 683 steps:
        // from the 683rd step, index 682), counted from the valve's closing.
        let k = flagged.expect("the contradiction is flagged");
        assert!((682..=700).contains(&k), "flagged at step {k}");
    }
}

#[test]
fn a_lost_transducer_drives_the_valve_to_its_safe_aperture_once_sigma_passes_its_bound() {
    use pto_model::scheduler::Override;
    let bound = SchedulerConfig::default().sensor_fault_sigma_bar;
    let safe = SchedulerConfig::default().sensor_fault_aperture_pct;
    // The HP accumulator empty (15 bar, precharge 25), the valve closed, no motor reading: the
    // transducer confirms 15 bar for 0.1 s, then its wire breaks; the stiff node's variance
    // grows at ≈ 0.08 bar² a step.
    let mut b = Bench::new(15.0, 0.0);
    b.run(HZ / 10, |_| still(Some(15.0)));
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
    b.run(HZ / 10, |_| still(Some(100.0)));
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

/// A host reset while the HP transducer is lost cannot stand in for it: until a valid reading
/// confirms the host's pressures, P2 stays as uncertain as at boot and the valve goes to its
/// sensor-fault aperture.
#[test]
fn a_reset_without_the_transducer_does_not_replace_it() {
    use pto_model::scheduler::Override;
    let mut b = Bench::new(100.0, 10.0);
    b.run(HZ / 10, |_| still(Some(100.0)));
    b.run(HZ / 10, |_| still(None));
    b.c.reset(Pressure::from_num(60.0), Pressure::from_num(8.0))
        .unwrap();
    let out = b.run(HZ / 10, |_| still(None));
    let sigma = out[0].estimate.p2_sigma().to_f32();
    println!("reset to 60 bar with the transducer lost: σ {sigma:.1} bar");
    assert!(sigma > 10.0);
    assert!(
        out.iter()
            .all(|o| o.command.safety == Override::SensorFault)
    );
    // A reading confirms it: the estimate converges and σ falls.
    let out = b.run(HZ, |_| still(Some(100.0)));
    let last = out.last().unwrap();
    assert!(last.command.safety == Override::None);
    assert!((last.estimate.p2.to_f32() - 100.0).abs() < 1.0);
}

/// The HP transducer fails to a valid low current (4 mA, 0 bar) while tripped at 150 bar: the
/// gate rejects it, then the estimator resets P2 to it and the two agree, low. The latch holds
/// (a contradiction) until the host acknowledges it.
#[test]
fn a_transducer_failing_low_while_tripped_holds_the_trip() {
    let mut b = Bench::new(100.0, 10.0);
    b.run(HZ, |_| still(Some(100.0)));
    b.run(HZ / 2, |i| {
        still(Some(100.0 + 50.0 * i as f32 / (HZ / 2) as f32))
    });
    b.run(HZ / 10, |_| still(Some(150.0)));
    assert!(b.c.status.tripped);
    let out = b.run(10 * HZ, |_| still(Some(0.0)));
    let snapped = out
        .iter()
        .position(|o| o.estimate.faults & fault::INNOVATION_RESET != 0)
        .expect("the estimator resets P2 to the reading");
    println!(
        "transducer fails to 0 bar while tripped: P2 reset to it after {snapped} steps; 10 s \
         later still tripped: {}",
        out.last().unwrap().dump
    );
    assert!(
        out.iter().all(|o| o.dump),
        "released on a failed transducer"
    );
    let e = b.c.reset(Pressure::from_num(0.0), Pressure::from_num(8.0));
    assert_eq!(
        e,
        Ok(()),
        "the acknowledgement is taken while both read low"
    );
    let out = b.run(HZ, |_| still(Some(0.0)));
    let free = out
        .iter()
        .position(|o| !o.dump)
        .expect("released after the hold");
    assert!(free + 1 >= usize::from(b.c.latch().hold_steps()));
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 2000,
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    /// For any sequence of steps the latch trips on every sign of overpressure, and never
    /// releases unless each of the last `hold` steps had a valid reading the gate took, it and
    /// the estimate below the release pressure and no trip sign — so never while any valid HP
    /// reading within the last hold time was at or above the release pressure.
    #[test]
    fn the_latch_trips_on_every_sign_and_releases_only_after_a_clean_hold(
        seq in prop::collection::vec(
            (
                prop::option::weighted(0.8, 0.0f32..270.0),
                any::<bool>(),
                prop::bool::weighted(0.9),
                prop::bool::weighted(0.02),
                0.0f32..200.0,
            ),
            1..600,
        ),
        hold in 1u16..50,
    ) {
        let (trip, release) = (140.0f32, 125.0f32);
        let mut l = TripLatch::new(Pressure::from_num(trip), Pressure::from_num(release), hold);
        let mut clean_run = 0usize;
        let mut contradicted = false;
        let mut was = false;
        for (i, (hp, in_range, accepted, reset, est)) in seq.iter().enumerate() {
            let s = TripSample {
                reading: hp.map(Pressure::from_num),
                in_range: *in_range,
                accepted: *accepted,
                innovation_reset: *reset,
                estimate: Pressure::from_num(*est),
            };
            let sign = hp.is_some_and(|p| p > trip) || *est > trip;
            contradicted |= was && *reset;
            let clean = !sign
                && *in_range
                && *accepted
                && hp.is_some_and(|p| p < release)
                && *est < release
                && !contradicted;
            clean_run = if clean { clean_run + 1 } else { 0 };
            let now = l.step(&s);
            if sign {
                prop_assert!(now, "step {}: a trip sign left the latch armed", i);
            }
            if was && !now {
                prop_assert!(
                    clean_run >= usize::from(hold),
                    "released at step {} after {} clean steps (hold {})", i, clean_run, hold
                );
            }
            if !now {
                contradicted = false;
            }
            was = now;
        }
    }
}

/// The bring-up self-test: it starts only from the safe state, drives one output at a time
/// from the de-energised state, and the trip wins over it in the very step that sees the
/// overpressure — with the dump valve driven closed by the test at that moment.
#[test]
fn the_self_test_starts_only_when_safe_and_the_trip_ends_it_at_once() {
    use pto_firmware::outputs::Outputs;
    use pto_firmware::selftest::Ended;
    use pto_model::protocol::selftest::{SELFTEST_IDLE_S, TestDrive};
    use pto_model::protocol::{NotSafe, SelfTestRefusal};

    let mut b = Bench::new(60.0, 10.0);
    b.run(300, |_| rest(Some(60.0)));
    assert_eq!(
        b.c.selftest_begin(),
        Err(SelfTestRefusal::NotSafe(NotSafe::ValveOpen)),
        "valve open"
    );
    b.c.set_mode(Mode::Fixed(Aperture::ZERO));
    b.run(HZ, |_| rest(Some(60.0)));
    assert_eq!(b.c.sensor_faults(), 0);
    assert_eq!(b.c.selftest_begin(), Ok(Outputs::DE_ENERGISED));
    assert_eq!(
        b.c.selftest_drive(TestDrive::Valve(Aperture::from_num(11.0))),
        Err(SelfTestRefusal::ApertureTooHigh(Aperture::from_num(11.0)))
    );
    let o =
        b.c.selftest_drive(TestDrive::Valve(Aperture::from_num(5.0)))
            .unwrap();
    assert!(o.dump_open && o.aperture.to_f32() == 5.0);
    let out = b.run(10, |_| rest(Some(60.0)));
    assert!(
        out.iter()
            .all(|o| o.dump && o.applied.to_f32() == 5.0 && o.on_duty == 0)
    );
    assert_eq!(
        b.c.safe_to_apply(),
        Err(NotSafe::SelfTest),
        "no commit meanwhile"
    );
    // The dump valve closed by the test, then an overpressure: the trip's safe state in that
    // same step, and the self-test is over.
    b.c.selftest_drive(TestDrive::DumpClosed).unwrap();
    let out = b.run(5, |_| rest(Some(60.0)));
    assert!(out.iter().all(|o| !o.dump && o.applied == Aperture::ZERO));
    let out = b.step(rest(Some(150.0)));
    assert!(out.dump && out.applied.to_f32() == 100.0, "{out:?}");
    assert_eq!(out.selftest_ended, Some(Ended::Tripped));
    assert!(!b.c.selftest_active());
    assert_eq!(
        b.c.selftest_drive(TestDrive::AllOff),
        Err(SelfTestRefusal::NotActive)
    );
    assert_eq!(
        b.c.selftest_begin(),
        Err(SelfTestRefusal::NotSafe(NotSafe::Tripped))
    );

    // A self-test left alone ends by itself, the outputs back to the controller from
    // de-energised; a mode command ends one at once.
    let mut b = Bench::new(60.0, 0.0);
    b.run(HZ, |_| rest(Some(60.0)));
    b.c.selftest_begin().unwrap();
    b.c.selftest_drive(TestDrive::Solenoid(3)).unwrap();
    let out = b.run(u32::from(SELFTEST_IDLE_S) * HZ, |_| rest(Some(60.0)));
    let ended: Vec<_> = out.iter().filter_map(|o| o.selftest_ended).collect();
    assert_eq!(ended, [Ended::Idle]);
    assert!(out[..10].iter().all(|o| o.on_duty == 0b1000));
    let last = out.last().unwrap();
    assert_eq!(last.selftest_ended, Some(Ended::Idle));
    assert_eq!(last.outputs(), Outputs::DE_ENERGISED, "the step it ends in");
    let next = b.step(rest(Some(60.0)));
    assert!(!next.dump && next.on_duty == pto_firmware::control::BOOT_ON_DUTY);
    b.c.selftest_begin().unwrap();
    b.c.set_mode(Mode::Fixed(Aperture::ZERO));
    assert!(!b.c.selftest_active());
}

/// A controller that just booted — after a watchdog reset, a fault, a brown-out — keeps every
/// output de-energised (the dump valve open, no solenoid) until the host's first mode, duty or
/// reset command, however plausible its readings; booted tripped, it drives the trip's valve
/// and still no solenoid. A configuration's commit keeps the hold.
#[test]
fn after_a_reset_nothing_is_energised_until_the_host_asks() {
    use pto_firmware::outputs::Outputs;
    let fresh = || {
        Controller::new(
            &ModelConfig::reference(),
            &SchedulerConfig::default(),
            &ControlConfig::default(),
        )
        .unwrap()
    };
    let mut b = Bench::new(60.0, 0.0);
    b.c = fresh();
    assert!(b.c.held() && b.c.status.held && b.c.status.dump_valve);
    let out = b.run(2 * HZ, |_| still(Some(60.0)));
    assert!(
        out.iter().all(|o| o.outputs() == Outputs::DE_ENERGISED),
        "{:?}",
        out[0]
    );
    // The commit of another configuration keeps it held.
    let mut cfg = ModelConfig::reference();
    cfg.trapped_air_fraction = 0.08;
    b.c.reconfigure(&cfg, &SchedulerConfig::default(), &ControlConfig::default())
        .unwrap();
    let out = b.run(10, |_| still(Some(60.0)));
    assert!(out.iter().all(|o| o.outputs() == Outputs::DE_ENERGISED));
    b.c.set_mode(Mode::Fixed(Aperture::ZERO));
    let o = b.step(still(Some(60.0)));
    assert!(
        !o.dump && o.on_duty == pto_firmware::control::BOOT_ON_DUTY,
        "{o:?}"
    );
    assert!(!b.c.status.held);

    // Booted tripped: the trip's valve, the dump valve open, no solenoid; released (a valid
    // low reading for the hold time), back to de-energised, not to running.
    let mut b = Bench::new(60.0, 0.0);
    b.c = fresh();
    b.c.boot_tripped();
    let out = b.run(HZ, |_| still(Some(60.0)));
    let tripped = out
        .iter()
        .take_while(|o| o.applied.to_f32() == 100.0)
        .count();
    assert!(
        tripped >= HZ as usize / 2 - 2,
        "released after {tripped} steps"
    );
    assert!(out.iter().all(|o| o.dump && o.on_duty == 0));
    assert_eq!(out.last().unwrap().outputs(), Outputs::DE_ENERGISED);
}

/// A controller just booted (no host reset: P2 unknown, outputs held) on a bench at rest — the
/// lever still at count 0, HP steady at 60 bar with the transducer's noise (σ 0.5 bar), the
/// motor stopped — holds no sensor faulted, over 20 boots of 10 s with different noise: a
/// still lever with a steady P2 is what a calm bench looks like, and the encoder check must
/// not take one reading's noise against another's for a rise in P2 (it latched the encoder
/// within 2 s of every such boot on the twin).
#[test]
fn a_booted_controller_at_rest_holds_no_sensor_faulted() {
    let mut latched = Vec::new();
    for seed in 1..=20u64 {
        let mut b = Bench::new(60.0, 0.0);
        b.c = Controller::new(
            &ModelConfig::reference(),
            &SchedulerConfig::default(),
            &ControlConfig::default(),
        )
        .unwrap();
        // The transducer's noise, σ 0.5 bar (the sensor model's): Box–Muller on a xorshift.
        let mut x = 0x9e37_79b9_7f4a_7c15u64 ^ seed.wrapping_mul(0x2545_f491_4f6c_dd1d);
        let mut uniform = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            ((x >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let noise: Vec<f32> = (0..10 * HZ)
            .map(|_| {
                let (u, v) = (uniform(), uniform());
                (0.5 * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32
            })
            .collect();
        let outs = b.run(10 * HZ, |i| rest(Some(60.0 + noise[i as usize])));
        let seen = outs.iter().fold(0u16, |a, o| a | o.estimate.faults);
        if b.c.status.sensor_faults != 0 {
            latched.push((seed, seen, b.c.status.sensor_faults));
        }
    }
    println!("20 boots of 10 s at rest: sensors latched in {latched:?}");
    assert!(latched.is_empty(), "{latched:?}");
}
