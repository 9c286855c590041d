//! The host end of the link to the firmware, over a real serial port (the `serialport` crate)
//! or the socket of a QEMU USART, behind one [`Port`] trait: the same frames, the same
//! [`Receiver`] counting what it drops, the same requests.

use pto_model::protocol::{self, FromFirmware, Hello, LinkCounts, MAX_FRAME, Receiver, ToFirmware};
use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// A byte stream to the firmware with a read timeout.
pub trait Port: Read + Write + Send {
    /// Sets the longest a read waits for a byte.
    fn set_timeout(&mut self, t: Duration) -> std::io::Result<()>;
}

impl Port for UnixStream {
    fn set_timeout(&mut self, t: Duration) -> std::io::Result<()> {
        self.set_read_timeout(Some(t.max(Duration::from_millis(1))))
    }
}

impl Port for Box<dyn serialport::SerialPort> {
    fn set_timeout(&mut self, t: Duration) -> std::io::Result<()> {
        serialport::SerialPort::set_timeout(self.as_mut(), t.max(Duration::from_millis(1)))
            .map_err(std::io::Error::other)
    }
}

/// The firmware's default baud rate on the bench (USART1, 8N1).
pub const DEFAULT_BAUD: u32 = 230_400;

/// Opens `port`: a serial device (`/dev/ttyUSB0`, `/dev/pts/3`, `COM3`) at `baud`, or
/// `unix:PATH` for a QEMU USART's socket.
pub fn open(port: &str, baud: u32) -> Result<Box<dyn Port>, LinkError> {
    if let Some(path) = port.strip_prefix("unix:") {
        let s = UnixStream::connect(path).map_err(|source| LinkError::Socket {
            path: path.into(),
            source,
        })?;
        return Ok(Box::new(s));
    }
    if !std::path::Path::new(port).exists() && !port.starts_with("COM") {
        return Err(LinkError::NoPort {
            port: port.into(),
            available: serialport::available_ports()
                .map(|v| v.into_iter().map(|p| p.port_name).collect())
                .unwrap_or_default(),
        });
    }
    {
        use std::os::unix::fs::FileTypeExt;
        if std::fs::metadata(port).is_ok_and(|m| !m.file_type().is_char_device()) {
            return Err(LinkError::Open {
                port: port.into(),
                reason: "not a serial port (not a character device)".into(),
            });
        }
    }
    let p = serialport::new(port, baud)
        .timeout(Duration::from_millis(100))
        .open_native()
        .map_err(|e| LinkError::Open {
            port: port.into(),
            reason: match e.kind() {
                serialport::ErrorKind::Io(std::io::ErrorKind::PermissionDenied) => format!(
                    "{e}: on Linux, add the user to the `dialout` group (then log in again)"
                ),
                serialport::ErrorKind::Io(std::io::ErrorKind::ResourceBusy) => {
                    format!("{e}: another program has it open")
                }
                _ => e.to_string(),
            },
        })?;
    // Exclusive (TIOCEXCL): a second `pto link` on the same port fails at once.
    let mut p = p;
    serialport::TTYPort::set_exclusive(&mut p, true).map_err(|e| LinkError::Open {
        port: port.into(),
        reason: e.to_string(),
    })?;
    let b: Box<dyn serialport::SerialPort> = Box::new(p);
    Ok(Box::new(b))
}

/// Reads until the pong numbered `nonce`, within the link's timeout.
fn drain_to_pong(link: &mut Link, nonce: u32) -> Result<(), LinkError> {
    let deadline = Instant::now() + link.timeout;
    while Instant::now() < deadline {
        match link.recv() {
            Ok(FromFirmware::Pong(n)) if n == nonce => return Ok(()),
            Ok(_) | Err(LinkError::NoReply(_)) => {}
            Err(e) => return Err(e),
        }
    }
    Err(LinkError::NoReply(link.timeout))
}

fn available_hint(v: &[String]) -> String {
    if v.is_empty() {
        " (no serial ports found)".into()
    } else {
        format!(" (available: {})", v.join(", "))
    }
}

