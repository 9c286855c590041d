//! The shaft stage: an α–β–γ tracker on the encoder angle, its residual, and the
//! expanding-memory start-up.

use super::*;

/// The tracker's residual, measured less predicted angle (Q32.32), held to ±0.5 rad so that it
/// fits an i32.
#[inline(always)]
pub(super) fn residual(theta_meas: i64, pred_theta: i64) -> i64 {
    i64::from((theta_meas - pred_theta).clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32)
}

/// The shaft tracker's first reading (it starts there, at rest) and its first
/// [`Coefficients::tracker_startup_len`] updates after it: the expanding-memory gains
/// [`TRACKER_STARTUP`] (the least-squares line through every reading so far), the acceleration
/// held at 0 until the fading-memory tracker takes over. Out of line: the steady step only
/// tests its phase.
#[inline(never)]
#[cold]
pub(super) fn tracker_startup(
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

/// The shaft stage of a step: the α–β–γ tracker on the encoder angle, in Q32.32 (i64), its
/// start-up and drop-outs, and the stuck-encoder check; returns the angle (rad) and speed
/// (rad/s) in Q16.16. Inlined into the step, its only caller.
#[inline(always)]
pub(super) fn track(k: &Coefficients, s: &mut State, inp: &Inputs, faults: &mut u16) -> (Fx, Fx) {
    // Bit budget: one count is < 2^29 (≥ 64 counts per revolution, validated), so a measured
    // angle is < 2^60 in magnitude; θ is held to ±2^61, ω to ±100 rad/s (< 2^39) and the
    // acceleration to ±1000 rad/s² (< 2^42); the residual is clamped to ±0.5 rad (2^31) and every
    // gain is < 2^31 (< 2^29 at the validated extremes of bandwidth and dt). No sum or product
    // below can leave i64, so the 64-bit saturating forms (≈ 8 instructions each on a 32-bit
    // core) are not needed. Plain operators: the test builds' overflow checks (and the property
    // tests' extreme inputs) verify this budget; the release build emits the same code.
    // The run-time shifts by dt (1..=25 bits) go through the two-word `shr64`.
    let n = u32::from(k.dt_log2);
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
                    *faults |= fault::ENCODER_STUCK;
                }
            }
        }
        None => {
            // No reading: assume the input has stopped (the safe side for autonomy); the next
            // reading starts the tracker afresh, start-up gains and all (the shaft may have
            // turned and changed speed meanwhile).
            *faults |= fault::ENCODER;
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
    (theta, omega)
}
