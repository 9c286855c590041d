//! Firmware sessions over the QEMU link: bit-exact replay of model inputs, and the
//! processor-in-the-loop run where the full simulation is the plant and the firmware, in
//! lockstep over USART1, is its valve controller (sensor frame out, command back, virtual time =
//! the tick in the frame). The same closed loop also runs on [`HostFirmware`], the firmware's
//! controller built for the host, for figures that need only what the controller computes.
//!
//! Over 1 000 lines, one job: the firmware as a valve controller (frames, faults injected, its
//! QEMU or host target) and the checks of each processor-in-the-loop run, which read its rows.

use crate::hil::qemu::{LinkError, Qemu};
use crate::sim::bench::{BAR, Bench};
use crate::sim::plant::Eval;
use crate::sim::scenario::Prepared;
use crate::sim::schedule::ValveController;
use crate::sim::solver::SimResult;
use crate::sim::trace::Truth;
use crate::validation::closed_loop::{LOOP_LP_START_BAR, LoopError, test3_like_loop};
use crate::validation::sensors::{Readings, SensorSpec, SensorSynth};
use pto_firmware::control::{Controller, NoClock};
use pto_firmware::frontend::{SpecError, Transducer};
use pto_model::ModelConfig;
use pto_model::estimator::{Estimate, Inputs};
use pto_model::fx::{Aperture, Pressure, Rpm};
use pto_model::protocol::{FromFirmware, Refusal, SensorFrame, Status, ToFirmware};
use pto_model::scheduler::{Command, Mode};

/// Why a firmware session failed.
#[derive(Debug, thiserror::Error)]
pub enum PilError {
    /// The link failed or the firmware answered out of turn.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The firmware refused to reset its estimator.
    #[error("{0}")]
    Refused(Refusal),
    /// The sensor model's 4–20 mA loop is not one the firmware's front end takes.
    #[error("{0}")]
    Transducer(SpecError),
    /// The closed-loop run could not be made.
    #[error(transparent)]
    Loop(#[from] LoopError),
    /// A frame damaged on purpose was answered.
    #[error("tick {0}: a damaged frame was accepted")]
    DamagedAccepted(u32),
    /// A burst of frames stepped the loop twice in one period.
    #[error("tick {0}: stepped twice in a burst")]
    SteppedTwice(u32),
    /// An unexpected message after a damaged frame.
    #[error("unexpected {0:?}")]
    Unexpected(Box<FromFirmware>),
    /// An unexpected message during a burst.
    #[error("unexpected {0:?} in a burst")]
    UnexpectedInBurst(Box<FromFirmware>),
    /// An unexpected message where a step's output was due.
    #[error("tick {tick}: unexpected {got:?}")]
    UnexpectedAt {
        /// The step's tick.
        tick: u32,
        /// What came instead.
        got: Box<FromFirmware>,
    },
    /// A closed-loop step failed at this time.
    #[error("t = {t:.4} s")]
    Step {
        /// Simulated time, s.
        t: f64,
        /// What failed.
        source: Box<PilError>,
    },
    /// A reset asked in a closed-loop step failed at this time.
    #[error("t = {t:.4} s: reset")]
    Reset {
        /// Simulated time, s.
        t: f64,
        /// What failed.
        source: Box<PilError>,
    },
    /// The overpressure check's firmware never tripped.
    #[error("the firmware never tripped")]
    NeverTripped,
    /// The host copy of the firmware ([`HostFirmware`]) was set up with a configuration the
    /// controller refuses.
    #[error("the host copy of the firmware: {0:?}")]
    HostSetup(pto_firmware::control::SetupError),
    /// An injection on the link's bytes (a damaged frame, a burst) asked of the host copy of
    /// the firmware, which has no link.
    #[error("{0:?} needs the firmware's link: the host copy has none")]
    NotOnHost(Injection),
}

/// Asks the firmware to restart its estimator from known pressures: `Ok(Err(refusal))` when
/// it refused (the overpressure trip holds), with its reason.
pub fn reset(q: &mut Qemu, p2: f32, lp: f32) -> Result<Result<(), Refusal>, LinkError> {
    q.link.request(
        &ToFirmware::Reset {
            p2: Pressure::from_num(p2),
            lp: Pressure::from_num(lp),
        },
        |r| match r {
            FromFirmware::ResetDone => Some(Ok(())),
            FromFirmware::Refused(why) => Some(Err(*why)),
            _ => None,
        },
    )
}

/// Starts the firmware's estimator from known pressures and sets its mode.
pub fn prime(q: &mut Qemu, p2: f32, lp: f32, mode: Mode) -> Result<(), PilError> {
    reset(q, p2, lp)?.map_err(PilError::Refused)?;
    Ok(q.link.send(&ToFirmware::SetMode(mode))?)
}

/// `n` samples of a bench at rest on the twin's hardware port (lever still, HP 60 bar, LP 8 bar,
/// motor stopped, 3.3 V supply), from `tick` on, each answered: what the declared safe state
/// needs besides fixed 0 % (a valid HP reading).
pub fn feed_at_rest(q: &mut Qemu, tick: &mut u32, n: u32) -> Result<(), PilError> {
    use pto_firmware::frontend::LoopSpec;
    let hp = Transducer::new(LoopSpec::HP).map_err(PilError::Transducer)?;
    let lp = Transducer::new(LoopSpec::LP).map_err(PilError::Transducer)?;
    for _ in 0..n {
        let f = SensorFrame {
            tick: *tick,
            encoder: 0,
            hp_adc: hp.counts_at_bar(60.0),
            lp_adc: lp.counts_at_bar(8.0),
            motor: Some(Rpm::from_num(0.0)),
            supply_mv: Some(3300),
        };
        let t = *tick;
        q.link.request(&ToFirmware::Sensors(f), |r| match r {
            FromFirmware::Output { tick, .. } if *tick == t => Some(()),
            _ => None,
        })?;
        *tick += 1;
    }
    Ok(())
}

/// Replays `inputs` through the firmware (lockstep), returning its outputs.
pub fn replay(
    q: &mut Qemu,
    inputs: &[Inputs],
    p2: f32,
    lp: f32,
    mode: Mode,
) -> Result<Vec<(Estimate, Command)>, PilError> {
    prime(q, p2, lp, mode)?;
    let mut out = Vec::with_capacity(inputs.len());
    for (i, inp) in inputs.iter().enumerate() {
        out.push(replay_step(q, i as u32, inp)?);
    }
    Ok(out)
}

/// One replayed step, answered for `tick`.
pub fn replay_step(
    q: &mut Qemu,
    tick: u32,
    inp: &Inputs,
) -> Result<(Estimate, Command), LinkError> {
    q.link
        .request(&ToFirmware::Replay { tick, inputs: *inp }, |r| match r {
            FromFirmware::Output {
                tick: t,
                estimate,
                command,
                ..
            } if *t == tick => Some((*estimate, *command)),
            _ => None,
        })
}

/// The firmware's counters.
pub fn status(q: &mut Qemu) -> Result<Status, LinkError> {
    q.link.request(&ToFirmware::GetStatus, |r| match r {
        FromFirmware::Status(s) => Some(*s),
        _ => None,
    })
}

/// A fault the host injects into the sensor frames or the link at one step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Injection {
    /// Normal frame.
    None,
    /// HP transducer wire break: the loop reads 0 mA.
    HpWireBreak,
    /// The encoder count does not move.
    EncoderStuck,
    /// HP reading ± this many bar (alternating sign).
    HpNoise(f64),
    /// The frame has a flipped byte (CRC fails).
    Corrupt,
    /// Only the first half of the frame is sent.
    Truncate,
    /// This many frames are sent back to back before waiting (a burst faster than the loop).
    Burst(u32),
    /// HP wire break, and after this step's output the host asks for a `Reset` to this P2,
    /// bar (its answer in [`PilRow::reset_reply`]).
    HpWireBreakAndReset(f32),
    /// After this step's output the host asks for a `Reset` to this P2, bar.
    HostReset(f32),
    /// The motor speed sensor reads this, rpm (whatever the plant does).
    MotorReads(f32),
    /// HP wire break and the motor speed sensor reading this, rpm.
    HpWireBreakMotorReads(f32),
    /// A sensor failing at plausible values (stuck, drifting, scaled: `model::faults`).
    Sensor(crate::validation::faults::Fault),
}

