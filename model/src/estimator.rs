//! The HP-pressure / restraining-torque estimator: the reduced-order node model of physics.md §2
//! as the prediction, corrected by the pressure transducers when they are valid.
//!
//! Per step: shaft angle and speed from the encoder (α–β–γ tracker) → per cylinder on duty, rod
//! speed from the lever-arm table and the stroke-reversal phases (both chambers follow the oil's
//! strain law from their pressures at the reversal until their forces balance, the eye crosses
//! the free play — all of it, none or a quarter, by the rod's net force when the lever turned,
//! see `play_to_cross` — the new chamber compresses to P2 and delivers; a reversal's set-up and
//! force-balance bisection run as small work units over the following steps, see
//! [`REVERSAL_UNITS_PER_STEP`]) → valve/motor flow from the
//! steady valve table, relief flow → P2 and LP predicted through the nodes' capacitance tables →
//! scalar Kalman correction of P2 (gain from a table of the prior variance, innovation gating,
//! reset after a run of rejections) or, without the HP transducer, a correction of P2 by the
//! motor speed read as a pressure (`motor_reading`) → a fixed-gain correction of LP → torque
//! from the chamber pressures and the rods' seal friction → motor speed (Eq. 9 on the load line)
//! and autonomy (table).

use crate::coeffs::{
    Coefficients, CylinderCoeffs, N_ARM, TRACKER_STARTUP, TRACKER_STARTUP_MAX,
    tracker_startup_gains,
};
use crate::fx::{
    Angle, AngularSpeed, Aperture, Flow, Fx, ONE, Pressure, PressureVariance, QMul, Rpm, Seconds,
    Torque, ZERO, clamp, mul_bounded, mul_dt, mul_frac, mul_q24, recip, shr64, sqrt0,
};
use crate::table::Table1;

/// Fault flags (bit set).
pub mod fault {
    /// HP transducer reading missing or outside its range (wire break reads below range).
    pub const HP_SENSOR: u16 = 1 << 0;
    /// LP transducer reading missing or outside its range.
    pub const LP_SENSOR: u16 = 1 << 1;
    /// Encoder reading missing.
    pub const ENCODER: u16 = 1 << 2;
    /// Motor speed reading missing or outside its range.
    pub const MOTOR_SENSOR: u16 = 1 << 3;
    /// HP innovation outside the gate (reading rejected this step).
    pub const INNOVATION: u16 = 1 << 4;
    /// HP innovation rejected for the whole reset window: estimate reset to the reading.
    pub const INNOVATION_RESET: u16 = 1 << 5;
    /// P2 (estimated or measured) above the trip pressure.
    pub const OVERPRESSURE: u16 = 1 << 6;
    /// Encoder static for 2 s while the HP reading rises by more than 1 bar: shaft moving.
    pub const ENCODER_STUCK: u16 = 1 << 7;
    /// Configuration index out of range (step ignored the duty mask).
    pub const BAD_CONFIG: u16 = 1 << 8;
    /// The motor speed contradicts the model: it turns behind a valve that has been closed for
    /// longer than the rotor takes to spin down, or, without the HP transducer, it reads a flow
    /// the valve could not pass at the modelled aperture with P2 at the relief (P2 is then not
    /// moved by it).
    pub const MOTOR_IMPLAUSIBLE: u16 = 1 << 9;
}

/// Sensor readings of one step. `None` = missing (the firmware also maps out-of-range raw
/// readings to `None`; the estimator range-checks what it gets as well).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "protocol", derive(postcard_schema::Schema))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Inputs {
    /// Shaft encoder count (quadrature-decoded, 0 at the neutral angle).
    pub encoder: Option<i32>,
    /// HP transducer.
    pub hp: Option<Pressure>,
    /// LP transducer.
    pub lp: Option<Pressure>,
    /// Motor speed sensor.
    pub motor: Option<Rpm>,
    /// Aperture commanded to the valve this step.
    pub aperture_cmd: Aperture,
    /// Cylinders on duty, bit i = HC3.(i+1).
    pub on_duty: u8,
    /// Geometry, 0..=3 = Config 1..4.
    pub config: u8,
}

/// What the estimator reports each step.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "protocol", derive(postcard_schema::Schema))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Estimate {
    /// Estimated P2.
    pub p2: Pressure,
    /// Its variance (the filter's own uncertainty figure; [`Estimate::p2_sigma`] is the standard
    /// deviation, taken on demand so that the step needs no square root).
    pub p2_var: PressureVariance,
    /// Estimated LP.
    pub lp: Pressure,
    /// Shaft angle.
    pub theta: Angle,
    /// Shaft speed.
    pub omega: AngularSpeed,
    /// Flow delivered into HP by the pump.
    pub q_pump: Flow,
    /// Pump flow averaged over ≈ one wave period.
    pub q_pump_mean: Flow,
    /// Control valve (= motor) flow.
    pub q_valve: Flow,
    /// Relief flow.
    pub q_relief: Flow,
    /// Restraining torque at the shaft.
    pub torque: Torque,
    /// Per cylinder.
    pub torque_cyl: [Torque; 4],
    /// Predicted motor speed (Eq. 9).
    pub motor_rpm: Rpm,
    /// Time the motor stays above the minimum speed if the input stops now.
    pub autonomy: Seconds,
    /// Effective spool aperture.
    pub aperture: Aperture,
    /// [`fault`] bits.
    pub faults: u16,
    /// Background work units the estimator spent this step: stroke-reversal units (up to
    /// [`REVERSAL_UNITS_PER_STEP`]) or, in a step without them, one for the autonomy refresh
    /// (every [`AUTONOMY_EVERY`]th step). The step's background slot: the scheduler refreshes
    /// its feed-forward only in a step that spent none, so no two of them add up in one step.
    pub background_units: u8,
    /// The HP accumulator is empty: the P2 estimate is below its precharge plus
    /// `ModelConfig::hp_empty_margin_bar` (the node is then the stiff oil of the lines alone,
    /// or about to be, where a small flow error moves P2 by bars).
    pub hp_empty: bool,
}

impl Estimate {
    /// Standard deviation of P2 (a square root: for display and telemetry, not the step).
    pub fn p2_sigma(&self) -> Pressure {
        Pressure(sqrt0(self.p2_var.0))
    }
}

/// Per-cylinder state.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct CylState {
    /// Direction of the rod: 1 extending, −1 retracting, 0 unknown.
    pub dir: i8,
    /// The last reversal started from rest (both chambers at LP).
    pub from_rest: bool,
    /// The free play this stroke crosses, mm: the configured play, 0 when the rod stays on one
    /// end of it, a quarter of it when the rod floated (see `play_to_cross`).
    pub play: Fx,
    /// Reversal set-up units still to run ([`SETUP_UNITS`] after a reversal, then 0).
    pub setup_left: u8,
    /// Force-balance bisection iterations still to run.
    pub bisect_left: u8,
    /// Eye travel since the last reversal, mm (stops counting once delivering).
    pub travel: Fx,
    /// Length of the new delivering chamber (dead volume + chamber at the reversal), mm.
    pub len_n: Fx,
    /// Length of the old (now sucking) chamber, mm.
    pub len_o: Fx,
    /// This stroke's milli-strain per mm of rod travel, new delivering chamber.
    pub ms_per_mm_n: Fx,
    /// Same for the old (now sucking) chamber.
    pub ms_per_mm_o: Fx,
    /// Milli-strain of the new chamber at the reversal (LP − drop).
    pub ms_new0: Fx,
    /// Milli-strain of the old chamber at the reversal (P2 + drop).
    pub ms_old0: Fx,
    /// Rod travel at which the chamber forces balance, mm (the bisection's lower bracket while
    /// it runs).
    pub u_bal: Fx,
    /// Upper bracket of the force balance while the bisection runs, mm.
    pub u_bal_hi: Fx,
    /// Rod travel at which the new chamber reaches P2 and delivers, mm.
    pub u_end: Fx,
    /// Rod travel at which the old chamber reaches LP and sucks, mm.
    pub u_suc: Fx,
    /// Cap-chamber pressure of the last step, bar.
    pub p_cap: Fx,
    /// Rod-chamber pressure of the last step, bar.
    pub p_rod: Fx,
}

/// Set-up units of a stroke reversal: (1) the chamber lengths and the new chamber's strain rate,
/// (2) the old chamber's, (3) the start strains, (4) the travels to delivery and suction and the
/// bisection bracket — each at most two table lookups or one reciprocal.
pub const SETUP_UNITS: u8 = 4;
/// Iterations of the force-balance bisection (its bracket shrinks 4096-fold: ≈ 2 µm on a 10 mm
/// stroke build-up).
pub const BISECT_ITERATIONS: u8 = 12;
/// Reversal work units per step, shared by all cylinders in order (HC3.1 first). A reversal
/// needs [`SETUP_UNITS`] + [`BISECT_ITERATIONS`] = 16 units (one bisection iteration each), so
/// with all four cylinders reversing in one step the last one is done 64 steps (63 ms at
/// 2^−10 s) later; the rod has then moved ≈ 0.04 mm of a several-mm build-up (a 0.1 Hz, ±24°
/// swing). While a set-up waits, its chambers hold their pressures and pass no flow; while the
/// bisection runs, the rod follows the lever up to the bracket's upper end. Spreading the work
/// keeps every step's cost flat: a reversal on all cylinders at once cost ≈ 7 000 instructions
/// in one step.
pub const REVERSAL_UNITS_PER_STEP: u8 = 1;

/// Steps between autonomy refreshes (8 ms at 2^−10 s; more while reversals hold the slot).
pub const AUTONOMY_EVERY: u8 = 8;

