//! Sensors that fail at plausible values, in closed loop: the firmware's own controller
//! (`pto_firmware::control::Controller`: front end, estimator, scheduler, trip latch, sensor-fault
//! latch) as the valve controller of the full simulation, a Test III-like run, with a fault
//! injected into one sensor from a given time — stuck at its reading, stuck at a chosen value, a
//! drift, a gain error — and what the controller made of it: when it flagged which sensor, and
//! where the plant's P2 went.

use super::closed_loop::{LOOP_LP_START_BAR, test3_like_loop};
use super::sensors::{SensorSpec, SensorSynth};
use super::{ModelError, controller_config, duty_mask, model_config};
use crate::sim::bench::Bench;
use crate::sim::plant::Eval;
use crate::sim::schedule::ValveController;
use crate::sim::trace::Truth;
use pto_firmware::control::{Controller, NoClock, SetupError, StepOut};
use pto_firmware::frontend::Transducer;
use pto_model::fx::{Pressure, Rpm};
use pto_model::protocol::SensorFrame;
use pto_model::scheduler::Mode;
use serde::Serialize;

/// A sensor of the bench.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Sensor {
    /// The HP transducer.
    Hp,
    /// The LP transducer.
    Lp,
    /// The motor speed pickup.
    Motor,
    /// The shaft encoder.
    Encoder,
}

impl std::fmt::Display for Sensor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Sensor::Hp => "HP",
            Sensor::Lp => "LP",
            Sensor::Motor => "motor",
            Sensor::Encoder => "encoder",
        })
    }
}

/// How it fails, in its own unit (bar, rpm, counts).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultKind {
    /// Stuck at the reading it had when the fault began.
    StuckAtReading,
    /// Stuck at this value.
    StuckAt(f64),
    /// Drifting away from the truth at this rate, per second.
    Drift(f64),
    /// Reading the truth times this.
    Gain(f64),
}

/// A fault of one sensor from a time on.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Fault {
    /// Which.
    pub sensor: Sensor,
    /// How.
    pub kind: FaultKind,
    /// From, s.
    pub from_s: f64,
}

impl Fault {
    /// The faulty reading of a value `truth` read at `t` (`start`: the reading when the fault
    /// began). `pub`: the processor-in-the-loop injects the same faults.
    pub fn apply(&self, t: f64, truth: f64, start: f64) -> f64 {
        if t < self.from_s {
            return truth;
        }
        match self.kind {
            FaultKind::StuckAtReading => start,
            FaultKind::StuckAt(v) => v,
            FaultKind::Drift(r) => truth + r * (t - self.from_s),
            FaultKind::Gain(g) => truth * g,
        }
    }
}

/// Why a fault's text (`pto pil --fault`) was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FaultParseError {
    /// Not `SENSOR:KIND`.
    #[error(
        "fault `{0}`: expected SENSOR:KIND[=VALUE][@FROM_S], e.g. hp:stuck, hp:stuck=60, \
         hp:drift=0.5@20, motor:gain=1.2, encoder:stuck"
    )]
    Shape(String),
    /// An unknown sensor.
    #[error("fault `{0}`: sensor `{1}` unknown (hp, lp, motor, encoder)")]
    Sensor(String, String),
    /// An unknown kind, or a value missing or where none is taken.
    #[error(
        "fault `{0}`: kind `{1}` unknown or its value missing (stuck, stuck=VALUE, drift=RATE, \
         gain=FACTOR)"
    )]
    Kind(String, String),
    /// A value out of its range.
    #[error("fault `{text}`: {what} = {value} {unit} out of range ({allowed})")]
    Range {
        /// The whole text.
        text: String,
        /// Which value.
        what: &'static str,
        /// What was given.
        value: String,
        /// Its unit.
        unit: &'static str,
        /// The range taken.
        allowed: &'static str,
    },
}

