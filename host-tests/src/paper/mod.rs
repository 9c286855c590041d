//! The paper's facts (Section 4.1), checked on the built-in scenarios.

use crate::runner::Outcome;
use crate::sim::bench::{BAR, Bench, LPM, RPM};
use crate::sim::scenario::{BLOCKED_APERTURES, SETS, TEST3_APERTURES};
use crate::sim::solver::SimResult;
use crate::sim::trace::Trace;
use serde::Serialize;
use std::collections::HashMap;

/// Tolerances of the facts, named.
pub mod tol {
    /// Fact 1: peak input speed 2.5 rpm ± 5 %.
    pub const PEAK_SPEED_RPM: f64 = 2.5;
    /// Fact 1 relative band.
    pub const PEAK_SPEED_REL: f64 = 0.05;
    /// Fact 2: P2 held within ± 2 bar of the relief setting over the last 100 s.
    pub const RELIEF_BAND_BAR: f64 = 2.0;
    /// Fact 5: motor speed within ± 3 % of its one-period moving mean (200–400 s).
    pub const SPEED_RIPPLE_REL: f64 = 0.03;
    /// Fact 5: speed vs Eq. 9 applied to the valve flow, RMS relative.
    pub const EQ9_REL: f64 = 0.03;
    /// Fact 6: mean motor flow vs mean injected flow minus leakage.
    pub const FLOW_MEAN_REL: f64 = 0.02;
    /// Fact 7: single-cylinder peak ratio vs A_cap/A_ann.
    pub const ASYM_RATIO_REL: f64 = 0.10;
    /// Fact 7: HC3.1 + HC3.3 peaks equal.
    pub const SYM_REL: f64 = 0.05;
    /// Fact 8: torque counts as applied above this fraction of the run's peak.
    pub const TORQUE_ON_FRACTION: f64 = 0.10;
    /// Fact 9: autonomy = time until the motor falls below this speed. It must lie below the
    /// speed the smallest tested aperture gives while the HP accumulator still holds oil
    /// (≈ 70 rpm at 10 % near the 25 bar precharge), else it measures the starting speed, not
    /// the stored volume: with 100 rpm the 10 % run starts at 168 rpm and "runs out" at 50 bar.
    pub const AUTONOMY_MIN_RPM: f64 = 50.0;
    /// Fact 10: volume and energy balances.
    pub const BALANCE_REL: f64 = 1e-4;
}

/// One checked fact.
#[derive(Debug, Clone, Serialize)]
pub struct Fact {
    /// 1..10.
    pub id: u32,
    /// The statement checked.
    pub statement: String,
    /// What was measured.
    pub measured: String,
    /// Holds?
    pub pass: bool,
}

fn max(x: &[f64]) -> f64 {
    x.iter().copied().fold(f64::NEG_INFINITY, f64::max)
}
fn min(x: &[f64]) -> f64 {
    x.iter().copied().fold(f64::INFINITY, f64::min)
}
fn mean(x: &[f64]) -> f64 {
    x.iter().sum::<f64>() / x.len().max(1) as f64
}

/// First time a series reaches `level` (linear interpolation).
pub fn time_to_reach(t: &[f64], x: &[f64], level: f64) -> Option<f64> {
    (1..x.len())
        .find(|&k| x[k - 1] < level && x[k] >= level)
        .map(|k| {
            let u = (level - x[k - 1]) / (x[k] - x[k - 1]);
            t[k - 1] + u * (t[k] - t[k - 1])
        })
}

/// First time a series falls below `level` after having been above it.
pub fn time_to_fall(t: &[f64], x: &[f64], level: f64) -> Option<f64> {
    let start = x.iter().position(|&v| v >= level)?;
    (start + 1..x.len()).find(|&k| x[k] < level).map(|k| t[k])
}

/// Largest relative deviation of `x` from its centred moving mean over `window` samples.
pub fn ripple_about_moving_mean(x: &[f64], window: usize) -> f64 {
    if x.len() < window + 1 || window == 0 {
        return f64::NAN;
    }
    let mut prefix = vec![0.0; x.len() + 1];
    for (i, v) in x.iter().enumerate() {
        prefix[i + 1] = prefix[i] + v;
    }
    let half = window / 2;
    let mut worst = 0.0f64;
    for k in half..x.len() - (window - half) {
        let m = (prefix[k - half + window] - prefix[k - half]) / window as f64;
        worst = worst.max(((x[k] - m) / m).abs());
    }
    worst
}

