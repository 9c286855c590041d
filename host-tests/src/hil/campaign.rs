//! `pto link campaign run`: a planned campaign on the controller, segment by segment.
//!
//! For each segment: the cylinders de-energised and the valve closed (the safe state) while the
//! operator changes the set-up and stops the lever; the estimator restarted from the pressure
//! readings; HP let down to the segment's start through the valve (mode `hold-pressure`; HP
//! below the start is reported, not pumped up: that would be a segment of its own); the
//! segment's aperture (mode `fixed`), reached before the log starts; then the cylinders
//! energised and the log started together — the chambers start from LP, as the fit's simulation
//! of a log starts them — and the operator starts the lever, which must show the planned motion
//! (amplitude and period within [`MOTION_TOLERANCE`]) within a grace time; the log is the
//! monitor's bench log at the segment's rate, for its planned length; then the safe state again.
//! Each log gets its sidecar (`plan::Record`): complete, unfinished (Ctrl-C, the link lost) or
//! mismatch (the motion off, the lever moving before the log began, frames lost, a trip, a
//! restart, a sensor held faulted, the start not reached), so `pto fit DIR/*.csv` takes the folder as it is and refuses what is not
//! complete. Running it again skips the complete segments and runs the others.

use crate::hil::client::{self, ClientError, LogWriter, Sample, Units};
use crate::hil::link::{Link, LinkError};
use crate::hil::selftest::Operator;
use crate::plan::{Campaign, CampaignError, Record, Segment, Status};
use crate::sim::bench::{BAR, Bench};
use crate::sim::motion::MotionSpec;
use crate::sim::scenario::{Prepared, ValveSpec};
use crate::validation::duty_mask;
use pto_model::fx::{Aperture, Pressure};
use pto_model::protocol::FromFirmware;
use pto_model::scheduler::Mode;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A motion matches its plan when its amplitude and its period are each within this fraction.
pub const MOTION_TOLERANCE: f64 = 0.10;
/// Shaft travel below which the lever counts as held, deg (as the fit's `input_moves`).
pub const HELD_TRAVEL_DEG: f64 = 0.5;
/// The valve counts as at the segment's aperture within this, %.
pub const APERTURE_REACHED_PCT: f32 = 0.1;
/// Frames lost (of those due) above which a segment's log is a mismatch.
pub const LOST_LIMIT: f64 = 0.01;

/// How long the runner waits, and how close the start pressure must be.
#[derive(Debug, Clone, Copy)]
pub struct Waits {
    /// For HP to come down to the segment's start (wall clock).
    pub prepare: Duration,
    /// HP at the start within max(this, 5 % of the start), bar.
    pub start_tolerance_bar: f64,
}

impl Default for Waits {
    fn default() -> Self {
        Waits {
            prepare: Duration::from_secs(300),
            start_tolerance_bar: 2.0,
        }
    }
}

/// Why a campaign could not run.
#[derive(Debug, thiserror::Error)]
pub enum CampaignRunError {
    /// The link failed.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// A log or sidecar could not be written, or the configuration not read.
    #[error(transparent)]
    Client(#[from] ClientError),
    /// A sidecar could not be read or written.
    #[error(transparent)]
    Campaign(#[from] CampaignError),
    /// The log folder could not be made.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// A segment the controller cannot run by itself.
    #[error("segment[{index}] ({name}): {what}")]
    Unsupported {
        /// The segment.
        index: usize,
        /// Its name.
        name: String,
        /// What is not supported, and what is.
        what: String,
    },
    /// The folder holds a complete log of a segment of the same name planned differently.
    #[error(
        "{log}: a complete log of another plan's segment {name:?} (its sidecar differs from the campaign's): use another --log-dir, or remove it to run this one"
    )]
    Foreign {
        /// The log.
        log: PathBuf,
        /// The segment's name.
        name: String,
    },
}

/// A lever motion as the encoder shows it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SeenMotion {
    /// Half the shaft's peak-to-peak travel, deg.
    pub amplitude_deg: f64,
    /// Mean time between upward crossings of the travel's middle, s (`None`: fewer than two).
    pub period_s: Option<f64>,
    /// The longest stretch without an upward crossing — from the first sample to the first
    /// crossing, between two, from the last to the last sample — s: a lever that stopped
    /// part-way shows here, not in the mean period.
    pub longest_s: f64,
}

