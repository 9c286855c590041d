//! `pto qemu`, `pil`, `twin` and `fw-cost`: the firmware under QEMU; where its ELF or its source
//! tree comes from (`--elf`, `--workspace`).

use super::{finite_in, load_bench, write_atomic};
use anyhow::Result;
use pto_host::hil::build::{self, Sources};
use std::path::PathBuf;

/// `pto qemu`'s options.
#[derive(clap::Args)]
pub(crate) struct QemuArgs {
    /// Print the log lines as they arrive and keep the firmware running until Ctrl-C (which
    /// stops QEMU and removes its socket; exit status 130).
    #[arg(long)]
    pub follow: bool,
    /// Machine-readable output (the firmware's Hello, its status and the host's link
    /// counts; the log goes to stderr).
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub fw: FirmwareArgs,
}

/// `pto pil`'s options.
#[derive(clap::Args)]
pub(crate) struct PilArgs {
    /// Bench parameter file (default: the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Instead of the standard checks, inject this sensor fault into the firmware's
    /// readings and check that it is flagged, named and made safe (repeatable):
    /// SENSOR:KIND with SENSOR hp, lp, motor or encoder and KIND stuck (at its reading),
    /// stuck=VALUE (bar, rpm, counts), drift=RATE (per s) or gain=FACTOR; from 20 s, or
    /// from the time after an @ (hp:drift=0.5@10).
    #[arg(long, value_name = "SENSOR:KIND")]
    pub fault: Vec<pto_host::validation::faults::Fault>,
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub fw: FirmwareArgs,
}

/// `pto twin`'s options.
#[derive(clap::Args)]
pub(crate) struct TwinArgs {
    /// The plant's bench file (default: the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Override a value of the plant's bench (as for `pto simulate`).
    #[arg(long = "set", value_name = "FIELD=VALUE")]
    pub set: Vec<String>,
    /// P2 at the start, bar (default 60; with `--campaign`, its first segment's start).
    #[arg(long, value_parser = finite_in(10.0, 125.0, "bar"))]
    p2_start: Option<f64>,
    /// Valve aperture, % (the firmware's mode `fixed`).
    #[arg(long, default_value_t = 10.0, value_parser = finite_in(0.0, 100.0, "%"))]
    pub aperture: f64,
    /// Simulated time, s.
    #[arg(long, default_value_t = 60.0, value_parser = finite_in(1.0, 3600.0, "s"))]
    pub duration: f64,
    /// Wall-clock seconds between printing the bench link and starting the plant (time to
    /// start `pto link … monitor`).
    #[arg(long, default_value_t = 3.0, value_parser = finite_in(0.0, 600.0, "s"))]
    pub start_after: f64,
    /// Follow a campaign instead (`pto link … campaign run` drives the firmware): the lever
    /// held between segments, each segment's motion and cylinders from when the controller
    /// energises them until it de-energises them. `--aperture` and `--duration` are then
    /// the campaign's.
    #[arg(long)]
    pub campaign: Option<PathBuf>,
    #[command(flatten)]
    pub fw: FirmwareArgs,
}

/// `pto fw-cost`'s options.
#[derive(clap::Args)]
pub(crate) struct FwCostArgs {
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
    /// Also write the four-cylinder run's cost step by step (CSV: step, instructions,
    /// background units, each cylinder's phase) to this file, to see which steps set the
    /// maximum.
    #[arg(long, value_name = "CSV")]
    pub trace: Option<PathBuf>,
    #[command(flatten)]
    pub src: WorkspaceArgs,
}

/// Where a command that runs the QEMU firmware takes it from.
#[derive(clap::Args, Debug, Clone)]
pub(crate) struct FirmwareArgs {
    /// Run this QEMU build of the firmware instead of building one (`cargo fw` in the source
    /// tree writes target/thumbv7em-none-eabihf/firmware/pto-firmware): for a pto installed
    /// away from its source tree.
    #[arg(long, value_name = "FILE", conflicts_with = "workspace")]
    pub elf: Option<PathBuf>,
    /// Build the firmware in this pto source tree (default: the one pto was compiled in).
    #[arg(long, value_name = "DIR")]
    pub workspace: Option<PathBuf>,
}

