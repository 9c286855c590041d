//! Messages between host tools and the firmware, defined once: postcard payload, CRC-16
//! (CRC-16/KERMIT, little-endian) appended, COBS-encoded, terminated by a 0 byte.

use crate::estimator::{Estimate, Inputs};
use crate::fx::{Aperture, Pressure, Rpm};
use crate::scheduler::{Command, Mode};
use serde::{Deserialize, Serialize};

/// Largest encoded frame, bytes (payload ≤ 240).
pub const MAX_FRAME: usize = 256;
const MAX_PAYLOAD: usize = 240;
const CRC: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_KERMIT);

/// One raw sensor sample, stamped with virtual time in model steps. The firmware converts it
/// exactly as it converts its own ADC and timer readings on the bench.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct SensorFrame {
    /// Step counter (virtual time = tick · dt).
    pub tick: u32,
    /// Shaft encoder timer count (32-bit timer in encoder mode, 0 at the neutral angle).
    pub encoder: i32,
    /// HP transducer loop, 12-bit ADC counts (4–20 mA across the shunt).
    pub hp_adc: u16,
    /// LP transducer loop, 12-bit ADC counts.
    pub lp_adc: u16,
    /// Motor speed from the pickup's input capture; `None` when no pulse was seen.
    pub motor: Option<Rpm>,
}

/// Host → firmware.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ToFirmware {
    /// Answer with `Pong` carrying the same number.
    Ping(u32),
    /// Full estimator inputs for a bit-exact replay (the firmware uses the given aperture and
    /// its actuator stage is bypassed).
    Replay {
        /// Step counter.
        tick: u32,
        /// Inputs.
        inputs: Inputs,
    },
    /// A sensor sample for closed-loop operation (the firmware commands the valve itself).
    Sensors(SensorFrame),
    /// Scheduler mode.
    SetMode(Mode),
    /// Cylinders on duty and geometry.
    SetDuty {
        /// Bit i = HC3.(i+1).
        on_duty: u8,
        /// 0..=3.
        config: u8,
    },
    /// Restart the estimator from known pressures and clear the scheduler. Answered with
    /// `ResetDone`, or `Refused(TripHeld)` while the overpressure trip holds and its release
    /// condition does not (a reset never releases the trip itself).
    Reset {
        /// P2.
        p2: Pressure,
        /// LP.
        lp: Pressure,
    },
    /// Ask for the link statistics.
    GetStatus,
    /// Watchdog self-test: the control task stops answering (it waits forever); the supervisor
    /// must then stop feeding the watchdog, which resets the controller.
    Stall,
    /// Stop (QEMU: exit with this code).
    Exit(u8),
}

/// Link and health counters.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Status {
    /// Frames decoded.
    pub frames_ok: u32,
    /// Frames dropped: bad COBS, CRC or payload, or longer than a frame.
    pub frames_dropped: u32,
    /// Sensor frames dropped because the control loop had not taken the previous ones.
    pub frames_overrun: u32,
    /// Received bytes lost because the receive buffer was full.
    pub bytes_lost: u32,
    /// Estimator steps run.
    pub steps: u32,
    /// OR of every fault flag seen.
    pub faults_seen: u16,
    /// Steps run with the HP transducer out of its 4–20 mA window (wire break or short).
    pub hp_loop_faults: u32,
    /// Times the overpressure trip latched.
    pub trips: u32,
    /// Trip latch state.
    pub tripped: bool,
    /// Dump valve output state.
    pub dump_valve: bool,
    /// Last valve aperture applied by the actuator stage.
    pub aperture: Aperture,
    /// Instructions (QEMU under `-icount shift=0`) or cycles (bench, DWT) of the last
    /// estimator + scheduler step.
    pub step_cost_last: u32,
    /// Largest of those.
    pub step_cost_max: u32,
    /// Sum over every step (mean = sum / steps).
    pub step_cost_sum: u64,
}

/// Firmware → host.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FromFirmware {
    /// Sent once the link is up.
    Ready {
        /// Firmware version, major·256 + minor.
        version: u16,
        /// Model step, dt = 2^−dt_log2 s.
        dt_log2: u8,
    },
    /// Reply to `Ping`.
    Pong(u32),
    /// One step's result.
    Output {
        /// Step counter it answers.
        tick: u32,
        /// Estimator output.
        estimate: Estimate,
        /// Scheduler output.
        command: Command,
        /// Aperture the actuator stage applied to the valve (after its slew limit and the trip
        /// latch).
        applied: Aperture,
        /// Dump (safe) valve output.
        dump: bool,
    },
    /// Reply to `GetStatus`.
    Status(Status),
    /// Reply to an accepted `Reset`: the estimator and the scheduler restarted (a trip latch
    /// that was set stays set until it releases by itself; `Status::tripped` says so).
    ResetDone,
    /// A command was refused, with the reason; nothing changed.
    Refused(Refusal),
}

