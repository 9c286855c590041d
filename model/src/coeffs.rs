//! Precomputed coefficients: the validated configuration turned into fixed-point constants and
//! tables, once, so the per-step functions need no float, no division and no trig.
//!
//! Everything here is computed in f32 at configuration time (libm for the transcendental
//! functions, so it is the same on host and target), then rounded to Q16.16.
//!
//! Over 600 lines: the builder and the reduced laws it tabulates (f32, configuration time),
//! with their tests.

use crate::config::{AccumulatorConfig, ConfigError, ModelConfig};
use crate::fx::Fx;
use crate::table::{Table1, Table2};
use libm::{cosf, expf, powf, sinf, sqrtf};

mod autonomy;

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

/// Per-cylinder constants.
#[derive(Debug, Clone, PartialEq)]
pub struct CylinderCoeffs {
    /// ±1.
    pub side: Fx,
    /// Cap-side flow per rod speed, L/min per mm/s.
    pub q_cap: Fx,
    /// Rod-side flow per rod speed, L/min per mm/s.
    pub q_ann: Fx,
    /// Cap-side force per bar, kN/bar.
    pub f_cap: Fx,
    /// Rod-side force per bar, kN/bar.
    pub f_ann: Fx,
    /// Cap-chamber dead volume (with hose) as a length of cap area, mm.
    pub dead_cap_mm: Fx,
    /// Rod-chamber dead volume (with hose) as a length of annulus area, mm.
    pub dead_rod_mm: Fx,
    /// Stroke, mm.
    pub stroke_mm: Fx,
    /// A_ann / A_cap (new/old area after a reversal to extending).
    pub ratio_ext: Fx,
    /// A_cap / A_ann (new/old area after a reversal to retracting).
    pub ratio_ret: Fx,
}

/// Length of the shaft tracker's start-up gain table (a power of two: the index is masked).
pub const TRACKER_STARTUP_MAX: usize = 64;

/// The shaft tracker's start-up gains for the n-th residual after its first encoder reading,
/// n = 1 ..= [`TRACKER_STARTUP_MAX`], as D_n = 1/((n + 1)(n + 2)) in Q0.32 (entry n − 1): the
/// expanding-memory α–β filter (the least-squares line through every reading so far) has
/// α_n = 2(2n + 1)·D_n and β_n = 6·D_n (Brookner, *Tracking and Kalman Filtering Made Easy*,
/// §1.2.10; α_1 = β_1 = 1: the line through the first two readings), so one word per step
/// holds both. They do not depend on the configuration: a constant in flash (256 B), built at
/// compile time. Started from ω = 0 with the fading-memory gains instead, a shaft already
/// turning at 0.26 rad/s (a Test I start) read 0 % of its speed at first, 18 % at 16 ms and
/// 125 % at 0.1 s, and the model's pump flow and rod travel with it.
pub static TRACKER_STARTUP: [u32; TRACKER_STARTUP_MAX] = tracker_startup_table();

const fn tracker_startup_table() -> [u32; TRACKER_STARTUP_MAX] {
    let mut t = [0u32; TRACKER_STARTUP_MAX];
    let mut i = 0;
    while i < TRACKER_STARTUP_MAX {
        let n = i as u64 + 1;
        let d = (n + 1) * (n + 2);
        // Rounded to nearest; D_1 = 1/6 < 1.
        t[i] = (((1u64 << 32) + d / 2) / d) as u32;
        i += 1;
    }
    t
}

/// The expanding-memory α–β gains (α_n, β_n) of the n-th update, n ≥ 1, in f64: the formula
/// [`TRACKER_STARTUP`] tabulates, for f64 models of the tracker (the host's reference model,
/// tests); not used by the step or by the coefficients (no f64 arithmetic in the firmware).
pub fn expanding_memory_gains(n: u32) -> (f64, f64) {
    let n = f64::from(n);
    let d = 1.0 / ((n + 1.0) * (n + 2.0));
    (2.0 * (2.0 * n + 1.0) * d, 6.0 * d)
}

