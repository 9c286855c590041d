//! Residuals: how far each sensor disagrees with the model, averaged over a window (analytic
//! redundancy, as in An & Sepehri's fault detection for hydraulic actuators). Each is an
//! exponential mean of the step's difference between a reading and the model's prediction of
//! it before that reading corrected anything, kept with shifts (no multiplication, no division):
//! - HP: the reading against the predicted P2 (the Kalman filter's innovation, judged over a
//!   window instead of a step: a reading that sticks, drifts or scales leaves a mean the
//!   model's own errors do not);
//! - LP: the reading against the predicted LP;
//! - motor: the measured speed against the model's rotor speed (Eq. 9 with the rotor's inertia,
//!   from P2 and the aperture).

use super::*;

/// The residuals' exponential means.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ResidualState {
    /// HP reading − predicted P2, bar.
    pub hp: Fx,
    /// P2 by the model alone since the window's start: the estimate then, plus every step's
    /// predicted change since (no reading's correction), bar.
    pub shadow: Fx,
    /// HP reading − shadow, exponential mean, bar.
    pub hp_dev: Fx,
    /// Steps left in the window.
    pub hp_left: u16,
    /// `hp_dev` at the last window's end, bar.
    pub hp_last: Fx,
    /// The model's own change of P2 over the window so far (the shadow's), bar.
    pub hp_change: Fx,
    /// Every step of the window so far could be judged (a reading, P2 between the empty
    /// accumulator and the relief).
    pub hp_judged: bool,
    /// The oil the model says went into HP (pump − valve − relief) while the HP reading has
    /// stayed below the shadow check's range, L/min·s (`stuck_low`).
    pub low_inflow: Fx,
    /// Consecutive steps the shadow has disagreed (it names the HP reading only after
    /// `SHADOW_PERSIST_STEPS` of them with the encoder moving).
    pub hp_flag_steps: u16,
    /// The latest judgment's verdict: the reading disagreed with the model.
    pub hp_flag: bool,
    /// Windows ended since the estimator started or the reading came back (saturating): the
    /// first full window starts from an estimate still settling on the readings and is not
    /// judged.
    pub hp_windows: u8,
    /// This step was judged (from `SHADOW_JUDGE_FROM` steps into a window, warm, P2 in range
    /// throughout the window so far).
    pub hp_last_judged: bool,
    /// |`hp_dev`| less the allowance in proportion to the model's change, at the latest judged
    /// step (what the fixed allowance must cover), bar.
    pub hp_excess: Fx,
    /// Consecutive steps the motor residual has been beyond its limit.
    pub motor_over: u16,
    /// Consecutive steps the LP residual has been beyond its limit.
    pub lp_over: u16,
    /// Steps with an LP reading since the estimator started (saturating): the check judges
    /// from `LP_SETTLE_STEPS` on, once the LP estimate has had the time to come to the
    /// readings from wherever it started (a controller that boots does not know LP).
    pub lp_seen: u16,
    /// LP reading − predicted LP, bar.
    pub lp: Fx,
    /// Measured − modelled motor speed, rpm.
    pub motor: Fx,
}

/// Window of the pressure residuals' means: 2^10 steps (1 s at 2^−10 s).
pub const PRESSURE_SHIFT: u32 = 10;
/// Window of the motor residual's mean: 2^8 steps (0.25 s at 2^−10 s).
pub const MOTOR_SHIFT: u32 = 8;

/// One step of an exponential mean `r` toward `e` with gain 2^−`shift`.
#[inline(always)]
pub(super) fn mean(r: &mut Fx, e: Fx, shift: u32) {
    *r = r.saturating_add(Fx::from_bits(e.saturating_sub(*r).to_bits() >> shift));
}

/// Steps in a shadow window: 2^12 (4 s at 2^−10 s).
pub const SHADOW_STEPS: u16 = 4096;
/// Window of the shadow deviation's mean: 2^8 steps.
pub const SHADOW_SHIFT: u32 = 8;
/// The HP shadow check's fixed allowance, bar: the reading's noise (σ 0.5 bar, ≈ 0.02 bar in a
/// 2^8-step mean), the estimate's own error when the shadow starts (σ ≈ 0.05 bar) and the
/// model's error over 4 s where P2 hardly moves, with margin.
pub const HP_ALLOW_BAR: Fx = Fx::from_bits(1 << 14);
/// The HP shadow check's allowance in proportion to the model's own change over the window,
/// as a right shift (3: an eighth): the model's flows are not exact, and where P2 moves by
/// 20 bar in 4 s a 10 % flow error is 2 bar. (A quarter let a reading drifting 0.2 bar/s
/// through a charge pass for 33 s; with an eighth the largest excess over every validation
/// run is 0.16 bar.)
pub const HP_ALLOW_SHIFT: u32 = 3;

