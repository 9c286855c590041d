//! How the control valve is driven in a run: a fixed aperture, a threshold, a table, or a
//! controller called every period ([`ValveController`]), and when the next valve event falls.

use crate::sim::plant::Eval;

/// A valve controller plugged into the plant: called every `period` seconds with the time and the
/// plant's instantaneous values; returns the commanded aperture (%, 0..100).
pub trait ValveController {
    /// Control period, s.
    fn period(&self) -> f64;
    /// New aperture command from the plant's values at time `t`.
    fn update(&mut self, t: f64, plant: &Eval) -> f64;
    /// Whether the run should end here, before its duration (asked after each update; the
    /// result then ends at the update's time).
    fn finished(&self) -> bool {
        false
    }
}

/// Two instants closer than this are one event, s. diffsol's BDF reports a stop time as reached
/// within 100 ε (|t| + |h|) of it (`handle_tstop`): 4·10⁻¹² s at 200 s, more than a fixed 10⁻¹²
/// s or 10⁻⁹ of a 2⁻¹⁰ s period. An event taken as still ahead from there is set as the next
/// stop time and refused ("Stop time is at the current state time": closed loops of 150–200 s
/// failed so). 1 ns is far above that rounding and far below any period or table step.
pub(crate) const EVENT_TOL_S: f64 = 1e-9;

/// How the control valve is driven.
pub enum ValveSchedule {
    /// Fixed aperture, %.
    Constant(f64),
    /// Closed until P2 reaches `threshold_pa`, then `aperture_pct` for the rest of the run.
    Threshold {
        /// P2 threshold, Pa.
        threshold_pa: f64,
        /// Aperture after the threshold, %.
        aperture_pct: f64,
    },
    /// Step changes (time s, aperture %), sorted by time; before the first, closed.
    Table(Vec<(f64, f64)>),
    /// External controller.
    Controller(Box<dyn ValveController>),
}

impl std::fmt::Debug for ValveSchedule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ValveSchedule::Constant(a) => write!(f, "Constant({a})"),
            ValveSchedule::Threshold {
                threshold_pa,
                aperture_pct,
            } => {
                write!(f, "Threshold({threshold_pa} Pa -> {aperture_pct} %)")
            }
            ValveSchedule::Table(t) => write!(f, "Table({t:?})"),
            ValveSchedule::Controller(c) => write!(f, "Controller(period {} s)", c.period()),
        }
    }
}

impl ValveSchedule {
    /// Aperture commanded at the start.
    pub(crate) fn initial(&mut self, plant0: &Eval) -> f64 {
        match self {
            ValveSchedule::Constant(a) => *a,
            ValveSchedule::Threshold {
                threshold_pa,
                aperture_pct,
            } => {
                if plant0.p2_pa >= *threshold_pa {
                    *aperture_pct
                } else {
                    0.0
                }
            }
            ValveSchedule::Table(t) => table_at(t, 0.0),
            ValveSchedule::Controller(c) => c.update(0.0, plant0),
        }
    }

    /// Next time after `t` at which the command may change (besides threshold roots).
    pub(crate) fn next_event(&self, t: f64) -> f64 {
        match self {
            ValveSchedule::Table(tab) => tab
                .iter()
                .map(|e| e.0)
                .find(|&te| te > t + EVENT_TOL_S)
                .unwrap_or(f64::INFINITY),
            ValveSchedule::Controller(c) => {
                let p = c.period();
                (((t + EVENT_TOL_S) / p).floor() + 1.0) * p
            }
            _ => f64::INFINITY,
        }
    }
}

pub(crate) fn table_at(t: &[(f64, f64)], time: f64) -> f64 {
    t.iter()
        .take_while(|e| e.0 <= time + EVENT_TOL_S)
        .last()
        .map_or(0.0, |e| e.1)
}
