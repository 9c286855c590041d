//! Lookup tables on uniform grids: linear (1-D) and bilinear (2-D) interpolation without division.
//!
//! The grid start and the reciprocal of the spacing are stored, so locating a point is a
//! subtraction, a multiplication and a truncation. Outside the grid the end segments are held
//! (clamped), never extrapolated.

use crate::fx::{Fx, ONE, QMul, ZERO, mul_frac, recip, wide};

/// Locates `x` on a grid: (index of the lower node, fraction in [0, 1]).
///
/// The Q16.16 offset times the Q16.16 reciprocal spacing is a Q32.32 position whose high word
/// is the cell index and whose bits 16..31 are the fraction: no saturation or 64-bit shift is
/// needed (offset ≥ 0 and < 2^31, reciprocal < 2^31, so the product is < 2^62). Past the last
/// cell the end segment is held, as a saturated product would also give.
#[inline(always)]
fn locate(x: Fx, x0: Fx, inv_dx: Fx, n: usize) -> (usize, Fx) {
    // Unsigned: the offset is held ≥ 0 and the reciprocal spacing is positive, and so the
    // index is known to lie in 0..=n − 2 (no bounds check, no panic path, in the callers).
    // It costs the step ≈ 40 instructions: the thumb targets force frame pointers, and a
    // lookup with no call left in it builds its frame on every call, where the bounds check's
    // cold panic call had LLVM build it on that path only (a cold non-panicking call in its
    // place did not remove the checks).
    let dx = x.saturating_sub(x0).max(ZERO).to_bits() as u32;
    let p = wide::mul_uu(dx, inv_dx.to_bits() as u32);
    let i = (p >> 32) as u32;
    if i > (n - 2) as u32 {
        return (n - 2, ONE);
    }
    (i as usize, Fx::from_bits(((p >> 16) as i32) & 0xffff))
}

/// The cell and the exact fraction of `x` on a grid of `n` nodes from `x0` with `inv_dx` nodes
/// per unit, held to the ends: the tables' own location of a Q16.16 point, in f64. For f64
/// models of the same tables (the host's reference model, tests); not used by the step.
pub fn locate_f64(x: f64, x0: Fx, inv_dx: Fx, n: usize) -> (usize, f64) {
    let u = ((x - x0.to_num::<f64>()) * inv_dx.to_num::<f64>()).clamp(0.0, (n - 1) as f64);
    let i = (u as usize).min(n - 2);
    (i, u - i as f64)
}

/// Linear interpolation in f64 between nodes `i` and `i + 1` of `ys` (see [`locate_f64`]).
pub fn lerp_f64(ys: &[Fx], (i, f): (usize, f64)) -> f64 {
    let (a, b) = (ys[i].to_num::<f64>(), ys[i + 1].to_num::<f64>());
    a + f * (b - a)
}

/// a + f·(b − a) for a fraction f ∈ [0, 1] (the product needs no range check, see
/// [`mul_frac`]).
#[inline(always)]
fn lerp(a: Fx, b: Fx, f: Fx) -> Fx {
    a.saturating_add(mul_frac(f, b.saturating_sub(a)))
}

/// A 1-D table of `N` values on a uniform grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Table1<const N: usize> {
    /// Grid start.
    pub x0: Fx,
    /// 1 / spacing.
    pub inv_dx: Fx,
    /// Values at the nodes.
    pub y: [Fx; N],
}

/// All zeros: a table to build into ([`crate::ModelConfig::coefficients_into`]).
impl<const N: usize> Default for Table1<N> {
    fn default() -> Self {
        Table1 {
            x0: ZERO,
            inv_dx: ZERO,
            y: [ZERO; N],
        }
    }
}

impl<const N: usize> Table1<N> {
    /// Node spacing of a table over [x0, x1].
    pub fn spacing(x0: f32, x1: f32) -> f32 {
        (x1 - x0) / (N - 1) as f32
    }

    /// Builds a table by sampling `f` on [x0, x1] (configuration time).
    pub fn sample(x0: f32, x1: f32, f: impl Fn(f32) -> f32) -> Self {
        let mut t = Self::default();
        t.sample_into(x0, x1, f);
        t
    }

    /// [`Table1::sample`] into this table, in place.
    pub fn sample_into(&mut self, x0: f32, x1: f32, f: impl Fn(f32) -> f32) {
        let dx = Self::spacing(x0, x1);
        for (i, v) in self.y.iter_mut().enumerate() {
            *v = Fx::saturating_from_num(f(x0 + dx * i as f32));
        }
        self.x0 = Fx::saturating_from_num(x0);
        self.inv_dx = Fx::saturating_from_num(1.0 / dx);
    }

