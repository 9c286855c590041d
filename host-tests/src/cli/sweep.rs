//! `pto sweep` and `pto sweep merge`: a design matrix run into one row per run, and the rows of
//! a sweep's shards joined.

use super::{count_bar, parse_shard};
use anyhow::{Context, Result, anyhow};
use pto_host::output::{StagedDir, stop_on_interrupt, stop_requested};
use pto_host::sweep::run::{self, Row, Status};
use pto_host::sweep::store::{self, Identity, Store};
use pto_host::sweep::{
    Matrix, RunKey, Shard, Written, default_heatmap, describe, heatmap_axes, write_tables,
};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// `pto sweep`'s options.
#[derive(clap::Args)]
pub(crate) struct SweepArgs {
    #[command(subcommand)]
    pub cmd: Option<SweepCmd>,
    /// The design matrix (TOML): a base scenario, `[set]` fields and `[[axis]]` entries
    /// (docs/sweep.md).
    #[arg(required = true)]
    pub matrix: Option<PathBuf>,
    /// Bench parameter file (default: the matrix's `bench`, else the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Output folder: sweep.json, runs.jsonl (a row per finished run, kept across
    /// reruns), sweep.csv, sweep.parquet, heatmap-*.png/svg.
    #[arg(long, default_value = "out/sweep")]
    pub out: PathBuf,
    /// Run only shard K of N: the runs whose number minus one is K − 1 modulo N (for a job
    /// array; `pto sweep merge` joins the shards' folders).
    #[arg(long, value_name = "K/N", value_parser = parse_shard)]
    pub shard: Option<pto_host::sweep::Shard>,
    /// Worker threads, 1 to 1024 (default: one per core).
    #[arg(long, value_parser = clap::value_parser!(u16).range(1..=1024))]
    pub jobs: Option<u16>,
    /// The heat maps' axes, two fields: X,Y (default: the matrix's `heatmap`, else its
    /// first two axes of more than one value).
    #[arg(long, value_name = "X,Y", value_delimiter = ',')]
    pub heatmap: Option<Vec<String>>,
    /// Run failed runs again (they are otherwise finished: their failure rows stay).
    #[arg(long)]
    pub retry_failed: bool,
    /// Check the matrix and count the runs (and those already finished in --out); run
    /// nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Skip the heat maps.
    #[arg(long)]
    pub no_plots: bool,
    /// Machine-readable summary on stdout.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Subcommand)]
pub(crate) enum SweepCmd {
    /// Join the folders of one sweep's shards into one table: checks they are of one matrix,
    /// names the runs missing and those found twice.
    #[command(
        after_help = "Examples:\n  pto sweep merge shards/* --out sweep\n\nExit status:\n  0 every run of the matrix has a row, none failed and every balance closed within 1e-4\n  1 runs are missing (listed, with the shards not given), failed or missed the balance target\n  2 bad input (a folder not a sweep's, folders of different matrices, an --out sweep folder with rows of its own or in use)"
    )]
    Merge {
        /// The shards' output folders.
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
        /// Output folder (replaced whole; a folder of other files is refused).
        #[arg(long, default_value = "out/sweep")]
        out: PathBuf,
        /// The heat maps' axes, two fields: X,Y (default: as the sweep chose).
        #[arg(long, value_name = "X,Y", value_delimiter = ',')]
        heatmap: Option<Vec<String>>,
        /// Skip the heat maps.
        #[arg(long)]
        no_plots: bool,
        /// Machine-readable summary on stdout.
        #[arg(long)]
        json: bool,
    },
}

/// What `pto sweep` was asked.
pub(crate) struct SweepOptions<'a> {
    pub matrix: &'a Path,
    pub bench: Option<&'a PathBuf>,
    pub out: &'a Path,
    pub shard: Option<Shard>,
    pub jobs: Option<usize>,
    pub heatmap: Option<&'a [String]>,
    pub retry_failed: bool,
    pub dry_run: bool,
    pub plots: bool,
    pub json: bool,
}

/// A failed run, for the report.
#[derive(Serialize)]
struct Failure {
    run: usize,
    values: String,
    error: String,
}

/// How many of the folder's runs ended how.
#[derive(Serialize, Default)]
struct Counts {
    ok: usize,
    balance_missed: usize,
    failed: usize,
    not_run: usize,
}

impl Counts {
    fn of(identity: &Identity, rows: &HashMap<RunKey, Row>) -> (Counts, Vec<Failure>) {
        let mut c = Counts::default();
        let mut failures = Vec::new();
        for i in identity.indices() {
            match rows.get(&identity.keys[i]) {
                None => c.not_run += 1,
                Some(r) => match r.status {
                    Status::Ok => c.ok += 1,
                    Status::Balance => c.balance_missed += 1,
                    Status::Failed => {
                        c.failed += 1;
                        failures.push(Failure {
                            run: i + 1,
                            values: describe(&identity.axes, i),
                            error: r.error.clone().unwrap_or_default(),
                        });
                    }
                },
            }
        }
        (c, failures)
    }

