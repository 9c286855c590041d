//! `pto link`: the bench engineer's tool, over a serial port to the controller or the QEMU
//! twin's pseudo-terminal.

use super::finite_in;
use anyhow::{Context, Result, bail};
use pto_host::hil::client::{self, LogWriter, Units};
use pto_host::hil::link::{self, Link};
use pto_model::ModelConfig;
use pto_model::protocol::{FromFirmware, Hello, Stored, config_fingerprint};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// `pto link`'s options.
#[derive(clap::Args)]
pub(crate) struct LinkArgs {
    /// Serial port of the controller (`/dev/ttyUSB0`, `COM3`), the QEMU twin's
    /// pseudo-terminal, or `unix:PATH` for a QEMU USART's socket.
    #[arg(long)]
    pub port: String,
    /// Baud rate (the firmware's: 230400 8N1).
    #[arg(long, default_value_t = pto_host::hil::link::DEFAULT_BAUD)]
    pub baud: u32,
    /// Machine-readable output.
    #[arg(long, global = true)]
    pub json: bool,
    #[command(subcommand)]
    pub cmd: LinkCmd,
}

#[derive(clap::Subcommand)]
pub(crate) enum LinkCmd {
    /// Firmware version, running configuration, link and health counters.
    Status,
    /// Scheduler mode: `fixed PCT`, `hold-pressure BAR`, `hold-speed RPM`, `max-autonomy RPM`.
    Mode {
        /// fixed, hold-pressure, hold-speed or max-autonomy.
        kind: String,
        /// Aperture %, P2 bar, or motor speed rpm.
        #[arg(allow_negative_numbers = true)]
        value: f64,
    },
    /// Cylinders on duty and geometry.
    Duty {
        /// HC3.1..HC3.4 as four 0/1 characters, e.g. 1001.
        #[arg(long)]
        on: String,
        /// Geometry 1..=4.
        #[arg(long, default_value_t = 1)]
        config: u8,
    },
    /// Restart the estimator from known pressures (refused while the overpressure trip holds).
    Reset {
        /// P2, bar.
        #[arg(long, allow_negative_numbers = true)]
        p2: f64,
        /// LP, bar.
        #[arg(long, allow_negative_numbers = true)]
        lp: f64,
    },
    /// The model configuration: upload (from `pto fit`'s *.model.toml or a bench file), show,
    /// clear the stored one.
    Config {
        #[command(subcommand)]
        cmd: ConfigCmd,
    },
    /// Live view of the estimates, command, faults and counters; `--log` writes the bench log
    /// `pto fit` reads (the sensors as the firmware saw them), the estimates in extra columns.
    Monitor {
        /// Bench log CSV to write (written as FILE.part, renamed when the monitor stops).
        #[arg(long)]
        log: Option<PathBuf>,
        /// Telemetry rate, Hz, up to 1024 (default 64, set at every start: a rate an earlier
        /// monitor set does not stay; the bench firmware goes no faster than 128 and says so).
        #[arg(long)]
        rate: Option<f64>,
        /// Stop after this much firmware time, s (default: at Ctrl-C).
        #[arg(long)]
        duration: Option<f64>,
    },
    /// Release the sensors the controller holds faulted (its residuals named them: the valve
    /// went to its sensor-fault aperture), each only if its reading agrees with the model now.
    ClearFaults,
    /// Guided bring-up of a freshly flashed controller: each input's reading and verdict
    /// (loop currents, ADC reference, clock, brown-out level), the encoder and the motor
    /// pickup while you move them by hand, then each output one at a time from the safe
    /// state (valve to a few % with the dump valve open, the dump valve closed, each
    /// solenoid), read back. A pass/fail checklist; `--json`.
    #[command(
        after_help = "Examples:\n  pto link --port /dev/ttyUSB0 selftest\n  pto link --port /dev/ttyUSB0 selftest --skip motor\n  pto link --port /dev/pts/3 selftest --yes --window 10 --json\n\nThe outputs are stepped only from the firmware's safe state (trip armed, mode fixed 0 %, valve\nclosed); the trip stays armed throughout and ends the self-test if it latches.\n\nExit status:\n  0 every check passed (n/a: what this board cannot show)\n  1 a check failed or was skipped\n  2 bad input, no answer, or a protocol mismatch\n  130 interrupted (the outputs are returned to the controller first)"
    )]
    Selftest {
        /// Unattended: no questions (instructions on stderr; motions must happen within
        /// each window). Needed when stdin is not a terminal.
        #[arg(long)]
        yes: bool,
        /// Seconds for each motion by hand (the lever, the motor's shaft).
        #[arg(long, default_value_t = 20.0)]
        window: f64,
        /// Seconds each output is held for you to see or hear it.
        #[arg(long, default_value_t = 2.0)]
        hold: f64,
        /// The valve's test aperture, % (at most 10).
        #[arg(long, default_value_t = 5.0)]
        valve: f32,
        /// Checks to skip (each is reported as skipped, and the run does not pass).
        #[arg(long, value_enum, value_delimiter = ',')]
        skip: Vec<pto_host::hil::selftest::Skippable>,
    },
    /// A planned campaign (`pto plan`): each segment's cylinders, mode and log, the lever set
    /// by the operator.
    Campaign {
        #[command(subcommand)]
        cmd: CampaignCmd,
    },
}