impl Sensor {
    /// The unit of its readings.
    pub fn unit(self) -> &'static str {
        match self {
            Sensor::Hp | Sensor::Lp => "bar",
            Sensor::Motor => "rpm",
            Sensor::Encoder => "counts",
        }
    }

    /// Its readings' plausible range (a stuck value outside is a range fault, not this kind):
    /// the transducers' 0–400 bar, the pickup's 0–3 000 rpm.
    fn plausible(self) -> Option<(f64, f64, &'static str)> {
        match self {
            Sensor::Hp | Sensor::Lp => Some((0.0, 400.0, "0–400 bar")),
            Sensor::Motor => Some((0.0, 3000.0, "0–3000 rpm")),
            Sensor::Encoder => None,
        }
    }
}

impl std::str::FromStr for Fault {
    type Err = FaultParseError;

    /// `SENSOR:KIND[=VALUE][@FROM_S]`: `hp:stuck` (at its reading), `hp:stuck=60` (bar),
    /// `lp:drift=0.5` (bar/s), `motor:gain=1.2`, `encoder:stuck`; from [`FAULT_FROM_S`] unless
    /// `@FROM_S` says.
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let bad = |e: fn(String) -> FaultParseError| e(text.to_owned());
        let range = |what, value: &str, unit, allowed| FaultParseError::Range {
            text: text.to_owned(),
            what,
            value: value.to_owned(),
            unit,
            allowed,
        };
        let (body, from) = match text.split_once('@') {
            Some((b, f)) => (b, Some(f)),
            None => (text, None),
        };
        let from_s = match from {
            None => FAULT_FROM_S,
            Some(f) => match f.trim().parse::<f64>() {
                Ok(v) if (0.0..=3600.0).contains(&v) => v,
                _ => return Err(range("from", f, "s", "0–3600 s")),
            },
        };
        let (sensor, kind) = body
            .split_once(':')
            .ok_or_else(|| bad(FaultParseError::Shape))?;
        let sensor = match sensor.trim().to_ascii_lowercase().as_str() {
            "hp" => Sensor::Hp,
            "lp" => Sensor::Lp,
            "motor" => Sensor::Motor,
            "encoder" => Sensor::Encoder,
            other => return Err(FaultParseError::Sensor(text.to_owned(), other.to_owned())),
        };
        let (name, value) = match kind.split_once('=') {
            Some((k, v)) => (k.trim(), Some(v.trim())),
            None => (kind.trim(), None),
        };
        let num = |v: &str| v.parse::<f64>().ok().filter(|x| x.is_finite());
        let kind = match (name.to_ascii_lowercase().as_str(), value) {
            ("stuck", None) => FaultKind::StuckAtReading,
            ("stuck", Some(v)) => {
                let x = num(v).ok_or_else(|| range("stuck", v, sensor.unit(), "a number"))?;
                if let Some((lo, hi, allowed)) = sensor.plausible()
                    && !(lo..=hi).contains(&x)
                {
                    return Err(range("stuck", v, sensor.unit(), allowed));
                }
                FaultKind::StuckAt(x)
            }
            ("drift", Some(v)) => match num(v) {
                Some(x) if x != 0.0 && x.abs() <= 100.0 => FaultKind::Drift(x),
                _ => return Err(range("drift", v, "/s", "±100 a second, not 0")),
            },
            ("gain", Some(v)) => match num(v) {
                Some(x) if (0.1..=10.0).contains(&x) && x != 1.0 => FaultKind::Gain(x),
                _ => return Err(range("gain", v, "×", "0.1–10, not 1")),
            },
            _ => return Err(FaultParseError::Kind(text.to_owned(), kind.to_owned())),
        };
        Ok(Fault {
            sensor,
            kind,
            from_s,
        })
    }
}

impl std::fmt::Display for Fault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let u = self.sensor.unit();
        match self.kind {
            FaultKind::StuckAtReading => write!(f, "{} stuck at its reading", self.sensor),
            FaultKind::StuckAt(v) => write!(f, "{} stuck at {v} {u}", self.sensor),
            FaultKind::Drift(r) => write!(f, "{} drifting {r:+} {u}/s", self.sensor),
            FaultKind::Gain(g) => write!(f, "{} reading {g} × the truth", self.sensor),
        }?;
        write!(f, " from {} s", self.from_s)
    }
}

