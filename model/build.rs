//! Sets `cfg(no_long_multiply)` for the cores whose only multiply is 32 × 32 → 32: ARMv6-M
//! (Cortex-M0/M0+/M1: `MULS`, ARMv6-M Architecture Reference Manual, DDI 0419E, §A6.7.44; no
//! `SMULL`/`UMULL`) and ARMv8-M Baseline (Cortex-M23, DDI 0553, "MUL"). There a 64-bit product
//! is a call to the generic `__aeabi_lmul` (64 × 64, ≈ 40 instructions); `pto_model::fx`'s
//! wide products take four 16 × 16 partial products inline instead (`fx::wide`).

fn main() {
    println!("cargo::rustc-check-cfg=cfg(no_long_multiply)");
    println!("cargo::rerun-if-changed=build.rs");
    let target = std::env::var("TARGET").unwrap_or_default();
    if target.starts_with("thumbv6m") || target.starts_with("thumbv8m.base") {
        println!("cargo::rustc-cfg=no_long_multiply");
    }
}
