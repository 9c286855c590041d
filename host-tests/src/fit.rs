//! Model adjustment from bench logs: least squares over full-simulation runs driven by the
//! logged shaft angle and valve aperture, solved with the MINPACK Levenberg–Marquardt of the
//! `levenberg-marquardt` crate. The Jacobian is taken by forward differences, every column's
//! simulations running in parallel (rayon).
//!
//! Parameters live in bounded form: the optimiser moves z ∈ ℝ and the bench value is
//! p = lo + (hi − lo)(1 + tanh z)/2, so a step can never leave the range the bench file accepts.
//! The valve's area table is fitted as factors on its increments (≥ 0), so it stays monotone.

use crate::model::sensors::{SensorSpec, SensorSynth};
use crate::sim::bench::{BAR, Bench, BenchFile};
use crate::sim::benchlog::BenchLog;
use crate::sim::motion::Motion;
use crate::sim::plant::Plant;
use crate::sim::solver::{self, Initial, Run, SolverOptions, ValveSchedule};
use crate::sim::trace::{Truth, truth_at};
use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{DMatrix, DVector, Dyn, Owned};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Residual weights: one standard deviation of the measurement, per quantity.
pub const SIGMA_P2_BAR: f64 = 0.5;
/// Motor speed σ, rpm.
pub const SIGMA_RPM: f64 = 5.0;

type Setter = Arc<dyn Fn(&mut BenchFile, f64) + Send + Sync>;

/// A fittable parameter.
#[derive(Clone)]
pub struct Param {
    /// Short name (command line).
    pub name: String,
    /// Bench file field.
    pub key: String,
    /// Unit.
    pub unit: String,
    /// Range the optimiser keeps to.
    pub lo: f64,
    /// Range the optimiser keeps to.
    pub hi: f64,
    /// Value in a bench file.
    pub get: Arc<dyn Fn(&BenchFile) -> f64 + Send + Sync>,
    /// Sets it.
    pub set: Setter,
}

impl std::fmt::Debug for Param {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}, {} in [{}, {}])",
            self.name, self.key, self.unit, self.lo, self.hi
        )
    }
}

fn scalar(
    name: &str,
    key: &str,
    unit: &str,
    lo: f64,
    hi: f64,
    get: fn(&BenchFile) -> f64,
    set: fn(&mut BenchFile, f64),
) -> Param {
    Param {
        name: name.into(),
        key: key.into(),
        unit: unit.into(),
        lo,
        hi,
        get: Arc::new(get),
        set: Arc::new(set),
    }
}

/// Names accepted by `--params` (`area_table` expands to one factor per table segment).
pub const PARAM_NAMES: &[&str] = &[
    "trapped_air",
    "cd",
    "cd_slope",
    "precharge",
    "hp_volume",
    "leakage",
    "area_table",
];

