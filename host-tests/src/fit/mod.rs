//! Model adjustment from bench logs: least squares over full-simulation runs driven by the
//! logged shaft angle and valve aperture, solved with the MINPACK Levenberg–Marquardt of the
//! `levenberg-marquardt` crate. The Jacobian is taken by forward differences, every column's
//! simulations running in parallel (rayon).
//!
//! Parameters live in bounded form: the optimiser moves z ∈ ℝ and the bench value is
//! p = lo + (hi − lo)(1 + tanh z)/2, so a step can never leave the range the bench file accepts.
//! The valve's area table is fitted as factors on its increments (≥ 0), so it stays monotone.

use crate::sim::bench::{BAR, Bench, BenchError, BenchFile, Setter, Shortcut};
use crate::sim::benchlog::BenchLog;
use crate::sim::motion::Motion;
use crate::sim::plant::Plant;
use crate::sim::scenario::{RunError, Scenario};
use crate::sim::schedule::ValveSchedule;
use crate::sim::solver::{self, Initial, Run, SimError, SolverOptions};
use crate::sim::trace::{Truth, truth_at};
use crate::validation::sensors::{Readings, SensorSpec, SensorSynth};
use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{DMatrix, DVector, Dyn, Owned};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;

mod edit;
mod information;
mod noise;
mod params;
mod problem;
mod residuals;
mod synth;
mod verdict;

pub use edit::*;
pub use information::*;
pub use noise::*;
pub use params::*;
pub use problem::*;
pub use residuals::*;
pub use synth::*;
pub use verdict::*;

/// Why a fit (or a synthetic log) could not be made.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// `--params` names a parameter the fit does not know.
    #[error("--params: unknown parameter `{name}` (known: {})", PARAM_NAMES.join(", "))]
    UnknownParam {
        /// The name.
        name: String,
    },
    /// `--precision` names a parameter that is not fitted.
    #[error("--precision: `{0}` is not among the fitted parameters (--params)")]
    PrecisionOf(String),
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
    /// A campaign's log whose sidecar says it did not come out as planned.
    #[error(
        "{}: segment {} of {} is marked {} ({}) in {}: rerun that segment, or leave the log out",
        .1.display(),
        .0.index,
        .0.campaign,
        format!("{:?}", .0.status).to_lowercase(),
        .0.note,
        crate::plan::record::Record::path_for(.1).display()
    )]
    Segment(Box<crate::plan::record::Record>, PathBuf),
    /// A campaign file or a segment's sidecar that does not read.
    #[error(transparent)]
    Campaign(#[from] crate::plan::record::CampaignError),
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
    /// One standard deviation: from the Jacobian at the optimum, scaled by the reduced χ² (when
    /// above 1) and by the residuals' autocorrelation; `None` if the logs do not determine it.
    pub sigma: Option<f64>,
    /// The range the fit keeps it in.
    pub bounds: (f64, f64),
    /// The precision the fitted bench needs of it (± this, in its unit): the `precision` check
    /// wants 3σ within it.
    pub needed: f64,
}

/// When the HP accumulator runs empty in a log (the motor below 25 % of its starting speed), s
/// from the log's start.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Emptying {
    /// In the log.
    pub logged: Option<f64>,
    /// In the fitted simulation.
    pub simulated: Option<f64>,
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
    /// Mean squared residual after the fit, in units of the noise (≈ 1 when the model explains
    /// the log to within its noise).
    pub chi2: f64,
    /// Start P2 read from the log's first samples, and as corrected by the fit, bar.
    pub start_p2_bar: (f64, f64),
    /// Start LP, likewise, bar.
    pub start_lp_bar: (f64, f64),
    /// When the HP accumulator runs empty.
    pub emptying_s: Emptying,
}

/// The default simulation budget of a fit: ≈ 60 s on 2 cores for the seven experimental runs
/// (a passing four-parameter fit of them takes 900–1 800).
pub const DEFAULT_MAX_SIMULATIONS: usize = 2500;

