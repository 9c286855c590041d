//! The QEMU build boots, logs its version and configuration, answers a ping, exits on command.

use pto_host::hil::build::{self, Build};
use pto_host::hil::qemu::Qemu;
use pto_model::protocol::{FromFirmware, ToFirmware};
use std::time::Duration;

#[test]
fn boots_logs_answers_a_ping_and_exits_zero() {
    let _qemu = crate::common::beside_other_qemus();
    let elf = build::build(Build::Qemu).unwrap();
    let t0 = std::time::Instant::now();
    let mut q = Qemu::boot(&elf, false).unwrap();
    let pong = q
        .link
        .request(&ToFirmware::Ping(0xC0FFEE), |r| match r {
            FromFirmware::Pong(n) => Some(*n),
            _ => None,
        })
        .unwrap();
    assert_eq!(pong, 0xC0FFEE);
    q.link.send(&ToFirmware::Exit(0)).unwrap();
    let code = q.wait_exit(Duration::from_secs(10)).unwrap();
    let log = q.log();
    for l in &log {
        println!("{l}");
    }
    println!("boot + ping + exit: {:.2} s", t0.elapsed().as_secs_f64());
    assert_eq!(code, 0);
    let v = pto_firmware::VERSION;
    let version = format!("pto-firmware {}.{} ", v >> 8, v & 0xff);
    let boot = log
        .iter()
        .find(|l| l.text.starts_with(&version))
        .expect("version line");
    assert!(
        log.iter().any(|l| l.text
            == "board: clock emulated (QEMU); last reset: unknown (no reset flag); brown-out \
                reset not applicable (QEMU)"),
        "the board's clock, reset cause and brown-out level are logged"
    );
    assert!(boot.text.contains("board=qemu-netduinoplus2"), "{boot}");
    assert!(boot.text.contains("dt=2^-10 s"), "{boot}");
    assert!(boot.text.contains("trip=140.0 bar"), "{boot}");
    assert!(
        log.iter()
            .any(|l| l.text.starts_with("scheduler: Fixed(0.0000 %)"))
    );
    assert!(log.iter().any(|l| l.text == "exit 0 on command"));
}

/// A `pto` away from its source tree runs a firmware ELF it is given (`--elf`): a copy of the
/// QEMU build, in a folder of its own.
#[test]
fn pto_qemu_runs_a_firmware_elf_it_is_given() {
    let _qemu = crate::common::beside_other_qemus();
    let elf = build::build(Build::Qemu).unwrap();
    let dir = tmp!("elf");
    let copy = dir.join("pto-firmware");
    std::fs::copy(&elf, &copy).unwrap();
    let out = crate::common::pto()
        .current_dir(&dir)
        .args(["qemu", "--json", "--elf"])
        .arg(&copy)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{err}");
    assert!(
        err.contains(&format!("the QEMU firmware: {}", copy.display())),
        "{err}"
    );
    assert!(!err.contains("building"), "{err}");
    let hello = crate::common::field(&String::from_utf8_lossy(&out.stdout), "/hello/firmware");
    assert_eq!(hello.as_u64(), Some(u64::from(pto_firmware::VERSION)));
}

/// Both builds share one target directory (`target/fw`), where cargo leaves the last build's
/// ELF at one path: asked for at once, from two threads, each caller still gets its own build
/// (the QEMU one names its board; the bench one does not).
#[test]
fn the_two_builds_asked_for_at_once_each_get_their_own_elf() {
    // Under `cargo test`, not beside a twin (a fat-LTO build beside one is what nextest's
    // `twins` group keeps apart too).
    let _qemu = crate::common::beside_other_qemus();
    let bench = std::thread::spawn(|| build::build(Build::Bench).expect("the bench build"));
    let qemu = build::build(Build::Qemu).expect("the QEMU build");
    let bench = bench.join().expect("the bench build's thread");
    let names_board = |p: &std::path::Path| build::is_qemu_build(&std::fs::read(p).unwrap());
    assert_ne!(qemu, bench);
    assert!(
        names_board(&qemu),
        "{} is not the QEMU build",
        qemu.display()
    );
    assert!(
        !names_board(&bench),
        "{} is the QEMU build, not the bench's",
        bench.display()
    );
}
