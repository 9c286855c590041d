//! The model on a Cortex-M0: `pto-m0` (firmware/m0) under QEMU `-M microbit` (nRF51822, a
//! Cortex-M0 r0p0) replays step vectors bit for bit and counts each step's instructions.
//!
//! The host writes the vectors (the format is `pto_model::protocol::vectors`): per run the configuration as the bench
//! workflow uploads it (postcard bytes and their CRC-32C), the mode, the start, and each step's
//! inputs with the host model's outputs. The target builds the coefficients itself, replays,
//! compares every output and prints one line per run: the steps matched and the instruction
//! counts (QEMU `-icount shift=10`: an instruction is 16.384 ticks of the nRF51's 16 MHz
//! TIMER0, so the counts are exact).

use super::build::BuildError;
use super::qemu;
use crate::validation::golden::{self, GoldenError};
use pto_model::estimator::{self, Inputs, State};
use pto_model::fx::Pressure;
use pto_model::protocol::vectors::{Header, Record, VERSION, checked_words};
use pto_model::protocol::{CONFIG_MAX_BYTES, config_fingerprint, encode_config};
use pto_model::scheduler::{self, Mode, SchedulerConfig, SchedulerState};
use pto_model::{ConfigError, ModelConfig};
use serde::Serialize;
use std::io::Read as _;
use std::os::unix::process::CommandExt as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Why the M0 replay could not run (a mismatch is not an error: it is in the [`Report`]).
#[derive(Debug, thiserror::Error)]
pub enum M0Error {
    /// The build failed.
    #[error(transparent)]
    Build(#[from] BuildError),
    /// The vectors could not be made.
    #[error(transparent)]
    Golden(#[from] GoldenError),
    /// The configuration has no coefficients.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The configuration or a record did not encode.
    #[error("encoding the vectors: {0}")]
    Encode(#[from] postcard::Error),
    /// A file or folder could not be written or read.
    #[error("{path}")]
    Io {
        /// The path.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The ELF could not be read as ARMv6-M code.
    #[error("{0}: {1}")]
    Elf(PathBuf, String),
    /// QEMU could not be started (`apt-get install qemu-system-arm`).
    #[error("cannot start qemu-system-arm (apt-get install qemu-system-arm)")]
    Start(#[source] std::io::Error),
    /// QEMU ran past its time.
    #[error("the M0 replay did not end within {0:?} (QEMU killed); its output:\n{1}")]
    Timeout(Duration, String),
    /// A run's header would not fit the target's buffer.
    #[error(
        "run \"{label}\": its header is {bytes} bytes, the M0 reads at most {max} (a shorter label)"
    )]
    HeaderTooLong {
        /// The run.
        label: String,
        /// Its encoded header.
        bytes: usize,
        /// `HEADER_MAX_BYTES`.
        max: usize,
    },
    /// The replay did not match or did not run through (the target's own report attached).
    #[error("the M0 replay failed (exit {exit}): {why}\n{output}")]
    Failed {
        /// Its exit status.
        exit: i32,
        /// The target's first failure line.
        why: String,
        /// What it printed.
        output: String,
    },
    /// The trace saw fewer steps than the vectors hold.
    #[error("the trace saw {traced} steps, the vectors hold {expected}:\n{output}")]
    TraceShort {
        /// Steps traced.
        traced: usize,
        /// Steps in the vectors.
        expected: usize,
        /// What the target printed.
        output: String,
    },
    /// The target's report lacks a line the host needs.
    #[error("the M0 replay's output has no {what} line:\n{output}")]
    Report {
        /// The line.
        what: &'static str,
        /// What it printed.
        output: String,
    },
}

/// The vectors' file name (`pto_model::protocol::vectors::VECTORS_FILE`).
fn vectors_file() -> &'static str {
    pto_model::protocol::vectors::VECTORS_FILE
        .to_str()
        .unwrap_or("vectors.bin")
}

/// One run to replay.
#[derive(Debug, Clone)]
pub struct Run {
    /// Its name in the report.
    pub label: String,
    /// The scheduler's mode.
    pub mode: Mode,
    /// Start P2, LP and P2's σ.
    pub start: [Pressure; 3],
    /// The inputs.
    pub inputs: Vec<Inputs>,
}

impl Run {
    /// A run from start pressures in bar (P2 known to 1 bar, as the firmware's `Reset`).
    pub fn new(label: &str, mode: Mode, inputs: Vec<Inputs>, p2: f32, lp: f32) -> Run {
        Run {
            label: label.into(),
            mode,
            start: [
                Pressure::from_num(p2),
                Pressure::from_num(lp),
                Pressure::from_num(1.0),
            ],
            inputs,
        }
    }
}

/// The golden vectors (`host-tests/data/golden-vectors.csv`) as a run.
pub fn golden_run(workspace: &Path) -> Result<Run, M0Error> {
    let path = workspace.join("host-tests").join(golden::FILE);
    let text = std::fs::read_to_string(&path).map_err(io(&path))?;
    let (p2, lp, inputs) = golden::parse(&text)?;
    Ok(Run {
        label: "golden vectors".into(),
        mode: golden::hold_p2(),
        start: [
            Pressure::from_bits(p2),
            Pressure::from_bits(lp),
            Pressure::from_num(1.0),
        ],
        inputs,
    })
}

/// The four-cylinder cost window (6 s of the Config 1 torque run through stroke reversals:
/// `pto fw-cost`'s), with the HP transducer and without it.
pub fn four_cylinder_runs() -> Result<[Run; 2], M0Error> {
    use crate::hil::fw_cost::{four_cylinder_inputs, without_hp};
    let (with, p2, lp) = four_cylinder_inputs()?;
    let without = without_hp(&with);
    Ok([
        Run::new("four cylinders", golden::hold_p2(), with, p2, lp),
        Run::new(
            "four cylinders, no HP transducer",
            golden::hold_p2(),
            without,
            p2,
            lp,
        ),
    ])
}

/// The vectors file for `runs` under `cfg`: each step's expected outputs from the host model
/// (the same code, built for the host).
pub fn vectors(cfg: &ModelConfig, runs: &[Run]) -> Result<Vec<u8>, M0Error> {
    vectors_tampered(cfg, runs, |_, _, _| {})
}

/// [`vectors`] with `tamper(run, step, inputs)` applied to each record's inputs after the host
/// model has run on the true ones (a test's flipped input bit).
pub fn vectors_tampered(
    cfg: &ModelConfig,
    runs: &[Run],
    tamper: impl Fn(usize, usize, &mut Inputs),
) -> Result<Vec<u8>, M0Error> {
    let k = cfg.coefficients()?;
    let sc = SchedulerConfig::default().coefficients(&k)?;
    let mut buf = [0u8; CONFIG_MAX_BYTES];
    let config = encode_config(cfg, &mut buf)?;
    let mut out = pto_model::protocol::vectors::MAGIC.to_vec();
    for (n, r) in runs.iter().enumerate() {
        let h = Header {
            version: VERSION,
            label: &r.label,
            steps: r.inputs.len() as u32,
            mode: r.mode,
            start: r.start,
            config_crc: config_fingerprint(config),
            config,
        };
        let header = postcard::to_stdvec(&h)?;
        if header.len() > pto_model::protocol::vectors::HEADER_MAX_BYTES {
            return Err(M0Error::HeaderTooLong {
                label: r.label.clone(),
                bytes: header.len(),
                max: pto_model::protocol::vectors::HEADER_MAX_BYTES,
            });
        }
        out.extend(header);
        let mut s = State::new(r.start[0], r.start[1], r.start[2]);
        let mut st = SchedulerState::default();
        for (i, inp) in r.inputs.iter().enumerate() {
            let e = estimator::step(&k, &mut s, inp);
            let c = scheduler::step(&k, &sc, &mut st, r.mode, &e, inp.motor);
            let mut inputs = *inp;
            tamper(n, i, &mut inputs);
            out.extend(postcard::to_stdvec(&Record {
                inputs,
                want: checked_words(&e, &c),
            })?);
        }
    }
    Ok(out)
}

/// Instruction counts of one run on the M0.
#[derive(Debug, Clone, Serialize)]
pub struct RunCost {
    /// The run.
    pub label: String,
    /// Steps replayed (every one matched).
    pub steps: u32,
    /// Mean instructions per step.
    pub mean: f64,
    /// Most instructions in a step.
    pub max: u32,
    /// The step that took them.
    pub max_at: u32,
}

/// What the M0 replay reported.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// The target's exit status (`pto_model::protocol::vectors::EXIT_*`); 0: every step of every run matched.
    pub exit: i32,
    /// The runs that matched, with their costs.
    pub runs: Vec<RunCost>,
    /// The first mismatch or failure, as the target printed it.
    pub failure: Option<String>,
    /// Bytes of the coefficients (built once, into place).
    pub coefficient_bytes: Option<u32>,
    /// Instructions the coefficient build took.
    pub build_instructions: Option<u64>,
    /// Stack the coefficient build used, bytes.
    pub build_stack_bytes: Option<u32>,
    /// Stack the build and the replay used at most, bytes (measured from a fresh paint after
    /// the harness zeroed the coefficients' static: that zeroing takes ≈ 6 KB once, a
    /// `Default` by value, which a part would do in its start-up code instead).
    pub stack_bytes: Option<u32>,
    /// Everything the target printed.
    pub output: String,
}

/// QEMU's options for the M0: the micro:bit's nRF51 with 32 KiB of SRAM instead of 16 (the
/// test binary's needs, `firmware/m0/memory.x`).
const SRAM: [&str; 2] = ["-global", "nrf51-soc.sram-size=32768"];

/// How long a replay may take (≈ 15 000 steps take ≈ 10 s).
const TIMEOUT: Duration = Duration::from_secs(300);

/// A QEMU `microbit` child running the M0 binary, its output read as it comes. Tracked for the
/// interrupt handler (`qemu::end_all_children`); [`Qemu::finish`] always kills and reaps it.
struct Qemu {
    child: std::process::Child,
    out: std::thread::JoinHandle<String>,
    err: std::thread::JoinHandle<String>,
}

impl Qemu {
    /// Starts `elf` in `dir` with `extra` options.
    fn start(elf: &Path, dir: &Path, extra: &[&str]) -> Result<Qemu, M0Error> {
        let mut child = Command::new("qemu-system-arm")
            .args(["-M", "microbit", "-nographic", "-monitor", "none"])
            .args(["-serial", "null"])
            .args(["-semihosting-config", "enable=on,target=native"])
            .args(SRAM)
            .args(extra)
            .arg("-kernel")
            .arg(elf)
            .current_dir(dir)
            // Its own process group: a terminal's Ctrl-C reaches `pto`, which ends it.
            .process_group(0)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(M0Error::Start)?;
        qemu::track(child.id());
        let read_all = |pipe: Option<Box<dyn std::io::Read + Send>>| {
            std::thread::spawn(move || {
                let mut s = String::new();
                if let Some(mut p) = pipe {
                    let _ = p.read_to_string(&mut s);
                }
                s
            })
        };
        let out = read_all(child.stdout.take().map(|p| Box::new(p) as _));
        let err = read_all(child.stderr.take().map(|p| Box::new(p) as _));
        Ok(Qemu { child, out, err })
    }

