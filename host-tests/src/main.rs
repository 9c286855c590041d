//! `pto`: simulate the hydraulic PTO bench, check the paper's facts, benchmark the solver.

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use pto_host::bench::{BAR, Bench};
use pto_host::paper::{self, Fact, Results, tol};
use pto_host::runner::{self, Outcome};
use pto_host::sim::{SimResult, SolverOptions};
use pto_host::{figures, perf, scenario};
use serde::Serialize;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "pto",
    version,
    about = "Hydraulic PTO test bench: full simulation, the paper's scenarios and facts"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// List the built-in scenarios.
    #[command(
        after_help = "Examples:\n  pto scenarios\n  pto scenarios --json > scenarios.json\n\nExit status:\n  0 always"
    )]
    Scenarios {
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Run one scenario (built-in name or TOML file): CSV, plots and a summary.
    #[command(
        after_help = "Examples:\n  pto simulate test3-ap10\n  pto simulate my-run.toml --bench my-bench.toml --out runs --json\n  pto simulate torque-cfg1-c14 --set hp_accumulator.volume_l=5\n\nExit status:\n  0 the run finished and its oil and energy balances close within 1e-4\n  1 a balance missed 1e-4\n  2 bad input (file, field, value, range and unit named), or the run failed\n  130 interrupted (nothing left half-written)"
    )]
    Simulate {
        /// Built-in scenario name (see `pto scenarios`) or a scenario TOML file.
        scenario: String,
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Output directory.
        #[arg(long, default_value = "out")]
        out: PathBuf,
        /// Machine-readable summary on stdout.
        #[arg(long)]
        json: bool,
        /// Override a bench value: `--set hp_accumulator.volume_l=5 --set cylinder[1].bore_mm=50`
        /// (any field of the bench file by its dotted path), or a fit parameter's short name
        /// (`trapped_air=0.04`, `cd=0.17`, `precharge=45`).
        #[arg(long = "set", value_name = "FIELD=VALUE")]
        set: Vec<String>,
        /// Solver relative tolerance, 1e-12 to 1e-2.
        #[arg(long, allow_hyphen_values = true, default_value_t = SolverOptions::default().rtol, value_parser = finite_in(1e-12, 1e-2, ""))]
        rtol: f64,
    },
    /// Run every built-in scenario, check the paper's ten facts, write the figures and a report.
    #[command(
        after_help = "Examples:\n  pto paper\n  pto paper --bench my-bench.toml --out out/my-paper --no-plots --json\n\nExit status:\n  0 every fact holds\n  1 a fact failed (the report says which)\n  2 bad input\n  130 interrupted (the previous output folder left whole)"
    )]
    Paper {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Output directory.
        #[arg(long, default_value = "out/paper")]
        out: PathBuf,
        /// Machine-readable output on stdout.
        #[arg(long)]
        json: bool,
        /// Skip the figures.
        #[arg(long)]
        no_plots: bool,
    },
    /// Run the fixed-point model against the full simulation on every built-in scenario, and the
    /// scheduler in closed loop; print the figures against the targets.
    #[command(
        after_help = "Examples:\n  pto validate\n  pto validate --filter test1 --no-loop --json\n\nExit status:\n  0 every target met in every scenario (and the closed loop, unless --no-loop)\n  1 a target missed (the row names it)\n  2 bad input"
    )]
    Validate {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Only scenarios whose name contains this.
        #[arg(long, default_value = "")]
        filter: String,
        /// Skip the closed-loop runs.
        #[arg(long)]
        no_loop: bool,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Per-step cost of the fixed-point model: host ns/step, state and code size for both thumb
    /// targets (builds pto-model for them; needs `rustup target add thumbv6m-none-eabi
    /// thumbv7em-none-eabihf`).
    #[command(
        after_help = "Examples:\n  pto model-cost --json\n\nExit status:\n  0 every budget met\n  1 a budget missed\n  2 the build failed"
    )]
    ModelCost {
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Make synthetic bench logs of the paper's experimental runs (64.5 / 67.2 / 72 / 101.5 bar
    /// starts; discharges from 102 / 84 / 71 bar) from the full simulation and the sensor model.
    #[command(
        after_help = "Examples:\n  pto synth-logs\n  pto synth-logs --set trapped_air=0.04 --set hp_accumulator.precharge_bar=45 --runs test3-ap10 --rate 50 --out logs\n\nExit status:\n  0 the logs were written\n  2 bad input\n  130 interrupted (the previous logs left whole)"
    )]
    SynthLogs {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Override a bench value: any field of the bench file by its dotted path
        /// (`--set hp_accumulator.precharge_bar=45 --set cylinder[1].bore_mm=50`), or a fit
        /// parameter's short name (`trapped_air=0.04`, `cd=0.17`, `precharge=45`).
        #[arg(long = "set", value_name = "NAME=VALUE")]
        set: Vec<String>,
        /// Built-in scenarios to log (default: the seven experimental runs).
        #[arg(long, value_delimiter = ',')]
        runs: Vec<String>,
        /// Sample rate, 0.1 to 1000 Hz.
        #[arg(long, allow_hyphen_values = true, default_value_t = 10.0, value_parser = finite_in(0.1, 1000.0, "Hz"))]
        rate: f64,
        /// Noise seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Output directory.
        #[arg(long, default_value = "out/logs")]
        out: PathBuf,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Fit bench parameters to bench logs by least squares over full simulations driven by the
    /// logged motion and valve aperture; writes the fitted bench file, the model-crate
    /// configuration for the firmware, a figure per log and `fit.json` into --out, swapped in
    /// whole.
    #[command(
        after_help = "Examples:\n  pto fit logs/*.csv\n  pto fit logs/*.csv --bench my-bench.toml --params trapped_air,cd --out fits/run1 --json\n\nExit status:\n  0 the fit converged\n  1 it did not\n  2 bad input\n  130 interrupted (the previous --out folder left whole)"
    )]
    Fit {
        /// Bench log CSV files.
        #[arg(required = true)]
        logs: Vec<PathBuf>,
        /// Bench parameter file to start from (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Parameters: trapped_air, cd, cd_slope (pressure-dependent Cd), precharge, hp_volume,
        /// leakage, area_table.
        #[arg(
            long,
            value_delimiter = ',',
            default_value = "trapped_air,cd,precharge"
        )]
        params: Vec<String>,
        /// Residual samples every this many seconds of each log, 0.01 to 60 s.
        #[arg(long, allow_hyphen_values = true, default_value_t = 0.5, value_parser = finite_in(0.01, 60.0, "s"))]
        spacing: f64,
        /// Iteration limit (Levenberg–Marquardt patience, × parameters + 1 evaluations), 1 to
        /// 10 000.
        #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..=10_000))]
        max_iter: u32,
        /// Output folder: fitted bench, model configuration, figures, fit.json (replaced whole;
        /// a folder of other files is refused).
        #[arg(long, default_value = "out/fit")]
        out: PathBuf,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Boot the QEMU firmware, ping it, print its decoded defmt log and its counters, stop it.
    /// Needs qemu-system-arm and the thumbv7em-none-eabihf target (it builds the firmware).
    #[command(
        after_help = "Examples:\n  pto qemu\n  pto qemu --follow     # keep it running, its log live; Ctrl-C stops it\n  pto qemu --json\n\nExit status:\n  0 the firmware answered and exited cleanly\n  1 it did not\n  2 QEMU or the build missing\n  130 interrupted (QEMU stopped, its socket removed)"
    )]
    Qemu {
        /// Print the log lines as they arrive and keep the firmware running until Ctrl-C (which
        /// stops QEMU and removes its socket; exit status 130).
        #[arg(long)]
        follow: bool,
        /// Machine-readable output (the firmware's Hello, its status and the host's link
        /// counts; the log goes to stderr).
        #[arg(long)]
        json: bool,
    },
    /// Processor-in-the-loop: the full simulation as the plant, the QEMU firmware as the
    /// controller in lockstep (hold P2, hold motor speed, overpressure trip).
    #[command(
        after_help = "Examples:\n  pto pil\n  pto pil --bench my-bench.toml --json\n\nExit status:\n  0 every check met\n  1 a check missed\n  2 bad input, QEMU or the build missing\n  130 interrupted"
    )]
    Pil {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Firmware cost: instructions per estimator + scheduler step (QEMU, -icount shift=0,
    /// TIM2), flash and static RAM of the bench and QEMU builds.
    #[command(
        after_help = "Examples:\n  pto fw-cost\n  pto fw-cost --json --trace step-costs.csv\n\nExit status:\n  0 every budget met (2 200 instructions a step, 128 KiB flash, 32 KiB RAM)\n  1 a budget missed\n  2 QEMU or the build missing\n  130 interrupted"
    )]
    FwCost {
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
        /// Also write the four-cylinder run's cost step by step (CSV: step, instructions,
        /// background units, each cylinder's phase) to this file, to see which steps set the
        /// maximum.
        #[arg(long, value_name = "CSV")]
        trace: Option<PathBuf>,
    },
    /// Wall time, real-time factor and accuracy of Test III and a 1000 s irregular sea.
    #[command(
        after_help = "Examples:\n  pto bench\n  pto bench --repeats 5 --json\n\nExit status:\n  0 every target met\n  1 a target missed\n  2 bad input"
    )]
    Bench {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Repeats (the median is reported).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
}

