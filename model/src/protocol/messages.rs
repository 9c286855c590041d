//! The messages: host → firmware ([`ToFirmware`]), firmware → host ([`FromFirmware`]) and what
//! they carry, with the protocol's version and the hash of both messages' schemas.

use super::selftest::{SelfTest, SelfTestRefusal, SelfTestReply};
use crate::estimator::{Estimate, Inputs};
use crate::fx::{Aperture, HydraulicPower, Pressure, Rpm};
use crate::scheduler::{Command, Mode};
use postcard_schema::Schema;
use postcard_schema::key::Key;
use serde::{Deserialize, Serialize};

/// Protocol version (in `Hello`).
pub const PROTOCOL_VERSION: u16 = 5;

/// Hash of the postcard schemas of [`ToFirmware`] and [`FromFirmware`] (each hashed with its
/// path by `postcard-schema`, FNV-1a 64, the two combined): it changes with any field, variant
/// or type of either message.
pub const SCHEMA_HASH: [u8; 8] = {
    let a = Key::for_path::<ToFirmware>("pto/to-firmware").to_bytes();
    let b = Key::for_path::<FromFirmware>("pto/from-firmware").to_bytes();
    let mut h = [0u8; 8];
    let mut i = 0;
    while i < 8 {
        h[i] = a[i] ^ b[i].rotate_left(3);
        i += 1;
    }
    h
};

/// One raw sensor sample, stamped with virtual time in model steps. The firmware converts it
/// exactly as it converts its own ADC and timer readings on the bench.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct SensorFrame {
    /// Step counter (virtual time = tick · dt).
    pub tick: u32,
    /// Shaft encoder timer count (32-bit timer in encoder mode, 0 at the neutral angle).
    pub encoder: i32,
    /// HP transducer loop, 12-bit ADC counts (4–20 mA across the shunt).
    pub hp_adc: u16,
    /// LP transducer loop, 12-bit ADC counts.
    pub lp_adc: u16,
    /// Motor speed from the pickup's input capture; `None` when no pulse was seen.
    pub motor: Option<Rpm>,
    /// The ADC's reference (VDDA) as the board measured it against its internal reference, mV;
    /// the loops' readings are corrected by it. `None`: not measured (the nominal reference of
    /// the loops' configuration is taken).
    pub supply_mv: Option<u16>,
}