/// The motor residual's fixed allowance, rpm.
pub const MOTOR_ALLOW_RPM: Fx = Fx::from_bits(5 << 16);
/// The motor residual's allowance in proportion to the modelled speed, as a right shift (4:
/// 1/16).
pub const MOTOR_ALLOW_SHIFT: u32 = 4;
/// The motor residual must stay beyond its allowance this many steps (1 s at 2^−10 s): the
/// valve's first opening, where the plant's motor line delays and overshoots the rotor (≈ 70 ms,
/// ≈ 15 %), passes well within it.
pub const MOTOR_PERSIST_STEPS: u16 = 1024;

/// The shadow check judges from this many steps into a window on (1 s: the deviation's 2^8-step
/// mean has settled), every step to the window's end: a fault that falls late in one window is
/// judged in the next from its first second on, not only at its end — flagged within 5 s
/// wherever it falls (at window ends alone: up to 7 s for a reading stuck while P2 crept).
pub const SHADOW_JUDGE_FROM: u16 = 1024;

/// The shadow check names the HP reading only while the encoder has moved within this many
/// steps (0.5 s; a regular wave's reversal holds the count ≈ 0.2 s): a stuck encoder starves the
/// shadow of the pump's flow and must not be taken for a faulty transducer.
pub const SHADOW_ENCODER_STILL_STEPS: u16 = 512;
/// The shadow must disagree this many steps in a row (0.5 s) before it names the HP reading:
/// a stuck encoder starves it of the pump's flow within 0.3 s at 100 bar, before the encoder
/// has stood still long enough to be suspected; by 0.5 s it has.
pub const SHADOW_PERSIST_STEPS: u16 = 512;

/// One step of the HP shadow check: `inc` is the step's predicted change of P2, `p2` the
/// estimate after this step's correction, `z` the HP reading (if taken), `judged` whether P2 is
/// where the check holds. Returns the latest judgment's verdict.
#[inline(always)]
pub(super) fn shadow(r: &mut ResidualState, inc: Fx, p2: Fx, z: Option<Fx>, judged: bool) -> bool {
    match z {
        Some(z) => {
            r.shadow = r.shadow.saturating_add(inc);
            r.hp_change = r.hp_change.saturating_add(inc);
            r.hp_judged &= judged;
            mean(&mut r.hp_dev, z.saturating_sub(r.shadow), SHADOW_SHIFT);
            r.hp_last_judged = false;
            if r.hp_left <= SHADOW_STEPS - SHADOW_JUDGE_FROM {
                r.hp_excess = r
                    .hp_dev
                    .abs()
                    .saturating_sub(Fx::from_bits(r.hp_change.abs().to_bits() >> HP_ALLOW_SHIFT));
                r.hp_last_judged = r.hp_windows >= 2 && r.hp_judged;
                r.hp_flag = r.hp_last_judged && r.hp_excess > HP_ALLOW_BAR;
            }
            if r.hp_left == 0 {
                r.hp_last = r.hp_dev;
                r.hp_windows = r.hp_windows.saturating_add(1);
                restart(r, p2);
            } else {
                r.hp_left -= 1;
            }
        }
        None => {
            restart(r, p2);
            (r.hp_flag, r.hp_windows, r.hp_last_judged) = (false, 0, false);
            // A missing (or held) reading restarts the stuck-low sum too.
            r.low_inflow = ZERO;
        }
    }
    r.hp_flag
}

/// The stuck-low sum forgets with this shift a step (2^17 steps, 128 s at 2^−10 s): a model
/// flow error of 0.2 L/min held at a P2 just below the shadow's range sums to 0.43 L, not
/// without bound (the limit is 0.64 L on the reference bench), while a reading stuck under a
/// charge (≈ 2.4 L/min of net inflow) still passes the limit (its sum would level at 5 L).
pub const LOW_FORGET_SHIFT: u32 = 17;

