//! The bench file as written: TOML sections whose key names carry their units, and editing a
//! field by its dotted path, alone or as a `--set NAME=VALUE` override.

use super::{BenchError, OverrideError, SetFieldError};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Raw bench file, field names carry their units.
#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct BenchFile {
    pub input: InputSection,
    pub oil: OilSection,
    pub cylinder_mounting: MountingSection,
    pub cylinder: Vec<CylinderSection>,
    pub config: Vec<ConfigSection>,
    pub check_valve: ValveSection,
    pub makeup_valve: ValveSection,
    pub relief_valve: ReliefSection,
    pub control_valve: ControlValveSection,
    pub hp_accumulator: AccumulatorSection,
    pub lp_accumulator: AccumulatorSection,
    pub motor: MotorSection,
    pub lines: LinesSection,
    /// The controller's settings (scheduler, transducer loops, trip release, slew); a file
    /// without the section gets the firmware's defaults.
    #[serde(default)]
    pub controller: ControllerSection,
    /// How the full simulation solves the bench; a file without the section gets the defaults.
    #[serde(default, skip_serializing_if = "SolverSection::is_default")]
    pub solver: SolverSection,
}

/// How the full simulation solves the bench.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SolverSection {
    /// The rods' free-play stops: `"spring"` (a stiff, damped spring the rod penetrates:
    /// `cylinder_mounting.hard_stop_stiffness_n_per_m`) or `"events"` (a rigid face, its
    /// contact located as a solver event).
    #[serde(default)]
    pub stops: StopsKind,
}

impl SolverSection {
    fn is_default(&self) -> bool {
        *self == SolverSection::default()
    }
}

