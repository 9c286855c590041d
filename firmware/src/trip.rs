//! The overpressure trip latch: a small state machine, fail-safe by construction.
//!
//! ```text
//!            any trip sign                      release condition held for `hold_steps`
//!   Armed ───────────────────▶ Tripped{n} ─────────────────────────────────────────▶ Armed
//!                              │   ▲
//!                              └───┘ n += 1 while the release condition holds, else n = 0
//! ```
//!
//! - **Trip** on any credible sign of overpressure, each step: an HP reading inside the loop's
//!   4–20 mA window above the trip pressure — whether or not the estimator's gate took it (a
//!   rejected reading above the trip is a fault, never a silent discard: the estimator flags it
//!   `INNOVATION` and `OVERPRESSURE`), and also past the transducer's range (a saturated high
//!   reading) — or the P2 estimate above the trip pressure.
//! - **Release** only when, for `hold_steps` consecutive steps, the HP reading is valid (in its
//!   window and range) and taken by the estimator's gate, it and the estimate are both below
//!   the release pressure, and no contradiction is pending. Anything else restarts the count:
//!   a missing or out-of-range reading (wire break, short) holds the trip however low the
//!   estimate is, and so does a reading the model disagrees with.
//! - **Contradiction**: if, while tripped, the estimator has to reset P2 to the reading (the
//!   two disagreed for its whole reset window — a transducer failing to a valid low current
//!   looks like this), the latch holds until the host acknowledges it.
//! - **Host reset** ([`TripLatch::reset_allowed`]): refused while tripped unless the release
//!   condition (less the contradiction) holds at that moment, with the reason ([`TripHold`]);
//!   an allowed reset acknowledges a contradiction and restarts the estimator but never
//!   releases the trip itself — the hold time still runs.
//! - **Across a controller reset** the firmware remembers a held trip (a word of RAM that the
//!   reset does not clear) and boots tripped ([`TripLatch::boot_tripped`]).
//!
//! So the latch never releases while any valid HP reading within the last hold time was above
//! the release pressure, missing, or rejected (a property test drives it with arbitrary
//! sequences).

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
    /// An HP reading above the trip pressure.
    HpReading,
    /// The P2 estimate above the trip pressure.
    Estimate,
    /// A trip held when the controller reset.
    Remembered,
}

/// What the latch sees of one step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TripSample {
    /// The HP reading, when inside the loop's 4–20 mA window (`None`: wire break or short).
    pub reading: Option<Pressure>,
    /// That reading lies inside the transducer's range.
    pub in_range: bool,
    /// The estimator's gate took it this step (no `INNOVATION` flag).
    pub accepted: bool,
    /// The estimator reset P2 to the reading this step (`INNOVATION_RESET`).
    pub innovation_reset: bool,
    /// The P2 estimate.
    pub estimate: Pressure,
}

/// The overpressure trip latch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TripLatch {
    trip: Fx,
    release: Fx,
    hold_steps: u16,
    state: TripState,
    contradicted: bool,
    /// What set the last trip.
    pub cause: Option<TripCause>,
    /// Times the latch tripped.
    pub trips: u32,
}

impl TripLatch {
    /// A latch that trips above `trip` and releases after `hold_steps` steps (≥ 1) that meet
    /// the release condition with `release` (< `trip`; the caller validates both).
    pub fn new(trip: Pressure, release: Pressure, hold_steps: u16) -> Self {
        TripLatch {
            trip: trip.0,
            release: release.0,
            hold_steps: hold_steps.max(1),
            state: TripState::Armed,
            contradicted: false,
            cause: None,
            trips: 0,
        }
    }

    /// Starts tripped: a trip held when the controller reset (it releases like any other).
    pub fn boot_tripped(&mut self) {
        self.state = TripState::Tripped { held: 0 };
        self.cause = Some(TripCause::Remembered);
    }

    /// The state.
    pub fn state(&self) -> TripState {
        self.state
    }

    /// Tripped.
    pub fn tripped(&self) -> bool {
        matches!(self.state, TripState::Tripped { .. })
    }

