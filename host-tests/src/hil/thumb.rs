//! ARMv6-M (Thumb) code of an ELF as QEMU executes it: each instruction's length, whether it
//! ends a translation block, its Cortex-M0+ cycles, and a function's call graph.
//!
//! Cycles are the Cortex-M0+ Technical Reference Manual's (ARM DDI 0484C, §3.3, Table 3-1,
//! "Cortex-M0+ instruction summary"), for a core with the single-cycle multiplier and memory
//! without wait states: 1 cycle for data processing and `MULS`; 2 for a load or store
//! (`LDR*`, `STR*`, `LDR` literal), `ADD`/`MOV` to the PC, `B`, `BX`/`BLX` and a taken
//! conditional branch (1 not taken); 3 for `BL`; 1 + N for `LDM`/`STM`/`PUSH`/`POP` of N
//! registers, 3 + N for a `POP` that loads the PC; 3 for `MRS`, `MSR` and the barriers (none of
//! which the model's step uses).
//!
//! A hand-written decoder: the step's code is the 16-bit Thumb subset plus `BL`, and only the
//! classes above matter; a disassembler crate would bring a full ARM decoder for this table.

use object::{Object, ObjectSection, ObjectSymbol};
use std::collections::BTreeMap;

/// One decoded instruction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Insn {
    /// Bytes: 2, or 4 for `BL` and the other 32-bit encodings.
    pub len: u32,
    /// Its class.
    pub class: Class,
}

/// What an instruction costs and does to the flow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Class {
    /// Data processing (`MULS` included): 1 cycle.
    Alu,
    /// Load or store of one register: 2.
    Memory,
    /// `LDM`/`STM`/`PUSH`/`POP` (without the PC) of N registers: 1 + N.
    Multiple(u32),
    /// `POP` that loads the PC (a return), of N registers counting the PC: 3 + (N − 1).
    PopPc(u32),
    /// Conditional branch to the target: 2 taken, 1 not.
    BranchCond(u32),
    /// Unconditional branch to the target: 2.
    Branch(u32),
    /// Call to the target: 3.
    Call(u32),
    /// `BX`/`BLX` to a register, `ADD`/`MOV` to the PC: 2.
    Indirect,
    /// A 32-bit system instruction (`MRS`, `MSR`, barriers): 3; `true` when QEMU ends a
    /// translation block after it (`MSR`, which may change the interrupt state, and `ISB`).
    System(bool),
    /// `SVC`, `BKPT`, `UDF`: an exception (not in the step).
    Trap,
}

impl Insn {
    /// Cycles on a Cortex-M0+ (module doc), `taken` for a conditional branch.
    pub fn cycles(self, taken: bool) -> u32 {
        match self.class {
            Class::Alu => 1,
            Class::Memory | Class::Branch(_) | Class::Indirect => 2,
            Class::Multiple(n) => 1 + n,
            // N counts the PC: 3 + (N − 1) = 2 + N.
            Class::PopPc(n) => 2 + n,
            Class::BranchCond(_) => 1 + u32::from(taken),
            Class::Call(_) => 3,
            Class::System(_) => 3,
            Class::Trap => 1,
        }
    }

    /// Whether QEMU ends a translation block after it (it writes the PC).
    pub fn ends_block(self) -> bool {
        matches!(
            self.class,
            Class::PopPc(_)
                | Class::BranchCond(_)
                | Class::Branch(_)
                | Class::Call(_)
                | Class::Indirect
                | Class::System(true)
                | Class::Trap
        )
    }
}

/// Sign-extends the low `bits` bits of `v`.
fn sext(v: u32, bits: u32) -> i32 {
    ((v << (32 - bits)) as i32) >> (32 - bits)
}

