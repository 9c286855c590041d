//! The bench workflow end to end on the QEMU twin: the full simulation is the plant of a bench
//! whose trapped air (9 %) differs from the firmware's built-in configuration (the reference
//! bench's 6 %); `pto link monitor --log` records a bench log over the twin's pseudo-terminal
//! (the serial-port code path); `pto fit` recovers the trapped air from it; `pto link config
//! upload` sends the fitted configuration; the firmware's estimates then equal, bit for bit, a
//! host copy of the controller that went through the same session, and its model-only P2 error
//! against the plant (HP transducer wire break) drops.

use crate::common::{Reaped, field, pto, run};
use pto_firmware::control::{ControlConfig, Controller, NoClock};
use pto_host::fit;
use pto_host::hil::build::{self, Build};
use pto_host::hil::pil::{self, Injection, PilRow};
use pto_host::hil::qemu::Qemu;
use pto_host::sim::bench::{Bench, apply_override};
use pto_host::validation::sensors::SensorSpec;
use pto_model::fx::{Aperture, Pressure};
use pto_model::scheduler::{Mode, SchedulerConfig};
use pto_model::{Estimate, ModelConfig};
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

const TRUE_TRAPPED_AIR: f64 = 0.09;
/// A charge with the valve closed from 64.5 bar (the paper's `exp-charge-64.5`): the pumped
/// flow, and so P2's rise, depends on the trapped air.
const P2_START_BAR: f64 = 64.5;
const RECORD_S: f64 = 60.0;
/// The check after the upload: the HP transducer's wire breaks at 3 s, the estimate runs on
/// the model alone for 22 s.
const CHECK_S: f64 = 25.0;
const WIRE_BREAK_S: f64 = 3.0;

/// The check run: the charge, the HP transducer's wire breaking at 3 s.
fn check_run(q: Qemu, plant: &Bench) -> (Qemu, Vec<PilRow>) {
    crate::common::check_run(q, plant, P2_START_BAR, CHECK_S, WIRE_BREAK_S)
}

/// RMS of the firmware's P2 estimate against the plant while the estimate runs on the model.
fn model_only_rms_bar(rows: &[PilRow]) -> f64 {
    crate::common::model_only_rms_bar(rows, WIRE_BREAK_S)
}

/// A host copy of the firmware's controller follows one closed-loop run as the firmware did
/// (reset, mode, duty from the harness's `prime`, then every frame); returns the steps whose
/// estimate differs in any bit.
fn mirror(c: &mut Controller, rows: &[PilRow], duty: (u8, u8)) -> (usize, usize) {
    c.reset(
        Pressure::from_num(P2_START_BAR as f32),
        Pressure::from_num(8.0f32),
    )
    .expect("reset");
    c.set_mode(Mode::Fixed(Aperture::ZERO));
    c.set_duty(duty.0, duty.1);
    let (mut compared, mut differ) = (0, 0);
    for r in rows {
        if !c.fresh(r.frame.tick) {
            continue;
        }
        let o = c.sample(&r.frame, &mut NoClock);
        let fw: Estimate = r.estimate.expect("every step answered");
        compared += 1;
        differ += usize::from(fw != o.estimate);
    }
    (compared, differ)
}

fn wait_line(
    lines: &std::sync::mpsc::Receiver<String>,
    what: &str,
    timeout: Duration,
) -> Vec<String> {
    let t0 = Instant::now();
    let mut seen = Vec::new();
    while t0.elapsed() < timeout {
        if let Ok(l) = lines.recv_timeout(Duration::from_millis(100)) {
            let hit = l.contains(what);
            seen.push(l);
            if hit {
                return seen;
            }
        }
    }
    panic!("no {what:?} within {timeout:?}; saw {seen:?}");
}

