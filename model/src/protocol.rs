//! Messages between host tools and the firmware, defined once, and their framing (protocol v5:
//! v4's, with the board's supply reading in each sensor sample, the solenoids in each step's
//! output, and the bring-up self-test, [`selftest`]).
//!
//! A frame on the wire is `COBS(seq ‖ payload ‖ crc) 0`:
//! - `seq`: a `u16` (little-endian) counting the sender's frames, so the receiver counts the
//!   frames lost between two it got ([`LinkCounts::lost`]); a `Hello` restarts the count (a new
//!   session);
//! - `payload`: the message, postcard, which must fill the frame exactly (trailing bytes are a
//!   [`FrameError::Trailing`] drop, never ignored);
//! - `crc`: CRC-32C (Castagnoli; start and final XOR `0xFFFF_FFFF`, so leading and trailing
//!   zeros, inserted and deleted bytes all change it) over `seq ‖ payload`, little-endian;
//! - COBS, then a `0` delimiter; a receiver resynchronises at every `0`.
//!
//! Every frame a [`Receiver`] cannot take is counted by cause ([`LinkCounts`]). At connect the
//! host sends [`ToFirmware::Hello`] and the firmware answers [`FromFirmware::Hello`] with
//! [`PROTOCOL_VERSION`] and [`SCHEMA_HASH`], a hash of both message types' postcard schemas
//! (`postcard-schema`): a firmware and a host built from different message definitions refuse
//! each other with a clear error instead of misreading frames. The firmware also sends its
//! `Hello` once at boot.
//!
//! ```
//! use pto_model::protocol::{MAX_FRAME, Receiver, ToFirmware, encode};
//!
//! // The host numbers its frames; frame 2 is lost on the way and one byte of frame 3 flips.
//! let mut wire = Vec::new();
//! for seq in 0..5u16 {
//!     let mut buf = [0u8; MAX_FRAME];
//!     let n = encode(seq, &ToFirmware::Ping(u32::from(seq)), &mut buf).unwrap();
//!     match seq {
//!         2 => {}
//!         3 => {
//!             buf[2] ^= 0x10;
//!             wire.extend_from_slice(&buf[..n]);
//!         }
//!         _ => wire.extend_from_slice(&buf[..n]),
//!     }
//! }
//! let mut rx = Receiver::<ToFirmware>::new();
//! let got: Vec<ToFirmware> = wire.iter().filter_map(|b| rx.push(*b)).collect();
//! assert_eq!(got, [ToFirmware::Ping(0), ToFirmware::Ping(1), ToFirmware::Ping(4)]);
//! // Every loss is counted: the damaged frame by its cause, and the sequence numbers missing
//! // before frame 4 (2 lost, 3 damaged).
//! let c = rx.counts;
//! assert_eq!((c.ok, c.cobs + c.crc + c.payload, c.lost), (3, 1, 2), "{c:?}");
//! ```
//!
//! A typed RPC layer (`postcard-rpc`: endpoints keyed by a hash of path and schema, sequence
//! numbers, a standard error type) was considered and left for later: its embassy server wraps
//! `embassy-executor` 0.9's spawner (this firmware runs 0.10, so it would need its own
//! `WireTx`/`WireRx`/`WireSpawn` implementations), its serial transport carries no CRC, and
//! the link is a lockstep of a few message kinds. The frame keeps postcard-rpc's ingredients —
//! a sequence number and a schema key — so that a switch stays cheap.
//!
//! The messages are in `messages.rs`, the framing and the `Receiver` in `frame.rs`, the
//! configuration's bytes in `config.rs`; this module re-exports them (the long fuzzing is in
//! `tests/link_fuzz.rs`).
mod board;
mod config;
mod frame;
mod messages;
pub mod selftest;
pub mod vectors;

pub use board::*;
pub use config::*;
pub use frame::{FrameError, MAX_FRAME, Receiver, Session, decode, encode};
pub use messages::*;
pub use selftest::{SelfTest, SelfTestRefusal, SelfTestReply};

#[cfg(test)]
mod tests {
    use super::frame::{CRC, CRC_LEN, SEQ_LEN};
    use super::*;
    use crate::estimator::Inputs;
    use crate::fx::{Aperture, Pressure, Rpm};

    fn replay() -> ToFirmware {
        ToFirmware::Replay {
            tick: 123_456,
            inputs: Inputs {
                encoder: Some(-1234),
                hp: Some(Pressure::from_num(101.5)),
                lp: None,
                motor: Some(Rpm::from_num(180.0)),
                aperture_cmd: Aperture::from_num(12.0),
                on_duty: 0b1001,
                config: 0,
            },
        }
    }

    fn frame(seq: u16, m: &ToFirmware) -> ([u8; MAX_FRAME], usize) {
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(seq, m, &mut buf).unwrap();
        (buf, n)
    }

    #[test]
    fn frames_round_trip_and_every_single_byte_flip_is_caught() {
        let msg = replay();
        let (buf, n) = frame(7, &msg);
        assert_eq!(buf[n - 1], 0);
        assert!(buf[..n - 1].iter().all(|b| *b != 0));
        assert_eq!(decode::<ToFirmware>(&buf[..n]).unwrap(), (7, msg));
        for i in 0..n - 1 {
            for bit in 0..8 {
                let mut bad = buf;
                bad[i] ^= 1 << bit;
                if bad[i] == 0 {
                    continue;
                }
                assert!(
                    decode::<ToFirmware>(&bad[..n]).is_err(),
                    "flip at {i}.{bit} accepted"
                );
            }
        }
        assert!(decode::<ToFirmware>(&buf[..n / 2]).is_err());
    }

