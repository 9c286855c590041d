//! Running the firmware under QEMU (built by [`super::build`]): boot it on `netduinoplus2`,
//! decode its defmt log with the ELF's table, and talk to it over USART1 (a Unix socket) with
//! the protocol frames.
//!
//! Every QEMU child is owned by a [`Qemu`], whose `Drop` kills and reaps it, pass or fail.

pub use super::link::{Link, LinkError};
use defmt_decoder::Table;
use pto_model::protocol::{LinkCounts, Status, ToFirmware};
use std::io::Read;
use std::os::unix::net::UnixStream;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Why QEMU could not boot the firmware, or did not end as asked.
#[derive(Debug, thiserror::Error)]
pub enum QemuError {
    /// The ELF could not be read.
    #[error("cannot read {elf}")]
    ReadElf {
        /// The ELF.
        elf: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The ELF's defmt table could not be parsed.
    #[error("{elf}: bad defmt table")]
    DefmtTable {
        /// The ELF.
        elf: PathBuf,
        /// The decoder's error.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The ELF has no defmt table.
    #[error("{elf}: no defmt table")]
    NoDefmtTable {
        /// The ELF.
        elf: PathBuf,
    },
    /// `qemu-system-arm` could not be started (shown in the message, with how to install it).
    #[error(
        "cannot start qemu-system-arm ({error}); install it with `apt-get install -y \
         qemu-system-arm`"
    )]
    Start {
        /// The OS error.
        error: std::io::Error,
    },
    /// A pipe to QEMU was not set up.
    #[error("no QEMU {0}")]
    NoPipe(&'static str),
    /// QEMU exited before the firmware's USART was connected.
    #[error("QEMU exited before the link was up ({status}): {said}")]
    ExitedEarly {
        /// Its exit status.
        status: ExitStatus,
        /// What it wrote to stderr.
        said: String,
    },
    /// The USART's socket did not accept a connection within 20 s.
    #[error("cannot connect to {sock}")]
    Connect {
        /// The socket.
        sock: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The firmware's greeting failed.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// Waiting for QEMU failed.
    #[error("waiting for QEMU")]
    Wait(#[source] std::io::Error),
    /// QEMU was ended by a signal.
    #[error("QEMU ended by {0}")]
    Signalled(ExitStatus),
    /// QEMU did not exit in time.
    #[error("QEMU still running after {0:?}")]
    StillRunning(Duration),
}

/// QEMU arguments for an instruction trace when `PTO_QEMU_TRACE=<file>` is set: every translated
/// block and every execution of one is logged there (`-d exec,nochain,in_asm`), which
/// `scripts/profile-step` turns into instructions per step by function and source line. Several
/// GB for a `pto fw-cost` run; off unless asked for.
fn trace_args() -> Vec<String> {
    std::env::var("PTO_QEMU_TRACE").map_or_else(
        |_| Vec::new(),
        |file| vec!["-d".into(), "exec,nochain,in_asm".into(), "-D".into(), file],
    )
}

/// One decoded defmt line.
#[derive(Debug, Clone)]
pub struct LogLine {
    /// Level (`INFO`, `WARN`, …).
    pub level: String,
    /// Message.
    pub text: String,
}

impl std::fmt::Display for LogLine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:<5} {}", self.level, self.text)
    }
}

/// A running firmware under QEMU.
pub struct Qemu {
    child: Child,
    sock: PathBuf,
    log: Arc<Mutex<Vec<LogLine>>>,
    reader: Option<JoinHandle<()>>,
    /// The firmware's USART1, the twin's hardware port (sensor frames in, each step's output
    /// back; it also takes every command).
    pub link: Link,
    /// The pseudo-terminal of USART2, the bench link, when booted with [`Qemu::boot_twin`].
    pub pty: Option<PathBuf>,
    /// What QEMU itself wrote to stderr.
    stderr: Arc<Mutex<String>>,
}

impl Qemu {
    /// QEMU's process id (a test's watchdog can end a session the host side waits on).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }
}

static SEQ: AtomicU32 = AtomicU32::new(0);

/// Every running QEMU child (its process id, which is also its process group's, and its
/// socket), for the interrupt handler.
static RUNNING: Mutex<Vec<(u32, PathBuf)>> = Mutex::new(Vec::new());

