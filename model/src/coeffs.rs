//! Precomputed coefficients: the validated configuration turned into fixed-point constants and
//! tables, once, so the per-step functions need no float, no division and no trig.
//!
//! Everything is computed in f32 at configuration time (libm for the transcendental functions,
//! so it is the same on host and target), then rounded to Q16.16. Each stage's coefficients
//! and their builder sit beside the stage (`estimator::tracker`, `cylinder`, `motor`,
//! `observer`; the scheduler's in `scheduler`); here are the table sizes, the reduced laws the
//! builders tabulate, [`ModelConfig::coefficients`] which runs them, and the advisor's autonomy
//! table.

use crate::config::{AccumulatorConfig, ConfigError, ModelConfig};
use crate::fx::Fx;
use crate::table::{Table1, Table2};
use libm::{cosf, powf, sinf, sqrtf};

mod autonomy;

pub use crate::estimator::{
    BranchCoeffs, CylinderCoeffs, ObserverCoeffs, PumpCoeffs, ReadingCoeffs, TRACKER_STARTUP,
    TRACKER_STARTUP_MAX, TrackerCoeffs, expanding_memory_gains, tracker_startup_gains,
};

/// Rows (aperture, 0..100 % in 5 % steps) of the valve and autonomy tables.
pub const N_APERTURE: usize = 21;
/// Columns (pressure, 0..160 bar in 5 bar steps) of the valve and autonomy tables.
pub const N_PRESSURE: usize = 33;
/// Points of the 1-D node tables over 0..160 bar (1.25 bar steps: the HP capacitance jumps by
/// four orders of magnitude at the 25 bar precharge).
pub const N_NODE: usize = 129;
/// Points of the lever-arm tables over ±[`ARM_RANGE_RAD`].
pub const N_ARM: usize = 65;
/// Half-range of the lever-arm tables, rad (the design limit is ±30° = ±0.52 rad).
pub const ARM_RANGE_RAD: f32 = 0.6;
/// Upper end of the pressure axes, bar.
pub const P_MAX_BAR: f32 = 160.0;
/// Upper end of the LP capacitance table's axis, bar.
pub const LP_MAX_BAR: f32 = 32.0;
/// Points of the LP capacitance table over 0..[`LP_MAX_BAR`] (1 bar steps).
pub const N_LP: usize = 33;
/// Ceiling of [`BranchCoeffs::motor_gain_valve`], per L/min: at the closed valve 1/K² is
/// infinite; any value ≥ 1 per L/min already makes a 1 L/min flow settle within the step.
pub const MOTOR_GAIN_VALVE_CAP: f32 = 256.0;
/// Autonomy reported when the motor would never slow below the minimum speed, s.
pub const AUTONOMY_CAP_S: f32 = 30_000.0;

const P_ATM_BAR: f32 = 1.01325;

/// Everything the step functions read: the configuration turned into fixed-point constants
/// and tables, one struct per stage of the step (`estimator::step`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Coefficients {
    /// dt = 2^−dt_log2 s.
    pub dt_log2: u8,
    /// The shaft tracker's gains and constants (`estimator::tracker`).
    pub tracker: TrackerCoeffs,
    /// The cylinders (`estimator::cylinder`).
    pub pump: PumpCoeffs,
    /// The valve/motor branch and the relief (`estimator::motor`).
    pub branch: BranchCoeffs,
    /// The motor reading's settings (`estimator::motor_reading`).
    pub reading: ReadingCoeffs,
    /// The nodes' prediction and the corrections by the transducers (`estimator::observer`).
    pub observer: ObserverCoeffs,
    /// Autonomy, s, vs (aperture %, P2 bar), input blocked, LP nominal.
    pub autonomy: Table2<N_APERTURE, N_PRESSURE>,
    /// Pump-flow averaging gain per step (≈ one wave period), dt/τ.
    pub mean_gain: Fx,
    /// Motor sensor full scale, rpm.
    pub motor_max_rpm: Fx,
    /// Overpressure trip, bar.
    pub trip_bar: Fx,
    /// Below this P2 the estimate reports the HP accumulator empty, bar: the precharge plus
    /// `ModelConfig::hp_empty_margin_bar`.
    pub hp_empty_below_bar: Fx,
    /// The predicted P2 range in which the HP shadow check judges (`estimator::residual`), bar:
    /// from 2 bar above the empty accumulator (below it the node is the lines' stiff oil, where
    /// a small flow error moves P2 by bars) to 2 bar below the relief (whose reduced law the
    /// filter corrects from the transducer).
    pub residual_p2_range: (Fx, Fx),
    /// The net inflow into HP, L/min·s, that a reading below the shadow check's range
    /// (`residual_p2_range.0`) cannot stay there through (`estimator::residual::stuck_low`):
    /// the oil the accumulator holds at that pressure plus 1 % of its volume (0.54 + 0.1 L on
    /// the reference bench: P2 then ≈ 0.5 bar above the range), so that the two checks leave
    /// no band between them. Most counted in any validation run: 0.13 L.
    pub stuck_low_inflow: Fx,
}

