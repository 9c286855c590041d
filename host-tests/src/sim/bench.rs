//! The bench parameter file: physical units in the key names, every field range-checked.
//!
//! [`BenchFile`] mirrors the TOML file (`host-tests/data/reference-bench.toml`); [`Bench`] is the
//! validated set in SI units that the simulation uses. Loading never yields a half-checked bench:
//! either every field is inside its range or [`BenchError`] lists every offending field as
//! `file:field: value outside [min, max] (unit)`.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};

/// Atmospheric pressure, Pa (all pressures in the model are gauge).
pub const P_ATM: f64 = 101_325.0;
/// Pa per bar.
pub const BAR: f64 = 1e5;

/// The reference bench shipped with the project (`data/reference-bench.toml`).
pub const REFERENCE_BENCH_TOML: &str = include_str!("../../data/reference-bench.toml");
/// Name under which the embedded reference bench reports errors.
pub const REFERENCE_BENCH_NAME: &str = "host-tests/data/reference-bench.toml";

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

/// One field outside its allowed range (or otherwise inconsistent).
#[derive(Debug, Clone, PartialEq)]
pub struct FieldError {
    /// Dotted path of the field, e.g. `cylinder[2].bore_mm`.
    pub field: String,
    /// What is wrong, e.g. `0 outside [1, 500] (mm)`.
    pub message: String,
}

/// Why a bench file could not be loaded.
#[derive(Debug, Clone, PartialEq)]
pub enum BenchError {
    /// The file could not be read.
    Io {
        /// The file.
        file: String,
        /// The OS error.
        message: String,
    },
    /// Not valid TOML, an unknown key, a missing key or a wrong type.
    Parse {
        /// The file.
        file: String,
        /// The parser's message (it names the line and key).
        message: String,
    },
    /// Fields outside their ranges; all of them are listed.
    Invalid {
        /// The file.
        file: String,
        /// Every offending field.
        errors: Vec<FieldError>,
    },
}

impl fmt::Display for BenchError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BenchError::Io { file, message } => write!(f, "{file}: cannot read: {message}"),
            BenchError::Parse { file, message } => write!(f, "{file}: {}", message.trim_end()),
            BenchError::Invalid { file, errors } => {
                for (i, e) in errors.iter().enumerate() {
                    if i > 0 {
                        writeln!(f)?;
                    }
                    write!(f, "{file}:{}: {}", e.field, e.message)?;
                }
                Ok(())
            }
        }
    }
}

impl std::error::Error for BenchError {}

/// Collects range errors with their field paths.
struct Checker {
    errors: Vec<FieldError>,
}

impl Checker {
    fn range(&mut self, field: impl Into<String>, value: f64, min: f64, max: f64, unit: &str) {
        if !(value.is_finite() && value >= min && value <= max) {
            self.errors.push(FieldError {
                field: field.into(),
                message: format!("{value} outside [{min}, {max}] ({unit})"),
            });
        }
    }

    fn fail(&mut self, field: impl Into<String>, message: impl Into<String>) {
        self.errors.push(FieldError {
            field: field.into(),
            message: message.into(),
        });
    }

    fn valve(&mut self, prefix: &str, v: &ValveSection) {
        self.range(
            format!("{prefix}.cracking_bar"),
            v.cracking_bar,
            0.01,
            20.0,
            "bar",
        );
        self.range(
            format!("{prefix}.full_open_bar"),
            v.full_open_bar,
            0.02,
            50.0,
            "bar",
        );
        if v.full_open_bar <= v.cracking_bar {
            self.fail(
                format!("{prefix}.full_open_bar"),
                format!(
                    "{} must exceed cracking_bar = {} (bar)",
                    v.full_open_bar, v.cracking_bar
                ),
            );
        }
        self.range(
            format!("{prefix}.max_area_mm2"),
            v.max_area_mm2,
            0.01,
            2000.0,
            "mm²",
        );
        self.range(
            format!("{prefix}.discharge_coefficient"),
            v.discharge_coefficient,
            0.01,
            1.0,
            "-",
        );
    }

