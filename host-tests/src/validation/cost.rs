//! Cost of the fixed-point model: host nanoseconds per estimator + scheduler step, code size
//! of `pto-model` for both thumb targets (the `.text` of its release rlib, and the per-step
//! code as the call graph of the step's entry points over the ELF objects' relocations), and
//! the model run on a Cortex-M0 under QEMU (`hil::m0`): its instructions and cycles per step,
//! the coefficients' build.

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
    /// A root of the per-step call graph is not in the rlib.
    #[error("{path}: no function `{root}` (the step's entry point) in the rlib")]
    NoRoot {
        /// The rlib.
        path: PathBuf,
        /// The entry point's path.
        root: &'static str,
    },
    /// The target's sysroot could not be found (`rustc --print sysroot`).
    #[error("cannot find the Rust sysroot (`rustc --print sysroot`): {0}")]
    Sysroot(String),
    /// A symbol the step reaches is defined in none of the rlibs read (another toolchain's
    /// sysroot?): the count would be short.
    #[error(
        "the step reaches symbols defined in none of the rlibs read (is `rustc` the toolchain \
         cargo builds with?): {0}"
    )]
    Unresolved(String),
    /// The reference configuration has no coefficients.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The Cortex-M0 replay could not run.
    #[error("the Cortex-M0 replay (QEMU microbit)")]
    M0(#[from] crate::hil::m0::M0Error),
}

/// Targets of the model-crate issue, the code's raised to 9 KiB for the sensor-fault checks and
/// the motor line (the team's budget).
pub mod target {
    /// Flash for the model's per-step code on the Cortex-M4, bytes.
    pub const FLASH_BYTES: u64 = 9 * 1024;
    /// Estimator + scheduler state, bytes.
    pub const STATE_BYTES: usize = 1024;
    /// Instructions of the worst step on a Cortex-M0 (the Cortex-M0 issue).
    pub const M0_STEP_INSTRUCTIONS: u32 = 4000;
    /// The Cortex-M0+ clock the core share is worked out at, Hz.
    pub const M0_CLOCK_HZ: f64 = 48e6;
    /// The control loop's rate, Hz.
    pub const M0_LOOP_HZ: f64 = 1000.0;
    /// Share of that core the worst step may take, %.
    pub const M0_CORE_PERCENT: f64 = 15.0;
    /// Stack the coefficients' build may take on the M0, bytes.
    pub const M0_BUILD_STACK_BYTES: u32 = 8 * 1024;
}

/// One run of the model on the Cortex-M0.
#[derive(Debug, Clone, Serialize)]
pub struct M0Run {
    /// Its instructions and cycles per step, from the trace of the step's code (every step bit
    /// for bit the host's).
    #[serde(flatten)]
    pub trace: crate::hil::m0::RunCycles,
    /// The worst step's share of the core at [`target::M0_CLOCK_HZ`] and
    /// [`target::M0_LOOP_HZ`], %.
    pub core_percent_max: f64,
    /// The timer's count around the call in the replay loop, mean and maximum (the step plus
    /// the call's set-up; a cross-check of the trace).
    pub timer_instructions: (f64, u32),
}

/// The model on a Cortex-M0 (`pto-m0` under QEMU `microbit`).
#[derive(Debug, Clone, Serialize)]
pub struct M0Cost {
    /// How it is measured.
    pub method: &'static str,
    /// The golden vectors and the four-cylinder window, with and without the HP transducer.
    pub runs: Vec<M0Run>,
    /// Coefficient bytes (built on the M0 from the uploaded configuration's bytes).
    pub coefficient_bytes: u32,
    /// Instructions of that build (soft float).
    pub build_instructions: u64,
    /// Stack the build took, bytes.
    pub build_stack_bytes: u32,
    /// Worst step's instructions, over the runs.
    pub step_instructions_max: u32,
    /// Worst step's share of the core, %.
    pub core_percent_max: f64,
    /// Step instructions within [`target::M0_STEP_INSTRUCTIONS`].
    pub instructions_met: bool,
    /// Core share within [`target::M0_CORE_PERCENT`].
    pub core_met: bool,
    /// Build stack within [`target::M0_BUILD_STACK_BYTES`].
    pub build_stack_met: bool,
}

/// How [`M0Cost`] is counted (also in the JSON).
const M0_METHOD: &str = "pto-m0 (firmware/m0) replays the vectors under QEMU -M microbit \
    (Cortex-M0) and checks every output against the host model's; instructions and Cortex-M0+ \
    cycles per step from QEMU's log of the step's code (-d exec,nochain, filtered to the step's \
    call graph, each block decoded from the ELF; cycles by the Cortex-M0+ TRM's table, single-cycle \
    multiplier, no wait states); the timer count (-icount shift=10, TIMER0) cross-checks it";