impl FirmwareArgs {
    /// Makes these the process's sources.
    pub(crate) fn apply(&self) {
        build::use_sources(Sources {
            elf: self.elf.clone(),
            workspace: self.workspace.clone(),
        });
    }
}

/// Where a command that measures builds of the sources (`fw-cost`, `model-cost`) finds them.
#[derive(clap::Args, Debug, Clone)]
pub(crate) struct WorkspaceArgs {
    /// The pto source tree to build and measure (default: the one pto was compiled in).
    #[arg(long, value_name = "DIR")]
    pub workspace: Option<PathBuf>,
}

impl WorkspaceArgs {
    /// Makes this the process's source tree.
    pub(crate) fn apply(&self) {
        build::use_sources(Sources {
            elf: None,
            workspace: self.workspace.clone(),
        });
    }
}

/// Says what the QEMU firmware is about to come from.
fn say_firmware(fw: &FirmwareArgs) {
    match &fw.elf {
        Some(elf) => eprintln!("the QEMU firmware: {}", elf.display()),
        None => eprintln!("building the QEMU firmware…"),
    }
}

pub(crate) fn qemu_cmd(a: &QemuArgs) -> Result<bool> {
    let (fw, follow, json) = (&a.fw, a.follow, a.json);
    use pto_host::hil::build::Build;
    use pto_host::hil::qemu::Qemu;
    use pto_model::protocol::{FromFirmware, ToFirmware};
    fw.apply();
    say_firmware(fw);
    let elf = build::build(Build::Qemu)?;
    let mut q = Qemu::boot(&elf, follow)?;
    let t0 = std::time::Instant::now();
    q.link.request(&ToFirmware::Ping(1), |r| {
        matches!(r, FromFirmware::Pong(1)).then_some(())
    })?;
    let ping = t0.elapsed();
    let hello = q.link.request(&ToFirmware::Hello, |r| match r {
        FromFirmware::Hello(h) => Some(*h),
        _ => None,
    })?;
    let st = pto_host::hil::pil::status(&mut q)?;
    let host = q.link.counts();
    if follow {
        eprintln!(
            "ping answered in {:.2} ms; following the firmware's log — Ctrl-C stops it",
            ping.as_secs_f64() * 1e3
        );
        eprint!("{}", pto_host::hil::qemu::status_table(&st, &host));
        while q.running() {
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        anyhow::bail!("QEMU ended by itself");
    }
    q.link.send(&ToFirmware::Exit(0))?;
    let code = q.wait_exit(std::time::Duration::from_secs(10))?;
    if !follow {
        for l in q.log() {
            if json {
                eprintln!("{l}");
            } else {
                println!("{l}");
            }
        }
    }
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "ping_ms": ping.as_secs_f64() * 1e3,
                "hello": hello,
                "status": st,
                "host_link": host,
                "exit_code": code,
            }))?
        );
    } else {
        println!(
            "pto-firmware {}.{}, protocol v{}, dt = 2^-{} s; ping answered in {:.2} ms",
            hello.firmware >> 8,
            hello.firmware & 0xff,
            hello.protocol,
            hello.dt_log2,
            ping.as_secs_f64() * 1e3
        );
        print!("{}", pto_host::hil::qemu::status_table(&st, &host));
        println!("QEMU exit code {code}");
    }
    Ok(code == 0)
}