    fn accumulator(&mut self, prefix: &str, a: &AccumulatorSection) {
        self.range(format!("{prefix}.volume_l"), a.volume_l, 0.1, 500.0, "L");
        self.range(
            format!("{prefix}.precharge_bar"),
            a.precharge_bar,
            0.5,
            400.0,
            "bar",
        );
        self.range(
            format!("{prefix}.polytropic_index"),
            a.polytropic_index,
            1.0,
            1.67,
            "-",
        );
    }

    fn line(&mut self, prefix: &str, length_m: f64, id_mm: f64) {
        self.range(
            format!("lines.{prefix}_length_m"),
            length_m,
            0.0,
            100.0,
            "m",
        );
        self.range(
            format!("lines.{prefix}_inner_diameter_mm"),
            id_mm,
            1.0,
            100.0,
            "mm",
        );
    }
}

impl BenchFile {
    /// Sets the field at a dotted path (`hp_accumulator.precharge_bar`, `cylinder[1].bore_mm`,
    /// `control_valve.area_mm2[3]`) to `value` (TOML: a number, a boolean, a quoted string or
    /// an array), keeping its type. Errors name the path and, for an unknown key, the keys
    /// there. The result is validated when it becomes a [`Bench`].
    pub fn set_field(&mut self, path: &str, value: &str) -> Result<(), String> {
        let mut root = toml::Value::try_from(&*self).map_err(|e| e.to_string())?;
        let mut at = &mut root;
        for part in path.split('.') {
            let (key, index) = match part.split_once('[') {
                Some((k, rest)) => {
                    let i = rest
                        .strip_suffix(']')
                        .and_then(|i| i.parse::<usize>().ok())
                        .ok_or_else(|| format!("{path}: bad index in `{part}`"))?;
                    (k, Some(i))
                }
                None => (part, None),
            };
            let table = at
                .as_table_mut()
                .ok_or_else(|| format!("{path}: `{key}` is inside a value, not a table"))?;
            let known: Vec<String> = table.keys().cloned().collect();
            at = table.get_mut(key).ok_or_else(|| {
                format!(
                    "{path}: unknown field `{key}` (fields here: {})",
                    known.join(", ")
                )
            })?;
            if let Some(i) = index {
                let arr = at
                    .as_array_mut()
                    .ok_or_else(|| format!("{path}: `{key}` is not a list"))?;
                let n = arr.len();
                at = arr
                    .get_mut(i)
                    .ok_or_else(|| format!("{path}: index {i} outside `{key}`'s 0..{n}"))?;
            }
        }
        let parsed: toml::Table = toml::from_str(&format!("v = {value}"))
            .or_else(|_| toml::from_str(&format!("v = {value:?}")))
            .map_err(|e| format!("{path}: `{value}` is not a value: {e}"))?;
        let mut new = parsed["v"].clone();
        new = match (&*at, new) {
            (toml::Value::Float(_), toml::Value::Integer(i)) => toml::Value::Float(i as f64),
            (old, new) if old.type_str() == new.type_str() => new,
            (old, new) => {
                return Err(format!(
                    "{path}: `{value}` is a {}, the field holds a {}",
                    new.type_str(),
                    old.type_str()
                ));
            }
        };
        *at = new;
        *self = root
            .try_into()
            .map_err(|e: toml::de::Error| format!("{path}: {e}"))?;
        Ok(())
    }

    /// Parses TOML text; `file` names the source in error messages.
    pub fn parse(text: &str, file: &str) -> Result<Self, BenchError> {
        toml::from_str(text).map_err(|e| BenchError::Parse {
            file: file.to_string(),
            message: e.to_string(),
        })
    }

