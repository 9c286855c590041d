//! The solver driver: diffsol BDF over the plant, valve schedules, sampling and balances.
//!
//! Over 600 lines on purpose: one integration loop (segments between valve events, roots,
//! sampling, balances) whose parts share its state; the trace and balance types sit with it.

use crate::sim::bench::{BAR, Bench, LPM, RPM};
use crate::sim::plant::{Eval, N_CYL, N_QUAD, Plant, QUAD_NAMES, Stored, quad};
use crate::sim::power::Power;
use diffsol::{
    NalgebraLU, NalgebraMat, NalgebraVec, OdeBuilder, OdeSolverMethod, OdeSolverStopReason, Vector,
};
use serde::Serialize;
use std::cell::RefCell;
use std::time::Instant;

type M = NalgebraMat<f64>;

/// A valve controller plugged into the plant: called every `period` seconds with the time and the
/// plant's instantaneous values; returns the commanded aperture (%, 0..100).
pub trait ValveController {
    /// Control period, s.
    fn period(&self) -> f64;
    /// New aperture command from the plant's values at time `t`.
    fn update(&mut self, t: f64, plant: &Eval) -> f64;
    /// Whether the run should end here, before its duration (asked after each update; the
    /// result then ends at the update's time).
    fn finished(&self) -> bool {
        false
    }
}

/// How the control valve is driven.
pub enum ValveSchedule {
    /// Fixed aperture, %.
    Constant(f64),
    /// Closed until P2 reaches `threshold_pa`, then `aperture_pct` for the rest of the run.
    Threshold {
        /// P2 threshold, Pa.
        threshold_pa: f64,
        /// Aperture after the threshold, %.
        aperture_pct: f64,
    },
    /// Step changes (time s, aperture %), sorted by time; before the first, closed.
    Table(Vec<(f64, f64)>),
    /// External controller.
    Controller(Box<dyn ValveController>),
}

impl std::fmt::Debug for ValveSchedule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ValveSchedule::Constant(a) => write!(f, "Constant({a})"),
            ValveSchedule::Threshold {
                threshold_pa,
                aperture_pct,
            } => {
                write!(f, "Threshold({threshold_pa} Pa -> {aperture_pct} %)")
            }
            ValveSchedule::Table(t) => write!(f, "Table({t:?})"),
            ValveSchedule::Controller(c) => write!(f, "Controller(period {} s)", c.period()),
        }
    }
}

impl ValveSchedule {
    /// Aperture commanded at the start.
    fn initial(&mut self, plant0: &Eval) -> f64 {
        match self {
            ValveSchedule::Constant(a) => *a,
            ValveSchedule::Threshold {
                threshold_pa,
                aperture_pct,
            } => {
                if plant0.p2_pa >= *threshold_pa {
                    *aperture_pct
                } else {
                    0.0
                }
            }
            ValveSchedule::Table(t) => table_at(t, 0.0),
            ValveSchedule::Controller(c) => c.update(0.0, plant0),
        }
    }

    /// Next time after `t` at which the command may change (besides threshold roots).
    fn next_event(&self, t: f64) -> f64 {
        match self {
            ValveSchedule::Table(tab) => tab
                .iter()
                .map(|e| e.0)
                .find(|&te| te > t + EVENT_TOL_S)
                .unwrap_or(f64::INFINITY),
            ValveSchedule::Controller(c) => {
                let p = c.period();
                (((t + EVENT_TOL_S) / p).floor() + 1.0) * p
            }
            _ => f64::INFINITY,
        }
    }
}

/// Two instants closer than this are one event, s. diffsol's BDF reports a stop time as reached
/// within 100 ε (|t| + |h|) of it (`handle_tstop`): 4·10⁻¹² s at 200 s, more than a fixed 10⁻¹²
/// s or 10⁻⁹ of a 2⁻¹⁰ s period. An event taken as still ahead from there is set as the next
/// stop time and refused ("Stop time is at the current state time": closed loops of 150–200 s
/// failed so). 1 ns is far above that rounding and far below any period or table step.
pub(crate) const EVENT_TOL_S: f64 = 1e-9;

fn table_at(t: &[(f64, f64)], time: f64) -> f64 {
    t.iter()
        .take_while(|e| e.0 <= time + EVENT_TOL_S)
        .last()
        .map_or(0.0, |e| e.1)
}