impl Fault {
    /// When it must be flagged by: a drift within the time it takes to drift 5 (bar, rpm,
    /// counts), a motor reading stuck once the speed leaves it, the rest at once.
    pub fn bound(&self) -> Bound {
        match (self.sensor, self.kind) {
            (_, FaultKind::Drift(_)) => Bound::DriftTo(5.0),
            (Sensor::Motor, FaultKind::StuckAt(_) | FaultKind::StuckAtReading) => {
                Bound::MotorLeaves
            }
            _ => Bound::Onset,
        }
    }

    /// The bound in s after the fault's start: for [`Bound::MotorLeaves`] and
    /// [`Bound::P2Above`], from the plant over the run (`(t s, motor rpm, P2 bar)`) and the
    /// reading it stuck at (`stuck_reading`, for [`FaultKind::StuckAtReading`]); infinite when
    /// the speed never left it, or P2 never passed the level.
    pub fn bound_s(
        &self,
        bound: Bound,
        stuck_reading: Option<f64>,
        mut plant: impl Iterator<Item = (f64, f64, f64)>,
    ) -> f64 {
        DETECT_WITHIN_S
            + match bound {
                Bound::Onset => 0.0,
                Bound::P2Above(x) => plant
                    .find(|&(t, _, p2)| t >= self.from_s && p2 > x)
                    .map_or(f64::INFINITY, |(t, _, _)| t - self.from_s),
                Bound::DriftTo(d) => match self.kind {
                    FaultKind::Drift(r) => d / r.abs(),
                    _ => 0.0,
                },
                Bound::MotorLeaves => {
                    let reading = match self.kind {
                        FaultKind::StuckAt(v) => Some(v),
                        _ => stuck_reading,
                    };
                    reading.map_or(f64::INFINITY, |v| self.motor_leaves(v, plant))
                }
            }
    }

    /// The first time, s after the fault's start, that the true speed has stayed for 1 s
    /// outside what the motor check can tell from the stuck reading `v`: its allowance (5 rpm +
    /// 1/16 of the speed) plus the model's own speed error (3 % of the speed, the validated
    /// RMS bound: the check compares with the model's speed, not the truth).
    fn motor_leaves(&self, v: f64, plant: impl Iterator<Item = (f64, f64, f64)>) -> f64 {
        let mut since = None;
        for (t, rpm, _) in plant.filter(|(t, _, _)| *t >= self.from_s) {
            let out = (rpm - v).abs() > 5.0 + rpm.abs() * (1.0 / 16.0 + 0.03);
            match (out, since) {
                (true, None) => since = Some(t),
                (false, _) => since = None,
                (true, Some(t0)) if t - t0 >= 1.0 => return t - self.from_s,
                _ => {}
            }
        }
        f64::INFINITY
    }

    /// The mode a run of it holds: the speed for a motor fault (its check needs the valve
    /// open), P2 at 100 bar for the others.
    pub fn mode(&self) -> Mode {
        match self.sensor {
            Sensor::Motor => Mode::HoldSpeed(Rpm::from_num(250.0)),
            _ => Mode::HoldPressure(Pressure::from_num(100.0)),
        }
    }
}

/// One step as the loop saw it.
#[derive(Debug, Clone, Copy)]
pub struct FaultRow {
    /// Time, s.
    pub t: f64,
    /// Plant P2, bar.
    pub p2_bar: f64,
    /// Plant motor speed, rpm.
    pub rpm: f64,
    /// The controller's step.
    pub out: StepOut,
    /// The sensor faults the controller holds (bit per [`Sensor`]).
    pub sensor_faults: u8,
    /// The estimator's residuals after the step.
    pub resid: pto_model::estimator::ResidualState,
}

/// The firmware's controller on a sensor model with one fault.
pub struct FaultLoop {
    ctl: Controller,
    synth: SensorSynth,
    hp: Transducer,
    lp: Transducer,
    fault: Option<Fault>,
    /// Each sensor's reading when the fault began.
    start: Option<f64>,
    tick: u32,
    period: f64,
    applied: f64,
    /// Every step.
    pub rows: Vec<FaultRow>,
}

