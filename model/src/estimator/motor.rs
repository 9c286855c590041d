//! The valve/motor branch (the rotor's flow, the relief) and the motor speed read as a pressure,
//! to correct P2 without the HP transducer.

use super::*;
use crate::coeffs::{MOTOR_GAIN_VALVE_CAP, N_APERTURE, N_PRESSURE, P_MAX_BAR, fx};
use crate::config::ModelConfig;
use crate::table::Table2;

/// The valve/motor branch's coefficients (`estimator::motor`): the spool, the rotor's flow
/// and the relief.
#[derive(Debug, Clone, PartialEq, Default)]
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

impl BranchCoeffs {
    /// The branch's coefficients for `cfg` at the step `dt` s, the rotor's inductance
    /// `inductance` ([`ModelConfig::motor_inductance`]), built into `self` in place.
    #[inline(never)]
    pub(crate) fn build(&mut self, cfg: &ModelConfig, dt: f32, inductance: f32) {
        self.valve_flow
            .sample_into((0.0, 100.0), (0.0, P_MAX_BAR), |a, dp| {
                cfg.steady_flow(a, dp)
            });
        let spool_gain = if cfg.spool_time_constant_ms <= 0.0 {
            1.0
        } else {
            (dt / (cfg.spool_time_constant_ms * 1e-3)).min(1.0)
        };
        self.spool_gain = fx(spool_gain);
        self.motor_gain0 = fx(dt * cfg.motor_bar_per_lpm() / inductance);
        // Sampled on the valve table's aperture rows (0..100 %, N_APERTURE nodes).
        self.motor_gain_valve = Table1::<N_APERTURE>::sample(0.0, 100.0, |a| {
            let kv = cfg.valve_k(a);
            if kv <= 0.0 {
                MOTOR_GAIN_VALVE_CAP
            } else {
                (dt / (inductance * kv * kv)).min(MOTOR_GAIN_VALVE_CAP)
            }
        })
        .y;
        self.rpm_per_lpm = fx(cfg.rpm_per_lpm());
        // Float-to-integer casts saturate; ≥ 1/10 000 rpm per L/min by validation.
        self.lpm_per_rpm_q24 = (16_777_216.0 / cfg.rpm_per_lpm()) as i32;
        self.relief_setting_bar = fx(cfg.relief_setting_bar);
        self.relief_gain_lpm_per_bar = fx(cfg.relief_gain_lpm_per_bar);
        self.spin_down_steps = (5.0 * cfg.rotor_time_constant_s() / dt).clamp(1.0, 60_000.0) as u16;
    }
}

/// The motor reading's coefficients (`estimator::motor_reading`), used without the HP
/// transducer.
#[derive(Debug, Clone, PartialEq, Default)]
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

impl ReadingCoeffs {
    /// The motor reading's coefficients for `cfg` at the step `dt` s, the rotor's inductance
    /// `inductance`. Its filters run every second step (`estimator::motor_reading`).
    #[inline(never)]
    pub(crate) fn of(cfg: &ModelConfig, dt: f32, inductance: f32) -> ReadingCoeffs {
        ReadingCoeffs {
            filter: fx((2.0 * dt / (cfg.motor_reading_filter_ms * 1e-3)).min(1.0)),
            ldt: fx(inductance / dt),
            lt: fx(inductance / (cfg.motor_reading_filter_ms * 1e-3)),
            gain: if cfg.motor_reading_time_constant_ms > 0.0 {
                fx((2.0 * dt / (cfg.motor_reading_time_constant_ms * 1e-3)).min(1.0))
            } else {
                Fx::ZERO
            },
            max_slope: fx(cfg.motor_reading_max_slope_bar_per_lpm),
            min_lpm: fx(cfg.motor_reading_min_rpm / cfg.rpm_per_lpm()),
            spool_tol: fx(cfg.motor_reading_spool_tolerance_pct),
            band: fx(cfg.motor_reading_band_pct * 1e-2),
            warm_steps: (1.5 * cfg.motor_reading_filter_ms * 1e-3 / dt).clamp(1.0, 60_000.0) as u16,
            min_aperture: fx(cfg.motor_reading_min_aperture_pct),
            min_rpm: fx(cfg.motor_reading_min_rpm),
            r: fx(cfg.motor_reading_noise_bar * cfg.motor_reading_noise_bar),
            p2_max: fx(cfg.relief_setting_bar + cfg.gate_sigma * cfg.motor_reading_noise_bar),
        }
    }
}

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

