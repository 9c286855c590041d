//! The control task's session: each sample's step and each host command, in the order that
//! keeps the bench safe, generic over the board (its actuators, the store's [`NorFlash`], the
//! step clock, the memory that survives a reset) so that every ordering is tested on the host.
//! The firmware's `app.rs` wires the tasks around it (queues, the boot's configuration, the
//! link counters in `Status`, the self-test's settling wait) and its `log.rs` logs the
//! [`Event`]s.
//!
//! The orderings this module keeps, each with a test below:
//! - A step drives the outputs before anything else happens (nothing is logged or remembered
//!   first).
//! - A configuration is committed or the store cleared only in the controller's declared safe
//!   state ([`Controller::safe_to_apply`]); the outputs are de-energised while the loop stops
//!   for the tables or the flash, and only then.
//! - A configuration to store is checked whole before the store is touched, stored and read
//!   back before it is applied: a store that fails leaves the previous configuration running
//!   (and stored).
//! - A commit keeps the trip latch's count and the sensors held faulted; the trip itself is
//!   never released by a commit (a tripped controller is not in the safe state).
//! - A host's replay never steps a board that samples its own sensors; the watchdog test is
//!   refused while the trip holds and de-energises everything before the task stops.
//!
//! The board's "unwatched" section (the watchdog raised around a flash erase, RM0090 §3.6) is
//! inside its [`NorFlash`] (`board::bench::WatchedFlash`): the session only sees a slow store,
//! and proves every task alive again after it ([`Heartbeats::beat_all`]).

use crate::control::{ControlConfig, Controller, ReconfigureError, SetupError, StepClock, StepOut};
use crate::outputs::{Actuators, DutyReadBack, Outputs, ReadBack};
use crate::selftest::Ended;
use crate::store::{ConfigStore, Loaded, NotStored, StoreError, stored_config};
use crate::supervisor::Heartbeats;
use crate::upload::Upload;
use embedded_hal::digital::OutputPin;
use embedded_hal::pwm::SetDutyCycle;
use embedded_storage_async::nor_flash::NorFlash;
use pto_model::ModelConfig;
use pto_model::fx::Pressure;
use pto_model::protocol::selftest::TestDrive;
use pto_model::protocol::{
    BoardInfo, CONFIG_MAX_BYTES, Chunk, ConfigInfo, ConfigRefusal, ConfigSource, FromFirmware,
    Refusal, SelfTest, SelfTestRefusal, SelfTestReply, SensorFrame, Status, Stored, Telemetry,
    ToFirmware, TripHold, config_fingerprint,
};
use pto_model::scheduler::{Mode, SchedulerConfig};

/// The configuration the firmware was built with (`built_config` on the target).
#[derive(Debug, Clone)]
pub struct BuiltIn<'a> {
    /// Its model configuration.
    pub model: ModelConfig,
    /// Its encoded bytes.
    pub bytes: &'a [u8],
    /// Their fingerprint: a stored configuration is taken only from a firmware built with the
    /// same one.
    pub fingerprint: u32,
}

/// The configuration that runs and its bytes (for `GetConfig` and `ConfigRead`).
#[derive(Debug, Clone)]
pub struct Running {
    bytes: [u8; CONFIG_MAX_BYTES],
    info: ConfigInfo,
}

impl Running {
    /// `bytes` (at most [`CONFIG_MAX_BYTES`]: longer ones are cut there) from `source`.
    pub fn new(bytes: &[u8], source: ConfigSource) -> Running {
        let n = bytes.len().min(CONFIG_MAX_BYTES);
        let mut b = [0u8; CONFIG_MAX_BYTES];
        b[..n].copy_from_slice(&bytes[..n]);
        Running {
            bytes: b,
            info: ConfigInfo {
                source,
                fingerprint: config_fingerprint(&bytes[..n]),
                len: n as u16,
            },
        }
    }

    /// Its bytes.
    pub fn bytes(&self) -> &[u8] {
        &self.bytes[..usize::from(self.info.len)]
    }

    /// Where it came from, its fingerprint and length.
    pub fn info(&self) -> ConfigInfo {
        self.info
    }
}

/// Why the boot runs the configuration it runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum BootChoice {
    /// The stored one.
    Stored,
    /// The built-in one: nothing usable was stored.
    NotStored(NotStored),
    /// The built-in one: the stored one decodes but no controller can be made from it here.
    StoredNotValid(SetupError),
}

/// The configuration to boot with: the stored one when there is a valid one, else the built-in
/// one, and why.
pub async fn boot_config<F: NorFlash>(
    store: Option<&mut ConfigStore<F>>,
    built: &BuiltIn<'_>,
    sched: &SchedulerConfig,
    cc: &ControlConfig,
) -> (ModelConfig, Running, BootChoice) {
    let mut buf = [0u8; CONFIG_MAX_BYTES];
    let loaded = match store {
        Some(s) => s.load(&mut buf).await,
        None => Loaded::Failed,
    };
    let why = match stored_config(loaded, &buf, built.fingerprint, built.model.dt_log2) {
        Ok(cfg) => match Controller::new(&cfg, sched, cc) {
            Ok(_) => {
                let len = match loaded {
                    Loaded::Found { len, .. } => len,
                    _ => 0,
                };
                let running = Running::new(&buf[..len], ConfigSource::Stored);
                return (cfg, running, BootChoice::Stored);
            }
            Err(e) => BootChoice::StoredNotValid(e),
        },
        Err(why) => BootChoice::NotStored(why),
    };
    (
        built.model.clone(),
        Running::new(built.bytes, ConfigSource::BuiltIn),
        why,
    )
}

/// What the board keeps across a controller reset (RAM the reset leaves alone on the bench).
pub trait ResetMemory {
    /// Remembers whether the trip latch holds.
    fn remember_trip(&mut self, tripped: bool);
    /// Remembers the sensors held faulted.
    fn remember_sensor_faults(&mut self, bits: u8);
}