pub(crate) fn pil_cmd(a: &PilArgs) -> Result<bool> {
    let (fw, bench, faults, json) = (&a.fw, a.bench.as_ref(), a.fault.as_slice(), a.json);
    use pto_host::hil::build::Build;
    use pto_host::hil::pil::{self, Check, PilError};
    use pto_host::hil::qemu::Qemu;
    use pto_host::sim::bench::Bench;
    type Run = Box<dyn Fn(Qemu, &Bench) -> Result<(Qemu, Check), PilError>>;
    let bench = load_bench(bench)?;
    fw.apply();
    say_firmware(fw);
    let elf = build::build(Build::Qemu)?;
    let checks: Vec<(String, Run)> = if faults.is_empty() {
        let standard: [(&str, pil::CheckFn); 6] = [
            ("hold P2", pil::check_hold_p2),
            ("hold speed", pil::check_hold_speed),
            ("trip", pil::check_trip),
            ("trip holds", pil::check_trip_holds),
            (
                "motor behind a closed valve",
                pil::check_motor_behind_closed_valve,
            ),
            ("HP stuck (sensor fault)", pil::check_sensor_fault),
        ];
        standard
            .into_iter()
            .map(|(n, f)| (n.to_owned(), Box::new(f) as Run))
            .collect()
    } else {
        faults
            .iter()
            .map(|&f| {
                (
                    f.to_string(),
                    Box::new(move |q, b: &Bench| pil::check_fault(q, b, f)) as Run,
                )
            })
            .collect()
    };
    let width = checks
        .iter()
        .map(|(n, _)| n.chars().count())
        .max()
        .unwrap_or(0)
        .max(24);
    let mut out = Vec::new();
    for (name, f) in &checks {
        eprintln!("PIL {name}: running in lockstep with the firmware (≈ 2–3 ms per step)…");
        let q = Qemu::boot(&elf, false)?;
        let (mut q, c) = f(q, &bench)?;
        let _ = q.link.send(&pto_model::protocol::ToFirmware::Exit(0));
        if !json {
            println!(
                "{:<w$} {:>8.3} {:<13} target {:<6.1} {}  ({} steps, {:.0} s)\n    {}",
                c.name,
                c.measured,
                c.unit,
                c.target,
                if c.pass { "ok" } else { "MISSED" },
                c.steps,
                c.wall_s,
                c.detail,
                w = width
            );
        }
        out.push(c);
    }
    let pass = out.iter().all(|c| c.pass);
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({ "checks": out, "pass": pass }))?
        );
    }
    Ok(pass)
}

pub(crate) fn fw_cost_cmd(a: &FwCostArgs) -> Result<bool> {
    let (src, json, trace) = (&a.src, a.json, a.trace.as_deref());
    src.apply();
    // Both builds come from the tree (a QEMU ELF alone would measure half).
    build::workspace_root("pto fw-cost (it builds both firmwares)")?;
    eprintln!(
        "building both firmwares and replaying the golden vectors (and a four-cylinder run) under QEMU…"
    );
    let r = pto_host::hil::fw_cost::measure()?;
    if let Some(path) = trace {
        eprintln!("tracing the four-cylinder run step by step…");
        let t = pto_host::hil::fw_cost::trace_four_cylinders()?;
        let mut csv = String::from("step,instructions,background_units,phases\n");
        for s in &t {
            csv += &format!(
                "{},{},{},{}\n",
                s.step, s.instructions, s.background_units, s.phases
            );
        }
        write_atomic(path, csv.as_bytes())?;
        eprintln!("wrote {}", path.display());
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        use pto_host::hil::fw_cost::target;
        for s in &r.step {
            println!(
                "step ({:<27}) {} steps: mean {:.0}, max {} instructions (target ≤ {})",
                s.mode,
                s.steps,
                s.mean,
                s.max,
                target::STEP_INSTRUCTIONS
            );
        }
        for (what, n) in [
            (
                "controller set-up at boot (its tables)",
                r.setup_instructions,
            ),
            (
                "configuration commit (its tables, not stored)",
                r.commit_instructions,
            ),
        ] {
            println!(
                "{what}: {n} instructions, {:.1} ms at 168 MHz (target ≤ {}): {}",
                f64::from(n) / 168e3,
                target::SETUP_INSTRUCTIONS,
                if n <= target::SETUP_INSTRUCTIONS {
                    "met"
                } else {
                    "MISSED"
                }
            );
        }
        for s in &r.size {
            println!(
                "{:<6} build: flash {} B, static RAM {} B{}",
                s.build,
                s.flash,
                s.ram,
                if s.build == "bench" {
                    format!(" (targets ≤ {} B, ≤ {} B)", target::FLASH, target::RAM)
                } else {
                    String::new()
                }
            );
        }
    }
    Ok(r.pass)
}

