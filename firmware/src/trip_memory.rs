//! The trip latch's memory across a controller reset (watchdog, hard fault, the `Stall`
//! self-test): one word of RAM the reset leaves alone (`.uninit`, which `cortex-m-rt` does not
//! zero). After power-on the word holds whatever the RAM woke up with: the chance that it
//! equals the mark (2^−32) errs on the safe side, a boot that starts tripped. On QEMU the RAM
//! starts zeroed and a watchdog expiry ends the run, so the memory is exercised on the bench
//! only; the latch's behaviour from it is tested on the host (`TripLatch::boot_tripped`).
#![allow(unsafe_code)]

use core::mem::MaybeUninit;

/// "TRIP".
const TRIPPED: u32 = 0x5452_4950;

#[unsafe(link_section = ".uninit.pto_trip")]
static mut MARK: MaybeUninit<u32> = MaybeUninit::uninit();

/// Whether the latch was tripped when the controller last reset.
pub fn remembered() -> bool {
    // SAFETY: a word-aligned static touched only by the control task (one core, no interrupt
    // uses it), read volatile so the compiler assumes nothing of its contents; every bit
    // pattern is a valid u32.
    unsafe { core::ptr::read_volatile(core::ptr::addr_of!(MARK).cast::<u32>()) == TRIPPED }
}

/// Records the latch's state for the next boot.
pub fn remember(tripped: bool) {
    // SAFETY: as in `remembered`.
    unsafe {
        core::ptr::write_volatile(
            core::ptr::addr_of_mut!(MARK).cast::<u32>(),
            if tripped { TRIPPED } else { 0 },
        );
    }
}
