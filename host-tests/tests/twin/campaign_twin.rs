//! A planned calibration end to end on the QEMU twin: `pto plan --budget-min 3` plans the
//! segment(s) that determine the trapped air from the reference bench; the twin's plant (trapped
//! air 9 %, the firmware's built-in configuration 6 %) follows the campaign while `pto link
//! campaign run` drives the firmware over the twin's pseudo-terminal (the serial-port code
//! path), logging each segment with its sidecar; `pto fit` takes the folder as it is;
//! `pto link config upload` sends the fitted configuration; the firmware's model-only P2 error
//! against the plant is measured before and after.

use crate::common::{field, pto, run};
use pto_host::fit;
use pto_host::hil::build::{self, Build};
use pto_host::hil::qemu::Qemu;
use pto_host::hil::twin;
use pto_host::plan::Campaign;
use pto_host::sim::bench::{Bench, apply_override};
use pto_host::validation::sensors::SensorSpec;
use std::process::Stdio;
use std::time::Instant;

const TRUE_TRAPPED_AIR: f64 = 0.09;
/// The model-only check: a charge from 64.5 bar, the HP wire breaking at 3 s, 15 s long.
const CHECK_P2_BAR: f64 = 64.5;
const CHECK_S: f64 = 15.0;
const WIRE_BREAK_S: f64 = 3.0;

