//! `pto link` against ports that are not a controller: each failure is a clear error (exit 2)
//! naming what to check, never a hang. A pseudo-terminal stands in for the serial port.

use crate::common::pto;
use nix::pty::openpty;
use pto_model::protocol::{self, FromFirmware, Hello, MAX_FRAME, PROTOCOL_VERSION, SCHEMA_HASH};
use std::io::{Read, Write};
use std::os::fd::OwnedFd;
use std::process::Output;
use std::time::{Duration, Instant};

/// A pseudo-terminal pair: the master end (ours), the slave (held open, raw, so that the
/// master's reads do not fail between `pto`'s opens) and the slave's path (the "serial port").
fn pty() -> (OwnedFd, OwnedFd, String) {
    let p = openpty(None, None).expect("openpty");
    let path = nix::unistd::ttyname(&p.slave).expect("ttyname");
    make_raw(&p.slave);
    (p.master, p.slave, path.display().to_string())
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn make_raw(fd: &OwnedFd) {
    use nix::sys::termios::{SetArg, cfmakeraw, tcgetattr, tcsetattr};
    let mut t = tcgetattr(fd).unwrap();
    cfmakeraw(&mut t);
    tcsetattr(fd, SetArg::TCSANOW, &t).unwrap();
}

#[test]
fn a_missing_port_is_named() {
    let t0 = Instant::now();
    let o = pto()
        .args(["link", "--port", "/dev/no-such-port", "status"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let e = stderr(&o);
    assert!(e.contains("serial port /dev/no-such-port not found"), "{e}");
    assert!(t0.elapsed() < Duration::from_secs(5));
}

#[test]
fn a_file_that_is_not_a_serial_port_is_named() {
    let f = std::env::temp_dir().join(format!("pto-not-a-port-{}", std::process::id()));
    std::fs::write(&f, "").unwrap();
    let o = pto()
        .args(["link", "--port"])
        .arg(&f)
        .arg("status")
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let e = stderr(&o);
    assert!(
        e.contains("not a serial port (not a character device)"),
        "{e}"
    );
    let _ = std::fs::remove_file(&f);
}

#[test]
fn a_silent_port_times_out_with_what_to_check() {
    let (master, _slave, path) = pty();
    make_raw(&master);
    let t0 = Instant::now();
    let o = pto()
        .args(["link", "--port", &path, "status"])
        .output()
        .unwrap();
    let wall = t0.elapsed();
    assert_eq!(o.status.code(), Some(2));
    let e = stderr(&o);
    assert!(
        e.contains(&format!("no answer from the firmware on {path} within 3s"))
            && e.contains("baud rate (230400)"),
        "{e}"
    );
    println!("silent port: gave up after {:.1} s", wall.as_secs_f64());
    assert!(wall < Duration::from_secs(8));
    drop(master);
}

/// A "firmware" that answers every frame with a `Hello` of protocol v2.
#[test]
fn a_firmware_of_another_protocol_is_refused() {
    let (master, _slave, path) = pty();
    make_raw(&master);
    let mut m = std::fs::File::from(master);
    let _keep = _slave;
    let mut w = m.try_clone().unwrap();
    std::thread::spawn(move || {
        let mut b = [0u8; 256];
        while let Ok(n) = m.read(&mut b) {
            if n == 0 {
                break;
            }
            if b[..n].contains(&0) {
                let mut f = [0u8; MAX_FRAME];
                let hello = FromFirmware::Hello(Hello {
                    protocol: PROTOCOL_VERSION - 1,
                    schema: SCHEMA_HASH,
                    firmware: 0x0100,
                    dt_log2: 10,
                });
                let k = protocol::encode(0, &hello, &mut f).unwrap();
                if w.write_all(&f[..k]).is_err() {
                    break;
                }
            }
        }
    });
    let o = pto()
        .args(["link", "--port", &path, "status"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let e = stderr(&o);
    assert!(
        e.contains(&format!(
            "protocol mismatch: the other end speaks v{}",
            PROTOCOL_VERSION - 1
        )) && e.contains("build the firmware and the host tools from the same revision"),
        "{e}"
    );
}

#[test]
fn bad_values_are_refused_before_anything_is_sent() {
    let cases: [(&[&str], &str); 5] = [
        (
            &["mode", "fixed", "150"],
            "mode fixed 150: outside [0, 100] %",
        ),
        (&["mode", "open", "10"], "want fixed PCT, hold-pressure BAR"),
        (&["duty", "--on", "10x1"], "want four 0/1 characters"),
        (
            &["duty", "--on", "1001", "--config", "5"],
            "want 1, 2, 3 or 4",
        ),
        (
            &["reset", "--p2", "-3", "--lp", "8"],
            "--p2 -3: outside [0, 400] bar",
        ),
    ];
    for (args, want) in cases {
        let o = pto()
            .args(["link", "--port", "/dev/not-opened"])
            .args(args)
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(2), "{args:?}");
        let e = stderr(&o);
        assert!(e.contains(want), "{args:?}: {e}");
    }
    // A configuration outside its ranges names the field; nothing is sent.
    let dir = std::env::temp_dir().join(format!("pto-link-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let f = dir.join("bad.model.toml");
    let mut cfg = pto_model::ModelConfig::reference();
    cfg.trapped_air_fraction = 0.9;
    std::fs::write(&f, toml::to_string(&cfg).unwrap()).unwrap();
    let o = pto()
        .args(["link", "--port", "/dev/not-opened", "config", "upload"])
        .arg(&f)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let e = stderr(&o);
    assert!(
        e.contains("bad.model.toml: trapped_air_fraction: 0.9 outside"),
        "{e}"
    );
    let junk = dir.join("junk.toml");
    std::fs::write(&junk, "x = 1\n").unwrap();
    let o = pto()
        .args(["link", "--port", "/dev/not-opened", "config", "upload"])
        .arg(&junk)
        .output()
        .unwrap();
    let e = stderr(&o);
    assert!(
        o.status.code() == Some(2) && e.contains("is neither a model configuration"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
