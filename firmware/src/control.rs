//! The control step shared by both boards: raw sample → supply correction → transducer
//! conversion → estimator → scheduler → overpressure trip latch → actuator stage (slew limit,
//! safe state) → the bring-up self-test's overlay, if one is active.
//!
//! Configuration ([`ControlConfig`], [`ModelConfig`], [`SchedulerConfig`]) is validated once by
//! [`Controller::new`]; the per-step functions cannot fail.

use crate::frontend::{LoopReading, SpecError, SupplyCorrection, Transducer};
use crate::outputs::Outputs;
use crate::selftest::{Ended, SelfTestState};
use crate::sensor_faults::{SensorFaults, bit};
use crate::trip::{TripLatch, TripSample};
use pto_model::estimator::{self, Estimate, Inputs, State, fault};
use pto_model::fx::{Aperture, Fx, Pressure, ZERO, clamp, mul_dt};
use pto_model::protocol::selftest::{InputReport, LoopReport, LoopState, TestDrive};
use pto_model::protocol::{
    BoardInfo, FromFirmware, SelfTestRefusal, SensorFrame, Status, TripHold,
};
use pto_model::scheduler::{self, Command, Mode, Override, SchedulerCoeffs, SchedulerConfig};
use pto_model::{Coefficients, ConfigError, ModelConfig, SchedulerState};

/// Measures the cost of the model step: instructions under QEMU `-icount shift=0` (TIM2), cycles
/// on the bench (DWT). Implementations run `f` with interrupts masked so the count is the step's
/// own.
pub trait StepClock {
    /// Runs `f` and returns its result and its cost.
    fn measure<R>(&mut self, f: impl FnOnce() -> R) -> (R, u32);
    /// The free-running count the costs are differences of (wraps), for what is too big to
    /// pass through [`StepClock::measure`]'s closure (a controller is ≈ 11 KB: each copy of it
    /// on the way out would be stack) and too long to mask interrupts for: such a cost includes
    /// any interrupt taken meanwhile.
    fn count(&mut self) -> u32;
}

/// A clock that does not measure (host tools, tests).
#[derive(Debug, Default, Clone, Copy)]
pub struct NoClock;

impl StepClock for NoClock {
    fn measure<R>(&mut self, f: impl FnOnce() -> R) -> (R, u32) {
        (f(), 0)
    }
    fn count(&mut self) -> u32 {
        0
    }
}

/// Cylinders on duty at boot, until the host or the operator says otherwise: HC3.1 and HC3.4,
/// the pair of the paper's Test III.
pub const BOOT_ON_DUTY: u8 = 0b1001;

pub use pto_model::control::ControlConfig;

/// Why the controller cannot start.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SetupError {
    /// Model or scheduler configuration.
    Model(ConfigError),
    /// Transducer loop.
    Loop(SpecError),
    /// A [`ControlConfig`] field outside its range.
    Control {
        /// Field.
        field: &'static str,
        /// Value.
        value: f32,
    },
}

impl core::fmt::Display for SetupError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            SetupError::Model(e) => write!(f, "{e}"),
            SetupError::Loop(e) => write!(f, "{e}"),
            SetupError::Control { field, value } => {
                write!(f, "control config: {field} = {value} is outside its range")
            }
        }
    }
}

pub use pto_model::protocol::NotSafe;

/// Why a configuration cannot replace the running one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ReconfigureError {
    /// Not in the declared safe state.
    NotSafe(NotSafe),
    /// The configuration is not valid.
    Setup(SetupError),
}

impl From<SetupError> for ReconfigureError {
    fn from(e: SetupError) -> Self {
        ReconfigureError::Setup(e)
    }
}

/// What one closed-loop step produced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepOut {
    /// Estimator output.
    pub estimate: Estimate,
    /// Scheduler output.
    pub command: Command,
    /// Aperture applied to the valve.
    pub applied: Aperture,
    /// Dump valve open.
    pub dump: bool,
    /// Solenoids energised (bit i = HC3.(i+1)).
    pub on_duty: u8,
    /// A self-test ended by itself in this step, and why.
    pub selftest_ended: Option<Ended>,
    /// Sensors the residuals named in this step and the controller now holds faulted.
    pub sensor_faults_new: u8,
}

impl StepOut {
    /// The step's answer to the host whose frame (`tick`) it stepped on.
    #[inline(always)]
    pub fn reply(self, tick: u32) -> FromFirmware {
        FromFirmware::Output {
            tick,
            estimate: self.estimate,
            command: self.command,
            applied: self.applied,
            dump: self.dump,
            on_duty: self.on_duty,
        }
    }

    /// The outputs to drive.
    pub fn outputs(&self) -> Outputs {
        Outputs {
            aperture: self.applied,
            dump_open: self.dump,
            on_duty: self.on_duty,
        }
    }
}

