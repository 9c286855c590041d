//! The fixed-point model: golden vectors, the bench file's conversion, its code cost, and its validation against the full simulation.

#[macro_use]
#[path = "../common/mod.rs"]
mod common;
mod golden_vectors;
mod m0;
mod model_config;
mod model_cost;
mod model_validation;
