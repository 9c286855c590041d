//! The bring-up self-test's messages (`pto link selftest`).
//!
//! - [`SelfTest::Inputs`] reports each input's raw value and the firmware's verdict on it at any
//!   time (read only: it changes nothing).
//! - [`SelfTest::Begin`] enters the self-test, only from the safe state (the trip armed, mode
//!   fixed 0 % and the valve closed): every output goes to its de-energised level (valve
//!   closed, dump valve open, solenoids off) and stays there except what one
//!   [`SelfTest::Drive`] asks for, one output at a time: the valve to at most
//!   [`SELFTEST_VALVE_MAX_PCT`] with the dump open, the dump valve closed with the valve closed,
//!   one solenoid. Each drive holds at most [`SELFTEST_DRIVE_HOLD_S`]; a self-test the host
//!   leaves alone for [`SELFTEST_IDLE_S`] ends by itself.
//! - The estimator and the overpressure trip run throughout: a trip ends the self-test at once
//!   and its safe state applies. A mode, duty or reset command ends it too.
//! - [`SelfTest::End`] returns the outputs to the controller (from the safe state: the valve
//!   slews from closed).

use crate::fx::{Aperture, Rpm};
use crate::protocol::{BoardInfo, NotSafe};
use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

/// The largest valve aperture a self-test drives, %.
pub const SELFTEST_VALVE_MAX_PCT: u8 = 10;
/// The longest a self-test drive holds before its output returns to its de-energised level, s.
pub const SELFTEST_DRIVE_HOLD_S: u16 = 10;
/// A self-test with no self-test command for this long ends by itself, s.
pub const SELFTEST_IDLE_S: u16 = 60;

/// Host → firmware: a self-test request (answered with [`SelfTestReply`] or a refusal).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SelfTest {
    /// Report the inputs (at any time; changes nothing). Answered with `Inputs`.
    Inputs,
    /// Enter the self-test (from the safe state only). Answered with `Inputs`.
    Begin,
    /// Drive one output, every other at its de-energised level. Answered with `Driven`.
    Drive(TestDrive),
    /// Leave the self-test. Answered with `Ended`.
    End,
}

/// One output a self-test drives (the others de-energised).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TestDrive {
    /// Every output de-energised: valve closed, dump valve open, solenoids off.
    AllOff,
    /// The valve at this aperture (≤ [`SELFTEST_VALVE_MAX_PCT`]), the dump valve open.
    Valve(Aperture),
    /// The dump valve energised (closed), the valve closed.
    DumpClosed,
    /// One duty solenoid energised: HC3.(n+1), n in 0..=3.
    Solenoid(u8),
}

/// A 4–20 mA loop's state as the firmware judges its reading.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LoopState {
    /// Inside the 3.6–21 mA window.
    InWindow,
    /// Below 3.6 mA: the loop is open (a broken wire, an unpowered transducer).
    Open,
    /// Above 21 mA: a short.
    Short,
    /// The ADC saturated (the voltage at or above its reference): a short, or a supply too low.
    Saturated,
    /// The measured ADC reference is implausible: no reading can be trusted.
    SupplyFault,
}

/// One loop's reading.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LoopReport {
    /// The raw ADC value (oversampled mean), counts.
    pub adc: u16,
    /// The loop current after the supply correction, µA.
    pub current_ua: u32,
    /// The verdict.
    pub state: LoopState,
}

/// The inputs as the firmware sees them.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct InputReport {
    /// The sample these come from (its tick; 0 before the first).
    pub tick: u32,
    /// Samples taken since boot.
    pub samples: u32,
    /// HP transducer loop.
    pub hp: LoopReport,
    /// LP transducer loop.
    pub lp: LoopReport,
    /// The ADC's reference as measured, mV (`None`: this board does not measure it).
    pub supply_mv: Option<u16>,
    /// Shaft encoder count.
    pub encoder: i32,
    /// Motor pickup's speed.
    pub motor: Option<Rpm>,
    /// The self-test is active.
    pub active: bool,
    /// The board: clock, last reset, brown-out level.
    pub board: BoardInfo,
}

/// The outputs as commanded and as read back.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct OutputReport {
    /// What was asked.
    pub drive: TestDrive,
    /// Valve aperture commanded.
    pub valve: Aperture,
    /// Dump valve open.
    pub dump_open: bool,
    /// Solenoids energised (bit i = HC3.(i+1)).
    pub solenoids: u8,
    /// The valve's command as read back from its driver (`None`: not readable).
    pub valve_readback: Option<Aperture>,
    /// The dump valve's pin level as read back: `true` = energised (closed).
    pub dump_readback: Option<bool>,
    /// The solenoid pins' levels as read back (bit i = HC3.(i+1) energised).
    pub solenoids_readback: Option<u8>,
}

/// Firmware → host: a self-test answer.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SelfTestReply {
    /// The inputs.
    Inputs(InputReport),
    /// An output driven.
    Driven(OutputReport),
    /// The self-test ended.
    Ended,
}

/// Why a self-test request was refused.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SelfTestRefusal {
    /// `Begin` outside the safe state.
    NotSafe(NotSafe),
    /// `Drive` or `End` without an active self-test (never begun, or ended by a trip, a
    /// command or its idle timeout).
    NotActive,
    /// A valve drive above [`SELFTEST_VALVE_MAX_PCT`].
    ApertureTooHigh(Aperture),
    /// A solenoid number outside 0..=3.
    NoSuchSolenoid(u8),
}

impl core::fmt::Display for SelfTestRefusal {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            SelfTestRefusal::NotSafe(why) => write!(
                f,
                "not in the safe state ({why}): the self-test starts only with the trip armed, \
                 in mode fixed 0 % with the valve closed"
            ),
            SelfTestRefusal::NotActive => f.write_str(
                "no self-test active (never begun, or ended by a trip, a command or its idle \
                 timeout)",
            ),
            SelfTestRefusal::ApertureTooHigh(a) => write!(
                f,
                "valve {:.1} % above the self-test's {SELFTEST_VALVE_MAX_PCT} %",
                a.to_f32()
            ),
            SelfTestRefusal::NoSuchSolenoid(n) => write!(f, "no solenoid {n} (0..=3)"),
        }
    }
}