/// The controller: model coefficients, estimator and scheduler state, trip latch, actuator.
#[derive(Debug, Clone)]
pub struct Controller {
    k: Coefficients,
    sc: SchedulerCoeffs,
    st: State,
    sst: SchedulerState,
    mode: Mode,
    on_duty: u8,
    config: u8,
    /// The outputs held de-energised since boot, until the host's first mode, duty or reset
    /// command: a controller that reset (watchdog, fault, brown-out) does not close the dump
    /// valve or energise a solenoid by itself.
    held: bool,
    hp: Transducer,
    lp: Transducer,
    hp_supply: SupplyCorrection,
    lp_supply: SupplyCorrection,
    /// The last sample stepped and how many were (the self-test's report).
    last_frame: Option<SensorFrame>,
    samples: u32,
    selftest: Option<SelfTestState>,
    safe_op: Fx,
    /// The valve's aperture while a sensor is held faulted (`sensor_fault_aperture_pct`).
    sensor_fault_op: Fx,
    /// The sensors held faulted.
    sensor_faults: SensorFaults,
    /// LP is known: from a reading since boot, or from the host's reset.
    lp_known: bool,
    latch: TripLatch,
    /// What the latch saw of the last step (what a host reset is judged on; `None` before the
    /// first step).
    last: Option<TripSample>,
    /// The estimate has been confirmed by a valid HP reading the gate took since boot or the
    /// host's last reset.
    confirmed: bool,
    /// P2's variance at boot (P2 unknown), bar².
    boot_var: Fx,
    slew_step: Fx,
    applied: Fx,
    last_tick: Option<u32>,
    /// Health counters (the link counters are filled in by the receive task).
    pub status: Status,
}

/// What a configuration makes of the controller besides its coefficient tables, worked out
/// and checked from them. The tables (≈ 11 KB) are built once into a local and moved into place
/// at the end: no second whole controller, and no chain of functions each returning a copy of
/// the tables, is ever on the stack (a commit that stored once took the stack down through the
/// statics: a QEMU lockup).
struct Rest {
    sc: SchedulerCoeffs,
    sensor_fault_op: Fx,
    hp: Transducer,
    lp: Transducer,
    latch: TripLatch,
    safe_op: Fx,
    boot_var: Fx,
    boot_sigma: Fx,
    slew_step: Fx,
}

impl Rest {
    #[inline(never)]
    fn of(
        k: &Coefficients,
        sched: &SchedulerConfig,
        cc: &ControlConfig,
    ) -> Result<Self, SetupError> {
        let sc = sched.coefficients(k).map_err(SetupError::Model)?;
        let hp = Transducer::new(cc.hp).map_err(SetupError::Loop)?;
        let lp = Transducer::new(cc.lp).map_err(SetupError::Loop)?;
        let check = |field, v: f32, lo: f32, hi: f32| {
            if v.is_finite() && v >= lo && v <= hi {
                Ok(())
            } else {
                Err(SetupError::Control { field, value: v })
            }
        };
        check(
            "trip_release_margin_bar",
            cc.trip_release_margin_bar,
            1.0,
            100.0,
        )?;
        check(
            "valve_slew_pct_per_s",
            cc.valve_slew_pct_per_s,
            1.0,
            10_000.0,
        )?;
        check("boot_sigma_bar", cc.boot_sigma_bar, 0.1, 200.0)?;
        let release = k
            .trip_bar
            .saturating_sub(Fx::saturating_from_num(cc.trip_release_margin_bar));
        let steps_per_s = f32::from(1u16 << k.dt_log2);
        // 1 ms to 60 s, and within what the hold's u16 step count holds at the configured dt.
        check(
            "trip_release_hold_ms",
            cc.trip_release_hold_ms,
            (1e3 / steps_per_s).max(1.0),
            (65_535e3 / steps_per_s).min(60_000.0),
        )?;
        let hold_steps = (cc.trip_release_hold_ms * 1e-3 * steps_per_s + 0.5) as u16;
        Ok(Rest {
            latch: TripLatch::new(Pressure(k.trip_bar), Pressure(release), hold_steps),
            slew_step: mul_dt(Fx::saturating_from_num(cc.valve_slew_pct_per_s), k.dt_log2),
            safe_op: Fx::saturating_from_num(sched.overpressure_aperture_pct),
            sensor_fault_op: Fx::saturating_from_num(sched.sensor_fault_aperture_pct),
            boot_var: Fx::saturating_from_num(cc.boot_sigma_bar * cc.boot_sigma_bar),
            boot_sigma: Fx::saturating_from_num(cc.boot_sigma_bar),
            sc,
            hp,
            lp,
        })
    }
}

impl Controller {
    /// Validates the configuration and precomputes everything; the estimator starts with P2
    /// unknown (large uncertainty) until [`Controller::reset`]. The outputs are held
    /// de-energised ([`Controller::held`]) until the host's first mode, duty or reset command.
    pub fn new(
        model: &ModelConfig,
        sched: &SchedulerConfig,
        cc: &ControlConfig,
    ) -> Result<Self, SetupError> {
        let k = match model.coefficients() {
            Ok(k) => k,
            Err(e) => return Err(SetupError::Model(e)),
        };
        let p = Rest::of(&k, sched, cc)?;
        Ok(Controller {
            sc: p.sc,
            st: State::new(Pressure::ZERO, Pressure::ZERO, Pressure(p.boot_sigma)),
            sst: SchedulerState::default(),
            mode: Mode::Fixed(Aperture::ZERO),
            on_duty: BOOT_ON_DUTY,
            config: 0,
            held: true,
            hp_supply: SupplyCorrection::new(p.hp.vref_mv()),
            lp_supply: SupplyCorrection::new(p.lp.vref_mv()),
            hp: p.hp,
            lp: p.lp,
            last_frame: None,
            samples: 0,
            selftest: None,
            safe_op: p.safe_op,
            sensor_fault_op: p.sensor_fault_op,
            sensor_faults: SensorFaults::default(),
            lp_known: false,
            latch: p.latch,
            last: None,
            confirmed: false,
            boot_var: p.boot_var,
            slew_step: p.slew_step,
            applied: ZERO,
            last_tick: None,
            status: Status {
                held: true,
                dump_valve: true,
                ..Status::default()
            },
            k,
        })
    }