/// Host → firmware.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ToFirmware {
    /// Start a session: the firmware answers with its [`Hello`] and restarts its count of the
    /// host's sequence numbers.
    Hello,
    /// Answer with `Pong` carrying the same number.
    Ping(u32),
    /// Full estimator inputs for a bit-exact replay (the firmware uses the given aperture and
    /// its actuator stage is bypassed).
    Replay {
        /// Step counter.
        tick: u32,
        /// Inputs.
        inputs: Inputs,
    },
    /// A sensor sample for closed-loop operation (the firmware commands the valve itself).
    Sensors(SensorFrame),
    /// Scheduler mode.
    SetMode(Mode),
    /// Cylinders on duty and geometry.
    SetDuty {
        /// Bit i = HC3.(i+1).
        on_duty: u8,
        /// 0..=3.
        config: u8,
    },
    /// Restart the estimator from known pressures and clear the scheduler. Answered with
    /// `ResetDone`, or `Refused(TripHeld)` while the overpressure trip holds and its release
    /// condition does not (a reset never releases the trip itself).
    Reset {
        /// P2.
        p2: Pressure,
        /// LP.
        lp: Pressure,
    },
    /// Ask for the link statistics.
    GetStatus,
    /// Watchdog self-test: the control task stops answering (it waits forever); the supervisor
    /// must then stop feeding the watchdog, which resets the controller.
    Stall,
    /// Stop (QEMU: exit with this code).
    Exit(u8),
    /// Telemetry on this link every `every` model steps (0: none). Answered with `Pong(every)`.
    SetTelemetry {
        /// Steps between two [`FromFirmware::Telemetry`] frames.
        every: u16,
    },
    /// Start a configuration upload of `len` bytes ([`encode_config`](super::encode_config)'s)
    /// whose CRC-32C is `crc` ([`config_fingerprint`](super::config_fingerprint)). Answered
    /// with `ConfigProgress(0)`; a new `ConfigBegin` abandons an upload in progress.
    ConfigBegin {
        /// Bytes to come.
        len: u16,
        /// Their CRC-32C.
        crc: u32,
    },
    /// The next piece of the upload, which must start where the last one ended. Answered with
    /// `ConfigProgress(bytes so far)`, or `Refused(Config(…))` (the upload is then abandoned).
    ConfigChunk(Chunk),
    /// Check the uploaded bytes (length, CRC, decoding, every field's range) and apply them at a
    /// safe point: the estimator restarts (P2 unknown until the next `Reset`), the valve goes to
    /// its safe state and slews back. With `persist`, store them in flash too, which is done
    /// only in the declared safe state (mode `Fixed(0)` and the valve closed) and refused
    /// otherwise, before anything changes. Answered with `ConfigApplied` or `Refused(Config(…))`.
    ConfigCommit {
        /// Also store the configuration (used at the next boot).
        persist: bool,
    },
    /// Erase the stored configuration (the next boot runs the built-in one; the running one
    /// is unchanged). Only in the declared safe state, like a commit. Answered with
    /// `ConfigCleared` or `Refused(Config(…))`.
    ConfigClear,
    /// Which configuration runs. Answered with `ConfigInfo`.
    GetConfig,
    /// Read back the running configuration's bytes from `offset`. Answered with `ConfigData`.
    ConfigRead {
        /// First byte.
        offset: u16,
    },
    /// The bring-up self-test ([`selftest`](super::selftest)). Answered with `SelfTest(…)` or
    /// `Refused(SelfTest(…))`.
    SelfTest(SelfTest),
    /// Release the sensors the controller holds faulted, each only if its reading agrees with
    /// the model now. Answered with `SensorFaults` (those still held).
    ClearSensorFaults,
}

/// Bytes carried by one configuration frame.
pub const CHUNK_BYTES: usize = 32;

/// A piece of a configuration's bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Chunk {
    /// Offset of the first byte in the whole.
    pub offset: u16,
    /// Bytes used in `data` (≤ [`CHUNK_BYTES`]).
    pub len: u8,
    /// The bytes (the first `len`).
    pub data: [u8; CHUNK_BYTES],
}

impl Chunk {
    /// The piece of `bytes` starting at `offset` (empty past the end).
    pub fn of(bytes: &[u8], offset: usize) -> Chunk {
        let piece = bytes.get(offset..).unwrap_or(&[]);
        let n = piece.len().min(CHUNK_BYTES);
        let mut data = [0u8; CHUNK_BYTES];
        data[..n].copy_from_slice(&piece[..n]);
        Chunk {
            offset: u16::try_from(offset).unwrap_or(u16::MAX),
            len: n as u8,
            data,
        }
    }

    /// The bytes it carries (a `len` beyond [`CHUNK_BYTES`] is cut to it).
    pub fn bytes(&self) -> &[u8] {
        &self.data[..usize::from(self.len).min(CHUNK_BYTES)]
    }
}

/// Where the running configuration came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ConfigSource {
    /// Built into the image (`PTO_BENCH`).
    BuiltIn,
    /// Read from the configuration store at boot.
    Stored,
    /// Uploaded in this session (not stored).
    Uploaded,
    /// Uploaded in this session and stored.
    UploadedStored,
}

impl core::fmt::Display for ConfigSource {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            ConfigSource::BuiltIn => "built into the image",
            ConfigSource::Stored => "stored (read at boot)",
            ConfigSource::Uploaded => "uploaded (not stored)",
            ConfigSource::UploadedStored => "uploaded and stored",
        })
    }
}

/// The running configuration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ConfigInfo {
    /// Where it came from.
    pub source: ConfigSource,
    /// [`config_fingerprint`](super::config_fingerprint) of its bytes.
    pub fingerprint: u32,
    /// Length of its bytes.
    pub len: u16,
}