/// A clap parser for a finite number in [lo, hi] (`unit` for the message): NaN, infinities and
/// values out of range are argument errors (exit 2), never a hang or a solver failure.
fn finite_in(lo: f64, hi: f64, unit: &'static str) -> impl Fn(&str) -> Result<f64, String> + Clone {
    move |v: &str| {
        let x: f64 = v.parse().map_err(|_| format!("{v:?} is not a number"))?;
        if x.is_finite() && (lo..=hi).contains(&x) {
            Ok(x)
        } else {
            Err(format!(
                "{v} outside [{lo:e}, {hi:e}]{}{unit}",
                if unit.is_empty() { "" } else { " " }
            ))
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Ctrl-C or SIGTERM: QEMU children ended, their sockets removed, exit 130.
    if let Err(e) = pto_host::output::install_interrupt_handler() {
        eprintln!("warning: {e}");
    }
    let result = match cli.cmd {
        Cmd::Scenarios { json } => scenarios(json),
        Cmd::Simulate {
            scenario,
            bench,
            out,
            json,
            set,
            rtol,
        } => simulate(&scenario, bench.as_ref(), &set, &out, json, rtol),
        Cmd::Paper {
            bench,
            out,
            json,
            no_plots,
        } => paper_cmd(bench.as_ref(), &out, json, !no_plots),
        Cmd::Bench {
            bench,
            repeats,
            json,
        } => bench_cmd(bench.as_ref(), repeats, json),
        Cmd::Validate {
            bench,
            filter,
            no_loop,
            json,
        } => validate_cmd(bench.as_ref(), &filter, !no_loop, json),
        Cmd::ModelCost { json } => model_cost_cmd(json),
        Cmd::Qemu { follow, json } => qemu_cmd(follow, json),
        Cmd::SynthLogs {
            bench,
            set,
            runs,
            rate,
            seed,
            out,
            json,
        } => synth_logs_cmd(bench.as_ref(), &set, &runs, rate, seed, &out, json),
        Cmd::Fit {
            logs,
            bench,
            params,
            spacing,
            max_iter,
            out,
            json,
        } => fit_cmd(
            &logs,
            bench.as_ref(),
            &params,
            spacing,
            max_iter as usize,
            &out,
            json,
        ),
        Cmd::Pil { bench, json } => pil_cmd(bench.as_ref(), json),
        Cmd::FwCost { json, trace } => fw_cost_cmd(json, trace.as_deref()),
    };
    match result {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(1),
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}

fn load_bench(path: Option<&PathBuf>) -> Result<Bench> {
    Ok(Bench::load_or_reference(path)?)
}

/// The bench file with `--set` overrides applied, validated (errors name the field).
fn load_bench_with(path: Option<&PathBuf>, set: &[String]) -> Result<Bench> {
    if set.is_empty() {
        return load_bench(path);
    }
    let base = load_bench(path)?;
    let mut file = base.file;
    for kv in set {
        pto_host::fit::apply_override(&mut file, kv).map_err(anyhow::Error::msg)?;
    }
    Ok(Bench::from_file(
        file,
        &format!("{} with --set", base.source),
    )?)
}

fn scenarios(json: bool) -> Result<bool> {
    let all = scenario::builtin();
    if json {
        println!("{}", serde_json::to_string_pretty(&all)?);
    } else {
        println!("{:<22} {:>7}  description", "name", "length");
        for s in &all {
            println!("{:<22} {:>6.0}s  {}", s.name, s.duration_s, s.description);
        }
        println!(
            "\n{} scenarios. Write your own in the same TOML form (`pto scenarios --json` shows the fields).",
            all.len()
        );
    }
    Ok(true)
}

#[derive(Serialize)]
struct RunSummary {
    scenario: String,
    simulated_s: f64,
    wall_s: f64,
    steps: usize,
    p2_start_bar: f64,
    p2_end_bar: f64,
    p2_min_bar: f64,
    p2_max_bar: f64,
    lp_end_bar: f64,
    mean_injected_lpm: f64,
    mean_motor_flow_lpm: f64,
    mean_motor_speed_rpm: f64,
    peak_torque_nm: f64,
    balance_worst_rel: f64,
    balance_target_rel: f64,
    csv: String,
    figure: String,
}

fn summarize(name: &str, r: &SimResult, csv: &Path, fig: &Path) -> RunSummary {
    let t = &r.trace;
    let mean = |x: &[f64]| x.iter().sum::<f64>() / x.len().max(1) as f64;
    RunSummary {
        scenario: name.into(),
        simulated_s: *t.t.last().unwrap_or(&0.0),
        wall_s: r.stats.wall_s,
        steps: r.stats.steps,
        p2_start_bar: t.p2[0] / BAR,
        p2_end_bar: t.p2[t.len() - 1] / BAR,
        p2_min_bar: t.p2.iter().copied().fold(f64::INFINITY, f64::min) / BAR,
        p2_max_bar: t.p2.iter().copied().fold(f64::NEG_INFINITY, f64::max) / BAR,
        lp_end_bar: t.lp[t.len() - 1] / BAR,
        mean_injected_lpm: mean(&t.q_inj) * 6e4,
        mean_motor_flow_lpm: mean(&t.q_motor) * 6e4,
        mean_motor_speed_rpm: mean(&t.omega) * 30.0 / std::f64::consts::PI,
        peak_torque_nm: t.torque.iter().fold(0.0f64, |m, v| m.max(v.abs())),
        balance_worst_rel: r.balance.worst(),
        balance_target_rel: tol::BALANCE_REL,
        csv: csv.display().to_string(),
        figure: fig.display().to_string(),
    }
}

fn progress_bar(len_ms: u64, label: &str) -> ProgressBar {
    let pb = ProgressBar::with_draw_target(Some(len_ms), ProgressDrawTarget::stderr());
    pb.set_style(
        ProgressStyle::with_template("{prefix} [{bar:40}] {pos}/{len} ms simulated  {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_prefix(label.to_string());
    pb
}

fn simulate(
    name: &str,
    bench_path: Option<&PathBuf>,
    set: &[String],
    out: &Path,
    json: bool,
    rtol: f64,
) -> Result<bool> {
    let bench = load_bench_with(bench_path, set)?;
    let (s, base) = scenario::resolve(name)?;
    let prepared = s.prepare(&bench, &base)?;
    let solver = SolverOptions {
        rtol,
        ..SolverOptions::default()
    };
    let pb = progress_bar((s.duration_s * 1000.0) as u64, &s.name);
    let at = |t: f64| pb.set_position((t * 1000.0) as u64);
    let r = prepared.run(solver, Some(&at))?;
    pb.finish_and_clear();
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let csv = out.join(format!("{}.csv", s.name));
    let names: [String; 4] = std::array::from_fn(|i| bench.cylinders[i].name.clone());
    r.trace
        .write_csv(&csv, &names)
        .with_context(|| format!("cannot write {}", csv.display()))?;
    let duty: Vec<(usize, String)> = prepared
        .on_duty
        .iter()
        .enumerate()
        .filter(|(_, d)| **d)
        .map(|(i, _)| (i, bench.cylinders[i].name.clone()))
        .collect();
    let fig = figures::single(&s.name, &r.trace, &duty)
        .write(out)
        .map_err(anyhow::Error::msg)?;
    let sum = summarize(&s.name, &r, &csv, &fig);
    let pass = sum.balance_worst_rel <= tol::BALANCE_REL;
    if json {
        println!("{}", serde_json::to_string_pretty(&sum)?);
    } else {
        println!("{} — {}", s.name, s.description);
        println!(
            "  simulated {:.0} s in {:.3} s ({} steps)",
            sum.simulated_s, sum.wall_s, sum.steps
        );
        println!(
            "  P2 {:.2} -> {:.2} bar (min {:.2}, max {:.2}); LP at end {:.2} bar",
            sum.p2_start_bar, sum.p2_end_bar, sum.p2_min_bar, sum.p2_max_bar, sum.lp_end_bar
        );
        println!(
            "  mean injected {:.3} L/min, mean motor flow {:.3} L/min, mean motor speed {:.1} rpm, peak torque {:.0} N·m",
            sum.mean_injected_lpm,
            sum.mean_motor_flow_lpm,
            sum.mean_motor_speed_rpm,
            sum.peak_torque_nm
        );
        println!(
            "  oil/energy balance worst relative error {:.1e} (target {:.0e}): {}",
            sum.balance_worst_rel,
            tol::BALANCE_REL,
            if pass { "met" } else { "MISSED" }
        );
        println!("  wrote {} and {}", sum.csv, sum.figure);
    }
    Ok(pass)
}

#[derive(Serialize)]
struct PaperReport<'a> {
    bench: String,
    runs: usize,
    failed_runs: Vec<String>,
    wall_s: f64,
    facts: &'a [Fact],
    pass: bool,
    figures: Vec<String>,
}

fn paper_cmd(bench_path: Option<&PathBuf>, out: &Path, json: bool, plots: bool) -> Result<bool> {
    let bench = load_bench(bench_path)?;
    let all = scenario::builtin();
    let start = std::time::Instant::now();
    if !json {
        eprintln!(
            "running {} scenarios on {} threads…",
            all.len(),
            rayon::current_num_threads()
        );
    }
    let outcomes = runner::run_all(
        &bench,
        &all,
        SolverOptions::default(),
        std::io::stderr().is_terminal(),
    );
    let wall = start.elapsed().as_secs_f64();
    let facts = paper::check(&bench, &outcomes);
    let pass = facts.iter().all(|f| f.pass);
    // Every file of the run goes into a staging folder swapped in whole at the end: an
    // interrupted run leaves the previous figures, report and facts together.
    let stage = pto_host::output::StagedDir::new(out).map_err(anyhow::Error::msg)?;
    let dir = stage.path().to_path_buf();
    let mut fig_paths = Vec::new();
    if plots {
        let r = Results::new(&outcomes);
        for f in figures::all(&r) {
            let p = f.write(&dir).map_err(anyhow::Error::msg)?;
            let name = p.file_name().map(PathBuf::from).unwrap_or_default();
            fig_paths.push(out.join(name).display().to_string());
        }
    }
    let failed_runs: Vec<String> = outcomes
        .iter()
        .filter_map(|o| o.result.as_ref().err().cloned())
        .collect();
    let report = PaperReport {
        bench: bench.source.clone(),
        runs: outcomes.len(),
        failed_runs,
        wall_s: wall,
        facts: &facts,
        pass,
        figures: fig_paths,
    };
    let md = markdown_report(&report, &outcomes);
    write_atomic(&dir.join("report.md"), md.as_bytes())?;
    write_atomic(
        &dir.join("facts.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    stage.commit().map_err(anyhow::Error::msg)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", facts_table(&facts));
        println!(
            "\n{} runs in {:.1} s on {}; {} of 10 facts hold. Report: {}, figures: {} in {}",
            report.runs,
            wall,
            bench.source,
            facts.iter().filter(|f| f.pass).count(),
            out.join("report.md").display(),
            report.figures.len(),
            out.display()
        );
    }
    Ok(pass)
}

fn facts_table(facts: &[Fact]) -> String {
    let mut s = String::new();
    s.push_str(&format!("{:<3} {:<5} {}\n", "#", "", "fact — measured"));
    for f in facts {
        s.push_str(&format!(
            "{:<3} {:<5} {}\n",
            f.id,
            if f.pass { "PASS" } else { "FAIL" },
            f.statement
        ));
        s.push_str(&format!("{:<9} {}\n", "", f.measured));
    }
    s
}

fn markdown_report(r: &PaperReport, outcomes: &[Outcome]) -> String {
    let mut s = format!(
        "# Paper check on `{}`\n\n{} runs in {:.1} s. Result: **{}**.\n\n| # | fact | measured | |\n|---|---|---|---|\n",
        r.bench,
        r.runs,
        r.wall_s,
        if r.pass {
            "all facts hold"
        } else {
            "some facts FAIL"
        }
    );
    for f in r.facts {
        s.push_str(&format!(
            "| {} | {} | {} | {} |\n",
            f.id,
            f.statement,
            f.measured,
            if f.pass { "pass" } else { "**FAIL**" }
        ));
    }
    s.push_str("\n## Runs\n\n| scenario | wall (s) | steps | P2 start → end (bar) | worst balance error |\n|---|---|---|---|---|\n");
    for o in outcomes {
        match &o.result {
            Ok(res) => {
                let t = &res.trace;
                s.push_str(&format!(
                    "| {} | {:.3} | {} | {:.1} → {:.1} | {:.1e} |\n",
                    o.scenario.name,
                    res.stats.wall_s,
                    res.stats.steps,
                    t.p2[0] / BAR,
                    t.p2[t.len() - 1] / BAR,
                    res.balance.worst()
                ));
            }
            Err(e) => s.push_str(&format!("| {} | failed: {e} | | | |\n", o.scenario.name)),
        }
    }
    if !r.figures.is_empty() {
        s.push_str("\n## Figures\n\n");
        for f in &r.figures {
            let file = Path::new(f)
                .file_name()
                .map(|n| n.to_string_lossy().to_string())
                .unwrap_or_default();
            s.push_str(&format!("![{file}]({file})\n\n"));
        }
    }
    s
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    runner::write_atomic(path, bytes).map_err(anyhow::Error::msg)
}

fn bench_cmd(bench_path: Option<&PathBuf>, repeats: usize, json: bool) -> Result<bool> {
    if repeats == 0 {
        bail!("--repeats must be at least 1");
    }
    let bench = load_bench(bench_path)?;
    let rep = perf::measure(&bench, repeats).map_err(anyhow::Error::msg)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&rep)?);
    } else {
        println!(
            "{:<16} {:>10} {:>10} {:>10} {:>9} {:>9} {:>14}",
            "scenario", "simulated", "wall (s)", "RTF", "steps", "f evals", "P2 err (bar)"
        );
        for r in &rep.rows {
            println!(
                "{:<16} {:>9.0}s {:>10.3} {:>10.0} {:>9} {:>9} {:>14}",
                r.scenario,
                r.simulated_s,
                r.wall_s,
                r.real_time_factor,
                r.steps,
                r.rhs_evals,
                r.p2_max_err_bar.map_or("-".into(), |e| format!("{e:.4}"))
            );
        }
        for t in &rep.targets {
            println!("{t}");
        }
    }
    Ok(rep.pass)
}

fn validate_cmd(
    bench_path: Option<&PathBuf>,
    filter: &str,
    with_loop: bool,
    json: bool,
) -> Result<bool> {
    use pto_host::validate::{self, target};
    let bench = load_bench(bench_path)?;
    let sel: Vec<_> = scenario::builtin()
        .into_iter()
        .filter(|s| s.name.contains(filter))
        .collect();
    if sel.is_empty() {
        bail!("--filter {filter:?} matches no built-in scenario (see `pto scenarios`)");
    }
    if !json {
        eprintln!(
            "validating the model on {} scenarios{}…",
            sel.len(),
            if with_loop { " + closed loop" } else { "" }
        );
    }
    let rep = validate::run(&bench, &sel, with_loop);
    if json {
        println!("{}", serde_json::to_string_pretty(&rep)?);
        return Ok(rep.pass);
    }
    println!(
        "{:<20} {:>7} {:>6} {:>7} {:>11} {:>11} {:>6} {:>7} {:>7} {:>7} {:>8} {:>7}",
        "scenario",
        "P2 RMS",
        "P2 max",
        "no-HP",
        "2σ",
        "3σ",
        "empty",
        "torque",
        "motor",
        "fx P2",
        "fx T",
        ""
    );
    println!(
        "{:<20} {:>7} {:>6} {:>7} {:>11} {:>11} {:>6} {:>7} {:>7} {:>7} {:>8}",
        "(target)",
        format!("≤{}", target::P2_RMS_BAR),
        "-",
        format!("≤{}*", target::P2_MODEL_ONLY_MAX_BAR),
        format!("≥{}", target::COVER_2S * 100.0),
        format!("≥{}", target::COVER_3S * 100.0),
        format!("≤{}", target::EMPTY_FLAG_MS),
        format!("≤{}%", target::TORQUE_RMS_OF_PEAK * 100.0),
        format!("≤{}%", target::MOTOR_RMS_REL * 100.0),
        format!("≤{}*", target::FIXED_VS_F64_BAR),
        format!("≤{}*", target::FIXED_VS_F64_NM)
    );
    let pct = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{:.2}%", v * 100.0));
    for r in &rep.rows {
        let misses = &r.missed;
        println!(
            "{:<20} {:>7.3} {:>6.2} {:>7.3} {:>11} {:>11} {:>6} {:>7} {:>7} {:>7.4} {:>8.3}  {}",
            r.scenario,
            r.p2_rms_bar,
            r.p2_max_bar,
            r.p2_model_only_max_bar,
            format!(
                "{:.2}/{:.2}",
                r.cover_2s * 100.0,
                r.cover_2s_model_only * 100.0
            ),
            format!(
                "{:.2}/{:.2}",
                r.cover_3s * 100.0,
                r.cover_3s_model_only * 100.0
            ),
            r.empty_flag_delay_ms
                .map_or("-".to_string(), |d| format!("{d:.0}")),
            pct(r.torque_rms_of_peak),
            pct(r.motor_rms_rel),
            r.fixed_vs_f64_bar,
            r.fixed_vs_f64_nm,
            if misses.is_empty() {
                "ok".to_string()
            } else {
                format!("MISSED: {}", misses.join("; "))
            }
        );
    }
    println!(
        "σ coverage: with the transducer / without it (%). * no-HP ≤ {} bar in runs whose \
         estimate stays above the precharge + {} bar (else σ coverage and the empty flag, ms \
         after the bench's accumulator ran empty, judge it); fixed vs f64 ≤ {} bar and ≤ {} N·m \
         where P2 stays out of the cells at the precharge, else ≤ {} bar (torque not judged)",
        target::P2_MODEL_ONLY_MAX_BAR,
        target::PRECHARGE_MARGIN_BAR,
        target::FIXED_VS_F64_BAR,
        target::FIXED_VS_F64_NM,
        target::FIXED_VS_F64_CELL_BAR
    );
    for l in &rep.closed_loop {
        println!(
            "closed loop: {:<24} max deviation {:.4} (target {}) over {:.0}–{:.0} s: {}",
            l.name,
            l.max_deviation,
            l.target,
            l.window_s.0,
            l.window_s.1,
            if l.pass { "met" } else { "MISSED" }
        );
    }
    for e in &rep.errors {
        println!("error: {e}");
    }
    let ok = rep.rows.iter().filter(|r| r.pass).count();
    println!(
        "{ok}/{} scenarios meet every target; closed loop {}",
        rep.rows.len(),
        if !with_loop {
            "not run (--no-loop)"
        } else if rep.closed_loop.iter().all(|l| l.pass) {
            "met"
        } else {
            "MISSED"
        }
    );
    Ok(rep.pass)
}

fn model_cost_cmd(json: bool) -> Result<bool> {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let cost = pto_host::model_cost::measure(&workspace).map_err(anyhow::Error::msg)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&cost)?);
    } else {
        println!(
            "estimator + scheduler step on this host: {:.0} ns",
            cost.host_ns_per_step
        );
        println!(
            "state: {} bytes (target ≤ {}); coefficients (tables, RAM): {} bytes",
            cost.state_bytes,
            pto_host::model_cost::target::STATE_BYTES,
            cost.coefficient_bytes
        );
        for c in &cost.code {
            println!(
                "{:<24} per-step code {:>6} B (target ≤ {} B); whole crate .text {:>6} B, .rodata {:>5} B",
                c.target,
                c.step_code_bytes,
                pto_host::model_cost::target::FLASH_BYTES,
                c.text_bytes,
                c.rodata_bytes
            );
        }
    }
    Ok(cost.pass)
}