/// The parameters called `names`, for a fit starting from `start`.
pub fn params(names: &[String], start: &BenchFile) -> Result<Vec<Param>, String> {
    let mut v = Vec::new();
    for n in names {
        match n.as_str() {
            "trapped_air" => v.push(scalar(
                "trapped_air",
                "oil.trapped_air_fraction",
                "-",
                0.0,
                0.3,
                |f| f.oil.trapped_air_fraction,
                |f, x| f.oil.trapped_air_fraction = x,
            )),
            "cd" => v.push(scalar(
                "cd",
                "control_valve.discharge_coefficient",
                "-",
                0.02,
                1.0,
                |f| f.control_valve.discharge_coefficient,
                |f, x| f.control_valve.discharge_coefficient = x,
            )),
            "precharge" => v.push(scalar(
                "precharge",
                "hp_accumulator.precharge_bar",
                "bar",
                1.0,
                120.0,
                |f| f.hp_accumulator.precharge_bar,
                |f, x| f.hp_accumulator.precharge_bar = x,
            )),
            "hp_volume" => v.push(scalar(
                "hp_volume",
                "hp_accumulator.volume_l",
                "L",
                0.1,
                200.0,
                |f| f.hp_accumulator.volume_l,
                |f, x| f.hp_accumulator.volume_l = x,
            )),
            "cd_slope" => v.push(scalar(
                "cd_slope",
                "control_valve.cd_slope_per_100bar",
                "1/100 bar",
                -0.5,
                0.5,
                |f| f.control_valve.cd_slope_per_100bar,
                |f, x| f.control_valve.cd_slope_per_100bar = x,
            )),
            "leakage" => v.push(scalar(
                "leakage",
                "motor.volumetric_efficiency",
                "-",
                0.5,
                1.0,
                |f| f.motor.volumetric_efficiency,
                |f, x| f.motor.volumetric_efficiency = x,
            )),
            "area_table" => {
                let a = start.control_valve.area_mm2.clone();
                let ap = start.control_valve.aperture_pct.clone();
                for i in 1..a.len() {
                    let base = a.clone();
                    v.push(Param {
                        name: format!("area_seg{}", i),
                        key: format!(
                            "control_valve.area_mm2 increment {:.0}→{:.0} % (factor)",
                            ap[i - 1],
                            ap[i]
                        ),
                        unit: "×".into(),
                        lo: 0.0,
                        hi: 5.0,
                        get: {
                            let base = a.clone();
                            Arc::new(move |f: &BenchFile| {
                                let cur = &f.control_valve.area_mm2;
                                let b = base[i] - base[i - 1];
                                if b > 0.0 {
                                    (cur[i] - cur[i - 1]) / b
                                } else {
                                    1.0
                                }
                            })
                        },
                        // Segment i's increment = factor × its starting increment; the rest of
                        // the table is rebuilt cumulatively, so it stays monotone.
                        set: Arc::new(move |f, x| {
                            let cur = &mut f.control_valve.area_mm2;
                            let inc_now: Vec<f64> =
                                (1..cur.len()).map(|k| cur[k] - cur[k - 1]).collect();
                            let mut acc = cur[0];
                            for k in 1..cur.len() {
                                let inc = if k == i {
                                    x * (base[k] - base[k - 1])
                                } else {
                                    inc_now[k - 1]
                                };
                                acc += inc.max(0.0);
                                cur[k] = acc;
                            }
                        }),
                    });
                }
            }
            other => {
                return Err(format!(
                    "--params: unknown parameter `{other}` (known: {})",
                    PARAM_NAMES.join(", ")
                ));
            }
        }
    }
    if v.is_empty() {
        return Err("--params: nothing to fit".into());
    }
    Ok(v)
}

fn to_z(p: &Param, x: f64) -> f64 {
    let u = (2.0 * (x - p.lo) / (p.hi - p.lo) - 1.0).clamp(-0.999_999, 0.999_999);
    u.atanh()
}

fn from_z(p: &Param, z: f64) -> f64 {
    p.lo + (p.hi - p.lo) * 0.5 * (1.0 + z.tanh())
}

fn dx_dz(p: &Param, z: f64) -> f64 {
    let c = z.cosh();
    (p.hi - p.lo) * 0.5 / (c * c)
}

/// A log prepared for simulation: the samples the residuals use.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// The log.
    pub log: BenchLog,
    /// Indices of the samples in the residual (≈ `spacing_s` apart).
    pub idx: Vec<usize>,
    motion: Motion,
    valve: Vec<(f64, f64)>,
    /// Motor speed at the start, rpm.
    pub rpm0: f64,
    /// When the logged motor speed falls below [`COLLAPSE_FRACTION`] of `rpm0` (HP accumulator
    /// empty), s; `None` if it does not.
    pub collapse: Option<f64>,
    /// Start pressures, bar (see `start_value`).
    pub p2_start: f64,
    /// Same for LP.
    pub lp_start: f64,
}

