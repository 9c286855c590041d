//! Board: the STM32F405RG bench controller (embassy-stm32). Thin by design: it brings the chip
//! up in a safe order, samples the sensors at the model's rate, and hands the tasks
//! embedded-hal / embedded-io-async objects; the logic it uses is the host-tested library's
//! (`clocks`, `outputs`, `sampler`, `frontend`, `watchdog`). Flash with `cargo flash-bench`
//! (probe-rs, STM32F405RGTx).
//!
//! Pin map (the one place it is written down; docs/firmware.md copies it):
//!
//! | Function                         | Peripheral          | Pins                       |
//! |----------------------------------|---------------------|----------------------------|
//! | HP transducer, 4–20 mA / 150 Ω   | ADC1 IN0            | PA0                        |
//! | LP transducer, 4–20 mA / 150 Ω   | ADC1 IN1            | PA1                        |
//! | Motor speed pickup (quadrature)  | TIM2 encoder, 32 bit | PA15 (CH1), PB3 (CH2)     |
//! | Shaft encoder (quadrature)       | TIM3 encoder, 16 bit | PA6 (CH1), PA7 (CH2)      |
//! | Proportional valve command (PWM) | TIM4 CH1, 20 kHz    | PB6 → RC filter → amp      |
//! | Duty solenoids HC3.1..HC3.4      | GPIO out, pulled down | PC0, PC1, PC2, PC3       |
//! | Dump valve (normally open)       | GPIO out, pulled down | PC4 (high = closed)      |
//! | Telemetry / host commands        | USART1 230400 8N1   | PA9 (TX), PA10 (RX)        |
//! | Debug (probe-rs, defmt over RTT) | SWD                 | PA13 (SWDIO), PA14 (SWCLK) |
//! | Crystal (`hse_mhz`, 8 MHz)       | HSE                 | PH0, PH1                   |
//! | Watchdog                         | IWDG (LSI)          | —                          |
//! | Configuration store              | flash sectors 10–11 | 0x080C_0000–0x080F_FFFF    |
//!
//! Bring-up order in [`init`]: the crystal (bounded wait, internal oscillator as fall-back) →
//! the outputs at their boot levels (de-energised, or the trip's from the trip memory) → the
//! flash's caches and prefetch → the watchdog (frozen while a debugger halts the core) → the
//! brown-out level (its option-byte write, when the chip has not had it, with the watchdog
//! raised: [`unwatched`]) → the clock monitor → the peripherals. Every flash erase comes after,
//! with the watchdog raised for it too; a table build runs inside the normal window.

#![allow(unsafe_code)]

use crate::app::{self, Board};
use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use defmt_rtt as _;
use embassy_embedded_hal::adapter::BlockingAsync;
use embassy_executor::Spawner;
use embassy_stm32::adc::{Adc, SampleTime, VrefInt};
use embassy_stm32::gpio::{Level, Output, OutputType, Pull, Speed};
use embassy_stm32::pac;
use embassy_stm32::peripherals::{ADC1, PA0, PA1, TIM3, TIM4, USART1};
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::low_level::CountingMode;
use embassy_stm32::timer::qei::Qei;
use embassy_stm32::timer::simple_pwm::{PwmPin, PwmPinConfig, SimplePwm, SimplePwmChannel};
use embassy_stm32::usart::{
    BufferedInterruptHandler, BufferedUart, BufferedUartRx, BufferedUartTx,
};
use embassy_stm32::{Peri, bind_interrupts, rcc, usart};
use embassy_time::Timer;
use embedded_storage::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};
use pto_firmware::built_config::{HSE_MHZ, SCHEDULER};
use pto_firmware::clocks::{self, HSE_STARTUP_TIMEOUT_MS, HSI_HZ};
use pto_firmware::control::StepClock;
use pto_firmware::frontend::{Unwrap16, oversampled, supply_mv_from_vrefint};
use pto_firmware::outputs::{Actuators, DutyReadBack, Outputs, ReadBack};
use pto_firmware::sampler::{CycleTime, MotorSpeed, Pacer, SupplyFilter};
use pto_firmware::watchdog::{self, Iwdg, IwdgRegs};
use pto_model::protocol::{BoardInfo, BrownOut, ClockSource, ResetCause, SensorFrame};
use static_cell::StaticCell;

