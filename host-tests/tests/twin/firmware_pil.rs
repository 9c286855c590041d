//! Processor-in-the-loop: the full simulation is the plant, the QEMU firmware its controller, in
//! lockstep over USART1 (one sensor frame out and one output back per 2^-10 s step). Also the
//! fault injections and the watchdog test.

use pto_host::hil::build::{self, Build};
use pto_host::hil::pil::{self, Injection, PilRow};
use pto_host::hil::qemu::Qemu;
use pto_host::sim::bench::Bench;
use pto_host::validation::sensors::SensorSpec;
use pto_model::estimator::fault;
use pto_model::fx::Pressure;
use pto_model::protocol::ToFirmware;
use pto_model::scheduler::Mode;
use std::time::Duration;

fn boot() -> Qemu {
    Qemu::boot(&build::build(Build::Qemu).unwrap(), false).unwrap()
}

fn finish(mut q: Qemu) {
    q.link.send(&ToFirmware::Exit(0)).unwrap();
    let code = q.wait_exit(Duration::from_secs(10)).unwrap();
    let log = q.log();
    assert_eq!(
        code,
        0,
        "firmware exit code; log tail: {:?}",
        &log[log.len().saturating_sub(5)..]
    );
    assert!(
        !log.iter()
            .any(|l| l.text.starts_with("watchdog expired") || l.text.starts_with("panic")),
        "unexpected reset path in the log"
    );
}

fn window(rows: &[PilRow], from: f64) -> impl Iterator<Item = &PilRow> {
    rows.iter().filter(move |r| r.t >= from)
}

fn run(check: pil::CheckFn) {
    let (q, c) = check(boot(), &Bench::reference())
        .unwrap_or_else(|e| panic!("{}", pto_host::error_chain(&e)));
    println!(
        "PIL {}: {:.3} {} (target {} {}); {}; {} steps in {:.1} s wall",
        c.name, c.measured, c.unit, c.target, c.unit, c.detail, c.steps, c.wall_s
    );
    assert!(c.pass, "{}: target missed", c.name);
    finish(q);
}

#[test]
fn pil_holds_p2_at_100_bar() {
    let _qemu = crate::common::beside_other_qemus();
    run(pil::check_hold_p2);
}

#[test]
fn pil_holds_motor_speed() {
    let _qemu = crate::common::beside_other_qemus();
    run(pil::check_hold_speed);
}

#[test]
fn pil_trips_to_the_safe_state_within_one_period() {
    let _qemu = crate::common::beside_other_qemus();
    run(pil::check_trip);
}

#[test]
fn pil_trip_holds_through_a_wire_break_and_refuses_a_reset() {
    let _qemu = crate::common::beside_other_qemus();
    run(pil::check_trip_holds);
}

#[test]
fn pil_motor_reading_behind_a_closed_valve_is_flagged_without_a_false_trip() {
    let _qemu = crate::common::beside_other_qemus();
    run(pil::check_motor_behind_closed_valve);
}

/// The HP transducer stuck at its reading: named by the firmware's residuals within 5 s, the
/// valve at the sensor-fault aperture from then on.
#[test]
fn pil_names_a_stuck_hp_transducer_and_goes_safe() {
    let _qemu = crate::common::beside_other_qemus();
    run(pil::check_sensor_fault);
}

/// The host copy of the firmware's controller ([`pil::host_closed_loop`], on which the twins
/// measure their built-in configuration's baseline) closes the loop as the firmware does under
/// QEMU, bit for bit: every step's estimate, command, aperture and dump valve, and so the
/// plant, over the twins' model-only check (a charge with the valve closed from 64.5 bar, the
/// HP transducer's wire breaking at 3 s).
#[test]
fn the_host_copy_closes_the_loop_as_the_firmware_does() {
    let _qemu = crate::common::beside_other_qemus();
    let (p2_start, check_s, wire_break_s) = (64.5, 5.0, 3.0);
    let plant = Bench::reference();
    let (q, fw) = crate::common::check_run(boot(), &plant, p2_start, check_s, wire_break_s);
    finish(q);
    let builtin = pto_firmware::built_config::model().expect("built-in configuration");
    let host = crate::common::host_check_run(&builtin, &plant, p2_start, check_s, wire_break_s);
    let differ = |what: &str, f: &dyn Fn(&PilRow, &PilRow) -> bool| {
        let n = fw.iter().zip(&host).filter(|(a, b)| !f(a, b)).count();
        println!("{what}: {n} of {} steps differ", fw.len());
        n
    };
    let n = differ("estimate", &|a, b| a.estimate == b.estimate)
        + differ("command", &|a, b| a.command == b.command)
        + differ("aperture", &|a, b| {
            a.applied.to_bits() == b.applied.to_bits()
        })
        + differ("dump valve", &|a, b| a.dump == b.dump)
        + differ("plant P2", &|a, b| a.p2_bar.to_bits() == b.p2_bar.to_bits());
    assert_eq!(fw.len(), host.len());
    assert!(fw.len() >= 5 * 1024 && fw.iter().all(|r| r.estimate.is_some()));
    assert_eq!(n, 0, "the host copy and the firmware differ");
}

