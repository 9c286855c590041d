//! The embassy tasks, shared by both boards. Hardware comes from `board` through embedded-hal and
//! embedded-io-async traits; the logic lives in the host-tested library.

use crate::board;
use core::cell::Cell;
use core::ops::Range;
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
use pto_firmware::control::{ControlConfig, Controller, ReconfigureError, SetupError};
use pto_firmware::link::{HostReceiver, Transmitter};
use pto_firmware::store::{ConfigStore, Loaded, NotStored, stored_config};
use pto_firmware::supervisor::{Heartbeats, Supervisor, Task, Watchdog as _};
use pto_firmware::upload::Upload;
use pto_firmware::{HEARTBEAT_MS, SUPERVISOR_PERIOD_MS, VERSION};
use pto_model::ModelConfig;
use pto_model::fx::Aperture;
use pto_model::protocol::{
    CONFIG_MAX_BYTES, Chunk, ConfigInfo, ConfigRefusal, ConfigSource, FromFirmware, Hello,
    LinkCounts, MAX_FRAME, PROTOCOL_VERSION, Refusal, SCHEMA_HASH, SensorFrame, Stored, Telemetry,
    ToFirmware, config_fingerprint,
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
    /// Proportional valve.
    pub valve: board::Valve,
    /// Dump valve.
    pub dump: board::Pin,
    /// Duty solenoids HC3.1..HC3.4.
    pub solenoids: [board::Pin; 4],
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
/// Frames queued for each port's transmit task.
const TX_QUEUE: usize = 8;
/// Queue slots telemetry leaves free for replies (the host waits for each reply, so a couple
/// are ever outstanding).
const REPLY_SLOTS: usize = 2;
static TO_TX: [Channel<CriticalSectionRawMutex, ToTx, TX_QUEUE>; 2] =
    [Channel::new(), Channel::new()];
static ACTUATE: Signal<CriticalSectionRawMutex, Outputs> = Signal::new();
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
    spawner.spawn(control_task(b.clock, b.store.0, b.store.1).expect("one control task"));
    spawner.spawn(actuator_task(b.valve, b.dump, b.solenoids).expect("one actuator task"));
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
                        if TO_CONTROL.try_send(s).is_err() {
                            FRAMES_OVERRUN.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    ToFirmware::Sensors(_) => {
                        SENSORS_ON_LINK.fetch_add(1, Ordering::Relaxed);
                    }
                    other => TO_CONTROL.send(ToControl::Command(port, other)).await,
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

async fn send(port: Port, msg: FromFirmware) {
    TO_TX[port as usize].send(ToTx::Send(msg)).await;
}

fn log_setup_error(e: &SetupError) {
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
}

/// The configuration that runs and its bytes (for `GetConfig` and `ConfigRead`).
struct Running {
    bytes: [u8; CONFIG_MAX_BYTES],
    info: ConfigInfo,
}

impl Running {
    fn new(bytes: &[u8], source: ConfigSource) -> Running {
        let mut b = [0u8; CONFIG_MAX_BYTES];
        b[..bytes.len()].copy_from_slice(bytes);
        Running {
            bytes: b,
            info: ConfigInfo {
                source,
                fingerprint: config_fingerprint(bytes),
                len: bytes.len() as u16,
            },
        }
    }

    fn bytes(&self) -> &[u8] {
        &self.bytes[..usize::from(self.info.len)]
    }
}

/// The stored configuration when there is a valid one, else the built-in one; the boot log
/// says which and why.
async fn boot_config(
    store: &mut Option<ConfigStore<board::Flash>>,
    sched: &SchedulerConfig,
    cc: &ControlConfig,
) -> (ModelConfig, Running) {
    let src = pto_firmware::built_config::SOURCE;
    let built_in = pto_firmware::built_config::FINGERPRINT;
    let Some(model) = pto_firmware::built_config::model() else {
        defmt::error!("the built-in model configuration does not decode: damaged image");
        board::fail(2)
    };
    let mut buf = [0u8; CONFIG_MAX_BYTES];
    let loaded = match store.as_mut() {
        Some(s) => s.load(&mut buf).await,
        None => Loaded::Failed,
    };
    match stored_config(loaded, &buf, built_in, model.dt_log2) {
        Ok(cfg) => match board::unwatched(|| valid(&cfg, sched, cc)) {
            Ok(()) => {
                let len = match loaded {
                    Loaded::Found { len, .. } => len,
                    _ => 0,
                };
                let bytes = &buf[..len];
                defmt::info!(
                    "model configuration: stored (fingerprint {=u32:08x}); the built-in one for \
                     {=str} (fingerprint {=u32:08x}) is not used",
                    config_fingerprint(bytes),
                    src,
                    built_in
                );
                return (cfg, Running::new(bytes, ConfigSource::Stored));
            }
            Err(e) => {
                defmt::warn!("the stored configuration is not valid for this firmware:");
                log_setup_error(&e);
            }
        },
        Err(NotStored::Empty) => defmt::info!("no stored configuration"),
        Err(why) => defmt::warn!("the stored configuration is not used: {}", why),
    }
    defmt::info!(
        "model configuration: built for {=str} (fingerprint {=u32:08x})",
        src,
        built_in
    );
    (
        model,
        Running::new(pto_firmware::built_config::BYTES, ConfigSource::BuiltIn),
    )
}

/// Whether a controller can be made (built on the stack and dropped, not kept in a future).
fn valid(
    model: &ModelConfig,
    sched: &SchedulerConfig,
    cc: &ControlConfig,
) -> Result<(), SetupError> {
    Controller::new(model, sched, cc).map(|_| ())
}

/// The controller (≈ 11 KB: coefficient tables and state), in a static of its own rather than
/// in the control task's future.
static CONTROLLER: StaticCell<Controller> = StaticCell::new();

/// What the control task keeps between steps besides the controller.
struct Session {
    sched: SchedulerConfig,
    cc: ControlConfig,
    store: Option<ConfigStore<board::Flash>>,
    upload: Upload,
    running: Running,
    telemetry_every: u16,
}

impl Session {
    /// `ConfigCommit`: checks (the declared safe state, then the configuration), stores when
    /// asked, applies. The controller stops stepping meanwhile (its tables are built once,
    /// twice when storing: ≈ 136 M instructions each), with the watchdog's timeout raised.
    async fn commit(
        &mut self,
        ctl: &mut Controller,
        persist: bool,
    ) -> Result<FromFirmware, ConfigRefusal> {
        ctl.safe_to_apply().map_err(ConfigRefusal::NotSafe)?;
        let (cfg, bytes) = self.upload.finish()?;
        let refusal = |e| match e {
            ReconfigureError::NotSafe(n) => ConfigRefusal::NotSafe(n),
            ReconfigureError::Setup(SetupError::Model(m)) => ConfigRefusal::from(m),
            ReconfigureError::Setup(_) => ConfigRefusal::Decode,
        };
        // Before storing, checked without changing anything (no controller is kept across the
        // store's await: one is ≈ 11 KB); without storing, `reconfigure` below checks it itself,
        // and the tables are built once.
        if persist {
            board::unwatched(|| ctl.check_reconfigure(&cfg, &self.sched, &self.cc))
                .map_err(refusal)?;
        }
        let stored = if persist {
            let store = self.store.as_mut().ok_or(ConfigRefusal::Store)?;
            defmt::info!("storing the configuration (the controller stalls during an erase)");
            let r = store
                .save(bytes, pto_firmware::built_config::FINGERPRINT)
                .await;
            r.map_err(|e| {
                defmt::error!("configuration store: {}", e);
                ConfigRefusal::Store
            })?;
            Stored::Yes
        } else {
            Stored::No
        };
        board::unwatched(|| ctl.reconfigure(&cfg, &self.sched, &self.cc)).map_err(refusal)?;
        // Every task stalled with us: none of them is stuck.
        HEARTBEATS.beat_all();
        let source = if persist {
            ConfigSource::UploadedStored
        } else {
            ConfigSource::Uploaded
        };
        self.running = Running::new(bytes, source);
        defmt::info!(
            "model configuration: uploaded (fingerprint {=u32:08x}), {=str}; estimator restarted",
            self.running.info.fingerprint,
            if persist { "stored" } else { "not stored" }
        );
        Ok(FromFirmware::ConfigApplied {
            info: self.running.info,
            stored,
        })
    }

    /// `ConfigClear`: erases the store (in the declared safe state).
    async fn clear(&mut self, ctl: &Controller) -> Result<FromFirmware, ConfigRefusal> {
        ctl.safe_to_apply().map_err(ConfigRefusal::NotSafe)?;
        let store = self.store.as_mut().ok_or(ConfigRefusal::Store)?;
        let r = store.clear().await;
        HEARTBEATS.beat_all();
        r.map_err(|_| ConfigRefusal::Store)?;
        // What runs is no longer stored.
        if self.running.info.source == ConfigSource::UploadedStored {
            self.running.info.source = ConfigSource::Uploaded;
        }
        defmt::info!("configuration store cleared: the next boot runs the built-in one");
        Ok(FromFirmware::ConfigCleared)
    }
}

#[embassy_executor::task]
async fn control_task(mut clock: board::Clock, flash: board::Flash, range: Range<u32>) {
    let sched = pto_firmware::built_config::SCHEDULER;
    let cc = pto_firmware::built_config::CONTROL;
    let mut store = ConfigStore::new(flash, range);
    if store.is_none() {
        defmt::error!("configuration store: bad flash range");
    }
    let (model, running) = boot_config(&mut store, &sched, &cc).await;
    let ctl: &'static mut Controller =
        match board::unwatched(|| Controller::new(&model, &sched, &cc)) {
            Ok(c) => CONTROLLER.init(c),
            Err(e) => {
                log_setup_error(&e);
                board::fail(2)
            }
        };
    if crate::trip_memory::remembered() {
        ctl.boot_tripped();
    }
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
    send(Port::Hardware, FromFirmware::Hello(hello())).await;
    let mut s = Session {
        sched,
        cc,
        store,
        upload: Upload::new(),
        running,
        telemetry_every: board::TELEMETRY_EVERY,
    };
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
            ToControl::Sample { frame: f, from } => {
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
                if let Some(port) = from {
                    send(
                        port,
                        FromFirmware::Output {
                            tick: f.tick,
                            estimate: o.estimate,
                            command: o.command,
                            applied: o.applied,
                            dump: o.dump,
                        },
                    )
                    .await;
                }
                let every = u32::from(s.telemetry_every);
                if every != 0 && f.tick.is_multiple_of(every) {
                    let (on_duty, config) = ctl.duty();
                    let t = FromFirmware::Telemetry(Telemetry {
                        sensors: f,
                        estimate: o.estimate,
                        command: o.command,
                        applied: o.applied,
                        dump: o.dump,
                        on_duty,
                        config,
                        hydraulic_power: o.estimate.hydraulic_power(),
                    });
                    // Never wait for the link: telemetry leaves room in the queue for the
                    // replies to commands (which the loop sends waiting), and a frame it
                    // cannot take is counted.
                    let q = &TO_TX[Port::Link as usize];
                    if q.len() + REPLY_SLOTS > TX_QUEUE || q.try_send(ToTx::Send(t)).is_err() {
                        TELEMETRY_DROPPED.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
            ToControl::Command(port, cmd) => match cmd {
                ToFirmware::Replay { tick, inputs } => {
                    let (estimate, command) = ctl.replay(&inputs, &mut clock);
                    send(
                        port,
                        FromFirmware::Output {
                            tick,
                            estimate,
                            command,
                            applied: ctl.status.aperture,
                            dump: ctl.status.dump_valve,
                        },
                    )
                    .await;
                }
                // The receive task turns sensor frames into samples: never a command.
                ToFirmware::Sensors(_) => {}
                ToFirmware::Ping(n) => send(port, FromFirmware::Pong(n)).await,
                ToFirmware::Hello => send(port, FromFirmware::Hello(hello())).await,
                ToFirmware::SetMode(m) => {
                    defmt::info!("mode {}", m);
                    ctl.set_mode(m);
                }
                ToFirmware::SetDuty { on_duty, config } => {
                    defmt::info!("on duty {=u8:#06b}, config {}", on_duty, config + 1);
                    ctl.set_duty(on_duty, config);
                }
                ToFirmware::SetTelemetry { every } => {
                    // No faster than the link carries (0 stays off).
                    let every = if every == 0 {
                        0
                    } else {
                        every.max(board::MIN_TELEMETRY_EVERY)
                    };
                    defmt::info!("telemetry every {=u16} steps", every);
                    s.telemetry_every = every;
                    send(port, FromFirmware::Pong(u32::from(every))).await;
                }
                ToFirmware::Reset { p2, lp } => match ctl.reset(p2, lp) {
                    Ok(()) => {
                        defmt::info!("reset: P2 {} bar, LP {} bar", p2.to_f32(), lp.to_f32());
                        faults_prev = 0;
                        send(port, FromFirmware::ResetDone).await;
                    }
                    Err(hold) => {
                        defmt::warn!("reset refused: the overpressure trip holds ({})", hold);
                        send(port, FromFirmware::Refused(Refusal::TripHeld(hold))).await;
                    }
                },
                ToFirmware::GetStatus => {
                    let mut st = ctl.status;
                    st.link = LINK_COUNTS[port as usize].lock(Cell::get);
                    st.frames_overrun = st
                        .frames_overrun
                        .wrapping_add(FRAMES_OVERRUN.load(Ordering::Relaxed))
                        .wrapping_add(SENSORS_ON_LINK.load(Ordering::Relaxed));
                    st.bytes_lost = board::bytes_lost() + RX_ERRORS.load(Ordering::Relaxed);
                    st.telemetry_dropped = TELEMETRY_DROPPED.load(Ordering::Relaxed);
                    send(port, FromFirmware::Status(st)).await;
                }
                ToFirmware::ConfigBegin { len, crc } => {
                    let r = s.upload.begin(len, crc).map(FromFirmware::ConfigProgress);
                    send(port, config_reply(r)).await;
                }
                ToFirmware::ConfigChunk(c) => {
                    let r = s.upload.chunk(&c).map(FromFirmware::ConfigProgress);
                    send(port, config_reply(r)).await;
                }
                ToFirmware::ConfigCommit { persist } => {
                    let r = s.commit(ctl, persist).await;
                    match &r {
                        Ok(_) => faults_prev = 0,
                        Err(e) => defmt::warn!("configuration refused: {}", e),
                    }
                    send(port, config_reply(r)).await;
                }
                ToFirmware::ConfigClear => {
                    let r = s.clear(ctl).await;
                    if let Err(e) = &r {
                        defmt::warn!("configuration store not cleared: {}", e);
                    }
                    send(port, config_reply(r)).await;
                }
                ToFirmware::GetConfig => {
                    send(port, FromFirmware::ConfigInfo(s.running.info)).await;
                }
                ToFirmware::ConfigRead { offset } => {
                    let bytes = s.running.bytes();
                    send(
                        port,
                        FromFirmware::ConfigData {
                            total: bytes.len() as u16,
                            chunk: Chunk::of(bytes, usize::from(offset)),
                        },
                    )
                    .await;
                }
                ToFirmware::Stall if ctl.status.tripped => {
                    defmt::warn!("watchdog test refused: the overpressure trip holds");
                    send(port, FromFirmware::Refused(Refusal::StallWhileTripped)).await;
                }
                ToFirmware::Stall => {
                    defmt::warn!("watchdog test: the control task stops");
                    core::future::pending::<()>().await;
                }
                ToFirmware::Exit(code) => TO_TX[port as usize].send(ToTx::Exit(code)).await,
            },
        }
    }
}

/// A configuration step's answer: the reply, or the refusal.
fn config_reply(r: Result<FromFirmware, ConfigRefusal>) -> FromFirmware {
    r.unwrap_or_else(|e| FromFirmware::Refused(Refusal::Config(e)))
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
async fn supervisor_task(mut wdg: board::Watchdog, mut sup: Supervisor) {
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
