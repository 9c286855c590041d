//! What a board says of itself (clock, last reset, brown-out level) and how long its slowest
//! operations may take by the datasheet, so that the host waits long enough for their replies.
//!
//! The STM32F405's flash stalls every read, so all code, while it erases: a configuration
//! commit or clear answers only after its erases. The bounds below are the datasheet's
//! maximum erase times at the program/erase parallelism the bench firmware sets (x32, for a
//! 2.7–3.6 V supply: RM0090 §3.6.2, table "Program/erase parallelism"; DS8626, table "Flash
//! memory programming": a 128 KiB sector 1 s typical, 2 s maximum at x32 — 4 s at x8, the
//! reset value of `FLASH_CR.PSIZE`).

use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

/// The longest erase of one 128 KiB sector at x32 parallelism (DS8626, "Flash memory
/// programming": t_ERASE128KB max), ms.
pub const SECTOR_ERASE_MAX_MS: u32 = 2_000;
/// Sectors of the configuration store (the last two 128 KiB sectors); a clear erases both, a
/// store erases at most one (`sequential-storage` keeps one page free and erases it when it
/// moves to it) — both are counted for either.
pub const STORE_SECTORS: u32 = 2;
/// The budget of a build of a controller's tables (at boot, and again at each configuration
/// commit), Cortex-M4 instructions (`pto fw-cost` asserts both; 2.3 M measured under QEMU).
pub const TABLE_BUILD_MAX_INSTRUCTIONS: u32 = 5_000_000;
/// Cycles per instruction assumed for that bound: the flash's wait states (the ART accelerator
/// hides most of them, RM0090 §3.5.2) and the multi-cycle instructions (an assumed average:
/// per-instruction cycles are in the Cortex-M4 TRM, not RM0090; the bring-up checklist checks
/// the boot log's DWT cycle count against it, docs/bench.md §0).
pub const TABLE_BUILD_CYCLES_PER_INSTRUCTION: u32 = 3;
/// The longest build of a controller's tables, ms: its instruction budget at that many cycles
/// each at 168 MHz, rounded up (90 ms). Two of them back to back fit the watchdog's normal
/// window (≥ 250 ms): a build does not raise it.
pub const TABLE_BUILD_MAX_MS: u32 = (TABLE_BUILD_MAX_INSTRUCTIONS as u64
    * TABLE_BUILD_CYCLES_PER_INSTRUCTION as u64)
    .div_ceil(168_000) as u32;
const _: () = assert!(TABLE_BUILD_MAX_MS == 90);
/// The longest a configuration commit may take before its answer (`persist`: the tables are
/// checked, the store erased and written, the tables built again), ms, plus 1 s for the link.
pub const COMMIT_REPLY_MAX_MS: u32 =
    2 * TABLE_BUILD_MAX_MS + STORE_SECTORS * SECTOR_ERASE_MAX_MS + 1_000;
/// The longest a store clear may take before its answer (both sectors erased), ms, plus 1 s for
/// the link.
pub const CLEAR_REPLY_MAX_MS: u32 = STORE_SECTORS * SECTOR_ERASE_MAX_MS + 1_000;

/// Which oscillator clocks the controller.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
pub enum ClockSource {
    /// The crystal (HSE) of this frequency, as configured (`[controller.board] hse_mhz`).
    Crystal {
        /// Its frequency, MHz.
        mhz: u8,
    },
    /// A crystal of this frequency is configured but did not start within its timeout: the
    /// controller runs on its internal RC oscillator (HSI, ±1 % at 25 °C, −8 … +4.5 % over
    /// −40 … 105 °C by the datasheet), with the PLL set for it.
    InternalFallback {
        /// The configured crystal, MHz.
        mhz: u8,
    },
    /// No crystal configured (`hse_mhz = 0`): the internal RC oscillator, as asked.
    Internal,
    /// QEMU's emulated clock (the twin).
    Emulated,
}

/// Why the controller last reset (the reset flags of `RCC_CSR`, RM0090 §7.3.21, most telling
/// first: a power-on also sets the pin and brown-out flags).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
pub enum ResetCause {
    /// The independent watchdog expired.
    Watchdog,
    /// The window watchdog (unused by this firmware).
    WindowWatchdog,
    /// A low-power management reset.
    LowPower,
    /// A software reset (`SCB::sys_reset`: a fault handler, or `Exit` on the bench).
    Software,
    /// Power-on or power-down reset.
    PowerOn,
    /// Brown-out reset: the supply fell below the brown-out level.
    BrownOut,
    /// The NRST pin (a debugger's reset, the reset button).
    Pin,
    /// No flag set (QEMU does not model them).
    Unknown,
}

