//! Running the firmware under QEMU: build it, boot it on `netduinoplus2`, decode its defmt log
//! with the ELF's table, and talk to it over USART1 (a Unix socket) with the protocol frames.
//!
//! Every QEMU child is owned by a [`Qemu`], whose `Drop` kills and reaps it, pass or fail.

use defmt_decoder::Table;
use pto_model::protocol::{self, FromFirmware, MAX_FRAME, ToFirmware};
use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Which firmware build.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Build {
    /// QEMU board (default features).
    Qemu,
    /// Real bench board (`--no-default-features --features bench`); built, never run here.
    Bench,
}

impl Build {
    /// Short name.
    pub fn name(self) -> &'static str {
        match self {
            Build::Qemu => "qemu",
            Build::Bench => "bench",
        }
    }
}

/// The workspace root.
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
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

static BUILT: [OnceLock<Result<PathBuf, String>>; 2] = [OnceLock::new(), OnceLock::new()];

/// Builds the firmware (profile `firmware`, `thumbv7em-none-eabihf`, its own target directory so that it
/// can run inside `cargo test`) once per process and returns the ELF path.
pub fn build(which: Build) -> Result<PathBuf, String> {
    BUILT[which as usize]
        .get_or_init(|| build_uncached(which))
        .clone()
}

fn build_uncached(which: Build) -> Result<PathBuf, String> {
    let root = workspace_root();
    let target_dir = root.join("target").join("fw").join(which.name());
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.current_dir(&root).args([
        "build",
        "--profile",
        "firmware",
        "-p",
        "pto-firmware",
        "--target",
        "thumbv7em-none-eabihf",
        "--target-dir",
    ]);
    cmd.arg(&target_dir);
    if which == Build::Bench {
        cmd.args(["--no-default-features", "--features", "bench"]);
    }
    let out = cmd
        .output()
        .map_err(|e| format!("cannot run cargo to build the firmware: {e}"))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = err.lines().rev().take(30).collect();
        return Err(format!(
            "firmware build ({}) failed (is the target installed? `rustup target add \
             thumbv7em-none-eabihf`):\n{}",
            which.name(),
            tail.into_iter().rev().collect::<Vec<_>>().join("\n")
        ));
    }
    Ok(target_dir
        .join("thumbv7em-none-eabihf")
        .join("firmware")
        .join("pto-firmware"))
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
    /// The firmware's USART1.
    pub link: Link,
}

static SEQ: AtomicU32 = AtomicU32::new(0);

/// QEMU options: instruction counting (one virtual ns per instruction, TIM2 counts
/// instructions) without sleeping, so that idle time costs no wall time.
pub const ICOUNT: &str = "shift=0,align=off,sleep=off";

