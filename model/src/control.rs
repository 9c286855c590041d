//! The controller's settings beyond the model and the scheduler: its two 4–20 mA transducer
//! loops, the overpressure trip's release, the actuator's slew limit and P2's uncertainty at
//! boot. Data only, in physical units: the firmware checks them when it builds its controller
//! (`pto_firmware::control::Controller::new`), and the bench file's `[controller]` section
//! carries them (`pto_bench::model::controller_config`).

/// A 4–20 mA pressure transducer loop.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct LoopSpec {
    /// Pressure at 20 mA, bar (0 bar at 4 mA).
    pub full_scale_bar: f32,
    /// Shunt resistor, Ω.
    pub shunt_ohm: f32,
    /// ADC reference, V.
    pub vref_v: f32,
}

impl LoopSpec {
    /// The reference bench's HP transducer: 0–250 bar, 150 Ω shunt, 3.3 V reference.
    pub const HP: LoopSpec = LoopSpec {
        full_scale_bar: 250.0,
        shunt_ohm: 150.0,
        vref_v: 3.3,
    };
    /// The reference bench's LP transducer: 0–40 bar.
    pub const LP: LoopSpec = LoopSpec {
        full_scale_bar: 40.0,
        ..LoopSpec::HP
    };
}

/// Firmware settings beyond the model and the scheduler.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct ControlConfig {
    /// HP transducer loop.
    pub hp: LoopSpec,
    /// LP transducer loop.
    pub lp: LoopSpec,
    /// The trip latch releases only when a valid HP reading and the P2 estimate are both this
    /// far below the trip pressure, bar …
    pub trip_release_margin_bar: f32,
    /// … for this long without a break, ms.
    pub trip_release_hold_ms: f32,
    /// Actuator slew limit (a second line behind the scheduler's rate limit), %/s. Safety
    /// overrides are applied at once.
    pub valve_slew_pct_per_s: f32,
    /// Start P2 standard deviation at boot (P2 unknown), bar.
    pub boot_sigma_bar: f32,
}

impl Default for ControlConfig {
    fn default() -> Self {
        ControlConfig {
            hp: LoopSpec::HP,
            lp: LoopSpec::LP,
            trip_release_margin_bar: 15.0,
            trip_release_hold_ms: 500.0,
            valve_slew_pct_per_s: 100.0,
            boot_sigma_bar: 50.0,
        }
    }
}
