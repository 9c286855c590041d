//! The target's side: vectors in over semihosting, the model, the timers, the report.

use pto_model::Coefficients;
use pto_model::estimator::{self, Estimate, Inputs, State};
use pto_model::protocol::vectors::{
    CHECKED, EXIT_BAD_CONFIG, EXIT_BAD_FILE, EXIT_MATCH, EXIT_MISMATCH, EXIT_PANIC,
    HEADER_MAX_BYTES, Header, MAGIC, RECORD_MAX_BYTES, Record, VECTORS_FILE, VERSION,
    checked_words, first_difference,
};
use pto_model::protocol::{config_fingerprint, decode_config};
use pto_model::scheduler::{self, Command, Mode, SchedulerCoeffs, SchedulerConfig, SchedulerState};
use semihosting::fs::File;
use semihosting::io::Read as _;
use semihosting::{println, process};
use static_cell::StaticCell;

/// TIMER0 of the nRF51 (nRF51 Series Reference Manual v3.0, §18 "Timer/counter"), as a 32-bit
/// counter at 16 MHz (TIMER1 and TIMER2 are 16-bit only on the silicon; QEMU does not enforce
/// it, this uses TIMER0 alone). At `-icount shift=10` it counts 16.384 a instruction: 262 M
/// instructions before it wraps, the coefficients' build (≈ 32 M) included.
mod timer {
    const BASE: usize = 0x4000_8000;
    const TASKS_START: usize = 0x000;
    const TASKS_CLEAR: usize = 0x00C;
    const TASKS_CAPTURE0: usize = 0x040;
    const MODE: usize = 0x504;
    const BITMODE: usize = 0x508;
    const PRESCALER: usize = 0x510;
    const CC0: usize = 0x540;

    #[allow(unsafe_code)]
    fn write(offset: usize, value: u32) {
        // SAFETY: one of TIMER0's word-aligned registers (the offsets above, all inside its
        // 4 KiB block), written volatile; nothing else in the program uses TIMER0.
        unsafe {
            core::ptr::write_volatile(
                core::ptr::with_exposed_provenance_mut::<u32>(BASE + offset),
                value,
            )
        }
    }

    #[allow(unsafe_code)]
    fn read(offset: usize) -> u32 {
        // SAFETY: as `write`, read volatile.
        unsafe {
            core::ptr::read_volatile(core::ptr::with_exposed_provenance::<u32>(BASE + offset))
        }
    }

    /// Starts TIMER0 from 0: timer mode, 32 bits, prescaler 0.
    pub fn start() {
        write(MODE, 0);
        write(BITMODE, 3);
        write(PRESCALER, 0);
        write(TASKS_CLEAR, 1);
        write(TASKS_START, 1);
    }

    /// The counter now (a capture into CC[0] and its read: a fixed number of instructions).
    #[inline(always)]
    pub fn now() -> u32 {
        write(TASKS_CAPTURE0, 1);
        read(CC0)
    }
}

/// The stack region: `_stack_end` (its lowest word) and `_stack_start` (its top), addresses.
#[allow(unsafe_code)]
fn stack_region() -> (usize, usize) {
    unsafe extern "C" {
        static _stack_end: u32;
        static _stack_start: u32;
    }
    // Only the symbols' addresses are taken (never a read through them).
    (
        core::ptr::addr_of!(_stack_end) as usize,
        core::ptr::addr_of!(_stack_start) as usize,
    )
}

/// The lowest stack address used since boot (or since [`repaint_free_stack`]) and the
/// stack's top: cortex-m-rt paints the stack region before `main` (feature `paint-stack`); the
/// words still painted at its bottom were never reached.
#[allow(unsafe_code)]
fn stack_reach() -> (usize, usize) {
    let (lo, hi) = stack_region();
    let mut a = lo;
    // SAFETY: every address read is a word of the stack region the linker reserved (cortex-m-rt
    // asserts its bounds are word-aligned), below the deepest live frame until the first word
    // found unpainted; read volatile, as plain memory.
    while a < hi
        && unsafe { core::ptr::read_volatile(core::ptr::with_exposed_provenance::<u32>(a)) }
            == cortex_m_rt::STACK_PAINT_VALUE
    {
        a += 4;
    }
    (a, hi)
}

