//! The fixed-point model on a Cortex-M0 (`thumbv6m-none-eabi`: no FPU, no 32 × 32 → 64
//! multiply), under QEMU `-M microbit` (nRF51822, Cortex-M0 r0p0).
//!
//! Reads `vectors.bin` over semihosting from QEMU's working directory (the format is
//! `pto_model::protocol::vectors`): for each run it checks the configuration's CRC, builds the coefficients
//! from it on the target (soft float), replays the records through `estimator::step` and
//! `scheduler::step` and compares every output with the host model's, bit for bit. It prints one
//! line per run and exits with that module's status codes (`EXIT_*`).
//!
//! Cost: TIMER0 (16 MHz, 32 bits) is read around each step and around the coefficients' build.
//! QEMU must run with `-icount shift=10` (an instruction is 1 024 ns of virtual time: 16.384
//! ticks), so the ticks give instructions exactly: round(ticks × 1000 / 16384), less the two
//! captures' own instructions (measured at start). The stack's high-water mark comes from
//! cortex-m-rt's paint. `pto_host::hil::m0` builds, runs and reads this (and traces the step's
//! code for its cycles); `pto model-cost` reports it.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(target_os = "none")]
mod target;

/// On the host there is nothing to run.
#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "pto-m0 runs on a Cortex-M0: `cargo build --profile firmware --target \
         thumbv6m-none-eabi` in firmware/m0, run by `cargo test -p pto-host --test model m0` \
         (QEMU microbit)"
    );
    std::process::exit(2);
}
