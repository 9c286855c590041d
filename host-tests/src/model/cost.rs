//! Cost of the fixed-point model: host nanoseconds per estimator + scheduler step, and code size
//! of `pto-model` for both thumb targets (the `.text` of its release rlib).

use super::{inputs, model_config};
use crate::sim::bench::Bench;
use pto_model::ConfigError;
use pto_model::estimator::{self, State};
use pto_model::fx::Pressure;
use pto_model::scheduler::{self, Mode, SchedulerConfig, SchedulerState};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// Why the model's cost could not be measured.
#[derive(Debug, thiserror::Error)]
pub enum CostError {
    /// Cargo could not be started.
    #[error("cannot run cargo")]
    Cargo(#[source] std::io::Error),
    /// The build for a target failed (its output kept).
    #[error(
        "cargo build -p pto-model --target {target} failed (is the target installed? `rustup \
         target add {target}`):\n{stderr}"
    )]
    Build {
        /// The target triple.
        target: String,
        /// Cargo's error output.
        stderr: String,
    },
    /// The built rlib could not be read.
    #[error("{path}")]
    Read {
        /// The rlib.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The rlib is not an archive.
    #[error("{path}")]
    Archive {
        /// The rlib.
        path: PathBuf,
        /// The parser's error.
        source: object::read::Error,
    },
    /// A member of the rlib could not be read.
    #[error(transparent)]
    Member(object::read::Error),
    /// A per-step function or table of the list is not in the rlib.
    #[error(
        "{path}: no symbol matches `{fragment}`: the per-step function list in model/cost.rs is \
         stale"
    )]
    StaleList {
        /// The rlib.
        path: PathBuf,
        /// The name fragment not found.
        fragment: &'static str,
    },
    /// The reference configuration has no coefficients.
    #[error(transparent)]
    Config(#[from] ConfigError),
}

/// Targets of the model-crate issue, the code's raised to 9 KiB for the sensor-fault checks and
/// the motor line (the team's budget).
pub mod target {
    /// Flash for the model's per-step code on the Cortex-M4, bytes.
    pub const FLASH_BYTES: u64 = 9 * 1024;
    /// Estimator + scheduler state, bytes.
    pub const STATE_BYTES: usize = 1024;
}

/// One target's code size.
#[derive(Debug, Clone, Serialize)]
pub struct CodeSize {
    /// Rust target triple.
    pub target: String,
    /// `.text*` bytes of the rlib.
    pub text_bytes: u64,
    /// `.rodata*` bytes of the rlib.
    pub rodata_bytes: u64,
    /// Code of the per-step path: `estimator::step`, its per-cylinder part and the shaft
    /// tracker's start-up (with its constant gain table), `scheduler::step`,
    /// `aperture_for_flow`, `recip` and the table lookups (symbol sizes); the
    /// rest of `.text` is configuration-time code (coefficient tables in soft or hard float),
    /// validation, formatting and the advisor.
    pub step_code_bytes: u64,
}

/// The report.
#[derive(Debug, Clone, Serialize)]
pub struct Cost {
    /// Host nanoseconds per estimator + scheduler step (median of 5 runs of 200 000 steps).
    pub host_ns_per_step: f64,
    /// State bytes (estimator + scheduler).
    pub state_bytes: usize,
    /// Coefficient bytes (tables, in RAM on the target).
    pub coefficient_bytes: usize,
    /// Code sizes.
    pub code: Vec<CodeSize>,
    /// Targets met.
    pub pass: bool,
}

/// Host nanoseconds per step on sensor inputs of a sine wave at 100 bar.
pub fn host_ns_per_step() -> f64 {
    let cfg =
        model_config(&Bench::reference()).unwrap_or_else(|_| pto_model::ModelConfig::reference());
    let Ok(k) = cfg.coefficients() else {
        return f64::NAN;
    };
    let Ok(sc) = SchedulerConfig::default().coefficients(&k) else {
        return f64::NAN;
    };
    let n = 200_000;
    let inputs: Vec<_> = (0..4096)
        .map(|i| {
            let t = i as f64 / 1024.0;
            let theta = 0.4167 * (0.2 * std::f64::consts::PI * t).sin();
            let enc = (theta / (2.0 * std::f64::consts::PI) * 16384.0).round() as i32;
            inputs(
                Some(enc),
                Some(100.0 + (t * 7.0).sin()),
                Some(8.0),
                Some(250.0),
                10.0,
                0b1001,
                0,
            )
        })
        .collect();
    let mut runs = Vec::new();
    for _ in 0..5 {
        let mut s = State::new(
            Pressure::from_num(100.0),
            Pressure::from_num(8.0),
            Pressure::from_num(1.0),
        );
        let mut st = SchedulerState::default();
        let start = Instant::now();
        let mut acc = 0i64;
        for i in 0..n {
            let inp = &inputs[i % inputs.len()];
            let e = estimator::step(&k, &mut s, inp);
            let c = scheduler::step(
                &k,
                &sc,
                &mut st,
                Mode::HoldPressure(Pressure::from_num(100.0)),
                &e,
                inp.motor,
            );
            acc = acc.wrapping_add(i64::from(c.aperture.to_bits()));
        }
        std::hint::black_box(acc);
        runs.push(start.elapsed().as_secs_f64() * 1e9 / n as f64);
    }
    runs.sort_by(f64::total_cmp);
    runs[2]
}

