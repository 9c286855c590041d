//! Configuration in physical units, validated once; see [`crate::Coefficients`] for what it
//! turns into.

/// One double-acting cylinder.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct CylinderConfig {
    /// Bore, mm.
    pub bore_mm: f32,
    /// Rod diameter, mm.
    pub rod_mm: f32,
    /// Stroke, mm.
    pub stroke_mm: f32,
    /// Side of the shaft, ±1.
    pub side: i8,
}

/// One lever geometry (Eq. 1): OB, AC, OC.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct GeometryConfig {
    /// OB = R, mm.
    pub ob_mm: f32,
    /// AC = L (retracted pin-to-pin), mm.
    pub ac_mm: f32,
    /// OC, mm.
    pub oc_mm: f32,
}

/// Gas accumulator.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct AccumulatorConfig {
    /// Total volume, L.
    pub volume_l: f32,
    /// Precharge, bar.
    pub precharge_bar: f32,
    /// Polytropic index.
    pub polytropic_index: f32,
    /// Oil volume of the node besides the accumulator (lines), L.
    pub line_volume_l: f32,
}

/// Everything the reduced model needs, in physical units.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ModelConfig {
    /// Step dt = 2^−dt_log2 s (6..=12; 10 ≈ 1 kHz).
    pub dt_log2: u8,
    /// Shaft encoder counts per revolution (after quadrature decoding).
    pub encoder_counts_per_rev: u32,
    /// Bandwidth of the α–β–γ tracker that turns encoder counts into shaft speed, Hz.
    pub encoder_bandwidth_hz: f32,
    /// HC3.1 … HC3.4.
    pub cylinders: [CylinderConfig; 4],
    /// Config 1 … 4.
    pub geometries: [GeometryConfig; 4],
    /// Rod-fixation free play, mm.
    pub free_play_mm: f32,
    /// Viscous friction of a rod's seals, N·s/m: a force against the rod's speed, which adds
    /// c·d²·θ̇ to the restraining torque of every rod on duty (counted all stroke long).
    pub seal_friction_n_s_per_m: f32,
    /// Chamber dead volume incl. its hose, cm³.
    pub chamber_dead_volume_cm3: f32,
    /// Oil liquid bulk modulus, MPa.
    pub oil_liquid_bulk_modulus_mpa: f32,
    /// Oil density, kg/m³.
    pub oil_density_kg_m3: f32,
    /// Trapped air fraction at atmospheric pressure.
    pub trapped_air_fraction: f32,
    /// Polytropic index of the trapped air (1 isothermal … 1.4 adiabatic).
    pub air_polytropic_index: f32,
    /// HP accumulator (+ HP line).
    pub hp_accumulator: AccumulatorConfig,
    /// LP accumulator (+ LP lines).
    pub lp_accumulator: AccumulatorConfig,
    /// Control valve discharge coefficient.
    pub valve_discharge_coefficient: f32,
    /// Control valve table: aperture, %.
    pub valve_aperture_pct: [f32; 11],
    /// Control valve table: area, mm².
    pub valve_area_mm2: [f32; 11],
    /// Spool time constant, ms (0 = ideal).
    pub spool_time_constant_ms: f32,
    /// Pressure drop across an open bridge check valve, bar: the delivering chamber sits this
    /// much above P2 and the sucking one this much below LP.
    pub check_valve_drop_bar: f32,
    /// Relief setting, bar.
    pub relief_setting_bar: f32,
    /// Relief flow gained per bar above the setting, L/min/bar.
    pub relief_gain_lpm_per_bar: f32,
    /// Motor displacement, cm³/rev.
    pub motor_displacement_cm3_per_rev: f32,
    /// Motor leakage, L/min per bar.
    pub motor_leak_lpm_per_bar: f32,
    /// Motor mechanical efficiency.
    pub motor_mech_efficiency: f32,
    /// Generator load, N·m per rpm (torque ∝ speed).
    pub load_nm_per_rpm: f32,
    /// Inertia of the motor and generator rotor, kg·m² (the valve/motor flow's lag behind the
    /// pressure across it, `coeffs::BranchCoeffs::motor_gain0`).
    pub motor_inertia_kg_m2: f32,
    /// HP transducer range, bar (readings outside are a sensor fault).
    pub hp_sensor_range_bar: (f32, f32),
    /// LP transducer range, bar.
    pub lp_sensor_range_bar: (f32, f32),
    /// Motor speed sensor full scale, rpm.
    pub motor_sensor_max_rpm: f32,
    /// HP/LP transducer noise (1σ), bar.
    pub pressure_noise_bar: f32,
    /// Model (process) uncertainty of the net node flow, L/min per √s (P2's uncertainty grows
    /// by this times dP2/dV of the HP node).
    pub process_noise_lpm_per_sqrt_s: f32,
    /// Innovation gate, in standard deviations.
    pub gate_sigma: f32,
    /// Without the HP transducer, P2 is read from the motor speed (the rotor's equation
    /// L·dQ/dt = P2 − LP − F(Q) solved for P2, see `estimator::motor_reading`): the low-pass time
    /// constant of that reading, ms (it sets the reading's noise, L·σ_Q/τ, against its lag).
    pub motor_reading_filter_ms: f32,
    /// Time constant with which P2 follows that reading, ms (0 = P2 from the model alone).
    pub motor_reading_time_constant_ms: f32,
    /// Dead band of that reading, % of ΔP = P2 − LP: P2 follows only the part of the
    /// difference beyond it (the reduced motor model's own accuracy).
    pub motor_reading_band_pct: f32,
    /// The reading is used only while the branch's steady pressure drop changes by at most this
    /// per L/min of flow (dF/dQ, bar per L/min): near the closed valve the flow says little
    /// about the pressure.
    pub motor_reading_max_slope_bar_per_lpm: f32,
    /// … and only while the motor turns at least this fast, rpm (the sensor's noise, rectified
    /// at standstill, is not a flow).
    pub motor_reading_min_rpm: f32,
    /// … and only while the spool sits within this of its command, % (while it moves, the
    /// plant's valve and the model's need not be at the same opening: on the reference bench
    /// 1 % of aperture at 25 % is ≈ 2.5 bar of valve drop at 100 bar).
    pub motor_reading_spool_tolerance_pct: f32,
    /// … and only while both the commanded and the modelled aperture are at least this, %
    /// (near the closed valve the branch's flow says nothing of the pressure).
    pub motor_reading_min_aperture_pct: f32,
    /// Noise of that reading after its filter (1σ), bar: it sets how far a reading may lie from
    /// the model's P2 (beyond the band) before it contradicts it, and the variance the reading
    /// brings P2's toward.
    pub motor_reading_noise_bar: f32,
    /// P2 uncertainty added per √s while P2 sits on the relief and the HP transducer corrects
    /// it, bar/√s: the reduced relief law (linear in P2 from the setting) sits up to 0.25 bar
    /// below the bench's at its pump flows, a bias the filter must take from the transducer.
    pub relief_process_noise_bar_per_sqrt_s: f32,
    /// Without the HP transducer, P2's standard deviation is at least
    /// [`ModelConfig::precharge_sigma_bar`] while the estimate lies within this of the HP
    /// precharge (above it), bar.
    pub precharge_band_bar: f32,
    /// That least standard deviation, bar.
    pub precharge_sigma_bar: f32,
    /// The estimate reports the HP accumulator empty below its precharge plus this, bar: the
    /// accumulator's last cm³ (0.1 bar ≈ 30 cm³ on the reference bench, ≈ 0.6 s of a
    /// one-cylinder pump's flow) are within the model's error there, and the bench's P2 can
    /// leave the precharge slowly (Config 3: 1.1 bar in 50 ms).
    pub hp_empty_margin_bar: f32,
    /// After this long of consecutive rejected HP readings the estimate is reset to them, ms.
    pub gate_reset_ms: f32,
    /// Overpressure trip, bar.
    pub trip_bar: f32,
    /// Minimum motor speed for the autonomy estimate, rpm.
    pub autonomy_min_rpm: f32,
    /// Nominal LP for the autonomy table, bar.
    pub nominal_lp_bar: f32,
}