/// An f32 coefficient in Q16.16, saturated. Out of line: the conversion is ≈ 100 bytes of
/// Cortex-M4 code, and [`ModelConfig::coefficients`] makes some 60 of them (inlined, they cost
/// the firmware image ≈ 4 KB of flash).
#[inline(never)]
pub(crate) fn fx(x: f32) -> Fx {
    Fx::saturating_from_num(x)
}

/// Trapped-air bulk modulus (`docs/physics.md` §2), bar.
pub(crate) fn modulus_bar(cfg: &ModelConfig, p: f32) -> f32 {
    let el = cfg.oil_liquid_bulk_modulus_mpa * 10.0;
    let a = cfg.trapped_air_fraction;
    let n = cfg.air_polytropic_index;
    let pabs = (P_ATM_BAR + p).max(1e-3);
    let ratio = powf(P_ATM_BAR / pabs, 1.0 / n);
    el * (1.0 + a * ratio) / (1.0 + a * ratio / (n * pabs) * el)
}

/// Accumulator oil volume (L) at gauge pressure p (bar).
pub(crate) fn acc_fluid(a: &AccumulatorConfig, p: f32) -> f32 {
    if p <= a.precharge_bar {
        0.0
    } else {
        a.volume_l
            * (1.0
                - powf(
                    (a.precharge_bar + P_ATM_BAR) / (p + P_ATM_BAR),
                    1.0 / a.polytropic_index,
                ))
    }
}

/// Node capacitance, L/bar: accumulator gas + compressibility of the node's oil.
pub(crate) fn capacitance(cfg: &ModelConfig, a: &AccumulatorConfig, p: f32) -> f32 {
    let gas = if p <= a.precharge_bar {
        0.0
    } else {
        (a.volume_l - acc_fluid(a, p)) / (a.polytropic_index * (p + P_ATM_BAR))
    };
    gas + (a.line_volume_l + acc_fluid(a, p)) / modulus_bar(cfg, p)
}

/// Node value of a capacitance table with node spacing `h` bar. The capacitance jumps at the
/// precharge (gas below it: none; just above it: the whole accumulator), and a linear
/// interpolation smears the jump over the cell that holds it. Sampled plainly, the cell just
/// above the precharge would see up to 3 000× the real dP/dV (the reference bench's HP node:
/// 1/C from 185 to 0.06 bar/(L/min·s) over 25–26.25 bar), a stiff node that amplified every
/// flow error where P2 settles just above the precharge (the blocked runs' end, the 71 bar
/// discharge). So the node at or just below the precharge takes the value just above it: the
/// smear falls into the cell below, where the accumulator is empty and P2 passes through
/// quickly.
pub(crate) fn capacitance_node(cfg: &ModelConfig, a: &AccumulatorConfig, p: f32, h: f32) -> f32 {
    if p <= a.precharge_bar && p + h > a.precharge_bar {
        capacitance(cfg, a, a.precharge_bar * (1.0 + f32::EPSILON))
    } else {
        capacitance(cfg, a, p)
    }
}

/// [`ModelConfig::steady_flow`] for a valve coefficient `k` (L/min per √bar) and the motor's
/// β (bar per L/min).
pub(crate) fn steady_flow_k(k: f32, beta: f32, dp: f32) -> f32 {
    if k <= 0.0 || dp <= 0.0 {
        return 0.0;
    }
    let k2 = k * k;
    // Q² + K²βQ − K²·dp = 0, the stable form of the positive root.
    2.0 * k2 * dp / (k2 * beta + sqrtf(k2 * k2 * beta * beta + 4.0 * k2 * dp))
}

/// Lever geometry: φ0 such that the eye is at mid-stroke at θ = 0.
pub(crate) fn arm_m(g: &crate::config::GeometryConfig, stroke_mm: f32, theta: f32) -> f32 {
    let (r, oc, mid) = (
        g.ob_mm * 1e-3,
        g.oc_mm * 1e-3,
        (g.ac_mm + 0.5 * stroke_mm) * 1e-3,
    );
    let c0 = ((r * r + oc * oc - mid * mid) / (2.0 * r * oc)).clamp(-1.0, 1.0);
    let phi = libm::acosf(c0) + theta;
    let cb = sqrtf(r * r + oc * oc - 2.0 * r * oc * cosf(phi));
    r * oc * sinf(phi) / cb
}

