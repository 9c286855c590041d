//! The bench file's ranges: every field checked against its allowed range and unit, and the
//! fields' mutual consistency, every offence collected (never the first one only).

use super::{AccumulatorSection, BenchError, BenchFile, FieldError, LoadSection, ValveSection};

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
        // The controller's settings: the firmware's own ranges (Controller::new,
        // SchedulerConfig::coefficients), so that a bench the firmware cannot take stops here
        // with the field's path.
        let k = &self.controller;
        let hse = k.board.hse_mhz;
        if hse != 0 && !(4..=26).contains(&hse) {
            c.fail(
                "controller.board.hse_mhz",
                format!(
                    "{hse} outside [4, 26] (MHz): the STM32F405's crystal range (DS8626, HSE \
                     oscillator); 0 for a board without a crystal"
                ),
            );
        }
        c.range(
            "controller.trip_release_margin_bar",
            k.trip_release_margin_bar,
            1.0,
            100.0,
            "bar",
        );
        c.range(
            "controller.trip_release_hold_ms",
            k.trip_release_hold_ms,
            1.0,
            60_000.0,
            "ms",
        );
        c.range(
            "controller.valve_slew_pct_per_s",
            k.valve_slew_pct_per_s,
            1.0,
            10_000.0,
            "%/s",
        );
        c.range(
            "controller.boot_sigma_bar",
            k.boot_sigma_bar,
            0.1,
            200.0,
            "bar",
        );
        for (name, t) in [
            ("hp_transducer", &k.hp_transducer),
            ("lp_transducer", &k.lp_transducer),
        ] {
            let p = format!("controller.{name}");
            c.range(
                format!("{p}.full_scale_bar"),
                t.full_scale_bar,
                1.0,
                1000.0,
                "bar",
            );
            c.range(format!("{p}.shunt_ohm"), t.shunt_ohm, 10.0, 1000.0, "Ω");
            c.range(format!("{p}.vref_v"), t.vref_v, 1.0, 5.0, "V");
            if t.shunt_ohm * 0.021 > t.vref_v {
                c.fail(
                    format!("{p}.shunt_ohm"),
                    format!(
                        "{} Ω puts 21 mA at {:.2} V, above the ADC reference vref_v = {} V (a \
                         short could not be told from full scale)",
                        t.shunt_ohm,
                        t.shunt_ohm * 0.021,
                        t.vref_v
                    ),
                );
            }
        }
        let s = &k.scheduler;
        for (field, v, lo, hi, unit) in [
            (
                "pressure_kp_pct_per_bar",
                s.pressure_kp_pct_per_bar,
                0.0,
                100.0,
                "%/bar",
            ),
            (
                "pressure_ki_pct_per_bar_s",
                s.pressure_ki_pct_per_bar_s,
                0.0,
                100.0,
                "%/(bar·s)",
            ),
            (
                "speed_kp_pct_per_rpm",
                s.speed_kp_pct_per_rpm,
                0.0,
                10.0,
                "%/rpm",
            ),
            (
                "speed_ki_pct_per_rpm_s",
                s.speed_ki_pct_per_rpm_s,
                0.0,
                10.0,
                "%/(rpm·s)",
            ),
            (
                "rate_limit_pct_per_s",
                s.rate_limit_pct_per_s,
                0.1,
                10_000.0,
                "%/s",
            ),
            ("min_aperture_pct", s.min_aperture_pct, 0.0, 100.0, "%"),
            (
                "max_aperture_pct",
                s.max_aperture_pct,
                s.min_aperture_pct,
                100.0,
                "%",
            ),
            ("autonomy_margin", s.autonomy_margin, 0.0, 2.0, "-"),
            (
                "overpressure_aperture_pct",
                s.overpressure_aperture_pct,
                0.0,
                100.0,
                "%",
            ),
            (
                "sensor_fault_aperture_pct",
                s.sensor_fault_aperture_pct,
                0.0,
                100.0,
                "%",
            ),
            (
                "sensor_fault_sigma_bar",
                s.sensor_fault_sigma_bar,
                0.1,
                100.0,
                "bar",
            ),
        ] {
            c.range(format!("controller.scheduler.{field}"), v, lo, hi, unit);
        }
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
