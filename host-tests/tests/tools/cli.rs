//! The `pto` binary: exit codes, error messages that name the file and field, outputs written.

use crate::common::pto;
use std::path::PathBuf;

#[test]
fn bad_bench_file_names_file_field_range_and_unit() {
    let dir = tmp!("bench");
    let f = dir.join("my-bench.toml");
    let text = pto_host::sim::bench::REFERENCE_BENCH_TOML
        .replace("setting_bar = 130.0", "setting_bar = 900.0");
    std::fs::write(&f, text).unwrap();
    let out = pto()
        .args(["simulate", "torque-cfg1-c1", "--bench"])
        .arg(&f)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("my-bench.toml:relief_valve.setting_bar: 900 outside [1, 400] (bar)"),
        "{err}"
    );
}

#[test]
fn unknown_scenario_is_a_clear_error() {
    let out = pto().args(["simulate", "no-such-test"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no-such-test:scenario: neither a built-in scenario"),
        "{err}"
    );
}

#[test]
fn simulate_writes_csv_with_units_and_a_json_summary() {
    let dir = tmp!("sim");
    let out = pto()
        .args(["simulate", "torque-cfg1-c14", "--json", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let worst = v["balance_worst_rel"].as_f64().unwrap();
    println!("balance {worst:e}, peak torque {}", v["peak_torque_nm"]);
    assert!(worst <= 1e-4);
    let csv = std::fs::read_to_string(dir.join("torque-cfg1-c14.csv")).unwrap();
    let header = csv.lines().next().unwrap();
    for col in [
        "time_s",
        "p2_bar",
        "motor_speed_rpm",
        "restraining_torque_nm",
        "hc3_4_cap_bar",
    ] {
        assert!(
            header.split(',').any(|h| h == col),
            "missing {col} in {header}"
        );
    }
    assert_eq!(csv.lines().count(), 1 + 6001);
    assert!(dir.join("torque-cfg1-c14.png").exists() && dir.join("torque-cfg1-c14.svg").exists());
    // Power: the path from the shaft to the generator closes with the energy balance, and its
    // figures are written.
    let p = &v["power"];
    let f = |k: &str| p[k].as_f64().unwrap_or(f64::NAN);
    println!(
        "input {:.1} W, pumped {:.1} W, generator {:.1} W, efficiency {}, closure {:e}",
        f("input_w"),
        f("pumped_w"),
        f("generator_w"),
        p["efficiency"],
        f("closure_rel")
    );
    assert!(f("closure_rel") <= 1e-4);
    assert!(f("input_w") > f("pumped_w") && f("pumped_w") > 0.0);
    for name in ["torque-cfg1-c14-power", "torque-cfg1-c14-losses"] {
        assert!(dir.join(format!("{name}.png")).exists(), "{name}");
        assert!(dir.join(format!("{name}.svg")).exists(), "{name}");
    }
    for col in ["input_power_w", "valve_power_w", "generator_power_w"] {
        assert!(header.split(',').any(|h| h == col), "missing {col}");
    }
}

#[test]
fn scenario_file_with_recorded_trace_runs() {
    let dir = tmp!("trace");
    let mut trace = String::from("time_s,shaft_angle_deg\n");
    for k in 0..=300 {
        let t = k as f64 * 0.1;
        trace.push_str(&format!(
            "{t},{}\n",
            20.0 * (0.2 * std::f64::consts::PI * t).sin()
        ));
    }
    std::fs::write(dir.join("motion.csv"), trace).unwrap();
    std::fs::write(
        dir.join("s.toml"),
        r#"name = "recorded"
config = "Config 1"
cylinders = ["HC3.1", "HC3.4"]
duration_s = 30.0
initial_hp_bar = 80.0
[motion]
kind = "trace"
file = "motion.csv"
[valve]
kind = "table"
time_s = [10.0, 20.0]
aperture_pct = [12.0, 0.0]
"#,
    )
    .unwrap();
    let out = pto()
        .arg("simulate")
        .arg(dir.join("s.toml"))
        .arg("--out")
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let csv = std::fs::read_to_string(dir.join("recorded.csv")).unwrap();
    // The valve table: closed, 12 % from 10 s, closed again from 20 s (spool lag 50 ms).
    let ap: Vec<f64> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(11).unwrap().parse().unwrap())
        .collect();
    assert!(
        ap[900] < 1e-9 && (ap[1500] - 12.0).abs() < 1e-3 && ap[2900] < 1e-3,
        "{} {} {}",
        ap[900],
        ap[1500],
        ap[2900]
    );
}

#[test]
fn scenarios_json_lists_every_builtin() {
    let out = pto().args(["scenarios", "--json"]).output().unwrap();
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        v.as_array().unwrap().len(),
        pto_host::sim::scenario::builtin().len() + pto_host::sim::scenario::sea_family().len()
    );
}

#[test]
fn a_scenario_name_cannot_leave_the_output_folder() {
    let dir = tmp!("escape");
    let f = dir.join("s.toml");
    let (mut s, _) = pto_host::sim::scenario::resolve("torque-cfg1-c1").unwrap();
    s.name = "../../escaped".into();
    std::fs::write(&f, toml::to_string(&s).unwrap()).unwrap();
    let out_dir = dir.join("out");
    let out = pto()
        .args(["simulate"])
        .arg(&f)
        .arg("--out")
        .arg(&out_dir)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains(":name: \"../../escaped\" is not a file-name-safe name"),
        "{err}"
    );
    assert!(
        !dir.join("escaped.csv").exists() && !std::env::temp_dir().join("escaped.csv").exists()
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `pto paper` interrupted (SIGINT) over an earlier run leaves that run's output whole and no
/// temporary folder; a folder of the user's own files is refused as `--out`, never replaced.
#[test]
fn an_interrupted_paper_run_leaves_the_previous_output_whole() {
    use nix::sys::signal::{Signal, kill};
    use nix::unistd::Pid;
    let base = tmp!("paper-int");
    let out_dir = base.join("paper");
    let run = |extra: &[&str]| {
        let mut c = pto();
        c.args(["paper", "--no-plots", "--json", "--out"])
            .arg(&out_dir)
            .args(extra);
        c
    };
    let first = run(&[]).output().unwrap();
    assert!(first.status.code().is_some_and(|c| c <= 1), "{first:?}");
    let report = std::fs::read(out_dir.join("report.md")).unwrap();
    let facts = std::fs::read(out_dir.join("facts.json")).unwrap();
    // A second run, interrupted while it simulates.
    let mut second = run(&[])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1500));
    kill(Pid::from_raw(second.id() as i32), Signal::SIGINT).unwrap();
    let st = second.wait().unwrap();
    assert_eq!(st.code(), Some(130), "interrupted: {st}");
    assert_eq!(std::fs::read(out_dir.join("report.md")).unwrap(), report);
    assert_eq!(std::fs::read(out_dir.join("facts.json")).unwrap(), facts);
    let left: Vec<String> = std::fs::read_dir(&base)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(
        left,
        vec!["paper".to_string()],
        "temporary folders left: {left:?}"
    );
    // The user's own folder.
    let mine = base.join("mine");
    std::fs::create_dir_all(&mine).unwrap();
    std::fs::write(mine.join("notes.txt"), "mine").unwrap();
    let r = pto()
        .args(["paper", "--no-plots", "--out"])
        .arg(&mine)
        .output()
        .unwrap();
    assert_eq!(r.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&r.stderr).contains("not made by pto"));
    assert!(mine.join("notes.txt").exists());
    std::fs::remove_dir_all(&base).unwrap();
}

