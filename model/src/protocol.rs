//! Messages between host tools and the firmware, defined once, and their framing (protocol v5:
//! v4's, with the board's supply reading in each sensor sample, the solenoids in each step's
//! output, and the bring-up self-test, [`selftest`]).
//!
//! A frame on the wire is `COBS(seq ‖ payload ‖ crc) 0`:
//! - `seq`: a `u16` (little-endian) counting the sender's frames, so the receiver counts the
//!   frames lost between two it got ([`LinkCounts::lost`]); a `Hello` restarts the count (a new
//!   session);
//! - `payload`: the message, postcard, which must fill the frame exactly (trailing bytes are a
//!   [`FrameError::Trailing`] drop, never ignored);
//! - `crc`: CRC-32C (Castagnoli; start and final XOR `0xFFFF_FFFF`, so leading and trailing
//!   zeros, inserted and deleted bytes all change it) over `seq ‖ payload`, little-endian;
//! - COBS, then a `0` delimiter; a receiver resynchronises at every `0`.
//!
//! Every frame a [`Receiver`] cannot take is counted by cause ([`LinkCounts`]). At connect the
//! host sends [`ToFirmware::Hello`] and the firmware answers [`FromFirmware::Hello`] with
//! [`PROTOCOL_VERSION`] and [`SCHEMA_HASH`], a hash of both message types' postcard schemas
//! (`postcard-schema`): a firmware and a host built from different message definitions refuse
//! each other with a clear error instead of misreading frames. The firmware also sends its
//! `Hello` once at boot.
//!
//! ```
//! use pto_model::protocol::{MAX_FRAME, Receiver, ToFirmware, encode};
//!
//! // The host numbers its frames; frame 2 is lost on the way and one byte of frame 3 flips.
//! let mut wire = Vec::new();
//! for seq in 0..5u16 {
//!     let mut buf = [0u8; MAX_FRAME];
//!     let n = encode(seq, &ToFirmware::Ping(u32::from(seq)), &mut buf).unwrap();
//!     match seq {
//!         2 => {}
//!         3 => {
//!             buf[2] ^= 0x10;
//!             wire.extend_from_slice(&buf[..n]);
//!         }
//!         _ => wire.extend_from_slice(&buf[..n]),
//!     }
//! }
//! let mut rx = Receiver::<ToFirmware>::new();
//! let got: Vec<ToFirmware> = wire.iter().filter_map(|b| rx.push(*b)).collect();
//! assert_eq!(got, [ToFirmware::Ping(0), ToFirmware::Ping(1), ToFirmware::Ping(4)]);
//! // Every loss is counted: the damaged frame by its cause, and the sequence numbers missing
//! // before frame 4 (2 lost, 3 damaged).
//! let c = rx.counts;
//! assert_eq!((c.ok, c.cobs + c.crc + c.payload, c.lost), (3, 1, 2), "{c:?}");
//! ```
//!
//! A typed RPC layer (`postcard-rpc`: endpoints keyed by a hash of path and schema, sequence
//! numbers, a standard error type) was considered and left for later: its embassy server wraps
//! `embassy-executor` 0.9's spawner (this firmware runs 0.10, so it would need its own
//! `WireTx`/`WireRx`/`WireSpawn` implementations), its serial transport carries no CRC, and
//! the link is a lockstep of a few message kinds. The frame keeps postcard-rpc's ingredients —
//! a sequence number and a schema key — so that a switch stays cheap.
//!
//! Over 600 lines: the messages, the framing and the `Receiver` belong to one wire format (the
//! long fuzzing is in `tests/link_fuzz.rs`).

mod board;
pub mod selftest;

pub use board::*;
pub use selftest::{SelfTest, SelfTestRefusal, SelfTestReply};

use crate::estimator::{Estimate, Inputs};
use crate::fx::{Aperture, HydraulicPower, Pressure, Rpm};
use crate::scheduler::{Command, Mode};
use core::marker::PhantomData;
use postcard_schema::Schema;
use postcard_schema::key::Key;
use serde::de::DeserializeOwned;
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

