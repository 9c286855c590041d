//! `pto sweep`: the matrix's expansion and its refusals, shards, resuming, merging, the tables
//! (Parquet read back equals the CSV), failure rows, Ctrl-C.

use crate::common::{pto, without_wall};
use proptest::prelude::*;
use pto_host::sweep::table::Table;
use pto_host::sweep::{Matrix, Shard};
use std::path::{Path, PathBuf};

/// A fresh folder `name` holding [`SMALL`] as `m.toml`: the folder and the matrix's path.
fn small_matrix(name: &str) -> (PathBuf, PathBuf) {
    let dir = tmp!(name);
    let m = dir.join("m.toml");
    std::fs::write(&m, SMALL).unwrap();
    (dir, m)
}

/// Test III cut to 20 s (the valve stays closed: P2 does not reach 100 bar), 2 × 2 runs.
const SMALL: &str = r#"
scenario = "test3-ap10"
[set]
"scenario.duration_s" = 20.0
"scenario.sample_interval_s" = 0.05
[[axis]]
field = "bench.hp_accumulator.volume_l"
values = [5.0, 10.0]
[[axis]]
field = "scenario.initial_hp_bar"
values = [60, 90]
"#;

fn parse(text: &str) -> Result<Matrix, pto_host::sweep::MatrixError> {
    Matrix::parse(text, "m.toml", Path::new("."), None)
}

/// The problems of a matrix the plan refuses, as one string.
fn refusal(text: &str) -> String {
    match parse(text) {
        Err(e) => e.to_string(),
        Ok(m) => m.plan().err().map(|e| e.to_string()).unwrap_or_default(),
    }
}

#[test]
fn a_matrix_expands_last_axis_fastest_and_every_run_has_its_values() {
    let m = parse(SMALL).unwrap();
    assert_eq!(m.len(), 4);
    assert_eq!(m.point(1), vec![0, 1]);
    assert_eq!(m.point(2), vec![1, 0]);
    assert_eq!(
        m.describe(3),
        "bench.hp_accumulator.volume_l = 10.0, scenario.initial_hp_bar = 90"
    );
    let s = m.spec(3).unwrap();
    assert_eq!(s.bench.file.hp_accumulator.volume_l, 10.0);
    assert_eq!(s.scenario.initial_hp_bar, Some(90.0));
    assert_eq!(s.scenario.duration_s, 20.0);
    let keys = m.plan().unwrap();
    assert_eq!(keys.len(), 4);
    // The key is the run's content: the same run written differently has the same key.
    let again = parse(&SMALL.replace("values = [60, 90]", "values = [60.0, 90.0]")).unwrap();
    assert_eq!(again.plan().unwrap(), keys);
    // Linked fields and the fixed-point controller as the valve's driver.
    let m = parse(
        r#"
scenario = "test3-ap10"
[set]
"controller.mode" = "hold-pressure"
[[axis]]
fields = ["controller.setpoint", "controller.seed"]
values = [[90, 1], [110, 2]]
"#,
    )
    .unwrap();
    assert_eq!(m.len(), 2);
    let s = m.spec(1).unwrap();
    assert_eq!(
        (
            s.controller.mode.as_str(),
            s.controller.setpoint,
            s.controller.seed
        ),
        ("hold-pressure", Some(110.0), 2)
    );
    m.plan().unwrap();
}

