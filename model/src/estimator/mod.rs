//! The HP-pressure / restraining-torque estimator: the reduced-order node model of `docs/physics.md` §2
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
//!
//! The stages live in files of their own: `tracker` (the shaft), `cylinder` (strokes,
//! reversals, play, flows and torque), `motor` (the motor speed read as a pressure), `observer`
//! (the Kalman update of P2), `fine` (values kept below the Q16.16 LSB); [`step`] here runs them
//! in order.

use crate::coeffs::{Coefficients, N_ARM};
use crate::fx::{
    Angle, AngularSpeed, Aperture, Flow, Fx, HydraulicPower, ONE, Pressure, PressureVariance, QMul,
    Rpm, Seconds, Torque, W_PER_BAR_LPM, ZERO, clamp, mul_bounded, mul_dt, mul_frac, mul_q24,
    recip, shr64, sqrt0, wide,
};
use crate::table::Table1;

/// P2's variance at or below which the estimate counts as settled on the readings, bar²
/// (σ 0.125 bar, a sixteenth of the reference HP reading's 0.25 bar²: ≈ 16 readings averaged,
/// so the stuck-encoder check's 1 bar is 8σ of its baseline; a reset starts at σ 1 bar, boot
/// far above; the steady σ is ≈ 0.05 bar).
pub const SETTLED_VAR: Fx = Fx::from_bits(1 << 10);

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
    /// Encoder static for 2 s while the HP reading rises by more than 1 bar, or while the HP
    /// shadow check disagrees (`estimator::residual`): shaft moving.
    pub const ENCODER_STUCK: u16 = 1 << 7;
    /// Configuration index out of range (step ignored the duty mask).
    pub const BAD_CONFIG: u16 = 1 << 8;
    /// The motor speed contradicts the model: it turns behind a valve that has been closed for
    /// longer than the rotor takes to spin down, or, without the HP transducer, it reads a flow
    /// the valve could not pass at the modelled aperture with P2 at the relief (P2 is then not
    /// moved by it).
    pub const MOTOR_IMPLAUSIBLE: u16 = 1 << 9;
    /// The HP reading disagrees with the model over a 4 s window (`estimator::residual`: it
    /// did not change as the model's flows say P2 did): stuck, drifting, or a jump the gate
    /// took in. Raised while the encoder moves (still, the encoder is suspect instead).
    pub const HP_DISAGREES: u16 = 1 << 10;
    /// The measured motor speed has disagreed with the model's (from P2 and the aperture) for
    /// 1 s: the motor pickup, or the P2 it is modelled from.
    pub const MOTOR_DISAGREES: u16 = 1 << 11;
    /// The LP reading has been more than 2 bar from the model's LP for 1 s.
    pub const LP_DISAGREES: u16 = 1 << 12;
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

    /// Hydraulic power into the control valve, P2 · valve flow (what drives the motor and the
    /// valve's throttling; 0 … 32 767 W, saturating). Taken on demand, like
    /// [`Estimate::p2_sigma`], for the telemetry: the per-step code stays within its 9 KiB.
    pub fn hydraulic_power(&self) -> HydraulicPower {
        hydraulic_power(self.p2.0, self.q_valve.0)
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
    /// The free play this stroke crosses, mm: after a stroke whose eye pushed the rod, the
    /// configured play, 0 when the rod stays on one end of it, a quarter of it when the rod
    /// floated (see `play_to_cross`); after one that turned before, [`CylState::gap`].
    pub play: Fx,
    /// The last stroke's eye had crossed its play and pushed the rod before the lever turned:
    /// the new stroke's play then follows the chambers' force on the rod (`play_to_cross`);
    /// else it is [`CylState::gap`].
    pub engaged: bool,
    /// The last stroke's new chamber had reached P2 and delivered before the lever turned
    /// (only then can its rod have floated: see `play_to_cross`).
    pub delivered: bool,
    /// The eye's distance, as the lever turned, from the face of its play that drives the rod
    /// in the new direction, mm: the play that lay behind the rod when the last stroke began
    /// (play − that stroke's `play`) plus the eye's travel past the rod since. A stroke shorter
    /// than the play leaves the eye part way across it, and the rod (standing at its force
    /// balance) is driven only once the eye is back at that face.
    pub gap: Fx,
    /// The reading ([`CylState::engaged`], [`CylState::delivered`], [`CylState::gap`]) for the
    /// stroke after the new one should the new one turn before its set-up has taken its play
    /// (no stroke: the one after continues the stroke before it). Swapped with the new
    /// stroke's at such a turn.
    pub alt_engaged: bool,
    /// See [`CylState::alt_engaged`].
    pub alt_delivered: bool,
    /// See [`CylState::alt_engaged`], mm.
    pub alt_gap: Fx,
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

/// Estimator state (416 bytes together with the scheduler's; `pto model-cost` prints it), a
/// sub-state per stage of [`step`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct State {
    /// The shaft tracker (`tracker`).
    pub tracker: TrackerState,
    /// The HP and LP nodes and P2's variance (`observer`).
    pub node: NodeState,
    /// The spool and the valve/motor flow (`motor`).
    pub branch: BranchState,
    /// Autonomy at the last refresh, s.
    pub autonomy: Fx,
    /// Steps since the last autonomy refresh (wraps).
    pub autonomy_tick: u8,
    /// Averaged pump flow, L/min.
    pub q_mean: Fx,
    /// Cylinders (`cylinder`).
    pub cyl: [CylState; 4],
    /// The motor reading, used without the HP transducer (`motor`).
    pub reading: ReadingState,
    /// The sensors' residuals against the model (`residual`).
    pub resid: ResidualState,
}