/// Paints the free stack below the caller's frame again (from the region's bottom up to 256
/// bytes below this function's own local), so that [`stack_reach`] after it measures what runs
/// next, not what ran deeper before.
#[inline(never)]
#[allow(unsafe_code)]
fn repaint_free_stack() {
    let here = 0u32;
    let limit = (core::ptr::addr_of!(here) as usize).saturating_sub(256);
    let (mut a, _) = stack_region();
    while a < limit {
        // SAFETY: the words from the region's bottom up to 256 bytes below this frame's local
        // are below every live frame (the stack grows down, nothing runs in an interrupt) and
        // inside the stack region the linker reserved; written volatile, never read as data.
        unsafe {
            core::ptr::write_volatile(
                core::ptr::with_exposed_provenance_mut::<u32>(a),
                cortex_m_rt::STACK_PAINT_VALUE,
            )
        };
        a += 4;
    }
}

/// The stack pointer now (the address of a local: within a few words of it).
#[inline(never)]
fn stack_pointer() -> usize {
    let here = 0u32;
    core::ptr::addr_of!(here) as usize
}

/// One step, timed: the estimator and the scheduler, as the controller's period runs them.
/// Out of line, so that its cost is the call's.
#[inline(never)]
fn step(
    k: &Coefficients,
    sc: &SchedulerCoeffs,
    s: &mut State,
    st: &mut SchedulerState,
    mode: Mode,
    inp: &Inputs,
) -> (Estimate, Command) {
    let e = estimator::step(k, s, inp);
    let c = scheduler::step(k, sc, st, mode, &e, inp.motor);
    (e, c)
}

/// TIMER0's ticks at `-icount shift=10` (16.384 a instruction) to instructions, rounded: exact
/// while the tick's error (< 1) is below half an instruction.
fn instructions(ticks: u32) -> u64 {
    (u64::from(ticks) * 1000 + 8192) >> 14
}

/// The vectors file, read in blocks.
struct Vectors {
    file: File,
    buf: [u8; 1024],
    start: usize,
    end: usize,
}

impl Vectors {
    /// At least `want` bytes buffered unless the file ends first; the buffered bytes.
    fn fill(&mut self, want: usize) -> &[u8] {
        if self.end - self.start < want {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
            while self.end < self.buf.len() {
                match self.file.read(&mut self.buf[self.end..]) {
                    Ok(0) => break,
                    Ok(n) => self.end += n,
                    Err(_) => fail(EXIT_BAD_FILE, "cannot read the vectors file"),
                }
            }
        }
        &self.buf[self.start..self.end]
    }

    fn consume(&mut self, n: usize) {
        self.start += n;
    }
}

fn fail(code: i32, why: &str) -> ! {
    println!("FAILED: {}", why);
    process::exit(code)
}

/// The coefficients, built once into place (≈ 11 KB: not on the stack).
static COEFFICIENTS: StaticCell<Coefficients> = StaticCell::new();

/// The coefficients' static, zeroed for the build (out of line: the zeroing's frame is not
/// `main`'s).
#[inline(never)]
fn zeroed_coefficients() -> &'static mut Coefficients {
    COEFFICIENTS.init_with(Coefficients::default)
}

