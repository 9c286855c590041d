//! The matrix file: its schema, its expansion into runs (each a [`RunSpec`]), and their
//! checks, every problem named with the file, the field and the run.

use super::axis::{Axis, heatmap_axes};
use super::expand::{describe, point_of};
use super::key::RunKey;
use super::run;
use super::spec::{ControllerSpec, RunSpec, trace_digest};
use crate::sim::bench::{Bench, BenchError, OverrideError, apply_override, set_value};
use crate::sim::scenario::{Scenario, resolve};
use crate::sim::solver::SolverOptions;
use rayon::prelude::*;
use serde::Deserialize;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The most runs a matrix may expand to.
pub const MAX_RUNS: usize = 10_000_000;
/// The most problems a refused matrix lists (then how many more).
const MAX_PROBLEMS: usize = 20;
/// Why a matrix was refused: every problem, each named with the matrix file.
#[derive(Debug, Clone, PartialEq)]
pub struct MatrixError {
    /// The matrix file.
    pub file: String,
    /// What is wrong, each naming the axis, the run, the value and the allowed range.
    pub problems: Vec<String>,
}

impl std::fmt::Display for MatrixError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (i, p) in self.problems.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{}: {p}", self.file)?;
        }
        Ok(())
    }
}

impl std::error::Error for MatrixError {}

/// The matrix as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MatrixFile {
    name: Option<String>,
    scenario: toml::Value,
    bench: Option<PathBuf>,
    rtol: Option<f64>,
    #[serde(default)]
    set: toml::Table,
    #[serde(default)]
    axis: Vec<AxisFile>,
    heatmap: Option<Vec<String>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct AxisFile {
    field: Option<String>,
    fields: Option<Vec<String>>,
    values: Vec<toml::Value>,
}

/// A design matrix: a base bench and scenario, fixed settings and axes.
#[derive(Debug, Clone)]
pub struct Matrix {
    /// The matrix file, for messages.
    pub source: String,
    /// Its name (the file's stem unless it says).
    pub name: String,
    /// The bench every run starts from.
    pub bench: Bench,
    /// The scenario every run starts from.
    pub scenario: Scenario,
    /// Where the scenario's relative files are.
    pub scenario_dir: PathBuf,
    /// Settings of every run: (field, value), applied before the axes.
    pub set: Vec<(String, toml::Value)>,
    /// The axes, the first varying slowest.
    pub axes: Vec<Axis>,
    /// The two axes of the heat maps, by index into `axes`, if the file names them.
    pub heatmap: Option<(usize, usize)>,
    /// Solver settings.
    pub solver: SolverOptions,
}

/// The roots a field may start with.
const ROOTS: [&str; 3] = ["bench", "scenario", "controller"];

impl Matrix {
    /// Loads a matrix file; `bench` (`--bench`) replaces the bench the file names.
    pub fn load(path: &Path, bench: Option<&PathBuf>) -> Result<Matrix, MatrixError> {
        let file = path.display().to_string();
        let refuse = |p: String| MatrixError {
            file: file.clone(),
            problems: vec![p],
        };
        let text =
            std::fs::read_to_string(path).map_err(|e| refuse(format!("cannot read: {e}")))?;
        let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Matrix::parse(&text, &file, &dir, bench)
    }

