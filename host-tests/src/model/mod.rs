//! The fixed-point model (`pto-model`) against the full simulation: the one conversion of a
//! bench into the model's configuration, the model's inputs from a run, the sensor model, the
//! f64 mirror of the estimator, and the tools built on them (`pto validate`, the golden vectors,
//! `pto model-cost`).
//!
//! The one conversion from a bench to the controller's model, then the model's coefficients:
//!
//! ```
//! use pto_host::model::model_config;
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
pub mod golden;
pub mod reference;
pub mod sensors;
pub mod validate;

use crate::sim::bench::{BAR, Bench, Load};
use crate::sim::scenario::{Scenario, ValveSpec};
use crate::sim::solver::SimResult;
use pto_model::ModelConfig;
use pto_model::config::{AccumulatorConfig, ConfigError, CylinderConfig, GeometryConfig};
use pto_model::estimator::Inputs;
use pto_model::fx::{Aperture, Pressure, Rpm};

const RPM: f64 = 30.0 / std::f64::consts::PI;

/// Why a bench has no model configuration, or a configuration no coefficients.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ModelError {
    /// The bench's generator load is a constant torque.
    #[error("the reduced model supports the viscous generator load only")]
    ConstantLoad,
    /// The bench's valve table does not have the model's 11 points.
    #[error("the reduced model needs an 11-point valve table")]
    ValveTable {
        /// The bench's number of points.
        points: usize,
    },
    /// A configuration field (or a coefficient made from it) is outside its range.
    #[error(transparent)]
    Config(#[from] ConfigError),
}

/// The model configuration of a bench (the firmware's is `ModelConfig::reference()`, which a test
/// keeps equal to this for the reference bench).
pub fn model_config(b: &Bench) -> Result<ModelConfig, ModelError> {
    let f = &b.file;
    let load_nm_per_rpm = match b.load {
        Load::Viscous(c) => c / RPM,
        Load::Constant(_) => return Err(ModelError::ConstantLoad),
    };
    let cylinders = std::array::from_fn(|i| CylinderConfig {
        bore_mm: f.cylinder[i].bore_mm as f32,
        rod_mm: f.cylinder[i].rod_mm as f32,
        stroke_mm: f.cylinder[i].stroke_mm as f32,
        side: f.cylinder[i].side as i8,
    });
    let geometries = std::array::from_fn(|i| GeometryConfig {
        ob_mm: f.config[i].ob_mm as f32,
        ac_mm: f.config[i].ac_mm as f32,
        oc_mm: f.config[i].oc_mm as f32,
    });
    let acc = |a: &crate::sim::bench::Accumulator, line: f64| AccumulatorConfig {
        volume_l: (a.volume_m3 * 1e3) as f32,
        precharge_bar: (a.precharge_pa / BAR) as f32,
        polytropic_index: a.index as f32,
        line_volume_l: (line * 1e3) as f32,
    };
    let table = |v: &[f64]| -> Result<[f32; 11], ModelError> {
        let a: Vec<f32> = v.iter().map(|x| *x as f32).collect();
        a.try_into()
            .map_err(|a: Vec<f32>| ModelError::ValveTable { points: a.len() })
    };
    // Relief: flow gained per bar above the setting, d/dp of Cd·A(p)·sqrt(2Δp/ρ) at the setting.
    let relief_gain = b.relief_cd * b.relief_area_m2 / b.relief_range_pa
        * (2.0 * (b.relief_setting_pa - 8.0 * BAR) / b.oil.density_kg_m3).sqrt()
        * 6e4
        * BAR;
    let r = ModelConfig::reference();
    let c = ModelConfig {
        cylinders,
        geometries,
        free_play_mm: (b.free_play_m * 1e3) as f32,
        seal_friction_n_s_per_m: b.seal_friction_n_s_per_m as f32,
        chamber_dead_volume_cm3: (b.chamber_dead_volume_m3 * 1e6) as f32,
        oil_liquid_bulk_modulus_mpa: (b.oil.liquid_modulus_pa * 1e-6) as f32,
        oil_density_kg_m3: b.oil.density_kg_m3 as f32,
        trapped_air_fraction: b.oil.trapped_air_fraction as f32,
        air_polytropic_index: b.oil.air_polytropic_index as f32,
        hp_accumulator: acc(&b.hp_acc, b.hp_line_volume_m3),
        lp_accumulator: acc(&b.lp_acc, b.lp_line_volume_m3),
        valve_discharge_coefficient: b.valve_cd as f32,
        valve_aperture_pct: table(&f.control_valve.aperture_pct)?,
        valve_area_mm2: table(&f.control_valve.area_mm2)?,
        spool_time_constant_ms: (b.spool_tau_s * 1e3) as f32,
        relief_setting_bar: (b.relief_setting_pa / BAR) as f32,
        relief_gain_lpm_per_bar: relief_gain as f32,
        motor_displacement_cm3_per_rev: f.motor.displacement_cm3_per_rev as f32,
        motor_leak_lpm_per_bar: (b.motor_leak_m3_per_s_pa * 6e4 * BAR) as f32,
        motor_mech_efficiency: b.motor_eta_mech as f32,
        load_nm_per_rpm: load_nm_per_rpm as f32,
        motor_inertia_kg_m2: b.motor_inertia_kg_m2 as f32,
        ..r
    };
    c.validate()?;
    Ok(c)
}

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