/// The per-step functions and tables, as fragments of their mangled names (legacy mangling:
/// length-prefixed path segments, then `17h` and the hash). Every one must be found in the
/// rlib ([`code_size`] fails otherwise), so a function moved to another module cannot drop out
/// of the count unnoticed.
const STEP: [&str; 12] = [
    "9estimator4step17h",
    "9estimator8cylinder8cylinder17h",
    "9estimator8cylinder13reversal_unit17h",
    "9estimator7tracker15tracker_startup17h",
    "6coeffs15TRACKER_STARTUP",
    "9scheduler4step17h",
    "17aperture_for_flow",
    "2fx5recip",
    "2fx7mul_q24",
    "2at17h",
    "6at_ext17h",
    "6at_q3217h",
];

/// Builds `pto-model` for `target` (release, into `target/model-size`) and sums its sections.
pub fn code_size(workspace: &Path, target: &str) -> Result<CodeSize, CostError> {
    let target_dir = workspace.join("target").join("model-size");
    let out = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()))
        .current_dir(workspace)
        .args([
            "build",
            "--release",
            "-p",
            "pto-model",
            "--target",
            target,
            "--target-dir",
        ])
        .arg(&target_dir)
        .output()
        .map_err(CostError::Cargo)?;
    if !out.status.success() {
        return Err(CostError::Build {
            target: target.into(),
            stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        });
    }
    let rlib = target_dir
        .join(target)
        .join("release")
        .join("libpto_model.rlib");
    let data = std::fs::read(&rlib).map_err(|source| CostError::Read {
        path: rlib.clone(),
        source,
    })?;
    let archive =
        object::read::archive::ArchiveFile::parse(&*data).map_err(|source| CostError::Archive {
            path: rlib.clone(),
            source,
        })?;
    let (mut text, mut rodata, mut step) = (0u64, 0u64, 0u64);
    let mut seen = [false; STEP.len()];
    for member in archive.members() {
        let member = member.map_err(CostError::Member)?;
        let name = String::from_utf8_lossy(member.name()).to_string();
        if !name.ends_with(".o") {
            continue;
        }
        let bytes = member.data(&*data).map_err(CostError::Member)?;
        let Ok(file) = object::File::parse(bytes) else {
            continue;
        };
        use object::{Object, ObjectSection, ObjectSymbol};
        for sym in file.symbols() {
            let n = sym.name().unwrap_or("");
            if !n.contains("9pto_model") {
                continue;
            }
            if let Some(i) = STEP.iter().position(|m| n.contains(m)) {
                step += sym.size();
                seen[i] = true;
            }
        }
        for s in file.sections() {
            let n = s.name().unwrap_or("");
            if n.starts_with(".text") {
                text += s.size();
            } else if n.starts_with(".rodata") {
                rodata += s.size();
            }
        }
    }
    // A function moved or renamed would silently drop out of the count: every entry must be
    // found.
    if let Some(i) = seen.iter().position(|s| !s) {
        return Err(CostError::StaleList {
            path: rlib,
            fragment: STEP[i],
        });
    }
    Ok(CodeSize {
        target: target.into(),
        text_bytes: text,
        rodata_bytes: rodata,
        step_code_bytes: step,
    })
}

/// The full report. `workspace` is the repository root (for the nested cargo builds).
pub fn measure(workspace: &Path) -> Result<Cost, CostError> {
    let ns = host_ns_per_step();
    let k = pto_model::ModelConfig::reference().coefficients()?;
    let mut code = Vec::new();
    for t in ["thumbv6m-none-eabi", "thumbv7em-none-eabihf"] {
        code.push(code_size(workspace, t)?);
    }
    let state_bytes = std::mem::size_of::<State>() + std::mem::size_of::<SchedulerState>();
    // The flash target is the bench MCU's (Cortex-M4F); thumbv6m is reported for the record.
    let pass = state_bytes <= target::STATE_BYTES
        && code
            .iter()
            .filter(|c| c.target.starts_with("thumbv7em"))
            .all(|c| c.step_code_bytes <= target::FLASH_BYTES);
    Ok(Cost {
        host_ns_per_step: ns,
        state_bytes,
        coefficient_bytes: std::mem::size_of_val(&k),
        code,
        pass,
    })
}
