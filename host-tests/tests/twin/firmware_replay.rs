//! Bit-exact replay: the golden vectors and ≥ 10 000-step full-simulation traces (Test III, an
//! irregular sea, and Test I with one cylinder without the HP transducer) streamed to the QEMU
//! firmware give, step for step, the same estimate and scheduler output as the model crate run
//! on the host.

use pto_host::hil::build::{self, Build};
use pto_host::hil::pil;
use pto_host::hil::qemu::Qemu;
use pto_host::sim::bench::Bench;
use pto_host::validation::golden;
use pto_model::fx::Pressure;
use pto_model::scheduler::Mode;
use std::time::{Duration, Instant};

#[test]
fn firmware_matches_the_host_model_bit_for_bit() {
    let _qemu = crate::common::beside_other_qemus();
    let elf = build::build(Build::Qemu).unwrap();
    let mut q = Qemu::boot(&elf, false).unwrap();
    let k = golden::coefficients().unwrap();
    let mode = Mode::HoldPressure(Pressure::from_num(golden::SETPOINT_BAR));

    // 1. The committed golden vectors.
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(golden::FILE);
    let text = std::fs::read_to_string(&path).unwrap();
    let (p2, lp, inputs) = golden::parse(&text).unwrap();
    let (p2, lp) = (
        Pressure::from_bits(p2).to_f32(),
        Pressure::from_bits(lp).to_f32(),
    );
    let t0 = Instant::now();
    let fw = pil::replay(&mut q, &inputs, p2, lp, mode).unwrap();
    let dt = t0.elapsed().as_secs_f64();
    let csv = golden::to_csv(&inputs, &fw, p2, lp);
    let bad = text
        .lines()
        .zip(csv.lines())
        .filter(|(a, b)| a != b)
        .count();
    println!(
        "golden vectors: {} steps, {bad} mismatching lines, {:.1} µs per round trip",
        inputs.len(),
        dt / inputs.len() as f64 * 1e6
    );
    assert_eq!(bad, 0);
    assert_eq!(text.lines().count(), csv.lines().count());

    // 2. Long traces from the full simulation.
    let bench = Bench::reference();
    // The small sea from 14 s: slow reversals with the tracker's speed flickering about zero,
    // strokes shorter than the free play (`CylState::gap`, `alt_gap`).
    for (name, start) in [
        ("test3-ap10", None),
        ("irregular-sea", Some(200.0)),
        ("sea-hs20-tp14-s11", Some(14.0)),
    ] {
        let (inputs, p2, lp) = golden::clean_inputs(&bench, name, start, 12_000).unwrap();
        let host = golden::run(&k, &inputs, p2, lp).unwrap();
        let t0 = Instant::now();
        let fw = pil::replay(&mut q, &inputs, p2, lp, mode).unwrap();
        let first_diff = host.iter().zip(&fw).position(|(a, b)| a != b);
        let torque_span = host
            .iter()
            .map(|(e, _)| e.torque.to_f32().abs())
            .fold(0.0f32, f32::max);
        println!(
            "{name}: {} steps replayed in {:.1} s, first difference at {:?} (|torque| up to {:.0} N·m)",
            fw.len(),
            t0.elapsed().as_secs_f64(),
            first_diff,
            torque_span
        );
        assert_eq!(fw.len(), inputs.len());
        assert!(inputs.len() >= 10_000);
        assert_eq!(first_diff, None, "{name}: firmware and host differ");
        assert!(torque_span > 100.0, "{name}: the trace exercises the pump");
        if name.starts_with("sea-") {
            let short = short_strokes(&k, &inputs, p2, lp);
            println!("{name}: {short} reversals before the eye had crossed its play");
            assert!(short > 0, "{name}: the trace exercises the short strokes");
        }
    }
    // 3. Test I with one cylinder without the HP transducer: the HP accumulator runs empty each
    // wave and the motor speed corrects P2 (the same inputs with that correction switched off
    // must give another P2, or the trace would not exercise it).
    let (inputs, p2, lp) =
        golden::scenario_inputs(&bench, "test1-cfg1-c1", None, 12_000, golden::no_hp).unwrap();
    let host = golden::run(&k, &inputs, p2, lp).unwrap();
    let mut k_off = k.clone();
    k_off.reading.gain = pto_model::fx::Fx::ZERO;
    let off = golden::run(&k_off, &inputs, p2, lp).unwrap();
    let p2_span = host
        .iter()
        .zip(&off)
        .map(|((a, _), (b, _))| (a.p2.to_f32() - b.p2.to_f32()).abs())
        .fold(0.0f32, f32::max);
    let t0 = Instant::now();
    let fw = pil::replay(&mut q, &inputs, p2, lp, mode).unwrap();
    let first_diff = host.iter().zip(&fw).position(|(a, b)| a != b);
    println!(
        "test1-cfg1-c1 without HP: {} steps replayed in {:.1} s, first difference at {:?} (the \
         motor reading moves P2 by up to {:.2} bar)",
        fw.len(),
        t0.elapsed().as_secs_f64(),
        first_diff,
        p2_span
    );
    assert_eq!(fw.len(), inputs.len());
    assert_eq!(
        first_diff, None,
        "test1-cfg1-c1 without HP: firmware and host differ"
    );
    assert!(p2_span > 1.0, "the trace exercises the motor reading");
    let st = pil::status(&mut q).unwrap();
    println!(
        "status: {} frames ok, {} dropped, {} lost, {} steps, step cost {} (max {}) instructions",
        st.link.ok,
        st.link.dropped(),
        st.link.lost,
        st.steps,
        st.step_cost_last,
        st.step_cost_max
    );
    assert_eq!((st.link.dropped(), st.link.lost), (0, 0));
    q.link
        .send(&pto_model::protocol::ToFirmware::Exit(0))
        .unwrap();
    assert_eq!(q.wait_exit(Duration::from_secs(10)).unwrap(), 0);
}

/// Reversals of the host model over `inputs` after which the new stroke crosses the eye's
/// distance back rather than following the chambers' force (`CylState::engaged` false after the
/// turn: the ending stroke's eye had not crossed its play, or it was no stroke at all).
fn short_strokes(
    k: &pto_model::Coefficients,
    inputs: &[pto_model::estimator::Inputs],
    p2: f32,
    lp: f32,
) -> usize {
    let mut st = pto_model::estimator::State::new(
        Pressure::from_num(p2),
        Pressure::from_num(lp),
        Pressure::from_num(1.0),
    );
    let mut n = 0;
    for inp in inputs {
        let before = st.cyl;
        pto_model::estimator::step(k, &mut st, inp);
        n += st
            .cyl
            .iter()
            .zip(&before)
            .filter(|(c, b)| c.dir != b.dir && b.dir != 0 && !c.engaged)
            .count();
    }
    n
}
