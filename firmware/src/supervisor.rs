//! Task heartbeats and the watchdog-feed decision.
//!
//! Every monitored task bumps its counter each time round its loop (and at least every
//! [`crate::HEARTBEAT_MS`] while idle). The supervisor feeds the watchdog only if every counter
//! moved since its last check: a task stuck in a busy loop starves the whole executor, and a task
//! stuck awaiting something that never comes stops its own counter — either way the watchdog
//! expires.

use core::sync::atomic::{AtomicU32, Ordering};

/// A watchdog the supervisor feeds (the bench's IWDG; under QEMU a SysTick countdown).
pub trait Watchdog {
    /// Restarts the countdown.
    fn feed(&mut self);
}

/// Monitored tasks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(usize)]
pub enum Task {
    /// Estimator + scheduler + actuator.
    Control = 0,
    /// Receive link.
    Rx = 1,
    /// Transmit link.
    Tx = 2,
}

/// Number of monitored tasks.
pub const TASKS: usize = 3;

/// Heartbeat counters, shared between tasks.
#[derive(Debug)]
pub struct Heartbeats {
    beats: [AtomicU32; TASKS],
}

impl Heartbeats {
    /// All counters at zero.
    pub const fn new() -> Self {
        Heartbeats {
            beats: [AtomicU32::new(0), AtomicU32::new(0), AtomicU32::new(0)],
        }
    }

    /// Records that `task` is alive.
    pub fn beat(&self, task: Task) {
        let b = &self.beats[task as usize];
        b.store(b.load(Ordering::Relaxed).wrapping_add(1), Ordering::Relaxed);
    }

    fn read(&self, i: usize) -> u32 {
        self.beats[i].load(Ordering::Relaxed)
    }
}

impl Default for Heartbeats {
    fn default() -> Self {
        Self::new()
    }
}

/// The supervisor's memory of the last check.
#[derive(Debug, Default)]
pub struct Supervisor {
    last: [u32; TASKS],
}

impl Supervisor {
    /// Checks the heartbeats; returns the first task that has not beaten since the last check,
    /// or `None` (feed the watchdog).
    pub fn check(&mut self, hb: &Heartbeats) -> Option<Task> {
        let mut silent = None;
        for (i, t) in [Task::Control, Task::Rx, Task::Tx].into_iter().enumerate() {
            let now = hb.read(i);
            if now == self.last[i] && silent.is_none() {
                silent = Some(t);
            }
            self.last[i] = now;
        }
        silent
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_silent_task_withholds_the_feed_until_it_beats_again() {
        let hb = Heartbeats::new();
        let mut s = Supervisor::default();
        hb.beat(Task::Control);
        hb.beat(Task::Rx);
        hb.beat(Task::Tx);
        assert_eq!(s.check(&hb), None);
        hb.beat(Task::Rx);
        hb.beat(Task::Tx);
        assert_eq!(s.check(&hb), Some(Task::Control));
        hb.beat(Task::Control);
        hb.beat(Task::Rx);
        assert_eq!(s.check(&hb), Some(Task::Tx));
        for t in [Task::Control, Task::Rx, Task::Tx] {
            hb.beat(t);
        }
        assert_eq!(s.check(&hb), None);
    }
}
