//! The firmware on its QEMU twin, end to end: boot, the bench file's build, configuration upload, cost, processor-in-the-loop, bit-exact replay, the bench workflow, a planned campaign, Ctrl-C.

#[macro_use]
#[path = "../common/mod.rs"]
mod common;
mod bench_workflow;
mod campaign_twin;
mod firmware_bench_config;
mod firmware_boot;
mod firmware_config_upload;
mod firmware_cost;
mod firmware_pil;
mod firmware_replay;
mod interrupt;
