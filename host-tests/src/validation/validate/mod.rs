//! `pto validate`: the fixed-point model against the full simulation, per scenario (both modes,
//! σ coverage, the empty flag, the f64 mirror), and the closed-loop rows of [`super::closed_loop`].

use super::closed_loop::{LoopRow, closed_loop_rows};
use super::{ModelError, commanded_aperture_pct, duty_mask, model_config};
use crate::sim::bench::{BAR, Bench};
use crate::sim::scenario::{RunError, Scenario};
use crate::sim::solver::SolverOptions;
use crate::sim::trace::{Truth, truth_at, value_at};
use crate::validation::reference::Reference;
use crate::validation::sensors::{SensorSpec, SensorSynth};
use pto_model::estimator::{self, Estimate, Inputs, State};
use pto_model::fx::Pressure;
use pto_model::table::Table1;
use pto_model::{Coefficients, ModelConfig, coeffs};
use rayon::prelude::*;
use spread::WorstWindow;
pub use spread::{FAMILY_GROUP, Spread, WORST_WINDOW_S};

mod spread;
use serde::Serialize;
use std::path::Path;

use super::target;

/// One scenario's figures.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// Scenario.
    pub scenario: String,
    /// P2 RMS error with the HP transducer, bar.
    pub p2_rms_bar: f64,
    /// P2 max error with the HP transducer, bar (not a target: where the HP accumulator runs
    /// empty, P2 falls several bar within one 8 ms trace sample, faster than a filter of a
    /// 0.5 bar-noise transducer follows).
    pub p2_max_bar: f64,
    /// P2 max error, model only, first 60 s, bar.
    pub p2_model_only_max_bar: f64,
    /// Torque RMS error / peak torque (None when the input does not move: no restraining
    /// torque to speak of, only the static LP·A_rod of the rods).
    pub torque_rms_of_peak: Option<f64>,
    /// The worst torque event: the largest RMS torque error over any 4 s window, as a fraction
    /// of the peak torque (information, not a target: where the error of a run sits).
    pub torque_worst_4s_of_peak: Option<f64>,
    /// Start of that window, s.
    pub torque_worst_4s_at_s: Option<f64>,
    /// Motor speed RMS error / RMS speed (None when the motor does not turn).
    pub motor_rms_rel: Option<f64>,
    /// Hydraulic power into the valve (the estimate's P2 · valve flow against the plant's): RMS
    /// error / mean power (information, not a target; None when the mean is below 1 W).
    pub valve_power_rms_of_mean: Option<f64>,
    /// Max |P2 fixed − P2 f64|, bar, over both runs (with the HP transducer, and without it for
    /// the first 60 s).
    pub fixed_vs_f64_bar: f64,
    /// RMS |torque fixed − torque f64|, N·m.
    pub fixed_vs_f64_nm: f64,
    /// Max of it, N·m: dominated by steps where one side detects a stroke reversal one step
    /// before the other (the torque then jumps by the full stroke torque); not a target.
    pub fixed_vs_f64_nm_max: f64,
    /// Share of the samples with the HP transducer (after 1 s) whose |P2 error| ≤ 2σ (σ the
    /// estimate's own [`Estimate::p2_sigma`]).
    pub cover_2s: f64,
    /// Same for ≤ 3σ.
    pub cover_3s: f64,
    /// Share of the model-only samples (first 60 s) with |P2 error| ≤ 2σ.
    pub cover_2s_model_only: f64,
    /// Same for ≤ 3σ.
    pub cover_3s_model_only: f64,
    /// Lowest model-only P2 estimate over the window, bar (the 2 bar target applies where it
    /// stays above the HP precharge + 1 bar).
    pub model_only_min_p2_bar: f64,
    /// Times the plant's HP accumulator ran empty (P2 below its precharge for at least the
    /// flag's allowed delay) in the model-only window.
    pub emptyings: usize,
    /// Longest delay from the plant's accumulator running empty to the model-only estimate's
    /// empty flag, ms (the window's rest when it never came; None without an emptying).
    pub empty_flag_delay_ms: Option<f64>,
    /// Share of the model-only samples with the empty flag up while the plant's P2 was more
    /// than 0.3 bar above the precharge (information: the flag's margin makes it early).
    pub empty_flag_early: f64,
    /// The f64 reference's P2 entered the capacitance table's cell at the HP precharge (there
    /// the node's dynamics are locally unstable and trajectories separate).
    pub crosses_precharge_cell: bool,
    /// The HP shadow check's largest excess at a judged step (the reading against the model
    /// alone since its window began, less a quarter of the model's own change), bar: what its fixed
    /// allowance (`estimator::residual`, 0.25 bar) must cover.
    pub resid_hp_max_bar: f64,
    /// The largest net inflow into HP the model counted while the HP reading stayed below the
    /// shadow check's range, L (the stuck-low check's limit: what the accumulator holds at the
    /// range's bottom, + 1 % of its volume).
    pub resid_low_inflow_max_l: f64,
    /// The largest motor residual (measured − modelled speed, 0.25 s mean) beyond 1/16 of the
    /// modelled speed, rpm (its fixed allowance is 5 rpm, for 1 s).
    pub resid_motor_max_rpm: f64,
    /// The largest LP residual (1 s mean), bar.
    pub resid_lp_max_bar: f64,
    /// Steps with a sensor-fault flag raised in this fault-free run (false alarms), by flag:
    /// HP, motor, LP, encoder stuck (target: none).
    pub false_alarms: [u64; 4],
    /// The longest the motor residual stayed beyond its allowance, steps (it flags at
    /// `estimator::MOTOR_PERSIST_STEPS`).
    pub motor_over_max: u16,
    /// The targets missed, each named with its figure (empty: every target met).
    pub missed: Vec<String>,
    /// Every target met.
    pub pass: bool,
}

