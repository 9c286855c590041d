//! The control task's log: the session's events and the configuration's set-up errors as defmt
//! lines (the host tools read some of them: `pto fw-cost` the costs, the QEMU tests the boot's
//! configuration), and the memory the trip and the held sensors keep across a reset.

use crate::board;
use pto_firmware::control::SetupError;
use pto_firmware::session::{Event, ResetMemory};

/// Logs why a configuration was rejected.
pub fn log_setup_error(e: &SetupError) {
    match e {
        SetupError::Model(m) => defmt::error!(
            "configuration rejected: {=str} = {} outside [{}, {}]",
            m.field,
            m.value,
            m.min,
            m.max
        ),
        SetupError::Loop(l) => {
            defmt::error!("transducer loop rejected: {=str} = {}", l.field, l.value)
        }
        SetupError::Control { field, value } => {
            defmt::error!("control config rejected: {=str} = {}", field, value)
        }
    }
}

/// The trip's and the held sensors' memory across a reset (RAM the reset leaves alone).
pub struct TripMemory;

impl ResetMemory for TripMemory {
    fn remember_trip(&mut self, tripped: bool) {
        crate::trip_memory::remember(tripped);
    }
    fn remember_sensor_faults(&mut self, bits: u8) {
        crate::trip_memory::remember_sensor_faults(bits);
    }
}

/// The session's events in the log.
pub fn log_event(e: Event) {
    match e {
        Event::NewFaults {
            tick,
            faults,
            p2,
            p2_sigma,
        } => defmt::warn!(
            "tick {}: new faults {=u16:#06x}, P2 {} bar ± {}",
            tick,
            faults,
            p2.to_f32(),
            p2_sigma.to_f32()
        ),
        Event::Tripped(tick) => {
            defmt::error!("tick {}: overpressure trip, valve and dump open", tick)
        }
        Event::TripReleased(tick) => defmt::info!("tick {}: trip released", tick),
        Event::SensorFaultsHeld { tick, bits } => defmt::error!(
            "tick {}: sensor fault held (bits {=u8:#06b}: 1 HP, 2 LP, 4 motor, 8 encoder): its \
             readings withheld, valve at the sensor-fault aperture",
            tick,
            bits
        ),
        Event::SelfTestTimedOut { tick, why } => {
            defmt::warn!("tick {}: self-test ended: {}", tick, why)
        }
        Event::SelfTestEndedBy(why) => defmt::warn!("self-test ended by {=str}", why),
        Event::ReplayRefused => defmt::warn!("replay refused: this board steps its own sensors"),
        Event::Mode(m) => defmt::info!("mode {}", m),
        Event::Duty { on_duty, config } => {
            defmt::info!("on duty {=u8:#06b}, config {}", on_duty, config + 1)
        }
        Event::Telemetry(every) => defmt::info!("telemetry every {=u16} steps", every),
        Event::Reset { p2, lp } => {
            defmt::info!("reset: P2 {} bar, LP {} bar", p2.to_f32(), lp.to_f32())
        }
        Event::ResetRefused(hold) => {
            defmt::warn!("reset refused: the overpressure trip holds ({})", hold)
        }
        Event::Storing => {
            defmt::info!("storing the configuration (the controller stalls during an erase)")
        }
        Event::StoreFailed(e) => defmt::error!("configuration store: {}", e),
        Event::Applied {
            fingerprint,
            stored,
            cost,
        } => {
            defmt::info!(
                "model configuration: uploaded (fingerprint {=u32:08x}), {=str}; estimator \
                 restarted",
                fingerprint,
                if stored { "stored" } else { "not stored" }
            );
            defmt::info!(
                "configuration applied in {=u32} {=str}",
                cost,
                board::CLOCK_UNIT
            );
        }
        Event::ConfigRefused(e) => defmt::warn!("configuration refused: {}", e),
        Event::Cleared => {
            defmt::info!("configuration store cleared: the next boot runs the built-in one")
        }
        Event::ClearRefused(e) => defmt::warn!("configuration store not cleared: {}", e),
        Event::StallRefused => defmt::warn!("watchdog test refused: the overpressure trip holds"),
        Event::Stall => {
            defmt::warn!("watchdog test: outputs de-energised, the control task stops")
        }
        Event::SensorFaultsCleared { cleared, held } => defmt::warn!(
            "sensor faults: {=u8:#06b} cleared by the host, {=u8:#06b} still held",
            cleared,
            held
        ),
        Event::SelfTestBegun => {
            defmt::warn!("self-test: outputs de-energised (valve closed, dump open)")
        }
        Event::SelfTestDrive(d) => defmt::info!("self-test: drive {}", d),
        Event::SelfTestEnded => defmt::info!("self-test ended"),
        Event::SelfTestRefused(e) => defmt::warn!("self-test request refused: {}", e),
    }
}