/// What the session tells the log, in the order it happened.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Event {
    /// A step raised fault flags not raised in the step before.
    NewFaults {
        /// The sample's tick.
        tick: u32,
        /// The new flags.
        faults: u16,
        /// The estimate, bar.
        p2: Pressure,
        /// Its 1σ, bar.
        p2_sigma: Pressure,
    },
    /// The overpressure trip latched in this step: valve and dump open.
    Tripped(u32),
    /// The trip released in this step.
    TripReleased(u32),
    /// Sensors the controller now holds faulted (bits: 1 HP, 2 LP, 4 motor, 8 encoder).
    SensorFaultsHeld {
        /// The sample's tick.
        tick: u32,
        /// The newly held sensors.
        bits: u8,
    },
    /// A self-test ended by itself in a step.
    SelfTestTimedOut {
        /// The sample's tick.
        tick: u32,
        /// Why.
        why: Ended,
    },
    /// A running self-test ended by a host command (named).
    SelfTestEndedBy(&'static str),
    /// A replay refused: this board steps its own sensors.
    ReplayRefused,
    /// A new scheduler mode.
    Mode(Mode),
    /// New cylinders on duty (bits) and geometry (0..=3).
    Duty {
        /// Cylinders on duty.
        on_duty: u8,
        /// Geometry.
        config: u8,
    },
    /// Telemetry every this many steps (0: off).
    Telemetry(u16),
    /// The estimator restarted from the host's pressures.
    Reset {
        /// P2, bar.
        p2: Pressure,
        /// LP, bar.
        lp: Pressure,
    },
    /// A reset refused: the trip holds.
    ResetRefused(TripHold),
    /// The store's write begins (the controller stalls during an erase).
    Storing,
    /// The store failed.
    StoreFailed(StoreError),
    /// A configuration applied.
    Applied {
        /// Its fingerprint.
        fingerprint: u32,
        /// Whether it was stored.
        stored: bool,
        /// The tables' build, in the clock's unit.
        cost: u32,
    },
    /// A configuration refused.
    ConfigRefused(ConfigRefusal),
    /// The store cleared.
    Cleared,
    /// The store not cleared.
    ClearRefused(ConfigRefusal),
    /// The watchdog test refused: the trip holds.
    StallRefused,
    /// The watchdog test: outputs de-energised, the control task stops.
    Stall,
    /// Sensor faults the host cleared, and those still held.
    SensorFaultsCleared {
        /// Cleared.
        cleared: u8,
        /// Still held.
        held: u8,
    },
    /// The self-test began: outputs de-energised.
    SelfTestBegun,
    /// A self-test drive.
    SelfTestDrive(TestDrive),
    /// The self-test ended by the host.
    SelfTestEnded,
    /// A self-test request refused.
    SelfTestRefused(SelfTestRefusal),
}

/// What is left to the control task after a command.
#[derive(Debug, Clone, PartialEq)]
pub enum Handled {
    /// Nothing to send.
    Nothing,
    /// Send this reply.
    Reply(FromFirmware),
    /// Send the firmware's `Hello`.
    Hello,
    /// Send the controller's status, once the task has added its link counters.
    Status(Status),
    /// A self-test drive: wait for the driver's output stage to settle, then reply with what
    /// [`readback_reply`] makes of the actuators.
    ReadBack(TestDrive, Outputs),
    /// The watchdog test: the outputs are de-energised; stop the task (never feed again).
    Stall,
    /// Send everything queued, then stop (QEMU: exit with this code).
    Exit(u8),
}

/// What a step leaves to the control task.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stepped {
    /// The step (already driven to the actuators).
    pub out: StepOut,
    /// Telemetry due in this step.
    pub telemetry: Option<Telemetry>,
}

/// What the board is: fixed at build time.
#[derive(Debug, Clone, Copy)]
pub struct BoardLimits {
    /// The board samples its own sensors (the bench): a host's replay never steps it.
    pub samples_itself: bool,
    /// Telemetry no more often than every this many steps (what the link carries).
    pub min_telemetry_every: u16,
    /// What the board says of itself.
    pub info: BoardInfo,
}

/// What the control task keeps between steps besides the controller.
pub struct Session<F: NorFlash> {
    sched: SchedulerConfig,
    cc: ControlConfig,
    store: Option<ConfigStore<F>>,
    upload: Upload,
    running: Running,
    built_in: u32,
    board: BoardLimits,
    telemetry_every: u16,
    faults_prev: u16,
    tripped_prev: bool,
    held_sensors_prev: Option<u8>,
}