/// The whole report.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Per scenario.
    pub rows: Vec<Row>,
    /// The spread of the sea family's rows (group `sea-family`), when any was validated.
    pub sea_family: Option<Spread>,
    /// Closed loop.
    pub closed_loop: Vec<LoopRow>,
    /// Sensor faults in closed loop with the firmware's controller (with the closed loop):
    /// each case's detection, the sensor named, the safe state.
    pub sensor_faults: Vec<crate::validation::faults::Detection>,
    /// Steps with a sensor fault held in the fault-free closed loops (with the closed loop).
    pub loop_false_alarms: usize,
    /// Failed runs, each error with its causes.
    pub errors: Vec<String>,
    /// Every target met.
    pub pass: bool,
}

/// Sample interval of the plant traces the sensors are made from, s (the model steps at
/// 2^−10 s in between, on linearly interpolated plant values).
const TRACE_DT: f64 = 1.0 / 128.0;

fn validate_scenario(
    bench: &Bench,
    mcfg: &ModelConfig,
    k: &Coefficients,
    s: &Scenario,
    seed: u64,
) -> Result<Row, RunError> {
    let mut s = s.clone();
    s.sample_interval_s = TRACE_DT;
    let (prep, res) = s.simulate(bench, Path::new("."), SolverOptions::default(), None)?;
    let tr = &res.trace;
    let motion = prep.plant.motion();
    let dt = 2f64.powi(-i32::from(mcfg.dt_log2));
    let n = (s.duration_s / dt) as usize;
    let duty = duty_mask(&prep.on_duty);
    let config = prep.config as u8;
    let t0 = truth_at(tr, 0.0);
    // With the HP transducer: fixed point and f64 side by side.
    let mut synth = SensorSynth::new(SensorSpec::default(), seed);
    let mut st = State::new(
        Pressure::from_num(t0.p2_bar as f32),
        Pressure::from_num(t0.lp_bar as f32),
        Pressure::from_num(1.0),
    );
    let mut rf = Reference::new(mcfg, k, t0.p2_bar, t0.lp_bar, 1.0);
    let (mut se_p2, mut se_tq, mut se_w, mut ss_w, mut peak_tq) = (0.0, 0.0, 0.0, 0.0, 0.0f64);
    let (mut se_pw, mut sum_pw) = (0.0, 0.0);
    let (mut d_p2, mut d_tq, mut se_d_tq) = (0.0f64, 0.0f64, 0.0f64);
    let mut count = 0.0f64;
    let mut max_p2 = 0.0f64;
    let mut cover = Coverage::default();
    let mut worst_window = WorstWindow::new((WORST_WINDOW_S / dt) as usize);
    // The capacitance table's cell around the precharge (its nodes on either side).
    let h = f64::from(Table1::<{ coeffs::N_NODE }>::spacing(
        0.0,
        coeffs::P_MAX_BAR,
    ));
    let pre_model = f64::from(mcfg.hp_accumulator.precharge_bar);
    // The cells on either side of the precharge (its dP/dV jump is interpolated over the one
    // below it, and P2 settles in the one above).
    let cell = (pre_model - h, pre_model + h);
    let in_cell = |p: f64| p >= cell.0 && p <= cell.1;
    let mut crosses_cell = false;
    let (mut r_hp, mut r_low, mut r_m, mut r_lp) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let (mut fa, mut mo_max) = ([0u64; 4], 0u16);
    for i in 0..n {
        let t = i as f64 * dt;
        let truth = truth_at(tr, t);
        let ap = commanded_aperture_pct(&s, &res, t);
        let inp = synth
            .read(motion.at(t).0, &truth)
            .to_inputs(ap, duty, config);
        let e = estimator::step(k, &mut st, &inp);
        let r = rf.step(&inp);
        crosses_cell |= in_cell(r.p2_bar);
        let (p2, tq, w) = (
            f64::from(e.p2.to_f32()),
            f64::from(e.torque.to_f32()),
            f64::from(e.motor_rpm.to_f32()),
        );
        d_p2 = d_p2.max((p2 - r.p2_bar).abs());
        if st.resid.hp_last_judged {
            r_hp = r_hp.max(st.resid.hp_excess.to_num::<f64>());
        }
        r_low = r_low.max(st.resid.low_inflow.to_num::<f64>() / 60.0);
        use pto_model::estimator::fault;
        fa[0] += u64::from(e.faults & fault::HP_DISAGREES != 0);
        fa[1] += u64::from(e.faults & fault::MOTOR_DISAGREES != 0);
        fa[2] += u64::from(e.faults & fault::LP_DISAGREES != 0);
        fa[3] += u64::from(e.faults & fault::ENCODER_STUCK != 0);
        mo_max = mo_max.max(st.resid.motor_over);
        if t >= 1.0 {
            let m = st.resid.motor.to_num::<f64>().abs() - 0.0625 * w.abs();
            r_m = r_m.max(m);
            r_lp = r_lp.max(st.resid.lp.to_num::<f64>().abs());
        }
        d_tq = d_tq.max((tq - r.torque_nm).abs());
        se_d_tq += (tq - r.torque_nm).powi(2);
        // Judge after the first wave period's start-up transient of the tracker (1 s).
        if t >= 1.0 {
            max_p2 = max_p2.max((p2 - truth.p2_bar).abs());
            se_p2 += (p2 - truth.p2_bar).powi(2);
            se_tq += (tq - truth.torque_nm).powi(2);
            worst_window.add(t, (tq - truth.torque_nm).powi(2));
            se_w += (w - truth.motor_rpm).powi(2);
            ss_w += truth.motor_rpm.powi(2);
            let pw = value_at(tr, &tr.valve_power_w, t);
            se_pw += (f64::from(e.hydraulic_power().to_f32()) - pw).powi(2);
            sum_pw += pw;
            peak_tq = peak_tq.max(truth.torque_nm.abs());
            count += 1.0;
            cover.add(p2 - truth.p2_bar, &e);
        }
    }
    // Without the HP transducer, from the known start, for 60 s (the f64 model alongside).
    let mut synth = SensorSynth::new(SensorSpec::default(), seed + 1);
    let mut st = State::new(
        Pressure::from_num(t0.p2_bar as f32),
        Pressure::from_num(t0.lp_bar as f32),
        Pressure::from_num(0.0),
    );
    let m = ((target::MODEL_ONLY_WINDOW_S.min(s.duration_s)) / dt) as usize;
    let mut max_mo = 0.0f64;
    let mut min_p2_mo = f64::INFINITY;
    let mut rf_mo = Reference::new(mcfg, k, t0.p2_bar, t0.lp_bar, 0.0);
    let mut d_p2_mo = 0.0f64;
    let mut cover_mo = Coverage::default();
    let mut empty = EmptyWatch::new(
        bench.hp_acc.precharge_pa / BAR,
        target::EMPTY_FLAG_MS * 1e-3,
    );
    for i in 0..m {
        let t = i as f64 * dt;
        let truth: Truth = truth_at(tr, t);
        let ap = commanded_aperture_pct(&s, &res, t);
        let inp = Inputs {
            hp: None,
            ..synth
                .read(motion.at(t).0, &truth)
                .to_inputs(ap, duty, config)
        };
        let e = estimator::step(k, &mut st, &inp);
        let p2 = f64::from(e.p2.to_f32());
        max_mo = max_mo.max((p2 - truth.p2_bar).abs());
        min_p2_mo = min_p2_mo.min(p2);
        cover_mo.add(p2 - truth.p2_bar, &e);
        empty.step(t, truth.p2_bar, e.hp_empty);
        let r = rf_mo.step(&inp);
        crosses_cell |= in_cell(r.p2_bar);
        d_p2_mo = d_p2_mo.max((p2 - r.p2_bar).abs());
    }
    let (emptyings, empty_flag_delay_ms, empty_flag_early) = empty.finish(m as f64 * dt);
    let rms = |se: f64| (se / count.max(1.0)).sqrt();
    let moving = !matches!(s.motion, crate::sim::motion::MotionSpec::Blocked { .. });
    let worst = worst_window.worst().filter(|_| moving);
    let motor_rms_rel = (ss_w / count.max(1.0) > 1.0).then(|| (se_w / ss_w).sqrt());
    let mean_pw = sum_pw / count.max(1.0);
    let valve_power_rms_of_mean = (mean_pw > 1.0).then(|| rms(se_pw) / mean_pw);
    let row = Row {
        scenario: s.name.clone(),
        p2_rms_bar: rms(se_p2),
        p2_max_bar: max_p2,
        p2_model_only_max_bar: max_mo,
        torque_rms_of_peak: moving.then(|| rms(se_tq) / peak_tq.max(1.0)),
        torque_worst_4s_of_peak: worst.map(|(ms, _)| ms.sqrt() / peak_tq.max(1.0)),
        torque_worst_4s_at_s: worst.map(|(_, t)| t),
        motor_rms_rel,
        valve_power_rms_of_mean,
        fixed_vs_f64_bar: d_p2.max(d_p2_mo),
        fixed_vs_f64_nm: (se_d_tq / n.max(1) as f64).sqrt(),
        fixed_vs_f64_nm_max: d_tq,
        cover_2s: cover.share(2),
        cover_3s: cover.share(3),
        cover_2s_model_only: cover_mo.share(2),
        cover_3s_model_only: cover_mo.share(3),
        model_only_min_p2_bar: min_p2_mo,
        emptyings,
        empty_flag_delay_ms: empty_flag_delay_ms.map(|d| d * 1e3),
        empty_flag_early,
        crosses_precharge_cell: crosses_cell,
        resid_hp_max_bar: r_hp,
        resid_low_inflow_max_l: r_low,
        resid_motor_max_rpm: r_m,
        resid_lp_max_bar: r_lp,
        false_alarms: fa,
        motor_over_max: mo_max,
        missed: Vec::new(),
        pass: false,
    };
    let missed = row.misses(pre_model);
    Ok(Row {
        pass: missed.is_empty(),
        missed,
        ..row
    })
}

