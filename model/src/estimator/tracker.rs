//! The shaft stage: an α–β–γ tracker on the encoder angle, its residual, and the
//! expanding-memory start-up.

use super::*;
use crate::config::ModelConfig;
use libm::expf;

/// ⌊2π · 2^32⌋: a full turn in the tracker's Q32.32 angle.
const TWO_PI_Q32: u64 = 26_986_075_409;

/// Length of the shaft tracker's start-up gain table (a power of two: the index is masked).
pub const TRACKER_STARTUP_MAX: usize = 64;

/// The shaft tracker's start-up gains for the n-th residual after its first encoder reading,
/// n = 1 ..= [`TRACKER_STARTUP_MAX`], as D_n = 1/((n + 1)(n + 2)) in Q0.32 (entry n − 1): the
/// expanding-memory α–β filter (the least-squares line through every reading so far) has
/// α_n = 2(2n + 1)·D_n and β_n = 6·D_n (Brookner, *Tracking and Kalman Filtering Made Easy*,
/// §1.2.10; α_1 = β_1 = 1: the line through the first two readings), so one word per step
/// holds both. They do not depend on the configuration: a constant in flash (256 B), built at
/// compile time. Started from ω = 0 with the fading-memory gains instead, a shaft already
/// turning at 0.26 rad/s (a Test I start) read 0 % of its speed at first, 18 % at 16 ms and
/// 125 % at 0.1 s, and the model's pump flow and rod travel with it.
pub static TRACKER_STARTUP: [u32; TRACKER_STARTUP_MAX] = tracker_startup_table();

const fn tracker_startup_table() -> [u32; TRACKER_STARTUP_MAX] {
    let mut t = [0u32; TRACKER_STARTUP_MAX];
    let mut i = 0;
    while i < TRACKER_STARTUP_MAX {
        let n = i as u64 + 1;
        let d = (n + 1) * (n + 2);
        // Rounded to nearest; D_1 = 1/6 < 1.
        t[i] = (((1u64 << 32) + d / 2) / d) as u32;
        i += 1;
    }
    t
}

/// The expanding-memory α–β gains (α_n, β_n) of the n-th update, n ≥ 1, in f64: the formula
/// [`TRACKER_STARTUP`] tabulates, for f64 models of the tracker (the host's reference model,
/// tests); not used by the step or by the coefficients (no f64 arithmetic in the firmware).
pub fn expanding_memory_gains(n: u32) -> (f64, f64) {
    let n = f64::from(n);
    let d = 1.0 / ((n + 1.0) * (n + 2.0));
    (2.0 * (2.0 * n + 1.0) * d, 6.0 * d)
}

/// α_n and β_n (both Q1.31, ≤ 2^31) of the tracker's n-th start-up update from
/// [`TRACKER_STARTUP`]'s D_n (Q0.32): 2(2n + 1)·D_n and 6·D_n.
#[inline]
pub fn tracker_startup_gains(n: usize, d_q32: u32) -> (u32, u32) {
    // α_n·2^31 = (2n + 1)·D_n·2^32 and β_n·2^31 = 3·D_n·2^32. n ≤ 2^8 and D_n < 2^32: < 2^42;
    // held to 2^31 (n = 1, where the rounded D_1 makes them one LSB over).
    (
        wide::mul_uu(2 * (n as u32) + 1, d_q32).min(1 << 31) as u32,
        wide::mul_uu(3, d_q32).min(1 << 31) as u32,
    )
}

