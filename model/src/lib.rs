#![doc = include_str!("../README.md")]
#![cfg_attr(not(any(test, feature = "std")), no_std)]
#![forbid(unsafe_code)]

pub mod advisor;
pub mod coeffs;
pub mod config;
pub mod control;
pub mod estimator;
pub mod fx;
#[cfg(feature = "protocol")]
pub mod protocol;
pub mod scheduler;
pub mod table;

pub use coeffs::Coefficients;
pub use config::{ConfigError, ModelConfig};
pub use estimator::{Estimate, Inputs, State};
pub use scheduler::{Command, Mode, SchedulerConfig, SchedulerState};