    /// Checks every field against its physical range.
    pub fn validate(&self, file: &str) -> Result<(), BenchError> {
        let mut c = Checker { errors: Vec::new() };
        c.range(
            "input.pinion_radius_mm",
            self.input.pinion_radius_mm,
            5.0,
            2000.0,
            "mm",
        );
        let o = &self.oil;
        c.range("oil.density_kg_m3", o.density_kg_m3, 600.0, 1200.0, "kg/m³");
        c.range(
            "oil.kinematic_viscosity_cst",
            o.kinematic_viscosity_cst,
            1.0,
            1000.0,
            "cSt",
        );
        c.range(
            "oil.liquid_bulk_modulus_mpa",
            o.liquid_bulk_modulus_mpa,
            100.0,
            5000.0,
            "MPa",
        );
        c.range(
            "oil.trapped_air_fraction",
            o.trapped_air_fraction,
            0.0,
            0.5,
            "-",
        );
        c.range(
            "oil.air_polytropic_index",
            o.air_polytropic_index,
            1.0,
            1.67,
            "-",
        );
        c.range(
            "oil.critical_reynolds",
            o.critical_reynolds,
            1.0,
            5000.0,
            "-",
        );
        c.range(
            "oil.leakage_area_mm2",
            o.leakage_area_mm2,
            1e-9,
            1e-2,
            "mm²",
        );
        let m = &self.cylinder_mounting;
        c.range(
            "cylinder_mounting.dead_volume_cm3",
            m.dead_volume_cm3,
            0.1,
            5000.0,
            "cm³",
        );
        c.range(
            "cylinder_mounting.hose_length_m",
            m.hose_length_m,
            0.0,
            50.0,
            "m",
        );
        c.range(
            "cylinder_mounting.hose_inner_diameter_mm",
            m.hose_inner_diameter_mm,
            1.0,
            100.0,
            "mm",
        );
        c.range(
            "cylinder_mounting.free_play_mm",
            m.free_play_mm,
            0.0,
            50.0,
            "mm",
        );
        c.range(
            "cylinder_mounting.hard_stop_stiffness_n_per_m",
            m.hard_stop_stiffness_n_per_m,
            1e5,
            1e11,
            "N/m",
        );
        c.range(
            "cylinder_mounting.hard_stop_damping_n_s_per_m",
            m.hard_stop_damping_n_s_per_m,
            0.0,
            1e7,
            "N·s/m",
        );
        c.range(
            "cylinder_mounting.seal_friction_n_s_per_m",
            m.seal_friction_n_s_per_m,
            10.0,
            1e6,
            "N·s/m",
        );
        if self.cylinder.len() != 4 {
            c.fail(
                "cylinder",
                format!(
                    "{} entries, the bench has exactly 4 (HC3.1..HC3.4)",
                    self.cylinder.len()
                ),
            );
        }
        for (i, cyl) in self.cylinder.iter().enumerate() {
            let p = format!("cylinder[{i}]");
            c.range(format!("{p}.bore_mm"), cyl.bore_mm, 5.0, 500.0, "mm");
            c.range(format!("{p}.rod_mm"), cyl.rod_mm, 2.0, 400.0, "mm");
            if cyl.rod_mm >= cyl.bore_mm {
                c.fail(
                    format!("{p}.rod_mm"),
                    format!(
                        "{} must be smaller than bore_mm = {} (mm)",
                        cyl.rod_mm, cyl.bore_mm
                    ),
                );
            }
            c.range(format!("{p}.stroke_mm"), cyl.stroke_mm, 10.0, 5000.0, "mm");
            if cyl.side != 1 && cyl.side != -1 {
                c.fail(
                    format!("{p}.side"),
                    format!("{} outside {{-1, 1}} (-)", cyl.side),
                );
            }
        }
        if self.config.len() != 4 {
            c.fail(
                "config",
                format!(
                    "{} entries, the bench has exactly 4 (Config 1..4)",
                    self.config.len()
                ),
            );
        }
        let min_stroke = self
            .cylinder
            .iter()
            .map(|c| c.stroke_mm)
            .fold(f64::INFINITY, f64::min);
        for (i, g) in self.config.iter().enumerate() {
            let p = format!("config[{i}]");
            c.range(format!("{p}.ob_mm"), g.ob_mm, 10.0, 5000.0, "mm");
            c.range(format!("{p}.ac_mm"), g.ac_mm, 10.0, 10000.0, "mm");
            c.range(format!("{p}.oc_mm"), g.oc_mm, 10.0, 20000.0, "mm");
            // The neutral angle must exist: |OC − OB| < L + S/2 < OC + OB.
            let mid = g.ac_mm + 0.5 * min_stroke;
            if !(mid > (g.oc_mm - g.ob_mm).abs() && mid < g.oc_mm + g.ob_mm) {
                c.fail(
                    format!("{p}.oc_mm"),
                    format!(
                        "{} cannot reach mid-stroke: need |OC − OB| < AC + stroke/2 = {mid} < OC + OB (mm)",
                        g.oc_mm
                    ),
                );
            }
        }
        c.valve("check_valve", &self.check_valve);
        c.valve("makeup_valve", &self.makeup_valve);
        let r = &self.relief_valve;
        c.range("relief_valve.setting_bar", r.setting_bar, 1.0, 400.0, "bar");
        c.range(
            "relief_valve.regulation_range_bar",
            r.regulation_range_bar,
            0.1,
            50.0,
            "bar",
        );
        c.range(
            "relief_valve.max_area_mm2",
            r.max_area_mm2,
            0.01,
            2000.0,
            "mm²",
        );
        c.range(
            "relief_valve.discharge_coefficient",
            r.discharge_coefficient,
            0.01,
            1.0,
            "-",
        );
        let v = &self.control_valve;
        c.range(
            "control_valve.discharge_coefficient",
            v.discharge_coefficient,
            0.01,
            1.0,
            "-",
        );
        c.range(
            "control_valve.cd_slope_per_100bar",
            v.cd_slope_per_100bar,
            -0.5,
            0.5,
            "1/100 bar",
        );
        c.range(
            "control_valve.spool_time_constant_ms",
            v.spool_time_constant_ms,
            0.0,
            5000.0,
            "ms",
        );
        if v.aperture_pct.len() != v.area_mm2.len() || v.aperture_pct.len() < 2 {
            c.fail(
                "control_valve.area_mm2",
                format!(
                    "{} areas for {} apertures: need the same number, at least 2",
                    v.area_mm2.len(),
                    v.aperture_pct.len()
                ),
            );
        }
        for (i, a) in v.aperture_pct.iter().enumerate() {
            c.range(
                format!("control_valve.aperture_pct[{i}]"),
                *a,
                0.0,
                100.0,
                "%",
            );
            if i > 0 && *a <= v.aperture_pct[i - 1] {
                c.fail(
                    format!("control_valve.aperture_pct[{i}]"),
                    format!(
                        "{a} not above the previous {} (%): must increase",
                        v.aperture_pct[i - 1]
                    ),
                );
            }
        }
        if v.aperture_pct.first() != Some(&0.0) || v.aperture_pct.last() != Some(&100.0) {
            c.fail(
                "control_valve.aperture_pct",
                "must start at 0 and end at 100 (%)",
            );
        }
        for (i, a) in v.area_mm2.iter().enumerate() {
            c.range(
                format!("control_valve.area_mm2[{i}]"),
                *a,
                0.0,
                5000.0,
                "mm²",
            );
            if i > 0 && *a < v.area_mm2[i - 1] {
                c.fail(
                    format!("control_valve.area_mm2[{i}]"),
                    format!(
                        "{a} below the previous {} (mm²): must not decrease",
                        v.area_mm2[i - 1]
                    ),
                );
            }
        }
        c.accumulator("hp_accumulator", &self.hp_accumulator);
        c.accumulator("lp_accumulator", &self.lp_accumulator);
        let mo = &self.motor;
        c.range(
            "motor.displacement_cm3_per_rev",
            mo.displacement_cm3_per_rev,
            0.1,
            1000.0,
            "cm³/rev",
        );
        c.range(
            "motor.volumetric_efficiency",
            mo.volumetric_efficiency,
            0.5,
            1.0,
            "-",
        );
        c.range("motor.total_efficiency", mo.total_efficiency, 0.3, 1.0, "-");
        if mo.total_efficiency > mo.volumetric_efficiency {
            c.fail(
                "motor.total_efficiency",
                format!(
                    "{} above volumetric_efficiency = {}: the mechanical efficiency would exceed 1",
                    mo.total_efficiency, mo.volumetric_efficiency
                ),
            );
        }
        c.range(
            "motor.nominal_pressure_bar",
            mo.nominal_pressure_bar,
            1.0,
            500.0,
            "bar",
        );
        c.range(
            "motor.nominal_speed_rpm",
            mo.nominal_speed_rpm,
            10.0,
            10000.0,
            "rpm",
        );
        c.range(
            "motor.inertia_kg_m2",
            mo.inertia_kg_m2,
            1e-5,
            100.0,
            "kg·m²",
        );
        match mo.load {
            LoadSection::Viscous {
                torque_per_speed_nm_per_rpm,
            } => c.range(
                "motor.load.torque_per_speed_nm_per_rpm",
                torque_per_speed_nm_per_rpm,
                0.0,
                10.0,
                "N·m/rpm",
            ),
            LoadSection::Constant { torque_nm } => {
                c.range("motor.load.torque_nm", torque_nm, 0.0, 1000.0, "N·m")
            }
        }
        let l = &self.lines;
        c.line("hp", l.hp_length_m, l.hp_inner_diameter_mm);
        c.line(
            "valve_to_motor",
            l.valve_to_motor_length_m,
            l.valve_to_motor_inner_diameter_mm,
        );
        c.line(
            "motor_to_lp",
            l.motor_to_lp_length_m,
            l.motor_to_lp_inner_diameter_mm,
        );
        c.line(
            "lp_to_manifold",
            l.lp_to_manifold_length_m,
            l.lp_to_manifold_inner_diameter_mm,
        );
        c.range(
            "lines.hp_line_resistance_bar_per_lpm",
            l.hp_line_resistance_bar_per_lpm,
            0.0,
            100.0,
            "bar/(L/min)",
        );
        c.range(
            "lines.lp_line_resistance_bar_per_lpm",
            l.lp_line_resistance_bar_per_lpm,
            0.0,
            100.0,
            "bar/(L/min)",
        );
        if c.errors.is_empty() {
            Ok(())
        } else {
            Err(BenchError::Invalid {
                file: file.to_string(),
                errors: c.errors,
            })
        }
    }
}

