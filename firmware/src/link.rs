//! The serial link: protocol frames (`pto_model::protocol`: sequence number, postcard,
//! CRC-32C, COBS, `0`-terminated; a leading `0` is allowed and resynchronises after a truncated
//! frame). The receiver counts every frame it cannot take by cause and every gap in the host's
//! sequence numbers; the transmitter numbers its own frames.

use pto_model::protocol::{self, FromFirmware, MAX_FRAME, Receiver, ToFirmware};

/// The firmware's receiver of host frames.
pub type HostReceiver = Receiver<ToFirmware>;

/// Numbers and encodes the firmware's frames.
#[derive(Debug, Default)]
pub struct Transmitter {
    seq: u16,
}

impl Transmitter {
    /// A transmitter whose first frame is numbered 0 (the boot `Hello`).
    pub const fn new() -> Self {
        Transmitter { seq: 0 }
    }

    /// Encodes `msg` as the next frame; `None` only if it cannot fit a frame (a bug caught by
    /// the tests), and then no number is used up.
    pub fn encode(&mut self, msg: &FromFirmware, out: &mut [u8; MAX_FRAME]) -> Option<usize> {
        let n = protocol::encode(self.seq, msg, out).ok()?;
        self.seq = self.seq.wrapping_add(1);
        Some(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pto_model::estimator::fault;
    use pto_model::fx::{Aperture, Fx, Pressure};
    use pto_model::protocol::{LinkCounts, Status};
    use pto_model::{Command, Estimate};

    fn frame(seq: u16, m: &ToFirmware) -> std::vec::Vec<u8> {
        let mut b = [0u8; MAX_FRAME];
        let n = protocol::encode(seq, m, &mut b).unwrap();
        b[..n].to_vec()
    }

    #[test]
    fn good_bad_truncated_oversized_and_missing_frames_are_counted() {
        let mut a = HostReceiver::new();
        let mut got = std::vec::Vec::new();
        let mut feed = |a: &mut HostReceiver, bytes: &[u8]| {
            for b in bytes {
                if let Some(m) = a.push(*b) {
                    got.push(m);
                }
            }
        };
        feed(&mut a, &frame(0, &ToFirmware::Ping(7)));
        // Corrupted.
        let mut bad = frame(1, &ToFirmware::Ping(7));
        bad[1] ^= 0x10;
        feed(&mut a, &bad);
        // Truncated, then resynchronised by a leading 0.
        let f2 = frame(2, &ToFirmware::Ping(7));
        feed(&mut a, &f2[..f2.len() / 2]);
        feed(&mut a, &[0]);
        feed(&mut a, &frame(3, &ToFirmware::Ping(7)));
        // Oversized garbage.
        feed(&mut a, &[0x55; 3 * MAX_FRAME]);
        feed(&mut a, &[0]);
        // Frame 4 never sent.
        feed(&mut a, &frame(5, &ToFirmware::Ping(7)));
        assert_eq!(got, vec![ToFirmware::Ping(7); 3]);
        let c = a.counts;
        assert_eq!(c.ok, 3);
        assert_eq!(c.dropped(), 3, "{c:?}");
        assert_eq!(c.too_long, 1);
        // Frames 1, 2 (dropped) and 4 (missing).
        assert_eq!(c.lost, 3);
    }

    #[test]
    fn the_transmitter_numbers_its_frames() {
        let mut t = Transmitter::new();
        let mut r = Receiver::<FromFirmware>::new();
        let mut b = [0u8; MAX_FRAME];
        for i in 0..3u32 {
            let n = t.encode(&FromFirmware::Pong(i), &mut b).unwrap();
            for x in &b[..n] {
                let _ = r.push(*x);
            }
            assert_eq!(r.last_seq(), Some(i as u16));
        }
        assert_eq!(r.counts.lost, 0);
    }

    #[test]
    fn the_largest_replies_fit_a_frame() {
        let big = Fx::from_bits(i32::MIN);
        let e = Estimate {
            p2: Pressure(big),
            p2_var: pto_model::fx::PressureVariance(big),
            faults: u16::MAX,
            hp_empty: true,
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
            on_duty: 0xff,
        };
        let mut t = Transmitter::new();
        let mut b = [0u8; MAX_FRAME];
        let n = t.encode(&out, &mut b).expect("Output fits");
        let all = u32::MAX;
        let st = FromFirmware::Status(Status {
            link: LinkCounts {
                ok: all,
                cobs: all,
                crc: all,
                payload: all,
                too_long: all,
                lost: all,
                out_of_order: all,
            },
            frames_overrun: all,
            bytes_lost: all,
            samples_missed: all,
            replies_dropped: all,
            telemetry_dropped: all,
            steps: all,
            faults_seen: fault::HP_SENSOR | fault::OVERPRESSURE,
            hp_loop_faults: all,
            supply_faults: all,
            trips: all,
            tripped: true,
            sensor_faults: u8::MAX,
            held: true,
            dump_valve: true,
            aperture: Aperture(big),
            step_cost_last: all,
            step_cost_max: all,
            step_cost_sum: u64::MAX,
            stack_unused: all,
        });
        let m = t.encode(&st, &mut b).expect("Status fits");
        let tel = |e: Estimate| {
            FromFirmware::Telemetry(pto_model::protocol::Telemetry {
                sensors: pto_model::protocol::SensorFrame {
                    tick: u32::MAX,
                    encoder: i32::MIN,
                    hp_adc: u16::MAX,
                    lp_adc: u16::MAX,
                    motor: Some(pto_model::fx::Rpm(big)),
                    supply_mv: Some(u16::MAX),
                },
                estimate: e,
                command: Command {
                    aperture: Aperture(big),
                    safety: Default::default(),
                },
                applied: Aperture(big),
                dump: true,
                on_duty: 0xff,
                config: 0xff,
                hydraulic_power: pto_model::fx::HydraulicPower(big),
                sensor_faults: 0xff,
            })
        };
        let k = t.encode(&tel(e2), &mut b).expect("Telemetry fits");
        use pto_model::protocol::selftest::{InputReport, LoopReport, LoopState};
        use pto_model::protocol::{BoardInfo, BrownOut, ClockSource, ResetCause, SelfTestReply};
        let lr = LoopReport {
            adc: u16::MAX,
            current_ua: u32::MAX,
            state: LoopState::SupplyFault,
        };
        let inputs = FromFirmware::SelfTest(SelfTestReply::Inputs(InputReport {
            tick: all,
            samples: all,
            hp: lr,
            lp: lr,
            supply_mv: Some(u16::MAX),
            encoder: i32::MIN,
            motor: Some(pto_model::fx::Rpm(big)),
            active: true,
            board: BoardInfo {
                clock: ClockSource::InternalFallback { mhz: u8::MAX },
                reset: ResetCause::Unknown,
                brownout: BrownOut::NotApplicable,
            },
        }));
        let i = t.encode(&inputs, &mut b).expect("self-test inputs fit");
        println!(
            "largest frames: Output {n} B, Status {m} B, Telemetry {k} B, self-test inputs {i} B \
             (limit {MAX_FRAME})"
        );
        // The link budget (docs/bench.md): at 230 400 baud 8N1 (23 040 B/s), the default 64
        // telemetry frames per second of the largest size take under half of the link.
        assert!(k * 64 * 2 < 23_040, "{k} B × 64/s");
    }
}
