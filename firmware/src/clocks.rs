//! The core clock: 168 MHz from the board's crystal (HSE) through the main PLL, or from the
//! internal RC oscillator (HSI, 16 MHz) when the board has no crystal or it does not start.
//!
//! The crystal is a setting of the bench file (`[controller.board] hse_mhz`, built in as
//! [`crate::built_config::HSE_MHZ`]), not an assumption: a 12 MHz crystal with the 8 MHz
//! settings would put the VCO at 504 MHz, above its 432 MHz limit. The PLL is worked out here,
//! checked against RM0090's limits, and tested for every crystal the datasheet allows.
//!
//! RM0090 §7.3.2 (`RCC_PLLCFGR`): VCO input = f_in / M in 1–2 MHz (2 MHz recommended, to limit
//! the PLL's jitter), 2 ≤ M ≤ 63; VCO output = VCO input × N in 100–432 MHz, 50 ≤ N ≤ 432;
//! SYSCLK = VCO / P, P ∈ {2, 4, 6, 8}, ≤ 168 MHz; the 48 MHz clock = VCO / Q, 2 ≤ Q ≤ 15.
//! DS8626 ("HSE 4–26 MHz oscillator characteristics"): a crystal of 4–26 MHz, starting in
//! 2 ms typically.

/// The core clock the firmware runs at, Hz (the datasheet's maximum).
pub const SYSCLK_HZ: u32 = 168_000_000;
/// The internal RC oscillator, Hz.
pub const HSI_HZ: u32 = 16_000_000;
/// How long the crystal is given to start before the internal oscillator is used instead, ms:
/// 50× the datasheet's typical 2 ms (a crystal that needs longer is out of its specification).
pub const HSE_STARTUP_TIMEOUT_MS: u32 = 100;
/// The crystals the datasheet allows, MHz.
pub const HSE_RANGE_MHZ: core::ops::RangeInclusive<u32> = 4..=26;

/// VCO output the firmware aims for, Hz: 168 MHz × 2 (P = 2), 48 MHz × 7 (Q = 7).
const VCO_HZ: u32 = 336_000_000;

/// The main PLL's dividers and multiplier (`RCC_PLLCFGR` fields).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pll {
    /// Input divider.
    pub m: u8,
    /// VCO multiplier.
    pub n: u16,
    /// SYSCLK divider.
    pub p: u8,
    /// 48 MHz clock divider.
    pub q: u8,
}

/// Why no PLL setting reaches 168 MHz from an input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClockError {
    /// A crystal outside the datasheet's 4–26 MHz.
    OutOfRange(u32),
    /// Not a whole number of MHz: no M gives a VCO input of exactly 1 or 2 MHz.
    NotWholeMhz(u32),
}

impl core::fmt::Display for ClockError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            ClockError::OutOfRange(hz) => write!(
                f,
                "a {hz} Hz crystal is outside the STM32F405's 4–26 MHz (DS8626, HSE oscillator)"
            ),
            ClockError::NotWholeMhz(hz) => write!(
                f,
                "a {hz} Hz crystal is not a whole number of MHz: the PLL cannot make 168 MHz from it"
            ),
        }
    }
}

impl Pll {
    /// The PLL that makes [`SYSCLK_HZ`] from `input_hz` (a crystal, or [`HSI_HZ`]): VCO input
    /// 2 MHz when `input_hz` is an even number of MHz, else 1 MHz.
    pub const fn for_input(input_hz: u32) -> Result<Pll, ClockError> {
        if input_hz < *HSE_RANGE_MHZ.start() * 1_000_000
            || input_hz > *HSE_RANGE_MHZ.end() * 1_000_000
        {
            return Err(ClockError::OutOfRange(input_hz));
        }
        let vco_in = if input_hz.is_multiple_of(2_000_000) {
            2_000_000
        } else if input_hz.is_multiple_of(1_000_000) {
            1_000_000
        } else {
            return Err(ClockError::NotWholeMhz(input_hz));
        };
        Ok(Pll {
            m: (input_hz / vco_in) as u8,
            n: (VCO_HZ / vco_in) as u16,
            p: 2,
            q: 7,
        })
    }

    /// The VCO input, Hz.
    pub const fn vco_input_hz(&self, input_hz: u32) -> u32 {
        input_hz / self.m as u32
    }

    /// The VCO output, Hz.
    pub const fn vco_hz(&self, input_hz: u32) -> u32 {
        self.vco_input_hz(input_hz) * self.n as u32
    }