    /// Runs another model configuration from the next step, refused (nothing changed) outside
    /// the declared safe state ([`Controller::safe_to_apply`]) or with another model step than
    /// the board samples at; otherwise the same checks as [`Controller::new`]. The estimator
    /// restarts from its last P2 and LP with the boot uncertainty (a missing HP reading keeps
    /// it there until a reading confirms P2, as after a host reset); the mode, the cylinders
    /// on duty, the hold, the health counters, the tick count, the trip latch (its count; its
    /// state when the trip pressure is unchanged) and the applied aperture carry over.
    #[inline(never)]
    pub fn reconfigure(
        &mut self,
        model: &ModelConfig,
        sched: &SchedulerConfig,
        cc: &ControlConfig,
    ) -> Result<(), ReconfigureError> {
        self.may_take(model)?;
        let k = match model.coefficients() {
            Ok(k) => k,
            Err(e) => return Err(SetupError::Model(e).into()),
        };
        let p = Rest::of(&k, sched, cc)?;
        if k.trip_bar != self.k.trip_bar {
            let trips = self.latch.trips;
            self.latch = p.latch;
            self.latch.trips = trips;
        }
        self.st = State::new(
            Pressure(self.st.node.p2),
            Pressure(self.st.node.lp),
            Pressure(p.boot_sigma),
        );
        self.sst = SchedulerState::default();
        self.confirmed = false;
        self.hp_supply = SupplyCorrection::new(p.hp.vref_mv());
        self.lp_supply = SupplyCorrection::new(p.lp.vref_mv());
        (self.hp, self.lp) = (p.hp, p.lp);
        (self.safe_op, self.boot_var, self.slew_step) = (p.safe_op, p.boot_var, p.slew_step);
        self.sensor_fault_op = p.sensor_fault_op;
        self.sc = p.sc;
        self.k = k;
        Ok(())
    }

    /// Whether [`Controller::reconfigure`] would take `model`, without changing anything (its
    /// coefficients are worked out on the stack and dropped).
    #[inline(never)]
    pub fn check_reconfigure(
        &self,
        model: &ModelConfig,
        sched: &SchedulerConfig,
        cc: &ControlConfig,
    ) -> Result<(), ReconfigureError> {
        self.may_take(model)?;
        match model.coefficients() {
            Ok(k) => Rest::of(&k, sched, cc)
                .map(|_| ())
                .map_err(ReconfigureError::from),
            Err(e) => Err(SetupError::Model(e).into()),
        }
    }

    /// Whether this controller may take `model` at all: the safe state, the board's step.
    fn may_take(&self, model: &ModelConfig) -> Result<(), ReconfigureError> {
        self.safe_to_apply().map_err(ReconfigureError::NotSafe)?;
        if model.dt_log2 != self.k.dt_log2 {
            // The step is the board's sampling period, fixed at boot.
            let dt = f32::from(self.k.dt_log2);
            return Err(ReconfigureError::Setup(SetupError::Model(ConfigError {
                field: "dt_log2",
                value: f32::from(model.dt_log2),
                min: dt,
                max: dt,
            })));
        }
        Ok(())
    }

    /// The declared safe state in which the controller may stop stepping for a while (building
    /// a configuration's tables, ≈ 1 s on the bench; a flash erase, up to ≈ 2 s): the host set
    /// mode `Fixed(0)`, the valve is closed (the relief valve caps HP), the trip latch is armed
    /// and the last sample had a valid HP reading (P2 is known).
    pub fn safe_to_apply(&self) -> Result<(), NotSafe> {
        if self.status.tripped {
            Err(NotSafe::Tripped)
        } else if self.selftest.is_some() {
            Err(NotSafe::SelfTest)
        } else if self.mode != Mode::Fixed(Aperture::ZERO) || self.applied != ZERO {
            Err(NotSafe::ValveOpen)
        } else if !self.last.is_some_and(|s| s.in_range) {
            Err(NotSafe::NoReading)
        } else {
            Ok(())
        }
    }

    /// Model step, dt = 2^−dt_log2 s.
    pub fn dt_log2(&self) -> u8 {
        self.k.dt_log2
    }

    /// Trip pressure, bar.
    pub fn trip(&self) -> Pressure {
        Pressure(self.k.trip_bar)
    }

    /// Scheduler mode.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// Cylinders on duty (bit i = HC3.(i+1)) and geometry (0..=3).
    pub fn duty(&self) -> (u8, u8) {
        (self.on_duty, self.config)
    }

    /// The overpressure trip latch.
    pub fn latch(&self) -> &TripLatch {
        &self.latch
    }

    /// Starts with the trip latch tripped: a trip held when the controller reset (the firmware
    /// remembers it across a reset). It releases like any other.
    pub fn boot_tripped(&mut self) {
        self.latch.boot_tripped();
        self.status.tripped = true;
        self.status.dump_valve = true;
        self.applied = self.safe_op;
        self.status.aperture = Aperture(self.applied);
    }

    /// Starts with sensors held faulted: those held when the controller reset (the firmware
    /// remembers them across a reset, as the trip). They clear like any other.
    pub fn boot_sensor_faults(&mut self, bits: u8) {
        self.sensor_faults.restore(bits);
        self.status.sensor_faults = self.sensor_faults.latched();
    }

