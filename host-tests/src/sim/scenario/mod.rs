//! Named scenarios: the format loadable from TOML, its feasibility checks and its preparation
//! against a bench; the paper's tests as built-ins in [`builtin`](mod@builtin).

use crate::sim::bench::{BAR, Bench};
use crate::sim::motion::{Motion, MotionSpec};
use crate::sim::plant::{N_CYL, Plant};
use crate::sim::schedule::ValveSchedule;
use crate::sim::solver::{self, Initial, Run, SimError, SimResult, SolverOptions};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub mod builtin;
pub use builtin::{
    BLOCKED_APERTURES, SETS, TEST3_APERTURES, builtin, builtin_named, every_builtin, sea_family,
};

/// How the control valve is driven, as written in scenario files (apertures in %).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ValveSpec {
    /// Fixed aperture.
    Constant {
        /// %.
        aperture_pct: f64,
    },
    /// Closed until P2 reaches the threshold, then the aperture (Test III).
    Threshold {
        /// bar.
        threshold_bar: f64,
        /// %.
        aperture_pct: f64,
    },
    /// Step changes at the given times (closed before the first).
    Table {
        /// s, increasing.
        time_s: Vec<f64>,
        /// %.
        aperture_pct: Vec<f64>,
    },
}

/// A scenario as written in a TOML file.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Short name (`test3-ap10`).
    pub name: String,
    /// One line for people.
    #[serde(default)]
    pub description: String,
    /// Family in the paper (`test1`, `test2`, …), used to group plots and facts.
    #[serde(default)]
    pub group: String,
    /// `Config 1` … `Config 4` (or 1 … 4).
    pub config: String,
    /// Cylinders on duty by name (`HC3.1`) or number.
    pub cylinders: Vec<String>,
    /// Input motion.
    pub motion: MotionSpec,
    /// Valve schedule.
    pub valve: ValveSpec,
    /// Simulated time, s.
    pub duration_s: f64,
    /// Output sample interval, s.
    #[serde(default = "default_sample")]
    pub sample_interval_s: f64,
    /// Initial P2; absent = periodic steady state for a constant-aperture sine run.
    #[serde(default)]
    pub initial_hp_bar: Option<f64>,
    /// Initial LP.
    #[serde(default = "default_lp")]
    pub initial_lp_bar: f64,
}

fn default_sample() -> f64 {
    0.01
}
fn default_lp() -> f64 {
    8.0
}

/// A scenario error, named like bench errors: `source:field: message`.
#[derive(Debug, thiserror::Error)]
#[error("{source_name}:{field}: {message}")]
pub struct ScenarioError {
    /// File or built-in name.
    pub source_name: String,
    /// Field.
    pub field: String,
    /// What is wrong.
    pub message: String,
}

/// Why [`Scenario::simulate`] failed: the scenario is not feasible on the bench, or its run
/// failed (named with the scenario, the solver's error as the source).
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The scenario does not prepare on the bench.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// The run failed.
    #[error("{scenario}")]
    Simulation {
        /// The scenario's name.
        scenario: String,
        /// The solver's error.
        source: SimError,
    },
}

/// A scenario resolved against a bench: ready to run.
pub struct Prepared {
    /// The scenario.
    pub scenario: Scenario,
    /// The plant.
    pub plant: Plant,
    /// Config index.
    pub config: usize,
    /// On-duty mask.
    pub on_duty: [bool; N_CYL],
    /// Initial pressures.
    pub initial: Initial,
}

impl Scenario {
    /// Loads a scenario file.
    pub fn load(path: &Path) -> Result<Self, ScenarioError> {
        let name = path.display().to_string();
        let err = |field: &str, message: String| ScenarioError {
            source_name: name.clone(),
            field: field.into(),
            message,
        };
        let text =
            std::fs::read_to_string(path).map_err(|e| err("", format!("cannot read: {e}")))?;
        toml::from_str(&text).map_err(|e| err("", e.to_string().trim_end().to_string()))
    }

