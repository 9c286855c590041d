//! The bench's sampling: one sample per model step, paced by the microsecond time base, with
//! the motor's speed from timestamped counts. Tested here; the board only reads the hardware.
//!
//! - **Stalls.** Every flash read stalls while the flash erases (RM0090 §3.6), so all code does:
//!   up to 2 s for one store sector. embassy's `Ticker` then fires every missed period back to
//!   back. The [`Pacer`] instead re-synchronises to the period after the wake-up and says how
//!   many periods were missed; the sample's tick jumps by them (a tick is time), and the motor
//!   speed's window starts again.
//! - **Motor count.** The pickup counts in a 32-bit timer (TIM2): 2^31 counts are 524 288
//!   revolutions, 2.9 h at 3 000 rpm, so no stall can make the count ambiguous (a 16-bit counter
//!   wraps in 4 s at 240 rpm).
//! - **Speed** is the count's change over the time it took, from the sample timestamps, over a
//!   window of [`MOTOR_WINDOW`] samples: a late sample does not read as a faster motor.

use pto_model::fx::Rpm;

/// Samples the motor's speed is averaged over (≈ 31 ms at 2^-10 s).
pub const MOTOR_WINDOW: usize = 32;

/// Paces the sampling at a fixed period and re-synchronises after a stall.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pacer {
    period_us: u64,
    deadline_us: u64,
}

impl Pacer {
    /// The first deadline one period after `now_us`.
    pub const fn new(now_us: u64, period_us: u32) -> Self {
        Pacer {
            period_us: period_us as u64,
            deadline_us: now_us + period_us as u64,
        }
    }

    /// When to wake next, µs.
    pub const fn deadline_us(&self) -> u64 {
        self.deadline_us
    }

    /// Woken at `now_us` for the current deadline: moves the deadline to the next period still
    /// ahead and returns how many whole periods were missed (0 on time). After a stall the
    /// next deadline is the first period boundary after `now_us`, so no missed sample is taken
    /// late.
    pub fn woke(&mut self, now_us: u64) -> u32 {
        let late = now_us.saturating_sub(self.deadline_us);
        let missed = late / self.period_us;
        self.deadline_us += (missed + 1) * self.period_us;
        u32::try_from(missed).unwrap_or(u32::MAX)
    }
}

/// The motor's speed from its 32-bit pickup count.
#[derive(Debug, Clone)]
pub struct MotorSpeed {
    counts_per_rev: u32,
    /// (timestamp µs, count) of the last samples, oldest first once full.
    history: [(u64, u32); MOTOR_WINDOW],
    len: usize,
    next: usize,
}

impl MotorSpeed {
    /// A window with nothing in it, for a pickup of `counts_per_rev` counts per revolution.
    pub const fn new(counts_per_rev: u32) -> Self {
        MotorSpeed {
            counts_per_rev,
            history: [(0, 0); MOTOR_WINDOW],
            len: 0,
            next: 0,
        }
    }

    /// Forgets the window (after a stall): no speed until it is full again.
    pub fn restart(&mut self) {
        self.len = 0;
        self.next = 0;
    }

    /// Takes the count at `now_us`; the speed over the window (`None` until it is full), rpm.
    pub fn sample(&mut self, now_us: u64, count: u32) -> Option<Rpm> {
        let (t0, c0) = self.history[self.next];
        let full = self.len == MOTOR_WINDOW;
        self.history[self.next] = (now_us, count);
        self.next = (self.next + 1) % MOTOR_WINDOW;
        self.len = (self.len + 1).min(MOTOR_WINDOW);
        if !full {
            return None;
        }
        let dt_us = now_us.saturating_sub(t0);
        if dt_us == 0 {
            return None;
        }
        // The pickup turns one way; a count going back is its jitter at standstill.
        let d = count.wrapping_sub(c0) as i32;
        let rpm = d.unsigned_abs() as f32 * 60.0e6 / (self.counts_per_rev as f32 * dt_us as f32);
        Some(Rpm::from_num(rpm))
    }
}

/// A microsecond time base from the core's 32-bit cycle counter (DWT `CYCCNT`, 168 MHz: it wraps
/// every 25.6 s), extended to 64 bits by reading it at least that often. It keeps counting
/// through a flash erase's stall, when no interrupt runs — unlike embassy's time driver on a
/// 16-bit timer, which loses whatever passes beyond its 32.8 ms half-period then.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CycleTime {
    last: u32,
    cycles: u64,
    per_us: u32,
}

impl CycleTime {
    /// Starts at the counter's value `now` (time 0), counting `hz` cycles a second.
    pub const fn new(now: u32, hz: u32) -> Self {
        CycleTime {
            last: now,
            cycles: 0,
            per_us: hz / 1_000_000,
        }
    }

    /// The time at the counter's value `now`, µs (the counter read less than 2^32 cycles after
    /// the last read).
    pub fn micros(&mut self, now: u32) -> u64 {
        self.cycles += u64::from(now.wrapping_sub(self.last));
        self.last = now;
        self.cycles / u64::from(self.per_us.max(1))
    }
}

/// VDDA readings (mV) in a running mean (the first [`SUPPLY_MEAN`] averaged, then each new one
/// weighing 1/[`SUPPLY_MEAN`]); a reading outside
/// [`crate::frontend::SUPPLY_PLAUSIBLE_MV`] is passed on at once (a failed measurement must not
/// be averaged away) and restarts the mean.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SupplyFilter {
    sum: u32,
    n: u32,
}