    /// A contradiction waits for the host's acknowledgement.
    pub fn contradicted(&self) -> bool {
        self.contradicted
    }

    /// Release pressure.
    pub fn release(&self) -> Pressure {
        Pressure(self.release)
    }

    /// Steps the release condition must hold.
    pub fn hold_steps(&self) -> u16 {
        self.hold_steps
    }

    /// Why the release condition (less a pending contradiction) does not hold for a step like
    /// `s`; `None` when it holds.
    fn reading_reason(&self, s: &TripSample) -> Option<TripHold> {
        match s.reading {
            Some(p) if !s.in_range => {
                // A saturated high reading is above the release pressure; a low one is missing.
                if p.0 >= self.release {
                    Some(TripHold::HpHigh(p))
                } else {
                    Some(TripHold::HpMissing)
                }
            }
            None => Some(TripHold::HpMissing),
            Some(p) if p.0 >= self.release => Some(TripHold::HpHigh(p)),
            Some(p) if !s.accepted => Some(TripHold::HpRejected(p)),
            Some(_) if s.estimate.0 >= self.release => Some(TripHold::EstimateHigh(s.estimate)),
            Some(_) => None,
        }
    }

    /// Why a tripped latch cannot release after a step like `s`; `None` when it can.
    pub fn hold_reason(&self, s: &TripSample) -> Option<TripHold> {
        self.reading_reason(s)
            .or(self.contradicted.then_some(TripHold::Contradicted))
    }

