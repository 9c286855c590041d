//! A sweep's output folder: what it holds (`sweep.json`), its rows as they finish
//! (`runs.jsonl`, one line per run, each written whole), resuming from it, and merging shards'
//! folders.
//!
//! A run's line is appended once the run is over, in one write: an interrupted sweep leaves
//! every finished run's row and no partial one (a line cut short by a crash is dropped when
//! the folder is opened again, and that run made again). Rows are found by their run's
//! [`RunKey`], so a rerun skips finished runs whatever the shard, and a matrix given more
//! values keeps the rows it already has.

use super::axis::Axis;
use super::key::{RunKey, Shard, fnv1a};
use super::matrix::Matrix;
use super::run::{Row, Status};
use crate::output::MARKER;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The folder's description of its sweep.
pub const IDENTITY: &str = "sweep.json";
/// The rows, one JSON line per finished run.
pub const ROWS: &str = "runs.jsonl";
/// The table as CSV.
pub const CSV: &str = "sweep.csv";
/// The table as Parquet.
pub const PARQUET: &str = "sweep.parquet";
/// Held while a sweep writes in the folder.
const LOCK: &str = ".lock";
/// Format of `sweep.json`.
const IDENTITY_FORMAT: u32 = 1;

/// Why a sweep folder could not be used, named with its file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A file could not be read or written (the OS error as the source).
    #[error("{path}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The folder holds files `pto` did not write.
    #[error(
        "--out {0}: the folder exists, is not empty and was not made by pto (no {MARKER} file): \
         choose a new or empty folder"
    )]
    NotOurs(PathBuf),
    /// Another sweep is writing in the folder.
    #[error("{0}: another pto sweep is writing in this folder (it holds {LOCK}); wait for it")]
    Busy(PathBuf),
    /// A folder to merge is not a sweep's.
    #[error("{0}: not a sweep folder (no {IDENTITY})")]
    NotASweep(PathBuf),
    /// `merge --out` names a sweep folder with rows that is not one of the folders merged:
    /// replacing it would lose them.
    #[error(
        "--out {0}: a sweep folder with rows of its own; name it among the folders to merge, or \
         choose a new or empty folder"
    )]
    WouldLoseRows(PathBuf),
    /// A `sweep.json` that cannot be read.
    #[error("{path}: {message}")]
    BadIdentity {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Folders of different matrices.
    #[error(
        "the folders hold different sweeps (not the same matrix, bench and scenario): {}",
        .0.join("; ")
    )]
    Mismatch(Vec<String>),
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// What a sweep folder holds: the matrix's axes and every run's key (so that a merge knows
/// which runs are missing without the matrix file), the shard.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Identity {
    /// Format of this file.
    pub format: u32,
    /// The matrix's name.
    pub name: String,
    /// The matrix file.
    pub matrix: String,
    /// A hash of the axes and every run's key: equal for the shards of one matrix.
    pub sweep_id: String,
    /// The base scenario's name.
    pub scenario: String,
    /// The bench's source.
    pub bench: String,
    /// The axes.
    pub axes: Vec<Axis>,
    /// Every run's key, in run order (run 1 first).
    pub keys: Vec<RunKey>,
    /// The shard the folder holds (`None`: every run).
    pub shard: Option<Shard>,
    /// The heat maps' axes (indices into `axes`).
    pub heatmap: Option<(usize, usize)>,
}

impl Identity {
    /// The identity of a matrix's sweep (its keys from [`Matrix::plan`]).
    pub fn new(m: &Matrix, keys: Vec<RunKey>, shard: Option<Shard>) -> Identity {
        Identity {
            format: IDENTITY_FORMAT,
            name: m.name.clone(),
            matrix: m.source.clone(),
            sweep_id: sweep_id(&m.axes, &keys),
            scenario: m.scenario.name.clone(),
            bench: m.bench.source.clone(),
            axes: m.axes.clone(),
            keys,
            shard,
            heatmap: m.heatmap,
        }
    }

    /// The runs (indices from 0) the folder is for.
    pub fn indices(&self) -> Vec<usize> {
        (0..self.keys.len())
            .filter(|i| self.shard.is_none_or(|s| s.has(*i)))
            .collect()
    }