    /// Restarts the estimator from known pressures and clears the scheduler. While the trip
    /// latch holds, refused unless its release condition held in the last step (a valid HP
    /// reading the estimator's gate took and the estimate both below the release pressure),
    /// with the reason; an allowed reset acknowledges a contradiction between reading and model
    /// but never releases the trip: its hold time runs again. Until a valid HP reading confirms
    /// the new estimate, a missing reading keeps P2's uncertainty at its boot value, so the
    /// host's pressures cannot stand in for a lost transducer.
    pub fn reset(&mut self, p2: Pressure, lp: Pressure) -> Result<(), TripHold> {
        self.latch.reset_allowed(self.last.as_ref())?;
        self.selftest = None;
        self.held = false;
        self.lp_known = true;
        self.st = State::new(p2, lp, Pressure(Fx::ONE));
        self.sst = SchedulerState::default();
        self.last_tick = None;
        self.confirmed = false;
        Ok(())
    }

    /// Whether a sample stamped `tick` is newer than the last one stepped (the loop steps once
    /// per period: a repeated or older tick is an overrun and is dropped and counted).
    pub fn fresh(&mut self, tick: u32) -> bool {
        let ok = self
            .last_tick
            .is_none_or(|last| (1..=u32::MAX / 2).contains(&tick.wrapping_sub(last)));
        if ok {
            self.last_tick = Some(tick);
        } else {
            self.status.frames_overrun = self.status.frames_overrun.wrapping_add(1);
        }
        ok
    }

    /// Switches the scheduler mode (bumpless: the integrator keeps its value); ends a
    /// self-test.
    pub fn set_mode(&mut self, mode: Mode) {
        self.mode = mode;
        self.selftest = None;
        self.held = false;
    }

    /// Cylinders on duty and geometry; out-of-range values are ignored and flagged by the
    /// estimator's `BAD_CONFIG` fault. Ends a self-test.
    pub fn set_duty(&mut self, on_duty: u8, config: u8) {
        self.on_duty = on_duty;
        self.config = config;
        self.selftest = None;
        self.held = false;
    }

    /// Whether the outputs are held de-energised since boot (until the host's first mode, duty
    /// or reset command).
    pub fn held(&self) -> bool {
        self.held
    }

    /// The estimator's residuals (each sensor against the model).
    pub fn residuals(&self) -> pto_model::estimator::ResidualState {
        self.st.resid
    }

    /// Whether a self-test drives the outputs.
    pub fn selftest_active(&self) -> bool {
        self.selftest.is_some()
    }

    /// Begins the bring-up self-test: only with the trip armed, in mode fixed 0 % with the
    /// valve closed. Returns the outputs to drive at once (all de-energised).
    pub fn selftest_begin(&mut self) -> Result<Outputs, SelfTestRefusal> {
        if self.status.tripped {
            return Err(SelfTestRefusal::NotSafe(NotSafe::Tripped));
        }
        if self.mode != Mode::Fixed(Aperture::ZERO) {
            return Err(SelfTestRefusal::NotSafe(NotSafe::ValveOpen));
        }
        // Without a valid HP reading P2 is unknown (in fixed 0 % the valve then stands at the
        // sensor-fault safe aperture): the outputs are not stepped.
        if !self.last.is_some_and(|s| s.in_range) {
            return Err(SelfTestRefusal::NotSafe(NotSafe::NoReading));
        }
        if self.applied != ZERO {
            return Err(SelfTestRefusal::NotSafe(NotSafe::ValveOpen));
        }
        let t = SelfTestState::begin(self.k.dt_log2);
        self.selftest = Some(t);
        Ok(self.selftest_applied(&t))
    }

    /// Drives one output (the others de-energised); returns the outputs to drive at once.
    pub fn selftest_drive(&mut self, d: TestDrive) -> Result<Outputs, SelfTestRefusal> {
        let mut t = self.selftest.ok_or(SelfTestRefusal::NotActive)?;
        t.drive(d)?;
        self.selftest = Some(t);
        Ok(self.selftest_applied(&t))
    }

    /// Ends the self-test; the controller's own outputs apply from the next step, from the
    /// de-energised state.
    pub fn selftest_end(&mut self) -> Result<Outputs, SelfTestRefusal> {
        self.selftest.take().ok_or(SelfTestRefusal::NotActive)?;
        let off = SelfTestState::begin(self.k.dt_log2);
        Ok(self.selftest_applied(&off))
    }

    /// A self-test request came (the idle time starts again).
    pub fn selftest_touch(&mut self) {
        if let Some(t) = &mut self.selftest {
            t.touch();
        }
    }

    /// The self-test's outputs, recorded as applied (the estimator sees the valve it drives).
    fn selftest_applied(&mut self, t: &SelfTestState) -> Outputs {
        let o = t.outputs();
        self.applied = o.aperture.0;
        let s = &mut self.status;
        s.aperture = o.aperture;
        s.dump_valve = o.dump_open;
        o
    }

    /// The inputs of the last sample as the self-test reports them.
    pub fn input_report(&self, board: BoardInfo) -> InputReport {
        let f = self.last_frame;
        let report = |t: &Transducer, c: &SupplyCorrection, raw: u16| {
            let (state, counts) = match c.correct(raw) {
                LoopReading::Counts(n) => (t.state(n), n),
                LoopReading::Saturated => (LoopState::Saturated, raw),
                LoopReading::SupplyFault => (LoopState::SupplyFault, raw),
            };
            LoopReport {
                adc: raw,
                current_ua: t.current_ua(counts),
                state,
            }
        };
        InputReport {
            tick: f.map_or(0, |f| f.tick),
            samples: self.samples,
            hp: report(&self.hp, &self.hp_supply, f.map_or(0, |f| f.hp_adc)),
            lp: report(&self.lp, &self.lp_supply, f.map_or(0, |f| f.lp_adc)),
            supply_mv: f.and_then(|f| f.supply_mv),
            encoder: f.map_or(0, |f| f.encoder),
            motor: f.and_then(|f| f.motor),
            active: self.selftest.is_some(),
            board,
        }
    }

