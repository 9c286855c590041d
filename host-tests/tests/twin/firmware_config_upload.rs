//! Configuration upload to the QEMU twin over its bench link (the pseudo-terminal, through the
//! serial-port code path): applied and stored only in the declared safe state (fixed 0 %, the
//! valve closed, a valid HP reading), refused with its reason when damaged or out of range, and
//! a refusal leaves the running configuration as it was.

use pto_host::hil::build::{self, Build};
use pto_host::hil::client;
use pto_host::hil::link::{self, LinkError};
use pto_host::hil::qemu::Qemu;
use pto_model::ModelConfig;
use pto_model::protocol::{
    Chunk, ConfigRefusal, ConfigSource, FromFirmware, NotSafe, Refusal, Stored, ToFirmware,
    config_fingerprint,
};
use pto_model::scheduler::Mode;
use std::time::Duration;

/// `n` sensor frames on the hardware port, HP reading 60 bar, each step's output awaited.
fn feed(q: &mut Qemu, tick: &mut u32, n: u32) {
    pto_host::hil::pil::feed_at_rest(q, tick, n).expect("a step's output");
}

fn refusal(e: client::ClientError) -> ConfigRefusal {
    match e {
        client::ClientError::Link(LinkError::Refused(Refusal::Config(c))) => c,
        other => panic!("expected a configuration refusal, got {other}"),
    }
}