impl Row {
    /// The targets this row misses, each named with its figure (empty: every target met).
    /// `precharge_bar` is the model's HP precharge.
    pub fn misses(&self, precharge_bar: f64) -> Vec<String> {
        let mut out = Vec::new();
        let mut miss = |ok: bool, what: String| {
            if !ok {
                out.push(what);
            }
        };
        miss(
            self.p2_rms_bar <= target::P2_RMS_BAR,
            format!("P2 RMS {:.3} bar > {}", self.p2_rms_bar, target::P2_RMS_BAR),
        );
        // Model-only P2: within 2 bar where the estimate stays above the precharge + 1 bar;
        // where it does not (the HP accumulator runs empty), covered by σ and flagged in time.
        if self.model_only_min_p2_bar >= precharge_bar + target::PRECHARGE_MARGIN_BAR {
            miss(
                self.p2_model_only_max_bar <= target::P2_MODEL_ONLY_MAX_BAR,
                format!(
                    "model-only P2 max {:.2} bar > {}",
                    self.p2_model_only_max_bar,
                    target::P2_MODEL_ONLY_MAX_BAR
                ),
            );
        }
        miss(
            self.false_alarms.iter().all(|&n| n == 0),
            format!(
                "false sensor-fault alarms (steps: HP {}, motor {}, LP {}, encoder {})",
                self.false_alarms[0],
                self.false_alarms[1],
                self.false_alarms[2],
                self.false_alarms[3]
            ),
        );
        if let Some(d) = self.empty_flag_delay_ms {
            miss(
                d <= target::EMPTY_FLAG_MS,
                format!("empty flag {d:.0} ms late > {}", target::EMPTY_FLAG_MS),
            );
        }
        for (c, t, what) in [
            (self.cover_2s, target::COVER_2S, "2σ coverage"),
            (self.cover_3s, target::COVER_3S, "3σ coverage"),
            (
                self.cover_2s_model_only,
                target::COVER_2S,
                "model-only 2σ coverage",
            ),
            (
                self.cover_3s_model_only,
                target::COVER_3S,
                "model-only 3σ coverage",
            ),
        ] {
            miss(
                c >= t,
                format!("{what} {:.2} % < {} %", c * 100.0, t * 100.0),
            );
        }
        if let Some(tq) = self.torque_rms_of_peak {
            miss(
                tq <= target::TORQUE_RMS_OF_PEAK,
                format!(
                    "torque {:.2} % > {} %",
                    tq * 100.0,
                    target::TORQUE_RMS_OF_PEAK * 100.0
                ),
            );
        }
        if let Some(m) = self.motor_rms_rel {
            miss(
                m <= target::MOTOR_RMS_REL,
                format!(
                    "motor {:.2} % > {} %",
                    m * 100.0,
                    target::MOTOR_RMS_REL * 100.0
                ),
            );
        }
        let fx_bar = if self.crosses_precharge_cell {
            target::FIXED_VS_F64_CELL_BAR
        } else {
            target::FIXED_VS_F64_BAR
        };
        miss(
            self.fixed_vs_f64_bar <= fx_bar,
            format!("fixed vs f64 {:.3} bar > {fx_bar}", self.fixed_vs_f64_bar),
        );
        miss(
            self.crosses_precharge_cell || self.fixed_vs_f64_nm <= target::FIXED_VS_F64_NM,
            format!(
                "fixed vs f64 {:.3} N·m > {}",
                self.fixed_vs_f64_nm,
                target::FIXED_VS_F64_NM
            ),
        );
        out
    }
}

