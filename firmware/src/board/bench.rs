//! Board: the STM32F405RG bench controller (embassy-stm32). Thin by design: it opens the
//! peripherals, samples the sensors at the model's rate, and hands the tasks embedded-hal /
//! embedded-io-async objects. Flash with `cargo flash-bench` (probe-rs, STM32F405RGTx).
//!
//! Pin map (the one place it is written down; docs/firmware.md copies it):
//!
//! | Function                         | Peripheral        | Pins                     |
//! |----------------------------------|-------------------|--------------------------|
//! | HP transducer, 4–20 mA / 150 Ω   | ADC1 IN0          | PA0                      |
//! | LP transducer, 4–20 mA / 150 Ω   | ADC1 IN1          | PA1                      |
//! | Shaft encoder (quadrature)       | TIM2 encoder mode | PA15 (CH1), PB3 (CH2)    |
//! | Motor speed pickup (quadrature)  | TIM3 encoder mode | PA6 (CH1), PA7 (CH2)     |
//! | Proportional valve command (PWM) | TIM4 CH1, 20 kHz  | PB6 → RC filter → amp    |
//! | Duty solenoids HC3.1..HC3.4      | GPIO out          | PC0, PC1, PC2, PC3       |
//! | Dump (safe) valve                | GPIO out          | PC4                      |
//! | Telemetry / host commands        | USART1 230400 8N1 | PA9 (TX), PA10 (RX)      |
//! | Debug (probe-rs, defmt over RTT) | SWD               | PA13 (SWDIO), PA14 (SWCLK) |
//! | Watchdog                         | IWDG              | —                        |
//! | Configuration store              | flash sectors 10–11 | 0x080C_0000–0x080F_FFFF |

use crate::app::{self, Board, ToControl};
use core::sync::atomic::Ordering;
use defmt_rtt as _;
use embassy_embedded_hal::adapter::BlockingAsync;
use embassy_executor::Spawner;
use embassy_stm32::adc::{Adc, SampleTime};
use embassy_stm32::gpio::{Level, Output, OutputType, Speed};
use embassy_stm32::peripherals::{ADC1, IWDG, PA0, PA1, TIM2, TIM3, TIM4, USART1};
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::low_level::CountingMode;
use embassy_stm32::timer::qei::Qei;
use embassy_stm32::timer::simple_pwm::{PwmPin, SimplePwm, SimplePwmChannel};
use embassy_stm32::usart::{
    BufferedInterruptHandler, BufferedUart, BufferedUartRx, BufferedUartTx,
};
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_stm32::{Peri, bind_interrupts, rcc, usart};
use embassy_time::{Duration, Ticker};
use embedded_storage::nor_flash::{ErrorType, NorFlash, ReadNorFlash};
use pto_firmware::control::StepClock;
use pto_firmware::frontend::Unwrap16;
use pto_model::fx::Rpm;
use pto_model::protocol::SensorFrame;
use static_cell::StaticCell;

/// Board name in the boot log.
pub const NAME: &str = "bench-stm32f405";
/// Telemetry every 16th step by default (64 frames/s at 2^-10 s; docs/bench.md has the link
/// budget at 230 400 baud).
pub const TELEMETRY_EVERY: u16 = 16;
/// The fastest telemetry: every 8th step (128 frames/s of at most 135 B: 75 % of 230 400 baud).
pub const MIN_TELEMETRY_EVERY: u16 = 8;
/// The configuration store: the last two 128 KiB sectors (offsets from the flash's start;
/// `memory.x` ends the code region before them).
const STORE: core::ops::Range<u32> = 0x000C_0000..0x0010_0000;
/// Sampling period: 977 µs ≈ 2^-10 s (1 MHz time base; the model's dt is 2^-10 s exactly, a
/// 0.05 % timing difference the encoder tracker absorbs).
const SAMPLE_US: u64 = 977;
/// Motor pickup counts per revolution (1024-line encoder, quadrature).
const MOTOR_COUNTS_PER_REV: u32 = 4096;
/// Motor speed window, samples (≈ 31 ms).
const MOTOR_WINDOW: usize = 32;

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
pub type Valve = SimplePwmChannel<'static, TIM4>;
/// Digital output.
pub type Pin = Output<'static>;
/// Watchdog.
pub type Watchdog = Iwdg;