/// The valve/motor branch's state: the spool and the rotor's flow.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct BranchState {
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
    /// Consecutive steps with the valve closed (commanded or modelled aperture below
    /// `ReadingCoeffs::min_aperture`).
    pub closed_steps: u16,
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
    k: &ReadingCoeffs,
    kb: &BranchCoeffs,
    r: &mut ReadingState,
    n: &mut NodeState,
    aperture: Fx,
    rpm: Fx,
    cmd: Fx,
    br: &Branch,
) -> u16 {
    let Branch {
        lp_dp, dp, q_ss, g, ..
    } = *br;
    // 0 ≤ rpm ≤ 10 000 (< 2^30 bits; the caller range-checks it) × L/min per rpm (< 2^31
    // bits): < 2^61; held to the flow range like every flow the nodes take.
    let q_m = Fx::from_bits(
        ((wide::mul(rpm.to_bits(), kb.lpm_per_rpm_q24) + (1 << 23)) >> 24)
            .min(i64::from(FLOW_LIM.to_bits())) as i32,
    );
    if !r.live {
        r.q = q_m;
        r.f = lp_plus_f(lp_dp, q_ss, q_m, mul_bounded(g, k.ldt));
        (r.live, r.odd) = (true, false);
        return 0;
    }
    // The work alternates between two steps, each filter running at half rate, so that a
    // step costs about what the HP transducer's Kalman update it replaces does: the guards, F
    // and both filters in one, P2's correction in the other.
    r.odd = !r.odd;
    if r.odd {
        // dF/dQ = g·L/dt: g ≤ 1 and L/dt < 2^15 bar per L/min (a saturated coefficient), so
        // the product fits.
        // Plausibility: the flow read must be one the valve can pass at the modelled aperture
        // and LP with P2 at most at the relief (plus the gate's worth of the reading's noise)
        // — the valve table at that ΔP, plus the reading's band and the sensor's floor. A
        // faster motor contradicts the model (or the sensor is wrong): flagged, and the
        // reading restarts, so P2 never takes it.
        let q_cap = kb.valve_flow.at(aperture, k.p2_max.saturating_sub(n.lp));
        let q_cap = q_cap
            .saturating_add(mul_bounded(q_cap, k.band))
            .saturating_add(k.min_lpm);
        if q_m > q_cap {
            (r.live, r.wait) = (false, k.warm_steps);
            return fault::MOTOR_IMPLAUSIBLE;
        }
        let slope = mul_bounded(g, k.ldt);
        if slope > k.max_slope || cmd.saturating_sub(aperture).abs() > k.spool_tol {
            // The valve near closed, or the spool moving: no reading; the filters restart
            // once both end, and P2 takes the reading after they have run a while.
            (r.live, r.wait) = (false, k.warm_steps);
            return 0;
        }
        let f = lp_plus_f(lp_dp, q_ss, q_m, slope);
        r.f = filter(r.f, k.filter, f);
        // The derivative L·(Q_m − Q̄)/τ of the next step takes Q̄ as of this one.
        r.q = filter(r.q, k.filter, q_m);
        // ΔP ≤ 400 bar × a band ≤ 0.5: fits.
        r.band = mul_bounded(dp, k.band);
        // band²/3 saturates above a 181 bar band: far beyond any P2 gate.
        r.var = r.band.qmul(r.band).qmul(ONE_THIRD).saturating_add(k.r);
        return 0;
    }
    if r.wait > 0 {
        r.wait -= 1;
    } else if q_m >= k.min_lpm {
        let z = r.f.saturating_add(q_m.saturating_sub(r.q).qmul(k.lt));
        // Only the part of the innovation beyond the band counts: inside it the reading does
        // not know P2 better than the model does.
        let e = z.saturating_sub(n.p2);
        let e = e - clamp(e, -r.band, r.band);
        // Plausibility: the flow read must be one the valve can pass at a P2 the relief allows,
        // i.e. the P2 it implies, less its band, at most the relief setting plus the gate's
        // worth of the reading's noise (F is monotone in the flow, so this is the valve's
        // capacity at the modelled aperture and LP without a table lookup). Beyond it the
        // speed sensor or the model is wrong: flagged, P2 not moved. (A gate on the distance
        // to P2 itself would refuse the readings the empty HP node needs most: there the
        // model can run empty 0.1 s before the bench, 17 bar below it.)
        if z.saturating_sub(r.band) > k.p2_max {
            return fault::MOTOR_IMPLAUSIBLE;
        }
        // P2 += gain·e, exact in Q32.32 (|e| < 2^31 bits × gain ≤ 2^16 bits: < 2^47) and kept
        // to 2^−32 like the node's prediction (rounded to the LSB it was half an LSB a step
        // from its f64 form), held to the pressure range.
        (n.p2, n.p2_lo) = split(
            (ext(n.p2, n.p2_lo) + wide::mul(k.gain.to_bits(), e.to_bits()))
                .clamp(ext(P_MIN, 0), ext(P_MAX, 0)),
        );
        // The reading brings P2's variance toward its own (never up to it).
        if n.var > r.var {
            relax(&mut n.var, &mut n.var_lo, k.gain, r.var);
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
    let d = (wide::mul(a.to_bits(), (target - x).to_bits()) + (1 << 15)) >> 16;
    x + Fx::from_bits(d as i32)
}

/// The valve/motor branch and the relief after one step (flows L/min, pressures bar).
#[derive(Clone, Copy)]
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

/// The spool's lag behind the command (% , held to 0..100); returns the held command and
/// whether this is the state's first step. The first step takes the spool as settled at the
/// command (a state started from known pressures is a bench at rest or in steady running, not a
/// valve half way through a change). Inlined into the step, its only caller.
#[inline(always)]
pub(super) fn spool(k: &BranchCoeffs, b: &mut BranchState, aperture_cmd: Fx) -> (Fx, bool) {
    let first = !b.started;
    b.started = true;
    let cmd = clamp(aperture_cmd, ZERO, Fx::from_num(100));
    if first {
        b.aperture = cmd;
    } else {
        b.aperture = b
            .aperture
            .saturating_add(mul_frac(k.spool_gain, cmd.saturating_sub(b.aperture)));
    }
    (cmd, first)
}

/// The valve/motor stage of a step at P2 and LP (bar): the rotor's flow relaxed toward the
/// steady flow of the pressure across the branch, and the relief. On the first step the flow
/// starts at its steady value. Inlined into the step, its only caller.
#[inline(always)]
pub(super) fn branch(k: &BranchCoeffs, b: &mut BranchState, p2: Fx, lp: Fx, first: bool) -> Branch {
    // The rotor's inertia: L·dQ/dt = ΔP − F(Q) with F the branch's steady pressure drop
    // (`ModelConfig::motor_inductance`). F(Q_ss) = ΔP, and F(Q_ss) − F(Q) = (Q_ss − Q)·(β +
    // (Q_ss + Q)/K²) exactly for the turbulent valve, so one explicit step is a relaxation
    // toward the steady flow with gain dt/L·(β + (Q_ss + Q)/K²). Held to 1 (where the valve's
    // resistance makes the branch faster than a step, e.g. near closed), the flow takes its
    // steady value: it never overshoots, so the step is stable at every aperture.
    let dp = p2.saturating_sub(lp).max(ZERO);
    let lp_dp = lp.saturating_add(dp);
    let (q_ss, gain_valve) = k.valve_flow.at_with(b.aperture, dp, &k.motor_gain_valve);
    if first {
        (b.q_motor, b.q_motor_lo) = (q_ss, 0);
    }
    let g = k
        .motor_gain0
        .saturating_add(q_ss.saturating_add(b.q_motor).qmul(gain_valve))
        .min(ONE);
    relax(&mut b.q_motor, &mut b.q_motor_lo, g, q_ss);
    let motor_rpm = b.q_motor.qmul(k.rpm_per_lpm);
    // A coasting rotor that outruns the pressure across it (P2 down to LP: an empty HP node
    // when the pump stops) draws the rest through the make-up valve from LP, not from HP.
    let q_valve = if dp > ZERO { b.q_motor } else { ZERO };
    let q_relief = p2
        .saturating_sub(k.relief_setting_bar)
        .max(ZERO)
        .qmul(k.relief_gain_lpm_per_bar);
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

/// The valve closed, commanded (`cmd`, %) or modelled: the branch's flow then says nothing of
/// P2, and once the rotor has had the time to spin down a turning motor (`motor`, rpm, if read)
/// contradicts the model ([`fault::MOTOR_IMPLAUSIBLE`]) — if it turns faster than the model's
/// own rotor (`model_rpm`) by more than the reading's least speed: "closed" here is below the
/// motor reading's least aperture, where a valve under 1 % open still turns the motor at
/// 8–15 rpm (a hold-pressure start flagged that for ≈ 30–450 steps). Inlined into the step,
/// its only caller.
#[inline(always)]
pub(super) fn valve_closed(
    k: &ReadingCoeffs,
    kb: &BranchCoeffs,
    b: &mut BranchState,
    cmd: Fx,
    motor: Option<Rpm>,
    model_rpm: Fx,
    faults: &mut u16,
) -> bool {
    let closed = cmd < k.min_aperture || b.aperture < k.min_aperture;
    if closed {
        b.closed_steps = b.closed_steps.saturating_add(1);
        if b.closed_steps >= kb.spin_down_steps
            && motor.is_some_and(|m| m.0.saturating_sub(model_rpm) > k.min_rpm)
        {
            *faults |= fault::MOTOR_IMPLAUSIBLE;
        }
    } else {
        b.closed_steps = 0;
    }
    closed
}