/// A configuration field outside its range.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ConfigError {
    /// Field name.
    pub field: &'static str,
    /// Offending value.
    pub value: f32,
    /// Allowed minimum.
    pub min: f32,
    /// Allowed maximum.
    pub max: f32,
}

impl core::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "{}: {} outside [{}, {}]",
            self.field, self.value, self.min, self.max
        )
    }
}

impl core::error::Error for ConfigError {}

fn check(field: &'static str, value: f32, min: f32, max: f32) -> Result<(), ConfigError> {
    if value.is_finite() && value >= min && value <= max {
        Ok(())
    } else {
        Err(ConfigError {
            field,
            value,
            min,
            max,
        })
    }
}

impl ModelConfig {
    /// The reference bench of `host-tests/data/reference-bench.toml`, to the bit: the values the
    /// host tools' conversion (`pto_bench::model::model_config`) gives for that file, as f32 (a
    /// host test keeps the two equal; the firmware built without `PTO_BENCH` runs this).
    pub fn reference() -> Self {
        let small = CylinderConfig {
            bore_mm: 32.0,
            rod_mm: 18.0,
            stroke_mm: 200.0,
            side: 1,
        };
        let big = CylinderConfig {
            bore_mm: 40.0,
            rod_mm: 22.0,
            stroke_mm: 200.0,
            side: 1,
        };
        let g = |ob_mm, ac_mm, oc_mm| GeometryConfig {
            ob_mm,
            ac_mm,
            oc_mm,
        };
        ModelConfig {
            dt_log2: 10,
            encoder_counts_per_rev: 16_384,
            encoder_bandwidth_hz: 4.0,
            cylinders: [
                small,
                big,
                CylinderConfig { side: -1, ..small },
                CylinderConfig { side: -1, ..big },
            ],
            geometries: [
                g(125.0, 400.0, 515.4),
                g(120.0, 450.0, 562.9),
                g(80.0, 350.0, 457.1),
                g(100.0, 400.0, 509.9),
            ],
            free_play_mm: 4.0,
            seal_friction_n_s_per_m: 2000.0,
            // 15 cm³ + 1 m of 9.5 mm hose.
            chamber_dead_volume_cm3: 85.882_19,
            oil_liquid_bulk_modulus_mpa: 1600.0,
            oil_density_kg_m3: 870.0,
            trapped_air_fraction: 0.06,
            air_polytropic_index: 1.4,
            // HP line 3 m × 12.7 mm; LP lines 6 m × 12.7 mm.
            hp_accumulator: AccumulatorConfig {
                volume_l: 10.0,
                precharge_bar: 25.0,
                polytropic_index: 1.4,
                line_volume_l: 0.380_030_6,
            },
            lp_accumulator: AccumulatorConfig {
                volume_l: 20.0,
                precharge_bar: 4.0,
                polytropic_index: 1.4,
                line_volume_l: 0.760_061_2,
            },
            valve_discharge_coefficient: 0.154,
            valve_aperture_pct: [
                0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 90.0, 100.0,
            ],
            valve_area_mm2: [
                0.0, 1.136, 2.756, 5.336, 8.876, 13.376, 18.836, 25.256, 32.636, 38.42, 44.18,
            ],
            spool_time_constant_ms: 50.0,
            // Between cracking (0.5 bar) and full opening (1.5 bar) at the test flows.
            check_valve_drop_bar: 0.7,
            relief_setting_bar: 130.0,
            // Cd·A_max/range·sqrt(2·Δp/ρ) with Δp = 130 − 8 bar:
            // 0.7 × 10 mm² / 3 bar × sqrt(2 × 122 bar / 870 kg/m³), in L/min per bar.
            relief_gain_lpm_per_bar: 23.445_707,
            motor_displacement_cm3_per_rev: 8.0,
            // D·ω_nom·(1 − η_v)/p_nom = 12 L/min × 0.08 / 100 bar.
            motor_leak_lpm_per_bar: 0.0096,
            motor_mech_efficiency: 0.923_913_06,
            load_nm_per_rpm: 0.00784,
            motor_inertia_kg_m2: 0.01,
            hp_sensor_range_bar: (-2.0, 250.0),
            lp_sensor_range_bar: (-2.0, 40.0),
            motor_sensor_max_rpm: 3000.0,
            pressure_noise_bar: 0.5,
            // The reduced model's net-flow error. On the empty HP node (dP2/dV ≈ 185 bar per
            // L/min·s) this is ≈ 9 bar/√s: the filter still averages a few readings (Test I P2
            // RMS 0.13–0.21 bar against the 0.5 bar sensor noise; 0.8 L/min/√s made it follow
            // the transducer, RMS 0.47). With gas in the accumulator (≈ 0.6 bar per L/min·s at
            // 100 bar) it is below the variance's floor of one Q16.16 LSB per step, which rules.
            process_noise_lpm_per_sqrt_s: 0.05,
            gate_sigma: 5.0,
            // Reading noise L·σ_Q/τ = 1.03 bar per L/min/s × 0.017 L/min (2 rpm) / 50 ms ≈
            // 0.36 bar per step, averaged over 25 ms of steps. Measured on Test I without the HP
            // transducer (`pto validate`, an earlier form of the reading): 20/50 ms filters and
            // 10/25/50 ms time constants gave 0.9–6.6 bar; 50/25 the least in the runs where the
            // accumulator empties each wave.
            motor_reading_filter_ms: 50.0,
            motor_reading_time_constant_ms: 25.0,
            // Motor speed RMS error of the reduced model against the full simulation: 0.4–1.9 %
            // (`pto validate`). 1 % kept the gas-node runs 0.5–0.7 bar off (model alone: 0.02–0.14).
            motor_reading_band_pct: 2.0,
            // 5× the motor's own load line (7.7 bar per L/min on the reference bench).
            motor_reading_max_slope_bar_per_lpm: 40.0,
            // 6 σ of the 2 rpm sensor noise.
            motor_reading_min_rpm: 12.0,
            motor_reading_spool_tolerance_pct: 0.05,
            // Below the valve table's first node (10 %) the area is interpolated from closed;
            // 2 % is 0.23 mm² on the reference valve, a tenth of the smallest run's.
            motor_reading_min_aperture_pct: 2.0,
            // L·σ_Q/τ = 1.03 bar per L/min/s × 0.017 L/min (2 rpm) / 50 ms ≈ 0.36 bar a sample.
            motor_reading_noise_bar: 0.36,
            // Measured with `pto validate` on the runs that sit on the relief (Test II, the
            // torque runs, Test III at 5–10 %): 0.5 left 2σ coverage at 94 % with four
            // cylinders; 1 and 2 both cover ≥ 95 % (P2 RMS there 0.10–0.17 → 0.07–0.10 bar).
            relief_process_noise_bar_per_sqrt_s: 1.0,
            // Test I without the transducer: the model's accumulator hovers within 0.3 bar of
            // the precharge before it empties, and the reading lets P2 lag the bench's fall by
            // up to 6–7 bar for 20–60 ms (`pto validate`); 2 bar makes that 3σ.
            precharge_band_bar: 1.0,
            precharge_sigma_bar: 2.0,
            // `pto validate`, Test I without the transducer: at 0 the flag came up to 60 ms
            // after the bench's accumulator ran empty (Config 3, HC3.1 + HC3.4); 0.05 bar: 46
            // ms; 0.1 bar: within 27 ms in every run (the table's `empty` column; how often it
            // stands while the bench is more than 0.3 bar above the precharge is its `early`
            // figure in `--json`).
            hp_empty_margin_bar: 0.1,
            gate_reset_ms: 250.0,
            trip_bar: 140.0,
            autonomy_min_rpm: 50.0,
            nominal_lp_bar: 8.0,
        }
    }