    /// Interpolated value at `x`. Out of line: it is called from ~20 places per step, and
    /// inlining each copy cost more flash than the call.
    #[inline(never)]
    pub fn at(&self, x: Fx) -> Fx {
        let (i, f) = locate(x, self.x0, self.inv_dx, N);
        lerp(self.y[i], self.y[i + 1], f)
    }

    /// Interpolated value at `x` in units of 2^−32 (Q16.32 in an `i64`): [`Table1::at`]
    /// without its final rounding to Q16.16 (the 16-bit fraction times the node difference is
    /// exact in Q32.32: < 2^47). Out of line like `at`.
    #[inline(never)]
    pub fn at_ext(&self, x: Fx) -> i64 {
        let (i, f) = locate(x, self.x0, self.inv_dx, N);
        let (a, b) = (self.y[i], self.y[i + 1]);
        (i64::from(a.to_bits()) << 16) + wide::mul(f.to_bits(), b.saturating_sub(a).to_bits())
    }

    /// Interpolated value at `x` given to 2^−32 (its Q16.16 value and the 16 bits below, as
    /// the estimator's nodes keep them), in units of 2^−32 (Q16.32 in an `i64`): the position
    /// with all 32 bits of its fraction, the product with the node difference exact. For the
    /// values whose one-step rounding matters (the Kalman gain and the process noise:
    /// `ObserverCoeffs::gain_q32`). Bit budget: the offset's Q16.16 part times the reciprocal
    /// spacing is < 2^62 as in `locate`, its 16 low bits times it < 2^47; the 32-bit fraction
    /// times a node difference (a saturated Q16.16 difference, < 2^31 in magnitude) is < 2^63.
    /// Every product is of two 32-bit words (one `smull`/`umull` each on a Cortex-M4). Out of
    /// line: on a Cortex-M0 its 64-bit arithmetic is long.
    #[inline(never)]
    pub fn at_q32(&self, x: Fx, lo: u16) -> i64 {
        let dx = x.saturating_sub(self.x0);
        // Unsigned, as in `locate`: the position is ≥ 0, so the index is known to be in range.
        let inv = self.inv_dx.to_bits() as u32;
        let p = if dx < ZERO {
            0
        } else {
            wide::mul_uu(dx.to_bits() as u32, inv) + (wide::mul_uu(u32::from(lo), inv) >> 16)
        };
        if (p >> 32) > (N - 2) as u64 {
            return i64::from(self.y[N - 1].to_bits()) << 16;
        }
        let i = (p >> 32) as usize;
        let (a, b) = (self.y[i], self.y[i + 1]);
        (i64::from(a.to_bits()) << 16)
            + (wide::mul_su(b.saturating_sub(a).to_bits(), p as u32) >> 16)
    }

    /// The same table interpolated in f64 (exact fraction and products; see [`locate_f64`]).
    pub fn at_f64(&self, x: f64) -> f64 {
        lerp_f64(&self.y, locate_f64(x, self.x0, self.inv_dx, N))
    }
}

/// A 2-D table, `R` rows (first coordinate) by `C` columns (second coordinate).
#[derive(Debug, Clone, PartialEq)]
pub struct Table2<const R: usize, const C: usize> {
    /// Row grid start.
    pub r0: Fx,
    /// Row spacing.
    pub dr: Fx,
    /// 1 / row spacing.
    pub inv_dr: Fx,
    /// Column grid start.
    pub c0: Fx,
    /// 1 / column spacing.
    pub inv_dc: Fx,
    /// Values, row-major.
    pub y: [[Fx; C]; R],
}

/// All zeros: a table to build into ([`crate::ModelConfig::coefficients_into`]).
impl<const R: usize, const C: usize> Default for Table2<R, C> {
    fn default() -> Self {
        Table2 {
            r0: ZERO,
            dr: ZERO,
            inv_dr: ZERO,
            c0: ZERO,
            inv_dc: ZERO,
            y: [[ZERO; C]; R],
        }
    }
}

impl<const R: usize, const C: usize> Table2<R, C> {
    /// Builds a table by sampling `f(r, c)` on [r0, r1] × [c0, c1] (configuration time).
    pub fn sample(r: (f32, f32), c: (f32, f32), f: impl Fn(f32, f32) -> f32) -> Self {
        let mut t = Self::default();
        t.sample_into(r, c, f);
        t
    }

    /// [`Table2::sample`] into this table, in place.
    pub fn sample_into(&mut self, r: (f32, f32), c: (f32, f32), f: impl Fn(f32, f32) -> f32) {
        let dc = (c.1 - c.0) / (C - 1) as f32;
        self.sample_rows_into(r, c, |x, row| {
            for (j, v) in row.iter_mut().enumerate() {
                *v = f(x, c.0 + dc * j as f32);
            }
        })
    }