#[test]
fn a_bad_matrix_is_refused_naming_file_axis_run_value_and_range() {
    for (change, want) in [
        (
            (
                "bench.hp_accumulator.volume_l",
                "bench.hp_acumulator.volume_l",
            ),
            "m.toml: runs 1, 2, 3, 4 of 4 (run 1: bench.hp_acumulator.volume_l = 5.0, \
             scenario.initial_hp_bar = 60): bench.hp_acumulator.volume_l: unknown field \
             `hp_acumulator` (fields here:",
        ),
        (
            ("values = [5.0, 10.0]", "values = [5.0, -1.0]"),
            "(run 3: bench.hp_accumulator.volume_l = -1.0, scenario.initial_hp_bar = 60): \
             bench.hp_accumulator.volume_l: -1 outside [0.1, 500] (L)",
        ),
        (
            ("values = [60, 90]", "values = [60, 900]"),
            "scenario.initial_hp_bar: 900 outside [0, 140] (bar)",
        ),
        (
            ("values = [60, 90]", "values = [60, \"high\"]"),
            "scenario.initial_hp_bar: `\"high\"` is a string",
        ),
        (
            ("\"scenario.duration_s\"", "\"scenaro.duration_s\""),
            "m.toml: scenaro.duration_s: a field starts with bench., scenario. or controller.",
        ),
        (
            (
                "\"scenario.duration_s\" = 20.0",
                "\"scenario.duration_s\" = 0.0",
            ),
            "scenario.duration_s: 0 outside [0.01, 1000000] (s)",
        ),
        (
            ("scenario = \"test3-ap10\"", "scenario = \"no-such\""),
            "no-such:scenario: neither a built-in scenario",
        ),
        (
            (
                "field = \"bench.hp_accumulator.volume_l\"",
                "field = \"controller.mode\"",
            ),
            "controller.mode: `5.0` is a float, the field holds a string",
        ),
        (
            (
                "[set]",
                "[set]\n\"controller.mode\" = \"hold\"\n\"controller.setpoint\" = 1",
            ),
            "controller: mode \"hold\": want fixed PCT, hold-pressure BAR, hold-speed RPM or \
             max-autonomy RPM (or `scenario`)",
        ),
        (
            (
                "[set]",
                "[set]\n\"controller.mode\" = \"hold-pressure\"\n\"controller.setpoint\" = 300",
            ),
            "controller: mode hold-pressure 300: outside [1, 130] bar",
        ),
    ] {
        let text = SMALL.replace(change.0, change.1);
        let e = refusal(&text);
        assert!(e.contains(want), "{change:?}:\n{e}\nwant: {want}");
    }
    // The runs refused for one reason are one line (here 2 of 4), with the first's values;
    // each other reason a line of its own.
    let e = refusal(&SMALL.replace("values = [5.0, 10.0]", "values = [5.0, -1.0]"));
    assert_eq!(e.lines().count(), 1, "{e}");
    assert!(
        e.starts_with("m.toml: runs 3, 4 of 4 (run 3: bench.hp_accumulator.volume_l = -1.0"),
        "{e}"
    );
    let e = refusal(
        &SMALL
            .replace("values = [60, 90]", "values = [\"high\", 90]")
            .replace("values = [5.0, 10.0]", "values = [5.0, -1.0]"),
    );
    assert_eq!(e.lines().count(), 2, "{e}");
    // Linked fields want one value per field; an axis wants values.
    let e = refusal(
        "scenario = \"test3-ap10\"\n[[axis]]\nfields = [\"scenario.duration_s\", \
         \"controller.seed\"]\nvalues = [[10, 1], [20]]\n",
    );
    assert!(e.contains("m.toml: axis 1: scenario.duration_s, controller.seed: values[1] = [20]: want a list of 2 values"), "{e}");
    let e = refusal(
        "scenario = \"test3-ap10\"\n[[axis]]\nfield = \"scenario.duration_s\"\nvalues = []\n",
    );
    assert!(
        e.contains("axis 1: scenario.duration_s: `values` is empty"),
        "{e}"
    );
    // A field set twice, an unknown key, a setpoint without a scheduler mode.
    let e = refusal(&format!(
        "{SMALL}\n[[axis]]\nfield = \"scenario.initial_hp_bar\"\nvalues = [1]\n"
    ));
    assert!(e.contains("scenario.initial_hp_bar: set twice"), "{e}");
    let e = refusal(&format!("runs = 3\n{SMALL}"));
    assert!(e.contains("unknown field `runs`"), "{e}");
    let e = refusal(&format!(
        "{SMALL}\n[[axis]]\nfield = \"controller.setpoint\"\nvalues = [100]\n"
    ));
    assert!(e.contains("takes no setpoint"), "{e}");
    // The same run twice.
    let e = refusal(&SMALL.replace("values = [60, 90]", "values = [60, 60.0]"));
    assert!(e.contains("is run 1 (") && e.contains("again"), "{e}");
}