/// Prepares logs: residual samples every `spacing_s` seconds.
pub fn prepare(logs: Vec<BenchLog>, spacing_s: f64) -> Vec<Prepared> {
    logs.into_iter()
        .map(|log| {
            let t0 = log.t[0];
            // Where the HP accumulator runs empty, P2 collapses and the motor stops within a
            // second or two. Pointwise residuals across that cliff would measure its timing
            // with huge, flat residuals (no gradient once the curves have parted); instead the
            // pointwise samples stop 1 s before the logged collapse and the collapse time itself
            // is one more residual, smooth in the parameters (it is what tells the precharge
            // apart from the accumulator volume).
            let moving = input_moves(&log);
            let rpm0 = start_value(&log.t, &log.rpm, moving);
            let collapse = (rpm0 > 50.0)
                .then(|| crossing(&log.t, &log.rpm, COLLAPSE_FRACTION * rpm0))
                .flatten();
            let end = collapse.map_or(log.t.len(), |tc| {
                log.t
                    .iter()
                    .position(|t| *t > tc - 1.0)
                    .unwrap_or(log.t.len())
            });
            let mut idx = Vec::new();
            let mut next = t0;
            for (i, &t) in log.t.iter().enumerate().take(end) {
                if t >= next {
                    idx.push(i);
                    next = t + spacing_s;
                }
            }
            let motion = Motion::from_samples(
                log.t.iter().map(|t| t - t0).collect(),
                log.theta_deg.iter().map(|a| a.to_radians()).collect(),
            );
            let (ts, ap) = log.valve_steps();
            let valve = ts
                .into_iter()
                .zip(ap)
                .map(|(t, a)| (t, a / 100.0))
                .collect();
            let p2_start = start_value(&log.t, &log.p2, moving);
            let lp_start = start_value(&log.t, &log.lp, moving);
            Prepared {
                log,
                idx,
                motion,
                valve,
                p2_start,
                lp_start,
                rpm0,
                collapse,
            }
        })
        .collect()
}

/// Start value of a logged pressure: one noisy sample would shift every later event — such as
/// the HP accumulator running empty — by its noise. With the input blocked the pressure decays
/// smoothly: a line through the first second, taken at the first sample. With the input moving,
/// P2 stays flat until the first chamber has compressed its trapped air and then climbs in
/// strokes, so a line would be biased: the mean of the first 0.3 s (at least three samples).
fn start_value(t: &[f64], y: &[f64], moving: bool) -> f64 {
    let window = if moving { 0.3 } else { 1.0 };
    let n = t
        .iter()
        .take_while(|&&x| x - t[0] <= window)
        .count()
        .max(3)
        .min(y.len());
    let (t, y) = (&t[..n], &y[..n]);
    let nf = n as f64;
    let ym = y.iter().sum::<f64>() / nf;
    if moving {
        return ym;
    }
    let tm = t.iter().sum::<f64>() / nf;
    let stt: f64 = t.iter().map(|x| (x - tm) * (x - tm)).sum();
    let sty: f64 = t.iter().zip(y).map(|(x, v)| (x - tm) * (v - ym)).sum();
    let slope = if stt > 0.0 { sty / stt } else { 0.0 };
    ym + slope * (t[0] - tm)
}

/// Whether the shaft moves in a log (more than 0.5° of travel).
pub fn input_moves(log: &BenchLog) -> bool {
    let (lo, hi) = log
        .theta_deg
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
            (a.min(*x), b.max(*x))
        });
    hi - lo >= 0.5
}

/// Solver settings of the fit's simulations: rtol 1e-7 keeps the finite-difference Jacobian
/// (steps of 1e-4 in the bounded coordinates) two orders above the integration noise at a
/// third of the cost of the default 1e-8.
pub const FIT_SOLVER: SolverOptions = SolverOptions {
    rtol: 1e-7,
    atol_scale: 1e-2,
};

/// Simulated (P2 bar, motor rpm) at every log sample.
pub fn simulate_log(bench: &Bench, p: &Prepared) -> Result<Vec<Truth>, String> {
    simulate_log_from(bench, p, 0.0)
}

/// Like [`simulate_log`], with the start P2 moved by `p2_offset` bar.
pub fn simulate_log_from(
    bench: &Bench,
    p: &Prepared,
    p2_offset: f64,
) -> Result<Vec<Truth>, String> {
    let log = &p.log;
    let on: [bool; 4] = log.on_duty;
    let plant = Plant::new(bench, log.config - 1, on, p.motion.clone());
    let t0 = log.t[0];
    let dur = log.t[log.t.len() - 1] - t0;
    let res = solver::simulate(Run {
        plant: &plant,
        valve: ValveSchedule::Table(p.valve.clone()),
        initial: Initial {
            p2: (p.p2_start + p2_offset) * BAR,
            lp: p.lp_start * BAR,
        },
        duration: dur,
        sample_dt: 0.05,
        solver: FIT_SOLVER,
        progress: None,
    })
    .map_err(|e| format!("{}: {e}", log.name()))?;
    Ok(log.t.iter().map(|t| truth_at(&res.trace, t - t0)).collect())
}