#[test]
fn a_planned_campaign_runs_on_the_twin_and_its_fit_goes_back_to_the_firmware() {
    let _twin = crate::common::one_twin();
    let t0 = Instant::now();
    let dir = std::env::temp_dir().join(format!("pto-campaign-twin-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let elf = build::build(Build::Qemu).expect("QEMU build");

    // The plan, from the reference bench (the firmware's built-in configuration), with a
    // margin on the fit's ± 0.005: the plan predicts σ at its guess (6 %), the fit judges at
    // the truth (9 %), where a charge says less of the trapped air.
    let campaign_file = dir.join("campaign.toml");
    run(pto()
        .args([
            "plan",
            "--params",
            "trapped_air",
            "--precision",
            "trapped_air=0.0035",
        ])
        .args(["--budget-min", "3", "--out"])
        .arg(&campaign_file));
    let reference = Bench::reference();
    let campaign = Campaign::load(&campaign_file, &reference).expect("the plan's campaign");
    let planned_s: f64 = campaign.segment.iter().map(|s| s.run.duration_s).sum();
    println!(
        "plan: {} segments, {planned_s:.0} s of logs, {:.1} min of bench time ({:.0} s wall)",
        campaign.segment.len(),
        campaign.minutes(),
        t0.elapsed().as_secs_f64()
    );
    assert!(campaign.minutes() <= 3.0);

    let mut file = reference.file.clone();
    apply_override(
        &mut file,
        &format!("trapped_air={TRUE_TRAPPED_AIR}"),
        &fit::set_shortcuts(),
    )
    .unwrap();
    let plant = Bench::from_file(file, "the twin's plant: trapped air 9 %").unwrap();

    // The model-only P2 error with the built-in configuration: the firmware's controller on the
    // host (its rows are the firmware's bit for bit: `firmware_pil`), no twin needed.
    let builtin = pto_firmware::built_config::model().expect("built-in configuration");
    let rows0 =
        crate::common::host_check_run(&builtin, &plant, CHECK_P2_BAR, CHECK_S, WIRE_BREAK_S);
    let err_builtin = crate::common::model_only_rms_bar(&rows0, WIRE_BREAK_S);

    // The campaign: the runner over the pseudo-terminal, the plant following in this thread.
    let q = Qemu::boot_twin(&elf, false).expect("twin");
    let pty = q.pty.clone().expect("pseudo-terminal");
    let logs = dir.join("logs");
    // The runner ends by itself when the twin's QEMU ends (its pseudo-terminal closes).
    let mut child = pto()
        .args(["link", "--port"])
        .arg(&pty)
        .args(["--json", "campaign", "run"])
        .arg(&campaign_file)
        .arg("--log-dir")
        .arg(&logs)
        .args(["--yes", "--prepare-wait", "120"])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("pto link campaign run");
    // A runner that fails leaves the twin waiting for its cylinders: a watchdog ends QEMU 30 s
    // after the runner ended if the campaign has not, so the test fails instead of hanging.
    let qemu_pid = q.pid();
    let stdout = child.stdout.take().unwrap();
    let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
    let watchdog = std::thread::spawn(move || {
        let status = child.wait().expect("the runner ends");
        if done_rx
            .recv_timeout(std::time::Duration::from_secs(30))
            .is_err()
        {
            let _ = std::process::Command::new("kill")
                .args(["-9", &qemu_pid.to_string()])
                .status();
        }
        status
    });
    let t_campaign = Instant::now();
    // The twin's P2 at the campaign's first start: letting 60 bar down to 10 through the motor
    // takes the reference bench ≈ 2 min (0.4 bar/s at 30 %, the motor's flow the limit), which
    // the runner does, and which this test does not wait for.
    let p2_start = campaign.segment[0].run.initial_hp_bar.unwrap_or(60.0);
    let (q, phases) =
        twin::run_campaign(q, &plant, &campaign, p2_start, SensorSpec::default(), |m| {
            println!("{m}")
        })
        .expect("the twin follows the campaign");
    let _ = done_tx.send(());
    let mut json = String::new();
    std::io::Read::read_to_string(&mut { stdout }, &mut json).unwrap();
    let status = watchdog.join().expect("the watchdog");
    let simulated: f64 = phases.iter().map(|p| p.duration_s).sum();
    println!(
        "campaign: {simulated:.0} s simulated in {:.0} s wall; runner: {json}",
        t_campaign.elapsed().as_secs_f64()
    );
    assert!(status.success(), "runner exit {status}");
    assert_eq!(field(&json, "/complete"), serde_json::Value::Bool(true));
    let segments = field(&json, "/segments");
    let segments = segments.as_array().expect("segments");
    assert_eq!(segments.len(), campaign.segment.len());
    for s in segments {
        assert_eq!(s["status"], "complete", "{s}");
        assert_eq!(s["lost"], 0, "{s}");
    }

    // The fit, on the folder as the runner left it.
    let mut fit_cmd = pto();
    fit_cmd.arg("fit");
    for s in &campaign.segment {
        fit_cmd.arg(logs.join(format!("{}.csv", s.run.name)));
    }
    let out = run(fit_cmd
        .args(["--params", "trapped_air", "--json", "--out"])
        .arg(dir.join("fit")));
    let fitted = field(&out, "/params/0/value").as_f64().unwrap();
    let sigma = field(&out, "/params/0/sigma").as_f64().unwrap_or(f64::NAN);
    println!(
        "trapped air: true {TRUE_TRAPPED_AIR}, built in 0.06, fitted {fitted:.4} ± {sigma:.4}"
    );
    assert!(
        (fitted - TRUE_TRAPPED_AIR).abs() <= 0.005,
        "fitted trapped air {fitted}"
    );
    // The upload over the pseudo-terminal, then the check on the fitted configuration.
    crate::common::upload_fitted(&out, &pty);
    let (q, rows1) = crate::common::check_run(q, &plant, CHECK_P2_BAR, CHECK_S, WIRE_BREAK_S);
    drop(q);
    let err_fitted = crate::common::model_only_rms_bar(&rows1, WIRE_BREAK_S);
    println!(
        "model-only P2 error RMS over {} s: built-in {err_builtin:.3} bar, fitted {err_fitted:.3} bar; {:.0} s wall in all",
        CHECK_S - WIRE_BREAK_S,
        t0.elapsed().as_secs_f64()
    );
    assert!(
        err_fitted < err_builtin,
        "the fitted configuration's P2 error {err_fitted} is not below the built-in's {err_builtin}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Resuming: a folder whose every segment is complete runs nothing (each skipped, exit 0); a
/// complete log of a differently planned segment of the same name is refused before any
/// segment runs (exit 2, the log named), the folder left as it was.
#[test]
fn a_campaign_resumes_past_complete_segments_and_refuses_a_foreign_log() {
    let _twin = crate::common::one_twin();
    let dir = std::env::temp_dir().join(format!("pto-campaign-resume-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let campaign = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/campaign-four.toml");
    let logs = dir.join("logs");
    run(pto()
        .args(["synth-logs", "--campaign"])
        .arg(&campaign)
        .arg("--out")
        .arg(&logs));
    let elf = build::build(Build::Qemu).expect("QEMU build");
    let q = Qemu::boot_twin(&elf, false).expect("twin");
    let pty = q.pty.clone().expect("pseudo-terminal");
    let runner = || {
        pto()
            .args(["link", "--port"])
            .arg(&pty)
            .args(["--json", "campaign", "run"])
            .arg(&campaign)
            .arg("--log-dir")
            .arg(&logs)
            .arg("--yes")
            .output()
            .expect("pto link campaign run")
    };
    let out = runner();
    let json = String::from_utf8_lossy(&out.stdout).into_owned();
    println!("every segment complete: {json}");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let segments = field(&json, "/segments");
    let segments = segments.as_array().expect("segments");
    assert_eq!(segments.len(), 2);
    assert!(
        segments
            .iter()
            .all(|s| s["skipped"] == true && s["status"] == "complete")
    );

    // The first segment left unfinished, the second's sidecar from another plan (another log
    // rate): refused before the first is run again.
    let first = logs.join("moving-cfg1-9pct-from100.segment.toml");
    let unfinished = std::fs::read_to_string(&first).unwrap().replacen(
        "status = \"complete\"",
        "status = \"unfinished\"",
        1,
    );
    std::fs::write(&first, &unfinished).unwrap();
    let sidecar = logs.join("charge-cfg1-c1234-40mm-0.2hz-from10.segment.toml");
    let text = std::fs::read_to_string(&sidecar).unwrap();
    std::fs::write(
        &sidecar,
        text.replacen("rate_hz = 64.0", "rate_hz = 32.0", 1),
    )
    .unwrap();
    let before: Vec<_> = std::fs::read_dir(&logs)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    let t0 = Instant::now();
    let out = runner();
    assert!(t0.elapsed().as_secs_f64() < 10.0, "refused at once");
    assert_eq!(std::fs::read_to_string(&first).unwrap(), unfinished);
    let err = String::from_utf8_lossy(&out.stderr);
    println!("a foreign log: {err}");
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("charge-cfg1-c1234-40mm-0.2hz-from10.csv")
            && err.contains("another plan's segment"),
        "{err}"
    );
    let after: Vec<_> = std::fs::read_dir(&logs)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(before.len(), after.len(), "nothing written");
    drop(q);
    let _ = std::fs::remove_dir_all(&dir);
}