    /// One control step; returns whether the latch is tripped after it.
    pub fn step(&mut self, s: &TripSample) -> bool {
        let cause = if s.reading.is_some_and(|p| p.0 > self.trip) {
            Some(TripCause::HpReading)
        } else if s.estimate.0 > self.trip {
            Some(TripCause::Estimate)
        } else {
            None
        };
        if self.tripped() && s.innovation_reset {
            self.contradicted = true;
        }
        let releasing = self.hold_reason(s).is_none();
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

    /// Whether a host reset may restart the estimator now, given the last step `last` (`None`:
    /// no step since boot): always when armed; when tripped only while the release condition,
    /// less a pending contradiction, holds. An allowed reset acknowledges the contradiction
    /// (the hold time then runs again) and does not release the trip.
    pub fn reset_allowed(&mut self, last: Option<&TripSample>) -> Result<(), TripHold> {
        if !self.tripped() {
            return Ok(());
        }
        match last.map_or(Some(TripHold::HpMissing), |s| self.reading_reason(s)) {
            Some(why) => Err(why),
            None => {
                self.contradicted = false;
                self.state = TripState::Tripped { held: 0 };
                Ok(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bar(v: f32) -> Pressure {
        Pressure::from_num(v)
    }

    /// A step with a valid reading the gate took.
    fn good(hp: f32, est: f32) -> TripSample {
        TripSample {
            reading: Some(bar(hp)),
            in_range: true,
            accepted: true,
            innovation_reset: false,
            estimate: bar(est),
        }
    }

    fn broken(est: f32) -> TripSample {
        TripSample {
            reading: None,
            ..good(0.0, est)
        }
    }

    fn latch() -> TripLatch {
        TripLatch::new(bar(140.0), bar(125.0), 100)
    }

    /// Steps `s` through the 100-step hold: tripped for 99 steps, released by the 100th.
    fn hold_releases(l: &mut TripLatch, s: &TripSample) {
        for i in 0..99 {
            assert!(l.step(s), "released early at step {i}");
        }
        assert!(!l.step(s), "released after 100 steps");
    }

    #[test]
    fn trips_on_the_reading_or_the_estimate_and_releases_after_the_hold() {
        let mut l = latch();
        assert!(!l.step(&good(100.0, 100.0)));
        assert!(
            l.step(&good(141.0, 100.0)),
            "a valid reading above the trip"
        );
        assert_eq!(l.cause, Some(TripCause::HpReading));
        hold_releases(&mut l, &good(100.0, 100.0));
        assert!(l.step(&good(100.0, 141.0)), "the estimate above the trip");
        assert_eq!((l.cause, l.trips), (Some(TripCause::Estimate), 2));
    }

    #[test]
    fn a_saturated_high_reading_trips_and_holds() {
        let mut l = latch();
        let saturated = TripSample {
            in_range: false,
            ..good(262.0, 100.0)
        };
        assert!(
            l.step(&saturated),
            "past the transducer's range but inside the loop window"
        );
        assert_eq!(
            l.hold_reason(&saturated),
            Some(TripHold::HpHigh(bar(262.0)))
        );
    }

    #[test]
    fn a_lost_transducer_holds_the_trip_however_low_the_estimate() {
        let mut l = latch();
        l.step(&good(150.0, 99.0));
        for _ in 0..10_000 {
            assert!(l.step(&broken(50.0)));
        }
        assert_eq!(
            l.reset_allowed(Some(&broken(50.0))),
            Err(TripHold::HpMissing)
        );
        assert_eq!(l.reset_allowed(None), Err(TripHold::HpMissing));
        // Readings return: the hold starts from their return.
        hold_releases(&mut l, &good(100.0, 100.0));
    }

    #[test]
    fn the_hold_restarts_on_any_step_that_misses_the_release_condition() {
        let mut l = latch();
        l.step(&good(150.0, 150.0));
        let rejected = TripSample {
            accepted: false,
            ..good(100.0, 100.0)
        };
        for miss in [
            good(126.0, 100.0),
            good(100.0, 125.0),
            broken(100.0),
            rejected,
        ] {
            for _ in 0..99 {
                assert!(l.step(&good(100.0, 100.0)));
            }
            assert!(l.step(&miss), "{miss:?} restarts the hold");
            assert_eq!(l.state(), TripState::Tripped { held: 0 });
        }
    }

    /// A transducer failing to a valid low current while tripped: the gate rejects it, then the
    /// estimator snaps P2 to it; reading and estimate then agree, low. The latch holds until
    /// the host acknowledges, and even then runs its hold time.
    #[test]
    fn a_contradiction_while_tripped_holds_until_acknowledged() {
        let mut l = latch();
        l.step(&good(150.0, 150.0));
        let snapped = TripSample {
            innovation_reset: true,
            ..good(0.0, 0.0)
        };
        assert!(l.step(&snapped));
        for _ in 0..10_000 {
            assert!(
                l.step(&good(0.0, 0.0)),
                "released on a contradicted reading"
            );
        }
        assert_eq!(l.hold_reason(&good(0.0, 0.0)), Some(TripHold::Contradicted));
        assert_eq!(l.reset_allowed(Some(&good(0.0, 0.0))), Ok(()));
        assert!(l.tripped() && !l.contradicted());
        hold_releases(&mut l, &good(0.0, 0.0));
    }

    #[test]
    fn a_reset_is_refused_with_its_reason_and_never_releases() {
        let mut l = latch();
        assert_eq!(l.reset_allowed(None), Ok(()), "armed: always");
        l.step(&good(150.0, 99.0));
        assert_eq!(
            l.reset_allowed(Some(&good(150.0, 99.0))),
            Err(TripHold::HpHigh(bar(150.0)))
        );
        assert_eq!(
            l.reset_allowed(Some(&good(100.0, 130.0))),
            Err(TripHold::EstimateHigh(bar(130.0)))
        );
        assert_eq!(l.reset_allowed(Some(&good(100.0, 100.0))), Ok(()));
        assert!(l.tripped(), "allowing a reset does not release");
    }

    #[test]
    fn a_remembered_trip_boots_tripped_and_releases_like_any_other() {
        let mut l = latch();
        l.boot_tripped();
        assert!(l.tripped());
        assert_eq!(l.cause, Some(TripCause::Remembered));
        assert_eq!(l.reset_allowed(None), Err(TripHold::HpMissing));
        hold_releases(&mut l, &good(100.0, 100.0));
    }
}
