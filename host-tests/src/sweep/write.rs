//! The sweep's table (CSV and Parquet) and heat maps written into its output folder, each file
//! whole or not at all.

use super::key::RunKey;
use super::{heatmap, run, store, table};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The files [`write_tables`] wrote.
#[derive(Debug, Clone, Default)]
pub struct Written {
    /// Rows in the table.
    pub rows: usize,
    /// The CSV.
    pub csv: PathBuf,
    /// The Parquet file.
    pub parquet: PathBuf,
    /// The heat maps (PNG; each with an SVG beside it).
    pub heatmaps: Vec<PathBuf>,
}

/// Why a sweep's table or figures could not be written, named with the file.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    /// The CSV could not be made.
    #[error("{path}")]
    Csv {
        /// The file.
        path: PathBuf,
        /// The CSV writer's error.
        source: csv::Error,
    },
    /// The Parquet file could not be made.
    #[error(transparent)]
    Table(#[from] table::TableError),
    /// A file could not be written.
    #[error(transparent)]
    Output(#[from] crate::output::OutputError),
    /// A figure could not be drawn.
    #[error(transparent)]
    Plot(#[from] crate::plot::PlotError),
}

/// Writes the table of the folder's runs (`identity.indices()`, those with a row) into `dir` as
/// `sweep.csv` and `sweep.parquet`, each whole or not at all, and, when every run of the
/// matrix has a row (not a shard, not an unfinished sweep) and with `plots`, the heat maps over
/// `identity.heatmap`.
pub fn write_tables(
    dir: &Path,
    identity: &store::Identity,
    rows: &HashMap<RunKey, run::Row>,
    plots: bool,
) -> Result<Written, WriteError> {
    let t = table::Table::of_rows(identity, rows, &identity.indices());
    let csv = dir.join(store::CSV);
    let text = t.csv().map_err(|source| WriteError::Csv {
        path: csv.clone(),
        source,
    })?;
    crate::output::write_atomic(&csv, text.as_bytes())?;
    let parquet = dir.join(store::PARQUET);
    let bytes = t.parquet(&parquet.display().to_string())?;
    crate::output::write_atomic(&parquet, &bytes)?;
    // Heat maps of the whole matrix only: a shard's or an unfinished sweep's would average
    // over some of the runs. Those of an earlier table go (they would no longer match it).
    for m in heatmap::METRICS {
        for ext in ["png", "svg"] {
            let _ = std::fs::remove_file(dir.join(format!("heatmap-{}.{ext}", m.0)));
        }
    }
    let mut heatmaps = Vec::new();
    let whole = identity.shard.is_none() && t.len() == identity.keys.len();
    if let (true, true, Some(axes)) = (plots, whole, identity.heatmap) {
        for h in heatmap::heatmaps(identity, &t, axes) {
            heatmaps.push(crate::plot::write_both(&h, dir)?);
        }
    }
    Ok(Written {
        rows: t.len(),
        csv,
        parquet,
        heatmaps,
    })
}
