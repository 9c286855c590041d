//! The configuration the firmware is built for: `PTO_BENCH=FILE cargo fw-bench` (a path from
//! the workspace root; default the reference bench). The build script loads and checks the
//! bench file with the host tools' own code, converts it (`pto_bench::model::model_config` and
//! `controller_config`), checks that the model gives coefficients and the scheduler takes them,
//! and embeds the model configuration as postcard bytes ([`BYTES`], the form an upload takes)
//! and the scheduler and control settings as constants ([`SCHEDULER`], [`CONTROL`]); a bench the
//! firmware cannot take fails the build with the file, the field and its range.

use pto_model::ModelConfig;
use pto_model::protocol::decode_config;

include!(concat!(env!("OUT_DIR"), "/bench-config.rs"));

/// The configuration's bytes ([`pto_model::protocol::encode_config`]).
pub const BYTES: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/bench-config.bin"));

/// The configuration the firmware is built for; `None` only if the image is damaged (the build
/// script decoded these very bytes).
pub fn model() -> Option<ModelConfig> {
    decode_config(BYTES).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The embedded configuration decodes, gives coefficients and carries its fingerprint;
    /// built for the reference bench it is `ModelConfig::reference()` to the bit (the golden
    /// vectors' configuration).
    #[test]
    fn the_built_in_configuration_decodes_and_names_its_source() {
        let cfg = model().unwrap();
        println!(
            "built for {SOURCE}: {} bytes, fingerprint {FINGERPRINT:08x}",
            BYTES.len()
        );
        assert_eq!(FINGERPRINT, pto_model::protocol::config_fingerprint(BYTES));
        assert!(cfg.coefficients().is_ok());
        assert!(crate::control::Controller::new(&cfg, &SCHEDULER, &CONTROL).is_ok());
        let (hz, pll) = crate::clocks::plan(HSE_MHZ, true);
        assert!(
            pll.unwrap().within_limits(hz),
            "the PLL for {HSE_MHZ:?} MHz"
        );
        if REFERENCE {
            assert_eq!(HSE_MHZ, Some(8));
            assert_eq!(cfg, ModelConfig::reference());
            assert_eq!(SCHEDULER, pto_model::SchedulerConfig::default());
            assert_eq!(CONTROL, crate::control::ControlConfig::default());
        }
    }
}