/// Results by scenario name.
pub struct Results<'a> {
    map: HashMap<&'a str, &'a SimResult>,
}

impl<'a> Results<'a> {
    /// Indexes successful outcomes.
    pub fn new(outcomes: &'a [Outcome]) -> Self {
        Results {
            map: outcomes
                .iter()
                .filter_map(|o| {
                    o.result
                        .as_ref()
                        .ok()
                        .map(|r| (o.scenario.name.as_str(), r))
                })
                .collect(),
        }
    }

    /// The trace of a scenario.
    pub fn trace(&self, name: &str) -> Option<&'a Trace> {
        self.map.get(name).map(|r| &r.trace)
    }

    /// The result of a scenario.
    pub fn get(&self, name: &str) -> Option<&'a SimResult> {
        self.map.get(name).copied()
    }
}

fn fact(id: u32, statement: &str, measured: String, pass: bool) -> Fact {
    Fact {
        id,
        statement: statement.into(),
        measured,
        pass,
    }
}

fn missing(id: u32, statement: &str, name: &str) -> Fact {
    fact(id, statement, format!("scenario {name} did not run"), false)
}

macro_rules! need {
    ($r:expr, $name:expr, $id:expr, $st:expr) => {
        match $r.trace(&$name) {
            Some(t) => t,
            None => return missing($id, $st, &$name),
        }
    };
}

/// Checks all ten facts.
pub fn check(bench: &Bench, outcomes: &[Outcome]) -> Vec<Fact> {
    let r = Results::new(outcomes);
    vec![
        fact1(&r),
        fact2(bench, &r),
        fact3(&r),
        fact4(&r),
        fact5(bench, &r),
        fact6(&r),
        fact7(bench, &r),
        fact8(&r),
        fact9(&r),
        fact10(outcomes),
    ]
}

fn fact1(r: &Results) -> Fact {
    let st = "peak shaft speed for ±40 mm at 0.1 Hz is 2.5 rpm ± 5 %";
    let t = need!(r, "test3-ap10", 1, st);
    let peak = t.theta_dot_rad_s.iter().fold(0.0f64, |m, v| m.max(v.abs())) * RPM;
    let rel = (peak / tol::PEAK_SPEED_RPM - 1.0).abs();
    fact(
        1,
        st,
        format!(
            "{peak:.3} rpm ({:+.2} %)",
            (peak / tol::PEAK_SPEED_RPM - 1.0) * 100.0
        ),
        rel <= tol::PEAK_SPEED_REL,
    )
}

fn fact2(bench: &Bench, r: &Results) -> Fact {
    let st =
        "valve closed: P2 rises to the relief setting and holds at 130 ± 2 bar; LP falls meanwhile";
    let setting = bench.relief_setting_pa / BAR;
    let (mut lo, mut hi, mut worst_lp, mut all) =
        (f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY, true);
    for config in 1..=4 {
        for (tag, _) in SETS {
            let name = format!("test2-cfg{config}-{tag}");
            let t = need!(r, name, 2, st);
            let end = *t.t_s.last().unwrap_or(&0.0);
            let w = t.window(end - 100.0, end);
            let (a, b) = (min(&t.p2_pa[w.clone()]) / BAR, max(&t.p2_pa[w]) / BAR);
            let lp_drop = (t.lp_pa[t.len() - 1] - t.lp_pa[0]) / BAR;
            lo = lo.min(a);
            hi = hi.max(b);
            worst_lp = worst_lp.max(lp_drop);
            all &= (a - setting).abs() <= tol::RELIEF_BAND_BAR
                && (b - setting).abs() <= tol::RELIEF_BAND_BAR
                && lp_drop < 0.0;
        }
    }
    fact(
        2,
        st,
        format!(
            "P2 over the last 100 s of 16 runs: {lo:.2}..{hi:.2} bar; LP change ≤ {worst_lp:+.2} bar"
        ),
        all,
    )
}

