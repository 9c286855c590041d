//! The outputs and their de-energised levels: the one place where "dump valve open" becomes a
//! pin level.
//!
//! Every output is safe when its driver is off, so a reset, a brown-out, a power loss or a
//! halted controller leaves the bench safe without any code running:
//!
//! | output | de-energised (pin low, pulled down) | energised (pin high) |
//! |---|---|---|
//! | proportional valve command (PWM → RC → amplifier) | 0 V: valve closed | aperture |
//! | dump valve (normally open) | **open**: HP vents to tank | closed |
//! | duty solenoids HC3.1…HC3.4 | off: cylinder idle | on duty |
//!
//! From reset the pins float (RM0090 §8.3.1: inputs, floating, until configured) and the
//! board's external pull-downs hold the drivers off; [`Outputs::at_boot`] is what the firmware
//! then drives before anything else, from the trip memory. The control task applies each
//! step's outputs itself, before it logs anything ([`Actuators::apply`]).

use embedded_hal::digital::OutputPin;
use embedded_hal::pwm::SetDutyCycle;
use pto_model::fx::Aperture;

/// What the outputs do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Outputs {
    /// Valve aperture.
    pub aperture: Aperture,
    /// Dump valve open.
    pub dump_open: bool,
    /// Solenoids energised (bit i = HC3.(i+1)).
    pub on_duty: u8,
}

impl Outputs {
    /// Every driver off: valve closed, dump valve open, solenoids off.
    pub const DE_ENERGISED: Outputs = Outputs {
        aperture: Aperture::ZERO,
        dump_open: true,
        on_duty: 0,
    };

    /// What the board drives at boot, before the controller exists: de-energised, or, when
    /// the trip held at the last reset, the trip's safe state (the dump valve open and the
    /// valve at the overpressure aperture, `overpressure_aperture_pct`).
    pub fn at_boot(tripped_before_reset: bool, overpressure_aperture_pct: f32) -> Outputs {
        if tripped_before_reset {
            Outputs {
                aperture: Aperture::from_num(overpressure_aperture_pct.clamp(0.0, 100.0)),
                ..Outputs::DE_ENERGISED
            }
        } else {
            Outputs::DE_ENERGISED
        }
    }

    /// The pin levels: the valve's duty (of `max_duty`), the dump valve's driver (on = closed),
    /// the solenoids' drivers.
    pub fn levels(&self, max_duty: u16) -> PinLevels {
        // Aperture % → duty: Q16.16 percent × max / 100, in integers.
        let bits = u64::try_from(self.aperture.to_bits().max(0)).unwrap_or(0);
        let duty = ((bits * u64::from(max_duty)) / (100u64 << 16)).min(u64::from(max_duty));
        PinLevels {
            valve_duty: duty as u16,
            dump_energised: !self.dump_open,
            solenoids_energised: self.on_duty & 0x0F,
        }
    }
}

/// Pin levels of [`Outputs`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PinLevels {
    /// The valve's PWM duty.
    pub valve_duty: u16,
    /// The dump valve's driver on (the valve closed).
    pub dump_energised: bool,
    /// Solenoid drivers on (bit i = HC3.(i+1)).
    pub solenoids_energised: u8,
}

/// An output whose level can be read back from the hardware (`None`: not readable).
pub trait ReadBack {
    /// The level the pin is at (`true`: high, the driver energised).
    fn read_back(&self) -> Option<bool>;
}

/// A PWM whose duty can be read back.
pub trait DutyReadBack {
    /// The duty the timer runs at.
    fn duty_read_back(&self) -> Option<u16>;
}

/// The valve, the dump valve and the four solenoids.
pub struct Actuators<V, P> {
    valve: V,
    dump: P,
    solenoids: [P; 4],
    applied: Outputs,
}

impl<V: SetDutyCycle + DutyReadBack, P: OutputPin + ReadBack> Actuators<V, P> {
    /// Takes the drivers and drives `at` at once.
    pub fn new(valve: V, dump: P, solenoids: [P; 4], at: Outputs) -> Self {
        let mut a = Actuators {
            valve,
            dump,
            solenoids,
            applied: at,
        };
        a.apply(&at);
        a
    }

    /// Drives `o` (driver errors are ignored: the board's drivers are infallible, and a pin that
    /// does not follow shows in [`Actuators::read_back`]).
    pub fn apply(&mut self, o: &Outputs) {
        let l = o.levels(self.valve.max_duty_cycle());
        let _ = self.valve.set_duty_cycle(l.valve_duty);
        let _ = self.dump.set_state(l.dump_energised.into());
        for (i, s) in self.solenoids.iter_mut().enumerate() {
            let _ = s.set_state((l.solenoids_energised & (1 << i) != 0).into());
        }
        self.applied = *o;
    }

