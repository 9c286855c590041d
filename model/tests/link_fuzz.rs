//! The link's framing under damage: random, bit-flipped, truncated, inserted-byte, deleted-byte
//! and concatenated streams of protocol frames fed to a [`Receiver`], 200 000 cases a run, and
//! 200 000 streams of random bytes (`PTO_FUZZ_CASES` raises both). Asserted: no panic; no
//! damaged frame is ever taken as a message (every message taken is, bit for bit, the one its
//! sender numbered so); every frame after the first one taken is taken or counted lost; frames
//! before it that never arrived left a dropped frame, unless not one of their bytes did. Long
//! runs: `cargo fuzz` (see `model/fuzz/README.md`).

use proptest::prelude::*;
use pto_model::estimator::Inputs;
use pto_model::fx::{Aperture, Pressure, Rpm};
use pto_model::protocol::selftest::{SelfTest, TestDrive};
use pto_model::protocol::{MAX_FRAME, Receiver, SensorFrame, ToFirmware, encode};
use pto_model::scheduler::Mode;

fn cases(default: u32) -> u32 {
    std::env::var("PTO_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn message() -> impl Strategy<Value = ToFirmware> {
    prop_oneof![
        any::<u32>().prop_map(ToFirmware::Ping),
        Just(ToFirmware::GetStatus),
        (
            any::<u32>(),
            any::<i32>(),
            any::<u16>(),
            any::<u16>(),
            any::<i32>(),
            any::<u16>()
        )
            .prop_map(|(tick, encoder, hp_adc, lp_adc, m, v)| ToFirmware::Sensors(
                SensorFrame {
                    tick,
                    encoder,
                    hp_adc,
                    lp_adc,
                    motor: (m % 3 != 0).then(|| Rpm::from_bits(m)),
                    supply_mv: (v % 5 != 0).then_some(v),
                }
            )),
        (any::<u32>(), any::<i32>(), any::<i32>(), any::<u8>()).prop_map(|(tick, e, p, d)| {
            ToFirmware::Replay {
                tick,
                inputs: Inputs {
                    encoder: Some(e),
                    hp: Some(Pressure::from_bits(p)),
                    lp: None,
                    motor: Some(Rpm::from_bits(p ^ e)),
                    aperture_cmd: Aperture::from_bits(e.wrapping_mul(3)),
                    on_duty: d,
                    config: d % 5,
                },
            }
        }),
        any::<i32>().prop_map(|p| ToFirmware::SetMode(Mode::HoldPressure(Pressure::from_bits(p)))),
        (any::<u8>(), any::<u8>())
            .prop_map(|(on_duty, config)| ToFirmware::SetDuty { on_duty, config }),
        (any::<i32>(), any::<u8>()).prop_map(|(a, k)| ToFirmware::SelfTest(match k % 7 {
            0 => SelfTest::Inputs,
            1 => SelfTest::Begin,
            2 => SelfTest::End,
            3 => SelfTest::Drive(TestDrive::AllOff),
            4 => SelfTest::Drive(TestDrive::DumpClosed),
            5 => SelfTest::Drive(TestDrive::Solenoid(k)),
            _ => SelfTest::Drive(TestDrive::Valve(Aperture::from_bits(a))),
        })),
    ]
}

/// Damage done to a clean stream.
#[derive(Debug, Clone)]
enum Damage {
    /// Flip one bit of the byte at (index mod length).
    Flip(usize, u8),
    /// Keep only the first (index mod length) bytes.
    Truncate(usize),
    /// Insert a byte before (index mod length).
    Insert(usize, u8),
    /// Delete the byte at (index mod length) — a lost delimiter when it is a 0.
    Delete(usize),
    /// Append a copy of the stream's first (index mod length) bytes (a resent, cut frame).
    Concat(usize),
}

fn damage() -> impl Strategy<Value = Damage> {
    prop_oneof![
        (any::<usize>(), 0u8..8).prop_map(|(i, b)| Damage::Flip(i, b)),
        any::<usize>().prop_map(Damage::Truncate),
        (any::<usize>(), any::<u8>()).prop_map(|(i, b)| Damage::Insert(i, b)),
        any::<usize>().prop_map(Damage::Delete),
        any::<usize>().prop_map(Damage::Concat),
    ]
}

fn apply(bytes: &mut Vec<u8>, d: &Damage) {
    if bytes.is_empty() {
        return;
    }
    let n = bytes.len();
    match *d {
        Damage::Flip(i, b) => bytes[i % n] ^= 1 << b,
        Damage::Truncate(i) => bytes.truncate(i % n),
        Damage::Insert(i, b) => bytes.insert(i % n, b),
        Damage::Delete(i) => {
            bytes.remove(i % n);
        }
        Damage::Concat(i) => {
            let head = bytes[..i % n].to_vec();
            bytes.extend_from_slice(&head);
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: cases(200_000),
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    /// Damaged streams of numbered frames, then one clean frame: nothing damaged is taken, and
    /// every frame after the first one taken is either taken or counted lost.
    #[test]
    fn damaged_streams_never_yield_a_wrong_message_and_count_every_loss(
        msgs in prop::collection::vec(message(), 1..8),
        first in any::<u16>(),
        leading_zero in any::<bool>(),
        damages in prop::collection::vec(damage(), 0..4),
    ) {
        let frame = |i: usize, m: &ToFirmware| {
            let mut b = [0u8; MAX_FRAME];
            let n = encode(first.wrapping_add(i as u16), m, &mut b).unwrap();
            b[..n].to_vec()
        };
        let mut bytes = Vec::new();
        for (i, m) in msgs.iter().enumerate() {
            if leading_zero {
                bytes.push(0);
            }
            bytes.extend(frame(i, m));
        }
        for d in &damages {
            apply(&mut bytes, d);
        }
        // A clean frame after the damage (a sender carries on): it reveals every gap before it.
        let sentinel = ToFirmware::Ping(0xdead_beef);
        bytes.push(0);
        bytes.extend(frame(msgs.len(), &sentinel));
        let mut rx = Receiver::<ToFirmware>::new();
        let mut taken = Vec::new();
        for b in &bytes {
            if let Some(m) = rx.push(*b) {
                let seq = rx.last_seq().unwrap();
                taken.push((seq.wrapping_sub(first) as usize, m));
            }
        }
        let c = rx.counts;
        // Nothing damaged taken: each message is the one its sender numbered so, bit for bit.
        for (i, m) in &taken {
            let want = msgs.get(*i).unwrap_or(&sentinel);
            prop_assert_eq!(m, want, "frame {} taken wrong", i);
        }
        let last = taken.last().map(|t| t.0);
        prop_assert_eq!(last, Some(msgs.len()), "the clean frame after the damage was lost");
        // Every frame after the first taken: taken or counted lost, exactly; a frame that comes
        // after a newer one (a resent copy, or one a damaged copy delayed) is counted out of
        // order, never as a loss.
        let first_taken = taken[0].0;
        let unique: std::collections::BTreeSet<usize> = taken.iter().map(|t| t.0).collect();
        let mut newest = None::<usize>;
        let mut late = 0;
        for (i, _) in &taken {
            if newest.is_some_and(|n| *i <= n) {
                late += 1;
            } else {
                newest = Some(*i);
            }
        }
        prop_assert_eq!(c.ok as usize, taken.len());
        prop_assert_eq!(c.out_of_order as usize, late, "{:?} {:?}", c, taken);
        // Counted lost: every frame of the span never taken, and besides those at most the ones
        // that arrived late after their gap had been counted.
        let never = msgs.len() + 1 - first_taken - unique.range(first_taken..).count();
        prop_assert!(
            never <= c.lost as usize && c.lost as usize <= never + late,
            "losses not counted: {} never taken, {} late, {:?}", never, late, c
        );
        // Frames before the first taken and never taken left a trace (a dropped frame), unless
        // not one byte of them reached the receiver.
        let damaged_prefix = &bytes[..bytes.len() - frame(msgs.len(), &sentinel).len() - 1];
        if (0..first_taken).any(|i| !unique.contains(&i)) && damaged_prefix.iter().any(|b| *b != 0) {
            prop_assert!(c.dropped() > 0, "frames before {} vanished without a trace", first_taken);
        }
    }

    /// Random bytes: no panic, and counts that add up.
    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
        let mut rx = Receiver::<ToFirmware>::new();
        let mut frames = 0u32;
        let mut last_zero = true;
        for b in &bytes {
            let _ = rx.push(*b);
            if *b == 0 {
                frames += u32::from(!last_zero);
            }
            last_zero = *b == 0;
        }
        prop_assert_eq!(rx.counts.ok + rx.counts.dropped(), frames);
    }
}
