//! Values kept to 16 bits below the Q16.16 LSB: the pressure nodes, the Kalman variance and
//! the motor flow integrate increments smaller than one LSB without losing them.

use super::*;

/// A pressure node's value to 2^−32 bar (Q16.32 in an `i64`): its Q16.16 value and the 16 bits
/// below that.
#[inline]
pub(super) fn ext(p: Fx, lo: u16) -> i64 {
    (i64::from(p.to_bits()) << 16) | i64::from(lo)
}

/// Splits a Q16.32 node value back into its Q16.16 value and the 16 bits below.
#[inline]
pub(super) fn split(e: i64) -> (Fx, u16) {
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
pub(super) fn node_step(p: &mut Fx, lo: &mut u16, net_inflow: Fx, dp_per_flow: Fx, dtl: u8) {
    let q = clamp(net_inflow, -FLOW_LIM, FLOW_LIM);
    let d = shr64(
        wide::mul(q.to_bits(), dp_per_flow.to_bits()),
        u32::from(dtl),
    );
    (*p, *lo) = split((ext(*p, *lo) + d).clamp(ext(P_MIN, 0), ext(P_MAX, 0)));
}

/// x += g·(target − x) with g ∈ [0, 1], x kept to 16 bits below its Q16.16 LSB like
/// [`node_step`]: the Q16.16 product g·(target − x) is exact in Q32.32. The result lies between
/// x and the target, so it needs no clamp (the difference of two values in range must not
/// overflow: both are held to a physical range well inside ±2^15).
#[inline]
pub(super) fn relax(x: &mut Fx, lo: &mut u16, g: Fx, target: Fx) {
    let d = target - *x;
    (*x, *lo) = split(ext(*x, *lo) + wide::mul(g.to_bits(), d.to_bits()));
}

/// An observer correction p += g·(z − p) with g ∈ [0, 1] ([`relax`]). The reading is first held
/// to the physical pressure range (a transducer's accepted range may reach past it, e.g.
/// −2 bar), so the result, between p and that, stays inside it.
#[inline]
pub(super) fn correct(p: &mut Fx, lo: &mut u16, g: Fx, z: Fx) {
    relax(p, lo, g, clamp(z, P_MIN, P_MAX));
}