impl FaultLoop {
    fn frame(&mut self, t: f64, theta: f64, truth: &Truth) -> SensorFrame {
        let r = self.synth.read_analog(theta, truth);
        let mut v = [r.hp_bar, r.lp_bar, r.motor_rpm, f64::from(r.encoder_count)];
        if let Some(f) = self.fault {
            let i = f.sensor as usize;
            if t >= f.from_s && self.start.is_none() {
                self.start = Some(v[i]);
            }
            v[i] = f.apply(t, v[i], self.start.unwrap_or(v[i]));
        }
        SensorFrame {
            tick: self.tick,
            encoder: v[3].round() as i32,
            hp_adc: self.hp.counts_at_bar(v[0] as f32),
            lp_adc: self.lp.counts_at_bar(v[1] as f32),
            motor: Some(Rpm::from_num(v[2].max(0.0) as f32)),
            supply_mv: Some(self.hp.vref_mv()),
        }
    }
}

impl ValveController for FaultLoop {
    fn period(&self) -> f64 {
        self.period
    }

    fn update(&mut self, t: f64, p: &Eval) -> f64 {
        let truth = Truth::of_eval(p);
        let f = self.frame(t, p.theta_rad, &truth);
        let out = self.ctl.sample(&f, &mut NoClock);
        self.tick = self.tick.wrapping_add(1);
        self.applied = f64::from(out.applied.to_f32());
        self.rows.push(FaultRow {
            t,
            p2_bar: truth.p2_bar,
            rpm: truth.motor_rpm,
            out,
            sensor_faults: self.ctl.status.sensor_faults,
            resid: self.ctl.residuals(),
        });
        self.applied
    }
}

/// Why a fault run could not be made.
#[derive(Debug, thiserror::Error)]
pub enum FaultRunError {
    /// The loop could not be run.
    #[error(transparent)]
    Loop(#[from] super::closed_loop::LoopError),
    /// The bench has no model configuration.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// The controller refused the configuration.
    #[error("{0}")]
    Setup(SetupError),
    /// The transducer loops.
    #[error("{0}")]
    Transducer(pto_firmware::frontend::SpecError),
}

/// A Test III-like run of `duration` s from P2 `p2_start` bar with the firmware's controller in
/// `mode`, the sensors of [`SensorSpec::default`] (noise seed `seed`) with `fault`.
pub fn fault_run(
    bench: &Bench,
    mode: Mode,
    p2_start: f64,
    duration: f64,
    fault: Option<Fault>,
    seed: u64,
) -> Result<FaultLoop, FaultRunError> {
    let mcfg = model_config(bench)?;
    let (sched, cc) = controller_config(bench);
    let period = 2f64.powi(-i32::from(mcfg.dt_log2));
    let (_, ctl) = test3_like_loop(bench, p2_start, duration, |prep| {
        let mut ctl = Controller::new(&mcfg, &sched, &cc).map_err(FaultRunError::Setup)?;
        ctl.reset(
            Pressure::from_num(p2_start as f32),
            Pressure::from_num(LOOP_LP_START_BAR as f32),
        )
        .map_err(|_| {
            FaultRunError::Setup(SetupError::Control {
                field: "reset",
                value: 0.0,
            })
        })?;
        ctl.set_duty(duty_mask(&prep.on_duty), prep.config as u8);
        ctl.set_mode(mode);
        let spec = SensorSpec::default();
        Ok::<_, FaultRunError>(FaultLoop {
            ctl,
            synth: SensorSynth::new(spec, seed),
            hp: Transducer::new(spec.hp_loop).map_err(FaultRunError::Transducer)?,
            lp: Transducer::new(spec.lp_loop).map_err(FaultRunError::Transducer)?,
            fault,
            start: None,
            tick: 0,
            period,
            applied: 0.0,
            rows: Vec::new(),
        })
    })?;
    Ok(ctl)
}

/// Start of the fault, s, in the cases below (the plant's P2 is still rising from 60 bar).
pub const FAULT_FROM_S: f64 = 20.0;
/// Length of the runs, s.
pub const RUN_S: f64 = 200.0;
/// Flagged within this of the fault's start, s (the acceptance's bound).
pub const DETECT_WITHIN_S: f64 = 5.0;

/// When a case must be flagged by.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Bound {
    /// Within [`DETECT_WITHIN_S`] of the fault's start.
    Onset,
    /// A drift: within the time it takes to drift this far, plus [`DETECT_WITHIN_S`], s.
    DriftTo(f64),
    /// A motor reading stuck where the speed was: the check sees it only once the true speed
    /// leaves it by the motor check's allowance (5 rpm + 1/16 of the speed, 1 s); flagged
    /// within [`DETECT_WITHIN_S`] of that.
    MotorLeaves,
    /// A reading stuck low, below where the shadow judges (27.1 bar on the reference bench):
    /// the stuck-low check names it once the model has counted more oil pumped in under it than
    /// the accumulator holds there (+ 1 % of its volume), i.e. once the plant's P2 is about a
    /// bar above that; within [`DETECT_WITHIN_S`] of the plant's P2 first exceeding this, bar.
    P2Above(f64),
}