proptest! {
    /// `--shard K/N` for K = 1..N covers every run exactly once, in shards that differ in size
    /// by at most one run.
    #[test]
    fn shards_cover_every_run_exactly_once(runs in 0usize..2000, n in 1usize..40) {
        let mut seen = vec![0u32; runs];
        let mut sizes = Vec::new();
        for k in 1..=n {
            let s: Shard = format!("{k}/{n}").parse().unwrap();
            let mine: Vec<usize> = (0..runs).filter(|i| s.has(*i)).collect();
            sizes.push(mine.len());
            for i in mine {
                seen[i] += 1;
            }
        }
        prop_assert!(seen.iter().all(|c| *c == 1));
        let (lo, hi) = (sizes.iter().min().unwrap(), sizes.iter().max().unwrap());
        prop_assert!(hi - lo <= 1);
    }
}

/// With plain `index mod N`, `--shard K/16` of a matrix whose last axis has 4 values gave each
/// shard one value of it (the docs' Slurm example on `sea-states.toml`); the turn each block
/// gives every shard each value.
#[test]
fn a_shard_does_not_hold_one_value_of_the_last_axis_alone() {
    for (runs, n, last) in [(72usize, 16usize, 4usize), (6, 3, 3), (64, 8, 8)] {
        for k in 1..=n {
            let s: Shard = format!("{k}/{n}").parse().unwrap();
            let mut values: Vec<usize> =
                (0..runs).filter(|i| s.has(*i)).map(|i| i % last).collect();
            values.sort_unstable();
            values.dedup();
            let share = runs / n;
            assert!(
                values.len() >= share.min(last).min(2),
                "{runs} runs, shard {k}/{n}, last axis of {last}: values {values:?}"
            );
        }
    }
}

/// A run's key is its content: not the spelling of the matrix's folder, and a recorded motion's
/// bytes (an edited trace makes its runs again).
#[test]
fn a_run_key_follows_the_trace_not_the_folder_spelling() {
    let dir = tmp!("key");
    let trace = |amp: f64| {
        let mut t = String::from("time_s,shaft_angle_deg\n");
        for k in 0..=200 {
            let x = k as f64 * 0.1;
            t.push_str(&format!("{x},{}\n", amp * (0.6 * x).sin()));
        }
        t
    };
    std::fs::write(dir.join("motion.csv"), trace(10.0)).unwrap();
    let text = SMALL.replace(
        "[[axis]]\nfield = \"bench.hp_accumulator.volume_l\"",
        "\"scenario.motion\" = { kind = \"trace\", file = \"motion.csv\" }\n[[axis]]\nfield = \"bench.hp_accumulator.volume_l\"",
    );
    assert!(text.contains("motion.csv"));
    let keys = |d: &Path| {
        Matrix::parse(&text, "m.toml", d, None)
            .unwrap()
            .keys()
            .unwrap()
    };
    let absolute = keys(&dir);
    let dotted = keys(&dir.join(".").join("..").join(dir.file_name().unwrap()));
    assert_eq!(absolute, dotted);
    std::fs::write(dir.join("motion.csv"), trace(12.0)).unwrap();
    let edited = keys(&dir);
    assert!(absolute.iter().zip(&edited).all(|(a, b)| a != b));
}

#[test]
fn shard_syntax_is_checked() {
    for bad in ["0/3", "4/3", "3", "a/b", "1/0"] {
        assert!(bad.parse::<Shard>().is_err(), "{bad}");
    }
    assert_eq!("2/3".parse::<Shard>().unwrap(), Shard { k: 2, n: 3 });
}

/// Runs `pto sweep` (or `merge`) and returns its JSON report and exit code.
fn sweep(args: &[&str]) -> (serde_json::Value, Option<i32>, String) {
    let out = pto()
        .arg("sweep")
        .args(args)
        .arg("--json")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    let v = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}\n{stderr}", String::from_utf8_lossy(&out.stdout)));
    (v, out.status.code(), stderr)
}

