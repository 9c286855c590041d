//! `pto synth-logs` and `fit`: bench logs and the fit to them.

use super::{count_bar, finite_in, load_bench, load_bench_with, name_value};
use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use pto_host::sim::bench::Bench;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

/// `pto synth-logs`'s options.
#[derive(clap::Args)]
pub(crate) struct SynthLogsArgs {
    /// Bench parameter file (default: the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Override a bench value: any field of the bench file by its dotted path
    /// (`--set hp_accumulator.precharge_bar=45 --set cylinder[0].bore_mm=50`; lists count
    /// from 0, `cylinder[0]` is HC3.1), or a fit parameter's short name (`trapped_air=0.04`,
    /// `cd=0.17`, `precharge=45`).
    #[arg(long = "set", value_name = "NAME=VALUE")]
    pub set: Vec<String>,
    /// Built-in scenarios to log (default: the seven experimental runs).
    #[arg(long, value_delimiter = ',', conflicts_with = "campaign")]
    pub runs: Vec<String>,
    /// A campaign file (`pto plan`): one log per segment, at the segment's rate.
    #[arg(long)]
    pub campaign: Option<PathBuf>,
    /// Sample rate, 0.1 to 1000 Hz.
    #[arg(long, allow_hyphen_values = true, default_value_t = 10.0, value_parser = finite_in(0.1, 1000.0, "Hz"))]
    pub rate: f64,
    /// Noise seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output directory.
    #[arg(long, default_value = "out/logs")]
    pub out: PathBuf,
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
}

/// `pto fit`'s options.
#[derive(clap::Args)]
pub(crate) struct FitArgs {
    /// Bench log CSV files.
    #[arg(required = true)]
    pub logs: Vec<PathBuf>,
    /// Bench parameter file to start from (default: the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Parameters: trapped_air, cd, cd_slope (pressure-dependent Cd), precharge, hp_volume,
    /// leakage, area_table.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "trapped_air,cd,precharge"
    )]
    pub params: Vec<String>,
    /// Residual samples every this many seconds of each log, 0 (every sample) to 60 s
    /// (default: 0.5 s, and every sample of a campaign's log: one with a complete
    /// `.segment.toml` sidecar).
    #[arg(long, allow_hyphen_values = true, value_parser = finite_in(0.0, 60.0, "s"))]
    pub spacing: Option<f64>,
    /// Iteration limit (Levenberg–Marquardt patience, × parameters + 1 evaluations), 1 to
    /// 10 000.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    pub max_iter: u32,
    /// Simulations the fit may run, 10 to 10 000 000 (its time limit, reproducible: ≈ 60 s
    /// on 2 cores for the seven experimental runs); past it the fit stops and fails.
    #[arg(long, default_value_t = pto_host::fit::DEFAULT_MAX_SIMULATIONS as u64, value_parser = clap::value_parser!(u64).range(10..=10_000_000))]
    pub max_simulations: u64,
    /// Output folder: fitted bench, model configuration, figures, fit.json (replaced whole;
    /// a folder of other files is refused).
    #[arg(long, default_value = "out/fit")]
    pub out: PathBuf,
    /// P2 sensor noise σ, bar (default: estimated from the logs).
    #[arg(long, value_parser = finite_in(0.001, 50.0, "bar"))]
    noise_p2: Option<f64>,
    /// Motor speed sensor noise σ, rpm (default: estimated from the logs).
    #[arg(long, value_parser = finite_in(0.01, 500.0, "rpm"))]
    pub noise_rpm: Option<f64>,
    /// LP sensor noise σ, bar (default: estimated from the logs).
    #[arg(long, value_parser = finite_in(0.001, 50.0, "bar"))]
    pub noise_lp: Option<f64>,
    /// Largest reduced χ² of the residuals against the noise that passes (raise it knowingly
    /// when the model's own error exceeds the sensors' noise), 1 to 10 000.
    #[arg(long, default_value_t = pto_host::fit::DEFAULT_LIMITS.max_chi2, value_parser = finite_in(1.0, 10_000.0, ""))]
    max_chi2: f64,
    /// Precision a parameter needs, in its unit (repeatable; e.g. `--precision
    /// trapped_air=0.01`): the fit fails its `precision` check when the parameter's 3σ
    /// exceeds it. Defaults: trapped_air 0.005, cd 3 %, precharge 2 bar, leakage 0.01,
    /// hp_volume 5 %, cd_slope 0.05, area-table factors 10 %.
    #[arg(long, value_name = "NAME=VALUE", value_parser = name_value)]
    pub precision: Vec<(String, f64)>,
    /// Write the fitted bench and model configuration even when a check failed (their first
    /// line then says which); without it they are written only when every check passed.
    #[arg(long)]
    pub write_anyway: bool,
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
}

