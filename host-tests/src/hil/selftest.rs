//! `pto link selftest`: a guided bring-up of a freshly flashed controller.
//!
//! The firmware reports each input's raw value and its own verdict on it; the host checks what
//! those say (loop currents in their window, the ADC reference, the clock, the brown-out level,
//! the controller sampling), then, with the operator, what only motion shows (the shaft encoder
//! counting both ways while the lever is moved by hand, the motor pickup while the motor's
//! shaft is turned). Then, in the firmware's self-test (from its safe state only, the trip
//! armed throughout), it steps each output one at a time from the de-energised state — the
//! valve to a few % with the dump valve open, the dump valve closed with the valve closed, each
//! solenoid — and compares what the hardware reads back with what was commanded. Every check
//! ends pass, fail, skipped (by the operator) or n/a (what this board cannot show, e.g. the
//! QEMU twin's clock); the run passes only when none failed or was skipped.

use crate::hil::link::{Link, LinkError};
use pto_model::fx::Aperture;
use pto_model::protocol::selftest::{
    InputReport, LoopReport, LoopState, OutputReport, SELFTEST_VALVE_MAX_PCT, SelfTest,
    SelfTestReply, TestDrive,
};
use pto_model::protocol::{BrownOut, ClockSource, FromFirmware, Refusal, ToFirmware};
use serde::Serialize;
use std::time::{Duration, Instant};

/// The shaft encoder must move at least this far each way, counts
/// (≈ 1.1° at 16 384 counts per turn: a hand on the lever does it in a moment, a count that
/// jitters on a dead channel does not).
pub const ENCODER_SPAN_COUNTS: i32 = 50;
/// The motor pickup must read at least this, rpm (a shaft turned by hand).
pub const MOTOR_MIN_RPM: f32 = 5.0;
/// The ADC reference must be within this of the loops' nominal 3.3 V, %.
pub const SUPPLY_TOLERANCE_PCT: f32 = 5.0;
/// How close the valve's read-back duty must be to the one commanded, % of aperture.
pub const VALVE_READBACK_PCT: f32 = 0.1;

/// A check's outcome.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// It held.
    Pass,
    /// It did not.
    Fail,
    /// The operator skipped it (`--skip`): not a pass.
    Skipped,
    /// This board cannot show it (the QEMU twin's clock, brown-out level, supply).
    NotApplicable,
    /// A fact worth reading, not a check (the last reset's cause).
    Info,
}

impl std::fmt::Display for Outcome {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Outcome::Pass => "pass",
            Outcome::Fail => "FAIL",
            Outcome::Skipped => "skipped",
            Outcome::NotApplicable => "n/a",
            Outcome::Info => "info",
        })
    }
}

/// One line of the checklist.
#[derive(Debug, Clone, Serialize)]
pub struct Check {
    /// What was checked.
    pub name: String,
    /// How it ended.
    pub outcome: Outcome,
    /// What was measured.
    pub measured: String,
    /// What passes.
    pub expected: String,
}

/// The whole run.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Every check, in order.
    pub checks: Vec<Check>,
    /// None failed or was skipped.
    pub passed: bool,
    /// Stopped by the operator (Ctrl-C) before the end; the outputs were returned first.
    pub interrupted: bool,
}

/// The checks the operator may skip.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Skippable {
    /// The shaft encoder (moving the lever by hand).
    Encoder,
    /// The motor pickup (turning the motor's shaft by hand).
    Motor,
    /// Every output step.
    Outputs,
}

/// How the run goes.
#[derive(Debug, Clone)]
pub struct Options {
    /// How long the operator has for each motion, and how long each output is held.
    pub window: Duration,
    /// How long each output is held for the operator to see or hear it.
    pub hold: Duration,
    /// The valve's test aperture, % (≤ the firmware's self-test maximum).
    pub valve_pct: f32,
    /// Checks skipped.
    pub skip: Vec<Skippable>,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            window: Duration::from_secs(20),
            hold: Duration::from_secs(2),
            valve_pct: 5.0,
            skip: Vec::new(),
        }
    }
}