#[cortex_m_rt::entry]
fn main() -> ! {
    timer::start();
    // The two captures' own cost, subtracted from every step's.
    let t0 = timer::now();
    let t1 = timer::now();
    let overhead = instructions(t1.wrapping_sub(t0));

    let file = match File::open(VECTORS_FILE) {
        Ok(f) => f,
        Err(_) => fail(EXIT_BAD_FILE, "cannot open vectors.bin"),
    };
    let mut v = Vectors {
        file,
        buf: [0; 1024],
        start: 0,
        end: 0,
    };
    if v.fill(MAGIC.len()).get(..MAGIC.len()) != Some(&MAGIC[..]) {
        fail(EXIT_BAD_FILE, "not a vectors file (magic)");
    }
    v.consume(MAGIC.len());

    let mut k_built: Option<(u32, &'static Coefficients, SchedulerCoeffs)> = None;
    let mut runs = 0u32;
    loop {
        let bytes = v.fill(HEADER_MAX_BYTES);
        if bytes.is_empty() {
            break;
        }
        let Ok((h, rest)) = postcard::take_from_bytes::<Header>(bytes) else {
            fail(EXIT_BAD_FILE, "a run's header does not decode");
        };
        let used = bytes.len() - rest.len();
        if h.version != VERSION {
            fail(EXIT_BAD_FILE, "another format version");
        }
        if config_fingerprint(h.config) != h.config_crc {
            fail(
                EXIT_BAD_CONFIG,
                "the configuration's CRC does not match its bytes",
            );
        }
        let (crc, steps, mode, start) = (h.config_crc, h.steps, h.mode, h.start);
        let label = copy_label(h.label);
        let (k, sc) = match &k_built {
            Some((c, k, sc)) if *c == crc => (*k, *sc),
            Some(_) => fail(
                EXIT_BAD_CONFIG,
                "one configuration per file (the coefficients are built once, into place)",
            ),
            None => {
                let Ok(cfg) = decode_config(h.config) else {
                    fail(EXIT_BAD_CONFIG, "the configuration does not decode");
                };
                let k = zeroed_coefficients();
                repaint_free_stack();
                let sp = stack_pointer();
                let c0 = timer::now();
                let built = cfg.coefficients_into(k);
                let c1 = timer::now();
                let build_stack = sp.saturating_sub(stack_reach().0);
                let k: &'static Coefficients = match built {
                    Ok(()) => k,
                    Err(e) => {
                        println!(
                            "FAILED: configuration refused: {} = {} (allowed {} ..= {})",
                            e.field, e.value, e.min, e.max
                        );
                        process::exit(EXIT_BAD_CONFIG)
                    }
                };
                let Ok(sc) = SchedulerConfig::default().coefficients(k) else {
                    fail(EXIT_BAD_CONFIG, "the scheduler refused the coefficients");
                };
                println!(
                    "coefficients bytes={} build_instructions={} build_stack_bytes={}",
                    core::mem::size_of::<Coefficients>(),
                    instructions(c1.wrapping_sub(c0)).saturating_sub(overhead),
                    build_stack
                );
                k_built = Some((crc, k, sc));
                (k, sc)
            }
        };
        v.consume(used);

        let mut s = State::new(start[0], start[1], start[2]);
        let mut st = SchedulerState::default();
        let (mut sum, mut max, mut max_at) = (0u64, 0u32, 0u32);
        for i in 0..steps {
            let bytes = v.fill(RECORD_MAX_BYTES);
            let Ok((r, rest)) = postcard::take_from_bytes::<Record>(bytes) else {
                fail(EXIT_BAD_FILE, "a record does not decode (file truncated?)");
            };
            let used = bytes.len() - rest.len();
            v.consume(used);
            let t0 = timer::now();
            let (e, c) = step(k, &sc, &mut s, &mut st, mode, &r.inputs);
            let t1 = timer::now();
            let n = instructions(t1.wrapping_sub(t0)).saturating_sub(overhead) as u32;
            sum += u64::from(n);
            if n > max {
                (max, max_at) = (n, i);
            }
            let got = checked_words(&e, &c);
            if let Some(j) = first_difference(&got, &r.want) {
                println!(
                    "MISMATCH {}: step {}, {}: got {} want {}",
                    label.as_str(),
                    i,
                    CHECKED[j],
                    got[j],
                    r.want[j]
                );
                process::exit(EXIT_MISMATCH);
            }
        }
        println!(
            "run steps={} sum={} max={} max_at={} label={}",
            steps,
            sum,
            max,
            max_at,
            label.as_str()
        );
        runs += 1;
    }
    if runs == 0 {
        fail(EXIT_BAD_FILE, "no run in the file");
    }
    let (lowest, top) = stack_reach();
    println!("stack bytes={}", top - lowest);
    process::exit(EXIT_MATCH)
}

/// A run's label, copied out of the read buffer (which the records overwrite); cut at 64
/// bytes.
fn copy_label(s: &str) -> heapless::String<64> {
    let mut l = heapless::String::new();
    for ch in s.chars() {
        if l.push(ch).is_err() {
            break;
        }
    }
    l
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    println!("PANIC: {}", info);
    process::exit(EXIT_PANIC)
}
