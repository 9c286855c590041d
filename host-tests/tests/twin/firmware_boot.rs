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
