//! Processor-in-the-loop: the full simulation is the plant, the QEMU firmware its controller, in
//! lockstep over USART1 (one sensor frame out and one output back per 2^-10 s step). Also the
//! fault injections and the watchdog test.

use pto_host::bench::{BAR, Bench};
use pto_host::estimation::SensorSpec;
use pto_host::pil::{self, Injection, PilRow};
use pto_host::qemu::{self, Build, Qemu};
use pto_model::estimator::fault;
use pto_model::fx::{Pressure, Rpm};
use pto_model::protocol::ToFirmware;
use pto_model::scheduler::{Mode, Override};
use std::time::{Duration, Instant};

fn boot() -> Qemu {
    Qemu::boot(&qemu::build(Build::Qemu).unwrap(), false).unwrap()
}

fn finish(mut q: Qemu) {
    q.link.send(&ToFirmware::Exit(0)).unwrap();
    let code = q.wait_exit(Duration::from_secs(10)).unwrap();
    let log = q.log();
    assert_eq!(code, 0, "firmware exit code; log tail: {:?}", &log[log.len().saturating_sub(5)..]);
    assert!(
        !log
            .iter()
            .any(|l| l.text.starts_with("watchdog expired") || l.text.starts_with("panic")),
        "unexpected reset path in the log"
    );
}

fn window(rows: &[PilRow], from: f64) -> impl Iterator<Item = &PilRow> {
    rows.iter().filter(move |r| r.t >= from)
}

#[test]
fn pil_holds_p2_at_100_bar() {
    let q = boot();
    let t0 = Instant::now();
    let (q, res, rows) = pil::closed_loop(
        q,
        &Bench::reference(),
        Mode::HoldPressure(Pressure::from_num(100.0)),
        92.0,
        60.0,
        SensorSpec::default(),
        Box::new(|_| Injection::None),
    )
    .unwrap();
    let reach = pto_host::paper::time_to_reach(&res.trace.t, &res.trace.p2, 100.0 * BAR)
        .expect("P2 reaches the setpoint");
    // The P2 loop (default gains) settles in ≈ 40 s, as in the in-process check of `pto
    // validate`, which judges from 60 s after the first crossing of a 400 s run.
    let from = 40.0;
    let worst = window(&rows, from)
        .map(|r| (r.p2 - 100.0).abs())
        .fold(0.0, f64::max);
    let est = window(&rows, from)
        .filter_map(|r| r.estimate.map(|e| (f64::from(e.p2.to_f32()) - r.p2).abs()))
        .fold(0.0, f64::max);
    println!(
        "PIL hold P2 at 100 bar: {} steps in {:.1} s wall; P2 reached 100 bar at {reach:.1} s; \
         from {from:.1} s to 60 s the plant's P2 is within ±{worst:.2} bar (target ±2), the \
         firmware's estimate within {est:.2} bar of it",
        rows.len(),
        t0.elapsed().as_secs_f64()
    );
    assert!(rows.len() >= 60 * 1024);
    assert!(worst <= 2.0);
    finish(q);
}

#[test]
fn pil_holds_motor_speed() {
    let q = boot();
    let sp = 250.0;
    let (q, _res, rows) = pil::closed_loop(
        q,
        &Bench::reference(),
        Mode::HoldSpeed(Rpm::from_num(sp as f32)),
        100.0,
        40.0,
        SensorSpec::default(),
        Box::new(|_| Injection::None),
    )
    .unwrap();
    let from = 15.0;
    let worst = window(&rows, from)
        .map(|r| (r.rpm - sp).abs() / sp)
        .fold(0.0, f64::max);
    let ap: Vec<f64> = window(&rows, from).map(|r| r.applied).collect();
    println!(
        "PIL hold motor at {sp} rpm: from {from} s to 40 s within ±{:.2} % (target ±3 %), \
         aperture {:.1}–{:.1} %",
        worst * 100.0,
        ap.iter().copied().fold(f64::INFINITY, f64::min),
        ap.iter().copied().fold(0.0, f64::max)
    );
    assert!(worst <= 0.03);
    finish(q);
}