/// A configuration field's name on the wire (up to 64 bytes of UTF-8).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FieldName {
    head: [u8; 32],
    tail: [u8; 32],
    len: u8,
}

impl FieldName {
    /// `name`, cut at 64 bytes (on a character boundary).
    pub fn new(name: &str) -> FieldName {
        let mut n = name.len().min(64);
        while !name.is_char_boundary(n) {
            n -= 1;
        }
        let b = &name.as_bytes()[..n];
        let mut head = [0u8; 32];
        let mut tail = [0u8; 32];
        let h = n.min(32);
        head[..h].copy_from_slice(&b[..h]);
        tail[..n - h].copy_from_slice(&b[h..]);
        FieldName {
            head,
            tail,
            len: n as u8,
        }
    }

    /// The name's bytes.
    fn bytes(&self, out: &mut [u8; 64]) -> usize {
        out[..32].copy_from_slice(&self.head);
        out[32..].copy_from_slice(&self.tail);
        usize::from(self.len).min(64)
    }
}

impl core::fmt::Display for FieldName {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let mut b = [0u8; 64];
        let n = self.bytes(&mut b);
        match core::str::from_utf8(&b[..n]) {
            Ok(s) => f.write_str(s),
            Err(_) => f.write_str("(bad field name)"),
        }
    }
}

/// Why an uploaded configuration was refused (nothing changed).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ConfigRefusal {
    /// A chunk or a commit without a `ConfigBegin`.
    NotStarted,
    /// The announced length is 0 or above the firmware's buffer.
    Length {
        /// Announced.
        len: u16,
        /// Largest taken.
        max: u16,
    },
    /// A chunk that does not start where the last ended, or runs past the announced length.
    OutOfOrder {
        /// Where the next chunk must start.
        expected: u16,
        /// Where it started.
        got: u16,
    },
    /// Committed before every byte arrived.
    Incomplete {
        /// Bytes received.
        received: u16,
        /// Bytes announced.
        len: u16,
    },
    /// The bytes' CRC-32C is not the announced one.
    Crc {
        /// Announced.
        expected: u32,
        /// Computed over the bytes received.
        got: u32,
    },
    /// The bytes are not a model configuration of this firmware's version.
    Decode,
    /// A field outside its range (the model's [`ConfigError`](crate::ConfigError)).
    Field {
        /// The field.
        field: FieldName,
        /// Its value.
        value: f32,
        /// Lowest allowed.
        min: f32,
        /// Highest allowed.
        max: f32,
    },
    /// Committed outside the declared safe state: applying a configuration stops the control
    /// loop for about a second (its tables are built once, twice when storing: checked, then applied), a flash
    /// erase for up to two more.
    NotSafe(NotSafe),
    /// The store failed (a commit: the configuration was not applied).
    Store,
}

impl core::fmt::Display for ConfigRefusal {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            ConfigRefusal::NotStarted => f.write_str("no upload in progress (ConfigBegin first)"),
            ConfigRefusal::Length { len, max } => {
                write!(f, "length {len} bytes outside [1, {max}]")
            }
            ConfigRefusal::OutOfOrder { expected, got } => write!(
                f,
                "chunk at byte {got}, expected byte {expected} (or past the announced length)"
            ),
            ConfigRefusal::Incomplete { received, len } => {
                write!(f, "committed after {received} of {len} bytes")
            }
            ConfigRefusal::Crc { expected, got } => write!(
                f,
                "CRC-32C of the bytes is {got:08x}, {expected:08x} announced"
            ),
            ConfigRefusal::Decode => {
                f.write_str("the bytes are not a model configuration of this firmware's version")
            }
            ConfigRefusal::Field {
                field,
                value,
                min,
                max,
            } => write!(f, "{field} = {value} outside [{min}, {max}]"),
            ConfigRefusal::NotSafe(why) => write!(
                f,
                "not in the declared safe state ({why}): a configuration is applied only in \
                 mode fixed 0 % with the valve closed, the trip armed and a valid HP reading \
                 (the controller stops stepping for about a second while it builds the tables)"
            ),
            ConfigRefusal::Store => f.write_str("the configuration store failed"),
        }
    }
}