/// Board name in the boot log.
pub const NAME: &str = "bench-stm32f405";
/// The board samples its own sensors (the control task's heartbeat needs fresh samples; a
/// host's `Replay` is refused).
pub const SAMPLES_ITSELF: bool = true;
/// Telemetry every 16th step by default (64 frames/s at 2^-10 s; docs/bench.md has the link
/// budget at 230 400 baud).
pub const TELEMETRY_EVERY: u16 = 16;

/// What the step clock counts (the DWT cycle counter at the core clock).
pub const CLOCK_UNIT: &str = "cycles";

/// The fastest telemetry: every 8th step (128 frames/s of at most 144 B: 80 % of 230 400 baud).
pub const MIN_TELEMETRY_EVERY: u16 = 8;
/// The configuration store: the last two 128 KiB sectors (offsets from the flash's start;
/// `memory.x` ends the code region before them).
const STORE: core::ops::Range<u32> = 0x000C_0000..0x0010_0000;
/// Sampling period: 977 µs ≈ 2^-10 s (1 MHz time base; the model's dt is 2^-10 s exactly, a
/// 0.05 % timing difference the encoder tracker absorbs).
const SAMPLE_US: u32 = 977;
/// Motor pickup counts per revolution (1024-line encoder, quadrature).
const MOTOR_COUNTS_PER_REV: u32 = 4096;
/// Conversions averaged per loop reading (4 × 4.6 µs at ADCCLK 21 MHz and 84 + 12 cycles).
const OVERSAMPLE: usize = 4;
/// VDDA is measured every this many samples (VREFINT needs ≥ 10 µs of sampling: 480 cycles,
/// 23 µs; 16 times a second is plenty for a supply).
const SUPPLY_EVERY: u32 = 64;
/// `VREFINT_CAL`: VREFINT converted at VDDA = 3.3 V, 30 °C, in the factory (DS8626, "Internal
/// reference voltage calibration values").
const VREFINT_CAL: *const u16 = 0x1FFF_7A2A as *const u16;

bind_interrupts!(struct Irqs {
    USART1 => BufferedInterruptHandler<USART1>;
});

/// The configuration store's flash.
pub type Flash = BlockingAsync<WatchedFlash>;
/// Receive side of the link.
pub type Rx = BufferedUartRx<'static>;
/// Transmit side of the link.
pub type Tx = BufferedUartTx<'static>;
/// Step-cost clock (DWT cycles).
pub type Clock = DwtClock;
/// Valve driver.
pub type Valve = ValvePwm;
/// Digital output.
pub type Pin = GpioOut;
/// Watchdog.
pub type Watchdog = Iwdg<PacIwdg>;

static TX_BUF: StaticCell<[u8; 512]> = StaticCell::new();
static RX_BUF: StaticCell<[u8; 256]> = StaticCell::new();
/// Sample periods missed (a flash erase, a table build): each sample's tick counts them.
static SAMPLES_MISSED: AtomicU32 = AtomicU32::new(0);

/// Starts the crystal and waits for it at most [`HSE_STARTUP_TIMEOUT_MS`] (embassy-stm32 waits
/// forever: a board without a crystal would hang before any log line, its outputs floating).
/// Runs on the internal 16 MHz oscillator, where the chip starts. Returns whether it started.
fn start_crystal() -> bool {
    if HSE_MHZ.is_none() {
        return false;
    }
    pac::RCC.cr().modify(|w| {
        w.set_hsebyp(false);
        w.set_hseon(true);
    });
    for _ in 0..HSE_STARTUP_TIMEOUT_MS {
        if pac::RCC.cr().read().hserdy() {
            return true;
        }
        // 1 ms at the 16 MHz the chip starts on.
        cortex_m::asm::delay(HSI_HZ / 1000);
    }
    pac::RCC.cr().modify(|w| w.set_hseon(false));
    false
}

