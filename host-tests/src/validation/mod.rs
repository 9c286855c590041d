//! The fixed-point model (`pto-model`) against the full simulation: the one conversion of a
//! bench into the model's configuration, the model's inputs from a run, the sensor model, the
//! f64 mirror of the estimator, and the tools built on them (`pto validate`, the golden vectors,
//! `pto model-cost`).
//!
//! The one conversion from a bench to the controller's model, then the model's coefficients:
//!
//! ```
//! use pto_host::validation::model_config;
//! use pto_host::sim::bench::Bench;
//!
//! let mut file = Bench::reference().file;
//! file.set_field("hp_accumulator.precharge_bar", "45")?;
//! let bench = Bench::from_file(file, "my bench")?;
//! let cfg = model_config(&bench)?;
//! assert_eq!(cfg.hp_accumulator.precharge_bar, 45.0);
//! let k = cfg.coefficients()?;
//! assert_eq!(k.dt_log2, 10);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod closed_loop;
pub mod cost;
pub mod faults;
pub mod golden;
pub mod reference;
pub mod sensors;
pub mod target;
pub mod validate;

use crate::sim::scenario::{Scenario, ValveSpec};
use crate::sim::solver::SimResult;
use pto_model::estimator::Inputs;
use pto_model::fx::{Aperture, Pressure, Rpm};

/// The one conversion of a bench into the model's configuration (in the bench crate, so the
/// firmware's build script uses the same code).
pub use pto_bench::model::{ModelError, controller_config, model_config};

/// The aperture the scenario commands at time t (the trace holds the spool's lagged aperture).
pub fn commanded_aperture_pct(s: &Scenario, res: &SimResult, t: f64) -> f64 {
    match &s.valve {
        ValveSpec::Constant { aperture_pct } => *aperture_pct,
        ValveSpec::Threshold { aperture_pct, .. } => match res.valve_opened_at {
            Some(t0) if t >= t0 => *aperture_pct,
            _ if res.trace.aperture_pct[0] > 0.0 => *aperture_pct,
            _ => 0.0,
        },
        ValveSpec::Table {
            time_s,
            aperture_pct,
        } => time_s
            .iter()
            .zip(aperture_pct)
            .take_while(|(ts, _)| **ts <= t)
            .last()
            .map_or(0.0, |(_, a)| *a),
    }
}

/// One step's inputs, in the model's types: the sensor readings (`None`: that sensor missing),
/// the commanded aperture (%), the cylinders on duty (bit i = HC3.(i+1)) and the geometry
/// (0..=3 = Config 1..4).
pub fn inputs(
    encoder_count: Option<i32>,
    hp_bar: Option<f64>,
    lp_bar: Option<f64>,
    motor_rpm: Option<f64>,
    aperture_pct: f64,
    on_duty: u8,
    config: u8,
) -> Inputs {
    Inputs {
        encoder: encoder_count,
        hp: hp_bar.map(|v| Pressure::from_num(v as f32)),
        lp: lp_bar.map(|v| Pressure::from_num(v as f32)),
        motor: motor_rpm.map(|v| Rpm::from_num(v as f32)),
        aperture_cmd: Aperture::from_num(aperture_pct as f32),
        on_duty,
        config,
    }
}

/// The duty mask of a boolean array.
pub fn duty_mask(on: &[bool; 4]) -> u8 {
    on.iter()
        .enumerate()
        .fold(0, |m, (i, b)| m | (u8::from(*b) << i))
}