fn qemu_cmd(follow: bool, json: bool) -> Result<bool> {
    use pto_host::qemu::{self, Build, Qemu};
    use pto_model::protocol::{FromFirmware, ToFirmware};
    eprintln!("building the QEMU firmware…");
    let elf = qemu::build(Build::Qemu).map_err(anyhow::Error::msg)?;
    let mut q = Qemu::boot(&elf, follow).map_err(anyhow::Error::msg)?;
    let t0 = std::time::Instant::now();
    q.link
        .request(&ToFirmware::Ping(1), |r| {
            matches!(r, FromFirmware::Pong(1)).then_some(())
        })
        .map_err(anyhow::Error::msg)?;
    let ping = t0.elapsed();
    let st = pto_host::pil::status(&mut q).map_err(anyhow::Error::msg)?;
    let host = q.link.counts();
    if follow {
        eprintln!(
            "ping answered in {:.2} ms; following the firmware's log — Ctrl-C stops it",
            ping.as_secs_f64() * 1e3
        );
        eprint!("{}", pto_host::qemu::status_table(&st, &host));
        while q.running() {
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        anyhow::bail!("QEMU ended by itself");
    }
    q.link
        .send(&ToFirmware::Exit(0))
        .map_err(anyhow::Error::msg)?;
    let code = q
        .wait_exit(std::time::Duration::from_secs(10))
        .map_err(anyhow::Error::msg)?;
    if !follow {
        for l in q.log() {
            if json {
                eprintln!("{l}");
            } else {
                println!("{l}");
            }
        }
    }
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "ping_ms": ping.as_secs_f64() * 1e3,
                "status": st,
                "host_link": host,
                "exit_code": code,
            }))?
        );
    } else {
        println!("ping answered in {:.2} ms", ping.as_secs_f64() * 1e3);
        print!("{}", pto_host::qemu::status_table(&st, &host));
        println!("QEMU exit code {code}");
    }
    Ok(code == 0)
}