/// Estimator state (352 bytes together with the scheduler's; `pto model-cost` prints it).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct State {
    /// Shaft angle estimate, rad, Q32.32.
    pub theta_q32: i64,
    /// Shaft speed estimate, rad/s, Q32.32.
    pub omega_q32: i64,
    /// Shaft acceleration estimate, rad/s², Q32.32.
    pub accel_q32: i64,
    /// The tracker's phase: 0 before its first encoder reading (and after a drop-out), 1
    /// tracking with the fading-memory gains, n + 1 with n start-up steps left
    /// ([`Coefficients::tracker_startup_len`], the expanding-memory gains [`TRACKER_STARTUP`]).
    /// One byte, so that the steady step tests one value.
    pub enc_phase: u8,
    /// Last encoder count.
    pub enc_last: i32,
    /// Steps since the encoder last changed.
    pub enc_still: u16,
    /// HP reading when the encoder last changed, bar.
    pub hp_at_enc_change: Fx,
    /// P2, bar.
    pub p2: Fx,
    /// The 16 bits of P2 below its Q16.16 LSB (units of 2^−32 bar): see `node_step`.
    pub p2_lo: u16,
    /// P2 variance, bar².
    pub var: Fx,
    /// The 16 bits of the P2 variance below its Q16.16 LSB (units of 2^−32 bar²). Near its
    /// steady value (≈ 0.002 bar², 130 LSBs) the Kalman update's shrink (1 − g)·var is ≈ 1 LSB
    /// per step: floored to the LSB, the variance ran 20 % below the f64 model's, its gain with
    /// it, and P2 up to 0.15 bar away from the f64 model where it crosses the precharge.
    pub var_lo: u16,
    /// LP, bar.
    pub lp: Fx,
    /// The 16 bits of LP below its Q16.16 LSB (units of 2^−32 bar).
    pub lp_lo: u16,
    /// Effective spool aperture, %.
    pub aperture: Fx,
    /// Valve/motor flow, L/min: the rotor's speed as the flow it passes (it lags the steady
    /// flow of the pressure across the branch by the rotor's inertia).
    pub q_motor: Fx,
    /// The 16 bits of the valve/motor flow below its Q16.16 LSB.
    pub q_motor_lo: u16,
    /// The first step has run: it set the spool to the command and the valve/motor flow to its
    /// steady value.
    pub started: bool,
    /// Autonomy at the last refresh, s.
    pub autonomy: Fx,
    /// Steps since the last autonomy refresh (wraps).
    pub autonomy_tick: u8,
    /// Averaged pump flow, L/min.
    pub q_mean: Fx,
    /// Cylinders.
    pub cyl: [CylState; 4],
    /// Consecutive rejected HP readings.
    pub rejected: u16,
    /// Measured motor flow (speed / rpm per L/min), low-passed, L/min (the motor reading, used
    /// without the HP transducer: see `estimator::motor_reading`).
    pub q_meas: Fx,
    /// LP + F(measured motor flow), low-passed, bar.
    pub f_meas: Fx,
    /// The motor reading's step: odd (the guards, F and both filters) or even (P2's
    /// correction).
    pub meas_odd: bool,
    /// The reading's dead band as of the last odd step, bar.
    pub meas_band: Fx,
    /// `q_meas` and `f_meas` follow the motor sensor. They run while the HP reading is missing,
    /// the spool stands at its command and the valve is open enough, and restart from the
    /// sensor after any of these changes.
    pub meas_live: bool,
    /// Correction steps the reading still waits before P2 takes it: set to
    /// [`Coefficients::motor_reading_warm_steps`] while the spool moves or the valve is near
    /// closed (the rotor may then be accelerating, which filters started from one sample do not
    /// know yet).
    pub meas_wait: u16,
    /// Variance of the motor reading as of the last odd step, bar²: its noise and its dead
    /// band (an error spread evenly over ±band: band²/3). P2's variance relaxes toward it as
    /// the reading corrects P2.
    pub meas_var: Fx,
    /// Consecutive steps with the valve closed (commanded or modelled aperture below
    /// `Coefficients::motor_reading_min_aperture`).
    pub closed_steps: u16,
}

impl State {
    /// A state starting from known pressures (bar, held to [`P_MIN`, `P_MAX`] like every
    /// pressure state) with the given P2 standard deviation.
    pub fn new(p2: Pressure, lp: Pressure, sigma: Pressure) -> Self {
        State {
            p2: clamp(p2.0, P_MIN, P_MAX),
            lp: clamp(lp.0, P_MIN, P_MAX),
            var: sigma.0.qmul(sigma.0),
            ..State::default()
        }
    }
}

/// [`State::enc_phase`] before the tracker's first encoder reading.
const ENC_UNSEEN: u8 = 0;
/// [`State::enc_phase`] once the fading-memory gains track the shaft.
const ENC_TRACKING: u8 = 1;

/// Lower end of the pressure states' range (P2, LP), bar: vacuum.
pub const P_MIN: Fx = Fx::from_bits(-65_536);
/// Upper end of the pressure states' range (P2, LP), bar.
pub const P_MAX: Fx = Fx::from_bits(400 << 16);
const FLOW_LIM: Fx = Fx::from_bits(1000 << 16);
const THETA_LIM_Q32: i64 = 1 << 61;
const OMEGA_LIM_Q32: i64 = 100 << 32;
const ACCEL_LIM_Q32: i64 = 1000 << 32;

/// A pressure node's value to 2^−32 bar (Q16.32 in an `i64`): its Q16.16 value and the 16 bits
/// below that.
#[inline]
fn ext(p: Fx, lo: u16) -> i64 {
    (i64::from(p.to_bits()) << 16) | i64::from(lo)
}

/// Splits a Q16.32 node value back into its Q16.16 value and the 16 bits below.
#[inline]
fn split(e: i64) -> (Fx, u16) {
    (Fx::from_bits((e >> 16) as i32), e as u16)
}

/// One explicit step of a pressure node: p += net inflow (L/min, clamped) × dP/dV × dt, held
/// inside the physical pressure range.
///
/// The node keeps 16 bits below the Q16.16 LSB (`lo`): a step's change is often only a few
/// LSBs (LP at 2 L/min: 1.3 · 10^−5 bar = 0.8 LSB per 2^−10 s step; the LP observer's correction
/// ≈ 10^−6 bar), and rounding it to 2^−16 bar every step drifts the node systematically —
/// the LP estimate ran 0.3 bar away from the f64 model in a Test II run, and P2 up to 1 bar
/// where it crosses the precharge. The product q × dP/dV is exact in Q32.32 (|q| ≤ 1000 L/min
/// < 2^26 bits, dP/dV < 2^31 bits: < 2^57) and × dt is a shift, so the node only truncates
/// below 2^−32 bar.
#[inline]
fn node_step(p: &mut Fx, lo: &mut u16, net_inflow: Fx, dp_per_flow: Fx, dtl: u8) {
    let q = clamp(net_inflow, -FLOW_LIM, FLOW_LIM);
    let d = shr64(
        i64::from(q.to_bits()) * i64::from(dp_per_flow.to_bits()),
        u32::from(dtl),
    );
    (*p, *lo) = split((ext(*p, *lo) + d).clamp(ext(P_MIN, 0), ext(P_MAX, 0)));
}

/// x += g·(target − x) with g ∈ [0, 1], x kept to 16 bits below its Q16.16 LSB like
/// [`node_step`]: the Q16.16 product g·(target − x) is exact in Q32.32. The result lies between
/// x and the target, so it needs no clamp (the difference of two values in range must not
/// overflow: both are held to a physical range well inside ±2^15).
#[inline]
fn relax(x: &mut Fx, lo: &mut u16, g: Fx, target: Fx) {
    let d = target - *x;
    (*x, *lo) = split(ext(*x, *lo) + i64::from(g.to_bits()) * i64::from(d.to_bits()));
}

/// An observer correction p += g·(z − p) with g ∈ [0, 1] ([`relax`]). The reading is first held
/// to the physical pressure range (a transducer's accepted range may reach past it, e.g.
/// −2 bar), so the result, between p and that, stays inside it.
#[inline]
fn correct(p: &mut Fx, lo: &mut u16, g: Fx, z: Fx) {
    relax(p, lo, g, clamp(z, P_MIN, P_MAX));
}