impl Injection {
    /// Acts on the link's bytes, not on the sensor frame or the firmware's commands.
    fn on_the_link(self) -> bool {
        matches!(
            self,
            Injection::Corrupt | Injection::Truncate | Injection::Burst(_)
        )
    }

    fn wire_break(self) -> bool {
        matches!(
            self,
            Injection::HpWireBreak
                | Injection::HpWireBreakAndReset(_)
                | Injection::HpWireBreakMotorReads(_)
        )
    }
}

/// One closed-loop step as seen by the host.
#[derive(Debug, Clone, Copy)]
pub struct PilRow {
    /// Time, s.
    pub t: f64,
    /// Plant P2, bar.
    pub p2_bar: f64,
    /// Plant motor speed, rpm.
    pub rpm: f64,
    /// Firmware estimate (when an output came back).
    pub estimate: Option<Estimate>,
    /// Scheduler command.
    pub command: Option<Command>,
    /// Aperture applied by the firmware (held from the last output when none came back), %.
    pub applied: f64,
    /// Dump valve.
    pub dump: bool,
    /// Injection at this step.
    pub injection: Injection,
    /// The firmware's answer to a `Reset` asked in this step.
    pub reset_reply: Option<Result<(), Refusal>>,
    /// The sensor frame sent (what a host-side copy of the controller replays).
    pub frame: SensorFrame,
}

/// What a closed loop's sensor frames go to: the firmware under QEMU over its link, or
/// [`HostFirmware`], its controller built for the host.
pub trait LoopTarget {
    /// One step: the frame sent, with the link's injections; the output it answered (none for
    /// a frame dropped on purpose).
    fn exchange(
        &mut self,
        f: SensorFrame,
        inj: Injection,
    ) -> Result<Option<FromFirmware>, PilError>;
    /// A reset asked after a step's output; `Ok(Err(refusal))` when refused.
    fn reset(&mut self, p2: f32, lp: f32) -> Result<Result<(), Refusal>, PilError>;
}

