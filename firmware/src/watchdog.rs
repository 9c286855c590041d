//! The independent watchdog (IWDG): its settings worked out from the LSI's datasheet range, and
//! a driver over its four registers that follows RM0090 §21.3 to the letter.
//!
//! The IWDG counts the LSI RC oscillator, 17–47 kHz (32 kHz typical; DS8626, "LSI oscillator
//! characteristics"), so a timeout is a range, not a number: a setting must cover what it
//! guards at the *fastest* LSI (the shortest timeout), and expires at the latest at the
//! slowest. A timeout is (RLR + 1) × prescaler / f_LSI (RM0090 §21.3, table 107: the /4 … /256
//! dividers, 0.125–32 768 ms at 32 kHz). [`IwdgSetting::covering`] picks the smallest prescaler
//! that does.
//!
//! RM0090 §21.4.3–§21.4.4: `IWDG_PR` and `IWDG_RLR` are written in the LSI domain; an update in
//! progress shows as `PVU` / `RVU` in `IWDG_SR`, during which the registers must not be written
//! again and their read value "may not be up to date/valid". So the driver never reads them
//! back (it restores a setting it knows, [`Iwdg::unwatched`]), waits for `PVU`/`RVU` to clear
//! before each write, and waits again before reloading the counter so the reload uses the new
//! value. Register access sits behind [`IwdgRegs`], so this is tested on the host against a
//! model of those rules.

/// The LSI's slowest frequency, Hz (DS8626, "LSI oscillator characteristics").
pub const LSI_MIN_HZ: u32 = 17_000;
/// The LSI's typical frequency, Hz.
pub const LSI_TYP_HZ: u32 = 32_000;
/// The LSI's fastest frequency, Hz.
pub const LSI_MAX_HZ: u32 = 47_000;

/// `IWDG_KR` keys (RM0090 §21.4.1).
pub mod key {
    /// Reload the counter ("feed").
    pub const RELOAD: u16 = 0xAAAA;
    /// Allow writes to `IWDG_PR` and `IWDG_RLR`.
    pub const UNLOCK: u16 = 0x5555;
    /// Start the watchdog.
    pub const START: u16 = 0xCCCC;
}

/// A prescaler and reload value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IwdgSetting {
    /// `IWDG_PR`: the prescaler is 4 · 2^pr (0..=6: /4 … /256).
    pub pr: u8,
    /// `IWDG_RLR`: 0..=0xFFF.
    pub rlr: u16,
}

impl IwdgSetting {
    /// The reset value (RM0090 §21.4.2–§21.4.3: /4, 0xFFF).
    pub const RESET: IwdgSetting = IwdgSetting { pr: 0, rlr: 0xFFF };

    /// The setting with the smallest prescaler whose timeout is at least `ms` at the fastest
    /// LSI (`None` above what /256 with 0xFFF gives: ≈ 22.3 s).
    pub const fn covering(ms: u32) -> Option<IwdgSetting> {
        let mut pr = 0u8;
        while pr <= 6 {
            let div = 4u64 << pr;
            // ticks = ms · f / (1000 · div), rounded up.
            let ticks = (ms as u64 * LSI_MAX_HZ as u64).div_ceil(1000 * div);
            if ticks >= 1 && ticks <= 0x1000 {
                return Some(IwdgSetting {
                    pr,
                    rlr: (ticks - 1) as u16,
                });
            }
            pr += 1;
        }
        None
    }

    /// The timeout at an LSI of `lsi_hz`, ms (rounded down).
    pub const fn timeout_ms(&self, lsi_hz: u32) -> u32 {
        ((self.rlr as u64 + 1) * (4u64 << self.pr) * 1000 / lsi_hz as u64) as u32
    }

    /// The shortest and longest timeout over the LSI's range, ms.
    pub const fn timeout_range_ms(&self) -> (u32, u32) {
        (self.timeout_ms(LSI_MAX_HZ), self.timeout_ms(LSI_MIN_HZ))
    }
}

