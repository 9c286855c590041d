//! `pto scenarios`, `simulate`, `paper` and `bench`: the simulation's commands.

use super::{finite_in, load_bench, load_bench_with, progress_bar, write_atomic};
use anyhow::{Context, Result, bail};
use pto_host::figures;
use pto_host::paper::{self, Fact, Results, tol};
use pto_host::perf;
use pto_host::runner::{self, Outcome};
use pto_host::sim::bench::{BAR, LPM};
use pto_host::sim::power::{Power, percent_text};
use pto_host::sim::scenario;
use pto_host::sim::solver::{SimResult, SolverOptions};
use serde::Serialize;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

/// `pto scenarios`'s options.
#[derive(clap::Args)]
pub(crate) struct ScenariosArgs {
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
}

/// `pto simulate`'s options.
#[derive(clap::Args)]
pub(crate) struct SimulateArgs {
    /// Built-in scenario name (see `pto scenarios`) or a scenario TOML file.
    pub scenario: String,
    /// Bench parameter file (default: the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Output directory.
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Machine-readable summary on stdout.
    #[arg(long)]
    pub json: bool,
    /// Override a bench value: `--set hp_accumulator.volume_l=5 --set cylinder[0].bore_mm=50`
    /// (any field of the bench file by its dotted path; lists count from 0 in file order,
    /// `cylinder[0]` is HC3.1), or a fit parameter's short name (`trapped_air=0.04`,
    /// `cd=0.17`, `precharge=45`).
    #[arg(long = "set", value_name = "FIELD=VALUE")]
    pub set: Vec<String>,
    /// Solver relative tolerance, 1e-12 to 1e-2.
    #[arg(long, allow_hyphen_values = true, default_value_t = SolverOptions::default().rtol, value_parser = finite_in(1e-12, 1e-2, ""))]
    pub rtol: f64,
}

/// `pto paper`'s options.
#[derive(clap::Args)]
pub(crate) struct PaperArgs {
    /// Bench parameter file (default: the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Output directory.
    #[arg(long, default_value = "out/paper")]
    pub out: PathBuf,
    /// Machine-readable output on stdout.
    #[arg(long)]
    pub json: bool,
    /// Skip the figures.
    #[arg(long)]
    pub no_plots: bool,
}

/// `pto perf`'s options.
#[derive(clap::Args)]
pub(crate) struct PerfArgs {
    /// Bench parameter file (default: the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Repeats (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Also run this many Test III runs on every core and time the batch (target: 1 000
    /// in 40 s).
    #[arg(long, value_name = "RUNS")]
    pub batch: Option<usize>,
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
}

pub(crate) fn scenarios(a: &ScenariosArgs) -> Result<bool> {
    let json = a.json;
    let all = scenario::every_builtin();
    if json {
        println!("{}", serde_json::to_string_pretty(&all)?);
    } else {
        println!("{:<22} {:>7}  description", "name", "length");
        for s in &all {
            println!("{:<22} {:>6.0}s  {}", s.name, s.duration_s, s.description);
        }
        println!(
            "\n{} scenarios: the paper's runs (`pto paper`) and the estimator's sea family \
             (`sea-*`, `sine-empty-start`: `pto validate`). Write your own in the same TOML form \
             (`pto scenarios --json` shows the fields).",
            all.len()
        );
    }
    Ok(true)
}

#[derive(Serialize)]
pub(crate) struct RunSummary {
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
    power: Power,
    csv: String,
    figure: String,
    power_figure: String,
    loss_figure: String,
}

pub(crate) fn summarize(name: &str, r: &SimResult, csv: &Path, figs: [&Path; 3]) -> RunSummary {
    let t = &r.trace;
    let mean = |x: &[f64]| x.iter().sum::<f64>() / x.len().max(1) as f64;
    RunSummary {
        scenario: name.into(),
        simulated_s: *t.t_s.last().unwrap_or(&0.0),
        wall_s: r.stats.wall_s,
        steps: r.stats.steps,
        p2_start_bar: t.p2_pa[0] / BAR,
        p2_end_bar: t.p2_pa[t.len() - 1] / BAR,
        p2_min_bar: t.p2_pa.iter().copied().fold(f64::INFINITY, f64::min) / BAR,
        p2_max_bar: t.p2_pa.iter().copied().fold(f64::NEG_INFINITY, f64::max) / BAR,
        lp_end_bar: t.lp_pa[t.len() - 1] / BAR,
        mean_injected_lpm: mean(&t.q_inj_m3_s) * LPM,
        mean_motor_flow_lpm: mean(&t.q_motor_m3_s) * LPM,
        mean_motor_speed_rpm: mean(&t.omega_rad_s) * 30.0 / std::f64::consts::PI,
        peak_torque_nm: t.torque_nm.iter().fold(0.0f64, |m, v| m.max(v.abs())),
        balance_worst_rel: r.balance.worst(),
        balance_target_rel: tol::BALANCE_REL,
        power: r.power,
        csv: csv.display().to_string(),
        figure: figs[0].display().to_string(),
        power_figure: figs[1].display().to_string(),
        loss_figure: figs[2].display().to_string(),
    }
}

