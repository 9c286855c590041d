//! The bench parameter file: physical units in the key names, every field range-checked.
//!
//! [`BenchFile`] mirrors the TOML file (`host-tests/data/reference-bench.toml`); [`Bench`] is the
//! validated set in SI units that the simulation uses. Loading never yields a half-checked bench:
//! either every field is inside its range or [`BenchError`] lists every offending field as
//! `file:field: value outside [min, max] (unit)`.

use std::path::{Path, PathBuf};

/// Atmospheric pressure, Pa (all pressures in the model are gauge).
pub const P_ATM: f64 = 101_325.0;
/// Pa per bar.
pub const BAR: f64 = 1e5;
/// rpm per rad/s.
pub const RPM: f64 = 30.0 / std::f64::consts::PI;
/// L/min per m³/s.
pub const LPM: f64 = 6e4;

/// The reference bench shipped with the project (`data/reference-bench.toml`).
pub const REFERENCE_BENCH_TOML: &str = include_str!("../../data/reference-bench.toml");
/// Name under which the embedded reference bench reports errors.
pub const REFERENCE_BENCH_NAME: &str = "the built-in reference bench";

mod check;
mod error;
mod file;
#[cfg(feature = "model")]
pub mod model;

pub use error::{BenchError, FieldError, OverrideError, SetFieldError};
pub use file::*;

/// Oil properties in SI units.
#[derive(Debug, Clone, PartialEq)]
pub struct Oil {
    /// kg/m³.
    pub density_kg_m3: f64,
    /// m²/s.
    pub viscosity_m2_s: f64,
    /// Liquid bulk modulus, Pa.
    pub liquid_modulus_pa: f64,
    /// Relative trapped air at atmospheric pressure.
    pub trapped_air_fraction: f64,
    /// Polytropic index of the trapped air.
    pub air_polytropic_index: f64,
    /// Critical Reynolds number of the orifices.
    pub re_crit: f64,
    /// Leakage area of closed valves, m².
    pub leak_area_m2: f64,
}

/// One double-acting cylinder in SI units.
#[derive(Debug, Clone, PartialEq)]
pub struct Cylinder {
    /// HC3.x.
    pub name: String,
    /// Piston (cap side) area, m².
    pub area_cap_m2: f64,
    /// Annulus (rod side) area, m².
    pub area_ann_m2: f64,
    /// Stroke, m.
    pub stroke_m: f64,
    /// Side of the shaft, ±1.
    pub side: f64,
}

/// A lever geometry (Eq. 1) in SI units.
#[derive(Debug, Clone, PartialEq)]
pub struct Geometry {
    /// Config name.
    pub name: String,
    /// OB = R, m.
    pub ob_m: f64,
    /// AC = L, retracted pin-to-pin length, m.
    pub ac_m: f64,
    /// OC, m.
    pub oc_m: f64,
}

/// A check valve (or make-up valve) in SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CheckValve {
    /// Pa.
    pub cracking_pa: f64,
    /// Pa.
    pub full_open_pa: f64,
    /// m².
    pub max_area_m2: f64,
    /// Discharge coefficient.
    pub cd: f64,
}

/// Gas accumulator in SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Accumulator {
    /// Total volume, m³.
    pub volume_m3: f64,
    /// Precharge, Pa gauge.
    pub precharge_pa: f64,
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

/// How the solver treats the ends of the rods' free play (the cylinders' end stops stay
/// springs in both).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Stops {
    /// A stiff, damped spring the rod penetrates (`hard_stop_stiffness_n_per_m`).
    Spring,
    /// A rigid face located as an event: the rod follows the eye while engaged (the default).
    #[default]
    Events,
}