/// Why the firmware refused a command.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Refusal {
    /// `Reset` while the overpressure trip holds: the trip's release condition (a valid HP
    /// reading and the estimate both below the release pressure) does not hold now.
    TripHeld(TripHold),
}

/// Why a tripped latch cannot release now.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TripHold {
    /// No valid HP reading (wire break, short, or outside the transducer's range): the pressure
    /// is unknown.
    HpMissing,
    /// The HP reading is above the release pressure (the reading).
    HpHigh(Pressure),
    /// The P2 estimate is above the release pressure (the estimate).
    EstimateHigh(Pressure),
}

impl core::fmt::Display for TripHold {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            TripHold::HpMissing => f.write_str("no valid HP reading (the pressure is unknown)"),
            TripHold::HpHigh(p) => {
                write!(
                    f,
                    "HP reading {:.2} bar above the release pressure",
                    p.to_f32()
                )
            }
            TripHold::EstimateHigh(p) => {
                write!(
                    f,
                    "P2 estimate {:.2} bar above the release pressure",
                    p.to_f32()
                )
            }
        }
    }
}

impl core::fmt::Display for Refusal {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Refusal::TripHeld(h) => write!(f, "reset refused: the overpressure trip holds: {h}"),
        }
    }
}

/// Why a frame could not be built or read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FrameError {
    /// The output buffer is too small.
    BufferTooSmall,
    /// Not valid COBS.
    Cobs,
    /// CRC mismatch.
    Crc,
    /// CRC fine but the payload is not a message.
    Payload,
}

impl core::fmt::Display for FrameError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            FrameError::BufferTooSmall => "buffer too small",
            FrameError::Cobs => "bad COBS encoding",
            FrameError::Crc => "CRC mismatch",
            FrameError::Payload => "bad payload",
        })
    }
}

impl core::error::Error for FrameError {}

/// Encodes `msg` into `out` (COBS frame + 0 terminator); returns the frame length.
pub fn encode<T: Serialize>(msg: &T, out: &mut [u8]) -> Result<usize, FrameError> {
    let mut raw = [0u8; MAX_PAYLOAD + 2];
    let n = postcard::to_slice(msg, &mut raw[..MAX_PAYLOAD])
        .map_err(|_| FrameError::BufferTooSmall)?
        .len();
    let crc = CRC.checksum(&raw[..n]).to_le_bytes();
    raw[n] = crc[0];
    raw[n + 1] = crc[1];
    let m = cobs::try_encode(&raw[..n + 2], out).map_err(|_| FrameError::BufferTooSmall)?;
    let end = out.get_mut(m).ok_or(FrameError::BufferTooSmall)?;
    *end = 0;
    Ok(m + 1)
}

/// Decodes one frame (with or without its 0 terminator).
pub fn decode<T: for<'de> Deserialize<'de>>(frame: &[u8]) -> Result<T, FrameError> {
    let frame = match frame.split_last() {
        Some((0, body)) => body,
        _ => frame,
    };
    let mut raw = [0u8; MAX_FRAME];
    let report = cobs::decode(frame, &mut raw).map_err(|_| FrameError::Cobs)?;
    let n = report.frame_size();
    if n < 2 {
        return Err(FrameError::Crc);
    }
    let (payload, crc) = raw[..n].split_at(n - 2);
    if CRC.checksum(payload).to_le_bytes() != [crc[0], crc[1]] {
        return Err(FrameError::Crc);
    }
    postcard::from_bytes(payload).map_err(|_| FrameError::Payload)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_round_trip_and_corruption_is_caught() {
        let msg = ToFirmware::Replay {
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
        };
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(&msg, &mut buf).unwrap();
        assert_eq!(buf[n - 1], 0);
        assert!(buf[..n - 1].iter().all(|b| *b != 0));
        assert_eq!(decode::<ToFirmware>(&buf[..n]).unwrap(), msg);
        for i in 0..n - 1 {
            let mut bad = buf;
            bad[i] ^= 0x5a;
            if bad[i] == 0 {
                continue;
            }
            assert!(
                decode::<ToFirmware>(&bad[..n]).is_err(),
                "flip at {i} accepted"
            );
        }
        assert!(decode::<ToFirmware>(&buf[..n / 2]).is_err());
    }
}
