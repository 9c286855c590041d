//! The scheduler in closed loop with the full simulation: the model crate (or, in `hil::pil`, the
//! firmware) as the plant's valve controller in a Test III-like run, and the checks that judge it.

use super::target;
use super::{ModelError, duty_mask, model_config};
use crate::sim::bench::{BAR, Bench};
use crate::sim::plant::Eval;
use crate::sim::scenario::ScenarioError;
use crate::sim::schedule::{ValveController, ValveSchedule};
use crate::sim::solver::{self, Initial, Run, SimError, SolverOptions};
use crate::sim::trace::Truth;
use crate::validation::sensors::{SensorSpec, SensorSynth};
use pto_model::estimator::{self, Estimate, State};
use pto_model::fx::{Aperture, Pressure, Rpm};
use pto_model::scheduler::{self, Mode, SchedulerCoeffs, SchedulerConfig, SchedulerState};
use pto_model::{Coefficients, ModelConfig};
use rayon::prelude::*;
use serde::Serialize;
use std::path::Path;

/// A closed-loop result.
#[derive(Debug, Clone, Serialize)]
pub struct LoopRow {
    /// What was held.
    pub name: String,
    /// Setpoint, in `setpoint_unit`.
    pub setpoint: f64,
    /// Unit of the setpoint: `bar` (P2) or `rpm` (motor speed).
    pub setpoint_unit: &'static str,
    /// Window judged, s.
    pub window_s: (f64, f64),
    /// Largest deviation from the setpoint in the window, in `deviation_unit`.
    pub max_deviation: f64,
    /// Target for it, in `deviation_unit`.
    pub target: f64,
    /// Unit of the deviation and its target: the setpoint's (`bar`), or
    /// [`FRACTION_OF_SETPOINT`].
    pub deviation_unit: &'static str,
    /// Met.
    pub pass: bool,
}

/// [`LoopRow::deviation_unit`] of a deviation relative to the setpoint.
pub const FRACTION_OF_SETPOINT: &str = "fraction of setpoint";

/// Why a closed-loop run could not be made (the controller's own errors aside: see
/// [`test3_like_loop`]).
#[derive(Debug, thiserror::Error)]
pub enum LoopError {
    /// The built-in scenario the run is made from is missing.
    #[error("{0} missing")]
    MissingScenario(&'static str),
    /// It does not prepare on the bench.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// The run failed.
    #[error(transparent)]
    Simulation(#[from] SimError),
    /// The bench has no model configuration, or the configuration no coefficients.
    #[error(transparent)]
    Model(#[from] ModelError),
}

/// Why a scheduler mode could not be made from its name and setpoint ([`parse_mode`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ModeError {
    /// The setpoint is outside the mode's range.
    #[error("mode {kind} {value}: outside [{lo}, {hi}] {unit}")]
    Range {
        /// The mode's name.
        kind: String,
        /// The setpoint.
        value: f64,
        /// Smallest setpoint.
        lo: f64,
        /// Largest setpoint.
        hi: f64,
        /// Its unit.
        unit: &'static str,
    },
    /// No such mode.
    #[error("mode {0:?}: want {MODES}")]
    Unknown(String),
}

/// The modes [`parse_mode`] takes, with their setpoints' units.
pub const MODES: &str = "fixed PCT, hold-pressure BAR, hold-speed RPM or max-autonomy RPM";

/// A scheduler mode from its name and setpoint, as `pto link mode` takes them: `fixed 12` (%),
/// `hold-pressure 100` (bar), `hold-speed 200` (rpm), `max-autonomy 150` (rpm).
pub fn parse_mode(kind: &str, value: f64) -> Result<Mode, ModeError> {
    let in_range = |lo: f64, hi: f64, unit: &'static str| {
        if value.is_finite() && (lo..=hi).contains(&value) {
            Ok(value as f32)
        } else {
            Err(ModeError::Range {
                kind: kind.into(),
                value,
                lo,
                hi,
                unit,
            })
        }
    };
    Ok(match kind {
        "fixed" => Mode::Fixed(Aperture::from_num(in_range(0.0, 100.0, "%")?)),
        "hold-pressure" => Mode::HoldPressure(Pressure::from_num(in_range(1.0, 130.0, "bar")?)),
        "hold-speed" => Mode::HoldSpeed(Rpm::from_num(in_range(1.0, 3000.0, "rpm")?)),
        "max-autonomy" => Mode::MaxAutonomy(Rpm::from_num(in_range(1.0, 3000.0, "rpm")?)),
        other => return Err(ModeError::Unknown(other.into())),
    })
}

/// The model crate's estimator + scheduler as the plant's valve controller.
pub struct ModelController {
    k: Coefficients,
    sc: SchedulerCoeffs,
    st: State,
    sst: SchedulerState,
    mode: Mode,
    synth: SensorSynth,
    duty: u8,
    config: u8,
    cmd: f64,
    keep_log: bool,
    /// Every estimate, for inspection (empty after [`ModelController::without_log`]).
    pub log: Vec<(f64, Estimate, f64)>,
}

impl ModelController {
    /// A controller holding `mode`, with the model stepping at its configured dt.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        mcfg: &ModelConfig,
        sched: &SchedulerConfig,
        mode: Mode,
        p2: f64,
        lp: f64,
        duty: u8,
        config: u8,
        seed: u64,
    ) -> Result<Self, ModelError> {
        let k = mcfg.coefficients()?;
        let sc = sched.coefficients(&k)?;
        Ok(ModelController {
            st: State::new(
                Pressure::from_num(p2 as f32),
                Pressure::from_num(lp as f32),
                Pressure::from_num(1.0),
            ),
            k,
            sc,
            sst: SchedulerState::default(),
            mode,
            synth: SensorSynth::new(SensorSpec::default(), seed),
            duty,
            config,
            cmd: 0.0,
            keep_log: true,
            log: Vec::new(),
        })
    }

