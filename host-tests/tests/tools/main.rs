//! The `pto` tool end to end: exit codes and messages, `pto link` against ports that are not a controller, sweeps, the fit and the plan.

#[macro_use]
#[path = "../common/mod.rs"]
mod common;
mod cli;
mod fit_recovery;
mod link_cli;
mod plan;
mod slurm;
mod sweep;