/// The person at the bench.
pub trait Operator {
    /// Tells them what to do now.
    fn say(&mut self, what: &str);
    /// Asks whether they saw or heard something; `None`: not asked (an unattended run).
    fn confirm(&mut self, question: &str) -> Option<bool>;
    /// Whether they asked to stop (Ctrl-C).
    fn stopped(&self) -> bool {
        false
    }
}

/// An unattended run (`--yes`): instructions go to stderr, nothing is asked.
pub struct Unattended;

impl Operator for Unattended {
    fn say(&mut self, what: &str) {
        eprintln!("{what}");
    }
    fn confirm(&mut self, _: &str) -> Option<bool> {
        None
    }
    fn stopped(&self) -> bool {
        crate::output::stop_requested()
    }
}

/// An operator at a terminal: instructions and questions on stderr, answers from stdin.
pub struct AtTerminal;

impl Operator for AtTerminal {
    fn say(&mut self, what: &str) {
        eprintln!("{what}");
    }
    fn confirm(&mut self, question: &str) -> Option<bool> {
        loop {
            eprint!("{question} [y/n] ");
            let mut line = String::new();
            if std::io::stdin().read_line(&mut line).ok()? == 0 {
                return None;
            }
            match line.trim() {
                "y" | "Y" | "yes" => return Some(true),
                "n" | "N" | "no" => return Some(false),
                _ => {}
            }
        }
    }
    fn stopped(&self) -> bool {
        crate::output::stop_requested()
    }
}

/// Why the self-test could not run.
#[derive(Debug, thiserror::Error)]
pub enum SelfTestError {
    /// The link failed.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// An option out of range.
    #[error("--valve {0}: outside (0, {SELFTEST_VALVE_MAX_PCT}] %")]
    Valve(f32),
}

fn ask(link: &mut Link, req: SelfTest) -> Result<Result<SelfTestReply, Refusal>, LinkError> {
    link.request(&ToFirmware::SelfTest(req), |r| match r {
        FromFirmware::SelfTest(s) => Some(Ok(*s)),
        FromFirmware::Refused(why) => Some(Err(*why)),
        _ => None,
    })
}

fn inputs(link: &mut Link) -> Result<InputReport, LinkError> {
    match ask(link, SelfTest::Inputs)? {
        Ok(SelfTestReply::Inputs(r)) => Ok(r),
        Ok(other) => Err(LinkError::Unexpected {
            sent: Box::new(ToFirmware::SelfTest(SelfTest::Inputs)),
            got: Box::new(FromFirmware::SelfTest(other)),
        }),
        Err(why) => Err(LinkError::Refused(why)),
    }
}

fn check(name: &str, outcome: Outcome, measured: String, expected: &str) -> Check {
    Check {
        name: name.into(),
        outcome,
        measured,
        expected: expected.into(),
    }
}

fn loop_check(name: &str, l: &LoopReport) -> Check {
    let ma = f64::from(l.current_ua) / 1000.0;
    let (outcome, what) = match l.state {
        LoopState::InWindow => (Outcome::Pass, format!("{ma:.2} mA")),
        LoopState::Open => (
            Outcome::Fail,
            format!("{ma:.2} mA: open loop (a broken wire, an unpowered transducer)"),
        ),
        LoopState::Short => (Outcome::Fail, format!("{ma:.2} mA: a short")),
        LoopState::Saturated => (
            Outcome::Fail,
            "the ADC saturates: a short, or the supply too low for the loop".into(),
        ),
        LoopState::SupplyFault => (
            Outcome::Fail,
            "the ADC reference measures implausibly: no reading can be trusted".into(),
        ),
    };
    check(
        name,
        outcome,
        format!("{what} (ADC {})", l.adc),
        "3.6–21 mA (4–20 mA loop)",
    )
}