/// Solver settings.
#[derive(Debug, Clone, Copy)]
pub struct SolverOptions {
    /// Relative tolerance.
    pub rtol: f64,
    /// Absolute tolerance scale (1 = 1e-3 bar on pressures, 1e-4 mm on rods).
    pub atol_scale: f64,
    /// Evaluations at one instant (a step's Newton iterations, the finite-difference Jacobian's
    /// columns) share the motion and lever values. Off: the reference path `pto perf` compares
    /// against, which evaluates them at every call (same results to the last bit).
    pub reuse_kinematics: bool,
}

/// The default: rtol 1e-8, atol 1e-5 bar / 1e-6 mm. Chosen so the oil and energy balances of
/// every paper scenario close within 1e-4 (looser settings leave 1–3e-4 in the runs that hover
/// at the HP precharge); Test III still runs in ≈0.25 s.
impl Default for SolverOptions {
    fn default() -> Self {
        SolverOptions {
            rtol: 1e-8,
            atol_scale: 1e-2,
            reuse_kinematics: true,
        }
    }
}

impl SolverOptions {
    /// The tight setting used as the accuracy reference (rtol 1e-11).
    pub fn tight() -> Self {
        SolverOptions {
            rtol: 1e-11,
            atol_scale: 1e-5,
            reuse_kinematics: true,
        }
    }

    /// These settings on the reference path (see [`SolverOptions::reuse_kinematics`]).
    pub fn reference_path(self) -> Self {
        SolverOptions {
            reuse_kinematics: false,
            ..self
        }
    }
}

/// Initial conditions.
#[derive(Debug, Clone, Copy)]
pub struct Initial {
    /// P2, Pa.
    pub p2_pa: f64,
    /// LP, Pa.
    pub lp_pa: f64,
}

/// Sampled outputs on the user grid (SI units internally; CSV headers carry display units).
#[derive(Debug, Clone, Default, Serialize)]
pub struct Trace {
    /// s.
    pub t_s: Vec<f64>,
    /// Shaft angle, rad.
    pub theta_rad: Vec<f64>,
    /// Shaft speed, rad/s.
    pub theta_dot_rad_s: Vec<f64>,
    /// Rod positions per cylinder, m.
    pub rod_m: [Vec<f64>; N_CYL],
    /// Cap pressures, Pa.
    pub p_cap_pa: [Vec<f64>; N_CYL],
    /// Rod-side pressures, Pa.
    pub p_rod_pa: [Vec<f64>; N_CYL],
    /// Flow into HP per cylinder, m³/s.
    pub q_cyl_m3_s: [Vec<f64>; N_CYL],
    /// Total flow into HP, m³/s.
    pub q_inj_m3_s: Vec<f64>,
    /// Flow through the motor, m³/s.
    pub q_motor_m3_s: Vec<f64>,
    /// Flow through the control valve, m³/s.
    pub q_valve_m3_s: Vec<f64>,
    /// Relief flow, m³/s.
    pub q_relief_m3_s: Vec<f64>,
    /// Motor speed, rad/s.
    pub omega_rad_s: Vec<f64>,
    /// P2, Pa.
    pub p2_pa: Vec<f64>,
    /// LP, Pa.
    pub lp_pa: Vec<f64>,
    /// Motor inlet, Pa.
    pub p_motor_pa: Vec<f64>,
    /// Spool aperture, %.
    pub aperture_pct: Vec<f64>,
    /// Restraining torque (input must supply it), N·m.
    pub torque_nm: Vec<f64>,
    /// Per cylinder, N·m.
    pub torque_cyl_nm: [Vec<f64>; N_CYL],
    /// Mechanical input power at the shaft, W.
    pub input_power_w: Vec<f64>,
    /// Hydraulic power into the control valve, P2 · valve flow, W (what the controller's
    /// estimator reports).
    pub valve_power_w: Vec<f64>,
    /// Power into the load (the generator), W.
    pub generator_power_w: Vec<f64>,
}

