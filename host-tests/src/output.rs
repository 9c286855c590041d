//! Multi-file outputs written whole or not at all, and what an interrupted run must undo.
//!
//! A [`StagedDir`] collects a run's files in a hidden sibling folder and swaps it in for the
//! output folder when the run is complete (Linux `renameat2(RENAME_EXCHANGE)`: one atomic
//! step), so an interrupted or failed run leaves the previous output whole and no temporary
//! files. Only a folder `pto` made (it holds a [`MARKER`] file) or an empty one is ever
//! replaced: `--out .` or a folder of the user's own files is refused, never emptied.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// Why an output could not be written, named with its file or folder (the OS error as the
/// source).
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// A file could not be written (or renamed into place).
    #[error("cannot write {path}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// A folder could not be created.
    #[error("cannot create {path}")]
    Create {
        /// The folder.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The staging folder's marker file could not be written.
    #[error("cannot write in {dir}")]
    WriteIn {
        /// The staging folder.
        dir: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// `--out` exists but cannot be listed.
    #[error("--out {out}")]
    ReadOut {
        /// The output folder.
        out: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// `--out` has no folder name (`/`, `..`).
    #[error("--out {out}: not a folder name")]
    NotAFolderName {
        /// The output folder as given.
        out: PathBuf,
    },
    /// `--out` holds files pto did not write: it is never replaced.
    #[error(
        "--out {out}: the folder exists, is not empty and was not made by pto (no {MARKER} \
         file); pto replaces its output folder whole: choose a new or empty folder"
    )]
    NotOurs {
        /// The output folder.
        out: PathBuf,
    },
    /// The staged folder could not be swapped in for the output folder.
    #[error("cannot replace {out}")]
    Exchange {
        /// The output folder.
        out: PathBuf,
        /// The OS error of `renameat2`.
        source: nix::errno::Errno,
    },
    /// The output folder (or the previous one, swapped out) could not be moved or removed.
    #[error("cannot replace {out}")]
    Replace {
        /// The output folder.
        out: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Files of someone else's appeared in the output folder during the run: swapped back.
    #[error(
        "{out}: files that pto did not write appeared there during the run: left as they were; \
         this run's output is in {kept}"
    )]
    Appeared {
        /// The output folder.
        out: PathBuf,
        /// Where this run's output was left.
        kept: PathBuf,
    },
    /// The SIGINT/SIGTERM handler could not be installed.
    #[error("cannot install the interrupt handler")]
    Interrupt(#[source] ctrlc::Error),
}

/// Writes `bytes` to a temporary name next to `path`, then renames it: a file is never left
/// half-written.
pub fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> Result<(), OutputError> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(|source| OutputError::Write {
        path: tmp.clone(),
        source,
    })?;
    std::fs::rename(&tmp, path).map_err(|source| OutputError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// The file that marks a folder as a `pto` output (so it may be replaced whole).
pub const MARKER: &str = ".pto-output";

/// A command that ends cleanly on the first Ctrl-C or SIGTERM (it polls [`stop_requested`]).
static GRACEFUL: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
/// Ctrl-C or SIGTERM arrived while [`GRACEFUL`].
static STOP: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// From now on the first Ctrl-C or SIGTERM only asks the command to stop
/// ([`stop_requested`]): it finishes its files itself (a second one abandons it as usual).
pub fn stop_on_interrupt() {
    GRACEFUL.store(true, std::sync::atomic::Ordering::Relaxed);
}

/// A Ctrl-C or SIGTERM asked the command to stop.
pub fn stop_requested() -> bool {
    STOP.load(std::sync::atomic::Ordering::Relaxed)
}

/// Staging folders not yet committed, for the interrupt handler.
static STAGED: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// A run's output folder under construction.
#[derive(Debug)]
pub struct StagedDir {
    out: PathBuf,
    tmp: PathBuf,
    committed: bool,
}

impl StagedDir {
    /// Stages `out`: checks that it is new, empty or a `pto` output, and makes the hidden
    /// sibling folder the run writes into.
    pub fn new(out: &Path) -> Result<Self, OutputError> {
        if out.exists() {
            let is_ours = out.join(MARKER).exists();
            let empty = std::fs::read_dir(out)
                .map_err(|source| OutputError::ReadOut {
                    out: out.to_path_buf(),
                    source,
                })?
                .next()
                .is_none();
            if !is_ours && !empty {
                return Err(OutputError::NotOurs {
                    out: out.to_path_buf(),
                });
            }
        }
        let name = out
            .file_name()
            .ok_or_else(|| OutputError::NotAFolderName {
                out: out.to_path_buf(),
            })?
            .to_string_lossy()
            .into_owned();
        let parent = match out.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent).map_err(|source| OutputError::Create {
            path: parent.clone(),
            source,
        })?;
        // Staging folders of earlier runs that were killed before they could clean up.
        let prefix = format!(".{name}.partial-");
        if let Ok(entries) = std::fs::read_dir(&parent) {
            for e in entries.flatten() {
                if e.file_name().to_string_lossy().starts_with(&prefix) {
                    let _ = std::fs::remove_dir_all(e.path());
                }
            }
        }
        let tmp = parent.join(format!("{prefix}{}", std::process::id()));
        std::fs::create_dir(&tmp).map_err(|source| OutputError::Create {
            path: tmp.clone(),
            source,
        })?;
        std::fs::write(
            tmp.join(MARKER),
            b"written by pto; replaced whole by its next run\n",
        )
        .map_err(|source| OutputError::WriteIn {
            dir: tmp.clone(),
            source,
        })?;
        if let Ok(mut s) = STAGED.lock() {
            s.push(tmp.clone());
        }
        Ok(StagedDir {
            out: out.to_path_buf(),
            tmp,
            committed: false,
        })
    }

    /// Where the run writes its files.
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// The final folder (for messages).
    pub fn out(&self) -> &Path {
        &self.out
    }

    /// Swaps the staged folder in for the output folder, the old one removed after.
    pub fn commit(mut self) -> Result<(), OutputError> {
        use nix::fcntl::{AT_FDCWD, RenameFlags, renameat2};
        let err = |source: std::io::Error| OutputError::Replace {
            out: self.out.clone(),
            source,
        };
        if self.out.exists() {
            let exchange = || {
                renameat2(
                    AT_FDCWD,
                    &self.tmp,
                    AT_FDCWD,
                    &self.out,
                    RenameFlags::RENAME_EXCHANGE,
                )
                .map_err(|source| OutputError::Exchange {
                    out: self.out.clone(),
                    source,
                })
            };
            exchange()?;
            // `tmp` now holds the previous output. Checked again (the run took a while): only a
            // folder pto made or an empty one is removed; anything else is swapped back.
            let ours = self.tmp.join(MARKER).exists()
                || std::fs::read_dir(&self.tmp).is_ok_and(|mut d| d.next().is_none());
            if !ours {
                exchange()?;
                // Kept where it is for the user to look at (the next run removes it).
                self.committed = true;
                forget(&self.tmp);
                return Err(OutputError::Appeared {
                    out: self.out.clone(),
                    kept: self.tmp.clone(),
                });
            }
            std::fs::remove_dir_all(&self.tmp).map_err(err)?;
        } else {
            std::fs::rename(&self.tmp, &self.out).map_err(err)?;
        }
        self.committed = true;
        forget(&self.tmp);
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_dir_all(&self.tmp);
            forget(&self.tmp);
        }
    }
}