fn fact3(r: &Results) -> Fact {
    let st = "valve closed: time to 100 bar is shortest in Config 1 and shortens with more cylinders on duty, in every config";
    let mut table = Vec::new();
    let mut times = [[f64::NAN; 4]; 4];
    for config in 1..=4 {
        for (j, (tag, _)) in SETS.iter().enumerate() {
            let name = format!("test2-cfg{config}-{tag}");
            let t = need!(r, name, 3, st);
            times[config - 1][j] =
                time_to_reach(&t.t_s, &t.p2_pa, 100.0 * BAR).unwrap_or(f64::INFINITY);
        }
        table.push(format!(
            "cfg{config}: {}",
            times[config - 1]
                .iter()
                .map(|x| format!("{x:.0}"))
                .collect::<Vec<_>>()
                .join("/")
        ));
    }
    let config1_fastest = (0..4).all(|j| (1..4).all(|c| times[0][j] < times[c][j]));
    // Sets in order {HC3.1}, {HC3.4}, {HC3.1, HC3.4}, all four: 1, 1, 2, 4 cylinders.
    let more_is_faster = times
        .iter()
        .all(|row| row[3] < row[2] && row[2] < row[0].min(row[1]));
    fact(
        3,
        st,
        format!(
            "s to 100 bar ({}): {}",
            SETS.map(|s| s.0).join("/"),
            table.join("; ")
        ),
        config1_fastest && more_is_faster,
    )
}

fn fact4(r: &Results) -> Fact {
    let st = "Test III: P2 rises for apertures ≤ 10 % and falls for ≥ 15 %; LP rises when P2 falls";
    let mut parts = Vec::new();
    let mut ok = true;
    for ap in TEST3_APERTURES {
        let name = format!("test3-ap{ap}");
        let res = match r.get(&name) {
            Some(x) => x,
            None => return missing(4, st, &name),
        };
        let t = &res.trace;
        let Some(t_open) = res.valve_opened_at else {
            return fact(4, st, format!("{name}: valve never opened"), false);
        };
        // Compare one-period means right after opening and at the end of the run.
        let a = t.window(t_open, t_open + 10.0);
        let end = *t.t_s.last().unwrap_or(&0.0);
        let b = t.window(end - 10.0, end);
        let dp2 = (mean(&t.p2_pa[b.clone()]) - mean(&t.p2_pa[a.clone()])) / BAR;
        let dlp = (mean(&t.lp_pa[b]) - mean(&t.lp_pa[a])) / BAR;
        parts.push(format!("{ap}%: ΔP2 {dp2:+.1}, ΔLP {dlp:+.2}"));
        if ap <= 10.0 {
            ok &= dp2 > 0.0;
        } else if ap >= 15.0 {
            ok &= dp2 < 0.0 && dlp > 0.0;
        }
    }
    fact(4, st, parts.join("; "), ok)
}

fn fact5(bench: &Bench, r: &Results) -> Fact {
    let st = "Test III: motor speed within ± 3 % of its one-period moving mean over 200–400 s, and proportional to motor flow per Eq. 9";
    let mut worst_ripple = 0.0f64;
    let mut worst_eq9 = 0.0f64;
    for ap in TEST3_APERTURES {
        let name = format!("test3-ap{ap}");
        let t = need!(r, name, 5, st);
        let w = t.window(200.0, 400.0);
        let dt = t.t_s[1] - t.t_s[0];
        let period = (10.0 / dt).round() as usize;
        worst_ripple =
            worst_ripple.max(ripple_about_moving_mean(&t.omega_rad_s[w.clone()], period));
        // Eq. 9 on the flow that reaches the motor: ω = (q − k_leak·Δp)/D.
        let mut se = 0.0;
        let mut n = 0.0;
        for k in w {
            let pred = (t.q_valve_m3_s[k]
                - bench.motor_leak_m3_per_s_pa * (t.p_motor_pa[k] - t.lp_pa[k]))
                / bench.motor_disp_m3_per_rad;
            se += ((pred - t.omega_rad_s[k]) / t.omega_rad_s[k]).powi(2);
            n += 1.0;
        }
        worst_eq9 = worst_eq9.max((se / n).sqrt());
    }
    fact(
        5,
        st,
        format!(
            "ripple ≤ {:.2} %, Eq. 9 RMS deviation ≤ {:.2} %",
            worst_ripple * 100.0,
            worst_eq9 * 100.0
        ),
        worst_ripple <= tol::SPEED_RIPPLE_REL && worst_eq9 <= tol::EQ9_REL,
    )
}

