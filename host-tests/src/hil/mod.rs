//! The firmware in the loop: its builds ([`build`]), the link to a controller over a serial
//! port or a QEMU socket ([`link`]) and what the bench engineer does over it ([`client`]), QEMU
//! runs of the firmware ([`qemu`]), processor-in-the-loop with the full simulation ([`pil`]),
//! the firmware's cost per step and per build ([`fw_cost`]), the model alone on a Cortex-M0
//! ([`m0`], its cycles from [`thumb`]), the bring-up self-test of a
//! freshly flashed controller ([`selftest`]), a planned campaign run on the controller
//! ([`campaign`]) and the twin's plant following one ([`twin`]).

pub mod build;
pub mod campaign;
pub mod client;
pub mod fw_cost;
pub mod link;
pub mod m0;
pub mod pil;
pub mod qemu;
pub mod selftest;
pub mod thumb;
pub mod twin;
