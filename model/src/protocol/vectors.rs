//! Step vectors: what the Cortex-M0 replay (`firmware/m0`) reads, in one format for the host
//! that writes them (`pto_host::hil::m0`) and the target that reads them.
//!
//! A file is [`MAGIC`] and then runs, each a postcard [`Header`] followed by its
//! [`Header::steps`] postcard [`Record`]s. A header carries the model configuration as the
//! bytes the bench workflow uploads ([`super::encode_config`]) with their CRC-32C
//! (`config_fingerprint`): the target checks them, builds the coefficients itself and runs the
//! estimator and the scheduler from the header's start over the records, comparing every
//! output with the record's [`Record::want`] (the host model's, [`checked_words`]).
use crate::estimator::{Estimate, Inputs};
use crate::fx::Pressure;
use crate::scheduler::{Command, Mode, Override};
use serde::{Deserialize, Serialize};

/// The file's first bytes.
pub const MAGIC: [u8; 4] = *b"PTM0";

/// The format's version (in every header).
pub const VERSION: u16 = 1;

/// Largest encoded [`Header`], bytes (the configuration is at most
/// [`super::CONFIG_MAX_BYTES`], 512).
pub const HEADER_MAX_BYTES: usize = 640;

/// Largest encoded [`Record`], bytes: 4 optional readings of ≤ 6 bytes, an aperture of ≤ 5,
/// two bytes, and [`N_CHECKED`] words of ≤ 5 (postcard's varints).
pub const RECORD_MAX_BYTES: usize = 4 * 6 + 5 + 2 + 5 * N_CHECKED;

/// One run's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Header<'a> {
    /// [`VERSION`].
    pub version: u16,
    /// What the run is ("golden vectors", …), echoed in the target's report.
    pub label: &'a str,
    /// Records that follow.
    pub steps: u32,
    /// The scheduler's mode throughout.
    pub mode: Mode,
    /// The estimator's start: P2, LP and P2's σ (`estimator::State::new`).
    pub start: [Pressure; 3],
    /// CRC-32C of [`Header::config`] ([`super::config_fingerprint`]).
    pub config_crc: u32,
    /// The model configuration, postcard ([`super::encode_config`]).
    pub config: &'a [u8],
}

/// One step: the sensor inputs and the outputs the host's model gave for them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    /// The step's inputs.
    pub inputs: Inputs,
    /// [`checked_words`] of the host's step.
    pub want: [i32; N_CHECKED],
}

/// Outputs compared per step.
pub const N_CHECKED: usize = 15;

/// Their names, in [`checked_words`]' order (the golden file's output columns).
pub const CHECKED: [&str; N_CHECKED] = [
    "p2",
    "p2_var",
    "lp_est",
    "q_pump",
    "q_valve",
    "q_relief",
    "hydraulic_power",
    "torque",
    "motor_rpm",
    "autonomy",
    "aperture",
    "faults",
    "hp_empty",
    "cmd_aperture",
    "safety",
];

/// A step's outputs as the words compared bit for bit: raw Q16.16 bits, the fault flags, the
/// HP-empty flag and the safety override's code (0 none, 1 overpressure, 2 sensor fault).
pub fn checked_words(e: &Estimate, c: &Command) -> [i32; N_CHECKED] {
    [
        e.p2.to_bits(),
        e.p2_var.to_bits(),
        e.lp.to_bits(),
        e.q_pump.to_bits(),
        e.q_valve.to_bits(),
        e.q_relief.to_bits(),
        e.hydraulic_power().to_bits(),
        e.torque.to_bits(),
        e.motor_rpm.to_bits(),
        e.autonomy.to_bits(),
        e.aperture.to_bits(),
        i32::from(e.faults),
        i32::from(e.hp_empty),
        c.aperture.to_bits(),
        match c.safety {
            Override::None => 0,
            Override::Overpressure => 1,
            Override::SensorFault => 2,
        },
    ]
}

/// The first output of `got` that differs from `want`: its index in [`CHECKED`].
pub fn first_difference(got: &[i32; N_CHECKED], want: &[i32; N_CHECKED]) -> Option<usize> {
    got.iter().zip(want).position(|(g, w)| g != w)
}

/// Exit status of the target binary: every step matched.
pub const EXIT_MATCH: i32 = 0;
/// Exit status: a step's output differed from the host's (reported with the step and output).
pub const EXIT_MISMATCH: i32 = 1;
/// Exit status: the vectors file is missing, unreadable, of another format or version, or
/// truncated.
pub const EXIT_BAD_FILE: i32 = 2;
/// Exit status: a header's configuration failed its CRC, did not decode, or the model refused
/// it (reported with the field and its range).
pub const EXIT_BAD_CONFIG: i32 = 3;
/// Exit status: the binary panicked (a defect: nothing in it should).
pub const EXIT_PANIC: i32 = 101;

/// The file's name, in the directory QEMU runs in (semihosting opens it there).
pub const VECTORS_FILE: &core::ffi::CStr = c"vectors.bin";

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::fx::{Aperture, Rpm};

    /// The largest record fits [`RECORD_MAX_BYTES`]; a header with the largest configuration
    /// fits [`HEADER_MAX_BYTES`].
    #[test]
    fn the_largest_record_and_header_fit_their_bounds() {
        let big = Record {
            inputs: Inputs {
                encoder: Some(i32::MIN),
                hp: Some(Pressure::from_bits(i32::MIN)),
                lp: Some(Pressure::from_bits(i32::MIN)),
                motor: Some(Rpm::from_bits(i32::MIN)),
                aperture_cmd: Aperture::from_bits(i32::MIN),
                on_duty: u8::MAX,
                config: u8::MAX,
            },
            want: [i32::MIN; N_CHECKED],
        };
        let mut buf = [0u8; 2 * RECORD_MAX_BYTES];
        let n = postcard::to_slice(&big, &mut buf).unwrap().len();
        std::println!("largest record {n} B (bound {RECORD_MAX_BYTES})");
        assert!(n <= RECORD_MAX_BYTES);
        let config = [0xffu8; super::super::CONFIG_MAX_BYTES];
        let h = Header {
            version: VERSION,
            label: "four cylinders, no HP transducer",
            steps: u32::MAX,
            mode: Mode::HoldPressure(Pressure::from_bits(i32::MIN)),
            start: [Pressure::from_bits(i32::MIN); 3],
            config_crc: u32::MAX,
            config: &config,
        };
        let mut buf = [0u8; 2 * HEADER_MAX_BYTES];
        let n = postcard::to_slice(&h, &mut buf).unwrap().len();
        std::println!("largest header {n} B (bound {HEADER_MAX_BYTES})");
        assert!(n <= HEADER_MAX_BYTES);
    }
}