/// The brown-out reset level programmed in the option bytes (`FLASH_OPTCR.BOR_LEV`, RM0090
/// §3.7.1; thresholds from DS8626, "Reset and power control block characteristics").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
pub enum BrownOut {
    /// Off (the factory setting): only the power-on/power-down reset at ≈ 1.8 V.
    Off,
    /// Level 1, ≈ 2.2 V falling.
    Level1,
    /// Level 2, ≈ 2.5 V falling.
    Level2,
    /// Level 3, ≈ 2.8 V falling: what the firmware sets (the ADC's reference and the flash's x32
    /// parallelism need VDD ≥ 2.7 V).
    Level3,
    /// Not a hardware board (the QEMU twin).
    NotApplicable,
}

/// What the board says of itself (boot log, self-test).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct BoardInfo {
    /// The clock it runs on.
    pub clock: ClockSource,
    /// Why it last reset.
    pub reset: ResetCause,
    /// Its brown-out reset level.
    pub brownout: BrownOut,
}

impl BoardInfo {
    /// The QEMU twin's.
    pub const EMULATED: BoardInfo = BoardInfo {
        clock: ClockSource::Emulated,
        reset: ResetCause::Unknown,
        brownout: BrownOut::NotApplicable,
    };
}

impl core::fmt::Display for ClockSource {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            ClockSource::Crystal { mhz } => write!(f, "{mhz} MHz crystal"),
            ClockSource::InternalFallback { mhz } => write!(
                f,
                "internal RC oscillator: the {mhz} MHz crystal did not start"
            ),
            ClockSource::Internal => f.write_str("internal RC oscillator (no crystal configured)"),
            ClockSource::Emulated => f.write_str("emulated (QEMU)"),
        }
    }
}

impl ResetCause {
    /// In words.
    pub const fn text(&self) -> &'static str {
        match self {
            ResetCause::Watchdog => "the watchdog expired",
            ResetCause::WindowWatchdog => "the window watchdog",
            ResetCause::LowPower => "low-power management",
            ResetCause::Software => "software (a fault handler, or Exit)",
            ResetCause::PowerOn => "power-on",
            ResetCause::BrownOut => "brown-out (the supply dipped)",
            ResetCause::Pin => "the reset pin (button or debugger)",
            ResetCause::Unknown => "unknown (no reset flag)",
        }
    }
}

impl core::fmt::Display for ResetCause {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.text())
    }
}

impl BrownOut {
    /// In words.
    pub const fn text(&self) -> &'static str {
        match self {
            BrownOut::Off => "off (factory setting: reset only at ≈ 1.8 V)",
            BrownOut::Level1 => "level 1 (≈ 2.2 V)",
            BrownOut::Level2 => "level 2 (≈ 2.5 V)",
            BrownOut::Level3 => "level 3 (≈ 2.8 V)",
            BrownOut::NotApplicable => "not applicable (QEMU)",
        }
    }
}

impl core::fmt::Display for BrownOut {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.text())
    }
}

// The boot log says these as the host prints them.
#[cfg(feature = "defmt")]
impl defmt::Format for ClockSource {
    fn format(&self, f: defmt::Formatter) {
        match self {
            ClockSource::Crystal { mhz } => defmt::write!(f, "{=u8} MHz crystal", mhz),
            ClockSource::InternalFallback { mhz } => defmt::write!(
                f,
                "internal RC oscillator: the {=u8} MHz crystal did not start",
                mhz
            ),
            ClockSource::Internal => {
                defmt::write!(f, "internal RC oscillator (no crystal configured)")
            }
            ClockSource::Emulated => defmt::write!(f, "emulated (QEMU)"),
        }
    }
}

#[cfg(feature = "defmt")]
impl defmt::Format for ResetCause {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(f, "{=str}", self.text());
    }
}

#[cfg(feature = "defmt")]
impl defmt::Format for BrownOut {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(f, "{=str}", self.text());
    }
}
