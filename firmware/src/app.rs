//! The embassy tasks, shared by both boards. Hardware comes from `board` through embedded-hal and
//! embedded-io-async traits; the logic lives in the host-tested library.

use crate::board;
use core::cell::Cell;
use core::sync::atomic::{AtomicU32, Ordering};
use embassy_executor::Spawner;
use embassy_sync::blocking_mutex::Mutex;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::channel::Channel;
use embassy_sync::signal::Signal;
use embassy_time::{Duration, Timer, with_timeout};
use embedded_hal::digital::OutputPin;
use embedded_hal::pwm::SetDutyCycle;
use embedded_io_async::{Read, Write};
use pto_firmware::control::{ControlConfig, Controller, SetupError};
use pto_firmware::link::{HostReceiver, Transmitter};
use pto_firmware::supervisor::{Heartbeats, Supervisor, Task, Watchdog as _};
use pto_firmware::{HEARTBEAT_MS, SUPERVISOR_PERIOD_MS, VERSION};
use pto_model::fx::Aperture;
use pto_model::protocol::{
    FromFirmware, Hello, LinkCounts, MAX_FRAME, PROTOCOL_VERSION, Refusal, SCHEMA_HASH,
    SensorFrame, ToFirmware,
};
use pto_model::scheduler::SchedulerConfig;
use static_cell::StaticCell;

/// What the tasks get from the board (its types are the board module's aliases).
pub struct Board {
    /// Link receive.
    pub rx: board::Rx,
    /// Link transmit.
    pub tx: board::Tx,
    /// Step-cost clock.
    pub clock: board::Clock,
    /// Proportional valve.
    pub valve: board::Valve,
    /// Dump valve.
    pub dump: board::Pin,
    /// Duty solenoids HC3.1..HC3.4.
    pub solenoids: [board::Pin; 4],
    /// Watchdog.
    pub watchdog: board::Watchdog,
}

/// What the control task is given.
pub enum ToControl {
    /// A sensor sample (from the link under QEMU, from the sampling task on the bench).
    Sample(SensorFrame),
    /// A host command, in arrival order.
    Command(ToFirmware),
}

/// What the transmit task is given.
pub enum ToTx {
    /// A message to send.
    Send(FromFirmware),
    /// Send everything queued, then stop (QEMU: exit with this code).
    Exit(u8),
}

/// Actuator outputs.
#[derive(Clone, Copy)]
pub struct Outputs {
    /// Valve aperture.
    pub aperture: Aperture,
    /// Dump valve open.
    pub dump: bool,
    /// Solenoids of the cylinders on duty (bit i = HC3.(i+1)).
    pub on_duty: u8,
}

/// Samples and commands for the control task. Samples are dropped (and counted) when it is full.
pub static TO_CONTROL: Channel<CriticalSectionRawMutex, ToControl, 4> = Channel::new();
static TO_TX: Channel<CriticalSectionRawMutex, ToTx, 8> = Channel::new();
static ACTUATE: Signal<CriticalSectionRawMutex, Outputs> = Signal::new();
static HEARTBEATS: Heartbeats = Heartbeats::new();
/// What the receive task took and dropped, by cause, for `Status`.
static LINK_COUNTS: Mutex<CriticalSectionRawMutex, Cell<LinkCounts>> =
    Mutex::new(Cell::new(LinkCounts::ZERO));
/// Sensor samples dropped because the control task's queue was full (repeated or stale ticks
/// are counted by the controller).
pub static FRAMES_OVERRUN: AtomicU32 = AtomicU32::new(0);
/// Receive errors (overrun, framing) reported by the UART driver.
static RX_ERRORS: AtomicU32 = AtomicU32::new(0);
static CONTROLLER: StaticCell<Controller> = StaticCell::new();
/// The model step, for `Hello`.
static DT_LOG2: AtomicU32 = AtomicU32::new(0);

/// What the firmware says of itself at boot and at every host `Hello`.
fn hello() -> Hello {
    Hello {
        protocol: PROTOCOL_VERSION,
        schema: SCHEMA_HASH,
        firmware: VERSION,
        dt_log2: DT_LOG2.load(Ordering::Relaxed) as u8,
    }
}