impl State {
    /// A state starting from known pressures (bar, held to [`P_MIN`, `P_MAX`] like every
    /// pressure state) with the given P2 standard deviation.
    pub fn new(p2: Pressure, lp: Pressure, sigma: Pressure) -> Self {
        State {
            node: NodeState {
                p2: clamp(p2.0, P_MIN, P_MAX),
                lp: clamp(lp.0, P_MIN, P_MAX),
                var: sigma.0.qmul(sigma.0),
                ..NodeState::default()
            },
            ..State::default()
        }
    }
}

/// [`TrackerState::phase`] before the tracker's first encoder reading.
const ENC_UNSEEN: u8 = 0;
/// [`TrackerState::phase`] once the fading-memory gains track the shaft.
const ENC_TRACKING: u8 = 1;

/// Lower end of the pressure states' range (P2, LP), bar: vacuum.
pub const P_MIN: Fx = Fx::from_bits(-65_536);
/// Upper end of the pressure states' range (P2, LP), bar.
pub const P_MAX: Fx = Fx::from_bits(400 << 16);
const FLOW_LIM: Fx = Fx::from_bits(1000 << 16);
const THETA_LIM_Q32: i64 = 1 << 61;
const OMEGA_LIM_Q32: i64 = 100 << 32;
const ACCEL_LIM_Q32: i64 = 1000 << 32;

mod cylinder;
mod fine;
mod motor;
mod observer;
mod residual;
#[cfg(test)]
mod tests;
mod tracker;

use cylinder::*;
pub use cylinder::{CylinderCoeffs, FLOAT_BAND, FLOAT_RAMP, PumpCoeffs};
use fine::*;
use motor::*;
pub use motor::{BranchCoeffs, BranchState, ReadingCoeffs, ReadingState};
use observer::*;
pub use observer::{NodeState, ObserverCoeffs};
pub use residual::{
    LP_ALLOW_BAR, MOTOR_SHIFT, PRESSURE_SHIFT, ResidualState, SHADOW_STEPS, motor_allowance,
};
use tracker::*;
pub use tracker::{
    TRACKER_STARTUP, TRACKER_STARTUP_MAX, TrackerCoeffs, TrackerState, expanding_memory_gains,
    tracker_startup_gains,
};