impl ResidualState {
    /// Every check stands down and starts afresh (the shadow's windows, the sums): the model's
    /// flows no longer describe the plant — the controller's dump valve, which the model does
    /// not know, is open.
    pub fn stand_down(&mut self) {
        restart(self, self.shadow);
        (self.hp_flag, self.hp_windows, self.hp_last_judged) = (false, 0, false);
        (self.low_inflow, self.hp_flag_steps) = (ZERO, 0);
    }
}

/// One step of the stuck-low check: while the HP reading `z` stays below `empty_below` (the
/// shadow check's range: the accumulator empty or nearly, by the reading), the model's net
/// inflow into HP `q_net` (L/min) is summed (not below zero); past `limit` (L/min·s: what the
/// accumulator holds there, and more) the reading cannot be right — that much oil would have
/// lifted P2 above it. The shadow cannot judge there: below the precharge P2 is the lines'
/// stiff oil, where its predicted change is bars per cm³ and off by as much. Returns whether
/// past the limit.
#[inline(always)]
pub(super) fn stuck_low(
    r: &mut ResidualState,
    q_net: Fx,
    z: Fx,
    empty_below: Fx,
    limit: Fx,
    dt_log2: u8,
) -> bool {
    if z < empty_below {
        let forget = Fx::from_bits(r.low_inflow.to_bits() >> LOW_FORGET_SHIFT);
        r.low_inflow = r
            .low_inflow
            .saturating_sub(forget)
            .saturating_add(crate::fx::mul_dt(q_net, dt_log2))
            .max(ZERO);
    } else {
        r.low_inflow = ZERO;
    }
    r.low_inflow > limit
}

fn restart(r: &mut ResidualState, p2: Fx) {
    (r.shadow, r.hp_dev, r.hp_left) = (p2, ZERO, SHADOW_STEPS);
    (r.hp_change, r.hp_judged) = (ZERO, true);
}

/// The motor check's allowance around the modelled speed `model`, rpm: 5 rpm +
/// 1/16 of it (also what the firmware's clearing asks of a held motor pickup).
#[inline(always)]
pub fn motor_allowance(model: Fx) -> Fx {
    MOTOR_ALLOW_RPM.saturating_add(Fx::from_bits(model.abs().to_bits() >> MOTOR_ALLOW_SHIFT))
}

/// One step of the motor check: `m` the measured speed, `model` the modelled one (rpm).
/// Returns whether the residual has been beyond its allowance for [`MOTOR_PERSIST_STEPS`].
#[inline(always)]
pub(super) fn motor(r: &mut ResidualState, m: Fx, model: Fx) -> bool {
    mean(&mut r.motor, m.saturating_sub(model), MOTOR_SHIFT);
    if r.motor.abs() > motor_allowance(model) {
        r.motor_over = r.motor_over.saturating_add(1);
    } else {
        r.motor_over = 0;
    }
    r.motor_over >= MOTOR_PERSIST_STEPS
}

/// The LP residual's allowance, bar: its 1 s mean against the model reached 0.88 bar in the
/// validation runs (at the relief, whose flow into LP the reduced law has to within ≈ 1 bar),
/// twice that with margin. An LP reading off by less stays undetected; it moves the motor
/// branch's pressure drop, not the trip.
pub const LP_ALLOW_BAR: Fx = Fx::from_bits(2 << 16);
/// The LP residual must stay beyond its allowance this many steps (1 s).
pub const LP_PERSIST_STEPS: u16 = 1024;
/// Steps with a reading before the LP check judges (4 s).
pub const LP_SETTLE_STEPS: u16 = 4096;

/// One step of the LP check with the reading `z` against the predicted LP: returns whether the
/// residual's mean has been beyond [`LP_ALLOW_BAR`] for [`LP_PERSIST_STEPS`].
#[inline(always)]
pub(super) fn lp(r: &mut ResidualState, z: Fx, predicted: Fx) -> bool {
    mean(&mut r.lp, z.saturating_sub(predicted), PRESSURE_SHIFT);
    r.lp_seen = r.lp_seen.saturating_add(1);
    if r.lp.abs() > LP_ALLOW_BAR && r.lp_seen >= LP_SETTLE_STEPS {
        r.lp_over = r.lp_over.saturating_add(1);
    } else {
        r.lp_over = 0;
    }
    r.lp_over >= LP_PERSIST_STEPS
}

#[cfg(test)]
mod tests {
    use super::*;