/// α_n and β_n (both Q1.31, ≤ 2^31) of the tracker's n-th start-up update from
/// [`TRACKER_STARTUP`]'s D_n (Q0.32): 2(2n + 1)·D_n and 6·D_n.
#[inline]
pub fn tracker_startup_gains(n: usize, d_q32: u32) -> (u32, u32) {
    // α_n·2^31 = (2n + 1)·D_n·2^32 and β_n·2^31 = 3·D_n·2^32. n ≤ 2^8 and D_n < 2^32: < 2^42;
    // held to 2^31 (n = 1, where the rounded D_1 makes them one LSB over).
    let d = u64::from(d_q32);
    (
        ((2 * n as u64 + 1) * d).min(1 << 31) as u32,
        (3 * d).min(1 << 31) as u32,
    )
}

/// The shaft tracker's coefficients (`estimator::tracker`).
#[derive(Debug, Clone, PartialEq)]
pub struct TrackerCoeffs {
    /// Encoder count → rad, as the fraction bits of Q32.32 so a 16 384-count encoder keeps full
    /// precision (< 2^29: ≥ 64 counts per revolution).
    pub rad_per_count_q32: i32,
    /// α of the α–β–γ shaft tracker, Q1.31 (< 1). The tracker runs in Q32.32: at 1 kHz a shaft
    /// at 0.2 rad/s advances 2e-4 rad per step, 13 LSB of Q16.16, and truncating that every step
    /// biased the speed by +0.026 rad/s (10 %).
    pub alpha_q31: i32,
    /// β/dt of the α–β–γ shaft tracker, 1/s, Q16.16 (< 2^23 over the validated bandwidth and dt).
    pub beta_over_dt_q16: i32,
    /// 2γ/dt² of the α–β–γ shaft tracker, 1/s², Q16.16 (< 2^28 likewise).
    pub gamma_over_dt2_q16: i32,
    /// Number of steps after the tracker's first encoder reading that take the
    /// expanding-memory gains [`TRACKER_STARTUP`] (≤ [`TRACKER_STARTUP_MAX`]; 53 at 4 Hz and
    /// 2^−10 s): while both exceed the fading-memory gains above.
    pub tracker_startup_len: u8,
    /// The rounding term of the tracker's × dt in Q32.32: 2^(dt_log2 − 1) (a run-time 64-bit
    /// shift to build it costs ≈ 14 Cortex-M4 instructions a step).
    pub round_dt_q32: i64,
    /// The rounding term of its × dt²/2: 2^(2·dt_log2).
    pub round_dt2_q32: i64,
    /// Steps without an encoder change after which the encoder is suspected stuck.
    pub stuck_steps: u16,
}

/// The motor reading's coefficients (`estimator::motor_reading`), used without the HP
/// transducer.
#[derive(Debug, Clone, PartialEq)]
pub struct ReadingCoeffs {
    /// Low-pass gain of the motor reading's filters (`estimator::motor_reading`), per second
    /// step: 2·dt/τ.
    pub filter: Fx,
    /// The rotor's inductance per step, L/dt, bar per L/min (the branch's dF/dQ is the step's
    /// relaxation gain times this).
    pub ldt: Fx,
    /// L/τ: the reading's pressure per L/min of measured flow above its low-passed value.
    pub lt: Fx,
    /// P2's gain toward the reading, per second step: 2·dt/T (0: the reading is not used).
    pub gain: Fx,
    /// Largest dF/dQ at which the reading is used, bar per L/min.
    pub max_slope: Fx,
    /// Smallest measured motor flow at which the reading is used, L/min.
    pub min_lpm: Fx,
    /// Largest |command − spool| at which the reading is used, %.
    pub spool_tol: Fx,
    /// The reading's dead band as a fraction of ΔP.
    pub band: Fx,
    /// Correction steps (every second step) the reading's filters run before P2 takes it:
    /// three filter time constants.
    pub warm_steps: u16,
    /// The reading is used only while both the commanded and the modelled aperture are at
    /// least this, %.
    pub min_aperture: Fx,
    /// Minimum motor speed for the reading, rpm (also: a motor turning faster than this behind
    /// a closed valve contradicts the model).
    pub min_rpm: Fx,
    /// Variance of the reading's noise, bar².
    pub r: Fx,
    /// Highest P2 a plausible reading implies (beyond its band), bar: the relief setting plus
    /// the gate's worth of the reading's noise.
    pub p2_max: Fx,
}