/// The firmware's controller built for the host (`pto_firmware::control`: the code the QEMU
/// build runs, with the scheduler and control settings it is built with): a closed loop without
/// QEMU, the firmware's own bit for bit (`twin::firmware_pil`'s
/// `the_host_copy_closes_the_loop_as_the_firmware_does`) at a small part of its cost. Frame-level
/// injections and resets (the controller's own, as the firmware's session makes them); the
/// link's bytes (damaged frames, bursts) need the firmware.
pub struct HostFirmware(Box<Controller>);

impl HostFirmware {
    /// The QEMU build's controller on `model` (its built-in configuration, or one uploaded),
    /// primed as [`closed_loop`] primes the firmware: reset to `p2` and `lp` bar, `mode`, the
    /// solenoids of `on_duty` in lever geometry `config`.
    pub fn new(
        model: &ModelConfig,
        (p2, lp): (f32, f32),
        mode: Mode,
        (on_duty, config): (u8, u8),
    ) -> Result<Self, PilError> {
        use pto_firmware::built_config::{CONTROL, SCHEDULER};
        let mut c = Controller::new(model, &SCHEDULER, &CONTROL).map_err(PilError::HostSetup)?;
        c.reset(Pressure::from_num(p2), Pressure::from_num(lp))
            .map_err(|t| PilError::Refused(Refusal::TripHeld(t)))?;
        c.set_mode(mode);
        c.set_duty(on_duty, config);
        Ok(HostFirmware(Box::new(c)))
    }
}

impl LoopTarget for HostFirmware {
    fn exchange(
        &mut self,
        f: SensorFrame,
        inj: Injection,
    ) -> Result<Option<FromFirmware>, PilError> {
        if inj.on_the_link() {
            return Err(PilError::NotOnHost(inj));
        }
        let c = &mut self.0;
        if !c.fresh(f.tick) {
            return Ok(None);
        }
        Ok(Some(c.sample(&f, &mut NoClock).reply(f.tick)))
    }

    fn reset(&mut self, p2: f32, lp: f32) -> Result<Result<(), Refusal>, PilError> {
        Ok(self
            .0
            .reset(Pressure::from_num(p2), Pressure::from_num(lp))
            .map_err(Refusal::TripHeld))
    }
}

/// The firmware (under QEMU, or [`HostFirmware`]) as the plant's valve controller.
pub struct FirmwareController<T: LoopTarget = Qemu> {
    q: T,
    period: f64,
    synth: SensorSynth,
    hp: Transducer,
    lp: Transducer,
    tick: u32,
    last_enc: i32,
    applied: f64,
    dump: bool,
    inject: Box<dyn Fn(f64) -> Injection>,
    /// The faulty sensor's reading when its [`Injection::Sensor`] began.
    fault_start: Option<f64>,
    /// Every step (none kept after [`FirmwareController::keep_rows`]`(false)`).
    pub rows: Vec<PilRow>,
    keep_rows: bool,
    /// The solenoids the firmware energised at its last output (bit i = HC3.(i+1)).
    pub on_duty: u8,
    /// Ends the run (before its duration) when the firmware energises exactly these solenoids.
    pub end_on_duty: Option<u8>,
    /// The first failed exchange (the run then holds the last command).
    pub error: Option<PilError>,
}

impl<T: LoopTarget> FirmwareController<T> {
    /// A controller on the firmware in `q`, whose model steps are 2^−dt_log2 s.
    pub fn new(
        q: T,
        dt_log2: u8,
        spec: SensorSpec,
        seed: u64,
        inject: Box<dyn Fn(f64) -> Injection>,
    ) -> Result<Self, PilError> {
        Ok(FirmwareController {
            q,
            period: 2f64.powi(-i32::from(dt_log2)),
            synth: SensorSynth::new(spec, seed),
            hp: Transducer::new(spec.hp_loop).map_err(PilError::Transducer)?,
            lp: Transducer::new(spec.lp_loop).map_err(PilError::Transducer)?,
            tick: 0,
            last_enc: 0,
            applied: 0.0,
            dump: false,
            inject,
            fault_start: None,
            rows: Vec::new(),
            keep_rows: true,
            on_duty: 0,
            end_on_duty: None,
            error: None,
        })
    }

    /// Keeps the rows of the steps (the default) or not (a campaign's hours at 1 kHz).
    pub fn keep_rows(&mut self, keep: bool) {
        self.keep_rows = keep;
        if !keep {
            self.rows = Vec::new();
        }
    }

    /// Gives back the firmware.
    pub fn into_target(self) -> T {
        self.q
    }

