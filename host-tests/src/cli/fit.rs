//! `pto synth-logs` and `fit`: bench logs and the fit to them.

use super::{count_bar, load_bench, load_bench_with};
use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use pto_host::sim::bench::Bench;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

pub(crate) fn synth_logs_cmd(
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
    let stage = pto_host::output::StagedDir::new(out)?;
    let staged = stage.path().to_path_buf();
    let pb = count_bar(names.len() as u64, "logs");
    let logs: Vec<Result<pto_host::sim::benchlog::BenchLog, fit::FitError>> = {
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
        let l = l?;
        l.write()?;
        let name = l.path.file_name().map(PathBuf::from).unwrap_or_default();
        written.push((out.join(name), l.t.len()));
    }
    stage.commit()?;
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

// The command's options, one argument each as clap hands them over.
#[allow(clippy::too_many_arguments)]
pub(crate) fn fit_cmd(
    log_paths: &[PathBuf],
    bench_path: Option<&PathBuf>,
    params: &[String],
    spacing: f64,
    max_iter: usize,
    out: &Path,
    write_anyway: bool,
    json: bool,
) -> Result<bool> {
    use pto_host::fit;
    use pto_host::sim::benchlog::BenchLog;
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
    let n_par = fit::params(params, &bench.file)?.len();
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
    )?;
    pb.finish_and_clear();
    // Outputs, all in --out and swapped in whole: the fitted bench, the model configuration
    // for the firmware, the figures and the report.
    let stage = pto_host::output::StagedDir::new(out)?;
    let stem = bench_path
        .and_then(|p| p.file_stem())
        .map_or("reference-bench".into(), |s| {
            s.to_string_lossy().into_owned()
        });
    // The fitted bench and the firmware's configuration only from a fit that converged (or
    // asked for anyway, their first line saying it did not).
    let write = o.report.converged || write_anyway;
    let mark = if o.report.converged {
        String::new()
    } else {
        format!(
            "# NOT CONVERGED ({}): written with --write-anyway; do not use it as a fitted bench.\n",
            o.report.termination
        )
    };
    if write {
        let fitted = Bench::from_file(o.fitted.clone(), "fitted").context("the fitted bench")?;
        let mut text = mark.clone();
        text.push_str(&format!(
            "# Fitted by `pto fit` to {} log(s) from {}; parameters: {}.\n",
            logs.len(),
            bench_path.map_or("the reference bench".into(), |p| p.display().to_string()),
            params.join(", ")
        ));
        text.push_str(&toml::to_string_pretty(&o.fitted)?);
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
                "fitted bench: {}\nmodel configuration for the firmware: {}{}",
                b.display(),
                m.display(),
                if r.converged {
                    ""
                } else {
                    "\n(NOT CONVERGED: written with --write-anyway, marked in their first line)"
                }
            );
        } else {
            println!(
                "not converged: no fitted bench or model configuration written (--write-anyway \
                 writes them, marked as not converged)"
            );
        }
        for f in &r.figures {
            println!("figure: {}", f.display());
        }
    }
    Ok(r.converged)
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
        let fig = Figure {
            name: format!("fit-{}", l.name()),
            title: format!("{}: measured vs simulated", l.name()),
            panels: vec![
                Panel {
                    title: "HP pressure P2".into(),
                    x_label: "time (s)".into(),
                    y_label: "P2 (bar)".into(),
                    series: vec![
                        s("measured", l.p2_bar.clone()),
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