/// A fault case of the table: the mode held, the fault, the sensor that must be named.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Case {
    /// Name.
    pub name: &'static str,
    /// The mode held.
    #[serde(skip)]
    pub mode: Mode,
    /// The fault.
    pub fault: Fault,
    /// The sensor the controller must hold faulted.
    pub named: Sensor,
    /// When by.
    pub bound: Bound,
    /// The plant's P2 at the start, bar.
    pub start_bar: f64,
}

/// The cases: the table (HP stuck at its reading, at 60 bar, drifting; HP stuck with
/// the valve closed; the motor stuck) and the same kinds on the other sensors.
pub fn cases() -> Vec<Case> {
    use pto_model::fx::{Aperture, Pressure, Rpm};
    let hold = Mode::HoldPressure(Pressure::from_num(100.0));
    let speed = Mode::HoldSpeed(Rpm::from_num(250.0));
    let closed = Mode::Fixed(Aperture::ZERO);
    use FaultKind::*;
    use Sensor::*;
    // (name, mode, sensor, kind, the plant's P2 at the start: 100 bar, the setpoint, where the
    // controller regulates when the fault comes; 60 bar for a charge)
    #[rustfmt::skip]
    let table = [
        ("HP stuck at its reading, hold P2 100 bar", hold, Hp, StuckAtReading, 100.0),
        ("HP stuck at 60 bar, hold P2 100 bar", hold, Hp, StuckAt(60.0), 100.0),
        ("HP drifting +0.5 bar/s, hold P2 100 bar", hold, Hp, Drift(0.5), 100.0),
        ("HP stuck at 72 bar, valve closed", closed, Hp, StuckAt(72.0), 60.0),
        ("HP reading 0.9 × P2, hold P2 100 bar", hold, Hp, Gain(0.9), 100.0),
        ("motor stuck at 245 rpm, hold speed 250 rpm", speed, Motor, StuckAt(245.0), 60.0),
        ("motor stuck at its reading, hold speed 250 rpm", speed, Motor, StuckAtReading, 60.0),
        ("motor reading 1.2 × speed, hold speed 250 rpm", speed, Motor, Gain(1.2), 60.0),
        ("LP stuck at 3 bar, hold P2 100 bar", hold, Lp, StuckAt(3.0), 100.0),
        ("LP drifting +0.5 bar/s, hold P2 100 bar", hold, Lp, Drift(0.5), 100.0),
        ("encoder stuck, hold P2 100 bar", hold, Encoder, StuckAtReading, 100.0),
        ("HP drifting −0.2 bar/s, hold P2 100 bar", hold, Hp, Drift(-0.2), 100.0),
        ("HP drifting −0.2 bar/s through a charge, hold P2 100 bar", hold, Hp, Drift(-0.2), 60.0),
        ("HP drifting −0.05 bar/s, hold P2 100 bar", hold, Hp, Drift(-0.05), 100.0),
        ("HP drifting −0.05 bar/s, valve closed", closed, Hp, Drift(-0.05), 60.0),
    ];
    let mut v: Vec<Case> = table
        .into_iter()
        .map(|(name, mode, sensor, kind, start_bar)| {
            let fault = Fault {
                sensor,
                kind,
                from_s: FAULT_FROM_S,
            };
            Case {
                name,
                mode,
                fault,
                named: sensor,
                bound: fault.bound(),
                start_bar,
            }
        })
        .collect();
    // A transducer dead at its rest reading from the start, below the precharge: the shadow
    // does not judge there (the lines' stiff oil); the stuck-low check does.
    let fault = Fault {
        sensor: Hp,
        kind: StuckAtReading,
        from_s: 0.05,
    };
    v.push(Case {
        name: "HP stuck at its reading from a start at 15 bar, hold P2 100 bar",
        mode: hold,
        fault,
        named: Hp,
        bound: Bound::P2Above(28.1),
        start_bar: 15.0,
    });
    v
}