/// Rod-eye extension x = CB − L, mm.
pub(crate) fn ext_mm(g: &crate::config::GeometryConfig, stroke_mm: f32, theta: f32) -> f32 {
    let (r, oc, mid) = (g.ob_mm, g.oc_mm, g.ac_mm + 0.5 * stroke_mm);
    let c0 = ((r * r + oc * oc - mid * mid) / (2.0 * r * oc)).clamp(-1.0, 1.0);
    let phi = libm::acosf(c0) + theta;
    sqrtf(r * r + oc * oc - 2.0 * r * oc * cosf(phi)) - g.ac_mm
}

impl ModelConfig {
    /// Valve flow coefficient K at aperture `a` %, L/min per √bar.
    pub fn valve_k(&self, a: f32) -> f32 {
        let xs = &self.valve_aperture_pct;
        let ys = &self.valve_area_mm2;
        let a = a.clamp(0.0, 100.0);
        let mut i = 1;
        while i < 10 && xs[i] < a {
            i += 1;
        }
        let area = ys[i - 1] + (ys[i] - ys[i - 1]) * (a - xs[i - 1]) / (xs[i] - xs[i - 1]);
        // Cd·A·sqrt(2/ρ) in m³/s per √Pa → L/min per √bar.
        self.valve_discharge_coefficient
            * area
            * 1e-6
            * sqrtf(2.0 / self.oil_density_kg_m3)
            * 6e4
            * sqrtf(1e5)
    }

    /// Motor pressure drop per rpm on the load line, bar/rpm.
    pub fn bar_per_rpm(&self) -> f32 {
        let nm_per_bar =
            self.motor_displacement_cm3_per_rev * 1e-6 / (2.0 * core::f32::consts::PI) * 1e5;
        self.load_nm_per_rpm / (nm_per_bar * self.motor_mech_efficiency)
    }

    /// Motor speed per motor flow, rpm per L/min (Eq. 9 with the load line's pressure drop).
    pub fn rpm_per_lpm(&self) -> f32 {
        1.0 / (self.motor_displacement_cm3_per_rev * 1e-3
            + self.motor_leak_lpm_per_bar * self.bar_per_rpm())
    }

    /// The motor's pressure drop per valve flow on its load line (β), bar per L/min.
    pub fn motor_bar_per_lpm(&self) -> f32 {
        self.bar_per_rpm() * self.rpm_per_lpm()
    }

    /// Hydraulic inductance of the valve/motor branch, bar per L/min/s: the pressure that
    /// accelerates the rotor, L = J·rpm_per_lpm/κ with κ = (60/2π)·D·η_m/J the rotor's
    /// acceleration per bar (rpm/s per bar; D in m³/rad, bar in Pa). The branch obeys
    /// L·dQ/dt = ΔP − F(Q), F(Q) = Q²/K² + β·Q the steady pressure drop of [`Self::steady_flow`]
    /// (1.03 bar per L/min/s on the reference bench).
    pub fn motor_inductance(&self) -> f32 {
        let d_rad = self.motor_displacement_cm3_per_rev * 1e-6 / (2.0 * core::f32::consts::PI);
        let kappa = 60.0 / (2.0 * core::f32::consts::PI) * d_rad * self.motor_mech_efficiency * 1e5
            / self.motor_inertia_kg_m2;
        self.rpm_per_lpm() / kappa
    }

    /// The rotor's own time constant J/c behind a closed valve, s: c the generator's load,
    /// N·m per rad/s (0.134 s on the reference bench).
    pub fn rotor_time_constant_s(&self) -> f32 {
        self.motor_inertia_kg_m2 / (self.load_nm_per_rpm * 60.0 / (2.0 * core::f32::consts::PI))
    }

    /// Steady valve/motor flow, L/min, at aperture `a` % and P2 − LP = `dp` bar: the root of
    /// Q = K·sqrt(dp − β·Q) with β the motor's bar per L/min.
    pub fn steady_flow(&self, a: f32, dp: f32) -> f32 {
        steady_flow_k(self.valve_k(a), self.motor_bar_per_lpm(), dp)
    }

    /// Turns the validated configuration into coefficients ([`ModelConfig::coefficients_into`]
    /// on a zeroed set).
    pub fn coefficients(&self) -> Result<Coefficients, ConfigError> {
        let mut k = Coefficients::default();
        self.coefficients_into(&mut k)?;
        Ok(k)
    }