fn pil_cmd(bench: Option<&PathBuf>, json: bool) -> Result<bool> {
    use pto_host::qemu::{self, Build, Qemu};
    let bench = load_bench(bench)?;
    eprintln!("building the QEMU firmware…");
    let elf = qemu::build(Build::Qemu).map_err(anyhow::Error::msg)?;
    let checks: [(&str, pto_host::pil::CheckFn); 5] = [
        ("hold P2", pto_host::pil::check_hold_p2),
        ("hold speed", pto_host::pil::check_hold_speed),
        ("trip", pto_host::pil::check_trip),
        ("trip holds", pto_host::pil::check_trip_holds),
        (
            "motor behind a closed valve",
            pto_host::pil::check_motor_behind_closed_valve,
        ),
    ];
    let mut out = Vec::new();
    for (name, f) in checks {
        eprintln!("PIL {name}: running in lockstep with the firmware (≈ 2–3 ms per step)…");
        let q = Qemu::boot(&elf, false).map_err(anyhow::Error::msg)?;
        let (mut q, c) = f(q, &bench).map_err(anyhow::Error::msg)?;
        let _ = q.link.send(&pto_model::protocol::ToFirmware::Exit(0));
        if !json {
            println!(
                "{:<24} {:>8.3} {:<13} target {:<6} {}  ({} steps, {:.0} s)\n    {}",
                c.name,
                c.measured,
                c.unit,
                c.target,
                if c.pass { "ok" } else { "MISSED" },
                c.steps,
                c.wall_s,
                c.detail
            );
        }
        out.push(c);
    }
    let pass = out.iter().all(|c| c.pass);
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({ "checks": out, "pass": pass }))?
        );
    }
    Ok(pass)
}

