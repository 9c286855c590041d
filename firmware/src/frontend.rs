//! Sensor front end: 4–20 mA pressure transducers read through a shunt by the 12-bit ADC.
//!
//! Configuration in physical units ([`LoopSpec`]) is validated once and turned into a
//! [`Transducer`] whose per-sample conversion is one subtraction and one multiplication in
//! Q16.16 and cannot fail. Readings outside the NAMUR NE 43 window (below 3.6 mA: wire break;
//! above 21 mA: short) are reported as missing, so the estimator falls back to its model.
//!
//! The ADC measures against its supply, VDDA, which is not exactly the loops' nominal reference
//! (`vref_v`): each 1 % of supply error is ≈ 2 bar at the 140 bar trip. The board measures VDDA
//! against the chip's internal reference (VREFINT, calibrated at 3.3 V in the factory: DS8626,
//! "Internal reference voltage calibration values", `VREFINT_CAL` at `0x1FFF_7A2A`) and each
//! sample carries it ([`supply_mv_from_vrefint`]); [`SupplyCorrection`] scales the readings by
//! it. A saturated conversion (at or above VDDA: a short, or a supply too low for the loop)
//! is never taken as a reading ([`LoopReading::Saturated`]), whatever the correction.

use pto_model::fx::{Fx, Pressure};
use pto_model::protocol::selftest::LoopState;

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

    /// The state of a (supply-corrected) reading: in the 3.6–21 mA window, open, or short.
    pub fn state(&self, counts: u16) -> LoopState {
        if counts < self.lo {
            LoopState::Open
        } else if counts > self.hi {
            LoopState::Short
        } else {
            LoopState::InWindow
        }
    }

    /// The loop current of a (supply-corrected) reading, µA (the self-test's report; not on
    /// the per-step path).
    pub fn current_ua(&self, counts: u16) -> u32 {
        (f32::from(counts) * 1000.0 / Self::counts_per_ma(&self.spec) + 0.5) as u32
    }

    /// The nominal ADC reference of this loop, mV.
    pub fn vref_mv(&self) -> u16 {
        (self.spec.vref_v * 1000.0 + 0.5) as u16
    }
}

/// The mean of oversampled conversions of one input, rounded; [`ADC_MAX`] if any of them
/// saturated (a saturated conversion says only "at or above the reference": its mean with the
/// others would be a plausible-looking number).
pub fn oversampled(conversions: &[u16]) -> u16 {
    if conversions.is_empty() || conversions.iter().any(|&c| c >= ADC_MAX) {
        return ADC_MAX;
    }
    let n = conversions.len() as u32;
    let sum: u32 = conversions.iter().map(|&c| u32::from(c)).sum();
    ((sum + n / 2) / n) as u16
}

/// The lowest and highest ADC reference (VDDA) taken as a real measurement, mV: below, the
/// brown-out reset (level 3, ≈ 2.8 V) would have stopped the chip; above, the datasheet's
/// 3.6 V maximum. A measurement outside is a failed measurement, not a supply.
pub const SUPPLY_PLAUSIBLE_MV: core::ops::RangeInclusive<u16> = 2_700..=3_600;
/// `VREFINT_CAL`'s plausible range, counts: VREFINT is 1.18–1.24 V (DS8626), 1 465–1 539
/// counts at 3.3 V; a value outside is an unreadable calibration, and the typical 1.21 V
/// ([`VREFINT_TYP_COUNTS`]) is used.
pub const VREFINT_CAL_PLAUSIBLE: core::ops::RangeInclusive<u16> = 1_400..=1_600;
/// VREFINT's typical 1.21 V as counts at 3.3 V.
pub const VREFINT_TYP_COUNTS: u16 = 1_502;

/// VDDA from a conversion of VREFINT and the chip's calibration (`VREFINT_CAL`, taken at
/// VDDA = 3.3 V): VDDA = 3.3 V · CAL / DATA, mV; 0 for a conversion that cannot be one (0, or
/// saturated). Whether it is plausible is [`SupplyCorrection`]'s to judge.
pub fn supply_mv_from_vrefint(vrefint: u16, cal: u16) -> u16 {
    let cal = if VREFINT_CAL_PLAUSIBLE.contains(&cal) {
        cal
    } else {
        VREFINT_TYP_COUNTS
    };
    if vrefint == 0 || vrefint >= ADC_MAX {
        return 0;
    }
    let mv = (3_300 * u32::from(cal) + u32::from(vrefint) / 2) / u32::from(vrefint);
    u16::try_from(mv).unwrap_or(u16::MAX)
}

/// A raw loop reading after the supply correction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoopReading {
    /// Counts as the nominal reference would have read them.
    Counts(u16),
    /// The conversion saturated: the voltage is at or above VDDA, its value unknown.
    Saturated,
    /// The measured supply is implausible: no reading can be trusted.
    SupplyFault,
}

/// Scales raw readings from the measured ADC reference to the loops' nominal one:
/// counts · VDDA / vref, as a Q16 gain worked out when the supply reading changes (the board
/// filters it, so that is rarely), a multiplication per reading otherwise.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SupplyCorrection {
    nominal_mv: u16,
    supply_mv: Option<u16>,
    gain_q16: u32,
    plausible: bool,
}

impl SupplyCorrection {
    /// No correction until a supply reading comes (nominal reference `nominal_mv`).
    pub const fn new(nominal_mv: u16) -> Self {
        SupplyCorrection {
            nominal_mv,
            supply_mv: None,
            gain_q16: 1 << 16,
            plausible: true,
        }
    }