#[derive(clap::Subcommand)]
pub(crate) enum CampaignCmd {
    /// Runs the campaign's segments in order: the cylinders de-energised and the valve closed
    /// while you change the set-up and stop the lever; the estimator restarted from the
    /// readings; HP let down to the segment's start through the valve (mode hold-pressure; HP
    /// below it is named and the segment skipped); the segment's aperture reached; then the
    /// cylinders energised and the log started together while you start the lever, which must
    /// show the planned motion (amplitude and period within 10 %) within max(4 periods, 20 s).
    /// One bench log per segment (the monitor's, at the segment's rate, its planned length)
    /// with a sidecar saying how it came out: complete, unfinished or mismatch (motion off,
    /// frames lost, a trip, a restart, a sensor held faulted, the start not reached). Running
    /// it again skips the complete segments. `pto fit DIR/*.csv` takes the folder as it is.
    #[command(
        after_help = "Examples:\n  pto plan --params trapped_air,cd,precharge,leakage --out day.toml\n  pto link --port /dev/ttyUSB0 campaign run day.toml --log-dir day\n  pto fit day/*.csv --params trapped_air,cd,precharge,leakage --out day-fit\n\nCtrl-C keeps the finished segments' logs, marks the one under way unfinished and leaves the\ncontroller in its safe state (cylinders de-energised, valve closed); running the command again\nresumes at the first segment not complete. Under the twin: `pto twin --campaign day.toml`.\n\nExit status:\n  0 every segment complete\n  1 a segment marked mismatch or unfinished (named)\n  2 bad input, no answer, or a protocol mismatch\n  130 interrupted"
    )]
    Run {
        /// The campaign file (`pto plan --out`).
        file: PathBuf,
        /// Folder of the segments' logs and sidecars (made if missing).
        #[arg(long)]
        log_dir: PathBuf,
        /// The bench file the campaign was planned for (its geometry gives the lever angles
        /// the encoder must show; default: the reference bench).
        #[arg(long)]
        bench: Option<PathBuf>,
        /// Unattended: no questions (instructions on stderr, a mismatched segment is not
        /// rerun). Needed when stdin is not a terminal.
        #[arg(long)]
        yes: bool,
        /// Wall-clock seconds to wait, per segment, for HP to come down to the segment's
        /// start (the lever gets max(4 periods, 20 s) of the log to show its motion).
        #[arg(long, default_value_t = 300.0, value_parser = finite_in(1.0, 3600.0, "s"))]
        prepare_wait: f64,
    },
}