/// Why the controller is not in the declared safe state in which it may stop stepping for a
/// while (a configuration's tables built, a flash erase).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum NotSafe {
    /// The overpressure trip holds.
    Tripped,
    /// The mode is not `Fixed(0)`, or the valve has not closed yet.
    ValveOpen,
    /// No valid HP reading in the last sample (or no sample yet): P2 is not known.
    NoReading,
    /// The bring-up self-test drives the outputs.
    SelfTest,
}

impl core::fmt::Display for NotSafe {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            NotSafe::Tripped => "the overpressure trip holds",
            NotSafe::ValveOpen => "the mode is not fixed 0 % or the valve has not closed yet",
            NotSafe::NoReading => "no valid HP reading: P2 is not known",
            NotSafe::SelfTest => "the self-test drives the outputs",
        })
    }
}

/// What became of a committed configuration's storing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Stored {
    /// Not asked (`persist: false`).
    No,
    /// Written to the store and read back.
    Yes,
}

/// One step as the bench link reports it: what the firmware saw, estimated and did.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Telemetry {
    /// The raw sensor sample of this step (its `tick` is the step's).
    pub sensors: SensorFrame,
    /// Estimator output.
    pub estimate: Estimate,
    /// Scheduler output.
    pub command: Command,
    /// Aperture applied to the valve.
    pub applied: Aperture,
    /// Dump valve output.
    pub dump: bool,
    /// Cylinders on duty (bit i = HC3.(i+1)).
    pub on_duty: u8,
    /// Geometry, 0..=3.
    pub config: u8,
    /// The estimate's hydraulic power into the valve ([`Estimate::hydraulic_power`]), W.
    pub hydraulic_power: HydraulicPower,
    /// Sensors the controller holds faulted (as `Status::sensor_faults`).
    pub sensor_faults: u8,
}

/// Frames a [`Receiver`](super::Receiver) took and the ones it could not, by cause.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LinkCounts {
    /// Frames decoded.
    pub ok: u32,
    /// Dropped: not valid COBS.
    pub cobs: u32,
    /// Dropped: CRC mismatch.
    pub crc: u32,
    /// Dropped: shorter than a sequence number and a CRC, not a message, or a message with
    /// bytes after it.
    pub payload: u32,
    /// Dropped: longer than [`MAX_FRAME`](super::MAX_FRAME).
    pub too_long: u32,
    /// Frames the sender numbered but that never arrived (gaps in the sequence numbers: lost
    /// whole, or inside a dropped frame).
    pub lost: u32,
    /// Frames that arrived with an older sequence number than the last one (duplicated or
    /// reordered; taken all the same).
    pub out_of_order: u32,
}

impl LinkCounts {
    /// Nothing counted yet (usable in `const` contexts, where `Default` is not).
    pub const ZERO: LinkCounts = LinkCounts {
        ok: 0,
        cobs: 0,
        crc: 0,
        payload: 0,
        too_long: 0,
        lost: 0,
        out_of_order: 0,
    };

    /// Frames dropped, every cause.
    pub fn dropped(&self) -> u32 {
        self.cobs
            .wrapping_add(self.crc)
            .wrapping_add(self.payload)
            .wrapping_add(self.too_long)
    }
}

