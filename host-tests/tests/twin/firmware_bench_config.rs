//! The firmware built for a bench file (`PTO_BENCH`): the build checks the file with the host
//! tools' code and fails on a bench the model cannot take, naming the file and the field; the
//! firmware boots with that bench's configuration (its fingerprint in the boot log) and, step
//! for step, gives the host model's estimate with that configuration bit for bit.

use pto_host::hil::build::{self, Build};
use pto_host::hil::pil;
use pto_host::hil::qemu::Qemu;
use pto_host::sim::bench::{Bench, REFERENCE_BENCH_TOML};
use pto_host::validation::{golden, model_config};
use pto_model::fx::Pressure;
use pto_model::protocol::{CONFIG_MAX_BYTES, config_fingerprint, encode_config};
use pto_model::scheduler::Mode;
use std::time::Duration;

/// The reference bench with `key = old` replaced by `key = new` (comments kept).
fn bench_with(key_old: &str, key_new: &str) -> String {
    assert!(REFERENCE_BENCH_TOML.contains(key_old), "{key_old}");
    REFERENCE_BENCH_TOML.replacen(key_old, key_new, 1)
}

#[test]
fn firmware_built_for_a_bench_file_runs_that_bench_s_configuration() {
    let _qemu = crate::common::beside_other_qemus();
    let dir = build::workspace_root("the test")
        .unwrap()
        .join("target")
        .join("fw-bench-file");
    std::fs::create_dir_all(&dir).unwrap();
    // A bench whose trapped air differs from the reference's.
    let path = dir.join("more-air.toml");
    // … and whose controller falls back to 15 % (not 12 %) when the HP transducer is lost.
    std::fs::write(
        &path,
        bench_with("trapped_air_fraction = 0.06", "trapped_air_fraction = 0.09").replace(
            "sensor_fault_aperture_pct = 12.0",
            "sensor_fault_aperture_pct = 15.0",
        ),
    )
    .unwrap();
    let bench = Bench::load(&path).unwrap();
    assert_eq!(
        pto_host::validation::controller_config(&bench)
            .0
            .sensor_fault_aperture_pct,
        15.0
    );
    let cfg = model_config(&bench).unwrap();
    assert_eq!(cfg.trapped_air_fraction, 0.09);
    let mut buf = [0u8; CONFIG_MAX_BYTES];
    let fingerprint = config_fingerprint(encode_config(&cfg, &mut buf).unwrap());

    let elf = build::build_for_bench(Build::Qemu, &path, &dir).unwrap();
    let mut q = Qemu::boot(&elf, false).unwrap();
    let k = cfg.coefficients().unwrap();
    let mode = Mode::HoldPressure(Pressure::from_num(golden::SETPOINT_BAR));
    let (inputs, p2, lp) =
        golden::clean_inputs(&Bench::reference(), "test1-cfg1-c14", None, 6_000).unwrap();
    let host = golden::run(&k, &inputs, p2, lp).unwrap();
    let reference = golden::run(&golden::coefficients().unwrap(), &inputs, p2, lp).unwrap();
    let fw = pil::replay(&mut q, &inputs, p2, lp, mode).unwrap();
    let first_diff = host.iter().zip(&fw).position(|(a, b)| a != b);
    let apart = host
        .iter()
        .zip(&reference)
        .map(|((a, _), (b, _))| (a.p2.to_f32() - b.p2.to_f32()).abs())
        .fold(0.0f32, f32::max);
    q.link
        .send(&pto_model::protocol::ToFirmware::Exit(0))
        .unwrap();
    q.wait_exit(Duration::from_secs(10)).unwrap();
    let log = q.log();
    let line = log
        .iter()
        .find(|l| l.text.starts_with("model configuration: built for"))
        .expect("the boot log names the configuration");
    println!("{line}");
    println!(
        "{} steps: first difference from the host model with the bench's configuration at \
         {first_diff:?}; P2 up to {apart:.3} bar from the reference configuration's",
        fw.len()
    );
    assert!(line.text.contains("more-air.toml"), "{line}");
    let sched = log
        .iter()
        .find(|l| l.text.starts_with("scheduler:"))
        .expect("the boot log gives the scheduler's settings");
    assert!(
        sched.text.contains("15.0 % (sensor fault)"),
        "the bench file's controller settings are built in: {sched}"
    );
    assert!(
        line.text
            .contains(&format!("fingerprint {fingerprint:08x}")),
        "{line} vs {fingerprint:08x}"
    );
    assert_eq!(fw.len(), inputs.len());
    assert_eq!(first_diff, None, "firmware and host differ");
    assert!(
        apart > 0.01,
        "the trapped air moves the estimate ({apart} bar)"
    );

    // A bench the firmware cannot be built for: the build stops and names file and field.
    let bad = dir.join("bad.toml");
    std::fs::write(
        &bad,
        bench_with("trapped_air_fraction = 0.06", "trapped_air_fraction = 0.9"),
    )
    .unwrap();
    let err = build::build_for_bench(Build::Qemu, &bad, &dir)
        .expect_err("an out-of-range bench does not build");
    let text = format!("{err:#}");
    println!("{text}");
    assert!(text.contains("bad.toml"), "{text}");
    assert!(text.contains("oil.trapped_air_fraction"), "{text}");
    // The same for the controller's settings.
    std::fs::write(&bad, bench_with("shunt_ohm = 150.0", "shunt_ohm = 1500.0")).unwrap();
    let err = build::build_for_bench(Build::Qemu, &bad, &dir)
        .expect_err("an out-of-range controller section does not build");
    let text = format!("{err:#}");
    println!("{text}");
    assert!(
        text.contains("bad.toml") && text.contains("controller.hp_transducer.shunt_ohm"),
        "{text}"
    );
}