impl Trace {
    fn push(&mut self, t: f64, e: &Eval) {
        self.t_s.push(t);
        self.theta_rad.push(e.theta_rad);
        self.theta_dot_rad_s.push(e.theta_dot_rad_s);
        for i in 0..N_CYL {
            self.rod_m[i].push(e.rod_m[i]);
            self.p_cap_pa[i].push(e.p_cap_pa[i]);
            self.p_rod_pa[i].push(e.p_rod_pa[i]);
            self.q_cyl_m3_s[i].push(e.q_into_hp_m3_s[i]);
            self.torque_cyl_nm[i].push(e.torque_nm[i]);
        }
        self.q_inj_m3_s.push(e.q_into_hp_m3_s.iter().sum());
        self.q_motor_m3_s.push(e.q_motor_m3_s);
        self.q_valve_m3_s.push(e.q_valve_m3_s);
        self.q_relief_m3_s.push(e.q_relief_m3_s);
        self.omega_rad_s.push(e.omega_rad_s);
        self.p2_pa.push(e.p2_pa);
        self.lp_pa.push(e.lp_pa);
        self.p_motor_pa.push(e.p_motor_pa);
        self.aperture_pct.push(e.aperture_pct);
        self.torque_nm.push(e.torque_nm.iter().sum());
        self.input_power_w.push(e.quad[quad::INPUT]);
        self.valve_power_w.push(e.p2_pa * e.q_valve_m3_s);
        self.generator_power_w
            .push(e.load_torque_nm * e.omega_rad_s);
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.t_s.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.t_s.is_empty()
    }

    /// Indices of samples with `from <= t <= to`.
    pub fn window(&self, from: f64, to: f64) -> std::ops::Range<usize> {
        let a = self.t_s.partition_point(|&x| x < from - 1e-9);
        let b = self.t_s.partition_point(|&x| x <= to + 1e-9);
        a..b
    }

    /// Writes the trace as CSV with units in the headers (to a temporary file renamed at the
    /// end, so an interrupted write leaves nothing half-written).
    pub fn write_csv(
        &self,
        path: &std::path::Path,
        names: &[String; N_CYL],
    ) -> std::io::Result<()> {
        let tmp = path.with_extension("csv.tmp");
        self.write_csv_to(&tmp, names)?;
        std::fs::rename(&tmp, path)
    }

    fn write_csv_to(&self, path: &std::path::Path, names: &[String; N_CYL]) -> std::io::Result<()> {
        let mut w = csv::Writer::from_path(path)?;
        let mut header: Vec<String> = [
            "time_s",
            "shaft_angle_deg",
            "shaft_speed_rpm",
            "p2_bar",
            "lp_bar",
            "motor_inlet_bar",
            "injected_flow_lpm",
            "motor_flow_lpm",
            "valve_flow_lpm",
            "relief_flow_lpm",
            "motor_speed_rpm",
            "valve_aperture_pct",
            "restraining_torque_nm",
            "input_power_w",
            "valve_power_w",
            "generator_power_w",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        for n in names {
            let n = n.replace('.', "_").to_lowercase();
            header.extend([
                format!("{n}_rod_mm"),
                format!("{n}_cap_bar"),
                format!("{n}_rod_side_bar"),
                format!("{n}_flow_lpm"),
                format!("{n}_torque_nm"),
            ]);
        }
        w.write_record(&header)?;
        for k in 0..self.len() {
            let mut row = vec![
                self.t_s[k],
                self.theta_rad[k].to_degrees(),
                self.theta_dot_rad_s[k] * RPM,
                self.p2_pa[k] / BAR,
                self.lp_pa[k] / BAR,
                self.p_motor_pa[k] / BAR,
                self.q_inj_m3_s[k] * LPM,
                self.q_motor_m3_s[k] * LPM,
                self.q_valve_m3_s[k] * LPM,
                self.q_relief_m3_s[k] * LPM,
                self.omega_rad_s[k] * RPM,
                self.aperture_pct[k],
                self.torque_nm[k],
                self.input_power_w[k],
                self.valve_power_w[k],
                self.generator_power_w[k],
            ];
            for i in 0..N_CYL {
                row.extend([
                    self.rod_m[i][k] * 1e3,
                    self.p_cap_pa[i][k] / BAR,
                    self.p_rod_pa[i][k] / BAR,
                    self.q_cyl_m3_s[i][k] * LPM,
                    self.torque_cyl_nm[i][k],
                ]);
            }
            w.write_record(row.iter().map(|v| format!("{v:.6}")))?;
        }
        w.flush()
    }
}

/// Oil-volume and energy balance of a run.
#[derive(Debug, Clone, Serialize)]
pub struct Balance {
    /// Integrated flows (L) and energies (kJ), named by [`QUAD_NAMES`].
    pub integrals: Vec<(String, f64)>,
    /// Relative oil (mass) balance error per node (HP, motor inlet, LP, chambers) and of the
    /// whole closed circuit.
    pub volume_rel_error: [f64; 5],
    /// Relative energy error of the whole circuit.
    pub energy_rel_error: f64,
    /// Energy into storage (oil, accumulator gas, motor inertia, hard stops), kJ.
    pub stored_kj: f64,
    /// That change by where it is stored, J.
    pub stored: Stored,
}

impl Balance {
    /// An integrated term by its index in [`QUAD_NAMES`] (L or kJ).
    pub fn integral(&self, i: usize) -> f64 {
        self.integrals[i].1
    }
}

impl Balance {
    /// Worst of the volume and energy relative errors.
    pub fn worst(&self) -> f64 {
        self.volume_rel_error
            .iter()
            .copied()
            .fold(self.energy_rel_error, f64::max)
    }
}

/// Solver statistics.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Stats {
    /// Accepted steps.
    pub steps: usize,
    /// Right-hand side evaluations (incl. Jacobian columns).
    pub rhs_evals: usize,
    /// Contact switches located (stops as events).
    pub contact_switches: usize,
    /// Wall time, s.
    pub wall_s: f64,
}