/// Decodes the instruction whose first halfword is `h` (and second `h2`) at `pc`.
pub fn decode(pc: u32, h: u16, h2: u16) -> Insn {
    let (h, h2) = (u32::from(h), u32::from(h2));
    let short = |class| Insn { len: 2, class };
    if h >> 11 >= 0b11101 {
        // 32-bit: BL (11110 … / 11x1 …) or a system instruction.
        let class = if h >> 11 == 0b11110 && (h2 >> 14) == 0b11 && (h2 >> 12) & 1 == 1 {
            let s = (h >> 10) & 1;
            let (j1, j2) = ((h2 >> 13) & 1, (h2 >> 11) & 1);
            let (i1, i2) = (!(j1 ^ s) & 1, !(j2 ^ s) & 1);
            let imm =
                (s << 24) | (i1 << 23) | (i2 << 22) | ((h & 0x3ff) << 12) | ((h2 & 0x7ff) << 1);
            Class::Call(pc.wrapping_add(4).wrapping_add(sext(imm, 25) as u32))
        } else {
            // MSR is 0xF38x …; ISB is 0xF3BF 0x8F6x; MRS (0xF3EF …), DMB and DSB go on.
            let msr = h & 0xfff0 == 0xf380;
            let isb = h == 0xf3bf && h2 & 0xfff0 == 0x8f60;
            Class::System(msr || isb)
        };
        return Insn { len: 4, class };
    }
    let class = match h >> 12 {
        // LDR/STR with register offset, LDR literal, hi-register ops, data processing.
        0b0100 => {
            if h >> 11 == 0b01001 {
                Class::Memory // LDR literal
            } else if h >> 10 == 0b010001 {
                let op = (h >> 8) & 3;
                let rd = ((h >> 4) & 8) | (h & 7);
                match op {
                    // BX / BLX
                    3 => Class::Indirect,
                    // ADD / MOV to the PC
                    0 | 2 if rd == 15 => Class::Indirect,
                    _ => Class::Alu,
                }
            } else {
                Class::Alu
            }
        }
        0b0101..=0b1001 => Class::Memory,
        0b1011 => {
            // Miscellaneous: PUSH/POP, SP adjust, extends, REV, CPS, BKPT, hints.
            let regs = (h & 0xff).count_ones();
            match (h >> 9) & 7 {
                0b010 => Class::Multiple(regs + ((h >> 8) & 1)), // PUSH (R = LR)
                0b110 if (h >> 8) & 1 == 1 => Class::PopPc(regs + 1),
                0b110 => Class::Multiple(regs),
                0b111 if (h >> 8) & 1 == 0 => Class::Trap, // BKPT
                _ => Class::Alu,
            }
        }
        0b1100 => Class::Multiple((h & 0xff).count_ones()), // LDM/STM
        0b1101 => match (h >> 8) & 0xf {
            0b1110 | 0b1111 => Class::Trap, // UDF, SVC
            _ => Class::BranchCond(
                pc.wrapping_add(4)
                    .wrapping_add((sext(h & 0xff, 8) * 2) as u32),
            ),
        },
        0b1110 => Class::Branch(
            pc.wrapping_add(4)
                .wrapping_add((sext(h & 0x7ff, 11) * 2) as u32),
        ),
        _ => Class::Alu, // shifts, add/sub, immediate ops, ADR, ADD SP
    };
    short(class)
}

/// An ELF's code: its executable sections and function symbols.
pub struct Code {
    /// (address, bytes) of each executable section.
    sections: Vec<(u32, Vec<u8>)>,
    /// Function start → (end, name).
    functions: BTreeMap<u32, (u32, String)>,
}

impl Code {
    /// Reads an ELF's executable sections and function symbols.
    pub fn parse(elf: &[u8]) -> Result<Code, object::read::Error> {
        let obj = object::File::parse(elf)?;
        let mut sections = Vec::new();
        for s in obj.sections() {
            if s.kind() == object::SectionKind::Text {
                sections.push((s.address() as u32, s.data()?.to_vec()));
            }
        }
        let mut functions = BTreeMap::new();
        for sym in obj.symbols() {
            if sym.kind() == object::SymbolKind::Text && sym.size() > 0 {
                // Thumb symbols carry bit 0.
                let start = (sym.address() as u32) & !1;
                let name = sym.name().unwrap_or("?").to_string();
                functions.insert(start, (start + sym.size() as u32, name));
            }
        }
        Ok(Code {
            sections,
            functions,
        })
    }

    /// The halfword at `pc`.
    pub fn halfword(&self, pc: u32) -> Option<u16> {
        self.sections.iter().find_map(|(base, bytes)| {
            let off = pc.checked_sub(*base)? as usize;
            let b = bytes.get(off..off + 2)?;
            Some(u16::from_le_bytes([b[0], b[1]]))
        })
    }

    /// The instruction at `pc`.
    pub fn insn(&self, pc: u32) -> Option<Insn> {
        let h = self.halfword(pc)?;
        Some(decode(pc, h, self.halfword(pc + 2).unwrap_or(0)))
    }

    /// The first function whose demangled name contains `needle`: (start, end).
    pub fn function(&self, needle: &str) -> Option<(u32, u32)> {
        self.functions.iter().find_map(|(start, (end, name))| {
            format!("{:#}", rustc_demangle::demangle(name))
                .contains(needle)
                .then_some((*start, *end))
        })
    }

