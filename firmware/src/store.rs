//! The configuration store: the last uploaded model configuration, kept across resets in a
//! `sequential-storage` map (CRC on every item, power-fail safe with repair, wear levelling) on
//! any `embedded-storage-async` [`NorFlash`]: the STM32F405's last two 128 KiB sectors on the
//! bench, a [`RamFlash`] under QEMU (whose flash is read-only) and in the host tests.
//!
//! One record, key [`CONFIG_KEY`]: a [`RECORD_VERSION`] byte, the fingerprint of the built-in
//! configuration of the firmware that stored it (4 bytes, little-endian), then the
//! configuration's [`encode_config`](pto_model::protocol::encode_config) bytes. At boot a record
//! of another version, one stored under a firmware built for another configuration (a bench
//! reflashed for another bench file), or one whose bytes do not decode or check is reported as
//! such and the built-in configuration runs.

use core::ops::Range;
use embedded_storage_async::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};
use pto_model::protocol::CONFIG_MAX_BYTES;
use sequential_storage::cache::{Cache, Uncached};
use sequential_storage::map::{MapConfig, MapStorage};

/// The map key of the configuration record.
pub const CONFIG_KEY: u8 = 1;
/// Version of the record's layout (bumped when it or the model configuration's encoding
/// changes).
pub const RECORD_VERSION: u8 = 2;
/// Version byte and built-in fingerprint.
const HEADER: usize = 5;
/// Working buffer: key, header and configuration, rounded up to the flash's words.
const BUF: usize = CONFIG_MAX_BYTES + HEADER + 8;

/// What the store held at boot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum Loaded {
    /// Nothing stored.
    Empty,
    /// A record of this version: `len` configuration bytes copied out, stored by a firmware
    /// whose built-in configuration had fingerprint `built_in`.
    Found {
        /// Configuration bytes.
        len: usize,
        /// The storing firmware's built-in fingerprint.
        built_in: u32,
    },
    /// A record of another layout version.
    OtherVersion(u8),
    /// The flash or the map failed (corrupted beyond repair, or a driver error).
    Failed,
}

/// Why a configuration could not be stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum StoreError {
    /// Longer than [`CONFIG_MAX_BYTES`].
    TooLong,
    /// The flash or the map failed.
    Flash,
    /// Read back different from what was written.
    Verify,
}

/// The configuration store on a flash `F`.
pub struct ConfigStore<F: NorFlash> {
    map: MapStorage<u8, F, Cache<Uncached, Uncached, Uncached, u8>>,
    buf: [u8; BUF],
}

impl<F: NorFlash> ConfigStore<F> {
    /// A store on `range` of `flash` (whole erase pages, at least two).
    pub fn new(flash: F, range: Range<u32>) -> Option<Self> {
        let cfg = MapConfig::try_new(range).ok()?;
        Some(ConfigStore {
            map: MapStorage::new(flash, cfg, Cache::new_uncached()),
            buf: [0; BUF],
        })
    }

    /// Copies the stored configuration's bytes into `out`.
    pub async fn load(&mut self, out: &mut [u8; CONFIG_MAX_BYTES]) -> Loaded {
        match self
            .map
            .fetch_item::<&[u8]>(&mut self.buf, &CONFIG_KEY)
            .await
        {
            Ok(None) => Loaded::Empty,
            Ok(Some(rec)) => match rec {
                [RECORD_VERSION, a, b, c, d, bytes @ ..] if bytes.len() <= CONFIG_MAX_BYTES => {
                    out[..bytes.len()].copy_from_slice(bytes);
                    Loaded::Found {
                        len: bytes.len(),
                        built_in: u32::from_le_bytes([*a, *b, *c, *d]),
                    }
                }
                [v, ..] => Loaded::OtherVersion(*v),
                [] => Loaded::OtherVersion(0),
            },
            Err(_) => Loaded::Failed,
        }
    }

