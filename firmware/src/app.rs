//! The embassy tasks, shared by both boards, wired: hardware comes from `board` through
//! embedded-hal and embedded-io-async traits; each step and each command is the host-tested
//! library's [`Session`], whose events `log.rs` logs.
//!
//! The control task owns the outputs: each step's are driven before anything is logged or
//! awaited, so neither the link nor a log (defmt-rtt never blocks: `disable-blocking-mode`)
//! stands between a trip and the dump valve.

use crate::board;
use crate::log::{TripMemory, log_event, log_setup_error};
use core::cell::Cell;
use core::ops::Range;
use core::sync::atomic::{AtomicU32, Ordering};
use embassy_executor::Spawner;
use embassy_sync::blocking_mutex::Mutex;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::channel::Channel;
use embassy_time::{Duration, Timer, with_timeout};
use embedded_io_async::{Read, Write};
use pto_firmware::control::{ControlConfig, Controller, StepClock};
use pto_firmware::link::{HostReceiver, Transmitter};
use pto_firmware::outputs::Actuators;
use pto_firmware::session::{
    self, BoardLimits, BootChoice, BuiltIn, Handled, Running, Session, readback_reply,
    telemetry_fits,
};
use pto_firmware::store::{ConfigStore, NotStored};
use pto_firmware::supervisor::{Heartbeats, Supervisor, Task, Watchdog};
use pto_firmware::{HEARTBEAT_MS, SUPERVISOR_PERIOD_MS, VERSION};
use pto_model::ModelConfig;
use pto_model::protocol::{
    BoardInfo, FromFirmware, Hello, LinkCounts, MAX_FRAME, PROTOCOL_VERSION, SCHEMA_HASH,
    SensorFrame, ToFirmware,
};
use pto_model::scheduler::SchedulerConfig;
use static_cell::StaticCell;

/// What the tasks get from the board (its types are the board module's aliases).
pub struct Board {
    /// The bench link (host commands, telemetry): its receive and transmit halves.
    pub link: (board::Rx, board::Tx),
    /// The QEMU twin's hardware port: the plant's sensor samples arrive on it and each step's
    /// output goes back on it (the virtual sensors and actuators). `None` on the bench, whose
    /// sensors are sampled by the board.
    pub hardware: Option<(board::Rx, board::Tx)>,
    /// Step-cost clock.
    pub clock: board::Clock,
    /// The valve, the dump valve and the duty solenoids, already at their boot levels
    /// ([`pto_firmware::outputs::Outputs::at_boot`]).
    pub actuators: Actuators<board::Valve, board::Pin>,
    /// What the board says of itself.
    pub info: BoardInfo,
    /// Watchdog.
    pub watchdog: board::Watchdog,
    /// The configuration store's flash and its byte range in it.
    pub store: (board::Flash, Range<u32>),
}

/// A link port: the bench link, or the QEMU twin's hardware port.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum Port {
    /// The bench link (USART1 on the bench; USART2, a pseudo-terminal, under QEMU).
    Link = 0,
    /// The QEMU twin's hardware port (USART1).
    Hardware = 1,
}

impl Port {
    fn tasks(self) -> (Task, Task) {
        match self {
            Port::Link => (Task::Rx, Task::Tx),
            Port::Hardware => (Task::HwRx, Task::HwTx),
        }
    }
}

/// What the control task is given.
pub enum ToControl {
    /// A sensor sample: from the sampling task on the bench (`from: None`), from the hardware
    /// port under QEMU (the step's output goes back on it).
    Sample {
        /// The sample.
        frame: SensorFrame,
        /// The port it came on.
        from: Option<Port>,
    },
    /// A host command, in arrival order, and the port to answer on.
    Command(Port, ToFirmware),
}

/// What the transmit task is given.
pub enum ToTx {
    /// A message to send.
    Send(FromFirmware),
    /// Send everything queued, then stop (QEMU: exit with this code).
    Exit(u8),
}

/// The board's own samples (the bench's sampler) for the control task, on a queue of their own:
/// commands, however many the host sends, never take a sample's place. A sample the queue
/// cannot take is dropped and counted.
static SAMPLES: Channel<CriticalSectionRawMutex, SensorFrame, 2> = Channel::new();
/// What the ports bring the control task, in arrival order: commands (a receive task waits for
/// room) and the twin's samples on its hardware port (dropped and counted when it is full), in
/// one queue so that a command and the samples around it keep their order.
static FROM_PORTS: Channel<CriticalSectionRawMutex, ToControl, 4> = Channel::new();

