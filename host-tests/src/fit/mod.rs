//! Model adjustment from bench logs: least squares over full-simulation runs driven by the
//! logged shaft angle and valve aperture, solved with the MINPACK Levenberg–Marquardt of the
//! `levenberg-marquardt` crate. The Jacobian is taken by forward differences, every column's
//! simulations running in parallel (rayon).
//!
//! Parameters live in bounded form: the optimiser moves z ∈ ℝ and the bench value is
//! p = lo + (hi − lo)(1 + tanh z)/2, so a step can never leave the range the bench file accepts.
//! The valve's area table is fitted as factors on its increments (≥ 0), so it stays monotone.

use crate::model::sensors::{Readings, SensorSpec, SensorSynth};
use crate::sim::bench::{BAR, Bench, BenchError, BenchFile, Setter, Shortcut};
use crate::sim::benchlog::BenchLog;
use crate::sim::motion::Motion;
use crate::sim::plant::Plant;
use crate::sim::scenario::RunError;
use crate::sim::solver::{self, Initial, Run, SimError, SolverOptions, ValveSchedule};
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

mod params;
mod problem;
mod residuals;
mod synth;

pub use params::*;
pub use problem::*;
pub use residuals::*;
pub use synth::*;

/// Why a fit (or a synthetic log) could not be made.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// `--params` names a parameter the fit does not know.
    #[error("--params: unknown parameter `{name}` (known: {})", PARAM_NAMES.join(", "))]
    UnknownParam {
        /// The name.
        name: String,
    },
    /// `--params` is empty.
    #[error("--params: nothing to fit")]
    NoParams,
    /// The starting or a trial bench is invalid.
    #[error(transparent)]
    Bench(#[from] BenchError),
    /// A log's simulation failed.
    #[error("{log}")]
    Simulation {
        /// The log's name.
        log: String,
        /// The solver's error.
        source: SimError,
    },
    /// No stage of the fit ran.
    #[error("no fit stage ran")]
    NoStage,
    /// The Jacobian at the optimum could not be evaluated.
    #[error("the Jacobian at the optimum failed")]
    Jacobian,
    /// The residuals at the optimum could not be evaluated.
    #[error("the residuals at the optimum failed")]
    Residuals,
    /// The pseudo-inverse of JᵀJ failed.
    #[error("covariance: {0}")]
    Covariance(&'static str),
    /// `pto synth-logs --runs` names no built-in scenario.
    #[error("unknown scenario `{0}` (see `pto scenarios`)")]
    UnknownScenario(String),
    /// A synthetic log's scenario could not be run.
    #[error(transparent)]
    Run(#[from] RunError),
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
    let dp: Vec<f64> = p
        .idx
        .iter()
        .map(|&i| sim[i].p2_bar - p.log.p2_bar[i])
        .collect();
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
) -> Result<FitOutcome, FitError> {
    let t0 = std::time::Instant::now();
    let params = params(names, start)?;
    let logs = Arc::new(prepare(logs, spacing_s));
    let b0 = Bench::from_file(start.clone(), "start")?;
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
    let (problem, _) = last.ok_or(FitError::NoStage)?;
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
    let jac = problem.jacobian().ok_or(FitError::Jacobian)?;
    let r_opt = problem.residuals().ok_or(FitError::Residuals)?;
    let m = r_opt.len();
    let n = z.len();
    let s2 = r_opt.iter().map(|x| x * x).sum::<f64>() / (m.saturating_sub(n)).max(1) as f64;
    let jtj = jac.transpose() * &jac;
    let svd = jtj.clone().svd(true, true);
    let smax = svd.singular_values.max();
    let pinv = svd
        .pseudo_inverse(smax * 1e-10)
        .map_err(FitError::Covariance)?;
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
                start_p2_bar: (p.p2_start_bar, p.p2_start_bar + c),
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