#[test]
fn pil_survives_injected_faults() {
    let _qemu = crate::common::beside_other_qemus();
    let q = boot();
    let inject = |t: f64| -> Injection {
        match t {
            t if (4.0..7.0).contains(&t) => Injection::HpWireBreak,
            // The estimator calls the encoder stuck when it has not moved for 2 s while the HP
            // reading changed by more than 1 bar.
            t if (8.0..13.0).contains(&t) => Injection::EncoderStuck,
            t if (14.0..14.2).contains(&t) => Injection::HpNoise(30.0),
            t if (15.0..16.0).contains(&t) && ((t * 1024.0) as i64) % 50 == 0 => Injection::Corrupt,
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
    let wb: Vec<&PilRow> = rows
        .iter()
        .filter(|r| r.injection == Injection::HpWireBreak)
        .collect();
    let wb_err = wb
        .iter()
        .filter_map(|r| {
            r.estimate
                .map(|e| (f64::from(e.p2.to_f32()) - r.p2_bar).abs())
        })
        .fold(0.0, f64::max);
    let noise_err = rows
        .iter()
        .filter(|r| matches!(r.injection, Injection::HpNoise(_)))
        .filter_map(|r| {
            r.estimate
                .map(|e| (f64::from(e.p2.to_f32()) - r.p2_bar).abs())
        })
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
            .filter_map(|r| {
                r.estimate
                    .map(|e| (f64::from(e.p2.to_f32()) - r.p2_bar).abs())
            })
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
         estimate within {noise_err:.2} bar; {damaged} damaged frames → {} dropped, {} lost; {bursts} \
         bursts of 40 frames → {} overruns, {} bytes lost; estimate within {est_err:.2} bar of the \
         plant outside the stuck-encoder window, {stuck_err:.2} bar inside it; {} steps run, {outputs} outputs for {} steps",
        st.link.dropped(),
        st.link.lost,
        st.frames_overrun,
        st.bytes_lost,
        st.steps,
        rows.len()
    );
    assert!(flagged(4.0, 7.0, fault::HP_SENSOR), "wire break flagged");
    assert!(st.hp_loop_faults >= 3 * 1000, "wire-break samples counted");
    assert!(wb_err <= 2.0, "model-only estimate during the wire break");
    assert!(
        flagged(8.0, 13.0, fault::ENCODER_STUCK),
        "stuck encoder flagged"
    );
    assert!(
        flagged(14.0, 14.2, fault::INNOVATION),
        "noise burst flagged"
    );
    assert!(noise_err <= 1.5, "noise rejected by the innovation gate");
    assert_eq!(st.link.dropped(), damaged, "every damaged frame counted");
    assert_eq!(
        st.link.lost, damaged,
        "every damaged frame's sequence number missed"
    );
    assert_eq!(st.link.out_of_order, 0);
    let host = q.link.counts();
    assert_eq!(
        (host.dropped(), host.lost),
        (0, 0),
        "the firmware's frames all arrived: {host:?}"
    );
    assert_eq!(
        st.frames_overrun,
        39 * bursts,
        "extra frames of a period dropped and counted"
    );
    assert_eq!(st.bytes_lost, 0);
    assert_eq!(
        outputs as u32,
        rows.len() as u32 - damaged,
        "one output per undamaged step"
    );
    assert!(
        est_err <= 1.0,
        "the estimate tracks the plant through the other faults"
    );
    assert!(
        stuck_err <= 3.0,
        "the estimate follows the HP reading with the encoder stuck"
    );
    finish(q);
}

#[test]
fn a_stalled_control_task_trips_the_watchdog() {
    let _qemu = crate::common::beside_other_qemus();
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
