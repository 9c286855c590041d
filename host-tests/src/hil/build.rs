//! Building the firmware from the host (inside `cargo test` too): the QEMU build and the
//! bench build, for the reference bench or for a bench file (`PTO_BENCH`), and the model's
//! Cortex-M0 replay binary (`pto-m0`, `thumbv6m-none-eabi`).
//!
//! Every build shares one target directory, `target/fw` (the thumb dependencies and the host's
//! proc macros compiled once for all of them: a fresh build of the QEMU and the bench variant,
//! each in a directory of its own, cost 84 and 103 s of CPU), and runs under a lock of its own,
//! `target/fw/build.lock`,
//! held across processes (the tests run in several) until its ELF is copied out of cargo's
//! output, where the next build of another kind would overwrite it: `target/fw/qemu.elf`,
//! `target/fw/bench.elf`, `target/fw/m0.elf`, or the folder a bench file's build is given.
//!
//! The sources are the workspace `pto` was compiled in, unless the command line says otherwise
//! ([`use_sources`]): a `pto` installed with `cargo install --path host-tests` runs the QEMU
//! firmware from an ELF (`--elf FILE`) or builds it in a source tree (`--workspace DIR`), and says
//! which of the two it needs when the tree it was compiled in is gone.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, OnceLock};

/// Why the firmware could not be built. `Clone`: the result of a build is kept for the
/// process.
#[derive(Debug, Clone, thiserror::Error)]
pub enum BuildError {
    /// Cargo could not be started.
    #[error("cannot run cargo to build the firmware")]
    Cargo(#[source] Arc<std::io::Error>),
    /// No source tree to build in (nor a firmware ELF given, where one would do).
    #[error(
        "{what} needs {needs}, and the source tree pto was compiled in ({compiled}) is not \
         there: {hint}"
    )]
    NoWorkspace {
        /// What needed it.
        what: &'static str,
        /// What it needs.
        needs: &'static str,
        /// The tree pto was compiled in.
        compiled: String,
        /// What to give.
        hint: &'static str,
    },
    /// `--workspace` names a folder that is not a pto source tree.
    #[error(
        "--workspace {0}: not a pto source tree (no firmware/Cargo.toml in it); give the folder \
         holding the top-level Cargo.toml"
    )]
    NotAWorkspace(String),
    /// `--elf` names a file that is missing or not an ELF.
    #[error(
        "--elf {path}: {why}; give the QEMU build of the firmware (`cargo fw` in the source tree, \
         with PTO_BENCH unset for the reference bench, writes \
         target/thumbv7em-none-eabihf/firmware/pto-firmware)"
    )]
    BadElf {
        /// The path given.
        path: String,
        /// What is wrong with it.
        why: String,
    },
    /// The build's folder, its lock or its ELF's copy could not be made.
    #[error("firmware build: {path}")]
    Output {
        /// The file or folder.
        path: String,
        /// The OS error.
        #[source]
        source: Arc<std::io::Error>,
    },
    /// The build failed (the last 30 lines of its output kept).
    #[error(
        "firmware build ({build}) failed (is the target installed? `rustup target add \
         {target}`; for a bench file, the build script's `error:` line says which \
         field):\n{tail}"
    )]
    Failed {
        /// Which build.
        build: &'static str,
        /// Its target triple.
        target: &'static str,
        /// The end of cargo's error output.
        tail: String,
    },
}

/// Which firmware build.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Build {
    /// QEMU board (default features).
    Qemu,
    /// Real bench board (`--no-default-features --features bench`); built, never run here.
    Bench,
    /// The model alone on a Cortex-M0 (`pto-m0`, QEMU `microbit`).
    M0,
}

impl Build {
    /// Short name.
    pub fn name(self) -> &'static str {
        match self {
            Build::Qemu => "qemu",
            Build::Bench => "bench",
            Build::M0 => "m0",
        }
    }

    /// Its manifest (from the workspace root), package (= binary) and target triple.
    fn package(self) -> (&'static str, &'static str, &'static str) {
        match self {
            Build::Qemu | Build::Bench => ("Cargo.toml", "pto-firmware", "thumbv7em-none-eabihf"),
            Build::M0 => ("firmware/m0/Cargo.toml", "pto-m0", "thumbv6m-none-eabi"),
        }
    }
}

/// Where the firmware and the sources come from (the command line's `--elf`, `--workspace`).
#[derive(Debug, Clone, Default)]
pub struct Sources {
    /// A QEMU build of the firmware to run instead of building one.
    pub elf: Option<PathBuf>,
    /// The pto source tree to build in instead of the one pto was compiled in.
    pub workspace: Option<PathBuf>,
}

static SOURCES: OnceLock<Sources> = OnceLock::new();

