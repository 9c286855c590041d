//! The model crate's code cost (`pto model-cost`): the per-step code, counted over the call
//! graph of `estimator::step` and `scheduler::step` in the release build's ELF objects (their
//! relocations, through `core` and the compiler builtins), fits its 9 KiB on the bench's
//! Cortex-M4, reaches no panic (the walk found `panic_bounds_check`, and with it 4 KiB of
//! `core::fmt`, behind the six table lookups, whose signed cell index the compiler could not
//! bound), and the estimator + scheduler state its 1 KiB.

use pto_host::validation::cost::{self, target};
use std::path::Path;

#[test]
fn per_step_code_and_state_fit_their_targets() {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    for t in ["thumbv6m-none-eabi", "thumbv7em-none-eabihf"] {
        let c = cost::code_size(&workspace, t).unwrap();
        println!(
            "{t}: per-step code {} B over {} functions ({} B of code; target {} B on thumbv7em), \
             crate .text {} B; from outside the crate: {:?}",
            c.step_code_bytes,
            c.step_functions,
            c.step_text_bytes,
            target::FLASH_BYTES,
            c.text_bytes,
            c.step_external
        );
        assert!(c.step_panics.is_empty(), "{t}: {:?}", c.step_panics);
        // The two entry points and the table lookups they call out of line, at least.
        assert!(c.step_functions >= 6, "{t}: {} functions", c.step_functions);
        assert!(c.step_text_bytes <= c.step_code_bytes && c.step_code_bytes < c.text_bytes);
        if t.starts_with("thumbv7em") {
            assert!(c.step_code_bytes <= target::FLASH_BYTES);
        }
    }
    let state =
        std::mem::size_of::<pto_model::State>() + std::mem::size_of::<pto_model::SchedulerState>();
    println!("state {state} B (target {} B)", target::STATE_BYTES);
    assert!(state <= target::STATE_BYTES);
}