impl Qemu {
    /// Boots `elf`; `echo` prints every log line to stderr as it arrives.
    pub fn boot(elf: &Path, echo: bool) -> Result<Qemu, String> {
        let bytes =
            std::fs::read(elf).map_err(|e| format!("cannot read {}: {e}", elf.display()))?;
        let table = Table::parse(&bytes)
            .map_err(|e| format!("{}: bad defmt table: {e}", elf.display()))?
            .ok_or_else(|| format!("{}: no defmt table", elf.display()))?;
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
            .args(["-serial", "chardev:u0", "-kernel"])
            .arg(elf)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| {
                format!(
                    "cannot start qemu-system-arm ({e}); install it with `apt-get install -y \
                     qemu-system-arm`"
                )
            })?;
        let mut stdout = child.stdout.take().ok_or("no QEMU stdout")?;
        // QEMU's own messages (the "waiting for connection" note, errors): kept for error reports.
        let mut stderr = child.stderr.take().ok_or("no QEMU stderr")?;
        let errors = Arc::new(Mutex::new(String::new()));
        let errors2 = errors.clone();
        std::thread::spawn(move || {
            let mut s = String::new();
            let _ = stderr.read_to_string(&mut s);
            if let Ok(mut g) = errors2.lock() {
                g.push_str(&s);
            }
        });
        let qemu_said = move || {
            errors
                .lock()
                .map(|g| g.trim().to_string())
                .unwrap_or_default()
        };
        let log = Arc::new(Mutex::new(Vec::new()));
        let log2 = log.clone();
        let reader = std::thread::spawn(move || {
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
                        std::thread::sleep(Duration::from_millis(50));
                        return Err(format!(
                            "QEMU exited before the link was up ({st}): {}",
                            qemu_said()
                        ));
                    }
                    if t0.elapsed() > Duration::from_secs(20) {
                        let _ = child.kill();
                        let _ = child.wait();
                        return Err(format!("cannot connect to {}: {e}", sock.display()));
                    }
                    std::thread::sleep(Duration::from_millis(10));
                }
            }
        };
        let mut q = Qemu {
            child,
            sock,
            log,
            reader: Some(reader),
            link: Link::new(stream)?,
        };
        match q.link.recv()? {
            FromFirmware::Ready { .. } => {}
            other => return Err(format!("expected Ready first, got {other:?}")),
        }
        Ok(q)
    }

    /// Log lines decoded so far.
    pub fn log(&self) -> Vec<LogLine> {
        self.log.lock().map(|g| g.clone()).unwrap_or_default()
    }

    /// Waits for QEMU to exit (wall-clock `timeout`); returns its exit code. The log reader is
    /// joined so that [`Qemu::log`] then holds every line.
    pub fn wait_exit(&mut self, timeout: Duration) -> Result<i32, String> {
        let t0 = Instant::now();
        loop {
            if let Some(st) = self
                .child
                .try_wait()
                .map_err(|e| format!("waiting for QEMU: {e}"))?
            {
                if let Some(r) = self.reader.take() {
                    let _ = r.join();
                }
                return st.code().ok_or_else(|| format!("QEMU ended by {st}"));
            }
            if t0.elapsed() > timeout {
                return Err(format!("QEMU still running after {timeout:?}"));
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

impl Drop for Qemu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if let Some(r) = self.reader.take() {
            let _ = r.join();
        }
        let _ = std::fs::remove_file(&self.sock);
    }
}

/// The host end of the firmware's USART.
pub struct Link {
    stream: UnixStream,
    pending: Vec<u8>,
    /// Wall-clock limit on one reply.
    pub timeout: Duration,
}

impl Link {
    fn new(stream: UnixStream) -> Result<Self, String> {
        Ok(Link {
            stream,
            pending: Vec::new(),
            timeout: Duration::from_secs(30),
        })
    }

    /// The bytes of a frame as the host sends it: a leading 0 (resynchronises after a
    /// truncated frame), the COBS frame, its 0 terminator.
    pub fn frame(msg: &ToFirmware) -> Vec<u8> {
        let mut b = [0u8; MAX_FRAME];
        let n = protocol::encode(msg, &mut b).expect("host messages fit a frame");
        let mut v = Vec::with_capacity(n + 1);
        v.push(0);
        v.extend_from_slice(&b[..n]);
        v
    }

    /// Sends a message.
    pub fn send(&mut self, msg: &ToFirmware) -> Result<(), String> {
        self.send_raw(&Self::frame(msg))
    }

    /// Sends raw bytes (corrupted or truncated frames in the fault tests).
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), String> {
        self.stream
            .write_all(bytes)
            .map_err(|e| format!("link write: {e}"))
    }

    /// Receives the next message (frames that fail to decode are an error: the firmware's
    /// replies must always be valid).
    pub fn recv(&mut self) -> Result<FromFirmware, String> {
        let t0 = Instant::now();
        let mut buf = [0u8; 4096];
        loop {
            if let Some(end) = self.pending.iter().position(|b| *b == 0) {
                let frame: Vec<u8> = self.pending.drain(..=end).collect();
                if frame.len() == 1 {
                    continue;
                }
                return protocol::decode::<FromFirmware>(&frame)
                    .map_err(|e| format!("bad frame from the firmware: {e}"));
            }
            let left = self.timeout.saturating_sub(t0.elapsed());
            if left.is_zero() {
                return Err(format!("no reply from the firmware in {:?}", self.timeout));
            }
            self.stream
                .set_read_timeout(Some(left))
                .map_err(|e| format!("link: {e}"))?;
            match self.stream.read(&mut buf) {
                Ok(0) => return Err("the firmware closed the link (QEMU exited?)".into()),
                Ok(n) => self.pending.extend_from_slice(&buf[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    return Err(format!("no reply from the firmware in {:?}", self.timeout));
                }
                Err(e) => return Err(format!("link read: {e}")),
            }
        }
    }

    /// Sends `msg` and returns the first reply `pick` accepts, failing on anything else
    /// arriving first.
    pub fn request<T>(
        &mut self,
        msg: &ToFirmware,
        pick: impl Fn(&FromFirmware) -> Option<T>,
    ) -> Result<T, String> {
        self.send(msg)?;
        let r = self.recv()?;
        pick(&r).ok_or_else(|| format!("unexpected reply to {msg:?}: {r:?}"))
    }
}
