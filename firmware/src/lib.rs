//! Hardware-independent logic of the PTO bench controller.
//!
//! Everything here compiles for the host and is unit-tested there; the firmware binary
//! (`src/main.rs`) adds the embassy tasks and one thin board module (`board/bench.rs` for the
//! STM32F405 bench, `board/qemu.rs` for QEMU `netduinoplus2`).
//!
//! - [`clocks`]: the core clock's PLL from the board's crystal, or the internal oscillator.
//! - [`frontend`]: 4–20 mA transducer loops read by the 12-bit ADC (wire-break window,
//!   saturation, the supply's correction).
//! - [`sampler`]: the bench's sample pacing (re-synchronised after a stall) and motor speed.
//! - [`outputs`]: the outputs, their de-energised (safe) levels, the actuators and their
//!   read-back.
//! - [`selftest`]: the bring-up self-test's state.
//! - [`sensor_faults`]: the sensor-fault latch: a sensor the estimator's residuals name is held
//!   faulted, its readings withheld, the controller in its safe state, until the host clears it.
//! - [`watchdog`]: the independent watchdog's settings over the LSI's range and its driver.
//! - [`link`]: COBS frame assembly with drop counting, reply encoding.
//! - [`control`]: the control step: raw sample → estimator → scheduler → trip latch → actuator
//!   stage, with the cost of the model step measured by a [`control::StepClock`].
//! - [`session`]: the control task's session: each sample's step and each host command
//!   (configuration upload, store, self-test, watchdog test) in the order that keeps the bench
//!   safe, generic over the board.
//! - [`supervisor`]: task heartbeats and the watchdog-feed decision.
//! - [`trip`]: the overpressure trip latch (a state machine that only a valid reading
//!   releases).
//! - [`built_config`]: the model configuration the firmware is built for (`PTO_BENCH`).
//! - [`upload`]: a configuration uploaded over the link, chunk by chunk, checked whole.
//! - [`store`]: the uploaded configuration kept across resets (`sequential-storage` on flash,
//!   or on RAM under QEMU).
#![cfg_attr(not(test), no_std)]
#![forbid(unsafe_code)]

pub mod built_config;
pub mod clocks;
pub mod control;
pub mod frontend;
pub mod link;
pub mod outputs;
pub mod sampler;
pub mod selftest;
pub mod sensor_faults;
pub mod session;
pub mod store;
pub mod supervisor;
pub mod trip;
pub mod upload;
pub mod watchdog;

/// The QEMU twin's board name (in its boot log; `pto --elf` checks a firmware for it).
pub const QEMU_BOARD: &str = "qemu-netduinoplus2";

/// Firmware version, major·256 + minor (reported in `Hello`).
pub const VERSION: u16 = 0x0300;

/// QEMU exit code when the watchdog expires (the bench MCU resets instead).
pub const EXIT_WATCHDOG: u8 = 3;
/// QEMU exit code after a panic.
pub const EXIT_PANIC: u8 = 101;
/// QEMU exit code after a hard fault.
pub const EXIT_HARDFAULT: u8 = 102;

/// Watchdog timeout, ms: the supervisor checks the heartbeats every [`SUPERVISOR_PERIOD_MS`]. On
/// the bench this is the shortest timeout over the LSI's range (≤ 0.69 s at its slowest:
/// [`watchdog::NORMAL`]); the QEMU twin's software watchdog runs exactly this.
pub const WATCHDOG_TIMEOUT_MS: u32 = 250;
/// Supervisor period, ms.
pub const SUPERVISOR_PERIOD_MS: u64 = 50;
/// Tasks wake at least this often even with nothing to do, so that their heartbeat shows they
/// are not stuck, ms.
pub const HEARTBEAT_MS: u64 = 20;
