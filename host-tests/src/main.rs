//! `pto`: the command-line tool. The command list and the dispatch here; each command's options
//! (a `clap::Args` struct) and its code beside each other in its family's module under `cli/`
//! (simulation, sweep, model, fit, plan, firmware, link), on the `pto_host` library.

use clap::{Parser, Subcommand};
use std::process::ExitCode;

mod cli;
use cli::firmware::{FwCostArgs, PilArgs, QemuArgs, TwinArgs};
use cli::fit::{FitArgs, SynthLogsArgs};
use cli::link::LinkArgs;
use cli::model::{ModelCostArgs, ValidateArgs};
use cli::plan::PlanArgs;
use cli::sim::{PaperArgs, PerfArgs, ScenariosArgs, SimulateArgs};
use cli::sweep::SweepArgs;

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
    Scenarios(ScenariosArgs),
    /// Run one scenario (built-in name or TOML file): CSV, plots and a summary.
    #[command(
        after_help = "Examples:\n  pto simulate test3-ap10\n  pto simulate my-run.toml --bench my-bench.toml --out runs --json\n  pto simulate torque-cfg1-c14 --set hp_accumulator.volume_l=5\n\nExit status:\n  0 the run finished and its oil and energy balances close within 1e-4\n  1 a balance missed 1e-4\n  2 bad input (file, field, value, range and unit named), or the run failed\n  130 interrupted (nothing left half-written)"
    )]
    Simulate(SimulateArgs),
    /// Run every built-in scenario, check the paper's ten facts, write the figures and a report.
    #[command(
        after_help = "Examples:\n  pto paper\n  pto paper --bench my-bench.toml --out out/my-paper --no-plots --json\n\nExit status:\n  0 every fact holds\n  1 a fact failed (the report says which)\n  2 bad input\n  130 interrupted (the previous output folder left whole)"
    )]
    Paper(PaperArgs),
    /// Run the fixed-point model against the full simulation on every built-in scenario (the
    /// paper's runs and the sea family of irregular seas), and the scheduler in closed loop;
    /// print the figures against the targets.
    #[command(
        after_help = "Examples:\n  pto validate\n  pto validate --filter test1 --no-loop --json\n  pto validate --filter sea- --no-loop\n\nExit status:\n  0 every target met in every scenario (and the closed loop, unless --no-loop)\n  1 a target missed (the row names it)\n  2 bad input"
    )]
    Validate(ValidateArgs),
    /// Per-step cost of the fixed-point model: host ns/step, state and code size for both thumb
    /// targets (builds pto-model for them; needs `rustup target add thumbv6m-none-eabi
    /// thumbv7em-none-eabihf`).
    #[command(
        after_help = "Examples:\n  pto model-cost --json\n\nExit status:\n  0 every budget met, no panic reachable from the step\n  1 a budget missed or a panic reachable\n  2 the build failed"
    )]
    ModelCost(ModelCostArgs),
    /// Make synthetic bench logs of the paper's experimental runs (64.5 / 67.2 / 72 / 101.5 bar
    /// starts; discharges from 102 / 84 / 71 bar) from the full simulation and the sensor model.
    #[command(
        after_help = "Examples:\n  pto synth-logs\n  pto synth-logs --set trapped_air=0.04 --set hp_accumulator.precharge_bar=45 --runs test3-ap10 --rate 50 --out logs\n\nExit status:\n  0 the logs were written\n  2 bad input\n  130 interrupted (the previous logs left whole)"
    )]
    SynthLogs(SynthLogsArgs),
    /// Fit bench parameters to bench logs by least squares over full simulations driven by the
    /// logged motion and valve aperture; writes the fitted bench file, the model-crate
    /// configuration for the firmware, a figure per log and `fit.json` into --out, swapped in
    /// whole.
    #[command(
        after_help = "Examples:\n  pto fit logs/*.csv\n  pto fit logs/*.csv --bench my-bench.toml --params trapped_air,cd --out fits/run1 --json\n\nExit status:\n  0 the fit passed every check (converged, goodness, bounds, emptying, determined, precision, correlation, logs)\n  1 a check failed (named in the output)\n  2 bad input\n  130 interrupted (the previous --out folder left whole)"
    )]
    Fit(FitArgs),
    /// Plan the experiments that determine the fit's parameters: for candidate segments a
    /// bench can run (charges with the lever moving, discharges with it blocked, fixed
    /// apertures), the Fisher information from the fit's own residuals on noise-free logs of
    /// the full simulation at the bench's values; the shortest campaign whose predicted 3σ
    /// meets every precision, written as a campaign file.
    #[command(
        after_help = "Examples:\n  pto plan --params trapped_air,cd,precharge,leakage --out campaign.toml\n  pto plan --bench my-bench.toml --params trapped_air,cd --budget-min 10 --rate 128 --out c.toml\n  pto plan --params trapped_air,cd,precharge --noise-from run1.csv --out c.toml --json\n\nExit status:\n  0 the campaign meets every precision within the budget\n  1 none does (the parameter, what blocks it and what would help are named)\n  2 bad input\n  130 interrupted"
    )]
    Plan(PlanArgs),
    /// Boot the QEMU firmware, ping it, print its decoded defmt log and its counters, stop it.
    /// Needs qemu-system-arm, and the thumbv7em-none-eabihf target unless `--elf` gives the firmware.
    #[command(
        after_help = "Examples:\n  pto qemu\n  pto qemu --follow     # keep it running, its log live; Ctrl-C stops it\n  pto qemu --json\n  pto qemu --elf pto-firmware   # a pto installed away from its source tree\n\nExit status:\n  0 the firmware answered and exited cleanly\n  1 it did not\n  2 QEMU or the build missing\n  130 interrupted (QEMU stopped, its socket removed)"
    )]
    Qemu(QemuArgs),
    /// Processor-in-the-loop: the full simulation as the plant, the QEMU firmware as the
    /// controller in lockstep (hold P2, hold motor speed, overpressure trip, the trip held
    /// through a wire break and a refused reset, a motor reading behind a closed valve).
    #[command(
        after_help = "Examples:\n  pto pil\n  pto pil --bench my-bench.toml --json\n  pto pil --fault hp:stuck=60 --fault motor:gain=1.2 --fault lp:drift=0.5@10\n\nExit status:\n  0 every check met\n  1 a check missed\n  2 bad input, QEMU or the build missing\n  130 interrupted"
    )]
    Pil(PilArgs),
    /// The bench engineer's link to a controller: status, mode, duty, reset, configuration
    /// upload and read-back, live monitor and bench log. Over a serial port (the bench) or the
    /// QEMU twin's pseudo-terminal (`pto twin` prints it).
    #[command(
        after_help = "Examples:\n  pto link --port /dev/ttyUSB0 status\n  pto link --port /dev/ttyUSB0 monitor --log run1.csv --rate 64\n  pto link --port /dev/ttyUSB0 mode fixed 12\n  pto link --port /dev/ttyUSB0 duty --on 1001 --config 1\n  pto link --port /dev/ttyUSB0 reset --p2 60 --lp 8\n  pto link --port /dev/ttyUSB0 config upload fit/my-bench.model.toml --store\n  pto link --port /dev/ttyUSB0 config show --out running.model.toml\n  pto link --port /dev/ttyUSB0 selftest\n\nExit status:\n  0 done (monitor: no frame lost or damaged)\n  1 monitor: frames were lost, damaged or not sent, the controller restarted, or none arrived\n  2 bad input, port missing or busy, no answer, protocol mismatch, or a refusal (its reason named)\n  130 interrupted (monitor: Ctrl-C ends it cleanly, its log kept, and the status is as above)"
    )]
    Link(LinkArgs),
    /// The bench's twin: the full simulation as the plant drives the QEMU firmware over its
    /// hardware port (USART1) while the bench link (USART2) is a pseudo-terminal for
    /// `pto link`. A Test III-like run (HC3.1 + HC3.4, ±40 mm at 0.1 Hz) at a fixed aperture.
    #[command(
        after_help = "Examples:\n  pto twin --duration 120 --start-after 5 &\n  pto link --port /dev/pts/3 monitor --log twin.csv\n  pto twin --set trapped_air=0.09 --p2-start 40 --aperture 4\n  pto twin --set trapped_air=0.09 --campaign day.toml &\n  pto link --port /dev/pts/3 campaign run day.toml --log-dir day --yes\n\nExit status:\n  0 the run finished\n  2 bad input, QEMU or the build missing, the run failed, or (with --campaign) the runner stalled\n  130 interrupted"
    )]
    Twin(TwinArgs),
    /// Firmware cost: instructions per estimator + scheduler step (QEMU, -icount shift=0,
    /// TIM2), flash and static RAM of the bench and QEMU builds.
    #[command(
        after_help = "Examples:\n  pto fw-cost\n  pto fw-cost --json --trace step-costs.csv\n  pto fw-cost --workspace ~/src/pto\n\nExit status:\n  0 every budget met (2 400 instructions a step, 5 M the set-up, 128 KiB flash, 32 KiB RAM)\n  1 a budget missed\n  2 QEMU or the build missing\n  130 interrupted"
    )]
    FwCost(FwCostArgs),
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
    Sweep(SweepArgs),
    /// Wall time, real-time factor and accuracy of Test III and a 1000 s irregular sea: the
    /// stops as events (the default) side by side with the stop spring and with the reference
    /// solver path, each against a tight run of its own stop model. (`pto bench`, its former
    /// name, still runs it for one release.)
    #[command(
        alias = "bench",
        after_help = "Examples:\n  pto perf\n  pto perf --repeats 5 --json\n  pto perf --batch 1000\n\nExit status:\n  0 every target met\n  1 a target missed\n  2 bad input"
    )]
    Perf(PerfArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Ctrl-C or SIGTERM: QEMU children ended, their sockets removed, exit 130.
    if let Err(e) =
        pto_host::output::install_interrupt_handler(pto_host::hil::qemu::end_all_children)
    {
        eprintln!("warning: {}", pto_host::error_chain(&e));
    }
    let result = match &cli.cmd {
        Cmd::Scenarios(a) => cli::sim::scenarios(a),
        Cmd::Simulate(a) => cli::sim::simulate(a),
        Cmd::Paper(a) => cli::sim::paper_cmd(a),
        Cmd::Perf(a) => cli::sim::perf_cmd(a),
        Cmd::Sweep(a) => cli::sweep::sweep(a),
        Cmd::Validate(a) => cli::model::validate_cmd(a),
        Cmd::ModelCost(a) => cli::model::model_cost_cmd(a),
        Cmd::Qemu(a) => cli::firmware::qemu_cmd(a),
        Cmd::SynthLogs(a) => cli::fit::synth_logs_cmd(a),
        Cmd::Plan(a) => cli::plan::plan_cmd(a),
        Cmd::Fit(a) => cli::fit::fit_cmd(a),
        Cmd::Pil(a) => cli::firmware::pil_cmd(a),
        Cmd::FwCost(a) => cli::firmware::fw_cost_cmd(a),
        Cmd::Link(a) => cli::link::link(a),
        Cmd::Twin(a) => cli::firmware::twin_cmd(a),
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