/// Link and health counters.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Status {
    /// The firmware's receiver: frames from the host taken, dropped by cause, lost.
    pub link: LinkCounts,
    /// Sensor frames dropped because the control loop had not taken the previous ones.
    pub frames_overrun: u32,
    /// Received bytes lost because the receive buffer was full.
    pub bytes_lost: u32,
    /// Replies not sent because the link's transmit queue was full (a host sending commands
    /// faster than it reads their replies): the control loop never waits for the link.
    pub replies_dropped: u32,
    /// Sample periods the bench's sampler missed (the controller stalled: a flash erase, a
    /// table build); its ticks count them, so the log's time jumps over them.
    pub samples_missed: u32,
    /// Telemetry frames not sent because the link's transmit queue was full (the telemetry
    /// rate is above what the baud rate carries): the control loop never waits for the link.
    pub telemetry_dropped: u32,
    /// Estimator steps run.
    pub steps: u32,
    /// OR of every fault flag seen.
    pub faults_seen: u16,
    /// Steps run with the HP transducer out of its 4–20 mA window (wire break or short).
    pub hp_loop_faults: u32,
    /// Samples whose measured ADC reference was implausible (their loop readings were taken as
    /// missing).
    pub supply_faults: u32,
    /// Times the overpressure trip latched.
    pub trips: u32,
    /// Trip latch state.
    pub tripped: bool,
    /// Sensors the controller holds faulted (bit 0 HP, 1 LP, 2 motor, 3 encoder): latched
    /// until the host clears them with the sensor agreeing again.
    pub sensor_faults: u8,
    /// The outputs are held de-energised since boot, until the host's first mode, duty or reset
    /// command.
    pub held: bool,
    /// Dump valve output state.
    pub dump_valve: bool,
    /// Last valve aperture applied by the actuator stage.
    pub aperture: Aperture,
    /// Instructions (QEMU under `-icount shift=0`) or cycles (bench, DWT) of the last
    /// estimator + scheduler step.
    pub step_cost_last: u32,
    /// Largest of those.
    pub step_cost_max: u32,
    /// Sum over every step (mean = sum / steps).
    pub step_cost_sum: u64,
    /// Bytes of the stack never used since boot (its high-water mark's distance from the
    /// statics).
    pub stack_unused: u32,
}

/// Firmware → host.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FromFirmware {
    /// At boot, and in answer to [`ToFirmware::Hello`].
    Hello(Hello),
    /// Reply to `Ping`.
    Pong(u32),
    /// One step's result.
    Output {
        /// Step counter it answers.
        tick: u32,
        /// Estimator output.
        estimate: Estimate,
        /// Scheduler output.
        command: Command,
        /// Aperture the actuator stage applied to the valve (after its slew limit and the trip
        /// latch).
        applied: Aperture,
        /// Dump (safe) valve output: open.
        dump: bool,
        /// Solenoids energised (bit i = HC3.(i+1)).
        on_duty: u8,
    },
    /// Reply to `GetStatus`.
    Status(Status),
    /// Reply to an accepted `Reset`: the estimator and the scheduler restarted (a trip latch
    /// that was set stays set until it releases by itself; `Status::tripped` says so).
    ResetDone,
    /// A command was refused, with the reason; nothing changed.
    Refused(Refusal),
    /// Every [`ToFirmware::SetTelemetry`]'th step on the bench link.
    Telemetry(Telemetry),
    /// Configuration bytes received so far in an upload.
    ConfigProgress(u16),
    /// The uploaded configuration runs (and was stored when asked).
    ConfigApplied {
        /// The configuration now running.
        info: ConfigInfo,
        /// Whether it was stored.
        stored: Stored,
    },
    /// The stored configuration was erased.
    ConfigCleared,
    /// Reply to `GetConfig`.
    ConfigInfo(ConfigInfo),
    /// Reply to `ConfigRead`: the running configuration's bytes from the chunk's offset (empty
    /// past the end).
    ConfigData {
        /// The whole configuration's length.
        total: u16,
        /// The piece.
        chunk: Chunk,
    },
    /// Reply to a `SelfTest` request.
    SelfTest(SelfTestReply),
    /// Reply to `ClearSensorFaults`: the sensors still held faulted (bit 0 HP, 1 LP, 2 motor,
    /// 3 encoder; 0: none).
    SensorFaults(u8),
}

/// What the firmware says of itself at connect.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Hello {
    /// [`PROTOCOL_VERSION`] it was built with.
    pub protocol: u16,
    /// [`SCHEMA_HASH`] it was built with.
    pub schema: [u8; 8],
    /// Firmware version, major·256 + minor.
    pub firmware: u16,
    /// Model step, dt = 2^−dt_log2 s.
    pub dt_log2: u8,
}