/// The clocks: 168 MHz through the PLL from the configured crystal, or from the internal
/// oscillator when there is none or it did not start.
fn clock_config(started: bool) -> (embassy_stm32::Config, ClockSource) {
    let (input_hz, pll) = clocks::plan(HSE_MHZ, started);
    let source = match (HSE_MHZ, started) {
        (Some(mhz), true) => ClockSource::Crystal { mhz },
        (Some(mhz), false) => ClockSource::InternalFallback { mhz },
        (None, _) => ClockSource::Internal,
    };
    // The build script checked the crystal (4–26 MHz, whole MHz); the internal oscillator's
    // PLL is a unit-tested constant.
    let Ok(pll) = pll else { fail(1) };
    let mut cfg = embassy_stm32::Config::default();
    if started {
        cfg.rcc.hse = Some(rcc::Hse {
            freq: Hertz(input_hz),
            mode: rcc::HseMode::Oscillator,
        });
        cfg.rcc.pll_src = rcc::PllSource::HSE;
    } else {
        cfg.rcc.pll_src = rcc::PllSource::HSI;
    }
    cfg.rcc.pll = Some(rcc::Pll {
        prediv: rcc::PllPreDiv::from_bits(pll.m),
        mul: rcc::PllMul::from_bits(pll.n),
        divp: Some(rcc::PllPDiv::from_bits(pll.p / 2 - 1)),
        divq: Some(rcc::PllQDiv::from_bits(pll.q)),
        divr: None,
    });
    cfg.rcc.ahb_pre = rcc::AHBPrescaler::DIV1;
    cfg.rcc.apb1_pre = rcc::APBPrescaler::DIV4;
    cfg.rcc.apb2_pre = rcc::APBPrescaler::DIV2;
    cfg.rcc.sys = rcc::Sysclk::PLL1_P;
    (cfg, source)
}

/// Why the chip last reset (`RCC_CSR`, then cleared so the next boot reads its own).
fn reset_cause() -> ResetCause {
    let csr = pac::RCC.csr().read();
    let cause = if csr.wdgrstf() {
        ResetCause::Watchdog
    } else if csr.wwdgrstf() {
        ResetCause::WindowWatchdog
    } else if csr.lpwrrstf() {
        ResetCause::LowPower
    } else if csr.sftrstf() {
        ResetCause::Software
    } else if csr.porrstf() {
        ResetCause::PowerOn
    } else if csr.borrstf() {
        ResetCause::BrownOut
    } else if csr.padrstf() {
        ResetCause::Pin
    } else {
        ResetCause::Unknown
    };
    pac::RCC.csr().modify(|w| w.set_rmvf(true));
    cause
}

/// The brown-out reset level, programmed to level 3 (≈ 2.8 V falling) when it is not: the
/// factory setting is off (reset only at ≈ 1.8 V), below the 2.7 V the flash's x32 erase and
/// the ADC's accuracy need. `FLASH_OPTCR.BOR_LEV`, RM0090 §3.7.1 and §3.7.2 (unlock with the
/// option keys, write, `OPTSTRT`, wait for `BSY`); ST's own STM32F4 examples (the standard
/// peripheral library's `PWR_BOR`) program it from the application the same way, once.
fn brownout_level3() -> BrownOut {
    let level = |bits: u8| match bits & 3 {
        0 => BrownOut::Level3,
        1 => BrownOut::Level2,
        2 => BrownOut::Level1,
        _ => BrownOut::Off,
    };
    let f = pac::FLASH;
    if f.optcr().read().bor_lev() != 0 {
        while f.sr().read().bsy() {}
        f.optkeyr().write_value(0x0819_2A3B);
        f.optkeyr().write_value(0x4C5D_6E7F);
        f.optcr().modify(|w| w.set_bor_lev(0));
        f.optcr().modify(|w| w.set_optstrt(true));
        while f.sr().read().bsy() {}
        f.optcr().modify(|w| w.set_optlock(true));
    }
    level(f.optcr().read().bor_lev())
}

