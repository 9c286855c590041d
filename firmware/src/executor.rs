//! A thread-mode executor that sleeps with WFI.
//!
//! embassy's own thread executor sleeps with WFE, which QEMU treats as a no-op (it would spin a
//! host core and slow virtual time twenty-fold). WFI works on both QEMU and the bench MCU. The
//! pender sets a flag; the idle check and the WFI run with interrupts masked, so a wake-up that
//! lands between the check and the WFI still ends the WFI (a pending interrupt does, even
//! masked) and is handled when interrupts are unmasked.

use core::sync::atomic::{AtomicBool, Ordering};
use embassy_executor::{Spawner, raw};
use static_cell::StaticCell;

static WORK: AtomicBool = AtomicBool::new(true);
static EXECUTOR: StaticCell<raw::Executor> = StaticCell::new();

#[allow(unsafe_code)]
// SAFETY: the symbol the executor calls to signal work; it only sets an atomic flag, which is
// safe from any context.
#[unsafe(export_name = "__pender")]
fn pender(_context: *mut ()) {
    WORK.store(true, Ordering::Release);
}

/// Runs `init` with a spawner, then polls the tasks forever.
pub fn run(init: impl FnOnce(Spawner)) -> ! {
    let ex: &'static raw::Executor = EXECUTOR.init(raw::Executor::new(core::ptr::null_mut()));
    init(ex.spawner());
    loop {
        WORK.store(false, Ordering::Release);
        #[allow(unsafe_code)]
        // SAFETY: `poll` is called from thread mode only, never from the pender.
        unsafe {
            ex.poll()
        };
        cortex_m::interrupt::free(|_| {
            if !WORK.load(Ordering::Acquire) {
                cortex_m::asm::wfi();
            }
        });
    }
}