#[derive(clap::Subcommand)]
pub(crate) enum ConfigCmd {
    /// Send a configuration; the firmware checks it (every field's range) and, in the declared
    /// safe state (mode `fixed 0`, valve closed, trip armed, a valid HP reading), applies it
    /// (estimator restarted from its last P2, uncertain as at boot) and, with `--store`, keeps
    /// it in flash for the next boot.
    Upload {
        /// `pto fit`'s *.model.toml, or a bench file.
        file: PathBuf,
        /// Also store it for the next boot.
        #[arg(long)]
        store: bool,
    },
    /// Erase the stored configuration: the next boot runs the built-in one (the running one
    /// is unchanged). Needs the declared safe state, as `upload`.
    Clear,
    /// The configuration the controller runs, and where it came from.
    Show {
        /// Write it to this file (TOML) instead of printing it.
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

/// The monitor's telemetry rate unless `--rate` says otherwise, Hz.
const DEFAULT_RATE_HZ: f64 = 64.0;

/// The port and how to reach it.
pub(crate) struct Target<'a> {
    pub(crate) port: &'a str,
    pub(crate) baud: u32,
}

fn connect(t: &Target) -> Result<(Link, Hello)> {
    Ok(link::connect(t.port, t.baud, Duration::from_secs(3))?)
}

/// `pto link`: one of its commands on the port.
pub(crate) fn link(a: &LinkArgs) -> Result<bool> {
    let t = Target {
        port: &a.port,
        baud: a.baud,
    };
    let json = a.json;
    match &a.cmd {
        LinkCmd::Status => status_cmd(&t, json),
        LinkCmd::Mode { kind, value } => mode_cmd(&t, kind, *value),
        LinkCmd::Duty { on, config } => duty_cmd(&t, on, *config),
        LinkCmd::Reset { p2, lp } => reset_cmd(&t, *p2, *lp),
        LinkCmd::Config {
            cmd: ConfigCmd::Upload { file, store },
        } => config_upload_cmd(&t, file, *store, json),
        LinkCmd::Config {
            cmd: ConfigCmd::Show { out },
        } => config_show_cmd(&t, out.as_ref(), json),
        LinkCmd::Config {
            cmd: ConfigCmd::Clear,
        } => config_clear_cmd(&t),
        LinkCmd::Monitor {
            log,
            rate,
            duration,
        } => monitor_cmd(&t, log.as_ref(), *rate, *duration, json),
        LinkCmd::ClearFaults => clear_faults_cmd(&t, json),
        LinkCmd::Campaign {
            cmd:
                CampaignCmd::Run {
                    file,
                    log_dir,
                    bench,
                    yes,
                    prepare_wait,
                },
        } => campaign_run_cmd(&t, file, log_dir, bench.as_ref(), *yes, *prepare_wait, json),
        LinkCmd::Selftest {
            yes,
            window,
            hold,
            valve,
            skip,
        } => selftest_cmd(&t, *yes, *window, *hold, *valve, skip.clone(), json),
    }
}

pub(crate) fn status_cmd(t: &Target, json: bool) -> Result<bool> {
    let (mut l, h) = connect(t)?;
    let st = client::status(&mut l)?;
    let (info, _) = client::read_config(&mut l)?;
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "port": t.port,
                "firmware": format!("{}.{}", h.firmware >> 8, h.firmware & 0xff),
                "protocol": h.protocol,
                "dt_log2": h.dt_log2,
                "configuration": { "source": format!("{:?}", info.source),
                    "fingerprint": format!("{:08x}", info.fingerprint), "bytes": info.len },
                "status": st,
                "host_link": l.counts(),
            }))?
        );
    } else {
        println!(
            "{}: pto-firmware {}.{}, protocol v{}, model step 2^-{} s",
            t.port,
            h.firmware >> 8,
            h.firmware & 0xff,
            h.protocol,
            h.dt_log2
        );
        println!(
            "{:<28} {} (fingerprint {:08x})",
            "model configuration", info.source, info.fingerprint
        );
        print!("{}", pto_host::hil::qemu::status_table(&st, &l.counts()));
    }
    Ok(true)
}

pub(crate) fn mode_cmd(t: &Target, kind: &str, value: f64) -> Result<bool> {
    let mode = pto_host::validation::closed_loop::parse_mode(kind, value)?;
    let (mut l, _) = connect(t)?;
    client::set_mode(&mut l, mode)?;
    println!("mode {kind} {value} set");
    Ok(true)
}

pub(crate) fn duty_cmd(t: &Target, on: &str, config: u8) -> Result<bool> {
    let mask = match on.as_bytes() {
        [a, b, c, d] if on.bytes().all(|x| x == b'0' || x == b'1') => [a, b, c, d]
            .iter()
            .enumerate()
            .fold(0u8, |m, (i, x)| m | (u8::from(**x == b'1') << i)),
        _ => bail!("--on {on:?}: want four 0/1 characters for HC3.1..HC3.4, e.g. 1001"),
    };
    if mask == 0 {
        bail!("--on 0000: no cylinder on duty");
    }
    if !(1..=4).contains(&config) {
        bail!("--config {config}: want 1, 2, 3 or 4");
    }
    let (mut l, _) = connect(t)?;
    client::set_duty(&mut l, mask, config - 1)?;
    println!("on duty {on}, config {config}");
    Ok(true)
}