    const STEP_S: f64 = 1.0 / 1024.0;

    /// P2 rising at `rate` bar/s, the model predicting `model_gain` × that; the reading stuck
    /// at its value from `fault_s` on (never, if `None`). Returns when the check first flagged,
    /// s (the estimate after each correction taken as the reading: a fully trusted transducer).
    fn first_flag(rate: f64, model_gain: f64, fault_s: Option<f64>) -> Option<f64> {
        let mut r = ResidualState::default();
        let inc = Fx::from_num(rate * model_gain * STEP_S);
        let mut stuck = None;
        for k in 0..(60 * 1024) {
            let t = f64::from(k) * STEP_S;
            let truth = 60.0 + rate * t;
            let z = match fault_s {
                Some(f) if t >= f => *stuck.get_or_insert(truth),
                _ => truth,
            };
            let z = Fx::from_num(z);
            if shadow(&mut r, inc, z, Some(z), true) {
                return Some(t);
            }
        }
        None
    }

    /// A reading stuck while P2 creeps at 0.2 bar/s is flagged within 5 s wherever in a window
    /// the fault falls (judged at window ends alone: 5.5 s when it falls 2.5 s into one); the
    /// model's flows 10 % off with a healthy reading are never flagged.
    #[test]
    fn a_stuck_reading_is_flagged_within_5_s_wherever_it_falls_in_a_window() {
        let window_s = f64::from(SHADOW_STEPS) / 1024.0;
        for k in 0..16 {
            let fault = 5.0 * window_s + f64::from(k) * window_s / 16.0;
            let at = first_flag(0.2, 1.0, Some(fault)).expect("never flagged");
            assert!(
                (0.0..=5.0).contains(&(at - fault)),
                "fault {fault:.2} s: flagged {:.2} s after",
                at - fault
            );
        }
        for gain in [0.9, 1.0, 1.1] {
            assert_eq!(first_flag(0.2, gain, None), None, "model gain {gain}");
            assert_eq!(first_flag(5.0, gain, None), None, "model gain {gain}");
        }
    }

    /// Under a reading below the empty band the model's net inflow is summed (never below 0):
    /// 6 L/min pumped in passes a 12 L/min·s (0.2 L) limit after 2 s; a steady small flow
    /// error levels off; a reading above the band starts the sum again; outflow alone never
    /// trips it.
    #[test]
    fn oil_pumped_under_a_reading_stuck_low_is_counted_to_its_limit() {
        let (below, limit) = (Fx::from_num(27.0), Fx::from_num(12.0));
        let run = |q: f64, z: f64, steps: u32| {
            let mut r = ResidualState::default();
            (0..steps)
                .position(|_| stuck_low(&mut r, Fx::from_num(q), Fx::from_num(z), below, limit, 10))
                .map(|k| k as f64 / 1024.0)
        };
        // With the sum forgetting over τ = 128 s: q·τ·(1 − e^(−t/τ)) = limit, t = 2.016 s.
        let tau = f64::from(1u32 << LOW_FORGET_SHIFT) / 1024.0;
        let want = -tau * (1.0 - 12.0 / (6.0 * tau)).ln();
        let t = run(6.0, 15.0, 4096).expect("never");
        assert!((t - want).abs() < 0.01, "{t} against {want}");
        // A steady flow error of 0.2 L/min levels off at 0.2·τ = 25.6 L/min·s, not beyond.
        let mut r = ResidualState::default();
        for _ in 0..(20 << 17) {
            stuck_low(
                &mut r,
                Fx::from_num(0.2),
                Fx::from_num(15.0),
                below,
                Fx::MAX,
                10,
            );
        }
        let level = r.low_inflow.to_num::<f64>();
        assert!((level - 0.2 * tau).abs() < 0.5, "{level}");
        assert_eq!(run(6.0, 40.0, 8192), None, "a reading above the band");
        assert_eq!(run(-6.0, 15.0, 8192), None, "outflow");
        let mut r = ResidualState::default();
        for _ in 0..1500 {
            stuck_low(
                &mut r,
                Fx::from_num(6.0),
                Fx::from_num(15.0),
                below,
                limit,
                10,
            );
        }
        stuck_low(
            &mut r,
            Fx::from_num(6.0),
            Fx::from_num(30.0),
            below,
            limit,
            10,
        );
        assert_eq!(r.low_inflow, ZERO, "the band left: counted afresh");
    }
}