    fn frame(&mut self, theta: f64, truth: &Truth, inj: Injection) -> SensorFrame {
        let Readings {
            encoder_count: mut enc,
            hp_bar: mut hp,
            lp_bar: mut lp,
            motor_rpm: mut motor,
        } = self.synth.read_analog(theta, truth);
        match inj {
            Injection::EncoderStuck => enc = self.last_enc,
            Injection::HpNoise(a) => hp += if self.tick.is_multiple_of(2) { a } else { -a },
            Injection::MotorReads(r) | Injection::HpWireBreakMotorReads(r) => motor = f64::from(r),
            Injection::Sensor(f) => {
                use crate::validation::faults::Sensor;
                let t = f64::from(self.tick) * self.period;
                let mut v = [hp, lp, motor, f64::from(enc)];
                let i = f.sensor as usize;
                let start = *self.fault_start.get_or_insert(v[i]);
                v[i] = f.apply(t, v[i], start);
                (hp, lp, motor) = (v[0], v[1], v[2]);
                if f.sensor == Sensor::Encoder {
                    enc = v[3].round() as i32;
                }
            }
            _ => {}
        }
        self.last_enc = enc;
        SensorFrame {
            tick: self.tick,
            encoder: enc,
            hp_adc: if inj.wire_break() {
                self.hp.counts_at_ma(0.0)
            } else {
                self.hp.counts_at_bar(hp as f32)
            },
            lp_adc: self.lp.counts_at_bar(lp as f32),
            motor: Some(Rpm::from_num(motor as f32)),
            // The twin's ADC reference is the loops' nominal one, as its counts are made.
            supply_mv: Some(self.hp.vref_mv()),
        }
    }
}

impl LoopTarget for Qemu {
    fn exchange(
        &mut self,
        f: SensorFrame,
        inj: Injection,
    ) -> Result<Option<FromFirmware>, PilError> {
        let link = &mut self.link;
        let bytes = link.frame(&ToFirmware::Sensors(f));
        match inj {
            Injection::Corrupt | Injection::Truncate => {
                let mut b = bytes.clone();
                if inj == Injection::Corrupt {
                    let i = b.len() / 2;
                    b[i] = if b[i] == 0x5a { 0x3c } else { 0x5a };
                } else {
                    b.truncate(b.len() / 2);
                }
                link.send_raw(&b)?;
                // No output is due: a ping marks where the dropped frame's answer would be.
                let ping = ToFirmware::Ping(f.tick);
                link.send(&ping)?;
                match link.recv()? {
                    FromFirmware::Pong(n) if n == f.tick => Ok(None),
                    FromFirmware::Output { tick, .. } if tick == f.tick => {
                        Err(PilError::DamagedAccepted(tick))
                    }
                    other => Err(PilError::Unexpected(Box::new(other))),
                }
            }
            Injection::Burst(n) => {
                // n copies of the period's frame back to back, then a ping: the loop steps once
                // (one output); the other copies are overruns, dropped and counted.
                let mut all = bytes;
                for _ in 1..n {
                    all.extend(link.frame(&ToFirmware::Sensors(f)));
                }
                link.send_raw(&all)?;
                link.send(&ToFirmware::Ping(f.tick))?;
                let mut last = None;
                loop {
                    match link.recv()? {
                        FromFirmware::Pong(x) if x == f.tick => return Ok(last),
                        o @ FromFirmware::Output { tick, .. } if tick == f.tick => {
                            if last.is_some() {
                                return Err(PilError::SteppedTwice(tick));
                            }
                            last = Some(o);
                        }
                        other => return Err(PilError::UnexpectedInBurst(Box::new(other))),
                    }
                }
            }
            _ => {
                link.send_raw(&bytes)?;
                match link.recv()? {
                    o @ FromFirmware::Output { tick, .. } if tick == f.tick => Ok(Some(o)),
                    other => Err(PilError::UnexpectedAt {
                        tick: f.tick,
                        got: Box::new(other),
                    }),
                }
            }
        }
    }

    fn reset(&mut self, p2: f32, lp: f32) -> Result<Result<(), Refusal>, PilError> {
        Ok(reset(self, p2, lp)?)
    }
}

impl<T: LoopTarget> ValveController for FirmwareController<T> {
    fn period(&self) -> f64 {
        self.period
    }

    fn update(&mut self, t: f64, p: &Eval) -> f64 {
        let inj = (self.inject)(t);
        let truth = Truth::of_eval(p);
        let f = self.frame(p.theta_rad, &truth, inj);
        let mut row = PilRow {
            t,
            p2_bar: truth.p2_bar,
            rpm: truth.motor_rpm,
            estimate: None,
            command: None,
            applied: self.applied,
            dump: self.dump,
            injection: inj,
            reset_reply: None,
            frame: f,
        };
        if self.error.is_none() {
            match self.q.exchange(f, inj) {
                Ok(Some(FromFirmware::Output {
                    estimate,
                    command,
                    applied,
                    dump,
                    on_duty,
                    ..
                })) => {
                    self.on_duty = on_duty;
                    self.applied = f64::from(applied.to_f32());
                    self.dump = dump;
                    row.estimate = Some(estimate);
                    row.command = Some(command);
                    row.applied = self.applied;
                    row.dump = dump;
                }
                Ok(_) => {}
                Err(e) => {
                    self.error = Some(PilError::Step {
                        t,
                        source: Box::new(e),
                    })
                }
            }
            if let Injection::HpWireBreakAndReset(p2) | Injection::HostReset(p2) = inj {
                match self.q.reset(p2, 8.0) {
                    Ok(r) => row.reset_reply = Some(r),
                    Err(e) => {
                        self.error = Some(PilError::Reset {
                            t,
                            source: Box::new(e),
                        })
                    }
                }
            }
        }
        self.tick = self.tick.wrapping_add(1);
        if self.keep_rows {
            self.rows.push(row);
        }
        self.applied
    }