/// Ends every QEMU child this process started (SIGKILL to its process group, then reaps it) and
/// removes its socket. Children are also ended by [`Qemu`]'s `Drop`; this is for the paths that
/// skip it: SIGINT and SIGTERM (`output::install_interrupt_handler`).
pub fn end_all_children() {
    use nix::sys::signal::{Signal, killpg};
    use nix::sys::wait::waitpid;
    use nix::unistd::Pid;
    let running = std::mem::take(&mut *RUNNING.lock().unwrap_or_else(|e| e.into_inner()));
    for (pid, sock) in running {
        let pid = Pid::from_raw(pid as i32);
        let _ = killpg(pid, Signal::SIGKILL);
        let _ = waitpid(pid, None);
        let _ = std::fs::remove_file(&sock);
    }
}

/// QEMU options: instruction counting (one virtual ns per instruction, TIM2 counts
/// instructions) without sleeping, so that idle time costs no wall time.
pub const ICOUNT: &str = "shift=0,align=off,sleep=off";

impl Qemu {
    /// Boots `elf`; `echo` prints every log line to stderr as it arrives.
    pub fn boot(elf: &Path, echo: bool) -> Result<Qemu, QemuError> {
        Self::boot_with(elf, echo, false)
    }

    /// Boots `elf` as the bench's twin: USART1 on a socket (the hardware port, [`Qemu::link`])
    /// and USART2, the bench link, on a pseudo-terminal ([`Qemu::pty`]) for `pto link`.
    pub fn boot_twin(elf: &Path, echo: bool) -> Result<Qemu, QemuError> {
        Self::boot_with(elf, echo, true)
    }