/// Boots the board, checks the configuration, spawns the tasks.
pub fn start(spawner: Spawner) {
    let b = board::init(spawner);
    let Some(model) = pto_firmware::built_config::model() else {
        defmt::error!("the built-in model configuration does not decode: damaged image");
        board::fail(2)
    };
    defmt::info!(
        "model configuration: built for {=str} (fingerprint {=u32:08x})",
        pto_firmware::built_config::SOURCE,
        pto_firmware::built_config::FINGERPRINT
    );
    let sched = SchedulerConfig::default();
    let cc = ControlConfig::default();
    let ctl = match Controller::new(&model, &sched, &cc) {
        Ok(mut c) => {
            if crate::trip_memory::remembered() {
                c.boot_tripped();
            }
            CONTROLLER.init(c)
        }
        Err(e) => {
            match e {
                SetupError::Model(m) => defmt::error!(
                    "configuration rejected: {=str} = {} outside [{}, {}]",
                    m.field,
                    m.value,
                    m.min,
                    m.max
                ),
                SetupError::Loop(l) => {
                    defmt::error!("transducer loop rejected: {=str} = {}", l.field, l.value)
                }
                SetupError::Control { field, value } => {
                    defmt::error!("control config rejected: {=str} = {}", field, value)
                }
            }
            board::fail(2)
        }
    };
    defmt::info!(
        "pto-firmware {}.{} protocol v{} board={} dt=2^-{} s trip={} bar on_duty={=u8:#06b} telemetry every {} steps",
        VERSION >> 8,
        VERSION & 0xff,
        PROTOCOL_VERSION,
        board::NAME,
        ctl.dt_log2(),
        ctl.trip().to_f32(),
        ctl.duty().0,
        board::TELEMETRY_EVERY
    );
    defmt::info!(
        "scheduler: {}; safe apertures {} % (overpressure), {} % (sensor fault); watchdog {} ms",
        ctl.mode(),
        sched.overpressure_aperture_pct,
        sched.sensor_fault_aperture_pct,
        pto_firmware::WATCHDOG_TIMEOUT_MS
    );
    DT_LOG2.store(u32::from(ctl.dt_log2()), Ordering::Relaxed);
    if TO_TX
        .try_send(ToTx::Send(FromFirmware::Hello(hello())))
        .is_err()
    {
        defmt::error!("transmit queue full at boot");
    }
    spawner.spawn(rx_task(b.rx).expect("one rx task"));
    spawner.spawn(tx_task(b.tx).expect("one tx task"));
    spawner.spawn(control_task(ctl, b.clock).expect("one control task"));
    spawner.spawn(actuator_task(b.valve, b.dump, b.solenoids).expect("one actuator task"));
    spawner.spawn(supervisor_task(b.watchdog).expect("one supervisor task"));
}