#[cfg_attr(not(feature = "bench"), allow(dead_code))]
/// Queues one of the board's own samples for the control task; counts it as overrun when the
/// queue is full.
pub fn queue_sample(frame: SensorFrame) {
    if SAMPLES.try_send(frame).is_err() {
        FRAMES_OVERRUN.fetch_add(1, Ordering::Relaxed);
    }
}

/// The next thing for the control task: the board's sample whenever one is waiting, else what
/// the ports brought.
async fn next_for_control() -> ToControl {
    use embassy_futures::select::{Either, select};
    // `select` polls its first future first: a waiting sample always goes ahead.
    match select(SAMPLES.receive(), FROM_PORTS.receive()).await {
        Either::First(frame) => ToControl::Sample { frame, from: None },
        Either::Second(m) => m,
    }
}

/// The control task stops proving itself alive (and so the watchdog expires) when the board's
/// sampler has given it no sample for this long: a dead sampler, or a control loop kept busy
/// by anything else, ends in a reset with the outputs de-energised.
const SAMPLE_STALE_MS: u64 = 100;
/// Frames queued for each port's transmit task.
const TX_QUEUE: usize = 8;
/// Queue slots telemetry leaves free for replies (the host waits for each reply, so a couple
/// are ever outstanding).
const REPLY_SLOTS: usize = 2;
static TO_TX: [Channel<CriticalSectionRawMutex, ToTx, TX_QUEUE>; 2] =
    [Channel::new(), Channel::new()];
static HEARTBEATS: Heartbeats = Heartbeats::new();
/// What each port's receive task took and dropped, by cause, for `Status`.
static LINK_COUNTS: [Mutex<CriticalSectionRawMutex, Cell<LinkCounts>>; 2] = [
    Mutex::new(Cell::new(LinkCounts::ZERO)),
    Mutex::new(Cell::new(LinkCounts::ZERO)),
];
/// Sensor samples dropped because the control task's queue was full (repeated or stale ticks
/// are counted by the controller).
pub static FRAMES_OVERRUN: AtomicU32 = AtomicU32::new(0);
/// Receive errors (overrun, framing) reported by the UART driver.
static RX_ERRORS: AtomicU32 = AtomicU32::new(0);
/// Sensor frames that came on the bench link (only the twin's hardware port carries them).
static SENSORS_ON_LINK: AtomicU32 = AtomicU32::new(0);
/// Telemetry frames the bench link's transmit queue could not take.
static TELEMETRY_DROPPED: AtomicU32 = AtomicU32::new(0);
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

/// Boots the board and spawns the tasks (the control task chooses the configuration).
pub fn start(spawner: Spawner) {
    let b = board::init(spawner);
    let mut watched = heapless::Vec::<Task, { pto_firmware::supervisor::TASKS }>::new();
    let _ = watched.extend_from_slice(&[Task::Control, Task::Rx, Task::Tx]);
    spawner.spawn(rx_task(Port::Link, b.link.0).expect("rx task pool"));
    spawner.spawn(tx_task(Port::Link, b.link.1).expect("tx task pool"));
    if let Some((rx, tx)) = b.hardware {
        let _ = watched.extend_from_slice(&[Task::HwRx, Task::HwTx]);
        spawner.spawn(rx_task(Port::Hardware, rx).expect("rx task pool"));
        spawner.spawn(tx_task(Port::Hardware, tx).expect("tx task pool"));
    }
    spawner.spawn(
        control_task(b.clock, b.store.0, b.store.1, b.actuators, b.info).expect("one control task"),
    );
    spawner.spawn(supervisor_task(b.watchdog, Supervisor::new(&watched)).expect("one supervisor"));
}

#[embassy_executor::task(pool_size = 2)]
async fn rx_task(port: Port, mut rx: board::Rx) {
    let mut asm = HostReceiver::new();
    let mut buf = [0u8; 64];
    let beat = port.tasks().0;
    loop {
        HEARTBEATS.beat(beat);
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
                    ToFirmware::Sensors(frame) if port == Port::Hardware => {
                        let s = ToControl::Sample {
                            frame,
                            from: Some(port),
                        };
                        if FROM_PORTS.try_send(s).is_err() {
                            FRAMES_OVERRUN.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    ToFirmware::Sensors(_) => {
                        SENSORS_ON_LINK.fetch_add(1, Ordering::Relaxed);
                    }
                    other => FROM_PORTS.send(ToControl::Command(port, other)).await,
                }
            }
        }
        LINK_COUNTS[port as usize].lock(|c| c.set(asm.counts));
    }
}

