//! One run of a sweep: its scenario on its bench, the valve driven by the scenario's schedule or
//! by the fixed-point controller, and the figures that make its row.

use super::key::RunKey;
use super::spec::RunSpec;
use crate::sim::bench::{BAR, RPM};
use crate::sim::scenario::Prepared;
use crate::sim::schedule::ValveSchedule;
use crate::sim::solver::{self, Run, SimResult};
use crate::validation::closed_loop::ModelController;
use crate::validation::{controller_config, duty_mask, model_config};
use pto_model::scheduler::Mode;
use serde::{Deserialize, Serialize};

/// Balance target of a run (as `pto simulate`'s): a run that misses it is flagged
/// ([`Status::Balance`]).
pub const BALANCE_REL: f64 = crate::paper::tol::BALANCE_REL;

/// A finished run's figures. Pressure and speed statistics are over the run's output samples
/// (a uniform grid); powers are means over the whole run from the energy balance's own terms
/// (`sim::power::Power`, the run's `power`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Figures {
    /// Simulated time, s.
    pub simulated_s: f64,
    /// Solver steps.
    pub steps: u64,
    /// Smallest P2, bar.
    pub p2_min_bar: f64,
    /// Mean P2, bar.
    pub p2_mean_bar: f64,
    /// Largest P2, bar.
    pub p2_max_bar: f64,
    /// Time with P2 at or above the relief valve's setting (where it starts to open), s.
    pub time_at_relief_s: f64,
    /// Smallest LP, bar.
    pub lp_min_bar: f64,
    /// Largest LP, bar.
    pub lp_max_bar: f64,
    /// Mean motor speed, rpm.
    pub motor_speed_mean_rpm: f64,
    /// Largest motor speed, rpm.
    pub motor_speed_max_rpm: f64,
    /// Standard deviation of the motor speed, rpm.
    pub motor_speed_std_rpm: f64,
    /// Mean mechanical power into the cylinders at the shaft, W.
    pub input_power_w: f64,
    /// Mean hydraulic power pumped into HP (exergy delivered into HP minus that drawn from
    /// LP), W.
    pub pumped_power_w: f64,
    /// Mean power at the motor's shaft, W.
    pub motor_shaft_power_w: f64,
    /// Mean power into the generator load, W.
    pub generator_power_w: f64,
    /// Generator power over the power supplied (shaft input plus what the run drew from
    /// storage), % (none when nothing was supplied).
    pub efficiency_pct: Option<f64>,
    /// (Generator power + what the run stored) over the power supplied, %: the share not
    /// dissipated (none when nothing was supplied).
    #[serde(default)]
    pub efficiency_with_storage_pct: Option<f64>,
    /// Mean dissipation, all causes, W.
    pub losses_w: f64,
    /// Mean dissipation in the relief valve, W.
    pub relief_loss_w: f64,
    /// Mean rate of change of the stored energy (accumulators, oil, inertia, stops), W.
    pub stored_w: f64,
    /// Worst relative error of the run's oil and energy balances.
    pub balance_worst_rel: f64,
}

/// What became of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    /// Finished, its balances within [`BALANCE_REL`].
    Ok,
    /// Finished, but a balance missed [`BALANCE_REL`]: its figures are less certain.
    Balance,
    /// It failed: the row's `error` says why.
    Failed,
}

impl Status {
    /// `ok`, `balance` or `failed`.
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Ok => "ok",
            Status::Balance => "balance",
            Status::Failed => "failed",
        }
    }
}

/// A finished run as stored (one line of `runs.jsonl`): its key, its figures or its error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Row {
    /// The run's identity.
    pub key: RunKey,
    /// What became of it.
    pub status: Status,
    /// Its figures (`None` when it failed).
    pub figures: Option<Figures>,
    /// Why it failed.
    pub error: Option<String>,
    /// Wall time of the run, s.
    pub wall_s: f64,
}

/// Checks that a run can start: its scenario prepares on its bench and, when the fixed-point
/// controller drives the valve, the controller takes the bench and the mode.
pub fn check(spec: &RunSpec) -> Result<(), String> {
    let prep = prepare(spec)?;
    if let Some(mode) = spec.controller.scheduler_mode()? {
        controller(spec, &prep, mode)?;
    }
    Ok(())
}

fn prepare(spec: &RunSpec) -> Result<Prepared, String> {
    spec.scenario
        .prepare(&spec.bench, &spec.scenario_dir)
        .map_err(|e| {
            // The field as the matrix names it: under `bench.` when it is the bench's (the
            // scenario checks the accumulators' precharges against it), else `scenario.`.
            let section = e.field.split(['.', '[']).next().unwrap_or_default();
            let has = |v: Result<toml::Value, _>| v.is_ok_and(|v| v.get(section).is_some());
            let of_bench = has(toml::Value::try_from(&spec.bench.file))
                && !has(toml::Value::try_from(&spec.scenario));
            let root = if of_bench { "bench" } else { "scenario" };
            format!("{root}.{}: {}", e.field, e.message)
        })
}