/// A synthetic log of the paper's charge from 64.5 bar at 5 Hz, in `base/logs`.
fn charge_log(base: &std::path::Path) -> PathBuf {
    synth_log_at_5hz(base, "exp-charge-64.5")
}

/// A synthetic log of the built-in scenario `run` at 5 Hz, in `base/logs`.
fn synth_log_at_5hz(base: &std::path::Path, run: &str) -> PathBuf {
    let logs = base.join("logs");
    let made = pto()
        .args(["synth-logs", "--runs", run, "--rate", "5", "--out"])
        .arg(&logs)
        .output()
        .unwrap();
    assert!(made.status.success(), "{made:?}");
    logs.join(format!("{run}.csv"))
}

/// `pto fit` writes all of its files into `--out`, swapped in whole: an interrupted fit leaves
/// the previous fitted bench, model configuration, figures and report as they were, and no
/// staging folder.
#[test]
fn an_interrupted_fit_leaves_the_previous_output_whole() {
    use nix::sys::signal::{Signal, kill};
    use nix::unistd::Pid;
    let base = tmp!("fit-int");
    let log = charge_log(&base);
    let out_dir = base.join("fit");
    let run = |max_iter: &str| {
        let mut c = pto();
        c.arg("fit")
            .arg(&log)
            .args([
                "--params",
                "trapped_air,cd",
                "--spacing",
                "1",
                "--max-iter",
                max_iter,
            ])
            .arg("--out")
            .arg(&out_dir);
        c
    };
    // One iteration does not converge: --write-anyway writes the fitted files all the same.
    let first = run("1").arg("--write-anyway").output().unwrap();
    assert!(first.status.code().is_some_and(|c| c <= 1), "{first:?}");
    let mut files: Vec<String> = std::fs::read_dir(&out_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    assert_eq!(
        files,
        [
            ".pto-output",
            "fit-exp-charge-64.5.png",
            "fit-exp-charge-64.5.svg",
            "fit.json",
            "reference-bench.fitted.toml",
            "reference-bench.model.toml",
        ]
    );
    let before: Vec<Vec<u8>> = files
        .iter()
        .map(|f| std::fs::read(out_dir.join(f)).unwrap())
        .collect();
    let mut second = run("200")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1200));
    kill(Pid::from_raw(second.id() as i32), Signal::SIGINT).unwrap();
    let st = second.wait().unwrap();
    assert_eq!(st.code(), Some(130), "interrupted: {st}");
    for (f, b) in files.iter().zip(&before) {
        assert_eq!(&std::fs::read(out_dir.join(f)).unwrap(), b, "{f} changed");
    }
    let mut left: Vec<String> = std::fs::read_dir(&base)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left, ["fit", "logs"], "temporary folders left: {left:?}");
    std::fs::remove_dir_all(&base).unwrap();
}

