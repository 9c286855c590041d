//! The commands, a module per family with each command's options beside its code; shared here:
//! loading the bench file, progress bars, atomic writes, the options' value parsers.

pub(crate) mod firmware;
pub(crate) mod fit;
pub(crate) mod link;
pub(crate) mod model;
pub(crate) mod plan;
pub(crate) mod sim;
pub(crate) mod sweep;

use anyhow::Result;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use pto_host::sim::bench::Bench;

use std::io::IsTerminal;
use std::path::{Path, PathBuf};

pub(crate) fn load_bench(path: Option<&PathBuf>) -> Result<Bench> {
    Ok(Bench::load_or_reference(path)?)
}

/// The bench file with `--set` overrides applied, validated (errors name the field).
pub(crate) fn load_bench_with(path: Option<&PathBuf>, set: &[String]) -> Result<Bench> {
    if set.is_empty() {
        return load_bench(path);
    }
    let base = load_bench(path)?;
    let mut file = base.file;
    // The fit's parameter names as short names (`trapped_air=0.04`), then any field by path.
    let shortcuts = pto_host::fit::set_shortcuts();
    for kv in set {
        pto_host::sim::bench::apply_override(&mut file, kv, &shortcuts)?;
    }
    Ok(Bench::from_file(
        file,
        &format!("{} with --set", base.source),
    )?)
}

pub(crate) fn progress_bar(len_ms: u64, label: &str) -> ProgressBar {
    let pb = ProgressBar::with_draw_target(Some(len_ms), ProgressDrawTarget::stderr());
    pb.set_style(
        ProgressStyle::with_template("{prefix} [{bar:40}] {pos}/{len} ms simulated  {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_prefix(label.to_string());
    pb
}

pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    Ok(pto_host::output::write_atomic(path, bytes)?)
}

pub(crate) fn count_bar(n: u64, what: &str) -> ProgressBar {
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

/// Progress bars of a parallel run: one per running scenario and a total, on stderr.
pub(crate) struct ScenarioBars {
    multi: indicatif::MultiProgress,
    overall: ProgressBar,
    style: ProgressStyle,
    bars: std::sync::Mutex<Vec<Option<ProgressBar>>>,
}

impl ScenarioBars {
    pub(crate) fn new(n: usize) -> Self {
        let multi = indicatif::MultiProgress::with_draw_target(ProgressDrawTarget::stderr());
        let overall = multi.add(ProgressBar::new(n as u64));
        overall.set_style(
            ProgressStyle::with_template("{prefix:>22} {pos}/{len} scenarios  {elapsed}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        overall.set_prefix("total");
        let style = ProgressStyle::with_template(
            "{prefix:>22} [{bar:30}] {pos:>7}/{len:7} ms sim  {elapsed}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> ");
        ScenarioBars {
            multi,
            overall,
            style,
            bars: std::sync::Mutex::new(vec![None; n]),
        }
    }

    pub(crate) fn finish(&self) {
        self.overall.finish_and_clear();
    }

    fn bar(&self, index: usize) -> Option<ProgressBar> {
        self.bars.lock().ok()?.get(index).cloned().flatten()
    }
}

impl pto_host::runner::RunProgress for ScenarioBars {
    fn start(&self, index: usize, name: &str, duration_s: f64) {
        let pb = self
            .multi
            .add(ProgressBar::new((duration_s * 1000.0) as u64));
        pb.set_style(self.style.clone());
        pb.set_prefix(name.to_string());
        if let Ok(mut bars) = self.bars.lock()
            && let Some(slot) = bars.get_mut(index)
        {
            *slot = Some(pb);
        }
    }

    fn at(&self, index: usize, t_s: f64) {
        if let Some(pb) = self.bar(index) {
            pb.set_position((t_s * 1000.0) as u64);
        }
    }

    fn done(&self, index: usize) {
        if let Some(pb) = self.bar(index) {
            pb.finish_and_clear();
            self.multi.remove(&pb);
        }
        self.overall.inc(1);
    }
}

/// A clap parser for a finite number in [lo, hi] (`unit` for the message): NaN, infinities and
/// values out of range are argument errors (exit 2), never a hang or a solver failure.
pub(crate) fn finite_in(
    lo: f64,
    hi: f64,
    unit: &'static str,
) -> impl Fn(&str) -> Result<f64, String> + Clone {
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

/// `K/N` with 1 ≤ K ≤ N.
pub(crate) fn parse_shard(v: &str) -> Result<pto_host::sweep::Shard, String> {
    v.parse()
}

/// `NAME=VALUE` with a finite, positive value.
pub(crate) fn name_value(v: &str) -> Result<(String, f64), String> {
    let (n, x) = v
        .split_once('=')
        .ok_or_else(|| format!("{v:?}: want NAME=VALUE, e.g. trapped_air=0.01"))?;
    let x: f64 = x
        .trim()
        .parse()
        .ok()
        .filter(|x: &f64| x.is_finite() && *x > 0.0)
        .ok_or_else(|| format!("{v:?}: the value must be a positive number"))?;
    Ok((n.trim().to_string(), x))
}