/// Advances the estimator by one step. Cannot fail; every reading may be missing or wrong.
pub fn step(k: &Coefficients, s: &mut State, inp: &Inputs) -> Estimate {
    let dtl = k.dt_log2;
    let mut faults = 0u16;
    // --- Shaft: α–β–γ tracker on the encoder angle, in Q32.32 (i64).
    // Bit budget: one count is < 2^29 (≥ 64 counts per revolution, validated), so a measured
    // angle is < 2^60 in magnitude; θ is held to ±2^61, ω to ±100 rad/s (< 2^39) and the
    // acceleration to ±1000 rad/s² (< 2^42); the residual is clamped to ±0.5 rad (2^31) and every
    // gain is < 2^31 (< 2^29 at the validated extremes of bandwidth and dt). No sum or product
    // below can leave i64, so the 64-bit saturating forms (≈ 8 instructions each on a 32-bit
    // core) are not needed. Plain operators: the test builds' overflow checks (and the property
    // tests' extreme inputs) verify this budget; the release build emits the same code.
    // The run-time shifts by dt (1..=25 bits) go through the two-word `shr64`.
    let n = u32::from(dtl);
    let half = k.round_dt_q32;
    let pred_theta = s.theta_q32
        + shr64(s.omega_q32 + half, n)
        + shr64(s.accel_q32 + k.round_dt2_q32, 2 * n + 1);
    let pred_omega = s.omega_q32 + shr64(s.accel_q32 + half, n);
    match inp.encoder {
        Some(count) => {
            let theta_meas = i64::from(count) * i64::from(k.rad_per_count_q32);
            if s.enc_phase == ENC_TRACKING {
                // The residual held to ±0.5 rad fits an i32, so each gain product is one
                // 32 × 32 → 64 multiply.
                let r = residual(theta_meas, pred_theta);
                s.theta_q32 = (pred_theta + ((r * i64::from(k.alpha_q31) + (1 << 30)) >> 31))
                    .clamp(-THETA_LIM_Q32, THETA_LIM_Q32);
                s.omega_q32 = (pred_omega
                    + ((r * i64::from(k.beta_over_dt_q16) + (1 << 15)) >> 16))
                    .clamp(-OMEGA_LIM_Q32, OMEGA_LIM_Q32);
                s.accel_q32 = (s.accel_q32
                    + ((r * i64::from(k.gamma_over_dt2_q16) + (1 << 15)) >> 16))
                    .clamp(-ACCEL_LIM_Q32, ACCEL_LIM_Q32);
            } else {
                tracker_startup(s, k, theta_meas, count, inp.hp);
            }
            if count != s.enc_last {
                s.enc_last = count;
                s.enc_still = 0;
                s.hp_at_enc_change = inp.hp.map_or(s.p2, |p| p.0);
            } else {
                s.enc_still = s.enc_still.saturating_add(1);
                if s.enc_still >= k.stuck_steps
                    && inp
                        .hp
                        .is_some_and(|p| p.0.saturating_sub(s.hp_at_enc_change) > ONE)
                {
                    faults |= fault::ENCODER_STUCK;
                }
            }
        }
        None => {
            // No reading: assume the input has stopped (the safe side for autonomy); the next
            // reading starts the tracker afresh, start-up gains and all (the shaft may have
            // turned and changed speed meanwhile).
            faults |= fault::ENCODER;
            s.theta_q32 = pred_theta;
            s.omega_q32 = 0;
            s.accel_q32 = 0;
            s.enc_phase = ENC_UNSEEN;
        }
    }
    let theta = Fx::from_bits(
        ((s.theta_q32 + (1 << 15)) >> 16).clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32,
    );
    let omega = Fx::from_bits(((s.omega_q32 + (1 << 15)) >> 16) as i32);
    // --- Spool lag.
    // The first step takes the spool as settled at the command and the valve/motor flow at its
    // steady value (a state started from known pressures is a bench at rest or in steady
    // running, not a valve or a rotor half way through a change).
    let first = !s.started;
    s.started = true;
    let cmd = clamp(inp.aperture_cmd.0, ZERO, Fx::from_num(100));
    if first {
        s.aperture = cmd;
    } else {
        s.aperture = s
            .aperture
            .saturating_add(mul_frac(k.spool_gain, cmd.saturating_sub(s.aperture)));
    }
    // --- Cylinders: delivered flow, suction flow, torque.
    let config = usize::from(inp.config);
    let (arm_table, ext_table, duty) = match (k.arm.get(config), k.ext.get(config)) {
        (Some(a), Some(e)) => (a, e, inp.on_duty),
        _ => {
            faults |= fault::BAD_CONFIG;
            (&k.arm[0], &k.ext[0], 0)
        }
    };
    let mut torque_cyl = [Torque::ZERO; 4];
    let mut torque = ZERO;
    let mut sh = Shared {
        k,
        ext: ext_table,
        lp: s.lp,
        lo: s.lp.saturating_sub(k.check_drop),
        hi: s.p2.saturating_add(k.check_drop),
        budget: REVERSAL_UNITS_PER_STEP,
        q_pump: ZERO,
        q_lp: ZERO,
    };
    // The lever on each side of the shaft (s = ±1): the arm tables are per geometry, so every
    // cylinder on one side shares s·θ, the signed arm s·d and the rod speed v = s·d·θ̇ (mm/s).
    // The shaft speed to 2^−24 rad/s for the rod speed: in Q16.16 its LSB is 6·10^−5 of a
    // 0.26 rad/s swing, and the pump flow on the empty HP node (≈ 0.18 bar per L/min a step)
    // took that as a P2 LSB a step. |ω| ≤ 100 rad/s (`OMEGA_LIM_Q32`) is < 2^31 in Q8.24, so
    // it is one word; times an arm (< 2^31 bits) < 2^62; the rod speed is held to the Q16.16
    // range.
    let omega24 = ((s.omega_q32 + (1 << 7)) >> 8) as i32;
    let lever = |th: Fx, negative: bool| {
        let d = arm_table.at(th);
        let sd = if negative { d.saturating_neg() } else { d };
        let v = mul_q24(sd, omega24);
        Lever {
            th,
            sd,
            v,
            seal: sd.qmul(v.qmul(k.seal_kn_per_mm_s)),
        }
    };
    let levers = [lever(theta, false), lever(theta.saturating_neg(), true)];
    for (i, (c, cs)) in k.cyl.iter().zip(s.cyl.iter_mut()).enumerate() {
        let on = duty & (1 << i) != 0;
        let lv = &levers[usize::from(c.side < ZERO)];
        let t = cylinder(&mut sh, c, cs, lv, on);
        torque_cyl[i] = Torque(t);
        torque = torque.saturating_add(t);
    }
    let (q_pump, q_lp_net) = (sh.q_pump, sh.q_lp);
    let mut background_units = REVERSAL_UNITS_PER_STEP - sh.budget;
    // --- Valve, relief, motor.
    // The rotor's inertia: L·dQ/dt = ΔP − F(Q) with F the branch's steady pressure drop
    // (`ModelConfig::motor_inductance`). F(Q_ss) = ΔP, and F(Q_ss) − F(Q) = (Q_ss − Q)·(β +
    // (Q_ss + Q)/K²) exactly for the turbulent valve, so one explicit step is a relaxation
    // toward the steady flow with gain dt/L·(β + (Q_ss + Q)/K²). Held to 1 (where the valve's
    // resistance makes the branch faster than a step, e.g. near closed), the flow takes its
    // steady value: it never overshoots, so the step is stable at every aperture.
    let dp = s.p2.saturating_sub(s.lp).max(ZERO);
    let lp_dp = s.lp.saturating_add(dp);
    let (q_ss, gain_valve) = k.valve_flow.at_with(s.aperture, dp, &k.motor_gain_valve);
    if first {
        (s.q_motor, s.q_motor_lo) = (q_ss, 0);
    }
    let g = k
        .motor_gain0
        .saturating_add(q_ss.saturating_add(s.q_motor).qmul(gain_valve))
        .min(ONE);
    relax(&mut s.q_motor, &mut s.q_motor_lo, g, q_ss);
    let motor_rpm = s.q_motor.qmul(k.rpm_per_lpm);
    // A coasting rotor that outruns the pressure across it (P2 down to LP: an empty HP node
    // when the pump stops) draws the rest through the make-up valve from LP, not from HP.
    let q_valve = if dp > ZERO { s.q_motor } else { ZERO };
    let q_relief =
        s.p2.saturating_sub(k.relief_setting)
            .max(ZERO)
            .qmul(k.relief_gain);
    // --- Predict.
    let net_hp = q_pump.saturating_sub(q_valve).saturating_sub(q_relief);
    let dp_per_flow = k.inv_c_hp.at(s.p2);
    node_step(&mut s.p2, &mut s.p2_lo, net_hp, dp_per_flow, dtl);
    let net_lp = q_valve.saturating_add(q_relief).saturating_sub(q_lp_net);
    let dp_per_flow = k.inv_c_lp.at(s.lp);
    node_step(&mut s.lp, &mut s.lp_lo, net_lp, dp_per_flow, dtl);
    // The process noise to 2^−32 bar² (`Table1::at_ext`): on the empty node it is ≈ 0.08 bar²
    // a step, and its Q16.16 rounding moved the Kalman gain by 3·10^−5 — a few P2 LSBs per
    // bar of innovation. Held below the variance's Q16.16 top.
    (s.var, s.var_lo) = split((ext(s.var, s.var_lo) + k.q_step.at_ext(s.p2)).min(ext(Fx::MAX, 0)));
    s.q_mean = s
        .q_mean
        .saturating_add(mul_frac(k.mean_gain, q_pump.saturating_sub(s.q_mean)));
    // --- Correct P2 with the HP transducer.
    let hp = inp
        .hp
        .map(|p| p.0)
        .filter(|p| *p >= k.hp_range.0 && *p <= k.hp_range.1);
    let motor = inp.motor.filter(|m| m.0 >= ZERO && m.0 <= k.motor_max);
    // The valve closed (commanded or modelled): the branch's flow says nothing of P2, and once
    // the rotor has had the time to spin down a turning motor contradicts the model.
    let closed = cmd < k.motor_reading_min_aperture || s.aperture < k.motor_reading_min_aperture;
    if closed {
        s.closed_steps = s.closed_steps.saturating_add(1);
        if s.closed_steps >= k.spin_down_steps
            && motor.is_some_and(|m| m.0 > k.motor_reading_min_rpm)
        {
            faults |= fault::MOTOR_IMPLAUSIBLE;
        }
    } else {
        s.closed_steps = 0;
    }
    match hp {
        Some(z) => {
            // On the relief P2 is set by the reduced relief law, whose bias the filter must take
            // from the transducer (`ModelConfig::relief_process_noise_bar_per_sqrt_s`).
            if s.p2 >= k.relief_setting {
                s.var = s.var.saturating_add(k.q_relief);
            }
            // The motor reading restarts when the transducer goes missing again.
            (s.meas_live, s.meas_wait) = (false, 0);
            let innov = z.saturating_sub(s.p2);
            let s_innov = s.var.saturating_add(k.r);
            if innov.qmul(innov) <= k.gate_sq.qmul(s_innov) {
                // The gain to 2^−32 (`Coefficients::gain_q32`); P2 += g·(z − P2) and
                // var ← (1 − g)·var kept to 2^−32 (see `State::var_lo`). Bit budget: g ≤ 2^32
                // times a Q16.16 value (< 2^31 in magnitude) is < 2^63; P2's bits below the LSB
                // are left out of the innovation (≤ g·2^−16 bar, 0.01 LSB at the steady gain).
                let g = i64::from(k.gain_q32(s.var, s.var_lo));
                let d = clamp(z, P_MIN, P_MAX) - s.p2;
                (s.p2, s.p2_lo) = split(
                    (ext(s.p2, s.p2_lo) + ((g * i64::from(d.to_bits())) >> 16))
                        .clamp(ext(P_MIN, 0), ext(P_MAX, 0)),
                );
                let dv = ((g * i64::from(s.var.to_bits())) >> 16)
                    + ((g * i64::from(i32::from(s.var_lo))) >> 32);
                (s.var, s.var_lo) = split(ext(s.var, s.var_lo) - dv);
                s.rejected = 0;
            } else {
                faults |= fault::INNOVATION;
                // Fading memory: each rejection widens the gate and raises the next gain, so a
                // persistent model error (e.g. a stuck encoder hiding the pump flow) is taken in
                // within a few steps; the ceiling keeps a burst of outliers outside the gate.
                if s.var < k.var_fade_max {
                    s.var = s.var.saturating_add(k.r).min(k.var_fade_max);
                }
                s.rejected = s.rejected.saturating_add(1);
                if s.rejected >= k.gate_reset_steps {
                    faults |= fault::INNOVATION_RESET;
                    (s.p2, s.p2_lo) = (z, 0);
                    (s.var, s.var_lo) = (k.r, 0);
                    s.rejected = 0;
                }
            }
        }
        None => {
            faults |= fault::HP_SENSOR;
            // Without it, correct P2 with the motor speed.
            match motor {
                Some(m) if !closed => faults |= motor_reading(k, s, m.0, cmd, lp_dp, dp, q_ss, g),
                // Closed: no reading; the filters restart once it opens, P2 waiting for them.
                Some(_) => (s.meas_live, s.meas_wait) = (false, k.motor_reading_warm_steps),
                None => (s.meas_live, s.meas_wait) = (false, 0),
            }
            // Within the band above the precharge the accumulator's last cm³ decide when it
            // runs empty, and P2 then falls to the empty node's level (5–15 bar lower) within
            // tens of ms, faster than any reading of the motor follows; on the empty node P2
            // follows the pump flow, and rises back as fast when it refills. P2's standard
            // deviation is at least `ModelConfig::precharge_sigma_bar` in both, after the
            // motor reading has had its say.
            if s.p2 <= k.precharge_band_top && s.var < k.var_precharge {
                (s.var, s.var_lo) = (k.var_precharge, 0);
            }
        }
    }
    // --- Correct LP with a fixed gain.
    match inp
        .lp
        .map(|p| p.0)
        .filter(|p| *p >= k.lp_range.0 && *p <= k.lp_range.1)
    {
        Some(z) => correct(&mut s.lp, &mut s.lp_lo, k.gain_lp, z),
        None => faults |= fault::LP_SENSOR,
    }
    if motor.is_none() {
        faults |= fault::MOTOR_SENSOR;
    }
    if s.p2 > k.trip || hp.is_some_and(|z| z > k.trip) {
        faults |= fault::OVERPRESSURE;
    }
    // Autonomy changes over seconds: it is refreshed in the background slot, every
    // AUTONOMY_EVERY-th step unless a reversal holds the slot (then in the next free step), so
    // its table lookup adds to neither a reversal's work nor the scheduler's feed-forward.
    s.autonomy_tick = s.autonomy_tick.wrapping_add(1);
    if background_units == 0 && s.autonomy_tick >= AUTONOMY_EVERY {
        s.autonomy = k.autonomy.at(s.aperture, s.p2);
        s.autonomy_tick = 0;
        background_units = 1;
    }
    Estimate {
        p2: Pressure(s.p2),
        p2_var: PressureVariance(s.var),
        lp: Pressure(s.lp),
        theta: Angle(theta),
        omega: AngularSpeed(omega),
        q_pump: Flow(q_pump),
        q_pump_mean: Flow(s.q_mean),
        q_valve: Flow(q_valve),
        q_relief: Flow(q_relief),
        torque: Torque(torque),
        torque_cyl,
        motor_rpm: Rpm(motor_rpm),
        autonomy: Seconds(s.autonomy),
        aperture: Aperture(s.aperture),
        faults,
        background_units,
        hp_empty: s.p2 < k.hp_empty_below,
    }
}