#[allow(clippy::too_many_arguments)]
pub(crate) fn synth_logs_cmd(a: &SynthLogsArgs) -> Result<bool> {
    let (bench, set, runs, campaign, rate, seed, out, json) = (
        a.bench.as_ref(),
        a.set.as_slice(),
        a.runs.as_slice(),
        a.campaign.as_deref(),
        a.rate,
        a.seed,
        a.out.as_path(),
        a.json,
    );
    use pto_host::fit;
    use pto_host::sim::scenario::{Scenario, builtin_named};
    let b = load_bench_with(bench, set)?;
    // (run, its rate)
    let segments = campaign
        .map(|c| pto_host::plan::Campaign::load(c, &b))
        .transpose()?
        .map(|c| c.segment);
    let jobs: Vec<(Scenario, f64)> = match &segments {
        Some(segs) => segs.iter().map(|s| (s.run.clone(), s.rate_hz)).collect(),
        None => {
            let names: Vec<String> = if runs.is_empty() {
                fit::EXPERIMENTAL_RUNS
                    .iter()
                    .map(|s| s.to_string())
                    .collect()
            } else {
                runs.to_vec()
            };
            names
                .iter()
                .map(|n| {
                    builtin_named(n)
                        .map(|s| (s, rate))
                        .ok_or_else(|| fit::FitError::UnknownScenario(n.clone()))
                })
                .collect::<Result<_, _>>()?
        }
    };
    // Written into a staging folder swapped in when every log is written (an interrupted run
    // leaves the previous logs whole).
    let stage = pto_host::output::StagedDir::new(out)?;
    let staged = stage.path().to_path_buf();
    let pb = count_bar(jobs.len() as u64, "logs");
    // Each log written as it is made (a campaign's with its sidecar), in the staging folder.
    let campaign_name = campaign.map(|c| c.display().to_string());
    let logs: Vec<Result<pto_host::sim::benchlog::BenchLog>> = {
        use rayon::prelude::*;
        jobs.par_iter()
            .enumerate()
            .map(|(i, (s, hz))| {
                let seed = seed + i as u64;
                let r = match (&campaign_name, &segments) {
                    (Some(c), Some(segs)) => {
                        pto_host::plan::synth_segment_log(&b, c, i, &segs[i], seed, &staged)
                            .map_err(|e| anyhow::anyhow!(e))
                    }
                    _ => fit::synth_scenario_log(
                        &b,
                        s,
                        *hz,
                        pto_host::validation::sensors::SensorSpec::default(),
                        seed,
                        &staged,
                    )
                    .map_err(anyhow::Error::from)
                    .and_then(|l| {
                        l.write()?;
                        Ok(l)
                    }),
                };
                pb.inc(1);
                r
            })
            .collect()
    };
    pb.finish_and_clear();
    let mut written = Vec::new();
    for l in logs {
        let l = l?;
        let name = l.path.file_name().map(PathBuf::from).unwrap_or_default();
        let hz = ((l.t.len() as f64 - 1.0) / (l.t[l.t.len() - 1] - l.t[0]).max(1e-9) * 1e4).round()
            / 1e4;
        written.push((out.join(name), l.t.len(), hz));
    }
    stage.commit()?;
    if json {
        let v: Vec<_> = written
            .iter()
            .map(|(p, n, hz)| serde_json::json!({"file": p, "samples": n, "rate_hz": hz}))
            .collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for (p, n, hz) in &written {
            println!("{} ({n} samples at {hz} Hz)", p.display());
        }
    }
    Ok(true)
}