/// Oil properties in SI units.
#[derive(Debug, Clone, PartialEq)]
pub struct Oil {
    /// kg/m³.
    pub density: f64,
    /// m²/s.
    pub viscosity: f64,
    /// Liquid bulk modulus, Pa.
    pub liquid_modulus: f64,
    /// Relative trapped air at atmospheric pressure.
    pub air_fraction: f64,
    /// Polytropic index of the trapped air.
    pub air_index: f64,
    /// Critical Reynolds number of the orifices.
    pub re_crit: f64,
    /// Leakage area of closed valves, m².
    pub leak_area: f64,
}

/// One double-acting cylinder in SI units.
#[derive(Debug, Clone, PartialEq)]
pub struct Cylinder {
    /// HC3.x.
    pub name: String,
    /// Piston (cap side) area, m².
    pub area_cap: f64,
    /// Annulus (rod side) area, m².
    pub area_ann: f64,
    /// Stroke, m.
    pub stroke: f64,
    /// Side of the shaft, ±1.
    pub side: f64,
}

/// A lever geometry (Eq. 1) in SI units.
#[derive(Debug, Clone, PartialEq)]
pub struct Geometry {
    /// Config name.
    pub name: String,
    /// OB = R, m.
    pub ob: f64,
    /// AC = L, retracted pin-to-pin length, m.
    pub ac: f64,
    /// OC, m.
    pub oc: f64,
}