/// Largest encoded frame, bytes, delimiter included.
pub const MAX_FRAME: usize = 256;
/// Largest payload, bytes: 2 (seq) + 240 + 4 (CRC) = 246 raw bytes, ≤ 248 after COBS, + 0.
const MAX_PAYLOAD: usize = 240;
const SEQ_LEN: usize = 2;
const CRC_LEN: usize = 4;
const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);
/// A frame numbered up to this many before the newest is a duplicate or a late frame (counted
/// [`LinkCounts::out_of_order`], the count going on from the newest); further back, the sender
/// restarted (the count starts again from it).
const REPLAY_WINDOW: u16 = 256;

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
    /// Start a configuration upload of `len` bytes ([`encode_config`]'s) whose CRC-32C is
    /// `crc` ([`config_fingerprint`]). Answered with `ConfigProgress(0)`; a new `ConfigBegin`
    /// abandons an upload in progress.
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
    /// The bring-up self-test ([`selftest`]). Answered with `SelfTest(…)` or
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
    /// [`config_fingerprint`] of its bytes.
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

/// Frames a [`Receiver`] took and the ones it could not, by cause.
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
    /// Dropped: longer than [`MAX_FRAME`].
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

/// Why a frame could not be built or read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FrameError {
    /// The output buffer is too small, or the message longer than a payload may be.
    BufferTooSmall,
    /// Not valid COBS.
    Cobs,
    /// CRC mismatch.
    Crc,
    /// Shorter than a sequence number and a CRC, or CRC fine but not a message.
    Payload,
    /// A message followed by bytes it does not use.
    Trailing,
    /// Longer than [`MAX_FRAME`].
    TooLong,
}

impl core::fmt::Display for FrameError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            FrameError::BufferTooSmall => "buffer too small",
            FrameError::Cobs => "bad COBS encoding",
            FrameError::Crc => "CRC mismatch",
            FrameError::Payload => "bad payload",
            FrameError::Trailing => "bytes after the message",
            FrameError::TooLong => "frame too long",
        })
    }
}

impl core::error::Error for FrameError {}

/// Encodes `msg` numbered `seq` into `out` (COBS frame + 0 terminator); returns its length.
pub fn encode<T: Serialize>(seq: u16, msg: &T, out: &mut [u8]) -> Result<usize, FrameError> {
    let mut raw = [0u8; SEQ_LEN + MAX_PAYLOAD + CRC_LEN];
    raw[..SEQ_LEN].copy_from_slice(&seq.to_le_bytes());
    let n = postcard::to_slice(msg, &mut raw[SEQ_LEN..SEQ_LEN + MAX_PAYLOAD])
        .map_err(|_| FrameError::BufferTooSmall)?
        .len();
    let body = SEQ_LEN + n;
    let crc = CRC.checksum(&raw[..body]).to_le_bytes();
    raw[body..body + CRC_LEN].copy_from_slice(&crc);
    let m =
        cobs::try_encode(&raw[..body + CRC_LEN], out).map_err(|_| FrameError::BufferTooSmall)?;
    let end = out.get_mut(m).ok_or(FrameError::BufferTooSmall)?;
    *end = 0;
    Ok(m + 1)
}

/// Decodes one frame (with or without its 0 terminator): its sequence number and message.
pub fn decode<T: DeserializeOwned>(frame: &[u8]) -> Result<(u16, T), FrameError> {
    let frame = match frame.split_last() {
        Some((0, body)) => body,
        _ => frame,
    };
    if frame.len() >= MAX_FRAME {
        return Err(FrameError::TooLong);
    }
    let mut raw = [0u8; MAX_FRAME];
    let n = cobs::decode(frame, &mut raw)
        .map_err(|_| FrameError::Cobs)?
        .frame_size();
    if n < SEQ_LEN + CRC_LEN {
        return Err(FrameError::Payload);
    }
    let (body, crc) = raw[..n].split_at(n - CRC_LEN);
    if CRC.checksum(body).to_le_bytes() != [crc[0], crc[1], crc[2], crc[3]] {
        return Err(FrameError::Crc);
    }
    let seq = u16::from_le_bytes([body[0], body[1]]);
    let (msg, rest) =
        postcard::take_from_bytes(&body[SEQ_LEN..]).map_err(|_| FrameError::Payload)?;
    if !rest.is_empty() {
        return Err(FrameError::Trailing);
    }
    Ok((seq, msg))
}