/// Starts a session on `port`: sends `Hello` until the firmware answers with its own (up to
/// `timeout`), and checks its protocol version and schema hash.
pub fn connect(port: &str, baud: u32, timeout: Duration) -> Result<(Link, Hello), LinkError> {
    let mut link = Link::new(open(port, baud)?);
    link.strict = false;
    let t0 = Instant::now();
    link.timeout = Duration::from_millis(300);
    while t0.elapsed() < timeout {
        link.send(&ToFirmware::Hello)?;
        while t0.elapsed() < timeout {
            match link.recv() {
                Ok(FromFirmware::Hello(h)) => {
                    h.check().map_err(LinkError::Protocol)?;
                    link.timeout = Duration::from_secs(5);
                    // Answers to our earlier `Hello`s (or a boot `Hello` still buffered) may
                    // follow: everything up to the answer to this ping is the past.
                    let nonce = 0x5a17_0000 | u32::from(link.seq);
                    link.send(&ToFirmware::Ping(nonce))?;
                    drain_to_pong(&mut link, nonce)?;
                    return Ok((link, h));
                }
                // Telemetry or an answer to another program's request: not ours.
                Ok(_) => continue,
                Err(LinkError::NoReply(_)) => break,
                Err(e) => return Err(e),
            }
        }
    }
    Err(LinkError::Silent {
        port: port.into(),
        baud,
        timeout,
    })
}

/// Why an exchange with the firmware over its link failed.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// The serial port does not exist.
    #[error("serial port {port} not found{}", available_hint(.available))]
    NoPort {
        /// The port asked for.
        port: String,
        /// The ports the system lists.
        available: Vec<String>,
    },
    /// The serial port exists but cannot be opened (busy, permissions, not a serial port).
    #[error("cannot open serial port {port}: {reason}")]
    Open {
        /// The port.
        port: String,
        /// What the OS said.
        reason: String,
    },
    /// The QEMU twin's socket cannot be connected.
    #[error("cannot connect to {path}")]
    Socket {
        /// The socket.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// No `Hello` from the firmware at connect.
    #[error(
        "no answer from the firmware on {port} within {timeout:?}: is it powered and flashed, \
         and is the baud rate ({baud}) the firmware's?"
    )]
    Silent {
        /// The port.
        port: String,
        /// The baud rate tried.
        baud: u32,
        /// How long it waited.
        timeout: Duration,
    },
    /// Sending failed.
    #[error("link write")]
    Write(#[source] std::io::Error),
    /// Setting the read timeout failed.
    #[error("link")]
    SetTimeout(#[source] std::io::Error),
    /// Receiving failed.
    #[error("link read")]
    Read(#[source] std::io::Error),
    /// No reply within the link's timeout.
    #[error("no reply from the firmware in {0:?}")]
    NoReply(Duration),
    /// The firmware closed its end.
    #[error("the firmware closed the link (QEMU exited?)")]
    Closed,
    /// A frame from the firmware failed to decode or was lost.
    #[error(
        "bad frame from the firmware (link counts now {0:?}); a firmware built from another \
         revision speaks another protocol: rebuild both"
    )]
    BadFrame(LinkCounts),
    /// The firmware speaks another protocol.
    #[error("{0}")]
    Protocol(protocol::HelloMismatch),
    /// Another message came where the firmware's `Hello` was due.
    #[error("expected the firmware's Hello, got {0:?}")]
    NotHello(Box<FromFirmware>),
    /// The firmware refused a command (nothing changed), with its reason.
    #[error("{0}")]
    Refused(pto_model::protocol::Refusal),
    /// A reply the request did not accept.
    #[error("unexpected reply to {sent:?}: {got:?}")]
    Unexpected {
        /// The request.
        sent: Box<ToFirmware>,
        /// The reply.
        got: Box<FromFirmware>,
    },
}

/// The host end of a link to the firmware (a serial port, or a QEMU USART's socket): numbers
/// the frames it sends, takes the firmware's through a [`Receiver`] that counts what it drops by
/// cause and the gaps in their numbers.
pub struct Link {
    stream: Box<dyn Port>,
    rx: Receiver<FromFirmware>,
    queue: std::collections::VecDeque<FromFirmware>,
    seq: u16,
    /// Wall-clock limit on one reply.
    pub timeout: Duration,
    /// Telemetry frames passed over while waiting for an answer.
    pub skipped: u64,
    /// A dropped or lost frame from the firmware is an error ([`LinkError::BadFrame`]): the
    /// lockstep harnesses, where every frame matters. The monitor clears it and reports the
    /// counts instead.
    pub strict: bool,
}

