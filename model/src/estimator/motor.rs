//! The valve/motor branch (the rotor's flow, the relief) and the motor speed read as a pressure,
//! to correct P2 without the HP transducer.

use super::*;

/// The motor reading's state: its filters and its phase.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ReadingState {
    /// Measured motor flow (speed / rpm per L/min), low-passed, L/min (the motor reading, used
    /// without the HP transducer: see `estimator::motor_reading`).
    pub q: Fx,
    /// LP + F(measured motor flow), low-passed, bar.
    pub f: Fx,
    /// The motor reading's step: odd (the guards, F and both filters) or even (P2's
    /// correction).
    pub odd: bool,
    /// The reading's dead band as of the last odd step, bar.
    pub band: Fx,
    /// `q` and `f` follow the motor sensor. They run while the HP reading is missing,
    /// the spool stands at its command and the valve is open enough, and restart from the
    /// sensor after any of these changes.
    pub live: bool,
    /// Correction steps the reading still waits before P2 takes it: set to
    /// [`ReadingCoeffs::warm_steps`](crate::coeffs::ReadingCoeffs::warm_steps) while the spool moves or the valve is near
    /// closed (the rotor may then be accelerating, which filters started from one sample do not
    /// know yet).
    pub wait: u16,
    /// Variance of the motor reading as of the last odd step, bar²: its noise and its dead
    /// band (an error spread evenly over ±band: band²/3). P2's variance relaxes toward it as
    /// the reading corrects P2.
    pub var: Fx,
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
pub(super) fn motor_reading(
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
    if !s.reading.live {
        s.reading.q = q_m;
        s.reading.f = lp_plus_f(lp_dp, q_ss, q_m, mul_bounded(g, k.reading.ldt));
        (s.reading.live, s.reading.odd) = (true, false);
        return 0;
    }
    // The work alternates between two steps, each filter running at half rate, so that a
    // step costs about what the HP transducer's Kalman update it replaces does: the guards, F
    // and both filters in one, P2's correction in the other.
    s.reading.odd = !s.reading.odd;
    if s.reading.odd {
        // dF/dQ = g·L/dt: g ≤ 1 and L/dt < 2^15 bar per L/min (a saturated coefficient), so
        // the product fits.
        // Plausibility: the flow read must be one the valve can pass at the modelled aperture
        // and LP with P2 at most at the relief (plus the gate's worth of the reading's noise)
        // — the valve table at that ΔP, plus the reading's band and the sensor's floor. A
        // faster motor contradicts the model (or the sensor is wrong): flagged, and the
        // reading restarts, so P2 never takes it.
        let q_cap = k
            .valve_flow
            .at(s.aperture, k.reading.p2_max.saturating_sub(s.lp));
        let q_cap = q_cap
            .saturating_add(mul_bounded(q_cap, k.reading.band))
            .saturating_add(k.reading.min_lpm);
        if q_m > q_cap {
            (s.reading.live, s.reading.wait) = (false, k.reading.warm_steps);
            return fault::MOTOR_IMPLAUSIBLE;
        }
        let slope = mul_bounded(g, k.reading.ldt);
        if slope > k.reading.max_slope || cmd.saturating_sub(s.aperture).abs() > k.reading.spool_tol
        {
            // The valve near closed, or the spool moving: no reading; the filters restart
            // once both end, and P2 takes the reading after they have run a while.
            (s.reading.live, s.reading.wait) = (false, k.reading.warm_steps);
            return 0;
        }
        let f = lp_plus_f(lp_dp, q_ss, q_m, slope);
        s.reading.f = filter(s.reading.f, k.reading.filter, f);
        // The derivative L·(Q_m − Q̄)/τ of the next step takes Q̄ as of this one.
        s.reading.q = filter(s.reading.q, k.reading.filter, q_m);
        // ΔP ≤ 400 bar × a band ≤ 0.5: fits.
        s.reading.band = mul_bounded(dp, k.reading.band);
        // band²/3 saturates above a 181 bar band: far beyond any P2 gate.
        s.reading.var = s
            .reading
            .band
            .qmul(s.reading.band)
            .qmul(ONE_THIRD)
            .saturating_add(k.reading.r);
        return 0;
    }
    if s.reading.wait > 0 {
        s.reading.wait -= 1;
    } else if q_m >= k.reading.min_lpm {
        let z = s
            .reading
            .f
            .saturating_add(q_m.saturating_sub(s.reading.q).qmul(k.reading.lt));
        // Only the part of the innovation beyond the band counts: inside it the reading does
        // not know P2 better than the model does.
        let e = z.saturating_sub(s.p2);
        let e = e - clamp(e, -s.reading.band, s.reading.band);
        // Plausibility: the flow read must be one the valve can pass at a P2 the relief allows,
        // i.e. the P2 it implies, less its band, at most the relief setting plus the gate's
        // worth of the reading's noise (F is monotone in the flow, so this is the valve's
        // capacity at the modelled aperture and LP without a table lookup). Beyond it the
        // speed sensor or the model is wrong: flagged, P2 not moved. (A gate on the distance
        // to P2 itself would refuse the readings the empty HP node needs most: there the
        // model can run empty 0.1 s before the bench, 17 bar below it.)
        if z.saturating_sub(s.reading.band) > k.reading.p2_max {
            return fault::MOTOR_IMPLAUSIBLE;
        }
        // P2 += gain·e, exact in Q32.32 (|e| < 2^31 bits × gain ≤ 2^16 bits: < 2^47) and kept
        // to 2^−32 like the node's prediction (rounded to the LSB it was half an LSB a step
        // from its f64 form), held to the pressure range.
        (s.p2, s.p2_lo) = split(
            (ext(s.p2, s.p2_lo) + i64::from(k.reading.gain.to_bits()) * i64::from(e.to_bits()))
                .clamp(ext(P_MIN, 0), ext(P_MAX, 0)),
        );
        // The reading brings P2's variance toward its own (never up to it).
        if s.var > s.reading.var {
            relax(&mut s.var, &mut s.var_lo, k.reading.gain, s.reading.var);
        }
    }
    0
}

