//! Configuration advisor: which cylinders to put on duty, and in which geometry, for a target
//! mean restraining torque at the measured motion amplitude (the paper: torque is adjusted by
//! geometry and by the number of cylinders on duty).

use crate::coeffs::Coefficients;
use crate::fx::{Angle, Fx, Pressure, Torque, ZERO};

/// sin(2π(i + ½)/16) for the 8 samples of a half wave (symmetric, so one half suffices).
const SIN8: [Fx; 8] = [
    Fx::from_bits(12_785),
    Fx::from_bits(36_410),
    Fx::from_bits(54_491),
    Fx::from_bits(64_277),
    Fx::from_bits(64_277),
    Fx::from_bits(54_491),
    Fx::from_bits(36_410),
    Fx::from_bits(12_785),
];

/// A recommendation.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Advice {
    /// 0..=3 = Config 1..4.
    pub config: u8,
    /// Cylinders on duty, bit i = HC3.(i+1).
    pub on_duty: u8,
    /// Mean |restraining torque| it should give.
    pub mean_torque: Torque,
}

/// Mean |torque| of one candidate over a sinusoidal swing of amplitude `amp` at P2/LP.
/// Over a cycle each chamber delivers half the time, so the mean force is
/// (P2 − LP)·(A_cap + A_ann)/2, times the mean arm over the swing.
pub fn mean_torque(
    k: &Coefficients,
    config: u8,
    on_duty: u8,
    amp: Angle,
    p2: Pressure,
    lp: Pressure,
) -> Torque {
    let Some(arm) = k.pump.arm.get(usize::from(config)) else {
        return Torque::ZERO;
    };
    let dp = p2.0.saturating_sub(lp.0).max(ZERO);
    let mut total = ZERO;
    for (i, c) in k.pump.cyl.iter().enumerate() {
        if on_duty & (1 << i) == 0 {
            continue;
        }
        let mut d_sum = ZERO;
        for s in SIN8 {
            d_sum = d_sum.saturating_add(arm.at(c.side.saturating_mul(amp.0.saturating_mul(s))));
        }
        let d_mean = Fx::from_bits(d_sum.to_bits() >> 3);
        let f_mean = dp.saturating_mul(Fx::from_bits((c.f_cap.to_bits() + c.f_ann.to_bits()) >> 1)); // kN
        total = total.saturating_add(d_mean.saturating_mul(f_mean));
    }
    // mm·kN = N·m.
    Torque(total)
}

/// The candidate (4 geometries × 15 non-empty cylinder sets) whose mean torque is closest to
/// `target`; ties go to fewer cylinders.
pub fn advise(k: &Coefficients, target: Torque, amp: Angle, p2: Pressure, lp: Pressure) -> Advice {
    let mut best = Advice {
        config: 0,
        on_duty: 0b1111,
        mean_torque: Torque::ZERO,
    };
    let mut best_err = Fx::MAX;
    let mut best_n = u32::MAX;
    for config in 0..4u8 {
        for on_duty in 1..16u8 {
            let t = mean_torque(k, config, on_duty, amp, p2, lp);
            let err = t.0.saturating_sub(target.0).abs();
            let n = on_duty.count_ones();
            if err < best_err || (err == best_err && n < best_n) {
                best = Advice {
                    config,
                    on_duty,
                    mean_torque: t,
                };
                best_err = err;
                best_n = n;
            }
        }
    }
    best
}