/// Residuals beyond this many σ are flattened (r → C·tanh(r/C)), so that a few samples far off
/// (a transient slightly shifted in time) cannot dominate the sum and pull the fit into a
/// compensating valley.
pub const ROBUST_SIGMAS: f64 = 10.0;

fn residuals_of(p: &Prepared, sim: &[Truth], out: &mut Vec<f64>) {
    let from = out.len();
    raw_residuals(p, sim, out);
    for r in &mut out[from..] {
        *r = ROBUST_SIGMAS * (*r / ROBUST_SIGMAS).tanh();
    }
}

fn raw_residuals(p: &Prepared, sim: &[Truth], out: &mut Vec<f64>) {
    for &i in &p.idx {
        out.push((sim[i].p2 - p.log.p2[i]) / SIGMA_P2_BAR);
        out.push((sim[i].motor_rpm - p.log.rpm[i]) / SIGMA_RPM);
    }
    if let Some(tc) = p.collapse {
        // A simulation that does not collapse within the log counts as collapsing at its end.
        let rpm: Vec<f64> = sim.iter().map(|x| x.motor_rpm).collect();
        let ts = crossing(&p.log.t, &rpm, COLLAPSE_FRACTION * p.rpm0)
            .unwrap_or(p.log.t[p.log.t.len() - 1]);
        out.push((ts - tc) / SIGMA_COLLAPSE_S);
    }
}

/// The collapse is where the motor speed falls below this fraction of its starting speed.
pub const COLLAPSE_FRACTION: f64 = 0.25;
/// σ of the collapse time, s.
pub const SIGMA_COLLAPSE_S: f64 = 2.0;

/// First time `y` falls below `level` after having been above it, linearly interpolated.
pub fn crossing(t: &[f64], y: &[f64], level: f64) -> Option<f64> {
    let first_above = y.iter().position(|v| *v >= level)?;
    (first_above + 1..y.len()).find(|&k| y[k] < level).map(|k| {
        let (y0, y1) = (y[k - 1], y[k]);
        let u = if y0 > y1 {
            (y0 - level) / (y0 - y1)
        } else {
            1.0
        };
        t[k - 1] + u.clamp(0.0, 1.0) * (t[k] - t[k - 1])
    })
}

/// A progress callback: called once per simulation the fit runs (from any thread).
pub type Tick = Arc<dyn Fn() + Send + Sync>;

/// The fit problem.
struct Problem {
    start: BenchFile,
    params: Vec<Param>,
    logs: Arc<Vec<Prepared>>,
    /// z = the parameters' bounded coordinates, then (if `offsets`) one start-P2 correction per
    /// log, bar.
    offsets: bool,
    z: DVector<f64>,
    progress: Option<Tick>,
    evals: std::sync::atomic::AtomicUsize,
}

impl Problem {
    fn bench_at(&self, z: &[f64]) -> Result<Bench, String> {
        let mut f = self.start.clone();
        for (p, &zi) in self.params.iter().zip(z) {
            (p.set)(&mut f, from_z(p, zi));
        }
        Bench::from_file(f, "fit").map_err(|e| e.to_string())
    }

    fn offsets_of(&self, z: &[f64]) -> Vec<f64> {
        if self.offsets {
            z[self.params.len()..].to_vec()
        } else {
            vec![0.0; self.logs.len()]
        }
    }

    /// Runs (bench, log, start-P2 offset) simulations in parallel.
    fn run_jobs(
        &self,
        benches: &[Option<Bench>],
        jobs: &[(usize, usize, f64)],
    ) -> Vec<Option<Vec<Truth>>> {
        let sims = jobs
            .par_iter()
            .map(|&(b, l, off)| {
                let r = benches[b]
                    .as_ref()
                    .and_then(|b| simulate_log_from(b, &self.logs[l], off).ok());
                if let Some(tick) = &self.progress {
                    tick();
                }
                r
            })
            .collect();
        self.evals
            .fetch_add(jobs.len(), std::sync::atomic::Ordering::Relaxed);
        sims
    }