/// What a case gave.
#[derive(Debug, Clone, Serialize)]
pub struct Detection {
    /// The case.
    pub case: Case,
    /// When the controller first held a sensor faulted, s after the fault's start.
    pub after_s: Option<f64>,
    /// Which it held first (names).
    pub held: Vec<&'static str>,
    /// The bound it had to meet, s after the fault's start.
    pub bound_s: f64,
    /// The plant's P2 then, bar.
    pub p2_at_detection_bar: Option<f64>,
    /// The plant's P2 from the fault's start to the end of the run, bar (min, max).
    pub p2_after_bar: (f64, f64),
    /// How far the fault moved the plant's P2 before it was flagged (to the run's end if
    /// never): the largest |P2 − P2 of the same run without the fault| from the fault's start,
    /// bar. "Never drifting silently": at most [`SILENT_DRIFT_BAR`].
    pub p2_silent_bar: f64,
    /// The plant's highest P2 from the detection on, bar (below the trip: the safe state holds
    /// P2 down, not only the relief).
    pub p2_max_after_detection_bar: Option<f64>,
    /// The controller stayed in its safe state from the detection to the end (the valve at the
    /// sensor-fault aperture, or tripped, or the dump valve open).
    pub safe_after: bool,
    /// Named the right sensor, within its bound, stayed safe, P2 not moved more than
    /// [`SILENT_DRIFT_BAR`] before and below the trip after.
    pub pass: bool,
}

/// The most a fault may move the plant's P2 before it is flagged, bar (the acceptance's
/// "within ± 10 bar … never drifting silently").
pub const SILENT_DRIFT_BAR: f64 = 10.0;

/// The latch's bit of a sensor (`pto_firmware::sensor_faults::bit`).
pub fn sensor_bit(s: Sensor) -> u8 {
    use pto_firmware::sensor_faults::bit;
    match s {
        Sensor::Hp => bit::HP,
        Sensor::Lp => bit::LP,
        Sensor::Motor => bit::MOTOR,
        Sensor::Encoder => bit::ENCODER,
    }
}

/// Runs the cases (noise seed `seed`) and judges each, in parallel; the first run that could
/// not be made ends it.
///
/// Each case is judged against the same run without its fault (same noise): what the fault did
/// to the plant. That run depends only on the mode held and the start, so the cases share one
/// per pair (five pairs for the sensor-fault test's 64 cases and `pto validate`'s 16): made
/// again for each case, it was half of the test's 128 s.
pub fn detect_all(
    bench: &Bench,
    cases: &[Case],
    seed: u64,
) -> Result<Vec<Detection>, FaultRunError> {
    use rayon::prelude::*;
    let mut starts: Vec<(Mode, f64)> = Vec::new();
    let start_of: Vec<usize> = cases
        .iter()
        .map(|c| {
            let s = (c.mode, c.start_bar);
            starts.iter().position(|x| *x == s).unwrap_or_else(|| {
                starts.push(s);
                starts.len() - 1
            })
        })
        .collect();
    let free: Vec<FaultLoop> = starts
        .par_iter()
        .map(|&(mode, p2)| fault_run(bench, mode, p2, RUN_S, None, seed))
        .collect::<Result<_, _>>()?;
    cases
        .par_iter()
        .zip(start_of)
        .map(|(c, i)| detect_against(bench, c, seed, &free[i]))
        .collect()
}