/// A message that can start a session (its sequence numbers restart).
pub trait Session {
    /// This message is a `Hello`.
    fn is_hello(&self) -> bool;
}

impl Session for ToFirmware {
    fn is_hello(&self) -> bool {
        matches!(self, ToFirmware::Hello)
    }
}

impl Session for FromFirmware {
    fn is_hello(&self) -> bool {
        matches!(self, FromFirmware::Hello(_))
    }
}

/// Turns received bytes into messages of type `T`, counting every frame it cannot take by cause
/// and every gap in the sender's sequence numbers ([`LinkCounts`]). Heap-free: one frame
/// buffer. The firmware's receive task and the host's link both use it.
#[derive(Debug)]
pub struct Receiver<T> {
    buf: [u8; MAX_FRAME],
    len: usize,
    overflow: bool,
    /// The sequence number the next frame should carry (`None` before the first one).
    expected: Option<u16>,
    /// The sequence number of the last frame taken.
    taken: Option<u16>,
    /// What it took and dropped.
    pub counts: LinkCounts,
    _msg: PhantomData<fn() -> T>,
}

impl<T> Default for Receiver<T> {
    fn default() -> Self {
        Self::new()
    }
}

impl<T> Receiver<T> {
    /// An empty receiver.
    pub const fn new() -> Self {
        Receiver {
            buf: [0; MAX_FRAME],
            len: 0,
            overflow: false,
            expected: None,
            taken: None,
            counts: LinkCounts::ZERO,
            _msg: PhantomData,
        }
    }
}

impl<T> Receiver<T> {
    /// Sequence number of the last frame taken (`None` before the first).
    pub fn last_seq(&self) -> Option<u16> {
        self.taken
    }
}

impl<T: DeserializeOwned + Session> Receiver<T> {
    /// Feeds one byte; returns a message when it completes a valid frame.
    pub fn push(&mut self, byte: u8) -> Option<T> {
        if byte != 0 {
            match self.buf.get_mut(self.len) {
                Some(b) => {
                    *b = byte;
                    self.len += 1;
                }
                None => self.overflow = true,
            }
            return None;
        }
        let result = if self.overflow {
            Err(FrameError::TooLong)
        } else if self.len == 0 {
            // A delimiter alone (a leading 0, back-to-back terminators): nothing to count.
            return None;
        } else {
            decode::<T>(&self.buf[..self.len])
        };
        self.len = 0;
        self.overflow = false;
        let c = &mut self.counts;
        match result {
            Ok((seq, msg)) => {
                c.ok = c.ok.wrapping_add(1);
                self.taken = Some(seq);
                if msg.is_hello() {
                    self.expected = None;
                }
                match self.expected {
                    // A frame from up to REPLAY_WINDOW back: a duplicate or a late one, taken and
                    // counted; the count of what comes next goes on from the newest.
                    Some(e) if e.wrapping_sub(seq).wrapping_sub(1) < REPLAY_WINDOW => {
                        c.out_of_order = c.out_of_order.wrapping_add(1);
                        return Some(msg);
                    }
                    Some(e) => {
                        let gap = seq.wrapping_sub(e);
                        if gap < 0x8000 {
                            c.lost = c.lost.wrapping_add(u32::from(gap));
                        } else {
                            // Far back: the sender restarted without a `Hello` reaching us.
                            c.out_of_order = c.out_of_order.wrapping_add(1);
                        }
                    }
                    None => {}
                }
                self.expected = Some(seq.wrapping_add(1));
                Some(msg)
            }
            Err(e) => {
                let n = match e {
                    FrameError::Cobs => &mut c.cobs,
                    FrameError::Crc => &mut c.crc,
                    FrameError::TooLong | FrameError::BufferTooSmall => &mut c.too_long,
                    FrameError::Payload | FrameError::Trailing => &mut c.payload,
                };
                *n = n.wrapping_add(1);
                None
            }
        }
    }
}

/// Largest postcard encoding of a [`ModelConfig`](crate::ModelConfig), bytes (its f32 fields
/// are 4 bytes each and its small integers varints: ≈ 300 bytes).
pub const CONFIG_MAX_BYTES: usize = 512;

