//! The trip latch's and the sensor-fault latch's memory across a controller reset (watchdog,
//! hard fault, the `Stall` self-test): a word each of RAM the reset leaves alone (`.uninit`, which `cortex-m-rt` does not
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

#[unsafe(link_section = ".uninit.pto_trip")]
static mut SENSORS: MaybeUninit<u32> = MaybeUninit::uninit();

/// "SF" and the held sensors' bits twice (once inverted): a word the RAM wakes up with passes
/// for a memory 2^−24 of the time, and then holds sensors faulted (the safe side).
const SENSORS_MARK: u32 = 0x5346_0000;

fn sensors_word(bits: u8) -> u32 {
    SENSORS_MARK | (u32::from(!bits) << 8) | u32::from(bits)
}

/// The sensors held faulted when the controller last reset (0: none, or no memory).
pub fn remembered_sensor_faults() -> u8 {
    // SAFETY: as in `remembered`.
    let w = unsafe { core::ptr::read_volatile(core::ptr::addr_of!(SENSORS).cast::<u32>()) };
    let bits = w as u8;
    if w == sensors_word(bits) { bits } else { 0 }
}

/// Records the held sensors for the next boot.
pub fn remember_sensor_faults(bits: u8) {
    // SAFETY: as in `remembered`.
    unsafe {
        core::ptr::write_volatile(
            core::ptr::addr_of_mut!(SENSORS).cast::<u32>(),
            sensors_word(bits),
        );
    }
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