    /// Stores `bytes` (replacing the record) under the running firmware's built-in
    /// configuration fingerprint `built_in`, then reads it back.
    pub async fn save(&mut self, bytes: &[u8], built_in: u32) -> Result<(), StoreError> {
        let mut rec = [0u8; CONFIG_MAX_BYTES + HEADER];
        let r = rec
            .get_mut(..bytes.len() + HEADER)
            .ok_or(StoreError::TooLong)?;
        r[0] = RECORD_VERSION;
        r[1..HEADER].copy_from_slice(&built_in.to_le_bytes());
        r[HEADER..].copy_from_slice(bytes);
        let rec: &[u8] = r;
        self.map
            .store_item(&mut self.buf, &CONFIG_KEY, &rec)
            .await
            .map_err(|_| StoreError::Flash)?;
        let mut back = [0u8; CONFIG_MAX_BYTES];
        match self.load(&mut back).await {
            Loaded::Found { len, built_in: b } if back[..len] == *bytes && b == built_in => Ok(()),
            _ => Err(StoreError::Verify),
        }
    }

    /// Erases the store (every page of its range).
    pub async fn clear(&mut self) -> Result<(), StoreError> {
        self.map.erase_all().await.map_err(|_| StoreError::Flash)
    }

    /// The flash (for the tests' power cuts).
    pub fn into_flash(self) -> F {
        self.map.destroy().0
    }
}

/// Why the stored configuration is not used at boot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum NotStored {
    /// Nothing stored.
    Empty,
    /// A record of another layout version.
    OtherVersion(u8),
    /// The flash or the map failed.
    Failed,
    /// Stored by a firmware built for another configuration (this fingerprint): the bench was
    /// reflashed for another bench file.
    OtherFirmware(u32),
    /// The bytes are not a configuration of this firmware's version.
    Decode,
    /// Another model step than the board samples at.
    OtherStep(u8),
}

/// The configuration to boot with from what the store held (`bytes`: the bytes it copied out),
/// for a firmware whose built-in configuration has fingerprint `built_in` and step `dt_log2`.
/// The caller still checks that a controller can be made from it.
pub fn stored_config(
    loaded: Loaded,
    bytes: &[u8],
    built_in: u32,
    dt_log2: u8,
) -> Result<pto_model::ModelConfig, NotStored> {
    match loaded {
        Loaded::Empty => Err(NotStored::Empty),
        Loaded::OtherVersion(v) => Err(NotStored::OtherVersion(v)),
        Loaded::Failed => Err(NotStored::Failed),
        Loaded::Found { built_in: b, .. } if b != built_in => Err(NotStored::OtherFirmware(b)),
        Loaded::Found { len, .. } => {
            let cfg = bytes
                .get(..len)
                .and_then(|b| pto_model::protocol::decode_config(b).ok())
                .ok_or(NotStored::Decode)?;
            if cfg.dt_log2 == dt_log2 {
                Ok(cfg)
            } else {
                Err(NotStored::OtherStep(cfg.dt_log2))
            }
        }
    }
}

/// NOR flash in RAM: erase sets a page to `0xFF`, a write can only clear bits. QEMU's store and
/// the host tests' flash. `N` bytes in pages of `PAGE` bytes, 4-byte words.
#[derive(Clone)]
pub struct RamFlash<const N: usize, const PAGE: usize> {
    mem: [u8; N],
}

impl<const N: usize, const PAGE: usize> Default for RamFlash<N, PAGE> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize, const PAGE: usize> RamFlash<N, PAGE> {
    /// Erased flash.
    pub const fn new() -> Self {
        RamFlash { mem: [0xFF; N] }
    }

    /// Its bytes.
    pub fn bytes(&self) -> &[u8; N] {
        &self.mem
    }

    fn range(&self, offset: u32, len: usize) -> Result<Range<usize>, RamFlashError> {
        let a = offset as usize;
        let b = a.checked_add(len).ok_or(RamFlashError::OutOfBounds)?;
        if b > N {
            return Err(RamFlashError::OutOfBounds);
        }
        Ok(a..b)
    }
}

/// A [`RamFlash`] access outside its bytes or not on its word / page boundaries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RamFlashError {
    /// Outside the flash.
    OutOfBounds,
    /// Not aligned.
    NotAligned,
}

impl NorFlashError for RamFlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            RamFlashError::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            RamFlashError::NotAligned => NorFlashErrorKind::NotAligned,
        }
    }
}

impl<const N: usize, const PAGE: usize> ErrorType for RamFlash<N, PAGE> {
    type Error = RamFlashError;
}

impl<const N: usize, const PAGE: usize> ReadNorFlash for RamFlash<N, PAGE> {
    const READ_SIZE: usize = 1;