    /// Builds a table a row at a time: `row(r, values)` fills the row at `r` (values start at
    /// 0), for a function whose values along a row are best worked out together (configuration
    /// time).
    pub fn sample_rows(r: (f32, f32), c: (f32, f32), row: impl FnMut(f32, &mut [f32; C])) -> Self {
        let mut t = Self::default();
        t.sample_rows_into(r, c, row);
        t
    }

    /// [`Table2::sample_rows`] into this table, in place (one row's values on the stack).
    pub fn sample_rows_into(
        &mut self,
        r: (f32, f32),
        c: (f32, f32),
        mut row: impl FnMut(f32, &mut [f32; C]),
    ) {
        let dr = (r.1 - r.0) / (R - 1) as f32;
        let dc = (c.1 - c.0) / (C - 1) as f32;
        for (i, out) in self.y.iter_mut().enumerate() {
            let mut values = [0.0f32; C];
            row(r.0 + dr * i as f32, &mut values);
            for (o, v) in out.iter_mut().zip(values) {
                *o = Fx::saturating_from_num(v);
            }
        }
        self.r0 = Fx::saturating_from_num(r.0);
        self.dr = Fx::saturating_from_num(dr);
        self.inv_dr = Fx::saturating_from_num(1.0 / dr);
        self.c0 = Fx::saturating_from_num(c.0);
        self.inv_dc = Fx::saturating_from_num(1.0 / dc);
    }

    /// Bilinear interpolation at (r, c) (out of line, like [`Table1::at`]).
    #[inline(never)]
    pub fn at(&self, r: Fx, c: Fx) -> Fx {
        self.bilinear(r, c).2
    }

    /// The same table interpolated bilinearly in f64 (see [`locate_f64`]).
    pub fn at_f64(&self, r: f64, c: f64) -> f64 {
        let (i, fr) = locate_f64(r, self.r0, self.inv_dr, R);
        let col = locate_f64(c, self.c0, self.inv_dc, C);
        let (lo, hi) = (lerp_f64(&self.y[i], col), lerp_f64(&self.y[i + 1], col));
        lo + fr * (hi - lo)
    }

    /// [`Self::at`], and at the same row coordinate the linear interpolation of `col`, a
    /// function of the row coordinate alone sampled on the same row nodes: one row locate
    /// serves both.
    #[inline(never)]
    pub fn at_with(&self, r: Fx, c: Fx, col: &[Fx; R]) -> (Fx, Fx) {
        let (i, fr, v) = self.bilinear(r, c);
        (v, lerp(col[i], col[i + 1], fr))
    }

    /// The row cell and fraction of `r`, and the bilinear value at (r, c).
    #[inline(always)]
    fn bilinear(&self, r: Fx, c: Fx) -> (usize, Fx, Fx) {
        let (i, fr) = locate(r, self.r0, self.inv_dr, R);
        let (j, fc) = locate(c, self.c0, self.inv_dc, C);
        let lo = lerp(self.y[i][j], self.y[i][j + 1], fc);
        let hi = lerp(self.y[i + 1][j], self.y[i + 1][j + 1], fc);
        (i, fr, lerp(lo, hi, fr))
    }

