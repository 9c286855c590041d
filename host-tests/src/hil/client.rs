//! What the bench engineer does over the link (`pto link`): status, mode, duty, reset, the
//! configuration (upload, read back) and the telemetry monitor with its bench log, the CSV
//! `pto fit` reads. Every function works on a [`Link`] whatever carries it: a serial port to
//! the bench, or the QEMU twin's pseudo-terminal.

use crate::hil::link::{Link, LinkError};
use pto_firmware::control::ControlConfig;
use pto_firmware::frontend::Transducer;
use pto_model::ModelConfig;
use pto_model::protocol::{
    CONFIG_MAX_BYTES, Chunk, ConfigInfo, FromFirmware, Refusal, Status, Stored, Telemetry,
    ToFirmware, config_fingerprint, decode_config, encode_config,
};
use pto_model::scheduler::Mode;
use std::io::Write as _;
use std::path::{Path, PathBuf};

/// Why a bench-link operation failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The link failed, or the firmware refused.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The configuration does not encode (a bug: every valid configuration fits).
    #[error("the configuration does not encode into {CONFIG_MAX_BYTES} bytes")]
    Encode,
    /// The firmware's configuration does not decode with this build's definition.
    #[error(
        "the firmware's configuration does not decode: build the host tools and the firmware from the same revision"
    )]
    Decode,
    /// The firmware answered with another configuration than the one sent.
    #[error("the firmware runs configuration {got:08x} after the upload of {sent:08x}")]
    Mismatch {
        /// Fingerprint sent.
        sent: u32,
        /// Fingerprint it reports.
        got: u32,
    },
    /// The log could not be written.
    #[error("cannot write {path}")]
    Log {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
}

fn refused(r: &FromFirmware) -> Option<Result<FromFirmware, Refusal>> {
    match r {
        FromFirmware::Refused(why) => Some(Err(*why)),
        FromFirmware::Telemetry(_) => None,
        other => Some(Ok(*other)),
    }
}

/// Sends `msg` and returns the answer, a refusal as [`LinkError::Refused`].
fn ask(link: &mut Link, msg: &ToFirmware) -> Result<FromFirmware, LinkError> {
    link.request(msg, refused)?.map_err(LinkError::Refused)
}

/// [`ask`], waiting at least `ms` for the answer: a commit or a clear answers only after its
/// flash erases, during which the whole controller stalls (their datasheet bounds are in
/// `pto_model::protocol`: `COMMIT_REPLY_MAX_MS`, `CLEAR_REPLY_MAX_MS`).
fn ask_within(link: &mut Link, msg: &ToFirmware, ms: u32) -> Result<FromFirmware, LinkError> {
    let before = link.timeout;
    link.timeout = before.max(std::time::Duration::from_millis(u64::from(ms)));
    let r = ask(link, msg);
    link.timeout = before;
    r
}

/// A command without an answer of its own, confirmed by a ping that follows it (the firmware
/// takes commands in order).
fn command(link: &mut Link, msg: &ToFirmware) -> Result<(), LinkError> {
    link.send(msg)?;
    let n = 0x5e7u32;
    link.request(&ToFirmware::Ping(n), |r| {
        matches!(r, FromFirmware::Pong(x) if *x == n).then_some(())
    })
}

fn unexpected(sent: ToFirmware, got: FromFirmware) -> LinkError {
    LinkError::Unexpected {
        sent: Box::new(sent),
        got: Box::new(got),
    }
}

/// The firmware's counters.
pub fn status(link: &mut Link) -> Result<Status, LinkError> {
    match ask(link, &ToFirmware::GetStatus)? {
        FromFirmware::Status(s) => Ok(s),
        other => Err(unexpected(ToFirmware::GetStatus, other)),
    }
}

/// Sets the scheduler mode.
pub fn set_mode(link: &mut Link, mode: Mode) -> Result<(), LinkError> {
    command(link, &ToFirmware::SetMode(mode))
}