    fn pass(&self) -> bool {
        self.balance_missed == 0 && self.failed == 0 && self.not_run == 0
    }
}

#[derive(Serialize)]
struct SweepReport {
    matrix: String,
    out: String,
    sweep_id: String,
    runs_in_matrix: usize,
    shard: Option<String>,
    runs_in_shard: usize,
    skipped_finished: usize,
    ran: usize,
    #[serde(flatten)]
    counts: Counts,
    interrupted: bool,
    wall_s: f64,
    runs_per_s: f64,
    csv: String,
    parquet: String,
    heatmaps: Vec<String>,
    failures: Vec<Failure>,
}

/// The heat maps' axes: `--heatmap`, else the matrix's `heatmap`, else the first two axes of
/// more than one value.
fn choose_heatmap(m: &Matrix, asked: Option<&[String]>) -> Result<Option<(usize, usize)>> {
    Ok(match asked {
        Some(h) => Some(heatmap_axes(&m.axes, h).map_err(|e| anyhow!("--{e}"))?),
        None => m.heatmap.or_else(|| default_heatmap(&m.axes)),
    })
}

/// `pto sweep`, or `pto sweep merge`.
pub(crate) fn sweep(a: &SweepArgs) -> Result<bool> {
    match &a.cmd {
        Some(SweepCmd::Merge {
            dirs,
            out,
            heatmap,
            no_plots,
            json,
        }) => merge_cmd(dirs, out, heatmap.as_deref(), !no_plots, *json),
        None => sweep_cmd(SweepOptions {
            matrix: a.matrix.as_deref().unwrap_or(std::path::Path::new("")),
            bench: a.bench.as_ref(),
            out: &a.out,
            shard: a.shard,
            jobs: a.jobs.map(usize::from),
            heatmap: a.heatmap.as_deref(),
            retry_failed: a.retry_failed,
            dry_run: a.dry_run,
            plots: !a.no_plots,
            json: a.json,
        }),
    }
}

pub(crate) fn sweep_cmd(o: SweepOptions) -> Result<bool> {
    let m = Matrix::load(o.matrix, o.bench)?;
    let heatmap = choose_heatmap(&m, o.heatmap)?;
    if !o.json {
        eprintln!("checking the {} runs of {}…", m.len(), m.source);
    }
    // The checks run on `--jobs` threads too (a job array's task keeps to its cores).
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(o.jobs.unwrap_or(0))
        .build()
        .context("cannot start the worker threads")?;
    let keys = pool.install(|| m.keys())?;
    let mut identity = Identity::new(&m, keys, o.shard);
    identity.heatmap = heatmap;
    let indices = identity.indices();
    if o.dry_run {
        pool.install(|| m.check(&(0..m.len()).collect::<Vec<_>>()))?;
        return dry_run(&m, &identity, o.out, o.json);
    }
    // Every run this sweep is to make prepares before any runs (and before --out is touched);
    // a shard checks its own runs (`--dry-run` checks them all, before a job array).
    let before = store::read_rows(&o.out.join(store::ROWS), false)?;
    pool.install(|| m.check(&store::pending(&identity, &before, o.retry_failed)))?;
    let (store, mut rows) = Store::open(o.out, &identity)?;
    let todo = store::pending(&identity, &rows, o.retry_failed);
    let skipped = indices.len() - todo.len();
    if !o.json {
        eprintln!(
            "{} runs{}: {} finished before, {} to run on {} threads; rows in {}",
            indices.len(),
            o.shard
                .map_or(String::new(), |s| format!(" in shard {s} of {}", m.len())),
            skipped,
            todo.len(),
            pool.current_num_threads(),
            o.out.join(store::ROWS).display()
        );
    }
    // The first Ctrl-C stops new runs; those under way finish and keep their rows.
    stop_on_interrupt();
    let pb = count_bar(todo.len() as u64, "runs");
    let start = Instant::now();
    let done = std::sync::Mutex::new(Vec::new());
    let result = pool.install(|| {
        todo.par_iter().try_for_each(|&i| {
            if stop_requested() {
                return Ok(());
            }
            let key = identity.keys[i];
            let row = match m.spec(i) {
                Ok(spec) => run::run(&spec, key),
                Err(e) => Row {
                    key,
                    status: Status::Failed,
                    figures: None,
                    error: Some(e),
                    wall_s: 0.0,
                },
            };
            if let Some(e) = &row.error {
                pb.suspend(|| eprintln!("run {} ({}) failed: {e}", i + 1, m.describe(i)));
            }
            store.append(&row)?;
            pb.inc(1);
            done.lock().unwrap_or_else(|e| e.into_inner()).push(row);
            Ok::<(), store::StoreError>(())
        })
    });
    pb.finish_and_clear();
    let wall_s = start.elapsed().as_secs_f64();
    let new_rows = done.into_inner().unwrap_or_else(|e| e.into_inner());
    let ran = new_rows.len();
    for r in new_rows {
        rows.insert(r.key, r);
    }
    // The rows so far are kept whatever happens next; the tables show them.
    let written = write_tables(o.out, &identity, &rows, o.plots)?;
    result?;
    let interrupted = stop_requested();
    let (counts, failures) = Counts::of(&identity, &rows);
    let pass = counts.pass();
    let report = SweepReport {
        matrix: m.source.clone(),
        out: o.out.display().to_string(),
        sweep_id: identity.sweep_id.clone(),
        runs_in_matrix: m.len(),
        shard: o.shard.map(|s| s.to_string()),
        runs_in_shard: indices.len(),
        skipped_finished: skipped,
        ran,
        counts,
        interrupted,
        wall_s,
        runs_per_s: if wall_s > 0.0 {
            ran as f64 / wall_s
        } else {
            0.0
        },
        csv: written.csv.display().to_string(),
        parquet: written.parquet.display().to_string(),
        heatmaps: written
            .heatmaps
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        failures,
    };
    if o.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&report, &written);
    }
    drop(store);
    if interrupted {
        eprintln!(
            "interrupted: {} runs not made; their rows are missing, every finished run's row is \
             kept — run the same command again to go on",
            report.counts.not_run
        );
        std::process::exit(130);
    }
    Ok(pass)
}

