//! The serial link: COBS frames (`0`-terminated; a leading `0` is allowed and resynchronises
//! after a truncated frame) carrying [`pto_model::protocol`] messages.

use heapless::Vec;
use pto_model::protocol::{self, FrameError, FromFirmware, MAX_FRAME, ToFirmware};

/// Collects received bytes into frames; counts what it has to drop.
#[derive(Debug, Default)]
pub struct FrameAssembler {
    buf: Vec<u8, MAX_FRAME>,
    overflow: bool,
    /// Frames decoded.
    pub ok: u32,
    /// Frames dropped (bad COBS, CRC, payload, or too long).
    pub dropped: u32,
}

impl FrameAssembler {
    /// An empty assembler.
    pub const fn new() -> Self {
        FrameAssembler {
            buf: Vec::new(),
            overflow: false,
            ok: 0,
            dropped: 0,
        }
    }

    /// Feeds one byte; returns a message when it completes a valid frame.
    pub fn push(&mut self, byte: u8) -> Option<ToFirmware> {
        if byte != 0 {
            if self.buf.push(byte).is_err() {
                self.overflow = true;
            }
            return None;
        }
        let result = if self.overflow {
            Err(FrameError::BufferTooSmall)
        } else if self.buf.is_empty() {
            // Delimiter only (leading 0 or back-to-back terminators): nothing to count.
            return None;
        } else {
            protocol::decode::<ToFirmware>(&self.buf)
        };
        self.buf.clear();
        self.overflow = false;
        match result {
            Ok(m) => {
                self.ok = self.ok.wrapping_add(1);
                Some(m)
            }
            Err(_) => {
                self.dropped = self.dropped.wrapping_add(1);
                None
            }
        }
    }
}

/// Encodes a reply; `None` only if the message cannot fit a frame (a bug caught by the tests).
pub fn encode(msg: &FromFirmware, out: &mut [u8; MAX_FRAME]) -> Option<usize> {
    protocol::encode(msg, out).ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use pto_model::estimator::fault;
    use pto_model::fx::{Aperture, Fx, Pressure};
    use pto_model::protocol::Status;
    use pto_model::{Command, Estimate};

    fn frame(m: &ToFirmware) -> std::vec::Vec<u8> {
        let mut b = [0u8; MAX_FRAME];
        let n = protocol::encode(m, &mut b).unwrap();
        b[..n].to_vec()
    }

    #[test]
    fn good_bad_truncated_and_oversized_frames_are_counted() {
        let mut a = FrameAssembler::new();
        let ping = frame(&ToFirmware::Ping(7));
        let mut got = std::vec::Vec::new();
        let mut feed = |a: &mut FrameAssembler, bytes: &[u8]| {
            for b in bytes {
                if let Some(m) = a.push(*b) {
                    got.push(m);
                }
            }
        };
        feed(&mut a, &ping);
        // Corrupted.
        let mut bad = ping.clone();
        bad[1] ^= 0x10;
        feed(&mut a, &bad);
        // Truncated, then resynchronised by a leading 0.
        feed(&mut a, &ping[..ping.len() / 2]);
        feed(&mut a, &[0]);
        feed(&mut a, &ping);
        // Oversized garbage.
        feed(&mut a, &[0x55; 3 * MAX_FRAME]);
        feed(&mut a, &[0]);
        feed(&mut a, &ping);
        assert_eq!(got, vec![ToFirmware::Ping(7); 3]);
        assert_eq!((a.ok, a.dropped), (3, 3));
    }

    #[test]
    fn the_largest_replies_fit_a_frame() {
        let big = Fx::from_bits(i32::MIN);
        let e = Estimate {
            p2: Pressure(big),
            p2_var: pto_model::fx::PressureVariance(big),
            faults: u16::MAX,
            ..Default::default()
        };
        let mut e2 = e;
        // Every field at its widest varint.
        e2.torque_cyl = [pto_model::fx::Torque(big); 4];
        e2.q_pump.0 = big;
        e2.q_pump_mean.0 = big;
        e2.q_valve.0 = big;
        e2.q_relief.0 = big;
        e2.torque.0 = big;
        e2.motor_rpm.0 = big;
        e2.autonomy.0 = big;
        e2.aperture.0 = big;
        e2.lp.0 = big;
        e2.theta.0 = big;
        e2.omega.0 = big;
        let out = FromFirmware::Output {
            tick: u32::MAX,
            estimate: e2,
            command: Command {
                aperture: Aperture(big),
                safety: Default::default(),
            },
            applied: Aperture(big),
            dump: true,
        };
        let mut b = [0u8; MAX_FRAME];
        let n = encode(&out, &mut b).expect("Output fits");
        let st = FromFirmware::Status(Status {
            frames_ok: u32::MAX,
            frames_dropped: u32::MAX,
            frames_overrun: u32::MAX,
            bytes_lost: u32::MAX,
            steps: u32::MAX,
            faults_seen: fault::HP_SENSOR | fault::OVERPRESSURE,
            hp_loop_faults: u32::MAX,
            trips: u32::MAX,
            tripped: true,
            dump_valve: true,
            aperture: Aperture(big),
            step_cost_last: u32::MAX,
            step_cost_max: u32::MAX,
            step_cost_sum: u64::MAX,
        });
        let m = encode(&st, &mut b).expect("Status fits");
        println!("largest Output frame {n} B, Status {m} B (limit {MAX_FRAME})");
    }
}