/// Window of the last `n` whole wave periods (10 s) of a run.
fn last_periods(t: &Trace, n: f64) -> std::ops::Range<usize> {
    let end = *t.t_s.last().unwrap_or(&0.0);
    t.window(end - 10.0 * n, end - 1e-9)
}

fn fact6(r: &Results) -> Fact {
    let st = "Test I: mean motor flow equals mean injected flow minus leakage within 2 %";
    let mut worst = 0.0f64;
    let mut parts = Vec::new();
    for config in [1, 3] {
        for (tag, _) in SETS {
            let name = format!("test1-cfg{config}-{tag}");
            let t = need!(r, name, 6, st);
            let w = last_periods(t, 5.0);
            let inj = mean(&t.q_inj_m3_s[w.clone()]);
            let leak = mean(&t.q_relief_m3_s[w.clone()]);
            let motor = mean(&t.q_motor_m3_s[w]);
            let rel = (motor - (inj - leak)).abs() / inj;
            worst = worst.max(rel);
            parts.push(format!("{config}/{tag} {:.2}", inj * LPM));
        }
    }
    fact(
        6,
        st,
        format!(
            "worst |Δ| {:.2} % (injected L/min: {})",
            worst * 100.0,
            parts.join(", ")
        ),
        worst <= tol::FLOW_MEAN_REL,
    )
}

/// Peak injected flow while the shaft turns positive and negative.
fn directional_peaks(t: &Trace) -> (f64, f64) {
    let w = last_periods(t, 3.0);
    let (mut pos, mut neg) = (0.0f64, 0.0f64);
    for k in w {
        if t.theta_dot_rad_s[k] > 0.0 {
            pos = pos.max(t.q_inj_m3_s[k]);
        } else {
            neg = neg.max(t.q_inj_m3_s[k]);
        }
    }
    (pos, neg)
}

fn fact7(bench: &Bench, r: &Results) -> Fact {
    let st = "flow asymmetry: one cylinder delivers peaks in ratio ≈ A_cap/A_ann; HC3.1 + HC3.3 deliver equal peaks both ways";
    let t1 = need!(r, "test1-cfg1-c1", 7, st);
    let t13 = need!(r, "test1-cfg1-c13", 7, st);
    let c = &bench.cylinders[0];
    let want = c.area_cap_m2 / c.area_ann_m2;
    let (a, b) = directional_peaks(t1);
    let ratio = a.max(b) / a.min(b);
    let (p, n) = directional_peaks(t13);
    let sym = (p / n - 1.0).abs();
    fact(
        7,
        st,
        format!(
            "HC3.1 ratio {ratio:.3} (A_cap/A_ann {want:.3}); HC3.1+HC3.3 peaks {:.2}/{:.2} L/min",
            p * LPM,
            n * LPM
        ),
        (ratio / want - 1.0).abs() <= tol::ASYM_RATIO_REL && sym <= tol::SYM_REL,
    )
}

/// Peak |torque| and the fraction of the cycle with |torque| above 10 % of that peak, over the
/// last two periods.
fn torque_stats(t: &Trace) -> (f64, f64) {
    let w = last_periods(t, 2.0);
    let peak = t.torque_nm[w.clone()]
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let on = t.torque_nm[w.clone()]
        .iter()
        .filter(|v| v.abs() > tol::TORQUE_ON_FRACTION * peak)
        .count();
    (peak, on as f64 / w.len().max(1) as f64)
}