/// The shaft tracker's coefficients (`estimator::tracker`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TrackerCoeffs {
    /// Encoder count → rad, as the fraction bits of Q32.32 so a 16 384-count encoder keeps full
    /// precision (< 2^29: ≥ 64 counts per revolution).
    pub rad_per_count_q32: i32,
    /// α of the α–β–γ shaft tracker, Q1.31 (< 1). The tracker runs in Q32.32: at 1 kHz a shaft
    /// at 0.2 rad/s advances 2e-4 rad per step, 13 LSB of Q16.16, and truncating that every step
    /// biased the speed by +0.026 rad/s (10 %).
    pub alpha_q31: i32,
    /// β/dt of the α–β–γ shaft tracker, 1/s, Q16.16 (< 2^23 over the validated bandwidth and dt).
    pub beta_over_dt_q16: i32,
    /// 2γ/dt² of the α–β–γ shaft tracker, 1/s², Q16.16 (< 2^28 likewise).
    pub gamma_over_dt2_q16: i32,
    /// Number of steps after the tracker's first encoder reading that take the
    /// expanding-memory gains [`TRACKER_STARTUP`] (≤ [`TRACKER_STARTUP_MAX`]; 53 at 4 Hz and
    /// 2^−10 s): while both exceed the fading-memory gains above.
    pub tracker_startup_len: u8,
    /// The rounding term of the tracker's × dt in Q32.32: 2^(dt_log2 − 1) (a run-time 64-bit
    /// shift to build it costs ≈ 14 Cortex-M4 instructions a step).
    pub round_dt_q32: i64,
    /// The rounding term of its × dt²/2: 2^(2·dt_log2).
    pub round_dt2_q32: i64,
    /// Steps without an encoder change after which the encoder is suspected stuck.
    pub stuck_steps: u16,
}

impl TrackerCoeffs {
    /// The tracker's coefficients for `cfg` at the step 2^−`k` = `dt` s.
    #[inline(never)]
    pub(crate) fn of(cfg: &ModelConfig, k: u8, dt: f32) -> TrackerCoeffs {
        // 2π·2^32 / counts, floored, in integers (no f64 arithmetic in the firmware image: the
        // soft-float double routines cost ≈ 3 KB of flash). ≥ 64 counts (validated): < 2^29.
        let rad_per_count_q32 =
            (TWO_PI_Q32 / u64::from(cfg.encoder_counts_per_rev)).min(i32::MAX as u64) as i32;
        // Fading-memory α–β–γ tracker (a triple pole at r = exp(−2π·bw·dt)): α = 1 − r³,
        // β = 1.5(1 − r)²(1 + r), γ = ½(1 − r)³. Its constant-acceleration model follows the
        // sinusoidal shaft with ≈0.3 % speed error at 4 Hz, where an α–β tracker lags by
        // 1/(π·bw) and shifts every stroke reversal of the torque estimate by as much.
        let rr = expf(-2.0 * core::f32::consts::PI * cfg.encoder_bandwidth_hz * dt);
        let om = 1.0 - rr;
        let alpha = 1.0 - rr * rr * rr;
        let beta = 1.5 * om * om * (1.0 + rr);
        let gamma = 0.5 * om * om * om;
        // The expanding-memory start-up gains while both exceed the fading-memory ones (they
        // fall as 4/n and 6/n²; after TRACKER_STARTUP_MAX steps the fading-memory gains take
        // over in any case).
        let tracker_startup_len = TRACKER_STARTUP
            .iter()
            .enumerate()
            .take_while(|(i, d)| {
                let (a, b) = tracker_startup_gains(i + 1, **d);
                let q31 = |x: u32| x as f32 / 2_147_483_648.0;
                q31(a) > alpha && q31(b) > beta
            })
            .count() as u8;
        TrackerCoeffs {
            rad_per_count_q32,
            // (Scaling an f32 by a power of two is exact, and float-to-integer casts
            // saturate: α rounds to at most i32::MAX = 1 − 2^−31.)
            tracker_startup_len,
            alpha_q31: (alpha * 2_147_483_648.0) as i32,
            beta_over_dt_q16: (beta / dt * 65_536.0) as i32,
            gamma_over_dt2_q16: (2.0 * gamma / (dt * dt) * 65_536.0) as i32,
            round_dt_q32: 1i64 << (k - 1),
            round_dt2_q32: 1i64 << (2 * k),
            stuck_steps: (2.0 / dt).min(60_000.0) as u16,
        }
    }
}