    /// Resolves names, checks ranges and builds the plant. `base` resolves relative trace files.
    pub fn prepare(&self, bench: &Bench, base: &Path) -> Result<Prepared, ScenarioError> {
        let err = |field: &str, message: String| ScenarioError {
            source_name: self.name.clone(),
            field: field.into(),
            message,
        };
        let range = |field: &str, v: f64, min: f64, max: f64, unit: &str| {
            if v.is_finite() && v >= min && v <= max {
                Ok(())
            } else {
                Err(err(field, format!("{v} outside [{min}, {max}] ({unit})")))
            }
        };
        // The name becomes file names in `--out` (`<name>.csv`, `<name>.png`): nothing that
        // could leave that folder or hide in it.
        if !is_file_name_safe(&self.name) {
            return Err(err(
                "name",
                format!(
                    "{:?} is not a file-name-safe name: 1–64 letters, digits, `.`, `_` or `-`, \
                     not starting with `.`",
                    self.name
                ),
            ));
        }
        let config = bench.config_index(&self.config).ok_or_else(|| {
            let names: Vec<_> = bench.configs.iter().map(|c| c.name.as_str()).collect();
            err(
                "config",
                format!("unknown `{}` (have: {})", self.config, names.join(", ")),
            )
        })?;
        let mut on_duty = [false; N_CYL];
        for (i, c) in self.cylinders.iter().enumerate() {
            let k = bench.cylinder_index(c).ok_or_else(|| {
                let names: Vec<_> = bench.cylinders.iter().map(|c| c.name.as_str()).collect();
                err(
                    &format!("cylinders[{i}]"),
                    format!("unknown `{c}` (have: {})", names.join(", ")),
                )
            })?;
            on_duty[k] = true;
        }
        if !on_duty.iter().any(|&d| d) {
            return Err(err("cylinders", "no cylinder on duty".into()));
        }
        range("duration_s", self.duration_s, 0.01, 1e6, "s")?;
        range("sample_interval_s", self.sample_interval_s, 1e-4, 10.0, "s")?;
        let n_samples = self.duration_s / self.sample_interval_s;
        if n_samples > 5e6 {
            return Err(err(
                "sample_interval_s",
                format!("{n_samples:.0} samples: over the 5e6 limit, use a coarser interval"),
            ));
        }
        if self.sample_interval_s >= self.duration_s {
            return Err(err(
                "sample_interval_s",
                format!(
                    "{} s is not shorter than duration_s = {} s (the run would record nothing)",
                    self.sample_interval_s, self.duration_s
                ),
            ));
        }
        range("initial_lp_bar", self.initial_lp_bar, 0.0, 100.0, "bar")?;
        let relief = bench.relief_setting_pa / BAR;
        // The accumulators must hold oil at the start: the HP precharge below the relief
        // setting (else the HP accumulator never takes any), the LP precharge below the LP
        // start (else LP runs below zero as the pumps draw from it).
        let hp_pre = bench.hp_acc.precharge_pa / BAR;
        if hp_pre >= relief {
            return Err(err(
                "hp_accumulator.precharge_bar",
                format!(
                    "{hp_pre} bar is not below the relief setting {relief} bar: the HP accumulator \
                     would never take oil"
                ),
            ));
        }
        let lp_pre = bench.lp_acc.precharge_pa / BAR;
        if lp_pre >= self.initial_lp_bar {
            return Err(err(
                "initial_lp_bar",
                format!(
                    "{} bar is not above the LP accumulator's precharge {lp_pre} bar: it would \
                     start empty and LP fall below zero",
                    self.initial_lp_bar
                ),
            ));
        }
        match &self.valve {
            ValveSpec::Constant { aperture_pct } => {
                range("valve.aperture_pct", *aperture_pct, 0.0, 100.0, "%")?
            }
            ValveSpec::Threshold {
                threshold_bar,
                aperture_pct,
            } => {
                range("valve.threshold_bar", *threshold_bar, 0.0, relief, "bar")?;
                range("valve.aperture_pct", *aperture_pct, 0.0, 100.0, "%")?;
            }
            ValveSpec::Table {
                time_s,
                aperture_pct,
            } => {
                if time_s.len() != aperture_pct.len() || time_s.is_empty() {
                    return Err(err(
                        "valve.aperture_pct",
                        "needs one aperture per time, at least one".into(),
                    ));
                }
                for (i, t) in time_s.iter().enumerate() {
                    range(&format!("valve.time_s[{i}]"), *t, 0.0, self.duration_s, "s")?;
                    if i > 0 && *t <= time_s[i - 1] {
                        return Err(err(
                            &format!("valve.time_s[{i}]"),
                            format!("{t} not after {} (s)", time_s[i - 1]),
                        ));
                    }
                }
                for (i, a) in aperture_pct.iter().enumerate() {
                    range(&format!("valve.aperture_pct[{i}]"), *a, 0.0, 100.0, "%")?;
                }
            }
        }
        let motion = Motion::from_spec(&self.motion, bench.pinion_radius_m, base)
            .map_err(|e| err("motion", e.to_string()))?;
        self.check_kinematics(bench, config, &motion)
            .map_err(|m| err("motion", m))?;
        let lp = self.initial_lp_bar * BAR;
        let p2 = match self.initial_hp_bar {
            Some(p) => {
                range("initial_hp_bar", p, 0.0, relief + 10.0, "bar")?;
                p * BAR
            }
            None => {
                let aperture_pct = match self.valve {
                    ValveSpec::Constant { aperture_pct } if aperture_pct > 0.0 => aperture_pct,
                    _ => {
                        return Err(err(
                            "initial_hp_bar",
                            "missing: the steady-state start needs a constant valve aperture above 0 %".into(),
                        ));
                    }
                };
                steady_p2(bench, config, &on_duty, &motion, lp, aperture_pct).ok_or_else(|| {
                    err(
                        "initial_hp_bar",
                        "missing: the steady-state start needs a sine input".into(),
                    )
                })?
            }
        };
        Ok(Prepared {
            scenario: self.clone(),
            plant: Plant::new(bench, config, on_duty, motion),
            config,
            on_duty,
            initial: Initial {
                p2_pa: p2,
                lp_pa: lp,
            },
        })
    }