/// A check valve (or make-up valve) in SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CheckValve {
    /// Pa.
    pub cracking: f64,
    /// Pa.
    pub full_open: f64,
    /// m².
    pub max_area: f64,
    /// Discharge coefficient.
    pub cd: f64,
}

/// Gas accumulator in SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Accumulator {
    /// Total volume, m³.
    pub volume: f64,
    /// Precharge, Pa gauge.
    pub precharge: f64,
    /// Polytropic index.
    pub index: f64,
}

/// Generator load.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Load {
    /// N·m per rad/s.
    Viscous(f64),
    /// N·m.
    Constant(f64),
}

/// Validated bench in SI units (pressures gauge, Pa).
#[derive(Debug, Clone, PartialEq)]
pub struct Bench {
    /// Where it came from (for messages and reports).
    pub source: String,
    /// The file as parsed (kept so fitted copies can be written back).
    pub file: BenchFile,
    /// Pinion pitch radius, m.
    pub pinion_radius: f64,
    /// Oil.
    pub oil: Oil,
    /// Chamber dead volume + hose volume, m³.
    pub chamber_dead_volume: f64,
    /// Rod-fixation free play, m.
    pub free_play: f64,
    /// Hard-stop stiffness, N/m.
    pub stop_stiffness: f64,
    /// Hard-stop damping, N·s/m.
    pub stop_damping: f64,
    /// Seal viscous friction, N·s/m.
    pub seal_friction: f64,
    /// HC3.1..HC3.4.
    pub cylinders: Vec<Cylinder>,
    /// Config 1..4.
    pub configs: Vec<Geometry>,
    /// Bridge check valves.
    pub check: CheckValve,
    /// Make-up valve LP -> motor inlet.
    pub makeup: CheckValve,
    /// Relief setting, Pa.
    pub relief_setting: f64,
    /// Relief regulation range, Pa.
    pub relief_range: f64,
    /// Relief max area, m².
    pub relief_area: f64,
    /// Relief Cd.
    pub relief_cd: f64,
    /// Control valve Cd (at 50 bar Δp).
    pub valve_cd: f64,
    /// Relative change of the control valve's Cd per 100 bar of Δp around 50 bar.
    pub valve_cd_slope: f64,
    /// Control valve aperture table, fraction 0..1.
    pub valve_aperture: Vec<f64>,
    /// Control valve area table, m².
    pub valve_area: Vec<f64>,
    /// Spool time constant, s (0 = ideal).
    pub spool_tau: f64,
    /// HP accumulator.
    pub hp_acc: Accumulator,
    /// LP accumulator.
    pub lp_acc: Accumulator,
    /// Motor displacement, m³/rad.
    pub motor_disp: f64,
    /// Motor leakage coefficient, m³/(s·Pa).
    pub motor_leak: f64,
    /// Motor mechanical efficiency.
    pub motor_eta_mech: f64,
    /// Motor + generator inertia, kg·m².
    pub motor_inertia: f64,
    /// Generator load.
    pub load: Load,
    /// HP line volume (lumped into the HP node), m³.
    pub hp_line_volume: f64,
    /// Valve -> motor line volume (motor inlet node), m³.
    pub motor_line_volume: f64,
    /// Motor -> LP and LP -> manifold line volume (LP node), m³.
    pub lp_line_volume: f64,
    /// LP -> manifold line volume alone, m³ (split off into the LP manifold node when the LP
    /// line has a resistance).
    pub lp_manifold_line_volume: f64,
    /// HP line resistance, Pa·s/m³ (0 = lumped).
    pub hp_line_resistance: f64,
    /// LP line resistance, Pa·s/m³ (0 = lumped).
    pub lp_line_resistance: f64,
}

