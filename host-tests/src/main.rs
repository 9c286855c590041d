//! `pto`: the command-line tool. Parsing and dispatch here; each family of commands in its own
//! module under `cli/` (simulation, model, firmware, fit), on the `pto_host` library.

use anyhow::Result;
use clap::{Parser, Subcommand};
use pto_host::sim::solver::SolverOptions;
use std::path::PathBuf;
use std::process::ExitCode;

mod cli;
use cli::firmware::{fw_cost_cmd, pil_cmd, qemu_cmd};
use cli::fit::{fit_cmd, synth_logs_cmd};
use cli::model::{model_cost_cmd, validate_cmd};
use cli::sim::{paper_cmd, perf_cmd, scenarios, simulate};

#[derive(Parser)]
#[command(
    name = "pto",
    version,
    about = "Hydraulic PTO test bench: full simulation, the paper's scenarios and facts"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// List the built-in scenarios.
    #[command(
        after_help = "Examples:\n  pto scenarios\n  pto scenarios --json > scenarios.json\n\nExit status:\n  0 always"
    )]
    Scenarios {
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Run one scenario (built-in name or TOML file): CSV, plots and a summary.
    #[command(
        after_help = "Examples:\n  pto simulate test3-ap10\n  pto simulate my-run.toml --bench my-bench.toml --out runs --json\n  pto simulate torque-cfg1-c14 --set hp_accumulator.volume_l=5\n\nExit status:\n  0 the run finished and its oil and energy balances close within 1e-4\n  1 a balance missed 1e-4\n  2 bad input (file, field, value, range and unit named), or the run failed\n  130 interrupted (nothing left half-written)"
    )]
    Simulate {
        /// Built-in scenario name (see `pto scenarios`) or a scenario TOML file.
        scenario: String,
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Output directory.
        #[arg(long, default_value = "out")]
        out: PathBuf,
        /// Machine-readable summary on stdout.
        #[arg(long)]
        json: bool,
        /// Override a bench value: `--set hp_accumulator.volume_l=5 --set cylinder[0].bore_mm=50`
        /// (any field of the bench file by its dotted path; lists count from 0 in file order,
        /// `cylinder[0]` is HC3.1), or a fit parameter's short name (`trapped_air=0.04`,
        /// `cd=0.17`, `precharge=45`).
        #[arg(long = "set", value_name = "FIELD=VALUE")]
        set: Vec<String>,
        /// Solver relative tolerance, 1e-12 to 1e-2.
        #[arg(long, allow_hyphen_values = true, default_value_t = SolverOptions::default().rtol, value_parser = finite_in(1e-12, 1e-2, ""))]
        rtol: f64,
    },
    /// Run every built-in scenario, check the paper's ten facts, write the figures and a report.
    #[command(
        after_help = "Examples:\n  pto paper\n  pto paper --bench my-bench.toml --out out/my-paper --no-plots --json\n\nExit status:\n  0 every fact holds\n  1 a fact failed (the report says which)\n  2 bad input\n  130 interrupted (the previous output folder left whole)"
    )]
    Paper {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Output directory.
        #[arg(long, default_value = "out/paper")]
        out: PathBuf,
        /// Machine-readable output on stdout.
        #[arg(long)]
        json: bool,
        /// Skip the figures.
        #[arg(long)]
        no_plots: bool,
    },
    /// Run the fixed-point model against the full simulation on every built-in scenario (the
    /// paper's runs and the sea family of irregular seas), and the scheduler in closed loop;
    /// print the figures against the targets.
    #[command(
        after_help = "Examples:\n  pto validate\n  pto validate --filter test1 --no-loop --json\n  pto validate --filter sea- --no-loop\n\nExit status:\n  0 every target met in every scenario (and the closed loop, unless --no-loop)\n  1 a target missed (the row names it)\n  2 bad input"
    )]
    Validate {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Only scenarios whose name contains this.
        #[arg(long, default_value = "")]
        filter: String,
        /// Skip the closed-loop runs.
        #[arg(long)]
        no_loop: bool,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Per-step cost of the fixed-point model: host ns/step, state and code size for both thumb
    /// targets (builds pto-model for them; needs `rustup target add thumbv6m-none-eabi
    /// thumbv7em-none-eabihf`).
    #[command(
        after_help = "Examples:\n  pto model-cost --json\n\nExit status:\n  0 every budget met, no panic reachable from the step\n  1 a budget missed or a panic reachable\n  2 the build failed"
    )]
    ModelCost {
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Make synthetic bench logs of the paper's experimental runs (64.5 / 67.2 / 72 / 101.5 bar
    /// starts; discharges from 102 / 84 / 71 bar) from the full simulation and the sensor model.
    #[command(
        after_help = "Examples:\n  pto synth-logs\n  pto synth-logs --set trapped_air=0.04 --set hp_accumulator.precharge_bar=45 --runs test3-ap10 --rate 50 --out logs\n\nExit status:\n  0 the logs were written\n  2 bad input\n  130 interrupted (the previous logs left whole)"
    )]
    SynthLogs {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Override a bench value: any field of the bench file by its dotted path
        /// (`--set hp_accumulator.precharge_bar=45 --set cylinder[0].bore_mm=50`; lists count
        /// from 0, `cylinder[0]` is HC3.1), or a fit parameter's short name (`trapped_air=0.04`,
        /// `cd=0.17`, `precharge=45`).
        #[arg(long = "set", value_name = "NAME=VALUE")]
        set: Vec<String>,
        /// Built-in scenarios to log (default: the seven experimental runs).
        #[arg(long, value_delimiter = ',', conflicts_with = "campaign")]
        runs: Vec<String>,
        /// A campaign file (`pto plan`): one log per segment, at the segment's rate.
        #[arg(long)]
        campaign: Option<PathBuf>,
        /// Sample rate, 0.1 to 1000 Hz.
        #[arg(long, allow_hyphen_values = true, default_value_t = 10.0, value_parser = finite_in(0.1, 1000.0, "Hz"))]
        rate: f64,
        /// Noise seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Output directory.
        #[arg(long, default_value = "out/logs")]
        out: PathBuf,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Fit bench parameters to bench logs by least squares over full simulations driven by the
    /// logged motion and valve aperture; writes the fitted bench file, the model-crate
    /// configuration for the firmware, a figure per log and `fit.json` into --out, swapped in
    /// whole.
    #[command(
        after_help = "Examples:\n  pto fit logs/*.csv\n  pto fit logs/*.csv --bench my-bench.toml --params trapped_air,cd --out fits/run1 --json\n\nExit status:\n  0 the fit passed every check (converged, goodness, bounds, emptying, determined, precision, correlation, logs)\n  1 a check failed (named in the output)\n  2 bad input\n  130 interrupted (the previous --out folder left whole)"
    )]
    Fit {
        /// Bench log CSV files.
        #[arg(required = true)]
        logs: Vec<PathBuf>,
        /// Bench parameter file to start from (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Parameters: trapped_air, cd, cd_slope (pressure-dependent Cd), precharge, hp_volume,
        /// leakage, area_table.
        #[arg(
            long,
            value_delimiter = ',',
            default_value = "trapped_air,cd,precharge"
        )]
        params: Vec<String>,
        /// Residual samples every this many seconds of each log, 0 (every sample) to 60 s
        /// (default: 0.5 s, and every sample of a campaign's log: one with a complete
        /// `.segment.toml` sidecar).
        #[arg(long, allow_hyphen_values = true, value_parser = finite_in(0.0, 60.0, "s"))]
        spacing: Option<f64>,
        /// Iteration limit (Levenberg–Marquardt patience, × parameters + 1 evaluations), 1 to
        /// 10 000.
        #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..=10_000))]
        max_iter: u32,
        /// Simulations the fit may run, 10 to 10 000 000 (its time limit, reproducible: ≈ 60 s
        /// on 2 cores for the seven experimental runs); past it the fit stops and fails.
        #[arg(long, default_value_t = pto_host::fit::DEFAULT_MAX_SIMULATIONS as u64, value_parser = clap::value_parser!(u64).range(10..=10_000_000))]
        max_simulations: u64,
        /// Output folder: fitted bench, model configuration, figures, fit.json (replaced whole;
        /// a folder of other files is refused).
        #[arg(long, default_value = "out/fit")]
        out: PathBuf,
        /// P2 sensor noise σ, bar (default: estimated from the logs).
        #[arg(long, value_parser = finite_in(0.001, 50.0, "bar"))]
        noise_p2: Option<f64>,
        /// Motor speed sensor noise σ, rpm (default: estimated from the logs).
        #[arg(long, value_parser = finite_in(0.01, 500.0, "rpm"))]
        noise_rpm: Option<f64>,
        /// LP sensor noise σ, bar (default: estimated from the logs).
        #[arg(long, value_parser = finite_in(0.001, 50.0, "bar"))]
        noise_lp: Option<f64>,
        /// Largest reduced χ² of the residuals against the noise that passes (raise it knowingly
        /// when the model's own error exceeds the sensors' noise), 1 to 10 000.
        #[arg(long, default_value_t = pto_host::fit::DEFAULT_LIMITS.max_chi2, value_parser = finite_in(1.0, 10_000.0, ""))]
        max_chi2: f64,
        /// Precision a parameter needs, in its unit (repeatable; e.g. `--precision
        /// trapped_air=0.01`): the fit fails its `precision` check when the parameter's 3σ
        /// exceeds it. Defaults: trapped_air 0.005, cd 3 %, precharge 2 bar, leakage 0.01,
        /// hp_volume 5 %, cd_slope 0.05, area-table factors 10 %.
        #[arg(long, value_name = "NAME=VALUE", value_parser = name_value)]
        precision: Vec<(String, f64)>,
        /// Write the fitted bench and model configuration even when a check failed (their first
        /// line then says which); without it they are written only when every check passed.
        #[arg(long)]
        write_anyway: bool,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Plan the experiments that determine the fit's parameters: for candidate segments a
    /// bench can run (charges with the lever moving, discharges with it blocked, fixed
    /// apertures), the Fisher information from the fit's own residuals on noise-free logs of
    /// the full simulation at the bench's values; the shortest campaign whose predicted 3σ
    /// meets every precision, written as a campaign file.
    #[command(
        after_help = "Examples:\n  pto plan --params trapped_air,cd,precharge,leakage --out campaign.toml\n  pto plan --bench my-bench.toml --params trapped_air,cd --budget-min 10 --rate 128 --out c.toml\n  pto plan --params trapped_air,cd,precharge --noise-from run1.csv --out c.toml --json\n\nExit status:\n  0 the campaign meets every precision within the budget\n  1 none does (the parameter, what blocks it and what would help are named)\n  2 bad input\n  130 interrupted"
    )]
    Plan {
        /// Bench parameter file: the current best guess (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Override a bench value (as `pto simulate --set`).
        #[arg(long = "set", value_name = "NAME=VALUE")]
        set: Vec<String>,
        /// Parameters to determine (the fit's names).
        #[arg(
            long,
            value_delimiter = ',',
            default_value = "trapped_air,cd,precharge,leakage"
        )]
        params: Vec<String>,
        /// Precision a parameter needs, in its unit (repeatable; as `pto fit --precision`).
        #[arg(long, value_name = "NAME=VALUE", value_parser = name_value)]
        precision: Vec<(String, f64)>,
        /// Bench time the campaign may take, 1 to 1440 min.
        #[arg(long, default_value_t = 45.0, value_parser = finite_in(1.0, 1440.0, "min"))]
        budget_min: f64,
        /// Log rate of the segments, 1 to 128 Hz (the link's telemetry).
        #[arg(long, default_value_t = 64.0, value_parser = finite_in(1.0, 128.0, "Hz"))]
        rate: f64,
        /// Geometries the candidates use (1 to 4).
        #[arg(long, value_delimiter = ',', default_value = "1", value_parser = clap::value_parser!(u8).range(1..=4))]
        configs: Vec<u8>,
        /// Bench logs to estimate the sensors' noise from (default: the sensor model's, HP 0.5
        /// bar, motor 2 rpm, LP 0.2 bar).
        #[arg(long, value_name = "FILE")]
        noise_from: Vec<PathBuf>,
        /// The campaign file to write.
        #[arg(long)]
        out: PathBuf,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// Boot the QEMU firmware, ping it, print its decoded defmt log and its counters, stop it.
    /// Needs qemu-system-arm and the thumbv7em-none-eabihf target (it builds the firmware).
    #[command(
        after_help = "Examples:\n  pto qemu\n  pto qemu --follow     # keep it running, its log live; Ctrl-C stops it\n  pto qemu --json\n\nExit status:\n  0 the firmware answered and exited cleanly\n  1 it did not\n  2 QEMU or the build missing\n  130 interrupted (QEMU stopped, its socket removed)"
    )]
    Qemu {
        /// Print the log lines as they arrive and keep the firmware running until Ctrl-C (which
        /// stops QEMU and removes its socket; exit status 130).
        #[arg(long)]
        follow: bool,
        /// Machine-readable output (the firmware's Hello, its status and the host's link
        /// counts; the log goes to stderr).
        #[arg(long)]
        json: bool,
    },
    /// Processor-in-the-loop: the full simulation as the plant, the QEMU firmware as the
    /// controller in lockstep (hold P2, hold motor speed, overpressure trip, the trip held
    /// through a wire break and a refused reset, a motor reading behind a closed valve).
    #[command(
        after_help = "Examples:\n  pto pil\n  pto pil --bench my-bench.toml --json\n  pto pil --fault hp:stuck=60 --fault motor:gain=1.2 --fault lp:drift=0.5@10\n\nExit status:\n  0 every check met\n  1 a check missed\n  2 bad input, QEMU or the build missing\n  130 interrupted"
    )]
    Pil {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Instead of the standard checks, inject this sensor fault into the firmware's
        /// readings and check that it is flagged, named and made safe (repeatable):
        /// SENSOR:KIND with SENSOR hp, lp, motor or encoder and KIND stuck (at its reading),
        /// stuck=VALUE (bar, rpm, counts), drift=RATE (per s) or gain=FACTOR; from 20 s, or
        /// from the time after an @ (hp:drift=0.5@10).
        #[arg(long, value_name = "SENSOR:KIND")]
        fault: Vec<pto_host::model::faults::Fault>,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
    /// The bench engineer's link to a controller: status, mode, duty, reset, configuration
    /// upload and read-back, live monitor and bench log. Over a serial port (the bench) or the
    /// QEMU twin's pseudo-terminal (`pto twin` prints it).
    #[command(
        after_help = "Examples:\n  pto link --port /dev/ttyUSB0 status\n  pto link --port /dev/ttyUSB0 monitor --log run1.csv --rate 64\n  pto link --port /dev/ttyUSB0 mode fixed 12\n  pto link --port /dev/ttyUSB0 duty --on 1001 --config 1\n  pto link --port /dev/ttyUSB0 reset --p2 60 --lp 8\n  pto link --port /dev/ttyUSB0 config upload fit/my-bench.model.toml --store\n  pto link --port /dev/ttyUSB0 config show --out running.model.toml\n  pto link --port /dev/ttyUSB0 selftest\n\nExit status:\n  0 done (monitor: no frame lost or damaged)\n  1 monitor: frames were lost, damaged or not sent, the controller restarted, or none arrived\n  2 bad input, port missing or busy, no answer, protocol mismatch, or a refusal (its reason named)\n  130 interrupted (monitor: Ctrl-C ends it cleanly, its log kept, and the status is as above)"
    )]
    Link {
        /// Serial port of the controller (`/dev/ttyUSB0`, `COM3`), the QEMU twin's
        /// pseudo-terminal, or `unix:PATH` for a QEMU USART's socket.
        #[arg(long)]
        port: String,
        /// Baud rate (the firmware's: 230400 8N1).
        #[arg(long, default_value_t = pto_host::hil::link::DEFAULT_BAUD)]
        baud: u32,
        /// Machine-readable output.
        #[arg(long, global = true)]
        json: bool,
        #[command(subcommand)]
        cmd: LinkCmd,
    },
    /// The bench's twin: the full simulation as the plant drives the QEMU firmware over its
    /// hardware port (USART1) while the bench link (USART2) is a pseudo-terminal for
    /// `pto link`. A Test III-like run (HC3.1 + HC3.4, ±40 mm at 0.1 Hz) at a fixed aperture.
    #[command(
        after_help = "Examples:\n  pto twin --duration 120 --start-after 5 &\n  pto link --port /dev/pts/3 monitor --log twin.csv\n  pto twin --set trapped_air=0.09 --p2-start 40 --aperture 4\n  pto twin --set trapped_air=0.09 --campaign day.toml &\n  pto link --port /dev/pts/3 campaign run day.toml --log-dir day --yes\n\nExit status:\n  0 the run finished\n  2 bad input, QEMU or the build missing, the run failed, or (with --campaign) the runner stalled\n  130 interrupted"
    )]
    Twin {
        /// The plant's bench file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Override a value of the plant's bench (as for `pto simulate`).
        #[arg(long = "set", value_name = "FIELD=VALUE")]
        set: Vec<String>,
        /// P2 at the start, bar (default 60; with `--campaign`, its first segment's start).
        #[arg(long, value_parser = finite_in(10.0, 125.0, "bar"))]
        p2_start: Option<f64>,
        /// Valve aperture, % (the firmware's mode `fixed`).
        #[arg(long, default_value_t = 10.0, value_parser = finite_in(0.0, 100.0, "%"))]
        aperture: f64,
        /// Simulated time, s.
        #[arg(long, default_value_t = 60.0, value_parser = finite_in(1.0, 3600.0, "s"))]
        duration: f64,
        /// Wall-clock seconds between printing the bench link and starting the plant (time to
        /// start `pto link … monitor`).
        #[arg(long, default_value_t = 3.0, value_parser = finite_in(0.0, 600.0, "s"))]
        start_after: f64,
        /// Follow a campaign instead (`pto link … campaign run` drives the firmware): the lever
        /// held between segments, each segment's motion and cylinders from when the controller
        /// energises them until it de-energises them. `--aperture` and `--duration` are then
        /// the campaign's.
        #[arg(long)]
        campaign: Option<PathBuf>,
    },
    /// Firmware cost: instructions per estimator + scheduler step (QEMU, -icount shift=0,
    /// TIM2), flash and static RAM of the bench and QEMU builds.
    #[command(
        after_help = "Examples:\n  pto fw-cost\n  pto fw-cost --json --trace step-costs.csv\n\nExit status:\n  0 every budget met (2 400 instructions a step, 5 M the set-up, 128 KiB flash, 32 KiB RAM)\n  1 a budget missed\n  2 QEMU or the build missing\n  130 interrupted"
    )]
    FwCost {
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
        /// Also write the four-cylinder run's cost step by step (CSV: step, instructions,
        /// background units, each cylinder's phase) to this file, to see which steps set the
        /// maximum.
        #[arg(long, value_name = "CSV")]
        trace: Option<PathBuf>,
    },
    /// Run a design matrix: axes over any bench, scenario or controller field, every run
    /// checked first, then run on all cores into one row per run (power, efficiency, P2, time
    /// at the relief, motor speed, balance) in CSV and Parquet, plus heat maps. Resumable
    /// (finished runs are skipped) and shardable (`--shard K/N`; `pto sweep merge` joins the
    /// shards).
    #[command(
        args_conflicts_with_subcommands = true,
        subcommand_negates_reqs = true,
        after_help = "Examples:\n  pto sweep host-tests/data/sweeps/accumulator-aperture.toml\n  pto sweep m.toml --dry-run\n  pto sweep m.toml --shard 3/16 --out shards/3 --jobs 1\n  pto sweep merge shards/* --out sweep\n\nExit status:\n  0 every run finished and its oil and energy balances close within 1e-4\n  1 a run failed (a failure row names why) or missed the balance target\n  2 bad input (the matrix refused before any run: file, axis, run, value, range and unit named)\n  130 interrupted (finished runs keep their rows; run again to go on)"
    )]
    Sweep {
        #[command(subcommand)]
        cmd: Option<SweepCmd>,
        /// The design matrix (TOML): a base scenario, `[set]` fields and `[[axis]]` entries
        /// (docs/sweep.md).
        #[arg(required = true)]
        matrix: Option<PathBuf>,
        /// Bench parameter file (default: the matrix's `bench`, else the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Output folder: sweep.json, runs.jsonl (a row per finished run, kept across
        /// reruns), sweep.csv, sweep.parquet, heatmap-*.png/svg.
        #[arg(long, default_value = "out/sweep")]
        out: PathBuf,
        /// Run only shard K of N: the runs whose number minus one is K − 1 modulo N (for a job
        /// array; `pto sweep merge` joins the shards' folders).
        #[arg(long, value_name = "K/N", value_parser = parse_shard)]
        shard: Option<pto_host::sweep::Shard>,
        /// Worker threads, 1 to 1024 (default: one per core).
        #[arg(long, value_parser = clap::value_parser!(u16).range(1..=1024))]
        jobs: Option<u16>,
        /// The heat maps' axes, two fields: X,Y (default: the matrix's `heatmap`, else its
        /// first two axes of more than one value).
        #[arg(long, value_name = "X,Y", value_delimiter = ',')]
        heatmap: Option<Vec<String>>,
        /// Run failed runs again (they are otherwise finished: their failure rows stay).
        #[arg(long)]
        retry_failed: bool,
        /// Check the matrix and count the runs (and those already finished in --out); run
        /// nothing.
        #[arg(long)]
        dry_run: bool,
        /// Skip the heat maps.
        #[arg(long)]
        no_plots: bool,
        /// Machine-readable summary on stdout.
        #[arg(long)]
        json: bool,
    },
    /// Wall time, real-time factor and accuracy of Test III and a 1000 s irregular sea: the
    /// stops as events (the default) side by side with the stop spring and with the reference
    /// solver path, each against a tight run of its own stop model. (`pto bench`, its former
    /// name, still runs it for one release.)
    #[command(
        alias = "bench",
        after_help = "Examples:\n  pto perf\n  pto perf --repeats 5 --json\n  pto perf --batch 1000\n\nExit status:\n  0 every target met\n  1 a target missed\n  2 bad input"
    )]
    Perf {
        /// Bench parameter file (default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Repeats (the median is reported).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
        /// Also run this many Test III runs on every core and time the batch (target: 1 000
        /// in 40 s).
        #[arg(long, value_name = "RUNS")]
        batch: Option<usize>,
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum SweepCmd {
    /// Join the folders of one sweep's shards into one table: checks they are of one matrix,
    /// names the runs missing and those found twice.
    #[command(
        after_help = "Examples:\n  pto sweep merge shards/* --out sweep\n\nExit status:\n  0 every run of the matrix has a row, none failed and every balance closed within 1e-4\n  1 runs are missing (listed, with the shards not given), failed or missed the balance target\n  2 bad input (a folder not a sweep's, folders of different matrices, an --out sweep folder with rows of its own or in use)"
    )]
    Merge {
        /// The shards' output folders.
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
        /// Output folder (replaced whole; a folder of other files is refused).
        #[arg(long, default_value = "out/sweep")]
        out: PathBuf,
        /// The heat maps' axes, two fields: X,Y (default: as the sweep chose).
        #[arg(long, value_name = "X,Y", value_delimiter = ',')]
        heatmap: Option<Vec<String>>,
        /// Skip the heat maps.
        #[arg(long)]
        no_plots: bool,
        /// Machine-readable summary on stdout.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum LinkCmd {
    /// Firmware version, running configuration, link and health counters.
    Status,
    /// Scheduler mode: `fixed PCT`, `hold-pressure BAR`, `hold-speed RPM`, `max-autonomy RPM`.
    Mode {
        /// fixed, hold-pressure, hold-speed or max-autonomy.
        kind: String,
        /// Aperture %, P2 bar, or motor speed rpm.
        #[arg(allow_negative_numbers = true)]
        value: f64,
    },
    /// Cylinders on duty and geometry.
    Duty {
        /// HC3.1..HC3.4 as four 0/1 characters, e.g. 1001.
        #[arg(long)]
        on: String,
        /// Geometry 1..=4.
        #[arg(long, default_value_t = 1)]
        config: u8,
    },
    /// Restart the estimator from known pressures (refused while the overpressure trip holds).
    Reset {
        /// P2, bar.
        #[arg(long, allow_negative_numbers = true)]
        p2: f64,
        /// LP, bar.
        #[arg(long, allow_negative_numbers = true)]
        lp: f64,
    },
    /// The model configuration: upload (from `pto fit`'s *.model.toml or a bench file), show,
    /// clear the stored one.
    Config {
        #[command(subcommand)]
        cmd: ConfigCmd,
    },
    /// Live view of the estimates, command, faults and counters; `--log` writes the bench log
    /// `pto fit` reads (the sensors as the firmware saw them), the estimates in extra columns.
    Monitor {
        /// Bench log CSV to write (written as FILE.part, renamed when the monitor stops).
        #[arg(long)]
        log: Option<PathBuf>,
        /// Telemetry rate, Hz, up to 1024 (default 64, set at every start: a rate an earlier
        /// monitor set does not stay; the bench firmware goes no faster than 128 and says so).
        #[arg(long)]
        rate: Option<f64>,
        /// Stop after this much firmware time, s (default: at Ctrl-C).
        #[arg(long)]
        duration: Option<f64>,
    },
    /// Release the sensors the controller holds faulted (its residuals named them: the valve
    /// went to its sensor-fault aperture), each only if its reading agrees with the model now.
    ClearFaults,
    /// Guided bring-up of a freshly flashed controller: each input's reading and verdict
    /// (loop currents, ADC reference, clock, brown-out level), the encoder and the motor
    /// pickup while you move them by hand, then each output one at a time from the safe
    /// state (valve to a few % with the dump valve open, the dump valve closed, each
    /// solenoid), read back. A pass/fail checklist; `--json`.
    #[command(
        after_help = "Examples:\n  pto link --port /dev/ttyUSB0 selftest\n  pto link --port /dev/ttyUSB0 selftest --skip motor\n  pto link --port /dev/pts/3 selftest --yes --window 10 --json\n\nThe outputs are stepped only from the firmware's safe state (trip armed, mode fixed 0 %, valve\nclosed); the trip stays armed throughout and ends the self-test if it latches.\n\nExit status:\n  0 every check passed (n/a: what this board cannot show)\n  1 a check failed or was skipped\n  2 bad input, no answer, or a protocol mismatch\n  130 interrupted (the outputs are returned to the controller first)"
    )]
    Selftest {
        /// Unattended: no questions (instructions on stderr; motions must happen within
        /// each window). Needed when stdin is not a terminal.
        #[arg(long)]
        yes: bool,
        /// Seconds for each motion by hand (the lever, the motor's shaft).
        #[arg(long, default_value_t = 20.0)]
        window: f64,
        /// Seconds each output is held for you to see or hear it.
        #[arg(long, default_value_t = 2.0)]
        hold: f64,
        /// The valve's test aperture, % (at most 10).
        #[arg(long, default_value_t = 5.0)]
        valve: f32,
        /// Checks to skip (each is reported as skipped, and the run does not pass).
        #[arg(long, value_enum, value_delimiter = ',')]
        skip: Vec<pto_host::hil::selftest::Skippable>,
    },
    /// A planned campaign (`pto plan`): each segment's cylinders, mode and log, the lever set
    /// by the operator.
    Campaign {
        #[command(subcommand)]
        cmd: CampaignCmd,
    },
}