    /// SYSCLK, Hz.
    pub const fn sysclk_hz(&self, input_hz: u32) -> u32 {
        self.vco_hz(input_hz) / self.p as u32
    }

    /// Whether every field and frequency is inside RM0090's limits.
    pub const fn within_limits(&self, input_hz: u32) -> bool {
        let vin = self.vco_input_hz(input_hz);
        let vco = self.vco_hz(input_hz);
        self.m >= 2
            && self.m <= 63
            && self.n >= 50
            && self.n <= 432
            && matches!(self.p, 2 | 4 | 6 | 8)
            && self.q >= 2
            && self.q <= 15
            && vin >= 1_000_000
            && vin <= 2_000_000
            && vco >= 100_000_000
            && vco <= 432_000_000
            && self.sysclk_hz(input_hz) <= SYSCLK_HZ
            && vco / self.q as u32 <= 48_000_000
    }
}

/// The clock plan of a board: the crystal it is built for (`None`: no crystal) and whether it
/// started. The PLL always comes out at 168 MHz.
pub const fn plan(hse_mhz: Option<u8>, started: bool) -> (u32, Result<Pll, ClockError>) {
    match hse_mhz {
        Some(mhz) if started => {
            let hz = mhz as u32 * 1_000_000;
            (hz, Pll::for_input(hz))
        }
        _ => (HSI_HZ, Pll::for_input(HSI_HZ)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_whole_mhz_crystal_and_the_internal_oscillator_give_168_mhz_within_limits() {
        for mhz in HSE_RANGE_MHZ {
            let hz = mhz * 1_000_000;
            let p = Pll::for_input(hz).unwrap();
            assert!(p.within_limits(hz), "{mhz} MHz: {p:?}");
            assert_eq!(p.sysclk_hz(hz), SYSCLK_HZ, "{mhz} MHz");
            assert_eq!(p.vco_hz(hz) / u32::from(p.q), 48_000_000, "{mhz} MHz");
            let vin = p.vco_input_hz(hz);
            assert_eq!(vin, if mhz % 2 == 0 { 2_000_000 } else { 1_000_000 });
        }
        let hsi = Pll::for_input(HSI_HZ).unwrap();
        assert_eq!(
            hsi,
            Pll {
                m: 8,
                n: 168,
                p: 2,
                q: 7
            }
        );
        assert!(hsi.within_limits(HSI_HZ));
    }

    /// The review's case: a 12 MHz crystal with the 8 MHz settings (M = 4, N = 168) puts the
    /// VCO at 504 MHz; worked out for 12 MHz it is 336 MHz.
    #[test]
    fn a_12_mhz_crystal_gets_its_own_dividers() {
        let wrong = Pll {
            m: 4,
            n: 168,
            p: 2,
            q: 7,
        };
        assert_eq!(wrong.vco_hz(12_000_000), 504_000_000);
        assert!(!wrong.within_limits(12_000_000));
        let p = Pll::for_input(12_000_000).unwrap();
        assert_eq!(
            p,
            Pll {
                m: 6,
                n: 168,
                p: 2,
                q: 7
            }
        );
        assert_eq!(p.vco_hz(12_000_000), 336_000_000);
        assert_eq!(
            Pll::for_input(8_000_000).unwrap(),
            Pll {
                m: 4,
                n: 168,
                p: 2,
                q: 7
            }
        );
        assert_eq!(
            Pll::for_input(25_000_000).unwrap(),
            Pll {
                m: 25,
                n: 336,
                p: 2,
                q: 7
            }
        );
    }

    #[test]
    fn crystals_the_pll_cannot_take_are_refused_and_a_dead_crystal_falls_back() {
        assert_eq!(
            Pll::for_input(3_000_000),
            Err(ClockError::OutOfRange(3_000_000))
        );
        assert_eq!(
            Pll::for_input(27_000_000),
            Err(ClockError::OutOfRange(27_000_000))
        );
        assert_eq!(
            Pll::for_input(14_745_600),
            Err(ClockError::NotWholeMhz(14_745_600))
        );
        assert!(ClockError::OutOfRange(3).to_string().contains("4–26 MHz"));
        assert_eq!(plan(Some(8), true).0, 8_000_000);
        assert_eq!(plan(Some(8), false).0, HSI_HZ, "crystal did not start");
        assert_eq!(plan(None, false).0, HSI_HZ);
        assert_eq!(plan(Some(8), false).1, Pll::for_input(HSI_HZ));
    }
}
