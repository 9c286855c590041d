//! `pto plan`: the campaign that determines the fit's parameters.

use super::{count_bar, finite_in, load_bench_with, name_value, write_atomic};
use anyhow::{Result, bail};
use pto_host::fit;
use pto_host::plan::{self, Goal, Menu};
use std::path::PathBuf;
use std::sync::Arc;

/// `pto plan`'s options.
#[derive(clap::Args)]
pub(crate) struct PlanArgs {
    /// Bench parameter file: the current best guess (default: the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Override a bench value (as `pto simulate --set`).
    #[arg(long = "set", value_name = "NAME=VALUE")]
    pub set: Vec<String>,
    /// Parameters to determine (the fit's names).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "trapped_air,cd,precharge,leakage"
    )]
    pub params: Vec<String>,
    /// Precision a parameter needs, in its unit (repeatable; as `pto fit --precision`).
    #[arg(long, value_name = "NAME=VALUE", value_parser = name_value)]
    pub precision: Vec<(String, f64)>,
    /// Bench time the campaign may take, 1 to 1440 min.
    #[arg(long, default_value_t = 45.0, value_parser = finite_in(1.0, 1440.0, "min"))]
    pub budget_min: f64,
    /// Log rate of the segments, 1 to 128 Hz (the link's telemetry).
    #[arg(long, default_value_t = 64.0, value_parser = finite_in(1.0, 128.0, "Hz"))]
    pub rate: f64,
    /// Geometries the candidates use (1 to 4).
    #[arg(long, value_delimiter = ',', default_value = "1", value_parser = clap::value_parser!(u8).range(1..=4))]
    pub configs: Vec<u8>,
    /// Bench logs to estimate the sensors' noise from (default: the sensor model's, HP 0.5
    /// bar, motor 2 rpm, LP 0.2 bar).
    #[arg(long, value_name = "FILE")]
    pub noise_from: Vec<PathBuf>,
    /// The campaign file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
}