    fn model_step<C: StepClock>(&mut self, inp: &Inputs, clock: &mut C) -> (Estimate, Command) {
        let (k, sc, st, sst, mode) = (&self.k, &self.sc, &mut self.st, &mut self.sst, self.mode);
        let ((e, c), cost) = clock.measure(|| {
            let e = estimator::step(k, st, inp);
            let c = scheduler::step(k, sc, sst, mode, &e, inp.motor);
            (e, c)
        });
        let s = &mut self.status;
        s.steps = s.steps.wrapping_add(1);
        s.faults_seen |= e.faults;
        s.step_cost_last = cost;
        s.step_cost_max = s.step_cost_max.max(cost);
        s.step_cost_sum = s.step_cost_sum.wrapping_add(u64::from(cost));
        (e, c)
    }

    /// Bit-exact replay of given estimator inputs; the actuator stage is bypassed.
    pub fn replay<C: StepClock>(&mut self, inp: &Inputs, clock: &mut C) -> (Estimate, Command) {
        self.model_step(inp, clock)
    }

    /// One closed-loop step from a raw sample.
    pub fn sample<C: StepClock>(&mut self, f: &SensorFrame, clock: &mut C) -> StepOut {
        self.last_frame = Some(*f);
        self.samples = self.samples.wrapping_add(1);
        let supply_ok = self.hp_supply.update(f.supply_mv) & self.lp_supply.update(f.supply_mv);
        if !supply_ok {
            self.status.supply_faults = self.status.supply_faults.wrapping_add(1);
        }
        let pressure = |t: &Transducer, c: &SupplyCorrection, raw: u16| match c.correct(raw) {
            LoopReading::Counts(n) => t.pressure(n),
            LoopReading::Saturated | LoopReading::SupplyFault => None,
        };
        let reading = pressure(&self.hp, &self.hp_supply, f.hp_adc);
        if reading.is_none() {
            self.status.hp_loop_faults = self.status.hp_loop_faults.wrapping_add(1);
        }
        let (lo, hi) = self.k.observer.hp_range_bar;
        let in_range = reading.is_some_and(|p| p.0 >= lo && p.0 <= hi);
        let hp_held = self.sensor_faults.latched() & bit::HP != 0;
        if !self.confirmed && (!in_range || hp_held) && self.st.node.var < self.boot_var {
            // Not yet confirmed by a reading (since boot or the host's reset): as unknown as
            // at boot while there is none (a held transducer's is none).
            (self.st.node.var, self.st.node.var_lo) = (self.boot_var, 0);
        }
        let inp = Inputs {
            encoder: Some(f.encoder),
            hp: reading,
            lp: pressure(&self.lp, &self.lp_supply, f.lp_adc),
            motor: f.motor,
            aperture_cmd: Aperture(self.applied),
            // During a self-test the cylinders are on duty as its solenoids are; held, none is.
            on_duty: match self.selftest {
                Some(t) => t.outputs().on_duty,
                None if self.held => 0,
                None => self.on_duty,
            },
            config: self.config,
        };
        let mut inp = inp;
        if !self.lp_known
            && let Some(z) = inp.lp
        {
            // A controller that boots does not know LP: its first reading is the best start
            // (its residual check would otherwise judge the estimate's way there).
            (self.st.node.lp, self.st.node.lp_lo) = (z.0, 0);
            self.lp_known = true;
        }
        self.sensor_faults.mask(&mut inp);
        if self.status.dump_valve {
            // The model knows no dump valve: with it open (a trip, P2 unbounded, a self-test
            // drive) its flows say nothing of P2, and its residual checks stand down, to start
            // afresh once it closes.
            self.st.resid.stand_down();
        }
        let (e, c) = self.model_step(&inp, clock);
        let newly = self.sensor_faults.take(e.faults, inp.encoder);
        let held_faults = self.sensor_faults.latched();
        // Trip latch (`crate::trip`): any reading in the loop window counts toward a trip,
        // whether or not the estimator took it; only a valid one the gate took counts toward a
        // release.
        // A reading of an HP transducer held faulted is not taken by anything: it can trip but
        // never release the trip, nor confirm a host's reset.
        let accepted = in_range
            && held_faults & bit::HP == 0
            && e.faults & (fault::INNOVATION | fault::INNOVATION_RESET) == 0;
        self.confirmed |= accepted;
        let sample = TripSample {
            reading,
            in_range,
            accepted,
            innovation_reset: e.faults & fault::INNOVATION_RESET != 0,
            estimate: e.p2,
        };
        let tripped = self.latch.step(&sample);
        self.last = Some(sample);
        let s = &mut self.status;
        s.tripped = tripped;
        s.trips = self.latch.trips;
        s.sensor_faults = held_faults;
        // Actuator stage: safety at once, otherwise slew-limited.
        self.applied = if s.tripped {
            self.safe_op
        } else if held_faults != 0 {
            // A sensor held faulted: the declared safe aperture, at once.
            self.sensor_fault_op
        } else if c.safety != Override::None {
            c.aperture.0
        } else {
            clamp(
                c.aperture.0,
                self.applied.saturating_sub(self.slew_step),
                self.applied.saturating_add(self.slew_step),
            )
        };
        // With the HP transducer held faulted and no motor speed to read P2 from, nothing bounds
        // P2: the dump valve opens.
        let unbounded =
            held_faults & bit::HP != 0 && (held_faults & bit::MOTOR != 0 || f.motor.is_none());
        let mut out = Outputs {
            aperture: Aperture(self.applied),
            dump_open: s.tripped || unbounded,
            on_duty: self.on_duty,
        };
        if self.held {
            // De-energised until the host asks for more; a trip still opens its valve.
            out.dump_open = true;
            out.on_duty = 0;
            if !s.tripped {
                out.aperture = Aperture::ZERO;
                self.applied = ZERO;
            }
        }
        s.held = self.held;
        // The self-test's overlay: the trip ends it at once; otherwise its outputs.
        let mut selftest_ended = None;
        if let Some(mut t) = self.selftest {
            match (s.tripped, t.step()) {
                (true, _) => selftest_ended = Some(Ended::Tripped),
                (false, Err(why)) => selftest_ended = Some(why),
                (false, Ok(())) => {
                    out = t.outputs();
                    self.applied = out.aperture.0;
                }
            }
            self.selftest = selftest_ended.is_none().then_some(t);
            if selftest_ended.is_some_and(|w| w != Ended::Tripped) {
                // Back to the controller from the de-energised state.
                out = Outputs::DE_ENERGISED;
                self.applied = ZERO;
            }
        }
        s.dump_valve = out.dump_open;
        s.aperture = out.aperture;
        StepOut {
            estimate: e,
            command: c,
            applied: out.aperture,
            dump: out.dump_open,
            on_duty: out.on_duty,
            selftest_ended,
            sensor_faults_new: newly,
        }
    }

