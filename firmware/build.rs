//! Puts the workspace's `memory.x` on the linker path and adds the cortex-m-rt and defmt linker
//! scripts (bare-metal targets only: the library and its tests also build for the host), and
//! builds the firmware for a bench file: `PTO_BENCH=FILE` (relative paths from the workspace
//! root; default the reference bench) is loaded and range-checked, converted into the model's
//! configuration by the host tools' own conversion (`pto_bench::model::model_config`), checked
//! by `ModelConfig::coefficients`, and embedded as postcard bytes (`OUT_DIR/bench-config.bin`,
//! `OUT_DIR/bench-config.rs`). A bench the model cannot take fails the build with the file, the
//! field and its range.

use pto_bench::Bench;
use pto_bench::model::{controller_config, model_config};
use pto_model::protocol::{CONFIG_MAX_BYTES, config_fingerprint, decode_config, encode_config};
use std::{env, fs, path::PathBuf, process};

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets it"));
    let workspace = manifest
        .parent()
        .expect("the firmware sits in the workspace")
        .to_path_buf();
    println!("cargo:rerun-if-changed=build.rs");
    embed_bench(&workspace, &out);
    let memory = workspace.join("memory.x");
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
    println!("cargo:rustc-link-arg-bins=-Tdefmt.x");
}

/// Stops the build with `message` (cargo prints a build script's stderr when it fails).
fn fail(message: &str) -> ! {
    eprintln!("error: {message}");
    process::exit(1)
}

fn embed_bench(workspace: &std::path::Path, out: &std::path::Path) {
    println!("cargo:rerun-if-env-changed=PTO_BENCH");
    let reference = workspace.join("host-tests/data/reference-bench.toml");
    println!("cargo:rerun-if-changed={}", reference.display());
    let (bench, source, reference) = match env::var_os("PTO_BENCH").filter(|p| !p.is_empty()) {
        Some(p) => {
            let path = workspace.join(PathBuf::from(p));
            println!("cargo:rerun-if-changed={}", path.display());
            let bench = Bench::load(&path).unwrap_or_else(|e| fail(&format!("PTO_BENCH: {e}")));
            (bench, path.display().to_string(), false)
        }
        None => (
            Bench::reference(),
            pto_bench::REFERENCE_BENCH_NAME.to_string(),
            true,
        ),
    };
    let cfg = model_config(&bench).unwrap_or_else(|e| {
        fail(&format!(
            "{source}: the controller's model cannot take this bench: {e}"
        ))
    });
    if let Err(e) = cfg.coefficients() {
        fail(&format!(
            "{source}: the controller's model configuration made from it is out of range: {e}"
        ));
    }
    let mut buf = [0u8; CONFIG_MAX_BYTES];
    let bytes = encode_config(&cfg, &mut buf)
        .unwrap_or_else(|e| fail(&format!("{source}: cannot encode the configuration: {e}")));
    match decode_config(bytes) {
        Ok(back) if back == cfg => {}
        _ => fail("the configuration does not survive its encoding"),
    }
    let (sched, control) = controller_config(&bench);
    let k = cfg
        .coefficients()
        .unwrap_or_else(|e| fail(&format!("{source}: {e}")));
    if let Err(e) = sched.coefficients(&k) {
        fail(&format!("{source}:controller.scheduler.{e}"));
    }
    let hse_mhz = bench.file.controller.board.hse_mhz;
    let hse = match hse_mhz {
        0 => "None".to_string(),
        mhz => format!("Some({mhz})"),
    };
    let fingerprint = config_fingerprint(bytes);
    fs::write(out.join("bench-config.bin"), &*bytes).expect("OUT_DIR is writable");
    fs::write(
        out.join("bench-config.rs"),
        format!(
            "/// Where the built-in configuration came from.\npub const SOURCE: &str = {source:?};\n\
             /// It is the reference bench's (`PTO_BENCH` unset).\n\
             pub const REFERENCE: bool = {reference};\n\
             /// Its fingerprint (`pto_model::protocol::config_fingerprint`).\n\
             pub const FINGERPRINT: u32 = {fingerprint:#010x};\n\
             /// The scheduler's settings (the bench file's `[controller.scheduler]`).\n\
             pub const SCHEDULER: pto_model::scheduler::SchedulerConfig = {};\n\
             /// The control settings (the bench file's `[controller]`).\n\
             pub const CONTROL: pto_model::control::ControlConfig = {};\n\
             /// The board's crystal, MHz (`[controller.board] hse_mhz`; `None`: no crystal).\n\
             pub const HSE_MHZ: Option<u8> = {hse};\n",
            rust_literal(&format!("{sched:?}"), "pto_model::scheduler::"),
            rust_literal(&format!("{control:?}"), "pto_model::control::"),
        ),
    )
    .expect("OUT_DIR is writable");
}

/// A `Debug` rendering of a struct of f32 fields (and nested structs) as a Rust literal: type
/// names qualified with `path`, numbers suffixed `f32` (`Debug` prints the shortest decimal that
/// gives the same f32 back, so the literal is the value to the bit).
fn rust_literal(debug: &str, path: &str) -> String {
    let mut out = String::new();
    let mut word = String::new();
    let flush = |word: &mut String, out: &mut String| {
        if word.is_empty() {
            return;
        }
        if word.chars().next().is_some_and(|c| c.is_ascii_uppercase()) {
            out.push_str(path);
            out.push_str(word);
        } else if word
            .chars()
            .next()
            .is_some_and(|c| c.is_ascii_digit() || c == '-')
        {
            out.push_str(word);
            out.push_str("f32");
        } else {
            out.push_str(word);
        }
        word.clear();
    };
    for ch in debug.chars() {
        if ch.is_ascii_alphanumeric() || ch == '_' || ch == '.' || ch == '-' {
            word.push(ch);
        } else {
            flush(&mut word, &mut out);
            out.push(ch);
        }
    }
    flush(&mut word, &mut out);
    out
}