fn controller(spec: &RunSpec, prep: &Prepared, mode: Mode) -> Result<ModelController, String> {
    let err =
        |e: &(dyn std::error::Error + 'static)| format!("controller: {}", crate::error_chain(e));
    let mut mcfg = model_config(&spec.bench).map_err(|e| err(&e))?;
    if let Some(d) = spec.controller.dt_log2 {
        mcfg.dt_log2 = d;
    }
    let (sched, _) = controller_config(&spec.bench);
    let c = ModelController::new(
        &mcfg,
        &sched,
        mode,
        prep.initial.p2_pa / BAR,
        prep.initial.lp_pa / BAR,
        duty_mask(&prep.on_duty),
        u8::try_from(prep.config).map_err(|_| "controller: configuration index over 255")?,
        spec.controller.seed,
    )
    .map_err(|e| err(&e))?;
    Ok(c.without_log())
}

/// Runs `spec` and makes its row; a run that fails (or panics) makes a failure row.
pub fn run(spec: &RunSpec, key: RunKey) -> Row {
    let start = std::time::Instant::now();
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| simulate(spec)))
        .unwrap_or_else(|p| {
            let what = p
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| p.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            Err(format!("the run panicked: {what}"))
        })
        .and_then(|res| figures(spec, &res));
    let wall_s = start.elapsed().as_secs_f64();
    match outcome {
        Ok(f) => Row {
            key,
            status: if f.balance_worst_rel <= BALANCE_REL {
                Status::Ok
            } else {
                Status::Balance
            },
            figures: Some(f),
            error: None,
            wall_s,
        },
        Err(e) => Row {
            key,
            status: Status::Failed,
            figures: None,
            error: Some(e),
            wall_s,
        },
    }
}

fn simulate(spec: &RunSpec) -> Result<SimResult, String> {
    let prep = prepare(spec)?;
    let res = match spec.controller.scheduler_mode()? {
        None => prep.run(spec.solver, None),
        Some(mode) => solver::simulate(Run {
            plant: &prep.plant,
            valve: ValveSchedule::Controller(Box::new(controller(spec, &prep, mode)?)),
            initial: prep.initial,
            duration: prep.scenario.duration_s,
            sample_dt: prep.scenario.sample_interval_s,
            solver: spec.solver,
            progress: None,
        }),
    };
    res.map_err(|e| crate::error_chain(&e))
}

/// The figures of a finished run (an error if any is not finite: a row holds numbers only).
pub fn figures(spec: &RunSpec, res: &SimResult) -> Result<Figures, String> {
    let t = &res.trace;
    if t.len() < 2 {
        return Err(format!("the run recorded {} samples", t.len()));
    }
    let (p2_min, p2_mean, p2_max, _) = stats(&t.p2_pa);
    let (lp_min, _, lp_max, _) = stats(&t.lp_pa);
    let (_, w_mean, w_max, w_std) = stats(&t.omega_rad_s);
    let relief = spec.bench.relief_setting_pa;
    let time_at_relief_s = t
        .t_s
        .windows(2)
        .zip(&t.p2_pa)
        .filter(|(_, p)| **p >= relief)
        .map(|(w, _)| w[1] - w[0])
        .fold(0.0, |a, b| a + b);
    let power = &res.power;
    let f = Figures {
        simulated_s: t.t_s[t.len() - 1],
        steps: res.stats.steps as u64,
        p2_min_bar: p2_min / BAR,
        p2_mean_bar: p2_mean / BAR,
        p2_max_bar: p2_max / BAR,
        time_at_relief_s,
        lp_min_bar: lp_min / BAR,
        lp_max_bar: lp_max / BAR,
        motor_speed_mean_rpm: w_mean * RPM,
        motor_speed_max_rpm: w_max * RPM,
        motor_speed_std_rpm: w_std * RPM,
        input_power_w: power.input_w,
        pumped_power_w: power.pumped_w,
        motor_shaft_power_w: power.motor_shaft_w,
        generator_power_w: power.generator_w,
        efficiency_pct: power.efficiency.map(|e| e * 100.0),
        efficiency_with_storage_pct: power.efficiency_with_storage.map(|e| e * 100.0),
        losses_w: power.losses.total_w(),
        relief_loss_w: power.losses.relief_w,
        stored_w: power.stored_w.total_w(),
        balance_worst_rel: res.balance.worst(),
    };
    let all = [
        f.p2_min_bar,
        f.p2_mean_bar,
        f.p2_max_bar,
        f.lp_min_bar,
        f.lp_max_bar,
        f.motor_speed_mean_rpm,
        f.motor_speed_max_rpm,
        f.motor_speed_std_rpm,
        f.balance_worst_rel,
        f.input_power_w,
        f.pumped_power_w,
        f.motor_shaft_power_w,
        f.generator_power_w,
        f.losses_w,
        f.relief_loss_w,
        f.stored_w,
    ];
    if all
        .iter()
        .chain(&f.efficiency_pct)
        .chain(&f.efficiency_with_storage_pct)
        .all(|x| x.is_finite())
    {
        Ok(f)
    } else {
        Err(format!("a figure of the run is not finite: {f:?}"))
    }
}

/// (min, mean, max, standard deviation) of samples.
fn stats(x: &[f64]) -> (f64, f64, f64, f64) {
    let n = x.len().max(1) as f64;
    let mean = x.iter().sum::<f64>() / n;
    let var = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    let (lo, hi) = x
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(*v), hi.max(*v))
        });
    (lo, mean, hi, var.sqrt())
}