impl SeenMotion {
    /// Of the samples at or after `from` s (times `t` increasing).
    pub fn since(t: &[f64], a: &[f64], from: f64) -> SeenMotion {
        let k = t.partition_point(|x| *x < from);
        SeenMotion::of(&t[k..], &a[k..])
    }

    /// Of shaft angles `a` (deg) at times `t` (s).
    pub fn of(t: &[f64], a: &[f64]) -> SeenMotion {
        let (lo, hi) = a
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), x| {
                (l.min(*x), h.max(*x))
            });
        if a.is_empty() {
            return SeenMotion {
                amplitude_deg: 0.0,
                period_s: None,
                longest_s: 0.0,
            };
        }
        let (mid, amp) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        // Upward crossings with a hysteresis of a fifth of the amplitude: sensor noise and
        // encoder steps never count as one.
        let band = 0.2 * amp;
        let mut below = false;
        let mut ups = Vec::new();
        for (ti, x) in t.iter().zip(a) {
            if *x < mid - band {
                below = true;
            } else if below && *x > mid + band {
                below = false;
                ups.push(*ti);
            }
        }
        let period_s =
            (ups.len() >= 2).then(|| (ups[ups.len() - 1] - ups[0]) / (ups.len() - 1) as f64);
        let ends = [t[0]]
            .into_iter()
            .chain(ups.iter().copied())
            .chain([t[t.len() - 1]]);
        let longest_s = ends
            .clone()
            .zip(ends.skip(1))
            .map(|(a, b)| b - a)
            .fold(0.0, f64::max);
        SeenMotion {
            amplitude_deg: amp,
            period_s,
            longest_s,
        }
    }
}

/// The shaft's travel over a log's first 1/64 s (its first frame at 64 Hz, or the rows that
/// span it at a higher rate) above which the lever was already moving when the log began, deg
/// (4.5 of the encoder's 16 384 counts a revolution: 6.4°/s, where the charge's lever runs at
/// 30°/s).
pub const STILL_AT_START_DEG: f64 = 0.1;

/// Why a log is refused that begins with the lever moving: the cylinders were energised, and
/// the chambers compressing, before its first row, where the fit's simulation starts them at LP
/// with the lever at rest. One frame of a 0.2 Hz charge before the log biased the fitted trapped
/// air by −1.3 %. `t` (s) and `a_deg` are the log's rows.
fn moving_at_start(t: &[f64], a_deg: &[f64]) -> Option<String> {
    let (t0, a0) = (*t.first()?, *a_deg.first()?);
    let k = t.iter().position(|ti| ti - t0 >= 1.0 / 64.0 - 1e-9)?;
    let travel = (a_deg[k] - a0).abs();
    (travel > STILL_AT_START_DEG).then(|| {
        format!(
            "the lever was already moving when the log began ({travel:.2}° over its first {:.0} \
             ms, above {STILL_AT_START_DEG}°): start it after the prompt, the log's first rows \
             must show it at rest",
            (t[k] - t0) * 1e3
        )
    })
}

/// The lever motion a segment plans, as the encoder would show it on `bench`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PlannedMotion {
    /// Half the shaft's peak-to-peak travel, deg (0: held).
    pub amplitude_deg: f64,
    /// Period, s (`None`: held).
    pub period_s: Option<f64>,
}