/// What the fit was given besides the bench and the logs.
#[derive(Clone)]
pub struct FitOptions {
    /// Parameter names ([`PARAM_NAMES`]).
    pub params: Vec<String>,
    /// Seconds between residual samples (0: every sample).
    pub spacing_s: f64,
    /// Logs whose residuals are taken at every sample whatever `spacing_s`.
    pub dense_logs: DenseLogs,
    /// Iterations per stage.
    pub max_iter: usize,
    /// Simulations the fit may run (its time limit, reproducible): past it, the fit stops and
    /// fails its `converged` check.
    pub max_simulations: usize,
    /// P2 noise σ, bar (`None`: estimated from the logs).
    pub noise_p2_bar: Option<f64>,
    /// Motor speed noise σ, rpm (`None`: estimated from the logs).
    pub noise_rpm: Option<f64>,
    /// LP noise σ, bar (`None`: estimated from the logs).
    pub noise_lp_bar: Option<f64>,
    /// The checks' limits.
    pub limits: Limits,
    /// Precision needed per parameter name, in its unit (overrides [`Precision`]'s defaults).
    pub precision: Vec<(String, f64)>,
    /// Called once per simulation.
    pub progress: Option<Tick>,
}

/// Which logs the fit takes at every sample.
#[derive(Debug, Clone, PartialEq)]
pub enum DenseLogs {
    /// None: every log at `spacing_s`.
    None,
    /// The logs of a campaign (with a complete `.segment.toml` sidecar, [`crate::plan::record::Record`]):
    /// their rate was planned for residuals at every sample, and `pto plan` predicted its σ
    /// from them.
    Campaign,
}

impl FitOptions {
    /// `params` with every other setting at `pto fit`'s default (a sample every 0.5 s, every
    /// sample of a campaign's log with a complete sidecar, 20 iterations,
    /// [`DEFAULT_MAX_SIMULATIONS`], the noise estimated, [`DEFAULT_LIMITS`]).
    pub fn new(params: &[&str]) -> Self {
        FitOptions {
            params: params.iter().map(|s| s.to_string()).collect(),
            spacing_s: 0.5,
            dense_logs: DenseLogs::Campaign,
            max_iter: 20,
            max_simulations: DEFAULT_MAX_SIMULATIONS,
            noise_p2_bar: None,
            noise_rpm: None,
            noise_lp_bar: None,
            limits: DEFAULT_LIMITS,
            precision: Vec::new(),
            progress: None,
        }
    }
}

