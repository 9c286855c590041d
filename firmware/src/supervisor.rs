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
    /// Receive, the bench link.
    Rx = 1,
    /// Transmit, the bench link.
    Tx = 2,
    /// Receive, the QEMU twin's hardware port (its virtual sensors and actuators).
    HwRx = 3,
    /// Transmit, the QEMU twin's hardware port.
    HwTx = 4,
}

/// Number of monitored tasks.
pub const TASKS: usize = 5;
const ALL: [Task; TASKS] = [Task::Control, Task::Rx, Task::Tx, Task::HwRx, Task::HwTx];

/// One heartbeat counter per task.
#[derive(Debug)]
pub struct Heartbeats {
    beats: [AtomicU32; TASKS],
}

impl Heartbeats {
    /// All counters at zero.
    pub const fn new() -> Self {
        Heartbeats {
            beats: [const { AtomicU32::new(0) }; TASKS],
        }
    }

    /// Records that `task` is alive.
    pub fn beat(&self, task: Task) {
        let b = &self.beats[task as usize];
        b.store(b.load(Ordering::Relaxed).wrapping_add(1), Ordering::Relaxed);
    }

    /// Marks every task alive (after the controller stalled on purpose for a flash erase,
    /// with the watchdog's timeout raised for it).
    pub fn beat_all(&self) {
        for t in ALL {
            self.beat(t);
        }
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

/// Remembers the counters between two checks.
#[derive(Debug)]
pub struct Supervisor {
    last: [u32; TASKS],
    watched: [bool; TASKS],
}

impl Supervisor {
    /// Watches `tasks` (the ones the board runs).
    pub fn new(tasks: &[Task]) -> Self {
        let mut watched = [false; TASKS];
        for t in tasks {
            watched[*t as usize] = true;
        }
        Supervisor {
            last: [0; TASKS],
            watched,
        }
    }

    /// Checks the heartbeats; returns the first watched task that has not beaten since the
    /// last check, or `None` (feed the watchdog).
    pub fn check(&mut self, hb: &Heartbeats) -> Option<Task> {
        let mut silent = None;
        for (i, t) in ALL.into_iter().enumerate() {
            let now = hb.read(i);
            if self.watched[i] && now == self.last[i] && silent.is_none() {
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
        let mut s = Supervisor::new(&[Task::Control, Task::Rx, Task::Tx]);
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
        // A task the board does not run is not waited for; one it runs is.
        let mut s = Supervisor::new(&[Task::Control, Task::Rx, Task::Tx, Task::HwRx]);
        hb.beat_all();
        assert_eq!(s.check(&hb), None);
        for t in [Task::Control, Task::Rx, Task::Tx] {
            hb.beat(t);
        }
        assert_eq!(s.check(&hb), Some(Task::HwRx));
    }
}