pub(crate) fn simulate(a: &SimulateArgs) -> Result<bool> {
    let (name, bench_path, set, out, json, rtol) = (
        a.scenario.as_str(),
        a.bench.as_ref(),
        a.set.as_slice(),
        a.out.as_path(),
        a.json,
        a.rtol,
    );
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
    let fig = figures::single(&s.name, &r.trace, &duty).write(out)?;
    let power_fig = figures::power_traces(&s.name, &r.trace).write(out)?;
    let loss_fig = figures::loss_breakdown(&s.name, &r.power).write(out)?;
    let sum = summarize(&s.name, &r, &csv, [&fig, &power_fig, &loss_fig]);
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
        print!("{}", power_lines(&sum.power));
        println!(
            "  oil/energy balance worst relative error {:.1e} (target {:.0e}): {}",
            sum.balance_worst_rel,
            tol::BALANCE_REL,
            if pass { "met" } else { "MISSED" }
        );
        println!(
            "  wrote {}, {}, {}, {} (and their .svg)",
            sum.csv, sum.figure, sum.power_figure, sum.loss_figure
        );
    }
    Ok(pass)
}

/// The power lines of a run's summary: the path from the shaft to the generator, the losses by
/// cause and the storage.
pub(crate) fn power_lines(p: &Power) -> String {
    let mut causes: Vec<(&str, f64)> = p.losses.by_cause().to_vec();
    causes.sort_by(|a, b| b.1.total_cmp(&a.1));
    let losses: Vec<String> = causes.iter().map(|(l, w)| format!("{l} {w:.1}")).collect();
    let st = &p.stored_w;
    format!(
        "  power (mean): shaft input {:.1} W -> pumped {:.1} W -> motor shaft {:.1} W -> generator {:.1} W; \
         efficiency {} ({} counting what the run stored)\n  \
         losses (W): {}; into storage {:.1} W (accumulators {:.1}, oil {:.1}, inertia {:.2}); \
         closes to {:.1e}\n",
        p.input_w,
        p.pumped_w,
        p.motor_shaft_w,
        p.generator_w,
        percent_text(p.efficiency),
        percent_text(p.efficiency_with_storage),
        losses.join(", "),
        st.total_w(),
        st.accumulators_w,
        st.oil_w,
        st.inertia_w,
        p.closure_rel
    )
}

/// One run's mean powers in the paper report.
#[derive(Serialize)]
pub(crate) struct RunPower {
    scenario: String,
    group: String,
    power: Power,
}

#[derive(Serialize)]
pub(crate) struct PaperReport<'a> {
    bench: String,
    runs: usize,
    failed_runs: Vec<String>,
    wall_s: f64,
    facts: &'a [Fact],
    pass: bool,
    figures: Vec<String>,
    power: Vec<RunPower>,
}

