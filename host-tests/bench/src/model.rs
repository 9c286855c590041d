//! The one conversion of a bench into the controller's configuration: the fixed-point model's
//! ([`pto_model::ModelConfig`]), the scheduler's ([`SchedulerConfig`]) and the firmware's
//! control settings ([`ControlConfig`]), for the host tools and for the firmware's build script.

use crate::{BAR, Bench, LPM, Load, RPM};
use pto_model::ModelConfig;
use pto_model::config::{AccumulatorConfig, ConfigError, CylinderConfig, GeometryConfig};
use pto_model::control::{ControlConfig, LoopSpec};
use pto_model::scheduler::SchedulerConfig;

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
    let acc = |a: &crate::Accumulator, line: f64| AccumulatorConfig {
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
        * LPM
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
        motor_leak_lpm_per_bar: (b.motor_leak_m3_per_s_pa * LPM * BAR) as f32,
        motor_mech_efficiency: b.motor_eta_mech as f32,
        load_nm_per_rpm: load_nm_per_rpm as f32,
        motor_inertia_kg_m2: b.motor_inertia_kg_m2 as f32,
        ..r
    };
    c.validate()?;
    Ok(c)
}

/// The scheduler and control settings of a bench's `[controller]` section (already
/// range-checked when the bench was loaded).
pub fn controller_config(b: &Bench) -> (SchedulerConfig, ControlConfig) {
    let k = &b.file.controller;
    let s = &k.scheduler;
    let sched = SchedulerConfig {
        pressure_kp_pct_per_bar: s.pressure_kp_pct_per_bar as f32,
        pressure_ki_pct_per_bar_s: s.pressure_ki_pct_per_bar_s as f32,
        speed_kp_pct_per_rpm: s.speed_kp_pct_per_rpm as f32,
        speed_ki_pct_per_rpm_s: s.speed_ki_pct_per_rpm_s as f32,
        rate_limit_pct_per_s: s.rate_limit_pct_per_s as f32,
        min_aperture_pct: s.min_aperture_pct as f32,
        max_aperture_pct: s.max_aperture_pct as f32,
        autonomy_margin: s.autonomy_margin as f32,
        overpressure_aperture_pct: s.overpressure_aperture_pct as f32,
        sensor_fault_aperture_pct: s.sensor_fault_aperture_pct as f32,
        sensor_fault_sigma_bar: s.sensor_fault_sigma_bar as f32,
    };
    let spec = |t: &crate::TransducerSection| LoopSpec {
        full_scale_bar: t.full_scale_bar as f32,
        shunt_ohm: t.shunt_ohm as f32,
        vref_v: t.vref_v as f32,
    };
    let control = ControlConfig {
        hp: spec(&k.hp_transducer),
        lp: spec(&k.lp_transducer),
        trip_release_margin_bar: k.trip_release_margin_bar as f32,
        trip_release_hold_ms: k.trip_release_hold_ms as f32,
        valve_slew_pct_per_s: k.valve_slew_pct_per_s as f32,
        boot_sigma_bar: k.boot_sigma_bar as f32,
    };
    (sched, control)
}
