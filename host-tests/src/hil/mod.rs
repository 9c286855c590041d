//! The firmware in the loop: its builds ([`build`]), QEMU runs of the firmware ([`qemu`]), processor-in-the-loop with
//! the full simulation ([`pil`]), and the firmware's cost per step and per build ([`fw_cost`]).

pub mod build;
pub mod fw_cost;
pub mod pil;
pub mod qemu;
