//! The P2 correction with the HP transducer: a scalar Kalman update behind an innovation gate,
//! with fading memory on rejections and a reset after a run of them.

use super::*;

/// One Kalman update of P2 with the HP reading `z` (bar, inside the transducer's range). Inlined
/// into the step, its only caller.
#[inline(always)]
pub(super) fn kalman(k: &Coefficients, s: &mut State, z: Fx, faults: &mut u16) {
    // On the relief P2 is set by the reduced relief law, whose bias the filter must take
    // from the transducer (`ModelConfig::relief_process_noise_bar_per_sqrt_s`).
    if s.p2 >= k.relief_setting {
        s.var = s.var.saturating_add(k.q_relief);
    }
    // The motor reading restarts when the transducer goes missing again.
    (s.reading.live, s.reading.wait) = (false, 0);
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
        let dv =
            ((g * i64::from(s.var.to_bits())) >> 16) + ((g * i64::from(i32::from(s.var_lo))) >> 32);
        (s.var, s.var_lo) = split(ext(s.var, s.var_lo) - dv);
        s.rejected = 0;
    } else {
        *faults |= fault::INNOVATION;
        // Fading memory: each rejection widens the gate and raises the next gain, so a
        // persistent model error (e.g. a stuck encoder hiding the pump flow) is taken in
        // within a few steps; the ceiling keeps a burst of outliers outside the gate.
        if s.var < k.var_fade_max {
            s.var = s.var.saturating_add(k.r).min(k.var_fade_max);
        }
        s.rejected = s.rejected.saturating_add(1);
        if s.rejected >= k.gate_reset_steps {
            *faults |= fault::INNOVATION_RESET;
            (s.p2, s.p2_lo) = (z, 0);
            (s.var, s.var_lo) = (k.r, 0);
            s.rejected = 0;
        }
    }
}