#[test]
fn a_sweep_resumes_shards_merge_to_the_whole_and_parquet_reads_back_as_the_csv() {
    let (dir, m) = small_matrix("resume");
    let m = m.to_str().unwrap();
    let whole = dir.join("whole");
    let whole_s = whole.to_str().unwrap();
    let (v, code, err) = sweep(&[m, "--out", whole_s]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(
        (v["ran"].as_u64(), v["ok"].as_u64()),
        (Some(4), Some(4)),
        "{v}"
    );
    println!("{} runs in {:.2} s", v["ran"], v["wall_s"]);
    // Parquet read back is the CSV, cell for cell.
    let csv = std::fs::read_to_string(whole.join("sweep.csv")).unwrap();
    let back = Table::read_parquet(&whole.join("sweep.parquet")).unwrap();
    assert_eq!(back.csv().unwrap(), csv);
    assert_eq!(back.len(), 4);
    for col in [
        "run",
        "bench.hp_accumulator.volume_l",
        "scenario.initial_hp_bar",
        "status",
        "p2_mean_bar",
        "input_power_w",
        "generator_power_w",
        "efficiency_pct",
        "time_at_relief_s",
        "motor_speed_std_rpm",
        "balance_worst_rel",
    ] {
        assert!(back.column(col).is_some(), "no column {col}");
    }
    // A larger accumulator from the same start: P2 rises more slowly.
    let p2 = back.column("p2_max_bar").unwrap();
    assert!(p2.cells.number(0).unwrap() > p2.cells.number(2).unwrap());
    assert!(whole.join("heatmap-efficiency_pct.png").exists());
    assert!(whole.join("heatmap-generator_power_w.svg").exists());
    // Again: every run is skipped, the table is the same.
    let (v, code, _) = sweep(&[m, "--out", whole_s]);
    assert_eq!(code, Some(0));
    assert_eq!(
        (v["ran"].as_u64(), v["skipped_finished"].as_u64()),
        (Some(0), Some(4))
    );
    assert_eq!(
        std::fs::read_to_string(whole.join("sweep.csv")).unwrap(),
        csv
    );
    // Two shards, merged: the whole sweep's table.
    let mut shard_dirs = Vec::new();
    for k in 1..=2 {
        let d = dir.join(format!("shard{k}"));
        let (v, code, err) = sweep(&[
            m,
            "--shard",
            &format!("{k}/2"),
            "--out",
            d.to_str().unwrap(),
        ]);
        assert_eq!(code, Some(0), "{err}");
        assert_eq!(v["ran"].as_u64(), Some(2));
        assert!(
            !d.join("heatmap-efficiency_pct.png").exists(),
            "a shard draws no heat maps"
        );
        shard_dirs.push(d);
    }
    let merged = dir.join("merged");
    let mut args: Vec<&str> = vec!["merge"];
    args.extend(shard_dirs.iter().map(|d| d.to_str().unwrap()));
    args.extend(["--out", merged.to_str().unwrap()]);
    let (v, code, err) = sweep(&args);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(v["missing_runs"].as_array().unwrap().len(), 0);
    let merged_csv = std::fs::read_to_string(merged.join("sweep.csv")).unwrap();
    assert_eq!(without_wall(&merged_csv), without_wall(&csv));
    assert!(merged.join("heatmap-efficiency_pct.png").exists());
    // One shard alone: the other's runs are missing, exit 1; a shard twice is reported. (Shard
    // 1/2 of 4 runs: run 1 of the first pair, run 4 of the second: the turn each block.)
    let (v, code, _) = sweep(&[
        "merge",
        shard_dirs[0].to_str().unwrap(),
        shard_dirs[0].to_str().unwrap(),
        "--out",
        dir.join("merged-one").to_str().unwrap(),
    ]);
    assert_eq!(code, Some(1));
    assert_eq!(v["missing_runs"], serde_json::json!([2, 3]));
    assert_eq!(v["duplicated_runs"], serde_json::json!([1, 4]));
    // A shard's folder resumed as the whole sweep runs only the other shard's runs.
    let (v, code, _) = sweep(&[m, "--out", shard_dirs[0].to_str().unwrap()]);
    assert_eq!(code, Some(0));
    assert_eq!(
        (v["ran"].as_u64(), v["skipped_finished"].as_u64()),
        (Some(2), Some(2))
    );
    // Folders of another matrix do not merge.
    let other = dir.join("other.toml");
    std::fs::write(&other, SMALL.replace("[5.0, 10.0]", "[5.0, 12.0]")).unwrap();
    let od = dir.join("other");
    let (_, code, _) = sweep(&[other.to_str().unwrap(), "--out", od.to_str().unwrap()]);
    assert_eq!(code, Some(0));
    let out = pto()
        .args(["sweep", "merge", whole_s, od.to_str().unwrap(), "--out"])
        .arg(&merged)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("the folders hold different sweeps"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_bad_matrix_exits_2_before_any_run_and_a_foreign_folder_is_refused() {
    let dir = tmp!("refuse");
    let m = dir.join("m.toml");
    std::fs::write(
        &m,
        SMALL.replace("values = [5.0, 10.0]", "values = [5.0, 0.0]"),
    )
    .unwrap();
    let out = pto()
        .args(["sweep", m.to_str().unwrap(), "--out"])
        .arg(dir.join("out"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("m.toml: runs 3, 4 of 4 (run 3: "), "{err}");
    assert!(!dir.join("out").exists(), "nothing written");
    let mine = dir.join("mine");
    std::fs::create_dir_all(&mine).unwrap();
    std::fs::write(mine.join("thesis.tex"), "x").unwrap();
    std::fs::write(&m, SMALL).unwrap();
    let out = pto()
        .args(["sweep", m.to_str().unwrap(), "--out"])
        .arg(&mine)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("was not made by pto"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_failed_run_is_a_failure_row_and_the_sweep_exits_1_until_it_is_run_again() {
    // A run that cannot be made becomes a row that says why, not a crash.
    let m = parse(SMALL).unwrap();
    let mut spec = m.spec(0).unwrap();
    let key = spec.key();
    spec.scenario.duration_s = -1.0;
    let row = pto_host::sweep::run::run(&spec, key);
    assert_eq!(row.status, pto_host::sweep::run::Status::Failed);
    assert!(row.figures.is_none());
    let e = row.error.unwrap();
    assert!(e.contains("scenario.duration_s: -1 outside"), "{e}");
    // Through the command: a failure row (here one a past run left) makes the sweep exit 1,
    // names the run, and stays finished until --retry-failed.
    let (dir, mf) = small_matrix("failed");
    let out = dir.join("out");
    let (_, code, _) = sweep(&[mf.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_eq!(code, Some(0));
    let rows = std::fs::read_to_string(out.join("runs.jsonl")).unwrap();
    let mut first: serde_json::Value = serde_json::from_str(rows.lines().next().unwrap()).unwrap();
    first["status"] = "failed".into();
    first["figures"] = serde_json::Value::Null;
    first["error"] = "solver failed at t = 3.000000 s: step size too small".into();
    let mut text = rows.clone();
    text.push_str(&format!("{first}\n"));
    std::fs::write(out.join("runs.jsonl"), text).unwrap();
    let (v, code, _) = sweep(&[mf.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_eq!(code, Some(1), "{v}");
    assert_eq!(
        (v["ran"].as_u64(), v["failed"].as_u64()),
        (Some(0), Some(1))
    );
    assert!(
        v["failures"][0]["error"]
            .as_str()
            .unwrap()
            .contains("step size too small")
    );
    let csv = std::fs::read_to_string(out.join("sweep.csv")).unwrap();
    let failed = csv.lines().find(|l| l.contains(",failed,")).unwrap();
    assert!(failed.ends_with("step size too small"), "{failed}");
    let (v, code, _) = sweep(&[
        mf.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--retry-failed",
    ]);
    assert_eq!(code, Some(0), "{v}");
    assert_eq!(
        (v["ran"].as_u64(), v["failed"].as_u64()),
        (Some(1), Some(0))
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn ctrl_c_keeps_every_finished_row_whole_and_a_rerun_goes_on() {
    use nix::sys::signal::{Signal, kill};
    use nix::unistd::Pid;
    let dir = tmp!("interrupt");
    let m = dir.join("m.toml");
    // Eight 400 s runs on one thread: a few seconds in all.
    std::fs::write(
        &m,
        "scenario = \"test3-ap10\"\n[[axis]]\nfield = \"scenario.valve.aperture_pct\"\n\
         values = [5, 8, 10, 12, 15, 20, 25, 30]\n",
    )
    .unwrap();
    let out = dir.join("out");
    let mut child = pto()
        .args(["sweep", m.to_str().unwrap(), "--jobs", "1", "--out"])
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let rows = out.join("runs.jsonl");
    let start = std::time::Instant::now();
    while std::fs::read_to_string(&rows).map_or(0, |t| t.lines().count()) < 2 {
        assert!(start.elapsed().as_secs() < 120, "no rows");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    kill(Pid::from_raw(child.id() as i32), Signal::SIGINT).unwrap();
    let status = child.wait().unwrap();
    let mut err = String::new();
    std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut err).unwrap();
    assert_eq!(status.code(), Some(130), "{err}");
    assert!(err.contains("interrupted"), "{err}");
    let text = std::fs::read_to_string(&rows).unwrap();
    assert!(text.ends_with('\n'));
    let done = text.lines().count();
    for l in text.lines() {
        serde_json::from_str::<serde_json::Value>(l).unwrap();
    }
    assert!((2..8).contains(&done), "{done} rows");
    let csv = std::fs::read_to_string(out.join("sweep.csv")).unwrap();
    assert_eq!(
        csv.lines().count(),
        1 + done,
        "the table holds the finished runs"
    );
    let (v, code, e) = sweep(&[m.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_eq!(code, Some(0), "{e}");
    assert_eq!(v["skipped_finished"].as_u64(), Some(done as u64));
    assert_eq!(v["ran"].as_u64(), Some(8 - done as u64));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `merge --out` does not replace a sweep folder whose rows it would lose, nor one a sweep is
/// writing (its lock).
#[test]
fn a_merge_does_not_replace_a_sweep_folder_it_was_not_given() {
    let (dir, m) = small_matrix("merge-out");
    let m = m.to_str().unwrap();
    let (whole, shard) = (dir.join("whole"), dir.join("shard1"));
    let (_, code, err) = sweep(&[m, "--out", whole.to_str().unwrap(), "--no-plots"]);
    assert_eq!(code, Some(0), "{err}");
    let (_, code, err) = sweep(&[m, "--shard", "1/2", "--out", shard.to_str().unwrap()]);
    assert_eq!(code, Some(0), "{err}");
    let rows_before = std::fs::read_to_string(whole.join("runs.jsonl")).unwrap();
    let o = pto()
        .args(["sweep", "merge", shard.to_str().unwrap(), "--out"])
        .arg(&whole)
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    println!("{e}");
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("rows of its own"), "{e}");
    assert_eq!(
        std::fs::read_to_string(whole.join("runs.jsonl")).unwrap(),
        rows_before
    );
    // Given among the inputs, it is merged (its rows kept).
    let o = pto()
        .args(["sweep", "merge"])
        .args([&shard, &whole])
        .arg("--out")
        .arg(&whole)
        .output()
        .unwrap();
    assert_eq!(
        o.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // A sweep writing there holds its lock: a merge is refused.
    let lock = std::fs::File::create(whole.join(".lock")).unwrap();
    let _held = nix::fcntl::Flock::lock(lock, nix::fcntl::FlockArg::LockExclusiveNonblock).unwrap();
    let o = pto()
        .args(["sweep", "merge", whole.to_str().unwrap(), "--out"])
        .arg(&whole)
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("another pto sweep is writing"), "{e}");
}