    /// Parses matrix text; `file` names it in messages, `dir` resolves its relative paths.
    pub fn parse(
        text: &str,
        file: &str,
        dir: &Path,
        bench: Option<&PathBuf>,
    ) -> Result<Matrix, MatrixError> {
        let refuse = |p: String| MatrixError {
            file: file.into(),
            problems: vec![p],
        };
        let m: MatrixFile =
            toml::from_str(text).map_err(|e| refuse(e.to_string().trim_end().to_string()))?;
        let bench_path = bench.cloned().or_else(|| m.bench.map(|b| dir.join(b)));
        let bench = Bench::load_or_reference(bench_path.as_ref())
            .map_err(|e| refuse(format!("bench: {e}")))?;
        let (scenario, scenario_dir) = match m.scenario {
            // A built-in's (or an inline table's) relative files, such as a trace the matrix
            // sets, are the matrix's; a scenario file's are its own.
            toml::Value::String(s) => match crate::sim::scenario::builtin_named(&s) {
                Some(sc) => (sc, dir.to_path_buf()),
                None => resolve(&dir.join(&s).display().to_string())
                    .map_err(|e| refuse(format!("scenario: {e}")))?,
            },
            v @ toml::Value::Table(_) => (
                v.try_into::<Scenario>()
                    .map_err(|e| refuse(format!("scenario: {}", e.to_string().trim_end())))?,
                dir.to_path_buf(),
            ),
            other => {
                return Err(refuse(format!(
                    "scenario: {other} is neither a scenario's name or file nor a table"
                )));
            }
        };
        let rtol = m.rtol.unwrap_or(SolverOptions::default().rtol);
        if !(rtol.is_finite() && (1e-12..=1e-2).contains(&rtol)) {
            return Err(refuse(format!("rtol: {rtol} outside [1e-12, 1e-2]")));
        }
        let mut problems = Vec::new();
        let mut axes = Vec::new();
        for (i, a) in m.axis.into_iter().enumerate() {
            match axis_of(a) {
                Ok(a) => axes.push(a),
                Err(p) => problems.push(format!("axis {}: {p}", i + 1)),
            }
        }
        let set: Vec<(String, toml::Value)> = m.set.into_iter().collect();
        let mut seen: Vec<&str> = Vec::new();
        for f in set.iter().map(|(f, _)| f.as_str()).chain(
            axes.iter()
                .flat_map(|a| a.fields.iter().map(String::as_str)),
        ) {
            if seen.contains(&f) {
                problems.push(format!("{f}: set twice (in [set] or the axes)"));
            }
            seen.push(f);
            let root = f.split('.').next().unwrap_or_default();
            if !ROOTS.contains(&root) || !f.contains('.') {
                problems.push(format!(
                    "{f}: a field starts with bench., scenario. or controller. \
                     (e.g. bench.hp_accumulator.volume_l, scenario.valve.aperture_pct, \
                     controller.mode)"
                ));
            }
        }
        let heatmap = match m.heatmap {
            None => None,
            Some(h) => match heatmap_axes(&axes, &h) {
                Ok(x) => Some(x),
                Err(p) => {
                    problems.push(p);
                    None
                }
            },
        };
        if !problems.is_empty() {
            return Err(MatrixError {
                file: file.into(),
                problems,
            });
        }
        let runs = axes
            .iter()
            .try_fold(1usize, |n, a| n.checked_mul(a.values.len()))
            .filter(|n| *n <= MAX_RUNS);
        if runs.is_none() {
            return Err(refuse(format!(
                "the axes make more than {MAX_RUNS} runs: split the matrix"
            )));
        }
        let name = m.name.unwrap_or_else(|| {
            Path::new(file)
                .file_stem()
                .map_or("sweep".into(), |s| s.to_string_lossy().into_owned())
        });
        Ok(Matrix {
            source: file.into(),
            name,
            bench,
            scenario,
            scenario_dir,
            set,
            axes,
            heatmap,
            solver: SolverOptions {
                rtol,
                ..SolverOptions::default()
            },
        })
    }

    /// Number of runs: the product of the axes' lengths.
    pub fn len(&self) -> usize {
        self.axes.iter().map(|a| a.values.len()).product()
    }

    /// Never: a matrix has at least one run (no axes: the base run alone).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Run `index`'s value index on each axis (the last axis varies fastest).
    pub fn point(&self, index: usize) -> Vec<usize> {
        point_of(&self.axes, index)
    }

    /// Run `index`'s axis values as `field = value, …`, for messages.
    pub fn describe(&self, index: usize) -> String {
        describe(&self.axes, index)
    }

