//! The observer: the HP and LP nodes' prediction from the step's flows, the P2 correction with
//! the HP transducer (a scalar Kalman update behind an innovation gate, with fading memory on
//! rejections and a reset after a run of them), the least P2 variance without it near the
//! precharge, and LP's fixed-gain correction.

use super::*;

/// The nodes' state: P2 and LP, P2's variance, each kept to 16 bits below its Q16.16 LSB
/// (see `node_step`), and the gate's count of rejections.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct NodeState {
    /// P2, bar.
    pub p2: Fx,
    /// The 16 bits of P2 below its Q16.16 LSB (units of 2^−32 bar): see `node_step`.
    pub p2_lo: u16,
    /// P2 variance, bar².
    pub var: Fx,
    /// The 16 bits of the P2 variance below its Q16.16 LSB (units of 2^−32 bar²). Near its
    /// steady value (≈ 0.002 bar², 130 LSBs) the Kalman update's shrink (1 − g)·var is ≈ 1 LSB
    /// per step: floored to the LSB, the variance would run 20 % below the f64 model's, its
    /// gain with it, and P2 up to 0.15 bar away from the f64 model where it crosses the
    /// precharge.
    pub var_lo: u16,
    /// LP, bar.
    pub lp: Fx,
    /// The 16 bits of LP below its Q16.16 LSB (units of 2^−32 bar).
    pub lp_lo: u16,
    /// Consecutive rejected HP readings.
    pub rejected: u16,
}

/// The nodes' prediction over one step from the flows (L/min) into HP (`q_pump`, the pump's
/// delivery) and out of it (`q_valve`, `q_relief`, both into LP) and out of LP (`q_lp`, the
/// cylinders' suction net of their idle return); P2's variance grows by the process noise at
/// P2. Inlined into the step, its only caller.
#[inline(always)]
pub(super) fn predict(
    k: &ObserverCoeffs,
    dtl: u8,
    n: &mut NodeState,
    q_pump: Fx,
    q_valve: Fx,
    q_relief: Fx,
    q_lp: Fx,
) {
    let net_hp = q_pump.saturating_sub(q_valve).saturating_sub(q_relief);
    let dp_per_flow = k.inv_c_hp.at(n.p2);
    node_step(&mut n.p2, &mut n.p2_lo, net_hp, dp_per_flow, dtl);
    let net_lp = q_valve.saturating_add(q_relief).saturating_sub(q_lp);
    let dp_per_flow = k.inv_c_lp.at(n.lp);
    node_step(&mut n.lp, &mut n.lp_lo, net_lp, dp_per_flow, dtl);
    // The process noise to 2^−32 bar² (`Table1::at_ext`): on the empty node it is ≈ 0.08 bar²
    // a step, and its Q16.16 rounding moved the Kalman gain by 3·10^−5 — a few P2 LSBs per
    // bar of innovation. Held below the variance's Q16.16 top.
    (n.var, n.var_lo) = split((ext(n.var, n.var_lo) + k.q_step.at_ext(n.p2)).min(ext(Fx::MAX, 0)));
}

/// One Kalman update of P2 with the HP reading `z` (bar, inside the transducer's range). Inlined
/// into the step, its only caller.
#[inline(always)]
pub(super) fn kalman(k: &ObserverCoeffs, n: &mut NodeState, z: Fx, faults: &mut u16) {
    // On the relief P2 is set by the reduced relief law, whose bias the filter must take
    // from the transducer (`ModelConfig::relief_process_noise_bar_per_sqrt_s`).
    if n.p2 >= k.relief_setting_bar {
        n.var = n.var.saturating_add(k.q_relief);
    }
    let innov = z.saturating_sub(n.p2);
    let s_innov = n.var.saturating_add(k.r);
    if innov.qmul(innov) <= k.gate_sq.qmul(s_innov) {
        // The gain to 2^−32 (`ObserverCoeffs::gain_q32`); P2 += g·(z − P2) and
        // var ← (1 − g)·var kept to 2^−32 (see `NodeState::var_lo`). Bit budget: g ≤ 2^32
        // times a Q16.16 value (< 2^31 in magnitude) is < 2^63; P2's bits below the LSB
        // are left out of the innovation (≤ g·2^−16 bar, 0.01 LSB at the steady gain).
        let g = i64::from(k.gain_q32(n.var, n.var_lo));
        let d = clamp(z, P_MIN, P_MAX) - n.p2;
        (n.p2, n.p2_lo) = split(
            (ext(n.p2, n.p2_lo) + ((g * i64::from(d.to_bits())) >> 16))
                .clamp(ext(P_MIN, 0), ext(P_MAX, 0)),
        );
        let dv =
            ((g * i64::from(n.var.to_bits())) >> 16) + ((g * i64::from(i32::from(n.var_lo))) >> 32);
        (n.var, n.var_lo) = split(ext(n.var, n.var_lo) - dv);
        n.rejected = 0;
    } else {
        *faults |= fault::INNOVATION;
        // Fading memory: each rejection widens the gate and raises the next gain, so a
        // persistent model error (e.g. a stuck encoder hiding the pump flow) is taken in
        // within a few steps; the ceiling keeps a burst of outliers outside the gate.
        if n.var < k.var_fade_max {
            n.var = n.var.saturating_add(k.r).min(k.var_fade_max);
        }
        n.rejected = n.rejected.saturating_add(1);
        if n.rejected >= k.gate_reset_steps {
            *faults |= fault::INNOVATION_RESET;
            (n.p2, n.p2_lo) = (z, 0);
            (n.var, n.var_lo) = (k.r, 0);
            n.rejected = 0;
        }
    }
}

/// Without the HP transducer, P2's least variance near the precharge. Within the band above it
/// the accumulator's last cm³ decide when it runs empty, and P2 then falls to the empty node's
/// level (5–15 bar lower) within tens of ms, faster than any reading of the motor follows; on
/// the empty node P2 follows the pump flow, and rises back as fast when it refills. P2's
/// standard deviation is at least `ModelConfig::precharge_sigma_bar` in both, after the motor
/// reading has had its say. Inlined into the step, its only caller.
#[inline(always)]
pub(super) fn model_only_floor(k: &ObserverCoeffs, n: &mut NodeState) {
    if n.p2 <= k.precharge_band_top_bar && n.var < k.var_precharge {
        (n.var, n.var_lo) = (k.var_precharge, 0);
    }
}

/// LP's fixed-gain correction with the LP reading (bar), if it is read and inside the
/// transducer's range; else [`fault::LP_SENSOR`]. Inlined into the step, its only caller.
#[inline(always)]
pub(super) fn correct_lp(
    k: &ObserverCoeffs,
    n: &mut NodeState,
    lp: Option<Pressure>,
    faults: &mut u16,
) {
    match lp
        .map(|p| p.0)
        .filter(|p| *p >= k.lp_range_bar.0 && *p <= k.lp_range_bar.1)
    {
        Some(z) => correct(&mut n.lp, &mut n.lp_lo, k.gain_lp, z),
        None => *faults |= fault::LP_SENSOR,
    }
}
