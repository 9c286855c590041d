//! PTO bench controller firmware (STM32F405, embassy).
//!
//! Tasks (all board-independent, in `app.rs`): link receive, control (estimator + scheduler +
//! trip latch, the model's power-of-two step), actuator output, link transmit, supervisor
//! (heartbeats → watchdog). One thin board module supplies the hardware: `board/bench.rs` (the
//! real bench, embassy-stm32) or `board/qemu.rs` (QEMU `netduinoplus2`, used by the tests).
//! Build: `cargo fw` (QEMU) or `cargo fw-bench`; see the README.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(target_os = "none")]
mod app;
#[cfg(target_os = "none")]
#[cfg_attr(feature = "bench", path = "board/bench.rs")]
#[cfg_attr(not(feature = "bench"), path = "board/qemu.rs")]
mod board;
#[cfg(target_os = "none")]
mod executor;
#[cfg(target_os = "none")]
mod trip_memory;

#[cfg(all(target_os = "none", feature = "qemu", feature = "bench"))]
compile_error!("choose one board: the default `qemu` or `--no-default-features --features bench`");
#[cfg(all(target_os = "none", not(feature = "qemu"), not(feature = "bench")))]
compile_error!("choose one board feature: `qemu` or `bench`");

#[cfg(target_os = "none")]
#[cortex_m_rt::entry]
fn main() -> ! {
    executor::run(app::start)
}

/// On the host the firmware is only a library (its logic is unit-tested there).
#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "pto-firmware runs on the STM32F405: build it with `cargo fw` (QEMU) or `cargo fw-bench`"
    );
    std::process::exit(2);
}