/// The checks on what the inputs report by themselves.
pub fn input_checks(first: &InputReport, later: &InputReport) -> Vec<Check> {
    let mut v = vec![
        check(
            "controller sampling",
            if later.samples > first.samples {
                Outcome::Pass
            } else {
                Outcome::Fail
            },
            format!(
                "{} samples, {} more since the first look",
                later.samples,
                later.samples.wrapping_sub(first.samples)
            ),
            "the sample count moving",
        ),
        loop_check("HP transducer loop", &later.hp),
        loop_check("LP transducer loop", &later.lp),
    ];
    let nominal = 3300.0;
    v.push(match later.supply_mv {
        Some(mv) => {
            let dev = (f32::from(mv) - nominal) / nominal * 100.0;
            check(
                "ADC reference (VDDA)",
                if dev.abs() <= SUPPLY_TOLERANCE_PCT {
                    Outcome::Pass
                } else {
                    Outcome::Fail
                },
                format!("{mv} mV ({dev:+.1} %)"),
                "3.3 V ± 5 % (measured against VREFINT)",
            )
        }
        None => check(
            "ADC reference (VDDA)",
            Outcome::NotApplicable,
            "not measured by this board".into(),
            "3.3 V ± 5 %",
        ),
    });
    let b = later.board;
    v.push(check(
        "clock",
        match b.clock {
            ClockSource::Crystal { .. } | ClockSource::Internal => Outcome::Pass,
            ClockSource::InternalFallback { .. } => Outcome::Fail,
            ClockSource::Emulated => Outcome::NotApplicable,
        },
        b.clock.to_string(),
        "the configured crystal running (hse_mhz)",
    ));
    v.push(check(
        "brown-out reset level",
        match b.brownout {
            BrownOut::Level3 => Outcome::Pass,
            BrownOut::NotApplicable => Outcome::NotApplicable,
            _ => Outcome::Fail,
        },
        b.brownout.to_string(),
        "level 3 (≈ 2.8 V), set by the firmware at boot",
    ));
    v.push(check("last reset", Outcome::Info, b.reset.to_string(), "-"));
    v
}