pub(crate) fn reset_cmd(t: &Target, p2: f64, lp: f64) -> Result<bool> {
    for (name, v, hi) in [("--p2", p2, 400.0), ("--lp", lp, 100.0)] {
        if !(v.is_finite() && (0.0..=hi).contains(&v)) {
            bail!("{name} {v}: outside [0, {hi}] bar");
        }
    }
    let (mut l, _) = connect(t)?;
    client::reset(&mut l, p2 as f32, lp as f32)?;
    println!("estimator restarted from P2 {p2} bar, LP {lp} bar");
    Ok(true)
}

/// A model configuration from `pto fit`'s `*.model.toml`, or converted from a bench file.
pub(crate) fn load_config(path: &Path) -> Result<ModelConfig> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let model_err = match toml::from_str::<ModelConfig>(&text) {
        Ok(cfg) => {
            cfg.coefficients()
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            return Ok(cfg);
        }
        Err(e) => e,
    };
    match pto_host::sim::bench::Bench::load(path) {
        Ok(b) => {
            let cfg = pto_host::validation::model_config(&b)?;
            cfg.coefficients()
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            Ok(cfg)
        }
        Err(bench_err) => bail!(
            "{} is neither a model configuration (`pto fit`'s *.model.toml: {}) nor a bench \
             file ({bench_err})",
            path.display(),
            model_err.message().trim()
        ),
    }
}

pub(crate) fn config_upload_cmd(t: &Target, file: &Path, store: bool, json: bool) -> Result<bool> {
    let cfg = load_config(file)?;
    let bytes = client::config_bytes(&cfg)?;
    let (mut l, _) = connect(t)?;
    let quiet = json || !std::io::stderr().is_terminal();
    let (info, stored) = client::upload(&mut l, &cfg, store, |n, total| {
        if !quiet {
            eprint!("\ruploading {n}/{total} bytes");
        }
    })?;
    if !quiet {
        eprintln!();
    }
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "file": file,
                "bytes": bytes.len(),
                "fingerprint": format!("{:08x}", config_fingerprint(&bytes)),
                "source": format!("{:?}", info.source),
                "stored": stored == Stored::Yes,
            }))?
        );
    } else {
        println!(
            "{}: {} bytes, fingerprint {:08x}; the firmware runs it ({})",
            file.display(),
            bytes.len(),
            info.fingerprint,
            info.source
        );
        println!(
            "the estimator restarted from its last P2, as uncertain as at boot until a valid HP \
             reading confirms it (or `pto link --port {} reset --p2 BAR --lp BAR`)",
            t.port
        );
    }
    Ok(true)
}

pub(crate) fn config_clear_cmd(t: &Target) -> Result<bool> {
    let (mut l, _) = connect(t)?;
    client::clear_store(&mut l)?;
    println!("stored configuration erased: the next boot runs the built-in one");
    Ok(true)
}

pub(crate) fn config_show_cmd(t: &Target, out: Option<&PathBuf>, json: bool) -> Result<bool> {
    let (mut l, _) = connect(t)?;
    let (info, cfg) = client::read_config(&mut l)?;
    let text = format!(
        "# Model configuration read from the controller on {}: {} (fingerprint {:08x}).\n{}",
        t.port,
        info.source,
        info.fingerprint,
        toml::to_string_pretty(&cfg)?
    );
    if let Some(p) = out {
        super::write_atomic(p, text.as_bytes())?;
    }
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "source": format!("{:?}", info.source),
                "fingerprint": format!("{:08x}", info.fingerprint),
                "configuration": cfg,
            }))?
        );
    } else if out.is_none() {
        print!("{text}");
    } else {
        println!(
            "{} ({}, fingerprint {:08x})",
            out.map_or(String::new(), |p| p.display().to_string()),
            info.source,
            info.fingerprint
        );
    }
    Ok(true)
}