/// A finished run.
#[derive(Debug, Clone)]
pub struct SimResult {
    /// Samples.
    pub trace: Trace,
    /// Conservation check.
    pub balance: Balance,
    /// Cost.
    pub stats: Stats,
    /// Time at which a threshold schedule opened the valve, s.
    pub valve_opened_at: Option<f64>,
    /// Mean powers, losses by cause and efficiency, from the energy balance's terms.
    pub power: Power,
}

/// Why a run failed.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The solver gave up.
    #[error("solver failed at t = {t:.6} s: {message}")]
    Solver {
        /// Time, s.
        t: f64,
        /// diffsol's message.
        message: String,
    },
    /// A state became NaN/infinite or a pressure fell below vacuum.
    #[error("non-physical state at t = {t:.6} s: {state} = {value}")]
    NonPhysical {
        /// Time, s.
        t: f64,
        /// State name with unit.
        state: String,
        /// Its value.
        value: f64,
    },
    /// Bad run settings.
    #[error("{0}")]
    Setup(String),
}

/// Finite-difference Jacobian–vector product with a cached f(x). diffsol needs J·v from closures;
/// the plant is piecewise smooth (valve corners), so a forward difference is as good as an
/// analytic Jacobian here and cannot drift out of sync with the right-hand side.
struct JvCache {
    t: f64,
    x: Vec<f64>,
    fx: Vec<f64>,
    xp: Vec<f64>,
    evals: usize,
}

impl JvCache {
    /// Forgets the cached f(x) (the right-hand side changed at the same (t, x)).
    fn invalidate(&mut self) {
        self.t = f64::NAN;
    }

    fn new(n: usize) -> Self {
        JvCache {
            t: f64::NAN,
            x: vec![f64::NAN; n],
            fx: vec![0.0; n],
            xp: vec![0.0; n],
            evals: 0,
        }
    }

    fn jv(
        &mut self,
        f: impl Fn(f64, &[f64], &mut [f64]),
        t: f64,
        x: &[f64],
        v: &[f64],
        out: &mut [f64],
    ) {
        if t != self.t || x != self.x.as_slice() {
            f(t, x, &mut self.fx);
            self.evals += 1;
            self.x.copy_from_slice(x);
            self.t = t;
        }
        let (mut vmax, mut xmax) = (0.0f64, 1.0f64);
        for (vi, xi) in v.iter().zip(x) {
            if *vi != 0.0 {
                vmax = vmax.max(vi.abs());
                xmax = xmax.max(xi.abs());
            }
        }
        if vmax == 0.0 {
            out.fill(0.0);
            return;
        }
        let eps = 1.49e-8 * xmax / vmax;
        for ((p, xi), vi) in self.xp.iter_mut().zip(x).zip(v) {
            *p = xi + eps * vi;
        }
        f(t, &self.xp, out);
        self.evals += 1;
        for (o, f0) in out.iter_mut().zip(&self.fx) {
            *o = (*o - f0) / eps;
        }
    }
}

/// A progress callback: the simulated time reached, s.
pub type Progress<'a> = &'a (dyn Fn(f64) + Sync);

/// Everything a run needs.
pub struct Run<'a> {
    /// The plant (bench, duty, geometry, motion).
    pub plant: &'a Plant,
    /// Valve schedule.
    pub valve: ValveSchedule,
    /// Initial pressures.
    pub initial: Initial,
    /// Duration, s.
    pub duration: f64,
    /// Output sample interval, s.
    pub sample_dt: f64,
    /// Solver settings.
    pub solver: SolverOptions,
    /// Told the simulated time reached, s (a progress bar, or nothing): the simulation
    /// library knows no terminal.
    pub progress: Option<Progress<'a>>,
}