    /// The row coordinate r at which [`Table2::at`]`(r, c)` equals `y`, for a table that does
    /// not decrease along its rows (held at the first / last row outside the range). At fixed c
    /// the bilinear table is piecewise linear in r: the bracketing cell is found by bisection
    /// (log2 R evaluations of one column interpolation), the position inside it with the
    /// division-free [`recip`].
    #[inline(never)]
    pub fn invert_r(&self, c: Fx, y: Fx) -> Fx {
        let (j, fc) = locate(c, self.c0, self.inv_dc, C);
        let col = |i: usize| lerp(self.y[i][j], self.y[i][j + 1], fc);
        if y <= col(0) {
            return self.r0;
        }
        let (mut lo, mut hi) = (0usize, R - 1);
        if y >= col(hi) {
            return self.r0.saturating_add(self.dr.qmul(Fx::from_num(hi)));
        }
        // Invariant: col(lo) < y < col(hi).
        while hi - lo > 1 {
            let mid = (lo + hi) / 2;
            if col(mid) < y {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        self.row_in_cell(lo, (col(lo), col(hi)), y)
    }

    /// The row coordinate of `y` inside the cell from row `lo` to `lo + 1` whose column values
    /// are `a`, `b` (held at the cell's edges; division-free through [`recip`]).
    fn row_in_cell(&self, lo: usize, (a, b): (Fx, Fx), y: Fx) -> Fx {
        let f = if y <= a {
            ZERO
        } else if y >= b {
            ONE
        } else {
            y.saturating_sub(a)
                .qmul(recip(b.saturating_sub(a)))
                .min(ONE)
        };
        self.r0
            .saturating_add(self.dr.qmul(Fx::from_num(lo).saturating_add(f)))
    }

    /// [`Table2::invert_r`] with bounded work for a slowly moving target, for the per-step
    /// path: `row` (kept by the caller between steps) is the lower row of the bracketing cell,
    /// moved at most one row towards `y` per call. Three column interpolations and one
    /// reciprocal, where `invert_r` needs up to eight; within its cell the result is
    /// `invert_r`'s, and after a jump of the target it reaches it within `R − 2` calls, held at the
    /// edge of the current cell meanwhile.
    #[inline(never)]
    pub fn invert_r_tracking(&self, c: Fx, y: Fx, row: &mut u8) -> Fx {
        let (j, fc) = locate(c, self.c0, self.inv_dc, C);
        let col = |i: usize| lerp(self.y[i][j], self.y[i][j + 1], fc);
        let mut lo = usize::from(*row).min(R - 2);
        let (mut a, mut b) = (col(lo), col(lo + 1));
        if y < a && lo > 0 {
            lo -= 1;
            b = a;
            a = col(lo);
        } else if y > b && lo < R - 2 {
            lo += 1;
            a = b;
            b = col(lo + 1);
        }
        *row = lo as u8;
        self.row_in_cell(lo, (a, b), y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_function_is_reproduced_and_ends_are_held() {
        let t = Table1::<11>::sample(0.0, 100.0, |x| 2.0 * x + 1.0);
        // 1/spacing = 0.1 rounds to 6554/65536 (+6e-5 relative): at x = 37.5 the position is off
        // by 2.3e-4 of a cell, i.e. 0.0046 in y here (slope 20 per unit x, 200 per cell).
        let v = t.at(Fx::from_num(37.5)).to_num::<f32>();
        assert!((v - 76.0).abs() < 0.005, "{v}");
        assert_eq!(t.at(Fx::from_num(-10)).to_num::<f32>(), 1.0);
        assert_eq!(t.at(Fx::from_num(500)).to_num::<f32>(), 201.0);
    }

    #[test]
    fn invert_r_undoes_at_along_the_rows() {
        // Monotone in r, curved in both coordinates, like the valve table.
        let t = Table2::<21, 33>::sample((0.0, 100.0), (0.0, 160.0), |r, c| {
            0.01 * r * r * (c + 1.0).sqrt() + 0.2 * r
        });
        let mut worst = 0.0f32;
        for ri in 0..=200 {
            for c in [0.0f32, 3.3, 47.0, 100.0, 159.0] {
                let r = ri as f32 * 0.5;
                let y = t.at(Fx::from_num(r), Fx::from_num(c));
                let back: f32 = t.invert_r(Fx::from_num(c), y).to_num();
                worst = worst.max((back - r).abs());
            }
        }
        println!("invert_r: worst round trip {worst:.5} (row units)");
        assert!(worst < 0.01, "{worst}");
        assert_eq!(t.invert_r(Fx::from_num(50), Fx::from_num(-1)), ZERO);
        assert_eq!(
            t.invert_r(Fx::from_num(50), Fx::from_num(1e4))
                .to_num::<f32>(),
            100.0
        );
    }

    #[test]
    fn tracking_inverse_reaches_invert_r() {
        let t = Table2::<21, 33>::sample((0.0, 100.0), (0.0, 160.0), |r, c| {
            0.01 * r * r * (c + 1.0).sqrt() + 0.2 * r
        });
        let mut row = 0u8;
        let mut worst = 0.0f32;
        for ri in 0..=40 {
            for c in [3.3f32, 47.0, 159.0] {
                let y = t.at(Fx::from_num(ri as f32 * 2.5), Fx::from_num(c));
                let want: f32 = t.invert_r(Fx::from_num(c), y).to_num();
                // From wherever the last target left the bracket: at most R − 2 calls.
                let mut got = 0.0;
                for _ in 0..19 {
                    got = t.invert_r_tracking(Fx::from_num(c), y, &mut row).to_num();
                }
                worst = worst.max((got - want).abs());
            }
        }
        println!("invert_r_tracking vs invert_r: worst {worst:.6} (row units)");
        assert!(worst < 1e-3, "{worst}");
    }

    #[test]
    fn bilinear_reproduces_a_bilinear_function() {
        let t = Table2::<5, 7>::sample((0.0, 4.0), (0.0, 6.0), |r, c| r * c + r - c);
        let (r, c) = (2.25f32, 3.5f32);
        let v: f32 = t.at(Fx::from_num(r), Fx::from_num(c)).to_num();
        assert!((v - (r * c + r - c)).abs() < 1e-3, "{v}");
    }
}