    fn finished(&self) -> bool {
        self.error.is_some() || self.end_on_duty == Some(self.on_duty)
    }
}

/// What a closed-loop run returns: the firmware (still running), the plant's trace, every step.
pub type LoopRun = (Qemu, SimResult, Vec<PilRow>);

/// A Test III-like closed-loop run ([`crate::validation::closed_loop::test3_like_loop`]) with the firmware as
/// the controller, from P2 `p2_start` bar, for `duration` s, with the sensors of `spec` (4–20 mA
/// loops quantised by the firmware's own front end).
pub fn closed_loop(
    mut q: Qemu,
    bench: &Bench,
    mode: Mode,
    p2_start: f64,
    duration: f64,
    spec: SensorSpec,
    inject: Box<dyn Fn(f64) -> Injection>,
) -> Result<LoopRun, PilError> {
    let dt_log2 = pto_model::ModelConfig::reference().dt_log2;
    let (res, ctrl) = loop_on(bench, p2_start, duration, dt_log2, spec, inject, |prep| {
        prime(&mut q, p2_start as f32, LOOP_LP_START_BAR as f32, mode)?;
        q.link.send(&ToFirmware::SetDuty {
            on_duty: crate::validation::duty_mask(&prep.on_duty),
            config: prep.config as u8,
        })?;
        Ok(q)
    })?;
    Ok((ctrl.q, res, ctrl.rows))
}

/// The Test III-like closed loop on the target `make` gives for the run (primed: reset to
/// `p2_start` and the loop's LP, its mode, the run's solenoids), steps of 2^−dt_log2 s; the first
/// failed step is the error.
fn loop_on<T: LoopTarget + 'static>(
    bench: &Bench,
    p2_start: f64,
    duration: f64,
    dt_log2: u8,
    spec: SensorSpec,
    inject: Box<dyn Fn(f64) -> Injection>,
    make: impl FnOnce(&Prepared) -> Result<T, PilError>,
) -> Result<(SimResult, FirmwareController<T>), PilError> {
    let (res, mut ctrl) = test3_like_loop(bench, p2_start, duration, |prep| {
        FirmwareController::new(make(prep)?, dt_log2, spec, 11, inject)
    })?;
    match ctrl.error.take() {
        Some(e) => Err(e),
        None => Ok((res, ctrl)),
    }
}

/// [`closed_loop`] on [`HostFirmware`] with `model` instead of the QEMU firmware: the plant's
/// trace and every step, the same rows bit for bit, at a small part of the cost (no QEMU, no
/// link). For the runs that compare a configuration with another and need only what the
/// controller computes.
pub fn host_closed_loop(
    bench: &Bench,
    model: &ModelConfig,
    mode: Mode,
    p2_start: f64,
    duration: f64,
    spec: SensorSpec,
    inject: Box<dyn Fn(f64) -> Injection>,
) -> Result<(SimResult, Vec<PilRow>), PilError> {
    let (res, ctrl) = loop_on(
        bench,
        p2_start,
        duration,
        model.dt_log2,
        spec,
        inject,
        |prep| {
            HostFirmware::new(
                model,
                (p2_start as f32, LOOP_LP_START_BAR as f32),
                mode,
                (
                    crate::validation::duty_mask(&prep.on_duty),
                    prep.config as u8,
                ),
            )
        },
    )?;
    Ok((res, ctrl.rows))
}

/// The scheduler mode of a fixed aperture, %.
pub fn fixed(pct: f32) -> Mode {
    Mode::Fixed(Aperture::from_num(pct))
}

/// A processor-in-the-loop check: runs on a booted firmware, returns it with the figures.
pub type CheckFn = fn(Qemu, &Bench) -> Result<(Qemu, Check), PilError>;

/// A processor-in-the-loop check and its figures.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Check {
    /// What was checked.
    pub name: String,
    /// The measured figure (its unit in `unit`).
    pub measured: f64,
    /// The target.
    pub target: f64,
    /// Unit of both.
    pub unit: String,
    /// One-line account.
    pub detail: String,
    /// Steps run in lockstep.
    pub steps: usize,
    /// Wall time, s.
    pub wall_s: f64,
    /// Met.
    pub pass: bool,
}

fn max_of(it: impl Iterator<Item = f64>) -> f64 {
    it.fold(0.0, f64::max)
}