#[test]
fn uploads_are_checked_applied_and_stored_only_in_the_safe_state() {
    let _twin = crate::common::one_twin();
    let elf = build::build(Build::Qemu).expect("QEMU build");
    let mut q = Qemu::boot_twin(&elf, false).expect("twin");
    let pty = q.pty.clone().unwrap();
    let (mut l, hello) = link::connect(&pty.display().to_string(), 230_400, Duration::from_secs(5))
        .expect("connect over the pseudo-terminal");
    assert_eq!(hello.dt_log2, 10);

    let (info, cfg) = client::read_config(&mut l).unwrap();
    assert_eq!(info.source, ConfigSource::BuiltIn);
    assert_eq!(info.fingerprint, pto_firmware::built_config::FINGERPRINT);
    assert_eq!(cfg, ModelConfig::reference());

    // At boot the mode is fixed 0 % with the valve closed, but P2 is not known yet.
    let mut wet = ModelConfig::reference();
    wet.trapped_air_fraction = 0.09;
    let e = refusal(client::upload(&mut l, &wet, true, |_, _| {}).unwrap_err());
    assert_eq!(e, ConfigRefusal::NotSafe(NotSafe::NoReading));
    // The plant's samples on the hardware port: a valid HP reading of 60 bar.
    let mut tick = 0;
    feed(&mut q, &mut tick, 10);
    let (info, stored) = client::upload(&mut l, &wet, true, |_, _| {}).unwrap_or_else(|e| {
        let code = q.wait_exit(Duration::from_secs(5));
        panic!("{e}: exit {code:?}: {}", q.qemu_stderr())
    });
    assert_eq!(
        (info.source, stored),
        (ConfigSource::UploadedStored, Stored::Yes)
    );
    let (back, cfg) = client::read_config(&mut l).unwrap();
    assert_eq!((back, cfg.clone()), (info, wet.clone()));

    // Outside the safe state (the valve open): refused, nothing changes.
    client::set_mode(&mut l, Mode::Fixed(pto_model::fx::Aperture::from_num(10.0))).unwrap();
    feed(&mut q, &mut tick, 10);
    let mut other = wet.clone();
    other.trapped_air_fraction = 0.03;
    let e = refusal(client::upload(&mut l, &other, false, |_, _| {}).unwrap_err());
    assert_eq!(e, ConfigRefusal::NotSafe(NotSafe::ValveOpen));
    assert_eq!(client::read_config(&mut l).unwrap().1, wet);
    // Back to fixed 0: the valve slews shut (100 %/s), then it runs at once.
    client::set_mode(&mut l, Mode::Fixed(pto_model::fx::Aperture::ZERO)).unwrap();
    feed(&mut q, &mut tick, 200);
    let (info, stored) = client::upload(&mut l, &other, false, |_, _| {}).unwrap();
    assert_eq!((info.source, stored), (ConfigSource::Uploaded, Stored::No));

    // A field out of range (not checked by the host here): the firmware names it.
    let mut bad = other.clone();
    bad.trapped_air_fraction = 0.9;
    let e = refusal(client::upload(&mut l, &bad, false, |_, _| {}).unwrap_err());
    let text = e.to_string();
    assert!(
        text.contains("trapped_air_fraction = 0.9 outside"),
        "{text}"
    );
    // Another model step than the board samples at.
    let mut dt = other.clone();
    dt.dt_log2 = 11;
    let e = refusal(client::upload(&mut l, &dt, false, |_, _| {}).unwrap_err());
    assert!(
        e.to_string().contains("dt_log2 = 11 outside [10, 10]"),
        "{e}"
    );

    // Damaged on the way (a byte changed inside a chunk whose frame was fine): the CRC over
    // the whole catches it.
    let bytes = client::config_bytes(&wet).unwrap();
    let ask = |l: &mut link::Link, m: ToFirmware| {
        l.request(&m, |r| match r {
            FromFirmware::Telemetry(_) => None,
            other => Some(*other),
        })
        .unwrap()
    };
    ask(
        &mut l,
        ToFirmware::ConfigBegin {
            len: bytes.len() as u16,
            crc: config_fingerprint(&bytes),
        },
    );
    let mut damaged = bytes.clone();
    damaged[100] ^= 0x04;
    let mut off = 0;
    while off < damaged.len() {
        let c = Chunk::of(&damaged, off);
        off += usize::from(c.len);
        ask(&mut l, ToFirmware::ConfigChunk(c));
    }
    let r = ask(&mut l, ToFirmware::ConfigCommit { persist: false });
    assert!(
        matches!(
            r,
            FromFirmware::Refused(Refusal::Config(ConfigRefusal::Crc { .. }))
        ),
        "{r:?}"
    );
    // A chunk out of order.
    ask(
        &mut l,
        ToFirmware::ConfigBegin {
            len: bytes.len() as u16,
            crc: config_fingerprint(&bytes),
        },
    );
    let r = ask(&mut l, ToFirmware::ConfigChunk(Chunk::of(&bytes, 64)));
    assert!(
        matches!(
            r,
            FromFirmware::Refused(Refusal::Config(ConfigRefusal::OutOfOrder {
                expected: 0,
                got: 64
            }))
        ),
        "{r:?}"
    );

    // Every refusal left the last accepted configuration running.
    let (info, cfg) = client::read_config(&mut l).unwrap();
    assert_eq!((info.source, cfg), (ConfigSource::Uploaded, other));
    // The store can be cleared (in the safe state); the running configuration stays.
    client::clear_store(&mut l).unwrap();
    assert_eq!(
        client::read_config(&mut l).unwrap().0.source,
        ConfigSource::Uploaded
    );
    let st = client::status(&mut l).unwrap();
    println!(
        "bench link: {} frames taken by the firmware, {} dropped, {} lost; host: {:?}",
        st.link.ok,
        st.link.dropped(),
        st.link.lost,
        l.counts()
    );
    assert_eq!((st.link.dropped(), st.link.lost), (0, 0));
    // Boot, a stored commit, commits and a clear have run: the deepest paths. Their stack
    // must leave room (before the change that built a second controller per commit, one
    // stored commit took it through the statics: a lockup).
    println!("stack never used: {} B", st.stack_unused);
    assert!(st.stack_unused >= 16 * 1024, "{} B left", st.stack_unused);
    let log: Vec<String> = q.log().iter().map(ToString::to_string).collect();
    assert!(
        log.iter()
            .any(|l| l.contains("uploaded") && l.contains("stored")),
        "{log:#?}"
    );
    // Each commit's table build, as the firmware measured it: within the set-up's budget.
    let lines = q.log();
    let applied: Vec<u32> =
        pto_host::hil::fw_cost::logged_instructions(&lines, "configuration applied in ").collect();
    println!("commits applied in {applied:?} instructions");
    assert!(!applied.is_empty(), "{log:#?}");
    for n in applied {
        assert!(
            (100_000..=pto_host::hil::fw_cost::target::SETUP_INSTRUCTIONS).contains(&n),
            "a commit's tables: {n} instructions"
        );
    }
}

