//! How the bench's sensors see the plant, as the firmware reads them.

use crate::sim::trace::Truth;
use pto_firmware::frontend::{LoopSpec, Transducer};
use pto_model::estimator::Inputs;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// How the bench's sensors see the plant: the one description used by `pto validate`,
/// `pto pil`, `pto synth-logs` and the golden vectors. The pressure transducers are the
/// firmware's own 4–20 mA loops ([`LoopSpec`]), read through the firmware's [`Transducer`].
#[derive(Debug, Clone, Copy)]
pub struct SensorSpec {
    /// Encoder counts per shaft revolution.
    pub counts_per_rev: u32,
    /// The HP transducer's loop (range, shunt, ADC reference).
    pub hp_loop: LoopSpec,
    /// The LP transducer's loop.
    pub lp_loop: LoopSpec,
    /// HP noise σ, bar.
    pub hp_noise_bar: f64,
    /// LP noise σ, bar.
    pub lp_noise_bar: f64,
    /// Motor speed noise σ, rpm.
    pub motor_noise_rpm: f64,
}

impl Default for SensorSpec {
    fn default() -> Self {
        SensorSpec {
            counts_per_rev: 16_384,
            hp_loop: LoopSpec::HP,
            lp_loop: LoopSpec::LP,
            hp_noise_bar: 0.5,
            lp_noise_bar: 0.2,
            motor_noise_rpm: 2.0,
        }
    }
}

/// One sample of the bench's sensors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Readings {
    /// Shaft encoder count.
    pub encoder_count: i32,
    /// HP transducer, bar.
    pub hp_bar: f64,
    /// LP transducer, bar.
    pub lp_bar: f64,
    /// Motor speed sensor, rpm.
    pub motor_rpm: f64,
}

impl Readings {
    /// The model's inputs of this sample, every sensor present (set `hp: None` for a run
    /// without the HP transducer), with the commanded aperture (%), the cylinders on duty and
    /// the geometry.
    pub fn to_inputs(&self, aperture_pct: f64, on_duty: u8, config: u8) -> Inputs {
        super::inputs(
            Some(self.encoder_count),
            Some(self.hp_bar),
            Some(self.lp_bar),
            Some(self.motor_rpm),
            aperture_pct,
            on_duty,
            config,
        )
    }
}

/// Makes sensor readings: quantised encoder, pressures with Gaussian noise read through the
/// firmware's 4–20 mA front end (its 12-bit ADC counts and its conversion back to bar).
pub struct SensorSynth {
    spec: SensorSpec,
    hp: Transducer,
    lp: Transducer,
    rng: ChaCha8Rng,
    hp_noise: Normal<f64>,
    lp_noise: Normal<f64>,
    motor_noise: Normal<f64>,
}

impl SensorSynth {
    /// A seeded synthesiser.
    ///
    /// # Panics
    /// If a loop of `spec` is not a valid transducer (the firmware's own loops are).
    pub fn new(spec: SensorSpec, seed: u64) -> Self {
        let loop_of = |l: LoopSpec| {
            Transducer::new(l).unwrap_or_else(|e| panic!("sensor spec: {l:?}: {e:?}"))
        };
        SensorSynth {
            spec,
            hp: loop_of(spec.hp_loop),
            lp: loop_of(spec.lp_loop),
            rng: ChaCha8Rng::seed_from_u64(seed),
            hp_noise: Normal::new(0.0, spec.hp_noise_bar.max(1e-12))
                .unwrap_or_else(|_| unreachable!()),
            lp_noise: Normal::new(0.0, spec.lp_noise_bar.max(1e-12))
                .unwrap_or_else(|_| unreachable!()),
            motor_noise: Normal::new(0.0, spec.motor_noise_rpm.max(1e-12))
                .unwrap_or_else(|_| unreachable!()),
        }
    }

    /// A pressure as the firmware reads it: the transducer's output held to its 4–20 mA range,
    /// the ADC's count, the firmware's conversion back to bar.
    fn through(t: &Transducer, spec: &LoopSpec, bar: f64) -> f64 {
        let held = bar.clamp(0.0, f64::from(spec.full_scale_bar)) as f32;
        // Inside the 3.6–21 mA window by construction: `None` cannot come back.
        t.pressure(t.counts_at_bar(held))
            .map_or(f64::NAN, |p| f64::from(p.to_f32()))
    }

    /// Encoder count of a shaft angle.
    pub fn encoder(&self, theta: f64) -> i32 {
        (theta / (2.0 * std::f64::consts::PI) * f64::from(self.spec.counts_per_rev)).round() as i32
    }

    /// Readings of the plant state `truth` at shaft angle `theta`.
    pub fn read(&mut self, theta: f64, truth: &Truth) -> Readings {
        let r = self.read_analog(theta, truth);
        Readings {
            hp_bar: Self::through(&self.hp, &self.spec.hp_loop, r.hp_bar),
            lp_bar: Self::through(&self.lp, &self.spec.lp_loop, r.lp_bar),
            ..r
        }
    }

    /// Like [`SensorSynth::read`] with the pressures noisy but not yet quantised (for a front
    /// end that quantises them itself, e.g. the firmware's 4–20 mA loops).
    pub fn read_analog(&mut self, theta: f64, truth: &Truth) -> Readings {
        let n_hp = self.hp_noise.sample(&mut self.rng);
        let n_lp = self.lp_noise.sample(&mut self.rng);
        let motor = (truth.motor_rpm + self.motor_noise.sample(&mut self.rng)).max(0.0);
        Readings {
            encoder_count: self.encoder(theta),
            hp_bar: truth.p2_bar + n_hp,
            lp_bar: truth.lp_bar + n_lp,
            motor_rpm: motor,
        }
    }
}