/// The cylinders stage's coefficients (`estimator::cylinder`): per cylinder, the lever
/// geometry's tables and the oil's strain law in the chambers.
#[derive(Debug, Clone, PartialEq)]
pub struct PumpCoeffs {
    /// Cylinders.
    pub cyl: [CylinderCoeffs; 4],
    /// Lever arm d (mm) vs s·θ (rad), per geometry. In mm so that d·F stays exact to
    /// 0.01 N·m (in m, Q16.16 would quantise the arm to 1e-4 of itself).
    pub arm: [Table1<N_ARM>; 4],
    /// Rod-eye extension x (mm) vs s·θ (rad), per geometry.
    pub ext: [Table1<N_ARM>; 4],
    /// Oil strain ∫_0^p dp/E in milli-strain vs p (0..160 bar).
    pub ms_of_p: Table1<N_NODE>,
    /// Its inverse: p (bar) vs milli-strain.
    pub p_of_ms: Table1<N_NODE>,
    /// Rod-fixation free play, mm.
    pub play_mm: Fx,
    /// Seal friction, kN per mm/s (2 kN·s/m = 0.002 kN per mm/s on the reference bench: 131
    /// LSB, 0.05 % resolution).
    pub seal_kn_per_mm_s: Fx,
    /// Open check-valve pressure drop, bar.
    pub check_drop_bar: Fx,
}

/// The valve/motor branch's coefficients (`estimator::motor`): the spool, the rotor's flow
/// and the relief.
#[derive(Debug, Clone, PartialEq)]
pub struct BranchCoeffs {
    /// Valve (= motor) flow, L/min, vs (aperture %, P2 − LP bar), motor on its load line.
    pub valve_flow: Table2<N_APERTURE, N_PRESSURE>,
    /// Spool lag gain per step, dt/τ (1 = ideal valve).
    pub spool_gain: Fx,
    /// The valve/motor flow's relaxation per step toward the steady flow, from the motor's own
    /// load line: dt·β/L (≈ dt/τ with τ = J/c the rotor's time constant, 0.134 s on the
    /// reference bench). See [`ModelConfig::motor_inductance`].
    pub motor_gain0: Fx,
    /// The valve's share of that relaxation per L/min of flow at the valve table's aperture
    /// nodes (read with [`Table2::at_with`]): dt/(L·K(a)²), held to [`MOTOR_GAIN_VALVE_CAP`]
    /// near the closed valve. The step's gain is `motor_gain0 + (Q_ss + Q)·motor_gain_valve(a)`
    /// (≤ 1).
    pub motor_gain_valve: [Fx; N_APERTURE],
    /// Motor speed per valve flow, rpm per L/min (Eq. 9 with the load line).
    pub rpm_per_lpm: Fx,
    /// Motor flow per rpm, L/min per rpm, Q8.24 (1/[`Self::rpm_per_lpm`]: 0.0086 on the
    /// reference bench, to 6·10^−8).
    pub lpm_per_rpm_q24: i32,
    /// Relief setting, bar.
    pub relief_setting_bar: Fx,
    /// Relief gain, L/min per bar.
    pub relief_gain_lpm_per_bar: Fx,
    /// Steps after which a rotor behind a closed valve has spun down (five of its time
    /// constants J/c): a motor still turning faster than `ReadingCoeffs::min_rpm` then contradicts
    /// the model.
    pub spin_down_steps: u16,
}