/// Runs `run` with `controller` driving the valve (whatever `run.valve` says) and hands the
/// controller back with the result, so that what it logged can be inspected.
pub fn simulate_with<C: ValveController + 'static>(
    mut run: Run<'_>,
    controller: C,
) -> (Result<SimResult, SimError>, C) {
    struct Lent<C>(std::rc::Rc<std::cell::RefCell<C>>);
    impl<C: ValveController> ValveController for Lent<C> {
        fn period(&self) -> f64 {
            self.0.borrow().period()
        }
        fn update(&mut self, t: f64, plant: &Eval) -> f64 {
            self.0.borrow_mut().update(t, plant)
        }
        fn finished(&self) -> bool {
            self.0.borrow().finished()
        }
    }
    let shared = std::rc::Rc::new(std::cell::RefCell::new(controller));
    run.valve = ValveSchedule::Controller(Box::new(Lent(shared.clone())));
    let res = simulate(run);
    // `simulate` consumed the run and with it the other handle.
    let controller = match std::rc::Rc::try_unwrap(shared) {
        Ok(cell) => cell.into_inner(),
        Err(_) => unreachable!("the run that held the other handle has been dropped"),
    };
    (res, controller)
}

/// Steady motor state (inlet pressure Pa, speed rad/s) for P2, LP and aperture.
pub fn steady_motor(bench: &Bench, p2: f64, lp: f64, aperture_pct: f64) -> (f64, f64) {
    use crate::sim::bench::Load;
    let dp_of = |w: f64| match bench.load {
        Load::Viscous(c) => c * w / (bench.motor_disp_m3_per_rad * bench.motor_eta_mech),
        Load::Constant(t) => t / (bench.motor_disp_m3_per_rad * bench.motor_eta_mech),
    };
    let resid = |w: f64| {
        let dpm = dp_of(w);
        crate::sim::physics::valve_flow(bench, aperture_pct, p2 - lp - dpm)
            - bench.motor_disp_m3_per_rad * w
            - bench.motor_leak_m3_per_s_pa * dpm
    };
    if aperture_pct <= 0.0 || resid(0.0) <= 0.0 {
        return (lp, 0.0);
    }
    let (mut lo, mut hi) = (0.0, 1.0);
    while resid(hi) > 0.0 && hi < 1e5 {
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if resid(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let w = 0.5 * (lo + hi);
    (lp + dp_of(w), w)
}

/// The first step's size, s (and a restarted run's).
const H0_S: f64 = 1e-5;

/// Whether diffsol gave up on a step's size (the error a restart can get past).
fn step_too_small(e: &diffsol::error::DiffsolError) -> bool {
    e.to_string().contains("Step size is too small")
}

/// Contact switches at one instant beyond which a run is refused (a rod chattering on a face).
const MAX_SWITCHES_AT_ONCE: usize = 16;

/// Runs the simulation.
pub fn simulate(mut run: Run<'_>) -> Result<SimResult, SimError> {
    let plant = run.plant;
    let bench = plant.bench();
    if !(run.duration > 0.0 && run.sample_dt > 0.0) {
        return Err(SimError::Setup(format!(
            "duration {} s and sample interval {} s must be positive",
            run.duration, run.sample_dt
        )));
    }
    let start = Instant::now();
    plant.set_reuse_kinematics(run.solver.reuse_kinematics);
    let n = plant.len();
    // Every rod free at its eye (the initial state's), before the controller's first look.
    let events = bench.stops == crate::sim::bench::Stops::Events;
    plant.set_contact_events(events);
    // Initial state: motor in steady state for the initial command.
    let probe = plant.initial_state(
        run.initial.p2_pa,
        run.initial.lp_pa,
        run.initial.lp_pa,
        0.0,
        0.0,
    );
    let a0 = run
        .valve
        .initial(&plant.evaluate(0.0, &probe, None, false))
        .clamp(0.0, 100.0);
    let (pm0, w0) = steady_motor(bench, run.initial.p2_pa, run.initial.lp_pa, a0);
    let y0 = plant.initial_state(run.initial.p2_pa, run.initial.lp_pa, pm0, w0, a0);
    let threshold = match run.valve {
        ValveSchedule::Threshold { threshold_pa, .. } if a0 == 0.0 => Some(threshold_pa / BAR),
        _ => None,
    };
    let latched = std::cell::Cell::new(threshold.is_none());
    let i_p2 = plant.p2_index();
    let n_roots = 1 + if events {
        plant.contact_root_count()
    } else {
        0
    };

    let cache = RefCell::new(JvCache::new(n));
    let qcache = RefCell::new(JvCache::new(n));
    let rhs_f = |t: f64, x: &[f64], y: &mut [f64]| plant.rhs(t, x, y);
    let quad_f = |t: f64, x: &[f64], y: &mut [f64]| plant.quadrature(t, x, y);
    let y0c = y0.clone();
    let mut problem = OdeBuilder::<M>::new()
        .rtol(run.solver.rtol)
        .atol(plant.atol(run.solver.atol_scale))
        .h0(H0_S)
        .rhs_implicit(
            |x: &[f64], _p: &[f64], t: f64, y: &mut [f64]| {
                cache.borrow_mut().evals += 1;
                plant.rhs(t, x, y)
            },
            |x: &[f64], _p: &[f64], t: f64, v: &[f64], y: &mut [f64]| {
                cache.borrow_mut().jv(rhs_f, t, x, v, y)
            },
        )
        .init(
            move |_p: &[f64], _t: f64, y: &mut [f64]| y.copy_from_slice(&y0c),
            n,
        )
        .root(
            |x: &[f64], _p: &[f64], t: f64, y: &mut [f64]| {
                y[0] = match threshold {
                    Some(th) if !latched.get() => x[i_p2] - th,
                    _ => -1.0,
                };
                if events {
                    plant.contact_roots(t, x, &mut y[1..]);
                }
            },
            n_roots,
        )
        .out_implicit(
            |x: &[f64], _p: &[f64], t: f64, y: &mut [f64]| plant.quadrature(t, x, y),
            |x: &[f64], _p: &[f64], t: f64, v: &[f64], y: &mut [f64]| {
                qcache.borrow_mut().jv(quad_f, t, x, v, y)
            },
            N_QUAD,
        )
        .integrate_out(true)
        .turn_off_output_error_control()
        .build()
        .map_err(|e| SimError::Setup(format!("cannot build the ODE problem: {e}")))?;
    // ~10 recoverable Newton failures per simulated second: never give up on the count alone.
    problem.ode_options.max_nonlinear_solver_failures = usize::MAX / 2;
    problem.ode_options.max_error_test_failures = usize::MAX / 2;
    let mut solver = problem
        .bdf::<NalgebraLU<f64>>()
        .map_err(|e| SimError::Solver {
            t: 0.0,
            message: e.to_string(),
        })?;

    let mut t_end = run.duration;
    let n_samples = (t_end / run.sample_dt + 1e-9).floor() as usize + 1;
    let mut trace = Trace::default();
    trace.push(0.0, &plant.evaluate(0.0, &y0, None, false));
    let mut next_k = 1usize;
    let mut valve_opened_at = None;
    let mut ybuf = NalgebraVec::zeros(n, Default::default());
    let mut yv = vec![0.0; n];
    let mut ysample = vec![0.0; n];
    let solver_err = |t: f64, e: diffsol::error::DiffsolError| SimError::Solver {
        t,
        message: e.to_string(),
    };
    // After a discrete input change, restart the BDF history from the current state with a
    // consistent derivative (diffsol re-initialises to first order on a modified state).
    let mut dybuf = vec![0.0; n];
    let mut qbuf = [0.0; N_QUAD];
    macro_rules! refresh_derivative {
        ($solver:ident, $t:expr) => {{
            let st = $solver.state_mut();
            let y = st.y.clone_as_vec();
            plant.rhs($t, &y, &mut dybuf);
            for (i, v) in dybuf.iter().enumerate() {
                st.dy[i] = *v;
            }
            plant.quadrature($t, &y, &mut qbuf);
            for (i, v) in qbuf.iter().enumerate() {
                st.dg[i] = *v;
            }
        }};
    }
    let mut stop = run.valve.next_event(0.0).min(t_end);
    solver.set_stop_time(stop).map_err(|e| solver_err(0.0, e))?;
    let mut steps = 0usize;
    let mut restarted_at = f64::NAN;
    let mut contact_switches = 0usize;
    loop {
        let t_before = solver.state().t;
        let reason = match solver.step() {
            Ok(r) => r,
            // A step whose size is driven below diffsol's minimum (e.g. where the motor line's
            // make-up valve and the motor's zero speed meet) restarts the BDF history once from
            // the state it stands at, with a consistent derivative, at first order and the
            // run's first step size (diffsol keeps the collapsed one). A second failure without
            // progress, or any other error, is the run's error.
            Err(e) if restarted_at == solver.state().t || !step_too_small(&e) => {
                return Err(solver_err(t_before, e));
            }
            Err(_) => {
                let t = solver.state().t;
                restarted_at = t;
                *solver.state_mut().h = H0_S;
                refresh_derivative!(solver, t);
                if stop > t {
                    solver.set_stop_time(stop).map_err(|e| solver_err(t, e))?;
                }
                continue;
            }
        };
        steps += 1;
        let t_now = solver.state().t;
        {
            let y = solver.state().y;
            for (i, v) in yv.iter_mut().enumerate() {
                *v = y[i];
            }
        }
        if let Err((i, v)) = plant.check_state(&yv) {
            return Err(SimError::NonPhysical {
                t: t_now,
                state: plant.state_name(i),
                value: v,
            });
        }
        let t_emit = match reason {
            OdeSolverStopReason::RootFound(tr, _) => tr,
            _ => t_now,
        };
        while next_k < n_samples {
            let tk = (next_k as f64 * run.sample_dt).min(t_end);
            if tk > t_emit + EVENT_TOL_S {
                break;
            }
            // (A stop time can be reached a rounding error short of `tk`.)
            solver
                .interpolate_inplace(tk.min(t_emit), &mut ybuf)
                .map_err(|e| solver_err(tk, e))?;
            for (i, v) in ysample.iter_mut().enumerate() {
                *v = ybuf[i];
            }
            trace.push(tk, &plant.evaluate(tk, &ysample, None, false));
            next_k += 1;
        }
        if let Some(progress) = run.progress {
            progress(t_emit);
        }
        match reason {
            OdeSolverStopReason::RootFound(tr, idx) if idx > 0 => {
                // A rod meets or leaves a face of its free play: the state on the face, every
                // other contact the search passed over settled too (a root the solver starts
                // from at or below zero would never change sign), the BDF history restarted.
                solver.state_mut_back(tr).map_err(|e| solver_err(tr, e))?;
                {
                    let st = solver.state_mut();
                    let mut y = st.y.clone_as_vec();
                    plant.switch_contact(tr, &mut y, idx - 1);
                    let more = plant
                        .settle_contacts(tr, &mut y, MAX_SWITCHES_AT_ONCE)
                        .ok_or_else(|| SimError::Solver {
                            t: tr,
                            message: format!(
                                "a rod's contact switched more than {MAX_SWITCHES_AT_ONCE} times \
                                 at one instant (chattering on a face of its free play)"
                            ),
                        })?;
                    contact_switches += more;
                    for (i, v) in y.iter().enumerate() {
                        st.y[i] = *v;
                    }
                }
                contact_switches += 1;
                cache.borrow_mut().invalidate();
                qcache.borrow_mut().invalidate();
                refresh_derivative!(solver, tr);
            }
            OdeSolverStopReason::RootFound(tr, _) => {
                latched.set(true);
                valve_opened_at = Some(tr);
                if let ValveSchedule::Threshold { aperture_pct, .. } = run.valve {
                    plant.command_pct.set(aperture_pct.clamp(0.0, 100.0));
                }
                solver.state_mut_back(tr).map_err(|e| solver_err(tr, e))?;
                refresh_derivative!(solver, tr);
            }
            OdeSolverStopReason::TstopReached => {
                if t_now >= t_end - EVENT_TOL_S {
                    break;
                }
                let e = plant.evaluate(t_now, &yv, None, false);
                let cmd = match &mut run.valve {
                    ValveSchedule::Table(tab) => table_at(tab, t_now),
                    ValveSchedule::Controller(c) => {
                        let a = c.update(t_now, &e);
                        if c.finished() {
                            // The trace already holds every sample up to here.
                            t_end = t_now;
                            break;
                        }
                        a
                    }
                    _ => plant.command_pct.get(),
                }
                .clamp(0.0, 100.0);
                if cmd != plant.command_pct.get() {
                    plant.command_pct.set(cmd);
                    refresh_derivative!(solver, t_now);
                }
                stop = run.valve.next_event(t_now).min(t_end);
                solver
                    .set_stop_time(stop)
                    .map_err(|e| solver_err(t_now, e))?;
            }
            OdeSolverStopReason::InternalTimestep => {}
        }
    }
    let g = solver.state().g.clone_as_vec();
    let y_end = yv.clone();
    let balance = balances(plant, (0.0, &y0), (t_end, &y_end), &g);
    let power = Power::of(&balance, t_end);
    let stats = Stats {
        steps,
        rhs_evals: cache.borrow().evals,
        contact_switches,
        wall_s: start.elapsed().as_secs_f64(),
    };
    Ok(SimResult {
        trace,
        balance,
        stats,
        valve_opened_at,
        power,
    })
}

fn balances(plant: &Plant, (t0, y0): (f64, &[f64]), (t1, y1): (f64, &[f64]), g: &[f64]) -> Balance {
    let (m0, e0) = plant.storage(t0, y0);
    let (m1, e1) = plant.storage(t1, y1);
    let q = |i: usize| g[i] * 1e-3; // L -> m³ of reference volume
    let w = |i: usize| g[i] * 1e3; // kJ -> J
    // Oil (mass, as reference volume) per node: Δcontent = ∫ inflow − ∫ outflow.
    let flows = [
        (q(0), q(1) + q(2)),
        (q(1) + q(3), q(4)),
        (q(4) + q(2), q(3) + q(5)),
        (q(5), q(0)),
    ];
    // Each node's error is relative to its own throughput plus 0.1 % of all the oil that moved
    // (a node that barely moves, like the chambers of a blocked run, is not judged on noise).
    let moved: f64 = (0..6).map(|i| q(i).abs()).sum();
    let mut volume_rel_error = [0.0; 5];
    for k in 0..4 {
        let (inflow, outflow) = flows[k];
        let dm = m1[k] - m0[k];
        let scale = inflow.abs() + outflow.abs() + dm.abs() + 1e-3 * moved;
        volume_rel_error[k] = if scale > 0.0 {
            (dm - (inflow - outflow)).abs() / scale
        } else {
            0.0
        };
    }
    // The circuit is closed: total oil is constant (a check on the solver alone).
    // Normalised by the oil that moved (or, in a run where nothing moved, by the oil present).
    let total = m1.iter().sum::<f64>() - m0.iter().sum::<f64>();
    let scale = if moved > 0.0 { moved } else { m0.iter().sum() };
    volume_rel_error[4] = total.abs() / scale;
    let stored_by = e1.since(&e0);
    let stored = stored_by.total();
    let losses: f64 = quad::OUT.iter().map(|&i| w(i)).sum();
    let input = w(quad::INPUT);
    let resid = input - losses - stored;
    let scale = input.abs() + losses.abs() + stored.abs();
    Balance {
        integrals: QUAD_NAMES
            .iter()
            .zip(g)
            .map(|(n, v)| (n.to_string(), *v))
            .collect(),
        volume_rel_error,
        energy_rel_error: if scale > 0.0 {
            resid.abs() / scale
        } else {
            0.0
        },
        stored_kj: stored * 1e-3,
        stored: stored_by,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Every(f64);
    impl ValveController for Every {
        fn period(&self) -> f64 {
            self.0
        }
        fn update(&mut self, _: f64, _: &Eval) -> f64 {
            0.0
        }
    }

    /// diffsol's BDF stops a rounding error short of a stop time late in a run (t = 187.8047 s
    /// was 3.6·10⁻¹² s short of 192 312 periods of 2⁻¹⁰ s in a closed loop): the next event from
    /// there is the period after, not the one just reached (which diffsol refuses as a stop
    /// time: "Stop time is at the current state time").
    #[test]
    fn an_event_reached_a_rounding_error_short_is_not_the_next_one() {
        let p = 2f64.powi(-10);
        let c = ValveSchedule::Controller(Box::new(Every(p)));
        for k in [1u32, 1024, 153_587, 192_312, 3_686_400] {
            let at = f64::from(k) * p;
            // diffsol's own tolerance there, for a step of a period.
            let roundoff = 100.0 * f64::EPSILON * (at + p);
            for t in [at - roundoff, at - 3.6e-12, at, at + roundoff] {
                let next = c.next_event(t);
                assert_eq!(next, f64::from(k + 1) * p, "k {k}, t {t:e}");
            }
        }
        let tab = vec![(10.0, 5.0), (187.8046875, 20.0), (190.0, 0.0)];
        let short = 187.8046875 - 3.6e-12;
        assert_eq!(table_at(&tab, short), 20.0);
        assert_eq!(ValveSchedule::Table(tab).next_event(short), 190.0);
    }
}