#[derive(Subcommand)]
enum CampaignCmd {
    /// Runs the campaign's segments in order: the cylinders de-energised and the valve closed
    /// while you change the set-up and stop the lever; the estimator restarted from the
    /// readings; HP let down to the segment's start through the valve (mode hold-pressure; HP
    /// below it is named and the segment skipped); the segment's aperture reached; then the
    /// cylinders energised and the log started together while you start the lever, which must
    /// show the planned motion (amplitude and period within 10 %) within max(4 periods, 20 s).
    /// One bench log per segment (the monitor's, at the segment's rate, its planned length)
    /// with a sidecar saying how it came out: complete, unfinished or mismatch (motion off,
    /// frames lost, a trip, a restart, a sensor held faulted, the start not reached). Running
    /// it again skips the complete segments. `pto fit DIR/*.csv` takes the folder as it is.
    #[command(
        after_help = "Examples:\n  pto plan --params trapped_air,cd,precharge,leakage --out day.toml\n  pto link --port /dev/ttyUSB0 campaign run day.toml --log-dir day\n  pto fit day/*.csv --params trapped_air,cd,precharge,leakage --out day-fit\n\nCtrl-C keeps the finished segments' logs, marks the one under way unfinished and leaves the\ncontroller in its safe state (cylinders de-energised, valve closed); running the command again\nresumes at the first segment not complete. Under the twin: `pto twin --campaign day.toml`.\n\nExit status:\n  0 every segment complete\n  1 a segment marked mismatch or unfinished (named)\n  2 bad input, no answer, or a protocol mismatch\n  130 interrupted"
    )]
    Run {
        /// The campaign file (`pto plan --out`).
        file: PathBuf,
        /// Folder of the segments' logs and sidecars (made if missing).
        #[arg(long)]
        log_dir: PathBuf,
        /// The bench file the campaign was planned for (its geometry gives the lever angles
        /// the encoder must show; default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Unattended: no questions (instructions on stderr, a mismatched segment is not
        /// rerun). Needed when stdin is not a terminal.
        #[arg(long)]
        yes: bool,
        /// Wall-clock seconds to wait, per segment, for HP to come down to the segment's
        /// start (the lever gets max(4 periods, 20 s) of the log to show its motion).
        #[arg(long, default_value_t = 300.0, value_parser = finite_in(1.0, 3600.0, "s"))]
        prepare_wait: f64,
    },
}