/// Sets the cylinders on duty (bit i = HC3.(i+1)) and the geometry (0..=3).
pub fn set_duty(link: &mut Link, on_duty: u8, config: u8) -> Result<(), LinkError> {
    command(link, &ToFirmware::SetDuty { on_duty, config })
}

/// Restarts the estimator from known pressures (refused while the overpressure trip holds).
pub fn reset(link: &mut Link, p2_bar: f32, lp_bar: f32) -> Result<(), LinkError> {
    use pto_model::fx::Pressure;
    let msg = ToFirmware::Reset {
        p2: Pressure::from_num(p2_bar),
        lp: Pressure::from_num(lp_bar),
    };
    match ask(link, &msg)? {
        FromFirmware::ResetDone => Ok(()),
        other => Err(unexpected(msg, other)),
    }
}

/// Telemetry every `every` model steps on this link (0: none); returns what the firmware
/// set (it goes no faster than its link carries).
pub fn set_telemetry(link: &mut Link, every: u16) -> Result<u16, LinkError> {
    let msg = ToFirmware::SetTelemetry { every };
    match ask(link, &msg)? {
        FromFirmware::Pong(n) if n <= u32::from(u16::MAX) => Ok(n as u16),
        other => Err(unexpected(msg, other)),
    }
}

/// Asks the controller to release the sensors it holds faulted (each only if it agrees with the
/// model now); returns those still held (bits of `pto_firmware::sensor_faults::bit`).
pub fn clear_sensor_faults(link: &mut Link) -> Result<u8, LinkError> {
    match ask(link, &ToFirmware::ClearSensorFaults)? {
        FromFirmware::SensorFaults(held) => Ok(held),
        other => Err(unexpected(ToFirmware::ClearSensorFaults, other)),
    }
}

/// Erases the stored configuration (the next boot runs the built-in one).
pub fn clear_store(link: &mut Link) -> Result<(), LinkError> {
    match ask_within(
        link,
        &ToFirmware::ConfigClear,
        pto_model::protocol::CLEAR_REPLY_MAX_MS,
    )? {
        FromFirmware::ConfigCleared => Ok(()),
        other => Err(unexpected(ToFirmware::ConfigClear, other)),
    }
}

/// A configuration's bytes as the firmware takes them.
pub fn config_bytes(cfg: &ModelConfig) -> Result<Vec<u8>, ClientError> {
    let mut buf = [0u8; CONFIG_MAX_BYTES];
    Ok(encode_config(cfg, &mut buf)
        .map_err(|_| ClientError::Encode)?
        .to_vec())
}

/// Uploads `cfg` in chunks, then commits it (and stores it with `persist`); `progress` is
/// told the bytes sent so far and the total. Returns what the firmware then runs.
pub fn upload(
    link: &mut Link,
    cfg: &ModelConfig,
    persist: bool,
    mut progress: impl FnMut(usize, usize),
) -> Result<(ConfigInfo, Stored), ClientError> {
    let bytes = config_bytes(cfg)?;
    let crc = config_fingerprint(&bytes);
    let begin = ToFirmware::ConfigBegin {
        len: bytes.len() as u16,
        crc,
    };
    match ask(link, &begin)? {
        FromFirmware::ConfigProgress(0) => {}
        other => return Err(unexpected(begin, other).into()),
    }
    let mut off = 0;
    while off < bytes.len() {
        let msg = ToFirmware::ConfigChunk(Chunk::of(&bytes, off));
        match ask(link, &msg)? {
            FromFirmware::ConfigProgress(n) if usize::from(n) > off => off = usize::from(n),
            other => return Err(unexpected(msg, other).into()),
        }
        progress(off, bytes.len());
    }
    let commit = ToFirmware::ConfigCommit { persist };
    match ask_within(link, &commit, pto_model::protocol::COMMIT_REPLY_MAX_MS)? {
        FromFirmware::ConfigApplied { info, stored } => {
            if info.fingerprint != crc {
                return Err(ClientError::Mismatch {
                    sent: crc,
                    got: info.fingerprint,
                });
            }
            Ok((info, stored))
        }
        other => Err(unexpected(commit, other).into()),
    }
}

