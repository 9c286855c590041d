//! `pto validate` and `model-cost`: the fixed-point model against the simulation.

use super::load_bench;
use anyhow::{Result, bail};
use pto_host::sim::scenario;
use std::path::PathBuf;

/// `pto validate`'s options.
#[derive(clap::Args)]
pub(crate) struct ValidateArgs {
    /// Bench parameter file (default: the reference bench).
    #[arg(long)]
    pub bench: Option<PathBuf>,
    /// Only scenarios whose name contains this.
    #[arg(long, default_value = "")]
    pub filter: String,
    /// Skip the closed-loop runs.
    #[arg(long)]
    pub no_loop: bool,
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
}

/// `pto model-cost`'s options.
#[derive(clap::Args)]
pub(crate) struct ModelCostArgs {
    /// Machine-readable output.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub src: super::firmware::WorkspaceArgs,
}

pub(crate) fn validate_cmd(a: &ValidateArgs) -> Result<bool> {
    let (bench_path, filter, with_loop, json) =
        (a.bench.as_ref(), a.filter.as_str(), !a.no_loop, a.json);
    use pto_host::validation::{target, validate};
    let bench = load_bench(bench_path)?;
    let sel: Vec<_> = scenario::every_builtin()
        .into_iter()
        .filter(|s| s.name.contains(filter))
        .collect();
    if sel.is_empty() {
        bail!("--filter {filter:?} matches no built-in scenario (see `pto scenarios`)");
    }
    if !json {
        eprintln!(
            "validating the model on {} scenarios{}…",
            sel.len(),
            if with_loop { " + closed loop" } else { "" }
        );
    }
    let rep = validate::run(&bench, &sel, with_loop);
    if json {
        println!("{}", serde_json::to_string_pretty(&rep)?);
        return Ok(rep.pass);
    }
    println!(
        "{:<20} {:>7} {:>6} {:>7} {:>11} {:>11} {:>6} {:>7} {:>7} {:>7} {:>7} {:>7} {:>8} {:>7}",
        "scenario",
        "P2 RMS",
        "P2 max",
        "no-HP",
        "2σ",
        "3σ",
        "empty",
        "torque",
        "T 4 s",
        "motor",
        "power",
        "fx P2",
        "fx T",
        ""
    );
    println!(
        "{:<20} {:>7} {:>6} {:>7} {:>11} {:>11} {:>6} {:>7} {:>7} {:>7} {:>7} {:>7} {:>8}",
        "(unit)",
        "bar",
        "bar",
        "bar",
        "%",
        "%",
        "ms",
        "of peak",
        "of peak",
        "of RMS",
        "of mean",
        "bar",
        "N·m"
    );
    println!(
        "{:<20} {:>7} {:>6} {:>7} {:>11} {:>11} {:>6} {:>7} {:>7} {:>7} {:>7} {:>7} {:>8}",
        "(target)",
        format!("≤{}", target::P2_RMS_BAR),
        "-",
        format!("≤{}*", target::P2_MODEL_ONLY_MAX_BAR),
        format!("≥{}", target::COVER_2S * 100.0),
        format!("≥{}", target::COVER_3S * 100.0),
        format!("≤{}", target::EMPTY_FLAG_MS),
        format!("≤{}%", target::TORQUE_RMS_OF_PEAK * 100.0),
        "-",
        format!("≤{}%", target::MOTOR_RMS_REL * 100.0),
        "-",
        format!("≤{}*", target::FIXED_VS_F64_BAR),
        format!("≤{}*", target::FIXED_VS_F64_NM)
    );
    let pct = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{:.2}%", v * 100.0));
    for r in &rep.rows {
        let misses = &r.missed;
        println!(
            "{:<20} {:>7.3} {:>6.2} {:>7.3} {:>11} {:>11} {:>6} {:>7} {:>7} {:>7} {:>7} {:>7.4} {:>8.3}  {}",
            r.scenario,
            r.p2_rms_bar,
            r.p2_max_bar,
            r.p2_model_only_max_bar,
            format!(
                "{:.2}/{:.2}",
                r.cover_2s * 100.0,
                r.cover_2s_model_only * 100.0
            ),
            format!(
                "{:.2}/{:.2}",
                r.cover_3s * 100.0,
                r.cover_3s_model_only * 100.0
            ),
            r.empty_flag_delay_ms
                .map_or("-".to_string(), |d| format!("{d:.0}")),
            pct(r.torque_rms_of_peak),
            pct(r.torque_worst_4s_of_peak),
            pct(r.motor_rms_rel),
            pct(r.valve_power_rms_of_mean),
            r.fixed_vs_f64_bar,
            r.fixed_vs_f64_nm,
            if misses.is_empty() {
                "ok".to_string()
            } else {
                format!("MISSED: {}", misses.join("; "))
            }
        );
    }
    println!(
        "σ coverage: with the transducer / without it (%). T 4 s: the largest RMS torque error \
         over 4 s (not a target). Power: the estimate's P2 · valve flow against the plant's, RMS \
         error of the mean (not a target). * no-HP ≤ {} bar in runs whose \
         estimate stays above the precharge + {} bar (else σ coverage and the empty flag, ms \
         after the bench's accumulator ran empty, judge it); fixed vs f64 ≤ {} bar and ≤ {} N·m \
         where P2 stays out of the cells at the precharge, else ≤ {} bar (torque not judged)",
        target::P2_MODEL_ONLY_MAX_BAR,
        target::PRECHARGE_MARGIN_BAR,
        target::FIXED_VS_F64_BAR,
        target::FIXED_VS_F64_NM,
        target::FIXED_VS_F64_CELL_BAR
    );
    if let Some(f) = &rep.sea_family {
        let p = |x: (f64, f64)| format!("{:.2} / {:.2} %", x.0 * 100.0, x.1 * 100.0);
        println!(
            "sea family, worst / median over {} runs ({} meet every target): torque RMS {} \
             (≤ {} %), worst 4 s torque error {} of peak, P2 RMS {:.3} / {:.3} bar, \
             model-only P2 max {:.2} / {:.2} bar, 2σ coverage {}, motor {}",
            f.runs,
            f.runs_met,
            p(f.torque_rms_of_peak),
            target::TORQUE_RMS_OF_PEAK * 100.0,
            p(f.torque_worst_4s_of_peak),
            f.p2_rms_bar.0,
            f.p2_rms_bar.1,
            f.p2_model_only_max_bar.0,
            f.p2_model_only_max_bar.1,
            p(f.cover_2s),
            p(f.motor_rms_rel),
        );
    }
    for l in &rep.closed_loop {
        println!(
            "closed loop: {:<24} max deviation {:.4} (target {}) over {:.0}–{:.0} s: {}",
            l.name,
            l.max_deviation,
            l.target,
            l.window_s.0,
            l.window_s.1,
            if l.pass { "met" } else { "MISSED" }
        );
    }
    if with_loop {
        println!(
            "sensor faults in closed loop with the firmware's controller (fault from {} s unless named):",
            pto_host::validation::faults::FAULT_FROM_S
        );
        println!(
            "  {:<48} {:>9} {:>8} {:<8} {:>8} {:>13} {:>7}  verdict",
            "case", "flagged", "bound", "held", "P2 then", "P2 after", "silent"
        );
        for d in &rep.sensor_faults {
            println!(
                "  {:<48} {:>9} {:>8} {:<8} {:>8} {:>13} {:>7}  {}",
                d.case.name,
                d.after_s.map_or("never".into(), |t| format!("{t:.2} s")),
                format!("{:.1} s", d.bound_s),
                d.held.join(","),
                d.p2_at_detection_bar
                    .map_or("-".into(), |p| format!("{p:.1}")),
                format!("{:.1}–{:.1}", d.p2_after_bar.0, d.p2_after_bar.1),
                format!("{:.1}", d.p2_silent_bar),
                if d.pass {
                    "met".to_string()
                } else {
                    format!("MISSED (named {:?}, safe after: {})", d.held, d.safe_after)
                }
            );
        }
        println!(
            "  false alarms: {} steps in {} fault-free scenarios, {} in the fault-free closed loops",
            rep.rows
                .iter()
                .map(|r| r.false_alarms.iter().sum::<u64>())
                .sum::<u64>(),
            rep.rows.len(),
            rep.loop_false_alarms
        );
        let most = |f: fn(&pto_host::validation::validate::Row) -> f64| {
            rep.rows.iter().map(f).fold(0.0, f64::max)
        };
        println!(
            "  the checks' margins over them: HP shadow excess {:.3} bar (allowed 0.25); oil \
             into HP under a reading below the range {:.3} L (allowed what the accumulator \
             holds there + 1 % of it); motor {:.1} rpm beyond 1/16 of the speed (allowed 5, for 1 s; \
             longest beyond: {} steps of 1024); LP {:.2} bar (allowed 2)",
            most(|r| r.resid_hp_max_bar),
            most(|r| r.resid_low_inflow_max_l),
            most(|r| r.resid_motor_max_rpm),
            rep.rows.iter().map(|r| r.motor_over_max).max().unwrap_or(0),
            most(|r| r.resid_lp_max_bar),
        );
    }
    for e in &rep.errors {
        println!("error: {e}");
    }
    let ok = rep.rows.iter().filter(|r| r.pass).count();
    println!(
        "{ok}/{} scenarios meet every target; closed loop {}",
        rep.rows.len(),
        if !with_loop {
            "not run (--no-loop)"
        } else if rep.closed_loop.iter().all(|l| l.pass)
            && rep.sensor_faults.iter().all(|d| d.pass)
            && rep.loop_false_alarms == 0
        {
            "met (and every sensor fault caught)"
        } else {
            "MISSED"
        }
    );
    Ok(rep.pass)
}

