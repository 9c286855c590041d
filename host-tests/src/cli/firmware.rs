//! `pto qemu`, `pil` and `fw-cost`: the firmware under QEMU.

use super::{load_bench, write_atomic};
use anyhow::Result;
use std::path::{Path, PathBuf};

pub(crate) fn qemu_cmd(follow: bool, json: bool) -> Result<bool> {
    use pto_host::hil::build::{self, Build};
    use pto_host::hil::qemu::Qemu;
    use pto_model::protocol::{FromFirmware, ToFirmware};
    eprintln!("building the QEMU firmware…");
    let elf = build::build(Build::Qemu)?;
    let mut q = Qemu::boot(&elf, follow)?;
    let t0 = std::time::Instant::now();
    q.link.request(&ToFirmware::Ping(1), |r| {
        matches!(r, FromFirmware::Pong(1)).then_some(())
    })?;
    let ping = t0.elapsed();
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
                "status": st,
                "host_link": host,
                "exit_code": code,
            }))?
        );
    } else {
        println!("ping answered in {:.2} ms", ping.as_secs_f64() * 1e3);
        print!("{}", pto_host::hil::qemu::status_table(&st, &host));
        println!("QEMU exit code {code}");
    }
    Ok(code == 0)
}

pub(crate) fn pil_cmd(
    bench: Option<&PathBuf>,
    faults: &[pto_host::model::faults::Fault],
    json: bool,
) -> Result<bool> {
    use pto_host::hil::build::{self, Build};
    use pto_host::hil::pil::{self, Check, PilError};
    use pto_host::hil::qemu::Qemu;
    use pto_host::sim::bench::Bench;
    type Run = Box<dyn Fn(Qemu, &Bench) -> Result<(Qemu, Check), PilError>>;
    let bench = load_bench(bench)?;
    eprintln!("building the QEMU firmware…");
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

pub(crate) fn fw_cost_cmd(json: bool, trace: Option<&Path>) -> Result<bool> {
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

pub(crate) fn twin_cmd(
    bench: Option<&PathBuf>,
    set: &[String],
    p2_start: Option<f64>,
    aperture: f64,
    duration: f64,
    start_after: f64,
    campaign: Option<&PathBuf>,
) -> Result<bool> {
    use pto_host::hil::build::{self, Build};
    use pto_host::hil::pil;
    use pto_host::hil::qemu::Qemu;
    use pto_host::model::sensors::SensorSpec;
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
    eprintln!("building the QEMU firmware…");
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