/// The configuration the firmware runs: where it came from, and the configuration.
pub fn read_config(link: &mut Link) -> Result<(ConfigInfo, ModelConfig), ClientError> {
    let info = match ask(link, &ToFirmware::GetConfig)? {
        FromFirmware::ConfigInfo(i) => i,
        other => return Err(unexpected(ToFirmware::GetConfig, other).into()),
    };
    let mut bytes = Vec::with_capacity(usize::from(info.len));
    while bytes.len() < usize::from(info.len) {
        let msg = ToFirmware::ConfigRead {
            offset: bytes.len() as u16,
        };
        match ask(link, &msg)? {
            FromFirmware::ConfigData { chunk, .. }
                if usize::from(chunk.offset) == bytes.len() && chunk.len > 0 =>
            {
                bytes.extend_from_slice(chunk.bytes());
            }
            other => return Err(unexpected(msg, other).into()),
        }
    }
    if config_fingerprint(&bytes) != info.fingerprint {
        return Err(ClientError::Mismatch {
            sent: info.fingerprint,
            got: config_fingerprint(&bytes),
        });
    }
    let cfg = decode_config(&bytes).map_err(|_| ClientError::Decode)?;
    Ok((info, cfg))
}

/// One telemetry frame in engineering units: the sensors as the firmware saw them (its own
/// front end's conversion) and its estimates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// Firmware time, s (tick · dt).
    pub t_s: f64,
    /// Shaft angle from the encoder count, deg.
    pub shaft_angle_deg: f64,
    /// HP reading, bar (`None`: the loop is outside 4–20 mA).
    pub hp_bar: Option<f64>,
    /// LP reading, bar.
    pub lp_bar: Option<f64>,
    /// Motor speed reading, rpm (0 when the pickup saw no pulse).
    pub motor_rpm: f64,
    /// The raw frame and the estimates.
    pub raw: Telemetry,
}

/// Turns telemetry into engineering units with the firmware's own conversions (its supply
/// correction included).
#[derive(Debug, Clone)]
pub struct Units {
    dt_s: f64,
    deg_per_count: f64,
    hp: Transducer,
    lp: Transducer,
}

/// A loop's reading as the firmware takes it: corrected for the sample's supply reading, `None`
/// when saturated, implausible or outside the loop's window.
fn loop_bar(t: &Transducer, raw: u16, supply_mv: Option<u16>) -> Option<f64> {
    use pto_firmware::frontend::{LoopReading, SupplyCorrection};
    let mut c = SupplyCorrection::new(t.vref_mv());
    c.update(supply_mv);
    match c.correct(raw) {
        LoopReading::Counts(n) => t.pressure(n).map(|p| f64::from(p.to_f32())),
        LoopReading::Saturated | LoopReading::SupplyFault => None,
    }
}

impl Units {
    /// For a firmware of model step 2^−`dt_log2` s running `cfg`.
    pub fn new(dt_log2: u8, cfg: &ModelConfig) -> Units {
        let cc = ControlConfig::default();
        Units {
            dt_s: 2f64.powi(-i32::from(dt_log2)),
            deg_per_count: 360.0 / f64::from(cfg.encoder_counts_per_rev.max(1)),
            hp: Transducer::new(cc.hp).expect("the firmware's own loop"),
            lp: Transducer::new(cc.lp).expect("the firmware's own loop"),
        }
    }