#[test]
fn pil_trips_to_the_safe_state_within_one_period() {
    // The relief valve is set above the trip (a relief that does not open), the control valve
    // is closed: P2 climbs through the 140 bar trip.
    let mut bench = Bench::reference();
    bench.relief_setting = 170.0 * BAR;
    // A noise-free HP transducer, so that the trip happens where P2 crosses it (with the 0.5 bar
    // noise of the other runs it trips up to ≈ 1.5 bar early, on a noise peak).
    let spec = SensorSpec {
        hp_noise_bar: 0.0,
        ..SensorSpec::default()
    };
    let q = boot();
    let (q, _res, rows) = pil::closed_loop(
        q,
        &bench,
        pil::fixed(0.0),
        136.0,
        4.0,
        spec,
        Box::new(|_| Injection::None),
    )
    .unwrap();
    let trip = 140.0;
    let first_safe = rows.iter().position(|r| r.dump).expect("the firmware trips");
    // The first step at which the plant's P2 is above the trip (if the valve let it get there).
    let k = rows.iter().position(|r| r.p2 > trip);
    let peak = rows.iter().map(|r| r.p2).fold(0.0, f64::max);
    println!(
        "PIL trip: firmware tripped at step {first_safe} (t = {:.4} s) with the plant's P2 at \
         {:.3} bar; the plant first exceeded {trip} bar at step {k:?}; the valve command of that \
         step: {:.0} %, dump {}; P2 peaked at {peak:.2} bar",
        rows[first_safe].t,
        rows[first_safe].p2,
        rows[first_safe].applied,
        rows[first_safe].dump,
    );
    // Safe in the very step that saw the overpressure (applied by the plant from the next
    // period on): never later than the first period in which P2 is above the trip.
    assert!(k.is_none_or(|k| first_safe <= k), "tripped late");
    assert!(rows[first_safe].p2 > trip - 0.2, "tripped early: not on the overpressure");
    assert!(rows[first_safe].applied == 100.0 && rows[first_safe].dump);
    assert!(peak < trip + 0.5, "P2 stopped at the trip");
    let cmd = rows[first_safe].command.expect("an output at the trip");
    assert_eq!(cmd.safety, Override::Overpressure);
    // Latched until P2 is well below the trip.
    for r in &rows[first_safe..] {
        if r.p2 > trip - 10.0 {
            assert!(r.dump && r.applied == 100.0, "t = {:.3}: released early", r.t);
        }
    }
    finish(q);
}