static TX_BUF: StaticCell<[u8; 512]> = StaticCell::new();
static RX_BUF: StaticCell<[u8; 256]> = StaticCell::new();

/// 168 MHz from the 8 MHz crystal; peripherals opened; sampling task spawned.
pub fn init(spawner: Spawner) -> Board {
    let mut cfg = embassy_stm32::Config::default();
    cfg.rcc.hse = Some(rcc::Hse {
        freq: Hertz(8_000_000),
        mode: rcc::HseMode::Oscillator,
    });
    cfg.rcc.pll_src = rcc::PllSource::HSE;
    cfg.rcc.pll = Some(rcc::Pll {
        prediv: rcc::PllPreDiv::DIV4,
        mul: rcc::PllMul::MUL168,
        divp: Some(rcc::PllPDiv::DIV2),
        divq: Some(rcc::PllQDiv::DIV7),
        divr: None,
    });
    cfg.rcc.ahb_pre = rcc::AHBPrescaler::DIV1;
    cfg.rcc.apb1_pre = rcc::APBPrescaler::DIV4;
    cfg.rcc.apb2_pre = rcc::APBPrescaler::DIV2;
    cfg.rcc.sys = rcc::Sysclk::PLL1_P;
    let p = embassy_stm32::init(cfg);

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

    let pwm = SimplePwm::new(
        p.TIM4,
        Some(PwmPin::new(p.PB6, OutputType::PushPull)),
        None,
        None,
        None,
        Hertz(20_000),
        CountingMode::EdgeAlignedUp,
    );
    let mut valve = pwm.split().ch1;
    valve.enable();

    let solenoids = [
        Output::new(p.PC0, Level::Low, Speed::Low),
        Output::new(p.PC1, Level::Low, Speed::Low),
        Output::new(p.PC2, Level::Low, Speed::Low),
        Output::new(p.PC3, Level::Low, Speed::Low),
    ];
    let dump = Output::new(p.PC4, Level::Low, Speed::Low);

    let shaft = Qei::new(p.TIM2, p.PA15, p.PB3, Default::default());
    let motor = Qei::new(p.TIM3, p.PA6, p.PA7, Default::default());
    let adc = Adc::new(p.ADC1);
    spawner.spawn(sampling_task(adc, p.PA0, p.PA1, shaft, motor).expect("one sampling task"));

    let mut wdg = IndependentWatchdog::new(p.IWDG, pto_firmware::WATCHDOG_TIMEOUT_MS * 1000);
    wdg.unleash();

    let mut cp = cortex_m::Peripherals::take().unwrap_or_else(|| fail(2));
    cp.DCB.enable_trace();
    cp.DWT.enable_cycle_counter();

    let flash = BlockingAsync::new(WatchedFlash(embassy_stm32::flash::Flash::new_blocking(
        p.FLASH,
    )));

    Board {
        link: (rx, tx),
        hardware: None,
        store: (flash, STORE),
        clock: DwtClock,
        valve,
        dump,
        solenoids,
        watchdog: Iwdg(wdg),
    }
}

/// Reads the sensors every model step and queues the sample for the control task.
#[embassy_executor::task]
async fn sampling_task(
    mut adc: Adc<'static, ADC1>,
    mut hp: Peri<'static, PA0>,
    mut lp: Peri<'static, PA1>,
    shaft: Qei<'static, TIM2>,
    motor: Qei<'static, TIM3>,
) {
    let mut ticker = Ticker::every(Duration::from_micros(SAMPLE_US));
    let mut shaft_count = Unwrap16::new(shaft.count());
    let mut motor_count = Unwrap16::new(motor.count());
    let mut history = [0i32; MOTOR_WINDOW];
    let mut tick: u32 = 0;
    // rpm = Δcounts · 60 / (counts/rev · window s), window = MOTOR_WINDOW · SAMPLE_US µs.
    let rpm_per_count =
        60.0e6 / (MOTOR_COUNTS_PER_REV as f32 * MOTOR_WINDOW as f32 * SAMPLE_US as f32);
    loop {
        ticker.next().await;
        let hp_adc = adc.blocking_read(&mut hp, SampleTime::CYCLES84);
        let lp_adc = adc.blocking_read(&mut lp, SampleTime::CYCLES84);
        let enc = shaft_count.update(shaft.count());
        let m = motor_count.update(motor.count());
        let slot = tick as usize % MOTOR_WINDOW;
        let delta = m.wrapping_sub(history[slot]);
        history[slot] = m;
        let motor = (tick as usize >= MOTOR_WINDOW)
            .then(|| Rpm::from_num(delta.unsigned_abs() as f32 * rpm_per_count));
        let frame = SensorFrame {
            tick,
            encoder: enc,
            hp_adc,
            lp_adc,
            motor,
        };
        if app::TO_CONTROL
            .try_send(ToControl::Sample { frame, from: None })
            .is_err()
        {
            app::FRAMES_OVERRUN.fetch_add(1, Ordering::Relaxed);
        }
        tick = tick.wrapping_add(1);
    }
}