pub(crate) fn paper_cmd(a: &PaperArgs) -> Result<bool> {
    let (bench_path, out, json, plots) = (a.bench.as_ref(), a.out.as_path(), a.json, !a.no_plots);
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
    let bars = std::io::stderr()
        .is_terminal()
        .then(|| super::ScenarioBars::new(all.len()));
    let outcomes = runner::run_all(
        &bench,
        &all,
        SolverOptions::default(),
        bars.as_ref().map(|b| b as &dyn runner::RunProgress),
    );
    if let Some(b) = &bars {
        b.finish();
    }
    let wall = start.elapsed().as_secs_f64();
    let facts = paper::check(&bench, &outcomes);
    let pass = facts.iter().all(|f| f.pass);
    // Every file of the run goes into a staging folder swapped in whole at the end: an
    // interrupted run leaves the previous figures, report and facts together.
    let stage = pto_host::output::StagedDir::new(out)?;
    let dir = stage.path().to_path_buf();
    let mut fig_paths = Vec::new();
    if plots {
        let r = Results::new(&outcomes);
        let mut written = Vec::new();
        for f in figures::all(&r) {
            written.push(f.write(&dir)?);
        }
        // Where the power goes: Test III at 10 % and the irregular sea.
        for name in ["test3-ap10", "irregular-sea"] {
            if let Some(res) = r.get(name) {
                written.push(figures::power_traces(name, &res.trace).write(&dir)?);
                written.push(figures::loss_breakdown(name, &res.power).write(&dir)?);
            }
        }
        for p in written {
            let name = p.file_name().map(PathBuf::from).unwrap_or_default();
            fig_paths.push(out.join(name).display().to_string());
        }
    }
    let power: Vec<RunPower> = outcomes
        .iter()
        .filter_map(|o| {
            o.result.as_ref().ok().map(|res| RunPower {
                scenario: o.scenario.name.clone(),
                group: o.scenario.group.clone(),
                power: res.power,
            })
        })
        .collect();
    let failed_runs: Vec<String> = outcomes
        .iter()
        .filter_map(|o| o.result.as_ref().err().map(|e| pto_host::error_chain(e)))
        .collect();
    let report = PaperReport {
        bench: bench.source.clone(),
        runs: outcomes.len(),
        failed_runs,
        wall_s: wall,
        facts: &facts,
        pass,
        figures: fig_paths,
        power,
    };
    let md = markdown_report(&report, &outcomes);
    write_atomic(&dir.join("report.md"), md.as_bytes())?;
    write_atomic(
        &dir.join("facts.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    stage.commit()?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", facts_table(&facts));
        print!("{}", power_by_group(&report.power));
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

/// Per group of runs: the ranges of mean input, generator power and efficiency.
pub(crate) fn power_by_group(runs: &[RunPower]) -> String {
    let mut groups: Vec<&str> = Vec::new();
    for r in runs {
        if !groups.contains(&r.group.as_str()) {
            groups.push(&r.group);
        }
    }
    let mut s = String::from("\npower by group of runs (means over each run):\n");
    s.push_str(&format!(
        "{:<14} {:>4} {:>17} {:>17} {:>17}\n",
        "group", "runs", "shaft input (W)", "generator (W)", "efficiency (%)"
    ));
    let range = |v: &[f64], k: f64| {
        let lo = v.iter().copied().fold(f64::INFINITY, f64::min) * k;
        let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max) * k;
        format!("{lo:.1}–{hi:.1}")
    };
    for g in groups {
        let rs: Vec<&RunPower> = runs.iter().filter(|r| r.group == g).collect();
        let input: Vec<f64> = rs.iter().map(|r| r.power.input_w).collect();
        let gen_w: Vec<f64> = rs.iter().map(|r| r.power.generator_w).collect();
        let eff: Vec<f64> = rs.iter().filter_map(|r| r.power.efficiency).collect();
        s.push_str(&format!(
            "{:<14} {:>4} {:>17} {:>17} {:>17}\n",
            g,
            rs.len(),
            range(&input, 1.0),
            range(&gen_w, 1.0),
            if eff.is_empty() {
                "-".into()
            } else {
                range(&eff, 100.0)
            }
        ));
    }
    s
}

pub(crate) fn facts_table(facts: &[Fact]) -> String {
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

pub(crate) fn markdown_report(r: &PaperReport, outcomes: &[Outcome]) -> String {
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
    s.push_str("\n## Runs\n\n| scenario | wall (s) | steps | P2 start → end (bar) | shaft input (W) | generator (W) | efficiency | worst balance error |\n|---|---|---|---|---|---|---|---|\n");
    for o in outcomes {
        match &o.result {
            Ok(res) => {
                let t = &res.trace;
                s.push_str(&format!(
                    "| {} | {:.3} | {} | {:.1} → {:.1} | {:.1} | {:.1} | {} | {:.1e} |\n",
                    o.scenario.name,
                    res.stats.wall_s,
                    res.stats.steps,
                    t.p2_pa[0] / BAR,
                    t.p2_pa[t.len() - 1] / BAR,
                    res.power.input_w,
                    res.power.generator_w,
                    percent_text(res.power.efficiency),
                    res.balance.worst()
                ));
            }
            Err(e) => s.push_str(&format!(
                "| {} | failed: {} | | | | | | |\n",
                o.scenario.name,
                pto_host::error_chain(e)
            )),
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

pub(crate) fn perf_cmd(a: &PerfArgs) -> Result<bool> {
    let (bench_path, repeats, batch, json) = (a.bench.as_ref(), a.repeats, a.batch, a.json);
    if repeats == 0 {
        bail!("--repeats must be at least 1");
    }
    if batch == Some(0) {
        bail!("--batch must be at least 1 run");
    }
    let bench = load_bench(bench_path)?;
    let rep = perf::measure(&bench, repeats, batch)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&rep)?);
    } else {
        println!(
            "{:<14} {:<22} {:>10} {:>9} {:>7} {:>8} {:>8} {:>13}",
            "scenario",
            "variant",
            "simulated",
            "wall (s)",
            "RTF",
            "steps",
            "f evals",
            "P2 err (bar)"
        );
        for r in &rep.rows {
            println!(
                "{:<14} {:<22} {:>9.0}s {:>9.3} {:>7.0} {:>8} {:>8} {:>13.1e}",
                r.scenario,
                r.variant,
                r.simulated_s,
                r.wall_s,
                r.real_time_factor,
                r.steps,
                r.rhs_evals,
                r.p2_max_err_bar
            );
        }
        for t in &rep.targets {
            println!("{t}");
        }
    }
    Ok(rep.pass)
}