/// The normal setting: at least [`crate::WATCHDOG_TIMEOUT_MS`] (the supervisor checks every
/// [`crate::SUPERVISOR_PERIOD_MS`], so a healthy firmware feeds it several times in the shortest
/// window); at most ≈ 0.69 s at the slowest LSI.
pub const NORMAL: IwdgSetting = match IwdgSetting::covering(crate::WATCHDOG_TIMEOUT_MS) {
    Some(s) => s,
    None => panic!("the watchdog timeout is beyond the IWDG"),
};

/// The longest operation done with the watchdog raised ([`Iwdg::unwatched`]), ms: an erase of
/// the two store sectors by the datasheet's bound (`pto_model::protocol::SECTOR_ERASE_MAX_MS`).
/// The other one, the brown-out level's option-byte write at boot (RM0090 §3.7.2, once in a
/// chip's life), has no bound in the datasheet: it relies on the raised window alone. A table
/// build is not one: it runs inside the normal window (asserted below).
pub const UNWATCHED_MAX_MS: u32 =
    pto_model::protocol::STORE_SECTORS * pto_model::protocol::SECTOR_ERASE_MAX_MS;

// Two of a controller's table builds back to back (`pto_model::protocol::TABLE_BUILD_MAX_MS`,
// its 5 M-instruction budget at 3 cycles each: a stored configuration checked then built at
// boot, an upload checked then applied) and a supervisor period fit the normal window at the
// fastest LSI: no feed is needed between them.
const _: () = assert!(
    2 * pto_model::protocol::TABLE_BUILD_MAX_MS as u64 + crate::SUPERVISOR_PERIOD_MS
        < NORMAL.timeout_range_ms().0 as u64
);

/// The raised setting around a long operation in the safe state: covers
/// [`UNWATCHED_MAX_MS`] at the fastest LSI (/64, 0xB79: 4.0 s; 11.1 s at the slowest).
pub const RAISED: IwdgSetting = match IwdgSetting::covering(UNWATCHED_MAX_MS) {
    Some(s) => s,
    None => panic!("the raised window is beyond the IWDG"),
};

/// The IWDG's registers.
pub trait IwdgRegs {
    /// `IWDG_SR`: (`PVU`, `RVU`), an update of the prescaler / reload in progress.
    fn updating(&self) -> (bool, bool);
    /// Writes `IWDG_KR`.
    fn key(&mut self, key: u16);
    /// Writes `IWDG_PR`.
    fn set_pr(&mut self, pr: u8);
    /// Writes `IWDG_RLR`.
    fn set_rlr(&mut self, rlr: u16);
}

/// The IWDG driver: the registers and the setting it runs at when nothing is raised.
#[derive(Debug)]
pub struct Iwdg<R> {
    regs: R,
    normal: IwdgSetting,
}

impl<R: IwdgRegs> Iwdg<R> {
    /// Starts the watchdog at `normal` (RM0090 §21.3.2: start, unlock, program, reload).
    pub fn start(regs: R, normal: IwdgSetting) -> Self {
        let mut w = Iwdg { regs, normal };
        w.regs.key(key::START);
        w.set(normal);
        w
    }

    /// A driver for a watchdog already started at `normal`.
    pub fn running(regs: R, normal: IwdgSetting) -> Self {
        Iwdg { regs, normal }
    }

    /// Reloads the counter.
    pub fn feed(&mut self) {
        self.regs.key(key::RELOAD);
    }

    fn wait_idle(&self) {
        // Bounded by 5 LSI periods (≤ 0.3 ms at 17 kHz); were it never to clear, the watchdog
        // itself would end the wait with a reset.
        while {
            let (p, r) = self.regs.updating();
            p || r
        } {
            core::hint::spin_loop();
        }
    }

    /// Programs `s` and reloads the counter with it.
    pub fn set(&mut self, s: IwdgSetting) {
        self.wait_idle();
        self.regs.key(key::UNLOCK);
        self.regs.set_pr(s.pr);
        self.regs.set_rlr(s.rlr);
        self.wait_idle();
        self.regs.key(key::RELOAD);
    }