/// Receive errors are counted by the receive task.
pub fn bytes_lost() -> u32 {
    0
}

/// The bench does not stop: `Exit` resets the controller.
pub fn exit(_code: u8) -> ! {
    cortex_m::peripheral::SCB::sys_reset()
}

/// Unrecoverable start-up error: log it (RTT) and halt; the watchdog is not started yet.
pub fn fail(code: u8) -> ! {
    defmt::error!("start-up failed ({=u8}); halted", code);
    loop {
        cortex_m::asm::wfi();
    }
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    // The location only (no core::fmt); then a breakpoint for probe-rs, and the watchdog resets
    // the controller if no debugger is attached.
    match info.location() {
        Some(l) => defmt::error!("panic at {=str}:{=u32}", l.file(), l.line()),
        None => defmt::error!("panic"),
    }
    loop {
        cortex_m::asm::bkpt();
    }
}

/// The independent watchdog.
pub struct Iwdg(IndependentWatchdog<'static, IWDG>);

impl pto_firmware::supervisor::Watchdog for Iwdg {
    fn feed(&mut self) {
        self.0.pet();
    }
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
}

/// The internal flash, with the watchdog's timeout raised ([`unwatched`]) around each erase: a
/// 128 KiB sector takes up to ≈ 2 s, during which every flash read, and so all code, stalls
/// (RM0090 §3.6). The store only writes in the declared safe state.
pub struct WatchedFlash(embassy_stm32::flash::Flash<'static, embassy_stm32::flash::Blocking>);

impl ErrorType for WatchedFlash {
    type Error = embassy_stm32::flash::Error;
}

impl ReadNorFlash for WatchedFlash {
    const READ_SIZE: usize = 1;
    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.0.blocking_read(offset, bytes)
    }
    fn capacity(&self) -> usize {
        embassy_stm32::flash::FLASH_SIZE
    }
}

impl NorFlash for WatchedFlash {
    const WRITE_SIZE: usize = <embassy_stm32::flash::Flash<'static, embassy_stm32::flash::Blocking> as NorFlash>::WRITE_SIZE;
    const ERASE_SIZE: usize = <embassy_stm32::flash::Flash<'static, embassy_stm32::flash::Blocking> as NorFlash>::ERASE_SIZE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        unwatched(|| self.0.blocking_erase(from, to))
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.0.blocking_write(offset, bytes)
    }
}

/// Runs `f`, a long operation the controller does only in its declared safe state (a
/// configuration's tables, ≈ 1 s; a 128 KiB sector erase, up to ≈ 2 s), with the independent
/// watchdog's timeout raised to its longest (prescaler /256, reload 0xFFF: ≈ 32 s); the normal
/// timeout is restored and the counter reloaded at its end.
pub fn unwatched<R>(f: impl FnOnce() -> R) -> R {
    use embassy_stm32::pac::{IWDG, iwdg::vals};
    let (pr, rl) = (IWDG.pr().read().pr(), IWDG.rlr().read().rl());
    let set = |pr: vals::Pr, rl: u16| {
        while IWDG.sr().read().pvu() || IWDG.sr().read().rvu() {}
        IWDG.kr().write(|w| w.set_key(vals::Key::ENABLE));
        IWDG.pr().write(|w| w.set_pr(pr));
        IWDG.rlr().write(|w| w.set_rl(rl));
        IWDG.kr().write(|w| w.set_key(vals::Key::RESET));
    };
    set(vals::Pr::DIVIDE_BY256, 0x0FFF);
    let r = f();
    set(pr, rl);
    r
}