fn forget(p: &Path) {
    if let Ok(mut s) = STAGED.lock() {
        s.retain(|x| x != p);
    }
}

/// Removes every staging folder not yet committed (for the interrupt handler).
pub fn remove_staged() {
    let staged = std::mem::take(&mut *STAGED.lock().unwrap_or_else(|e| e.into_inner()));
    for p in staged {
        let _ = std::fs::remove_dir_all(p);
    }
}

/// On SIGINT (Ctrl-C) or SIGTERM: run `end_children` (the caller's child processes, e.g.
/// `hil::qemu::end_all_children`), remove the staging folders, exit with 130. Call once at the
/// start of the program.
pub fn install_interrupt_handler(end_children: fn()) -> Result<(), OutputError> {
    ctrlc::set_handler(move || {
        use std::sync::atomic::Ordering;
        if GRACEFUL.load(Ordering::Relaxed) && !STOP.swap(true, Ordering::Relaxed) {
            eprintln!("\nstopping (Ctrl-C again to abandon)…");
            return;
        }
        end_children();
        remove_staged();
        eprintln!("interrupted: nothing left half-written, child processes stopped");
        std::process::exit(130);
    })
    .map_err(OutputError::Interrupt)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_staged_folder_replaces_the_old_output_whole_or_not_at_all() {
        let base = std::env::temp_dir().join(format!("pto-staged-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&base);
        std::fs::create_dir_all(&base).unwrap();
        let out = base.join("out");
        // First run: a new folder.
        let s = StagedDir::new(&out).unwrap();
        std::fs::write(s.path().join("a.txt"), "1").unwrap();
        s.commit().unwrap();
        assert_eq!(std::fs::read_to_string(out.join("a.txt")).unwrap(), "1");
        // A run that fails: the old output stays whole, no temporary folder left.
        {
            let s = StagedDir::new(&out).unwrap();
            std::fs::write(s.path().join("b.txt"), "half").unwrap();
        }
        assert!(out.join("a.txt").exists() && !out.join("b.txt").exists());
        // A complete second run replaces it whole.
        let s = StagedDir::new(&out).unwrap();
        std::fs::write(s.path().join("b.txt"), "2").unwrap();
        s.commit().unwrap();
        assert!(!out.join("a.txt").exists() && out.join("b.txt").exists());
        let left: Vec<_> = std::fs::read_dir(&base).unwrap().collect();
        assert_eq!(left.len(), 1, "no temporary folders: {left:?}");
        // Files of the user's appearing in an empty --out during the run: swapped back, kept.
        let late = base.join("late");
        let s = StagedDir::new(&late).unwrap();
        std::fs::create_dir_all(&late).unwrap();
        std::fs::write(late.join("mine.txt"), "x").unwrap();
        let e = s.commit().unwrap_err().to_string();
        assert!(e.contains("did not write"), "{e}");
        assert!(late.join("mine.txt").exists());
        let kept = base.join(format!(".late.partial-{}", std::process::id()));
        assert!(
            kept.join(MARKER).exists(),
            "this run's output kept for the user"
        );
        std::fs::remove_dir_all(&late).unwrap();
        std::fs::remove_dir_all(&kept).unwrap();
        // A staging folder a killed run left behind goes with the next run.
        let stale = base.join(".out.partial-1");
        std::fs::create_dir_all(&stale).unwrap();
        let s = StagedDir::new(&out).unwrap();
        assert!(!stale.exists());
        drop(s);
        // A folder of the user's own files is refused, never replaced.
        let mine = base.join("mine");
        std::fs::create_dir_all(&mine).unwrap();
        std::fs::write(mine.join("thesis.tex"), "x").unwrap();
        let e = StagedDir::new(&mine).unwrap_err().to_string();
        assert!(e.contains("not made by pto"), "{e}");
        assert!(mine.join("thesis.tex").exists());
        std::fs::remove_dir_all(&base).unwrap();
    }
}