/// The result of a fit.
#[derive(Debug, Clone, Serialize)]
pub struct FitReport {
    /// Whether every check held: the only "success".
    pub passed: bool,
    /// The checks, in order; the failed ones say why.
    pub checks: Vec<Check>,
    /// Parameters.
    pub params: Vec<Fitted>,
    /// Correlation matrix of the parameters (in `params`' order), from the covariance.
    pub correlations: Vec<Vec<f64>>,
    /// Reduced χ² of the P2, speed and LP residuals against the noise.
    pub chi2_reduced: f64,
    /// Lag-1 autocorrelation of the residuals (pooled), and the factor it puts on the σ.
    pub autocorrelation: f64,
    /// Factor on the Jacobian's σ: √(max(1, χ²) · (1 + ρ)/(1 − ρ)).
    pub sigma_scale: f64,
    /// The sensors' noise the residuals are weighted with.
    pub noise: Noise,
    /// How the first stage started.
    pub start: String,
    /// Implausible columns in the logs.
    pub findings: Vec<Finding>,
    /// Weighted residual RMS (noise units) before and after.
    pub residual_rms: (f64, f64),
    /// Before / after.
    pub improvement: f64,
    /// Per log.
    pub logs: Vec<LogFit>,
    /// Simulations run.
    pub simulations: usize,
    /// LM termination (last stage).
    pub termination: String,
    /// Levenberg–Marquardt's own termination was successful (one of the checks).
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

impl FitReport {
    /// The checks, one line each: `ok`/`FAIL`, the check's name, what it found.
    pub fn checks_table(&self) -> String {
        self.checks
            .iter()
            .map(|c| {
                format!(
                    "{:<4} {:<12} {}\n",
                    if c.passed { "ok" } else { "FAIL" },
                    c.name,
                    c.detail
                )
            })
            .collect()
    }
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

/// The HP precharge the logs show: where a discharge empties the accumulator, its gas is back
/// at its precharge volume, so the P2 just before the cliff is the precharge (plus the last
/// second's decay, < 1 bar). The median over the logs that empty; `None` when none does.
pub(super) fn emptying_precharge(logs: &[Prepared]) -> Option<f64> {
    let mut v: Vec<f64> = logs
        .iter()
        .filter_map(|p| {
            let tc = p.collapse?;
            let w: Vec<f64> = p
                .log
                .t
                .iter()
                .zip(&p.log.p2_bar)
                .filter(|(t, _)| (tc - 1.5..=tc - 0.5).contains(*t))
                .map(|(_, y)| *y)
                .collect();
            (!w.is_empty()).then(|| w.iter().sum::<f64>() / w.len() as f64)
        })
        .collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[v.len() / 2])
}

/// Factors on Cd and on the HP volume tried by the coarse stage.
const COARSE_FACTORS: [f64; 5] = [0.7, 0.85, 1.0, 1.15, 1.3];
/// Precharges tried by the coarse stage when no log's emptying gives it, as fractions of the
/// lowest start P2 of the stage's logs.
const COARSE_PRECHARGE: [f64; 5] = [0.2, 0.35, 0.5, 0.65, 0.8];

/// The best grid point for the first stage, and its description, and the simulations run.
fn coarse_start(
    cur: &BenchFile,
    params: &[Param],
    pj: &[usize],
    lk: &[usize],
    logs: &Arc<Vec<Prepared>>,
    precharge_known: bool,
    progress: Option<Tick>,
) -> (Option<(BenchFile, String)>, usize) {
    let sub: Vec<Prepared> = lk.iter().map(|&k| logs[k].clone()).collect();
    // Each axis's values: Cd and the HP volume as factors on the start; the precharge, when no
    // log's emptying gave it, as fractions of the lowest start P2 of the logs that start above
    // the guessed precharge (the gas is compressed there, the precharge lies below), and the
    // guess itself. A log that starts below the guess (a campaign's charge from an empty
    // accumulator, from 10 bar) says nothing of where it lies: with it, the grid was 2–8 bar
    // and a fit started from the true bench ended at χ²ᵣ 315.
    let guess = params
        .iter()
        .find(|p| p.name == "precharge")
        .map(|p| (p.get)(cur));
    let p2_min = sub
        .iter()
        .map(|p| p.p2_start_bar)
        .filter(|p2| guess.is_none_or(|g| *p2 > g))
        .fold(f64::INFINITY, f64::min);
    let axes: Vec<(&Param, Vec<f64>)> = pj
        .iter()
        .map(|&j| &params[j])
        .filter_map(|p| match p.name.as_str() {
            "cd" | "hp_volume" => {
                Some((p, COARSE_FACTORS.iter().map(|k| (p.get)(cur) * k).collect()))
            }
            "precharge" if !precharge_known && p2_min.is_finite() => Some((
                p,
                COARSE_PRECHARGE
                    .iter()
                    .map(|k| k * p2_min)
                    .chain([(p.get)(cur)])
                    .collect(),
            )),
            _ => None,
        })
        .collect();
    if axes.is_empty() {
        return (None, 0);
    }
    let mut points: Vec<Vec<f64>> = vec![Vec::new()];
    for (_, values) in &axes {
        points = points
            .into_iter()
            .flat_map(|p| {
                values.iter().map(move |v| {
                    let mut q = p.clone();
                    q.push(*v);
                    q
                })
            })
            .collect();
    }
    let costs: Vec<(f64, BenchFile)> = points
        .par_iter()
        .filter_map(|vs| {
            let mut f = cur.clone();
            for ((p, _), v) in axes.iter().zip(vs) {
                (p.set)(&mut f, v.clamp(p.lo, p.hi));
            }
            let b = Bench::from_file(f.clone(), "coarse").ok()?;
            let mut r = Vec::new();
            for p in &sub {
                let sim = simulate_log(&b, p).ok();
                if let Some(t) = &progress {
                    t();
                }
                residuals_of(p, &sim?, &mut r);
            }
            Some((r.iter().map(|x| x * x).sum::<f64>(), f))
        })
        .collect();
    let n = points.len() * sub.len();
    let best = costs
        .into_iter()
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, f)| {
            let note = axes
                .iter()
                .map(|(p, _)| format!("{} {:.4}", p.name, (p.get)(&f)))
                .collect::<Vec<_>>()
                .join(", ");
            (f, note)
        });
    (best, n)
}