/// The tracker's residual, measured less predicted angle (Q32.32), held to ±0.5 rad so that it
/// fits an i32.
#[inline(always)]
fn residual(theta_meas: i64, pred_theta: i64) -> i64 {
    i64::from((theta_meas - pred_theta).clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32)
}

/// The shaft tracker's first reading (it starts there, at rest) and its first
/// [`Coefficients::tracker_startup_len`] updates after it: the expanding-memory gains
/// [`TRACKER_STARTUP`] (the least-squares line through every reading so far), the acceleration
/// held at 0 until the fading-memory tracker takes over. Out of line: the steady step only
/// tests its phase.
#[inline(never)]
#[cold]
fn tracker_startup(
    s: &mut State,
    k: &Coefficients,
    theta_meas: i64,
    count: i32,
    hp: Option<Pressure>,
) {
    if s.enc_phase == ENC_UNSEEN {
        // The first reading: the tracker starts at it, at rest.
        s.theta_q32 = theta_meas;
        s.omega_q32 = 0;
        s.accel_q32 = 0;
        s.enc_phase = k.tracker_startup_len.saturating_add(ENC_TRACKING);
        s.enc_last = count;
        s.hp_at_enc_change = hp.map_or(s.p2, |p| p.0);
        return;
    }
    // The prediction with the acceleration at 0, as it is all through the start-up.
    let pred_theta = s.theta_q32 + shr64(s.omega_q32 + k.round_dt_q32, u32::from(k.dt_log2));
    let pred_omega = s.omega_q32;
    let r = residual(theta_meas, pred_theta);
    // The n-th update since the start, n − 1 the table's index; its length is a power of two,
    // so the masked index cannot leave it.
    let i = usize::from(
        k.tracker_startup_len
            .wrapping_add(ENC_TRACKING)
            .wrapping_sub(s.enc_phase),
    ) & (TRACKER_STARTUP_MAX - 1);
    let (a, b) = tracker_startup_gains(i + 1, TRACKER_STARTUP[i]);
    s.enc_phase = s.enc_phase.saturating_sub(1).max(ENC_TRACKING);
    // β_n/dt in Q16.16: β_n (Q1.31) · 2^dt_log2 / 2^15; dt_log2 ≤ 12 (validated), so the shift
    // is 3..=9 bits and β_n/dt < 2^29 as the fading-memory β/dt.
    let b = b >> (15u8.saturating_sub(k.dt_log2) & 31);
    s.theta_q32 =
        (pred_theta + ((r * i64::from(a) + (1 << 30)) >> 31)).clamp(-THETA_LIM_Q32, THETA_LIM_Q32);
    s.omega_q32 =
        (pred_omega + ((r * i64::from(b) + (1 << 15)) >> 16)).clamp(-OMEGA_LIM_Q32, OMEGA_LIM_Q32);
}

/// P2 read from the motor speed, for a step without the HP transducer.
///
/// The rotor's equation L·dQ/dt = P2 − LP − F(Q) (see the valve/motor step in [`step`]) read
/// backwards: the measured flow Q_m (speed / rpm per L/min) and its rate give
/// P2 = LP + F(Q_m) + L·dQ_m/dt. Both terms are low-passed with the same first-order filter
/// (τ = `ModelConfig::motor_reading_filter_ms`): the rate is that filter's own derivative
/// (Q_m − Q̄)/τ, so the reading is P2 itself low-passed, not a noisy difference of two samples,
/// and F is taken at each step's own aperture and flow before the filter, so the valve's
/// square law and a moving aperture do not bias it. F(Q_m) needs no inverse table: the step's
/// steady flow Q_ss at the model's ΔP satisfies F(Q_ss) = ΔP, and for F(Q) = β·Q + Q²/K²,
/// F(Q_ss) − F(Q_m) = (Q_ss − Q_m)·(β + (Q_ss + Q_m)/K²) ≈ (Q_ss − Q_m)·g·L/dt with g the
/// step's relaxation gain of the valve/motor flow. P2 then moves toward the reading (time
/// constant T = `motor_reading_time_constant_ms`) less a band of `motor_reading_band_pct` of
/// ΔP: the reduced model's motor (Eq. 9 on the load line)
/// is good to 1–2 % of ΔP (its speed's RMS error against the full simulation), so a reading
/// that close is no evidence against the model — at 100 bar, where the model alone drifts by
/// 0.02 bar in a minute, the reading's ≈ 1 bar bias would otherwise set the error.
///
/// Where the accumulator is empty, P2 follows the pump flow within a fraction of a second and
/// a pump-flow error of 1 L/min is ≈ 8 bar of P2; the motor speed is then the best P2 sensor
/// left (Test I with one cylinder: model-only P2 3.2–4.4 → 1.2–1.3 bar). The reading is
/// skipped where it says little: the valve near closed (dF/dQ above
/// `motor_reading_max_slope_bar_per_lpm`), the motor below `motor_reading_min_rpm`; and the
/// filters restart after the spool has moved (the plant's valve and the model's need not open
/// at the same instant, and 1 % of aperture is several bar of valve drop at 100 bar), P2 taking
/// the reading only after three filter time constants. (When the HP reading goes missing the
/// filters start at once: a state started from known pressures has its rotor at steady speed.)
/// The work alternates between two steps (the guards, F and both filters at half rate in one,
/// the correction in the other), so that a step costs about what one with the transducer's
/// Kalman update does.
// The step's own values, passed as they are (inlined into the step: its only caller).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn motor_reading(
    k: &Coefficients,
    s: &mut State,
    rpm: Fx,
    cmd: Fx,
    lp_dp: Fx,
    dp: Fx,
    q_ss: Fx,
    g: Fx,
) -> u16 {
    // 0 ≤ rpm ≤ 10 000 (< 2^30 bits; the caller range-checks it) × L/min per rpm (< 2^31
    // bits): < 2^61; held to the flow range like every flow the nodes take.
    let q_m = Fx::from_bits(
        ((i64::from(rpm.to_bits()) * i64::from(k.lpm_per_rpm_q24) + (1 << 23)) >> 24)
            .min(i64::from(FLOW_LIM.to_bits())) as i32,
    );
    if !s.meas_live {
        s.q_meas = q_m;
        s.f_meas = lp_plus_f(lp_dp, q_ss, q_m, mul_bounded(g, k.motor_reading_ldt));
        (s.meas_live, s.meas_odd) = (true, false);
        return 0;
    }
    // The work alternates between two steps, each filter running at half rate, so that a
    // step costs about what the HP transducer's Kalman update it replaces does: the guards, F
    // and both filters in one, P2's correction in the other.
    s.meas_odd = !s.meas_odd;
    if s.meas_odd {
        // dF/dQ = g·L/dt: g ≤ 1 and L/dt < 2^15 bar per L/min (a saturated coefficient), so
        // the product fits.
        // Plausibility: the flow read must be one the valve can pass at the modelled aperture
        // and LP with P2 at most at the relief (plus the gate's worth of the reading's noise)
        // — the valve table at that ΔP, plus the reading's band and the sensor's floor. A
        // faster motor contradicts the model (or the sensor is wrong): flagged, and the
        // reading restarts, so P2 never takes it.
        let q_cap = k
            .valve_flow
            .at(s.aperture, k.motor_reading_p2_max.saturating_sub(s.lp));
        let q_cap = q_cap
            .saturating_add(mul_bounded(q_cap, k.motor_reading_band))
            .saturating_add(k.motor_reading_min_lpm);
        if q_m > q_cap {
            (s.meas_live, s.meas_wait) = (false, k.motor_reading_warm_steps);
            return fault::MOTOR_IMPLAUSIBLE;
        }
        let slope = mul_bounded(g, k.motor_reading_ldt);
        if slope > k.motor_reading_max_slope
            || cmd.saturating_sub(s.aperture).abs() > k.motor_reading_spool_tol
        {
            // The valve near closed, or the spool moving: no reading; the filters restart
            // once both end, and P2 takes the reading after they have run a while.
            (s.meas_live, s.meas_wait) = (false, k.motor_reading_warm_steps);
            return 0;
        }
        let f = lp_plus_f(lp_dp, q_ss, q_m, slope);
        s.f_meas = filter(s.f_meas, k.motor_reading_filter, f);
        // The derivative L·(Q_m − Q̄)/τ of the next step takes Q̄ as of this one.
        s.q_meas = filter(s.q_meas, k.motor_reading_filter, q_m);
        // ΔP ≤ 400 bar × a band ≤ 0.5: fits.
        s.meas_band = mul_bounded(dp, k.motor_reading_band);
        // band²/3 saturates above a 181 bar band: far beyond any P2 gate.
        s.meas_var = s
            .meas_band
            .qmul(s.meas_band)
            .qmul(ONE_THIRD)
            .saturating_add(k.motor_reading_r);
        return 0;
    }
    if s.meas_wait > 0 {
        s.meas_wait -= 1;
    } else if q_m >= k.motor_reading_min_lpm {
        let z = s
            .f_meas
            .saturating_add(q_m.saturating_sub(s.q_meas).qmul(k.motor_reading_lt));
        // Only the part of the innovation beyond the band counts: inside it the reading does
        // not know P2 better than the model does.
        let e = z.saturating_sub(s.p2);
        let e = e - clamp(e, -s.meas_band, s.meas_band);
        // Plausibility: the flow read must be one the valve can pass at a P2 the relief allows,
        // i.e. the P2 it implies, less its band, at most the relief setting plus the gate's
        // worth of the reading's noise (F is monotone in the flow, so this is the valve's
        // capacity at the modelled aperture and LP without a table lookup). Beyond it the
        // speed sensor or the model is wrong: flagged, P2 not moved. (A gate on the distance
        // to P2 itself would refuse the readings the empty HP node needs most: there the
        // model can run empty 0.1 s before the bench, 17 bar below it.)
        if z.saturating_sub(s.meas_band) > k.motor_reading_p2_max {
            return fault::MOTOR_IMPLAUSIBLE;
        }
        // P2 += gain·e, exact in Q32.32 (|e| < 2^31 bits × gain ≤ 2^16 bits: < 2^47) and kept
        // to 2^−32 like the node's prediction (rounded to the LSB it was half an LSB a step
        // from its f64 form), held to the pressure range.
        (s.p2, s.p2_lo) = split(
            (ext(s.p2, s.p2_lo)
                + i64::from(k.motor_reading_gain.to_bits()) * i64::from(e.to_bits()))
            .clamp(ext(P_MIN, 0), ext(P_MAX, 0)),
        );
        // The reading brings P2's variance toward its own (never up to it).
        if s.var > s.meas_var {
            relax(&mut s.var, &mut s.var_lo, k.motor_reading_gain, s.meas_var);
        }
    }
    0
}

