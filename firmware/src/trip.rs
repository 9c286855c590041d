//! The overpressure trip latch: a small state machine, fail-safe by construction.
//!
//! ```text
//!            any trip sign                      release condition held for `hold_steps`
//!   Armed ───────────────────▶ Tripped{n} ─────────────────────────────────────────▶ Armed
//!                              │   ▲
//!                              └───┘ n += 1 while the release condition holds, else n = 0
//! ```
//!
//! - **Trip** on any credible sign of overpressure, each step: a *valid* HP reading above the
//!   trip pressure — whether or not the estimator's innovation gate took it (a rejected reading
//!   above the trip is a fault, never a silent discard: the estimator flags it `INNOVATION` and
//!   `OVERPRESSURE`, and the latch trips on it) — or the P2 estimate above the trip pressure.
//! - **Release** only when a valid HP reading *and* the estimate are both below the release
//!   pressure for `hold_steps` consecutive steps. A missing or out-of-range reading (wire
//!   break, short) restarts the count: a lost transducer while tripped holds the trip, however
//!   low the estimate is, because the estimate alone is what a lost sensor can no longer
//!   check.
//! - **Host reset** ([`TripLatch::reset_allowed`]): refused while tripped unless the release
//!   condition holds at that moment, with the reason ([`TripHold`]); an allowed reset restarts
//!   the estimator but never releases the trip itself — the hold time still runs.
//!
//! So the latch never releases while any valid HP reading within the last hold time was above
//! the release pressure (a property test drives it with arbitrary sequences).

use pto_model::fx::{Fx, Pressure};
use pto_model::protocol::TripHold;

/// The latch's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TripState {
    /// Not tripped.
    Armed,
    /// Tripped; `held` consecutive steps have met the release condition so far.
    Tripped {
        /// Steps the release condition has held.
        held: u16,
    },
}

/// What set the trip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TripCause {
    /// A valid HP reading above the trip pressure.
    HpReading,
    /// The P2 estimate above the trip pressure.
    Estimate,
}

/// The overpressure trip latch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TripLatch {
    trip: Fx,
    release: Fx,
    hold_steps: u16,
    state: TripState,
    /// What set the last trip.
    pub cause: Option<TripCause>,
    /// Times the latch tripped.
    pub trips: u32,
}

impl TripLatch {
    /// A latch that trips above `trip` and releases after `hold_steps` steps (≥ 1) with a valid
    /// reading and the estimate both below `release` (< `trip`; the caller validates both).
    pub fn new(trip: Pressure, release: Pressure, hold_steps: u16) -> Self {
        TripLatch {
            trip: trip.0,
            release: release.0,
            hold_steps: hold_steps.max(1),
            state: TripState::Armed,
            cause: None,
            trips: 0,
        }
    }

    /// The state.
    pub fn state(&self) -> TripState {
        self.state
    }

    /// Tripped.
    pub fn tripped(&self) -> bool {
        matches!(self.state, TripState::Tripped { .. })
    }

    /// Release pressure.
    pub fn release(&self) -> Pressure {
        Pressure(self.release)
    }

    /// Steps the release condition must hold.
    pub fn hold_steps(&self) -> u16 {
        self.hold_steps
    }

    /// Why the release condition does not hold for a step with this valid HP reading (`None`:
    /// missing or out of range) and this estimate; `None` when it holds.
    pub fn hold_reason(&self, hp: Option<Pressure>, estimate: Pressure) -> Option<TripHold> {
        match hp {
            None => Some(TripHold::HpMissing),
            Some(p) if p.0 >= self.release => Some(TripHold::HpHigh(p)),
            Some(_) if estimate.0 >= self.release => Some(TripHold::EstimateHigh(estimate)),
            Some(_) => None,
        }
    }

