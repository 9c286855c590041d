//! Firmware sessions over the QEMU link: bit-exact replay of model inputs, and the
//! processor-in-the-loop run where the full simulation is the plant and the firmware, in
//! lockstep over USART1, is its valve controller (sensor frame out, command back, virtual time =
//! the tick in the frame).

use crate::bench::{BAR, Bench};
use crate::estimation::{SensorSpec, SensorSynth, Truth};
use crate::plant::Eval;
use crate::qemu::Qemu;
use crate::sim::{self, Initial, Run, SimResult, SolverOptions, ValveController, ValveSchedule};
use pto_firmware::frontend::{LoopSpec, Transducer};
use pto_model::estimator::{Estimate, Inputs};
use pto_model::fx::{Aperture, Pressure, Rpm};
use pto_model::protocol::{FromFirmware, SensorFrame, Status, ToFirmware};
use pto_model::scheduler::{Command, Mode};
use std::path::Path;

/// Starts the firmware's estimator from known pressures and sets its mode.
pub fn prime(q: &mut Qemu, p2: f32, lp: f32, mode: Mode) -> Result<(), String> {
    q.link.send(&ToFirmware::Reset {
        p2: Pressure::from_num(p2),
        lp: Pressure::from_num(lp),
    })?;
    q.link.send(&ToFirmware::SetMode(mode))
}

/// Replays `inputs` through the firmware (lockstep), returning its outputs.
pub fn replay(
    q: &mut Qemu,
    inputs: &[Inputs],
    p2: f32,
    lp: f32,
    mode: Mode,
) -> Result<Vec<(Estimate, Command)>, String> {
    prime(q, p2, lp, mode)?;
    let mut out = Vec::with_capacity(inputs.len());
    for (i, inp) in inputs.iter().enumerate() {
        let tick = i as u32;
        let r = q.link.request(
            &ToFirmware::Replay {
                tick,
                inputs: *inp,
            },
            |r| match r {
                FromFirmware::Output {
                    tick: t,
                    estimate,
                    command,
                    ..
                } if *t == tick => Some((*estimate, *command)),
                _ => None,
            },
        )?;
        out.push(r);
    }
    Ok(out)
}

/// The firmware's counters.
pub fn status(q: &mut Qemu) -> Result<Status, String> {
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
}

/// One closed-loop step as seen by the host.
#[derive(Debug, Clone, Copy)]
pub struct PilRow {
    /// Time, s.
    pub t: f64,
    /// Plant P2, bar.
    pub p2: f64,
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
}

/// The firmware as the plant's valve controller.
pub struct FirmwareController {
    q: Qemu,
    period: f64,
    synth: SensorSynth,
    hp: Transducer,
    lp: Transducer,
    tick: u32,
    last_enc: i32,
    applied: f64,
    dump: bool,
    inject: Box<dyn Fn(f64) -> Injection>,
    /// Every step.
    pub rows: Vec<PilRow>,
    /// First link error (the run then holds the last command).
    pub error: Option<String>,
}

impl FirmwareController {
    /// A controller on the firmware in `q`, whose model steps are 2^−dt_log2 s.
    pub fn new(
        q: Qemu,
        dt_log2: u8,
        spec: SensorSpec,
        seed: u64,
        inject: Box<dyn Fn(f64) -> Injection>,
    ) -> Result<Self, String> {
        Ok(FirmwareController {
            q,
            period: 2f64.powi(-i32::from(dt_log2)),
            synth: SensorSynth::new(spec, seed),
            hp: Transducer::new(LoopSpec::HP).map_err(|e| e.to_string())?,
            lp: Transducer::new(LoopSpec::LP).map_err(|e| e.to_string())?,
            tick: 0,
            last_enc: 0,
            applied: 0.0,
            dump: false,
            inject,
            rows: Vec::new(),
            error: None,
        })
    }

    fn frame(&mut self, t: f64, p: &Eval, inj: Injection) -> SensorFrame {
        let truth = Truth {
            p2: p.p2 / BAR,
            lp: p.lp / BAR,
            torque: p.torque.iter().sum(),
            motor_rpm: p.omega * 30.0 / std::f64::consts::PI,
        };
        let (mut enc, mut hp, lp, motor) = self.synth.read_analog(p.theta, &truth);
        match inj {
            Injection::EncoderStuck => enc = self.last_enc,
            Injection::HpNoise(a) => hp += if self.tick % 2 == 0 { a } else { -a },
            _ => {}
        }
        self.last_enc = enc;
        let _ = t;
        SensorFrame {
            tick: self.tick,
            encoder: enc,
            hp_adc: if inj == Injection::HpWireBreak {
                self.hp.counts_at_ma(0.0)
            } else {
                self.hp.counts_at_bar(hp as f32)
            },
            lp_adc: self.lp.counts_at_bar(lp as f32),
            motor: Some(Rpm::from_num(motor as f32)),
        }
    }

