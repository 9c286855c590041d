//! Board: QEMU `netduinoplus2` (STM32F405 memory map), the bench's twin. Thin by design:
//! - USART1, the hardware port: the plant's sensor samples arrive on it and each step's output
//!   goes back (the virtual sensors and actuators); USART2, the bench link, with exactly the
//!   bench's protocol (QEMU's second `-serial`, e.g. `-serial pty`). Both through stm32-metapac
//!   registers: RXNE interrupt into a byte pipe, polled transmit (QEMU's USART never stalls);
//!   RCC is left alone (QEMU does not gate clocks, and embassy-stm32's clock setup spins
//!   forever under QEMU);
//! - the configuration store on 8 KiB of RAM (QEMU's flash is read-only): the same
//!   `sequential-storage` map as the bench's flash, lost when QEMU exits;
//! - a SysTick time driver for embassy-time (1 kHz ticks) and, in the same interrupt, a software
//!   watchdog that ends the run with exit code 3 (the real board's IWDG resets the MCU);
//! - TIM2 free-running: under `-icount shift=0` it counts executed instructions, the cost metric;
//! - defmt and exit codes over semihosting; valve, dump valve and solenoids are virtual outputs
//!   that remember their level (read back by the self-test; the host learns them from each
//!   step's `Output` and the telemetry).
#![allow(unsafe_code)]

use crate::app::Board;
use core::cell::{Cell, RefCell};
use core::convert::Infallible;
use core::sync::atomic::{AtomicU32, Ordering};
use cortex_m::peripheral::syst::SystClkSource;
use critical_section::Mutex;
use defmt_semihosting as _;
use embassy_executor::Spawner;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::pipe::Pipe;
use embassy_time_queue_utils::Queue;
use pto_firmware::control::StepClock;
use pto_firmware::outputs::{Actuators, DutyReadBack, Outputs, ReadBack};
use pto_firmware::{EXIT_HARDFAULT, EXIT_PANIC, EXIT_WATCHDOG, WATCHDOG_TIMEOUT_MS};
use pto_model::protocol::BoardInfo;
use stm32_metapac as pac;

/// Board name in the boot log.
pub const NAME: &str = pto_firmware::QEMU_BOARD;
/// The twin's samples come from its host, which may pause or replay: the control task beats
/// without them, and `Replay` is taken.
pub const SAMPLES_ITSELF: bool = false;
/// Telemetry on the bench link every 16th step, as on the bench (the hardware port answers
/// every step).
pub const TELEMETRY_EVERY: u16 = 16;

/// What the step clock counts (QEMU `-icount shift=0`: TIM2 counts one tick per instruction).
pub const CLOCK_UNIT: &str = "instructions";

/// The fastest telemetry (every step: the pseudo-terminal has no baud rate).
pub const MIN_TELEMETRY_EVERY: u16 = 1;
/// SysTick reload for 1 ms at the 168 MHz core clock.
const SYSTICK_RELOAD: u32 = 168_000 - 1;

static RX_PIPE: [Pipe<CriticalSectionRawMutex, 512>; 2] = [Pipe::new(), Pipe::new()];
static BYTES_LOST: AtomicU32 = AtomicU32::new(0);

/// Receive side of a port.
pub type Rx = &'static Pipe<CriticalSectionRawMutex, 512>;
/// The configuration store's flash: RAM (QEMU's flash is read-only), in a static (never moved
/// through the stack).
pub type Flash = &'static mut RamStore;
/// 8 KiB of RAM in two 4 KiB pages.
pub type RamStore = pto_firmware::store::RamFlash<{ 8 * 1024 }, { 4 * 1024 }>;
static STORE: static_cell::ConstStaticCell<RamStore> =
    static_cell::ConstStaticCell::new(RamStore::new());
/// Step-cost clock.
pub type Clock = Tim2Clock;
/// Valve driver.
pub type Valve = VirtualPwm;
/// Digital output.
pub type Pin = VirtualPin;
/// Watchdog.
pub type Watchdog = SoftWatchdog;