/// Validated bench in SI units (pressures gauge, Pa).
#[derive(Debug, Clone, PartialEq)]
pub struct Bench {
    /// Where it came from (for messages and reports).
    pub source: String,
    /// The file as parsed (kept so fitted copies can be written back).
    pub file: BenchFile,
    /// Pinion pitch radius, m.
    pub pinion_radius_m: f64,
    /// Oil.
    pub oil: Oil,
    /// Chamber dead volume + hose volume, m³.
    pub chamber_dead_volume_m3: f64,
    /// Rod-fixation free play, m.
    pub free_play_m: f64,
    /// Hard-stop stiffness, N/m.
    pub stop_stiffness_n_per_m: f64,
    /// Hard-stop damping, N·s/m.
    pub stop_damping_n_s_per_m: f64,
    /// Seal viscous friction, N·s/m.
    pub seal_friction_n_s_per_m: f64,
    /// The free play's stops in the solver.
    pub stops: Stops,
    /// HC3.1..HC3.4.
    pub cylinders: Vec<Cylinder>,
    /// Config 1..4.
    pub configs: Vec<Geometry>,
    /// Bridge check valves.
    pub check: CheckValve,
    /// Make-up valve LP -> motor inlet.
    pub makeup: CheckValve,
    /// Relief setting, Pa.
    pub relief_setting_pa: f64,
    /// Relief regulation range, Pa.
    pub relief_range_pa: f64,
    /// Relief max area, m².
    pub relief_area_m2: f64,
    /// Relief Cd.
    pub relief_cd: f64,
    /// Control valve Cd (at 50 bar Δp).
    pub valve_cd: f64,
    /// Relative change of the control valve's Cd per 100 bar of Δp around 50 bar.
    pub valve_cd_slope_per_100bar: f64,
    /// Control valve aperture table, %.
    pub valve_aperture_pct: Vec<f64>,
    /// Control valve area table, m².
    pub valve_area_m2: Vec<f64>,
    /// Spool time constant, s (0 = ideal).
    pub spool_tau_s: f64,
    /// HP accumulator.
    pub hp_acc: Accumulator,
    /// LP accumulator.
    pub lp_acc: Accumulator,
    /// Motor displacement, m³/rad.
    pub motor_disp_m3_per_rad: f64,
    /// Motor leakage coefficient, m³/(s·Pa).
    pub motor_leak_m3_per_s_pa: f64,
    /// Motor mechanical efficiency.
    pub motor_eta_mech: f64,
    /// Motor + generator inertia, kg·m².
    pub motor_inertia_kg_m2: f64,
    /// Generator load.
    pub load: Load,
    /// HP line volume (lumped into the HP node), m³.
    pub hp_line_volume_m3: f64,
    /// Valve -> motor line volume (motor inlet node), m³.
    pub motor_line_volume_m3: f64,
    /// Motor -> LP and LP -> manifold line volume (LP node), m³.
    pub lp_line_volume_m3: f64,
    /// LP -> manifold line volume alone, m³ (split off into the LP manifold node when the LP
    /// line has a resistance).
    pub lp_manifold_line_volume_m3: f64,
    /// HP line resistance, Pa·s/m³ (0 = lumped).
    pub hp_line_resistance_pa_s_per_m3: f64,
    /// LP line resistance, Pa·s/m³ (0 = lumped).
    pub lp_line_resistance_pa_s_per_m3: f64,
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
            density_kg_m3: f.oil.density_kg_m3,
            viscosity_m2_s: f.oil.kinematic_viscosity_cst * 1e-6,
            liquid_modulus_pa: f.oil.liquid_bulk_modulus_mpa * 1e6,
            trapped_air_fraction: f.oil.trapped_air_fraction,
            air_polytropic_index: f.oil.air_polytropic_index,
            re_crit: f.oil.critical_reynolds,
            leak_area_m2: f.oil.leakage_area_mm2 * 1e-6,
        };
        let m = &f.cylinder_mounting;
        let cylinders = f
            .cylinder
            .iter()
            .map(|c| {
                let cap = disc_area(c.bore_mm);
                Cylinder {
                    name: c.name.clone(),
                    area_cap_m2: cap,
                    area_ann_m2: cap - disc_area(c.rod_mm),
                    stroke_m: c.stroke_mm * 1e-3,
                    side: f64::from(c.side),
                }
            })
            .collect();
        let configs = f
            .config
            .iter()
            .map(|g| Geometry {
                name: g.name.clone(),
                ob_m: g.ob_mm * 1e-3,
                ac_m: g.ac_mm * 1e-3,
                oc_m: g.oc_mm * 1e-3,
            })
            .collect();
        let valve = |v: &ValveSection| CheckValve {
            cracking_pa: v.cracking_bar * BAR,
            full_open_pa: v.full_open_bar * BAR,
            max_area_m2: v.max_area_mm2 * 1e-6,
            cd: v.discharge_coefficient,
        };
        let acc = |a: &AccumulatorSection| Accumulator {
            volume_m3: a.volume_l * 1e-3,
            precharge_pa: a.precharge_bar * BAR,
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
            pinion_radius_m: f.input.pinion_radius_mm * 1e-3,
            oil,
            chamber_dead_volume_m3: m.dead_volume_cm3 * 1e-6
                + pipe_volume(m.hose_length_m, m.hose_inner_diameter_mm),
            free_play_m: m.free_play_mm * 1e-3,
            stop_stiffness_n_per_m: m.hard_stop_stiffness_n_per_m,
            stop_damping_n_s_per_m: m.hard_stop_damping_n_s_per_m,
            seal_friction_n_s_per_m: m.seal_friction_n_s_per_m,
            stops: match f.solver.stops {
                file::StopsKind::Spring => Stops::Spring,
                file::StopsKind::Events => Stops::Events,
            },
            cylinders,
            configs,
            check: valve(&f.check_valve),
            makeup: valve(&f.makeup_valve),
            relief_setting_pa: f.relief_valve.setting_bar * BAR,
            relief_range_pa: f.relief_valve.regulation_range_bar * BAR,
            relief_area_m2: f.relief_valve.max_area_mm2 * 1e-6,
            relief_cd: f.relief_valve.discharge_coefficient,
            valve_cd: f.control_valve.discharge_coefficient,
            valve_cd_slope_per_100bar: f.control_valve.cd_slope_per_100bar,
            valve_aperture_pct: f.control_valve.aperture_pct.clone(),
            valve_area_m2: f.control_valve.area_mm2.iter().map(|a| a * 1e-6).collect(),
            spool_tau_s: f.control_valve.spool_time_constant_ms * 1e-3,
            hp_acc: acc(&f.hp_accumulator),
            lp_acc: acc(&f.lp_accumulator),
            motor_disp_m3_per_rad: motor_disp,
            motor_leak_m3_per_s_pa: motor_leak,
            motor_eta_mech: mo.total_efficiency / mo.volumetric_efficiency,
            motor_inertia_kg_m2: mo.inertia_kg_m2,
            load,
            hp_line_volume_m3: pipe_volume(l.hp_length_m, l.hp_inner_diameter_mm),
            motor_line_volume_m3: pipe_volume(
                l.valve_to_motor_length_m,
                l.valve_to_motor_inner_diameter_mm,
            ),
            lp_line_volume_m3: pipe_volume(l.motor_to_lp_length_m, l.motor_to_lp_inner_diameter_mm)
                + pipe_volume(
                    l.lp_to_manifold_length_m,
                    l.lp_to_manifold_inner_diameter_mm,
                ),
            lp_manifold_line_volume_m3: pipe_volume(
                l.lp_to_manifold_length_m,
                l.lp_to_manifold_inner_diameter_mm,
            ),
            hp_line_resistance_pa_s_per_m3: l.hp_line_resistance_bar_per_lpm * BAR * LPM,
            lp_line_resistance_pa_s_per_m3: l.lp_line_resistance_bar_per_lpm * BAR * LPM,
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
        assert!((b.cylinders[0].area_cap_m2 * 1e6 - 804.25).abs() < 0.01);
        assert!((b.cylinders[0].area_ann_m2 * 1e6 - 549.78).abs() < 0.01);
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

    /// The stops' model: a file without `[solver]` gets the events; `"spring"` is read; any
    /// other word is named with the two allowed; the default is not written back.
    #[test]
    fn the_stop_model_is_read_and_a_bad_one_named() {
        assert_eq!(Bench::reference().stops, Stops::Events);
        let spring = format!("{REFERENCE_BENCH_TOML}\n[solver]\nstops = \"spring\"\n");
        let b = Bench::from_toml(&spring, "my.toml").unwrap();
        assert_eq!(b.stops, Stops::Spring);
        let bad = format!("{REFERENCE_BENCH_TOML}\n[solver]\nstops = \"rigid\"\n");
        let err = Bench::from_toml(&bad, "my.toml").unwrap_err().to_string();
        println!("{err}");
        assert!(
            err.contains("my.toml")
                && err.contains("rigid")
                && err.contains("`spring` or `events`"),
            "{err}"
        );
        let written = toml::to_string(&Bench::reference().file).unwrap();
        assert!(!written.contains("[solver]"), "{written}");
    }

    /// The board's crystal is a setting with the datasheet's range; a file without the section
    /// gets the reference board's 8 MHz; 0 is a board without a crystal.
    #[test]
    fn the_crystal_is_checked_and_defaults_to_the_reference_board() {
        let text = REFERENCE_BENCH_TOML.replace("hse_mhz = 8", "hse_mhz = 30");
        let err = Bench::from_toml(&text, "my.toml").unwrap_err().to_string();
        assert!(
            err.contains("controller.board.hse_mhz") && err.contains("[4, 26] (MHz)"),
            "{err}"
        );
        let i = REFERENCE_BENCH_TOML.find("[controller.board]").unwrap();
        let without = &REFERENCE_BENCH_TOML[..i];
        let b = Bench::from_toml(without, "old.toml").unwrap();
        assert_eq!(b.file.controller.board.hse_mhz, 8);
        let none = REFERENCE_BENCH_TOML.replace("hse_mhz = 8", "hse_mhz = 0");
        assert_eq!(
            Bench::from_toml(&none, "x.toml")
                .unwrap()
                .file
                .controller
                .board
                .hse_mhz,
            0
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