/// Counts the samples whose P2 error lies within 2σ and 3σ of the estimate's own σ.
#[derive(Default)]
struct Coverage {
    n: u64,
    in_2s: u64,
    in_3s: u64,
}

impl Coverage {
    fn add(&mut self, err_bar: f64, e: &Estimate) {
        let var: f64 = e.p2_var.0.to_num();
        let e2 = err_bar * err_bar;
        self.n += 1;
        self.in_2s += u64::from(e2 <= 4.0 * var);
        self.in_3s += u64::from(e2 <= 9.0 * var);
    }

    /// Share within `k`σ (1 when there were no samples).
    fn share(&self, k: u8) -> f64 {
        let inside = if k == 2 { self.in_2s } else { self.in_3s };
        if self.n == 0 {
            1.0
        } else {
            inside as f64 / self.n as f64
        }
    }
}

/// Watches the plant's HP accumulator run empty (P2 below its precharge) and the estimate's
/// empty flag follow it.
struct EmptyWatch {
    precharge_bar: f64,
    allowed_s: f64,
    /// When the plant's P2 last fell below the precharge, and when the flag followed.
    below_since: Option<(f64, Option<f64>)>,
    events: usize,
    worst_s: Option<f64>,
    /// Samples, and those with the flag up while the plant's accumulator still held oil
    /// (P2 more than [`EARLY_MARGIN_BAR`] above the precharge).
    samples: u64,
    early: u64,
}