/// Starts SysTick, TIM2, USART1 and USART2 (with their interrupts). Under QEMU the sensor
/// samples arrive on the hardware port: there is no sampling task. The virtual outputs start
/// at their boot levels, as the bench's do.
pub fn init(_spawner: Spawner) -> Board {
    let at_boot = Outputs::at_boot(
        crate::trip_memory::remembered(),
        pto_firmware::built_config::SCHEDULER.overpressure_aperture_pct,
    );
    let actuators = Actuators::new(
        VirtualPwm(0),
        VirtualPin(false),
        [VirtualPin(false); 4],
        at_boot,
    );
    // SAFETY: called once at boot, before any other user of the core peripherals.
    let mut cp = unsafe { cortex_m::Peripherals::steal() };
    cp.SYST.set_clock_source(SystClkSource::Core);
    cp.SYST.set_reload(SYSTICK_RELOAD);
    cp.SYST.clear_current();
    cp.SYST.enable_interrupt();
    cp.SYST.enable_counter();
    let tim = pac::TIM2;
    tim.psc().write_value(0);
    tim.arr().write_value(u32::MAX);
    tim.cr1().modify(|w| w.set_cen(true));
    for u in [pac::USART1, pac::USART2] {
        u.cr1().modify(|w| {
            w.set_ue(true);
            w.set_te(true);
            w.set_re(true);
            w.set_rxneie(true);
        });
    }
    // SAFETY: the handlers below only touch their pipe and an atomic.
    unsafe {
        cortex_m::peripheral::NVIC::unmask(pac::Interrupt::USART1);
        cortex_m::peripheral::NVIC::unmask(pac::Interrupt::USART2);
    }
    Board {
        link: (&RX_PIPE[1], Tx(pac::USART2)),
        hardware: Some((&RX_PIPE[0], Tx(pac::USART1))),
        store: (STORE.take(), 0..8 * 1024),
        clock: Tim2Clock::calibrated(),
        actuators,
        info: BoardInfo::EMULATED,
        watchdog: SoftWatchdog::start(),
    }
}

/// Bytes lost because the receive pipe was full.
pub fn bytes_lost() -> u32 {
    BYTES_LOST.load(Ordering::Relaxed)
}

/// The twin is stepped by its host: no sample period is missed.
pub fn samples_missed() -> u32 {
    0
}

/// Ends the QEMU run with `code`.
pub fn exit(code: u8) -> ! {
    semihosting::process::exit(i32::from(code))
}

/// Unrecoverable start-up error.
pub fn fail(code: u8) -> ! {
    exit(code)
}

fn receive(u: pac::usart::Usart, pipe: &Pipe<CriticalSectionRawMutex, 512>) {
    loop {
        let sr = u.sr().read();
        if !sr.rxne() && !sr.ore() {
            break;
        }
        // Reading DR after SR clears RXNE and ORE.
        let b = u.dr().read().dr() as u8;
        if pipe.try_write(&[b]).is_err() {
            BYTES_LOST.fetch_add(1, Ordering::Relaxed);
        }
    }
}

#[unsafe(no_mangle)]
extern "C" fn USART1() {
    receive(pac::USART1, &RX_PIPE[0]);
}

#[unsafe(no_mangle)]
extern "C" fn USART2() {
    receive(pac::USART2, &RX_PIPE[1]);
}

/// Transmit side of a port (blocking on TXE, which QEMU sets at once).
pub struct Tx(pac::usart::Usart);

impl embedded_io_async::ErrorType for Tx {
    type Error = Infallible;
}

impl embedded_io_async::Write for Tx {
    async fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
        let u = self.0;
        for b in buf {
            while !u.sr().read().txe() {}
            u.dr().write(|w| w.set_dr(u16::from(*b)));
        }
        Ok(buf.len())
    }

    async fn flush(&mut self) -> Result<(), Infallible> {
        Ok(())
    }
}

/// TIM2 instruction counter.
pub struct Tim2Clock {
    overhead: u32,
}

impl Tim2Clock {
    fn calibrated() -> Self {
        let mut c = Tim2Clock { overhead: 0 };
        let (_, o) = c.measure(|| ());
        c.overhead = o;
        c
    }
}

impl StepClock for Tim2Clock {
    fn measure<R>(&mut self, f: impl FnOnce() -> R) -> (R, u32) {
        cortex_m::interrupt::free(|_| {
            let t0 = pac::TIM2.cnt().read();
            let r = f();
            let t1 = pac::TIM2.cnt().read();
            (r, t1.wrapping_sub(t0).saturating_sub(self.overhead))
        })
    }
    fn count(&mut self) -> u32 {
        pac::TIM2.cnt().read()
    }
}

/// A valve driver that only remembers its duty.
pub struct VirtualPwm(u16);