/// Hold P2 at 100 bar from 92 bar for 60 s; judged from 40 s (the loop, with the scheduler's
/// default gains, settles in ≈ 40 s, as in the in-process check of `pto validate`).
pub fn check_hold_p2(q: Qemu, bench: &Bench) -> Result<(Qemu, Check), PilError> {
    let t0 = std::time::Instant::now();
    let (q, _res, rows) = closed_loop(
        q,
        bench,
        Mode::HoldPressure(Pressure::from_num(100.0)),
        92.0,
        60.0,
        SensorSpec::default(),
        Box::new(|_| Injection::None),
    )?;
    let from = 40.0;
    let late = || rows.iter().filter(move |r| r.t >= from);
    let worst = max_of(late().map(|r| (r.p2_bar - 100.0).abs()));
    let est = max_of(late().filter_map(|r| {
        r.estimate
            .map(|e| (f64::from(e.p2.to_f32()) - r.p2_bar).abs())
    }));
    Ok((
        q,
        Check {
            name: "hold P2 at 100 bar".into(),
            measured: worst,
            target: 2.0,
            unit: "bar".into(),
            detail: format!(
                "Test III-like run from 92 bar, 60 s; plant P2 within ±{worst:.2} bar of 100 from \
                 {from} s on; firmware estimate within {est:.2} bar of the plant"
            ),
            steps: rows.len(),
            wall_s: t0.elapsed().as_secs_f64(),
            pass: worst <= 2.0,
        },
    ))
}

/// Hold the motor at 250 rpm from 100 bar for 40 s; judged from 15 s.
pub fn check_hold_speed(q: Qemu, bench: &Bench) -> Result<(Qemu, Check), PilError> {
    let t0 = std::time::Instant::now();
    let sp = 250.0;
    let (q, _res, rows) = closed_loop(
        q,
        bench,
        Mode::HoldSpeed(Rpm::from_num(sp as f32)),
        100.0,
        40.0,
        SensorSpec::default(),
        Box::new(|_| Injection::None),
    )?;
    let from = 15.0;
    let late = || rows.iter().filter(move |r| r.t >= from);
    let worst = max_of(late().map(|r| (r.rpm - sp).abs() / sp)) * 100.0;
    let (lo, hi) = late().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
        (lo.min(r.applied), hi.max(r.applied))
    });
    Ok((
        q,
        Check {
            name: "hold motor at 250 rpm".into(),
            measured: worst,
            target: 3.0,
            unit: "%".into(),
            detail: format!(
                "Test III-like run from 100 bar, 40 s; motor within ±{worst:.2} % from {from} s \
                 on, aperture {lo:.1}–{hi:.1} %"
            ),
            steps: rows.len(),
            wall_s: t0.elapsed().as_secs_f64(),
            pass: worst <= 3.0,
        },
    ))
}

/// Overpressure: the relief valve set above the trip (it does not open), the control valve
/// closed, P2 climbing from 136 bar; a noise-free HP transducer so that the trip happens where
/// P2 crosses 140 bar (with 0.5 bar noise it trips up to ≈ 1.5 bar early, on a noise peak).
/// Measured: periods from the plant's crossing (or the firmware's trip, if earlier) to the
/// safe state.
pub fn check_trip(q: Qemu, bench: &Bench) -> Result<(Qemu, Check), PilError> {
    let t0 = std::time::Instant::now();
    let trip = 140.0;
    let (q, _res, rows) = overpressure_run(q, bench, Box::new(|_| Injection::None))?;
    let tripped = rows
        .iter()
        .position(|r| r.dump)
        .ok_or(PilError::NeverTripped)?;
    let crossed = rows.iter().position(|r| r.p2_bar > trip);
    let onset = crossed.map_or(tripped, |k| k.min(tripped));
    // Safe state: valve fully open and dump valve on, from the onset step to the end while P2
    // is above the release threshold.
    let late = tripped.saturating_sub(onset);
    let held = rows[tripped..]
        .iter()
        .filter(|r| r.p2_bar > trip - 10.0)
        .all(|r| r.dump && r.applied == 100.0);
    let near = rows[tripped].p2_bar > trip - 0.2;
    let peak = max_of(rows.iter().map(|r| r.p2_bar));
    let safety = rows[tripped].command.map(|c| c.safety);
    Ok((
        q,
        Check {
            name: "overpressure trip".into(),
            measured: late as f64,
            target: 0.0,
            unit: "periods late".into(),
            detail: format!(
                "tripped at t = {:.4} s with the plant at {:.3} bar (crossed {trip} bar: {}); \
                 valve 100 % and dump on in that step's output ({safety:?}), held while P2 > {} \
                 bar: {held}; peak {peak:.2} bar",
                rows[tripped].t,
                rows[tripped].p2_bar,
                crossed.map_or("never".into(), |k| format!("step {k}")),
                trip - 10.0
            ),
            steps: rows.len(),
            wall_s: t0.elapsed().as_secs_f64(),
            pass: late == 0 && held && near && peak < trip + 0.5,
        },
    ))
}

/// A sensor failing at a plausible value under QEMU: the HP transducer stuck at its reading 10 s
/// into a hold of P2 at 100 bar from 60 bar (P2 rising; the checks judge from 9 s after a
/// start). See [`check_fault`].
pub fn check_sensor_fault(q: Qemu, bench: &Bench) -> Result<(Qemu, Check), PilError> {
    use crate::validation::faults::{Fault, FaultKind, Sensor};
    check_fault(
        q,
        bench,
        Fault {
            sensor: Sensor::Hp,
            kind: FaultKind::StuckAtReading,
            from_s: 10.0,
        },
    )
}