fn fw_cost_cmd(json: bool, trace: Option<&Path>) -> Result<bool> {
    eprintln!(
        "building both firmwares and replaying the golden vectors (and a four-cylinder run) under QEMU…"
    );
    let r = pto_host::fw_cost::measure().map_err(anyhow::Error::msg)?;
    if let Some(path) = trace {
        eprintln!("tracing the four-cylinder run step by step…");
        let t = pto_host::fw_cost::trace_four_cylinders().map_err(anyhow::Error::msg)?;
        let mut csv = String::from("step,instructions,background_units,phases\n");
        for s in &t {
            csv += &format!(
                "{},{},{},{}\n",
                s.step, s.instructions, s.background_units, s.phases
            );
        }
        write_atomic(path, csv.as_bytes())?;
        eprintln!("wrote {}", path.display());
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        use pto_host::fw_cost::target;
        for s in &r.step {
            println!(
                "step ({:<27}) {} steps: mean {:.0}, max {} instructions (target ≤ {})",
                s.mode,
                s.steps,
                s.mean,
                s.max,
                target::STEP_INSTRUCTIONS
            );
        }
        for s in &r.size {
            println!(
                "{:<6} build: flash {} B, static RAM {} B{}",
                s.build,
                s.flash,
                s.ram,
                if s.build == "bench" {
                    format!(" (targets ≤ {} B, ≤ {} B)", target::FLASH, target::RAM)
                } else {
                    String::new()
                }
            );
        }
    }
    Ok(r.pass)
}