    /// The residual vector from one simulation per log (plus the start-offset priors).
    fn assemble(&self, sims: &[&Vec<Truth>], offsets: &[f64]) -> Vec<f64> {
        let mut out = Vec::new();
        for (l, sim) in sims.iter().enumerate() {
            residuals_of(&self.logs[l], sim, &mut out);
        }
        if self.offsets {
            out.extend(offsets.iter().map(|o| o / SIGMA_START_BAR));
        }
        out
    }

    fn base(&self, z: &[f64]) -> Option<(Vec<Vec<Truth>>, Vec<f64>)> {
        let offsets = self.offsets_of(z);
        let benches = [self.bench_at(z).ok()];
        let jobs: Vec<(usize, usize, f64)> =
            (0..self.logs.len()).map(|l| (0, l, offsets[l])).collect();
        let sims: Option<Vec<Vec<Truth>>> = self.run_jobs(&benches, &jobs).into_iter().collect();
        Some((sims?, offsets))
    }
}

/// σ of a log's start P2 as read from its first samples, bar (the prior on its correction).
pub const SIGMA_START_BAR: f64 = 0.3;

impl LeastSquaresProblem<f64, Dyn, Dyn> for Problem {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, z: &DVector<f64>) {
        self.z.copy_from(z);
    }

    fn params(&self) -> DVector<f64> {
        self.z.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let z: Vec<f64> = self.z.iter().copied().collect();
        let (sims, offsets) = self.base(&z)?;
        let refs: Vec<&Vec<Truth>> = sims.iter().collect();
        Some(DVector::from_vec(self.assemble(&refs, &offsets)))
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        // Forward differences. A parameter's column re-simulates every log; a log's start-P2
        // correction re-simulates that log only.
        let z: Vec<f64> = self.z.iter().copied().collect();
        let ng = self.params.len();
        let nl = self.logs.len();
        let h: Vec<f64> = z.iter().map(|zi| 1e-4 * (1.0 + zi.abs())).collect();
        let offsets = self.offsets_of(&z);
        let mut benches = vec![self.bench_at(&z).ok()];
        for j in 0..ng {
            let mut zj = z.clone();
            zj[j] += h[j];
            benches.push(self.bench_at(&zj).ok());
        }
        let mut jobs: Vec<(usize, usize, f64)> = Vec::new();
        for b in 0..=ng {
            for (l, off) in offsets.iter().enumerate() {
                jobs.push((b, l, *off));
            }
        }
        if self.offsets {
            for (l, off) in offsets.iter().enumerate() {
                jobs.push((0, l, off + h[ng + l]));
            }
        }
        let sims: Vec<Vec<Truth>> = self
            .run_jobs(&benches, &jobs)
            .into_iter()
            .collect::<Option<_>>()?;
        let base: Vec<&Vec<Truth>> = sims[..nl].iter().collect();
        let r0 = self.assemble(&base, &offsets);
        let mut jac = DMatrix::zeros(r0.len(), z.len());
        let mut fill = |j: usize, r: Vec<f64>| {
            for i in 0..r0.len() {
                jac[(i, j)] = (r[i] - r0[i]) / h[j];
            }
        };
        for j in 0..ng {
            let col: Vec<&Vec<Truth>> = sims[(j + 1) * nl..(j + 2) * nl].iter().collect();
            fill(j, self.assemble(&col, &offsets));
        }
        if self.offsets {
            for l in 0..nl {
                let mut col = base.clone();
                col[l] = &sims[(ng + 1) * nl + l];
                let mut off = offsets.clone();
                off[l] += h[ng + l];
                fill(ng + l, self.assemble(&col, &off));
            }
        }
        Some(jac)
    }
}

/// One fitted parameter.
#[derive(Debug, Clone, Serialize)]
pub struct Fitted {
    /// Short name.
    pub name: String,
    /// Bench file field.
    pub key: String,
    /// Unit.
    pub unit: String,
    /// Starting value.
    pub start: f64,
    /// Fitted value.
    pub value: f64,
    /// One standard deviation (from the Jacobian at the optimum); `None` if the logs do not
    /// determine it.
    pub sigma: Option<f64>,
}