/// A sensor fault injected into the firmware's readings under QEMU (`pto pil --fault`), in the
/// mode [`Fault::mode`] picks, from 60 bar (100 bar for a motor fault): the firmware must hold
/// that sensor — and only it, to the end — faulted within the fault's bound ([`Fault::bound`]: 5 s; a
/// drift, the time to drift 5 units more; a motor reading stuck, 5 s after the speed left it)
/// and keep its valve at the sensor-fault aperture (or the dump open) from then to the end.
/// The run lasts until 10 s past the bound (120 s at most for a stuck motor reading).
///
/// [`Fault::mode`]: crate::validation::faults::Fault::mode
/// [`Fault::bound`]: crate::validation::faults::Fault::bound
pub fn check_fault(
    q: Qemu,
    bench: &Bench,
    fault: crate::validation::faults::Fault,
) -> Result<(Qemu, Check), PilError> {
    use crate::validation::faults::{Bound, Sensor, sensor_bit};
    use pto_firmware::sensor_faults::{SensorFaults, names};
    let t0 = std::time::Instant::now();
    let from = fault.from_s;
    let bound = fault.bound();
    let run_s = from
        + match bound {
            Bound::MotorLeaves => 120.0,
            _ => fault.bound_s(bound, None, std::iter::empty()) + 10.0,
        };
    let p2_start = if fault.sensor == Sensor::Motor {
        100.0
    } else {
        60.0
    };
    let (mut q, _res, rows) = closed_loop(
        q,
        bench,
        fault.mode(),
        p2_start,
        run_s,
        SensorSpec::default(),
        Box::new(move |t| {
            if t >= from {
                Injection::Sensor(fault)
            } else {
                Injection::None
            }
        }),
    )?;
    // The firmware's latch, followed step by step from its outputs (the same code: what it
    // holds after each step); checked against its status at the end.
    let mut latch = SensorFaults::default();
    let mut first = None;
    for (k, r) in rows.iter().enumerate() {
        if let Some(e) = r.estimate {
            latch.take(e.faults, Some(r.frame.encoder));
        }
        if first.is_none() && latch.latched() != 0 {
            first = Some((k, latch.latched()));
        }
    }
    // The motor reading it stuck at (sent in the fault's first step): what its bound needs.
    let stuck = rows
        .iter()
        .find(|r| r.t >= from)
        .and_then(|r| r.frame.motor)
        .map(|m| f64::from(m.to_f32()));
    let bound_s = fault.bound_s(bound, stuck, rows.iter().map(|r| (r.t, r.rpm, r.p2_bar)));
    let safe_op = f64::from(
        crate::validation::controller_config(bench)
            .0
            .sensor_fault_aperture_pct,
    );
    let after = first.map_or(f64::INFINITY, |(k, _)| rows[k].t - from);
    let safe = first.is_some_and(|(k, _)| {
        rows[k + 1..]
            .iter()
            .all(|r| r.dump || (r.applied - safe_op).abs() < 1e-3)
    });
    let (lo, hi) = rows
        .iter()
        .filter(|r| r.t >= from)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), r| {
            (a.min(r.p2_bar), b.max(r.p2_bar))
        });
    let held_first = first.map_or(0, |(_, b)| b);
    let st = status(&mut q)?;
    let want = sensor_bit(fault.sensor);
    let named = |b: u8| names(b).collect::<Vec<_>>().join(", ");
    Ok((
        q,
        Check {
            name: fault.to_string(),
            measured: after,
            target: bound_s,
            unit: "s to the flag".into(),
            detail: format!(
                "{:?} from {p2_start} bar; held first: [{}] (want [{}]), at the end: [{}]; valve \
                 at the sensor-fault aperture ({safe_op} %) or dumped from then: {safe}; plant P2 \
                 {lo:.1}–{hi:.1} bar after the fault",
                fault.mode(),
                named(held_first),
                named(want),
                named(st.sensor_faults),
            ),
            steps: rows.len(),
            wall_s: t0.elapsed().as_secs_f64(),
            pass: crate::validation::faults::judge(
                held_first,
                want,
                first.map(|_| after),
                bound_s,
                safe,
            ) && st.sensor_faults == latch.latched()
                && (first.is_none() || st.sensor_faults == want),
        },
    ))
}

/// The run of [`check_trip`]: the relief set at 170 bar, the valve closed, P2 climbing from 136
/// bar for 4 s with a noise-free HP transducer, and `inject`'s faults.
fn overpressure_run(
    q: Qemu,
    bench: &Bench,
    inject: Box<dyn Fn(f64) -> Injection>,
) -> Result<LoopRun, PilError> {
    let mut b = bench.clone();
    b.relief_setting_pa = 170.0 * BAR;
    let spec = SensorSpec {
        hp_noise_bar: 0.0,
        ..SensorSpec::default()
    };
    closed_loop(q, &b, fixed(0.0), 136.0, 4.0, spec, inject)
}