#[test]
fn pil_survives_injected_faults() {
    let q = boot();
    let inject = |t: f64| -> Injection {
        match t {
            t if (4.0..7.0).contains(&t) => Injection::HpWireBreak,
            // The estimator calls the encoder stuck when it has not moved for 2 s while the HP
            // reading changed by more than 1 bar.
            t if (8.0..13.0).contains(&t) => Injection::EncoderStuck,
            t if (14.0..14.2).contains(&t) => Injection::HpNoise(30.0),
            t if (15.0..16.0).contains(&t) && ((t * 1024.0) as i64) % 50 == 0 => {
                Injection::Corrupt
            }
            t if (16.0..17.0).contains(&t) && ((t * 1024.0) as i64) % 50 == 0 => {
                Injection::Truncate
            }
            t if (17.0..18.0).contains(&t) && ((t * 1024.0) as i64) % 100 == 0 => {
                Injection::Burst(40)
            }
            _ => Injection::None,
        }
    };
    let (mut q, _res, rows) = pil::closed_loop(
        q,
        &Bench::reference(),
        Mode::HoldPressure(Pressure::from_num(100.0)),
        100.0,
        19.0,
        SensorSpec::default(),
        Box::new(inject),
    )
    .unwrap();
    let st = pil::status(&mut q).unwrap();
    let flagged = |from: f64, to: f64, bit: u16| {
        rows.iter()
            .filter(|r| r.t >= from && r.t < to)
            .filter_map(|r| r.estimate)
            .any(|e| e.faults & bit != 0)
    };
    // Model-only P2 during the wire break.
    let wb: Vec<&PilRow> = rows.iter().filter(|r| r.injection == Injection::HpWireBreak).collect();
    let wb_err = wb
        .iter()
        .filter_map(|r| r.estimate.map(|e| (f64::from(e.p2.to_f32()) - r.p2).abs()))
        .fold(0.0, f64::max);
    let noise_err = rows
        .iter()
        .filter(|r| matches!(r.injection, Injection::HpNoise(_)))
        .filter_map(|r| r.estimate.map(|e| (f64::from(e.p2.to_f32()) - r.p2).abs()))
        .fold(0.0, f64::max);
    let damaged = rows
        .iter()
        .filter(|r| matches!(r.injection, Injection::Corrupt | Injection::Truncate))
        .count() as u32;
    let bursts = rows
        .iter()
        .filter(|r| matches!(r.injection, Injection::Burst(_)))
        .count() as u32;
    let err_in = |keep: &dyn Fn(f64) -> bool| {
        window(&rows, 1.0)
            .filter(|r| keep(r.t))
            .filter_map(|r| r.estimate.map(|e| (f64::from(e.p2.to_f32()) - r.p2).abs()))
            .fold(0.0, f64::max)
    };
    // While the encoder is stuck (and for 1 s after) the pump model sees a still shaft: the
    // estimate then rides on the gated HP correction.
    let stuck = |t: f64| (8.0..14.0).contains(&t);
    let est_err = err_in(&|t| !stuck(t));
    let stuck_err = err_in(&stuck);
    let outputs = rows.iter().filter(|r| r.estimate.is_some()).count();
    println!(
        "PIL faults: wire break 3 s — model-only P2 within {wb_err:.2} bar; noise bursts ±30 bar — \
         estimate within {noise_err:.2} bar; {damaged} damaged frames → {} dropped; {bursts} \
         bursts of 40 frames → {} overruns, {} bytes lost; estimate within {est_err:.2} bar of the \
         plant outside the stuck-encoder window, {stuck_err:.2} bar inside it; {} steps run, {outputs} outputs for {} steps",
        st.frames_dropped,
        st.frames_overrun,
        st.bytes_lost,
        st.steps,
        rows.len()
    );
    assert!(flagged(4.0, 7.0, fault::HP_SENSOR), "wire break flagged");
    assert!(st.hp_loop_faults >= 3 * 1000, "wire-break samples counted");
    assert!(wb_err <= 2.0, "model-only estimate during the wire break");
    assert!(flagged(8.0, 13.0, fault::ENCODER_STUCK), "stuck encoder flagged");
    assert!(flagged(14.0, 14.2, fault::INNOVATION), "noise burst flagged");
    assert!(noise_err <= 1.5, "noise rejected by the innovation gate");
    assert_eq!(st.frames_dropped, damaged, "every damaged frame counted");
    assert_eq!(st.frames_overrun, 39 * bursts, "extra frames of a period dropped and counted");
    assert_eq!(st.bytes_lost, 0);
    assert_eq!(outputs as u32, rows.len() as u32 - damaged, "one output per undamaged step");
    assert!(est_err <= 1.0, "the estimate tracks the plant through the other faults");
    assert!(stuck_err <= 3.0, "the estimate follows the HP reading with the encoder stuck");
    finish(q);
}

#[test]
fn a_stalled_control_task_trips_the_watchdog() {
    let mut q = boot();
    q.link
        .request(&ToFirmware::Ping(1), |r| {
            matches!(r, pto_model::protocol::FromFirmware::Pong(1)).then_some(())
        })
        .unwrap();
    q.link.send(&ToFirmware::Stall).unwrap();
    let code = q.wait_exit(Duration::from_secs(20)).unwrap();
    let log = q.log();
    for l in log.iter().rev().take(3).rev() {
        println!("{l}");
    }
    assert_eq!(code, i32::from(pto_firmware::EXIT_WATCHDOG));
    assert!(log.iter().any(|l| l.text.contains("task 0 silent")));
    assert!(log.iter().any(|l| l.text.starts_with("watchdog expired")));
}