pub(crate) fn monitor_cmd(
    t: &Target,
    log: Option<&PathBuf>,
    rate_hz: Option<f64>,
    duration_s: Option<f64>,
    json: bool,
) -> Result<bool> {
    if let Some(r) = rate_hz
        && !(r.is_finite() && r > 0.0 && r <= 1024.0)
    {
        bail!("--rate {r}: outside (0, 1024] Hz");
    }
    if let Some(d) = duration_s
        && !(d.is_finite() && d > 0.0)
    {
        bail!("--duration {d}: want a positive number of seconds");
    }
    let (mut l, h) = connect(t)?;
    let (_, cfg) = client::read_config(&mut l)?;
    let units = Units::new(h.dt_log2, &cfg);
    let steps_per_s = 2f64.powi(i32::from(h.dt_log2));
    {
        // Set at every start (64 Hz unless asked): a rate an earlier monitor set does not stay.
        let r = rate_hz.unwrap_or(DEFAULT_RATE_HZ);
        let asked = (steps_per_s / r).round().clamp(1.0, 65_535.0) as u16;
        let every = client::set_telemetry(&mut l, asked)?;
        eprintln!(
            "telemetry every {every} steps ({:.1} Hz){}",
            steps_per_s / f64::from(every),
            if every != asked {
                " — the fastest this controller's link carries"
            } else {
                ""
            }
        );
    }
    // Frames the firmware could not queue never get a sequence number: its own count, before
    // and after, shows them.
    let dropped_before = client::status(&mut l)?.telemetry_dropped;
    let mut writer = log.map(|p| LogWriter::create(p)).transpose()?;
    pto_host::output::stop_on_interrupt();
    eprintln!(
        "monitoring {}{} — Ctrl-C stops{}",
        t.port,
        log.map_or(String::new(), |p| format!(", logging to {}", p.display())),
        duration_s.map_or(String::new(), |d| format!(" (or {d} s of firmware time)"))
    );
    let tty = std::io::stderr().is_terminal();
    let before = l.counts();
    l.timeout = Duration::from_millis(500);
    let (mut first, mut frames, mut last_print) = (None::<f64>, 0u64, Instant::now());
    let mut last: Option<client::Sample> = None;
    let mut silent = Instant::now();
    let mut restarts = 0u32;
    let mut failure = None;
    while !pto_host::output::stop_requested() {
        let m = match l.recv() {
            Ok(m) => m,
            Err(link::LinkError::NoReply(_)) => {
                if silent.elapsed() > Duration::from_secs(5) {
                    eprintln!("no telemetry for 5 s (is the controller stepping?)");
                    silent = Instant::now();
                }
                continue;
            }
            // The log so far is kept (finished below), then the error is reported.
            Err(e) => {
                failure = Some(e);
                break;
            }
        };
        let tel = match m {
            FromFirmware::Telemetry(tel) => tel,
            FromFirmware::Hello(_) => {
                eprintln!("the controller restarted (its boot Hello arrived)");
                restarts += 1;
                continue;
            }
            _ => continue,
        };
        silent = Instant::now();
        let s = units.sample(&tel);
        if last.is_some_and(|p| s.t_s <= p.t_s) {
            // Time went back: the controller restarted or reset its tick count. A log must
            // keep increasing time: the monitor stops here.
            eprintln!(
                "firmware time went back ({:.3} s after {:.3} s): the controller restarted; \
                 the log ends here",
                s.t_s,
                last.map_or(0.0, |p| p.t_s)
            );
            restarts += 1;
            break;
        }
        let t0 = *first.get_or_insert(s.t_s);
        if duration_s.is_some_and(|d| s.t_s - t0 > d) {
            break;
        }
        frames += 1;
        if let Some(w) = writer.as_mut() {
            w.row(&s)?;
        }
        if !json && last_print.elapsed() > Duration::from_millis(if tty { 200 } else { 2000 }) {
            last_print = Instant::now();
            let c = l.counts();
            let e = &tel.estimate;
            let line = format!(
                "t {:>8.2} s  P2 {:>6.2} ± {:.2} bar (HP {})  LP {:>5.2}  motor {:>6.1} rpm  \
                 torque {:>7.0} N·m  valve {:>5.1} %{} {:>6.0} W  faults {:#06x}{}  frames {} ok, {} lost, {} bad",
                s.t_s,
                e.p2.to_f32(),
                e.p2_sigma().to_f32(),
                s.hp_bar.map_or("—".into(), |p| format!("{p:.2}")),
                s.lp_bar.unwrap_or(f64::NAN),
                s.motor_rpm,
                e.torque.to_f32(),
                tel.applied.to_f32(),
                if tel.dump { " DUMP" } else { "" },
                tel.hydraulic_power.to_f32(),
                e.faults,
                if tel.sensor_faults == 0 {
                    String::new()
                } else {
                    format!(
                        " SENSOR FAULT: {}",
                        pto_firmware::sensor_faults::described(tel.sensor_faults)
                            .map(|(n, why)| format!("{n} ({why})"))
                            .collect::<Vec<_>>()
                            .join(", ")
                    )
                },
                c.ok - before.ok,
                c.lost - before.lost,
                c.dropped() - before.dropped()
            );
            if tty {
                eprint!("\r{line}");
            } else {
                eprintln!("{line}");
            }
        }
        last = Some(s);
    }
    if tty && !json {
        eprintln!();
    }
    let c = l.counts();
    let (lost, bad) = (c.lost - before.lost, c.dropped() - before.dropped());
    let not_sent = if failure.is_none() {
        client::status(&mut l)
            .ok()
            .map(|st| st.telemetry_dropped.wrapping_sub(dropped_before))
    } else {
        None
    };
    let written = match writer {
        Some(w) => {
            let (rows, skipped) = (w.rows, w.skipped);
            Some((w.finish()?, rows, skipped))
        }
        None => None,
    };
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "frames": frames,
                "lost": lost,
                "dropped": bad,
                "not_sent_by_the_firmware": not_sent,
                "restarts": restarts,
                "first_s": first,
                "last_s": last.map(|s| s.t_s),
                "log": written.as_ref().map(|w| &w.0),
                "rows": written.as_ref().map(|w| w.1),
                "rows_skipped_missing_reading": written.as_ref().map(|w| w.2),
            }))?
        );
    } else {
        println!(
            "{frames} telemetry frames ({} – {} s), {lost} lost, {bad} damaged, {} not sent \
             (the firmware's queue was full){}",
            first.map_or("—".into(), |t| format!("{t:.2}")),
            last.map_or("—".into(), |s| format!("{:.2}", s.t_s)),
            not_sent.map_or("?".into(), |n| n.to_string()),
            if restarts > 0 {
                format!(", the controller restarted {restarts}×")
            } else {
                String::new()
            }
        );
        if let Some((p, rows, skipped)) = &written {
            println!(
                "bench log {} ({rows} rows{})",
                p.display(),
                if *skipped > 0 {
                    format!(", {skipped} frames left out: a pressure reading was missing")
                } else {
                    String::new()
                }
            );
        }
    }
    if let Some(e) = failure {
        return Err(anyhow::Error::from(e).context(match &written {
            Some((p, rows, _)) => format!(
                "the link failed; the {rows} rows so far are in {}",
                p.display()
            ),
            None => "the link failed".into(),
        }));
    }
    if frames == 0 {
        eprintln!("no telemetry frame arrived: is the controller stepping?");
    }
    // Frames lost on the way, or never sent, are a miss: the log has gaps; so is no frame.
    Ok(frames > 0 && lost == 0 && bad == 0 && not_sent == Some(0) && restarts == 0)
}