/// Sets where the firmware and the sources come from, for the whole process (the first call
/// wins; without one, the workspace `pto` was compiled in).
pub fn use_sources(s: Sources) {
    let _ = SOURCES.set(s);
}

fn sources() -> &'static Sources {
    SOURCES.get_or_init(Sources::default)
}

/// The workspace `pto` was compiled in.
fn compiled_workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
}

/// The workspace root: `--workspace`, else the one `pto` was compiled in while it is there.
/// `what` names the command or step that needs it, for the error.
pub fn workspace_root(what: &'static str) -> Result<PathBuf, BuildError> {
    resolve_workspace(sources().workspace.as_deref(), &compiled_workspace(), what)
}

/// [`workspace_root`] from the `--workspace` given and the tree pto was compiled in. A
/// relative `--workspace` is made absolute here: cargo runs inside the tree, and a relative
/// `--target-dir` would be taken from there.
fn resolve_workspace(
    given: Option<&Path>,
    compiled: &Path,
    what: &'static str,
) -> Result<PathBuf, BuildError> {
    let is_tree = |d: &Path| d.join("firmware").join("Cargo.toml").is_file();
    if let Some(w) = given {
        return match std::path::absolute(w) {
            Ok(abs) if is_tree(&abs) => Ok(abs),
            _ => Err(BuildError::NotAWorkspace(w.display().to_string())),
        };
    }
    if is_tree(compiled) {
        Ok(compiled.to_path_buf())
    } else {
        Err(BuildError::NoWorkspace {
            what,
            needs: "the pto source tree",
            compiled: compiled.display().to_string(),
            hint: "give --workspace DIR (a pto source tree)",
        })
    }
}

/// The `--elf` file, checked: there, an ELF, and the QEMU build (its board's name in it; a
/// bench build would boot on no twin).
fn given_elf(path: &Path) -> Result<PathBuf, BuildError> {
    let bad = |why: String| BuildError::BadElf {
        path: path.display().to_string(),
        why,
    };
    let bytes = std::fs::read(path).map_err(|e| bad(e.to_string()))?;
    if !bytes.starts_with(b"\x7fELF") {
        return Err(bad("not an ELF file".into()));
    }
    if !is_qemu_build(&bytes) {
        return Err(bad(format!(
            "not the QEMU build (no `{}` in it: a bench build?)",
            pto_firmware::QEMU_BOARD
        )));
    }
    Ok(path.to_path_buf())
}

/// Whether a firmware image is the QEMU build: its board's name is in it (a bench build's is not).
pub fn is_qemu_build(elf: &[u8]) -> bool {
    let board = pto_firmware::QEMU_BOARD.as_bytes();
    elf.windows(board.len()).any(|w| w == board)
}

/// The error of an I/O step of a build on `path` (its folder, lock or ELF).
fn output_error(path: &Path) -> impl FnOnce(std::io::Error) -> BuildError {
    let path = path.display().to_string();
    move |e| BuildError::Output {
        path,
        source: Arc::new(e),
    }
}

static BUILT: [OnceLock<Result<PathBuf, BuildError>>; 3] =
    [OnceLock::new(), OnceLock::new(), OnceLock::new()];

/// The firmware's ELF: for the QEMU build, the `--elf` file when one was given; otherwise
/// built (profile `firmware`, `thumbv7em-none-eabihf` or for the M0 `thumbv6m-none-eabi`, in
/// `target/fw` so that it can run inside `cargo test`) once per process.
pub fn build(which: Build) -> Result<PathBuf, BuildError> {
    if let (Build::Qemu, Some(elf)) = (which, &sources().elf) {
        return given_elf(elf);
    }
    BUILT[which as usize]
        .get_or_init(|| build_uncached(which))
        .clone()
}

fn build_uncached(which: Build) -> Result<PathBuf, BuildError> {
    let root = workspace_root(match which {
        Build::Qemu => "the QEMU firmware",
        Build::Bench => "the bench firmware",
        Build::M0 => "the Cortex-M0 replay",
    })
    .map_err(|e| match e {
        BuildError::NoWorkspace { what, compiled, .. } if which == Build::Qemu => {
            BuildError::NoWorkspace {
                what,
                needs: "a firmware ELF or the pto source tree to build one in",
                compiled,
                hint: "give --elf FILE (a QEMU build of the firmware) or --workspace DIR (a pto \
                   source tree)",
            }
        }
        e => e,
    })?;
    let elf = fw_dir(&root).join(format!("{}.elf", which.name()));
    build_into(which, None, &elf)
}

/// The firmware builds' target directory.
fn fw_dir(root: &Path) -> PathBuf {
    root.join("target").join("fw")
}

