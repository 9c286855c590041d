//! Fixed-point quantities: one named type per physical quantity, all Q16.16 (`I16F16`).
//!
//! | type | unit | range used (saturation limits) | resolution |
//! |---|---|---|---|
//! | [`Pressure`] | bar (gauge) | −1 … 400 | 1.5e-5 bar |
//! | [`PressureVariance`] | bar² | 0 … 32 767 (σ ≤ 181 bar) | 1.5e-5 bar² |
//! | [`Flow`] | L/min | ±1000 | 1.5e-5 L/min |
//! | [`Torque`] | N·m | ±30 000 | 1.5e-5 N·m |
//! | [`Angle`] | rad | ±π | 1.5e-5 rad (an encoder count of a 16 384-count encoder is 3.8e-4 rad) |
//! | [`AngularSpeed`] | rad/s | ±100 | 1.5e-5 rad/s |
//! | [`Rpm`] | rev/min | 0 … 10 000 | 1.5e-5 rpm |
//! | [`Aperture`] | % of the valve stroke | 0 … 100 | 1.5e-5 % |
//! | [`Seconds`] | s | 0 … 32 767 | 1.5e-5 s |
//! | [`HydraulicPower`] | W | 0 … 32 767 (a 400 bar, 11.8 L/min valve flow: saturates above) | 1.5e-5 W |
//!
//! Q16.16 holds every signal of the bench with headroom (the largest, restraining torque, peaks at
//! ≈ 6 kN·m with all four cylinders at 130 bar). Products that could exceed it (Δp², K⁴β²) are
//! never formed: the valve law comes from a precomputed table. Every sum and product in the step
//! uses the saturating forms; the physical limits above are applied where a state is stored.

use fixed::types::I16F16;

/// The raw Q16.16 number every quantity wraps.
pub type Fx = I16F16;

/// 0.
pub const ZERO: Fx = Fx::ZERO;
/// 1.
pub const ONE: Fx = Fx::ONE;