fn synth_logs_cmd(
    bench: Option<&PathBuf>,
    set: &[String],
    runs: &[String],
    rate: f64,
    seed: u64,
    out: &Path,
    json: bool,
) -> Result<bool> {
    use pto_host::fit;
    let b = load_bench_with(bench, set)?;
    let names: Vec<String> = if runs.is_empty() {
        fit::EXPERIMENTAL_RUNS
            .iter()
            .map(|s| s.to_string())
            .collect()
    } else {
        runs.to_vec()
    };
    // Written into a staging folder swapped in when every log is written (an interrupted run
    // leaves the previous logs whole).
    let stage = pto_host::output::StagedDir::new(out).map_err(anyhow::Error::msg)?;
    let staged = stage.path().to_path_buf();
    let pb = count_bar(names.len() as u64, "logs");
    let logs: Vec<Result<pto_host::benchlog::BenchLog, String>> = {
        use rayon::prelude::*;
        names
            .par_iter()
            .enumerate()
            .map(|(i, n)| {
                let r = fit::synth_log(&b, n, rate, seed + i as u64, &staged);
                pb.inc(1);
                r
            })
            .collect()
    };
    pb.finish_and_clear();
    let mut written = Vec::new();
    for l in logs {
        let l = l.map_err(anyhow::Error::msg)?;
        l.write().map_err(anyhow::Error::msg)?;
        let name = l.path.file_name().map(PathBuf::from).unwrap_or_default();
        written.push((out.join(name), l.t.len()));
    }
    stage.commit().map_err(anyhow::Error::msg)?;
    if json {
        let v: Vec<_> = written
            .iter()
            .map(|(p, n)| serde_json::json!({"file": p, "samples": n}))
            .collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for (p, n) in &written {
            println!("{} ({n} samples at {rate} Hz)", p.display());
        }
    }
    Ok(true)
}

