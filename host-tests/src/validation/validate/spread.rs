//! Where a run's error sits and how a family of runs spreads: the largest mean over a sliding
//! window (`pto validate`'s worst 4 s of torque error) and the worst and median of a family's
//! figures (the sea family).

use super::Row;
use serde::Serialize;

/// The scenario group whose spread the report gives ([`crate::sim::scenario::sea_family`]).
pub const FAMILY_GROUP: &str = "sea-family";

/// Length of the window of [`Row::torque_worst_4s_of_peak`], s.
pub const WORST_WINDOW_S: f64 = 4.0;

/// The largest mean of a quantity over a sliding window of `len` samples.
pub(super) struct WorstWindow {
    len: usize,
    ring: std::collections::VecDeque<(f64, f64)>,
    sum: f64,
    /// (largest mean, start of its window).
    worst: Option<(f64, f64)>,
}

impl WorstWindow {
    pub(super) fn new(len: usize) -> Self {
        WorstWindow {
            len: len.max(1),
            ring: std::collections::VecDeque::with_capacity(len.max(1) + 1),
            sum: 0.0,
            worst: None,
        }
    }

    pub(super) fn add(&mut self, t: f64, x: f64) {
        self.ring.push_back((t, x));
        self.sum += x;
        if self.ring.len() > self.len {
            let (_, old) = self.ring.pop_front().unwrap_or_default();
            self.sum -= old;
        }
        if self.ring.len() == self.len {
            // (The running sum's rounding is ≈ 1e-11 of it over a 300 s run; a NaN sample
            // makes the worst window NaN, which shows.)
            let mean = self.sum / self.len as f64;
            let start = self.ring.front().map_or(t, |f| f.0);
            if self.worst.is_none_or(|w| mean > w.0 || mean.is_nan()) {
                self.worst = Some((mean, start));
            }
        }
    }

    /// (largest window mean, its start), None when fewer samples than a window came.
    pub(super) fn worst(&self) -> Option<(f64, f64)> {
        self.worst
    }
}

/// Worst and median of a family of rows, per figure.
#[derive(Debug, Clone, Serialize)]
pub struct Spread {
    /// Rows in the family.
    pub runs: usize,
    /// Rows meeting every target.
    pub runs_met: usize,
    /// Torque RMS error / peak: (worst, median); every figure is such a pair (`[worst,
    /// median]` in JSON), over the rows that have the figure.
    pub torque_rms_of_peak: (f64, f64),
    /// Worst 4 s torque error / peak: (worst, median).
    pub torque_worst_4s_of_peak: (f64, f64),
    /// P2 RMS error with the transducer, bar: (worst, median).
    pub p2_rms_bar: (f64, f64),
    /// Model-only P2 max error (first 60 s), bar: (worst, median).
    pub p2_model_only_max_bar: (f64, f64),
    /// 2σ coverage with the transducer: (worst, median).
    pub cover_2s: (f64, f64),
    /// 3σ coverage with the transducer: (worst, median).
    pub cover_3s: (f64, f64),
    /// Motor speed RMS error / RMS speed: (worst, median).
    pub motor_rms_rel: (f64, f64),
}

impl Spread {
    /// The spread of `rows` (None when empty).
    pub fn of(rows: &[&Row]) -> Option<Spread> {
        if rows.is_empty() {
            return None;
        }
        // (worst, median) of the figures present; `high_is_bad` says which end is the worst.
        let wm = |xs: Vec<f64>, high_is_bad: bool| {
            let mut xs = xs;
            xs.sort_by(f64::total_cmp);
            if xs.is_empty() {
                return (f64::NAN, f64::NAN);
            }
            let worst = if high_is_bad { xs[xs.len() - 1] } else { xs[0] };
            let n = xs.len();
            let median = if n % 2 == 1 {
                xs[n / 2]
            } else {
                0.5 * (xs[n / 2 - 1] + xs[n / 2])
            };
            (worst, median)
        };
        let col = |f: &dyn Fn(&Row) -> Option<f64>| rows.iter().filter_map(|r| f(r)).collect();
        Some(Spread {
            runs: rows.len(),
            runs_met: rows.iter().filter(|r| r.pass).count(),
            torque_rms_of_peak: wm(col(&|r| r.torque_rms_of_peak), true),
            torque_worst_4s_of_peak: wm(col(&|r| r.torque_worst_4s_of_peak), true),
            p2_rms_bar: wm(col(&|r| Some(r.p2_rms_bar)), true),
            p2_model_only_max_bar: wm(col(&|r| Some(r.p2_model_only_max_bar)), true),
            cover_2s: wm(col(&|r| Some(r.cover_2s)), false),
            cover_3s: wm(col(&|r| Some(r.cover_3s)), false),
            motor_rms_rel: wm(col(&|r| r.motor_rms_rel), true),
        })
    }
}