/// The observer's coefficients (`estimator::observer`): the nodes' prediction, the Kalman
/// update of P2 with the HP transducer and the fixed-gain correction of LP.
#[derive(Debug, Clone, PartialEq)]
pub struct ObserverCoeffs {
    /// dP2/dt per net HP inflow, bar/s per L/min, vs P2.
    pub inv_c_hp: Table1<N_NODE>,
    /// dLP/dt per net LP inflow, bar/s per L/min, vs LP.
    pub inv_c_lp: Table1<N_LP>,
    /// Process noise added to the P2 variance per step vs P2, bar²: the model's flow
    /// uncertainty times the node's dP2/dV, so an empty accumulator (tiny capacitance) makes the
    /// filter follow the transducer.
    pub q_step: Table1<N_NODE>,
    /// Process noise added to the P2 variance per step while P2 is at or above the relief
    /// setting and the HP transducer corrects it, bar²: the reduced relief law's own error
    /// (`ModelConfig::relief_process_noise_bar_per_sqrt_s`).
    pub q_relief: Fx,
    /// Relief setting, bar (where [`Self::q_relief`] starts).
    pub relief_setting_bar: Fx,
    /// Measurement variance, bar².
    pub r: Fx,
    /// Kalman gain vs prior variance on [0, r].
    pub gain_fine: Table1<33>,
    /// Kalman gain vs prior variance on [0, 32 r].
    pub gain_coarse: Table1<33>,
    /// Steady-state Kalman gain used for LP.
    pub gain_lp: Fx,
    /// Gate², in σ².
    pub gate_sq: Fx,
    /// Consecutive rejected steps before the estimate is reset to the sensor.
    pub gate_reset_steps: u16,
    /// Ceiling of the variance a rejected reading adds (fading memory): 16 r, i.e. a P2 σ of
    /// 4 measurement σ, so the gate never opens wider than ≈ 20 measurement σ.
    pub var_fade_max: Fx,
    /// HP sensor range, bar.
    pub hp_range_bar: (Fx, Fx),
    /// LP sensor range, bar.
    pub lp_range_bar: (Fx, Fx),
    /// Top of the band above the HP precharge where model-only P2 may fall at any moment, bar.
    pub precharge_band_top_bar: Fx,
    /// Least model-only P2 variance in that band, bar².
    pub var_precharge: Fx,
}

/// Everything the step functions read: the configuration turned into fixed-point constants
/// and tables, one struct per stage of the step (`estimator::step`).
#[derive(Debug, Clone, PartialEq)]
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
fn fx(x: f32) -> Fx {
    Fx::saturating_from_num(x)
}

/// ⌊2π · 2^32⌋: a full turn in the tracker's Q32.32 angle.
const TWO_PI_Q32: u64 = 26_986_075_409;

/// Trapped-air bulk modulus (`docs/physics.md` §2), bar.
fn modulus_bar(cfg: &ModelConfig, p: f32) -> f32 {
    let el = cfg.oil_liquid_bulk_modulus_mpa * 10.0;
    let a = cfg.trapped_air_fraction;
    let n = cfg.air_polytropic_index;
    let pabs = (P_ATM_BAR + p).max(1e-3);
    let ratio = powf(P_ATM_BAR / pabs, 1.0 / n);
    el * (1.0 + a * ratio) / (1.0 + a * ratio / (n * pabs) * el)
}

