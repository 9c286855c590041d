//! Golden vectors: the committed inputs → outputs file reproduces bit for bit. `PTO_BLESS=1`
//! regenerates it from the full simulation, says how many lines changed against the committed
//! file, and then checks the new file as always (its inputs, read back, must reproduce its
//! outputs); review the diff before committing it. (The reference bench ↔ firmware
//! configuration check is `tests/model/model_config.rs`.)

use pto_host::sim::bench::Bench;
use pto_host::validation::golden;
use pto_model::fx::Pressure;

#[test]
fn golden_vectors_reproduce_bit_for_bit() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(golden::FILE);
    let k = golden::coefficients().unwrap();
    if std::env::var_os("PTO_BLESS").is_some() {
        let (inputs, p2, lp) = golden::make_inputs(&Bench::reference()).unwrap();
        let out = golden::run(&k, &inputs, p2, lp).unwrap();
        let new = golden::to_csv(&inputs, &out, p2, lp);
        let old = std::fs::read_to_string(&path).unwrap_or_default();
        let changed = new.lines().zip(old.lines()).filter(|(a, b)| a != b).count()
            + new.lines().count().abs_diff(old.lines().count());
        println!(
            "PTO_BLESS: {changed} of {} lines changed against {}; review the diff",
            new.lines().count(),
            path.display()
        );
        std::fs::write(&path, new).unwrap();
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