    /// The sensors held faulted (bits of [`crate::sensor_faults::bit`]).
    pub fn sensor_faults(&self) -> u8 {
        self.sensor_faults.latched()
    }

    /// The host's clear of the held sensor faults: each is released only if its last reading
    /// agrees with the model now (HP: within 3σ of the estimate, at least 2 bar, and only from
    /// an estimate with σ ≤ 1 bar and the dump valve closed; LP: within 2 bar of the estimate;
    /// motor: within the motor check's allowance of the modelled speed; encoder: it moved 50
    /// counts from where it stuck). Returns the sensors still held (0: all cleared).
    pub fn clear_sensor_faults(&mut self) -> u8 {
        let Some(f) = self.last_frame else {
            return self.sensor_faults.latched();
        };
        let mut agree = 0;
        if let LoopReading::Counts(n) = self.lp_supply.correct(f.lp_adc)
            && let Some(z) = self.lp.pressure(n)
            && z.0.saturating_sub(self.st.node.lp).abs() <= estimator::LP_ALLOW_BAR
        {
            agree |= bit::LP;
        }
        let pressure = match self.hp_supply.correct(f.hp_adc) {
            LoopReading::Counts(n) => self.hp.pressure(n),
            _ => None,
        };
        let p2 = self.st.node.p2;
        // 3σ from the variance without a square root: (z − P2)² ≤ 9·var, or ≤ (2 bar)² — and
        // only from an estimate that knows P2 (σ ≤ 1 bar) with the dump valve closed (the model
        // knows no dump): one that has run on the model alone for long, or was reset by the host
        // and not yet confirmed, cannot vouch for a reading. The transducer then stays held
        // until the model knows P2 again (the valve open and the motor read).
        if let Some(z) = pressure
            && self.st.node.var <= Fx::ONE
            && !self.status.dump_valve
        {
            let d = z.0.saturating_sub(p2);
            let d2 = d.saturating_mul(d);
            if d2 <= self.st.node.var.saturating_mul(Fx::from_num(9)) || d2 <= Fx::from_num(4) {
                agree |= bit::HP;
            }
        }
        if let Some(m) = f.motor {
            let model = self
                .st
                .branch
                .q_motor
                .saturating_mul(self.k.branch.rpm_per_lpm);
            if m.0.saturating_sub(model).abs() <= estimator::motor_allowance(model) {
                agree |= bit::MOTOR;
            }
        }
        agree |= bit::ENCODER;
        self.sensor_faults.clear(agree, Some(f.encoder))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frontend::LoopSpec;

    fn ctl() -> Controller {
        Controller::new(
            &ModelConfig::reference(),
            &SchedulerConfig::default(),
            &ControlConfig::default(),
        )
        .unwrap()
    }

    fn frame(tick: u32, hp_bar: f32) -> SensorFrame {
        let t = Transducer::new(LoopSpec::HP).unwrap();
        let l = Transducer::new(LoopSpec::LP).unwrap();
        SensorFrame {
            tick,
            encoder: 0,
            hp_adc: t.counts_at_bar(hp_bar),
            lp_adc: l.counts_at_bar(8.0),
            motor: Some(pto_model::fx::Rpm::from_num(200.0)),
            supply_mv: Some(3300),
        }
    }

    #[test]
    fn overpressure_latches_the_safe_state_in_the_same_step_and_releases_with_margin() {
        let mut c = ctl();
        c.reset(Pressure::from_num(100.0), Pressure::from_num(8.0))
            .unwrap();
        c.set_mode(Mode::Fixed(Aperture::from_num(5.0)));
        let trip = c.trip().to_f32();
        for i in 0..50 {
            let o = c.sample(&frame(i, 100.0), &mut NoClock);
            assert!(!o.dump);
        }
        let o = c.sample(&frame(50, trip + 1.0), &mut NoClock);
        assert!(
            o.dump,
            "dump valve on in the step that sees the overpressure"
        );
        assert_eq!(
            o.applied.to_f32(),
            100.0,
            "valve at its safe aperture at once"
        );
        // Still latched a little below the trip.
        let o = c.sample(&frame(51, trip - 5.0), &mut NoClock);
        assert!(o.dump && o.applied.to_f32() == 100.0);
        // Released once P2 is 15 bar below, then the valve slews back (100 %/s, 2^-10 s) —
        // or, once the residuals name a sensor (these frames hold the encoder still while P2
        // rises, and the motor at 200 rpm whatever the valve), it goes at once to the
        // sensor-fault aperture.
        let mut n = 0;
        let mut last = 100.0;
        for i in 52..6000 {
            let o = c.sample(&frame(i, trip - 30.0), &mut NoClock);
            if !o.dump {
                let a = o.applied.to_f32();
                if c.sensor_faults() == 0 {
                    assert!(last - a <= 100.0 / 1024.0 + 1e-3, "slew {last} -> {a}");
                    n += 1;
                } else {
                    assert_eq!(a, 12.0, "the sensor-fault aperture");
                }
                last = a;
            }
        }
        assert!(n > 0 && c.status.trips == 1 && !c.status.tripped);
        assert_ne!(c.sensor_faults(), 0);
    }

    /// A reading of an HP transducer held faulted trips but never releases the trip, nor lets
    /// the host reset while tripped; an estimate run on the model alone for long, or with the
    /// dump open, does not vouch for a reading when the host clears; the held sensors come back
    /// after a reset.
    #[test]
    fn a_held_hp_transducer_never_releases_the_trip_nor_clears_on_a_loose_estimate() {
        let mut c = ctl();
        c.reset(Pressure::from_num(100.0), Pressure::from_num(8.0))
            .unwrap();
        c.set_mode(Mode::Fixed(Aperture::from_num(5.0)));
        for i in 0..20 {
            c.sample(&frame(i, 100.0), &mut NoClock);
        }
        c.sensor_faults.take(fault::HP_DISAGREES, Some(0));
        let trip = c.trip().to_f32();
        let o = c.sample(&frame(20, trip + 1.0), &mut NoClock);
        assert!(o.dump, "a held transducer's reading still trips");
        // Far below the release for long: the reading is never taken, the trip holds.
        for i in 21..3000 {
            let o = c.sample(&frame(i, 60.0), &mut NoClock);
            assert!(o.dump && c.status.tripped, "released at step {i}");
            assert!(!c.last.unwrap().accepted);
        }
        assert!(
            c.reset(Pressure::from_num(60.0), Pressure::from_num(8.0))
                .is_err(),
            "a reset on a held transducer's word"
        );
        // The estimate's σ grown beyond a bar in 40 s on the model (no motor reading to bound
        // it; 1.27 bar here): no reading clears, not even one on the estimate (the transducer
        // stays held until the model knows P2 again). With σ under a bar one within 2 bar
        // does — but not with the dump valve open (the model knows no dump).
        let mut g = ctl();
        g.reset(Pressure::from_num(80.0), Pressure::from_num(8.0))
            .unwrap();
        g.sensor_faults.take(fault::HP_DISAGREES, Some(0));
        let mut f = frame(0, 80.0);
        f.motor = None;
        for i in 0..40_000 {
            f.tick = i;
            g.sample(&f, &mut NoClock);
        }
        assert!(g.st.node.var > Fx::from_num(1.5), "σ² {}", g.st.node.var);
        let p2 = g.st.node.p2.to_num::<f32>();
        for off in [3.5, 0.0] {
            g.last_frame = Some(frame(40_000, p2 + off));
            assert_eq!(g.clear_sensor_faults(), bit::HP, "a loose estimate vouched");
        }
        g.st.node.var = Fx::from_num(0.5);
        g.status.dump_valve = true;
        g.last_frame = Some(frame(40_000, p2 + 1.0));
        assert_eq!(g.clear_sensor_faults(), bit::HP, "with the dump open");
        g.status.dump_valve = false;
        assert_eq!(g.clear_sensor_faults(), 0);
        // Across a reset.
        let mut h = ctl();
        h.boot_sensor_faults(bit::HP | bit::ENCODER);
        assert_eq!(h.sensor_faults(), bit::HP | bit::ENCODER);
        assert_eq!(h.status.sensor_faults, bit::HP | bit::ENCODER);
    }

    /// Tripped with the lever still pumping: the dump valve (which the model does not know)
    /// takes P2 down to a few bar while the model counts the pumps' oil into HP. The residual
    /// checks stand down while the dump is open: no sensor is named for it.
    #[test]
    fn the_dump_valve_open_names_no_sensor() {
        let mut c = ctl();
        c.reset(Pressure::from_num(100.0), Pressure::from_num(8.0))
            .unwrap();
        c.set_duty(0b1111, 0);
        c.set_mode(Mode::Fixed(Aperture::from_num(5.0)));
        // The lever at ±20° and 0.2 Hz: 16 384 counts a turn.
        let enc = |i: u32| {
            let t = f64::from(i) / 1024.0;
            (20.0 / 360.0 * 16384.0 * (2.0 * core::f64::consts::PI * 0.2 * t).sin()) as i32
        };
        let trip = c.trip().to_f32();
        // (No motor reading: its check is not what this is about.)
        let mut f = frame(0, trip + 1.0);
        (f.encoder, f.motor) = (enc(0), None);
        assert!(c.sample(&f, &mut NoClock).dump);
        for i in 1..90_000 {
            let p = (trip - 1.0 - i as f32 * 0.01).max(3.0);
            let mut f = frame(i, p);
            (f.encoder, f.motor) = (enc(i), None);
            let o = c.sample(&f, &mut NoClock);
            assert!(o.dump, "step {i}");
            assert_eq!(c.sensor_faults(), 0, "named at step {i}, P2 {p}");
        }
    }

    #[test]
    fn repeated_and_stale_ticks_are_overruns() {
        let mut c = ctl();
        assert!(c.fresh(10) && c.fresh(11) && c.fresh(13));
        assert!(!c.fresh(13) && !c.fresh(12));
        assert!(c.fresh(14));
        assert_eq!(c.status.frames_overrun, 2);
        c.reset(Pressure::ZERO, Pressure::ZERO).unwrap();
        assert!(c.fresh(0), "a reset restarts the tick count");
        assert!(
            c.fresh(u32::MAX / 2) && c.fresh(u32::MAX - 5) && c.fresh(3),
            "ticks wrap"
        );
    }

    #[test]
    fn a_wire_break_is_counted_and_the_estimate_runs_on_the_model() {
        let mut c = ctl();
        c.reset(Pressure::from_num(90.0), Pressure::from_num(8.0))
            .unwrap();
        let mut f = frame(0, 90.0);
        f.hp_adc = 0;
        let o = c.sample(&f, &mut NoClock);
        assert_ne!(o.estimate.faults & fault::HP_SENSOR, 0);
        assert_eq!(c.status.hp_loop_faults, 1);
        assert!((o.estimate.p2.to_f32() - 90.0).abs() < 1.0);
    }

    /// A configuration is applied only in the declared safe state; it restarts the estimator
    /// from its last P2 with the boot uncertainty and keeps the mode, the duty, the counters
    /// and the latch; a bad one changes nothing.
    #[test]
    fn a_reconfiguration_needs_the_safe_state_and_keeps_the_rest() {
        let (sc, cc) = (SchedulerConfig::default(), ControlConfig::default());
        let mut cfg = ModelConfig::reference();
        cfg.trapped_air_fraction = 0.09;
        let mut c = ctl();
        // No sample yet: P2 unknown.
        assert_eq!(
            c.reconfigure(&cfg, &sc, &cc),
            Err(ReconfigureError::NotSafe(NotSafe::NoReading))
        );
        c.reset(Pressure::from_num(100.0), Pressure::from_num(8.0))
            .unwrap();
        c.set_mode(Mode::Fixed(Aperture::from_num(5.0)));
        c.set_duty(0b0011, 2);
        for i in 0..100 {
            assert!(c.fresh(i));
            c.sample(&frame(i, 100.0), &mut NoClock);
        }
        assert_eq!(
            c.safe_to_apply(),
            Err(NotSafe::ValveOpen),
            "valve open: not safe"
        );
        assert!(matches!(
            c.check_reconfigure(&cfg, &sc, &cc),
            Err(ReconfigureError::NotSafe(NotSafe::ValveOpen))
        ));
        // Fixed 0: the valve slews shut (5 % at 100 %/s ≈ 52 steps).
        c.set_mode(Mode::Fixed(Aperture::ZERO));
        for i in 100..200 {
            assert!(c.fresh(i));
            c.sample(&frame(i, 100.0), &mut NoClock);
        }
        assert_eq!(c.safe_to_apply(), Ok(()));
        let before = c.clone();
        let mut bad = cfg.clone();
        bad.trapped_air_fraction = 5.0;
        assert!(matches!(
            c.reconfigure(&bad, &sc, &cc),
            Err(ReconfigureError::Setup(SetupError::Model(_)))
        ));
        let mut other_dt = cfg.clone();
        other_dt.dt_log2 += 1;
        assert!(matches!(
            c.reconfigure(&other_dt, &sc, &cc),
            Err(ReconfigureError::Setup(SetupError::Model(ConfigError {
                field: "dt_log2",
                ..
            })))
        ));
        assert_eq!(c.status, before.status);
        c.reconfigure(&cfg, &sc, &cc).unwrap();
        assert_eq!(c.duty(), (0b0011, 2));
        assert_eq!(c.mode(), Mode::Fixed(Aperture::ZERO));
        assert_eq!(c.status.steps, 200);
        assert!(!c.fresh(199), "the tick count goes on");
        // The estimate goes on from where it was, as uncertain as at boot until a reading.
        let mut f = frame(201, 100.0);
        f.hp_adc = 0;
        let o = c.sample(&f, &mut NoClock);
        assert!((o.estimate.p2.to_f32() - 100.0).abs() < 1.0, "{o:?}");
        assert!(o.estimate.p2_sigma().to_f32() > 10.0, "{o:?}");
        // Tripped: refused, the latch untouched.
        let trip = c.trip().to_f32();
        c.sample(&frame(202, trip + 1.0), &mut NoClock);
        assert_eq!(c.safe_to_apply(), Err(NotSafe::Tripped));
        assert!(c.reconfigure(&cfg, &sc, &cc).is_err());
        assert!(c.status.tripped && c.status.dump_valve && c.status.trips == 1);
    }

    #[test]
    fn bad_settings_name_their_field() {
        let e = Controller::new(
            &ModelConfig::reference(),
            &SchedulerConfig::default(),
            &ControlConfig {
                valve_slew_pct_per_s: 0.0,
                ..Default::default()
            },
        )
        .unwrap_err();
        assert_eq!(
            e,
            SetupError::Control {
                field: "valve_slew_pct_per_s",
                value: 0.0
            }
        );
    }
}
