//! `pto synth-logs` and `fit`: bench logs and the fit to them.

use super::{count_bar, load_bench, load_bench_with};
use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use pto_host::sim::bench::Bench;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

#[allow(clippy::too_many_arguments)]
pub(crate) fn synth_logs_cmd(
    bench: Option<&PathBuf>,
    set: &[String],
    runs: &[String],
    campaign: Option<&Path>,
    rate: f64,
    seed: u64,
    out: &Path,
    json: bool,
) -> Result<bool> {
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
                        pto_host::model::sensors::SensorSpec::default(),
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

pub(crate) fn fit_cmd(
    log_paths: &[PathBuf],
    bench_path: Option<&PathBuf>,
    mut opts: pto_host::fit::FitOptions,
    out: &Path,
    write_anyway: bool,
    json: bool,
) -> Result<bool> {
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
        let model = pto_host::model::model_config(&fitted)?;
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