fn fact8(r: &Results) -> Fact {
    let st = "restraining torque grows with cylinders on duty; Config 1 has the largest peak, Config 3 the smallest and the shortest torque fraction of the cycle";
    let mut peak = [[0.0; 4]; 3];
    let mut frac = [[0.0; 4]; 3];
    for config in 1..=3 {
        for (j, (tag, _)) in SETS.iter().enumerate() {
            let name = format!("torque-cfg{config}-{tag}");
            let t = need!(r, name, 8, st);
            (peak[config - 1][j], frac[config - 1][j]) = torque_stats(t);
        }
    }
    let grows = peak
        .iter()
        .all(|row| row[3] > row[2] && row[2] > row[0].max(row[1]));
    let order = (0..4).all(|j| peak[0][j] > peak[1][j] && peak[1][j] > peak[2][j]);
    let shorter = (0..4).all(|j| frac[2][j] < frac[0][j]);
    let fmt = |row: &[f64; 4], k: f64, d: usize| {
        row.iter()
            .map(|v| format!("{:.*}", d, v * k))
            .collect::<Vec<_>>()
            .join("/")
    };
    fact(
        8,
        st,
        format!(
            "peak N·m cfg1 {} | cfg2 {} | cfg3 {}; on-fraction % cfg1 {} cfg3 {}",
            fmt(&peak[0], 1.0, 0),
            fmt(&peak[1], 1.0, 0),
            fmt(&peak[2], 1.0, 0),
            fmt(&frac[0], 100.0, 1),
            fmt(&frac[2], 100.0, 1)
        ),
        grows && order && shorter,
    )
}

/// Autonomy of a blocked-input run: time until the motor falls below the minimum speed.
pub fn autonomy(t: &Trace, min_rpm: f64) -> Option<f64> {
    let rpm: Vec<f64> = t.omega_rad_s.iter().map(|w| w * RPM).collect();
    time_to_fall(&t.t_s, &rpm, min_rpm)
}

fn fact9(r: &Results) -> Fact {
    let st = "blocked input from 102 bar: autonomy (motor above 50 rpm) strictly decreases with aperture";
    let mut a = Vec::new();
    for ap in BLOCKED_APERTURES {
        let name = format!("blocked-ap{ap}");
        let t = need!(r, name, 9, st);
        a.push(autonomy(t, tol::AUTONOMY_MIN_RPM));
    }
    let ok = a.iter().all(Option::is_some) && a.windows(2).all(|w| w[1] < w[0]);
    let txt: Vec<String> = BLOCKED_APERTURES
        .iter()
        .zip(&a)
        .map(|(ap, x)| match x {
            Some(v) => format!("{ap}%: {v:.1} s"),
            None => format!("{ap}%: never"),
        })
        .collect();
    fact(9, st, txt.join(", "), ok)
}

fn fact10(outcomes: &[Outcome]) -> Fact {
    let st = "oil (mass) and energy balances close within 1e-4 in every run";
    let mut worst = 0.0f64;
    let mut worst_name = String::new();
    let mut failed = Vec::new();
    for o in outcomes {
        match &o.result {
            Ok(res) => {
                if res.balance.worst() > worst {
                    worst = res.balance.worst();
                    worst_name = o.scenario.name.clone();
                }
            }
            Err(e) => failed.push(crate::error_chain(e)),
        }
    }
    if !failed.is_empty() {
        return fact(
            10,
            st,
            format!("{} runs failed: {}", failed.len(), failed.join("; ")),
            false,
        );
    }
    fact(
        10,
        st,
        format!(
            "worst {worst:.1e} ({worst_name}) over {} runs",
            outcomes.len()
        ),
        worst <= tol::BALANCE_REL,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ripple_of_a_pure_sine_about_its_mean() {
        let x: Vec<f64> = (0..2000)
            .map(|k| 100.0 + 2.0 * (k as f64 * 0.01 * std::f64::consts::TAU).sin())
            .collect();
        let r = ripple_about_moving_mean(&x, 100);
        assert!((r - 0.02).abs() < 1e-3, "{r}");
    }

    #[test]
    fn crossing_times_interpolate() {
        let t = [0.0, 1.0, 2.0];
        let x = [0.0, 10.0, 20.0];
        assert_eq!(time_to_reach(&t, &x, 15.0), Some(1.5));
        assert_eq!(time_to_reach(&t, &x, 25.0), None);
        assert_eq!(time_to_fall(&t, &[5.0, 3.0, 1.0], 2.0), Some(2.0));
    }
}
