//! The sensor-fault latch: a sensor the estimator's residuals name (`pto_model::estimator`:
//! [`fault::HP_DISAGREES`], [`fault::MOTOR_DISAGREES`], [`fault::LP_DISAGREES`],
//! [`fault::ENCODER_STUCK`]) is held
//! faulted, its readings are no longer given to the estimator, and the controller goes to its
//! safe state, until the host clears it while the sensor agrees with the model again.
//!
//! Isolation, two residuals against one: the HP shadow check compares the HP reading with the
//! model alone (the pump's flow from the encoder, the valve's from P2 and the aperture); the
//! motor check compares the measured speed with the model's from P2. A stuck, drifting or
//! scaled HP reading trips the first (and may trip the second later); a faulty motor pickup
//! trips only the second. So the HP check names the HP transducer; the motor check names the
//! motor pickup only while the HP reading is trusted — and then says that the two disagree
//! (a scale error of the HP transducer at a steady P2 looks the same: the reaction is the same
//! safe state).

use pto_model::estimator::{Inputs, fault};

/// Bits of the latched faults (`Status::sensor_faults`).
pub mod bit {
    /// The HP transducer.
    pub const HP: u8 = 1 << 0;
    /// The LP transducer.
    pub const LP: u8 = 1 << 1;
    /// The motor speed pickup.
    pub const MOTOR: u8 = 1 << 2;
    /// The shaft encoder.
    pub const ENCODER: u8 = 1 << 3;
}

/// The latch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SensorFaults {
    latched: u8,
    /// The encoder count when its fault latched (it must move to clear).
    encoder_at_fault: i32,
    /// The encoder's count at its fault is not known (restored across a reset).
    encoder_unknown: bool,
}

impl SensorFaults {
    /// The latched sensors.
    pub fn latched(&self) -> u8 {
        self.latched
    }

    /// Takes a step's estimator flags (the encoder count it saw): latches what they name;
    /// returns the sensors newly latched.
    pub fn take(&mut self, faults: u16, encoder: Option<i32>) -> u8 {
        let mut new = 0;
        if faults & fault::HP_DISAGREES != 0 {
            new |= bit::HP;
        } else if faults & fault::MOTOR_DISAGREES != 0 && self.latched & bit::HP == 0 {
            new |= bit::MOTOR;
        }
        if faults & fault::LP_DISAGREES != 0 {
            new |= bit::LP;
        }
        if faults & fault::ENCODER_STUCK != 0 {
            new |= bit::ENCODER;
        }
        let fresh = new & !self.latched;
        // The count where the encoder stuck, taken once (a held encoder is masked: later
        // steps see no count).
        if fresh & bit::ENCODER != 0 {
            self.encoder_at_fault = encoder.unwrap_or(0);
        }
        self.latched |= new;
        fresh
    }

    /// Holds `bits` (sensors remembered across a reset); the encoder's count at its fault is
    /// unknown then, so it clears only once it has moved from wherever it is at the first
    /// clearing attempt.
    pub fn restore(&mut self, bits: u8) {
        self.latched |= bits & (bit::HP | bit::LP | bit::MOTOR | bit::ENCODER);
        self.encoder_unknown = self.latched & bit::ENCODER != 0;
    }

    /// The estimator's inputs without the latched sensors' readings.
    pub fn mask(&self, inp: &mut Inputs) {
        if self.latched & bit::HP != 0 {
            inp.hp = None;
        }
        if self.latched & bit::LP != 0 {
            inp.lp = None;
        }
        if self.latched & bit::MOTOR != 0 {
            inp.motor = None;
        }
        if self.latched & bit::ENCODER != 0 {
            inp.encoder = None;
        }
    }

    /// Clears the latched sensors in `agree` (the ones that agree with the model now); the
    /// encoder only once its count has moved since its fault. Returns the sensors still held.
    pub fn clear(&mut self, agree: u8, encoder: Option<i32>) -> u8 {
        if self.encoder_unknown {
            self.encoder_at_fault = encoder.unwrap_or(0);
            self.encoder_unknown = false;
        }
        let mut ok = agree;
        if encoder.is_none_or(|e| e.wrapping_sub(self.encoder_at_fault).unsigned_abs() < 50) {
            ok &= !bit::ENCODER;
        }
        self.latched &= !ok;
        self.latched
    }
}