/// Per log.
#[derive(Debug, Clone, Serialize)]
pub struct LogFit {
    /// Name.
    pub name: String,
    /// P2 RMS difference before / after, bar.
    pub p2_rms_bar: (f64, f64),
    /// Motor speed RMS difference before / after, rpm.
    pub rpm_rms: (f64, f64),
    /// Start P2 read from the log's first samples, and as corrected by the fit, bar.
    pub start_p2_bar: (f64, f64),
}

/// The result of a fit.
#[derive(Debug, Clone, Serialize)]
pub struct FitReport {
    /// Parameters.
    pub params: Vec<Fitted>,
    /// Weighted residual RMS before and after.
    pub residual_rms: (f64, f64),
    /// Before / after.
    pub improvement: f64,
    /// Per log.
    pub logs: Vec<LogFit>,
    /// Simulations run.
    pub simulations: usize,
    /// LM termination.
    pub termination: String,
    /// Converged.
    pub converged: bool,
    /// Wall time, s.
    pub wall_s: f64,
    /// Fitted bench file (set by the caller that writes it).
    pub bench_file: Option<PathBuf>,
    /// Model-crate configuration for the firmware (set by the caller that writes it).
    pub model_file: Option<PathBuf>,
    /// Figures.
    pub figures: Vec<PathBuf>,
}