fn count_bar(n: u64, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(n);
    if std::io::stderr().is_terminal() {
        pb.set_style(
            ProgressStyle::with_template(&format!("{{bar:40}} {{pos}}/{{len}} {what} {{elapsed}}"))
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
    } else {
        pb.set_draw_target(ProgressDrawTarget::hidden());
    }
    pb
}

fn fit_cmd(
    log_paths: &[PathBuf],
    bench_path: Option<&PathBuf>,
    params: &[String],
    spacing: f64,
    max_iter: usize,
    out: &Path,
    json: bool,
) -> Result<bool> {
    use pto_host::benchlog::BenchLog;
    use pto_host::fit;
    if !(0.01..=60.0).contains(&spacing) {
        bail!("--spacing {spacing}: outside [0.01, 60] s");
    }
    let bench = load_bench(bench_path)?;
    let logs: Vec<BenchLog> = log_paths
        .iter()
        .map(|p| BenchLog::read(p))
        .collect::<Result<_, _>>()?;
    for l in &logs {
        if l.config > bench.configs.len() {
            bail!(
                "{}: config {} but the bench has {} configurations",
                l.path.display(),
                l.config,
                bench.configs.len()
            );
        }
    }
    // Residual evaluations: (parameters + 1) × logs per Jacobian.
    let n_par = fit::params(params, &bench.file)
        .map_err(anyhow::Error::msg)?
        .len();
    let pb = ProgressBar::new(((n_par + 1) * logs.len() * (max_iter + 2)) as u64);
    if std::io::stderr().is_terminal() {
        pb.set_style(
            ProgressStyle::with_template("{spinner} {pos} simulations {elapsed} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_spinner()),
        );
    } else {
        pb.set_draw_target(ProgressDrawTarget::hidden());
    }
    let mut o = fit::fit(
        &bench.file,
        params,
        logs.clone(),
        spacing,
        max_iter,
        Some({
            let pb = pb.clone();
            std::sync::Arc::new(move || pb.inc(1))
        }),
    )
    .map_err(anyhow::Error::msg)?;
    pb.finish_and_clear();
    // Outputs, all in --out and swapped in whole: the fitted bench, the model configuration
    // for the firmware, the figures and the report.
    let stage = pto_host::output::StagedDir::new(out).map_err(anyhow::Error::msg)?;
    let stem = bench_path
        .and_then(|p| p.file_stem())
        .map_or("reference-bench".into(), |s| {
            s.to_string_lossy().into_owned()
        });
    let fitted = Bench::from_file(o.fitted.clone(), "fitted").context("the fitted bench")?;
    let mut text = format!(
        "# Fitted by `pto fit` to {} log(s) from {}; parameters: {}.\n",
        logs.len(),
        bench_path.map_or("the reference bench".into(), |p| p.display().to_string()),
        params.join(", ")
    );
    text.push_str(&toml::to_string_pretty(&o.fitted)?);
    let bench_name = format!("{stem}.fitted.toml");
    std::fs::write(stage.path().join(&bench_name), text.as_bytes())?;
    // The reduced model has a constant Cd: it takes the fitted Cd at 50 bar Δp.
    let model = pto_host::estimation::model_config(&fitted).map_err(anyhow::Error::msg)?;
    model
        .validate()
        .map_err(|e| anyhow::anyhow!("fitted model configuration: {e}"))?;
    let model_name = format!("{stem}.model.toml");
    std::fs::write(
        stage.path().join(&model_name),
        toml::to_string_pretty(&model)?.as_bytes(),
    )?;
    o.report.bench_file = Some(out.join(bench_name));
    o.report.model_file = Some(out.join(model_name));
    o.report.figures = fit_figures(&logs, &o, stage.path())?
        .iter()
        .filter_map(|f| f.file_name().map(|n| out.join(n)))
        .collect();
    std::fs::write(
        stage.path().join("fit.json"),
        serde_json::to_string_pretty(&o.report)?,
    )?;
    stage.commit().map_err(anyhow::Error::msg)?;
    let r = &o.report;
    if json {
        println!("{}", serde_json::to_string_pretty(r)?);
    } else {
        println!(
            "{:<14} {:>10} {:>10} {:>10}  unit  field",
            "parameter", "start", "fitted", "± 1σ"
        );
        for p in &r.params {
            println!(
                "{:<14} {:>10.4} {:>10.4} {:>10}  {:<4}  {}",
                p.name,
                p.start,
                p.value,
                p.sigma.map_or("—".into(), |s| format!("{s:.4}")),
                p.unit,
                p.key
            );
        }
        println!(
            "weighted residual RMS {:.3} → {:.3} ({:.1}× smaller; σ = {} bar, {} rpm)",
            r.residual_rms.0,
            r.residual_rms.1,
            r.improvement,
            fit::SIGMA_P2_BAR,
            fit::SIGMA_RPM
        );
        for l in &r.logs {
            println!(
                "  {:<24} P2 RMS {:.2} → {:.2} bar, motor {:.1} → {:.1} rpm",
                l.name, l.p2_rms_bar.0, l.p2_rms_bar.1, l.rpm_rms.0, l.rpm_rms.1
            );
        }
        println!(
            "{} simulations in {:.1} s; {}",
            r.simulations, r.wall_s, r.termination
        );
        if let (Some(b), Some(m)) = (&r.bench_file, &r.model_file) {
            println!(
                "fitted bench: {}\nmodel configuration for the firmware: {}",
                b.display(),
                m.display()
            );
        }
        for f in &r.figures {
            println!("figure: {}", f.display());
        }
    }
    Ok(r.converged)
}

fn fit_figures(
    logs: &[pto_host::benchlog::BenchLog],
    o: &pto_host::fit::FitOutcome,
    out: &Path,
) -> Result<Vec<PathBuf>> {
    use pto_host::plot::{Figure, Panel, Series};
    let mut files = Vec::new();
    for (k, l) in logs.iter().enumerate() {
        let t: Vec<f64> = l.t.iter().map(|t| t - l.t[0]).collect();
        let col = |v: &[pto_host::estimation::Truth],
                   f: fn(&pto_host::estimation::Truth) -> f64| {
            v.iter().map(f).collect::<Vec<f64>>()
        };
        let rel = |sim: &[f64], meas: &[f64], floor: f64| -> Vec<f64> {
            sim.iter()
                .zip(meas)
                .map(|(s, m)| (100.0 * (s - m) / m.abs().max(floor)).clamp(-30.0, 30.0))
                .collect()
        };
        let (p2b, p2a) = (col(&o.before[k], |x| x.p2), col(&o.after[k], |x| x.p2));
        let (rb, ra) = (
            col(&o.before[k], |x| x.motor_rpm),
            col(&o.after[k], |x| x.motor_rpm),
        );
        let s = |label: &str, y: Vec<f64>| Series {
            label: label.into(),
            x: t.clone(),
            y,
        };
        let fig = Figure {
            name: format!("fit-{}", l.name()),
            title: format!("{}: measured vs simulated", l.name()),
            panels: vec![
                Panel {
                    title: "HP pressure P2".into(),
                    x_label: "time (s)".into(),
                    y_label: "P2 (bar)".into(),
                    series: vec![
                        s("measured", l.p2.clone()),
                        s("simulated, start", p2b),
                        s("simulated, fitted", p2a.clone()),
                    ],
                },
                Panel {
                    title: "Motor speed".into(),
                    x_label: "time (s)".into(),
                    y_label: "speed (rpm)".into(),
                    series: vec![
                        s("measured", l.rpm.clone()),
                        s("simulated, start", rb),
                        s("simulated, fitted", ra.clone()),
                    ],
                },
                Panel {
                    title: "Fitted − measured, % (Fig. 26 view; clipped to ±30 %)".into(),
                    x_label: "time (s)".into(),
                    y_label: "difference (%)".into(),
                    series: vec![
                        s("P2", rel(&p2a, &l.p2, 1.0)),
                        s(
                            "motor speed (of max(speed, 50 rpm))",
                            rel(&ra, &l.rpm, 50.0),
                        ),
                    ],
                },
            ],
            cols: 1,
        };
        files.push(fig.write(out).map_err(anyhow::Error::msg)?);
    }
    Ok(files)
}
