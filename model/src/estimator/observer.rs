//! The observer: the HP and LP nodes' prediction from the step's flows, the P2 correction with
//! the HP transducer (a scalar Kalman update behind an innovation gate, with fading memory on
//! rejections and a reset after a run of them), the least P2 variance without it near the
//! precharge, and LP's fixed-gain correction.

use super::*;
use crate::coeffs::{LP_MAX_BAR, N_LP, N_NODE, P_MAX_BAR, capacitance, capacitance_node, fx};
use crate::config::ModelConfig;
use libm::sqrtf;

/// The observer's coefficients (`estimator::observer`): the nodes' prediction, the Kalman
/// update of P2 with the HP transducer and the fixed-gain correction of LP.
#[derive(Debug, Clone, PartialEq, Default)]
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

impl ObserverCoeffs {
    /// The observer's coefficients for `cfg` at the step `dt` s.
    #[inline(never)]
    pub(crate) fn of(cfg: &ModelConfig, dt: f32) -> ObserverCoeffs {
        let lp_nom = cfg.nominal_lp_bar;
        let (h_hp, h_lp) = (
            Table1::<N_NODE>::spacing(0.0, P_MAX_BAR),
            Table1::<N_LP>::spacing(0.0, LP_MAX_BAR),
        );
        let inv_c_hp = Table1::sample(0.0, P_MAX_BAR, |p| {
            1.0 / (60.0 * capacitance_node(cfg, &cfg.hp_accumulator, p, h_hp))
        });
        let inv_c_lp = Table1::sample(0.0, LP_MAX_BAR, |p| {
            1.0 / (60.0 * capacitance_node(cfg, &cfg.lp_accumulator, p, h_lp))
        });
        let r = cfg.pressure_noise_bar * cfg.pressure_noise_bar;
        // LP: steady-state gain for the flow uncertainty at nominal LP.
        let ic_lp = 1.0 / (60.0 * capacitance(cfg, &cfg.lp_accumulator, lp_nom));
        let qf = cfg.process_noise_lpm_per_sqrt_s * ic_lp;
        let q = qf * qf * dt;
        let gain = |v: f32| v / (v + r);
        let pp = 0.5 * (q + sqrtf(q * q + 4.0 * q * r));
        ObserverCoeffs {
            inv_c_hp,
            inv_c_lp,
            q_step: Table1::sample(0.0, P_MAX_BAR, |p| {
                let ic = 1.0 / (60.0 * capacitance_node(cfg, &cfg.hp_accumulator, p, h_hp));
                let qf = cfg.process_noise_lpm_per_sqrt_s * ic;
                (qf * qf * dt).max(1.0 / 65_536.0)
            }),
            q_relief: fx(cfg.relief_process_noise_bar_per_sqrt_s
                * cfg.relief_process_noise_bar_per_sqrt_s
                * dt),
            relief_setting_bar: fx(cfg.relief_setting_bar),
            r: fx(r),
            gain_fine: Table1::sample(0.0, r, gain),
            gain_coarse: Table1::sample(0.0, 32.0 * r, gain),
            gain_lp: fx(pp / (pp + r)),
            gate_sq: fx(cfg.gate_sigma * cfg.gate_sigma),
            gate_reset_steps: (cfg.gate_reset_ms * 1e-3 / dt).clamp(1.0, 60_000.0) as u16,
            var_fade_max: fx(16.0 * r),
            hp_range_bar: (fx(cfg.hp_sensor_range_bar.0), fx(cfg.hp_sensor_range_bar.1)),
            lp_range_bar: (fx(cfg.lp_sensor_range_bar.0), fx(cfg.lp_sensor_range_bar.1)),
            precharge_band_top_bar: fx(cfg.hp_accumulator.precharge_bar + cfg.precharge_band_bar),
            var_precharge: fx(cfg.precharge_sigma_bar * cfg.precharge_sigma_bar),
        }
    }

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
        let g = k.gain_q32(n.var, n.var_lo);
        let d = clamp(z, P_MIN, P_MAX) - n.p2;
        (n.p2, n.p2_lo) = split(
            (ext(n.p2, n.p2_lo) + (wide::mul_su(d.to_bits(), g) >> 16))
                .clamp(ext(P_MIN, 0), ext(P_MAX, 0)),
        );
        let dv =
            (wide::mul_su(n.var.to_bits(), g) >> 16) + (wide::mul_su(i32::from(n.var_lo), g) >> 32);
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