impl PlannedMotion {
    /// Of a segment's run prepared on its bench: the rack's sine through the geometry's
    /// kinematics.
    pub fn of(prep: &Prepared) -> PlannedMotion {
        match prep.scenario.motion {
            MotionSpec::Sine { frequency_hz, .. } => {
                let period = 1.0 / frequency_hz;
                let (lo, hi) = (0..=400)
                    .map(|k| prep.plant.motion().at(period * f64::from(k) / 400.0).0)
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), x| {
                        (l.min(x), h.max(x))
                    });
                PlannedMotion {
                    amplitude_deg: 0.5 * (hi - lo).to_degrees(),
                    period_s: Some(period),
                }
            }
            _ => PlannedMotion {
                amplitude_deg: 0.0,
                period_s: None,
            },
        }
    }

    /// How the seen motion differs from it, if it does (beyond [`MOTION_TOLERANCE`]).
    pub fn differs(&self, seen: &SeenMotion) -> Option<String> {
        let Some(period) = self.period_s else {
            return (2.0 * seen.amplitude_deg >= HELD_TRAVEL_DEG).then(|| {
                format!(
                    "the lever moved ±{:.2}° where it should be held",
                    seen.amplitude_deg
                )
            });
        };
        let off = |x: f64, want: f64| ((x - want) / want).abs() > MOTION_TOLERANCE;
        if off(seen.amplitude_deg, self.amplitude_deg) {
            return Some(format!(
                "lever amplitude ±{:.2}° against ±{:.2}° planned",
                seen.amplitude_deg, self.amplitude_deg
            ));
        }
        match seen.period_s {
            None => Some(format!("no full lever period seen (planned {period:.2} s)")),
            Some(p) if off(p, period) => Some(format!(
                "lever period {p:.2} s against {period:.2} s planned"
            )),
            Some(_) if seen.longest_s > (1.0 + MOTION_TOLERANCE) * period => Some(format!(
                "the lever went {:.1} s without a period (planned {period:.2} s): it stopped part-way",
                seen.longest_s
            )),
            Some(_) => None,
        }
    }
}

/// How one segment came out.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// The segment's place in the campaign (from 0).
    pub index: usize,
    /// Its name.
    pub name: String,
    /// How it came out (`Complete` also for one found complete and skipped).
    pub status: Status,
    /// Skipped: complete from an earlier run.
    pub skipped: bool,
    /// Why, when not complete.
    pub note: String,
    /// The log.
    pub log: PathBuf,
    /// Rows written.
    pub rows: u64,
    /// Telemetry frames lost (gaps in the ticks).
    pub lost: u64,
    /// The motion seen over the log.
    pub motion: Option<SeenMotion>,
    /// The motion planned.
    pub planned: Option<PlannedMotion>,
}

impl Outcome {
    /// Ends the segment before its log began: the controller put in its safe state, the
    /// outcome marked with why.
    fn before_log(
        mut self,
        link: &mut Link,
        config: u8,
        status: Status,
        note: impl Into<String>,
    ) -> Result<Outcome, CampaignRunError> {
        safe(link, config)?;
        self.status = status;
        self.note = note.into();
        Ok(self)
    }

    /// [`Outcome::before_log`] when the operator stopped the run (Ctrl-C): unfinished.
    fn interrupted(
        self,
        link: &mut Link,
        config: u8,
        note: &str,
    ) -> Result<Outcome, CampaignRunError> {
        self.before_log(link, config, Status::Unfinished, note)
    }
}

/// What a campaign run did.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Each segment, in order (those reached).
    pub segments: Vec<Outcome>,
    /// Stopped by Ctrl-C.
    pub interrupted: bool,
}

impl Report {
    /// Every segment complete.
    pub fn complete(&self, n: usize) -> bool {
        !self.interrupted
            && self.segments.len() == n
            && self.segments.iter().all(|o| o.status == Status::Complete)
    }
}

/// Telemetry in engineering units, with what went wrong on the way.
struct Feed<'a> {
    link: &'a mut Link,
    units: Units,
    last_tick: Option<u32>,
    every: u32,
    lost: u64,
    restarted: bool,
}

