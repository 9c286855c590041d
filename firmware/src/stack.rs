//! How much of the stack has never been used: cortex-m-rt paints the whole stack region
//! (`_stack_end` … `_stack_start`) with [`cortex_m_rt::STACK_PAINT_VALUE`] before `main`
//! (feature `paint-stack`); the words still painted at its bottom were never reached. Reported
//! in `Status::stack_unused` and checked by the QEMU tests after the deepest paths (boot, a
//! stored commit): the tables are built on the stack, ≈ 11 KB at a time, and a path that took it
//! through the statics once locked QEMU up.
#![allow(unsafe_code)]

unsafe extern "C" {
    static _stack_end: u32;
    static _stack_start: u32;
}

/// Bytes at the bottom of the stack region never used since boot.
pub fn unused_bytes() -> u32 {
    // SAFETY: the linker's symbols bound the stack region, word-aligned (cortex-m-rt's
    // link.x asserts it); words below the deepest frame so far are only read here, volatile.
    unsafe {
        let lo = core::ptr::addr_of!(_stack_end);
        let hi = core::ptr::addr_of!(_stack_start);
        let mut p = lo;
        while p < hi && core::ptr::read_volatile(p) == cortex_m_rt::STACK_PAINT_VALUE {
            p = p.add(1);
        }
        (p as usize - lo as usize) as u32
    }
}