    /// The function containing `pc`: (start, end).
    fn containing(&self, pc: u32) -> Option<(u32, u32)> {
        let (start, (end, _)) = self.functions.range(..=pc).next_back()?;
        (pc < *end).then_some((*start, *end))
    }

    /// Every function reachable from the one at `root` by calls and branches (tail calls
    /// included), as (start, end) ranges in address order: the code a step can run.
    pub fn call_graph(&self, root: (u32, u32)) -> Vec<(u32, u32)> {
        let mut seen = std::collections::BTreeSet::from([root]);
        let mut todo = vec![root];
        while let Some((start, end)) = todo.pop() {
            let mut pc = start;
            while pc < end {
                let Some(i) = self.insn(pc) else { break };
                if let Class::Call(t) | Class::Branch(t) | Class::BranchCond(t) = i.class
                    && let Some(f) = self.containing(t)
                    && seen.insert(f)
                {
                    todo.push(f);
                }
                pc += i.len;
            }
        }
        seen.into_iter().collect()
    }

    /// The return addresses of every call to `target` (the instruction after each `BL`), over
    /// every function.
    pub fn returns_from(&self, target: u32) -> Vec<u32> {
        let mut out = Vec::new();
        for (&start, &(end, _)) in &self.functions {
            let mut pc = start;
            while pc < end {
                let Some(i) = self.insn(pc) else { break };
                if i.class == Class::Call(target) {
                    out.push(pc + i.len);
                }
                pc += i.len;
            }
        }
        out
    }

    /// The instructions QEMU runs as one translation block from `pc`: up to and including the
    /// first that writes the PC, never across a 1 KiB page (`TARGET_PAGE_BITS` 10 for Arm
    /// M-profile), at most 512 (`TCG_MAX_INSNS`).
    pub fn block(&self, pc: u32) -> Vec<(u32, Insn)> {
        let page_end = (pc | 0x3ff) + 1;
        let mut out = Vec::new();
        let mut at = pc;
        while at < page_end && out.len() < 512 {
            let Some(i) = self.insn(at) else { break };
            // A 32-bit instruction that would cross the page starts the next block.
            if at + i.len > page_end && !out.is_empty() {
                break;
            }
            out.push((at, i));
            if i.ends_block() {
                break;
            }
            at += i.len;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Encodings from the ARMv6-M Architecture Reference Manual (DDI 0419E, §A6.7), each with
    /// its class and Cortex-M0+ cycles.
    #[test]
    fn decodes_the_classes_and_cycles_of_the_manual() {
        let cases: [(u16, u16, Class, u32); 14] = [
            (0x1c08, 0, Class::Alu, 1),                // adds r0, r1, #0
            (0x4348, 0, Class::Alu, 1),                // muls r0, r1, r0
            (0x6808, 0, Class::Memory, 2),             // ldr r0, [r1]
            (0x4801, 0, Class::Memory, 2),             // ldr r0, [pc, #4]
            (0x9001, 0, Class::Memory, 2),             // str r0, [sp, #4]
            (0xb5f0, 0, Class::Multiple(5), 6),        // push {r4-r7, lr}
            (0xbcf0, 0, Class::Multiple(4), 5),        // pop {r4-r7}
            (0xbdf0, 0, Class::PopPc(5), 7),           // pop {r4-r7, pc}: 3 + 4
            (0xc90c, 0, Class::Multiple(2), 3),        // ldmia r1!, {r2, r3}
            (0x4770, 0, Class::Indirect, 2),           // bx lr
            (0x4687, 0, Class::Indirect, 2),           // mov pc, r0
            (0xd0fe, 0, Class::BranchCond(0x1000), 2), // beq . (taken)
            (0xe7fe, 0, Class::Branch(0x1000), 2),     // b .
            (0xf7ff, 0xfffe, Class::Call(0x1000), 3),  // bl .
        ];
        for (h, h2, class, cycles) in cases {
            let i = decode(0x1000, h, h2);
            assert_eq!(i.class, class, "{h:#06x}");
            let taken = matches!(class, Class::BranchCond(_));
            assert_eq!(i.cycles(taken), cycles, "{h:#06x}");
        }
        assert_eq!(decode(0x1000, 0xd0fe, 0).cycles(false), 1);
        assert_eq!(decode(0x1000, 0xf7ff, 0xfffe).len, 4);
        // bl with a forward offset: 0xf000 0xf802 → pc + 4 + 4.
        assert_eq!(decode(0x1000, 0xf000, 0xf802).class, Class::Call(0x1008));
    }
}