/// Enables the flash's instruction and data caches (RM0090 §3.5.2; embassy sets the wait
/// states, 5 at 168 MHz, and leaves them off: every fetch would wait) and, on silicon past
/// revision A, its prefetch (ES0182: the prefetch is not to be used on revision A; REV_ID
/// 0x1000 there, and 0 where the ID cannot be read without a debugger: prefetch off then too).
/// Returns whether prefetch is on.
fn enable_flash_caches() -> bool {
    let rev = pac::DBGMCU.idcode().read().rev_id();
    let prefetch = rev != 0 && rev != 0x1000;
    reset_flash_caches(true, true);
    pac::FLASH.acr().modify(|w| w.set_prften(prefetch));
    prefetch
}

/// Every output de-energised through the registers (valve duty 0, PC0–PC4 low: solenoids off,
/// dump valve open), for the fault handlers, which cannot reach the drivers. A write to a
/// peripheral whose clock is still off is ignored: before `init` the pull-downs hold them.
fn outputs_off() {
    pac::TIM4.ccr(0).write_value(pac::timer::regs::Ccr1ch(0));
    pac::GPIOC.bsrr().write(|w| {
        for pin in 0..5 {
            w.set_br(pin, true);
        }
    });
}

/// 168 MHz from the configured crystal (or the internal oscillator); the outputs at their boot
/// levels; caches; watchdog; brown-out level; peripherals; sampling task spawned.
pub fn init(spawner: Spawner) -> Board {
    // The watchdog first (on the LSI, independent of the clocks): every wait that follows is
    // bounded by it, the crystal's 100 ms within its ≥ 250 ms.
    let watchdog = Iwdg::start(PacIwdg, watchdog::NORMAL);
    let started = start_crystal();
    let (cfg, clock) = clock_config(started);
    let p = embassy_stm32::init(cfg);

    // The outputs before anything else: de-energised, or the trip's levels when the trip held
    // at the reset (the dump valve open either way; the pull-downs held them until now).
    let at_boot = Outputs::at_boot(
        crate::trip_memory::remembered(),
        SCHEDULER.overpressure_aperture_pct,
    );
    let pwm = SimplePwm::new(
        p.TIM4,
        Some(PwmPin::new_with_config(
            p.PB6,
            PwmPinConfig {
                output_type: OutputType::PushPull,
                // 20 kHz into an RC filter: the slowest edge rate (2 MHz) is ample and rings
                // least.
                speed: Speed::Low,
                pull: Pull::Down,
            },
        )),
        None,
        None,
        None,
        Hertz(20_000),
        CountingMode::EdgeAlignedUp,
    );
    let mut ch1 = pwm.split().ch1;
    ch1.enable();
    let actuators = Actuators::new(
        ValvePwm(ch1),
        GpioOut::new(p.PC4, 4),
        [
            GpioOut::new(p.PC0, 0),
            GpioOut::new(p.PC1, 1),
            GpioOut::new(p.PC2, 2),
            GpioOut::new(p.PC3, 3),
        ],
        at_boot,
    );

    let prefetch = enable_flash_caches();
    // A debugger's halt freezes the watchdog (RM0090 §38.16.4, DBGMCU_APB1_FZ.DBG_IWDG_STOP):
    // a breakpoint holds the outputs where they are instead of resetting the chip
    // (docs/bench.md: halt only with the hydraulics depressurised).
    pac::DBGMCU.apb1fzr().modify(|w| w.set_iwdg(true));
    let reset = reset_cause();
    defmt::info!(
        "flash: caches on, prefetch {=str}",
        if prefetch {
            "on"
        } else {
            "off (revision A, or its ID unreadable)"
        }
    );
    let brownout = unwatched(brownout_level3);
    if started {
        // The clock monitor: a crystal that stops raises the NMI (RM0090 §7.2.7), which resets
        // the controller; it then boots on the internal oscillator.
        pac::RCC.cr().modify(|w| w.set_csson(true));
    }

    let mut ucfg = usart::Config::default();
    ucfg.baudrate = 230_400;
    let uart = match BufferedUart::new(
        p.USART1,
        p.PA10,
        p.PA9,
        TX_BUF.init([0; 512]),
        RX_BUF.init([0; 256]),
        Irqs,
        ucfg,
    ) {
        Ok(u) => u,
        Err(_) => fail(2),
    };
    let (tx, rx) = uart.split();

    // Quadrature inputs with the timers' digital filter: fSAMPLING = fDTS/8 (10.5 MHz at the
    // 84 MHz timer clock), N = 8: an edge must hold 0.76 µs (RM0090 §18.4.7, IC1F/IC2F). The
    // motor's fastest edges (3 000 rpm, 4 096 counts/rev) are 4.9 µs apart.
    let motor = Qei::new(p.TIM2, p.PA15, p.PB3, Default::default());
    let shaft = Qei::new(p.TIM3, p.PA6, p.PA7, Default::default());
    for filter in [
        |v| pac::TIM2.ccmr_input(0).modify(v),
        |v| pac::TIM3.ccmr_input(0).modify(v),
    ] {
        filter(|w: &mut pac::timer::regs::CcmrInput2ch| {
            w.set_icf(0, pac::timer::vals::FilterValue::FDTS_DIV8_N8);
            w.set_icf(1, pac::timer::vals::FilterValue::FDTS_DIV8_N8);
        });
    }
    // The motor count is TIM2's full 32 bits (embassy's Qei sets a 16-bit reload).
    pac::TIM2.arr().write_value(u32::MAX);
    // The cycle counter before the sampler: it is the sampler's time base.
    let mut cp = cortex_m::Peripherals::take().unwrap_or_else(|| fail(2));
    cp.DCB.enable_trace();
    cp.DWT.enable_cycle_counter();
    let adc = Adc::new(p.ADC1);
    let vrefint = adc.enable_vrefint();
    // SAFETY: a half-word of the system memory's OTP area, readable at any time.
    let cal = unsafe { core::ptr::read_volatile(VREFINT_CAL) };
    spawner.spawn(
        sampling_task(adc, p.PA0, p.PA1, vrefint, shaft, motor, cal).expect("one sampling task"),
    );

    let flash = BlockingAsync::new(WatchedFlash(embassy_stm32::flash::Flash::new_blocking(
        p.FLASH,
    )));

    Board {
        link: (rx, tx),
        hardware: None,
        store: (flash, STORE),
        clock: DwtClock,
        actuators,
        info: BoardInfo {
            clock,
            reset,
            brownout,
        },
        watchdog,
    }
}