    /// Runs `f` with the watchdog at `raised`, then back at the normal setting (never read back
    /// from the registers), the counter reloaded.
    pub fn unwatched<T>(&mut self, raised: IwdgSetting, f: impl FnOnce() -> T) -> T {
        self.set(raised);
        let r = f();
        self.set(self.normal);
        r
    }

    /// The registers.
    pub fn regs(&self) -> &R {
        &self.regs
    }
}

impl<R: IwdgRegs> crate::supervisor::Watchdog for Iwdg<R> {
    fn feed(&mut self) {
        Iwdg::feed(self);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The IWDG as RM0090 §21 describes it, counting its misuses: a write to `PR`/`RLR` while
    /// its update is in progress or while locked, and a reload while `RVU` is set (the counter
    /// then takes the old reload value). An update takes `lag` polls of `IWDG_SR`; reads of
    /// `PR`/`RLR` return the old value until then.
    #[derive(Debug, Default)]
    struct Model {
        unlocked: bool,
        started: bool,
        pr: (u8, u8),
        rlr: (u16, u16),
        pvu_left: core::cell::Cell<u32>,
        rvu_left: core::cell::Cell<u32>,
        lag: u32,
        misuse: Vec<&'static str>,
        /// The prescaler and reload value the counter took at each reload.
        reloads: Vec<(u8, u16)>,
    }

    impl Model {
        fn new(lag: u32) -> Self {
            Model {
                pr: (0, 0),
                rlr: (0xFFF, 0xFFF),
                lag,
                ..Default::default()
            }
        }
        fn settle(&self) {
            for left in [&self.pvu_left, &self.rvu_left] {
                left.set(left.get().saturating_sub(1));
            }
        }
        /// What a program reading `PR`/`RLR` back would see.
        fn read_back(&self) -> (u8, u16) {
            let p = if self.pvu_left.get() > 0 {
                self.pr.0
            } else {
                self.pr.1
            };
            let r = if self.rvu_left.get() > 0 {
                self.rlr.0
            } else {
                self.rlr.1
            };
            (p, r)
        }
    }

    impl IwdgRegs for Model {
        fn updating(&self) -> (bool, bool) {
            self.settle();
            (self.pvu_left.get() > 0, self.rvu_left.get() > 0)
        }
        fn key(&mut self, k: u16) {
            match k {
                key::UNLOCK => self.unlocked = true,
                key::START => self.started = true,
                key::RELOAD => {
                    if self.rvu_left.get() > 0 || self.pvu_left.get() > 0 {
                        self.misuse.push("reload during an update");
                        self.reloads.push((self.pr.0, self.rlr.0));
                    } else {
                        self.reloads.push((self.pr.1, self.rlr.1));
                    }
                    self.unlocked = false;
                }
                _ => self.misuse.push("bad key"),
            }
        }
        fn set_pr(&mut self, pr: u8) {
            if !self.unlocked {
                self.misuse.push("PR written while locked");
            }
            if self.pvu_left.get() > 0 {
                self.misuse.push("PR written during its update");
            }
            self.pr = (self.pr.1, pr);
            self.pvu_left.set(self.lag);
        }
        fn set_rlr(&mut self, rlr: u16) {
            if !self.unlocked {
                self.misuse.push("RLR written while locked");
            }
            if self.rvu_left.get() > 0 {
                self.misuse.push("RLR written during its update");
            }
            self.rlr = (self.rlr.1, rlr);
            self.rvu_left.set(self.lag);
        }
    }

    #[test]
    fn the_settings_cover_their_windows_over_the_whole_lsi_range() {
        let (lo, hi) = NORMAL.timeout_range_ms();
        println!(
            "normal {NORMAL:?}: {lo}–{hi} ms; raised {RAISED:?}: {:?} ms",
            RAISED.timeout_range_ms()
        );
        assert!(
            lo >= crate::WATCHDOG_TIMEOUT_MS && hi <= 700,
            "{lo}–{hi} ms"
        );
        // The supervisor feeds at least three times within the shortest window.
        assert!(u64::from(lo) >= 3 * crate::SUPERVISOR_PERIOD_MS);
        let (lo, hi) = RAISED.timeout_range_ms();
        assert!(
            lo >= UNWATCHED_MAX_MS,
            "raised {lo} ms < {UNWATCHED_MAX_MS} ms"
        );
        assert!(hi <= 16_000, "raised window {hi} ms at the slowest LSI");
        assert_eq!(RAISED.pr, 4, "/64");
        // The old raised window (/256, 0xFFF) was 22–62 s: four times what is needed.
        let old = IwdgSetting { pr: 6, rlr: 0xFFF };
        assert_eq!(old.timeout_range_ms(), (22_310, 61_680));
        assert_eq!(IwdgSetting::covering(30_000), None);
        for ms in [1, 10, 250, 999, 4_000, 22_000] {
            let s = IwdgSetting::covering(ms).unwrap();
            assert!(
                s.timeout_ms(LSI_MAX_HZ) >= ms && s.rlr <= 0xFFF,
                "{ms}: {s:?}"
            );
            if s.pr > 0 {
                // A smaller prescaler could not have covered it.
                let finer = IwdgSetting {
                    pr: s.pr - 1,
                    rlr: 0xFFF,
                };
                assert!(finer.timeout_ms(LSI_MAX_HZ) < ms, "{ms}: {s:?}");
            }
        }
    }

    #[test]
    fn a_raised_window_is_restored_from_the_known_setting_without_misuse() {
        let n = (NORMAL.pr, NORMAL.rlr);
        let r = (RAISED.pr, RAISED.rlr);
        for lag in [0, 1, 5, 40] {
            let mut w = Iwdg::start(Model::new(lag), NORMAL);
            assert_eq!(w.regs().reloads, [n], "lag {lag}");
            let x = w.unwatched(RAISED, || 7);
            assert_eq!(x, 7);
            w.feed();
            assert_eq!(
                w.regs().reloads,
                [n, r, n, n],
                "lag {lag}: raised, then back"
            );
            assert!(
                w.regs().misuse.is_empty(),
                "lag {lag}: {:?}",
                w.regs().misuse
            );
        }
    }

    /// The defect the bring-up review found: the old restore read `PR`/`RLR` back, then raised,
    /// ran, and wrote back what it had read. Two raised sections back to back (a commit that
    /// stores: the tables checked, then a sector erased) read the first one's restore while
    /// its update is still in progress — the raised values — and leave the watchdog raised
    /// for good. The driver above restores the setting it knows.
    #[test]
    fn reading_the_setting_back_during_an_update_leaves_the_window_raised() {
        fn old_unwatched(m: &mut Model) {
            let saved = m.read_back();
            let set = |m: &mut Model, (pr, rlr): (u8, u16)| {
                while {
                    let (p, r) = m.updating();
                    p || r
                } {}
                m.key(key::UNLOCK);
                m.set_pr(pr);
                m.set_rlr(rlr);
                m.key(key::RELOAD);
            };
            set(m, (RAISED.pr, RAISED.rlr));
            set(m, saved);
        }
        let mut m = Model::new(5);
        m.key(key::START);
        m.key(key::UNLOCK);
        m.set_pr(NORMAL.pr);
        m.set_rlr(NORMAL.rlr);
        for _ in 0..10 {
            m.updating();
        }
        old_unwatched(&mut m);
        old_unwatched(&mut m);
        for _ in 0..10 {
            m.updating();
        }
        assert_eq!(
            m.read_back(),
            (RAISED.pr, RAISED.rlr),
            "the old restore leaves the raised window"
        );
        // The driver, the same two sections back to back.
        let mut w = Iwdg::start(Model::new(5), NORMAL);
        w.unwatched(RAISED, || ());
        w.unwatched(RAISED, || ());
        for _ in 0..10 {
            w.regs().updating();
        }
        assert_eq!(w.regs().read_back(), (NORMAL.pr, NORMAL.rlr));
        assert!(w.regs().misuse.is_empty(), "{:?}", w.regs().misuse);
    }
}