macro_rules! quantity {
    ($(#[$m:meta])* $name:ident, $unit:literal) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Default, Hash)]
        #[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
        #[repr(transparent)]
        pub struct $name(pub Fx);

        impl $name {
            /// Zero.
            pub const ZERO: Self = Self(Fx::ZERO);
            #[doc = concat!("From a value in ", $unit, " (saturating; for configuration and host tools).")]
            pub fn from_num(v: f32) -> Self {
                Self(Fx::saturating_from_num(v))
            }
            #[doc = concat!("The value in ", $unit, " (for display and host tools).")]
            pub fn to_f32(self) -> f32 {
                self.0.to_num()
            }
            /// From raw Q16.16 bits.
            pub const fn from_bits(bits: i32) -> Self {
                Self(Fx::from_bits(bits))
            }
            /// Raw Q16.16 bits.
            pub const fn to_bits(self) -> i32 {
                self.0.to_bits()
            }
        }

        #[cfg(feature = "protocol")]
        impl postcard_schema::Schema for $name {
            const SCHEMA: &'static postcard_schema::schema::NamedType =
                &postcard_schema::schema::NamedType {
                    name: stringify!($name),
                    ty: <i32 as postcard_schema::Schema>::SCHEMA.ty,
                };
        }

        #[cfg(feature = "defmt")]
        impl defmt::Format for $name {
            fn format(&self, f: defmt::Formatter) {
                // Decimal with 4 digits, in integers (no float formatting on the target).
                let b = i64::from(self.0.to_bits());
                let a = b.unsigned_abs();
                let frac = ((a & 0xffff) * 10_000 + 0x8000) >> 16;
                let (int, frac) = if frac == 10_000 { ((a >> 16) + 1, 0) } else { (a >> 16, frac) };
                let sign = if b < 0 { "-" } else { "" };
                defmt::write!(f, "{=str}{=u64}.{=u64:04} {=str}", sign, int, frac, $unit)
            }
        }
    };
}

quantity!(
    /// Gauge pressure, bar.
    Pressure, "bar"
);
quantity!(
    /// Variance of a pressure estimate, bar².
    PressureVariance, "bar²"
);
quantity!(
    /// Volumetric flow, L/min.
    Flow, "L/min"
);
quantity!(
    /// Torque, N·m.
    Torque, "N·m"
);
quantity!(
    /// Shaft angle, rad.
    Angle, "rad"
);
quantity!(
    /// Shaft speed, rad/s.
    AngularSpeed, "rad/s"
);
quantity!(
    /// Motor speed, rev/min.
    Rpm, "rpm"
);
quantity!(
    /// Control valve aperture, % of stroke.
    Aperture, "%"
);
quantity!(
    /// Time, s.
    Seconds, "s"
);
quantity!(
    /// Hydraulic power, W.
    HydraulicPower, "W"
);

/// 1 bar · 1 L/min in W: 1e5 Pa · 1e-3/60 m³/s = 5/3 W (Q16.16: 109 227/65 536, 3.1e-6 high).
pub const W_PER_BAR_LPM: Fx = Fx::from_bits(109_227);

/// Multiplication by dt = 2^−k, k = `dt_log2` in 1..=31 (the configuration allows 6..=12): a
/// rounding arithmetic shift (a truncating one would bias every integrated quantity by −½ LSB
/// per step), i.e. ⌊(x + 2^(k−1)) / 2^k⌋. Done in 32 bits as ⌊x / 2^k⌋ plus bit k−1 of x, which
/// is the same value without the 64-bit sum (a 64-bit shift by a run-time amount is ≈ 14
/// Cortex-M4 instructions, this is 4; property-tested against the 64-bit form).
#[inline]
pub fn mul_dt(x: Fx, dt_log2: u8) -> Fx {
    let (b, k) = (x.to_bits(), u32::from(dt_log2));
    Fx::from_bits(b.wrapping_shr(k) + (b.wrapping_shr(k.wrapping_sub(1)) & 1))
}

/// `x >> n` for an `i64` and a run-time `n` in 1..=31, from the two 32-bit halves: ≈ 5
/// Cortex-M4 instructions where the general 64-bit shift (any `n`, branches for `n` ≥ 32) is
/// ≈ 14. Same bits as `x >> n` (property-tested); outside 1..=31 the result is unspecified but
/// nothing panics.
#[inline(always)]
pub fn shr64(x: i64, n: u32) -> i64 {
    let (hi, lo) = ((x >> 32) as i32, x as u32);
    let lo = lo.wrapping_shr(n) | (hi as u32).wrapping_shl(32u32.wrapping_sub(n));
    (i64::from(hi.wrapping_shr(n)) << 32) | i64::from(lo)
}

/// The exact products of two 32-bit words, the forms the per-step path uses.
///
/// A Cortex-M4 forms a 32 × 32 → 64 product in one instruction (`smull`/`umull`); a Cortex-M0
/// (ARMv6-M) has only `MULS`, 32 × 32 → 32, so the compiler calls the generic 64 × 64
/// `__aeabi_lmul` (≈ 40 instructions) for every `i64` product. Where the target lacks the long
/// multiply (`cfg(no_long_multiply)`, set by the build script) these take the product from four
/// 16 × 16 → 32 partial products inline, and a Q16.16 product known to fit 32 bits in 32-bit
/// arithmetic only; elsewhere they are the plain widening product. Both forms are exact, so
/// every target gets the same bits: the partial-product forms (`*_halves`) are compiled on the
/// host too and property-tested there against the exact product
/// (`wide_products_are_the_exact_products`). Measured on the Cortex-M0 (docs/model.md): the
/// worst step 7 262 → 5 153 instructions; two other forms (carries in 32-bit adds, ⌊ab/2¹⁶⌋
/// without the 64-bit shift) compiled longer.
pub mod wide {
    /// A word's low half (unsigned) and its high half (signed).
    #[inline(always)]
    fn halves(a: i32) -> (u32, i32) {
        ((a as u32) & 0xffff, a >> 16)
    }

    /// `a·b` from partial products: a = aₕ·2¹⁶ + aₗ, b likewise; each product of halves
    /// fits 32 bits (|aₕ·bₗ| ≤ 2¹⁵·(2¹⁶ − 1) < 2³¹), the sum is the exact `i64`.
    #[inline(always)]
    pub fn mul_halves(a: i32, b: i32) -> i64 {
        let ((al, ah), (bl, bh)) = (halves(a), halves(b));
        let mid = i64::from(ah * bl as i32) + i64::from(al as i32 * bh);
        ((i64::from(ah * bh) << 32) | i64::from(al * bl)) + (mid << 16)
    }

    /// `a·b` for an unsigned `b`, from partial products.
    #[inline(always)]
    pub fn mul_su_halves(a: i32, b: u32) -> i64 {
        let (al, ah) = halves(a);
        let (bl, bh) = (b & 0xffff, b >> 16);
        let mid = i64::from(ah * bl as i32) + i64::from(al * bh);
        ((i64::from(ah * bh as i32) << 32) | i64::from(al * bl)) + (mid << 16)
    }

    /// `a·b` for unsigned words, from partial products.
    #[inline(always)]
    pub fn mul_uu_halves(a: u32, b: u32) -> u64 {
        let (al, ah, bl, bh) = (a & 0xffff, a >> 16, b & 0xffff, b >> 16);
        let mid = u64::from(ah * bl) + u64::from(al * bh);
        ((u64::from(ah * bh) << 32) | u64::from(al * bl)) + (mid << 16)
    }

    /// ⌊a·b / 2¹⁶⌋ from partial products (the exact product shifted: summing the partial
    /// products at 2¹⁶ instead compiled ≈ 5 instructions longer a product on ARMv6-M).
    #[inline(always)]
    pub fn mul_q16_halves(a: i32, b: i32) -> i64 {
        mul_halves(a, b) >> 16
    }

    /// The low 32 bits of ⌊a·b / 2¹⁶⌋ from partial products, in 32-bit arithmetic: the whole
    /// result when it is known to fit an `i32`.
    #[inline(always)]
    pub fn mul_q16_low_halves(a: i32, b: i32) -> i32 {
        let ((al, ah), (bl, bh)) = (halves(a), halves(b));
        (ah * bh)
            .wrapping_shl(16)
            .wrapping_add(ah * bl as i32)
            .wrapping_add(al as i32 * bh)
            .wrapping_add(((al * bl) >> 16) as i32)
    }

    /// `p` held to the `i32` range.
    #[inline(always)]
    pub fn saturate(p: i64) -> i32 {
        let r = p as i32;
        if i64::from(r) == p {
            r
        } else {
            ((p >> 63) as i32) ^ i32::MAX
        }
    }

    /// `a·b`, exact.
    #[inline(always)]
    pub fn mul(a: i32, b: i32) -> i64 {
        if cfg!(no_long_multiply) {
            mul_halves(a, b)
        } else {
            i64::from(a) * i64::from(b)
        }
    }

    /// `a·b` for an unsigned `b`, exact.
    #[inline(always)]
    pub fn mul_su(a: i32, b: u32) -> i64 {
        if cfg!(no_long_multiply) {
            mul_su_halves(a, b)
        } else {
            i64::from(a) * i64::from(b)
        }
    }

    /// `a·b` for unsigned words, exact.
    #[inline(always)]
    pub fn mul_uu(a: u32, b: u32) -> u64 {
        if cfg!(no_long_multiply) {
            mul_uu_halves(a, b)
        } else {
            u64::from(a) * u64::from(b)
        }
    }

    /// ⌊a·b / 2¹⁶⌋, exact.
    #[inline(always)]
    pub fn mul_q16(a: i32, b: i32) -> i64 {
        mul(a, b) >> 16
    }

    /// ⌊a·b / 2¹⁶⌋ for a product known to fit an `i32` after the shift (else its low 32 bits).
    #[inline(always)]
    pub fn mul_q16_low(a: i32, b: i32) -> i32 {
        if cfg!(no_long_multiply) {
            mul_q16_low_halves(a, b)
        } else {
            ((i64::from(a) * i64::from(b)) >> 16) as i32
        }
    }

    /// The low 64 bits of `x·c` (the whole product where it fits an `i64`), from two word
    /// products: x = xₕ·2³² + xₗ.
    #[inline(always)]
    pub fn mul_i64_i32(x: i64, c: i32) -> i64 {
        if cfg!(no_long_multiply) {
            mul_i64_i32_halves(x, c)
        } else {
            x.wrapping_mul(i64::from(c))
        }
    }

    /// [`mul_i64_i32`] from two word products: the low word's exact product and the high
    /// word's low 32 bits.
    #[inline(always)]
    pub fn mul_i64_i32_halves(x: i64, c: i32) -> i64 {
        let (xh, xl) = ((x >> 32) as i32, x as u32);
        mul_su_halves(c, xl).wrapping_add(i64::from(xh.wrapping_mul(c)) << 32)
    }
}

/// The saturating Q16.16 product used in the per-step path.
///
/// `fixed`'s `saturating_mul` widens both operands to `i64` and runs a generic overflow-checked
/// 64 × 64 multiply: ≈ 20 Cortex-M4 instructions per product, measured as ≈ 1 400 of the
/// ≈ 3 200 instructions a step cost. The product of two `i32` fits `i64` exactly, so it is one
/// `smull`, a 64-bit shift and a one-compare range check (≈ 8 instructions) — hand-written for
/// that reason.
/// The result is the same bits as `saturating_mul` (floor of the exact product, saturated to the
/// Q16.16 range; property-tested against it).
pub trait QMul {
    /// `self × rhs`, floored to Q16.16, saturated at the type's limits.
    fn qmul(self, rhs: Self) -> Self;
}

impl QMul for Fx {
    #[inline(always)]
    fn qmul(self, rhs: Fx) -> Fx {
        if cfg!(no_long_multiply) {
            // ⌊p / 2¹⁶⌋ from partial products, then the plain range check.
            return Fx::from_bits(wide::saturate(wide::mul_q16_halves(
                self.to_bits(),
                rhs.to_bits(),
            )));
        }
        let p = i64::from(self.to_bits()) * i64::from(rhs.to_bits());
        let r = (p >> 16) as i32;
        // In range iff bits 63..31 of the shifted product all equal its sign bit, i.e. bits
        // 47..16+31 of p are copies of bit 47: compare them with r's sign (one `cmp` with a
        // shifted operand instead of two 64-bit compares).
        if (p >> 47) as i32 == r >> 31 {
            Fx::from_bits(r)
        } else {
            Fx::from_bits(((p >> 63) as i32) ^ i32::MAX)
        }
    }
}

/// `a × b` for a Q8.24 `b` (a shaft speed kept to 2^−24 rad/s), floored to Q16.16 and
/// saturated like [`QMul::qmul`] (the same one-compare range check, on bits 55..24). Out of
/// line: called twice a step, and on a Cortex-M0 its 64-bit product is long.
#[inline(never)]
pub fn mul_q24(a: Fx, b_q24: i32) -> Fx {
    if cfg!(no_long_multiply) {
        // ⌊⌊p / 2¹⁶⌋ / 2⁸⌋ = ⌊p / 2²⁴⌋.
        return Fx::from_bits(wide::saturate(
            wide::mul_q16_halves(a.to_bits(), b_q24) >> 8,
        ));
    }
    let p = i64::from(a.to_bits()) * i64::from(b_q24);
    let r = (p >> 24) as i32;
    if (p >> 55) as i32 == r >> 31 {
        Fx::from_bits(r)
    } else {
        Fx::from_bits(((p >> 63) as i32) ^ i32::MAX)
    }
}

/// `f × x` for a fraction `f` in [0, 1] (a filter or interpolation gain): |f·x| ≤ |x|, so the
/// product needs no range check (3 instructions where [`QMul::qmul`] takes 7). Same bits as
/// `f.qmul(x)` (floor of the exact product) for every such `f`; the gains passed are built in
/// [0, 1] by the configuration.
#[inline(always)]
pub fn mul_frac(f: Fx, x: Fx) -> Fx {
    Fx::from_bits(wide::mul_q16_low(f.to_bits(), x.to_bits()))
}

/// `a × b` floored to Q16.16, for operands whose product is known to lie well inside the
/// Q16.16 range: no range check (3 Cortex-M4 instructions where [`QMul::qmul`] takes 8). Used
/// for a chamber force, pressure × area: a chamber pressure is held to [LP − drop, P2 + drop]
/// ⊂ [−21, 420] bar (< 2^25 bits) and an area to ≤ 19.7 kN/bar (bore ≤ 500 mm, validated:
/// < 2^21 bits), so the product is < 2^46 and the result < 2^30 bits. Test builds check the
/// bound (`debug_assert`); the release code is the bare product.
#[inline(always)]
pub fn mul_bounded(a: Fx, b: Fx) -> Fx {
    debug_assert!(
        {
            let p = (i64::from(a.to_bits()) * i64::from(b.to_bits())) >> 16;
            p == i64::from(p as i32)
        },
        "mul_bounded out of range: {a} × {b}"
    );
    Fx::from_bits(wide::mul_q16_low(a.to_bits(), b.to_bits()))
}

/// Saturating clamp to [lo, hi].
#[inline]
pub fn clamp(x: Fx, lo: Fx, hi: Fx) -> Fx {
    x.max(lo).min(hi)
}

/// Square root that is 0 for negative input (no panic path). Out of line: one copy serves
/// every caller.
#[inline(never)]
pub fn sqrt0(x: Fx) -> Fx {
    x.max(ZERO).checked_sqrt().unwrap_or(ZERO)
}

/// Reciprocal of a positive number without a division instruction: normalise to m ∈ [1, 2),
/// start from the linear estimate 24/17 − 8/17·m (error ≤ 1/17), refine with three
/// Newton–Raphson steps y ← y(2 − m·y) in Q2.30 (error < 1e-9), scale back. Returns
/// `Fx::MAX` for x ≤ 2^−16 (saturation at the physical limit of the callers). Out of line:
/// it runs three times per stroke reversal, not per step.
#[inline(never)]
pub fn recip(x: Fx) -> Fx {
    let bits = x.to_bits();
    if bits <= 1 {
        return Fx::MAX;
    }
    let n = 31 - bits.leading_zeros() as i32; // top bit index, 1..=30
    // Q2.30, in [2^30, 2^31): fits an i32, so every product below is one `smull`.
    let m = bits << (30 - n);
    let mul30 = |a: i32, b: i32| (wide::mul(a, b) >> 30) as i32;
    // 1/m ≈ 24/17 − 8/17·m on [1, 2) (the classic 48/17 − 32/17·d on d = m/2), in Q2.30: y in
    // (2^29, 2^30 + 2^26], m·y within 1/17 of 2^30, 2 − m·y below 2^31: all i32.
    let mut y = 1_515_870_810 - mul30(m, 505_290_270);
    for _ in 0..3 {
        let my = mul30(m, y);
        y = mul30(y, i32::MAX - my + 1);
    }
    // 1/x = y·2^(16−n) (y in Q2.30) → Q16.16 bits = y·2^(32−n)/2^30 = y·2^(2−n).
    let y = i64::from(y);
    let shift = n - 2;
    let r = if shift >= 0 {
        y >> shift
    } else {
        y << (-shift)
    };
    Fx::from_bits(r.min(i64::from(i32::MAX)) as i32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn qmul_equals_fixed_saturating_mul() {
        let edge = [
            i32::MIN,
            i32::MIN + 1,
            -65_537,
            -65_536,
            -1,
            0,
            1,
            65_535,
            65_536,
            i32::MAX,
        ];
        for &a in &edge {
            for &b in &edge {
                let (x, y) = (Fx::from_bits(a), Fx::from_bits(b));
                assert_eq!(x.qmul(y), x.saturating_mul(y), "{a} × {b}");
            }
        }
    }

    proptest::proptest! {
        #[test]
        fn qmul_equals_fixed_saturating_mul_anywhere(
            a in proptest::num::i32::ANY,
            b in proptest::num::i32::ANY,
            sa in 0u32..24,
            sb in 0u32..24,
        ) {
            // Shifted operands cover small magnitudes as well as the saturating ones.
            let (x, y) = (Fx::from_bits(a >> sa), Fx::from_bits(b >> sb));
            proptest::prop_assert_eq!(x.qmul(y), x.saturating_mul(y));
        }
    }

    proptest::proptest! {
        #[test]
        fn mul_dt_is_the_rounded_64_bit_shift(a in proptest::num::i32::ANY, k in 1u8..=31) {
            let want = (i64::from(a) + ((1i64 << k) >> 1)) >> k;
            proptest::prop_assert_eq!(i64::from(mul_dt(Fx::from_bits(a), k).to_bits()), want);
        }
    }

    proptest::proptest! {
        #[test]
        fn mul_frac_equals_qmul_for_fractions(f in 0i32..=65_536, x in proptest::num::i32::ANY) {
            let (f, x) = (Fx::from_bits(f), Fx::from_bits(x));
            proptest::prop_assert_eq!(mul_frac(f, x), f.qmul(x));
        }

        /// Over its documented range (a pressure in [−21, 420] bar times a force per bar up
        /// to 19.7 kN/bar, either sign) the unchecked product is the saturating one.
        #[test]
        fn mul_bounded_equals_qmul_over_its_range(
            p in (-21i32 << 16)..=(420 << 16), a in -1_291_000i32..=1_291_000,
        ) {
            let (p, a) = (Fx::from_bits(p), Fx::from_bits(a));
            proptest::prop_assert_eq!(mul_bounded(p, a), p.qmul(a));
        }

        #[test]
        fn shr64_equals_the_64_bit_shift(a in proptest::num::i64::ANY, n in 1u32..=31) {
            proptest::prop_assert_eq!(shr64(a, n), a >> n);
        }
    }

    /// The reciprocal's Newton iteration in 64-bit arithmetic throughout (its first form).
    fn recip_i64(x: Fx) -> Fx {
        let bits = x.to_bits();
        if bits <= 1 {
            return Fx::MAX;
        }
        let n = 31 - bits.leading_zeros() as i32;
        let m = i64::from(bits) << (30 - n);
        let mut y = 1_515_870_810i64 - ((m * 505_290_270i64) >> 30);
        for _ in 0..3 {
            let my = (m * y) >> 30;
            y = (y * ((2i64 << 30) - my)) >> 30;
        }
        let r = if n >= 2 { y >> (n - 2) } else { y << (2 - n) };
        Fx::from_bits(r.min(i64::from(i32::MAX)) as i32)
    }

    proptest::proptest! {
        #[test]
        fn recip_in_32_bit_products_equals_the_64_bit_form(a in proptest::num::i32::ANY, s in 0u32..31) {
            let x = Fx::from_bits(a >> s);
            proptest::prop_assert_eq!(recip(x), recip_i64(x));
        }
    }

    #[test]
    fn recip_is_accurate_over_the_range() {
        let mut worst = 0.0f64;
        for k in 1..20_000 {
            let x = 0.0005 * 1.0007f64.powi(k);
            if x > 30_000.0 {
                break;
            }
            let fx = Fx::from_num(x);
            let want = 1.0 / fx.to_num::<f64>();
            if want > 30_000.0 {
                continue;
            }
            let got: f64 = recip(fx).to_num();
            worst = worst.max((got - want).abs() / want.max(1.0));
        }
        println!("recip worst error {worst:.2e} (relative, absolute below 1)");
        assert!(worst < 2e-5);
    }
}

#[cfg(test)]
mod q24_tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// `mul_q24` is the floor of the exact product, saturated at the Q16.16 range.
        #[test]
        fn mul_q24_is_the_saturated_floor_of_the_exact_product(a in any::<i32>(), b in any::<i32>()) {
            let exact = (i128::from(a) * i128::from(b)) >> 24;
            let want = exact.clamp(i128::from(i32::MIN), i128::from(i32::MAX)) as i32;
            prop_assert_eq!(mul_q24(Fx::from_bits(a), b).to_bits(), want);
        }
    }
}