/// Reads the sensors every model step and queues the sample for the control task.
#[embassy_executor::task]
async fn sampling_task(
    mut adc: Adc<'static, ADC1>,
    mut hp: Peri<'static, PA0>,
    mut lp: Peri<'static, PA1>,
    mut vrefint: VrefInt,
    shaft: Qei<'static, TIM3>,
    // Kept so its pins stay in their timer's function; counted through TIM2's 32-bit register.
    _motor: Qei<'static, embassy_stm32::peripherals::TIM2>,
    cal: u16,
) {
    let cycles = cortex_m::peripheral::DWT::cycle_count;
    let mut time = CycleTime::new(cycles(), clocks::SYSCLK_HZ);
    let mut pacer = Pacer::new(time.micros(cycles()), SAMPLE_US);
    let mut shaft_count = Unwrap16::new(shaft.count());
    let mut motor = MotorSpeed::new(MOTOR_COUNTS_PER_REV);
    let mut supply = SupplyFilter::default();
    let mut supply_mv = None;
    let mut tick: u32 = 0;
    loop {
        // Waits are relative: the time base is the cycle counter, which runs through a flash
        // erase's stall (embassy's 16-bit time driver does not).
        // Never longer than a period: a cycle counter that stopped (a debugger clearing
        // DEMCR.TRCENA) cannot stretch the sampling.
        let wait = pacer
            .deadline_us()
            .saturating_sub(time.micros(cycles()))
            .min(u64::from(SAMPLE_US));
        Timer::after_micros(wait).await;
        let now = time.micros(cycles());
        let missed = pacer.woke(now);
        if missed > 0 {
            // A stall (a flash erase, a table build): the periods it took are time, not samples.
            motor.restart();
            tick = tick.wrapping_add(missed);
            SAMPLES_MISSED.fetch_add(missed, Ordering::Relaxed);
        }
        if tick.is_multiple_of(SUPPLY_EVERY) || supply_mv.is_none() {
            let v = adc.blocking_read(&mut vrefint, SampleTime::CYCLES480);
            supply_mv = Some(supply.take(supply_mv_from_vrefint(v, cal)));
        }
        let mut h = [0u16; OVERSAMPLE];
        let mut l = [0u16; OVERSAMPLE];
        for (a, b) in h.iter_mut().zip(l.iter_mut()) {
            *a = adc.blocking_read(&mut hp, SampleTime::CYCLES84);
            *b = adc.blocking_read(&mut lp, SampleTime::CYCLES84);
        }
        let frame = SensorFrame {
            tick,
            encoder: shaft_count.update(shaft.count()),
            hp_adc: oversampled(&h),
            lp_adc: oversampled(&l),
            motor: motor.sample(now, pac::TIM2.cnt().read()),
            supply_mv,
        };
        app::queue_sample(frame);
        tick = tick.wrapping_add(1);
    }
}

