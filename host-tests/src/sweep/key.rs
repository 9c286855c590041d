//! A run's identity, its key (a hash of everything that makes its figures), and shards: run
//! `K` of every `N` by key.

use serde::{Deserialize, Serialize};

/// A run's identity ([`RunSpec::key`](super::spec::RunSpec::key)); 16 hex digits as text.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct RunKey(pub u64);

impl std::fmt::Display for RunKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:016x}", self.0)
    }
}

impl std::str::FromStr for RunKey {
    type Err = std::num::ParseIntError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        u64::from_str_radix(s, 16).map(RunKey)
    }
}

impl Serialize for RunKey {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for RunKey {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

/// FNV-1a, 64 bits: stable across builds and platforms (unlike `std`'s hasher).
pub fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// `--shard K/N`: in each block of N consecutive runs (by index from 0), one run, the block's
/// (K − 1 + block) mod N-th: every shard takes one run a block (sizes differ by at most one),
/// and the turn by one each block keeps a shard from holding one value of the last axis alone
/// when N and that axis's length share a factor (with plain `index mod N`, `--shard K/16` of a
/// matrix whose last axis has 4 values gave each shard a single value).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    /// 1..=n.
    pub k: usize,
    /// Shards in all.
    pub n: usize,
}

impl Shard {
    /// Whether run `index` is this shard's.
    pub fn has(&self, index: usize) -> bool {
        let (block, place) = (index / self.n, index % self.n);
        (place + self.n - block % self.n) % self.n == self.k - 1
    }
}

impl std::str::FromStr for Shard {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("--shard {s}: want K/N with 1 ≤ K ≤ N, e.g. 3/16");
        let (k, n) = s.split_once('/').ok_or_else(bad)?;
        let (k, n): (usize, usize) = (
            k.trim().parse().map_err(|_| bad())?,
            n.trim().parse().map_err(|_| bad())?,
        );
        if k == 0 || k > n {
            return Err(bad());
        }
        Ok(Shard { k, n })
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.k, self.n)
    }
}
