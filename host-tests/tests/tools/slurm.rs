//! `pto sweep` on a real scheduler: a single-node Slurm started for the test (`munged`,
//! `slurmctld` and `slurmd` on localhost, in a folder of their own, no systemd) runs the job-array
//! script of docs/sweep.md as it is written there, in 3 shards; the merge equals a one-machine
//! run of the same matrix row for row; a task cancelled with `scancel` and submitted again
//! completes its shard without making its finished runs again.
//!
//! `scripts/test` installs `slurm-wlm` and `munge` (apt) as it installs QEMU. A machine where
//! Slurm does not start fails this test with the reason and the daemons' logs: it never passes
//! without a scheduler.

use crate::common::{Reaped, pto, without_wall};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Twelve runs of Test III cut to 150 s, the fixed-point controller holding P2 (≈ 1.5 s of one
/// core a run: long enough that a cancel lands between two runs of a shard).
const MATRIX: &str = r#"
scenario = "test3-ap10"
[set]
"scenario.duration_s" = 150.0
"controller.mode" = "hold-pressure"
[[axis]]
field = "bench.hp_accumulator.volume_l"
values = [5.0, 10.0]
[[axis]]
field = "controller.setpoint"
values = [70, 80, 90, 100, 110, 120]
"#;
const RUNS: usize = 12;
const SHARDS: usize = 3;

/// A single-node Slurm: its folder, its configuration, its daemons (killed and reaped when it is
/// dropped, after the jobs it was given are cancelled).
struct Cluster {
    dir: PathBuf,
    /// The folders jobs were submitted from (their `slurm-*.out`).
    submitted_from: Vec<PathBuf>,
    conf: PathBuf,
    daemons: Vec<(&'static str, Reaped)>,
    jobs: Vec<String>,
}

/// Two different ports the system has free now (both held until both are chosen).
fn free_ports() -> (u16, u16) {
    let bind = || std::net::TcpListener::bind("127.0.0.1:0").expect("a free local port");
    let (a, b) = (bind(), bind());
    let port = |l: &std::net::TcpListener| l.local_addr().expect("its address").port();
    (port(&a), port(&b))
}

/// `name` on the PATH or in the system's sbin folders (the daemons are in `/usr/sbin`, often not
/// on a user's PATH).
fn find_bin(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .chain(["/usr/local/sbin", "/usr/sbin", "/sbin"].map(PathBuf::from))
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

fn user() -> String {
    let out = Command::new("id").arg("-un").output().expect("id runs");
    String::from_utf8_lossy(&out.stdout).trim().to_owned()
}

impl Cluster {
    /// Starts munged, slurmctld and slurmd in `dir` and waits until the node is idle; the error
    /// says why Slurm did not start.
    fn start(dir: &Path) -> Result<Cluster, String> {
        let bin = |name: &str| {
            find_bin(name).ok_or_else(|| {
                format!(
                    "`{name}` is not installed (scripts/test installs slurm-wlm and munge with apt)"
                )
            })
        };
        let (munged, mungekey) = (bin("munged")?, bin("mungekey")?);
        let (slurmctld, slurmd) = (bin("slurmctld")?, bin("slurmd")?);
        for client in ["sbatch", "squeue", "scancel", "scontrol", "sinfo"] {
            bin(client)?;
        }
        let run = dir.join("run");
        for d in ["run", "state", "spool", "log"] {
            std::fs::create_dir_all(dir.join(d)).map_err(|e| format!("{}: {e}", dir.display()))?;
        }
        // munged refuses a socket folder that others may write in.
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&run, std::fs::Permissions::from_mode(0o755))
            .map_err(|e| e.to_string())?;
        let key = dir.join("munge.key");
        let status = Command::new(mungekey)
            .args(["--create", "--keyfile"])
            .arg(&key)
            .status()
            .map_err(|e| format!("mungekey: {e}"))?;
        if !status.success() {
            return Err(format!("mungekey: {status}"));
        }
        let socket = run.join("munge.socket");
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map_err(|e| format!("the host name: {e}"))?;
        let host = host
            .trim()
            .split('.')
            .next()
            .unwrap_or("localhost")
            .to_owned();
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        let (user, d) = (user(), dir.display());
        let conf = dir.join("slurm.conf");
        let (ctld_port, slurmd_port) = free_ports();
        let text = format!(
            "ClusterName=ptotest\n\
             SlurmctldHost={host}(127.0.0.1)\n\
             SlurmctldPort={}\nSlurmdPort={}\n\
             SlurmUser={user}\nSlurmdUser={user}\n\
             AuthType=auth/munge\nCredType=cred/munge\nAuthInfo=socket={}\n\
             StateSaveLocation={d}/state\nSlurmdSpoolDir={d}/spool\n\
             SlurmctldPidFile={d}/run/slurmctld.pid\nSlurmdPidFile={d}/run/slurmd.pid\n\
             SlurmctldLogFile={d}/log/slurmctld.log\nSlurmdLogFile={d}/log/slurmd.log\n\
             ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\nMpiDefault=none\n\
             SchedulerType=sched/backfill\nSelectType=select/cons_tres\n\
             SelectTypeParameters=CR_CPU\nReturnToService=2\n\
             JobAcctGatherType=jobacct_gather/none\n\
             AccountingStorageType=accounting_storage/none\n\
             NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} State=UNKNOWN\n\
             PartitionName=pto Nodes=ALL Default=YES MaxTime=INFINITE State=UP\n",
            ctld_port,
            slurmd_port,
            socket.display(),
        );
        std::fs::write(&conf, text).map_err(|e| e.to_string())?;
        let mut cluster = Cluster {
            dir: dir.to_owned(),
            submitted_from: Vec::new(),
            conf,
            daemons: Vec::new(),
            jobs: Vec::new(),
        };
        // One file for a daemon's stdout and stderr (two opens would overwrite each other).
        let log = |name: &str| {
            let f = std::fs::File::create(dir.join("log").join(format!("{name}.out")))
                .map_err(|e| e.to_string())?;
            let g = f.try_clone().map_err(|e| e.to_string())?;
            Ok::<_, String>((Stdio::from(f), Stdio::from(g)))
        };
        let mut munged = Command::new(munged);
        munged
            .args(["--foreground", "--force", "--socket"])
            .arg(&socket)
            .arg("--key-file")
            .arg(&key)
            .arg("--pid-file")
            .arg(run.join("munged.pid"))
            .arg("--seed-file")
            .arg(run.join("munged.seed"))
            .arg("--log-file")
            .arg(dir.join("log/munged.log"));
        let (out, err) = log("munged")?;
        cluster.spawn("munged", munged.stdout(out).stderr(err))?;
        cluster.wait_for("munged's socket", Duration::from_secs(10), || {
            socket.exists()
        })?;
        for (daemon, path) in [("slurmctld", slurmctld), ("slurmd", slurmd)] {
            let mut c = Command::new(path);
            c.arg("-D").arg("-f").arg(&cluster.conf);
            let (out, err) = log(daemon)?;
            cluster.spawn(daemon, c.stdout(out).stderr(err))?;
        }
        let conf = cluster.conf.clone();
        let node_idle = move || {
            Command::new("sinfo")
                .env("SLURM_CONF", &conf)
                .args(["-h", "-o", "%T"])
                .output()
                .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "idle")
        };
        cluster.wait_for("the node to be idle", Duration::from_secs(60), node_idle)?;
        Ok(cluster)
    }

    fn spawn(&mut self, name: &'static str, cmd: &mut Command) -> Result<(), String> {
        let child = cmd
            .stdin(Stdio::null())
            .spawn()
            .map_err(|e| format!("{name}: {e}"))?;
        self.daemons.push((name, Reaped(child)));
        Ok(())
    }

    /// Polls `ready` until it holds; the error names what was awaited, a daemon that exited
    /// and the logs.
    fn wait_for(
        &mut self,
        what: &str,
        limit: Duration,
        ready: impl Fn() -> bool,
    ) -> Result<(), String> {
        let start = Instant::now();
        while !ready() {
            let exited = self
                .daemons
                .iter_mut()
                .find_map(|(name, d)| Some((*name, d.0.try_wait().ok()??)));
            if let Some((name, status)) = exited {
                return Err(format!(
                    "{name} exited ({status}) waiting for {what}\n{}",
                    self.logs()
                ));
            }
            if start.elapsed() > limit {
                return Err(format!("no {what} after {limit:?}\n{}", self.logs()));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        Ok(())
    }

    /// The tail of every daemon log and job output, for a failure's message.
    fn logs(&self) -> String {
        let mut all = String::new();
        // The daemons' folder (every file in it), then each submitting folder's job outputs.
        let folders = std::iter::once((self.dir.join("log"), true))
            .chain(self.submitted_from.iter().map(|d| (d.clone(), false)));
        for (d, daemon_log) in folders {
            let Ok(entries) = std::fs::read_dir(&d) else {
                continue;
            };
            for e in entries.flatten() {
                let p = e.path();
                let name = p
                    .file_name()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .into_owned();
                if p.is_file() && (daemon_log || name.starts_with("slurm-")) {
                    let text = std::fs::read_to_string(&p).unwrap_or_default();
                    let tail: Vec<&str> = text.lines().rev().take(15).collect();
                    all += &format!("--- {name}\n");
                    for l in tail.into_iter().rev() {
                        all += l;
                        all.push('\n');
                    }
                }
            }
        }
        all
    }

    /// A Slurm command against this cluster.
    fn cmd(&self, program: &str) -> Command {
        let mut c = Command::new(program);
        c.env("SLURM_CONF", &self.conf);
        c
    }

    /// `sbatch --parsable ARGS` in `cwd` with `pto` on the PATH; the array job's id.
    fn submit(&mut self, cwd: &Path, args: &[&str]) -> String {
        let bin = Path::new(env!("CARGO_BIN_EXE_pto")).parent().unwrap();
        let path = std::env::join_paths(std::iter::once(bin.to_owned()).chain(
            std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default()),
        ))
        .unwrap();
        let out = self
            .cmd("sbatch")
            .arg("--parsable")
            .args(args)
            .current_dir(cwd)
            .env("PATH", path)
            .output()
            .expect("sbatch runs");
        assert!(
            out.status.success(),
            "sbatch {args:?}: {}\n{}",
            String::from_utf8_lossy(&out.stderr),
            self.logs()
        );
        let id = String::from_utf8_lossy(&out.stdout).trim().to_owned();
        self.jobs.push(id.clone());
        if !self.submitted_from.iter().any(|d| d == cwd) {
            self.submitted_from.push(cwd.to_owned());
        }
        id
    }

    /// Whether `job` (an array, or one of its tasks `J_K`) still has a task queued or running
    /// (a `squeue` that fails, as under load, counts as yes: it is asked again).
    fn pending(&self, job: &str) -> bool {
        let out = self
            .cmd("squeue")
            .args(["-h", "-j", job])
            .output()
            .expect("squeue");
        !out.status.success() || !String::from_utf8_lossy(&out.stdout).trim().is_empty()
    }

    /// Waits until `job` has no task queued or running.
    fn wait(&self, job: &str, limit: Duration) {
        let start = Instant::now();
        while self.pending(job) {
            assert!(
                start.elapsed() < limit,
                "job {job} not done after {limit:?}\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// Each task of the array job `job`: (task id, state, exit code).
    fn tasks(&self, job: &str) -> Vec<(usize, String, String)> {
        let out = self
            .cmd("scontrol")
            .args(["-o", "show", "job", job])
            .output()
            .expect("scontrol");
        let field = |line: &str, key: &str| {
            line.split_whitespace()
                .find_map(|w| w.strip_prefix(key))
                .unwrap_or("")
                .to_owned()
        };
        let mut tasks: Vec<_> = String::from_utf8_lossy(&out.stdout)
            .lines()
            .map(|l| {
                (
                    field(l, "ArrayTaskId=").parse().unwrap_or(0),
                    field(l, "JobState="),
                    field(l, "ExitCode="),
                )
            })
            .collect();
        tasks.sort();
        tasks
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        if !self.jobs.is_empty() {
            let _ = self.cmd("scancel").args(&self.jobs).status();
            let start = Instant::now();
            while self.jobs.iter().any(|j| self.pending(j)) && start.elapsed().as_secs() < 40 {
                std::thread::sleep(Duration::from_millis(200));
            }
        }
        // slurmd before slurmctld before munged.
        while let Some((_, d)) = self.daemons.pop() {
            drop(d);
        }
    }
}

/// The job-array script of docs/sweep.md: its code block that starts `#!/bin/bash`.
fn docs_job_script() -> String {
    let doc = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/sweep.md"))
        .expect("docs/sweep.md");
    let start = doc
        .find("```sh\n#!/bin/bash\n")
        .expect("docs/sweep.md shows a job script")
        + 6;
    let len = doc[start..].find("```").expect("the script's block ends");
    doc[start..start + len].to_owned()
}

fn lines(path: &Path) -> Vec<String> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .map(str::to_owned)
        .collect()
}

#[test]
fn the_docs_job_array_on_slurm_merges_to_the_one_machine_table_and_a_cancelled_task_resumes() {
    let dir = tmp!("slurm");
    let mut cluster = Cluster::start(&dir.join("slurm"))
        .unwrap_or_else(|why| panic!("Slurm did not start on this machine: {why}"));
    let work = dir.join("work");
    std::fs::create_dir_all(&work).unwrap();
    std::fs::write(work.join("m.toml"), MATRIX).unwrap();
    std::fs::write(work.join("sweep.sbatch"), docs_job_script()).unwrap();

    // The array as docs/sweep.md submits it, on one CPU a task (the script asks for 4; the
    // command line's option overrides the script's, as in any sbatch).
    let n = SHARDS.to_string();
    let array = format!("--array=1-{SHARDS}");
    let job = cluster.submit(
        &work,
        &[&array, "--cpus-per-task=1", "sweep.sbatch", "m.toml", &n],
    );
    // Task 2 is cancelled once it has a finished run, while it makes its next.
    let rows2 = work.join("shards/2/runs.jsonl");
    let start = Instant::now();
    while lines(&rows2).is_empty() {
        assert!(
            start.elapsed() < Duration::from_secs(300) && cluster.pending(&job),
            "task 2 made no run\n{}",
            cluster.logs()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let status = cluster
        .cmd("scancel")
        .arg(format!("{job}_2"))
        .status()
        .unwrap();
    assert!(status.success(), "scancel {job}_2: {status}");
    cluster.wait(&job, Duration::from_secs(600));
    let tasks = cluster.tasks(&job);
    let states: Vec<(usize, &str)> = tasks.iter().map(|(k, s, _)| (*k, s.as_str())).collect();
    assert_eq!(
        states,
        [(1, "COMPLETED"), (2, "CANCELLED"), (3, "COMPLETED")],
        "{tasks:?}\n{}",
        cluster.logs()
    );
    let share = RUNS / SHARDS;
    let before = lines(&rows2);
    println!(
        "the cancelled task kept {} of its {share} runs",
        before.len()
    );
    // The run under way when the cancel came finished and kept its row (pto's SIGTERM path): 2
    // rows, or 3 had the cancel come late. (This node tracks a job's processes by their tree,
    // proctrack/linuxproc, and signals pto with or without the script's `exec`; on a
    // proctrack/cgroup node the `exec` is what keeps the shell's death from ending the step.)
    assert!(
        (2..share).contains(&before.len()),
        "task 2 kept {} rows of {share}: 1 is the run under way killed, {share} a cancel too late",
        before.len()
    );
    for l in &before {
        serde_json::from_str::<serde_json::Value>(l).expect("a whole row");
    }

    // The cancelled task submitted again, as docs/sweep.md says.
    let again = cluster.submit(
        &work,
        &[
            "--array=2",
            "--cpus-per-task=1",
            "sweep.sbatch",
            "m.toml",
            &n,
        ],
    );
    cluster.wait(&again, Duration::from_secs(600));
    let tasks = cluster.tasks(&again);
    assert!(
        matches!(tasks.as_slice(), [(2, s, e)] if s == "COMPLETED" && e == "0:0"),
        "{tasks:?}\n{}",
        cluster.logs()
    );
    let after = lines(&rows2);
    assert_eq!(after.len(), share, "{after:?}");
    assert_eq!(
        after[..before.len()],
        before[..],
        "the finished runs' rows are kept as they were"
    );
    let out = std::fs::read_to_string(work.join(format!("slurm-{again}_2.out"))).unwrap();
    assert!(
        out.contains(&format!(
            "{} finished before, {} run now",
            before.len(),
            share - before.len()
        )),
        "{out}"
    );

    let merged = work.join("sweep");
    let shards: Vec<PathBuf> = (1..=SHARDS)
        .map(|k| work.join(format!("shards/{k}")))
        .collect();
    let m = pto()
        .args(["sweep", "merge"])
        .args(&shards)
        .arg("--out")
        .arg(&merged)
        .arg("--no-plots")
        .output()
        .unwrap();
    assert!(m.status.success(), "{}", String::from_utf8_lossy(&m.stderr));
    drop(cluster);

    let one = work.join("one");
    let o = pto()
        .args(["sweep", "m.toml", "--no-plots", "--out", "one"])
        .current_dir(&work)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let table = |d: &Path| without_wall(&std::fs::read_to_string(d.join("sweep.csv")).unwrap());
    let (merged, one) = (table(&merged), table(&one));
    assert_eq!(merged.len(), RUNS + 1);
    assert_eq!(merged, one, "the merged shards against one machine's run");
    std::fs::remove_dir_all(&dir).unwrap();
}