    /// Validates the configuration and builds its coefficients into `k`, stage by stage, each
    /// stage's builder writing its part in place: the stack holds one stage's work at a time,
    /// not a second set of tables (≈ 11 KB; a Cortex-M0 built the whole set by value in
    /// 17.8 KB of stack, `pto model-cost`). A configuration that fails validation leaves `k`
    /// as it was. Each stage's builder (`TrackerCoeffs::of`, …) is out of line like this one:
    /// inlined here, the compiler kept the generic table samplers out of line instead, and the
    /// bench image grew by 1.2 KB (out of line, 0.3 KB, and the set-up 1 500 instructions
    /// shorter; `pto fw-cost`).
    #[inline(never)]
    pub fn coefficients_into(&self, k: &mut Coefficients) -> Result<(), ConfigError> {
        self.validate()?;
        let dt_log2 = self.dt_log2;
        let dt = powf(2.0, -f32::from(dt_log2));
        let inductance = self.motor_inductance();
        k.dt_log2 = dt_log2;
        k.tracker = TrackerCoeffs::of(self, dt_log2, dt);
        k.pump.build(self);
        k.branch.build(self, dt, inductance);
        k.reading = ReadingCoeffs::of(self, dt, inductance);
        k.observer = ObserverCoeffs::of(self, dt);
        self.autonomy_table_into(&mut k.autonomy);
        k.mean_gain = fx(dt / 10.0).max(Fx::DELTA);
        k.motor_max_rpm = fx(self.motor_sensor_max_rpm);
        k.trip_bar = fx(self.trip_bar);
        k.hp_empty_below_bar = fx(self.hp_accumulator.precharge_bar + self.hp_empty_margin_bar);
        k.residual_p2_range = (
            fx(self.hp_accumulator.precharge_bar + self.hp_empty_margin_bar + 2.0),
            fx(self.relief_setting_bar - 2.0),
        );
        k.stuck_low_inflow = fx(60.0
            * (acc_fluid(
                &self.hp_accumulator,
                self.hp_accumulator.precharge_bar + self.hp_empty_margin_bar + 2.0,
            ) + 0.01 * self.hp_accumulator.volume_l));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The tracker's start-up gains from the constant table are the expanding-memory α–β gains
    /// to within 2^−25 (D_n's rounding to half an LSB of Q0.32 times 2n + 1 ≤ 129; 4·10^−7 of
    /// the smallest α), both 1 for the first residual and falling after
    /// it; the reference configuration takes 53 of them before the fading-memory gains.
    #[test]
    fn tracker_startup_gains_are_the_expanding_memory_gains() {
        let mut worst = 0.0f64;
        let mut last = (u32::MAX, u32::MAX);
        for (i, d) in TRACKER_STARTUP.iter().enumerate() {
            let n = i as u32 + 1;
            let (a, b) = tracker_startup_gains(i + 1, *d);
            let q31 = |x: u32| f64::from(x) / 2_147_483_648.0;
            let (alpha, beta) = expanding_memory_gains(n);
            worst = worst.max((q31(a) - alpha).abs()).max((q31(b) - beta).abs());
            assert!(
                a < last.0 || i == 1 && a == last.0,
                "α not falling at n = {n}"
            );
            assert!(b < last.1, "β not falling at n = {n}");
            last = (a, b);
        }
        let first = tracker_startup_gains(1, TRACKER_STARTUP[0]);
        let k = crate::ModelConfig::reference().coefficients().unwrap();
        println!(
            "start-up gains within {:.2e} of the formula over {} entries; {} used at the \
             reference's 4 Hz and 2^-10 s",
            worst, TRACKER_STARTUP_MAX, k.tracker.tracker_startup_len
        );
        assert_eq!(first, (1 << 31, 1 << 31));
        assert!(worst < 2f64.powi(-25), "{worst}");
        assert_eq!(k.tracker.tracker_startup_len, 53);
    }

    /// Just above an accumulator's precharge the node tables give the accumulator's own dP/dV
    /// (the jump to the empty accumulator's stiffness is smeared below the precharge, not
    /// above it).
    #[test]
    fn capacitance_tables_are_soft_just_above_the_precharge() {
        let cfg = ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        fn check<const N: usize>(
            cfg: &ModelConfig,
            name: &str,
            acc: &AccumulatorConfig,
            table: &Table1<N>,
            p_max: f32,
        ) {
            let h = Table1::<N>::spacing(0.0, p_max);
            let below = 1.0 / (60.0 * capacitance(cfg, acc, acc.precharge_bar - h));
            let mut worst = 0.0f32;
            for i in 1..=20 {
                let p = acc.precharge_bar + 2.0 * h * i as f32 / 20.0;
                let exact = 1.0 / (60.0 * capacitance(cfg, acc, p));
                let got: f32 = table.at(Fx::from_num(p)).to_num();
                worst = worst.max((got / exact - 1.0).abs());
            }
            println!(
                "{name}: dP/dV one cell below the precharge {below:.3}, up to two cells above \
                 within {:.1} % of the exact 1/C",
                100.0 * worst
            );
            assert!(worst < 0.05, "{name}: {worst}");
        }
        check(
            &cfg,
            "HP",
            &cfg.hp_accumulator,
            &k.observer.inv_c_hp,
            P_MAX_BAR,
        );
        check(
            &cfg,
            "LP",
            &cfg.lp_accumulator,
            &k.observer.inv_c_lp,
            LP_MAX_BAR,
        );
    }
}
