//! The embassy tasks, shared by both boards. Hardware comes from `board` through embedded-hal and
//! embedded-io-async traits; the logic lives in the host-tested library.
//!
//! The control task owns the outputs: each step's are driven before anything is logged or
//! awaited, so neither the link nor a log (defmt-rtt never blocks: `disable-blocking-mode`)
//! stands between a trip and the dump valve.

use crate::board;
use core::cell::Cell;
use core::ops::Range;
use core::sync::atomic::{AtomicU32, Ordering};
use embassy_executor::Spawner;
use embassy_sync::blocking_mutex::Mutex;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::channel::Channel;
use embassy_time::{Duration, Timer, with_timeout};
use embedded_io_async::{Read, Write};
use pto_firmware::control::{ControlConfig, Controller, ReconfigureError, SetupError, StepClock};
use pto_firmware::link::{HostReceiver, Transmitter};
use pto_firmware::outputs::{Actuators, Outputs};
use pto_firmware::store::{ConfigStore, Loaded, NotStored, stored_config};
use pto_firmware::supervisor::{Heartbeats, Supervisor, Task, Watchdog};
use pto_firmware::upload::Upload;
use pto_firmware::{HEARTBEAT_MS, SUPERVISOR_PERIOD_MS, VERSION};
use pto_model::ModelConfig;
use pto_model::protocol::selftest::OutputReport;
use pto_model::protocol::{
    BoardInfo, CONFIG_MAX_BYTES, Chunk, ConfigInfo, ConfigRefusal, ConfigSource, FromFirmware,
    Hello, LinkCounts, MAX_FRAME, PROTOCOL_VERSION, Refusal, SCHEMA_HASH, SelfTest,
    SelfTestRefusal, SelfTestReply, SensorFrame, Stored, Telemetry, ToFirmware, config_fingerprint,
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
    /// ([`Outputs::at_boot`]).
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
        Ok(cfg) => match valid(&cfg, sched, cc) {
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
    /// twice when storing: ≈ 2.3 M instructions each, inside the watchdog's normal window; the
    /// store's erase raises it).
    async fn commit(
        &mut self,
        ctl: &mut Controller,
        clock: &mut board::Clock,
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
            ctl.check_reconfigure(&cfg, &self.sched, &self.cc)
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
        // Measured like the boot's set-up (logged below; `firmware_config_upload` reads it).
        let t0 = clock.count();
        ctl.reconfigure(&cfg, &self.sched, &self.cc)
            .map_err(refusal)?;
        let cost = clock.count().wrapping_sub(t0);
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
        defmt::info!(
            "configuration applied in {=u32} {=str}",
            cost,
            board::CLOCK_UNIT
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

/// The self-test's answer to a drive: what was commanded, what the hardware reads back.
async fn driven(
    d: pto_model::protocol::selftest::TestDrive,
    o: Outputs,
    act: &Actuators<board::Valve, board::Pin>,
) -> SelfTestReply {
    // A GPIO's input register follows its pin within a few AHB cycles (RM0090 §8.3.1); the
    // wait leaves the driver's output stage time to settle as well.
    Timer::after_micros(200).await;
    let (valve_readback, dump_readback, solenoids_readback) = act.read_back();
    SelfTestReply::Driven(OutputReport {
        drive: d,
        valve: o.aperture,
        dump_open: o.dump_open,
        solenoids: o.on_duty,
        valve_readback,
        dump_readback,
        solenoids_readback,
    })
}

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
    // Written in the first step: a memory that held nothing valid then holds "none".
    let mut held_sensors_prev = u8::MAX;
    let selftest_ends = |ctl: &Controller, why: &str| {
        if ctl.selftest_active() {
            defmt::warn!("self-test ended by {=str}", why);
        }
    };
    if tripped_prev {
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
                if !ctl.fresh(f.tick) {
                    continue;
                }
                let o = ctl.sample(&f, &mut clock);
                // The outputs first: nothing is logged or awaited before they are driven.
                act.apply(&o.outputs());
                let tripped = ctl.status.tripped;
                if tripped != tripped_prev {
                    crate::trip_memory::remember(tripped);
                }
                // The held sensors survive a reset too (a reboot does not clear them).
                let held_sensors = ctl.sensor_faults();
                if held_sensors != held_sensors_prev {
                    crate::trip_memory::remember_sensor_faults(held_sensors);
                    held_sensors_prev = held_sensors;
                }
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
                if tripped != tripped_prev {
                    if tripped {
                        defmt::error!("tick {}: overpressure trip, valve and dump open", f.tick);
                    } else {
                        defmt::info!("tick {}: trip released", f.tick);
                    }
                    tripped_prev = tripped;
                }
                if o.sensor_faults_new != 0 {
                    defmt::error!(
                        "tick {}: sensor fault held (bits {=u8:#06b}: 1 HP, 2 LP, 4 motor, 8 \
                         encoder): its readings withheld, valve at the sensor-fault aperture",
                        f.tick,
                        o.sensor_faults_new
                    );
                }
                if let Some(why) = o.selftest_ended {
                    defmt::warn!("tick {}: self-test ended: {}", f.tick, why);
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
                            on_duty: o.on_duty,
                        },
                    )
                    .await;
                }
                let every = u32::from(s.telemetry_every);
                if every != 0 && f.tick.is_multiple_of(every) {
                    let (_, config) = ctl.duty();
                    let t = FromFirmware::Telemetry(Telemetry {
                        sensors: f,
                        estimate: o.estimate,
                        command: o.command,
                        applied: o.applied,
                        dump: o.dump,
                        on_duty: o.on_duty,
                        config,
                        hydraulic_power: o.estimate.hydraulic_power(),
                        sensor_faults: ctl.sensor_faults(),
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
                // The live estimator is the trip's input: on a board that samples its own
                // sensors, a host's inputs never step it.
                ToFirmware::Replay { .. } if board::SAMPLES_ITSELF => {
                    defmt::warn!("replay refused: this board steps its own sensors");
                    send(port, FromFirmware::Refused(Refusal::ReplayOnTwinOnly)).await;
                }
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
                            on_duty: act.applied().on_duty,
                        },
                    )
                    .await;
                }
                // The receive task turns sensor frames into samples: never a command.
                ToFirmware::Sensors(_) => {}
                ToFirmware::Ping(n) => send(port, FromFirmware::Pong(n)).await,
                ToFirmware::Hello => send(port, FromFirmware::Hello(hello())).await,
                ToFirmware::SetMode(m) => {
                    selftest_ends(ctl, "a mode command");
                    defmt::info!("mode {}", m);
                    ctl.set_mode(m);
                }
                ToFirmware::SetDuty { on_duty, config } => {
                    selftest_ends(ctl, "a duty command");
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
                ToFirmware::Reset { p2, lp } => {
                    let selftest = ctl.selftest_active();
                    match ctl.reset(p2, lp) {
                        Ok(()) => {
                            if selftest {
                                defmt::warn!("self-test ended by a reset");
                            }
                            defmt::info!("reset: P2 {} bar, LP {} bar", p2.to_f32(), lp.to_f32());
                            faults_prev = 0;
                            send(port, FromFirmware::ResetDone).await;
                        }
                        Err(hold) => {
                            defmt::warn!("reset refused: the overpressure trip holds ({})", hold);
                            send(port, FromFirmware::Refused(Refusal::TripHeld(hold))).await;
                        }
                    }
                }
                ToFirmware::GetStatus => {
                    let mut st = ctl.status;
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
                ToFirmware::ConfigBegin { len, crc } => {
                    let r = s.upload.begin(len, crc).map(FromFirmware::ConfigProgress);
                    send(port, config_reply(r)).await;
                }
                ToFirmware::ConfigChunk(c) => {
                    let r = s.upload.chunk(&c).map(FromFirmware::ConfigProgress);
                    send(port, config_reply(r)).await;
                }
                ToFirmware::ConfigCommit { persist } => {
                    // The loop stops for the tables (and the erase): the dump valve open and the
                    // solenoids off meanwhile; the next step drives the outputs again.
                    if ctl.safe_to_apply().is_ok() {
                        act.apply(&Outputs::DE_ENERGISED);
                    }
                    let r = s.commit(ctl, &mut clock, persist).await;
                    match &r {
                        Ok(_) => faults_prev = 0,
                        Err(e) => defmt::warn!("configuration refused: {}", e),
                    }
                    send(port, config_reply(r)).await;
                }
                ToFirmware::ConfigClear => {
                    if ctl.safe_to_apply().is_ok() {
                        act.apply(&Outputs::DE_ENERGISED);
                    }
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
                    let _ = ctl.selftest_end();
                    // Nothing stays energised while the watchdog runs out.
                    act.apply(&Outputs::DE_ENERGISED);
                    defmt::warn!("watchdog test: outputs de-energised, the control task stops");
                    core::future::pending::<()>().await;
                }
                ToFirmware::Exit(code) => TO_TX[port as usize].send(ToTx::Exit(code)).await,
                ToFirmware::ClearSensorFaults => {
                    let before = ctl.sensor_faults();
                    let held = ctl.clear_sensor_faults();
                    defmt::warn!(
                        "sensor faults: {=u8:#06b} cleared by the host, {=u8:#06b} still held",
                        before & !held,
                        held
                    );
                    send(port, FromFirmware::SensorFaults(held)).await;
                }
                ToFirmware::SelfTest(req) => {
                    let r: Result<SelfTestReply, SelfTestRefusal> = match req {
                        SelfTest::Inputs => {
                            ctl.selftest_touch();
                            Ok(SelfTestReply::Inputs(ctl.input_report(info)))
                        }
                        SelfTest::Begin => match ctl.selftest_begin() {
                            Ok(o) => {
                                act.apply(&o);
                                defmt::warn!(
                                    "self-test: outputs de-energised (valve closed, dump open)"
                                );
                                Ok(SelfTestReply::Inputs(ctl.input_report(info)))
                            }
                            Err(e) => Err(e),
                        },
                        SelfTest::Drive(d) => match ctl.selftest_drive(d) {
                            Ok(o) => {
                                act.apply(&o);
                                defmt::info!("self-test: drive {}", d);
                                Ok(driven(d, o, &act).await)
                            }
                            Err(e) => Err(e),
                        },
                        SelfTest::End => match ctl.selftest_end() {
                            Ok(o) => {
                                act.apply(&o);
                                defmt::info!("self-test ended");
                                Ok(SelfTestReply::Ended)
                            }
                            Err(e) => Err(e),
                        },
                    };
                    let reply = match r {
                        Ok(r) => FromFirmware::SelfTest(r),
                        Err(e) => {
                            defmt::warn!("self-test request refused: {}", e);
                            FromFirmware::Refused(Refusal::SelfTest(e))
                        }
                    };
                    send(port, reply).await;
                }
            },
        }
    }
}

/// A configuration step's answer: the reply, or the refusal.
fn config_reply(r: Result<FromFirmware, ConfigRefusal>) -> FromFirmware {
    r.unwrap_or_else(|e| FromFirmware::Refused(Refusal::Config(e)))
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
