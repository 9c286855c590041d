//! The bring-up self-test's state in the controller: which output it drives and for how much
//! longer (the messages and the rules are in [`pto_model::protocol::selftest`]).

use crate::outputs::Outputs;
use pto_model::fx::Aperture;
use pto_model::protocol::selftest::{
    SELFTEST_DRIVE_HOLD_S, SELFTEST_IDLE_S, SELFTEST_VALVE_MAX_PCT, SelfTestRefusal, TestDrive,
};

/// An active self-test.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SelfTestState {
    drive: TestDrive,
    /// Steps until the drive returns to all-off.
    drive_left: u32,
    /// Steps until the self-test ends for want of a request.
    idle_left: u32,
    dt_log2: u8,
}

/// Why a self-test ended by itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum Ended {
    /// No request for [`SELFTEST_IDLE_S`].
    Idle,
    /// The overpressure trip latched.
    Tripped,
}

impl SelfTestState {
    /// A self-test just begun, everything de-energised.
    pub fn begin(dt_log2: u8) -> Self {
        SelfTestState {
            drive: TestDrive::AllOff,
            drive_left: 0,
            idle_left: u32::from(SELFTEST_IDLE_S) << dt_log2,
            dt_log2,
        }
    }

    /// Takes a drive request (checked first; nothing changes when refused).
    pub fn drive(&mut self, d: TestDrive) -> Result<(), SelfTestRefusal> {
        match d {
            TestDrive::Valve(a)
                if a < Aperture::ZERO
                    || a > Aperture::from_num(f32::from(SELFTEST_VALVE_MAX_PCT)) =>
            {
                return Err(SelfTestRefusal::ApertureTooHigh(a));
            }
            TestDrive::Solenoid(n) if n > 3 => return Err(SelfTestRefusal::NoSuchSolenoid(n)),
            _ => {}
        }
        self.drive = d;
        self.drive_left = u32::from(SELFTEST_DRIVE_HOLD_S) << self.dt_log2;
        self.touch();
        Ok(())
    }

    /// A request came: the idle time starts again.
    pub fn touch(&mut self) {
        self.idle_left = u32::from(SELFTEST_IDLE_S) << self.dt_log2;
    }

    /// One step: the drive's hold and the idle time run down; `Err` when the self-test ends.
    pub fn step(&mut self) -> Result<(), Ended> {
        self.idle_left = self.idle_left.saturating_sub(1);
        if self.idle_left == 0 {
            return Err(Ended::Idle);
        }
        if self.drive_left > 0 {
            self.drive_left -= 1;
            if self.drive_left == 0 {
                self.drive = TestDrive::AllOff;
            }
        }
        Ok(())
    }

    /// What is driven.
    pub fn driving(&self) -> TestDrive {
        self.drive
    }

    /// The outputs: the one driven, every other de-energised.
    pub fn outputs(&self) -> Outputs {
        let off = Outputs::DE_ENERGISED;
        match self.drive {
            TestDrive::AllOff => off,
            TestDrive::Valve(a) => Outputs { aperture: a, ..off },
            TestDrive::DumpClosed => Outputs {
                dump_open: false,
                ..off
            },
            TestDrive::Solenoid(n) => Outputs {
                on_duty: 1 << (n & 3),
                ..off
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_output_at_a_time_within_its_limits_and_for_a_bounded_time() {
        let mut t = SelfTestState::begin(10);
        assert_eq!(t.outputs(), Outputs::DE_ENERGISED);
        assert!(matches!(
            t.drive(TestDrive::Valve(Aperture::from_num(10.5))),
            Err(SelfTestRefusal::ApertureTooHigh(_))
        ));
        assert!(t.drive(TestDrive::Valve(Aperture::from_num(-1.0))).is_err());
        assert_eq!(
            t.drive(TestDrive::Solenoid(4)),
            Err(SelfTestRefusal::NoSuchSolenoid(4))
        );
        assert_eq!(
            t.outputs(),
            Outputs::DE_ENERGISED,
            "refusals change nothing"
        );
        t.drive(TestDrive::Valve(Aperture::from_num(5.0))).unwrap();
        let o = t.outputs();
        assert!(o.dump_open && o.on_duty == 0 && o.aperture.to_f32() == 5.0);
        t.drive(TestDrive::DumpClosed).unwrap();
        let o = t.outputs();
        assert!(!o.dump_open && o.aperture == Aperture::ZERO && o.on_duty == 0);
        t.drive(TestDrive::Solenoid(2)).unwrap();
        assert_eq!(t.outputs().on_duty, 0b0100);
        assert!(t.outputs().dump_open);
        // The drive holds 10 s, then all off; the self-test ends after 60 s without a request.
        let hold = u32::from(SELFTEST_DRIVE_HOLD_S) << 10;
        for _ in 0..hold - 1 {
            t.step().unwrap();
        }
        assert_eq!(t.driving(), TestDrive::Solenoid(2));
        t.step().unwrap();
        assert_eq!(t.driving(), TestDrive::AllOff);
        let idle = u32::from(SELFTEST_IDLE_S) << 10;
        let mut n = hold;
        while t.step().is_ok() {
            n += 1;
        }
        assert_eq!(n + 1, idle);
        assert_eq!(t.step(), Err(Ended::Idle));
    }
}