/// The plant's P2 this far above the precharge still has oil in its accumulator, bar (an
/// empty flag then is early).
const EARLY_MARGIN_BAR: f64 = 0.3;

impl EmptyWatch {
    fn new(precharge_bar: f64, allowed_s: f64) -> Self {
        EmptyWatch {
            precharge_bar,
            allowed_s,
            below_since: None,
            events: 0,
            worst_s: None,
            samples: 0,
            early: 0,
        }
    }

    fn step(&mut self, t: f64, plant_p2_bar: f64, flag: bool) {
        self.samples += 1;
        if flag && plant_p2_bar > self.precharge_bar + EARLY_MARGIN_BAR {
            self.early += 1;
        }
        if plant_p2_bar >= self.precharge_bar {
            // Back above (a dip shorter than the allowed delay is not an emptying).
            self.close(t);
            return;
        }
        let (since, seen) = self.below_since.get_or_insert((t, None));
        if flag && seen.is_none() {
            *seen = Some(t - *since);
        }
    }

    /// The plant's P2 is back above the precharge (or the window ends) at `t`: a stay below of
    /// at least the allowed delay was an emptying.
    fn close(&mut self, t: f64) {
        if let Some((since, seen)) = self.below_since.take()
            && t - since >= self.allowed_s
        {
            self.events += 1;
            let d = seen.unwrap_or(t - since);
            self.worst_s = Some(self.worst_s.map_or(d, |w: f64| w.max(d)));
        }
    }