#[embassy_executor::task(pool_size = 2)]
async fn tx_task(port: Port, mut tx: board::Tx) {
    let mut buf = [0u8; MAX_FRAME];
    let mut link = Transmitter::new();
    let beat = port.tasks().1;
    loop {
        HEARTBEATS.beat(beat);
        match with_timeout(
            Duration::from_millis(HEARTBEAT_MS),
            TO_TX[port as usize].receive(),
        )
        .await
        {
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

/// Queues a reply for `port`'s transmit task without waiting: a host that floods commands
/// without reading their replies loses replies (counted), never the control loop's time.
async fn send(port: Port, msg: FromFirmware) {
    if TO_TX[port as usize].try_send(ToTx::Send(msg)).is_err() {
        REPLIES_DROPPED.fetch_add(1, Ordering::Relaxed);
    }
}

/// Replies the transmit queue could not take.
static REPLIES_DROPPED: AtomicU32 = AtomicU32::new(0);

/// The stored configuration when there is a valid one, else the built-in one; the boot log
/// says which and why.
async fn boot_config(
    store: &mut Option<ConfigStore<board::Flash>>,
    sched: &SchedulerConfig,
    cc: &ControlConfig,
) -> (ModelConfig, Running) {
    let src = pto_firmware::built_config::SOURCE;
    let Some(model) = pto_firmware::built_config::model() else {
        defmt::error!("the built-in model configuration does not decode: damaged image");
        board::fail(2)
    };
    let built = BuiltIn {
        model,
        bytes: pto_firmware::built_config::BYTES,
        fingerprint: pto_firmware::built_config::FINGERPRINT,
    };
    let (cfg, running, why) = session::boot_config(store.as_mut(), &built, sched, cc).await;
    match why {
        BootChoice::Stored => {
            defmt::info!(
                "model configuration: stored (fingerprint {=u32:08x}); the built-in one for \
                 {=str} (fingerprint {=u32:08x}) is not used",
                running.info().fingerprint,
                src,
                built.fingerprint
            );
            return (cfg, running);
        }
        BootChoice::StoredNotValid(e) => {
            defmt::warn!("the stored configuration is not valid for this firmware:");
            log_setup_error(&e);
        }
        BootChoice::NotStored(NotStored::Empty) => defmt::info!("no stored configuration"),
        BootChoice::NotStored(why) => {
            defmt::warn!("the stored configuration is not used: {}", why)
        }
    }
    defmt::info!(
        "model configuration: built for {=str} (fingerprint {=u32:08x})",
        src,
        built.fingerprint
    );
    (cfg, running)
}

/// The controller (≈ 11 KB: coefficient tables and state), in a static of its own rather than
/// in the control task's future.
static CONTROLLER: StaticCell<Controller> = StaticCell::new();

#[embassy_executor::task]
async fn control_task(
    mut clock: board::Clock,
    flash: board::Flash,
    range: Range<u32>,
    mut act: Actuators<board::Valve, board::Pin>,
    info: BoardInfo,
) {
    let sched = pto_firmware::built_config::SCHEDULER;
    let cc = pto_firmware::built_config::CONTROL;
    let mut store = ConfigStore::new(flash, range);
    if store.is_none() {
        defmt::error!("configuration store: bad flash range");
    }
    let (model, running) = boot_config(&mut store, &sched, &cc).await;
    // The tables' build, measured (`pto fw-cost` reads the line below under QEMU): ≈ 2.3 M
    // instructions, well inside the watchdog's normal window.
    let t0 = clock.count();
    let made = Controller::new(&model, &sched, &cc);
    let setup_cost = clock.count().wrapping_sub(t0);
    let ctl: &'static mut Controller = match made {
        Ok(c) => CONTROLLER.init(c),
        Err(e) => {
            log_setup_error(&e);
            board::fail(2)
        }
    };
    defmt::info!(
        "controller set up in {=u32} {=str}",
        setup_cost,
        board::CLOCK_UNIT
    );
    if crate::trip_memory::remembered() {
        ctl.boot_tripped();
    }
    ctl.boot_sensor_faults(crate::trip_memory::remembered_sensor_faults());
    let held = ctl.sensor_faults();
    if held != 0 {
        defmt::warn!(
            "sensor faults held at the reset kept (bits {=u8:#06b}: 1 HP, 2 LP, 4 motor, 8 \
             encoder): clear them with the host once the sensor agrees",
            held
        );
    }
    defmt::info!(
        "board: clock {}; last reset: {}; brown-out reset {}",
        info.clock,
        info.reset,
        info.brownout
    );
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
    send(Port::Link, FromFirmware::Hello(hello())).await;
    if !board::SAMPLES_ITSELF {
        // Only the twin has a hardware port.
        send(Port::Hardware, FromFirmware::Hello(hello())).await;
    }
    let limits = BoardLimits {
        samples_itself: board::SAMPLES_ITSELF,
        min_telemetry_every: board::MIN_TELEMETRY_EVERY,
        info,
    };
    let mut s = Session::new(
        ctl,
        sched,
        cc,
        store,
        running,
        pto_firmware::built_config::FINGERPRINT,
        limits,
        board::TELEMETRY_EVERY,
    );
    if ctl.status.tripped {
        defmt::error!(
            "booted tripped: the trip held when the controller reset; valve and dump open"
        );
    }
    let mut last_sample = embassy_time::Instant::now();
    loop {
        if !board::SAMPLES_ITSELF || last_sample.elapsed() < Duration::from_millis(SAMPLE_STALE_MS)
        {
            HEARTBEATS.beat(Task::Control);
        }
        let Ok(msg) = with_timeout(Duration::from_millis(HEARTBEAT_MS), next_for_control()).await
        else {
            continue;
        };
        match msg {
            ToControl::Sample { frame: f, from } => {
                last_sample = embassy_time::Instant::now();
                // The outputs first: the session drives them before it logs anything.
                let Some(st) = s.step(
                    &f,
                    ctl,
                    &mut act,
                    &mut clock,
                    &mut TripMemory,
                    &mut log_event,
                ) else {
                    continue;
                };
                let o = st.out;
                if let Some(port) = from {
                    send(port, o.reply(f.tick)).await;
                }
                if let Some(t) = st.telemetry {
                    // Never wait for the link: telemetry leaves room in the queue for the
                    // replies to commands (which the loop sends waiting), and a frame it
                    // cannot take is counted.
                    let q = &TO_TX[Port::Link as usize];
                    if !telemetry_fits(q.len(), TX_QUEUE, REPLY_SLOTS)
                        || q.try_send(ToTx::Send(FromFirmware::Telemetry(t))).is_err()
                    {
                        TELEMETRY_DROPPED.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
            ToControl::Command(port, cmd) => {
                let h = s
                    .command(cmd, ctl, &mut act, &mut clock, &HEARTBEATS, &mut log_event)
                    .await;
                match h {
                    Handled::Nothing => {}
                    Handled::Reply(r) => send(port, r).await,
                    Handled::Hello => send(port, FromFirmware::Hello(hello())).await,
                    Handled::Status(mut st) => {
                        st.link = LINK_COUNTS[port as usize].lock(Cell::get);
                        st.frames_overrun = st
                            .frames_overrun
                            .wrapping_add(FRAMES_OVERRUN.load(Ordering::Relaxed))
                            .wrapping_add(SENSORS_ON_LINK.load(Ordering::Relaxed));
                        st.bytes_lost = board::bytes_lost() + RX_ERRORS.load(Ordering::Relaxed);
                        st.samples_missed = board::samples_missed();
                        st.stack_unused = crate::stack::unused_bytes();
                        st.replies_dropped = REPLIES_DROPPED.load(Ordering::Relaxed);
                        st.telemetry_dropped = TELEMETRY_DROPPED.load(Ordering::Relaxed);
                        send(port, FromFirmware::Status(st)).await;
                    }
                    Handled::ReadBack(d, o) => {
                        // A GPIO's input register follows its pin within a few AHB cycles
                        // (RM0090 §8.3.1); the wait leaves the driver's output stage time to
                        // settle as well.
                        Timer::after_micros(200).await;
                        send(port, readback_reply(d, o, &act)).await;
                    }
                    Handled::Stall => core::future::pending::<()>().await,
                    Handled::Exit(code) => TO_TX[port as usize].send(ToTx::Exit(code)).await,
                }
            }
        }
    }
}

#[embassy_executor::task]
async fn supervisor_task(mut wdg: board::Watchdog, mut sup: Supervisor) {
    let mut starving = false;
    loop {
        Timer::after_millis(SUPERVISOR_PERIOD_MS).await;
        match sup.check(&HEARTBEATS) {
            None => {
                Watchdog::feed(&mut wdg);
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