/// The trip latch under QEMU: the run of [`check_trip`] (P2 crosses the trip 1.47 s in); at
/// 1.5 s, P2 still high, the host asks for a `Reset` to 100 bar; from 1.6 s the HP
/// transducer's wire breaks and stays broken, and at 2.0 s the host asks again. The latch must
/// hold to the end and both resets must be refused with their reasons.
pub fn check_trip_holds(q: Qemu, bench: &Bench) -> Result<(Qemu, Check), PilError> {
    let t0 = std::time::Instant::now();
    // P2 crosses 140 bar 1.47 s in (`pil_trips_to_the_safe_state_within_one_period`), then
    // falls through the open valve.
    let step = 1.0 / 1024.0;
    let inject = move |t: f64| match t {
        t if (1.5..1.5 + step).contains(&t) => Injection::HostReset(100.0),
        t if (2.0..2.0 + step).contains(&t) => Injection::HpWireBreakAndReset(100.0),
        t if t >= 1.6 => Injection::HpWireBreak,
        _ => Injection::None,
    };
    let (q, _res, rows) = overpressure_run(q, bench, Box::new(inject))?;
    let tripped = rows
        .iter()
        .position(|r| r.dump)
        .ok_or(PilError::NeverTripped)?;
    let broken: Vec<&PilRow> = rows.iter().filter(|r| r.injection.wire_break()).collect();
    let held = broken
        .iter()
        .filter(|r| r.dump && r.applied == 100.0)
        .count();
    let replies: Vec<_> = rows.iter().filter_map(|r| r.reset_reply).collect();
    let (high, reply) = (replies.first().copied(), replies.get(1).copied());
    let refused_high = matches!(
        high,
        Some(Err(Refusal::TripHeld(
            pto_model::protocol::TripHold::HpHigh(_)
        )))
    );
    let low_estimate = broken
        .iter()
        .filter_map(|r| r.estimate)
        .filter(|e| e.p2.to_f32() < 125.0)
        .count();
    let refused = matches!(
        reply,
        Some(Err(Refusal::TripHeld(
            pto_model::protocol::TripHold::HpMissing
        )))
    );
    Ok((
        q,
        Check {
            name: "trip holds through a wire break".into(),
            measured: (broken.len() - held) as f64,
            target: 0.0,
            unit: "steps released".into(),
            detail: format!(
                "tripped at t = {:.4} s; reset to 100 bar at 1.5 s (P2 high): {}; wire break \
                 from 1.6 s: {held} of {} steps held the safe state ({low_estimate} with the \
                 estimate below the release pressure); reset to 100 bar at 2.0 s: {}",
                rows[tripped].t,
                match high {
                    Some(Ok(())) => "ACCEPTED".to_string(),
                    Some(Err(why)) => format!("refused: {why}"),
                    None => "no answer".to_string(),
                },
                broken.len(),
                match reply {
                    Some(Ok(())) => "ACCEPTED".to_string(),
                    Some(Err(why)) => format!("refused: {why}"),
                    None => "no answer".to_string(),
                }
            ),
            steps: rows.len(),
            wall_s: t0.elapsed().as_secs_f64(),
            pass: !broken.is_empty() && held == broken.len() && refused && refused_high,
        },
    ))
}

/// A motor reading with the valve closed under QEMU: the valve commanded closed from the start,
/// the HP transducer lost after 0.5 s and the motor sensor then reading 200 rpm behind the
/// valve; the lever pumps P2 up from 60 bar for 4 s. No false trip, the contradiction flagged once a real rotor would have
/// spun down, and the estimate following the plant (the pump), not the motor reading.
pub fn check_motor_behind_closed_valve(q: Qemu, bench: &Bench) -> Result<(Qemu, Check), PilError> {
    let t0 = std::time::Instant::now();
    // The transducer confirms the start for 0.5 s, then breaks.
    let inject = |t: f64| {
        if t < 0.5 {
            Injection::None
        } else {
            Injection::HpWireBreakMotorReads(200.0)
        }
    };
    let (q, _res, rows) = closed_loop(
        q,
        bench,
        fixed(0.0),
        60.0,
        4.0,
        SensorSpec::default(),
        Box::new(inject),
    )?;
    let trips = rows.iter().filter(|r| r.dump).count();
    let flagged = rows.iter().position(|r| {
        r.estimate
            .is_some_and(|e| e.faults & pto_model::estimator::fault::MOTOR_IMPLAUSIBLE != 0)
    });
    let err = max_of(rows.iter().filter_map(|r| {
        r.estimate
            .map(|e| (f64::from(e.p2.to_f32()) - r.p2_bar).abs())
    }));
    let flagged_s = flagged.map(|k| rows[k].t);
    Ok((
        q,
        Check {
            name: "motor reading behind a closed valve".into(),
            measured: err,
            target: 2.0,
            unit: "bar (model-only P2 max error)".into(),
            detail: format!(
                "{trips} steps tripped; contradiction flagged from t = {}",
                flagged_s.map_or("never".into(), |t| format!("{t:.3} s"))
            ),
            steps: rows.len(),
            wall_s: t0.elapsed().as_secs_f64(),
            // Not before a real rotor would have spun down behind the valve closed since t = 0
            // (683 steps, 0.667 s), and soon after.
            pass: trips == 0 && flagged_s.is_some_and(|t| (0.66..1.0).contains(&t)) && err <= 2.0,
        },
    ))
}