    /// Checks every field against its physical range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check("dt_log2", f32::from(self.dt_log2), 6.0, 12.0)?;
        check(
            "encoder_counts_per_rev",
            self.encoder_counts_per_rev as f32,
            64.0,
            1_048_576.0,
        )?;
        check(
            "encoder_bandwidth_hz",
            self.encoder_bandwidth_hz,
            0.05,
            50.0,
        )?;
        for c in &self.cylinders {
            check("cylinders.bore_mm", c.bore_mm, 5.0, 500.0)?;
            check("cylinders.rod_mm", c.rod_mm, 2.0, c.bore_mm - 1.0)?;
            check("cylinders.stroke_mm", c.stroke_mm, 10.0, 5000.0)?;
            // A cylinder sits on one side of the shaft or the other: −1 or +1, never 0.
            if c.side.unsigned_abs() != 1 {
                return Err(ConfigError {
                    field: "cylinders.side (−1 or +1)",
                    value: f32::from(c.side),
                    min: -1.0,
                    max: 1.0,
                });
            }
        }
        for g in &self.geometries {
            check("geometries.ob_mm", g.ob_mm, 10.0, 5000.0)?;
            check("geometries.ac_mm", g.ac_mm, 10.0, 10_000.0)?;
            check("geometries.oc_mm", g.oc_mm, g.ob_mm + 1.0, 20_000.0)?;
        }
        check("free_play_mm", self.free_play_mm, 0.0, 50.0)?;
        check(
            "seal_friction_n_s_per_m",
            self.seal_friction_n_s_per_m,
            0.0,
            100_000.0,
        )?;
        check(
            "chamber_dead_volume_cm3",
            self.chamber_dead_volume_cm3,
            0.1,
            5000.0,
        )?;
        check(
            "oil_liquid_bulk_modulus_mpa",
            self.oil_liquid_bulk_modulus_mpa,
            100.0,
            5000.0,
        )?;
        check("oil_density_kg_m3", self.oil_density_kg_m3, 600.0, 1200.0)?;
        check("trapped_air_fraction", self.trapped_air_fraction, 0.0, 0.5)?;
        check("air_polytropic_index", self.air_polytropic_index, 1.0, 1.67)?;
        for a in [&self.hp_accumulator, &self.lp_accumulator] {
            check("accumulator.volume_l", a.volume_l, 0.1, 500.0)?;
            check("accumulator.precharge_bar", a.precharge_bar, 0.5, 400.0)?;
            check(
                "accumulator.polytropic_index",
                a.polytropic_index,
                1.0,
                1.67,
            )?;
            check("accumulator.line_volume_l", a.line_volume_l, 0.001, 100.0)?;
        }
        check(
            "valve_discharge_coefficient",
            self.valve_discharge_coefficient,
            0.01,
            1.0,
        )?;
        for w in self.valve_aperture_pct.windows(2) {
            check("valve_aperture_pct", w[1], w[0] + 0.01, 100.0)?;
        }
        check(
            "valve_aperture_pct[0]",
            self.valve_aperture_pct[0],
            0.0,
            0.0,
        )?;
        check(
            "valve_aperture_pct[10]",
            self.valve_aperture_pct[10],
            100.0,
            100.0,
        )?;
        for w in self.valve_area_mm2.windows(2) {
            check("valve_area_mm2", w[1], w[0], 5000.0)?;
        }
        check(
            "spool_time_constant_ms",
            self.spool_time_constant_ms,
            0.0,
            5000.0,
        )?;
        check("check_valve_drop_bar", self.check_valve_drop_bar, 0.0, 20.0)?;
        check("relief_setting_bar", self.relief_setting_bar, 1.0, 300.0)?;
        check(
            "relief_gain_lpm_per_bar",
            self.relief_gain_lpm_per_bar,
            0.01,
            1000.0,
        )?;
        check(
            "motor_displacement_cm3_per_rev",
            self.motor_displacement_cm3_per_rev,
            0.1,
            1000.0,
        )?;
        check(
            "motor_leak_lpm_per_bar",
            self.motor_leak_lpm_per_bar,
            0.0,
            1.0,
        )?;
        check(
            "motor_mech_efficiency",
            self.motor_mech_efficiency,
            0.3,
            1.0,
        )?;
        check("load_nm_per_rpm", self.load_nm_per_rpm, 1e-5, 10.0)?;
        check("motor_inertia_kg_m2", self.motor_inertia_kg_m2, 1e-5, 10.0)?;
        check(
            "hp_sensor_range_bar.1",
            self.hp_sensor_range_bar.1,
            self.hp_sensor_range_bar.0 + 1.0,
            1000.0,
        )?;
        check(
            "lp_sensor_range_bar.1",
            self.lp_sensor_range_bar.1,
            self.lp_sensor_range_bar.0 + 1.0,
            1000.0,
        )?;
        check(
            "motor_sensor_max_rpm",
            self.motor_sensor_max_rpm,
            10.0,
            10_000.0,
        )?;
        check("pressure_noise_bar", self.pressure_noise_bar, 0.001, 20.0)?;
        check(
            "process_noise_lpm_per_sqrt_s",
            self.process_noise_lpm_per_sqrt_s,
            0.001,
            100.0,
        )?;
        check("gate_sigma", self.gate_sigma, 2.0, 50.0)?;
        check(
            "motor_reading_filter_ms",
            self.motor_reading_filter_ms,
            1.0,
            10_000.0,
        )?;
        if self.motor_reading_time_constant_ms != 0.0 {
            check(
                "motor_reading_time_constant_ms",
                self.motor_reading_time_constant_ms,
                1.0,
                100_000.0,
            )?;
        }
        check(
            "motor_reading_band_pct",
            self.motor_reading_band_pct,
            0.0,
            50.0,
        )?;
        check(
            "motor_reading_max_slope_bar_per_lpm",
            self.motor_reading_max_slope_bar_per_lpm,
            0.1,
            10_000.0,
        )?;
        check(
            "motor_reading_min_rpm",
            self.motor_reading_min_rpm,
            0.0,
            self.motor_sensor_max_rpm,
        )?;
        check(
            "motor_reading_spool_tolerance_pct",
            self.motor_reading_spool_tolerance_pct,
            0.0,
            100.0,
        )?;
        check(
            "motor_reading_min_aperture_pct",
            self.motor_reading_min_aperture_pct,
            0.0,
            100.0,
        )?;
        check(
            "motor_reading_noise_bar",
            self.motor_reading_noise_bar,
            0.001,
            100.0,
        )?;
        check(
            "relief_process_noise_bar_per_sqrt_s",
            self.relief_process_noise_bar_per_sqrt_s,
            0.0,
            100.0,
        )?;
        check("precharge_band_bar", self.precharge_band_bar, 0.0, 50.0)?;
        check("precharge_sigma_bar", self.precharge_sigma_bar, 0.0, 100.0)?;
        check("hp_empty_margin_bar", self.hp_empty_margin_bar, 0.0, 10.0)?;
        check("gate_reset_ms", self.gate_reset_ms, 1.0, 60_000.0)?;
        check("trip_bar", self.trip_bar, 1.0, 400.0)?;
        check("autonomy_min_rpm", self.autonomy_min_rpm, 1.0, 5000.0)?;
        check("nominal_lp_bar", self.nominal_lp_bar, 0.0, 100.0)?;
        Ok(())
    }
}