/// Fits `opts.params` to `logs`, starting from `start`, and judges the result.
pub fn fit(
    start: &BenchFile,
    logs: Vec<BenchLog>,
    opts: &FitOptions,
) -> Result<FitOutcome, FitError> {
    let t0 = std::time::Instant::now();
    let params = params(&opts.params, start)?;
    if let Some((n, _)) = opts
        .precision
        .iter()
        .find(|(n, _)| !params.iter().any(|p| p.name == *n))
    {
        return Err(FitError::PrecisionOf(n.clone()));
    }
    let findings: Vec<Finding> = logs.iter().flat_map(sanity).collect();
    let noise = noise_of(&logs, opts.noise_p2_bar, opts.noise_rpm, opts.noise_lp_bar);
    let mut spacing = Vec::with_capacity(logs.len());
    for l in &logs {
        spacing.push(match opts.dense_logs {
            DenseLogs::None => opts.spacing_s,
            DenseLogs::Campaign => match crate::plan::record::Record::read_for(&l.path)? {
                None => opts.spacing_s,
                Some(r) if r.status == crate::plan::record::Status::Complete => 0.0,
                Some(r) => return Err(FitError::Segment(Box::new(r), l.path.clone())),
            },
        });
    }
    let logs = Arc::new(prepare_each(logs, &spacing, &noise));
    let b0 = Bench::from_file(start.clone(), "start")?;
    let before: Vec<Vec<Truth>> = logs
        .par_iter()
        .map(|p| simulate_log(&b0, p))
        .collect::<Result<_, _>>()?;
    let mut r_before = Vec::new();
    for (p, s) in logs.iter().zip(&before) {
        pointwise_residuals(p, s, &mut r_before);
    }
    // A start that does not hang on the noise: the precharge read off the logged emptying (a
    // level, not a slope), when the precharge is fitted and a log empties the accumulator. The
    // LM from the bench's own value can stop in a valley where the simulated accumulator empties
    // seconds early and the flattened residuals of the gap no longer pull.
    let mut cur = start.clone();
    let mut start_note = "the bench's values".to_string();
    let mut precharge_known = false;
    if let Some(pc) = params.iter().find(|p| p.name == "precharge")
        && let Some(est) = emptying_precharge(&logs)
    {
        let est = est.clamp(pc.lo, pc.hi);
        (pc.set)(&mut cur, est);
        precharge_known = true;
        start_note =
            format!("the bench's values, precharge {est:.2} bar read off the logged emptying");
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
    let mut evals = 0;
    let budget = Arc::new(std::sync::atomic::AtomicIsize::new(
        opts.max_simulations.min(isize::MAX as usize) as isize,
    ));
    // The coarse global stage: the parameters that move the emptying's timing (Cd, the HP
    // volume) on a small grid around the start, each point one simulation of the first stage's
    // logs; the first stage starts from the best point.
    if let Some((pj, lk)) = stages.first() {
        let (best, n) = coarse_start(
            &cur,
            &params,
            pj,
            lk,
            &logs,
            precharge_known,
            opts.progress.clone(),
        );
        evals += n;
        if let Some((f, note)) = best {
            cur = f;
            start_note = format!("{start_note}; {note} from a coarse grid");
        }
    }
    // The optimiser's steps: wide ([`STEP_OF_RANGE`]) where the residuals are smooth, narrow
    // where a log empties the accumulator. Measured both ways: on a planned campaign (no
    // emptying) narrow steps let the solver's noise steer Levenberg–Marquardt to trapped air's
    // bound (0.30 for 0.068), wide ones recovered every value within 1.5σ; on the paper's runs
    // (three discharges to the emptying) wide steps, moving the simulated cliff by more, sent a
    // fit from χ²ᵣ 0.91 to 80.
    let wide_steps = logs.iter().all(|p| p.collapse.is_none());
    let mut termination = String::new();
    let mut converged = false;
    let mut last: Option<Problem> = None;
    let n_stages = stages.len();
    for (stage, (pj, lk)) in stages.into_iter().enumerate() {
        let sub: Vec<Param> = pj.iter().map(|&j| params[j].clone()).collect();
        let sub_logs: Vec<Prepared> = lk.iter().map(|&k| logs[k].clone()).collect();
        let mut z0: Vec<f64> = sub.iter().map(|p| to_z(p, (p.get)(&cur))).collect();
        // The last stage also corrects each log's start P2 (read from noisy first samples, it
        // would otherwise shift the moment the accumulator runs empty by up to a second).
        let offsets = stage + 1 == n_stages;
        if offsets {
            z0.extend(std::iter::repeat_n(0.0, 2 * sub_logs.len()));
        }
        let problem = Problem {
            start: cur.clone(),
            params: sub,
            logs: Arc::new(sub_logs),
            offsets,
            z: DVector::from_vec(z0),
            progress: opts.progress.clone(),
            evals: Default::default(),
            budget: Some(budget.clone()),
            wide_steps,
        };
        let lm = LevenbergMarquardt::<f64>::new()
            .with_patience(opts.max_iter.max(1))
            .with_ftol(1e-5)
            .with_xtol(1e-5);
        let (problem, report) = lm.minimize(problem);
        evals += problem.evals.load(std::sync::atomic::Ordering::Relaxed);
        if budget.load(std::sync::atomic::Ordering::Relaxed) < 0 {
            termination = format!(
                "stopped: the budget of {} simulations ran out (--max-simulations)",
                opts.max_simulations
            );
            converged = false;
            // Reported at this stage's start (a point that was evaluated; LM leaves its refused
            // trial in `problem`), over every parameter and log, so the report below has the
            // full problem's shape whichever stage ran out.
            let mut z: Vec<f64> = params.iter().map(|p| to_z(p, (p.get)(&cur))).collect();
            z.extend(std::iter::repeat_n(0.0, 2 * logs.len()));
            last = Some(Problem {
                start: cur.clone(),
                params: params.clone(),
                logs: logs.clone(),
                offsets: true,
                z: DVector::from_vec(z),
                progress: opts.progress.clone(),
                evals: Default::default(),
                budget: None,
                wide_steps: false,
            });
            break;
        }
        termination = format!("{:?}", report.termination);
        converged = report.termination.was_successful();
        let z: Vec<f64> = problem.z.iter().copied().collect();
        for (p, &zi) in problem.params.iter().zip(&z) {
            (p.set)(&mut cur, from_z(p, zi));
        }
        last = Some(problem);
    }
    let problem = last.ok_or(FitError::NoStage)?;
    let z: Vec<f64> = problem.z.iter().copied().collect();
    let fitted_bench = problem.bench_at(&z)?;
    let corrections = problem.offsets_of(&z);
    let after: Vec<Vec<Truth>> = logs
        .par_iter()
        .zip(&corrections)
        .map(|(p, off)| simulate_log_from(&fitted_bench, p, *off))
        .collect::<Result<_, _>>()?;
    // Goodness of fit and the residuals' autocorrelation, from the raw (not flattened) P2 and
    // speed residuals in units of the noise.
    let n = z.len();
    let mut r_after = Vec::new();
    let (mut lag_num, mut lag_den) = (0.0, 0.0);
    let mut chi2_log = Vec::new();
    for (p, s) in logs.iter().zip(&after) {
        let from = r_after.len();
        pointwise_residuals(p, s, &mut r_after);
        let r = &r_after[from..];
        // Interleaved (P2, speed, LP): each channel's sequence at lag 1.
        for ch in 0..CHANNELS {
            let seq: Vec<f64> = r.iter().skip(ch).step_by(CHANNELS).copied().collect();
            lag_num += seq.windows(2).map(|w| w[0] * w[1]).sum::<f64>();
            lag_den += seq.iter().map(|x| x * x).sum::<f64>();
        }
        chi2_log.push(r.iter().map(|x| x * x).sum::<f64>() / r.len().max(1) as f64);
    }
    let m = r_after.len();
    let chi2_reduced =
        r_after.iter().map(|x| x * x).sum::<f64>() / m.saturating_sub(n).max(1) as f64;
    let rho = if lag_den > 0.0 {
        (lag_num / lag_den).clamp(0.0, 0.98)
    } else {
        0.0
    };
    // σ: the Jacobian's (JᵀJ)⁻¹ is the covariance for residuals of unit variance and no
    // correlation. Scaled by the reduced χ² when the fit is worse than the noise (the model's
    // own error) and by the effective sample size of AR(1)-correlated residuals, n(1 − ρ)/(1 + ρ):
    // model error is smooth in time, so neighbouring residuals do not count twice.
    let sigma_scale = (chi2_reduced.max(1.0) * (1.0 + rho) / (1.0 - rho)).sqrt();
    // The Jacobian for the covariance leaves out the samples within 1 s of a simulated
    // emptying that comes before the logged one: on the cliff a residual's derivative is that of
    // a step, and one such sample made a σ hundreds of times smaller than the error.
    let cov_logs: Vec<Prepared> = problem
        .logs
        .iter()
        .zip(&after)
        .map(|(p, a)| {
            let mut p = p.clone();
            if let Some(ts) = simulated_collapse(&p, a) {
                let log_t = &p.log.t;
                p.idx.retain(|&i| log_t[i] < ts - 1.0);
            }
            p
        })
        .collect();
    let mut cov_problem = problem.over(cov_logs);
    cov_problem.wide_steps = true;
    let jac = cov_problem.jacobian().ok_or(FitError::Jacobian)?;
    evals += cov_problem.evals.load(std::sync::atomic::Ordering::Relaxed);
    let jtj = jac.transpose() * &jac;
    let svd = jtj.clone().svd(true, true);
    let smax = svd.singular_values.max();
    let pinv = svd
        .pseudo_inverse(smax * 1e-10)
        .map_err(FitError::Covariance)?;
    let mut fitted = start.clone();
    let mut out = Vec::new();
    let np = params.len();
    let mut determined = vec![false; np];
    for (j, p) in params.iter().enumerate() {
        let value = from_z(p, z[j]);
        (p.set)(&mut fitted, value);
        let var = pinv[(j, j)];
        determined[j] = jtj[(j, j)] > smax * 1e-10 && var.is_finite() && var > 0.0;
        out.push(Fitted {
            name: p.name.clone(),
            key: p.key.clone(),
            unit: p.unit.clone(),
            start: (p.get)(start),
            value,
            sigma: determined[j].then(|| sigma_scale * var.sqrt() * dx_dz(p, z[j])),
            bounds: (p.lo, p.hi),
            needed: p.needed_at(value, &opts.precision),
        });
    }
    let correlations: Vec<Vec<f64>> = (0..np)
        .map(|i| {
            (0..np)
                .map(|j| {
                    if i == j {
                        1.0
                    } else if determined[i] && determined[j] {
                        pinv[(i, j)] / (pinv[(i, i)] * pinv[(j, j)]).sqrt()
                    } else {
                        0.0
                    }
                })
                .collect()
        })
        .collect();
    let per_log: Vec<LogFit> = logs
        .iter()
        .zip(before.iter().zip(&after))
        .zip(corrections.iter().zip(&chi2_log))
        .map(|((p, (b, a)), (c, chi2))| {
            let (pb, rb) = log_rms(p, b);
            let (pa, ra) = log_rms(p, a);
            LogFit {
                name: p.log.name(),
                p2_rms_bar: (pb, pa),
                rpm_rms: (rb, ra),
                chi2: *chi2,
                start_p2_bar: (p.p2_start_bar, p.p2_start_bar + c[0]),
                start_lp_bar: (p.lp_start_bar, p.lp_start_bar + c[1]),
                emptying_s: Emptying {
                    logged: p.collapse.map(|t| t - p.log.t[0]),
                    simulated: simulated_collapse(p, a).map(|t| t - p.log.t[0]),
                },
            }
        })
        .collect();
    let bounds: Vec<(f64, f64)> = params.iter().map(|p| (p.lo, p.hi)).collect();
    let checks = verdict(
        &Evidence {
            termination: &termination,
            converged,
            chi2_reduced,
            noise: &noise,
            params: &out,
            bounds: &bounds,
            correlations: &correlations,
            logs: &per_log,
            findings: &findings,
        },
        &opts.limits,
    );
    let (rb, ra) = (rms(&r_before), rms(&r_after));
    Ok(FitOutcome {
        report: FitReport {
            passed: checks.iter().all(|c| c.passed),
            checks,
            params: out,
            correlations,
            chi2_reduced,
            autocorrelation: rho,
            sigma_scale,
            noise,
            start: start_note,
            findings,
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