fn print_report(r: &SweepReport, w: &Written) {
    println!(
        "{}: {} runs{} — {} ok, {} missed the balance target, {} failed, {} not run \
         ({} finished before, {} run now in {:.1} s: {:.2} runs/s)",
        r.matrix,
        r.runs_in_shard,
        r.shard.as_ref().map_or(String::new(), |s| format!(
            " (shard {s} of {})",
            r.runs_in_matrix
        )),
        r.counts.ok,
        r.counts.balance_missed,
        r.counts.failed,
        r.counts.not_run,
        r.skipped_finished,
        r.ran,
        r.wall_s,
        r.runs_per_s
    );
    for f in r.failures.iter().take(10) {
        println!("  run {} ({}) failed: {}", f.run, f.values, f.error);
    }
    if r.failures.len() > 10 {
        println!(
            "  … and {} more failed runs (see the table)",
            r.failures.len() - 10
        );
    }
    println!("wrote {} rows to {} and {}", w.rows, r.csv, r.parquet);
    if !w.heatmaps.is_empty() {
        println!("heat maps: {} (each with an .svg)", r.heatmaps.join(", "));
    }
}

#[derive(Serialize)]
struct Plan {
    matrix: String,
    sweep_id: String,
    runs: usize,
    axes: Vec<String>,
    shard: Option<String>,
    runs_in_shard: usize,
    finished_in_out: usize,
}

fn dry_run(m: &Matrix, identity: &Identity, out: &Path, json: bool) -> Result<bool> {
    let rows = store::read_rows(&out.join(store::ROWS), false)?;
    let indices = identity.indices();
    let finished = indices
        .iter()
        .filter(|i| rows.contains_key(&identity.keys[**i]))
        .count();
    let plan = Plan {
        matrix: m.source.clone(),
        sweep_id: identity.sweep_id.clone(),
        runs: m.len(),
        axes: m
            .axes
            .iter()
            .map(|a| format!("{} ({} values)", a.name(), a.values.len()))
            .collect(),
        shard: identity.shard.map(|s| s.to_string()),
        runs_in_shard: indices.len(),
        finished_in_out: finished,
    };
    if json {
        println!("{}", serde_json::to_string_pretty(&plan)?);
    } else {
        println!(
            "{}: {} runs, every one checked (sweep {})",
            plan.matrix, plan.runs, plan.sweep_id
        );
        for a in &plan.axes {
            println!("  axis {a}");
        }
        if let Some(s) = &plan.shard {
            println!("  shard {s}: {} runs", plan.runs_in_shard);
        }
        println!(
            "  {} of them already have a row in {}",
            plan.finished_in_out,
            out.display()
        );
    }
    Ok(true)
}

#[derive(Serialize)]
struct MergeReport {
    folders: Vec<String>,
    shards: Vec<String>,
    sweep_id: String,
    runs_in_matrix: usize,
    rows: usize,
    missing_runs: Vec<usize>,
    duplicated_runs: Vec<usize>,
    #[serde(flatten)]
    counts: Counts,
    out: String,
    csv: String,
    parquet: String,
    heatmaps: Vec<String>,
    failures: Vec<Failure>,
}

