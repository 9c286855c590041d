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
//! `pto validate` (see the README).

use pto_host::bench::Bench;
use pto_host::validate::{self, target};

/// `pto validate`'s rows for the named built-in scenarios (every one must exist and run).
fn validate_named(names: &[&str]) -> Vec<validate::Row> {
    let sel: Vec<_> = pto_host::scenario::builtin()
        .into_iter()
        .filter(|s| names.contains(&s.name.as_str()))
        .collect();
    assert_eq!(sel.len(), names.len());
    let rep = validate::run(&Bench::reference(), &sel, false);
    assert!(rep.errors.is_empty(), "{:?}", rep.errors);
    rep.rows
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
        assert!(r.p2_rms_bar <= target::P2_RMS_BAR, "{}", r.scenario);
        assert!(
            r.p2_model_only_max_bar <= target::P2_MODEL_ONLY_MAX_BAR,
            "{}",
            r.scenario
        );
        assert!(
            r.motor_rms_rel.is_none_or(|m| m <= target::MOTOR_RMS_REL),
            "{}",
            r.scenario
        );
        assert!(
            r.fixed_vs_f64_bar <= target::FIXED_VS_F64_BAR,
            "{}",
            r.scenario
        );
        assert!(
            r.fixed_vs_f64_nm <= target::FIXED_VS_F64_NM,
            "{}",
            r.scenario
        );
        assert!(
            r.torque_rms_of_peak
                .is_none_or(|t| t <= target::TORQUE_RMS_OF_PEAK),
            "{}",
            r.scenario
        );
        assert!(r.pass, "{}", r.scenario);
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
    assert!(r.p2_rms_bar <= target::P2_RMS_BAR);
    assert!(r.p2_model_only_max_bar <= target::P2_MODEL_ONLY_MAX_BAR);
    assert!(torque <= target::TORQUE_RMS_OF_PEAK);
    assert!(motor <= target::MOTOR_RMS_REL);
    assert!(r.fixed_vs_f64_bar <= target::FIXED_VS_F64_BAR);
    assert!(r.pass);
}

#[test]
fn scheduler_holds_p2_and_motor_speed_in_closed_loop_with_the_full_simulation() {
    for row in validate::closed_loop_rows(&Bench::reference()) {
        let row = row.unwrap();
        println!(
            "{}: max deviation {:.4} (target {})",
            row.name, row.max_deviation, row.target
        );
        assert!(row.pass, "{}", row.name);
    }
}