    /// The motion must stay feasible for the whole run: a trace must cover it, and every rod's
    /// eye (all four are linked to the lever, on duty or not) must stay within its stroke.
    fn check_kinematics(
        &self,
        bench: &Bench,
        config: usize,
        motion: &Motion,
    ) -> Result<(), String> {
        if let Motion::Trace { t, .. } = motion
            && let Some(&end) = t.last()
            && end < self.duration_s
        {
            return Err(format!(
                "the trace ends at {end} s, before the run's {} s (its last angle would be held)",
                self.duration_s
            ));
        }
        // The extreme angles of the run (exact for a sine or a blocked input, sampled at
        // ≤ 1 ms, at most 10^6 points, otherwise).
        let (lo, hi, t_lo, t_hi) = match motion {
            Motion::Sine { amplitude, omega } => {
                let quarter = std::f64::consts::FRAC_PI_2 / omega.max(1e-12);
                (-amplitude, *amplitude, 3.0 * quarter, quarter)
            }
            Motion::Blocked(a) => (*a, *a, 0.0, 0.0),
            _ => {
                let n = ((self.duration_s / 1e-3).ceil() as usize).clamp(2, 1_000_000);
                let mut ext = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0.0);
                for i in 0..=n {
                    let t = self.duration_s * i as f64 / n as f64;
                    let a = motion.at(t).0;
                    if a < ext.0 {
                        ext = (a, ext.1, t, ext.3);
                    }
                    if a > ext.1 {
                        ext = (ext.0, a, ext.2, t);
                    }
                }
                ext
            }
        };
        let geom = &bench.configs[config];
        // Every angle the shaft passes through (the eye is not monotonic over a whole turn).
        let sweep = (0..=256).map(|i| {
            let a = lo + (hi - lo) * f64::from(i) / 256.0;
            (a, if i < 128 { t_lo } else { t_hi })
        });
        for c in &bench.cylinders {
            let lever = crate::sim::physics::Lever::new(geom, c.stroke_m, c.side);
            for (a, t) in sweep.clone() {
                let x = lever.eye(a, 0.0).0;
                if !(0.0..=c.stroke_m).contains(&x) {
                    let past = if x < 0.0 { -x } else { x - c.stroke_m };
                    return Err(format!(
                        "the shaft swings to {:.1}° (its extreme near t = {t:.2} s); at {:.1}° \
                         {}'s rod eye is {:.1} mm past its {} (stroke {:.0} mm, lever {}): \
                         reduce the amplitude",
                        if a < 0.5 * (lo + hi) { lo } else { hi }.to_degrees(),
                        a.to_degrees(),
                        c.name,
                        past * 1e3,
                        if x < 0.0 {
                            "retracted end"
                        } else {
                            "extended end"
                        },
                        c.stroke_m * 1e3,
                        geom.name
                    ));
                }
            }
        }
        Ok(())
    }

    /// The valve schedule in simulator units.
    pub fn schedule(&self) -> ValveSchedule {
        match &self.valve {
            ValveSpec::Constant { aperture_pct } => ValveSchedule::Constant(*aperture_pct),
            ValveSpec::Threshold {
                threshold_bar,
                aperture_pct,
            } => ValveSchedule::Threshold {
                threshold_pa: threshold_bar * BAR,
                aperture_pct: *aperture_pct,
            },
            ValveSpec::Table {
                time_s,
                aperture_pct,
            } => ValveSchedule::Table(
                time_s
                    .iter()
                    .zip(aperture_pct)
                    .map(|(t, a)| (*t, *a))
                    .collect(),
            ),
        }
    }
}

