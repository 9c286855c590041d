//! Puts this crate's `memory.x` (the nRF51822's map, not the workspace's STM32F405 one) on the
//! linker path and adds cortex-m-rt's linker script, for bare-metal targets only: the library
//! (the vectors' format) also builds for the host.

use std::{env, fs, path::PathBuf};

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets it"));
    let memory = manifest.join("memory.x");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed={}", memory.display());
    if env::var("CARGO_CFG_TARGET_OS").as_deref() != Ok("none") {
        return;
    }
    let text =
        fs::read(&memory).unwrap_or_else(|e| panic!("cannot read {}: {e}", memory.display()));
    fs::write(out.join("memory.x"), text).expect("OUT_DIR is writable");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rustc-link-arg-bins=--nmagic");
    println!("cargo:rustc-link-arg-bins=-Tlink.x");
}