impl<F: NorFlash> Session<F> {
    /// A session for `ctl` (whose trip state it starts from), running `running`, built with a
    /// configuration of fingerprint `built_in`, with telemetry every `telemetry_every` steps.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctl: &Controller,
        sched: SchedulerConfig,
        cc: ControlConfig,
        store: Option<ConfigStore<F>>,
        running: Running,
        built_in: u32,
        board: BoardLimits,
        telemetry_every: u16,
    ) -> Self {
        Session {
            sched,
            cc,
            store,
            upload: Upload::new(),
            running,
            built_in,
            board,
            telemetry_every,
            faults_prev: 0,
            tripped_prev: ctl.status.tripped,
            // Written in the first step: a memory that held nothing valid then holds "none".
            held_sensors_prev: None,
        }
    }

    /// The configuration that runs.
    pub fn running(&self) -> &Running {
        &self.running
    }

    /// Telemetry every this many steps (0: off).
    pub fn telemetry_every(&self) -> u16 {
        self.telemetry_every
    }

    /// One sample's step: the outputs driven first, then the reset memory, then the log.
    /// `None` when the sample is not newer than the last one stepped (counted as an overrun).
    pub fn step<C: StepClock, V, P, M>(
        &mut self,
        f: &SensorFrame,
        ctl: &mut Controller,
        act: &mut Actuators<V, P>,
        clock: &mut C,
        memory: &mut M,
        log: &mut impl FnMut(Event),
    ) -> Option<Stepped>
    where
        V: SetDutyCycle + DutyReadBack,
        P: OutputPin + ReadBack,
        M: ResetMemory,
    {
        if !ctl.fresh(f.tick) {
            return None;
        }
        let o = ctl.sample(f, clock);
        act.apply(&o.outputs());
        let tripped = ctl.status.tripped;
        if tripped != self.tripped_prev {
            memory.remember_trip(tripped);
        }
        // The held sensors survive a reset too (a reboot does not clear them).
        let held = ctl.sensor_faults();
        if self.held_sensors_prev != Some(held) {
            memory.remember_sensor_faults(held);
            self.held_sensors_prev = Some(held);
        }
        let new = o.estimate.faults & !self.faults_prev;
        if new != 0 {
            log(Event::NewFaults {
                tick: f.tick,
                faults: new,
                p2: o.estimate.p2,
                p2_sigma: o.estimate.p2_sigma(),
            });
        }
        self.faults_prev = o.estimate.faults;
        if tripped != self.tripped_prev {
            log(if tripped {
                Event::Tripped(f.tick)
            } else {
                Event::TripReleased(f.tick)
            });
            self.tripped_prev = tripped;
        }
        if o.sensor_faults_new != 0 {
            log(Event::SensorFaultsHeld {
                tick: f.tick,
                bits: o.sensor_faults_new,
            });
        }
        if let Some(why) = o.selftest_ended {
            log(Event::SelfTestTimedOut { tick: f.tick, why });
        }
        let every = u32::from(self.telemetry_every);
        let telemetry = (every != 0 && f.tick.is_multiple_of(every)).then(|| {
            let (_, config) = ctl.duty();
            Telemetry {
                sensors: *f,
                estimate: o.estimate,
                command: o.command,
                applied: o.applied,
                dump: o.dump,
                on_duty: o.on_duty,
                config,
                hydraulic_power: o.estimate.hydraulic_power(),
                sensor_faults: held,
            }
        });
        Some(Stepped { out: o, telemetry })
    }

    /// One host command. `beats` is told that every task stalled with this one (a table build,
    /// a flash erase) and so none of them is stuck.
    #[allow(clippy::too_many_arguments)]
    pub async fn command<C: StepClock, V, P>(
        &mut self,
        cmd: ToFirmware,
        ctl: &mut Controller,
        act: &mut Actuators<V, P>,
        clock: &mut C,
        beats: &Heartbeats,
        log: &mut impl FnMut(Event),
    ) -> Handled
    where
        V: SetDutyCycle + DutyReadBack,
        P: OutputPin + ReadBack,
    {
        let selftest_ends = |ctl: &Controller, log: &mut dyn FnMut(Event), why| {
            if ctl.selftest_active() {
                log(Event::SelfTestEndedBy(why));
            }
        };
        let reply = match cmd {
            // The live estimator is the trip's input: on a board that samples its own sensors,
            // a host's inputs never step it.
            ToFirmware::Replay { .. } if self.board.samples_itself => {
                log(Event::ReplayRefused);
                FromFirmware::Refused(Refusal::ReplayOnTwinOnly)
            }
            ToFirmware::Replay { tick, inputs } => {
                let (estimate, command) = ctl.replay(&inputs, clock);
                FromFirmware::Output {
                    tick,
                    estimate,
                    command,
                    applied: ctl.status.aperture,
                    dump: ctl.status.dump_valve,
                    on_duty: act.applied().on_duty,
                }
            }
            // The receive task turns sensor frames into samples: never a command.
            ToFirmware::Sensors(_) => return Handled::Nothing,
            ToFirmware::Ping(n) => FromFirmware::Pong(n),
            ToFirmware::Hello => return Handled::Hello,
            ToFirmware::SetMode(m) => {
                selftest_ends(ctl, log, "a mode command");
                log(Event::Mode(m));
                ctl.set_mode(m);
                return Handled::Nothing;
            }
            ToFirmware::SetDuty { on_duty, config } => {
                selftest_ends(ctl, log, "a duty command");
                log(Event::Duty { on_duty, config });
                ctl.set_duty(on_duty, config);
                return Handled::Nothing;
            }
            ToFirmware::SetTelemetry { every } => {
                // No faster than the link carries (0 stays off).
                let every = if every == 0 {
                    0
                } else {
                    every.max(self.board.min_telemetry_every)
                };
                log(Event::Telemetry(every));
                self.telemetry_every = every;
                FromFirmware::Pong(u32::from(every))
            }
            ToFirmware::Reset { p2, lp } => {
                let selftest = ctl.selftest_active();
                match ctl.reset(p2, lp) {
                    Ok(()) => {
                        if selftest {
                            log(Event::SelfTestEndedBy("a reset"));
                        }
                        log(Event::Reset { p2, lp });
                        self.faults_prev = 0;
                        FromFirmware::ResetDone
                    }
                    Err(hold) => {
                        log(Event::ResetRefused(hold));
                        FromFirmware::Refused(Refusal::TripHeld(hold))
                    }
                }
            }
            ToFirmware::GetStatus => return Handled::Status(ctl.status),
            ToFirmware::ConfigBegin { len, crc } => config_reply(
                self.upload
                    .begin(len, crc)
                    .map(FromFirmware::ConfigProgress),
            ),
            ToFirmware::ConfigChunk(c) => {
                config_reply(self.upload.chunk(&c).map(FromFirmware::ConfigProgress))
            }
            ToFirmware::ConfigCommit { persist } => {
                // The loop stops for the tables (and the erase): the dump valve open and the
                // solenoids off meanwhile; the next step drives the outputs again.
                if ctl.safe_to_apply().is_ok() {
                    act.apply(&Outputs::DE_ENERGISED);
                }
                let r = self.commit(ctl, clock, persist, beats, log).await;
                match &r {
                    Ok(_) => self.faults_prev = 0,
                    Err(e) => log(Event::ConfigRefused(*e)),
                }
                config_reply(r)
            }
            ToFirmware::ConfigClear => {
                if ctl.safe_to_apply().is_ok() {
                    act.apply(&Outputs::DE_ENERGISED);
                }
                let r = self.clear(ctl, beats, log).await;
                if let Err(e) = &r {
                    log(Event::ClearRefused(*e));
                }
                config_reply(r)
            }
            ToFirmware::GetConfig => FromFirmware::ConfigInfo(self.running.info),
            ToFirmware::ConfigRead { offset } => {
                let bytes = self.running.bytes();
                FromFirmware::ConfigData {
                    total: bytes.len() as u16,
                    chunk: Chunk::of(bytes, usize::from(offset)),
                }
            }
            ToFirmware::Stall if ctl.status.tripped => {
                log(Event::StallRefused);
                FromFirmware::Refused(Refusal::StallWhileTripped)
            }
            ToFirmware::Stall => {
                let _ = ctl.selftest_end();
                // Nothing stays energised while the watchdog runs out.
                act.apply(&Outputs::DE_ENERGISED);
                log(Event::Stall);
                return Handled::Stall;
            }
            ToFirmware::Exit(code) => return Handled::Exit(code),
            ToFirmware::ClearSensorFaults => {
                let before = ctl.sensor_faults();
                let held = ctl.clear_sensor_faults();
                log(Event::SensorFaultsCleared {
                    cleared: before & !held,
                    held,
                });
                FromFirmware::SensorFaults(held)
            }
            ToFirmware::SelfTest(req) => {
                let r = match req {
                    SelfTest::Inputs => {
                        ctl.selftest_touch();
                        Ok(SelfTestReply::Inputs(ctl.input_report(self.board.info)))
                    }
                    SelfTest::Begin => ctl.selftest_begin().map(|o| {
                        act.apply(&o);
                        log(Event::SelfTestBegun);
                        SelfTestReply::Inputs(ctl.input_report(self.board.info))
                    }),
                    SelfTest::Drive(d) => match ctl.selftest_drive(d) {
                        Ok(o) => {
                            act.apply(&o);
                            log(Event::SelfTestDrive(d));
                            return Handled::ReadBack(d, o);
                        }
                        Err(e) => Err(e),
                    },
                    SelfTest::End => ctl.selftest_end().map(|o| {
                        act.apply(&o);
                        log(Event::SelfTestEnded);
                        SelfTestReply::Ended
                    }),
                };
                match r {
                    Ok(r) => FromFirmware::SelfTest(r),
                    Err(e) => {
                        log(Event::SelfTestRefused(e));
                        FromFirmware::Refused(Refusal::SelfTest(e))
                    }
                }
            }
        };
        Handled::Reply(reply)
    }

    /// `ConfigCommit`: checks (the declared safe state, then the configuration), stores when
    /// asked, applies. The controller stops stepping meanwhile (its tables are built once,
    /// twice when storing: ≈ 2.3 M instructions each, inside the watchdog's normal window; the
    /// store's erase raises it).
    async fn commit<C: StepClock>(
        &mut self,
        ctl: &mut Controller,
        clock: &mut C,
        persist: bool,
        beats: &Heartbeats,
        log: &mut impl FnMut(Event),
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
            let store = self.store.as_mut().ok_or(ConfigRefusal::Store)?;
            log(Event::Storing);
            let r = store.save(bytes, self.built_in).await;
            beats.beat_all();
            r.map_err(|e| {
                log(Event::StoreFailed(e));
                ConfigRefusal::Store
            })?;
        }
        // Measured like the boot's set-up (`firmware_config_upload` reads its log line).
        let t0 = clock.count();
        ctl.reconfigure(&cfg, &self.sched, &self.cc)
            .map_err(refusal)?;
        let cost = clock.count().wrapping_sub(t0);
        // Every task stalled with us: none of them is stuck.
        beats.beat_all();
        let source = if persist {
            ConfigSource::UploadedStored
        } else {
            ConfigSource::Uploaded
        };
        self.running = Running::new(bytes, source);
        log(Event::Applied {
            fingerprint: self.running.info.fingerprint,
            stored: persist,
            cost,
        });
        Ok(FromFirmware::ConfigApplied {
            info: self.running.info,
            stored: if persist { Stored::Yes } else { Stored::No },
        })
    }

    /// `ConfigClear`: erases the store (in the declared safe state).
    async fn clear(
        &mut self,
        ctl: &Controller,
        beats: &Heartbeats,
        log: &mut impl FnMut(Event),
    ) -> Result<FromFirmware, ConfigRefusal> {
        ctl.safe_to_apply().map_err(ConfigRefusal::NotSafe)?;
        let store = self.store.as_mut().ok_or(ConfigRefusal::Store)?;
        let r = store.clear().await;
        beats.beat_all();
        r.map_err(|_| ConfigRefusal::Store)?;
        // What runs is no longer stored.
        if self.running.info.source == ConfigSource::UploadedStored {
            self.running.info.source = ConfigSource::Uploaded;
        }
        log(Event::Cleared);
        Ok(FromFirmware::ConfigCleared)
    }
}