/// 1/3 in Q16.16.
pub(super) const ONE_THIRD: Fx = Fx::from_bits(21_845);

/// LP + F(Q_m), bar, from F(Q_ss) = ΔP: F(Q_ss) − F(Q_m) = (Q_ss − Q_m)·dF/dQ.
#[inline(always)]
pub(super) fn lp_plus_f(lp_dp: Fx, q_ss: Fx, q_m: Fx, slope: Fx) -> Fx {
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
pub(super) fn filter(x: Fx, a: Fx, target: Fx) -> Fx {
    let d = (i64::from(a.to_bits()) * i64::from((target - x).to_bits()) + (1 << 15)) >> 16;
    x + Fx::from_bits(d as i32)
}

/// The valve/motor branch and the relief after one step (flows L/min, pressures bar).
pub(super) struct Branch {
    /// P2 − LP, held ≥ 0.
    pub(super) dp: Fx,
    /// LP + (P2 − LP).
    pub(super) lp_dp: Fx,
    /// The branch's steady flow at `dp`.
    pub(super) q_ss: Fx,
    /// The relaxation gain of this step.
    pub(super) g: Fx,
    /// Motor speed, rpm.
    pub(super) motor_rpm: Fx,
    /// Flow out of HP through the valve.
    pub(super) q_valve: Fx,
    /// Relief flow.
    pub(super) q_relief: Fx,
}

/// The valve/motor stage of a step: the rotor's flow relaxed toward the steady flow of the
/// pressure across the branch, and the relief. Inlined into the step, its only caller.
#[inline(always)]
pub(super) fn branch(k: &Coefficients, s: &mut State, first: bool) -> Branch {
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
    Branch {
        dp,
        lp_dp,
        q_ss,
        g,
        motor_rpm,
        q_valve,
        q_relief,
    }
}