#[embassy_executor::task]
async fn rx_task(mut rx: board::Rx) {
    let mut asm = HostReceiver::new();
    let mut buf = [0u8; 64];
    loop {
        HEARTBEATS.beat(Task::Rx);
        let n = match with_timeout(
            Duration::from_millis(HEARTBEAT_MS),
            Read::read(&mut rx, &mut buf),
        )
        .await
        {
            Ok(Ok(n)) => n,
            Ok(Err(_)) => {
                // Framing/overrun errors: the frame in progress fails its CRC and is counted.
                RX_ERRORS.fetch_add(1, Ordering::Relaxed);
                continue;
            }
            Err(_) => continue,
        };
        for b in &buf[..n] {
            if let Some(msg) = asm.push(*b) {
                match msg {
                    ToFirmware::Sensors(f) => {
                        if TO_CONTROL.try_send(ToControl::Sample(f)).is_err() {
                            FRAMES_OVERRUN.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    other => TO_CONTROL.send(ToControl::Command(other)).await,
                }
            }
        }
        LINK_COUNTS.lock(|c| c.set(asm.counts));
    }
}

#[embassy_executor::task]
async fn tx_task(mut tx: board::Tx) {
    let mut buf = [0u8; MAX_FRAME];
    let mut link = Transmitter::new();
    loop {
        HEARTBEATS.beat(Task::Tx);
        match with_timeout(Duration::from_millis(HEARTBEAT_MS), TO_TX.receive()).await {
            Err(_) => {}
            Ok(ToTx::Send(msg)) => match link.encode(&msg, &mut buf) {
                Some(n) => {
                    if tx.write_all(&buf[..n]).await.is_err() {
                        defmt::warn!("link write failed");
                    }
                }
                None => defmt::error!("reply does not fit a frame"),
            },
            Ok(ToTx::Exit(code)) => {
                let _ = tx.flush().await;
                defmt::info!("exit {=u8} on command", code);
                board::exit(code)
            }
        }
    }
}

async fn send(msg: FromFirmware) {
    TO_TX.send(ToTx::Send(msg)).await;
}

#[embassy_executor::task]
async fn control_task(ctl: &'static mut Controller, mut clock: board::Clock) {
    let mut faults_prev = 0u16;
    let mut tripped_prev = ctl.status.tripped;
    if tripped_prev {
        defmt::error!(
            "booted tripped: the trip held when the controller reset; valve and dump open"
        );
    }
    loop {
        HEARTBEATS.beat(Task::Control);
        let Ok(msg) = with_timeout(Duration::from_millis(HEARTBEAT_MS), TO_CONTROL.receive()).await
        else {
            continue;
        };
        match msg {
            ToControl::Sample(f) => {
                if !ctl.fresh(f.tick) {
                    continue;
                }
                let o = ctl.sample(&f, &mut clock);
                ACTUATE.signal(Outputs {
                    aperture: o.applied,
                    dump: o.dump,
                    on_duty: ctl.duty().0,
                });
                let new = o.estimate.faults & !faults_prev;
                if new != 0 {
                    defmt::warn!(
                        "tick {}: new faults {=u16:#06x}, P2 {} bar ± {}",
                        f.tick,
                        new,
                        o.estimate.p2.to_f32(),
                        o.estimate.p2_sigma().to_f32()
                    );
                }
                faults_prev = o.estimate.faults;
                if o.dump != tripped_prev {
                    crate::trip_memory::remember(o.dump);
                    if o.dump {
                        defmt::error!("tick {}: overpressure trip, valve and dump open", f.tick);
                    } else {
                        defmt::info!("tick {}: trip released", f.tick);
                    }
                    tripped_prev = o.dump;
                }
                if f.tick.is_multiple_of(board::TELEMETRY_EVERY) {
                    send(FromFirmware::Output {
                        tick: f.tick,
                        estimate: o.estimate,
                        command: o.command,
                        applied: o.applied,
                        dump: o.dump,
                    })
                    .await;
                }
            }
            ToControl::Command(cmd) => match cmd {
                ToFirmware::Replay { tick, inputs } => {
                    let (estimate, command) = ctl.replay(&inputs, &mut clock);
                    send(FromFirmware::Output {
                        tick,
                        estimate,
                        command,
                        applied: ctl.status.aperture,
                        dump: ctl.status.dump_valve,
                    })
                    .await;
                }
                // The receive task turns sensor frames into samples: never a command.
                ToFirmware::Sensors(_) => {}
                ToFirmware::Ping(n) => send(FromFirmware::Pong(n)).await,
                ToFirmware::Hello => send(FromFirmware::Hello(hello())).await,
                ToFirmware::SetMode(m) => {
                    defmt::info!("mode {}", m);
                    ctl.set_mode(m);
                }
                ToFirmware::SetDuty { on_duty, config } => {
                    defmt::info!("on duty {=u8:#06b}, config {}", on_duty, config + 1);
                    ctl.set_duty(on_duty, config);
                }
                ToFirmware::Reset { p2, lp } => match ctl.reset(p2, lp) {
                    Ok(()) => {
                        defmt::info!("reset: P2 {} bar, LP {} bar", p2.to_f32(), lp.to_f32());
                        faults_prev = 0;
                        send(FromFirmware::ResetDone).await;
                    }
                    Err(hold) => {
                        defmt::warn!("reset refused: the overpressure trip holds ({})", hold);
                        send(FromFirmware::Refused(Refusal::TripHeld(hold))).await;
                    }
                },
                ToFirmware::GetStatus => {
                    let mut s = ctl.status;
                    s.link = LINK_COUNTS.lock(Cell::get);
                    s.frames_overrun = s
                        .frames_overrun
                        .wrapping_add(FRAMES_OVERRUN.load(Ordering::Relaxed));
                    s.bytes_lost = board::bytes_lost() + RX_ERRORS.load(Ordering::Relaxed);
                    send(FromFirmware::Status(s)).await;
                }
                ToFirmware::Stall if ctl.status.tripped => {
                    defmt::warn!("watchdog test refused: the overpressure trip holds");
                    send(FromFirmware::Refused(Refusal::StallWhileTripped)).await;
                }
                ToFirmware::Stall => {
                    defmt::warn!("watchdog test: the control task stops");
                    core::future::pending::<()>().await;
                }
                ToFirmware::Exit(code) => TO_TX.send(ToTx::Exit(code)).await,
            },
        }
    }
}

#[embassy_executor::task]
async fn actuator_task(mut valve: board::Valve, mut dump: board::Pin, mut sol: [board::Pin; 4]) {
    loop {
        let o = ACTUATE.wait().await;
        // Aperture % → duty: Q16.16 percent × max / 100, computed in integers.
        let max = u64::from(SetDutyCycle::max_duty_cycle(&valve));
        let bits = u64::try_from(o.aperture.to_bits().max(0)).unwrap_or(0);
        let duty = ((bits * max) / (100u64 << 16)).min(max) as u16;
        let _ = SetDutyCycle::set_duty_cycle(&mut valve, duty);
        let _ = OutputPin::set_state(&mut dump, o.dump.into());
        for (i, s) in sol.iter_mut().enumerate() {
            let _ = OutputPin::set_state(s, (o.on_duty & (1 << i) != 0).into());
        }
    }
}

#[embassy_executor::task]
async fn supervisor_task(mut wdg: board::Watchdog) {
    let mut sup = Supervisor::default();
    let mut starving = false;
    loop {
        Timer::after_millis(SUPERVISOR_PERIOD_MS).await;
        match sup.check(&HEARTBEATS) {
            None => {
                wdg.feed();
                starving = false;
            }
            Some(t) => {
                if !starving {
                    defmt::error!("task {} silent: watchdog no longer fed", t as u8);
                }
                starving = true;
            }
        }
    }
}