    fn exchange(&mut self, f: SensorFrame, inj: Injection) -> Result<Option<FromFirmware>, String> {
        let link = &mut self.q.link;
        let bytes = crate::qemu::Link::frame(&ToFirmware::Sensors(f));
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
                loop {
                    match link.recv()? {
                        FromFirmware::Pong(n) if n == f.tick => return Ok(None),
                        FromFirmware::Output { tick, .. } if tick == f.tick => {
                            return Err(format!("tick {tick}: a damaged frame was accepted"));
                        }
                        other => return Err(format!("unexpected {other:?}")),
                    }
                }
            }
            Injection::Burst(n) => {
                // n copies of the period's frame back to back, then a ping: the loop steps once
                // (one output); the other copies are overruns, dropped and counted.
                let mut all = Vec::new();
                for _ in 0..n {
                    all.extend_from_slice(&bytes);
                }
                link.send_raw(&all)?;
                link.send(&ToFirmware::Ping(f.tick))?;
                let mut last = None;
                loop {
                    match link.recv()? {
                        FromFirmware::Pong(x) if x == f.tick => return Ok(last),
                        o @ FromFirmware::Output { tick, .. } if tick == f.tick => {
                            if last.is_some() {
                                return Err(format!("tick {tick}: stepped twice in a burst"));
                            }
                            last = Some(o);
                        }
                        other => return Err(format!("unexpected {other:?} in a burst")),
                    }
                }
            }
            _ => {
                link.send_raw(&bytes)?;
                match link.recv()? {
                    o @ FromFirmware::Output { tick, .. } if tick == f.tick => Ok(Some(o)),
                    other => Err(format!("tick {}: unexpected {other:?}", f.tick)),
                }
            }
        }
    }
}

impl ValveController for FirmwareController {
    fn period(&self) -> f64 {
        self.period
    }

    fn update(&mut self, t: f64, p: &Eval) -> f64 {
        let inj = (self.inject)(t);
        let f = self.frame(t, p, inj);
        let mut row = PilRow {
            t,
            p2: p.p2 / BAR,
            rpm: p.omega * 30.0 / std::f64::consts::PI,
            estimate: None,
            command: None,
            applied: self.applied,
            dump: self.dump,
            injection: inj,
        };
        if self.error.is_none() {
            match self.exchange(f, inj) {
                Ok(Some(FromFirmware::Output {
                    estimate,
                    command,
                    applied,
                    dump,
                    ..
                })) => {
                    self.applied = f64::from(applied.to_f32());
                    self.dump = dump;
                    row.estimate = Some(estimate);
                    row.command = Some(command);
                    row.applied = self.applied;
                    row.dump = dump;
                }
                Ok(_) => {}
                Err(e) => self.error = Some(format!("t = {t:.4} s: {e}")),
            }
        }
        self.tick = self.tick.wrapping_add(1);
        self.rows.push(row);
        self.applied / 100.0
    }
}

/// What a closed-loop run returns: the firmware (still running), the plant's trace, every step.
pub type LoopRun = (Qemu, SimResult, Vec<PilRow>);

/// A Test III-like closed-loop run (HC3.1 + HC3.4, Config 1, ±40 mm at 0.1 Hz) with the
/// firmware as the controller, from P2 `p2_start` bar, for `duration` s, with the sensors of
/// `spec` (4–20 mA loops quantised by the firmware's own front end).
pub fn closed_loop(
    mut q: Qemu,
    bench: &Bench,
    mode: Mode,
    p2_start: f64,
    duration: f64,
    spec: SensorSpec,
    inject: Box<dyn Fn(f64) -> Injection>,
) -> Result<LoopRun, String> {
    let s = crate::scenario::builtin_named("test3-ap10").ok_or("test3-ap10 missing")?;
    let prep = s
        .prepare(bench, Path::new("."))
        .map_err(|e| e.to_string())?;
    let lp_start = 8.0;
    prime(&mut q, p2_start as f32, lp_start as f32, mode)?;
    q.link.send(&ToFirmware::SetDuty {
        on_duty: crate::estimation::duty_mask(&prep.on_duty),
        config: prep.config as u8,
    })?;
    let dt_log2 = pto_model::ModelConfig::reference().dt_log2;
    let ctrl = FirmwareController::new(q, dt_log2, spec, 11, inject)?;
    let shared = std::rc::Rc::new(std::cell::RefCell::new(ctrl));
    struct Shim(std::rc::Rc<std::cell::RefCell<FirmwareController>>);
    impl ValveController for Shim {
        fn period(&self) -> f64 {
            self.0.borrow().period()
        }
        fn update(&mut self, t: f64, p: &Eval) -> f64 {
            self.0.borrow_mut().update(t, p)
        }
    }
    let res = sim::simulate(Run {
        plant: &prep.plant,
        valve: ValveSchedule::Controller(Box::new(Shim(shared.clone()))),
        initial: Initial {
            p2: p2_start * BAR,
            lp: lp_start * BAR,
        },
        duration,
        sample_dt: 0.05,
        solver: SolverOptions {
            rtol: 1e-6,
            atol_scale: 0.1,
        },
        progress: None,
    })
    .map_err(|e| e.to_string())?;
    let ctrl = std::rc::Rc::try_unwrap(shared)
        .map_err(|_| "controller still shared")?
        .into_inner();
    if let Some(e) = ctrl.error {
        return Err(e);
    }
    Ok((ctrl.q, res, ctrl.rows))
}

/// Sets the applied aperture to a value for fixed-aperture runs.
pub fn fixed(pct: f32) -> Mode {
    Mode::Fixed(Aperture::from_num(pct))
}