impl Feed<'_> {
    /// The next sample; `None` when nothing came within the link's timeout.
    fn next(&mut self) -> Result<Option<Sample>, LinkError> {
        let before = self.link.timeout;
        self.link.timeout = Duration::from_millis(500);
        let got = self.link.recv();
        self.link.timeout = before;
        match got {
            Ok(FromFirmware::Telemetry(tel)) => {
                let tick = tel.sensors.tick;
                if let Some(last) = self.last_tick {
                    if tick <= last {
                        self.restarted = true;
                    } else {
                        let every = self.every.max(1);
                        let gap = (tick - last + every / 2) / every;
                        self.lost += u64::from(gap.saturating_sub(1));
                    }
                }
                self.last_tick = Some(tick);
                Ok(Some(self.units.sample(&tel)))
            }
            Ok(FromFirmware::Hello(_)) => {
                self.restarted = true;
                Ok(None)
            }
            Ok(_) => Ok(None),
            Err(LinkError::NoReply(_)) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// Forgets the frames so far (a new window).
    fn restart_counts(&mut self) {
        self.lost = 0;
        self.restarted = false;
    }
}

/// Checks that the controller can run every segment by itself: a fixed aperture, a sine or a
/// held lever.
pub fn check_runnable(campaign: &Campaign) -> Result<(), CampaignRunError> {
    for (index, s) in campaign.segment.iter().enumerate() {
        let unsupported = |what: &str| CampaignRunError::Unsupported {
            index,
            name: s.run.name.clone(),
            what: what.into(),
        };
        if !matches!(s.run.valve, ValveSpec::Constant { .. }) {
            return Err(unsupported(
                "valve: the runner sets one fixed aperture per segment (valve kind \"constant\")",
            ));
        }
        if !matches!(
            s.run.motion,
            MotionSpec::Sine { .. } | MotionSpec::Blocked { .. }
        ) {
            return Err(unsupported(
                "motion: the runner checks a sine or a held lever (kind \"sine\" or \"blocked\")",
            ));
        }
    }
    Ok(())
}

/// `, sensors held faulted: …` when any is.
fn held_faults(bits: u8) -> String {
    if bits == 0 {
        return String::new();
    }
    format!(
        ", sensors held faulted: {}",
        pto_firmware::sensor_faults::names(bits)
            .collect::<Vec<_>>()
            .join(", ")
    )
}

/// Writes segment `index`'s sidecar beside `log`.
fn write_record(
    campaign_file: &str,
    index: usize,
    status: Status,
    note: &str,
    seg: &Segment,
    log: &Path,
) -> Result<(), CampaignRunError> {
    Record {
        campaign: campaign_file.to_string(),
        index,
        status,
        note: note.to_string(),
        segment: seg.clone(),
    }
    .write_for(log)
    .map_err(|source| CampaignRunError::Io {
        path: Record::path_for(log),
        source,
    })
}

/// Puts the controller in its safe state: cylinders de-energised, valve closed.
fn safe(link: &mut Link, config: u8) -> Result<(), LinkError> {
    // Both, whatever the first answers: the first error is reported.
    let duty = client::set_duty(link, 0, config);
    let valve = client::set_mode(link, Mode::Fixed(Aperture::ZERO));
    duty.and(valve)
}

/// Runs `campaign` (read from `campaign_file`) on the controller at `link`, logging into `dir`.
#[allow(clippy::too_many_arguments)]
pub fn run(
    link: &mut Link,
    dt_log2: u8,
    bench: &Bench,
    campaign: &Campaign,
    campaign_file: &str,
    dir: &Path,
    waits: Waits,
    op: &mut dyn Operator,
) -> Result<Report, CampaignRunError> {
    check_runnable(campaign)?;
    std::fs::create_dir_all(dir).map_err(|source| CampaignRunError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let (_, cfg) = client::read_config(link)?;
    let units = Units::new(dt_log2, &cfg);
    let steps_per_s = 2f64.powi(i32::from(dt_log2));
    let mut report = Report {
        segments: Vec::new(),
        interrupted: false,
    };
    // Each segment's run prepared on the bench, its log and whether an earlier run completed
    // it; a complete log of a differently planned segment of the same name is refused before
    // any segment runs.
    let mut segments = Vec::with_capacity(campaign.segment.len());
    for (index, seg) in campaign.segment.iter().enumerate() {
        let prep = seg
            .run
            .prepare(bench, Path::new("."))
            .map_err(|source| CampaignError::Run {
                file: campaign_file.to_string(),
                index,
                source,
            })?;
        let log = dir.join(format!("{}.csv", seg.run.name));
        let complete = match Record::read_for(&log)? {
            Some(rec) if rec.status == Status::Complete && rec.segment != *seg => {
                return Err(CampaignRunError::Foreign {
                    log,
                    name: seg.run.name.clone(),
                });
            }
            Some(rec) => rec.status == Status::Complete && log.exists(),
            None => false,
        };
        segments.push((prep, log, complete));
    }
    let mut last_config = None;
    for (index, (seg, (prep, log_path, complete))) in
        campaign.segment.iter().zip(segments).enumerate()
    {
        let name = seg.run.name.clone();
        if complete {
            op.say(&format!(
                "segment {}/{} ({name}): complete in {} — skipped",
                index + 1,
                campaign.segment.len(),
                log_path.display()
            ));
            report.segments.push(Outcome {
                index,
                name,
                status: Status::Complete,
                skipped: true,
                note: String::new(),
                log: log_path,
                rows: 0,
                lost: 0,
                motion: None,
                planned: None,
            });
            continue;
        }
        loop {
            // Until the segment's verdict: whatever stops the run before it (an error, a second
            // Ctrl-C) leaves the log marked, never taken as complete or as a plain log.
            write_record(
                campaign_file,
                index,
                Status::Unfinished,
                "under way",
                seg,
                &log_path,
            )?;
            let o = match run_segment(
                link,
                &units,
                steps_per_s,
                &prep,
                seg,
                (index, campaign.segment.len()),
                &log_path,
                waits,
                last_config,
                op,
            ) {
                Ok(o) => o,
                Err(e) => {
                    // Whatever failed, the controller is left in its safe state if it answers.
                    let _ = safe(link, prep.config as u8);
                    return Err(e);
                }
            };
            last_config = Some(prep.config);
            write_record(campaign_file, index, o.status, &o.note, seg, &log_path)?;
            let stop = o.status == Status::Unfinished;
            let mismatch = o.status == Status::Mismatch;
            op.say(&format!(
                "segment {}/{} ({name}): {}{}",
                index + 1,
                campaign.segment.len(),
                o.status.label(),
                if o.note.is_empty() {
                    String::new()
                } else {
                    format!(" — {}", o.note)
                }
            ));
            report.segments.push(o);
            if stop {
                report.interrupted = op.stopped();
                return Ok(report);
            }
            if mismatch && op.confirm("rerun this segment now?") == Some(true) {
                report.segments.pop();
                continue;
            }
            break;
        }
    }
    Ok(report)
}

#[allow(clippy::too_many_arguments)]
fn run_segment(
    link: &mut Link,
    units: &Units,
    steps_per_s: f64,
    prep: &Prepared,
    seg: &Segment,
    (index, of): (usize, usize),
    log_path: &Path,
    waits: Waits,
    last_config: Option<usize>,
    op: &mut dyn Operator,
) -> Result<Outcome, CampaignRunError> {
    let name = seg.run.name.clone();
    let planned = PlannedMotion::of(prep);
    let config = prep.config as u8;
    let mask = duty_mask(&prep.on_duty);
    let aperture = match seg.run.valve {
        ValveSpec::Constant { aperture_pct } => aperture_pct,
        _ => unreachable!("check_runnable refused it"),
    };
    let mut outcome = Outcome {
        index,
        name: name.clone(),
        status: Status::Unfinished,
        skipped: false,
        note: String::new(),
        log: log_path.to_path_buf(),
        rows: 0,
        lost: 0,
        motion: None,
        planned: Some(planned),
    };
    // 1. The safe state while the set-up changes.
    safe(link, config)?;
    op.say(&format!(
        "segment {}/{of} ({name}), {:.0} s at {} Hz: {}",
        index + 1,
        seg.run.duration_s,
        seg.rate_hz,
        seg.operator
    ));
    if last_config != Some(prep.config)
        && op.confirm(&format!(
            "is the lever in {} with the rack drive ready?",
            seg.run.config
        )) == Some(false)
    {
        outcome.note = "the operator did not set the geometry".into();
        return Ok(outcome);
    }
    let every = (steps_per_s / seg.rate_hz).round().clamp(1.0, 65_535.0) as u16;
    let every = client::set_telemetry(link, every)?;
    let trips_before = client::status(link)?.trips;
    let mut feed = Feed {
        link,
        units: units.clone(),
        last_tick: None,
        every: u32::from(every),
        lost: 0,
        restarted: false,
    };
    // 2. The estimator from the readings.
    let t_wait = Instant::now();
    // The mean of 32 frames: one reading's noise would be the estimate's start.
    let mut sum = (0.0, 0.0, 0u32);
    let first = loop {
        if op.stopped() {
            return outcome.interrupted(feed.link, config, "interrupted before the segment began");
        }
        if let Some(s) = feed.next()?
            && let (Some(hp), Some(lp)) = (s.hp_bar, s.lp_bar)
        {
            sum = (sum.0 + hp, sum.1 + lp, sum.2 + 1);
            if sum.2 == 32 {
                break (sum.0 / 32.0, sum.1 / 32.0);
            }
        }
        if t_wait.elapsed() > Duration::from_secs(10) {
            return outcome.before_log(
                feed.link,
                config,
                Status::Mismatch,
                "no telemetry with both pressure readings for 10 s",
            );
        }
    };
    client::reset(feed.link, first.0 as f32, first.1 as f32)?;
    // 3. The start pressure, the lever held and the cylinders de-energised: HP above it is let
    //    down through the valve (mode hold-pressure); HP below it cannot be pumped up without
    //    starting the segment, and the segment is not run.
    let start_bar = prep.initial.p2_pa / BAR;
    let tol = waits.start_tolerance_bar.max(0.05 * start_bar);
    let mut hp_now = first.0;
    if seg.run.initial_hp_bar.is_some() {
        if hp_now < start_bar - tol {
            return outcome.before_log(feed.link, config, Status::Mismatch, format!(
                    "HP {hp_now:.1} bar is below the planned start {start_bar:.1} ± {tol:.1} bar: pump it up first \
                 (the lever running, `pto link … duty` and `mode hold-pressure {start_bar:.0}`), then run again"
                ),
            );
        }
        if hp_now > start_bar + tol {
            op.say(&format!(
                "  letting HP down from {hp_now:.1} to {start_bar:.1} bar through the valve (the lever held)…"
            ));
            client::set_mode(
                feed.link,
                Mode::HoldPressure(Pressure::from_num(start_bar.clamp(1.0, 130.0) as f32)),
            )?;
            let t_wait = Instant::now();
            while hp_now > start_bar + tol {
                if op.stopped() {
                    return outcome.interrupted(
                        feed.link,
                        config,
                        "interrupted before the segment's log began",
                    );
                }
                if t_wait.elapsed() > waits.prepare {
                    return outcome.before_log(feed.link, config, Status::Mismatch, format!(
                            "HP still {hp_now:.1} bar after {:.0} s against the planned start {start_bar:.1} ± {tol:.1} bar",
                            waits.prepare.as_secs_f64()
                        ),
                    );
                }
                if let Some(s) = feed.next()?
                    && let Some(hp) = s.hp_bar
                {
                    hp_now = hp;
                }
            }
        }
    }
    // 4. The segment's aperture, reached before the log starts (the valve slews).
    let aperture = Aperture::from_num(aperture.clamp(0.0, 100.0) as f32);
    client::set_mode(feed.link, Mode::Fixed(aperture))?;
    let t_wait = Instant::now();
    let mut applied = None;
    loop {
        if let Some(s) = feed.next()? {
            applied = Some(s.raw.applied);
            // Within the actuator's resolution of the aperture asked.
            if (s.raw.applied.to_f32() - aperture.to_f32()).abs() <= APERTURE_REACHED_PCT {
                break;
            }
        }
        if op.stopped() {
            return outcome.interrupted(
                feed.link,
                config,
                "interrupted before the segment's log began",
            );
        }
        if t_wait.elapsed() > Duration::from_secs(30) {
            return outcome.before_log(feed.link, config, Status::Mismatch, format!(
                    "the valve stayed at {} % for 30 s where the segment asks {:.1} % (a limit or a safety override: `pto link … status`)",
                    applied.map_or("—".into(), |a| format!("{:.1}", a.to_f32())),
                    aperture.to_f32()
                ),
            );
        }
    }
    // 5. The cylinders energised and the log started together: the chambers start from LP
    //    (de-energised, they vent to it), as the fit's simulation of the log starts them. The
    //    operator starts the lever; it must show the planned motion within the grace time.
    client::set_duty(feed.link, mask, config)?;
    op.say(&format!(
        "  logging {}: start the lever now — {}",
        log_path.display(),
        match planned.period_s {
            Some(p) => format!("±{:.1}° of shaft every {p:.2} s", planned.amplitude_deg),
            None => "held still".into(),
        }
    ));
    let window = planned.period_s.map_or(3.0, |p| 2.5 * p);
    let grace = planned.period_s.map_or(3.0, |p| (4.0 * p).max(20.0));
    feed.restart_counts();
    let mut writer = LogWriter::create(log_path)?;
    let (mut t_log, mut a_log) = (Vec::new(), Vec::new());
    let (mut frames, mut dump, mut faults) = (0u64, false, 0u8);
    let mut t0 = None;
    let mut seen_from = None;
    let mut silent = Instant::now();
    let mut last_print = Instant::now();
    let mut lost_link = None;
    loop {
        if op.stopped() {
            break;
        }
        let s = match feed.next() {
            Ok(Some(s)) => s,
            Ok(None) => {
                if feed.restarted {
                    break;
                }
                if silent.elapsed() > Duration::from_secs(5) {
                    lost_link = Some("no telemetry for 5 s".to_string());
                    break;
                }
                continue;
            }
            Err(e) => {
                lost_link = Some(e.to_string());
                break;
            }
        };
        silent = Instant::now();
        if feed.restarted {
            break;
        }
        if t0.is_none() && s.raw.on_duty != mask {
            // Frames from before the cylinders were energised.
            continue;
        }
        let t0 = *t0.get_or_insert(s.t_s);
        if s.t_s - t0 > seg.run.duration_s + 1e-9 {
            break;
        }
        frames += 1;
        dump |= s.raw.dump;
        faults |= s.raw.sensor_faults;
        t_log.push(s.t_s);
        a_log.push(s.shaft_angle_deg);
        writer.row(&s)?;
        if seen_from.is_none() && s.t_s - t0 >= window {
            if planned
                .differs(&SeenMotion::since(&t_log, &a_log, s.t_s - window))
                .is_none()
            {
                seen_from = Some(s.t_s - t0);
                op.say(&format!("  the lever as planned from {:.1} s", s.t_s - t0));
            } else if s.t_s - t0 > grace {
                break;
            }
        }
        if last_print.elapsed() > Duration::from_secs(5) {
            last_print = Instant::now();
            let seen = SeenMotion::since(&t_log, &a_log, s.t_s - window);
            op.say(&format!(
                "  {:.0} of {:.0} s: lever ±{:.1}° {}, HP {}, valve {:.1} %{}{}",
                s.t_s - t0,
                seg.run.duration_s,
                seen.amplitude_deg,
                seen.period_s
                    .map_or("no period yet".into(), |p| format!("every {p:.2} s")),
                s.hp_bar.map_or("—".into(), |p| format!("{p:.1} bar")),
                s.raw.applied.to_f32(),
                if s.raw.dump { " DUMP" } else { "" },
                held_faults(s.raw.sensor_faults)
            ));
        }
    }
    let reached = t0.is_some_and(|t0| {
        t_log
            .last()
            .is_some_and(|t| t - t0 >= seg.run.duration_s - 2.0 / seg.rate_hz)
    });
    outcome.rows = writer.rows;
    outcome.lost = feed.lost;
    let skipped = writer.skipped;
    writer.finish()?;
    let restarted = feed.restarted;
    let link = feed.link;
    if lost_link.is_some() || op.stopped() {
        outcome.note = lost_link.unwrap_or_else(|| "interrupted".into());
        let _ = safe(link, config);
        return Ok(outcome);
    }
    let mut why = Vec::new();
    safe(link, config)?;
    let trips = client::status(link)?.trips.wrapping_sub(trips_before);
    // The motion over the log from the first window that showed it (the operator's start of
    // the rack drive left out); over all of it when none did.
    let from = t_log.first().map_or(0.0, |t0| {
        t0 + seen_from.map_or(0.0, |s: f64| (s - window).max(0.0))
    });
    let seen = SeenMotion::since(&t_log, &a_log, from);
    outcome.motion = Some(seen);
    if seen_from.is_none() && planned.period_s.is_some() {
        why.push(format!(
            "the lever did not show the planned motion within {grace:.0} s"
        ));
    }
    if restarted {
        why.push("the controller restarted".to_string());
    }
    if !reached && !restarted {
        why.push("the log ended early".into());
    }
    if let Some(d) = planned.differs(&seen) {
        why.push(d);
    }
    if let Some(d) = moving_at_start(&t_log, &a_log) {
        why.push(d);
    }
    let due = frames + outcome.lost;
    if outcome.lost as f64 > LOST_LIMIT * due as f64 {
        why.push(format!("{} of {due} frames lost", outcome.lost));
    }
    if skipped > 0 {
        why.push(format!("{skipped} frames without a pressure reading"));
    }
    if trips > 0 || dump {
        why.push(format!(
            "the overpressure trip latched ({trips}×) or the dump valve opened"
        ));
    }
    if faults != 0 {
        why.push(format!(
            "sensors held faulted: {}",
            pto_firmware::sensor_faults::names(faults)
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }
    if why.is_empty() {
        outcome.status = Status::Complete;
        if outcome.lost > 0 {
            outcome.note = format!(
                "{} frames lost (within {:.0} %)",
                outcome.lost,
                LOST_LIMIT * 100.0
            );
        }
    } else {
        outcome.status = Status::Mismatch;
        outcome.note = why.join("; ");
    }
    Ok(outcome)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sine(amp: f64, period: f64, phase: f64, secs: f64, hz: f64) -> (Vec<f64>, Vec<f64>) {
        (0..(secs * hz) as usize)
            .map(|i| {
                let t = i as f64 / hz;
                (t, amp * (std::f64::consts::TAU * t / period + phase).sin())
            })
            .unzip()
    }

    /// A log that begins with the lever moving is named; one that begins at rest (an
    /// encoder step of jitter) or is too short to tell is not.
    #[test]
    fn a_log_that_begins_with_the_lever_moving_is_refused() {
        // ±20° at 0.2 Hz from mid-stroke: 25°/s, at 64 Hz and at 256 Hz.
        for hz in [64.0, 256.0] {
            let (t, moving) = sine(20.0, 5.0, 0.1, 1.0, hz);
            let why = moving_at_start(&t, &moving).expect("moving at the start");
            assert!(why.contains("already moving"), "{why}");
        }
        // At rest for the first frame (an encoder step of jitter), then moving.
        let t: Vec<f64> = (0..5).map(|i| f64::from(i) / 64.0).collect();
        assert_eq!(moving_at_start(&t, &[0.0, 0.022, 0.5, 1.0, 1.5]), None);
        assert_eq!(moving_at_start(&t[..1], &[3.0]), None);
        assert_eq!(moving_at_start(&[], &[]), None);
    }

    /// A sine's amplitude and period are read back from any phase, with the encoder's steps;
    /// a held lever has no period; a motion 15 % off in either is named, 5 % off is not.
    #[test]
    fn the_lever_motion_is_read_and_judged_against_its_plan() {
        let planned = PlannedMotion {
            amplitude_deg: 24.0,
            period_s: Some(5.0),
        };
        for phase in [0.0, 1.0, 2.5] {
            let (t, a) = sine(24.0, 5.0, phase, 12.5, 64.0);
            // The encoder's 16 384 counts a revolution.
            let step = 360.0 / 16_384.0;
            let a: Vec<f64> = a.iter().map(|x| (x / step).round() * step).collect();
            let m = SeenMotion::of(&t, &a);
            println!(
                "phase {phase}: ±{:.3}° every {:?} s",
                m.amplitude_deg, m.period_s
            );
            assert!((m.amplitude_deg - 24.0).abs() < 0.05);
            assert!((m.period_s.unwrap() - 5.0).abs() < 0.05);
            assert_eq!(planned.differs(&m), None);
        }
        let judge = |amp: f64, period: f64| {
            let (t, a) = sine(amp, period, 0.3, 15.0, 64.0);
            planned.differs(&SeenMotion::of(&t, &a))
        };
        assert_eq!(judge(25.2, 5.25), None);
        assert!(judge(27.6, 5.0).unwrap().contains("amplitude"));
        assert!(judge(24.0, 5.75).unwrap().contains("period"));
        let held = SeenMotion::of(&[0.0, 1.0, 2.0], &[3.0, 3.0, 3.1]);
        // A lever that stops for 8 s after two periods: the mean period holds, the gap does not.
        let (mut t, mut a) = sine(24.0, 5.0, 0.3, 10.0, 64.0);
        let last = *a.last().unwrap();
        for i in 0..(8.0 * 64.0) as usize {
            t.push(10.0 + i as f64 / 64.0);
            a.push(last);
        }
        assert!(
            planned
                .differs(&SeenMotion::of(&t, &a))
                .unwrap()
                .contains("stopped")
        );
        assert_eq!(held.period_s, None);
        assert!(planned.differs(&held).is_some());
        let at_rest = PlannedMotion {
            amplitude_deg: 0.0,
            period_s: None,
        };
        assert_eq!(at_rest.differs(&held), None);
        let (t, a) = sine(2.0, 5.0, 0.0, 10.0, 64.0);
        assert!(at_rest.differs(&SeenMotion::of(&t, &a)).is_some());
    }
}
