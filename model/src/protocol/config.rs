//! The model configuration on the wire: its postcard bytes (uploaded in [`Chunk`]s, kept by
//! the firmware's store) and their fingerprint.
//!
//! [`Chunk`]: super::Chunk

use super::frame::CRC;
use super::messages::{ConfigRefusal, FieldName};

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
