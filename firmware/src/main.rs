//! PTO bench controller firmware (STM32F405, embassy).
//!
//! Tasks (all board-independent, wired in `app.rs`; each step and command is the library's
//! `session`, logged by `log.rs`): link receive and transmit per port, control (estimator +
//! scheduler + trip latch at the model's power-of-two step, driving the outputs itself),
//! supervisor (heartbeats → watchdog); the bench's board adds its sampling task. One thin board module supplies the hardware: `board/bench.rs` (the
//! real bench, embassy-stm32) or `board/qemu.rs` (QEMU `netduinoplus2`, used by the tests).
//! Build: `cargo fw` (QEMU) or `cargo fw-bench`; see the README.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(target_os = "none")]
mod app;
#[cfg(target_os = "none")]
#[cfg_attr(feature = "bench", path = "board/bench.rs")]
#[cfg_attr(not(feature = "bench"), path = "board/qemu.rs")]
mod board;
#[cfg(all(target_os = "none", not(feature = "bench")))]
mod executor;
#[cfg(target_os = "none")]
mod log;
#[cfg(target_os = "none")]
mod stack;
#[cfg(target_os = "none")]
mod trip_memory;

#[cfg(all(target_os = "none", feature = "qemu", feature = "bench"))]
compile_error!("choose one board: the default `qemu` or `--no-default-features --features bench`");
#[cfg(all(target_os = "none", not(feature = "qemu"), not(feature = "bench")))]
compile_error!("choose one board feature: `qemu` or `bench`");

/// The QEMU twin: a WFI executor (QEMU treats WFE as a no-op, `executor.rs`).
#[cfg(all(target_os = "none", not(feature = "bench")))]
#[cortex_m_rt::entry]
fn main() -> ! {
    executor::run(app::start)
}

/// The bench: embassy's own thread executor (WFE/SEV, interrupts never masked around the
/// sleep). A WFI executed from flash with interrupts masked while a debugger has set
/// `DBGMCU_CR.DBG_SLEEP` (probe-rs does, to keep RTT alive) can fetch the wrong instruction on
/// wake-up on STM32F4 parts: a hard fault or a wrong path, only with the probe attached (not in
/// ES0182; reproduced and written up by Cliff Biffle, "An STM32 WFI bug", cliffle.com). The
/// twin's executor masks interrupts around its WFI, so the bench does not use it.
#[cfg(all(target_os = "none", feature = "bench"))]
#[cortex_m_rt::entry]
fn main() -> ! {
    static EXECUTOR: static_cell::StaticCell<embassy_executor::Executor> =
        static_cell::StaticCell::new();
    EXECUTOR
        .init(embassy_executor::Executor::new())
        .run(app::start)
}

/// On the host the firmware is only a library (its logic is unit-tested there).
#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "pto-firmware runs on the STM32F405: build it with `cargo fw` (QEMU) or `cargo fw-bench`"
    );
    std::process::exit(2);
}