/// The shaft tracker's state.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct TrackerState {
    /// Shaft angle estimate, rad, Q32.32.
    pub theta_q32: i64,
    /// Shaft speed estimate, rad/s, Q32.32.
    pub omega_q32: i64,
    /// Shaft acceleration estimate, rad/s², Q32.32.
    pub accel_q32: i64,
    /// The tracker's phase: 0 before its first encoder reading (and after a drop-out), 1
    /// tracking with the fading-memory gains, n + 1 with n start-up steps left
    /// ([`TrackerCoeffs::tracker_startup_len`], the expanding-memory gains [`TRACKER_STARTUP`]).
    /// One byte: the steady step tests it against 0 and 1.
    pub phase: u8,
    /// Last encoder count.
    pub last_count: i32,
    /// Steps since the encoder last changed.
    pub still_steps: u16,
    /// P2 estimate when the encoder last changed (or, while the estimate is not settled on the
    /// readings, at the last step), bar: the stuck-encoder check's rise is the estimate's rise
    /// from it. The estimate, not a raw reading: one reading's noise (σ 0.5 bar on the
    /// reference bench) against another's passed the 1 bar rise within 2 s of a lever at rest.
    pub hp_at_change: Fx,
}

/// The tracker's residual, measured less predicted angle (Q32.32), held to ±0.5 rad so that it
/// fits an i32.
#[inline(always)]
pub(super) fn residual(theta_meas: i64, pred_theta: i64) -> i32 {
    (theta_meas - pred_theta).clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32
}

/// The shaft tracker's first reading: it starts there, at rest, and takes the expanding-memory
/// gains for its next [`TrackerCoeffs::tracker_startup_len`] updates ([`startup_gains`]). Out of
/// line: the steady step only tests its phase.
#[inline(never)]
#[cold]
pub(super) fn tracker_start(t: &mut TrackerState, c: &TrackerCoeffs, theta_meas: i64, p2: Fx) {
    t.theta_q32 = theta_meas;
    t.omega_q32 = 0;
    t.accel_q32 = 0;
    t.phase = c.tracker_startup_len.saturating_add(ENC_TRACKING);
    t.hp_at_change = p2;
}

/// The gains of one of the first [`TrackerCoeffs::tracker_startup_len`] updates after the first
/// reading: the expanding-memory gains [`TRACKER_STARTUP`] (the least-squares line through every
/// reading so far) as α (Q1.31, up to 1: a `u32`), β/dt (Q16.16) and 2γ/dt² = 0, so that the
/// acceleration stays 0 until the fading-memory gains take over (and with it the prediction's
/// acceleration terms: the update is the steady one with these gains). Counts the phase down.
/// Out of line: the steady step only tests its phase.
#[inline(never)]
#[cold]
pub(super) fn startup_gains(t: &mut TrackerState, c: &TrackerCoeffs, dtl: u8) -> (u32, i32, i32) {
    // The n-th update since the start, n − 1 the table's index; its length is a power of two,
    // so the masked index cannot leave it.
    let i = usize::from(
        c.tracker_startup_len
            .wrapping_add(ENC_TRACKING)
            .wrapping_sub(t.phase),
    ) & (TRACKER_STARTUP_MAX - 1);
    let (a, b) = tracker_startup_gains(i + 1, TRACKER_STARTUP[i]);
    t.phase = t.phase.saturating_sub(1).max(ENC_TRACKING);
    // β_n/dt in Q16.16: β_n (Q1.31) · 2^dt_log2 / 2^15; dt_log2 ≤ 12 (validated), so the shift
    // is 3..=9 bits and β_n/dt < 2^29 as the fading-memory β/dt.
    (a, (b >> (15u8.saturating_sub(dtl) & 31)) as i32, 0)
}