fn pipe_volume(length_m: f64, id_mm: f64) -> f64 {
    length_m * std::f64::consts::PI / 4.0 * (id_mm * 1e-3).powi(2)
}

fn disc_area(d_mm: f64) -> f64 {
    std::f64::consts::PI / 4.0 * (d_mm * 1e-3).powi(2)
}

impl Bench {
    /// The reference bench shipped with the project.
    pub fn reference() -> Self {
        // The embedded file is part of the build and checked by the test suite.
        Self::from_toml(REFERENCE_BENCH_TOML, REFERENCE_BENCH_NAME)
            .expect("the embedded reference bench is valid")
    }

    /// Loads and validates a bench file.
    pub fn load(path: &Path) -> Result<Self, BenchError> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| BenchError::Io {
            file: name.clone(),
            message: e.to_string(),
        })?;
        Self::from_toml(&text, &name)
    }

    /// Loads the file at `path`, or the reference bench when `None`.
    pub fn load_or_reference(path: Option<&PathBuf>) -> Result<Self, BenchError> {
        match path {
            Some(p) => Self::load(p),
            None => Ok(Self::reference()),
        }
    }

    /// Parses, validates and converts TOML text.
    pub fn from_toml(text: &str, file: &str) -> Result<Self, BenchError> {
        let raw = BenchFile::parse(text, file)?;
        Self::from_file(raw, file)
    }

    /// Validates and converts a parsed file.
    pub fn from_file(f: BenchFile, source: &str) -> Result<Self, BenchError> {
        f.validate(source)?;
        let oil = Oil {
            density: f.oil.density_kg_m3,
            viscosity: f.oil.kinematic_viscosity_cst * 1e-6,
            liquid_modulus: f.oil.liquid_bulk_modulus_mpa * 1e6,
            air_fraction: f.oil.trapped_air_fraction,
            air_index: f.oil.air_polytropic_index,
            re_crit: f.oil.critical_reynolds,
            leak_area: f.oil.leakage_area_mm2 * 1e-6,
        };
        let m = &f.cylinder_mounting;
        let cylinders = f
            .cylinder
            .iter()
            .map(|c| {
                let cap = disc_area(c.bore_mm);
                Cylinder {
                    name: c.name.clone(),
                    area_cap: cap,
                    area_ann: cap - disc_area(c.rod_mm),
                    stroke: c.stroke_mm * 1e-3,
                    side: f64::from(c.side),
                }
            })
            .collect();
        let configs = f
            .config
            .iter()
            .map(|g| Geometry {
                name: g.name.clone(),
                ob: g.ob_mm * 1e-3,
                ac: g.ac_mm * 1e-3,
                oc: g.oc_mm * 1e-3,
            })
            .collect();
        let valve = |v: &ValveSection| CheckValve {
            cracking: v.cracking_bar * BAR,
            full_open: v.full_open_bar * BAR,
            max_area: v.max_area_mm2 * 1e-6,
            cd: v.discharge_coefficient,
        };
        let acc = |a: &AccumulatorSection| Accumulator {
            volume: a.volume_l * 1e-3,
            precharge: a.precharge_bar * BAR,
            index: a.polytropic_index,
        };
        let mo = &f.motor;
        let motor_disp = mo.displacement_cm3_per_rev * 1e-6 / (2.0 * std::f64::consts::PI);
        let omega_nom = mo.nominal_speed_rpm * std::f64::consts::PI / 30.0;
        let motor_leak = motor_disp * omega_nom * (1.0 - mo.volumetric_efficiency)
            / (mo.nominal_pressure_bar * BAR);
        let load = match mo.load {
            LoadSection::Viscous {
                torque_per_speed_nm_per_rpm,
            } => Load::Viscous(torque_per_speed_nm_per_rpm * 30.0 / std::f64::consts::PI),
            LoadSection::Constant { torque_nm } => Load::Constant(torque_nm),
        };
        let l = &f.lines;
        Ok(Bench {
            source: source.to_string(),
            pinion_radius: f.input.pinion_radius_mm * 1e-3,
            oil,
            chamber_dead_volume: m.dead_volume_cm3 * 1e-6
                + pipe_volume(m.hose_length_m, m.hose_inner_diameter_mm),
            free_play: m.free_play_mm * 1e-3,
            stop_stiffness: m.hard_stop_stiffness_n_per_m,
            stop_damping: m.hard_stop_damping_n_s_per_m,
            seal_friction: m.seal_friction_n_s_per_m,
            cylinders,
            configs,
            check: valve(&f.check_valve),
            makeup: valve(&f.makeup_valve),
            relief_setting: f.relief_valve.setting_bar * BAR,
            relief_range: f.relief_valve.regulation_range_bar * BAR,
            relief_area: f.relief_valve.max_area_mm2 * 1e-6,
            relief_cd: f.relief_valve.discharge_coefficient,
            valve_cd: f.control_valve.discharge_coefficient,
            valve_cd_slope: f.control_valve.cd_slope_per_100bar,
            valve_aperture: f
                .control_valve
                .aperture_pct
                .iter()
                .map(|a| a / 100.0)
                .collect(),
            valve_area: f.control_valve.area_mm2.iter().map(|a| a * 1e-6).collect(),
            spool_tau: f.control_valve.spool_time_constant_ms * 1e-3,
            hp_acc: acc(&f.hp_accumulator),
            lp_acc: acc(&f.lp_accumulator),
            motor_disp,
            motor_leak,
            motor_eta_mech: mo.total_efficiency / mo.volumetric_efficiency,
            motor_inertia: mo.inertia_kg_m2,
            load,
            hp_line_volume: pipe_volume(l.hp_length_m, l.hp_inner_diameter_mm),
            motor_line_volume: pipe_volume(
                l.valve_to_motor_length_m,
                l.valve_to_motor_inner_diameter_mm,
            ),
            lp_line_volume: pipe_volume(l.motor_to_lp_length_m, l.motor_to_lp_inner_diameter_mm)
                + pipe_volume(
                    l.lp_to_manifold_length_m,
                    l.lp_to_manifold_inner_diameter_mm,
                ),
            lp_manifold_line_volume: pipe_volume(
                l.lp_to_manifold_length_m,
                l.lp_to_manifold_inner_diameter_mm,
            ),
            hp_line_resistance: l.hp_line_resistance_bar_per_lpm * BAR * 6e4,
            lp_line_resistance: l.lp_line_resistance_bar_per_lpm * BAR * 6e4,
            file: f,
        })
    }

    /// Index of a cylinder by name (`HC3.1`) or by its number (`1`).
    pub fn cylinder_index(&self, name: &str) -> Option<usize> {
        let n = name.trim();
        self.cylinders
            .iter()
            .position(|c| c.name.eq_ignore_ascii_case(n))
            .or_else(|| {
                n.parse::<usize>()
                    .ok()
                    .filter(|i| (1..=self.cylinders.len()).contains(i))
                    .map(|i| i - 1)
            })
    }

    /// Index of a config by name (`Config 1`) or number (`1`).
    pub fn config_index(&self, name: &str) -> Option<usize> {
        let n = name.trim();
        self.configs
            .iter()
            .position(|c| c.name.eq_ignore_ascii_case(n))
            .or_else(|| {
                n.trim_start_matches(|c: char| !c.is_ascii_digit())
                    .parse::<usize>()
                    .ok()
                    .filter(|i| (1..=self.configs.len()).contains(i))
                    .map(|i| i - 1)
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_bench_loads_and_matches_physics_md() {
        let b = Bench::reference();
        assert_eq!(b.cylinders.len(), 4);
        assert_eq!(b.configs.len(), 4);
        // 32/18 mm cylinder: cap 804.2 mm², annulus 549.8 mm².
        assert!((b.cylinders[0].area_cap * 1e6 - 804.25).abs() < 0.01);
        assert!((b.cylinders[0].area_ann * 1e6 - 549.78).abs() < 0.01);
        // Mechanical efficiency 0.85 / 0.92.
        assert!((b.motor_eta_mech - 0.923_913).abs() < 1e-6);
    }

    #[test]
    fn out_of_range_field_is_named_with_file_range_and_unit() {
        let text = REFERENCE_BENCH_TOML.replace("bore_mm = 32.0", "bore_mm = 0.5");
        let err = Bench::from_toml(&text, "my.toml").unwrap_err().to_string();
        assert!(
            err.contains("my.toml:cylinder[0].bore_mm: 0.5 outside [5, 500] (mm)"),
            "{err}"
        );
    }

    #[test]
    fn unknown_key_is_an_error() {
        let text = REFERENCE_BENCH_TOML.replace("[input]\n", "[input]\nbogus_key = 1.0\n");
        let err = Bench::from_toml(&text, "my.toml").unwrap_err().to_string();
        assert!(err.starts_with("my.toml: "), "{err}");
        assert!(err.contains("bogus_key"), "{err}");
    }

    #[test]
    fn every_bad_field_is_reported() {
        let text = REFERENCE_BENCH_TOML
            .replace("density_kg_m3 = 870.0", "density_kg_m3 = 10.0")
            .replace("precharge_bar = 25.0", "precharge_bar = -3.0");
        match Bench::from_toml(&text, "b.toml") {
            Err(BenchError::Invalid { errors, .. }) => {
                let fields: Vec<_> = errors.iter().map(|e| e.field.as_str()).collect();
                assert_eq!(
                    fields,
                    ["oil.density_kg_m3", "hp_accumulator.precharge_bar"]
                );
            }
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    #[test]
    fn names_and_numbers_resolve() {
        let b = Bench::reference();
        assert_eq!(b.cylinder_index("HC3.4"), Some(3));
        assert_eq!(b.cylinder_index("2"), Some(1));
        assert_eq!(b.cylinder_index("HC9"), None);
        assert_eq!(b.config_index("Config 3"), Some(2));
        assert_eq!(b.config_index("4"), Some(3));
        assert_eq!(b.config_index("c5"), None);
    }
}