    /// Keeps no log of the estimates (a long run's log takes ≈ 100 MB per 1000 s at 1 kHz).
    pub fn without_log(mut self) -> Self {
        self.keep_log = false;
        self
    }
}

impl ValveController for ModelController {
    fn period(&self) -> f64 {
        2f64.powi(-i32::from(self.k.dt_log2))
    }

    fn update(&mut self, t: f64, p: &Eval) -> f64 {
        let inp = self.synth.read(p.theta_rad, &Truth::of_eval(p)).to_inputs(
            self.cmd,
            self.duty,
            self.config,
        );
        let e = estimator::step(&self.k, &mut self.st, &inp);
        let c = scheduler::step(&self.k, &self.sc, &mut self.sst, self.mode, &e, inp.motor);
        self.cmd = f64::from(c.aperture.to_f32());
        if self.keep_log {
            self.log.push((t, e, self.cmd));
        }
        self.cmd
    }
}

/// LP at the start of the closed-loop runs, bar.
pub const LOOP_LP_START_BAR: f64 = 8.0;

/// A Test III-like closed-loop run (HC3.1 + HC3.4, Config 1, ±40 mm at 0.1 Hz, from `p2_start`
/// bar, LP 8 bar) for `duration` s, with the controller `make` builds for the prepared scenario
/// (its duty and geometry); returns the controller with the result. Errors are the caller's
/// type `E`, which takes the run's own ([`LoopError`]) and those of `make`.
pub fn test3_like_loop<C: ValveController + 'static, E: From<LoopError>>(
    bench: &Bench,
    p2_start: f64,
    duration: f64,
    make: impl FnOnce(&crate::sim::scenario::Prepared) -> Result<C, E>,
) -> Result<(crate::sim::solver::SimResult, C), E> {
    const SCENARIO: &str = "test3-ap10";
    let s = crate::sim::scenario::builtin_named(SCENARIO)
        .ok_or(LoopError::MissingScenario(SCENARIO))?;
    let prep = s.prepare(bench, Path::new(".")).map_err(LoopError::from)?;
    let ctrl = make(&prep)?;
    let (res, ctrl) = solver::simulate_with(
        Run {
            plant: &prep.plant,
            valve: ValveSchedule::Constant(0.0),
            initial: Initial {
                p2_pa: p2_start * BAR,
                lp_pa: LOOP_LP_START_BAR * BAR,
            },
            duration,
            sample_dt: 0.05,
            solver: SolverOptions {
                rtol: 1e-6,
                atol_scale: 0.1,
                ..SolverOptions::default()
            },
            progress: None,
        },
        ctrl,
    );
    Ok((res.map_err(LoopError::from)?, ctrl))
}