/// The supply mean's length, readings.
pub const SUPPLY_MEAN: u32 = 4;

impl SupplyFilter {
    /// Takes a reading; returns the supply to report.
    pub fn take(&mut self, mv: u16) -> u16 {
        if !crate::frontend::SUPPLY_PLAUSIBLE_MV.contains(&mv) {
            *self = SupplyFilter::default();
            return mv;
        }
        if self.n == SUPPLY_MEAN {
            self.sum -= self.sum / SUPPLY_MEAN;
            self.n -= 1;
        }
        self.sum += u32::from(mv);
        self.n += 1;
        ((self.sum + self.n / 2) / self.n) as u16
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PERIOD: u32 = 977;

    #[test]
    fn the_pacer_keeps_the_period_and_resynchronises_after_a_stall() {
        let mut p = Pacer::new(0, PERIOD);
        let mut missed_total = 0;
        let mut wakes = 0;
        // Woken a little late each time: nothing missed, the period kept (no drift).
        for k in 1..=1000u64 {
            let now = p.deadline_us() + 30;
            assert_eq!(p.woke(now), 0);
            assert_eq!(p.deadline_us(), (k + 1) * u64::from(PERIOD));
            wakes += 1;
        }
        // A 2 s stall (a sector erase): woken once, the missed periods counted, and the next
        // deadline ahead of now: no burst of samples.
        let now = p.deadline_us() + 2_000_000;
        let m = p.woke(now);
        missed_total += m;
        assert_eq!(m, 2_000_000 / PERIOD);
        assert!(p.deadline_us() > now && p.deadline_us() - now <= u64::from(PERIOD));
        // (embassy's `Ticker` moves its deadline one period per `next()`: here it would have
        // fired 2 047 samples back to back, microseconds apart.)
        let next = p.deadline_us();
        assert_eq!(p.woke(next), 0);
        assert!(wakes + 2 < 1010 && missed_total > 2000);
    }

    #[test]
    fn speed_comes_from_counts_over_the_time_they_took() {
        let mut m = MotorSpeed::new(4096);
        // 250 rpm: 4096 · 250 / 60 counts/s.
        let rate = 4096.0 * 250.0 / 60.0;
        let mut last = None;
        for k in 0..200u64 {
            let t = k * u64::from(PERIOD);
            let c = (rate * t as f64 * 1e-6) as u32;
            last = m.sample(t, c);
            if k < MOTOR_WINDOW as u64 {
                assert_eq!(last, None, "window not full at {k}");
            }
        }
        let rpm = last.unwrap().to_f32() as f64;
        assert!((rpm - 250.0).abs() < 0.5, "{rpm}");
        // Across the 32-bit wrap.
        let mut m = MotorSpeed::new(4096);
        let start = u32::MAX - 1000;
        for k in 0..64u32 {
            let got = m.sample(u64::from(k) * 1000, start.wrapping_add(k * 68));
            if k >= 32 {
                // 68 counts/ms = 996 rpm.
                let r = got.unwrap().to_f32() as f64;
                assert!((r - 996.1).abs() < 0.2, "{r}");
            }
        }
    }

    #[test]
    fn cycle_time_runs_through_a_stall_and_across_the_wrap() {
        let hz = 168_000_000u32;
        let mut t = CycleTime::new(u32::MAX - 1_000, hz);
        assert_eq!(t.micros(u32::MAX - 1_000), 0);
        // An 8 s stall (four sector erases) across the counter's wrap.
        let after = (u32::MAX - 1_000).wrapping_add(8 * hz);
        assert_eq!(t.micros(after), 8_000_000);
        assert_eq!(t.micros(after.wrapping_add(168)), 8_000_001);
    }

    #[test]
    fn the_supply_is_averaged_but_a_failed_measurement_passes_at_once() {
        let mut f = SupplyFilter::default();
        assert_eq!(f.take(3300), 3300);
        assert_eq!(f.take(3310), 3305);
        for _ in 0..10 {
            f.take(3290);
        }
        assert!((3289..=3291).contains(&f.take(3290)));
        assert_eq!(f.take(0), 0, "a failed conversion");
        assert_eq!(f.take(1500), 1500);
        assert_eq!(f.take(3200), 3200, "the mean starts again");
    }

    /// A stall inside the window: the speed is the mean over the real time (a fixed-period
    /// window would read 65× too fast), and after a restart there is none until the window
    /// fills again.
    #[test]
    fn a_late_sample_does_not_read_as_a_faster_motor() {
        let mut m = MotorSpeed::new(4096);
        let rate_per_us = 4096.0 * 300.0 / 60.0 / 1e6;
        let mut t = 0u64;
        for k in 0..40 {
            t += if k == 35 {
                2_000_000
            } else {
                u64::from(PERIOD)
            };
            let r = m.sample(t, (rate_per_us * t as f64) as u32);
            if k == 35 {
                let rpm = r.unwrap().to_f32() as f64;
                assert!((rpm - 300.0).abs() < 1.0, "{rpm}");
            }
        }
        m.restart();
        for k in 0..MOTOR_WINDOW {
            t += u64::from(PERIOD);
            assert_eq!(m.sample(t, (rate_per_us * t as f64) as u32), None, "{k}");
        }
        t += u64::from(PERIOD);
        assert!(m.sample(t, (rate_per_us * t as f64) as u32).is_some());
    }
}
