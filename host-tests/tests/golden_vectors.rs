//! Golden vectors: the committed inputs → outputs file reproduces bit for bit. `PTO_BLESS=1`
//! regenerates it from the full simulation (then review the diff).

use pto_host::bench::Bench;
use pto_host::golden;
use pto_model::fx::Pressure;

#[test]
fn golden_vectors_reproduce_bit_for_bit() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(golden::FILE);
    let k = golden::coefficients().unwrap();
    if std::env::var_os("PTO_BLESS").is_some() {
        let (inputs, p2, lp) = golden::make_inputs(&Bench::reference()).unwrap();
        let out = golden::run(&k, &inputs, p2, lp).unwrap();
        std::fs::write(&path, golden::to_csv(&inputs, &out, p2, lp)).unwrap();
    }
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("{}: {e} (PTO_BLESS=1 makes it)", path.display()));
    let (p2, lp, inputs) = golden::parse(&text).unwrap();
    let (p2, lp) = (
        Pressure::from_bits(p2).to_f32(),
        Pressure::from_bits(lp).to_f32(),
    );
    let out = golden::run(&k, &inputs, p2, lp).unwrap();
    let again = golden::to_csv(&inputs, &out, p2, lp);
    let mismatches: Vec<usize> = text
        .lines()
        .zip(again.lines())
        .enumerate()
        .filter(|(_, (a, b))| a != b)
        .map(|(i, _)| i + 1)
        .collect();
    println!(
        "{} steps, {} mismatching lines",
        inputs.len(),
        mismatches.len()
    );
    assert_eq!(text.lines().count(), again.lines().count());
    assert!(
        mismatches.is_empty(),
        "first mismatching lines: {:?}",
        &mismatches[..mismatches.len().min(5)]
    );
    // The vectors exercise the fault paths they claim to.
    let faults = out.iter().fold(0u16, |m, (e, _)| m | e.faults);
    use pto_model::estimator::fault;
    for f in [fault::HP_SENSOR, fault::INNOVATION, fault::ENCODER] {
        assert!(faults & f != 0, "fault bit {f:#x} never raised");
    }
}

#[test]
fn reference_bench_model_config_matches_the_firmware_default() {
    let from_bench = pto_host::estimation::model_config(&Bench::reference()).unwrap();
    let fw = pto_model::ModelConfig::reference();
    // Equal to f32 rounding of the derived numbers.
    let close = |a: f32, b: f32, what: &str| {
        assert!(
            (a - b).abs() <= 1e-3 * b.abs().max(1.0),
            "{what}: bench {a} vs firmware {b}"
        )
    };
    close(
        from_bench.chamber_dead_volume_cm3,
        fw.chamber_dead_volume_cm3,
        "chamber_dead_volume_cm3",
    );
    close(
        from_bench.hp.line_volume_l,
        fw.hp.line_volume_l,
        "hp.line_volume_l",
    );
    close(
        from_bench.lp.line_volume_l,
        fw.lp.line_volume_l,
        "lp.line_volume_l",
    );
    close(
        from_bench.relief_gain_lpm_per_bar,
        fw.relief_gain_lpm_per_bar,
        "relief_gain_lpm_per_bar",
    );
    close(
        from_bench.motor_leak_lpm_per_bar,
        fw.motor_leak_lpm_per_bar,
        "motor_leak_lpm_per_bar",
    );
    close(
        from_bench.motor_mech_efficiency,
        fw.motor_mech_efficiency,
        "motor_mech_efficiency",
    );
    close(
        from_bench.load_nm_per_rpm,
        fw.load_nm_per_rpm,
        "load_nm_per_rpm",
    );
    close(
        from_bench.motor_inertia_kg_m2,
        fw.motor_inertia_kg_m2,
        "motor_inertia_kg_m2",
    );
    assert_eq!(from_bench.cylinders, fw.cylinders);
    assert_eq!(from_bench.geometries, fw.geometries);
    assert_eq!(from_bench.valve_area_mm2, fw.valve_area_mm2);
}