/// The free-play stops' model, as written in the bench file.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum StopsKind {
    /// A stiff, damped spring.
    Spring,
    /// A rigid face located as an event (the default).
    #[default]
    Events,
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct InputSection {
    pub pinion_radius_mm: f64,
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct OilSection {
    pub density_kg_m3: f64,
    pub kinematic_viscosity_cst: f64,
    pub liquid_bulk_modulus_mpa: f64,
    pub trapped_air_fraction: f64,
    pub air_polytropic_index: f64,
    pub critical_reynolds: f64,
    pub leakage_area_mm2: f64,
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MountingSection {
    pub dead_volume_cm3: f64,
    pub hose_length_m: f64,
    pub hose_inner_diameter_mm: f64,
    pub free_play_mm: f64,
    pub hard_stop_stiffness_n_per_m: f64,
    pub hard_stop_damping_n_s_per_m: f64,
    pub seal_friction_n_s_per_m: f64,
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CylinderSection {
    pub name: String,
    pub bore_mm: f64,
    pub rod_mm: f64,
    pub stroke_mm: f64,
    pub side: i32,
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ConfigSection {
    pub name: String,
    pub ob_mm: f64,
    pub ac_mm: f64,
    pub oc_mm: f64,
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ValveSection {
    pub cracking_bar: f64,
    pub full_open_bar: f64,
    pub max_area_mm2: f64,
    pub discharge_coefficient: f64,
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ReliefSection {
    pub setting_bar: f64,
    pub regulation_range_bar: f64,
    pub max_area_mm2: f64,
    pub discharge_coefficient: f64,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ControlValveSection {
    pub discharge_coefficient: f64,
    /// Pressure-dependent characteristic: Cd(Δp) = Cd·(1 + slope·(Δp − 50 bar)/100 bar).
    /// Optional (0: the paper's constant Cd); `pto fit --params cd_slope` fits it.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub cd_slope_per_100bar: f64,
    pub aperture_pct: Vec<f64>,
    pub area_mm2: Vec<f64>,
    pub spool_time_constant_ms: f64,
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AccumulatorSection {
    pub volume_l: f64,
    pub precharge_bar: f64,
    pub polytropic_index: f64,
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MotorSection {
    pub displacement_cm3_per_rev: f64,
    pub volumetric_efficiency: f64,
    pub total_efficiency: f64,
    pub nominal_pressure_bar: f64,
    pub nominal_speed_rpm: f64,
    pub inertia_kg_m2: f64,
    pub load: LoadSection,
}

/// Generator load on the motor shaft.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum LoadSection {
    /// Torque proportional to speed.
    Viscous {
        /// N·m per rpm.
        torque_per_speed_nm_per_rpm: f64,
    },
    /// Constant torque opposing rotation (smoothed over ±1 rpm around standstill).
    Constant {
        /// N·m.
        torque_nm: f64,
    },
}

#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LinesSection {
    pub hp_length_m: f64,
    pub hp_inner_diameter_mm: f64,
    pub valve_to_motor_length_m: f64,
    pub valve_to_motor_inner_diameter_mm: f64,
    pub motor_to_lp_length_m: f64,
    pub motor_to_lp_inner_diameter_mm: f64,
    pub lp_to_manifold_length_m: f64,
    pub lp_to_manifold_inner_diameter_mm: f64,
    /// Laminar resistance of the HP line between the check-valve manifold and the accumulator
    /// block; 0 (the default) lumps manifold, line and accumulator into one node.
    #[serde(default)]
    pub hp_line_resistance_bar_per_lpm: f64,
    /// Same for the LP line between the LP accumulator and the manifold.
    #[serde(default)]
    pub lp_line_resistance_bar_per_lpm: f64,
}

/// The controller's settings beyond its model: what the firmware's `SchedulerConfig` and
/// `ControlConfig` hold.
#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ControllerSection {
    pub trip_release_margin_bar: f64,
    pub trip_release_hold_ms: f64,
    pub valve_slew_pct_per_s: f64,
    pub boot_sigma_bar: f64,
    pub hp_transducer: TransducerSection,
    pub lp_transducer: TransducerSection,
    pub scheduler: SchedulerSection,
    /// The controller board (its crystal); absent: the reference board's.
    #[serde(default)]
    pub board: BoardSection,
}

/// The controller board's hardware settings the firmware is built with.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct BoardSection {
    /// The crystal on the board's HSE pins, MHz: a whole number of 4–26 (the STM32F405's
    /// range), or 0 for a board without one (the internal 16 MHz RC oscillator, ±1 % at 25 °C,
    /// −8 … +4.5 % over temperature: the link's baud rate and the model's step drift with it).
    pub hse_mhz: u32,
}

impl Default for BoardSection {
    /// The reference board: an 8 MHz crystal.
    fn default() -> Self {
        BoardSection { hse_mhz: 8 }
    }
}

/// A 4–20 mA pressure transducer loop read by the controller's 12-bit ADC.
#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TransducerSection {
    pub full_scale_bar: f64,
    pub shunt_ohm: f64,
    pub vref_v: f64,
}

/// The valve scheduler's gains, limits and safe apertures.
#[allow(missing_docs)]
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SchedulerSection {
    pub pressure_kp_pct_per_bar: f64,
    pub pressure_ki_pct_per_bar_s: f64,
    pub speed_kp_pct_per_rpm: f64,
    pub speed_ki_pct_per_rpm_s: f64,
    pub rate_limit_pct_per_s: f64,
    pub min_aperture_pct: f64,
    pub max_aperture_pct: f64,
    pub autonomy_margin: f64,
    pub overpressure_aperture_pct: f64,
    pub sensor_fault_aperture_pct: f64,
    pub sensor_fault_sigma_bar: f64,
}

impl Default for ControllerSection {
    /// The firmware's defaults (`SchedulerConfig::default()`, `ControlConfig::default()`; a
    /// test keeps them equal).
    fn default() -> Self {
        ControllerSection {
            trip_release_margin_bar: 15.0,
            trip_release_hold_ms: 500.0,
            valve_slew_pct_per_s: 100.0,
            boot_sigma_bar: 50.0,
            hp_transducer: TransducerSection {
                full_scale_bar: 250.0,
                shunt_ohm: 150.0,
                vref_v: 3.3,
            },
            lp_transducer: TransducerSection {
                full_scale_bar: 40.0,
                shunt_ohm: 150.0,
                vref_v: 3.3,
            },
            scheduler: SchedulerSection {
                pressure_kp_pct_per_bar: 1.0,
                pressure_ki_pct_per_bar_s: 0.2,
                speed_kp_pct_per_rpm: 0.02,
                speed_ki_pct_per_rpm_s: 0.02,
                rate_limit_pct_per_s: 20.0,
                min_aperture_pct: 0.0,
                max_aperture_pct: 100.0,
                autonomy_margin: 0.1,
                overpressure_aperture_pct: 100.0,
                sensor_fault_aperture_pct: 12.0,
                sensor_fault_sigma_bar: 3.0,
            },
            board: BoardSection::default(),
        }
    }
}

impl BenchFile {
    /// Sets the field at a dotted path (`hp_accumulator.precharge_bar`, `cylinder[1].bore_mm`,
    /// `control_valve.area_mm2[3]`) to `value` (TOML: a number, a boolean, a quoted string or
    /// an array), keeping its type. Errors name the path and, for an unknown key, the keys
    /// there. The result is validated when it becomes a [`Bench`](super::Bench).
    pub fn set_field(&mut self, path: &str, value: &str) -> Result<(), SetFieldError> {
        let mut root = toml::Value::try_from(&*self)?;
        let parsed: toml::Table = toml::from_str(&format!("v = {value}"))
            .or_else(|_| toml::from_str(&format!("v = {value:?}")))
            .map_err(|error| SetFieldError::NotAValue {
                path: path.into(),
                value: value.into(),
                error: Box::new(error),
            })?;
        set_value(&mut root, path, parsed["v"].clone(), false).map_err(|e| match e {
            // The value as the user wrote it.
            SetFieldError::WrongType {
                path, given, held, ..
            } => SetFieldError::WrongType {
                path,
                value: value.into(),
                given,
                held,
            },
            e => e,
        })?;
        *self = root.try_into().map_err(|error| SetFieldError::Rebuild {
            path: path.into(),
            error: Box::new(error),
        })?;
        Ok(())
    }

    /// Parses TOML text; `file` names the source in error messages.
    pub fn parse(text: &str, file: &str) -> Result<Self, BenchError> {
        toml::from_str(text).map_err(|e| BenchError::Parse {
            file: file.to_string(),
            message: e.to_string(),
        })
    }
}

/// Sets the value at a dotted path (`valve.aperture_pct`, `cylinder[1].bore_mm`) in a TOML
/// tree (a bench file's, a scenario's) to `value`, keeping the type of the value it replaces
/// (an integer becomes a float in a float field). A key missing at the end of the path is an
/// error naming the keys there, or, with `add_missing`, added as given (for optional fields:
/// the type's own deserialisation then judges it). Errors start with the path.
pub fn set_value(
    root: &mut toml::Value,
    path: &str,
    value: toml::Value,
    add_missing: bool,
) -> Result<(), SetFieldError> {
    let parts: Vec<&str> = path.split('.').collect();
    let mut at = root;
    for (n, part) in parts.iter().enumerate() {
        let (key, index) = match part.split_once('[') {
            Some((k, rest)) => {
                let i = rest
                    .strip_suffix(']')
                    .and_then(|i| i.parse::<usize>().ok())
                    .ok_or_else(|| SetFieldError::BadIndex {
                        path: path.into(),
                        part: (*part).into(),
                    })?;
                (k, Some(i))
            }
            None => (*part, None),
        };
        let table = at.as_table_mut().ok_or_else(|| SetFieldError::NotATable {
            path: path.into(),
            key: key.into(),
        })?;
        if add_missing && index.is_none() && n + 1 == parts.len() && !table.contains_key(key) {
            table.insert(key.into(), value);
            return Ok(());
        }
        let known: Vec<String> = table.keys().cloned().collect();
        at = table
            .get_mut(key)
            .ok_or_else(|| SetFieldError::UnknownField {
                path: path.into(),
                key: key.into(),
                known,
            })?;
        if let Some(i) = index {
            let arr = at.as_array_mut().ok_or_else(|| SetFieldError::NotAList {
                path: path.into(),
                key: key.into(),
            })?;
            let len = arr.len();
            at = arr.get_mut(i).ok_or_else(|| SetFieldError::IndexOutside {
                path: path.into(),
                key: key.into(),
                index: i,
                len,
            })?;
        }
    }
    *at = match (&*at, value) {
        (toml::Value::Float(_), toml::Value::Integer(i)) => toml::Value::Float(i as f64),
        (old, new) if old.type_str() == new.type_str() => new,
        (old, new) => {
            return Err(SetFieldError::WrongType {
                path: path.into(),
                value: new.to_string(),
                given: new.type_str(),
                held: old.type_str(),
            });
        }
    };
    Ok(())
}

/// Sets a value of a bench file, as the fit's parameters do.
pub type Setter = Arc<dyn Fn(&mut BenchFile, f64) + Send + Sync>;

/// A short name `--set` takes for a bench field (the fit's parameter names: `trapped_air`,
/// `cd`, `precharge`, …), and how it sets the field.
#[derive(Clone)]
pub struct Shortcut {
    /// The short name.
    pub name: String,
    /// The field it sets, by its dotted path (`--set` takes that too).
    pub field: String,
    /// Sets it.
    pub set: Setter,
}

impl std::fmt::Debug for Shortcut {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({})", self.name, self.field)
    }
}

/// Sets a `name=value` override on a bench file (`pto simulate --set`, `pto synth-logs
/// --set`): any bench field by its dotted path (`hp_accumulator.volume_l`,
/// `cylinder[1].bore_mm`), or, for a numeric value, one of `shortcuts` by its short name
/// (`fit::set_shortcuts()`: `trapped_air`, `cd`, `precharge`, …); a plain name that is neither
/// is a top-level bench field.
pub fn apply_override(
    f: &mut BenchFile,
    kv: &str,
    shortcuts: &[Shortcut],
) -> Result<(), OverrideError> {
    let (k, v) = kv
        .split_once('=')
        .ok_or_else(|| OverrideError::Syntax { kv: kv.into() })?;
    let k = k.trim();
    if k.contains('.') || k.contains('[') {
        return f.set_field(k, v.trim()).map_err(OverrideError::Field);
    }
    let Ok(v) = v.trim().parse::<f64>() else {
        return f.set_field(k, v.trim()).map_err(OverrideError::Field);
    };
    match shortcuts.iter().find(|s| s.name == k || s.field == k) {
        Some(s) => {
            (s.set)(f, v);
            Ok(())
        }
        // Not a short name: a top-level bench field.
        None => f
            .set_field(k, &v.to_string())
            .map_err(|error| OverrideError::FieldOrShortcut {
                error,
                shortcuts: shortcuts.iter().map(|s| s.name.clone()).collect(),
            }),
    }
}