#[allow(clippy::too_many_arguments)]
pub(crate) fn twin_cmd(a: &TwinArgs) -> Result<bool> {
    let (fw, bench, set, p2_start, aperture, duration, start_after, campaign) = (
        &a.fw,
        a.bench.as_ref(),
        a.set.as_slice(),
        a.p2_start,
        a.aperture,
        a.duration,
        a.start_after,
        a.campaign.as_ref(),
    );
    use pto_host::hil::build::Build;
    use pto_host::hil::pil;
    use pto_host::hil::qemu::Qemu;
    use pto_host::validation::sensors::SensorSpec;
    let plant = super::load_bench_with(bench, set)?;
    let campaign = campaign
        .map(|p| {
            let c = pto_host::plan::Campaign::load(p, &plant)?;
            pto_host::hil::campaign::check_runnable(&c)?;
            anyhow::Ok(c)
        })
        .transpose()?;
    let p2_start = p2_start
        .or_else(|| {
            campaign
                .as_ref()
                .and_then(|c| c.segment.first())
                .and_then(|s| s.run.initial_hp_bar)
        })
        .unwrap_or(60.0);
    fw.apply();
    say_firmware(fw);
    let elf = build::build(Build::Qemu)?;
    let q = Qemu::boot_twin(&elf, false)?;
    let pty = q
        .pty
        .clone()
        .ok_or_else(|| anyhow::anyhow!("no pseudo-terminal"))?;
    println!("bench link on {}", pty.display());
    println!(
        "  e.g. pto link --port {} monitor --log twin.csv",
        pty.display()
    );
    use std::io::Write as _;
    let _ = std::io::stdout().flush();
    std::thread::sleep(std::time::Duration::from_secs_f64(start_after));
    if let Some(c) = campaign {
        eprintln!(
            "plant: {} from P2 {p2_start} bar, following {} segments ({:.1} min of bench time)",
            plant.source,
            c.segment.len(),
            c.minutes()
        );
        let t0 = std::time::Instant::now();
        let (q, phases) = pto_host::hil::twin::run_campaign(
            q,
            &plant,
            &c,
            p2_start,
            SensorSpec::default(),
            |m| eprintln!("{m}"),
        )?;
        let simulated: f64 = phases.iter().map(|p| p.duration_s).sum();
        println!(
            "campaign done: {} segments, {simulated:.0} s simulated in {:.0} s wall; plant P2 at the end {:.1} bar",
            c.segment.len(),
            t0.elapsed().as_secs_f64(),
            phases.last().map_or(p2_start, |p| p.p2_end_bar)
        );
        drop(q);
        return Ok(true);
    }
    eprintln!(
        "plant: {} from P2 {p2_start} bar, valve fixed {aperture} %, {duration} s",
        plant.source
    );
    let t0 = std::time::Instant::now();
    let (q, res, rows) = pil::closed_loop(
        q,
        &plant,
        pil::fixed(aperture as f32),
        p2_start,
        duration,
        SensorSpec::default(),
        Box::new(|_| pil::Injection::None),
    )?;
    let err: Vec<f64> = rows
        .iter()
        .filter_map(|r| r.estimate.map(|e| f64::from(e.p2.to_f32()) - r.p2_bar))
        .collect();
    let rms = (err.iter().map(|e| e * e).sum::<f64>() / err.len().max(1) as f64).sqrt();
    println!(
        "{} steps in {:.1} s wall ({:.2}× real time); plant P2 {:.1} → {:.1} bar; firmware P2 error RMS {rms:.3} bar",
        rows.len(),
        t0.elapsed().as_secs_f64(),
        duration / t0.elapsed().as_secs_f64(),
        res.trace
            .p2_pa
            .first()
            .map_or(f64::NAN, |p| p / pto_host::sim::bench::BAR),
        res.trace
            .p2_pa
            .last()
            .map_or(f64::NAN, |p| p / pto_host::sim::bench::BAR),
    );
    drop(q);
    Ok(true)
}