/// A configuration step's answer: the reply, or the refusal.
fn config_reply(r: Result<FromFirmware, ConfigRefusal>) -> FromFirmware {
    r.unwrap_or_else(|e| FromFirmware::Refused(Refusal::Config(e)))
}

/// The self-test's answer to a drive once its outputs settled: what was commanded, what the
/// hardware reads back.
pub fn readback_reply<V, P>(d: TestDrive, o: Outputs, act: &Actuators<V, P>) -> FromFirmware
where
    V: SetDutyCycle + DutyReadBack,
    P: OutputPin + ReadBack,
{
    let (valve_readback, dump_readback, solenoids_readback) = act.read_back();
    FromFirmware::SelfTest(SelfTestReply::Driven(
        pto_model::protocol::selftest::OutputReport {
            drive: d,
            valve: o.aperture,
            dump_open: o.dump_open,
            solenoids: o.on_duty,
            valve_readback,
            dump_readback,
            solenoids_readback,
        },
    ))
}

/// Whether a transmit queue holding `queued` of `capacity` frames takes telemetry: it leaves
/// `reply_slots` free for the replies to commands (which the host waits for), so telemetry
/// beyond what the link carries is dropped (and counted), never a reply.
pub fn telemetry_fits(queued: usize, capacity: usize, reply_slots: usize) -> bool {
    queued + reply_slots <= capacity
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frontend::{LoopSpec, Transducer};
    use crate::outputs::MemPwm as Pwm;
    use crate::store::{RamFlash, RamFlashError};
    use core::cell::{Cell, RefCell};
    use core::convert::Infallible;
    use embassy_futures::block_on;
    use embedded_storage_async::nor_flash::{ErrorType, ReadNorFlash};
    use pto_model::fx::{Aperture, Rpm};
    use pto_model::protocol::{NotSafe, encode_config};
    use std::rc::Rc;
    use std::vec::Vec;

    /// What happened, in order, across the actuators, the reset memory and the log.
    type Journal = Rc<RefCell<Vec<&'static str>>>;

    struct Pin {
        high: bool,
        journal: Journal,
    }
    impl embedded_hal::digital::ErrorType for Pin {
        type Error = Infallible;
    }
    impl OutputPin for Pin {
        fn set_low(&mut self) -> Result<(), Infallible> {
            self.high = false;
            self.journal.borrow_mut().push("drive");
            Ok(())
        }
        fn set_high(&mut self) -> Result<(), Infallible> {
            self.high = true;
            self.journal.borrow_mut().push("drive");
            Ok(())
        }
    }
    impl ReadBack for Pin {
        fn read_back(&self) -> Option<bool> {
            Some(self.high)
        }
    }
    struct Memory(Journal);
    impl ResetMemory for Memory {
        fn remember_trip(&mut self, _: bool) {
            self.0.borrow_mut().push("remember");
        }
        fn remember_sensor_faults(&mut self, _: u8) {
            self.0.borrow_mut().push("remember");
        }
    }

    type Ram = RamFlash<{ 8 * 1024 }, { 4 * 1024 }>;

    /// A flash whose writes and erases fail while `fail` is set (a worn or disconnected part).
    struct Flaky {
        flash: Ram,
        fail: Rc<Cell<bool>>,
    }
    impl ErrorType for Flaky {
        type Error = RamFlashError;
    }
    impl ReadNorFlash for Flaky {
        const READ_SIZE: usize = 1;
        async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), RamFlashError> {
            self.flash.read(offset, bytes).await
        }
        fn capacity(&self) -> usize {
            self.flash.capacity()
        }
    }
    impl NorFlash for Flaky {
        const WRITE_SIZE: usize = 4;
        const ERASE_SIZE: usize = 4 * 1024;
        async fn erase(&mut self, from: u32, to: u32) -> Result<(), RamFlashError> {
            if self.fail.get() {
                return Err(RamFlashError::OutOfBounds);
            }
            self.flash.erase(from, to).await
        }
        async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), RamFlashError> {
            if self.fail.get() {
                return Err(RamFlashError::OutOfBounds);
            }
            self.flash.write(offset, bytes).await
        }
    }

    /// The bench under test: controller, session, actuators, journal, the flash's failure
    /// switch.
    struct Rig {
        ctl: Controller,
        s: Session<Flaky>,
        act: Actuators<Pwm, Pin>,
        memory: Memory,
        journal: Journal,
        events: Vec<Event>,
        fail: Rc<Cell<bool>>,
        tick: u32,
    }

    fn encoded(cfg: &ModelConfig) -> Vec<u8> {
        let mut buf = [0u8; CONFIG_MAX_BYTES];
        encode_config(cfg, &mut buf).unwrap().to_vec()
    }

    fn rig(samples_itself: bool) -> Rig {
        rig_with(samples_itself, SchedulerConfig::default())
    }

    fn rig_with(samples_itself: bool, sched: SchedulerConfig) -> Rig {
        let journal: Journal = Rc::default();
        let pin = || Pin {
            high: false,
            journal: journal.clone(),
        };
        let act = Actuators::new(
            Pwm(0),
            pin(),
            [pin(), pin(), pin(), pin()],
            Outputs::DE_ENERGISED,
        );
        let fail = Rc::new(Cell::new(false));
        let flash = Flaky {
            flash: Ram::new(),
            fail: fail.clone(),
        };
        let model = ModelConfig::reference();
        let built = encoded(&model);
        let cc = ControlConfig::default();
        let ctl = Controller::new(&model, &sched, &cc).unwrap();
        let board = BoardLimits {
            samples_itself,
            min_telemetry_every: 8,
            info: BoardInfo::EMULATED,
        };
        let store = ConfigStore::new(flash, 0..8 * 1024);
        let running = Running::new(&built, ConfigSource::BuiltIn);
        let s = Session::new(&ctl, sched, cc, store, running, 0x1234, board, 16);
        Rig {
            ctl,
            s,
            act,
            memory: Memory(journal.clone()),
            journal,
            events: Vec::new(),
            fail,
            tick: 0,
        }
    }

    impl Rig {
        fn step(&mut self, hp_bar: f32) -> Option<Stepped> {
            let t = Transducer::new(LoopSpec::HP).unwrap();
            let l = Transducer::new(LoopSpec::LP).unwrap();
            let f = SensorFrame {
                tick: self.tick,
                encoder: 0,
                hp_adc: t.counts_at_bar(hp_bar),
                lp_adc: l.counts_at_bar(8.0),
                motor: Some(Rpm::from_num(200.0)),
                supply_mv: Some(3300),
            };
            self.tick += 1;
            let (journal, events) = (&self.journal, &mut self.events);
            let mut log = |e| {
                journal.borrow_mut().push("log");
                events.push(e);
            };
            self.s.step(
                &f,
                &mut self.ctl,
                &mut self.act,
                &mut crate::control::NoClock,
                &mut self.memory,
                &mut log,
            )
        }

        fn command(&mut self, cmd: ToFirmware) -> Handled {
            let beats = Heartbeats::new();
            let (journal, events) = (&self.journal, &mut self.events);
            let mut log = |e| {
                journal.borrow_mut().push("log");
                events.push(e);
            };
            block_on(self.s.command(
                cmd,
                &mut self.ctl,
                &mut self.act,
                &mut crate::control::NoClock,
                &beats,
                &mut log,
            ))
        }

        /// Uploads `bytes` (begin and chunks, every reply a progress).
        fn upload(&mut self, bytes: &[u8]) {
            let r = self.command(ToFirmware::ConfigBegin {
                len: bytes.len() as u16,
                crc: config_fingerprint(bytes),
            });
            assert!(
                matches!(r, Handled::Reply(FromFirmware::ConfigProgress(0))),
                "{r:?}"
            );
            for off in (0..bytes.len()).step_by(pto_model::protocol::CHUNK_BYTES) {
                let r = self.command(ToFirmware::ConfigChunk(Chunk::of(bytes, off)));
                assert!(
                    matches!(r, Handled::Reply(FromFirmware::ConfigProgress(_))),
                    "{r:?}"
                );
            }
        }

        /// Brings the controller to its declared safe state: a reading, mode Fixed(0).
        fn make_safe(&mut self) {
            self.command(ToFirmware::Reset {
                p2: Pressure::from_num(100.0),
                lp: Pressure::from_num(8.0),
            });
            self.command(ToFirmware::SetMode(Mode::Fixed(Aperture::ZERO)));
            // The valve slews shut at its rate limit.
            for _ in 0..2000 {
                self.step(100.0);
                if self.ctl.safe_to_apply().is_ok() {
                    return;
                }
            }
            panic!("not safe: {:?}", self.ctl.safe_to_apply());
        }

        fn stored(&mut self) -> Option<Vec<u8>> {
            let mut out = [0u8; CONFIG_MAX_BYTES];
            match block_on(self.s.store.as_mut().unwrap().load(&mut out)) {
                Loaded::Found { len, .. } => Some(out[..len].to_vec()),
                _ => None,
            }
        }
    }

    /// Another configuration the controller takes (another trip pressure, so that applying it
    /// shows in the controller).
    fn other() -> (ModelConfig, Vec<u8>) {
        let mut cfg = ModelConfig::reference();
        cfg.trip_bar = 135.0;
        let b = encoded(&cfg);
        (cfg, b)
    }

    fn refused(h: &Handled) -> Option<ConfigRefusal> {
        match h {
            Handled::Reply(FromFirmware::Refused(Refusal::Config(e))) => Some(*e),
            _ => None,
        }
    }

    #[test]
    fn a_step_drives_the_outputs_before_it_remembers_or_logs() {
        let mut r = rig(true);
        r.make_safe();
        r.journal.borrow_mut().clear();
        let trip = r.ctl.trip().to_f32();
        let s = r.step(trip + 5.0).expect("a fresh tick");
        assert!(s.out.dump, "tripped in this step");
        let j = r.journal.borrow().clone();
        let first_other = j.iter().position(|x| *x != "drive").unwrap();
        assert!(
            first_other >= 5,
            "dump and four solenoids driven first: {j:?}"
        );
        assert!(j[first_other..].iter().all(|x| *x != "drive"), "{j:?}");
        assert!(j.contains(&"remember") && j.contains(&"log"), "{j:?}");
        assert!(
            r.events.contains(&Event::Tripped(r.tick - 1)),
            "{:?}",
            r.events
        );
        assert!(r.act.applied().dump_open);
        // A repeated tick is not stepped.
        r.tick -= 1;
        assert_eq!(r.step(100.0), None);
    }

    #[test]
    fn a_commit_outside_the_safe_state_is_refused_and_touches_nothing() {
        let mut r = rig(false);
        let (_, bytes) = other();
        // No reading yet.
        r.upload(&bytes);
        let h = r.command(ToFirmware::ConfigCommit { persist: true });
        assert_eq!(
            refused(&h),
            Some(ConfigRefusal::NotSafe(NotSafe::NoReading))
        );
        // Valve open.
        r.make_safe();
        r.command(ToFirmware::SetMode(Mode::Fixed(Aperture::from_num(5.0))));
        for _ in 0..20 {
            r.step(100.0);
        }
        let applied = r.act.applied();
        assert!(applied.aperture > Aperture::ZERO);
        r.upload(&bytes);
        r.journal.borrow_mut().clear();
        let h = r.command(ToFirmware::ConfigCommit { persist: true });
        assert_eq!(
            refused(&h),
            Some(ConfigRefusal::NotSafe(NotSafe::ValveOpen))
        );
        assert_eq!(
            r.act.applied(),
            applied,
            "outputs not de-energised outside the safe state"
        );
        assert!(!r.journal.borrow().contains(&"drive"));
        assert_eq!(
            r.ctl.trip().to_f32(),
            140.0,
            "the configuration that ran runs"
        );
        assert_eq!(r.s.running().info().source, ConfigSource::BuiltIn);
        assert_eq!(r.stored(), None, "nothing stored");
        assert!(!r.events.contains(&Event::Storing), "{:?}", r.events);
        // The store is not cleared either, and the outputs stay.
        let h = r.command(ToFirmware::ConfigClear);
        assert_eq!(
            refused(&h),
            Some(ConfigRefusal::NotSafe(NotSafe::ValveOpen))
        );
        assert_eq!(r.act.applied(), applied);
        assert!(!r.journal.borrow().contains(&"drive"));
    }

    #[test]
    fn a_configuration_to_store_is_checked_whole_before_the_store_is_touched() {
        let mut r = rig(false);
        r.make_safe();
        let mut cfg = ModelConfig::reference();
        cfg.trip_bar = 500.0;
        r.upload(&encoded(&cfg));
        r.events.clear();
        let h = r.command(ToFirmware::ConfigCommit { persist: true });
        assert!(
            matches!(refused(&h), Some(ConfigRefusal::Field { .. })),
            "{h:?}"
        );
        assert!(!r.events.contains(&Event::Storing), "{:?}", r.events);
        assert_eq!(r.stored(), None);
        assert_eq!(r.ctl.trip().to_f32(), 140.0);
    }

    #[test]
    fn a_commit_in_the_safe_state_de_energises_stores_reads_back_then_applies() {
        let mut r = rig(false);
        let (_, bytes) = other();
        r.make_safe();
        r.upload(&bytes);
        r.events.clear();
        r.journal.borrow_mut().clear();
        let h = r.command(ToFirmware::ConfigCommit { persist: true });
        let j = r.journal.borrow().clone();
        let first_log = j.iter().position(|x| *x == "log").unwrap();
        assert!(
            j[..first_log].iter().filter(|x| **x == "drive").count() >= 5,
            "de-energised before the store: {j:?}"
        );
        let Handled::Reply(FromFirmware::ConfigApplied { info, stored }) = h else {
            panic!("{h:?}")
        };
        assert_eq!(stored, Stored::Yes);
        assert_eq!(info.source, ConfigSource::UploadedStored);
        assert_eq!(info.fingerprint, config_fingerprint(&bytes));
        assert_eq!(r.act.applied(), Outputs::DE_ENERGISED);
        assert!(
            matches!(
                r.events[..],
                [Event::Storing, Event::Applied { stored: true, .. }]
            ),
            "{:?}",
            r.events
        );
        assert_eq!(r.ctl.trip().to_f32(), 135.0);
        assert_eq!(r.stored(), Some(bytes.clone()));
        let h = r.command(ToFirmware::ConfigRead { offset: 0 });
        let Handled::Reply(FromFirmware::ConfigData { total, chunk }) = h else {
            panic!("{h:?}")
        };
        assert_eq!(usize::from(total), bytes.len());
        assert_eq!(
            chunk.data[..usize::from(chunk.len)],
            bytes[..usize::from(chunk.len)]
        );
        // Cleared: what runs is no longer stored.
        r.step(100.0);
        let h = r.command(ToFirmware::ConfigClear);
        assert_eq!(h, Handled::Reply(FromFirmware::ConfigCleared));
        assert_eq!(r.s.running().info().source, ConfigSource::Uploaded);
        assert_eq!(r.stored(), None);
    }

    #[test]
    fn a_failed_store_write_keeps_the_previous_configuration_running_and_stored() {
        let mut r = rig(false);
        let (_, first) = other();
        r.make_safe();
        r.upload(&first);
        let h = r.command(ToFirmware::ConfigCommit { persist: true });
        assert!(
            matches!(h, Handled::Reply(FromFirmware::ConfigApplied { .. })),
            "{h:?}"
        );
        let mut cfg = ModelConfig::reference();
        cfg.trip_bar = 120.0;
        let second = encoded(&cfg);
        r.step(100.0);
        r.upload(&second);
        r.fail.set(true);
        r.events.clear();
        let h = r.command(ToFirmware::ConfigCommit { persist: true });
        assert_eq!(refused(&h), Some(ConfigRefusal::Store));
        assert!(
            matches!(
                r.events[..],
                [
                    Event::Storing,
                    Event::StoreFailed(_),
                    Event::ConfigRefused(ConfigRefusal::Store)
                ]
            ),
            "{:?}",
            r.events
        );
        assert_eq!(
            r.ctl.trip().to_f32(),
            135.0,
            "the previous configuration runs"
        );
        assert_eq!(r.s.running().info().fingerprint, config_fingerprint(&first));
        r.fail.set(false);
        assert_eq!(r.stored(), Some(first), "and stays stored");
        // The running one is unchanged in `GetConfig`.
        let h = r.command(ToFirmware::GetConfig);
        assert_eq!(
            h,
            Handled::Reply(FromFirmware::ConfigInfo(r.s.running().info()))
        );
    }

    #[test]
    fn the_trip_latch_is_kept_across_a_commit_and_a_tripped_controller_takes_none() {
        let mut r = rig(false);
        let (_, bytes) = other();
        r.make_safe();
        let trip = r.ctl.trip().to_f32();
        r.step(trip + 5.0);
        assert!(r.ctl.status.tripped && r.ctl.status.trips == 1);
        let tripped_outputs = r.act.applied();
        assert!(tripped_outputs.dump_open);
        r.upload(&bytes);
        let h = r.command(ToFirmware::ConfigCommit { persist: false });
        assert_eq!(refused(&h), Some(ConfigRefusal::NotSafe(NotSafe::Tripped)));
        assert!(r.ctl.status.tripped, "a commit never releases the trip");
        assert_eq!(r.act.applied(), tripped_outputs);
        // Released by readings well below, held for the hold time.
        for _ in 0..2000 {
            r.step(90.0);
            if !r.ctl.status.tripped {
                break;
            }
        }
        assert!(!r.ctl.status.tripped, "released");
        r.make_safe();
        r.upload(&bytes);
        let h = r.command(ToFirmware::ConfigCommit { persist: false });
        assert!(
            matches!(
                h,
                Handled::Reply(FromFirmware::ConfigApplied {
                    stored: Stored::No,
                    ..
                })
            ),
            "{h:?}"
        );
        assert_eq!(r.ctl.status.trips, 1, "the trip count carries over");
        assert_eq!(r.ctl.trip().to_f32(), 135.0);
        assert_eq!(r.stored(), None, "not asked to store");
    }

    #[test]
    fn a_sensor_fault_held_keeps_the_valve_at_its_aperture_and_refuses_a_commit() {
        let mut r = rig(false);
        let (_, bytes) = other();
        r.make_safe();
        r.ctl.boot_sensor_faults(0b0100);
        for _ in 0..2000 {
            r.step(100.0);
        }
        assert!(
            r.act.applied().aperture > Aperture::ZERO,
            "{:?}",
            r.act.applied()
        );
        r.upload(&bytes);
        let h = r.command(ToFirmware::ConfigCommit { persist: true });
        assert_eq!(
            refused(&h),
            Some(ConfigRefusal::NotSafe(NotSafe::ValveOpen))
        );
        assert_eq!(r.ctl.sensor_faults(), 0b0100, "still held");
        assert_eq!(r.stored(), None);
    }

    #[test]
    fn the_sensors_held_faulted_are_kept_across_a_commit() {
        // A bench whose sensor-fault aperture is 0 %: a held fault leaves the valve closed, so
        // the safe state (and a commit) is reachable with it held.
        let sched = SchedulerConfig {
            sensor_fault_aperture_pct: 0.0,
            ..SchedulerConfig::default()
        };
        let mut r = rig_with(false, sched);
        let (_, bytes) = other();
        r.make_safe();
        r.ctl.boot_sensor_faults(0b0100);
        r.make_safe();
        r.upload(&bytes);
        let h = r.command(ToFirmware::ConfigCommit { persist: false });
        assert!(
            matches!(h, Handled::Reply(FromFirmware::ConfigApplied { .. })),
            "{h:?}"
        );
        assert_eq!(r.ctl.trip().to_f32(), 135.0);
        assert_eq!(r.ctl.sensor_faults(), 0b0100, "still held");
    }

    #[test]
    fn a_host_never_steps_a_board_that_samples_itself_and_the_watchdog_test_is_safe() {
        let mut r = rig(true);
        r.make_safe();
        let inputs = pto_model::estimator::Inputs::default();
        let steps = r.ctl.status.steps;
        let h = r.command(ToFirmware::Replay { tick: 1, inputs });
        assert_eq!(
            h,
            Handled::Reply(FromFirmware::Refused(Refusal::ReplayOnTwinOnly))
        );
        assert_eq!(r.ctl.status.steps, steps, "a refused replay steps nothing");
        let trip = r.ctl.trip().to_f32();
        r.step(trip + 5.0);
        assert_eq!(
            r.command(ToFirmware::Stall),
            Handled::Reply(FromFirmware::Refused(Refusal::StallWhileTripped))
        );
        assert_eq!(r.ctl.status.steps, steps + 1);
        // Not tripped: everything de-energised, then the task stops.
        let mut r = rig(false);
        r.make_safe();
        r.command(ToFirmware::SetDuty {
            on_duty: 0b1111,
            config: 0,
        });
        r.step(100.0);
        assert_eq!(r.act.applied().on_duty, 0b1111);
        assert_eq!(r.command(ToFirmware::Stall), Handled::Stall);
        assert_eq!(r.act.applied(), Outputs::DE_ENERGISED);
    }

    #[test]
    fn telemetry_keeps_to_what_the_link_carries_and_leaves_room_for_replies() {
        let mut r = rig(true);
        let h = r.command(ToFirmware::SetTelemetry { every: 1 });
        assert_eq!(
            h,
            Handled::Reply(FromFirmware::Pong(8)),
            "raised to the board's minimum"
        );
        let h = r.command(ToFirmware::SetTelemetry { every: 0 });
        assert_eq!(h, Handled::Reply(FromFirmware::Pong(0)), "off stays off");
        r.command(ToFirmware::SetTelemetry { every: 8 });
        let due = (0..16)
            .filter(|_| r.step(100.0).unwrap().telemetry.is_some())
            .count();
        assert_eq!(due, 2);
        assert!(telemetry_fits(6, 8, 2));
        assert!(!telemetry_fits(7, 8, 2));
    }

    #[test]
    fn the_boot_takes_the_stored_configuration_only_when_this_firmware_made_it() {
        let (cfg, bytes) = other();
        let model = ModelConfig::reference();
        let built_bytes = encoded(&model);
        let (sched, cc) = (SchedulerConfig::default(), ControlConfig::default());
        let mut store = ConfigStore::new(Ram::new(), 0..8 * 1024).unwrap();
        let built = BuiltIn {
            model: model.clone(),
            bytes: &built_bytes,
            fingerprint: 0x1234,
        };
        let (m, run, why) = block_on(boot_config(Some(&mut store), &built, &sched, &cc));
        assert_eq!(
            (m.trip_bar, why),
            (140.0, BootChoice::NotStored(NotStored::Empty))
        );
        assert_eq!(run.info().source, ConfigSource::BuiltIn);
        block_on(store.save(&bytes, 0x1234)).unwrap();
        let (m, run, why) = block_on(boot_config(Some(&mut store), &built, &sched, &cc));
        assert_eq!((m.trip_bar, why), (cfg.trip_bar, BootChoice::Stored));
        assert_eq!(run.bytes(), &bytes[..]);
        let other_fw = BuiltIn {
            fingerprint: 0x5678,
            ..built.clone()
        };
        let (m, _, why) = block_on(boot_config(Some(&mut store), &other_fw, &sched, &cc));
        assert_eq!(
            (m.trip_bar, why),
            (
                140.0,
                BootChoice::NotStored(NotStored::OtherFirmware(0x1234))
            )
        );
        let (_, _, why) = block_on(boot_config::<Ram>(None, &built, &sched, &cc));
        assert_eq!(why, BootChoice::NotStored(NotStored::Failed));
    }
}