    fn boot_with(elf: &Path, echo: bool, pty: bool) -> Result<Qemu, QemuError> {
        let bytes = std::fs::read(elf).map_err(|source| QemuError::ReadElf {
            elf: elf.to_path_buf(),
            source,
        })?;
        let table = Table::parse(&bytes)
            .map_err(|e| QemuError::DefmtTable {
                elf: elf.to_path_buf(),
                source: e.into(),
            })?
            .ok_or_else(|| QemuError::NoDefmtTable {
                elf: elf.to_path_buf(),
            })?;
        let sock = std::env::temp_dir().join(format!(
            "pto-qemu-{}-{}.sock",
            std::process::id(),
            SEQ.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_file(&sock);
        let mut child = Command::new("qemu-system-arm")
            .args(["-M", "netduinoplus2", "-nographic", "-monitor", "none"])
            .args(["-semihosting-config", "enable=on,target=native"])
            .args(["-icount", ICOUNT])
            .args(trace_args())
            .arg("-chardev")
            .arg(format!(
                "socket,id=u0,path={},server=on,wait=on",
                sock.display()
            ))
            .args(["-serial", "chardev:u0"])
            .args(if pty { &["-serial", "pty"][..] } else { &[] })
            .arg("-kernel")
            .arg(elf)
            // Its own process group: a terminal's Ctrl-C reaches `pto`, which ends it (and
            // `end_all_children` kills the whole group).
            .process_group(0)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|error| QemuError::Start { error })?;
        if let Ok(mut r) = RUNNING.lock() {
            r.push((child.id(), sock.clone()));
        }
        let mut stdout = child.stdout.take().ok_or(QemuError::NoPipe("stdout"))?;
        // QEMU's own messages (the "waiting for connection" note, errors): kept for error reports.
        let mut stderr = child.stderr.take().ok_or(QemuError::NoPipe("stderr"))?;
        let errors = Arc::new(Mutex::new(String::new()));
        let errors2 = errors.clone();
        let stderr_kept = errors.clone();
        std::thread::spawn(move || {
            let mut s = String::new();
            let _ = stderr.read_to_string(&mut s);
            if let Ok(mut g) = errors2.lock() {
                g.push_str(&s);
            }
        });
        let (pty_tx, pty_rx) = std::sync::mpsc::channel::<PathBuf>();
        let qemu_said = move || {
            errors
                .lock()
                .map(|g| g.trim().to_string())
                .unwrap_or_default()
        };
        let log = Arc::new(Mutex::new(Vec::new()));
        let log2 = log.clone();
        let reader = std::thread::spawn(move || {
            if pty {
                // QEMU's first line on stdout (before the guest runs): "char device redirected
                // to /dev/pts/3 (label serial1)"; the defmt stream follows.
                let mut line = Vec::new();
                let mut b = [0u8; 1];
                while let Ok(1) = stdout.read(&mut b) {
                    if b[0] == b'\n' {
                        break;
                    }
                    line.push(b[0]);
                }
                let line = String::from_utf8_lossy(&line);
                if let Some(rest) = line.split("redirected to ").nth(1)
                    && let Some(path) = rest.split_whitespace().next()
                {
                    let _ = pty_tx.send(PathBuf::from(path));
                }
            }
            drop(pty_tx);
            let mut dec = table.new_stream_decoder();
            let mut buf = [0u8; 4096];
            while let Ok(n) = stdout.read(&mut buf) {
                if n == 0 {
                    break;
                }
                dec.received(&buf[..n]);
                loop {
                    match dec.decode() {
                        Ok(f) => {
                            let line = LogLine {
                                level: f
                                    .level()
                                    .map_or("PRINT".into(), |l| l.as_str().to_uppercase()),
                                text: f.display_message().to_string(),
                            };
                            if echo {
                                eprintln!("[fw] {line}");
                            }
                            if let Ok(mut g) = log2.lock() {
                                g.push(line);
                            }
                        }
                        Err(defmt_decoder::DecodeError::UnexpectedEof) => break,
                        Err(defmt_decoder::DecodeError::Malformed) => {
                            if let Ok(mut g) = log2.lock() {
                                g.push(LogLine {
                                    level: "ERROR".into(),
                                    text: "(malformed defmt frame)".into(),
                                });
                            }
                            break;
                        }
                    }
                }
            }
        });
        // QEMU waits for the connection before it starts the guest.
        let t0 = Instant::now();
        let stream = loop {
            match UnixStream::connect(&sock) {
                Ok(s) => break s,
                Err(e) => {
                    if let Ok(Some(st)) = child.try_wait() {
                        forget(child.id());
                        let _ = std::fs::remove_file(&sock);
                        std::thread::sleep(Duration::from_millis(50));
                        return Err(QemuError::ExitedEarly {
                            status: st,
                            said: qemu_said(),
                        });
                    }
                    if t0.elapsed() > Duration::from_secs(20) {
                        forget(child.id());
                        let _ = child.kill();
                        let _ = child.wait();
                        return Err(QemuError::Connect {
                            sock: sock.clone(),
                            source: e,
                        });
                    }
                    std::thread::sleep(Duration::from_millis(10));
                }
            }
        };
        // QEMU names the pseudo-terminal once the socket is connected, before the guest runs.
        let pty_path = if pty {
            pty_rx.recv_timeout(Duration::from_secs(10)).ok()
        } else {
            None
        };
        let mut q = Qemu {
            child,
            sock,
            log,
            reader: Some(reader),
            link: Link::new(Box::new(stream)),
            pty: pty_path,
            stderr: stderr_kept,
        };
        if pty && q.pty.is_none() {
            // `q`'s Drop ends and reaps QEMU.
            return Err(QemuError::NoPipe("pseudo-terminal for USART2"));
        }
        // The firmware's boot `Hello`, then a session of our own (its count of our sequence
        // numbers starts from our `Hello`).
        q.link.hello()?;
        q.link.send(&ToFirmware::Hello)?;
        q.link.hello()?;
        Ok(q)
    }

    /// What QEMU itself wrote to stderr so far (its own errors; the firmware logs to stdout).
    pub fn qemu_stderr(&self) -> String {
        self.stderr.lock().map(|g| g.clone()).unwrap_or_default()
    }

    /// QEMU is still running.
    pub fn running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// Log lines decoded so far.
    pub fn log(&self) -> Vec<LogLine> {
        self.log.lock().map(|g| g.clone()).unwrap_or_default()
    }

    /// Waits for QEMU to exit (wall-clock `timeout`); returns its exit code. The log reader is
    /// joined so that [`Qemu::log`] then holds every line.
    pub fn wait_exit(&mut self, timeout: Duration) -> Result<i32, QemuError> {
        let t0 = Instant::now();
        loop {
            if let Some(st) = self.child.try_wait().map_err(QemuError::Wait)? {
                if let Some(r) = self.reader.take() {
                    let _ = r.join();
                }
                return st.code().ok_or(QemuError::Signalled(st));
            }
            if t0.elapsed() > timeout {
                return Err(QemuError::StillRunning(timeout));
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

/// Puts a QEMU child started elsewhere (in its own process group) on the interrupt handler's
/// list; [`forget`] takes it off once reaped.
pub(crate) fn track(pid: u32) {
    if let Ok(mut r) = RUNNING.lock() {
        r.push((pid, PathBuf::new()));
    }
}

/// Takes a child off the interrupt handler's list (it has been or is being reaped: its pid may
/// be reused).
pub(crate) fn forget(pid: u32) {
    if let Ok(mut r) = RUNNING.lock() {
        r.retain(|(p, _)| *p != pid);
    }
}

impl Drop for Qemu {
    fn drop(&mut self) {
        forget(self.child.id());
        let _ = self.child.kill();
        let _ = self.child.wait();
        if let Some(r) = self.reader.take() {
            let _ = r.join();
        }
        let _ = std::fs::remove_file(&self.sock);
    }
}

/// The firmware's status and the host's link counts as a labelled table, one quantity a line.
pub fn status_table(st: &Status, host: &LinkCounts) -> String {
    let mean = if st.steps == 0 {
        0.0
    } else {
        st.step_cost_sum as f64 / f64::from(st.steps)
    };
    let link = |who: &str, c: &LinkCounts| {
        format!(
            "{who:<28} {:>10} taken, {} dropped (COBS {}, CRC {}, payload {}, too long {}), \
             {} lost, {} out of order\n",
            c.ok,
            c.dropped(),
            c.cobs,
            c.crc,
            c.payload,
            c.too_long,
            c.lost,
            c.out_of_order
        )
    };
    let mut s = String::new();
    s += &link("frames host → firmware", &st.link);
    s += &link("frames firmware → host", host);
    s += &format!(
        "{:<28} {:>10} (the control loop had not taken the previous ones)\n",
        "sensor frames overrun", st.frames_overrun
    );
    s += &format!("{:<28} {:>10}\n", "received bytes lost", st.bytes_lost);
    s += &format!(
        "{:<28} {:>10} (the host sent commands faster than it read their replies)\n",
        "replies dropped", st.replies_dropped
    );
    s += &format!(
        "{:<28} {:>10} (sample periods the controller stalled through: flash erases)\n",
        "sample periods missed", st.samples_missed
    );
    s += &format!(
        "{:<28} {:>10} (the link's transmit queue was full: rate above the baud rate's)\n",
        "telemetry frames dropped", st.telemetry_dropped
    );
    s += &format!("{:<28} {:>10}\n", "estimator steps", st.steps);
    s += &format!(
        "{:<28} {:>10} B (never used since boot)\n",
        "stack unused", st.stack_unused
    );
    s += &format!(
        "{:<28} {:>10} (steps with the HP loop outside 4–20 mA)\n",
        "HP loop faults", st.hp_loop_faults
    );
    s += &format!(
        "{:<28} {:>10} (samples whose measured ADC reference was implausible)\n",
        "supply faults", st.supply_faults
    );
    s += &format!("{:<28} {:>#10x}\n", "fault flags seen", st.faults_seen);
    let held: Vec<String> = pto_firmware::sensor_faults::described(st.sensor_faults)
        .map(|(n, why)| format!("{n}: {why}"))
        .collect();
    s += &format!(
        "{:<28} {:>10}\n",
        "sensor faults held",
        if held.is_empty() {
            "none".to_string()
        } else {
            format!(
                "{} (valve at the sensor-fault aperture; `clear-faults` once they agree)",
                held.join("; ")
            )
        }
    );
    s += &format!(
        "{:<28} {:>10} (now {}; dump valve {})\n",
        "overpressure trips",
        st.trips,
        if st.tripped { "TRIPPED" } else { "armed" },
        if st.dump_valve { "open" } else { "closed" }
    );
    s += &format!(
        "{:<28} {:>10.2} %\n",
        "valve aperture applied",
        st.aperture.to_f32()
    );
    s += &format!(
        "{:<28} {:>10} last, {} max, {mean:.0} mean (instructions under QEMU, cycles on the \
         bench)\n",
        "model step cost", st.step_cost_last, st.step_cost_max
    );
    s
}