    /// Builds run `index`: the base bench and scenario with `[set]` and the run's axis values.
    /// Errors name the field and the value, and why (an unknown field lists the fields there).
    pub fn spec(&self, index: usize) -> Result<RunSpec, String> {
        let mut file = self.bench.file.clone();
        let mut scenario = toml::Value::try_from(&self.scenario)
            .map_err(|e| format!("scenario: cannot serialise: {e}"))?;
        let mut controller = toml::Value::try_from(ControllerSpec::default())
            .map_err(|e| format!("controller: cannot serialise: {e}"))?;
        let p = self.point(index);
        let axis_values = self
            .axes
            .iter()
            .zip(&p)
            .flat_map(|(a, &v)| a.fields.iter().zip(&a.values[v]));
        let shortcuts = crate::fit::set_shortcuts();
        for (field, value) in self.set.iter().map(|(f, v)| (f, v)).chain(axis_values) {
            let (root, rest) = field.split_once('.').unwrap_or((field, ""));
            match root {
                "bench" => apply_override(&mut file, &format!("{rest}={value}"), &shortcuts)
                    .map_err(|e| override_text(&e))?,
                "scenario" => set_value(&mut scenario, rest, value.clone(), true)
                    .map_err(|e| format!("scenario.{e}"))?,
                _ => set_value(&mut controller, rest, value.clone(), true)
                    .map_err(|e| format!("controller.{e}"))?,
            }
        }
        let bench = Bench::from_file(file, "bench").map_err(|e| bench_text(&e))?;
        let scenario: Scenario = scenario
            .try_into()
            .map_err(|e: toml::de::Error| format!("scenario: {}", e.to_string().trim_end()))?;
        let controller: ControllerSpec = controller
            .try_into()
            .map_err(|e: toml::de::Error| format!("controller: {}", e.to_string().trim_end()))?;
        Ok(RunSpec {
            bench,
            scenario,
            scenario_dir: self.scenario_dir.clone(),
            controller,
            solver: self.solver,
        })
    }

    /// Every run's key, in run order: each run is built (its fields exist, its values have
    /// their fields' types, its bench is inside every range, its controller mode is known) and
    /// no two are the same run. Quick (no run is prepared): [`Matrix::check`] does the rest.
    pub fn keys(&self) -> Result<Vec<RunKey>, MatrixError> {
        let digests = std::sync::Mutex::new(HashMap::<PathBuf, String>::new());
        let digest = |path: &Path| {
            let mut known = digests
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            known
                .entry(path.to_path_buf())
                .or_insert_with(|| trace_digest(path))
                .clone()
        };
        let built: Vec<Result<RunKey, String>> = (0..self.len())
            .into_par_iter()
            .map(|i| {
                let spec = self.spec(i)?;
                spec.controller.scheduler_mode()?;
                Ok(spec.key_with(&digest))
            })
            .collect();
        let keys = self.refusals(built.into_iter().enumerate())?;
        let mut problems = Vec::new();
        let mut first = HashMap::new();
        for (i, k) in keys.iter().enumerate() {
            if let Some(j) = first.insert(*k, i) {
                problems.push(format!(
                    "run {} ({}) is run {} ({}) again: the same bench, scenario and controller",
                    i + 1,
                    self.describe(i),
                    j + 1,
                    self.describe(j)
                ));
                if problems.len() >= MAX_PROBLEMS {
                    break;
                }
            }
        }
        self.unless(problems, keys)
    }

    /// Checks that runs `indices` can start, on all cores: each run's scenario prepares on its
    /// bench (ranges, the rods' strokes over the whole motion, the accumulators' precharges)
    /// and its controller takes the bench.
    pub fn check(&self, indices: &[usize]) -> Result<(), MatrixError> {
        let checked: Vec<(usize, Result<(), String>)> = indices
            .par_iter()
            .map(|&i| (i, self.spec(i).and_then(|s| run::check(&s))))
            .collect();
        self.refusals(checked.into_iter()).map(|_| ())
    }

    /// [`Matrix::keys`], then [`Matrix::check`] of every run.
    pub fn plan(&self) -> Result<Vec<RunKey>, MatrixError> {
        let keys = self.keys()?;
        self.check(&(0..self.len()).collect::<Vec<_>>())?;
        Ok(keys)
    }