/// Ctrl-C (SIGINT) stops `pto link monitor` cleanly: the log is finished under its name (no
/// `.part` left), every frame it took is in it, and the exit status says no frame was missed.
#[test]
fn a_monitor_stopped_by_ctrl_c_keeps_its_log() {
    let _twin = crate::common::one_twin();
    use nix::sys::signal::{Signal, kill};
    use nix::unistd::Pid;
    use std::io::{BufRead, BufReader};
    use std::process::{Command, Stdio};
    let elf = build::build(Build::Qemu).expect("QEMU build");
    let mut q = Qemu::boot_twin(&elf, false).expect("twin");
    let pty = q.pty.clone().unwrap();
    let dir = std::env::temp_dir().join(format!("pto-monitor-int-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let log = dir.join("run.csv");
    let mut mon = Command::new(env!("CARGO_BIN_EXE_pto"))
        .args(["link", "--port"])
        .arg(&pty)
        .args(["monitor", "--log"])
        .arg(&log)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = BufReader::new(mon.stderr.take().unwrap());
    let mut line = String::new();
    while !line.contains("monitoring") {
        line.clear();
        if err.read_line(&mut line).unwrap() == 0 {
            let _ = mon.kill();
            panic!("the monitor ended before it started");
        }
    }
    // 1 600 steps: 100 telemetry frames at every 16th step.
    let mut tick = 0;
    feed(&mut q, &mut tick, 1_600);
    // Time for the monitor to read every frame the pseudo-terminal holds (Ctrl-C stops it at
    // once: frames still unread are not taken).
    std::thread::sleep(Duration::from_millis(2_000));
    kill(Pid::from_raw(mon.id() as i32), Signal::SIGINT).unwrap();
    let t0 = std::time::Instant::now();
    let status = loop {
        if let Some(st) = mon.try_wait().unwrap() {
            break st;
        }
        if t0.elapsed() > Duration::from_secs(10) {
            let _ = mon.kill();
            let _ = mon.wait();
            panic!("the monitor did not stop on SIGINT");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut out = String::new();
    std::io::Read::read_to_string(mon.stdout.as_mut().unwrap(), &mut out).unwrap();
    println!("{out}");
    assert_eq!(status.code(), Some(0), "{out}");
    let text = std::fs::read_to_string(&log).expect("the log under its name");
    let rows = text.lines().count() - 1;
    assert_eq!(rows, 100, "{out}");
    assert!(!dir.join("run.csv.part").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// The twin's actuators in one step: valve %, dump valve open, solenoids.
type TwinOutputs = (f32, bool, u8);

/// The plant and the operator's hands on the twin's hardware port, from a thread: the lever
/// swung by hand (±2 000 counts, `lever` false: held still), the motor's shaft turned at 30 rpm,
/// HP at 60 bar (`hp_open`: the loop open), LP at 8 bar. Records every step's outputs as the
/// twin's actuators got them (valve %, dump valve open, solenoids).
fn hands(
    mut q: Qemu,
    lever: bool,
    hp_open: bool,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> std::thread::JoinHandle<(Qemu, Vec<TwinOutputs>)> {
    use pto_firmware::frontend::{LoopSpec, Transducer};
    std::thread::spawn(move || {
        let hp = Transducer::new(LoopSpec::HP).unwrap();
        let lp = Transducer::new(LoopSpec::LP).unwrap();
        let mut outs = Vec::new();
        let mut tick = 0u32;
        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
            let phase = f64::from(tick) * std::f64::consts::TAU / 1500.0;
            let f = pto_model::protocol::SensorFrame {
                tick,
                encoder: if lever {
                    (2000.0 * phase.sin()) as i32
                } else {
                    0
                },
                hp_adc: if hp_open {
                    hp.counts_at_ma(0.0)
                } else {
                    hp.counts_at_bar(60.0)
                },
                lp_adc: lp.counts_at_bar(8.0),
                motor: Some(pto_model::fx::Rpm::from_num(30.0)),
                supply_mv: Some(3300),
            };
            let t = tick;
            let o = q
                .link
                .request(&ToFirmware::Sensors(f), |r| match r {
                    FromFirmware::Output {
                        tick,
                        applied,
                        dump,
                        on_duty,
                        ..
                    } if *tick == t => Some((applied.to_f32(), *dump, *on_duty)),
                    _ => None,
                })
                .expect("a step's output");
            if outs.last() != Some(&o) {
                outs.push(o);
            }
            tick += 1;
        }
        (q, outs)
    })
}

/// `pto link selftest` end to end on the twin, over its pseudo-terminal: a healthy bench (the
/// test plays the plant and the operator's hands on the hardware port) passes every check the
/// twin can show, its clock, brown-out level and supply reported n/a or measured, and the
/// twin's actuators went through each output step from the de-energised state and back to the
/// controller; a bench with an open HP loop and a lever nobody moves fails, those checks named,
/// and its outputs are not stepped (P2 unknown: the valve at its sensor-fault aperture).
#[test]
fn a_guided_selftest_passes_on_a_healthy_twin_and_names_what_fails() {
    let _twin = crate::common::one_twin();
    use std::process::Command;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};
    let elf = build::build(Build::Qemu).expect("QEMU build");
    let run = |lever: bool, hp_open: bool, extra: &[&str]| {
        let q = Qemu::boot_twin(&elf, false).expect("twin");
        let pty = q.pty.clone().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let feeder = hands(q, lever, hp_open, stop.clone());
        let out = Command::new(env!("CARGO_BIN_EXE_pto"))
            .args(["link", "--port"])
            .arg(&pty)
            .args(["selftest", "--yes", "--hold", "0.2", "--json"])
            .args(extra)
            .output()
            .expect("pto runs");
        stop.store(true, Ordering::Relaxed);
        let (q, outs) = feeder.join().expect("the feeder");
        let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
            panic!(
                "{e}: {}\n{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            )
        });
        (q, out.status.code(), json, outs)
    };

    let (q, code, json, outs) = run(true, false, &["--window", "30"]);
    let checks = json["checks"].as_array().unwrap();
    for c in checks {
        println!(
            "{:<34} {:<14} {}",
            c["name"].as_str().unwrap(),
            c["outcome"].as_str().unwrap(),
            c["measured"].as_str().unwrap()
        );
    }
    let outcome = |name: &str| {
        checks
            .iter()
            .find(|c| c["name"] == name)
            .map(|c| c["outcome"].as_str().unwrap().to_string())
            .unwrap_or_else(|| panic!("no check {name}"))
    };
    assert_eq!(code, Some(0), "{json:#}");
    assert_eq!(json["passed"], true);
    for name in ["clock", "brown-out reset level"] {
        assert_eq!(outcome(name), "not_applicable", "the twin has no {name}");
    }
    for name in [
        "controller sampling",
        "HP transducer loop",
        "LP transducer loop",
        "ADC reference (VDDA)",
        "shaft encoder",
        "motor pickup",
        "valve to 5 % (dump open)",
        "dump valve closed (valve closed)",
        "solenoid HC3.1",
        "solenoid HC3.4",
    ] {
        assert_eq!(outcome(name), "pass", "{name}");
    }
    // The twin's actuators, step by step: held de-energised since boot (no mode, duty or reset
    // command came), each output alone and back to de-energised, held again after the test.
    println!("twin outputs: {outs:?}");
    let off = (0.0, true, 0u8);
    let expected = [
        off,
        (5.0, true, 0),
        off,
        (0.0, false, 0),
        off,
        (0.0, true, 0b0001),
        off,
        (0.0, true, 0b0010),
        off,
        (0.0, true, 0b0100),
        off,
        (0.0, true, 0b1000),
        off,
    ];
    assert_eq!(outs.len(), expected.len(), "{outs:?}");
    for (got, want) in outs.iter().zip(expected) {
        assert!(
            (got.0 - want.0).abs() < 0.01 && got.1 == want.1 && got.2 == want.2,
            "{outs:?}"
        );
    }
    drop(q);

    let (_q, code, json, _) = run(false, true, &["--window", "3", "--skip", "motor"]);
    assert_eq!(code, Some(1), "{json:#}");
    assert_eq!(json["passed"], false);
    let failed: Vec<&str> = json["checks"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["outcome"] == "fail" || c["outcome"] == "skipped")
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        failed,
        [
            "HP transducer loop",
            "shaft encoder",
            "motor pickup",
            "outputs"
        ],
        "{json:#}"
    );
    // No HP reading: P2 is unknown, the valve stands at its sensor-fault aperture, and the
    // outputs are not stepped.
    let outputs = &json["checks"].as_array().unwrap().last().unwrap()["measured"];
    assert!(
        outputs.as_str().unwrap().contains("no valid HP reading"),
        "{outputs}"
    );
}

/// A sensor held faulted over the link: a motor pickup reading 100 rpm behind the closed valve
/// (the motor check names it after 1 s), `status` names it, `pto link clear-faults` refuses while
/// it still reads 100 rpm (exit 1, "still held: motor") and clears it once it reads the standing
/// motor again (exit 0).
#[test]
fn a_held_sensor_fault_is_shown_and_cleared_only_when_it_agrees() {
    use pto_firmware::frontend::{LoopSpec, Transducer};
    use std::process::Command;
    let _twin = crate::common::one_twin();
    let elf = build::build(Build::Qemu).expect("QEMU build");
    let mut q = Qemu::boot_twin(&elf, false).expect("twin");
    let pty = q.pty.clone().unwrap().display().to_string();
    let hp = Transducer::new(LoopSpec::HP).unwrap();
    let lp = Transducer::new(LoopSpec::LP).unwrap();
    let mut tick = 0u32;
    let mut feed_rpm = |q: &mut Qemu, rpm: f32, n: u32| {
        for _ in 0..n {
            let f = pto_model::protocol::SensorFrame {
                tick,
                encoder: 0,
                hp_adc: hp.counts_at_bar(60.0),
                lp_adc: lp.counts_at_bar(8.0),
                motor: Some(pto_model::fx::Rpm::from_num(rpm)),
                supply_mv: Some(3300),
            };
            let t = tick;
            q.link
                .request(&ToFirmware::Sensors(f), |r| match r {
                    FromFirmware::Output { tick, .. } if *tick == t => Some(()),
                    _ => None,
                })
                .expect("a step's output");
            tick += 1;
        }
    };
    let clear = || {
        Command::new(env!("CARGO_BIN_EXE_pto"))
            .args(["link", "--port", &pty, "clear-faults"])
            .output()
            .expect("pto runs")
    };
    feed_rpm(&mut q, 100.0, 2_000);
    let (mut l, _) = link::connect(&pty, 230_400, Duration::from_secs(5)).unwrap();
    let st = client::status(&mut l).unwrap();
    assert_eq!(
        st.sensor_faults,
        pto_firmware::sensor_faults::bit::MOTOR,
        "{st:?}"
    );
    drop(l);
    let out = clear();
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    assert_eq!(out.status.code(), Some(1), "{text}");
    assert!(text.contains("still held: motor"), "{text}");
    feed_rpm(&mut q, 0.0, 600);
    let out = clear();
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    assert_eq!(out.status.code(), Some(0), "{text}");
    assert!(text.contains("cleared: motor"), "{text}");
    let log: Vec<String> = q.log().iter().map(ToString::to_string).collect();
    assert!(
        log.iter().any(|l| l.contains("sensor fault held")),
        "{log:#?}"
    );
}