/// The model crate as the controller of a Test III-like run, its model at 2^−dt_log2 s.
pub fn closed_loop(
    bench: &Bench,
    mode: Mode,
    p2_start: f64,
    duration: f64,
    dt_log2: u8,
) -> Result<(crate::sim::solver::SimResult, ModelController), LoopError> {
    let mut mcfg = model_config(bench)?;
    mcfg.dt_log2 = dt_log2;
    let (sched, _) = super::controller_config(bench);
    test3_like_loop(bench, p2_start, duration, |prep| {
        Ok(ModelController::new(
            &mcfg,
            &sched,
            mode,
            p2_start,
            LOOP_LP_START_BAR,
            duty_mask(&prep.on_duty),
            prep.config as u8,
            7,
        )?)
    })
}

/// The row of a run holding `setpoint` (in `setpoint_unit`): the largest deviation of `f`
/// from it from `settle_from` s to the end, in the setpoint's unit or, if `rel`, as a fraction
/// of it.
#[allow(clippy::too_many_arguments)]
fn judge_loop(
    name: &str,
    res: &crate::sim::solver::SimResult,
    setpoint: f64,
    setpoint_unit: &'static str,
    settle_from: f64,
    rel: bool,
    target: f64,
    f: impl Fn(usize) -> f64,
) -> LoopRow {
    let tr = &res.trace;
    let end = *tr.t_s.last().unwrap_or(&0.0);
    let w = tr.window(settle_from, end);
    let mut worst = 0.0f64;
    for kk in w {
        let d = (f(kk) - setpoint).abs();
        worst = worst.max(if rel { d / setpoint } else { d });
    }
    LoopRow {
        name: name.into(),
        setpoint,
        setpoint_unit,
        window_s: (settle_from, end),
        max_deviation: worst,
        target,
        deviation_unit: if rel {
            FRACTION_OF_SETPOINT
        } else {
            setpoint_unit
        },
        pass: worst <= target,
    }
}

/// Closed-loop checks: hold P2 at 100 bar; hold the motor at 250 rpm.
pub fn closed_loop_rows(bench: &Bench) -> Vec<Result<LoopRow, LoopError>> {
    let cases: Vec<(&str, Mode)> = vec![
        (
            "hold P2 at 100 bar",
            Mode::HoldPressure(Pressure::from_num(100.0)),
        ),
        (
            "hold motor at 250 rpm",
            Mode::HoldSpeed(Rpm::from_num(250.0)),
        ),
    ];
    cases
        .into_par_iter()
        .map(|(name, mode)| {
            let (res, _) = closed_loop(bench, mode, 60.0, 400.0, 8)?;
            let tr = &res.trace;
            Ok(match mode {
                Mode::HoldPressure(p) => {
                    let sp = f64::from(p.to_f32());
                    // Judge from 60 s after P2 first reaches the setpoint.
                    let reach = crate::paper::time_to_reach(&tr.t_s, &tr.p2_pa, sp * BAR)
                        .unwrap_or(f64::INFINITY);
                    judge_loop(
                        name,
                        &res,
                        sp,
                        "bar",
                        reach + 60.0,
                        false,
                        target::HOLD_P2_BAR,
                        |k| tr.p2_pa[k] / BAR,
                    )
                }
                Mode::HoldSpeed(r) => {
                    let sp = f64::from(r.to_f32());
                    judge_loop(
                        name,
                        &res,
                        sp,
                        "rpm",
                        150.0,
                        true,
                        target::HOLD_SPEED_REL,
                        |k| tr.omega_rad_s[k] * 30.0 / std::f64::consts::PI,
                    )
                }
                _ => unreachable!(),
            })
        })
        .collect()
}