#[test]
fn a_fitted_configuration_goes_from_the_bench_log_to_the_twin() {
    let _twin = crate::common::one_twin();
    let dir = std::env::temp_dir().join(format!("pto-bench-workflow-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let elf = build::build(Build::Qemu).expect("QEMU build");
    let mut file = Bench::reference().file;
    apply_override(
        &mut file,
        &format!("trapped_air={TRUE_TRAPPED_AIR}"),
        &fit::set_shortcuts(),
    )
    .unwrap();
    let plant = Bench::from_file(file, "the plant: trapped air 9 %").unwrap();
    let builtin = pto_firmware::built_config::model().expect("built-in configuration");
    assert_eq!(builtin, ModelConfig::reference());
    let spec = SensorSpec::default();

    // The model-only P2 error with the built-in configuration: the firmware's controller on the
    // host (its rows are the firmware's bit for bit: `firmware_pil`), no twin needed.
    let t0 = Instant::now();
    let rows0 =
        crate::common::host_check_run(&builtin, &plant, P2_START_BAR, CHECK_S, WIRE_BREAK_S);
    let err_builtin = model_only_rms_bar(&rows0);

    // The session: record over the pseudo-terminal while the plant runs.
    let q = Qemu::boot_twin(&elf, false).expect("twin");
    let pty = q.pty.clone().expect("pseudo-terminal");
    let log = dir.join("charge.csv");
    let mut mon = Reaped(
        pto()
            .args(["link", "--port"])
            .arg(&pty)
            .args(["monitor", "--log"])
            .arg(&log)
            .args(["--duration", &format!("{}", RECORD_S - 1.0), "--json"])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("pto link monitor"),
    );
    let stderr = mon.0.stderr.take().unwrap();
    let (tx, lines) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for l in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(l);
        }
    });
    wait_line(&lines, "monitoring", Duration::from_secs(30));
    let (q, _, rows_a) = pil::closed_loop(
        q,
        &plant,
        pil::fixed(0.0),
        P2_START_BAR,
        RECORD_S,
        spec,
        Box::new(|_| Injection::None),
    )
    .expect("recording run");
    let t_wait = Instant::now();
    let status = loop {
        if let Some(st) = mon.0.try_wait().unwrap() {
            break st;
        }
        assert!(
            t_wait.elapsed() < Duration::from_secs(30),
            "the monitor did not stop"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut json = String::new();
    std::io::Read::read_to_string(mon.0.stdout.as_mut().unwrap(), &mut json).unwrap();
    println!("monitor: {json}");
    assert!(status.success(), "monitor exit {status}: {json}");
    let frames = field(&json, "/frames").as_u64().unwrap();
    let rows = field(&json, "/rows").as_u64().unwrap();
    assert_eq!(field(&json, "/lost").as_u64(), Some(0), "telemetry lost");
    assert_eq!(
        field(&json, "/dropped").as_u64(),
        Some(0),
        "telemetry damaged"
    );
    // 64 Hz over 59 s of firmware time, every frame.
    assert_eq!(frames, 59 * 64 + 1, "{json}");
    assert_eq!(rows, frames);

    // The fit, on the log as the monitor wrote it.
    let fit_dir = dir.join("fit");
    let out = run(pto()
        .arg("fit")
        .arg(&log)
        .args([
            "--params",
            "trapped_air",
            "--spacing",
            "0.015625",
            "--json",
            "--out",
        ])
        .arg(&fit_dir));
    let fitted = field(&out, "/params/0/value").as_f64().unwrap();
    let sigma = field(&out, "/params/0/sigma").as_f64().unwrap_or(f64::NAN);
    println!(
        "trapped air: true {TRUE_TRAPPED_AIR}, built in {}, fitted {fitted:.4} ± {sigma:.4}",
        builtin.trapped_air_fraction
    );
    assert!(
        (fitted - TRUE_TRAPPED_AIR).abs() <= 0.005,
        "fitted trapped air {fitted}"
    );
    // The upload over the pseudo-terminal, then its read-back.
    let (model_file, up) = crate::common::upload_fitted(&out, &pty);
    let fitted_cfg = load_model(&model_file);
    assert!((f64::from(fitted_cfg.trapped_air_fraction) - fitted).abs() < 1e-6);
    let shown = run(pto()
        .args(["link", "--port"])
        .arg(&pty)
        .args(["--json", "config", "show"]));
    assert_eq!(field(&shown, "/source").as_str(), Some("Uploaded"));
    assert_eq!(field(&shown, "/fingerprint"), field(&up, "/fingerprint"));

    // The check run on the fitted configuration.
    let (q, rows_b) = check_run(q, &plant);
    drop(q);
    let err_fitted = model_only_rms_bar(&rows_b);

    // Bit for bit: a host copy of the controller through the same session.
    let sched = SchedulerConfig::default();
    let cc = ControlConfig::default();
    let mut c = Controller::new(&builtin, &sched, &cc).unwrap();
    let duty = (0b1001, 0);
    let (na, da) = mirror(&mut c, &rows_a, duty);
    c.reconfigure(&fitted_cfg, &sched, &cc).unwrap();
    let (nb, db) = mirror(&mut c, &rows_b, duty);
    println!("bit for bit: {na} steps before the upload ({da} differ), {nb} after ({db} differ)");
    println!(
        "model-only P2 error RMS over {} s: built-in {err_builtin:.3} bar, fitted {err_fitted:.3} bar; {:.0} s wall",
        CHECK_S - WIRE_BREAK_S,
        t0.elapsed().as_secs_f64()
    );
    assert_eq!((da, db), (0, 0));
    assert!(na > 60_000 && nb > 25_000);
    assert!(
        err_fitted < err_builtin,
        "the fitted configuration's P2 error {err_fitted} is not below the built-in's {err_builtin}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

fn load_model(path: &Path) -> ModelConfig {
    toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}