/// 1/3 in Q16.16.
const ONE_THIRD: Fx = Fx::from_bits(21_845);

/// LP + F(Q_m), bar, from F(Q_ss) = ΔP: F(Q_ss) − F(Q_m) = (Q_ss − Q_m)·dF/dQ.
#[inline(always)]
fn lp_plus_f(lp_dp: Fx, q_ss: Fx, q_m: Fx, slope: Fx) -> Fx {
    clamp(
        lp_dp.saturating_sub(slope.qmul(q_ss.saturating_sub(q_m))),
        P_MIN,
        P_MAX,
    )
}

/// One step of a first-order filter x += a·(target − x), the product rounded to the nearest
/// LSB (unbiased on a noisy input, where flooring it would offset x by half an LSB per step
/// over the filter's 1/a steps; the filters follow noisy readings, so no bits below the LSB
/// are kept). Both values lie in a physical range well inside ±2^15, a ∈ [0, 1].
#[inline(always)]
fn filter(x: Fx, a: Fx, target: Fx) -> Fx {
    let d = (i64::from(a.to_bits()) * i64::from((target - x).to_bits()) + (1 << 15)) >> 16;
    x + Fx::from_bits(d as i32)
}

/// Pressures of the new (compressing) and old (relaxing) chambers after `u` mm of rod travel
/// since the reversal, bar: the strain moves by u·(strain per mm) from its value at the reversal.
#[inline]
fn p_new_at(k: &Coefficients, cs: &CylState, u: Fx, lo: Fx, hi: Fx) -> Fx {
    p_at_strain(k, cs.ms_new0.saturating_add(u.qmul(cs.ms_per_mm_n)), lo, hi)
}

#[inline]
fn p_old_at(k: &Coefficients, cs: &CylState, u: Fx, lo: Fx, hi: Fx) -> Fx {
    p_at_strain(k, cs.ms_old0.saturating_sub(u.qmul(cs.ms_per_mm_o)), lo, hi)
}

/// Oil pressure at a milli-strain, held between the check valves' limits.
#[inline]
fn p_at_strain(k: &Coefficients, ms: Fx, lo: Fx, hi: Fx) -> Fx {
    clamp(k.p_of_ms.at(ms), lo, hi)
}

/// `a·b/1000` for a milli-strain `a` and a length `b` in mm (a travel in mm), without a
/// division: the Q32.32 product times 2^32/1000 (relative error 7e-8), saturated.
#[inline]
fn ms_times_mm(a: Fx, b: Fx) -> Fx {
    let p = (i64::from(a.to_bits()) * i64::from(b.to_bits())) >> 16; // Q16.16, |p| < 2^47
    let p = p.clamp(-(1i64 << 31), 1i64 << 31);
    Fx::from_bits(((p * 4_294_967 + (1i64 << 31)) >> 32) as i32)
}

/// The lever on one side of the shaft this step.
struct Lever {
    /// s·θ, rad.
    th: Fx,
    /// s·d: the signed lever arm, mm.
    sd: Fx,
    /// Rod speed s·d·θ̇, mm/s.
    v: Fx,
    /// Restraining torque of a rod's seal friction, N·m: s·d·c·v.
    seal: Fx,
}

/// What the cylinders of one step share.
struct Shared<'a> {
    k: &'a Coefficients,
    /// Rod-eye extension table of the geometry on duty.
    ext: &'a Table1<N_ARM>,
    /// LP, bar.
    lp: Fx,
    /// LP less the check valve's drop: a chamber at it sucks, bar.
    lo: Fx,
    /// P2 plus the check valve's drop: a chamber at it delivers, bar.
    hi: Fx,
    /// Reversal work units left this step.
    budget: u8,
    /// Flow the cylinders deliver into HP so far, L/min.
    q_pump: Fx,
    /// Flow the cylinders take from LP so far (suction − idle bypass return), L/min.
    q_lp: Fx,
}

/// One unit of a cylinder's pending reversal work (see [`REVERSAL_UNITS_PER_STEP`]).
#[inline(never)]
fn reversal_unit(sh: &Shared, c: &CylinderCoeffs, cs: &mut CylState, th: Fx) {
    let (k, lo, hi) = (sh.k, sh.lo, sh.hi);
    if cs.setup_left == 0 {
        // Force balance A_o·p_old(u) = A_n·p_new(u) (p_old falls, p_new rises): bisection.
        let ratio = area_ratio(c, cs.dir);
        let m = Fx::from_bits((cs.u_bal.to_bits() + cs.u_bal_hi.to_bits()) >> 1);
        let (pn, po) = (p_new_at(k, cs, m, lo, hi), p_old_at(k, cs, m, lo, hi));
        if po.saturating_sub(ratio.qmul(pn)) > ZERO {
            cs.u_bal = m;
        } else {
            cs.u_bal_hi = m;
        }
        cs.bisect_left -= 1;
        if cs.bisect_left == 0 {
            if cs.from_rest {
                // From rest both chambers start at LP and the eye sits in the middle of its free
                // play. Where their forces push the rod the new way (an extension: LP on the
                // larger cap side) it floats ahead to the balance u_bal as the lever starts, and
                // the eye meets it after u_bal + half the play: the eye's travel counts from
                // half the play, the rod held at u_bal until the eye arrives (counting from
                // u_bal + half, as before, met it u_bal early: Test I with HC3.1 started 1.4
                // bar off instead of 0.8). Against the stroke (a retraction: no balance) the
                // rod floated back by the extension's balance, which is not computed here: the
                // eye crosses half the play (≈ 0.2 mm too much for HC3.4 in Config 1, whose
                // model-only start is then 1.6 bar off, not the run's largest error).
                cs.travel = cs.travel.saturating_add(k.play_mm >> 1u32);
            } else if cs.u_bal_hi == cs.u_end.max(cs.u_suc) {
                // No balance up to full build-up: the old chamber's force still drives the rod
                // ahead of the eye once both chambers are at P2 and LP, so it stays there.
                cs.play = ZERO;
            }
        }
        return;
    }
    if cs.setup_left == SETUP_UNITS {
        // (1) Chamber lengths at the rod's position and the new chamber's strain per mm: a
        // chamber of length L (dead volume + chamber) moved by u changes its strain by u/L.
        // 1000/L is taken as (1024/L)·(1000/1024) so the reciprocal keeps 1e-5 precision.
        let pos = sh.ext.at(th);
        let l_cap = c.dead_cap_mm.saturating_add(pos);
        let l_rod = c
            .dead_rod_mm
            .saturating_add(c.stroke_mm.saturating_sub(pos));
        (cs.len_n, cs.len_o) = if cs.dir >= 0 {
            (l_rod, l_cap)
        } else {
            (l_cap, l_rod)
        };
        cs.ms_per_mm_n = recip(Fx::from_bits(cs.len_n.to_bits() >> 10)).qmul(KMS);
    } else if cs.setup_left == SETUP_UNITS - 1 {
        // (2) The old chamber's strain per mm, and the play the eye has to cross.
        cs.ms_per_mm_o = recip(Fx::from_bits(cs.len_o.to_bits() >> 10)).qmul(KMS);
        if !cs.from_rest {
            cs.play = play_to_cross(k, c, cs, lo, hi);
        }
    } else if cs.setup_left == SETUP_UNITS - 2 {
        // (3) Start from the chambers' pressures at the reversal (held since), not from P2/LP:
        // in an irregular sea the shaft can turn back before a stroke has built up.
        let (p_new0, p_old0) = held_pressures(cs, lo, hi);
        cs.ms_new0 = k.ms_of_p.at(p_new0);
        cs.ms_old0 = k.ms_of_p.at(p_old0);
    } else {
        // (4) Travel for the new chamber to reach P2 (delivery) and the old one LP (suction):
        // strain to go × L / 1000; the bisection's bracket.
        let to_hi = k.ms_of_p.at(hi).saturating_sub(cs.ms_new0).max(ZERO);
        let to_lo = cs.ms_old0.saturating_sub(k.ms_of_p.at(lo)).max(ZERO);
        cs.u_end = ms_times_mm(to_hi, cs.len_n);
        cs.u_suc = ms_times_mm(to_lo, cs.len_o);
        cs.u_bal = ZERO;
        cs.u_bal_hi = cs.u_end.max(cs.u_suc);
        // The balance is sought only where the eye then crosses the whole play: a rod pushed at
        // once, or one that floated, has none to reach (u_bal = 0).
        if cs.from_rest || cs.play == k.play_mm {
            cs.bisect_left = BISECT_ITERATIONS;
        }
    }
    cs.setup_left -= 1;
}

/// The free play the eye crosses after a reversal, from the chambers' net force on the rod when
/// the lever turned (held pressures, the old chamber's force less the new one's, as a pressure
/// on the old chamber: `p_old − (A_new/A_old)·p_new`). The rod lies against whichever end of the
/// play that force presses it to:
/// - it assists the new motion (the usual case: the old chamber delivered at P2 and resisted
///   the old motion): the rod follows the eye until the forces balance, then stands while the
///   eye crosses the whole play;
/// - it already resists the new motion: the rod ran ahead of the eye on the old stroke (P2 below
///   LP·A_suc/A_del, a low P2 on an annulus stroke) and lies against the end that now pushes
///   it: no play to cross;
/// - within ±[`FLOAT_BAND`] of zero the rod floated: the pump's delivery and the motor's draw
///   held P2 at the balance while the rod drifted ahead in its play. The full simulation shows
///   it most of the way across when the lever turns (0.2–1 mm of a 4 mm play left in the Test I
///   runs with one cylinder); a quarter of the play is taken.
///
/// The band's edges are ramps [`FLOAT_RAMP`] wide (0 → a quarter at −band, a quarter → all of it
/// at +band), so that a rounding difference in the held pressures moves the play by a small
/// amount, not by a quarter of it: such a step at the band's edge separated the fixed-point model
/// from its f64 reference by 0.5 bar in a Config 2 run. Inside the band the play stays a
/// quarter: a slope there would turn the 1e-4 bar by which the two models' pressures differ into
/// a persistent torque offset on every floating reversal (≈ 3 000 N·m per mm of play during
/// compression; a linear play over the whole band gave 0.6 N·m RMS in the irregular sea).
/// Both widths are powers of two: two shifts and a multiply.
fn play_to_cross(k: &Coefficients, c: &CylinderCoeffs, cs: &CylState, lo: Fx, hi: Fx) -> Fx {
    let (p_new0, p_old0) = held_pressures(cs, lo, hi);
    let net = p_old0.saturating_sub(area_ratio(c, cs.dir).qmul(p_new0));
    let quarter = k.play_mm >> 2u32;
    if net <= -FLOAT_BAND {
        ZERO
    } else if net >= FLOAT_BAND {
        k.play_mm
    } else if net < FLOAT_RAMP - FLOAT_BAND {
        // (net + band)/ramp in [0, 1).
        quarter.qmul((net + FLOAT_BAND) << FLOAT_RAMP_SHIFT)
    } else if net > FLOAT_BAND - FLOAT_RAMP {
        // (net − (band − ramp))/ramp in (0, 1).
        quarter + (k.play_mm - quarter).qmul((net - (FLOAT_BAND - FLOAT_RAMP)) << FLOAT_RAMP_SHIFT)
    } else {
        quarter
    }
}