/// The shaft stage of a step: the α–β–γ tracker on the encoder angle, in Q32.32 (i64), its
/// start-up and drop-outs, and the stuck-encoder check; returns the angle (rad) and speed
/// (rad/s) in Q16.16. Inlined into the step, its only caller.
#[inline(always)]
pub(super) fn track(
    c: &TrackerCoeffs,
    dtl: u8,
    t: &mut TrackerState,
    p2: Fx,
    settled: bool,
    inp: &Inputs,
    faults: &mut u16,
) -> (Fx, Fx) {
    // Bit budget: one count is < 2^29 (≥ 64 counts per revolution, validated), so a measured
    // angle is < 2^60 in magnitude; θ is held to ±2^61, ω to ±100 rad/s (< 2^39) and the
    // acceleration to ±1000 rad/s² (< 2^42); the residual is clamped to ±0.5 rad (2^31) and every
    // gain is < 2^31 (< 2^29 at the validated extremes of bandwidth and dt). No sum or product
    // below can leave i64, so the 64-bit saturating forms (≈ 8 instructions each on a 32-bit
    // core) are not needed. Plain operators: the test builds' overflow checks (and the property
    // tests' extreme inputs) verify this budget; the release build emits the same code.
    // The run-time shifts by dt (1..=25 bits) go through the two-word `shr64`.
    let n = u32::from(dtl);
    let half = c.round_dt_q32;
    let pred_theta = t.theta_q32
        + shr64(t.omega_q32 + half, n)
        + shr64(t.accel_q32 + c.round_dt2_q32, 2 * n + 1);
    let pred_omega = t.omega_q32 + shr64(t.accel_q32 + half, n);
    match inp.encoder {
        Some(count) => {
            let theta_meas = wide::mul(count, c.rad_per_count_q32);
            if t.phase == ENC_UNSEEN {
                tracker_start(t, c, theta_meas, p2);
                t.last_count = count;
            } else {
                // The fading-memory gains, or during the start-up the expanding-memory ones
                // (whose acceleration stays 0, so the prediction above is theirs too).
                let (a, b, g) = if t.phase == ENC_TRACKING {
                    (c.alpha_q31 as u32, c.beta_over_dt_q16, c.gamma_over_dt2_q16)
                } else {
                    startup_gains(t, c, dtl)
                };
                // The residual held to ±0.5 rad fits an i32, so each gain product is one
                // 32 × 32 → 64 multiply (α unsigned: it reaches 1 at the first update).
                let r = residual(theta_meas, pred_theta);
                t.theta_q32 = (pred_theta + ((wide::mul_su(r, a) + (1 << 30)) >> 31))
                    .clamp(-THETA_LIM_Q32, THETA_LIM_Q32);
                t.omega_q32 = (pred_omega + ((wide::mul(r, b) + (1 << 15)) >> 16))
                    .clamp(-OMEGA_LIM_Q32, OMEGA_LIM_Q32);
                t.accel_q32 = (t.accel_q32 + ((wide::mul(r, g) + (1 << 15)) >> 16))
                    .clamp(-ACCEL_LIM_Q32, ACCEL_LIM_Q32);
            }
            if count != t.last_count {
                t.last_count = count;
                t.still_steps = 0;
                t.hp_at_change = p2;
            } else {
                t.still_steps = t.still_steps.saturating_add(1);
                if !settled {
                    // From boot or a reset the estimate climbs to the readings: that is no rise.
                    t.hp_at_change = p2;
                } else if t.still_steps >= c.stuck_steps
                    && inp.hp.is_some()
                    && p2.saturating_sub(t.hp_at_change) > ONE
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
            t.theta_q32 = pred_theta;
            t.omega_q32 = 0;
            t.accel_q32 = 0;
            t.phase = ENC_UNSEEN;
        }
    }
    let theta = Fx::from_bits(
        ((t.theta_q32 + (1 << 15)) >> 16).clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32,
    );
    let omega = Fx::from_bits(((t.omega_q32 + (1 << 15)) >> 16) as i32);
    (theta, omega)
}
