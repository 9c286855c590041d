//! A run's full specification (bench, scenario, controller, solver) and its key: everything
//! that makes its figures.

use super::key::{RunKey, fnv1a};
use crate::sim::bench::Bench;
use crate::sim::scenario::Scenario;
use crate::sim::solver::SolverOptions;
use crate::validation::closed_loop::{MODES, parse_mode};
use pto_model::scheduler::Mode;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Bumped when a run's figures change meaning: rows of an older format are run again.
pub const ROW_FORMAT: u32 = 3;

/// How the valve is driven in a run: the scenario's schedule, or the fixed-point controller
/// (`pto-model`'s estimator and scheduler, through `sim::schedule::ValveController`) in a mode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerSpec {
    /// `scenario`, `fixed`, `hold-pressure`, `hold-speed` or `max-autonomy`.
    #[serde(default = "scenario_mode")]
    pub mode: String,
    /// The mode's setpoint: % (`fixed`), bar (`hold-pressure`), rpm (the speed modes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub setpoint: Option<f64>,
    /// Seed of the controller's sensor noise.
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// The controller's step, 2^−dt_log2 s (6..=12; default the bench's model configuration,
    /// 10: 1024 Hz, as the firmware; 8 runs about three times faster).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dt_log2: Option<u8>,
}

fn scenario_mode() -> String {
    SCENARIO_MODE.into()
}
fn default_seed() -> u64 {
    7
}

/// [`ControllerSpec::mode`] of a run whose valve follows the scenario's schedule.
pub const SCENARIO_MODE: &str = "scenario";

impl Default for ControllerSpec {
    fn default() -> Self {
        ControllerSpec {
            mode: scenario_mode(),
            setpoint: None,
            seed: default_seed(),
            dt_log2: None,
        }
    }
}

impl ControllerSpec {
    /// The scheduler mode, or `None` for the scenario's own schedule.
    pub fn scheduler_mode(&self) -> Result<Option<Mode>, String> {
        match (self.mode.as_str(), self.setpoint) {
            (SCENARIO_MODE, None) => Ok(None),
            (SCENARIO_MODE, Some(v)) => Err(format!(
                "controller.setpoint = {v}: controller.mode `scenario` (the scenario's own valve \
                 schedule) takes no setpoint; set controller.mode to one of {MODES}"
            )),
            (m, None) => Err(format!(
                "controller.setpoint: missing: controller.mode `{m}` needs one (modes: {MODES})"
            )),
            (m, Some(v)) => parse_mode(m, v)
                .map(Some)
                .map_err(|e| format!("controller: {e} (or `scenario`)")),
        }
    }
}

/// Everything one run needs: the bench, the scenario and the valve's driver.
#[derive(Debug, Clone)]
pub struct RunSpec {
    /// The bench with the run's values.
    pub bench: Bench,
    /// The scenario with the run's values.
    pub scenario: Scenario,
    /// Where the scenario's relative files are.
    pub scenario_dir: PathBuf,
    /// How the valve is driven.
    pub controller: ControllerSpec,
    /// Solver settings.
    pub solver: SolverOptions,
}

impl RunSpec {
    /// The run's identity: a hash of everything that decides its result (the bench file, the
    /// scenario, the controller, the solver tolerance, [`ROW_FORMAT`] and `pto`'s version),
    /// however the matrix wrote it. A rerun skips a run whose key has a row.
    pub fn key(&self) -> RunKey {
        self.key_with(&trace_digest)
    }

    /// [`RunSpec::key`], the recorded motion's part given by `digest` (of the trace's path):
    /// [`Matrix::keys`] reads a trace once for all the runs that share it.
    pub(crate) fn key_with(&self, digest: &(dyn Fn(&Path) -> String + Sync)) -> RunKey {
        // A recorded motion's content decides the run, not where its file is or how the
        // matrix's path was typed (the folder was in the key: a rerun from another working
        // directory made every run again, and an edited trace made none).
        let trace = match &self.scenario.motion {
            crate::sim::motion::MotionSpec::Trace { file } => digest(&self.scenario_dir.join(file)),
            _ => String::new(),
        };
        let text = format!(
            "{ROW_FORMAT} {}\n{}\n{}\n{}\n{}\n{:e} {:e}",
            env!("CARGO_PKG_VERSION"),
            toml::to_string(&self.bench.file).unwrap_or_default(),
            toml::to_string(&self.scenario).unwrap_or_default(),
            trace,
            serde_json::to_string(&self.controller).unwrap_or_default(),
            self.solver.rtol,
            self.solver.atol_scale
        );
        RunKey(fnv1a(text.as_bytes()))
    }
}

/// A recorded motion's part of a run's key: the hash of the trace file's content, or why it
/// cannot be read.
pub(crate) fn trace_digest(path: &Path) -> String {
    match std::fs::read(path) {
        Ok(bytes) => format!("trace {:016x}", fnv1a(&bytes)),
        Err(e) => format!("trace unreadable: {e}"),
    }
}
