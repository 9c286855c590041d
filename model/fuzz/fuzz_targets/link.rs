//! Long-run fuzzing of the link's framing: arbitrary bytes into both receivers (the firmware's
//! of host frames, the host's of firmware frames). Must never panic; a frame it takes must
//! re-encode under its own sequence number to bytes that decode to the same message (the
//! receiver never hands out a message its frame does not carry).
#![no_main]

use libfuzzer_sys::fuzz_target;
use pto_model::protocol::{FromFirmware, MAX_FRAME, Receiver, ToFirmware, decode, encode};

fuzz_target!(|data: &[u8]| {
    let mut to_fw = Receiver::<ToFirmware>::new();
    let mut from_fw = Receiver::<FromFirmware>::new();
    for b in data {
        if let Some(m) = to_fw.push(*b) {
            let seq = to_fw.last_seq().unwrap();
            let mut out = [0u8; MAX_FRAME];
            let n = encode(seq, &m, &mut out).unwrap();
            assert_eq!(decode::<ToFirmware>(&out[..n]).unwrap(), (seq, m));
        }
        if let Some(m) = from_fw.push(*b) {
            let seq = from_fw.last_seq().unwrap();
            let mut out = [0u8; MAX_FRAME];
            let n = encode(seq, &m, &mut out).unwrap();
            assert_eq!(decode::<FromFirmware>(&out[..n]).unwrap(), (seq, m));
        }
    }
    let c = to_fw.counts;
    assert!(c.ok + c.dropped() <= data.iter().filter(|b| **b == 0).count() as u32);
});