/// A model configuration as postcard bytes: the form the firmware's build script embeds (and in
/// which a configuration travels to the firmware). The bytes are written into `out`; the
/// encoded part is returned.
pub fn encode_config<'a>(
    cfg: &crate::ModelConfig,
    out: &'a mut [u8],
) -> Result<&'a mut [u8], postcard::Error> {
    postcard::to_slice(cfg, out)
}

/// The model configuration of [`encode_config`]'s bytes: exactly those bytes, nothing left over.
pub fn decode_config(bytes: &[u8]) -> Result<crate::ModelConfig, postcard::Error> {
    match postcard::take_from_bytes(bytes)? {
        (cfg, []) => Ok(cfg),
        _ => Err(postcard::Error::DeserializeBadEncoding),
    }
}

impl From<crate::ConfigError> for ConfigRefusal {
    fn from(e: crate::ConfigError) -> Self {
        ConfigRefusal::Field {
            field: FieldName::new(e.field),
            value: e.value,
            min: e.min,
            max: e.max,
        }
    }
}

/// A configuration's fingerprint: the CRC-32C of its [`encode_config`] bytes (the firmware logs
/// it at boot; `pto` prints the same figure for a bench file).
pub fn config_fingerprint(bytes: &[u8]) -> u32 {
    CRC.checksum(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn replay() -> ToFirmware {
        ToFirmware::Replay {
            tick: 123_456,
            inputs: Inputs {
                encoder: Some(-1234),
                hp: Some(Pressure::from_num(101.5)),
                lp: None,
                motor: Some(Rpm::from_num(180.0)),
                aperture_cmd: Aperture::from_num(12.0),
                on_duty: 0b1001,
                config: 0,
            },
        }
    }

    fn frame(seq: u16, m: &ToFirmware) -> ([u8; MAX_FRAME], usize) {
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(seq, m, &mut buf).unwrap();
        (buf, n)
    }

    #[test]
    fn frames_round_trip_and_every_single_byte_flip_is_caught() {
        let msg = replay();
        let (buf, n) = frame(7, &msg);
        assert_eq!(buf[n - 1], 0);
        assert!(buf[..n - 1].iter().all(|b| *b != 0));
        assert_eq!(decode::<ToFirmware>(&buf[..n]).unwrap(), (7, msg));
        for i in 0..n - 1 {
            for bit in 0..8 {
                let mut bad = buf;
                bad[i] ^= 1 << bit;
                if bad[i] == 0 {
                    continue;
                }
                assert!(
                    decode::<ToFirmware>(&bad[..n]).is_err(),
                    "flip at {i}.{bit} accepted"
                );
            }
        }
        assert!(decode::<ToFirmware>(&buf[..n / 2]).is_err());
    }

    /// CRC-16/KERMIT (protocol v1) started from 0: a zero byte before the payload left it
    /// unchanged. CRC-32C starts from all ones and sees it.
    #[test]
    fn leading_and_trailing_zeros_change_the_crc() {
        let body = [0x11u8, 0x22, 0x33];
        let lead = [0u8, 0x11, 0x22, 0x33];
        let trail = [0x11u8, 0x22, 0x33, 0];
        assert_ne!(CRC.checksum(&body), CRC.checksum(&lead));
        assert_ne!(CRC.checksum(&body), CRC.checksum(&trail));
        let kermit = crc::Crc::<u16>::new(&crc::CRC_16_KERMIT);
        assert_eq!(
            kermit.checksum(&body),
            kermit.checksum(&lead),
            "v1's blind spot"
        );
    }

    /// A message followed by bytes it does not use is dropped (v1 ignored them).
    #[test]
    fn trailing_bytes_after_a_message_are_a_dropped_frame() {
        let mut raw = [0u8; 16];
        let n = postcard::to_slice(&ToFirmware::Ping(6), &mut raw[SEQ_LEN..])
            .unwrap()
            .len();
        raw[SEQ_LEN + n] = 0x2a; // one byte too many, inside the CRC
        let body = SEQ_LEN + n + 1;
        let crc = CRC.checksum(&raw[..body]).to_le_bytes();
        raw[body..body + CRC_LEN].copy_from_slice(&crc);
        let mut out = [0u8; 32];
        let m = cobs::try_encode(&raw[..body + CRC_LEN], &mut out).unwrap();
        assert_eq!(decode::<ToFirmware>(&out[..m]), Err(FrameError::Trailing));
    }

    /// One lost delimiter merges two frames into one dropped frame; the next frame's sequence
    /// number shows both lost (v1: the second frame vanished and nothing moved).
    #[test]
    fn a_lost_delimiter_is_counted() {
        let mut rx = Receiver::<ToFirmware>::new();
        let mut got = 0;
        let mut feed = |rx: &mut Receiver<ToFirmware>, b: &[u8]| {
            for x in b {
                got += usize::from(rx.push(*x).is_some());
            }
        };
        let (f0, n0) = frame(0, &ToFirmware::Hello);
        let (f1, n1) = frame(1, &ToFirmware::GetStatus);
        let (f2, n2) = frame(2, &ToFirmware::Ping(6));
        let (f3, n3) = frame(3, &ToFirmware::Ping(7));
        feed(&mut rx, &f0[..n0]);
        feed(&mut rx, &f1[..n1 - 1]); // its delimiter lost
        feed(&mut rx, &f2[..n2]);
        feed(&mut rx, &f3[..n3]);
        assert_eq!(got, 2);
        let c = rx.counts;
        assert_eq!((c.ok, c.dropped(), c.lost), (2, 1, 2), "{c:?}");
    }

    #[test]
    fn the_schema_hash_is_stable_within_a_build_and_checked() {
        let h = Hello {
            protocol: PROTOCOL_VERSION,
            schema: SCHEMA_HASH,
            firmware: 0x0100,
            dt_log2: 10,
        };
        assert!(h.check().is_ok());
        let old = Hello { protocol: 2, ..h };
        let e = old.check().unwrap_err().to_string();
        assert!(
            e.contains("v2") && e.contains(&format!("v{PROTOCOL_VERSION}")),
            "{e}"
        );
        let other = Hello {
            schema: [0; 8],
            ..h
        };
        assert!(other.check().is_err());
        assert_ne!(SCHEMA_HASH, [0; 8]);
    }

    #[test]
    fn chunks_cover_a_configuration_and_field_names_survive_the_wire() {
        let bytes: Vec<u8> = (0..=200u8).collect();
        let mut back = Vec::new();
        let mut off = 0;
        loop {
            let c = Chunk::of(&bytes, off);
            if c.len == 0 {
                break;
            }
            assert_eq!(usize::from(c.offset), off);
            back.extend_from_slice(c.bytes());
            off += usize::from(c.len);
        }
        assert_eq!(back, bytes);
        let long = "relief_process_noise_bar_per_sqrt_s_and_then_some_more_text_past_64";
        let f = FieldName::new(long);
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(
            0,
            &FromFirmware::Refused(Refusal::Config(ConfigRefusal::Field {
                field: f,
                value: 1.0,
                min: 0.0,
                max: 0.5,
            })),
            &mut buf,
        )
        .unwrap();
        let (_, m): (u16, FromFirmware) = decode(&buf[..n]).unwrap();
        let s = m_text(&m);
        assert!(s.contains(&long[..64]) && !s.contains(long), "{s}");
        assert_eq!(FieldName::new("motor.x").to_string(), "motor.x");
    }

    fn m_text(m: &FromFirmware) -> String {
        match m {
            FromFirmware::Refused(r) => r.to_string(),
            other => format!("{other:?}"),
        }
    }

    /// The reference configuration survives the embedding's round trip field for field, and a
    /// truncated or padded encoding is refused.
    #[test]
    fn a_model_configuration_round_trips_through_its_bytes() {
        let cfg = crate::ModelConfig::reference();
        let mut buf = [0u8; CONFIG_MAX_BYTES];
        let bytes = encode_config(&cfg, &mut buf).unwrap().to_vec();
        println!(
            "reference configuration: {} bytes, fingerprint {:08x}",
            bytes.len(),
            config_fingerprint(&bytes)
        );
        assert_eq!(decode_config(&bytes).unwrap(), cfg);
        assert!(decode_config(&bytes[..bytes.len() - 1]).is_err());
        let mut padded = bytes.clone();
        padded.push(0);
        assert!(decode_config(&padded).is_err());
    }
}