impl Hello {
    /// Checks that the other end speaks this build's protocol: its version and schema hash.
    pub fn check(&self) -> Result<(), HelloMismatch> {
        if self.protocol != PROTOCOL_VERSION || self.schema != SCHEMA_HASH {
            Err(HelloMismatch {
                theirs: (self.protocol, self.schema),
            })
        } else {
            Ok(())
        }
    }
}

/// The other end speaks another protocol version or message schema.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HelloMismatch {
    /// Its protocol version and schema hash.
    pub theirs: (u16, [u8; 8]),
}

impl core::fmt::Display for HelloMismatch {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let hex = |f: &mut core::fmt::Formatter<'_>, h: &[u8; 8]| {
            h.iter().try_for_each(|b| write!(f, "{b:02x}"))
        };
        write!(
            f,
            "protocol mismatch: the other end speaks v{} (schema ",
            self.theirs.0
        )?;
        hex(f, &self.theirs.1)?;
        write!(f, "), this build v{PROTOCOL_VERSION} (schema ")?;
        hex(f, &SCHEMA_HASH)?;
        f.write_str("): build the firmware and the host tools from the same revision")
    }
}

/// Why the firmware refused a command.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Refusal {
    /// `Reset` while the overpressure trip holds: the trip's release condition (a valid HP
    /// reading and the estimate both below the release pressure) does not hold now.
    TripHeld(TripHold),
    /// `Stall` (the watchdog self-test) while the overpressure trip holds: the reset it ends in
    /// must not interrupt the safe state.
    StallWhileTripped,
    /// A configuration upload step was refused; the running configuration is unchanged.
    Config(ConfigRefusal),
    /// A self-test request was refused; nothing changed.
    SelfTest(SelfTestRefusal),
    /// `Replay` on a board that samples its own sensors: the live estimator is the trip's input
    /// and is never stepped with a host's inputs (the QEMU twin takes it).
    ReplayOnTwinOnly,
}

/// Why a tripped latch cannot release now.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TripHold {
    /// No valid HP reading (wire break, short, or outside the transducer's range): the pressure
    /// is unknown.
    HpMissing,
    /// The HP reading (this value) disagrees with the model beyond the estimator's gate.
    HpRejected(Pressure),
    /// The HP reading is above the release pressure (the reading).
    HpHigh(Pressure),
    /// The P2 estimate is above the release pressure (the estimate).
    EstimateHigh(Pressure),
    /// While tripped the estimator had to reset P2 to the HP reading (they disagreed for the
    /// whole reset window): a contradictory sensor, as a transducer failing to a valid low
    /// current would be. Held until the host acknowledges it with a `Reset` while the reading
    /// and the estimate are both below the release pressure; the hold time then runs again.
    Contradicted,
}

impl core::fmt::Display for TripHold {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            TripHold::HpMissing => f.write_str("no valid HP reading (the pressure is unknown)"),
            TripHold::HpRejected(p) => write!(
                f,
                "the HP reading {:.2} bar disagrees with the model beyond the gate",
                p.to_f32()
            ),
            TripHold::Contradicted => f.write_str(
                "the HP reading and the model contradicted each other while tripped: \
                 acknowledge with a reset once both are below the release pressure",
            ),
            TripHold::HpHigh(p) => {
                write!(
                    f,
                    "HP reading {:.2} bar above the release pressure",
                    p.to_f32()
                )
            }
            TripHold::EstimateHigh(p) => {
                write!(
                    f,
                    "P2 estimate {:.2} bar above the release pressure",
                    p.to_f32()
                )
            }
        }
    }
}

impl core::fmt::Display for Refusal {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Refusal::TripHeld(h) => write!(f, "reset refused: the overpressure trip holds: {h}"),
            Refusal::StallWhileTripped => {
                f.write_str("watchdog test refused: the overpressure trip holds")
            }
            Refusal::Config(c) => write!(f, "configuration refused: {c}"),
            Refusal::SelfTest(t) => write!(f, "self-test refused: {t}"),
            Refusal::ReplayOnTwinOnly => f.write_str(
                "replay refused: this controller steps its own sensors (only the QEMU twin \
                 replays a host's inputs)",
            ),
        }
    }
}