/// Replays the golden vectors and the four-cylinder window (with and without the HP transducer)
/// on the Cortex-M0 and measures them.
pub fn m0_cost() -> Result<M0Cost, CostError> {
    use crate::hil::m0;
    let workspace = crate::hil::build::workspace_root("the Cortex-M0 replay")
        .map_err(crate::hil::m0::M0Error::from)?;
    let mut runs = vec![m0::golden_run(&workspace)?];
    runs.extend(m0::four_cylinder_runs()?);
    let dir = std::env::temp_dir().join(format!("pto-model-cost-m0-{}", std::process::id()));
    let result = (|| {
        let elf = crate::hil::build::build(crate::hil::build::Build::M0)?;
        let v = m0::vectors(&pto_model::ModelConfig::reference(), &runs)?;
        let r = m0::replay_in(&elf, &v, &dir)?;
        if r.exit != 0 || r.runs.len() != runs.len() {
            return Err(m0::M0Error::Failed {
                exit: r.exit,
                why: r
                    .failure
                    .clone()
                    .unwrap_or_else(|| "a run did not report".into()),
                output: r.output,
            });
        }
        let cycles = m0::cycles(&elf, &v, &runs, &dir, m0::Trace::Blocks)?;
        Ok((r, cycles))
    })();
    let _ = std::fs::remove_dir_all(&dir);
    let (r, cycles) = result?;
    let per_loop = target::M0_CLOCK_HZ / target::M0_LOOP_HZ;
    let runs: Vec<M0Run> = r
        .runs
        .iter()
        .zip(cycles)
        .map(|(t, c)| M0Run {
            core_percent_max: 100.0 * f64::from(c.cycles_max) / per_loop,
            timer_instructions: (t.mean, t.max),
            trace: c,
        })
        .collect();
    let missing = |what| crate::hil::m0::M0Error::Report {
        what,
        output: r.output.clone(),
    };
    let step_instructions_max = runs
        .iter()
        .map(|r| r.trace.instructions_max)
        .max()
        .unwrap_or(0);
    let core_percent_max = runs.iter().map(|r| r.core_percent_max).fold(0.0, f64::max);
    let build_stack_bytes = r.build_stack_bytes.ok_or_else(|| missing("coefficients"))?;
    Ok(M0Cost {
        method: M0_METHOD,
        coefficient_bytes: r.coefficient_bytes.ok_or_else(|| missing("coefficients"))?,
        build_instructions: r
            .build_instructions
            .ok_or_else(|| missing("coefficients"))?,
        build_stack_bytes,
        step_instructions_max,
        core_percent_max,
        instructions_met: step_instructions_max <= target::M0_STEP_INSTRUCTIONS,
        core_met: core_percent_max <= target::M0_CORE_PERCENT,
        build_stack_met: build_stack_bytes <= target::M0_BUILD_STACK_BYTES,
        runs,
    })
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
    /// Per-step code and the constants it reads: every section reached from
    /// `estimator::step` and `scheduler::step` (the firmware's per-period calls) over the
    /// relocations of the ELF objects — calls, branches and data references — through this
    /// crate, its dependencies and the target's `core` and `compiler_builtins`. The rest of
    /// `.text` is configuration-time code (coefficient tables in soft or hard float),
    /// validation, formatting and the advisor.
    pub step_code_bytes: u64,
    /// Of it, code (`.text*` sections), bytes.
    pub step_text_bytes: u64,
    /// Functions reached.
    pub step_functions: usize,
    /// The step's functions by code size, largest first (demangled path, bytes).
    pub step_largest: Vec<(String, u64)>,
    /// Functions reached outside `pto_model`'s own objects (compiler builtins, `core`),
    /// demangled.
    pub step_external: Vec<String>,
    /// Panic entry points reached (`core::panicking::*`, however reached: an `unwrap`, a slice
    /// index, a bounds check), each with the crate's function on the way to it: none, or the
    /// step can panic.
    pub step_panics: Vec<String>,
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
    /// The model on a Cortex-M0.
    pub m0: M0Cost,
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

/// The step's entry points (the firmware's per-period calls), as demangled paths.
const ROOTS: [&str; 2] = ["pto_model::estimator::step", "pto_model::scheduler::step"];

/// Undefined symbols the rlibs may leave unresolved (demangled paths' last segment): the panic
/// handler, defined by the final binary (reached only behind a panic, reported as one).
const LINK_TIME: [&str; 1] = ["rust_begin_unwind"];

/// A section of one object: the call graph's node.
type Node = (usize, object::SectionIndex);

/// Builds `pto-model` for `target` (release, into `target/model-size`), sums its sections and
/// walks the step's call graph.
pub fn code_size(workspace: &Path, target: &str) -> Result<CodeSize, CostError> {
    use object::{Object, ObjectSection, ObjectSymbol, RelocationTarget, SymbolSection};
    use std::collections::{HashMap, HashSet};
    let target_dir = workspace.join("target").join("model-size");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(&cargo)
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
    let release = target_dir.join(target).join("release");
    let rlib = release.join("libpto_model.rlib");
    // The crate first (its symbols win a name), then its dependencies, then the sysroot's.
    let mut rlibs = vec![rlib.clone()];
    let mut deps: Vec<PathBuf> = std::fs::read_dir(release.join("deps"))
        .map_err(|source| CostError::Read {
            path: release.join("deps"),
            source,
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let n = p
                .file_name()
                .map(|n| n.to_string_lossy())
                .unwrap_or_default();
            n.ends_with(".rlib") && !n.starts_with("libpto_model")
        })
        .collect();
    deps.sort();
    rlibs.extend(deps);
    rlibs.extend(sysroot_rlibs(workspace, target)?);
    let data: Vec<Vec<u8>> = rlibs
        .iter()
        .map(|p| {
            std::fs::read(p).map_err(|source| CostError::Read {
                path: p.clone(),
                source,
            })
        })
        .collect::<Result<_, _>>()?;
    // The rlibs' ELF objects.
    let mut objs: Vec<object::File> = Vec::new();
    // Objects 0..crate_objs are the crate's own.
    let mut crate_objs = 0;
    let (mut text, mut rodata) = (0u64, 0u64);
    for (k, (bytes, path)) in data.iter().zip(&rlibs).enumerate() {
        let archive = object::read::archive::ArchiveFile::parse(&**bytes).map_err(|source| {
            CostError::Archive {
                path: path.clone(),
                source,
            }
        })?;
        for member in archive.members() {
            let member = member.map_err(CostError::Member)?;
            if !String::from_utf8_lossy(member.name()).ends_with(".o") {
                continue;
            }
            // An object that does not parse (LLVM bitcode, say) would drop its code from the
            // count: an error, not a skip.
            let file = object::File::parse(member.data(&**bytes).map_err(CostError::Member)?)
                .map_err(CostError::Member)?;
            if k == 0 {
                for s in file.sections() {
                    let n = s.name().unwrap_or("");
                    if n.starts_with(".text") {
                        text += s.size();
                    } else if n.starts_with(".rodata") {
                        rodata += s.size();
                    }
                }
            }
            objs.push(file);
        }
        if k == 0 {
            crate_objs = objs.len();
        }
    }
    // Defined global symbols by name: the first strong definition wins (the crate's own first),
    // a weak one only where there is none.
    let mut global: HashMap<&str, (Node, bool)> = HashMap::new();
    let mut roots: Vec<Option<Node>> = vec![None; ROOTS.len()];
    for (i, o) in objs.iter().enumerate() {
        for sym in o.symbols() {
            let (Ok(name), SymbolSection::Section(sec)) = (sym.name(), sym.section()) else {
                continue;
            };
            if sym.is_global() {
                let weak = sym.is_weak();
                match global.get(name) {
                    Some((_, false)) => {}
                    Some((_, true)) if weak => {}
                    _ => {
                        global.insert(name, ((i, sec), weak));
                    }
                }
            }
            if i < crate_objs && sym.kind() == object::SymbolKind::Text {
                let path = demangled(name);
                for (r, root) in roots.iter_mut().zip(ROOTS) {
                    if r.is_none() && path == root {
                        *r = Some((i, sec));
                    }
                }
            }
        }
    }
    let mut queue = Vec::new();
    for (r, root) in roots.iter().zip(ROOTS) {
        queue.push(r.ok_or_else(|| CostError::NoRoot {
            path: rlib.clone(),
            root,
        })?);
    }
    let mut seen: HashSet<Node> = queue.iter().copied().collect();
    // Every reference followed (to name a panic's callers), and what resolved to nothing.
    let mut edges: Vec<(Node, Node)> = Vec::new();
    let mut unresolved: Vec<String> = Vec::new();
    while let Some((i, sec)) = queue.pop() {
        let file = &objs[i];
        let Ok(section) = file.section_by_index(sec) else {
            continue;
        };
        for (_, rel) in section.relocations() {
            let next = match rel.target() {
                RelocationTarget::Symbol(idx) => {
                    let Ok(sym) = file.symbol_by_index(idx) else {
                        continue;
                    };
                    match sym.section() {
                        SymbolSection::Section(s) => Some((i, s)),
                        _ => {
                            let name = sym.name().unwrap_or("?");
                            let found = global.get(name).map(|(n, _)| *n);
                            let path = demangled(name);
                            let last = path.rsplit("::").next().unwrap_or("");
                            if found.is_none() && !LINK_TIME.contains(&last) {
                                unresolved.push(path);
                            }
                            found
                        }
                    }
                }
                RelocationTarget::Section(s) => Some((i, s)),
                _ => None,
            };
            let Some(n) = next else {
                continue;
            };
            edges.push(((i, sec), n));
            if seen.insert(n) {
                queue.push(n);
            }
        }
    }
    if !unresolved.is_empty() {
        unresolved.sort();
        unresolved.dedup();
        return Err(CostError::Unresolved(unresolved.join(", ")));
    }
    // A code section's function, demangled (`.text.<name>`, `.text.unlikely.<name>`; a bare
    // `.text`, hand-written assembly, by the object's name for it).
    let function = |(i, sec): Node| -> String {
        let name = objs[i]
            .section_by_index(sec)
            .ok()
            .and_then(|s| s.name().ok())
            .unwrap_or("?");
        let mangled = name.strip_prefix(".text.").unwrap_or(name);
        let mangled = mangled.strip_prefix("unlikely.").unwrap_or(mangled);
        demangled(mangled)
    };
    let (mut step, mut step_text, mut functions) = (0u64, 0u64, 0usize);
    let (mut external, mut panics, mut sizes) = (Vec::new(), Vec::new(), Vec::new());
    for &node in &seen {
        let Ok(section) = objs[node.0].section_by_index(node.1) else {
            continue;
        };
        use object::SectionKind::{Text, UninitializedData, UninitializedTls};
        let kind = section.kind();
        // RAM, not flash.
        if matches!(kind, UninitializedData | UninitializedTls) {
            continue;
        }
        step += section.size();
        // Constants: flash, not code.
        if kind != Text {
            continue;
        }
        step_text += section.size();
        functions += 1;
        let path = function(node);
        sizes.push((path.clone(), section.size()));
        if path.starts_with("core::panicking") {
            // Named with the crate's functions on the way to it (back along the references
            // followed, to the nearest of the crate's own).
            let mut from: Vec<Node> = vec![node];
            let mut back: HashSet<Node> = from.iter().copied().collect();
            while let Some(n) = from.pop() {
                for &(a, _) in edges.iter().filter(|(_, b)| *b == n) {
                    if a.0 < crate_objs {
                        panics.push(format!("{path} from {}", function(a)));
                    } else if back.insert(a) {
                        from.push(a);
                    }
                }
            }
        }
        if node.0 >= crate_objs {
            external.push(path);
        }
    }
    panics.sort();
    panics.dedup();
    external.sort();
    sizes.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    Ok(CodeSize {
        target: target.into(),
        text_bytes: text,
        rodata_bytes: rodata,
        step_code_bytes: step,
        step_text_bytes: step_text,
        step_functions: functions,
        step_largest: sizes,
        step_external: external,
        step_panics: panics,
    })
}

/// The target's `core`, `compiler_builtins` (and the rest of its sysroot's rlibs), of the
/// toolchain that builds in `workspace` (its overrides apply).
fn sysroot_rlibs(workspace: &Path, target: &str) -> Result<Vec<PathBuf>, CostError> {
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into());
    let out = Command::new(rustc)
        .current_dir(workspace)
        .args(["--print", "sysroot"])
        .output()
        .map_err(|e| CostError::Sysroot(e.to_string()))?;
    if !out.status.success() {
        return Err(CostError::Sysroot(
            String::from_utf8_lossy(&out.stderr).into_owned(),
        ));
    }
    let lib = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim())
        .join("lib/rustlib")
        .join(target)
        .join("lib");
    let mut v: Vec<PathBuf> = std::fs::read_dir(&lib)
        .map_err(|e| CostError::Sysroot(format!("{}: {e}", lib.display())))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "rlib"))
        .collect();
    v.sort();
    Ok(v)
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
    let m0 = m0_cost()?;
    // The flash target is the bench MCU's (Cortex-M4F); thumbv6m's is reported for the record.
    // No target's step may reach a panic. The M0's step, core share and build stack have
    // targets of their own.
    let pass = state_bytes <= target::STATE_BYTES
        && m0.instructions_met
        && m0.core_met
        && m0.build_stack_met
        && code.iter().all(|c| c.step_panics.is_empty())
        && code
            .iter()
            .filter(|c| c.target.starts_with("thumbv7em"))
            .all(|c| c.step_code_bytes <= target::FLASH_BYTES);
    Ok(Cost {
        host_ns_per_step: ns,
        state_bytes,
        coefficient_bytes: std::mem::size_of_val(&k),
        code,
        m0,
        pass,
    })
}
/// A symbol's Rust path without its hash (`pto_model::estimator::step`).
fn demangled(symbol: &str) -> String {
    format!("{:#}", rustc_demangle::demangle(symbol))
}
