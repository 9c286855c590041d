//! An interrupted `pto` leaves nothing behind: SIGINT (Ctrl-C) or SIGTERM while `pto qemu
//! --follow` runs the firmware ends QEMU (its whole process group) and removes its socket; the
//! exit status is 130.

use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Pids of the qemu-system-arm processes started by `pto` process `pto` (their socket's name
/// carries its pid).
fn qemu_children_of(pto: u32) -> Vec<u32> {
    let tag = format!("pto-qemu-{pto}-");
    std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|pid| {
            std::fs::read(format!("/proc/{pid}/cmdline"))
                .is_ok_and(|c| String::from_utf8_lossy(&c).contains(&tag))
        })
        .collect()
}

fn sockets_of(pto: u32) -> Vec<std::path::PathBuf> {
    let tag = format!("pto-qemu-{pto}-");
    std::fs::read_dir(std::env::temp_dir())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with(&tag))
        .map(|e| e.path())
        .collect()
}

fn interrupt_while_following(signal: Signal) {
    let mut pto = Command::new(env!("CARGO_BIN_EXE_pto"))
        .args(["qemu", "--follow"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let pid = pto.id();
    // Wait for the firmware to answer (the build may take a while on a cold tree).
    let mut err = BufReader::new(pto.stderr.take().unwrap());
    let mut line = String::new();
    let t0 = Instant::now();
    loop {
        line.clear();
        assert!(
            err.read_line(&mut line).unwrap() > 0,
            "pto ended before the firmware ran"
        );
        if line.contains("following the firmware's log") {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(600),
            "no answer from the firmware"
        );
    }
    let qemu = qemu_children_of(pid);
    assert_eq!(qemu.len(), 1, "one QEMU running: {qemu:?}");
    assert_eq!(sockets_of(pid).len(), 1, "its socket");
    kill(Pid::from_raw(pid as i32), signal).unwrap();
    // Drain stderr so pto never blocks on it.
    std::thread::spawn(move || for _ in err.lines() {});
    let t0 = Instant::now();
    let status = loop {
        if let Some(st) = pto.try_wait().unwrap() {
            break st;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "pto did not exit on {signal}"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    let left = qemu_children_of(pid);
    println!(
        "{signal}: pto exited with {status} after {:.0} ms; QEMU processes left {left:?}, sockets \
         left {:?}",
        t0.elapsed().as_secs_f64() * 1e3,
        sockets_of(pid)
    );
    assert_eq!(status.code(), Some(130));
    assert!(left.is_empty(), "QEMU still running: {left:?}");
    assert!(sockets_of(pid).is_empty(), "socket left behind");
}

#[test]
fn ctrl_c_ends_qemu_and_removes_its_socket() {
    let _qemu = crate::common::beside_other_qemus();
    interrupt_while_following(Signal::SIGINT);
}

#[test]
fn sigterm_ends_qemu_and_removes_its_socket() {
    let _qemu = crate::common::beside_other_qemus();
    interrupt_while_following(Signal::SIGTERM);
}