    fn read(dir: &Path) -> Result<Identity, StoreError> {
        let path = dir.join(IDENTITY);
        if !path.exists() {
            return Err(StoreError::NotASweep(dir.to_path_buf()));
        }
        let text = std::fs::read_to_string(&path).map_err(io(&path))?;
        let id: Identity = serde_json::from_str(&text).map_err(|e| StoreError::BadIdentity {
            path: path.clone(),
            message: e.to_string(),
        })?;
        if id.format != IDENTITY_FORMAT {
            return Err(StoreError::BadIdentity {
                path,
                message: format!(
                    "format {} (this pto reads {IDENTITY_FORMAT}): made by another version",
                    id.format
                ),
            });
        }
        Ok(id)
    }
}

fn sweep_id(axes: &[Axis], keys: &[RunKey]) -> String {
    let mut text = serde_json::to_string(axes).unwrap_or_default();
    for k in keys {
        text.push_str(&k.to_string());
    }
    format!("{:016x}", fnv1a(text.as_bytes()))
}

/// Takes sweep folder `dir`'s lock (`file`, its [`LOCK`]) without waiting: refused while
/// another `pto sweep` (or merge) holds it; held until dropped.
fn lock_sweep(
    dir: &Path,
    file: std::fs::File,
) -> Result<nix::fcntl::Flock<std::fs::File>, StoreError> {
    nix::fcntl::Flock::lock(file, nix::fcntl::FlockArg::LockExclusiveNonblock)
        .map_err(|_| StoreError::Busy(dir.to_path_buf()))
}