/// The latched sensors by name, for logs and the host (`HP, motor`).
pub fn names(bits: u8) -> impl Iterator<Item = &'static str> {
    [
        (bit::HP, "HP"),
        (bit::LP, "LP"),
        (bit::MOTOR, "motor"),
        (bit::ENCODER, "encoder"),
    ]
    .into_iter()
    .filter(move |(b, _)| bits & b != 0)
    .map(|(_, n)| n)
}

/// Why each sensor is held, for people: the check that names it (one per sensor).
pub fn why(bit: u8) -> &'static str {
    match bit {
        bit::HP => "its reading disagrees with the model's P2 (the pumps' and the valve's flows)",
        bit::LP => "its reading disagrees with the model's LP",
        bit::MOTOR => "its speed disagrees with the model's from P2 and the aperture",
        bit::ENCODER => "it stood still while the pumps acted on P2",
        _ => "",
    }
}

/// The latched sensors by name with why, for the host's status, monitor and clearing
/// (`HP: its reading disagrees with …`).
pub fn described(bits: u8) -> impl Iterator<Item = (&'static str, &'static str)> {
    [bit::HP, bit::LP, bit::MOTOR, bit::ENCODER]
        .into_iter()
        .filter(move |b| bits & b != 0)
        .zip(names(bits))
        .map(|(b, n)| (n, why(b)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_hp_check_names_hp_and_the_motor_check_names_the_motor_only_behind_a_trusted_hp() {
        let mut f = SensorFaults::default();
        assert_eq!(
            f.take(fault::MOTOR_DISAGREES | fault::HP_DISAGREES, Some(0)),
            bit::HP
        );
        assert_eq!(
            f.take(fault::MOTOR_DISAGREES, Some(0)),
            0,
            "HP already held"
        );
        let mut inp = Inputs {
            hp: Some(pto_model::fx::Pressure::from_num(80.0)),
            motor: Some(pto_model::fx::Rpm::from_num(200.0)),
            encoder: Some(5),
            ..Default::default()
        };
        f.mask(&mut inp);
        assert!(inp.hp.is_none() && inp.motor.is_some());
        let mut g = SensorFaults::default();
        assert_eq!(g.take(fault::MOTOR_DISAGREES, Some(0)), bit::MOTOR);
        assert_eq!(g.take(fault::ENCODER_STUCK, Some(100)), bit::ENCODER);
        // The encoder clears only once it moved; a sensor that does not agree stays.
        assert_eq!(g.clear(bit::ENCODER | bit::MOTOR, Some(120)), bit::ENCODER);
        assert_eq!(g.clear(bit::ENCODER, Some(400)), 0);
        assert_eq!(
            names(bit::HP | bit::MOTOR).collect::<Vec<_>>(),
            ["HP", "motor"]
        );
        let d: Vec<_> = described(bit::LP | bit::ENCODER).collect();
        assert_eq!(d.len(), 2);
        assert_eq!(d[0].0, "LP");
        assert!(
            d[0].1.contains("model's LP") && d[1].0 == "encoder",
            "{d:?}"
        );
    }

    /// The encoder's count at its fault is taken once: a held encoder is masked, so later steps
    /// (the check still firing) see no count and must not move it to 0, where any count 50 away
    /// from zero would clear a stuck encoder. Restored across a reset, it must move from where
    /// it is at the first clearing.
    #[test]
    fn a_stuck_encoder_clears_only_once_it_moved_from_where_it_stuck() {
        let mut f = SensorFaults::default();
        assert_eq!(f.take(fault::ENCODER_STUCK, Some(700)), bit::ENCODER);
        assert_eq!(f.take(fault::ENCODER_STUCK, None), 0);
        assert_eq!(
            f.clear(bit::ENCODER, Some(700)),
            bit::ENCODER,
            "still stuck"
        );
        assert_eq!(f.clear(bit::ENCODER, Some(760)), 0);
        let mut r = SensorFaults::default();
        r.restore(bit::ENCODER | 0x80);
        assert_eq!(r.latched(), bit::ENCODER);
        assert_eq!(r.clear(bit::ENCODER, Some(5000)), bit::ENCODER);
        assert_eq!(r.clear(bit::ENCODER, Some(5010)), bit::ENCODER);
        assert_eq!(r.clear(bit::ENCODER, Some(5080)), 0);
    }
}