/// Receive errors are counted by the receive task.
pub fn bytes_lost() -> u32 {
    0
}

/// Sample periods missed in stalls.
pub fn samples_missed() -> u32 {
    SAMPLES_MISSED.load(Ordering::Relaxed)
}

/// The bench does not stop: `Exit` resets the controller.
pub fn exit(_code: u8) -> ! {
    cortex_m::peripheral::SCB::sys_reset()
}

/// Unrecoverable start-up error: every output de-energised, the code logged (RTT), then a safe
/// stop that keeps the watchdog fed (a reset would only fail the same way again): the
/// controller stays there until it is power-cycled or reflashed.
pub fn fail(code: u8) -> ! {
    outputs_off();
    defmt::error!(
        "start-up failed ({=u8}): outputs de-energised (valve closed, dump open); halted",
        code
    );
    let mut w = Iwdg::running(PacIwdg, watchdog::NORMAL);
    loop {
        w.feed();
        cortex_m::asm::delay(clocks::SYSCLK_HZ / 100);
    }
}

/// A fault handler has begun: a second fault (one inside the logger, which a nested log call
/// would only repeat) resets at once.
static FAULTING: AtomicBool = AtomicBool::new(false);

/// The first step of every fault handler: the outputs de-energised; on a fault within a fault,
/// the reset at once, without logging.
fn fault_entry() {
    outputs_off();
    if FAULTING.swap(true, Ordering::Relaxed) {
        cortex_m::peripheral::SCB::sys_reset();
    }
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    // The outputs first; then the location only (no core::fmt); then a reset, the trip memory
    // kept. Never a breakpoint: DHCSR.C_DEBUGEN outlives a probe's session, and with the
    // watchdog frozen on halt the controller would stay stopped until powered off.
    fault_entry();
    match info.location() {
        Some(l) => defmt::error!("panic at {=str}:{=u32}: reset", l.file(), l.line()),
        None => defmt::error!("panic: reset"),
    }
    cortex_m::peripheral::SCB::sys_reset()
}

#[cortex_m_rt::exception]
unsafe fn HardFault(ef: &cortex_m_rt::ExceptionFrame) -> ! {
    fault_entry();
    defmt::error!("hard fault at pc {=u32:#010x}: reset", ef.pc());
    cortex_m::peripheral::SCB::sys_reset()
}

#[cortex_m_rt::exception]
unsafe fn NonMaskableInt() {
    // The clock monitor: the crystal stopped (the chip already runs on the internal
    // oscillator, the PLL off). Reset: the next boot uses the internal oscillator, logged.
    fault_entry();
    defmt::error!("the crystal stopped (clock security system): reset");
    cortex_m::peripheral::SCB::sys_reset()
}

/// The IWDG's registers.
pub struct PacIwdg;

