//! The model on a Cortex-M0 (`pto-m0` under QEMU `microbit`, `pto_host::hil::m0`): the golden
//! vectors and the four-cylinder cost runs replay bit for bit with the coefficients built on the
//! target, in place, in ≤ 8 KiB of stack; a flipped input bit, a damaged configuration and a cut
//! file each fail it; the cycle count's block decoding equals a per-instruction trace.

use crate::common;
use pto_host::hil::build::{self, Build};
use pto_host::hil::m0::{self, Run, Trace};
use pto_model::ModelConfig;
use pto_model::protocol::vectors::{EXIT_BAD_CONFIG, EXIT_BAD_FILE, EXIT_MISMATCH};

fn golden(steps: usize) -> Run {
    let workspace = build::workspace_root("the M0 test").unwrap();
    let mut r = m0::golden_run(&workspace).unwrap();
    r.inputs.truncate(steps);
    r
}

#[test]
fn golden_vectors_and_four_cylinder_runs_replay_bit_for_bit_on_a_cortex_m0() {
    let mut runs = vec![golden(usize::MAX)];
    runs.extend(m0::four_cylinder_runs().unwrap());
    let dir = common::fresh_dir("m0", "replay");
    let elf = build::build(Build::M0).unwrap();
    let v = m0::vectors(&ModelConfig::reference(), &runs).unwrap();
    let r = m0::replay_in(&elf, &v, &dir).unwrap();
    println!("{}", r.output);
    assert_eq!(r.exit, 0, "{:?}", r.failure);
    assert_eq!(r.runs.len(), runs.len());
    for (got, want) in r.runs.iter().zip(&runs) {
        assert_eq!(
            (got.label.as_str(), got.steps as usize),
            (want.label.as_str(), want.inputs.len())
        );
    }
    let build_stack = r.build_stack_bytes.unwrap();
    println!(
        "coefficients {} B built on the M0 in {} instructions with {build_stack} B of stack \
         (target ≤ 8 KiB)",
        r.coefficient_bytes.unwrap(),
        r.build_instructions.unwrap()
    );
    assert!(build_stack <= 8 * 1024, "{build_stack} B");
    // The cycle trace counts the same steps: its instructions are the timer's less a fixed
    // number, the replay loop's code the compiler placed between the timer's two reads (the
    // call's set-up, ≈ 80), the same for the mean and the worst step.
    let c = m0::cycles(&elf, &v, &runs, &dir, Trace::Blocks).unwrap();
    for (t, k) in r.runs.iter().zip(&c) {
        let gap = t.mean - k.instructions_mean;
        println!(
            "{}: instructions mean {:.0} max {} (timer), {:.0} / {} (trace); cycles mean {:.0} \
             max {} ({:.1} % of a 1 kHz loop at 48 MHz)",
            t.label,
            t.mean,
            t.max,
            k.instructions_mean,
            k.instructions_max,
            k.cycles_mean,
            k.cycles_max,
            f64::from(k.cycles_max) / 48_000.0 * 100.0
        );
        let gap_max = f64::from(t.max) - f64::from(k.instructions_max);
        assert!((0.0..128.0).contains(&gap), "{}: {gap}", t.label);
        assert!(
            (gap - gap_max).abs() <= 1.0,
            "{}: {gap} vs {gap_max}",
            t.label
        );
        assert!(k.cycles_mean >= k.instructions_mean && k.cycles_max >= k.instructions_max);
    }
}

#[test]
fn a_flipped_input_bit_a_damaged_configuration_or_a_cut_file_fail_the_m0_replay() {
    let runs = [golden(300)];
    let cfg = ModelConfig::reference();
    let elf = build::build(Build::M0).unwrap();
    let dir = common::fresh_dir("m0", "faults");
    // The HP reading's bit 16 (1 bar) at step 120.
    let step = 120;
    assert!(runs[0].inputs[step].hp.is_some());
    let flipped = m0::vectors_tampered(&cfg, &runs, |_, i, inp| {
        if i == step {
            inp.hp = inp
                .hp
                .map(|p| pto_model::fx::Pressure::from_bits(p.to_bits() ^ (1 << 16)));
        }
    })
    .unwrap();
    let r = m0::replay_in(&elf, &flipped, &dir).unwrap();
    println!("flipped: {:?}", r.failure);
    assert_eq!(r.exit, EXIT_MISMATCH);
    assert!(
        r.failure
            .as_deref()
            .unwrap_or("")
            .contains(&format!("step {step},"))
    );
    // The untouched file passes (the same steps, the same binary).
    let clean = m0::vectors(&cfg, &runs).unwrap();
    assert_eq!(m0::replay_in(&elf, &clean, &dir).unwrap().exit, 0);
    // A configuration byte changed under its CRC.
    let mut buf = [0u8; pto_model::protocol::CONFIG_MAX_BYTES];
    let config = pto_model::protocol::encode_config(&cfg, &mut buf).unwrap();
    let at = clean
        .windows(config.len())
        .position(|w| w == &config[..])
        .expect("the configuration's bytes in the file");
    let mut bad = clean.clone();
    bad[at + config.len() / 2] ^= 1;
    let r = m0::replay_in(&elf, &bad, &dir).unwrap();
    println!("damaged configuration: {:?}", r.failure);
    assert_eq!(r.exit, EXIT_BAD_CONFIG);
    // The file cut in the middle of a record.
    let r = m0::replay_in(&elf, &clean[..clean.len() - 7], &dir).unwrap();
    println!("cut file: {:?}", r.failure);
    assert_eq!(r.exit, EXIT_BAD_FILE);
    // Not a vectors file.
    let r = m0::replay_in(&elf, b"PTO0 not vectors", &dir).unwrap();
    assert_eq!(r.exit, EXIT_BAD_FILE);
}

#[test]
fn the_cycle_count_by_blocks_equals_a_trace_of_every_instruction() {
    let runs = [golden(300)];
    let elf = build::build(Build::M0).unwrap();
    let v = m0::vectors(&ModelConfig::reference(), &runs).unwrap();
    let dir = common::fresh_dir("m0", "trace");
    let blocks = m0::cycles(&elf, &v, &runs, &dir, Trace::Blocks).unwrap();
    let each = m0::cycles(&elf, &v, &runs, &dir, Trace::Instructions).unwrap();
    println!("{blocks:?}\n{each:?}");
    let key = |c: &m0::RunCycles| {
        (
            c.instructions_mean,
            c.instructions_max,
            c.cycles_mean,
            c.cycles_max,
        )
    };
    assert_eq!(key(&blocks[0]), key(&each[0]));
    assert!(blocks[0].cycles_max > 4000);
}