#[cfg(test)]
mod wide_tests {
    use super::wide::*;
    use super::*;
    use proptest::prelude::*;

    /// Words that reach every partial product's extremes, and random ones.
    fn word() -> impl Strategy<Value = i32> {
        prop_oneof![
            prop::sample::select(vec![
                i32::MIN,
                i32::MIN + 1,
                -65_537,
                -65_536,
                -32_768,
                -1,
                0,
                1,
                32_767,
                65_535,
                65_536,
                i32::MAX
            ]),
            any::<i32>()
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(20_000))]
        /// The Cortex-M0 forms (partial products) are the exact products, and the Q16.16
        /// product and `mul_q24` built from them saturate to the bits of the Cortex-M4's.
        #[test]
        fn wide_products_are_the_exact_products(a in word(), b in word(), w in any::<i64>()) {
            let exact = i128::from(a) * i128::from(b);
            prop_assert_eq!(i128::from(mul_halves(a, b)), exact);
            prop_assert_eq!(i128::from(mul_su_halves(a, b as u32)), i128::from(a) * i128::from(b as u32));
            prop_assert_eq!(
                i128::from(mul_uu_halves(a as u32, b as u32)),
                i128::from(a as u32) * i128::from(b as u32)
            );
            prop_assert_eq!(i128::from(mul_q16_halves(a, b)), exact >> 16);
            prop_assert_eq!(mul_q16_low_halves(a, b), (exact >> 16) as i32);
            let (x, y) = (Fx::from_bits(a), Fx::from_bits(b));
            prop_assert_eq!(saturate(mul_q16_halves(a, b)), x.saturating_mul(y).to_bits());
            prop_assert_eq!(saturate(mul_q16_halves(a, b) >> 8), mul_q24(x, b).to_bits());
            prop_assert_eq!(mul_i64_i32(w, b), (i128::from(w) * i128::from(b)) as i64);
            prop_assert_eq!(mul_i64_i32_halves(w, b), (i128::from(w) * i128::from(b)) as i64);
            // Each dispatching form equals its exact value on this target too.
            prop_assert_eq!(i128::from(mul(a, b)), exact);
            prop_assert_eq!(i128::from(mul_q16(a, b)), exact >> 16);
            prop_assert_eq!(mul_q16_low(a, b), (exact >> 16) as i32);
        }
    }
}
