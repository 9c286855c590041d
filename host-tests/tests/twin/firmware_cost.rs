//! Firmware cost report: instructions per estimator + scheduler step and of the controller's
//! set-up at boot under QEMU, flash and static RAM of both builds. Asserted: the memory
//! targets, the 5 M-instruction set-up and the 2 400-instruction step target
//! for every run — the golden vectors (two cylinders on duty, fixed aperture and holding P2) and
//! six seconds of four cylinders holding P2 through a stroke reversal (the costliest case).
//! QEMU's instruction count is deterministic, so the maxima are exact, not samples.

use pto_host::hil::fw_cost::{self, target};

#[test]
fn firmware_cost_report() {
    let _qemu = crate::common::beside_other_qemus();
    let r = fw_cost::measure().unwrap();
    for s in &r.step {
        println!(
            "{:<20} {} steps: mean {:.0}, max {} instructions (target {})",
            s.mode,
            s.steps,
            s.mean,
            s.max,
            target::STEP_INSTRUCTIONS
        );
        assert!(s.steps >= 2048 && s.mean > 0.0, "TIM2 counts instructions");
    }
    for s in &r.step {
        assert!(
            s.max <= target::STEP_INSTRUCTIONS,
            "{}: max {} instructions per step",
            s.mode,
            s.max
        );
    }
    for (what, n) in [
        ("controller set-up at boot", r.setup_instructions),
        ("configuration commit", r.commit_instructions),
    ] {
        println!(
            "{what}: {n} instructions (target {})",
            target::SETUP_INSTRUCTIONS
        );
        assert!(
            n > 100_000 && n <= target::SETUP_INSTRUCTIONS,
            "{what}: {n} instructions"
        );
    }
    for s in &r.size {
        println!("{:<6} flash {} B, static RAM {} B", s.build, s.flash, s.ram);
    }
    let bench = &r.size[0];
    assert_eq!(bench.build, "bench");
    assert!(
        bench.flash <= target::FLASH,
        "bench flash {} B",
        bench.flash
    );
    assert!(bench.ram <= target::RAM, "bench static RAM {} B", bench.ram);
}