#[derive(Subcommand)]
enum ConfigCmd {
    /// Send a configuration; the firmware checks it (every field's range) and, in the declared
    /// safe state (mode `fixed 0`, valve closed, trip armed, a valid HP reading), applies it
    /// (estimator restarted from its last P2, uncertain as at boot) and, with `--store`, keeps
    /// it in flash for the next boot.
    Upload {
        /// `pto fit`'s *.model.toml, or a bench file.
        file: PathBuf,
        /// Also store it for the next boot.
        #[arg(long)]
        store: bool,
    },
    /// Erase the stored configuration: the next boot runs the built-in one (the running one
    /// is unchanged). Needs the declared safe state, as `upload`.
    Clear,
    /// The configuration the controller runs, and where it came from.
    Show {
        /// Write it to this file (TOML) instead of printing it.
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

/// A clap parser for a finite number in [lo, hi] (`unit` for the message): NaN, infinities and
/// values out of range are argument errors (exit 2), never a hang or a solver failure.
fn finite_in(lo: f64, hi: f64, unit: &'static str) -> impl Fn(&str) -> Result<f64, String> + Clone {
    move |v: &str| {
        let x: f64 = v.parse().map_err(|_| format!("{v:?} is not a number"))?;
        if x.is_finite() && (lo..=hi).contains(&x) {
            Ok(x)
        } else {
            Err(format!(
                "{v} outside [{lo:e}, {hi:e}]{}{unit}",
                if unit.is_empty() { "" } else { " " }
            ))
        }
    }
}

/// `K/N` with 1 ≤ K ≤ N.
fn parse_shard(v: &str) -> Result<pto_host::sweep::Shard, String> {
    v.parse()
}

/// `NAME=VALUE` with a finite, positive value.
fn name_value(v: &str) -> Result<(String, f64), String> {
    let (n, x) = v
        .split_once('=')
        .ok_or_else(|| format!("{v:?}: want NAME=VALUE, e.g. trapped_air=0.01"))?;
    let x: f64 = x
        .trim()
        .parse()
        .ok()
        .filter(|x: &f64| x.is_finite() && *x > 0.0)
        .ok_or_else(|| format!("{v:?}: the value must be a positive number"))?;
    Ok((n.trim().to_string(), x))
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Ctrl-C or SIGTERM: QEMU children ended, their sockets removed, exit 130.
    if let Err(e) =
        pto_host::output::install_interrupt_handler(pto_host::hil::qemu::end_all_children)
    {
        eprintln!("warning: {}", pto_host::error_chain(&e));
    }
    let result = match cli.cmd {
        Cmd::Scenarios { json } => scenarios(json),
        Cmd::Simulate {
            scenario,
            bench,
            out,
            json,
            set,
            rtol,
        } => simulate(&scenario, bench.as_ref(), &set, &out, json, rtol),
        Cmd::Paper {
            bench,
            out,
            json,
            no_plots,
        } => paper_cmd(bench.as_ref(), &out, json, !no_plots),
        Cmd::Perf {
            bench,
            repeats,
            batch,
            json,
        } => perf_cmd(bench.as_ref(), repeats, batch, json),
        Cmd::Sweep {
            cmd:
                Some(SweepCmd::Merge {
                    dirs,
                    out,
                    heatmap,
                    no_plots,
                    json,
                }),
            ..
        } => cli::sweep::merge_cmd(&dirs, &out, heatmap.as_deref(), !no_plots, json),
        Cmd::Sweep {
            cmd: None,
            matrix,
            bench,
            out,
            shard,
            jobs,
            heatmap,
            retry_failed,
            dry_run,
            no_plots,
            json,
        } => cli::sweep::sweep_cmd(cli::sweep::SweepOptions {
            matrix: matrix.as_deref().unwrap_or(std::path::Path::new("")),
            bench: bench.as_ref(),
            out: &out,
            shard,
            jobs: jobs.map(usize::from),
            heatmap: heatmap.as_deref(),
            retry_failed,
            dry_run,
            plots: !no_plots,
            json,
        }),
        Cmd::Validate {
            bench,
            filter,
            no_loop,
            json,
        } => validate_cmd(bench.as_ref(), &filter, !no_loop, json),
        Cmd::ModelCost { json } => model_cost_cmd(json),
        Cmd::Qemu { follow, json } => qemu_cmd(follow, json),
        Cmd::SynthLogs {
            bench,
            set,
            runs,
            campaign,
            rate,
            seed,
            out,
            json,
        } => synth_logs_cmd(
            bench.as_ref(),
            &set,
            &runs,
            campaign.as_deref(),
            rate,
            seed,
            &out,
            json,
        ),
        Cmd::Plan {
            bench,
            set,
            params,
            precision,
            budget_min,
            rate,
            configs,
            noise_from,
            out,
            json,
        } => cli::plan::plan_cmd(&cli::plan::PlanArgs {
            bench: bench.as_ref(),
            set: &set,
            params: &params,
            precision: &precision,
            budget_min,
            rate,
            configs: &configs,
            noise_from: &noise_from,
            out: &out,
            json,
        }),
        Cmd::Fit {
            logs,
            bench,
            params,
            spacing,
            max_iter,
            max_simulations,
            out,
            noise_p2,
            noise_rpm,
            noise_lp,
            max_chi2,
            precision,
            write_anyway,
            json,
        } => fit_cmd(
            &logs,
            bench.as_ref(),
            pto_host::fit::FitOptions {
                params,
                spacing_s: spacing.unwrap_or(0.5),
                dense_logs: if spacing.is_some() {
                    pto_host::fit::DenseLogs::None
                } else {
                    pto_host::fit::DenseLogs::Campaign
                },
                max_iter: max_iter as usize,
                max_simulations: max_simulations as usize,
                noise_p2_bar: noise_p2,
                noise_rpm,
                noise_lp_bar: noise_lp,
                limits: pto_host::fit::Limits {
                    max_chi2,
                    ..pto_host::fit::DEFAULT_LIMITS
                },
                precision,
                progress: None,
            },
            &out,
            write_anyway,
            json,
        ),
        Cmd::Pil { bench, fault, json } => pil_cmd(bench.as_ref(), &fault, json),
        Cmd::FwCost { json, trace } => fw_cost_cmd(json, trace.as_deref()),
        Cmd::Link {
            port,
            baud,
            json,
            cmd,
        } => {
            use cli::link::*;
            let t = Target { port: &port, baud };
            match cmd {
                LinkCmd::Status => status_cmd(&t, json),
                LinkCmd::Mode { kind, value } => mode_cmd(&t, &kind, value),
                LinkCmd::Duty { on, config } => duty_cmd(&t, &on, config),
                LinkCmd::Reset { p2, lp } => reset_cmd(&t, p2, lp),
                LinkCmd::Config {
                    cmd: ConfigCmd::Upload { file, store },
                } => config_upload_cmd(&t, &file, store, json),
                LinkCmd::Config {
                    cmd: ConfigCmd::Show { out },
                } => config_show_cmd(&t, out.as_ref(), json),
                LinkCmd::Config {
                    cmd: ConfigCmd::Clear,
                } => config_clear_cmd(&t),
                LinkCmd::Monitor {
                    log,
                    rate,
                    duration,
                } => monitor_cmd(&t, log.as_ref(), rate, duration, json),
                LinkCmd::ClearFaults => clear_faults_cmd(&t, json),
                LinkCmd::Campaign {
                    cmd:
                        CampaignCmd::Run {
                            file,
                            log_dir,
                            bench,
                            yes,
                            prepare_wait,
                        },
                } => cli::link::campaign_run_cmd(
                    &t,
                    &file,
                    &log_dir,
                    bench.as_ref(),
                    yes,
                    prepare_wait,
                    json,
                ),
                LinkCmd::Selftest {
                    yes,
                    window,
                    hold,
                    valve,
                    skip,
                } => selftest_cmd(&t, yes, window, hold, valve, skip, json),
            }
        }
        Cmd::Twin {
            bench,
            set,
            p2_start,
            aperture,
            duration,
            start_after,
            campaign,
        } => cli::firmware::twin_cmd(
            bench.as_ref(),
            &set,
            p2_start,
            aperture,
            duration,
            start_after,
            campaign.as_ref(),
        ),
    };
    match result {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(1),
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}