    /// (emptyings, worst delay in s, share of samples flagged early) at the end of the window
    /// `t_end`.
    fn finish(mut self, t_end: f64) -> (usize, Option<f64>, f64) {
        self.close(t_end);
        let early = self.early as f64 / self.samples.max(1) as f64;
        (self.events, self.worst_s, early)
    }
}

/// The sensor-noise seed of a scenario: from its name (FNV-1a), so a row does not depend on
/// which other scenarios `--filter` selected.
fn seed_of(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// Validates `scenarios` (in parallel) and the closed loop.
pub fn run(bench: &Bench, scenarios: &[Scenario], with_loop: bool) -> Report {
    let configured = model_config(bench).and_then(|c| {
        let k = c.coefficients().map_err(ModelError::from)?;
        Ok((c, k))
    });
    let (mcfg, k) = match configured {
        Ok(x) => x,
        Err(e) => {
            return Report {
                rows: vec![],
                sea_family: None,
                closed_loop: vec![],
                sensor_faults: vec![],
                loop_false_alarms: 0,
                errors: vec![crate::error_chain(&e)],
                pass: false,
            };
        }
    };
    let results: Vec<Result<Row, RunError>> = scenarios
        .par_iter()
        // Errors from `Scenario::simulate` already name the scenario.
        .map(|s| validate_scenario(bench, &mcfg, &k, s, seed_of(&s.name)))
        .collect();
    let loops = if with_loop {
        closed_loop_rows(bench)
    } else {
        vec![]
    };
    let (detections, loop_fa) = if with_loop {
        sensor_fault_rows(bench)
    } else {
        (vec![], vec![])
    };
    let mut rows = Vec::new();
    let mut errors = Vec::new();
    for r in results {
        match r {
            Ok(x) => rows.push(x),
            Err(e) => errors.push(crate::error_chain(&e)),
        }
    }
    let mut closed = Vec::new();
    for r in loops {
        match r {
            Ok(x) => closed.push(x),
            Err(e) => errors.push(crate::error_chain(&e)),
        }
    }
    let mut sensor_faults = Vec::new();
    for d in detections {
        match d {
            Ok(d) => sensor_faults.push(d),
            Err(e) => errors.push(crate::error_chain(&e)),
        }
    }
    let mut loop_false_alarms = 0;
    for n in loop_fa {
        match n {
            Ok(n) => loop_false_alarms += n,
            Err(e) => errors.push(crate::error_chain(&e)),
        }
    }
    let pass = errors.is_empty()
        && rows.iter().all(|r| r.pass)
        && closed.iter().all(|r| r.pass)
        && sensor_faults.iter().all(|d| d.pass)
        && loop_false_alarms == 0;
    let in_family = |name: &str| {
        scenarios
            .iter()
            .any(|s| s.name == name && s.group == FAMILY_GROUP)
    };
    let family: Vec<&Row> = rows.iter().filter(|r| in_family(&r.scenario)).collect();
    let sea_family = Spread::of(&family);
    Report {
        sea_family,
        rows,
        closed_loop: closed,
        sensor_faults,
        loop_false_alarms,
        errors,
        pass,
    }
}

/// The sensor-fault cases and the fault-free closed loops (`model::faults`), in parallel.
#[allow(clippy::type_complexity)]
fn sensor_fault_rows(
    bench: &Bench,
) -> (
    Vec<Result<crate::validation::faults::Detection, crate::validation::faults::FaultRunError>>,
    Vec<Result<usize, crate::validation::faults::FaultRunError>>,
) {
    use crate::validation::faults;
    let d = match faults::detect_all(bench, &faults::cases(), 11) {
        Ok(v) => v.into_iter().map(Ok).collect(),
        Err(e) => vec![Err(e)],
    };
    let fa = faults::fault_free_loops()
        .par_iter()
        .map(|(m, p0)| faults::false_alarms(bench, *m, *p0, 12))
        .collect();
    (d, fa)
}