    /// Waits for the exit (killing QEMU after [`TIMEOUT`]), reaps it: its status (`None`: timed
    /// out) and what it printed, QEMU's own messages last.
    fn finish(mut self) -> (Option<std::process::ExitStatus>, String) {
        // QEMU's stdout closes when it exits: wait for that (not reaping it yet, so that its pid
        // stays ours while the interrupt handler's list still holds it), then take it off the
        // list, kill (if still running: the time-out) and reap.
        let started = Instant::now();
        while !self.out.is_finished() && started.elapsed() < TIMEOUT {
            std::thread::sleep(Duration::from_millis(20));
        }
        qemu::forget(self.child.id());
        let timed_out = !self.out.is_finished();
        if timed_out {
            let _ = self.child.kill();
        }
        let status = self.child.wait().ok().filter(|_| !timed_out);
        let mut output = self.out.join().unwrap_or_default();
        let qemu_said = self.err.join().unwrap_or_default();
        if !qemu_said.trim().is_empty() {
            output.push_str(&format!("(qemu: {})\n", qemu_said.trim()));
        }
        (status, output)
    }
}

/// An I/O error on `path`.
fn io(path: &Path) -> impl FnOnce(std::io::Error) -> M0Error {
    let path = path.to_path_buf();
    move |source| M0Error::Io { path, source }
}

/// Creates `dir` and writes `vectors` there, where the M0 binary opens them.
fn write_vectors(dir: &Path, vectors: &[u8]) -> Result<(), M0Error> {
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let file = dir.join(vectors_file());
    std::fs::write(&file, vectors).map_err(io(&file))
}

/// Runs the M0 binary `elf` on `vectors` in `dir` (created; `vectors.bin` is written there).
pub fn replay_in(elf: &Path, vectors: &[u8], dir: &Path) -> Result<Report, M0Error> {
    write_vectors(dir, vectors)?;
    let (status, output) =
        Qemu::start(elf, dir, &["-icount", "shift=10,align=off,sleep=off"])?.finish();
    let Some(status) = status else {
        return Err(M0Error::Timeout(TIMEOUT, output));
    };
    Ok(parse_report(status.code().unwrap_or(-1), output))
}

/// The target's printed lines as a [`Report`]: `coefficients`, `run` and `stack` lines of
/// `key=value` words (a run's label last, the rest of its line), `MISMATCH`, `FAILED` and
/// `PANIC` lines as they are.
fn parse_report(exit: i32, output: String) -> Report {
    let mut r = Report {
        exit,
        runs: Vec::new(),
        failure: None,
        coefficient_bytes: None,
        build_instructions: None,
        build_stack_bytes: None,
        stack_bytes: None,
        output: String::new(),
    };
    for line in output.lines() {
        let (head, rest) = line.split_once(' ').unwrap_or((line, ""));
        let (fields, label) = rest.split_once("label=").unwrap_or((rest, ""));
        let get = |key: &str| -> Option<u64> {
            fields
                .split_whitespace()
                .find_map(|w| w.strip_prefix(key)?.strip_prefix('='))
                .and_then(|v| v.parse().ok())
        };
        match head {
            "coefficients" => {
                r.coefficient_bytes = get("bytes").map(|v| v as u32);
                r.build_instructions = get("build_instructions");
                r.build_stack_bytes = get("build_stack_bytes").map(|v| v as u32);
            }
            "run" => {
                if let (Some(steps), Some(sum), Some(max), Some(at)) =
                    (get("steps"), get("sum"), get("max"), get("max_at"))
                {
                    r.runs.push(RunCost {
                        label: label.to_string(),
                        steps: steps as u32,
                        mean: sum as f64 / steps.max(1) as f64,
                        max: max as u32,
                        max_at: at as u32,
                    });
                }
            }
            "stack" => r.stack_bytes = get("bytes").map(|v| v as u32),
            "MISMATCH" | "FAILED:" | "PANIC:" => {
                r.failure.get_or_insert_with(|| line.to_string());
            }
            _ => {}
        }
    }
    r.output = output;
    r
}

/// Instructions and Cortex-M0+ cycles of one run's steps, from QEMU's trace of the step's
/// code.
#[derive(Debug, Clone, Serialize)]
pub struct RunCycles {
    /// The run.
    pub label: String,
    /// Steps traced.
    pub steps: u32,
    /// Mean instructions per step, of the step's own code (the call's argument set-up in the
    /// replay loop not counted).
    pub instructions_mean: f64,
    /// Most instructions in a step.
    pub instructions_max: u32,
    /// Mean cycles per step (`thumb`'s table).
    pub cycles_mean: f64,
    /// Most cycles in a step.
    pub cycles_max: u32,
    /// The step that took them.
    pub cycles_max_at: u32,
}

/// How QEMU logs the step's code for [`cycles`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Trace {
    /// One line per translation block run, its instructions decoded from the ELF (fast).
    Blocks,
    /// One line per instruction (`-singlestep`: slow; the check of the block decoding).
    Instructions,
}