pub(crate) fn model_cost_cmd(a: &ModelCostArgs) -> Result<bool> {
    let json = a.json;
    a.src.apply();
    let workspace = pto_host::hil::build::workspace_root("pto model-cost (it builds pto-model)")?;
    let cost = pto_host::validation::cost::measure(&workspace)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&cost)?);
    } else {
        println!(
            "estimator + scheduler step on this host: {:.0} ns",
            cost.host_ns_per_step
        );
        println!(
            "state: {} bytes (target ≤ {}); coefficients (tables, RAM): {} bytes",
            cost.state_bytes,
            pto_host::validation::cost::target::STATE_BYTES,
            cost.coefficient_bytes
        );
        for c in &cost.code {
            let budget = if c.target.starts_with("thumbv7em") {
                format!(
                    "target ≤ {} B",
                    pto_host::validation::cost::target::FLASH_BYTES
                )
            } else {
                "no target: reported".to_string()
            };
            println!(
                "{:<24} per-step code {:>6} B ({budget}): {} functions, {} B of code, the \
                 rest constants; whole crate .text {:>6} B, .rodata {:>5} B",
                c.target,
                c.step_code_bytes,
                c.step_functions,
                c.step_text_bytes,
                c.text_bytes,
                c.rodata_bytes
            );
            let largest: Vec<String> = c
                .step_largest
                .iter()
                .take(5)
                .map(|(f, b)| format!("{f} {b} B"))
                .collect();
            println!("  largest: {}", largest.join(", "));
            if !c.step_external.is_empty() {
                println!("  from outside the crate: {}", c.step_external.join(", "));
            }
            if !c.step_panics.is_empty() {
                println!("  MISSED: the step can panic: {}", c.step_panics.join(", "));
            }
        }
        use pto_host::validation::cost::target as t;
        let m = &cost.m0;
        let verdict = |ok: bool| if ok { "met" } else { "MISSED" };
        println!(
            "Cortex-M0 (QEMU microbit), every step bit for bit the host's; coefficients {} B built \
             on it in {:.1} M instructions with {} B of stack (target ≤ {} B): {}",
            m.coefficient_bytes,
            m.build_instructions as f64 / 1e6,
            m.build_stack_bytes,
            t::M0_BUILD_STACK_BYTES,
            verdict(m.build_stack_met)
        );
        for r in &m.runs {
            println!(
                "  {:<34} {:>5} steps: instructions mean {:>5.0} max {:>5}; cycles mean {:>5.0} \
                 max {:>5} ({:.2} % of a {:.0} Hz loop at {:.0} MHz)",
                r.trace.label,
                r.trace.steps,
                r.trace.instructions_mean,
                r.trace.instructions_max,
                r.trace.cycles_mean,
                r.trace.cycles_max,
                r.core_percent_max,
                t::M0_LOOP_HZ,
                t::M0_CLOCK_HZ / 1e6
            );
        }
        println!(
            "  worst step {} instructions (target ≤ {}): {}; {:.2} % of the core (target ≤ {} %): {}",
            m.step_instructions_max,
            t::M0_STEP_INSTRUCTIONS,
            verdict(m.instructions_met),
            m.core_percent_max,
            t::M0_CORE_PERCENT,
            verdict(m.core_met)
        );
    }
    Ok(cost.pass)
}