pub(crate) fn plan_cmd(a: &PlanArgs) -> Result<bool> {
    let t0 = std::time::Instant::now();
    let bench = load_bench_with(a.bench.as_ref(), &a.set)?;
    let start = bench.file.clone();
    let params = fit::params(&a.params, &start)?;
    for (n, v) in &a.precision {
        if !params.iter().any(|p| p.name == *n) {
            bail!(
                "--precision {n}={v}: `{n}` is not among --params ({})",
                a.params.join(",")
            );
        }
        if !(v.is_finite() && *v > 0.0) {
            bail!("--precision {n}={v}: a precision above 0, in the parameter's unit");
        }
    }
    let needed: Vec<f64> = params
        .iter()
        .map(|p| p.needed_at((p.get)(&start), &a.precision))
        .collect();
    let noise = if a.noise_from.is_empty() {
        fit::sensor_noise()
    } else {
        let logs = a
            .noise_from
            .iter()
            .map(|p| pto_host::sim::benchlog::BenchLog::read(p))
            .collect::<Result<Vec<_>, _>>()?;
        fit::noise_of(&logs, None, None, None)
    };
    let mut configs: Vec<usize> = a.configs.iter().map(|&c| usize::from(c)).collect();
    configs.sort_unstable();
    configs.dedup();
    if let Some(c) = configs.iter().find(|&&c| c > bench.configs.len()) {
        bail!(
            "--configs {c}: the bench has {} geometries",
            bench.configs.len()
        );
    }
    let menu = Menu {
        rate_hz: a.rate,
        configs,
    };
    let cands = plan::candidates(&bench, &menu);
    let n_sims = cands.len() * plan::simulations_per_candidate(params.len());
    eprintln!(
        "scoring {} candidate segments ({n_sims} simulations)…",
        cands.len()
    );
    let pb = count_bar(n_sims as u64, "simulations");
    let tick: fit::Tick = {
        let pb = pb.clone();
        Arc::new(move || pb.inc(1))
    };
    let scored = plan::score(&start, &params, &noise, cands, Some(tick))?;
    pb.finish_and_clear();
    let goal = Goal {
        needed,
        budget_min: a.budget_min,
    };
    let p = plan::plan(&scored, &params, &start, &noise, &goal);
    let header = format!(
        "pto plan: {} from {}, budget {} min, {} Hz; predicted {}",
        a.params.join(", "),
        a.bench
            .as_ref()
            .map_or("the reference bench".into(), |b| b.display().to_string()),
        a.budget_min,
        a.rate,
        if p.met {
            "to meet every precision"
        } else {
            "NOT to meet every precision"
        }
    );
    if p.campaign.segment.is_empty() {
        let shortest = scored
            .iter()
            .map(|s| s.segment.minutes())
            .fold(f64::INFINITY, f64::min);
        eprintln!(
            "no segment fits within --budget-min {} (the shortest takes {shortest:.1} min): \
             nothing written",
            a.budget_min
        );
        return Ok(false);
    }
    p.campaign.validate(&a.out.display().to_string(), &bench)?;
    let text = p.campaign.to_toml(&header)?;
    write_atomic(&a.out, text.as_bytes())?;
    // Advice on the campaign written: a failure here costs the advice, not the campaign.
    let n_held = p.campaign.segment.len()
        * plan::simulations_per_candidate(params.len() + fit::held_params(&params, &start).len());
    eprintln!("the held fields' leverage ({n_held} simulations)…");
    let pb = count_bar(n_held as u64, "simulations");
    let tick: fit::Tick = {
        let pb = pb.clone();
        Arc::new(move || pb.inc(1))
    };
    let held = plan::held_leverage(
        &start,
        &params,
        &noise,
        &p.campaign.segment,
        &goal.needed,
        Some(tick),
    )
    .map_err(|e| eprintln!("warning: the held fields' leverage could not be taken: {e}"))
    .unwrap_or_default();
    pb.finish_and_clear();
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "out": a.out,
                "plan": p,
                "held": held,
                "wall_s": t0.elapsed().as_secs_f64(),
            }))?
        );
        return Ok(p.met);
    }
    println!(
        "{} segments, {:.0} min of bench time, {} set-ups by the operator ({} candidates, {:.0} s)",
        p.campaign.segment.len(),
        p.minutes,
        p.interventions,
        p.candidates,
        t0.elapsed().as_secs_f64()
    );
    let names: Vec<&str> = params.iter().map(|x| x.name.as_str()).collect();
    println!(
        "{:<44} {:>5} {:>4}  what it adds (each σ without it → with it)",
        "segment", "min", "Hz"
    );
    for (s, without) in p.campaign.segment.iter().zip(&p.without) {
        let adds: Vec<String> = names
            .iter()
            .zip(without.iter().zip(&p.campaign.predicted))
            .filter(|(_, (w, q))| **w > q.sigma * 1.05)
            .map(|(n, (w, q))| format!("{n} {w:.3e} → {:.3e}", q.sigma))
            .collect();
        println!(
            "{:<44} {:>5.1} {:>4}  {}",
            s.run.name,
            s.minutes(),
            s.rate_hz,
            if adds.is_empty() {
                "little alone (together with the others)".into()
            } else {
                adds.join(", ")
            }
        );
    }
    println!(
        "\n{:<12} {:>12} {:>12} {:>12}  verdict",
        "parameter", "value", "3σ", "needed"
    );
    for q in &p.campaign.predicted {
        println!(
            "{:<12} {:>12.5} {:>12.5} {:>12.5}  {}",
            q.name,
            q.value,
            3.0 * q.sigma,
            q.needed,
            if q.met() { "met" } else { "MISSED" }
        );
    }
    println!("correlations:");
    for (i, row) in p.correlations.iter().enumerate() {
        let cells: Vec<String> = row.iter().map(|c| format!("{c:+.3}")).collect();
        println!("  {:<12} {}", names[i], cells.join(" "));
    }
    println!(
        "held fields (the fit keeps the bench file's value; the plant's value one unit above it \
         shifts the fitted values this much, and only what they cannot take up shows in the \
         residuals):"
    );
    for h in &held {
        let shifts: Vec<String> = names
            .iter()
            .zip(&h.shift_per_unit)
            .map(|(n, d)| format!("{n} {d:+.2e}"))
            .collect();
        println!(
            "  {:<42} {:>9} {:<6} 1 {} shifts {}; keep it within {}",
            h.field,
            sig3(h.value),
            h.unit,
            h.unit,
            shifts.join(", "),
            h.keep_within
                .as_ref()
                .map_or("(it moves none)".into(), |k| format!(
                    "± {} {} ({}){}",
                    sig3(k.error),
                    h.unit,
                    k.limited_by,
                    if k.error > h.value.abs() {
                        ": more than its whole value, a linear extrapolation"
                    } else {
                        ""
                    }
                ))
        );
    }
    for s in &p.short {
        println!(
            "not determined: {} (3σ {:.3e} against {:.3e}){}; {}",
            s.name,
            s.three_sigma,
            s.needed,
            s.blocked_by
                .as_ref()
                .map_or(String::new(), |(n, r)| format!(
                    ", correlated {r:+.3} with {n}"
                )),
            s.help
        );
    }
    println!("campaign written to {}", a.out.display());
    Ok(p.met)
}

/// `x` to three significant digits, in plain notation from 0.001 to 10⁶ (a bench file's own
/// numbers), else in scientific.
fn sig3(x: f64) -> String {
    let a = x.abs();
    if a == 0.0 || !(1e-3..1e6).contains(&a) {
        return format!("{x:.2e}");
    }
    // The exponent of the value rounded to three digits (9.996 is 10.0, not 10.00).
    let rounded: f64 = format!("{a:.2e}").parse().unwrap_or(a);
    let decimals = (2 - rounded.log10().floor() as i32).max(0) as usize;
    format!("{x:.decimals$}")
}

#[cfg(test)]
mod tests {
    #[test]
    fn three_significant_digits() {
        assert_eq!(super::sig3(0.5249), "0.525");
        assert_eq!(super::sig3(27.70), "27.7");
        assert_eq!(super::sig3(215_700.0), "215700");
        assert_eq!(super::sig3(1600.0), "1600");
        assert_eq!(super::sig3(0.0433), "0.0433");
        assert_eq!(super::sig3(2.0e-4), "2.00e-4");
        assert_eq!(super::sig3(9.996), "10.0");
        assert_eq!(super::sig3(-0.0999), "-0.0999");
    }
}