/// Runs a case (noise seed `seed`) and judges it against `free`, the same run without the
/// fault.
fn detect_against(
    bench: &Bench,
    c: &Case,
    seed: u64,
    free: &FaultLoop,
) -> Result<Detection, FaultRunError> {
    let (sched, _) = controller_config(bench);
    let l = fault_run(bench, c.mode, c.start_bar, RUN_S, Some(c.fault), seed)?;
    let from = c.fault.from_s;
    let first = l.rows.iter().find(|r| r.sensor_faults != 0);
    let bound_s = c.fault.bound_s(
        c.bound,
        l.start,
        l.rows.iter().map(|r| (r.t, r.rpm, r.p2_bar)),
    );
    let after: Vec<&FaultRow> = l.rows.iter().filter(|r| r.t >= from).collect();
    let (lo, hi) = after
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), r| {
            (a.min(r.p2_bar), b.max(r.p2_bar))
        });
    let safe_op = f64::from(sched.sensor_fault_aperture_pct);
    let safe_after = first.is_some_and(|f0| {
        l.rows
            .iter()
            .filter(|r| r.t >= f0.t)
            .all(|r| r.out.dump || (f64::from(r.out.applied.to_f32()) - safe_op).abs() < 1e-3)
    });
    let held = first.map_or(0, |r| r.sensor_faults);
    let held_at_end = l.rows.last().map_or(0, |r| r.sensor_faults);
    let after_s = first.map(|r| r.t - from);
    let until = first.map_or(f64::INFINITY, |r| r.t);
    let p2_silent_bar = l
        .rows
        .iter()
        .zip(&free.rows)
        .filter(|(r, _)| r.t >= from && r.t <= until)
        .map(|(r, g)| (r.p2_bar - g.p2_bar).abs())
        .fold(0.0, f64::max);
    let p2_max_after_detection_bar = first.map(|f0| {
        l.rows
            .iter()
            .filter(|r| r.t >= f0.t)
            .map(|r| r.p2_bar)
            .fold(f64::NEG_INFINITY, f64::max)
    });
    let trip_bar = f64::from(model_config(bench)?.trip_bar);
    Ok(Detection {
        case: *c,
        after_s,
        held: pto_firmware::sensor_faults::names(held).collect(),
        bound_s,
        p2_at_detection_bar: first.map(|r| r.p2_bar),
        p2_after_bar: (lo, hi),
        p2_silent_bar,
        p2_max_after_detection_bar,
        safe_after,
        pass: judge(held, sensor_bit(c.named), after_s, bound_s, safe_after)
            && (after_s.is_none() || held_at_end == held)
            && p2_silent_bar <= SILENT_DRIFT_BAR
            && p2_max_after_detection_bar.is_none_or(|p| p < trip_bar),
    })
}

/// A fault run's verdict: the sensor `want` (alone) held within the bound and the controller
/// safe from then on; or, where the bound is infinite (a motor reading stuck where the speed
/// stayed: nothing to tell it by), nothing held.
pub fn judge(held: u8, want: u8, after_s: Option<f64>, bound_s: f64, safe_after: bool) -> bool {
    match after_s {
        Some(t) => held == want && (0.0..=bound_s).contains(&t) && safe_after,
        None => bound_s.is_infinite(),
    }
}

/// The fault-free closed loops the false alarms are counted in (mode, P2 at the start, bar):
/// hold P2 from 60 bar and from its setpoint (a start there once flagged the motor implausible
/// while the valve opened), hold the speed, the valve closed and at 10 %.
pub fn fault_free_loops() -> [(Mode, f64); 5] {
    use pto_model::fx::{Aperture, Pressure, Rpm};
    let hold = Mode::HoldPressure(Pressure::from_num(100.0));
    [
        (hold, 60.0),
        (hold, 100.0),
        (Mode::HoldSpeed(Rpm::from_num(250.0)), 60.0),
        (Mode::Fixed(Aperture::ZERO), 60.0),
        (Mode::Fixed(Aperture::from_num(10.0)), 60.0),
    ]
}