/// The operator of a guided command: at the terminal, or unattended with `--yes` (needed when
/// stdin is not a terminal).
fn operator(yes: bool) -> Result<Box<dyn pto_host::hil::selftest::Operator>> {
    use pto_host::hil::selftest::{AtTerminal, Unattended};
    if yes {
        Ok(Box::new(Unattended))
    } else if std::io::stdin().is_terminal() {
        Ok(Box::new(AtTerminal))
    } else {
        bail!("stdin is not a terminal: answer the questions at one, or run unattended with --yes")
    }
}

pub(crate) fn selftest_cmd(
    t: &Target,
    yes: bool,
    window_s: f64,
    hold_s: f64,
    valve_pct: f32,
    skip: Vec<pto_host::hil::selftest::Skippable>,
    json: bool,
) -> Result<bool> {
    use pto_host::hil::selftest as st;
    for (name, v, hi) in [("--window", window_s, 600.0), ("--hold", hold_s, 60.0)] {
        if !(v.is_finite() && v > 0.0 && v <= hi) {
            bail!("{name} {v}: outside (0, {hi}] s");
        }
    }
    let mut op = operator(yes)?;
    let opts = st::Options {
        window: Duration::from_secs_f64(window_s),
        hold: Duration::from_secs_f64(hold_s),
        valve_pct,
        skip,
    };
    let (mut l, h) = connect(t)?;
    pto_host::output::stop_on_interrupt();
    let r = st::run(&mut l, &opts, op.as_mut())?;
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "port": t.port,
                "firmware": format!("{}.{}", h.firmware >> 8, h.firmware & 0xff),
                "protocol": h.protocol,
                "checks": r.checks,
                "passed": r.passed,
                "interrupted": r.interrupted,
            }))?
        );
    } else {
        print!("{}", st::table(&r));
    }
    if r.interrupted {
        std::process::exit(130);
    }
    Ok(r.passed)
}