    /// CRC-16/KERMIT (protocol v1) started from 0: a zero byte before the payload left it
    /// unchanged. CRC-32C starts from all ones and sees it.
    #[test]
    fn leading_and_trailing_zeros_change_the_crc() {
        let body = [0x11u8, 0x22, 0x33];
        let lead = [0u8, 0x11, 0x22, 0x33];
        let trail = [0x11u8, 0x22, 0x33, 0];
        assert_ne!(CRC.checksum(&body), CRC.checksum(&lead));
        assert_ne!(CRC.checksum(&body), CRC.checksum(&trail));
        let kermit = crc::Crc::<u16>::new(&crc::CRC_16_KERMIT);
        assert_eq!(
            kermit.checksum(&body),
            kermit.checksum(&lead),
            "v1's blind spot"
        );
    }

    /// A message followed by bytes it does not use is dropped (v1 ignored them).
    #[test]
    fn trailing_bytes_after_a_message_are_a_dropped_frame() {
        let mut raw = [0u8; 16];
        let n = postcard::to_slice(&ToFirmware::Ping(6), &mut raw[SEQ_LEN..])
            .unwrap()
            .len();
        raw[SEQ_LEN + n] = 0x2a; // one byte too many, inside the CRC
        let body = SEQ_LEN + n + 1;
        let crc = CRC.checksum(&raw[..body]).to_le_bytes();
        raw[body..body + CRC_LEN].copy_from_slice(&crc);
        let mut out = [0u8; 32];
        let m = cobs::try_encode(&raw[..body + CRC_LEN], &mut out).unwrap();
        assert_eq!(decode::<ToFirmware>(&out[..m]), Err(FrameError::Trailing));
    }

    /// One lost delimiter merges two frames into one dropped frame; the next frame's sequence
    /// number shows both lost (v1: the second frame vanished and nothing moved).
    #[test]
    fn a_lost_delimiter_is_counted() {
        let mut rx = Receiver::<ToFirmware>::new();
        let mut got = 0;
        let mut feed = |rx: &mut Receiver<ToFirmware>, b: &[u8]| {
            for x in b {
                got += usize::from(rx.push(*x).is_some());
            }
        };
        let (f0, n0) = frame(0, &ToFirmware::Hello);
        let (f1, n1) = frame(1, &ToFirmware::GetStatus);
        let (f2, n2) = frame(2, &ToFirmware::Ping(6));
        let (f3, n3) = frame(3, &ToFirmware::Ping(7));
        feed(&mut rx, &f0[..n0]);
        feed(&mut rx, &f1[..n1 - 1]); // its delimiter lost
        feed(&mut rx, &f2[..n2]);
        feed(&mut rx, &f3[..n3]);
        assert_eq!(got, 2);
        let c = rx.counts;
        assert_eq!((c.ok, c.dropped(), c.lost), (2, 1, 2), "{c:?}");
    }

    #[test]
    fn the_schema_hash_is_stable_within_a_build_and_checked() {
        let h = Hello {
            protocol: PROTOCOL_VERSION,
            schema: SCHEMA_HASH,
            firmware: 0x0100,
            dt_log2: 10,
        };
        assert!(h.check().is_ok());
        let old = Hello { protocol: 2, ..h };
        let e = old.check().unwrap_err().to_string();
        assert!(
            e.contains("v2") && e.contains(&format!("v{PROTOCOL_VERSION}")),
            "{e}"
        );
        let other = Hello {
            schema: [0; 8],
            ..h
        };
        assert!(other.check().is_err());
        assert_ne!(SCHEMA_HASH, [0; 8]);
    }

    #[test]
    fn chunks_cover_a_configuration_and_field_names_survive_the_wire() {
        let bytes: Vec<u8> = (0..=200u8).collect();
        let mut back = Vec::new();
        let mut off = 0;
        loop {
            let c = Chunk::of(&bytes, off);
            if c.len == 0 {
                break;
            }
            assert_eq!(usize::from(c.offset), off);
            back.extend_from_slice(c.bytes());
            off += usize::from(c.len);
        }
        assert_eq!(back, bytes);
        let long = "relief_process_noise_bar_per_sqrt_s_and_then_some_more_text_past_64";
        let f = FieldName::new(long);
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(
            0,
            &FromFirmware::Refused(Refusal::Config(ConfigRefusal::Field {
                field: f,
                value: 1.0,
                min: 0.0,
                max: 0.5,
            })),
            &mut buf,
        )
        .unwrap();
        let (_, m): (u16, FromFirmware) = decode(&buf[..n]).unwrap();
        let s = m_text(&m);
        assert!(s.contains(&long[..64]) && !s.contains(long), "{s}");
        assert_eq!(FieldName::new("motor.x").to_string(), "motor.x");
    }

    fn m_text(m: &FromFirmware) -> String {
        match m {
            FromFirmware::Refused(r) => r.to_string(),
            other => format!("{other:?}"),
        }
    }

    /// The reference configuration survives the embedding's round trip field for field, and a
    /// truncated or padded encoding is refused.
    #[test]
    fn a_model_configuration_round_trips_through_its_bytes() {
        let cfg = crate::ModelConfig::reference();
        let mut buf = [0u8; CONFIG_MAX_BYTES];
        let bytes = encode_config(&cfg, &mut buf).unwrap().to_vec();
        println!(
            "reference configuration: {} bytes, fingerprint {:08x}",
            bytes.len(),
            config_fingerprint(&bytes)
        );
        assert_eq!(decode_config(&bytes).unwrap(), cfg);
        assert!(decode_config(&bytes[..bytes.len() - 1]).is_err());
        let mut padded = bytes.clone();
        padded.push(0);
        assert!(decode_config(&padded).is_err());
    }
}