/// The new and the old chamber's pressures when the lever turned (held since; both at LP − drop
/// on a first stroke from rest), held to [LP − drop, P2 + drop], bar.
#[inline(always)]
fn held_pressures(cs: &CylState, lo: Fx, hi: Fx) -> (Fx, Fx) {
    let (p_new0, p_old0) = if cs.from_rest {
        (lo, lo)
    } else if cs.dir >= 0 {
        (cs.p_rod, cs.p_cap)
    } else {
        (cs.p_cap, cs.p_rod)
    };
    (clamp(p_new0, lo, hi), clamp(p_old0, lo, hi))
}

/// A_new/A_old of a stroke in direction `dir` (extending: annulus over cap).
#[inline(always)]
fn area_ratio(c: &CylinderCoeffs, dir: i8) -> Fx {
    if dir >= 0 { c.ratio_ext } else { c.ratio_ret }
}

/// Band of the net chamber force at a reversal within which the rod floats in its play (as a
/// pressure on the old chamber: ±0.25 bar, about the estimate's own noise with the HP
/// transducer).
pub const FLOAT_BAND: Fx = Fx::from_bits(16_384);

/// Width of the ramps at the float band's edges: 2^-4 = 0.0625 bar (see [`play_to_cross`]).
pub const FLOAT_RAMP: Fx = Fx::from_bits(1 << (16 - FLOAT_RAMP_SHIFT));
const FLOAT_RAMP_SHIFT: u32 = 4;

/// 1000/1024, exact in Q16.16.
const KMS: Fx = Fx::from_bits(64_000);