    /// One control step; returns whether the latch is tripped after it.
    pub fn step(&mut self, hp: Option<Pressure>, estimate: Pressure) -> bool {
        let cause = if hp.is_some_and(|p| p.0 > self.trip) {
            Some(TripCause::HpReading)
        } else if estimate.0 > self.trip {
            Some(TripCause::Estimate)
        } else {
            None
        };
        let releasing = self.hold_reason(hp, estimate).is_none();
        self.state = match (self.state, cause) {
            (TripState::Armed, None) => TripState::Armed,
            (TripState::Armed, Some(c)) => {
                self.trips = self.trips.wrapping_add(1);
                self.cause = Some(c);
                TripState::Tripped { held: 0 }
            }
            (TripState::Tripped { .. }, Some(_)) => TripState::Tripped { held: 0 },
            (TripState::Tripped { held }, None) if releasing => {
                let held = held.saturating_add(1);
                if held >= self.hold_steps {
                    TripState::Armed
                } else {
                    TripState::Tripped { held }
                }
            }
            (TripState::Tripped { .. }, None) => TripState::Tripped { held: 0 },
        };
        self.tripped()
    }

    /// Whether a host reset may restart the estimator now, given the last step's valid HP
    /// reading and estimate: always when armed; when tripped only while the release condition
    /// holds (the reset does not release the trip: the hold time still runs).
    pub fn reset_allowed(&self, hp: Option<Pressure>, estimate: Pressure) -> Result<(), TripHold> {
        if !self.tripped() {
            return Ok(());
        }
        self.hold_reason(hp, estimate).map_or(Ok(()), Err)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bar(v: f32) -> Pressure {
        Pressure::from_num(v)
    }

    fn latch() -> TripLatch {
        TripLatch::new(bar(140.0), bar(125.0), 100)
    }

    #[test]
    fn trips_on_the_reading_or_the_estimate_and_releases_after_the_hold() {
        let mut l = latch();
        assert!(!l.step(Some(bar(100.0)), bar(100.0)));
        assert!(
            l.step(Some(bar(141.0)), bar(100.0)),
            "a valid reading above the trip"
        );
        assert_eq!(l.cause, Some(TripCause::HpReading));
        for i in 0..99 {
            assert!(
                l.step(Some(bar(100.0)), bar(100.0)),
                "released early at step {i}"
            );
        }
        assert!(
            !l.step(Some(bar(100.0)), bar(100.0)),
            "released after 100 steps"
        );
        assert!(
            l.step(Some(bar(100.0)), bar(141.0)),
            "the estimate above the trip"
        );
        assert_eq!((l.cause, l.trips), (Some(TripCause::Estimate), 2));
    }

    #[test]
    fn a_lost_transducer_holds_the_trip_however_low_the_estimate() {
        let mut l = latch();
        l.step(Some(bar(150.0)), bar(99.0));
        for _ in 0..10_000 {
            assert!(l.step(None, bar(50.0)));
        }
        assert_eq!(l.reset_allowed(None, bar(50.0)), Err(TripHold::HpMissing));
        // Readings return: the hold starts from their return.
        for _ in 0..99 {
            assert!(l.step(Some(bar(100.0)), bar(100.0)));
        }
        assert!(!l.step(Some(bar(100.0)), bar(100.0)));
    }

    #[test]
    fn the_hold_restarts_on_any_step_that_misses_the_release_condition() {
        let mut l = latch();
        l.step(Some(bar(150.0)), bar(150.0));
        for miss in [
            (Some(bar(126.0)), bar(100.0)),
            (Some(bar(100.0)), bar(125.0)),
            (None, bar(100.0)),
        ] {
            for _ in 0..99 {
                assert!(l.step(Some(bar(100.0)), bar(100.0)));
            }
            assert!(l.step(miss.0, miss.1), "{miss:?} restarts the hold");
            assert_eq!(l.state(), TripState::Tripped { held: 0 });
        }
    }

    #[test]
    fn a_reset_is_refused_with_its_reason_and_never_releases() {
        let mut l = latch();
        assert_eq!(l.reset_allowed(None, bar(200.0)), Ok(()), "armed: always");
        l.step(Some(bar(150.0)), bar(99.0));
        assert_eq!(
            l.reset_allowed(Some(bar(150.0)), bar(99.0)),
            Err(TripHold::HpHigh(bar(150.0)))
        );
        assert_eq!(
            l.reset_allowed(Some(bar(100.0)), bar(130.0)),
            Err(TripHold::EstimateHigh(bar(130.0)))
        );
        assert_eq!(l.reset_allowed(Some(bar(100.0)), bar(100.0)), Ok(()));
        assert!(l.tripped(), "allowing a reset does not release");
    }
}
