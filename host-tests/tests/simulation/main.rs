//! The full simulation: solver accuracy, the paper's facts, the stops as events.

#[macro_use]
#[path = "../common/mod.rs"]
mod common;
mod accuracy;
mod paper_facts;
mod stops;