pub(crate) fn clear_faults_cmd(t: &Target, json: bool) -> Result<bool> {
    let (mut l, _) = connect(t)?;
    let before = client::status(&mut l)?.sensor_faults;
    let held = client::clear_sensor_faults(&mut l)?;
    let names = |b: u8| pto_firmware::sensor_faults::names(b).collect::<Vec<_>>();
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "cleared": names(before & !held),
                "still_held": names(held),
            }))?
        );
    } else if before == 0 {
        println!("no sensor fault held");
    } else {
        if before & !held != 0 {
            println!(
                "cleared: {} (they agree with the model again)",
                names(before & !held).join(", ")
            );
        }
        if held != 0 {
            println!(
                "still held: {} — check the sensor; `pto link … status`, `monitor`",
                pto_firmware::sensor_faults::described(held)
                    .map(|(n, why)| format!("{n}: {why}"))
                    .collect::<Vec<_>>()
                    .join("; ")
            );
            if held & pto_firmware::sensor_faults::bit::HP != 0 {
                println!(
                    "  HP clears only against an estimate that knows P2 (σ ≤ 1 bar, the dump valve \
                     closed): open the valve with the motor read (the model then reads P2 off the \
                     motor), or power the controller off and on (a power cycle forgets held \
                     sensors, as it forgets the trip)"
                );
            }
        }
    }
    Ok(held == 0)
}

pub(crate) fn campaign_run_cmd(
    t: &Target,
    file: &Path,
    log_dir: &Path,
    bench: Option<&PathBuf>,
    yes: bool,
    prepare_wait_s: f64,
    json: bool,
) -> Result<bool> {
    use pto_host::hil::campaign::{self, Waits};
    use pto_host::plan::{Campaign, Status};
    let b = super::load_bench_with(bench, &[])?;
    let c = Campaign::load(file, &b)?;
    campaign::check_runnable(&c)?;
    let mut op = operator(yes)?;
    let (mut l, h) = connect(t)?;
    pto_host::output::stop_on_interrupt();
    let waits = Waits {
        prepare: Duration::from_secs_f64(prepare_wait_s),
        ..Waits::default()
    };
    let r = campaign::run(
        &mut l,
        h.dt_log2,
        &b,
        &c,
        &file.display().to_string(),
        log_dir,
        waits,
        op.as_mut(),
    )?;
    let complete = r.complete(c.segment.len());
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "campaign": file.display().to_string(),
                "log_dir": log_dir.display().to_string(),
                "segments": r.segments,
                "interrupted": r.interrupted,
                "complete": complete,
            }))?
        );
    } else {
        println!(
            "{:<44} {:<10} {:>7} {:>5}  {:<26} note",
            "segment", "status", "rows", "lost", "lever seen (planned)"
        );
        for o in &r.segments {
            let lever = match (o.motion, o.planned) {
                (Some(m), Some(p)) => format!(
                    "±{:.1}° {} (±{:.1}° {})",
                    m.amplitude_deg,
                    m.period_s.map_or("—".into(), |x| format!("{x:.2} s")),
                    p.amplitude_deg,
                    p.period_s.map_or("held".into(), |x| format!("{x:.2} s")),
                ),
                _ => String::new(),
            };
            println!(
                "{:<44} {:<10} {:>7} {:>5}  {:<26} {}",
                o.name,
                if o.skipped { "done" } else { o.status.label() },
                o.rows,
                o.lost,
                lever,
                o.note
            );
        }
        let not: Vec<&str> = c
            .segment
            .iter()
            .map(|s| s.run.name.as_str())
            .filter(|n| {
                !r.segments
                    .iter()
                    .any(|o| o.name == *n && o.status == Status::Complete)
            })
            .collect();
        if not.is_empty() {
            println!(
                "{} of {} segments complete; not complete: {} — run the same command again to \
                 run them",
                c.segment.len() - not.len(),
                c.segment.len(),
                not.join(", ")
            );
        } else {
            println!(
                "every segment complete; next: pto fit {}/*.csv --params {} --out FIT",
                log_dir.display(),
                c.params.join(",")
            );
        }
    }
    if r.interrupted {
        std::process::exit(130);
    }
    Ok(complete)
}