    /// The frame in engineering units.
    pub fn sample(&self, t: &Telemetry) -> Sample {
        let f = &t.sensors;
        Sample {
            t_s: f64::from(f.tick) * self.dt_s,
            shaft_angle_deg: f64::from(f.encoder) * self.deg_per_count,
            hp_bar: loop_bar(&self.hp, f.hp_adc, f.supply_mv),
            lp_bar: loop_bar(&self.lp, f.lp_adc, f.supply_mv),
            motor_rpm: f.motor.map_or(0.0, |r| f64::from(r.to_f32())),
            raw: *t,
        }
    }
}

/// The bench log's columns (`pto fit` reads the first eight; the estimates follow).
pub const LOG_HEADER: &str = "time_s,shaft_angle_deg,p2_bar,lp_bar,motor_rpm,aperture_pct,\
on_duty,config,tick,p2_est_bar,p2_sigma_bar,lp_est_bar,torque_est_nm,q_pump_est_lpm,\
q_valve_est_lpm,motor_est_rpm,aperture_cmd_pct,dump,faults,hydraulic_power_est_w";

/// A bench log being recorded: rows go to `FILE.part`, which becomes `FILE` when it is
/// finished (an interrupted run leaves no half log under the final name).
pub struct LogWriter {
    path: PathBuf,
    part: PathBuf,
    out: std::io::BufWriter<std::fs::File>,
    /// Rows written.
    pub rows: u64,
    /// Frames not written because a pressure reading was missing (wire break or short).
    pub skipped: u64,
}

impl LogWriter {
    /// Starts `path`.
    pub fn create(path: &Path) -> Result<LogWriter, ClientError> {
        let mut part = path.as_os_str().to_owned();
        part.push(".part");
        let part = PathBuf::from(part);
        let err = |source| ClientError::Log {
            path: part.clone(),
            source,
        };
        let f = std::fs::File::create(&part).map_err(err)?;
        let mut out = std::io::BufWriter::new(f);
        writeln!(out, "{LOG_HEADER}").map_err(err)?;
        Ok(LogWriter {
            path: path.to_path_buf(),
            part,
            out,
            rows: 0,
            skipped: 0,
        })
    }

    /// Writes one frame (skipped, and counted, when a pressure reading is missing: the fit
    /// needs numbers).
    pub fn row(&mut self, s: &Sample) -> Result<(), ClientError> {
        let (Some(p2), Some(lp)) = (s.hp_bar, s.lp_bar) else {
            self.skipped += 1;
            return Ok(());
        };
        let t = &s.raw;
        let e = &t.estimate;
        let duty: String = (0..4)
            .map(|i| if t.on_duty & (1 << i) != 0 { '1' } else { '0' })
            .collect();
        writeln!(
            self.out,
            "{:.6},{:.4},{:.3},{:.3},{:.2},{:.3},{},{},{},{:.4},{:.4},{:.4},{:.2},{:.4},{:.4},{:.2},{:.3},{},{:#06x},{:.2}",
            s.t_s,
            s.shaft_angle_deg,
            p2,
            lp,
            s.motor_rpm,
            t.applied.to_f32(),
            duty,
            t.config + 1,
            t.sensors.tick,
            e.p2.to_f32(),
            e.p2_sigma().to_f32(),
            e.lp.to_f32(),
            e.torque.to_f32(),
            e.q_pump.to_f32(),
            e.q_valve.to_f32(),
            e.motor_rpm.to_f32(),
            t.command.aperture.to_f32(),
            u8::from(t.dump),
            e.faults,
            t.hydraulic_power.to_f32()
        )
        .map_err(|source| ClientError::Log {
            path: self.part.clone(),
            source,
        })?;
        self.rows += 1;
        Ok(())
    }

    /// Flushes the rows and gives the log its name.
    pub fn finish(mut self) -> Result<PathBuf, ClientError> {
        self.out.flush().map_err(|source| ClientError::Log {
            path: self.part.clone(),
            source,
        })?;
        std::fs::rename(&self.part, &self.path).map_err(|source| ClientError::Log {
            path: self.path.clone(),
            source,
        })?;
        Ok(self.path)
    }
}
