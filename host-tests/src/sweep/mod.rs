//! `pto sweep`: a design matrix whose axes are any bench, scenario or controller field, run on
//! all cores into one row per run (CSV and Parquet), resumable and shardable.
//!
//! - [`matrix`]: the matrix file, its expansion into runs and their validation (every run is
//!   built, and every run to be made prepares, before any runs), over its [`axis`] entries;
//! - [`spec`]: a run's full specification and its key;
//! - [`expand`]: a run's place on the axes, for messages;
//! - [`key`]: a run's identity (its key) and shards;
//! - [`run`]: one run and its row of figures;
//! - [`store`]: the output folder (`sweep.json`, `runs.jsonl`), resuming, merging shards;
//! - [`table`]: the rows as typed columns, written as CSV and Parquet and read back;
//! - [`heatmap`]: a figure per metric over two axes;
//! - [`write`](mod@write): the table and the heat maps written into the output folder.
//!
//! This module only re-exports.
//!
//! A matrix file:
//!
//! ```toml
//! scenario = "test3-ap10"                 # a built-in, a scenario file, or an inline table
//! bench = "my-bench.toml"                 # optional: default the reference bench
//!
//! [set]                                   # every run
//! "scenario.duration_s" = 200
//!
//! [[axis]]                                # the first axis varies slowest
//! field = "bench.hp_accumulator.volume_l"
//! values = [2.0, 4.0]
//!
//! [[axis]]                                # fields set together
//! fields = ["scenario.motion.significant_mm", "scenario.motion.peak_period_s"]
//! values = [[30, 8], [50, 10]]
//! ```
//!
//! Fields are dotted paths under `bench.` (any bench-file field, or a fit parameter's short
//! name: `bench.precharge`), `scenario.` (any scenario field: `scenario.valve.aperture_pct`,
//! `scenario.cylinders`, `scenario.config`) or `controller.` (`mode`: `scenario` — the
//! scenario's own valve schedule, the default — or a scheduler mode `fixed`, `hold-pressure`,
//! `hold-speed`, `max-autonomy` with its `setpoint` in %, bar or rpm, driving the valve through
//! the fixed-point controller; `seed`: its sensor noise; `dt_log2`: its step, 2^−dt_log2 s).

pub mod axis;
pub mod expand;
pub mod heatmap;
pub mod key;
pub mod matrix;
pub mod run;
pub mod spec;
pub mod store;
pub mod table;
pub mod write;

pub use axis::{Axis, default_heatmap, heatmap_axes, value_text};
pub use expand::{describe, point_of};
pub use key::{RunKey, Shard, fnv1a};
pub use matrix::{MAX_RUNS, Matrix, MatrixError};
pub use spec::{ControllerSpec, ROW_FORMAT, RunSpec, SCENARIO_MODE};
pub use write::{WriteError, Written, write_tables};