/// Numeric options: NaN, infinities and out-of-range values are argument errors (exit 2) that
/// name the option and its range (`--rtol nan` used to hang, `--rtol 1` to fail in the solver).
#[test]
fn numeric_options_must_be_finite_and_in_range() {
    for (args, want) in [
        (
            vec!["simulate", "torque-cfg1-c1", "--rtol", "nan"],
            "'--rtol <RTOL>': nan outside [1e-12, 1e-2]",
        ),
        (
            vec!["simulate", "torque-cfg1-c1", "--rtol", "inf"],
            "inf outside",
        ),
        (
            vec!["simulate", "torque-cfg1-c1", "--rtol", "-1"],
            "-1 outside",
        ),
        (
            vec!["simulate", "torque-cfg1-c1", "--rtol", "1"],
            "1 outside",
        ),
        (
            vec!["synth-logs", "--rate", "0"],
            "'--rate <RATE>': 0 outside [1e-1, 1e3] Hz",
        ),
        (vec!["fit", "x.csv", "--spacing", "nan"], "nan outside"),
        (
            vec!["fit", "x.csv", "--max-iter", "0"],
            "0 is not in 1..=10000",
        ),
    ] {
        let out = pto().args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(want), "{args:?}: {err}");
    }
}

/// Scenarios that cannot run as written are errors naming the field and the limit (they used
/// to run with exit 0: rods past their end caps, "simulated 0 s", a held last angle, an HP
/// accumulator that never takes oil, LP below zero).
#[test]
fn infeasible_scenarios_are_refused_with_the_field_and_the_limit() {
    let dir = tmp!("feasible");
    let base = || {
        pto_host::sim::scenario::resolve("torque-cfg1-c1")
            .unwrap()
            .0
    };
    let trace = dir.join("short.csv");
    std::fs::write(&trace, "time_s,shaft_angle_deg\n0,0\n1,2\n2,0\n").unwrap();
    let bench_hi = dir.join("hi-precharge.toml");
    std::fs::write(
        &bench_hi,
        pto_host::sim::bench::REFERENCE_BENCH_TOML.replacen(
            "precharge_bar = 25.0",
            "precharge_bar = 135.0",
            1,
        ),
    )
    .unwrap();
    let cases: Vec<(
        pto_host::sim::scenario::Scenario,
        Option<&std::path::Path>,
        &str,
    )> = vec![
        (
            pto_host::sim::scenario::Scenario {
                motion: pto_host::sim::motion::MotionSpec::Sine {
                    amplitude_mm: 500.0,
                    frequency_hz: 0.1,
                },
                ..base()
            },
            None,
            ":motion: the shaft swings to",
        ),
        (
            pto_host::sim::scenario::Scenario {
                sample_interval_s: 5.0,
                duration_s: 2.0,
                ..base()
            },
            None,
            ":sample_interval_s: 5 s is not shorter than duration_s = 2 s",
        ),
        (
            pto_host::sim::scenario::Scenario {
                motion: pto_host::sim::motion::MotionSpec::Trace {
                    file: trace.clone(),
                },
                duration_s: 10.0,
                ..base()
            },
            None,
            ":motion: the trace ends at 2 s, before the run's 10 s",
        ),
        (
            pto_host::sim::scenario::Scenario {
                initial_lp_bar: 3.0,
                ..base()
            },
            None,
            ":initial_lp_bar: 3 bar is not above the LP accumulator's precharge",
        ),
        (
            base(),
            Some(&bench_hi),
            ":hp_accumulator.precharge_bar: 135 bar is not below the relief",
        ),
    ];
    for (i, (s, bench, want)) in cases.into_iter().enumerate() {
        let f = dir.join(format!("case{i}.toml"));
        std::fs::write(&f, toml::to_string(&s).unwrap()).unwrap();
        let mut c = pto();
        c.args(["simulate"])
            .arg(&f)
            .arg("--out")
            .arg(dir.join("out"));
        if let Some(b) = bench {
            c.arg("--bench").arg(b);
        }
        let out = c.output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        println!("case {i}: {}", err.trim());
        assert_eq!(out.status.code(), Some(2), "case {i}: {err}");
        assert!(err.contains(want), "case {i}: {err}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--set` reaches any bench field by its dotted path (simulate and synth-logs alike), keeps
/// its type, and names a wrong path with the fields there.
#[test]
fn set_reaches_any_bench_field() {
    let dir = tmp!("set");
    let ok = pto()
        .args([
            "simulate",
            "torque-cfg1-c1",
            "--json",
            "--set",
            "hp_accumulator.precharge_bar=30",
            "--set",
            "cylinder[0].bore_mm=40",
            "--out",
        ])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    for (set, want) in [
        (
            "hp_accumulator.precharge=30",
            "unknown field `precharge` (fields here:",
        ),
        ("cylinder[9].bore_mm=40", "index 9 outside"),
        (
            "hp_accumulator.precharge_bar=\"high\"",
            "is a string, the field holds a float",
        ),
        (
            "relief_valve.setting_bar=900",
            "relief_valve.setting_bar: 900 outside [1, 400] (bar)",
        ),
    ] {
        let out = pto()
            .args(["simulate", "torque-cfg1-c1", "--set", set, "--out"])
            .arg(&dir)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{set}: {err}");
        assert!(err.contains(want), "{set}: {err}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn every_command_help_shows_examples_and_exit_codes() {
    for cmd in [
        "scenarios",
        "simulate",
        "paper",
        "validate",
        "model-cost",
        "synth-logs",
        "fit",
        "qemu",
        "pil",
        "fw-cost",
        "perf",
        "link",
        "twin",
    ] {
        let out = pto().args([cmd, "--help"]).output().unwrap();
        let help = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{cmd}");
        assert!(
            help.contains("Examples:\n  pto ") && help.contains("Exit status:\n  0 "),
            "{cmd} --help:\n{help}"
        );
    }
    // `pto bench`, `pto perf`'s former name, still runs it (hidden from the command list).
    let out = pto().args(["bench", "--help"]).output().unwrap();
    let help = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && help.contains("Usage: pto perf"),
        "{help}"
    );
    let out = pto().arg("--help").output().unwrap();
    assert!(!String::from_utf8_lossy(&out.stdout).contains("  bench "));
}

/// A fit that did not converge (stopped by its simulation budget: a fit of the charge can
/// converge within any iteration limit, its Cd running to a bound) exits 1, its `converged`
/// check failed, and writes no fitted bench or model configuration (the report and figures
/// only); `--write-anyway` writes them with a first line saying so.
#[test]
fn an_unconverged_fit_writes_no_fitted_bench_unless_asked() {
    let base = tmp!("fit-unconverged");
    let log = charge_log(&base);
    let out_dir = base.join("fit");
    let fit = |extra: &[&str]| {
        pto()
            .arg("fit")
            .arg(&log)
            .args([
                "--params",
                "trapped_air,cd",
                "--spacing",
                "1",
                "--max-simulations",
                "10",
                "--json",
            ])
            .args(extra)
            .arg("--out")
            .arg(&out_dir)
            .output()
            .unwrap()
    };
    let o = fit(&[]);
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["converged"], serde_json::json!(false));
    assert_eq!(v["passed"], serde_json::json!(false));
    let failed: Vec<&str> = v["checks"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["passed"] == serde_json::json!(false))
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    assert!(failed.contains(&"converged"), "{failed:?}");
    assert!(
        v["bench_file"].is_null() && v["model_file"].is_null(),
        "{v}"
    );
    assert!(out_dir.join("fit.json").exists());
    assert!(!out_dir.join("reference-bench.fitted.toml").exists());
    assert!(!out_dir.join("reference-bench.model.toml").exists());
    let o = fit(&["--write-anyway"]);
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    for f in ["reference-bench.fitted.toml", "reference-bench.model.toml"] {
        let text = std::fs::read_to_string(out_dir.join(f)).unwrap();
        assert!(
            text.starts_with("# NOT A FITTED BENCH: the fit failed its checks (converged"),
            "{f}: {text:.80}"
        );
    }
    let _ = std::fs::remove_dir_all(&base);
}

/// An aperture column given as a fraction (0.09 for 9 %) is named before the fit with a hint,
/// fails the `logs` check (exit 1), and no fitted bench is written.
#[test]
fn an_aperture_given_as_a_fraction_is_refused_with_a_hint() {
    let base = tmp!("fit-fraction");
    let path = synth_log_at_5hz(&base, "exp-9pct-101.5");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines = text.lines();
    let header = lines.next().unwrap();
    let col = header.split(',').position(|h| h == "aperture_pct").unwrap();
    let mut out = format!("{header}\n");
    for l in lines {
        let mut f: Vec<String> = l.split(',').map(String::from).collect();
        f[col] = format!("{}", f[col].parse::<f64>().unwrap() / 100.0);
        out.push_str(&f.join(","));
        out.push('\n');
    }
    std::fs::write(&path, out).unwrap();
    let out_dir = base.join("fit");
    let o = pto()
        .arg("fit")
        .arg(&path)
        .args(["--params", "cd", "--spacing", "2", "--out"])
        .arg(&out_dir)
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    println!("{stderr}\n{stdout}");
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr.contains("aperture_pct") && stderr.contains("looks like a fraction"),
        "{stderr}"
    );
    assert!(stdout.contains("FAIL logs"), "{stdout}");
    assert!(!out_dir.join("reference-bench.fitted.toml").exists());
    let _ = std::fs::remove_dir_all(&base);
}

/// A fit whose simulation budget runs out in its first stage (blocked and moving logs: three
/// stages) stops, fails `converged` and exits 1 — it used to index past its partial stage and
/// panic.
#[test]
fn a_fit_out_of_budget_in_an_early_stage_fails_cleanly() {
    let base = tmp!("fit-budget");
    let charge = charge_log(&base.join("a"));
    let discharge = synth_log_at_5hz(&base.join("b"), "exp-discharge-71");
    let o = pto()
        .arg("fit")
        .arg(&charge)
        .arg(&discharge)
        .args([
            "--spacing",
            "2",
            "--max-simulations",
            "10",
            "--json",
            "--out",
        ])
        .arg(base.join("fit"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(v["termination"].as_str().unwrap().contains("budget"), "{v}");
    let _ = std::fs::remove_dir_all(&base);
}

/// `pto link --port PORT campaign run FILE --log-dir DIR` and `extra`, as arguments.
fn campaign_run<'a>(
    port: &'a str,
    file: &'a str,
    log_dir: &'a str,
    extra: &[&'a str],
) -> Vec<&'a str> {
    let mut v = vec![
        "link",
        "--port",
        port,
        "campaign",
        "run",
        file,
        "--log-dir",
        log_dir,
    ];
    v.extend_from_slice(extra);
    v
}

/// `pto plan`, `synth-logs --campaign` and a campaign's logs in `pto fit`: bad input is exit 2
/// naming the file, the field, the value and what is allowed, before any simulation; a log
/// whose sidecar marks it unfinished is refused, with the way out.
#[test]
fn campaign_inputs_are_checked_and_named() {
    let dir = tmp!("campaign");
    let good_path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/campaign-four.toml");
    let good = std::fs::read_to_string(&good_path).unwrap();
    // A copy of the good campaign with one edit.
    let variant = |name: &str, text: String| {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let bad_rate = variant(
        "rate.toml",
        good.replacen("rate_hz = 64.0", "rate_hz = 500.0", 1),
    );
    let bad_cyl = variant(
        "cyl.toml",
        good.replacen(
            "cylinders = [\"HC3.1\", \"HC3.3\"]",
            "cylinders = [\"HC9\"]",
            1,
        ),
    );
    let unknown = variant("unknown.toml", format!("{good}\nbudget = 3\n"));
    let table = variant(
        "table.toml",
        good.replacen(
            "kind = \"constant\"\naperture_pct = 9.0",
            "kind = \"table\"\ntime_s = [0.0]\naperture_pct = [9.0]",
            1,
        ),
    );
    let out_dir = dir.join("logs");
    let s = |p: &std::path::Path| p.display().to_string();
    let (good_file, table_file, bad_rate_file, out) =
        (s(&good_path), s(&table), s(&bad_rate), s(&out_dir));
    let no_port = "/dev/pto-no-such-port";
    for (args, want) in [
        (
            vec!["plan", "--params", "trapped_air,cdd", "--out", "x.toml"],
            "cdd".to_string(),
        ),
        (
            vec!["plan", "--precision", "hp_volume=0.1", "--out", "x.toml"],
            "--precision hp_volume=0.1: `hp_volume` is not among --params".into(),
        ),
        (
            vec!["plan", "--precision", "cd=-1", "--out", "x.toml"],
            "'--precision <NAME=VALUE>': \"cd=-1\": the value must be a positive number".into(),
        ),
        (
            vec!["plan", "--budget-min", "0", "--out", "x.toml"],
            "0 outside [1e0, 1.44e3] min".into(),
        ),
        (
            vec!["plan", "--rate", "500", "--out", "x.toml"],
            "500 outside [1e0, 1.28e2] Hz".into(),
        ),
        (
            vec![
                "synth-logs",
                "--campaign",
                &s(&bad_rate),
                "--out",
                &s(&out_dir),
            ],
            format!("{}: segment[0].rate_hz = 500: 1 to 128 Hz", s(&bad_rate)),
        ),
        (
            vec![
                "synth-logs",
                "--campaign",
                &s(&bad_cyl),
                "--out",
                &s(&out_dir),
            ],
            format!("{}: segment[0].run:", s(&bad_cyl)),
        ),
        (
            vec![
                "synth-logs",
                "--campaign",
                &s(&unknown),
                "--out",
                &s(&out_dir),
            ],
            "unknown field `budget`".into(),
        ),
        // The runner refuses what the controller cannot do by itself, before any port.
        (
            campaign_run(no_port, &table_file, &out, &["--yes"]),
            "segment[0] (moving-cfg1-9pct-from100): valve: the runner sets one fixed aperture"
                .to_string(),
        ),
        (
            campaign_run(no_port, &bad_rate_file, &out, &["--yes"]),
            format!("{bad_rate_file}: segment[0].rate_hz = 500"),
        ),
        (
            campaign_run("x", "c.toml", &out, &["--prepare-wait", "0"]),
            "0 outside [1e0, 3.6e3] s".into(),
        ),
        (
            campaign_run("x", &good_file, &out, &[]),
            "stdin is not a terminal".into(),
        ),
    ] {
        let out = pto().args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(&want), "{args:?}: {err}");
    }
    assert!(!out_dir.exists(), "nothing written on bad input");
    // A segment's log marked unfinished is not fitted.
    let bench = pto_host::sim::bench::Bench::reference();
    let c = pto_host::plan::Campaign::load(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/campaign-four.toml"),
        &bench,
    )
    .unwrap();
    let mut short = c.segment[0].run.clone();
    short.duration_s = 10.0;
    let log = pto_host::fit::synth_scenario_log(
        &bench,
        &short,
        16.0,
        pto_host::validation::sensors::SensorSpec::default(),
        1,
        &dir,
    )
    .unwrap();
    log.write().unwrap();
    pto_host::plan::Record {
        campaign: "c.toml".into(),
        index: 0,
        status: pto_host::plan::Status::Unfinished,
        note: "interrupted at 10 s of 120".into(),
        segment: c.segment[0].clone(),
    }
    .write_for(&log.path)
    .unwrap();
    let out = pto()
        .args(["fit", &s(&log.path), "--out", &s(&dir.join("fit"))])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("segment 0 of c.toml is marked unfinished (interrupted at 10 s of 120)")
            && err.contains("rerun that segment"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_firmware_elf_or_source_tree_that_is_not_one_is_named() {
    let dir = tmp!("sources");
    let not_elf = dir.join("pto-firmware");
    std::fs::write(&not_elf, "#!/bin/sh\n").unwrap();
    let cases: [(&[&str], String); 6] = [
        (
            &["qemu", "--elf", "/no/such/pto-firmware"],
            "--elf /no/such/pto-firmware: No such file".into(),
        ),
        (
            &["pil", "--elf", not_elf.to_str().unwrap()],
            format!("--elf {}: not an ELF file", not_elf.display()),
        ),
        (
            &["model-cost", "--workspace", dir.to_str().unwrap()],
            format!(
                "--workspace {}: not a pto source tree (no firmware/Cargo.toml in it)",
                dir.display()
            ),
        ),
        (
            &["fw-cost", "--workspace", dir.to_str().unwrap()],
            "not a pto source tree".into(),
        ),
        (
            &["fw-cost", "--elf", "x"],
            "unexpected argument '--elf'".into(),
        ),
        (
            &["twin", "--elf", "a", "--workspace", "b"],
            "cannot be used with".into(),
        ),
    ];
    for (args, expect) in cases {
        let out = pto().args(args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(&expect), "{args:?}: {err}");
    }
    // What a missing firmware says it needs (`cargo fw` writes one).
    let out = pto()
        .args(["qemu", "--elf", not_elf.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("`cargo fw`"));
}

/// The motor line kept as a patch for a decision (docs/model.md, known limits) still applies to
/// the tree: a change that moves the code under it must carry the patch along.
#[test]
fn the_kept_motor_line_patch_still_applies() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    if !root.join(".git").exists() {
        println!("not a git checkout: the patch is not checked here");
        return;
    }
    let out = std::process::Command::new("git")
        .current_dir(&root)
        .args(["apply", "--check", "docs/motor-line.patch"])
        .output()
        .expect("git runs");
    assert!(
        out.status.success(),
        "docs/motor-line.patch no longer applies:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