/// Torque of one cylinder (N·m); adds its flows to the step's sums and advances its stroke
/// state, spending the step's reversal work budget. Kept out of line: the step would otherwise
/// carry four unrolled copies of it, ×4 the flash.
#[inline(never)]
fn cylinder(sh: &mut Shared, c: &CylinderCoeffs, cs: &mut CylState, lever: &Lever, on: bool) -> Fx {
    let (k, lo, hi) = (sh.k, sh.lo, sh.hi);
    let dtl = k.dt_log2;
    let (th, sd, v) = (lever.th, lever.sd, lever.v);
    if !on {
        // Idle: bypassed to LP; LP·A_rod pushes the rod out, the rod volume flows to LP.
        let a_rod_q = c.q_cap.saturating_sub(c.q_ann);
        sh.q_lp = sh.q_lp.saturating_add(a_rod_q.qmul(v));
        let f = mul_bounded(sh.lp, c.f_cap.saturating_sub(c.f_ann));
        return sd.qmul(f).saturating_neg();
    }
    let dir: i8 = if v > ZERO {
        1
    } else if v < ZERO {
        -1
    } else {
        cs.dir
    };
    // After a reversal (eye travel e since it, mm): the rod first follows the lever while the
    // old delivering chamber relaxes and the new one compresses, until their forces balance at
    // u_bal; the eye then crosses the free play (`cs.play`) with the rod standing; then the rod
    // moves again until the new chamber reaches P2 and delivers. The rod's own travel u sets
    // both chamber pressures through the oil's strain law p = P(strain) (inverse strain table).
    // (A linear pressure–travel law put the new chamber at ~45 bar instead of ~19 bar when the
    // forces balance, so the torque built up too early.)
    if dir != cs.dir {
        cs.from_rest = cs.dir == 0;
        cs.dir = dir;
        cs.travel = ZERO;
        cs.play = k.play_mm;
        cs.setup_left = SETUP_UNITS;
        cs.bisect_left = 0;
    }
    if (cs.setup_left | cs.bisect_left) != 0 && sh.budget > 0 {
        sh.budget -= 1;
        reversal_unit(sh, c, cs, th);
    }
    let speed = v.abs();
    let mm = mul_dt(speed, dtl); // mm this step = mm/s × dt
    if cs.setup_left == 0 {
        // Flow per unit rod speed of the delivering and the sucking chamber (the flows
        // themselves are taken only when they pass a check valve).
        let (a_del, a_suc) = if dir >= 0 {
            (c.q_ann, c.q_cap)
        } else {
            (c.q_cap, c.q_ann)
        };
        // While the bisection runs, u_bal is known to lie in [u_bal, u_bal_hi]: the rod follows
        // the lever up to the upper end.
        let ub = if cs.bisect_left > 0 {
            cs.u_bal_hi
        } else {
            cs.u_bal
        };
        let e_end = cs.u_end.saturating_add(cs.play);
        // The rod's travel: the eye's up to the balance, held there while the eye crosses the
        // play, the eye's less the play after (branch-free: min/max of the three).
        let u = cs.travel.min(ub).max(cs.travel.saturating_sub(cs.play));
        // The travel counts until the new chamber delivers and the old one sucks (then it is
        // not needed: kept bounded). (Counting stopped at delivery alone once left an old
        // chamber that needs more travel than the new one short of LP for the rest of the
        // stroke: above LP, no suction flow, its strain table read every step.)
        if cs.travel < e_end {
            cs.travel = cs.travel.saturating_add(mm);
        } else {
            sh.q_pump = sh.q_pump.saturating_add(a_del.qmul(speed));
            if u < cs.u_suc {
                cs.travel = cs.travel.saturating_add(mm);
            }
        }
        if u >= cs.u_suc {
            sh.q_lp = sh.q_lp.saturating_add(a_suc.qmul(speed));
        }
        // Once delivering (sucking) the chamber follows P2 (LP), which may have moved since the
        // reversal the strain constants were taken at.
        // (The strain table is read only for a chamber that is still building up or relaxing.)
        let p_new = if cs.travel >= e_end {
            hi
        } else {
            p_new_at(k, cs, u, lo, hi)
        };
        let p_old = if u >= cs.u_suc {
            lo
        } else {
            p_old_at(k, cs, u, lo, hi)
        };
        (cs.p_cap, cs.p_rod) = if dir >= 0 {
            (p_old, p_new)
        } else {
            (p_new, p_old)
        };
    } else {
        // Set-up pending: the chambers hold the pressures they had at the reversal and pass no
        // flow; the eye's travel is counted.
        cs.travel = cs.travel.saturating_add(mm);
    }
    let f_hyd = mul_bounded(cs.p_cap, c.f_cap).saturating_sub(mul_bounded(cs.p_rod, c.f_ann)); // kN
    // mm·kN = N·m. The seals' drag adds to it: counted all stroke long, also while the eye
    // crosses its free play (the rod then stands in the plant, but that is right after a
    // reversal, where the lever's speed and with it the drag are small).
    sd.qmul(f_hyd).saturating_neg().saturating_add(lever.seal)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Increments below the Q16.16 LSB add up: 10 000 steps of 0.3 LSB each (a node at
    /// 2 L/min whose change per step is 0.3 · 2^−16 bar) land within one LSB of the exact sum,
    /// where rounding each step would have lost all of it.
    #[test]
    fn node_keeps_sub_lsb_increments() {
        let dtl = 10;
        let q = Fx::from_num(2.0);
        // dP/dV such that q · dP/dV · 2^−10 s = 0.3 · 2^−16 bar.
        let dp_per_flow = Fx::from_num(0.3 * 1024.0 / 65_536.0 / 2.0);
        let (mut p, mut lo) = (Fx::from_num(100.0), 0u16);
        for _ in 0..10_000 {
            node_step(&mut p, &mut lo, q, dp_per_flow, dtl);
        }
        let exact = 100.0 + 10_000.0 * q.to_num::<f64>() * dp_per_flow.to_num::<f64>() / 1024.0;
        let err_lsb = (p.to_num::<f64>() - exact).abs() * 65_536.0;
        println!("after 10 000 sub-LSB steps: {err_lsb:.3} LSB from the exact sum");
        assert!(err_lsb < 1.0);
    }

    /// The rotor's inertia: at full aperture (the valve's share of the pressure is ≈ 1 %) the
    /// valve/motor flow rises toward its steady value with the rotor's time constant J/c (rad/s
    /// units: 0.01 kg·m² / (0.00784 N·m/rpm × 60/2π) = 0.134 s on the reference bench), and a
    /// closing valve stops it within the step (the gain is held to 1: no overshoot).
    #[test]
    fn motor_flow_lags_by_the_rotor_time_constant_and_stops_with_the_valve() {
        let cfg = crate::ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        let dt = 1.0 / f64::from(1u32 << k.dt_log2);
        // Just above the precharge the accumulator holds P2 (≈ 0.1 bar over the rise).
        let mut s = State::new(
            Pressure::from_num(30.0),
            Pressure::from_num(8.0),
            Pressure::ZERO,
        );
        s.aperture = Fx::from_num(100);
        s.started = true;
        let inp = Inputs {
            aperture_cmd: Aperture::from_num(100.0),
            ..Inputs::default()
        };
        let q_ss = f64::from(k.valve_flow.at(s.aperture, s.p2 - s.lp).to_num::<f32>());
        let mut steps = 0u32;
        while f64::from(s.q_motor.to_num::<f32>()) < (1.0 - (-1f64).exp()) * q_ss {
            step(&k, &mut s, &inp);
            steps += 1;
            assert!(steps < 10_000);
        }
        let tau = f64::from(steps) * dt;
        let c_rad = f64::from(cfg.load_nm_per_rpm) * 60.0 / (2.0 * core::f64::consts::PI);
        let tau_rotor = f64::from(cfg.motor_inertia_kg_m2) / c_rad;
        println!(
            "flow reaches 63 % of {q_ss:.3} L/min after {tau:.4} s; rotor J/c = {tau_rotor:.4} s"
        );
        assert!((tau / tau_rotor - 1.0).abs() < 0.05, "{tau} vs {tau_rotor}");
        // Close the valve at once (no spool lag in this state): the flow stops in one step.
        s.aperture = ZERO;
        let inp = Inputs {
            aperture_cmd: Aperture::ZERO,
            ..Inputs::default()
        };
        let e = step(&k, &mut s, &inp);
        assert_eq!(s.q_motor, ZERO);
        assert_eq!(e.motor_rpm.0, ZERO);
    }

    /// The shaft tracker reads a shaft that is already turning when it starts (a Test I start:
    /// 0.26 rad/s, 16 384 counts per revolution) from its first readings: with the
    /// expanding-memory start-up gains its speed is within 3 % of the shaft's from 16 ms on
    /// (1.2 %), where the fading-memory gains alone start from 0 and are still 82 % short at
    /// 16 ms. After a 0.1 s encoder drop-out (the shaft turned on meanwhile) the tracker starts
    /// again the same way.
    #[test]
    fn shaft_tracker_reads_a_turning_shaft_from_its_first_readings() {
        let cfg = crate::ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        let dt = 1.0 / f64::from(1u32 << k.dt_log2);
        let w = 0.2618;
        let settle = (0.016 / dt) as usize;
        // Largest relative speed error over 0.5 s from `settle` steps after the tracker
        // (re)starts at step `from`, the encoder missing for the 100 steps before `from` if
        // `from` > 0 (a drop-out: the shaft turns on and the readings resume).
        let run = |k: &Coefficients, from: usize| {
            let mut s = State::new(
                Pressure::from_num(25.0),
                Pressure::from_num(8.0),
                Pressure::from_num(1.0),
            );
            let mut worst = 0.0f64;
            for i in 0..from + 512 {
                let theta = 0.05 + w * i as f64 * dt;
                let mut inp = held_inputs(&cfg, theta, Pressure(s.p2), Pressure(s.lp), 0, 0);
                if i < from && i + 100 >= from {
                    inp.encoder = None;
                }
                let e = step(k, &mut s, &inp);
                if i >= from + settle {
                    worst = worst.max((f64::from(e.omega.0.to_num::<f32>()) / w - 1.0).abs());
                }
            }
            worst
        };
        let mut fading = k.clone();
        fading.tracker_startup_len = 0;
        let (with, without) = (run(&k, 0), run(&fading, 0));
        let after_dropout = run(&k, 400);
        println!(
            "speed error from {:.0} ms on: start-up gains {:.2} % ({} steps), fading-memory \
             gains alone {:.1} %; after a 0.1 s drop-out {:.2} %",
            settle as f64 * dt * 1e3,
            with * 100.0,
            k.tracker_startup_len,
            without * 100.0,
            after_dropout * 100.0
        );
        assert_eq!(k.tracker_startup_len, 53);
        assert!(with < 0.03, "{with}");
        assert!(after_dropout < 0.03, "{after_dropout}");
        assert!(without > 0.2, "{without}");
    }

    /// A step's readings with the lever at `theta` (rad, as the encoder counts it) and both
    /// transducers reading `p2` and `lp`; valve at 10 %, no motor-speed reading.
    fn held_inputs(
        cfg: &crate::ModelConfig,
        theta: f64,
        p2: Pressure,
        lp: Pressure,
        on_duty: u8,
        config: u8,
    ) -> Inputs {
        let count = theta / (2.0 * core::f64::consts::PI) * f64::from(cfg.encoder_counts_per_rev);
        Inputs {
            encoder: Some(count.round() as i32),
            hp: Some(p2),
            lp: Some(lp),
            motor: None,
            aperture_cmd: Aperture::from_num(10.0),
            on_duty,
            config,
        }
    }

    /// Runs `steps` steps without the HP reading: shaft still, no cylinder on duty, the valve
    /// held at `aperture` %, the motor sensor reading `rpm` (or missing), from P2 = `p2` bar.
    fn run_without_hp(
        k: &Coefficients,
        p2: f32,
        aperture: f32,
        rpm: Option<f32>,
        steps: usize,
    ) -> Fx {
        let lp = Pressure::from_num(8.0);
        let mut s = State::new(Pressure::from_num(p2), lp, Pressure::from_num(0.0));
        let inp = Inputs {
            hp: None,
            motor: rpm.map(Rpm::from_num),
            aperture_cmd: Aperture::from_num(aperture),
            ..held_inputs(&crate::ModelConfig::reference(), 0.0, lp, lp, 0, 0)
        };
        for _ in 0..steps {
            step(k, &mut s, &inp);
        }
        s.p2
    }

    /// Without the HP reading, the motor speed of a rotor held steady by P2 = 40 bar (LP 8, the
    /// valve fully open) pulls a P2 estimate started 5 bar low to 40 bar less the reading's
    /// band (2 % of ΔP) within a quarter of a second; the model alone stays 5 bar off. Near the
    /// closed valve, and with the motor below its minimum speed, the reading is not used: P2
    /// is bit for bit the model's own.
    #[test]
    fn motor_speed_reads_p2_without_the_hp_transducer() {
        let cfg = crate::ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        let (p_true, lp) = (40.0f32, 8.0f32);
        let q = k
            .valve_flow
            .at(Fx::from_num(100.0), Fx::from_num(p_true - lp))
            .to_num::<f32>();
        let rpm = q * cfg.rpm_per_lpm();
        let steps = 256; // 0.25 s: ten time constants of 25 ms
        let with = run_without_hp(&k, p_true - 5.0, 100.0, Some(rpm), steps).to_num::<f32>();
        let alone = run_without_hp(&k, p_true - 5.0, 100.0, None, steps).to_num::<f32>();
        let band = 0.02 * (p_true - lp);
        let expect = p_true - band;
        std::println!(
            "steady rotor at {rpm:.1} rpm ({q:.3} L/min) for P2 = {p_true} bar: from {} bar, P2 \
             {with:.3} bar with the motor reading (expected {expect:.2} within 0.05), {alone:.3} \
             bar from the model alone",
            p_true - 5.0
        );
        assert!((with - expect).abs() < 0.05, "{with} vs {expect}");
        assert!(p_true - alone > 4.5, "{alone}");
        // Started at the right pressure, the reading keeps it there (inside its band).
        let held = run_without_hp(&k, p_true, 100.0, Some(rpm), steps).to_num::<f32>();
        assert!((held - p_true).abs() <= band + 0.1, "{held}");
        // Guards: valve near closed (dF/dQ above the limit), motor below its minimum speed.
        for (aperture, rpm) in [(1.0, rpm), (100.0, 0.5 * cfg.motor_reading_min_rpm)] {
            let a = run_without_hp(&k, p_true - 5.0, aperture, Some(rpm), steps);
            let b = run_without_hp(&k, p_true - 5.0, aperture, None, steps);
            assert_eq!(a, b, "aperture {aperture} %, {rpm} rpm");
        }
    }

    /// Behind a closed valve (commanded 0 %) a motor sensor reading 50 or 200 rpm moves P2 by
    /// nothing — bit for bit the model alone — and is flagged as a contradiction once a real
    /// rotor would have spun down (five of its time constants J/c, 0.67 s), not before. With the
    /// valve open, a reading that implies a P2 above the relief is refused and flagged.
    #[test]
    fn contradicting_motor_readings_are_flagged_not_followed() {
        let cfg = crate::ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        let lp = Pressure::from_num(8.0);
        let run = |aperture: f32, rpm: Option<f32>, steps: usize| {
            let mut s = State::new(Pressure::from_num(50.0), lp, Pressure::from_num(1.0));
            let inp = Inputs {
                hp: None,
                motor: rpm.map(Rpm::from_num),
                aperture_cmd: Aperture::from_num(aperture),
                ..held_inputs(&cfg, 0.0, lp, lp, 0, 0)
            };
            let mut first = None;
            for i in 0..steps {
                if step(&k, &mut s, &inp).faults & fault::MOTOR_IMPLAUSIBLE != 0 {
                    first = first.or(Some(i));
                }
            }
            (s.p2, first)
        };
        let steps = 3 << k.dt_log2;
        let (alone, none) = run(0.0, None, steps);
        assert_eq!(none, None);
        for rpm in [50.0, 200.0] {
            let (p2, first) = run(0.0, Some(rpm), steps);
            std::println!(
                "{rpm} rpm behind a closed valve: P2 {} bar after 3 s (model alone {}), flagged \
                 from step {first:?} (spin-down {} steps)",
                p2.to_num::<f32>(),
                alone.to_num::<f32>(),
                k.spin_down_steps
            );
            assert_eq!(p2, alone, "P2 followed the reading");
            assert_eq!(first, Some(usize::from(k.spin_down_steps) - 1));
        }
        // The valve fully open, the motor reading the flow of ΔP = 160 bar: above the relief.
        let q = k.valve_flow.at(Fx::from_num(100.0), Fx::from_num(160.0));
        let rpm = q.to_num::<f32>() * cfg.rpm_per_lpm();
        let (p2, first) = run(100.0, Some(rpm), steps);
        let (p2_alone, _) = run(100.0, None, steps);
        std::println!(
            "{rpm:.0} rpm at 100 % (ΔP 160 bar): flagged from step {first:?}, P2 {} bar (model \
             alone {})",
            p2.to_num::<f32>(),
            p2_alone.to_num::<f32>()
        );
        assert!(first.is_some(), "an impossible reading was taken");
        assert!(
            (p2.to_num::<f32>() - p2_alone.to_num::<f32>()).abs() < 0.01,
            "{p2} vs {p2_alone}"
        );
    }

    /// Without the HP transducer, P2's σ is at least `precharge_sigma_bar` once the estimate
    /// is within `precharge_band_bar` of the precharge or below it (the accumulator may run
    /// empty at any moment, or has), and grows freely above; the empty flag stands below the
    /// precharge plus `hp_empty_margin_bar`.
    #[test]
    fn model_only_sigma_is_wide_where_the_accumulator_empties() {
        let cfg = crate::ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        let lp = Pressure::from_num(8.0);
        for (p2, want_floor, empty) in [
            (20.0, true, true),
            (25.05, true, true),
            (25.5, true, false),
            (27.0, false, false),
            (100.0, false, false),
        ] {
            let mut s = State::new(Pressure::from_num(p2), lp, Pressure::from_num(0.1));
            let inp = Inputs {
                hp: None,
                ..held_inputs(&cfg, 0.0, lp, lp, 0, 0)
            };
            let e = step(&k, &mut s, &inp);
            let sigma = e.p2_sigma().to_f32();
            std::println!(
                "P2 {p2} bar without HP: σ {sigma:.3} bar, empty {}",
                e.hp_empty
            );
            assert_eq!(sigma >= cfg.precharge_sigma_bar - 0.01, want_floor, "{p2}");
            assert_eq!(e.hp_empty, empty, "{p2}");
        }
    }

    /// The Kalman variance follows its f64 recursion var ← (var + q)·(1 − g(var)) (the same
    /// tables, interpolated in f64) over 4 s of HP readings at 100 bar from σ = 1 bar: within
    /// 10^−4 all the way down, its bits below the LSB counted (the gain is looked up with them,
    /// `Coefficients::gain_q32`; read at the Q16.16 value, near the steady ≈ 130 LSBs, one LSB
    /// was 0.8 %). Floored to its Q16.16 LSB, the shrink lost up to 1 LSB a step on the way
    /// down and the variance ran up to 17 % below the f64 one (in `pto validate`, after each
    /// crossing of the precharge, 20 %: P2 up to 0.15 bar away from the f64 model). The process
    /// noise q is at its floor of one LSB per step here.
    #[test]
    fn kalman_variance_keeps_its_sub_lsb_bits() {
        let cfg = crate::ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        let r = k.r.to_num::<f64>();
        let (p2, lp) = (Pressure::from_num(100.0), Pressure::from_num(8.0));
        let mut s = State::new(p2, lp, Pressure::from_num(1.0));
        let inp = held_inputs(&cfg, 0.0, p2, lp, 0, 0);
        let mut var = 1.0f64;
        let mut worst = 0.0f64;
        // The variance with its bits below the LSB (the step's gain reads them too).
        let fixed = |s: &State| s.var.to_num::<f64>() + f64::from(s.var_lo) / 4_294_967_296.0;
        for _ in 0..4 << k.dt_log2 {
            step(&k, &mut s, &inp);
            var += k.q_step.at_ext(s.p2) as f64 / 4_294_967_296.0;
            let g = if var < r {
                k.gain_fine.at_f64(var)
            } else {
                k.gain_coarse.at_f64(var).clamp(0.0, 1.0)
            };
            var *= 1.0 - g;
            worst = worst.max((fixed(&s) / var - 1.0).abs());
        }
        let last = (fixed(&s) / var - 1.0).abs();
        std::println!(
            "P2 100 bar: variance after 4 s {:.6} bar² (f64 {var:.6}: {:.4} % apart, allowed \
             0.01 %), {:.4} % apart at worst on the way (allowed 0.01 %)",
            fixed(&s),
            100.0 * last,
            100.0 * worst
        );
        assert!(last < 1e-4, "{last}");
        assert!(worst < 1e-4, "{worst}");
    }

    /// Mid-stroke (the shaft at full speed), every cylinder on duty has one chamber at
    /// P2 + drop delivering and the other at LP − drop sucking, in both directions, every
    /// geometry and around several lever positions: the rod's travel counts on until the old
    /// chamber reaches LP, also where (the rod off centre) that chamber is the longer one and
    /// needs more travel than the new one does to reach P2. (The travel used to stop at
    /// delivery, and such an old chamber stayed above LP for the rest of the stroke, passing no
    /// flow.)
    #[test]
    fn both_chambers_reach_their_check_valves_by_mid_stroke() {
        let cfg = crate::ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        let n = 1u32 << k.dt_log2;
        let (p2, lp) = (Pressure::from_num(100.0), Pressure::from_num(8.0));
        let (mut worst, mut checked) = (0.0f32, 0);
        // ±8° at 0.1 Hz around three lever positions, P2 held at 100 bar by its transducer.
        let (amp, f) = (8f64.to_radians(), 0.1);
        for offset_deg in [-15.0f64, 0.0, 15.0] {
            for config in 0..4u8 {
                let mut s = State::new(p2, lp, Pressure::ZERO);
                // Two periods; the shaft at full speed at t = j/(2f): 10 s and 15 s are
                // mid-stroke after a reversal each way.
                for i in 0..=(15 * n) {
                    let t = f64::from(i) / f64::from(n);
                    let theta =
                        offset_deg.to_radians() + amp * (2.0 * core::f64::consts::PI * f * t).sin();
                    let inp = held_inputs(&cfg, theta, p2, lp, 0b1111, config);
                    let e = step(&k, &mut s, &inp);
                    if i == 10 * n || i == 15 * n {
                        let (lo, hi) = (e.lp.0 - k.check_drop, e.p2.0 + k.check_drop);
                        for cs in &s.cyl {
                            let (p_hi, p_lo) = if cs.p_cap > cs.p_rod {
                                (cs.p_cap, cs.p_rod)
                            } else {
                                (cs.p_rod, cs.p_cap)
                            };
                            worst = worst
                                .max((p_hi - hi).abs().to_num())
                                .max((p_lo - lo).abs().to_num());
                            checked += 1;
                        }
                    }
                }
            }
        }
        println!(
            "{checked} chamber pairs mid-stroke: worst {worst:.4} bar from P2 + drop / LP − drop"
        );
        assert_eq!(checked, 96);
        assert!(worst < 0.01, "{worst}");
    }

    /// The play the eye crosses after a reversal follows the sign of the chambers' net force on
    /// the rod when the lever turns, computed here in f64 from the bores and rods: every
    /// cylinder, both directions, chamber pressures over LP − drop … P2 + drop.
    #[test]
    fn the_play_to_cross_follows_the_rods_net_force_at_the_reversal() {
        let cfg = crate::ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        let (lo, hi) = (7.5f64, 30.5f64);
        let play: f64 = k.play_mm.to_num();
        let band: f64 = FLOAT_BAND.to_num();
        let mut count = [0u32; 3]; // none, within the band, all of it
        let mut worst = 0.0f64;
        for (c, cc) in k.cyl.iter().zip(cfg.cylinders.iter()) {
            let a_cap = core::f64::consts::PI / 4.0 * f64::from(cc.bore_mm).powi(2);
            let a_ann = a_cap - core::f64::consts::PI / 4.0 * f64::from(cc.rod_mm).powi(2);
            for dir in [1i8, -1] {
                for i in 0..=62 {
                    for j in 0..=62 {
                        let (p_cap, p_rod) = (lo + 0.37 * f64::from(i), lo + 0.37 * f64::from(j));
                        // The force pushing the rod the new way, per unit area of the old
                        // chamber (the one that delivered on the last stroke).
                        let (assist, a_old) = if dir > 0 {
                            (p_cap * a_cap - p_rod * a_ann, a_cap)
                        } else {
                            (p_rod * a_ann - p_cap * a_cap, a_ann)
                        };
                        let net = assist / a_old;
                        let cs = CylState {
                            dir,
                            p_cap: Fx::from_num(p_cap),
                            p_rod: Fx::from_num(p_rod),
                            ..CylState::default()
                        };
                        let got: f64 =
                            play_to_cross(&k, c, &cs, Fx::from_num(lo), Fx::from_num(hi)).to_num();
                        let ramp: f64 = FLOAT_RAMP.to_num();
                        let (expected, class) = if net <= -band {
                            (0.0, 0)
                        } else if net >= band {
                            (play, 2)
                        } else if net < ramp - band {
                            (0.25 * play * (net + band) / ramp, 1)
                        } else if net > band - ramp {
                            (0.25 * play + 0.75 * play * (net - (band - ramp)) / ramp, 1)
                        } else {
                            (0.25 * play, 1)
                        };
                        // Q16.16 area ratio (±7.6e-6 relative) times ≤ 30 bar: the net force
                        // is off by ≤ 2.3e-4 bar, the play on the steeper ramp by
                        // ≤ 0.75·play/ramp × that = 0.0028·play.
                        let err = (got - expected).abs();
                        worst = worst.max(err);
                        assert!(
                            err <= 0.003 * play,
                            "p_cap {p_cap}, p_rod {p_rod}, dir {dir}: {got} vs {expected}"
                        );
                        count[class] += 1;
                    }
                }
            }
        }
        println!("worst play error {worst:.5} mm of {play} mm");
        println!(
            "reversals: {} with no play to cross, {} floating (within the band), {} the whole play",
            count[0], count[1], count[2]
        );
        assert!(count.iter().all(|&n| n > 100), "{count:?}");
    }

    /// Seal friction: every rod on duty adds c·d²·θ̇ to the restraining torque (a force c·v
    /// against its speed v = d·θ̇ on the arm d); an idle rod, bypassed and pushed out by LP,
    /// adds none. Two estimators, with and without friction, on the same readings, mid-stroke
    /// in every geometry.
    #[test]
    fn seal_friction_adds_c_d2_omega_per_rod_on_duty() {
        let cfg = crate::ModelConfig::reference();
        let k = cfg.coefficients().unwrap();
        let k0 = crate::ModelConfig {
            seal_friction_n_s_per_m: 0.0,
            ..cfg
        }
        .coefficients()
        .unwrap();
        let n = 1u32 << k.dt_log2;
        let (p2, lp) = (Pressure::from_num(60.0), Pressure::from_num(8.0));
        let c = f64::from(cfg.seal_friction_n_s_per_m) * 1e-6; // kN per mm/s
        let (mut worst, mut checked) = (0.0f64, 0);
        for config in 0..4u8 {
            let (mut s, mut s0) = (
                State::new(p2, lp, Pressure::ZERO),
                State::new(p2, lp, Pressure::ZERO),
            );
            for i in 0..=(10 * n) {
                let t = f64::from(i) / f64::from(n);
                let theta = 20f64.to_radians() * (2.0 * core::f64::consts::PI * 0.1 * t).sin();
                let inp = held_inputs(&cfg, theta, p2, lp, 0b0101, config);
                let (e, e0) = (step(&k, &mut s, &inp), step(&k0, &mut s0, &inp));
                if i == 5 * n || i == 10 * n {
                    let omega: f64 = e.omega.0.to_num();
                    for (j, cyl) in k.cyl.iter().enumerate() {
                        let sth = if cyl.side < ZERO {
                            -e.theta.0
                        } else {
                            e.theta.0
                        };
                        let d: f64 = k.arm[usize::from(config)].at(sth).to_num();
                        let expected = if inp.on_duty & (1 << j) != 0 {
                            c * d * d * omega
                        } else {
                            0.0
                        };
                        let got: f64 = (e.torque_cyl[j].0 - e0.torque_cyl[j].0).to_num();
                        worst = worst.max((got - expected).abs() / (c * d * d * omega).abs());
                        checked += 1;
                    }
                }
            }
        }
        println!(
            "{checked} rods mid-stroke: seal torque within {:.3} % of c·d²·θ̇",
            100.0 * worst
        );
        assert_eq!(checked, 32);
        assert!(worst < 0.01, "{worst}");
    }

    proptest! {
        /// A relaxation never overshoots its target (the fraction bits may carry it less than
        /// one LSB past it), for any flows and gains in range.
        #[test]
        fn relaxation_never_overshoots(
            x in 0i32..(1000 << 16), lo in any::<u16>(), t in 0i32..(1000 << 16),
            g in 0i32..=65_536,
        ) {
            let (mut xx, mut ll) = (Fx::from_bits(x), lo);
            relax(&mut xx, &mut ll, Fx::from_bits(g), Fx::from_bits(t));
            let (a, b) = (x.min(t), x.max(t));
            prop_assert!(xx.to_bits() >= a && xx.to_bits() <= b, "{} not in [{a}, {b}]", xx.to_bits());
        }

        /// An observer correction lands between the estimate and the reading (the fraction
        /// bits may carry it less than one LSB past the reading) and inside the pressure range,
        /// for readings outside it too.
        #[test]
        fn correction_stays_between_estimate_and_reading(
            p in -65_536i32..(400 << 16), lo in any::<u16>(), z in (-10i32 << 16)..(500 << 16),
            g in 0i32..=65_536,
        ) {
            let (mut pp, mut ll) = (Fx::from_bits(p), lo);
            correct(&mut pp, &mut ll, Fx::from_bits(g), Fx::from_bits(z));
            let zc = z.clamp(P_MIN.to_bits(), P_MAX.to_bits());
            let (a, b) = (p.min(zc), p.max(zc));
            prop_assert!(pp.to_bits() >= a && pp.to_bits() <= b, "{} not in [{a}, {b}]", pp.to_bits());
        }

        /// A node step never leaves the physical pressure range, for any flow and dP/dV.
        #[test]
        fn node_step_stays_in_range(
            p in -65_536i32..(400 << 16), lo in any::<u16>(), q in any::<i32>(),
            dpdv in 0i32..i32::MAX, dtl in 6u8..=12,
        ) {
            let (mut pp, mut ll) = (Fx::from_bits(p), lo);
            node_step(&mut pp, &mut ll, Fx::from_bits(q), Fx::from_bits(dpdv), dtl);
            prop_assert!(pp >= P_MIN && pp <= P_MAX);
        }
    }
}