/// Watches the inputs for `window` until `seen` says the motion is there; returns whether it
/// was and the last report.
fn watch(
    link: &mut Link,
    op: &dyn Operator,
    window: Duration,
    mut seen: impl FnMut(&InputReport) -> bool,
) -> Result<(bool, InputReport), LinkError> {
    let t0 = Instant::now();
    loop {
        let r = inputs(link)?;
        if seen(&r) {
            return Ok((true, r));
        }
        if t0.elapsed() >= window || op.stopped() {
            return Ok((false, r));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn drive(link: &mut Link, d: TestDrive) -> Result<Result<OutputReport, Refusal>, LinkError> {
    Ok(match ask(link, SelfTest::Drive(d))? {
        Ok(SelfTestReply::Driven(r)) => Ok(r),
        Ok(other) => {
            return Err(LinkError::Unexpected {
                sent: Box::new(ToFirmware::SelfTest(SelfTest::Drive(d))),
                got: Box::new(FromFirmware::SelfTest(other)),
            });
        }
        Err(why) => Err(why),
    })
}

/// What the read-back says of a drive: `None` when everything read back as commanded, else
/// what did not.
pub fn readback_mismatch(r: &OutputReport) -> Option<String> {
    let mut wrong = Vec::new();
    match r.valve_readback {
        Some(v) if (v.to_f32() - r.valve.to_f32()).abs() > VALVE_READBACK_PCT => {
            wrong.push(format!(
                "valve reads {:.2} %, commanded {:.2} %",
                v.to_f32(),
                r.valve.to_f32()
            ))
        }
        None => wrong.push("valve not readable".into()),
        _ => {}
    }
    match r.dump_readback {
        Some(energised) if energised == r.dump_open => wrong.push(format!(
            "dump valve's driver reads {}, commanded {}",
            if energised {
                "on (closed)"
            } else {
                "off (open)"
            },
            if r.dump_open {
                "off (open)"
            } else {
                "on (closed)"
            }
        )),
        None => wrong.push("dump valve not readable".into()),
        _ => {}
    }
    match r.solenoids_readback {
        Some(s) if s != r.solenoids => wrong.push(format!(
            "solenoids read {s:04b}, commanded {:04b} (bit 0 = HC3.1)",
            r.solenoids
        )),
        None => wrong.push("solenoids not readable".into()),
        _ => {}
    }
    (!wrong.is_empty()).then(|| wrong.join("; "))
}

/// The output steps: each drive, its read-back, the operator's word when asked, back to all
/// off.
fn output_checks(
    link: &mut Link,
    opts: &Options,
    op: &mut dyn Operator,
) -> Result<Vec<Check>, LinkError> {
    let valve = Aperture::from_num(opts.valve_pct);
    let steps: Vec<(String, TestDrive, String)> = [
        (
            format!("valve to {} % (dump open)", opts.valve_pct),
            TestDrive::Valve(valve),
            "Did the valve open a little (spool moves, oil to tank)?".to_string(),
        ),
        (
            "dump valve closed (valve closed)".into(),
            TestDrive::DumpClosed,
            "Did the dump valve close (its coil clicks)?".into(),
        ),
    ]
    .into_iter()
    .chain((0..4u8).map(|n| {
        (
            format!("solenoid HC3.{}", n + 1),
            TestDrive::Solenoid(n),
            format!("Did HC3.{}'s solenoid switch?", n + 1),
        )
    }))
    .collect();
    let mut v = Vec::new();
    for (name, d, question) in steps {
        if op.stopped() {
            break;
        }
        op.say(&format!("output: {name}"));
        let r = match drive(link, d)? {
            Ok(r) => r,
            Err(why) => {
                v.push(check(
                    &name,
                    Outcome::Fail,
                    format!("refused: {why}"),
                    "driven",
                ));
                break;
            }
        };
        std::thread::sleep(opts.hold);
        let seen = op.confirm(&question);
        let back = drive(link, TestDrive::AllOff)?;
        // Off for a moment too: each step is a separate click for the operator.
        std::thread::sleep(opts.hold / 2);
        let off_ok = match &back {
            Ok(b) => readback_mismatch(b).map(|m| format!("back to all off: {m}")),
            Err(why) => Some(format!("back to all off refused: {why}")),
        };
        let mismatch = readback_mismatch(&r);
        let measured = format!(
            "read back: valve {}, dump driver {}, solenoids {}{}",
            r.valve_readback
                .map_or("-".into(), |a| format!("{:.2} %", a.to_f32())),
            r.dump_readback
                .map_or("-", |e| if e { "on (closed)" } else { "off (open)" }),
            r.solenoids_readback
                .map_or("-".into(), |s| format!("{s:04b}")),
            match seen {
                Some(true) => "; seen by the operator",
                Some(false) => "; NOT seen by the operator",
                None => "",
            }
        );
        let outcome = if mismatch.is_none() && off_ok.is_none() && seen != Some(false) {
            Outcome::Pass
        } else {
            Outcome::Fail
        };
        let measured = match (mismatch, off_ok) {
            (None, None) => measured,
            (a, b) => format!(
                "{measured}; {}",
                [a, b].into_iter().flatten().collect::<Vec<_>>().join("; ")
            ),
        };
        v.push(check(&name, outcome, measured, "read back as commanded"));
    }
    Ok(v)
}

/// Runs the self-test on a connected link.
pub fn run(
    link: &mut Link,
    opts: &Options,
    op: &mut dyn Operator,
) -> Result<Report, SelfTestError> {
    let max = f32::from(SELFTEST_VALVE_MAX_PCT);
    if !(opts.valve_pct > 0.0 && opts.valve_pct <= max) {
        return Err(SelfTestError::Valve(opts.valve_pct));
    }
    let first = inputs(link)?;
    std::thread::sleep(Duration::from_millis(200));
    let later = inputs(link)?;
    let mut checks = input_checks(&first, &later);
    let skipped = |s: Skippable| opts.skip.contains(&s);

    // The lever: both ways from where it is.
    if skipped(Skippable::Encoder) {
        checks.push(check(
            "shaft encoder",
            Outcome::Skipped,
            "-".into(),
            "counts both ways",
        ));
    } else {
        op.say(&format!(
            "Move the lever by hand back and forth ({} s)…",
            opts.window.as_secs()
        ));
        // Both ways: a rise of ≥ 50 counts above the lowest count so far, and a fall of ≥ 50
        // below the highest (wherever the lever started, even at an end stop).
        let start = later.encoder;
        let (mut lo, mut hi, mut rise, mut fall) = (0i32, 0i32, 0i32, 0i32);
        let (ok, _) = watch(link, &*op, opts.window, |r| {
            let d = r.encoder.wrapping_sub(start);
            lo = lo.min(d);
            hi = hi.max(d);
            rise = rise.max(d - lo);
            fall = fall.max(hi - d);
            rise >= ENCODER_SPAN_COUNTS && fall >= ENCODER_SPAN_COUNTS
        })?;
        checks.push(check(
            "shaft encoder",
            if ok { Outcome::Pass } else { Outcome::Fail },
            format!("rose {rise}, fell {fall} counts (range {lo:+} … {hi:+} from {start})"),
            "≥ 50 counts each way",
        ));
    }
    if skipped(Skippable::Motor) {
        checks.push(check(
            "motor pickup",
            Outcome::Skipped,
            "-".into(),
            "a speed reading",
        ));
    } else {
        op.say(&format!(
            "Turn the motor's shaft by hand ({} s)…",
            opts.window.as_secs()
        ));
        let mut top = 0f32;
        let (ok, _) = watch(link, &*op, opts.window, |r| {
            let rpm = r.motor.map_or(0.0, |m| m.to_f32());
            top = top.max(rpm);
            rpm >= MOTOR_MIN_RPM
        })?;
        checks.push(check(
            "motor pickup",
            if ok { Outcome::Pass } else { Outcome::Fail },
            format!("up to {top:.1} rpm"),
            "≥ 5 rpm while turned",
        ));
    }

    if skipped(Skippable::Outputs) {
        checks.push(check(
            "outputs",
            Outcome::Skipped,
            "-".into(),
            "each read back",
        ));
    } else if !op.stopped() {
        match ask(link, SelfTest::Begin)? {
            Ok(_) => {
                op.say("self-test: every output de-energised (valve closed, dump valve open)");
                let steps = output_checks(link, opts, op);
                // Whatever happened, the outputs go back to the controller.
                let ended = ask(link, SelfTest::End);
                checks.extend(steps?);
                if let Err(why) = ended? {
                    checks.push(check(
                        "self-test end",
                        Outcome::Fail,
                        format!(
                            "{why} (it ended by itself: a trip, a command or the idle timeout)"
                        ),
                        "ended by the host",
                    ));
                }
            }
            Err(why) => checks.push(check(
                "outputs",
                Outcome::Fail,
                format!("not run: {why}"),
                "the self-test entered",
            )),
        }
    }
    let interrupted = op.stopped();
    let passed = !interrupted
        && checks
            .iter()
            .all(|c| !matches!(c.outcome, Outcome::Fail | Outcome::Skipped));
    Ok(Report {
        checks,
        passed,
        interrupted,
    })
}

/// The checklist as a table.
pub fn table(r: &Report) -> String {
    let w = r
        .checks
        .iter()
        .map(|c| c.name.chars().count())
        .max()
        .unwrap_or(5)
        .max(5);
    let mut s = format!(
        "{:<w$}  {:<7}  {}\n",
        "check", "result", "measured (expected)"
    );
    for c in &r.checks {
        s += &format!(
            "{:<w$}  {:<7}  {} ({})\n",
            c.name,
            c.outcome.to_string(),
            c.measured,
            c.expected
        );
    }
    let failed: Vec<&str> = r
        .checks
        .iter()
        .filter(|c| matches!(c.outcome, Outcome::Fail | Outcome::Skipped))
        .map(|c| c.name.as_str())
        .collect();
    s += &if r.interrupted {
        "self-test interrupted: NOT complete (the outputs were returned to the controller)\n"
            .to_string()
    } else if r.passed {
        "self-test passed: every check held\n".to_string()
    } else {
        format!("self-test FAILED: {}\n", failed.join(", "))
    };
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use pto_model::protocol::selftest::InputReport;
    use pto_model::protocol::{BoardInfo, BrownOut, ClockSource, ResetCause};

    fn report(samples: u32) -> InputReport {
        let l = LoopReport {
            adc: 2400,
            current_ua: 12_000,
            state: LoopState::InWindow,
        };
        InputReport {
            tick: samples,
            samples,
            hp: l,
            lp: l,
            supply_mv: Some(3310),
            encoder: 0,
            motor: None,
            active: false,
            board: BoardInfo {
                clock: ClockSource::Crystal { mhz: 8 },
                reset: ResetCause::PowerOn,
                brownout: BrownOut::Level3,
            },
        }
    }

    #[test]
    fn each_input_verdict_becomes_a_named_check() {
        let ok = input_checks(&report(10), &report(20));
        assert!(
            ok.iter()
                .all(|c| matches!(c.outcome, Outcome::Pass | Outcome::Info)),
            "{ok:?}"
        );
        let mut bad = report(10);
        bad.hp.state = LoopState::Open;
        bad.lp.state = LoopState::Saturated;
        bad.supply_mv = Some(3000);
        bad.board.clock = ClockSource::InternalFallback { mhz: 8 };
        bad.board.brownout = BrownOut::Off;
        let v = input_checks(&report(10), &bad);
        let failed: Vec<&str> = v
            .iter()
            .filter(|c| c.outcome == Outcome::Fail)
            .map(|c| c.name.as_str())
            .collect();
        assert_eq!(
            failed,
            [
                "controller sampling",
                "HP transducer loop",
                "LP transducer loop",
                "ADC reference (VDDA)",
                "clock",
                "brown-out reset level"
            ]
        );
        assert!(v[1].measured.contains("open loop"), "{:?}", v[1]);
        let mut twin = report(20);
        twin.board = BoardInfo::EMULATED;
        twin.supply_mv = None;
        let v = input_checks(&report(10), &twin);
        let na = v
            .iter()
            .filter(|c| c.outcome == Outcome::NotApplicable)
            .count();
        assert_eq!(na, 3, "{v:?}");
    }

    #[test]
    fn a_readback_that_differs_from_the_command_is_named() {
        let r = OutputReport {
            drive: TestDrive::Solenoid(1),
            valve: Aperture::ZERO,
            dump_open: true,
            solenoids: 0b0010,
            valve_readback: Some(Aperture::ZERO),
            dump_readback: Some(false),
            solenoids_readback: Some(0b0010),
        };
        assert_eq!(readback_mismatch(&r), None);
        let bad = OutputReport {
            solenoids_readback: Some(0),
            dump_readback: Some(true),
            ..r
        };
        let m = readback_mismatch(&bad).unwrap();
        assert!(m.contains("solenoids read 0000, commanded 0010"), "{m}");
        assert!(m.contains("dump valve's driver reads on (closed)"), "{m}");
    }
}