/// Steps with a false alarm in a fault-free closed loop holding `mode` from `p2_start` bar: a
/// sensor held faulted, or the motor reading flagged implausible (`MOTOR_IMPLAUSIBLE`, raised
/// for ≈ 450 steps at every start before the check asked the model's own rotor too).
pub fn false_alarms(
    bench: &Bench,
    mode: Mode,
    p2_start: f64,
    seed: u64,
) -> Result<usize, FaultRunError> {
    use pto_model::estimator::fault::MOTOR_IMPLAUSIBLE;
    let l = fault_run(bench, mode, p2_start, RUN_S, None, seed)?;
    Ok(l.rows
        .iter()
        .filter(|r| r.sensor_faults != 0 || r.out.estimate.faults & MOTOR_IMPLAUSIBLE != 0)
        .count())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fault_is_read_from_its_text_and_bad_text_is_refused_naming_what_and_the_range() {
        let f: Fault = "hp:stuck=60@12.5".parse().unwrap();
        assert_eq!(
            f,
            Fault {
                sensor: Sensor::Hp,
                kind: FaultKind::StuckAt(60.0),
                from_s: 12.5
            }
        );
        assert_eq!(f.to_string(), "HP stuck at 60 bar from 12.5 s");
        let g: Fault = "Motor:gain=1.2".parse().unwrap();
        assert_eq!(
            (g.kind, g.from_s, g.bound()),
            (FaultKind::Gain(1.2), FAULT_FROM_S, Bound::Onset)
        );
        assert_eq!(
            "encoder:stuck".parse::<Fault>().unwrap().kind,
            FaultKind::StuckAtReading
        );
        assert_eq!(
            "lp:drift=-0.5".parse::<Fault>().unwrap().bound(),
            Bound::DriftTo(5.0)
        );
        assert_eq!(
            "motor:stuck".parse::<Fault>().unwrap().bound(),
            Bound::MotorLeaves
        );
        for (text, says) in [
            ("hp", "expected SENSOR:KIND"),
            ("pump:stuck", "sensor `pump` unknown"),
            ("hp:wobble", "kind `wobble` unknown"),
            ("hp:drift", "kind `drift` unknown or its value missing"),
            ("hp:stuck=500", "stuck = 500 bar out of range (0–400 bar)"),
            ("motor:stuck=-3", "stuck = -3 rpm out of range (0–3000 rpm)"),
            ("hp:drift=0", "drift = 0 /s out of range"),
            ("hp:gain=1", "gain = 1 × out of range (0.1–10, not 1)"),
            ("hp:gain=NaN", "gain = NaN"),
            ("hp:stuck@-1", "from = -1 s out of range (0–3600 s)"),
        ] {
            let e = text.parse::<Fault>().unwrap_err().to_string();
            assert!(e.contains(says), "{text}: {e}");
            assert!(e.contains(text.split('@').next().unwrap()), "{text}: {e}");
        }
    }

    #[test]
    fn a_fault_s_bound_follows_its_kind() {
        // A drift of 0.5 bar/s has 10 s to reach 5 bar, then the 5 s.
        let d: Fault = "hp:drift=0.5".parse().unwrap();
        assert_eq!(d.bound_s(d.bound(), None, std::iter::empty()), 15.0);
        // A motor reading stuck at 245 rpm: the speed leaves 245 ± (5 rpm + 9.25 %) at 22 s
        // and stays out; bound 1 s later plus 5 s. Stuck at its reading of 252 rpm with the
        // speed at 250 to the end: never (nothing to tell it by), and judged so.
        let speed = || {
            (0..4000).map(|k| {
                let t = f64::from(k) * 0.01;
                (t, if t < 22.0 { 250.0 } else { 300.0 }, 100.0)
            })
        };
        let m: Fault = "motor:stuck=245".parse().unwrap();
        let b = m.bound_s(m.bound(), None, speed());
        assert!((b - 8.0).abs() < 0.02, "{b}");
        let r: Fault = "motor:stuck".parse().unwrap();
        let flat = (0..4000).map(|k| (f64::from(k) * 0.01, 250.0, 100.0));
        let inf = r.bound_s(r.bound(), Some(252.0), flat);
        assert!(inf.is_infinite());
        assert!(judge(0, 4, None, inf, false));
        assert!(!judge(1, 4, Some(3.0), inf, true), "the wrong sensor named");
        assert!(!judge(0, 4, None, 8.0, false), "a fault to tell, missed");
    }
}
