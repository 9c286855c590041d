//! The model crate's code cost (`pto model-cost`): every per-step function is found in the
//! release build for both thumb targets (a function moved to another module or renamed would
//! otherwise drop out of the count unnoticed, as three did when the estimator was split into
//! files), the per-step code fits its 8 KiB on the bench's Cortex-M4 and the estimator +
//! scheduler state its 1 KiB.

use pto_host::model::cost::{self, target};
use std::path::Path;

#[test]
fn per_step_code_and_state_fit_their_targets() {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    for t in ["thumbv6m-none-eabi", "thumbv7em-none-eabihf"] {
        let c = cost::code_size(&workspace, t).unwrap();
        println!(
            "{t}: per-step code {} B (target {} B on thumbv7em), crate .text {} B",
            c.step_code_bytes,
            target::FLASH_BYTES,
            c.text_bytes
        );
        assert!(c.step_code_bytes > 0 && c.step_code_bytes < c.text_bytes);
        if t.starts_with("thumbv7em") {
            assert!(c.step_code_bytes <= target::FLASH_BYTES);
        }
    }
    let state =
        std::mem::size_of::<pto_model::State>() + std::mem::size_of::<pto_model::SchedulerState>();
    println!("state {state} B (target {} B)", target::STATE_BYTES);
    assert!(state <= target::STATE_BYTES);
}