    async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), RamFlashError> {
        let r = self.range(offset, bytes.len())?;
        bytes.copy_from_slice(&self.mem[r]);
        Ok(())
    }

    fn capacity(&self) -> usize {
        N
    }
}

impl<const N: usize, const PAGE: usize> NorFlash for RamFlash<N, PAGE> {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = PAGE;

    async fn erase(&mut self, from: u32, to: u32) -> Result<(), RamFlashError> {
        if !(from as usize).is_multiple_of(PAGE) || !(to as usize).is_multiple_of(PAGE) || to < from
        {
            return Err(RamFlashError::NotAligned);
        }
        let r = self.range(from, (to - from) as usize)?;
        self.mem[r].fill(0xFF);
        Ok(())
    }

    async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), RamFlashError> {
        if !(offset as usize).is_multiple_of(4) || !bytes.len().is_multiple_of(4) {
            return Err(RamFlashError::NotAligned);
        }
        let r = self.range(offset, bytes.len())?;
        for (m, b) in self.mem[r].iter_mut().zip(bytes) {
            *m &= *b;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embassy_futures::block_on;
    use pto_model::protocol::encode_config;

    type Flash = RamFlash<{ 4 * 1024 }, 1024>;
    /// The built-in fingerprint the tests store under.
    const FP: u32 = 0x07a8_78ed;

    /// A flash whose power fails after `budget` words written or pages erased: the failing
    /// operation is left half done (half of its words written, half of its page erased).
    struct PowerCut {
        flash: Flash,
        budget: usize,
    }

    impl ErrorType for PowerCut {
        type Error = RamFlashError;
    }

    impl ReadNorFlash for PowerCut {
        const READ_SIZE: usize = 1;
        async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), RamFlashError> {
            self.flash.read(offset, bytes).await
        }
        fn capacity(&self) -> usize {
            self.flash.capacity()
        }
    }

    impl NorFlash for PowerCut {
        const WRITE_SIZE: usize = 4;
        const ERASE_SIZE: usize = 1024;
        async fn erase(&mut self, from: u32, to: u32) -> Result<(), RamFlashError> {
            for page in (from..to).step_by(1024) {
                if self.budget == 0 {
                    // Half the page erased, then the power goes.
                    self.flash.mem[page as usize..page as usize + 512].fill(0xFF);
                    return Err(RamFlashError::OutOfBounds);
                }
                self.budget -= 1;
                self.flash.erase(page, page + 1024).await?;
            }
            Ok(())
        }
        async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), RamFlashError> {
            for (i, w) in bytes.chunks(4).enumerate() {
                if self.budget == 0 {
                    // The word half written.
                    let a = offset as usize + 4 * i;
                    self.flash.mem[a] &= w[0];
                    self.flash.mem[a + 1] &= w[1];
                    return Err(RamFlashError::OutOfBounds);
                }
                self.budget -= 1;
                self.flash.write(offset + 4 * i as u32, w).await?;
            }
            Ok(())
        }
    }

    fn config(trapped_air: f32) -> std::vec::Vec<u8> {
        let mut cfg = pto_model::ModelConfig::reference();
        cfg.trapped_air_fraction = trapped_air;
        let mut b = [0u8; CONFIG_MAX_BYTES];
        encode_config(&cfg, &mut b).unwrap().to_vec()
    }

    fn load<F: NorFlash>(s: &mut ConfigStore<F>) -> Option<std::vec::Vec<u8>> {
        let mut out = [0u8; CONFIG_MAX_BYTES];
        match block_on(s.load(&mut out)) {
            Loaded::Found { len, built_in } => {
                assert_eq!(built_in, FP);
                Some(out[..len].to_vec())
            }
            Loaded::Empty => None,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_configuration_is_stored_replaced_and_read_back() {
        let mut s = ConfigStore::new(Flash::new(), 0..4096).unwrap();
        assert_eq!(load(&mut s), None);
        let a = config(0.05);
        let b = config(0.09);
        block_on(s.save(&a, FP)).unwrap();
        assert_eq!(load(&mut s).as_deref(), Some(&a[..]));
        // Many replacements: the map wraps around its pages and keeps only the newest.
        for i in 0..40 {
            let c = if i % 2 == 0 { &b } else { &a };
            block_on(s.save(c, FP)).unwrap();
            assert_eq!(load(&mut s).as_deref(), Some(&c[..]), "write {i}");
        }
        // A new store on the same flash (a reboot) finds the last one.
        let flash = s.into_flash();
        let mut s = ConfigStore::new(flash, 0..4096).unwrap();
        assert_eq!(load(&mut s).as_deref(), Some(&a[..]));
        // Cleared: nothing stored.
        block_on(s.clear()).unwrap();
        assert_eq!(load(&mut s), None);
        block_on(s.save(&a, FP)).unwrap();
        assert_eq!(
            block_on(s.save(&[0u8; CONFIG_MAX_BYTES + 1], FP)),
            Err(StoreError::TooLong)
        );
    }

    /// The power fails at every point of a write in turn: after the reboot the store holds
    /// either the previous configuration or, when the write completed, the new one; never
    /// nothing, never a mix.
    #[test]
    fn a_power_loss_in_the_middle_of_a_write_keeps_the_previous_configuration() {
        let old = config(0.05);
        let new = config(0.09);
        // A flash that already went round its pages a few times, so that the cut also lands
        // in page erasures.
        let mut s = ConfigStore::new(Flash::new(), 0..4096).unwrap();
        for _ in 0..7 {
            block_on(s.save(&old, FP)).unwrap();
        }
        let base = s.into_flash();
        let (mut kept, mut took, mut cuts) = (0, 0, 0);
        for budget in 0..200 {
            let mut s = ConfigStore::new(
                PowerCut {
                    flash: base.clone(),
                    budget,
                },
                0..4096,
            )
            .unwrap();
            let done = block_on(s.save(&new, FP)).is_ok();
            let after = s.into_flash().flash;
            let mut s = ConfigStore::new(after, 0..4096).unwrap();
            let got = load(&mut s).expect("a configuration survives");
            if done {
                assert_eq!(got, new, "budget {budget}: a completed write reads back");
                took += 1;
            } else {
                cuts += 1;
                assert!(got == old || got == new, "budget {budget}: a mix");
                kept += usize::from(got == old);
            }
            // The store still works after the cut.
            block_on(s.save(&new, FP)).unwrap();
            assert_eq!(load(&mut s), Some(new.clone()));
        }
        println!("power cuts: {cuts} (previous kept {kept}), completed writes: {took}");
        assert!(cuts > 50 && kept > 0 && took > 0);
    }

    /// At boot the stored configuration is taken only when it was stored by a firmware built
    /// for the same configuration, decodes, and has the board's step.
    #[test]
    fn the_boot_takes_a_stored_configuration_only_when_it_fits_this_firmware() {
        let mut s = ConfigStore::new(Flash::new(), 0..4096).unwrap();
        let mut out = [0u8; CONFIG_MAX_BYTES];
        let l = block_on(s.load(&mut out));
        assert_eq!(stored_config(l, &out, FP, 10), Err(NotStored::Empty));
        let b = config(0.09);
        block_on(s.save(&b, FP)).unwrap();
        let l = block_on(s.load(&mut out));
        assert_eq!(
            stored_config(l, &out, FP, 10).unwrap().trapped_air_fraction,
            0.09
        );
        assert_eq!(
            stored_config(l, &out, FP ^ 1, 10),
            Err(NotStored::OtherFirmware(FP))
        );
        assert_eq!(
            stored_config(l, &out, FP, 11),
            Err(NotStored::OtherStep(10))
        );
        block_on(s.save(&[1, 2, 3], FP)).unwrap();
        let l = block_on(s.load(&mut out));
        assert_eq!(stored_config(l, &out, FP, 10), Err(NotStored::Decode));
    }

    #[test]
    fn a_record_of_another_version_is_not_taken() {
        let mut s = ConfigStore::new(Flash::new(), 0..4096).unwrap();
        let rec: &[u8] = &[RECORD_VERSION + 1, 1, 2, 3];
        let mut buf = [0u8; BUF];
        block_on(s.map.store_item(&mut buf, &CONFIG_KEY, &rec)).unwrap();
        let mut out = [0u8; CONFIG_MAX_BYTES];
        assert_eq!(
            block_on(s.load(&mut out)),
            Loaded::OtherVersion(RECORD_VERSION + 1)
        );
    }
}