/// P2 · valve flow in W, floored at 0 (no power flows back through the valve into HP: its flow
/// is 0 unless P2 is above the motor inlet) and saturating at the Q16.16 range: two saturating
/// multiplications.
fn hydraulic_power(p2_bar: Fx, q_valve_lpm: Fx) -> HydraulicPower {
    let w = p2_bar
        .max(ZERO)
        .saturating_mul(W_PER_BAR_LPM)
        .saturating_mul(q_valve_lpm.max(ZERO));
    HydraulicPower(w)
}

/// Advances the estimator by one step. Cannot fail; every reading may be missing or wrong.
pub fn step(k: &Coefficients, s: &mut State, inp: &Inputs) -> Estimate {
    let dtl = k.dt_log2;
    let mut faults = 0u16;
    // --- Shaft: α–β–γ tracker on the encoder angle.
    let settled = s.node.var <= SETTLED_VAR;
    let (theta, omega) = track(
        &k.tracker,
        dtl,
        &mut s.tracker,
        s.node.p2,
        settled,
        inp,
        &mut faults,
    );
    // --- Spool lag.
    let (cmd, first) = spool(&k.branch, &mut s.branch, inp.aperture_cmd.0);
    // --- Cylinders: delivered flow, suction flow, torque.
    let (torque, torque_cyl, sh) = cylinders(
        &k.pump,
        dtl,
        &mut s.cyl,
        s.node.p2,
        s.node.lp,
        theta,
        s.tracker.omega_q32,
        inp,
        &mut faults,
    );
    let (q_pump, q_lp_net) = (sh.q_pump, sh.q_lp);
    let mut background_units = REVERSAL_UNITS_PER_STEP - sh.budget;
    // --- Valve, relief, motor.
    let br = branch(&k.branch, &mut s.branch, s.node.p2, s.node.lp, first);
    // --- Predict.
    let p2_before = s.node.p2;
    predict(
        &k.observer,
        dtl,
        &mut s.node,
        q_pump,
        br.q_valve,
        br.q_relief,
        q_lp_net,
    );
    s.q_mean = s
        .q_mean
        .saturating_add(mul_frac(k.mean_gain, q_pump.saturating_sub(s.q_mean)));
    // --- Correct P2: with the HP transducer, else with the motor speed.
    let (hp_lo, hp_hi) = k.observer.hp_range_bar;
    let hp = inp.hp.map(|p| p.0).filter(|p| *p >= hp_lo && *p <= hp_hi);
    let motor = inp.motor.filter(|m| m.0 >= ZERO && m.0 <= k.motor_max_rpm);
    let closed = valve_closed(
        &k.reading,
        &k.branch,
        &mut s.branch,
        cmd,
        motor,
        br.motor_rpm,
        &mut faults,
    );
    // The predictions before any reading corrects them: what the residuals judge.
    let (p2_pred, lp_pred) = (s.node.p2, s.node.lp);
    if let Some(m) = motor
        && residual::motor(&mut s.resid, m.0, br.motor_rpm)
    {
        faults |= fault::MOTOR_DISAGREES;
    }
    match hp {
        Some(z) => {
            residual::mean(&mut s.resid.hp, z.saturating_sub(p2_pred), PRESSURE_SHIFT);
            // The motor reading restarts when the transducer goes missing again.
            (s.reading.live, s.reading.wait) = (false, 0);
            kalman(&k.observer, &mut s.node, z, &mut faults);
        }
        None => {
            faults |= fault::HP_SENSOR;
            match motor {
                Some(m) if !closed => {
                    faults |= motor_reading(
                        &k.reading,
                        &k.branch,
                        &mut s.reading,
                        &mut s.node,
                        s.branch.aperture,
                        m.0,
                        cmd,
                        &br,
                    )
                }
                // Closed: no reading; the filters restart once it opens, P2 waiting for them.
                Some(_) => (s.reading.live, s.reading.wait) = (false, k.reading.warm_steps),
                None => (s.reading.live, s.reading.wait) = (false, 0),
            }
            model_only_floor(&k.observer, &mut s.node);
        }
    }
    let judged = p2_pred >= k.residual_p2_range.0 && p2_pred <= k.residual_p2_range.1;
    // Both HP checks weigh the pump's flow, from the encoder: without its reading they say
    // nothing, and start afresh when it comes back (as without the HP reading).
    let hp_judged = hp.filter(|_| inp.encoder.is_some());
    if let Some(z) = hp_judged
        && residual::stuck_low(
            &mut s.resid,
            q_pump
                .saturating_sub(br.q_valve)
                .saturating_sub(br.q_relief),
            z,
            k.residual_p2_range.0,
            k.stuck_low_inflow,
            k.dt_log2,
        )
    {
        faults |= fault::HP_DISAGREES;
    }
    if residual::shadow(
        &mut s.resid,
        p2_pred.saturating_sub(p2_before),
        s.node.p2,
        hp_judged,
        judged,
    ) {
        s.resid.hp_flag_steps = s.resid.hp_flag_steps.saturating_add(1);
    } else {
        s.resid.hp_flag_steps = 0;
    }
    if s.resid.hp_flag_steps >= residual::SHADOW_PERSIST_STEPS {
        // Isolation: the shadow's flows come from the encoder as much as from P2. While the
        // encoder moves, the HP reading is what disagrees. Once it has stood still as long as
        // the encoder check waits, the encoder is suspect if nothing says P2 is not as read:
        // the valve closed (a lever truly at rest then changes nothing the shadow could
        // miss), or the motor read and agreeing with P2. A speed that disagrees, or none read
        // with the valve open (a lever at rest, P2 falling under a stuck reading: the safer
        // call, HP held and no motor to bound P2 opens the dump), names the reading.
        let still = s.tracker.still_steps;
        let encoder_suspect = still >= k.tracker.stuck_steps
            && (closed || (motor.is_some() && s.resid.motor_over == 0));
        if encoder_suspect {
            faults |= fault::ENCODER_STUCK;
        } else if still < residual::SHADOW_ENCODER_STILL_STEPS || still >= k.tracker.stuck_steps {
            faults |= fault::HP_DISAGREES;
        }
    }
    // --- Correct LP with a fixed gain.
    if let Some(z) = inp.lp.map(|p| p.0)
        && residual::lp(&mut s.resid, z, lp_pred)
    {
        faults |= fault::LP_DISAGREES;
    }
    correct_lp(&k.observer, &mut s.node, inp.lp, &mut faults);
    if motor.is_none() {
        faults |= fault::MOTOR_SENSOR;
    }
    if s.node.p2 > k.trip_bar || hp.is_some_and(|z| z > k.trip_bar) {
        faults |= fault::OVERPRESSURE;
    }
    // Autonomy changes over seconds: it is refreshed in the background slot, every
    // AUTONOMY_EVERY-th step unless a reversal holds the slot (then in the next free step), so
    // its table lookup adds to neither a reversal's work nor the scheduler's feed-forward.
    s.autonomy_tick = s.autonomy_tick.wrapping_add(1);
    if background_units == 0 && s.autonomy_tick >= AUTONOMY_EVERY {
        s.autonomy = k.autonomy.at(s.branch.aperture, s.node.p2);
        s.autonomy_tick = 0;
        background_units = 1;
    }
    Estimate {
        p2: Pressure(s.node.p2),
        p2_var: PressureVariance(s.node.var),
        lp: Pressure(s.node.lp),
        theta: Angle(theta),
        omega: AngularSpeed(omega),
        q_pump: Flow(q_pump),
        q_pump_mean: Flow(s.q_mean),
        q_valve: Flow(br.q_valve),
        q_relief: Flow(br.q_relief),
        torque: Torque(torque),
        torque_cyl,
        motor_rpm: Rpm(br.motor_rpm),
        autonomy: Seconds(s.autonomy),
        aperture: Aperture(s.branch.aperture),
        faults,
        background_units,
        hp_empty: s.node.p2 < k.hp_empty_below_bar,
    }
}