impl IwdgRegs for PacIwdg {
    fn updating(&self) -> (bool, bool) {
        let sr = pac::IWDG.sr().read();
        (sr.pvu(), sr.rvu())
    }
    fn key(&mut self, key: u16) {
        pac::IWDG
            .kr()
            .write(|w| w.set_key(pac::iwdg::vals::Key::from_bits(key)));
    }
    fn set_pr(&mut self, pr: u8) {
        pac::IWDG
            .pr()
            .write(|w| w.set_pr(pac::iwdg::vals::Pr::from_bits(pr)));
    }
    fn set_rlr(&mut self, rlr: u16) {
        pac::IWDG.rlr().write(|w| w.set_rl(rlr));
    }
}

/// Runs `f`, a long operation the controller does only in its declared safe state (a flash
/// erase), with the watchdog raised to
/// [`watchdog::RAISED`] (≥ 4 s at the fastest LSI), then back at [`watchdog::NORMAL`], set from
/// the known setting (never read back) and the counter reloaded.
pub fn unwatched<R>(f: impl FnOnce() -> R) -> R {
    Iwdg::running(PacIwdg, watchdog::NORMAL).unwatched(watchdog::RAISED, f)
}

/// DWT cycle counter.
pub struct DwtClock;

impl StepClock for DwtClock {
    fn measure<R>(&mut self, f: impl FnOnce() -> R) -> (R, u32) {
        cortex_m::interrupt::free(|_| {
            let t0 = cortex_m::peripheral::DWT::cycle_count();
            let r = f();
            (r, cortex_m::peripheral::DWT::cycle_count().wrapping_sub(t0))
        })
    }
    fn count(&mut self) -> u32 {
        cortex_m::peripheral::DWT::cycle_count()
    }
}

/// The valve's PWM channel, read back from its compare register.
pub struct ValvePwm(SimplePwmChannel<'static, TIM4>);

impl embedded_hal::pwm::ErrorType for ValvePwm {
    type Error = core::convert::Infallible;
}

impl embedded_hal::pwm::SetDutyCycle for ValvePwm {
    fn max_duty_cycle(&self) -> u16 {
        embedded_hal::pwm::SetDutyCycle::max_duty_cycle(&self.0)
    }
    fn set_duty_cycle(&mut self, duty: u16) -> Result<(), Self::Error> {
        let _ = embedded_hal::pwm::SetDutyCycle::set_duty_cycle(&mut self.0, duty);
        Ok(())
    }
}

impl DutyReadBack for ValvePwm {
    fn duty_read_back(&self) -> Option<u16> {
        Some(pac::TIM4.ccr(0).read().ccr())
    }
}

/// A push-pull output on port C read back from its pin (the input register follows the pin, so
/// a driver shorted to a rail reads wrong).
pub struct GpioOut(Output<'static>, u8);

impl GpioOut {
    /// PC`n`, driven low (de-energised) at once.
    fn new(pin: Peri<'static, impl embassy_stm32::gpio::Pin>, n: u8) -> Self {
        GpioOut(Output::new(pin, Level::Low, Speed::Low), n)
    }
}

impl embedded_hal::digital::ErrorType for GpioOut {
    type Error = core::convert::Infallible;
}

impl embedded_hal::digital::OutputPin for GpioOut {
    fn set_low(&mut self) -> Result<(), Self::Error> {
        self.0.set_low();
        Ok(())
    }
    fn set_high(&mut self) -> Result<(), Self::Error> {
        self.0.set_high();
        Ok(())
    }
}

impl ReadBack for GpioOut {
    fn read_back(&self) -> Option<bool> {
        // `Output::is_set_high` reads the output register; the pin's level is the input's.
        Some(pac::GPIOC.idr().read().idr(usize::from(self.1)) == pac::gpio::vals::Idr::HIGH)
    }
}

/// The internal flash: sector erases at x32 parallelism (embassy's erase leaves `PSIZE` at its
/// reset value, x8: up to 4 s a sector instead of 2 s), the watchdog raised around each
/// ([`unwatched`]: every flash read, and so all code, stalls meanwhile, RM0090 §3.6), and the
/// caches flushed after every erase and write (a cached line would serve the old bytes). The
/// store writes only in the declared safe state.
pub struct WatchedFlash(embassy_stm32::flash::Flash<'static, embassy_stm32::flash::Blocking>);

/// A flash operation failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, defmt::Format)]
pub enum FlashError {
    /// embassy's driver (reads, writes).
    Driver(embassy_stm32::flash::Error),
    /// An erase outside the store's whole sectors.
    NotSectors,
    /// The erase ended with an error flag in `FLASH_SR` (its bits).
    Erase(u32),
}

impl NorFlashError for FlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            FlashError::NotSectors => NorFlashErrorKind::NotAligned,
            _ => NorFlashErrorKind::Other,
        }
    }
}