/// Accumulator oil volume (L) at gauge pressure p (bar).
fn acc_fluid(a: &AccumulatorConfig, p: f32) -> f32 {
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
fn capacitance(cfg: &ModelConfig, a: &AccumulatorConfig, p: f32) -> f32 {
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
fn capacitance_node(cfg: &ModelConfig, a: &AccumulatorConfig, p: f32, h: f32) -> f32 {
    if p <= a.precharge_bar && p + h > a.precharge_bar {
        capacitance(cfg, a, a.precharge_bar * (1.0 + f32::EPSILON))
    } else {
        capacitance(cfg, a, p)
    }
}

/// [`ModelConfig::steady_flow`] for a valve coefficient `k` (L/min per √bar) and the motor's
/// β (bar per L/min).
fn steady_flow_k(k: f32, beta: f32, dp: f32) -> f32 {
    if k <= 0.0 || dp <= 0.0 {
        return 0.0;
    }
    let k2 = k * k;
    // Q² + K²βQ − K²·dp = 0, the stable form of the positive root.
    2.0 * k2 * dp / (k2 * beta + sqrtf(k2 * k2 * beta * beta + 4.0 * k2 * dp))
}

/// Lever geometry: φ0 such that the eye is at mid-stroke at θ = 0.
fn arm_m(g: &crate::config::GeometryConfig, stroke_mm: f32, theta: f32) -> f32 {
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
fn ext_mm(g: &crate::config::GeometryConfig, stroke_mm: f32, theta: f32) -> f32 {
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

    /// Turns the validated configuration into coefficients.
    #[inline(never)]
    pub fn coefficients(&self) -> Result<Coefficients, ConfigError> {
        self.validate()?;
        let k = self.dt_log2;
        let dt = powf(2.0, -f32::from(k));
        // 2π·2^32 / counts, floored, in integers (no f64 arithmetic in the firmware image: the
        // soft-float double routines cost ≈ 3 KB of flash). ≥ 64 counts (validated): < 2^29.
        let rad_per_count_q32 =
            (TWO_PI_Q32 / u64::from(self.encoder_counts_per_rev)).min(i32::MAX as u64) as i32;
        // Fading-memory α–β–γ tracker (a triple pole at r = exp(−2π·bw·dt)): α = 1 − r³,
        // β = 1.5(1 − r)²(1 + r), γ = ½(1 − r)³. Its constant-acceleration model follows the
        // sinusoidal shaft with ≈0.3 % speed error at 4 Hz, where an α–β tracker lags by
        // 1/(π·bw) and shifts every stroke reversal of the torque estimate by as much.
        let rr = expf(-2.0 * core::f32::consts::PI * self.encoder_bandwidth_hz * dt);
        let om = 1.0 - rr;
        let alpha = 1.0 - rr * rr * rr;
        let beta = 1.5 * om * om * (1.0 + rr);
        let gamma = 0.5 * om * om * om;
        // The expanding-memory start-up gains while both exceed the fading-memory ones (they
        // fall as 4/n and 6/n²; after TRACKER_STARTUP_MAX steps the fading-memory gains take
        // over in any case).
        let tracker_startup_len = TRACKER_STARTUP
            .iter()
            .enumerate()
            .take_while(|(i, d)| {
                let (a, b) = tracker_startup_gains(i + 1, **d);
                let q31 = |x: u32| x as f32 / 2_147_483_648.0;
                q31(a) > alpha && q31(b) > beta
            })
            .count() as u8;
        let lp_nom = self.nominal_lp_bar;
        let cyl = core::array::from_fn(|i| {
            let c = &self.cylinders[i];
            let a_cap = core::f32::consts::PI / 4.0 * c.bore_mm * c.bore_mm * 1e-6;
            let a_ann = a_cap - core::f32::consts::PI / 4.0 * c.rod_mm * c.rod_mm * 1e-6;
            CylinderCoeffs {
                side: fx(f32::from(c.side)),
                q_cap: fx(a_cap * 60.0),
                q_ann: fx(a_ann * 60.0),
                f_cap: fx(a_cap * 100.0),
                f_ann: fx(a_ann * 100.0),
                dead_cap_mm: fx(self.chamber_dead_volume_cm3 * 1e-6 / a_cap * 1e3),
                dead_rod_mm: fx(self.chamber_dead_volume_cm3 * 1e-6 / a_ann * 1e3),
                stroke_mm: fx(c.stroke_mm),
                ratio_ext: fx(a_ann / a_cap),
                ratio_ret: fx(a_cap / a_ann),
            }
        });
        let stroke = self.cylinders[0].stroke_mm;
        let arm = core::array::from_fn(|g| {
            let geo = self.geometries[g];
            Table1::sample(-ARM_RANGE_RAD, ARM_RANGE_RAD, move |th| {
                1e3 * arm_m(&geo, stroke, th)
            })
        });
        let ext = core::array::from_fn(|g| {
            let geo = self.geometries[g];
            Table1::sample(-ARM_RANGE_RAD, ARM_RANGE_RAD, move |th| {
                ext_mm(&geo, stroke, th)
            })
        });
        // Milli-strain on a fine pressure grid (0.25 bar, accumulated once), then both tables
        // by linear interpolation of it: the strain law is monotone, so its inverse is too.
        const FINE: usize = 641;
        let step = P_MAX_BAR / (FINE - 1) as f32;
        let mut fine = [0.0f32; FINE];
        for i in 1..FINE {
            let mid = (i as f32 - 0.5) * step;
            fine[i] = fine[i - 1] + 1e3 * step / modulus_bar(self, mid);
        }
        let ms_at = |p: f32| {
            let u = (p / step).clamp(0.0, (FINE - 1) as f32);
            let i = (u as usize).min(FINE - 2);
            fine[i] + (u - i as f32) * (fine[i + 1] - fine[i])
        };
        let p_at = |ms: f32| {
            let i = fine.partition_point(|&v| v <= ms).clamp(1, FINE - 1);
            let (a, b) = (fine[i - 1], fine[i]);
            step * ((i - 1) as f32 + ((ms - a) / (b - a)).clamp(0.0, 1.0))
        };
        let ms_of_p = Table1::sample(0.0, P_MAX_BAR, ms_at);
        let p_of_ms = Table1::sample(0.0, fine[FINE - 1], p_at);
        let valve_flow = Table2::sample((0.0, 100.0), (0.0, P_MAX_BAR), |a, dp| {
            self.steady_flow(a, dp)
        });
        let autonomy = self.autonomy_table();
        let (h_hp, h_lp) = (
            Table1::<N_NODE>::spacing(0.0, P_MAX_BAR),
            Table1::<N_LP>::spacing(0.0, LP_MAX_BAR),
        );
        let inv_c_hp = Table1::sample(0.0, P_MAX_BAR, |p| {
            1.0 / (60.0 * capacitance_node(self, &self.hp_accumulator, p, h_hp))
        });
        let inv_c_lp = Table1::sample(0.0, LP_MAX_BAR, |p| {
            1.0 / (60.0 * capacitance_node(self, &self.lp_accumulator, p, h_lp))
        });
        let spool_gain = if self.spool_time_constant_ms <= 0.0 {
            1.0
        } else {
            (dt / (self.spool_time_constant_ms * 1e-3)).min(1.0)
        };
        let inductance = self.motor_inductance();
        let r = self.pressure_noise_bar * self.pressure_noise_bar;
        // LP: steady-state gain for the flow uncertainty at nominal LP.
        let ic_lp = 1.0 / (60.0 * capacitance(self, &self.lp_accumulator, lp_nom));
        let qf = self.process_noise_lpm_per_sqrt_s * ic_lp;
        let q = qf * qf * dt;
        let gain = |v: f32| v / (v + r);
        let pp = 0.5 * (q + sqrtf(q * q + 4.0 * q * r));
        Ok(Coefficients {
            dt_log2: k,
            tracker: TrackerCoeffs {
                rad_per_count_q32,
                // (Scaling an f32 by a power of two is exact, and float-to-integer casts
                // saturate: α rounds to at most i32::MAX = 1 − 2^−31.)
                tracker_startup_len,
                alpha_q31: (alpha * 2_147_483_648.0) as i32,
                beta_over_dt_q16: (beta / dt * 65_536.0) as i32,
                gamma_over_dt2_q16: (2.0 * gamma / (dt * dt) * 65_536.0) as i32,
                round_dt_q32: 1i64 << (k - 1),
                round_dt2_q32: 1i64 << (2 * k),
                stuck_steps: (2.0 / dt).min(60_000.0) as u16,
            },
            pump: PumpCoeffs {
                cyl,
                arm,
                ext,
                ms_of_p,
                p_of_ms,
                play_mm: fx(self.free_play_mm),
                seal_kn_per_mm_s: fx(self.seal_friction_n_s_per_m * 1e-6),
                check_drop_bar: fx(self.check_valve_drop_bar),
            },
            branch: BranchCoeffs {
                valve_flow,
                spool_gain: fx(spool_gain),
                motor_gain0: fx(dt * self.motor_bar_per_lpm() / inductance),
                // Sampled on the valve table's aperture rows (0..100 %, N_APERTURE nodes).
                motor_gain_valve: Table1::<N_APERTURE>::sample(0.0, 100.0, |a| {
                    let kv = self.valve_k(a);
                    if kv <= 0.0 {
                        MOTOR_GAIN_VALVE_CAP
                    } else {
                        (dt / (inductance * kv * kv)).min(MOTOR_GAIN_VALVE_CAP)
                    }
                })
                .y,
                rpm_per_lpm: fx(self.rpm_per_lpm()),
                // Float-to-integer casts saturate; ≥ 1/10 000 rpm per L/min by validation.
                lpm_per_rpm_q24: (16_777_216.0 / self.rpm_per_lpm()) as i32,
                relief_setting_bar: fx(self.relief_setting_bar),
                relief_gain_lpm_per_bar: fx(self.relief_gain_lpm_per_bar),
                spin_down_steps: (5.0 * self.rotor_time_constant_s() / dt).clamp(1.0, 60_000.0)
                    as u16,
            },
            // The reading's filters run every second step (`estimator::motor_reading`).
            reading: ReadingCoeffs {
                filter: fx((2.0 * dt / (self.motor_reading_filter_ms * 1e-3)).min(1.0)),
                ldt: fx(inductance / dt),
                lt: fx(inductance / (self.motor_reading_filter_ms * 1e-3)),
                gain: if self.motor_reading_time_constant_ms > 0.0 {
                    fx((2.0 * dt / (self.motor_reading_time_constant_ms * 1e-3)).min(1.0))
                } else {
                    Fx::ZERO
                },
                max_slope: fx(self.motor_reading_max_slope_bar_per_lpm),
                min_lpm: fx(self.motor_reading_min_rpm / self.rpm_per_lpm()),
                spool_tol: fx(self.motor_reading_spool_tolerance_pct),
                band: fx(self.motor_reading_band_pct * 1e-2),
                warm_steps: (1.5 * self.motor_reading_filter_ms * 1e-3 / dt).clamp(1.0, 60_000.0)
                    as u16,
                min_aperture: fx(self.motor_reading_min_aperture_pct),
                min_rpm: fx(self.motor_reading_min_rpm),
                r: fx(self.motor_reading_noise_bar * self.motor_reading_noise_bar),
                p2_max: fx(self.relief_setting_bar + self.gate_sigma * self.motor_reading_noise_bar),
            },
            observer: ObserverCoeffs {
                inv_c_hp,
                inv_c_lp,
                q_step: Table1::sample(0.0, P_MAX_BAR, |p| {
                    let ic = 1.0 / (60.0 * capacitance_node(self, &self.hp_accumulator, p, h_hp));
                    let qf = self.process_noise_lpm_per_sqrt_s * ic;
                    (qf * qf * dt).max(1.0 / 65_536.0)
                }),
                q_relief: fx(self.relief_process_noise_bar_per_sqrt_s
                    * self.relief_process_noise_bar_per_sqrt_s
                    * dt),
                relief_setting_bar: fx(self.relief_setting_bar),
                r: fx(r),
                gain_fine: Table1::sample(0.0, r, gain),
                gain_coarse: Table1::sample(0.0, 32.0 * r, gain),
                gain_lp: fx(pp / (pp + r)),
                gate_sq: fx(self.gate_sigma * self.gate_sigma),
                gate_reset_steps: (self.gate_reset_ms * 1e-3 / dt).clamp(1.0, 60_000.0) as u16,
                var_fade_max: fx(16.0 * r),
                hp_range_bar: (
                    fx(self.hp_sensor_range_bar.0),
                    fx(self.hp_sensor_range_bar.1),
                ),
                lp_range_bar: (
                    fx(self.lp_sensor_range_bar.0),
                    fx(self.lp_sensor_range_bar.1),
                ),
                precharge_band_top_bar: fx(
                    self.hp_accumulator.precharge_bar + self.precharge_band_bar
                ),
                var_precharge: fx(self.precharge_sigma_bar * self.precharge_sigma_bar),
            },
            autonomy,
            mean_gain: fx(dt / 10.0).max(Fx::DELTA),
            motor_max_rpm: fx(self.motor_sensor_max_rpm),
            trip_bar: fx(self.trip_bar),
            hp_empty_below_bar: fx(self.hp_accumulator.precharge_bar + self.hp_empty_margin_bar),
            residual_p2_range: (
                fx(self.hp_accumulator.precharge_bar + self.hp_empty_margin_bar + 2.0),
                fx(self.relief_setting_bar - 2.0),
            ),
            stuck_low_inflow: fx(60.0
                * (acc_fluid(
                    &self.hp_accumulator,
                    self.hp_accumulator.precharge_bar + self.hp_empty_margin_bar + 2.0,
                ) + 0.01 * self.hp_accumulator.volume_l)),
        })
    }
}

impl ObserverCoeffs {
    /// Kalman gain for the prior variance `var` with its 16 bits below the LSB (`var_lo`), in
    /// units of 2^−32, held to [0, 1]. A Q16.16 gain near its steady ≈ 0.008 is good to 0.2 %:
    /// times a 2 bar innovation that was 2.5 P2 LSBs a step, and the variance's own rounding
    /// to its LSB another 7 (the gain table's slope there is ≈ 4 per bar²); this one leaves the
    /// step within 2 LSB of its f64 form (`tests/model/model_validation.rs`).
    /// (1 is returned as 1 − 2^−32, so the gain is one 32-bit word.)
    #[inline]
    pub fn gain_q32(&self, var: Fx, var_lo: u16) -> u32 {
        let t = if var < self.r {
            &self.gain_fine
        } else {
            &self.gain_coarse
        };
        t.at_q32(var, var_lo).clamp(0, i64::from(u32::MAX)) as u32
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