    /// The results of runs, or a refusal listing the runs that fail (the first
    /// [`MAX_PROBLEMS`]) with their values.
    fn refusals<T>(
        &self,
        results: impl Iterator<Item = (usize, Result<T, String>)>,
    ) -> Result<Vec<T>, MatrixError> {
        // Runs refused for the same reason (one bad axis value refuses a whole slice of the
        // matrix) are one problem: the reason, the runs, the first run's values.
        let mut why: Vec<(String, Vec<usize>)> = Vec::new();
        let mut ok = Vec::new();
        for (i, r) in results {
            match r {
                Ok(t) => ok.push(t),
                Err(e) => match why.iter_mut().find(|(w, _)| *w == e) {
                    Some((_, runs)) => runs.push(i),
                    None => why.push((e, vec![i])),
                },
            }
        }
        let n = self.len();
        let mut problems: Vec<String> = why
            .iter()
            .take(MAX_PROBLEMS)
            .map(|(e, runs)| match runs.as_slice() {
                [i] => format!("run {} of {n} ({}): {e}", i + 1, self.describe(*i)),
                [first, ..] => {
                    let mut list: Vec<String> =
                        runs.iter().take(8).map(|i| (i + 1).to_string()).collect();
                    if runs.len() > 8 {
                        list.push(format!("… ({} runs)", runs.len()));
                    }
                    format!(
                        "runs {} of {n} (run {}: {}): {e}",
                        list.join(", "),
                        first + 1,
                        self.describe(*first)
                    )
                }
                [] => String::new(),
            })
            .collect();
        if why.len() > MAX_PROBLEMS {
            let more: usize = why[MAX_PROBLEMS..].iter().map(|(_, r)| r.len()).sum();
            problems.push(format!("… and {more} more runs refused for other reasons"));
        }
        self.unless(problems, ok)
    }

    /// `ok`, unless there are problems.
    fn unless<T>(&self, problems: Vec<String>, ok: T) -> Result<T, MatrixError> {
        if problems.is_empty() {
            Ok(ok)
        } else {
            Err(MatrixError {
                file: self.source.clone(),
                problems,
            })
        }
    }
}

fn axis_of(a: AxisFile) -> Result<Axis, String> {
    let fields = match (a.field, a.fields) {
        (Some(f), None) => vec![f],
        (None, Some(fs)) if !fs.is_empty() => fs,
        (None, None) | (None, Some(_)) => {
            return Err("needs `field = \"…\"` or `fields = [\"…\", …]`".into());
        }
        (Some(_), Some(_)) => return Err("has both `field` and `fields`: give one".into()),
    };
    let name = fields.join(", ");
    if a.values.is_empty() {
        return Err(format!("{name}: `values` is empty"));
    }
    let values = if fields.len() == 1 {
        a.values.into_iter().map(|v| vec![v]).collect()
    } else {
        let mut out = Vec::new();
        for (i, v) in a.values.into_iter().enumerate() {
            match v {
                toml::Value::Array(t) if t.len() == fields.len() => out.push(t),
                other => {
                    return Err(format!(
                        "{name}: values[{i}] = {other}: want a list of {} values, one per field",
                        fields.len()
                    ));
                }
            }
        }
        out
    };
    Ok(Axis { fields, values })
}

/// An override's error as `bench.field: …` (the CLI's `--set` wording left out).
fn override_text(e: &OverrideError) -> String {
    match e {
        OverrideError::Syntax { kv } => format!("bench: `{kv}` is not field=value"),
        OverrideError::Field(e) => format!("bench.{e}"),
        OverrideError::FieldOrShortcut { error, shortcuts } => {
            format!("bench.{error} (or a parameter: {})", shortcuts.join(", "))
        }
    }
}

/// A bench error as `bench.field: value outside [min, max] (unit)`, one line per field.
fn bench_text(e: &BenchError) -> String {
    match e {
        BenchError::Invalid { errors, .. } => errors
            .iter()
            .map(|f| format!("bench.{}: {}", f.field, f.message))
            .collect::<Vec<_>>()
            .join("; "),
        other => format!("bench: {other}"),
    }
}