pub(crate) fn fit_cmd(a: &FitArgs) -> Result<bool> {
    let (log_paths, bench_path, out, write_anyway, json) = (
        a.logs.as_slice(),
        a.bench.as_ref(),
        a.out.as_path(),
        a.write_anyway,
        a.json,
    );
    let mut opts = pto_host::fit::FitOptions {
        params: a.params.clone(),
        spacing_s: a.spacing.unwrap_or(0.5),
        dense_logs: if a.spacing.is_some() {
            pto_host::fit::DenseLogs::None
        } else {
            pto_host::fit::DenseLogs::Campaign
        },
        max_iter: a.max_iter as usize,
        max_simulations: a.max_simulations as usize,
        noise_p2_bar: a.noise_p2,
        noise_rpm: a.noise_rpm,
        noise_lp_bar: a.noise_lp,
        limits: pto_host::fit::Limits {
            max_chi2: a.max_chi2,
            ..pto_host::fit::DEFAULT_LIMITS
        },
        precision: a.precision.clone(),
        progress: None,
    };
    use pto_host::fit;
    use pto_host::sim::benchlog::BenchLog;
    let bench = load_bench(bench_path)?;
    let input_text = match bench_path {
        Some(p) => std::fs::read_to_string(p).with_context(|| p.display().to_string())?,
        None => pto_host::sim::bench::REFERENCE_BENCH_TOML.to_string(),
    };
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
    // Implausible columns are said before the minute of fitting, not only in the verdict.
    if !json {
        for f in logs.iter().flat_map(fit::sanity) {
            eprintln!(
                "{}: {} `{}`: {}",
                match f.severity {
                    fit::Severity::Error => "error",
                    fit::Severity::Warning => "warning",
                },
                f.file.display(),
                f.column,
                f.message
            );
        }
    }
    fit::params(&opts.params, &bench.file)?;
    // Simulations run, against the budget that stops the fit.
    let pb = ProgressBar::new(opts.max_simulations as u64);
    if std::io::stderr().is_terminal() {
        pb.set_style(
            ProgressStyle::with_template("{spinner} {pos}/{len} simulations {elapsed} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_spinner()),
        );
    } else {
        pb.set_draw_target(ProgressDrawTarget::hidden());
    }
    opts.progress = Some({
        let pb = pb.clone();
        std::sync::Arc::new(move || pb.inc(1))
    });
    let mut o = fit::fit(&bench.file, logs.clone(), &opts)?;
    pb.finish_and_clear();
    // Outputs, all in --out and swapped in whole: the fitted bench, the model configuration
    // for the firmware, the figures and the report.
    let stage = pto_host::output::StagedDir::new(out)?;
    let stem = bench_path
        .and_then(|p| p.file_stem())
        .map_or("reference-bench".into(), |s| {
            s.to_string_lossy().into_owned()
        });
    let failed: Vec<&str> = o
        .report
        .checks
        .iter()
        .filter(|c| !c.passed)
        .map(|c| c.name)
        .collect();
    // The fitted bench and the firmware's configuration only from a fit that passed every
    // check (or asked for anyway, their first line saying which checks failed).
    let write = o.report.passed || write_anyway;
    let mark = if o.report.passed {
        String::new()
    } else {
        format!(
            "# NOT A FITTED BENCH: the fit failed its checks ({}); written with --write-anyway.\n",
            failed.join(", ")
        )
    };
    if write {
        let fitted = Bench::from_file(o.fitted.clone(), "fitted").context("the fitted bench")?;
        let mut text = mark.clone();
        text.push_str(&format!(
            "# Fitted by `pto fit` to {} log(s) from {}; parameters: {}; reduced χ² {:.2}.\n",
            logs.len(),
            bench_path.map_or("the reference bench".into(), |p| p.display().to_string()),
            opts.params.join(", "),
            o.report.chi2_reduced
        ));
        text.push_str(&fit::fitted_bench_text(
            &input_text,
            &bench.file,
            &o.fitted,
        )?);
        let bench_name = format!("{stem}.fitted.toml");
        std::fs::write(stage.path().join(&bench_name), text.as_bytes())?;
        // The reduced model has a constant Cd: it takes the fitted Cd at 50 bar Δp.
        let model = pto_host::validation::model_config(&fitted)?;
        model.validate().context("fitted model configuration")?;
        let model_name = format!("{stem}.model.toml");
        let mut text = mark;
        text.push_str(&toml::to_string_pretty(&model)?);
        std::fs::write(stage.path().join(&model_name), text.as_bytes())?;
        o.report.bench_file = Some(out.join(bench_name));
        o.report.model_file = Some(out.join(model_name));
    }
    o.report.figures = fit_figures(&logs, &o, stage.path())?
        .iter()
        .filter_map(|f| f.file_name().map(|n| out.join(n)))
        .collect();
    let report_json = serde_json::to_string_pretty(&o.report)?;
    std::fs::write(stage.path().join("fit.json"), &report_json)?;
    stage.commit()?;
    let r = &o.report;
    if json {
        println!("{report_json}");
    } else {
        print_report(r, &failed);
    }
    Ok(r.passed)
}

fn print_report(r: &pto_host::fit::FitReport, failed: &[&str]) {
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
        "σ: the Jacobian's × {:.2} (reduced χ² {:.2}, residual autocorrelation {:.2}); start: {}",
        r.sigma_scale, r.chi2_reduced, r.autocorrelation, r.start
    );
    if r.params.len() > 1 {
        let mut pairs: Vec<String> = Vec::new();
        for (i, row) in r.correlations.iter().enumerate() {
            for (j, c) in row.iter().enumerate().skip(i + 1) {
                pairs.push(format!("{}/{} {c:+.2}", r.params[i].name, r.params[j].name));
            }
        }
        println!("correlations: {}", pairs.join(", "));
    }
    println!(
        "residual RMS {:.2} → {:.2} noise σ ({:.1}× smaller)",
        r.residual_rms.0, r.residual_rms.1, r.improvement
    );
    let t = |x: Option<f64>| x.map_or("—".into(), |v| format!("{v:.1} s"));
    println!(
        "  {:<24} {:>15} {:>15} {:>6} {:>9} {:>9}",
        "log", "P2 RMS (bar)", "speed RMS (rpm)", "χ²", "empty log", "empty sim"
    );
    for l in &r.logs {
        println!(
            "  {:<24} {:>6.2} → {:<6.2} {:>6.1} → {:<6.1} {:>6.2} {:>9} {:>9}",
            l.name,
            l.p2_rms_bar.0,
            l.p2_rms_bar.1,
            l.rpm_rms.0,
            l.rpm_rms.1,
            l.chi2,
            t(l.emptying_s.logged),
            t(l.emptying_s.simulated)
        );
    }
    println!(
        "{} simulations in {:.1} s; Levenberg–Marquardt: {}",
        r.simulations, r.wall_s, r.termination
    );
    print!("{}", r.checks_table());
    if r.passed {
        println!("fit passed every check");
    } else {
        println!("FIT FAILED: {}", failed.join(", "));
    }
    if let (Some(b), Some(m)) = (&r.bench_file, &r.model_file) {
        println!(
            "fitted bench: {}\nmodel configuration for the firmware: {}{}",
            b.display(),
            m.display(),
            if r.passed {
                ""
            } else {
                "\n(NOT A FITTED BENCH: written with --write-anyway, marked in their first line)"
            }
        );
    } else {
        println!(
            "no fitted bench or model configuration written (--write-anyway writes them, marked \
             as failed)"
        );
    }
    for f in &r.figures {
        println!("figure: {}", f.display());
    }
}

