//! The framing: `COBS(seq ‖ postcard payload ‖ CRC-32C) 0`, [`encode`] and [`decode`], and the
//! [`Receiver`] both ends use, which counts every frame it drops by cause and every one lost.

use super::messages::{FromFirmware, LinkCounts, ToFirmware};
use core::marker::PhantomData;
use serde::Serialize;
use serde::de::DeserializeOwned;

/// Largest encoded frame, bytes, delimiter included.
pub const MAX_FRAME: usize = 256;
/// Largest payload, bytes: 2 (seq) + 240 + 4 (CRC) = 246 raw bytes, ≤ 248 after COBS, + 0.
pub(crate) const MAX_PAYLOAD: usize = 240;
pub(crate) const SEQ_LEN: usize = 2;
pub(crate) const CRC_LEN: usize = 4;
pub(crate) const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);
/// A frame numbered up to this many before the newest is a duplicate or a late frame (counted
/// [`LinkCounts::out_of_order`], the count going on from the newest); further back, the sender
/// restarted (the count starts again from it).
const REPLAY_WINDOW: u16 = 256;

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
