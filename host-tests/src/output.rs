//! Multi-file outputs written whole or not at all, and what an interrupted run must undo.
//!
//! A [`StagedDir`] collects a run's files in a hidden sibling folder and swaps it in for the
//! output folder when the run is complete (Linux `renameat2(RENAME_EXCHANGE)`: one atomic
//! step), so an interrupted or failed run leaves the previous output whole and no temporary
//! files. Only a folder `pto` made (it holds a [`MARKER`] file) or an empty one is ever
//! replaced: `--out .` or a folder of the user's own files is refused, never emptied.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// Writes `bytes` to a temporary name next to `path`, then renames it: a file is never left
/// half-written.
pub fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> Result<(), String> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(|e| format!("cannot write {}: {e}", tmp.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| format!("cannot write {}: {e}", path.display()))
}

/// The file that marks a folder as a `pto` output (so it may be replaced whole).
pub const MARKER: &str = ".pto-output";

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
    pub fn new(out: &Path) -> Result<Self, String> {
        if out.exists() {
            let is_ours = out.join(MARKER).exists();
            let empty = std::fs::read_dir(out)
                .map_err(|e| format!("--out {}: {e}", out.display()))?
                .next()
                .is_none();
            if !is_ours && !empty {
                return Err(format!(
                    "--out {}: the folder exists, is not empty and was not made by pto (no {MARKER} \
                     file); pto replaces its output folder whole: choose a new or empty folder",
                    out.display()
                ));
            }
        }
        let name = out
            .file_name()
            .ok_or_else(|| format!("--out {}: not a folder name", out.display()))?
            .to_string_lossy()
            .into_owned();
        let parent = match out.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent)
            .map_err(|e| format!("cannot create {}: {e}", parent.display()))?;
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
        std::fs::create_dir(&tmp).map_err(|e| format!("cannot create {}: {e}", tmp.display()))?;
        std::fs::write(
            tmp.join(MARKER),
            b"written by pto; replaced whole by its next run\n",
        )
        .map_err(|e| format!("cannot write in {}: {e}", tmp.display()))?;
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
    pub fn commit(mut self) -> Result<(), String> {
        use nix::fcntl::{AT_FDCWD, RenameFlags, renameat2};
        let err = |e: &dyn std::fmt::Display| format!("cannot replace {}: {e}", self.out.display());
        if self.out.exists() {
            let exchange = || {
                renameat2(
                    AT_FDCWD,
                    &self.tmp,
                    AT_FDCWD,
                    &self.out,
                    RenameFlags::RENAME_EXCHANGE,
                )
                .map_err(|e| err(&e))
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
                return Err(format!(
                    "{}: files that pto did not write appeared there during the run: left as \
                     they were; this run's output is in {}",
                    self.out.display(),
                    self.tmp.display()
                ));
            }
            std::fs::remove_dir_all(&self.tmp).map_err(|e| err(&e))?;
        } else {
            std::fs::rename(&self.tmp, &self.out).map_err(|e| err(&e))?;
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
pub fn install_interrupt_handler(end_children: fn()) -> Result<(), String> {
    ctrlc::set_handler(move || {
        end_children();
        remove_staged();
        eprintln!("interrupted: nothing left half-written, child processes stopped");
        std::process::exit(130);
    })
    .map_err(|e| format!("cannot install the interrupt handler: {e}"))
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
        let e = s.commit().unwrap_err();
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
        let e = StagedDir::new(&mine).unwrap_err();
        assert!(e.contains("not made by pto"), "{e}");
        assert!(mine.join("thesis.tex").exists());
        std::fs::remove_dir_all(&base).unwrap();
    }
}