    /// What was last applied.
    pub fn applied(&self) -> Outputs {
        self.applied
    }

    /// The outputs as the hardware reads them back: the valve's aperture from its duty, the
    /// dump valve's driver (`true` = energised, closed), the solenoids' drivers.
    pub fn read_back(&self) -> (Option<Aperture>, Option<bool>, Option<u8>) {
        let max = u64::from(self.valve.max_duty_cycle().max(1));
        let valve = self
            .valve
            .duty_read_back()
            .map(|d| Aperture::from_bits(((u64::from(d) * (100u64 << 16) + max / 2) / max) as i32));
        let solenoids = self
            .solenoids
            .iter()
            .enumerate()
            .try_fold(0u8, |m, (i, s)| {
                s.read_back().map(|on| m | (u8::from(on) << i))
            });
        (valve, self.dump.read_back(), solenoids)
    }
}

/// A valve PWM channel in memory for the host tests: the duty it was set to, read back (4 199
/// counts full scale, as the bench's timer).
#[cfg(test)]
#[derive(Default)]
pub(crate) struct MemPwm(pub u16);

#[cfg(test)]
impl embedded_hal::pwm::ErrorType for MemPwm {
    type Error = core::convert::Infallible;
}

#[cfg(test)]
impl SetDutyCycle for MemPwm {
    fn max_duty_cycle(&self) -> u16 {
        4199
    }
    fn set_duty_cycle(&mut self, d: u16) -> Result<(), core::convert::Infallible> {
        self.0 = d;
        Ok(())
    }
}

#[cfg(test)]
impl DutyReadBack for MemPwm {
    fn duty_read_back(&self) -> Option<u16> {
        Some(self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use core::convert::Infallible;

    #[derive(Default)]
    struct Pin {
        high: bool,
        stuck_low: bool,
    }
    impl embedded_hal::digital::ErrorType for Pin {
        type Error = Infallible;
    }
    impl OutputPin for Pin {
        fn set_low(&mut self) -> Result<(), Infallible> {
            self.high = false;
            Ok(())
        }
        fn set_high(&mut self) -> Result<(), Infallible> {
            self.high = !self.stuck_low;
            Ok(())
        }
    }
    impl ReadBack for Pin {
        fn read_back(&self) -> Option<bool> {
            Some(self.high)
        }
    }
    use crate::outputs::MemPwm as Pwm;

    fn actuators(at: Outputs) -> Actuators<Pwm, Pin> {
        Actuators::new(Pwm::default(), Pin::default(), Default::default(), at)
    }

    /// The review's finding: dump open was a high pin, so a reset, a brown-out or a power loss
    /// (every pin low or floating) closed the dump valve. Now every de-energised pin is the
    /// safe state, and a boot that remembers a trip drives the trip's valve at once.
    #[test]
    fn de_energised_pins_are_the_safe_state_and_a_tripped_boot_drives_the_trip_levels() {
        let all_low = PinLevels {
            valve_duty: 0,
            dump_energised: false,
            solenoids_energised: 0,
        };
        assert_eq!(Outputs::DE_ENERGISED.levels(4199), all_low);
        const { assert!(Outputs::DE_ENERGISED.dump_open) };
        assert_eq!(Outputs::at_boot(false, 100.0), Outputs::DE_ENERGISED);
        let t = Outputs::at_boot(true, 100.0);
        assert!(t.dump_open && t.on_duty == 0 && t.aperture.to_f32() == 100.0);
        let a = actuators(t);
        let (valve, dump, sol) = a.read_back();
        assert_eq!(valve.unwrap().to_f32(), 100.0);
        assert_eq!((dump, sol), (Some(false), Some(0)), "dump driver off: open");
        // Running, untripped: the dump valve's driver on (closed).
        let run = Outputs {
            aperture: Aperture::from_num(12.5),
            dump_open: false,
            on_duty: 0b1001,
        };
        let l = run.levels(4199);
        assert!(l.dump_energised && l.solenoids_energised == 0b1001);
        assert_eq!(l.valve_duty, 524, "12.5 % of 4199");
    }

    #[test]
    fn a_pin_that_does_not_follow_shows_in_the_read_back() {
        let mut a = actuators(Outputs::DE_ENERGISED);
        a.solenoids[2].stuck_low = true;
        a.apply(&Outputs {
            aperture: Aperture::from_num(5.0),
            dump_open: true,
            on_duty: 0b0100,
        });
        let (valve, dump, sol) = a.read_back();
        assert!((valve.unwrap().to_f32() - 5.0).abs() < 0.03);
        assert_eq!(dump, Some(false));
        assert_eq!(sol, Some(0), "HC3.3 commanded, its pin stays low");
        assert_eq!(a.applied().on_duty, 0b0100);
    }
}
