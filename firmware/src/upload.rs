//! A configuration upload, chunk by chunk: `ConfigBegin` announces the length and the CRC-32C,
//! `ConfigChunk`s must follow in order, `ConfigCommit` checks the whole (length, CRC, decoding;
//! the ranges are checked by [`Controller::new`](crate::control::Controller::new) when it is
//! applied). Any refusal abandons the upload: the host starts again from `ConfigBegin`.

use pto_model::ModelConfig;
use pto_model::protocol::{
    CONFIG_MAX_BYTES, Chunk, ConfigRefusal, config_fingerprint, decode_config,
};

/// An upload in progress (or none).
#[derive(Debug, Clone)]
pub struct Upload {
    buf: [u8; CONFIG_MAX_BYTES],
    len: u16,
    crc: u32,
    got: u16,
    active: bool,
}

impl Default for Upload {
    fn default() -> Self {
        Self::new()
    }
}

impl Upload {
    /// No upload in progress.
    pub const fn new() -> Self {
        Upload {
            buf: [0; CONFIG_MAX_BYTES],
            len: 0,
            crc: 0,
            got: 0,
            active: false,
        }
    }

    /// Starts an upload of `len` bytes whose CRC-32C is `crc` (abandoning any other).
    pub fn begin(&mut self, len: u16, crc: u32) -> Result<u16, ConfigRefusal> {
        self.active = false;
        if len == 0 || usize::from(len) > CONFIG_MAX_BYTES {
            return Err(ConfigRefusal::Length {
                len,
                max: CONFIG_MAX_BYTES as u16,
            });
        }
        (self.len, self.crc, self.got, self.active) = (len, crc, 0, true);
        Ok(0)
    }

    /// Takes the next chunk; returns the bytes received so far.
    pub fn chunk(&mut self, c: &Chunk) -> Result<u16, ConfigRefusal> {
        if !self.active {
            return Err(ConfigRefusal::NotStarted);
        }
        let bytes = c.bytes();
        let end = usize::from(self.got) + bytes.len();
        if c.offset != self.got || end > usize::from(self.len) {
            self.active = false;
            return Err(ConfigRefusal::OutOfOrder {
                expected: self.got,
                got: c.offset,
            });
        }
        self.buf[usize::from(self.got)..end].copy_from_slice(bytes);
        self.got = end as u16;
        Ok(self.got)
    }

    /// Ends the upload: the bytes and the configuration they decode to.
    pub fn finish(&mut self) -> Result<(ModelConfig, &[u8]), ConfigRefusal> {
        if !self.active {
            return Err(ConfigRefusal::NotStarted);
        }
        self.active = false;
        if self.got != self.len {
            return Err(ConfigRefusal::Incomplete {
                received: self.got,
                len: self.len,
            });
        }
        let bytes = &self.buf[..usize::from(self.len)];
        let got = config_fingerprint(bytes);
        if got != self.crc {
            return Err(ConfigRefusal::Crc {
                expected: self.crc,
                got,
            });
        }
        let cfg = decode_config(bytes).map_err(|_| ConfigRefusal::Decode)?;
        Ok((cfg, bytes))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pto_model::protocol::encode_config;

    fn bytes(cfg: &ModelConfig) -> std::vec::Vec<u8> {
        let mut b = [0u8; CONFIG_MAX_BYTES];
        encode_config(cfg, &mut b).unwrap().to_vec()
    }

    fn send(u: &mut Upload, b: &[u8]) -> Result<(), ConfigRefusal> {
        u.begin(b.len() as u16, config_fingerprint(b))?;
        let mut off = 0;
        while off < b.len() {
            let c = Chunk::of(b, off);
            off = usize::from(u.chunk(&c)?);
        }
        Ok(())
    }

    #[test]
    fn an_upload_in_chunks_gives_back_the_configuration() {
        let mut cfg = ModelConfig::reference();
        cfg.trapped_air_fraction = 0.09;
        let b = bytes(&cfg);
        let mut u = Upload::new();
        send(&mut u, &b).unwrap();
        let (got, raw) = u.finish().unwrap();
        assert_eq!(got, cfg);
        assert_eq!(raw, &b[..]);
        // Finished: a second commit has nothing to commit.
        assert_eq!(u.finish().unwrap_err(), ConfigRefusal::NotStarted);
    }

    #[test]
    fn bad_uploads_are_refused_with_their_reason() {
        let b = bytes(&ModelConfig::reference());
        let mut u = Upload::new();
        assert_eq!(u.chunk(&Chunk::of(&b, 0)), Err(ConfigRefusal::NotStarted));
        assert!(matches!(u.begin(0, 0), Err(ConfigRefusal::Length { .. })));
        assert!(matches!(
            u.begin(CONFIG_MAX_BYTES as u16 + 1, 0),
            Err(ConfigRefusal::Length { .. })
        ));
        // A chunk skipped.
        u.begin(b.len() as u16, config_fingerprint(&b)).unwrap();
        u.chunk(&Chunk::of(&b, 0)).unwrap();
        assert_eq!(
            u.chunk(&Chunk::of(&b, 64)),
            Err(ConfigRefusal::OutOfOrder {
                expected: 32,
                got: 64
            })
        );
        assert_eq!(u.finish().unwrap_err(), ConfigRefusal::NotStarted);
        // Committed early.
        u.begin(b.len() as u16, config_fingerprint(&b)).unwrap();
        u.chunk(&Chunk::of(&b, 0)).unwrap();
        assert!(matches!(
            u.finish(),
            Err(ConfigRefusal::Incomplete { received: 32, .. })
        ));
        // One byte flipped on the way (inside a chunk whose frame CRC was fine).
        let mut bad = b.clone();
        bad[40] ^= 1;
        u.begin(b.len() as u16, config_fingerprint(&b)).unwrap();
        let mut off = 0;
        while off < bad.len() {
            off = usize::from(u.chunk(&Chunk::of(&bad, off)).unwrap());
        }
        assert!(matches!(u.finish(), Err(ConfigRefusal::Crc { .. })));
        // Bytes that are not a configuration, with a correct CRC.
        let junk = [0xFFu8; 40];
        send(&mut u, &junk).unwrap();
        assert_eq!(u.finish().unwrap_err(), ConfigRefusal::Decode);
    }
}