/// Builds the firmware for the bench file `bench` (`PTO_BENCH`, see `pto_firmware::built_config`)
/// and returns its ELF, `pto-firmware-<build>.elf` in `out_dir` (removed first; not cached: each
/// call runs cargo, which rebuilds only what changed: the firmware crate, whose build script
/// reads the file, and its link; the next default build of the same variant rebuilds it back).
/// A bench the model cannot take fails the build; the error's tail carries the build script's
/// message (file, field, range).
pub fn build_for_bench(which: Build, bench: &Path, out_dir: &Path) -> Result<PathBuf, BuildError> {
    std::fs::create_dir_all(out_dir).map_err(output_error(out_dir))?;
    let elf = out_dir.join(format!("pto-firmware-{}.elf", which.name()));
    // An earlier bench's ELF is not left behind where this build fails.
    if let Err(e) = std::fs::remove_file(&elf)
        && e.kind() != std::io::ErrorKind::NotFound
    {
        return Err(output_error(&elf)(e));
    }
    build_into(which, Some(bench), &elf)
}

/// Builds in `target/fw` under its lock and copies the ELF to `elf` (a new file renamed over
/// the old: a QEMU started from the old one keeps it).
fn build_into(which: Build, bench: Option<&Path>, elf: &Path) -> Result<PathBuf, BuildError> {
    let root = workspace_root("building the firmware")?;
    let target_dir = fw_dir(&root);
    std::fs::create_dir_all(&target_dir).map_err(output_error(&target_dir))?;
    let lock_path = target_dir.join("build.lock");
    let lock = std::fs::File::create(&lock_path).map_err(output_error(&lock_path))?;
    // Released when `lock` is dropped (and by the OS if this process dies).
    lock.lock().map_err(output_error(&lock_path))?;
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut cmd = Command::new(cargo);
    let (manifest, package, target) = which.package();
    cmd.current_dir(&root).args([
        "build",
        "--manifest-path",
        manifest,
        "--profile",
        "firmware",
        "-p",
        package,
        "--target",
        target,
        "--target-dir",
    ]);
    cmd.arg(&target_dir);
    // The default builds are for the reference bench whatever the caller's environment says
    // (the golden vectors and the PIL runs assume it).
    match bench {
        Some(b) => cmd.env("PTO_BENCH", b),
        None => cmd.env_remove("PTO_BENCH"),
    };
    if which == Build::Bench {
        cmd.args(["--no-default-features", "--features", "bench"]);
    }
    let out = cmd.output().map_err(|e| BuildError::Cargo(Arc::new(e)))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = err.lines().rev().take(30).collect();
        return Err(BuildError::Failed {
            build: which.name(),
            target,
            tail: tail.into_iter().rev().collect::<Vec<_>>().join("\n"),
        });
    }
    let built = target_dir.join(target).join("firmware").join(package);
    let part = elf.with_extension("elf.part");
    std::fs::copy(&built, &part).map_err(output_error(&built))?;
    std::fs::rename(&part, elf).map_err(output_error(elf))?;
    drop(lock);
    Ok(elf.to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_relative_workspace_is_made_absolute_and_a_missing_tree_is_named() {
        let compiled = compiled_workspace();
        // The tests run in host-tests/: ".." is the tree.
        let w = resolve_workspace(Some(Path::new("..")), Path::new("/nowhere"), "x").unwrap();
        assert!(w.is_absolute(), "{}", w.display());
        assert!(w.join("firmware").join("Cargo.toml").is_file());
        let e = resolve_workspace(Some(Path::new("src")), &compiled, "x").unwrap_err();
        assert!(
            matches!(e, BuildError::NotAWorkspace(ref p) if p == "src"),
            "{e}"
        );
        let e = resolve_workspace(None, Path::new("/nowhere"), "pto model-cost").unwrap_err();
        let text = e.to_string();
        assert!(
            text.starts_with("pto model-cost needs the pto source tree")
                && text.contains("/nowhere")
                && text.contains("--workspace DIR"),
            "{text}"
        );
        assert_eq!(resolve_workspace(None, &compiled, "x").unwrap(), compiled);
    }

    #[test]
    fn an_elf_that_is_not_the_qemu_build_is_named() {
        let dir = std::env::temp_dir().join(format!("pto-elf-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let bench_like = dir.join("bench.elf");
        std::fs::write(&bench_like, b"\x7fELF\x01\x01 stm32f405 bench image").unwrap();
        let e = given_elf(&bench_like).unwrap_err().to_string();
        assert!(e.contains("not the QEMU build"), "{e}");
        let qemu_like = dir.join("qemu.elf");
        let mut bytes = b"\x7fELF\x01\x01".to_vec();
        bytes.extend_from_slice(pto_firmware::QEMU_BOARD.as_bytes());
        std::fs::write(&qemu_like, bytes).unwrap();
        assert_eq!(given_elf(&qemu_like).unwrap(), qemu_like);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