    /// Takes a sample's supply reading (`None`: the board does not measure it, the nominal
    /// reference stands); returns whether it is plausible.
    pub fn update(&mut self, supply_mv: Option<u16>) -> bool {
        if supply_mv != self.supply_mv {
            self.supply_mv = supply_mv;
            match supply_mv {
                None => {
                    self.gain_q16 = 1 << 16;
                    self.plausible = true;
                }
                Some(mv) => {
                    self.plausible = SUPPLY_PLAUSIBLE_MV.contains(&mv) && self.nominal_mv > 0;
                    if self.plausible {
                        self.gain_q16 = ((u32::from(mv) << 16) + u32::from(self.nominal_mv) / 2)
                            / u32::from(self.nominal_mv);
                    }
                }
            }
        }
        self.plausible
    }

    /// A raw reading, corrected.
    pub fn correct(&self, raw: u16) -> LoopReading {
        if !self.plausible {
            LoopReading::SupplyFault
        } else if raw >= ADC_MAX {
            LoopReading::Saturated
        } else {
            let c = (u32::from(raw) * self.gain_q16 + (1 << 15)) >> 16;
            LoopReading::Counts(u16::try_from(c).unwrap_or(u16::MAX))
        }
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

    /// The review's cases. A short (21.5 mA, 3.23 V across 150 Ω) with VDDA at 3.4 V converts
    /// to 3 885 counts: inside the nominal window (20.6 mA), a plausible pressure; corrected
    /// for the supply it is a short. With VDDA at 3.1 V the same short saturates the ADC, and
    /// a saturated 4 095 corrected down for the low supply would be 20.7 mA, in the window
    /// again: a saturated conversion is never a reading.
    #[test]
    fn a_short_is_a_short_whatever_the_supply() {
        let lp = Transducer::new(LoopSpec::LP).unwrap();
        let hp = Transducer::new(LoopSpec::HP).unwrap();
        let at = |ma: f32, vdda_mv: f32| -> u16 {
            // What the ADC converts for `ma` with its reference at `vdda_mv`.
            let v = ma * 150e-3;
            ((v / (vdda_mv * 1e-3) * 4096.0) as u32).min(4095) as u16
        };
        let mut c = SupplyCorrection::new(3300);
        let raw = at(21.5, 3400.0);
        assert!(
            lp.pressure(raw).is_some(),
            "uncorrected: a plausible LP reading"
        );
        assert!(c.update(Some(3400)));
        match c.correct(raw) {
            LoopReading::Counts(n) => {
                assert_eq!(lp.state(n), LoopState::Short);
                assert_eq!(lp.pressure(n), None);
            }
            other => panic!("{other:?}"),
        }
        let raw = at(21.5, 3100.0);
        assert_eq!(raw, ADC_MAX);
        assert!(c.update(Some(3100)));
        let naive = (u32::from(raw) * 3100 / 3300) as u16;
        assert_eq!(lp.state(naive), LoopState::InWindow, "the naive correction");
        assert_eq!(c.correct(raw), LoopReading::Saturated);
        assert_eq!(oversampled(&[4000, 4095, 3990, 4010]), ADC_MAX);
        assert_eq!(oversampled(&[1000, 1001, 1002, 1002]), 1001);
        // A supply 3 % low: a 12 mA reading (125 bar) is ≈ 3.9 bar high uncorrected, within a
        // count corrected.
        let raw = at(12.0, 3200.0);
        let uncorrected = hp.pressure(raw).unwrap().0.to_num::<f32>();
        let corrected = match c.update(Some(3200)).then(|| c.correct(raw)) {
            Some(LoopReading::Counts(n)) => hp.pressure(n).unwrap().0.to_num::<f32>(),
            other => panic!("{other:?}"),
        };
        println!("12 mA at VDDA 3.2 V: {uncorrected:.2} bar uncorrected, {corrected:.2} corrected");
        assert!((uncorrected - 125.0).abs() > 3.5);
        assert!(
            (corrected - 125.0).abs() <= 1.5 * hp.resolution_bar(),
            "{corrected}"
        );
        // Implausible supply readings make every loop reading untrusted.
        assert!(!c.update(Some(2000)));
        assert_eq!(c.correct(1000), LoopReading::SupplyFault);
        assert!(c.update(None), "no measurement: the nominal reference");
        assert_eq!(c.correct(1000), LoopReading::Counts(1000));
    }

    #[test]
    fn vdda_comes_from_vrefint_and_its_factory_calibration() {
        // VREFINT 1.21 V, calibrated 1 502 counts at 3.3 V; at VDDA 3.0 V it converts to 1 652.
        assert_eq!(supply_mv_from_vrefint(1652, 1502), 3000);
        assert_eq!(supply_mv_from_vrefint(1502, 1502), 3300);
        // An unreadable calibration: the typical value.
        assert_eq!(supply_mv_from_vrefint(1502, 0xFFFF), 3300);
        assert_eq!(supply_mv_from_vrefint(0, 1502), 0);
        assert_eq!(supply_mv_from_vrefint(ADC_MAX, 1502), 0);
        // A VREFINT conversion of 3 300 counts would mean VDDA = 1.5 V: a failed measurement,
        // which the correction refuses.
        let mut c = SupplyCorrection::new(3300);
        assert!(!c.update(Some(supply_mv_from_vrefint(3300, 1502))));
        assert!(!c.update(Some(supply_mv_from_vrefint(0, 1502))));
        let t = Transducer::new(LoopSpec::HP).unwrap();
        assert_eq!(t.state(t.counts_at_ma(2.0)), LoopState::Open);
        assert_eq!(t.state(t.counts_at_ma(12.0)), LoopState::InWindow);
        assert_eq!(t.state(t.counts_at_ma(21.5)), LoopState::Short);
        let ua = t.current_ua(t.counts_at_ma(12.0));
        assert!((11_990..=12_010).contains(&ua), "{ua}");
        assert_eq!(t.vref_mv(), 3300);
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