impl embedded_hal::pwm::ErrorType for VirtualPwm {
    type Error = Infallible;
}

impl embedded_hal::pwm::SetDutyCycle for VirtualPwm {
    fn max_duty_cycle(&self) -> u16 {
        10_000
    }
    fn set_duty_cycle(&mut self, duty: u16) -> Result<(), Infallible> {
        self.0 = duty;
        Ok(())
    }
}

impl DutyReadBack for VirtualPwm {
    fn duty_read_back(&self) -> Option<u16> {
        Some(self.0)
    }
}

/// A digital output that only remembers its level.
#[derive(Clone, Copy)]
pub struct VirtualPin(bool);

impl embedded_hal::digital::ErrorType for VirtualPin {
    type Error = Infallible;
}

impl embedded_hal::digital::OutputPin for VirtualPin {
    fn set_low(&mut self) -> Result<(), Infallible> {
        self.0 = false;
        Ok(())
    }
    fn set_high(&mut self) -> Result<(), Infallible> {
        self.0 = true;
        Ok(())
    }
}

impl ReadBack for VirtualPin {
    fn read_back(&self) -> Option<bool> {
        Some(self.0)
    }
}

// --- SysTick: time driver and software watchdog.

static WATCHDOG_LEFT_MS: AtomicU32 = AtomicU32::new(u32::MAX);

/// Software stand-in for the IWDG: counted down by SysTick, which keeps running when the
/// executor is stuck.
pub struct SoftWatchdog;

impl SoftWatchdog {
    fn start() -> Self {
        WATCHDOG_LEFT_MS.store(WATCHDOG_TIMEOUT_MS, Ordering::Relaxed);
        SoftWatchdog
    }
}

impl pto_firmware::supervisor::Watchdog for SoftWatchdog {
    fn feed(&mut self) {
        WATCHDOG_LEFT_MS.store(WATCHDOG_TIMEOUT_MS, Ordering::Relaxed);
    }
}

struct SysTickDriver {
    ticks: Mutex<Cell<u64>>,
    alarm: Mutex<Cell<u64>>,
    queue: Mutex<RefCell<Queue>>,
}

embassy_time_driver::time_driver_impl!(static DRIVER: SysTickDriver = SysTickDriver {
    ticks: Mutex::new(Cell::new(0)),
    alarm: Mutex::new(Cell::new(u64::MAX)),
    queue: Mutex::new(RefCell::new(Queue::new())),
});

impl embassy_time_driver::Driver for SysTickDriver {
    fn now(&self) -> u64 {
        critical_section::with(|cs| self.ticks.borrow(cs).get())
    }

    fn schedule_wake(&self, at: u64, waker: &core::task::Waker) {
        critical_section::with(|cs| {
            let mut q = self.queue.borrow(cs).borrow_mut();
            if q.schedule_wake(at, waker) {
                let now = self.ticks.borrow(cs).get();
                self.alarm.borrow(cs).set(q.next_expiration(now));
            }
        });
    }
}

#[cortex_m_rt::exception]
fn SysTick() {
    let left = WATCHDOG_LEFT_MS.load(Ordering::Relaxed);
    if left <= 1 {
        defmt::error!(
            "watchdog expired: no feed for {} ms — reset",
            WATCHDOG_TIMEOUT_MS
        );
        exit(EXIT_WATCHDOG);
    }
    WATCHDOG_LEFT_MS.store(left - 1, Ordering::Relaxed);
    critical_section::with(|cs| {
        let t = DRIVER.ticks.borrow(cs).get() + 1;
        DRIVER.ticks.borrow(cs).set(t);
        if t >= DRIVER.alarm.borrow(cs).get() {
            let next = DRIVER.queue.borrow(cs).borrow_mut().next_expiration(t);
            DRIVER.alarm.borrow(cs).set(next);
        }
    });
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    // The location only: formatting the message would link core::fmt's float code (~20 KB).
    match info.location() {
        Some(l) => defmt::error!("panic at {=str}:{=u32}", l.file(), l.line()),
        None => defmt::error!("panic"),
    }
    exit(EXIT_PANIC)
}

#[cortex_m_rt::exception]
unsafe fn HardFault(ef: &cortex_m_rt::ExceptionFrame) -> ! {
    defmt::error!("hard fault at pc {=u32:#010x}", ef.pc());
    exit(EXIT_HARDFAULT)
}
