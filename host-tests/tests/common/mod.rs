//! What the integration tests share: the `pto` binary and its reaped children, a fresh folder
//! per test ([`tmp!`]), a JSON field of `pto`'s output, and, for the QEMU twin, the check of the firmware's model-only P2 error (the HP
//! transducer's wire broken, the estimate on the model alone) against the plant.

#![allow(dead_code)]

use pto_host::hil::pil::{self, Injection, PilRow};
use pto_host::hil::qemu::Qemu;
use pto_host::sim::bench::Bench;
use pto_host::validation::sensors::SensorSpec;
use std::path::PathBuf;
use std::process::{Child, Command};

/// A child process ended and reaped whatever happens.
pub struct Reaped(pub Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The twins against the other QEMU tests of a crate under `cargo test` (one process, its tests
/// on threads): a twin's pseudo-terminal and its plant run against the clock, and more QEMUs
/// beside it on a 2-core machine starved it (42 of 100 frames read by a monitor; with the tests
/// of several files in one crate, a campaign's twin reset mid-segment and a self-test went
/// unanswered). A twin runs alone ([`one_twin`]); the lockstep tests, which wait for each step,
/// run beside each other ([`beside_other_qemus`]). Under cargo-nextest (`scripts/test`) each
/// test is a process of its own: `.config/nextest.toml`'s `twins` group runs each twin alone
/// (beside a fit on both cores, a campaign's runner went unanswered for 3 s).
static TWIN: std::sync::RwLock<()> = std::sync::RwLock::new(());

/// Runs a twin alone for as long as the guard lives (a test that failed holding it passes it
/// on). Under nextest, the test must be in `.config/nextest.toml`'s `twins` group (checked).
pub fn one_twin() -> std::sync::RwLockWriteGuard<'static, ()> {
    if std::env::var_os("NEXTEST").is_some() {
        assert_eq!(
            std::env::var("NEXTEST_TEST_GROUP").as_deref(),
            Ok("twins"),
            "a twin test runs in .config/nextest.toml's `twins` group: add it to the group's filter"
        );
    }
    TWIN.write().unwrap_or_else(|e| e.into_inner())
}

/// Runs a lockstep QEMU test while no twin runs.
pub fn beside_other_qemus() -> std::sync::RwLockReadGuard<'static, ()> {
    TWIN.read().unwrap_or_else(|e| e.into_inner())
}

/// The `pto` binary.
pub fn pto() -> Command {
    Command::new(env!("CARGO_BIN_EXE_pto"))
}

/// Runs `cmd`, asserting it succeeds; returns its stdout.
pub fn run(cmd: &mut Command) -> String {
    let out = cmd.output().expect("pto runs");
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{cmd:?} failed ({}):\n{text}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    text
}

/// The value at `pointer` in a JSON text (null if absent).
pub fn field(json: &str, pointer: &str) -> serde_json::Value {
    let v: serde_json::Value = serde_json::from_str(json).expect("json");
    v.pointer(pointer).cloned().unwrap_or_default()
}

/// The model configuration `pto fit --json` wrote (`out` its output), uploaded over the twin's
/// pseudo-terminal `pty` with `pto link config upload`; returns the file and the upload's JSON.
pub fn upload_fitted(out: &str, pty: &std::path::Path) -> (std::path::PathBuf, String) {
    let model_file = field(out, "/model_file")
        .as_str()
        .map(std::path::PathBuf::from)
        .expect("the fit writes the model configuration");
    let up = run(pto()
        .args(["link", "--port"])
        .arg(pty)
        .args(["--json", "config", "upload"])
        .arg(&model_file));
    println!("upload: {up}");
    (model_file, up)
}

/// The HP transducer's wire broken from `t_s` on.
fn wire_break_from(t_s: f64) -> Box<dyn Fn(f64) -> Injection> {
    Box::new(move |t| {
        if t >= t_s {
            Injection::HpWireBreak
        } else {
            Injection::None
        }
    })
}

/// The model-only check: a charge with the valve closed from `p2_start` bar for `check_s`
/// seconds, the HP transducer's wire breaking at `wire_break_s`.
pub fn check_run(
    q: Qemu,
    plant: &Bench,
    p2_start: f64,
    check_s: f64,
    wire_break_s: f64,
) -> (Qemu, Vec<PilRow>) {
    let (q, _, rows) = pil::closed_loop(
        q,
        plant,
        pil::fixed(0.0),
        p2_start,
        check_s,
        SensorSpec::default(),
        wire_break_from(wire_break_s),
    )
    .expect("check run");
    (q, rows)
}

/// [`check_run`] on the host copy of the firmware's controller with `model`
/// ([`pil::host_closed_loop`]: the firmware's rows bit for bit, `firmware_pil` checks it), for
/// a configuration's figure that needs no twin.
pub fn host_check_run(
    model: &pto_model::ModelConfig,
    plant: &Bench,
    p2_start: f64,
    check_s: f64,
    wire_break_s: f64,
) -> Vec<PilRow> {
    let (_, rows) = pil::host_closed_loop(
        plant,
        model,
        pil::fixed(0.0),
        p2_start,
        check_s,
        SensorSpec::default(),
        wire_break_from(wire_break_s),
    )
    .expect("check run on the host");
    rows
}

/// RMS of the firmware's P2 estimate against the plant from `from_s` on (while the estimate
/// runs on the model), bar.
pub fn model_only_rms_bar(rows: &[PilRow], from_s: f64) -> f64 {
    let e: Vec<f64> = rows
        .iter()
        .filter(|r| r.t >= from_s)
        .filter_map(|r| r.estimate.map(|e| f64::from(e.p2.to_f32()) - r.p2_bar))
        .collect();
    assert!(e.len() > 10_000, "{} model-only steps", e.len());
    (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt()
}

/// The CSV's lines without its `wall_s` column (wall times differ between runs).
pub fn without_wall(csv: &str) -> Vec<String> {
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let wall = header.iter().position(|h| *h == "wall_s").unwrap();
    csv.lines()
        .map(|l| {
            let mut cells: Vec<&str> = l.split(',').collect();
            cells.remove(wall);
            cells.join(",")
        })
        .collect()
}

/// A fresh, empty folder for one test's files, named for its module and `name` and unique to
/// this run: `tmp!("bench")`.
#[allow(unused_macros)]
macro_rules! tmp {
    ($name:expr) => {
        $crate::common::fresh_dir(module_path!(), $name)
    };
}

/// The folder [`tmp!`] makes: `pto-<module>-<pid>-<name>` in the system's temporary folder,
/// emptied if a run left it.
pub fn fresh_dir(module: &str, name: &str) -> PathBuf {
    let module = module.rsplit("::").next().unwrap_or(module);
    let d = std::env::temp_dir().join(format!("pto-{module}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("a temporary folder");
    d
}