/// What a fit returns besides its report: the fitted bench file and the simulations before /
/// after (for the figures).
pub struct FitOutcome {
    /// Report.
    pub report: FitReport,
    /// Fitted bench file.
    pub fitted: BenchFile,
    /// Simulated samples per log, before.
    pub before: Vec<Vec<Truth>>,
    /// After.
    pub after: Vec<Vec<Truth>>,
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

fn log_rms(p: &Prepared, sim: &[Truth]) -> (f64, f64) {
    let dp: Vec<f64> = p.idx.iter().map(|&i| sim[i].p2 - p.log.p2[i]).collect();
    let dr: Vec<f64> = p
        .idx
        .iter()
        .map(|&i| sim[i].motor_rpm - p.log.rpm[i])
        .collect();
    (rms(&dp), rms(&dr))
}

/// Fits `params` to `logs`, starting from `start`.
pub fn fit(
    start: &BenchFile,
    names: &[String],
    logs: Vec<BenchLog>,
    spacing_s: f64,
    max_iter: usize,
    progress: Option<Tick>,
) -> Result<FitOutcome, String> {
    let t0 = std::time::Instant::now();
    let params = params(names, start)?;
    let logs = Arc::new(prepare(logs, spacing_s));
    let b0 = Bench::from_file(start.clone(), "start").map_err(|e| e.to_string())?;
    let before: Vec<Vec<Truth>> = logs
        .par_iter()
        .map(|p| simulate_log(&b0, p))
        .collect::<Result<_, _>>()?;
    let mut r_before = Vec::new();
    for (p, s) in logs.iter().zip(&before) {
        raw_residuals(p, s, &mut r_before);
    }
    // Stages, as the paper adjusts by hand: the accumulator and the valve from the runs with
    // the input blocked (no pumping), the trapped air from the runs with the input moving (the
    // accumulator then known), then everything on every log from there.
    let blocked: Vec<usize> = (0..logs.len())
        .filter(|&k| !input_moves(&logs[k].log))
        .collect();
    let moving: Vec<usize> = (0..logs.len()).filter(|k| !blocked.contains(k)).collect();
    let is_air = |p: &Param| p.name == "trapped_air";
    let mut stages: Vec<(Vec<usize>, Vec<usize>)> = Vec::new();
    let acc: Vec<usize> = (0..params.len()).filter(|&j| !is_air(&params[j])).collect();
    let air: Vec<usize> = (0..params.len()).filter(|&j| is_air(&params[j])).collect();
    if !blocked.is_empty() && !acc.is_empty() && !air.is_empty() && !moving.is_empty() {
        stages.push((acc.clone(), blocked.clone()));
        stages.push((air.clone(), moving.clone()));
    }
    stages.push(((0..params.len()).collect(), (0..logs.len()).collect()));
    let mut cur = start.clone();
    let mut evals = 0;
    let mut termination = String::new();
    let mut converged = false;
    let mut last: Option<(Problem, Vec<usize>)> = None;
    let n_stages = stages.len();
    for (stage, (pj, lk)) in stages.into_iter().enumerate() {
        let sub: Vec<Param> = pj.iter().map(|&j| params[j].clone()).collect();
        let sub_logs: Vec<Prepared> = lk.iter().map(|&k| logs[k].clone()).collect();
        let mut z0: Vec<f64> = sub.iter().map(|p| to_z(p, (p.get)(&cur))).collect();
        // The last stage also corrects each log's start P2 (read from noisy first samples, it
        // would otherwise shift the moment the accumulator runs empty by up to a second).
        let offsets = stage + 1 == n_stages;
        if offsets {
            z0.extend(std::iter::repeat_n(0.0, sub_logs.len()));
        }
        let problem = Problem {
            start: cur.clone(),
            params: sub,
            logs: Arc::new(sub_logs),
            offsets,
            z: DVector::from_vec(z0),
            progress: progress.clone(),
            evals: Default::default(),
        };
        let lm = LevenbergMarquardt::<f64>::new()
            .with_patience(max_iter.max(1))
            .with_ftol(1e-5)
            .with_xtol(1e-5);
        let (problem, report) = lm.minimize(problem);
        evals += problem.evals.load(std::sync::atomic::Ordering::Relaxed);
        termination = format!("{:?}", report.termination);
        converged = report.termination.was_successful();
        let z: Vec<f64> = problem.z.iter().copied().collect();
        for (p, &zi) in problem.params.iter().zip(&z) {
            (p.set)(&mut cur, from_z(p, zi));
        }
        last = Some((problem, pj));
    }
    let (problem, _) = last.ok_or("no fit stage ran")?;
    let z: Vec<f64> = problem.z.iter().copied().collect();
    let fitted_bench = problem.bench_at(&z)?;
    let corrections = problem.offsets_of(&z);
    let after: Vec<Vec<Truth>> = logs
        .par_iter()
        .zip(&corrections)
        .map(|(p, off)| simulate_log_from(&fitted_bench, p, *off))
        .collect::<Result<_, _>>()?;
    let mut r_after = Vec::new();
    for (p, s) in logs.iter().zip(&after) {
        raw_residuals(p, s, &mut r_after);
    }
    // Uncertainty: cov(z) = s²(JᵀJ)⁻¹ with s² = SSR/(m − n), through the bounds' transform.
    let jac = problem
        .jacobian()
        .ok_or("the Jacobian at the optimum failed")?;
    let r_opt = problem
        .residuals()
        .ok_or("the residuals at the optimum failed")?;
    let m = r_opt.len();
    let n = z.len();
    let s2 = r_opt.iter().map(|x| x * x).sum::<f64>() / (m.saturating_sub(n)).max(1) as f64;
    let jtj = jac.transpose() * &jac;
    let svd = jtj.clone().svd(true, true);
    let smax = svd.singular_values.max();
    let pinv = svd
        .pseudo_inverse(smax * 1e-10)
        .map_err(|e| format!("covariance: {e}"))?;
    let mut fitted = start.clone();
    let mut out = Vec::new();
    for (j, p) in params.iter().enumerate() {
        let value = from_z(p, z[j]);
        (p.set)(&mut fitted, value);
        let determined = jtj[(j, j)] > smax * 1e-10;
        let var = s2 * pinv[(j, j)];
        out.push(Fitted {
            name: p.name.clone(),
            key: p.key.clone(),
            unit: p.unit.clone(),
            start: (p.get)(start),
            value,
            sigma: (determined && var.is_finite() && var >= 0.0)
                .then(|| var.sqrt() * dx_dz(p, z[j])),
        });
    }
    // Area-table factors report the table itself.
    let per_log = logs
        .iter()
        .zip(before.iter().zip(&after))
        .zip(&corrections)
        .map(|((p, (b, a)), c)| {
            let (pb, rb) = log_rms(p, b);
            let (pa, ra) = log_rms(p, a);
            LogFit {
                name: p.log.name(),
                p2_rms_bar: (pb, pa),
                rpm_rms: (rb, ra),
                start_p2_bar: (p.p2_start, p.p2_start + c),
            }
        })
        .collect();
    let (rb, ra) = (rms(&r_before), rms(&r_after));
    Ok(FitOutcome {
        report: FitReport {
            params: out,
            residual_rms: (rb, ra),
            improvement: rb / ra.max(1e-12),
            logs: per_log,
            simulations: evals + 2 * logs.len(),
            termination,
            converged,
            wall_s: t0.elapsed().as_secs_f64(),
            bench_file: None,
            model_file: None,
            figures: Vec::new(),
        },
        fitted,
        before,
        after,
    })
}

/// Makes a bench log of a built-in scenario from the full simulation and the sensor model
/// (encoder 16 384 counts/rev, 12-bit pressures with noise, motor speed noise), sampled at
/// `rate_hz`.
pub fn synth_log(
    bench: &Bench,
    scenario: &str,
    rate_hz: f64,
    seed: u64,
    out: &Path,
) -> Result<BenchLog, String> {
    let mut s = crate::sim::scenario::builtin_named(scenario)
        .ok_or_else(|| format!("unknown scenario `{scenario}` (see `pto scenarios`)"))?;
    s.sample_interval_s = (0.5 / rate_hz).min(s.sample_interval_s);
    let (prep, res) = s.simulate(bench, Path::new("."), SolverOptions::default(), None)?;
    let mut synth = SensorSynth::new(SensorSpec::default(), seed);
    let n = (s.duration_s * rate_hz).floor() as usize + 1;
    let spec = SensorSpec::default();
    let mut log = BenchLog {
        path: out.join(format!("{scenario}.csv")),
        t: Vec::with_capacity(n),
        theta_deg: Vec::with_capacity(n),
        p2: Vec::with_capacity(n),
        lp: Vec::with_capacity(n),
        rpm: Vec::with_capacity(n),
        aperture: Vec::with_capacity(n),
        on_duty: prep.on_duty,
        config: prep.config + 1,
    };
    for k in 0..n {
        let t = k as f64 / rate_hz;
        let truth = truth_at(&res.trace, t);
        let theta = prep.plant.motion().at(t).0;
        let (enc, hp, lp, motor) = synth.read(theta, &truth);
        log.t.push(t);
        log.theta_deg
            .push(f64::from(enc) * 360.0 / f64::from(spec.counts_per_rev));
        log.p2.push(hp);
        log.lp.push(lp);
        log.rpm.push(motor);
        log.aperture
            .push(crate::model::commanded_aperture_pct(&s, &res, t));
    }
    Ok(log)
}

/// The paper's experimental runs (Section 4.2), as built-in scenario names.
pub const EXPERIMENTAL_RUNS: [&str; 7] = [
    "exp-charge-64.5",
    "exp-charge-67.2",
    "exp-charge-72",
    "exp-9pct-101.5",
    "exp-discharge-102",
    "exp-discharge-84",
    "exp-discharge-71",
];

/// Sets a `name=value` override on a bench file (`pto synth-logs --set`, `pto simulate
/// --set`): a fit parameter's short name (`trapped_air`, `cd`, `precharge`, …) or any bench
/// field by its dotted path (`hp_accumulator.volume_l`, `cylinder[1].bore_mm`).
pub fn apply_override(f: &mut BenchFile, kv: &str) -> Result<(), String> {
    let (k, v) = kv
        .split_once('=')
        .ok_or_else(|| format!("--set {kv}: want name=value"))?;
    let k = k.trim();
    if k.contains('.') || k.contains('[') {
        return f.set_field(k, v.trim()).map_err(|e| format!("--set {e}"));
    }
    let Ok(v) = v.trim().parse::<f64>() else {
        return f.set_field(k, v.trim()).map_err(|e| format!("--set {e}"));
    };
    let scalars: Vec<String> = PARAM_NAMES
        .iter()
        .filter(|n| **n != "area_table")
        .map(|n| n.to_string())
        .collect();
    let all = params(&scalars, f)?;
    match all.iter().find(|p| p.name == k || p.key == k) {
        Some(p) => {
            (p.set)(f, v);
            Ok(())
        }
        // Not a parameter name: a top-level bench field.
        None => f.set_field(k, &v.to_string()).map_err(|e| {
            format!(
                "--set {e} (or a parameter: {})",
                all.iter()
                    .map(|p| p.name.clone())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        }),
    }
}