pub(crate) fn merge_cmd(
    dirs: &[PathBuf],
    out: &Path,
    heatmap: Option<&[String]>,
    plots: bool,
    json: bool,
) -> Result<bool> {
    let merged = store::merge(dirs)?;
    let _out_lock = store::claim_merge_out(out, dirs)?;
    let mut identity = merged.identity;
    if let Some(h) = heatmap {
        identity.heatmap = Some(heatmap_axes(&identity.axes, h).map_err(|e| anyhow!("--{e}"))?);
    }
    // Only the runs of this matrix, in run order: the merged folder is a sweep folder too
    // (`pto sweep` resumes from it).
    let mut lines = String::new();
    for k in &identity.keys {
        if let Some(r) = merged.rows.get(k) {
            lines.push_str(&serde_json::to_string(r)?);
            lines.push('\n');
        }
    }
    let stage = StagedDir::new(out)?;
    let dir = stage.path().to_path_buf();
    pto_host::output::write_atomic(
        &dir.join(store::IDENTITY),
        serde_json::to_string_pretty(&identity)?.as_bytes(),
    )?;
    pto_host::output::write_atomic(&dir.join(store::ROWS), lines.as_bytes())?;
    let written = write_tables(&dir, &identity, &merged.rows, plots)?;
    stage.commit()?;
    let in_out = |p: &Path| {
        out.join(p.file_name().unwrap_or_default())
            .display()
            .to_string()
    };
    let (counts, failures) = Counts::of(&identity, &merged.rows);
    let report = MergeReport {
        folders: dirs.iter().map(|d| d.display().to_string()).collect(),
        shards: merged
            .shards
            .iter()
            .map(|s| s.map_or("all".into(), |s| s.to_string()))
            .collect(),
        sweep_id: identity.sweep_id.clone(),
        runs_in_matrix: identity.keys.len(),
        rows: written.rows,
        missing_runs: merged.missing.iter().map(|i| i + 1).collect(),
        duplicated_runs: merged.duplicated.iter().map(|i| i + 1).collect(),
        counts,
        out: out.display().to_string(),
        csv: in_out(&written.csv),
        parquet: in_out(&written.parquet),
        heatmaps: written.heatmaps.iter().map(|p| in_out(p)).collect(),
        failures,
    };
    let pass = report.missing_runs.is_empty() && report.counts.pass();
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(pass);
    }
    println!(
        "merged {} folders (shards {}) of sweep {} ({}): {} of {} runs — {} ok, {} missed the \
         balance target, {} failed",
        dirs.len(),
        report.shards.join(", "),
        report.sweep_id,
        identity.matrix,
        report.rows,
        report.runs_in_matrix,
        report.counts.ok,
        report.counts.balance_missed,
        report.counts.failed
    );
    if !report.duplicated_runs.is_empty() {
        println!(
            "  {} runs had a row in more than one folder (the first folder's kept): runs {}",
            report.duplicated_runs.len(),
            list(&report.duplicated_runs)
        );
    }
    if !merged.missing.is_empty() {
        println!(
            "  {} runs MISSING (no folder has their row): runs {}",
            merged.missing.len(),
            list(&report.missing_runs)
        );
        for &i in merged.missing.iter().take(5) {
            println!("    run {}: {}", i + 1, describe(&identity.axes, i));
        }
        let shards: Vec<Shard> = merged.shards.iter().flatten().copied().collect();
        if let Some(n) = shards.first().map(|s| s.n) {
            let absent: Vec<String> = (1..=n)
                .filter(|k| !shards.iter().any(|s| s.k == *k && s.n == n))
                .map(|k| format!("{k}/{n}"))
                .collect();
            if !absent.is_empty() {
                println!("  shards not given: {}", absent.join(", "));
            }
        }
        println!(
            "  to make them: pto sweep {} --out {} (it runs only the missing runs)",
            identity.matrix,
            out.display()
        );
    }
    for f in report.failures.iter().take(10) {
        println!("  run {} ({}) failed: {}", f.run, f.values, f.error);
    }
    println!("wrote {} and {}", report.csv, report.parquet);
    if !report.heatmaps.is_empty() {
        println!(
            "heat maps: {} (each with an .svg)",
            report.heatmaps.join(", ")
        );
    }
    Ok(pass)
}

/// `1, 2, 5, …` (the first 20).
fn list(runs: &[usize]) -> String {
    let mut s: Vec<String> = runs.iter().take(20).map(|r| r.to_string()).collect();
    if runs.len() > 20 {
        s.push("…".into());
    }
    s.join(", ")
}