impl Link {
    /// A link over `stream`.
    pub fn new(stream: Box<dyn Port>) -> Self {
        Link {
            stream,
            rx: Receiver::new(),
            queue: std::collections::VecDeque::new(),
            seq: 0,
            timeout: Duration::from_secs(30),
            skipped: 0,
            strict: true,
        }
    }

    /// What the host's receiver took from the firmware and dropped, by cause.
    pub fn counts(&self) -> LinkCounts {
        self.rx.counts
    }

    /// The bytes of the next frame as the host sends it: a leading 0 (resynchronises after a
    /// truncated frame), the COBS frame numbered with the host's next sequence number, its 0
    /// terminator. Each call uses up a number (a frame the tests then damage counts as lost at
    /// the firmware).
    pub fn frame(&mut self, msg: &ToFirmware) -> Vec<u8> {
        let mut b = [0u8; MAX_FRAME];
        let n = protocol::encode(self.seq, msg, &mut b).expect("host messages fit a frame");
        self.seq = self.seq.wrapping_add(1);
        let mut v = Vec::with_capacity(n + 1);
        v.push(0);
        v.extend_from_slice(&b[..n]);
        v
    }

    /// Sends a message.
    pub fn send(&mut self, msg: &ToFirmware) -> Result<(), LinkError> {
        if matches!(msg, ToFirmware::Hello) {
            // A new session: numbered from 0 again.
            self.seq = 0;
        }
        let f = self.frame(msg);
        self.send_raw(&f)
    }

    /// Sends raw bytes (corrupted or truncated frames in the fault tests).
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.stream.write_all(bytes).map_err(LinkError::Write)
    }

    /// Receives the next message. A frame from the firmware that fails to decode is an error
    /// (its replies must always be valid), named with its cause.
    pub fn recv(&mut self) -> Result<FromFirmware, LinkError> {
        let t0 = Instant::now();
        let mut buf = [0u8; 4096];
        loop {
            if let Some(m) = self.queue.pop_front() {
                return Ok(m);
            }
            let left = self.timeout.saturating_sub(t0.elapsed());
            if left.is_zero() {
                return Err(LinkError::NoReply(self.timeout));
            }
            self.stream
                .set_timeout(left)
                .map_err(LinkError::SetTimeout)?;
            let n = match self.stream.read(&mut buf) {
                Ok(0) => return Err(LinkError::Closed),
                Ok(n) => n,
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    return Err(LinkError::NoReply(self.timeout));
                }
                // A signal (Ctrl-C asking a monitor to stop): read again until the timeout.
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(LinkError::Read(e)),
            };
            let before = self.rx.counts;
            for b in &buf[..n] {
                if let Some(m) = self.rx.push(*b) {
                    self.queue.push_back(m);
                }
            }
            let after = self.rx.counts;
            if self.strict && (after.dropped() != before.dropped() || after.lost != before.lost) {
                return Err(LinkError::BadFrame(after));
            }
        }
    }

    /// Receives the firmware's `Hello` and checks its protocol version and schema hash.
    pub fn hello(&mut self) -> Result<Hello, LinkError> {
        match self.recv()? {
            FromFirmware::Hello(h) => {
                h.check().map_err(LinkError::Protocol)?;
                Ok(h)
            }
            other => Err(LinkError::NotHello(Box::new(other))),
        }
    }

    /// Sends `msg` and returns the first reply `pick` accepts, failing on anything else
    /// arriving first.
    pub fn request<T>(
        &mut self,
        msg: &ToFirmware,
        pick: impl Fn(&FromFirmware) -> Option<T>,
    ) -> Result<T, LinkError> {
        self.send(msg)?;
        // One deadline for the answer, however much telemetry arrives meanwhile.
        let deadline = Instant::now() + self.timeout;
        let timeout = self.timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                self.timeout = timeout;
                return Err(LinkError::NoReply(timeout));
            }
            self.timeout = left;
            let r = self.recv();
            self.timeout = timeout;
            let r = r.map_err(|e| match e {
                LinkError::NoReply(_) => LinkError::NoReply(timeout),
                e => e,
            })?;
            if let FromFirmware::Telemetry(_) = r {
                // The bench link's stream goes on between a request and its answer.
                self.skipped = self.skipped.wrapping_add(1);
                continue;
            }
            return pick(&r).ok_or_else(|| LinkError::Unexpected {
                sent: Box::new(*msg),
                got: Box::new(r),
            });
        }
    }
}