pub(crate) fn fit_figures(
    logs: &[pto_host::sim::benchlog::BenchLog],
    o: &pto_host::fit::FitOutcome,
    out: &Path,
) -> Result<Vec<PathBuf>> {
    use pto_host::plot::{Figure, Panel, Series};
    let mut files = Vec::new();
    for (k, l) in logs.iter().enumerate() {
        let t: Vec<f64> = l.t.iter().map(|t| t - l.t[0]).collect();
        let col = |v: &[pto_host::sim::trace::Truth],
                   f: fn(&pto_host::sim::trace::Truth) -> f64| {
            v.iter().map(f).collect::<Vec<f64>>()
        };
        let rel = |sim: &[f64], meas: &[f64], floor: f64| -> Vec<f64> {
            sim.iter()
                .zip(meas)
                .map(|(s, m)| (100.0 * (s - m) / m.abs().max(floor)).clamp(-30.0, 30.0))
                .collect()
        };
        let (p2b, p2a) = (
            col(&o.before[k], |x| x.p2_bar),
            col(&o.after[k], |x| x.p2_bar),
        );
        let (rb, ra) = (
            col(&o.before[k], |x| x.motor_rpm),
            col(&o.after[k], |x| x.motor_rpm),
        );
        let s = |label: &str, y: Vec<f64>| Series {
            label: label.into(),
            x: t.clone(),
            y,
        };
        // The moments the HP accumulator runs empty, logged and simulated, as vertical lines
        // over the measured range.
        let e = &o.report.logs[k].emptying_s;
        let marks = |y: &[f64]| -> Vec<Series> {
            let lo = y.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = y.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            [
                ("emptying, logged", e.logged),
                ("emptying, fitted", e.simulated),
            ]
            .into_iter()
            .filter_map(|(label, at)| {
                at.map(|x| Series {
                    label: format!("{label} ({x:.1} s)"),
                    x: vec![x, x],
                    y: vec![lo, hi],
                })
            })
            .collect()
        };
        let fig = Figure {
            name: format!("fit-{}", l.name()),
            title: format!("{}: measured vs simulated", l.name()),
            panels: vec![
                Panel {
                    title: "HP pressure P2".into(),
                    x_label: "time (s)".into(),
                    y_label: "P2 (bar)".into(),
                    series: [
                        s("measured", l.p2_bar.clone()),
                        s("simulated, start", p2b),
                        s("simulated, fitted", p2a.clone()),
                    ]
                    .into_iter()
                    .chain(marks(&l.p2_bar))
                    .collect(),
                },
                Panel {
                    title: "Motor speed".into(),
                    x_label: "time (s)".into(),
                    y_label: "speed (rpm)".into(),
                    series: [
                        s("measured", l.rpm.clone()),
                        s("simulated, start", rb),
                        s("simulated, fitted", ra.clone()),
                    ]
                    .into_iter()
                    .chain(marks(&l.rpm))
                    .collect(),
                },
                Panel {
                    title: "Fitted − measured, % (Fig. 26 view; clipped to ±30 %)".into(),
                    x_label: "time (s)".into(),
                    y_label: "difference (%)".into(),
                    series: vec![
                        s("P2", rel(&p2a, &l.p2_bar, 1.0)),
                        s(
                            "motor speed (of max(speed, 50 rpm))",
                            rel(&ra, &l.rpm, 50.0),
                        ),
                    ],
                },
            ],
            cols: 1,
        };
        files.push(fig.write(out)?);
    }
    Ok(files)
}