impl ErrorType for WatchedFlash {
    type Error = FlashError;
}

/// Sectors 5–11 of the F405 are 128 KiB from offset 0x2_0000 (RM0090 §3.3, table 5).
const SECTOR_128K: u32 = 0x2_0000;

/// Disables and resets the instruction and data caches, then enables them as asked (RM0090
/// §3.5.2: the reset bits work only with the caches off).
fn reset_flash_caches(icen: bool, dcen: bool) {
    let acr = pac::FLASH.acr();
    acr.modify(|w| {
        w.set_icen(false);
        w.set_dcen(false);
    });
    acr.modify(|w| {
        w.set_icrst(true);
        w.set_dcrst(true);
    });
    acr.modify(|w| {
        w.set_icrst(false);
        w.set_dcrst(false);
    });
    acr.modify(|w| {
        w.set_icen(icen);
        w.set_dcen(dcen);
    });
}

/// Flushes the caches after an erase or a write, leaving them as they were.
fn flush_flash_caches() {
    let r = pac::FLASH.acr().read();
    reset_flash_caches(r.icen(), r.dcen());
}

/// Erases one 128 KiB sector at x32 (RM0090 §3.6.3, sector erase; §3.6.2 parallelism).
fn erase_sector(snb: u8) -> Result<(), FlashError> {
    let f = pac::FLASH;
    while f.sr().read().bsy() {}
    if f.cr().read().lock() {
        f.keyr().write_value(0x4567_0123);
        f.keyr().write_value(0xCDEF_89AB);
    }
    // Clear the error flags (write 1 to clear) left by an earlier operation.
    f.sr().write_value(f.sr().read());
    f.cr().write(|w| {
        w.set_psize(pac::flash::vals::Psize::PSIZE32);
        w.set_ser(true);
        w.set_snb(snb);
    });
    f.cr().modify(|w| w.set_strt(true));
    while f.sr().read().bsy() {}
    let sr = f.sr().read();
    f.cr().write(|w| w.set_lock(true));
    flush_flash_caches();
    // PGSERR, PGPERR, PGAERR, WRPERR (bits 7..4), OPERR (bit 1).
    let errors = sr.0 & 0xF2;
    if errors != 0 {
        Err(FlashError::Erase(errors))
    } else {
        Ok(())
    }
}

impl ReadNorFlash for WatchedFlash {
    const READ_SIZE: usize = 1;
    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.0
            .blocking_read(offset, bytes)
            .map_err(FlashError::Driver)
    }
    fn capacity(&self) -> usize {
        embassy_stm32::flash::FLASH_SIZE
    }
}

impl NorFlash for WatchedFlash {
    const WRITE_SIZE: usize = embassy_stm32::flash::WRITE_SIZE;
    const ERASE_SIZE: usize = SECTOR_128K as usize;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        if from < STORE.start
            || to > STORE.end
            || !from.is_multiple_of(SECTOR_128K)
            || !to.is_multiple_of(SECTOR_128K)
        {
            return Err(FlashError::NotSectors);
        }
        let mut at = from;
        while at < to {
            let snb = (5 + (at - SECTOR_128K) / SECTOR_128K) as u8;
            unwatched(|| erase_sector(snb))?;
            at += SECTOR_128K;
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let r = self
            .0
            .blocking_write(offset, bytes)
            .map_err(FlashError::Driver);
        flush_flash_caches();
        r
    }
}
