//! Sensor front end: 4–20 mA pressure transducers read through a shunt by the 12-bit ADC.
//!
//! Configuration in physical units ([`LoopSpec`]) is validated once and turned into a
//! [`Transducer`] whose per-sample conversion is one subtraction and one multiplication in
//! Q16.16 and cannot fail. Readings outside the NAMUR NE 43 window (below 3.6 mA: wire break;
//! above 21 mA: short) are reported as missing, so the estimator falls back to its model.

use pto_model::fx::{Fx, Pressure};

pub use pto_model::control::LoopSpec;

/// ADC full scale (12 bits).
pub const ADC_MAX: u16 = 4095;
/// Below this current the loop is open (wire break), mA.
pub const WIRE_BREAK_MA: f32 = 3.6;
/// Above this current the loop is shorted, mA.
pub const SHORT_MA: f32 = 21.0;

/// Why a [`LoopSpec`] is rejected.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpecError {
    /// Field name.
    pub field: &'static str,
    /// Its value.
    pub value: f32,
}

impl core::fmt::Display for SpecError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "transducer loop: {} = {} is outside its range (full scale 1–1000 bar, shunt \
             10–1000 Ω, reference 1–5 V, 21 mA within the ADC range)",
            self.field, self.value
        )
    }
}

/// Precomputed conversion of one loop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transducer {
    counts_at_4ma: Fx,
    bar_per_count: Fx,
    lo: u16,
    hi: u16,
    spec: LoopSpec,
}

impl Transducer {
    /// Validates `spec` and precomputes the conversion.
    pub fn new(spec: LoopSpec) -> Result<Self, SpecError> {
        let check = |field, v: f32, lo: f32, hi: f32| {
            if v.is_finite() && v >= lo && v <= hi {
                Ok(())
            } else {
                Err(SpecError { field, value: v })
            }
        };
        check("full_scale_bar", spec.full_scale_bar, 1.0, 1000.0)?;
        check("shunt_ohm", spec.shunt_ohm, 10.0, 1000.0)?;
        check("vref_v", spec.vref_v, 1.0, 5.0)?;
        let per_ma = Self::counts_per_ma(&spec);
        check(
            "shunt_ohm",
            spec.shunt_ohm,
            10.0,
            f32::from(ADC_MAX) / (SHORT_MA * per_ma) * spec.shunt_ohm,
        )?;
        let round = |x: f32| (x + 0.5) as u16;
        Ok(Transducer {
            counts_at_4ma: Fx::from_num(4.0 * per_ma),
            bar_per_count: Fx::from_num(spec.full_scale_bar / (16.0 * per_ma)),
            lo: round(WIRE_BREAK_MA * per_ma),
            hi: round(SHORT_MA * per_ma),
            spec,
        })
    }

    fn counts_per_ma(spec: &LoopSpec) -> f32 {
        spec.shunt_ohm * 1e-3 / spec.vref_v * (f32::from(ADC_MAX) + 1.0)
    }

    /// The pressure of a reading, or `None` outside the 3.6–21 mA window.
    #[inline]
    pub fn pressure(&self, counts: u16) -> Option<Pressure> {
        if counts < self.lo || counts > self.hi {
            return None;
        }
        Some(Pressure(
            Fx::from_num(counts)
                .saturating_sub(self.counts_at_4ma)
                .saturating_mul(self.bar_per_count),
        ))
    }

    /// The ADC reading of a loop current, mA (rounded, clamped to the ADC range). Host tools use
    /// it to make raw samples; it is not on the firmware's per-step path.
    pub fn counts_at_ma(&self, ma: f32) -> u16 {
        let c = ma * Self::counts_per_ma(&self.spec);
        if c <= 0.0 {
            0
        } else if c >= f32::from(ADC_MAX) {
            ADC_MAX
        } else {
            (c + 0.5) as u16
        }
    }

    /// The ADC reading of a pressure, bar (4–20 mA over 0–full scale).
    pub fn counts_at_bar(&self, bar: f32) -> u16 {
        self.counts_at_ma(4.0 + 16.0 * bar / self.spec.full_scale_bar)
    }

    /// Resolution, bar per ADC count.
    pub fn resolution_bar(&self) -> f32 {
        self.bar_per_count.to_num()
    }
}

/// Extends a 16-bit timer count (encoder mode) to 32 bits: the counter must not move by more
/// than ±32 767 counts between two updates (≈ 2 shaft revolutions at 16 384 counts per turn).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Unwrap16 {
    last: u16,
    total: i32,
}

impl Unwrap16 {
    /// Starts at 0 from the counter's current value.
    pub const fn new(now: u16) -> Self {
        Unwrap16 {
            last: now,
            total: 0,
        }
    }

    /// The extended count after the counter reads `now`.
    pub fn update(&mut self, now: u16) -> i32 {
        let step = now.wrapping_sub(self.last) as i16;
        self.last = now;
        self.total = self.total.wrapping_add(i32::from(step));
        self.total
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conversion_round_trips_within_one_count_and_flags_the_window() {
        let t = Transducer::new(LoopSpec::HP).unwrap();
        let res = t.resolution_bar();
        assert!((0.08..0.09).contains(&res), "resolution {res} bar/count");
        let mut worst = 0.0f32;
        for i in 0..=250 {
            let bar = i as f32;
            let p = t.pressure(t.counts_at_bar(bar)).unwrap().0.to_num::<f32>();
            worst = worst.max((p - bar).abs());
        }
        println!("HP loop: worst round trip {worst:.4} bar, resolution {res:.4} bar");
        assert!(worst <= 0.5 * res + 1e-3, "worst {worst}");
        assert_eq!(t.pressure(t.counts_at_ma(0.0)), None, "wire break");
        assert_eq!(t.pressure(t.counts_at_ma(3.5)), None);
        assert!(t.pressure(t.counts_at_ma(3.7)).is_some());
        assert_eq!(t.pressure(t.counts_at_ma(22.0)), None, "short");
        assert_eq!(t.pressure(ADC_MAX), None);
    }

    #[test]
    fn sixteen_bit_counts_unwrap_across_the_wrap() {
        let mut u = Unwrap16::new(65_530);
        assert_eq!(u.update(65_535), 5);
        assert_eq!(u.update(4), 10);
        assert_eq!(u.update(65_000), 10 - 540);
        let mut v = Unwrap16::new(0);
        let mut raw = 0u16;
        for i in 1..=200_000i32 {
            raw = raw.wrapping_add(7);
            assert_eq!(v.update(raw), 7 * i);
        }
    }

    #[test]
    fn bad_specs_are_rejected_with_their_field() {
        let e = Transducer::new(LoopSpec {
            shunt_ohm: 5.0,
            ..LoopSpec::HP
        })
        .unwrap_err();
        assert_eq!(e.field, "shunt_ohm");
        // 21 mA across 200 Ω is 4.2 V: above the 3.3 V reference.
        let e = Transducer::new(LoopSpec {
            shunt_ohm: 200.0,
            ..LoopSpec::HP
        })
        .unwrap_err();
        assert_eq!(e.field, "shunt_ohm");
        assert!(Transducer::new(LoopSpec::LP).is_ok());
    }
}
