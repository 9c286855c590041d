//! The solver driver: diffsol BDF over the plant, segment by segment between the valve's
//! events ([`schedule`](crate::sim::schedule)), the stops' contacts as located roots, sampling
//! into a [`Trace`] and the run's [`Balance`].
//!
//! Over 500 lines on purpose: one integration loop (segments, roots, sampling, balances) whose
//! parts share its state.

use crate::sim::balance::{Balance, balances};
use crate::sim::bench::BAR;
use crate::sim::physics::steady_motor;
use crate::sim::plant::{Eval, N_QUAD, Plant};
use crate::sim::power::Power;
use crate::sim::schedule::{EVENT_TOL_S, ValveController, ValveSchedule, table_at};
use crate::sim::trace::Trace;
use diffsol::{
    NalgebraLU, NalgebraMat, NalgebraVec, OdeBuilder, OdeSolverMethod, OdeSolverStopReason, Vector,
};
use serde::Serialize;
use std::cell::RefCell;
use std::time::Instant;

type M = NalgebraMat<f64>;

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
