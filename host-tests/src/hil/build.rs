//! Building the firmware from the host (inside `cargo test` too): the QEMU build and the
//! bench build, each in a target directory of its own, for the reference bench or for a bench
//! file (`PTO_BENCH`).

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
    /// The build failed (the last 30 lines of its output kept).
    #[error(
        "firmware build ({build}) failed (is the target installed? `rustup target add \
         thumbv7em-none-eabihf`; for a bench file, the build script's `error:` line says which \
         field):\n{tail}"
    )]
    Failed {
        /// Which build.
        build: &'static str,
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
}

impl Build {
    /// Short name.
    pub fn name(self) -> &'static str {
        match self {
            Build::Qemu => "qemu",
            Build::Bench => "bench",
        }
    }
}

/// The workspace root.
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
}

static BUILT: [OnceLock<Result<PathBuf, BuildError>>; 2] = [OnceLock::new(), OnceLock::new()];

/// Builds the firmware (profile `firmware`, `thumbv7em-none-eabihf`, its own target directory so that it
/// can run inside `cargo test`) once per process and returns the ELF path.
pub fn build(which: Build) -> Result<PathBuf, BuildError> {
    BUILT[which as usize]
        .get_or_init(|| build_uncached(which))
        .clone()
}

fn build_uncached(which: Build) -> Result<PathBuf, BuildError> {
    build_into(
        which,
        None,
        &workspace_root()
            .join("target")
            .join("fw")
            .join(which.name()),
    )
}

/// Builds the firmware for the bench file `bench` (`PTO_BENCH`, see `pto_firmware::built_config`)
/// into `target_dir` (not cached: each call runs cargo, which rebuilds only what changed) and
/// returns the ELF path. A bench the model cannot take fails the build; the error's tail carries
/// the build script's message (file, field, range).
pub fn build_for_bench(
    which: Build,
    bench: &Path,
    target_dir: &Path,
) -> Result<PathBuf, BuildError> {
    build_into(which, Some(bench), target_dir)
}

fn build_into(
    which: Build,
    bench: Option<&Path>,
    target_dir: &Path,
) -> Result<PathBuf, BuildError> {
    let root = workspace_root();
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.current_dir(&root).args([
        "build",
        "--profile",
        "firmware",
        "-p",
        "pto-firmware",
        "--target",
        "thumbv7em-none-eabihf",
        "--target-dir",
    ]);
    cmd.arg(target_dir);
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
            tail: tail.into_iter().rev().collect::<Vec<_>>().join("\n"),
        });
    }
    Ok(target_dir
        .join("thumbv7em-none-eabihf")
        .join("firmware")
        .join("pto-firmware"))
}