/// Periodic steady-state P2 of a constant-aperture sine run: the pressure at which the motor
/// passes the mean pumped flow. Mean pumped flow = f·Σ(A_cap + A_ann)·(eye travel − free play),
/// less the ≈1.6 % compressibility lag of `docs/physics.md`; the run then settles within a few periods.
fn steady_p2(
    bench: &Bench,
    config: usize,
    on_duty: &[bool; N_CYL],
    motion: &Motion,
    lp: f64,
    aperture_pct: f64,
) -> Option<f64> {
    let Motion::Sine { amplitude, omega } = motion else {
        return None;
    };
    let f = omega / (2.0 * std::f64::consts::PI);
    let geom = &bench.configs[config];
    let mut q = 0.0;
    for (c, _) in bench.cylinders.iter().zip(on_duty).filter(|(_, d)| **d) {
        let lever = crate::sim::physics::Lever::new(geom, c.stroke_m, c.side);
        let travel = (lever.eye(*amplitude, 0.0).0 - lever.eye(-amplitude, 0.0).0).abs();
        q += f * (c.area_cap_m2 + c.area_ann_m2) * (travel - bench.free_play_m).max(0.0);
    }
    let q = q * (1.0 - 0.016);
    let motor_flow = |p2: f64| {
        let (pm, w) = crate::sim::physics::steady_motor(bench, p2, lp, aperture_pct);
        bench.motor_disp_m3_per_rad * w + bench.motor_leak_m3_per_s_pa * (pm - lp)
    };
    let (mut lo, mut hi) = (lp, bench.relief_setting_pa);
    if motor_flow(hi) < q {
        return Some(hi);
    }
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if motor_flow(mid) < q {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some(0.5 * (lo + hi))
}

impl Scenario {
    /// Prepares and runs the scenario; errors name it.
    pub fn simulate(
        &self,
        bench: &Bench,
        base: &Path,
        solver: SolverOptions,
        progress: Option<crate::sim::solver::Progress<'_>>,
    ) -> Result<(Prepared, SimResult), RunError> {
        let prep = self.prepare(bench, base)?;
        let res = prep
            .run(solver, progress)
            .map_err(|source| RunError::Simulation {
                scenario: self.name.clone(),
                source,
            })?;
        Ok((prep, res))
    }
}

impl Prepared {
    /// Runs it.
    pub fn run(
        &self,
        solver: SolverOptions,
        progress: Option<crate::sim::solver::Progress<'_>>,
    ) -> Result<SimResult, SimError> {
        solver::simulate(Run {
            plant: &self.plant,
            valve: self.scenario.schedule(),
            initial: self.initial,
            duration: self.scenario.duration_s,
            sample_dt: self.scenario.sample_interval_s,
            solver,
            progress,
        })
    }
}

/// A scenario name that is safe as a file name in any output folder: 1–64 ASCII letters,
/// digits, `.`, `_` or `-`, not starting with `.` (so no `..`, no path separators, no hidden
/// files).
pub fn is_file_name_safe(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && !name.starts_with('.')
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

/// A built-in by name, or a scenario file by path.
pub fn resolve(name_or_file: &str) -> Result<(Scenario, PathBuf), ScenarioError> {
    if let Some(s) = builtin_named(name_or_file) {
        return Ok((s, PathBuf::from(".")));
    }
    let p = Path::new(name_or_file);
    if p.exists() {
        let base = p.parent().map(Path::to_path_buf).unwrap_or_default();
        return Ok((Scenario::load(p)?, base));
    }
    Err(ScenarioError {
        source_name: name_or_file.into(),
        field: "scenario".into(),
        message: "neither a built-in scenario (see `pto scenarios`) nor a file".into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_names_are_unique_and_all_prepare() {
        let b = Bench::reference();
        let all = builtin();
        let mut names: Vec<_> = all.iter().map(|s| s.name.clone()).collect();
        names.sort();
        names.dedup();
        assert_eq!(names.len(), all.len());
        for s in &all {
            s.prepare(&b, Path::new("."))
                .unwrap_or_else(|e| panic!("{e}"));
        }
    }

    #[test]
    fn scenario_round_trips_through_toml_and_errors_name_the_field() {
        let s = builtin()
            .into_iter()
            .find(|s| s.name == "test3-ap10")
            .unwrap();
        let text = toml::to_string(&s).unwrap();
        let back: Scenario = toml::from_str(&text).unwrap();
        assert_eq!(back, s);
        let mut bad = s.clone();
        bad.cylinders.push("HC7".into());
        let e = bad
            .prepare(&Bench::reference(), Path::new("."))
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.starts_with("test3-ap10:cylinders[2]: unknown `HC7`"),
            "{e}"
        );
        let mut bad = s;
        bad.valve = ValveSpec::Constant {
            aperture_pct: 120.0,
        };
        let e = bad
            .prepare(&Bench::reference(), Path::new("."))
            .err()
            .unwrap()
            .to_string();
        assert_eq!(e, "test3-ap10:valve.aperture_pct: 120 outside [0, 100] (%)");
    }
}