/// Makes sure `merge --out` may replace `out`: takes its sweep lock when it is a sweep folder
/// (refused while a sweep writes there; held until dropped, past the swap) and refuses a sweep
/// folder with rows that is not among the folders merged.
pub fn claim_merge_out(
    out: &Path,
    inputs: &[PathBuf],
) -> Result<Option<nix::fcntl::Flock<std::fs::File>>, StoreError> {
    let lock_path = out.join(LOCK);
    let lock = if lock_path.exists() {
        let file = std::fs::File::open(&lock_path).map_err(io(&lock_path))?;
        Some(lock_sweep(out, file)?)
    } else {
        None
    };
    let rows = out.join(ROWS);
    let has_rows = std::fs::metadata(&rows).is_ok_and(|m| m.len() > 0);
    let same = |d: &PathBuf| match (d.canonicalize(), out.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    if has_rows && !inputs.iter().any(same) {
        return Err(StoreError::WouldLoseRows(out.to_path_buf()));
    }
    Ok(lock)
}

/// A sweep folder open for writing: rows are appended as runs finish.
pub struct Store {
    dir: PathBuf,
    rows: Mutex<std::fs::File>,
    // Held (an exclusive `flock`) while the store is open: a second sweep in the folder is
    // refused rather than interleaving its rows.
    _lock: nix::fcntl::Flock<std::fs::File>,
}

impl Store {
    /// Opens (or makes) `dir` for `identity`'s sweep and returns the rows it already holds, by
    /// key (rows of other matrices included: the caller picks its own). Only a new, empty or
    /// `pto`-made folder is used.
    pub fn open(
        dir: &Path,
        identity: &Identity,
    ) -> Result<(Store, HashMap<RunKey, Row>), StoreError> {
        if dir.exists()
            && !dir.join(MARKER).exists()
            && std::fs::read_dir(dir).map_err(io(dir))?.next().is_some()
        {
            return Err(StoreError::NotOurs(dir.to_path_buf()));
        }
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let marker = dir.join(MARKER);
        std::fs::write(
            &marker,
            b"written by pto sweep; its rows are kept across reruns\n",
        )
        .map_err(io(&marker))?;
        let lock_path = dir.join(LOCK);
        let lock_file = std::fs::File::create(&lock_path).map_err(io(&lock_path))?;
        let lock = lock_sweep(dir, lock_file)?;
        let rows_path = dir.join(ROWS);
        let rows = read_rows(&rows_path, true)?;
        let text = serde_json::to_string_pretty(identity).unwrap_or_default();
        crate::output::write_atomic(&dir.join(IDENTITY), text.as_bytes()).map_err(|e| {
            StoreError::Io {
                path: dir.join(IDENTITY),
                source: std::io::Error::other(crate::error_chain(&e)),
            }
        })?;
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&rows_path)
            .map_err(io(&rows_path))?;
        Ok((
            Store {
                dir: dir.to_path_buf(),
                rows: Mutex::new(file),
                _lock: lock,
            },
            rows,
        ))
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Appends a finished run's row: one line, one write.
    pub fn append(&self, row: &Row) -> Result<(), StoreError> {
        let path = self.dir.join(ROWS);
        let mut line =
            serde_json::to_string(row).map_err(|e| io(&path)(std::io::Error::other(e)))?;
        line.push('\n');
        let mut f = self.rows.lock().unwrap_or_else(|e| e.into_inner());
        f.write_all(line.as_bytes()).map_err(io(&path))
    }
}

/// The rows of a `runs.jsonl`, by key (a later line for the same key wins). A last line cut
/// short by a crash is dropped and, with `repair`, cut from the file so that appending goes on
/// after a whole line.
pub fn read_rows(path: &Path, repair: bool) -> Result<HashMap<RunKey, Row>, StoreError> {
    let mut rows = HashMap::new();
    if !path.exists() {
        return Ok(rows);
    }
    let bytes = std::fs::read(path).map_err(io(path))?;
    let whole = bytes.iter().rposition(|b| *b == b'\n').map_or(0, |i| i + 1);
    if repair && whole < bytes.len() {
        let f = std::fs::OpenOptions::new()
            .write(true)
            .open(path)
            .map_err(io(path))?;
        f.set_len(whole as u64).map_err(io(path))?;
    }
    for line in String::from_utf8_lossy(&bytes[..whole]).lines() {
        // A line of another format (an older pto) is not a row: its run is made again.
        if let Ok(r) = serde_json::from_str::<Row>(line) {
            rows.insert(r.key, r);
        }
    }
    Ok(rows)
}

/// The runs of a folder still to make: those of `identity` without a row in `rows` (and, with
/// `retry_failed`, those whose row is a failure).
pub fn pending(identity: &Identity, rows: &HashMap<RunKey, Row>, retry_failed: bool) -> Vec<usize> {
    identity
        .indices()
        .into_iter()
        .filter(|&i| match rows.get(&identity.keys[i]) {
            None => true,
            Some(r) => retry_failed && r.status == Status::Failed,
        })
        .collect()
}

/// Shards' folders joined ([`merge`]).
#[derive(Debug)]
pub struct Merged {
    /// The whole sweep's identity (no shard).
    pub identity: Identity,
    /// Every row found, by key.
    pub rows: HashMap<RunKey, Row>,
    /// The shards the folders held (`None`: a whole sweep).
    pub shards: Vec<Option<Shard>>,
    /// Runs (indices from 0) that no folder has a row for.
    pub missing: Vec<usize>,
    /// Runs that more than one folder has a row for (the first folder's is kept).
    pub duplicated: Vec<usize>,
}

/// Joins the folders of one sweep's shards: checks they are of one matrix (the same
/// `sweep_id`), keeps each run's row once, and names the runs missing and those found twice.
pub fn merge(dirs: &[PathBuf]) -> Result<Merged, StoreError> {
    let mut ids = Vec::new();
    for d in dirs {
        ids.push(Identity::read(d)?);
    }
    let Some(first) = ids.first().cloned() else {
        return Err(StoreError::Mismatch(vec!["no folders given".into()]));
    };
    if ids.iter().any(|i| i.sweep_id != first.sweep_id) {
        return Err(StoreError::Mismatch(
            dirs.iter()
                .zip(&ids)
                .map(|(d, i)| {
                    format!(
                        "{} is sweep {} ({}, {} runs, shard {})",
                        d.display(),
                        i.sweep_id,
                        i.matrix,
                        i.keys.len(),
                        i.shard.map_or("all".into(), |s| s.to_string())
                    )
                })
                .collect(),
        ));
    }
    let wanted: HashMap<RunKey, usize> = first
        .keys
        .iter()
        .enumerate()
        .map(|(i, k)| (*k, i))
        .collect();
    let mut rows: HashMap<RunKey, Row> = HashMap::new();
    let mut duplicated = Vec::new();
    for (d, id) in dirs.iter().zip(&ids) {
        let found = read_rows(&d.join(ROWS), false)?;
        // Only the rows of the runs this folder is for (a folder may hold other rows).
        let mine: std::collections::HashSet<RunKey> =
            id.indices().into_iter().map(|i| id.keys[i]).collect();
        for (k, r) in found {
            if !mine.contains(&k) {
                continue;
            }
            match rows.entry(k) {
                std::collections::hash_map::Entry::Occupied(_) => duplicated.push(wanted[&k]),
                std::collections::hash_map::Entry::Vacant(v) => {
                    v.insert(r);
                }
            }
        }
    }
    duplicated.sort_unstable();
    let missing = (0..first.keys.len())
        .filter(|i| !rows.contains_key(&first.keys[*i]))
        .collect();
    Ok(Merged {
        shards: ids.iter().map(|i| i.shard).collect(),
        identity: Identity {
            shard: None,
            ..first
        },
        rows,
        missing,
        duplicated,
    })
}