/// QEMU's option for one instruction per translation block: `-singlestep` before QEMU 8.1,
/// `-accel tcg,one-insn-per-tb=on` from 8.1 (`-singlestep` is gone from 9.0).
fn one_instruction_per_block() -> Result<Vec<&'static str>, M0Error> {
    let out = Command::new("qemu-system-arm")
        .arg("--version")
        .output()
        .map_err(M0Error::Start)?;
    let text = String::from_utf8_lossy(&out.stdout);
    let version: Vec<u32> = text
        .split_whitespace()
        .skip_while(|w| *w != "version")
        .nth(1)
        .unwrap_or("0.0")
        .split('.')
        .map_while(|n| n.parse().ok())
        .collect();
    let new = (
        version.first().copied().unwrap_or(0),
        version.get(1).copied().unwrap_or(0),
    ) >= (8, 1);
    Ok(if new {
        vec!["-accel", "tcg,one-insn-per-tb=on"]
    } else {
        vec!["-singlestep"]
    })
}

/// Replays `runs` (their vectors from [`vectors`]) on the M0 binary `elf` under QEMU without
/// instruction counting, logging the execution of the step's code only (`-d exec,nochain
/// -dfilter` over the call graph of `pto_m0`'s `step`), and counts each step's instructions and
/// Cortex-M0+ cycles from the log, read through a FIFO as it is written.
pub fn cycles(
    elf: &Path,
    vectors: &[u8],
    runs: &[Run],
    dir: &Path,
    trace: Trace,
) -> Result<Vec<RunCycles>, M0Error> {
    use super::thumb::{Class, Code};
    use std::io::BufRead as _;
    let bytes = std::fs::read(elf).map_err(io(elf))?;
    let code = Code::parse(&bytes).map_err(|e| M0Error::Elf(elf.to_path_buf(), e.to_string()))?;
    let step = code.function("pto_m0::target::step").ok_or_else(|| {
        M0Error::Elf(elf.to_path_buf(), "no function pto_m0::target::step".into())
    })?;
    // The step's code, and where each call to it returns: a block there ends the step (the
    // replay loop may call functions the step also calls, which are in the filter).
    let returns = code.returns_from(step.0);
    if returns.is_empty() {
        return Err(M0Error::Elf(
            elf.to_path_buf(),
            "no call to pto_m0::target::step".into(),
        ));
    }
    let filter: Vec<String> = code
        .call_graph(step)
        .iter()
        .map(|(a, b)| format!("0x{a:x}+0x{:x}", b - a))
        .chain(returns.iter().map(|r| format!("0x{r:x}+0x2")))
        .collect();
    write_vectors(dir, vectors)?;
    let fifo = dir.join("trace.fifo");
    let _ = std::fs::remove_file(&fifo);
    nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::S_IRWXU).map_err(|e| M0Error::Io {
        path: fifo.clone(),
        source: e.into(),
    })?;
    let fifo_arg = fifo.to_string_lossy().into_owned();
    let filter = filter.join(",");
    let mut args = vec!["-d", "exec,nochain", "-dfilter", &filter, "-D", &fifo_arg];
    if trace == Trace::Instructions {
        args.extend(one_instruction_per_block()?);
    }
    let q = match Qemu::start(elf, dir, &args) {
        Ok(q) => q,
        Err(e) => {
            let _ = std::fs::remove_file(&fifo);
            return Err(e);
        }
    };
    let pid = q.child.id();
    // The FIFO's reader below blocks in `open` until QEMU opens it for writing; if QEMU ends
    // first (an error, Ctrl-C), the waiter opens it for writing itself until the reader is
    // through, so that the reader sees the end instead of waiting for ever.
    let opened = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let waiter = {
        let (fifo, opened) = (fifo.clone(), opened.clone());
        std::thread::spawn(move || {
            let done = q.finish();
            while !opened.load(std::sync::atomic::Ordering::Acquire) {
                use std::os::unix::fs::OpenOptionsExt as _;
                let _ = std::fs::OpenOptions::new()
                    .write(true)
                    .custom_flags(nix::fcntl::OFlag::O_NONBLOCK.bits())
                    .open(&fifo);
                std::thread::sleep(Duration::from_millis(10));
            }
            done
        })
    };
    // Steps, in order: (instructions, cycles).
    let mut steps: Vec<(u32, u32)> = Vec::new();
    let read = std::fs::File::open(&fifo).map_err(io(&fifo));
    opened.store(true, std::sync::atomic::Ordering::Release);
    if read.is_err() {
        // QEMU waits in its own open of the FIFO: end it now, not at the time-out.
        let _ = nix::sys::signal::killpg(
            nix::unistd::Pid::from_raw(pid as i32),
            nix::sys::signal::Signal::SIGKILL,
        );
    }
    let result = read.map(|f| {
        let mut blocks = std::collections::HashMap::new();
        // The last block's final conditional branch, waiting for the next block's address.
        let mut pending: Option<(u32, super::thumb::Insn)> = None;
        let mut in_step = false;
        for line in std::io::BufReader::with_capacity(1 << 20, f).lines() {
            let Ok(line) = line else { break };
            let Some(pc) = line
                .split_once('[')
                .and_then(|(_, r)| r.split('/').nth(1))
                .and_then(|p| u32::from_str_radix(p, 16).ok())
            else {
                continue;
            };
            if let Some((at, i)) = pending.take()
                && let Some(s) = steps.last_mut()
            {
                s.1 += i.cycles(pc != at + i.len);
            }
            if pc == step.0 {
                steps.push((0, 0));
                in_step = true;
            } else if returns.contains(&pc) {
                in_step = false;
            }
            if !in_step {
                continue;
            }
            let block = blocks.entry(pc).or_insert_with(|| match trace {
                Trace::Blocks => code.block(pc),
                Trace::Instructions => code.insn(pc).map(|i| vec![(pc, i)]).unwrap_or_default(),
            });
            let Some(s) = steps.last_mut() else { continue };
            for (n, &(at, i)) in block.iter().enumerate() {
                s.0 += 1;
                if n + 1 == block.len() && matches!(i.class, Class::BranchCond(_)) {
                    pending = Some((at, i));
                } else {
                    s.1 += i.cycles(false);
                }
            }
        }
    });
    let (status, output) = waiter.join().unwrap_or((None, String::new()));
    let _ = std::fs::remove_file(&fifo);
    result?;
    let Some(status) = status else {
        return Err(M0Error::Timeout(TIMEOUT, output));
    };
    if !status.success() {
        let exit = status.code().unwrap_or(-1);
        return Err(M0Error::Failed {
            exit,
            why: parse_report(exit, output.clone())
                .failure
                .unwrap_or_else(|| "no report".into()),
            output,
        });
    }
    let mut out = Vec::new();
    let mut from = 0usize;
    for r in runs {
        let n = r.inputs.len();
        let Some(s) = steps.get(from..from + n) else {
            return Err(M0Error::TraceShort {
                traced: steps.len(),
                expected: runs.iter().map(|r| r.inputs.len()).sum(),
                output,
            });
        };
        let (imax, (cmax_at, cmax)) = (
            s.iter().map(|x| x.0).max().unwrap_or(0),
            s.iter()
                .enumerate()
                .max_by_key(|(_, x)| x.1)
                .map_or((0, 0), |(i, x)| (i, x.1)),
        );
        out.push(RunCycles {
            label: r.label.clone(),
            steps: n as u32,
            instructions_mean: s.iter().map(|x| f64::from(x.0)).sum::<f64>() / n.max(1) as f64,
            instructions_max: imax,
            cycles_mean: s.iter().map(|x| f64::from(x.1)).sum::<f64>() / n.max(1) as f64,
            cycles_max: cmax,
            cycles_max_at: cmax_at as u32,
        });
        from += n;
    }
    Ok(out)
}
