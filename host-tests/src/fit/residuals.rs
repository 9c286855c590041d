//! Logs prepared for the fit, their simulation, and the weighted, robust residuals.

use super::*;
use std::cmp::Ordering;

/// A log prepared for simulation: the samples the residuals use.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// The log.
    pub log: BenchLog,
    /// Indices of the samples in the residual (≈ `spacing_s` apart).
    pub idx: Vec<usize>,
    motion: Motion,
    valve: Vec<(f64, f64)>,
    /// Motor speed at the start, rpm.
    pub rpm0: f64,
    /// When the logged motor speed falls below [`COLLAPSE_FRACTION`] of `rpm0` (HP accumulator
    /// empty), s; `None` if it does not.
    pub collapse: Option<f64>,
    /// Start P2, bar (see `start_value`).
    pub p2_start_bar: f64,
    /// Start LP, bar.
    pub lp_start_bar: f64,
    /// Noise σ of P2, bar: its residuals' weight.
    pub sigma_p2_bar: f64,
    /// Noise σ of the motor speed, rpm.
    pub sigma_rpm: f64,
    /// Noise σ of LP, bar.
    pub sigma_lp_bar: f64,
}

/// Prepares logs: residual samples every `spacing_s` seconds, weighted by the sensors' noise.
pub fn prepare(logs: Vec<BenchLog>, spacing_s: f64, noise: &Noise) -> Vec<Prepared> {
    let spacing = vec![spacing_s; logs.len()];
    prepare_each(logs, &spacing, noise)
}

/// [`prepare`] with each log's own spacing, s (0: every sample).
pub fn prepare_each(logs: Vec<BenchLog>, spacing: &[f64], noise: &Noise) -> Vec<Prepared> {
    logs.into_iter()
        .zip(spacing)
        .map(|(log, &spacing_s)| {
            let t0 = log.t[0];
            // Where the HP accumulator runs empty, P2 collapses and the motor stops within a
            // second or two. Pointwise residuals across that cliff would measure its timing
            // with huge, flat residuals (no gradient once the curves have parted); instead the
            // pointwise samples stop 1 s before the logged collapse and the collapse time itself
            // is one more residual, smooth in the parameters (it is what tells the precharge
            // apart from the accumulator volume).
            let moving = input_moves(&log);
            let rpm0 = start_value(&log.t, &log.rpm, moving);
            let collapse = collapse_time(&log.t, &log.rpm, rpm0);
            let end = collapse.map_or(log.t.len(), |tc| {
                log.t
                    .iter()
                    .position(|t| *t > tc - 1.0)
                    .unwrap_or(log.t.len())
            });
            let mut idx = Vec::new();
            let mut next = t0;
            for (i, &t) in log.t.iter().enumerate().take(end) {
                if t >= next {
                    idx.push(i);
                    next = t + spacing_s;
                }
            }
            let motion = Motion::from_samples(
                log.t.iter().map(|t| t - t0).collect(),
                log.theta_deg.iter().map(|a| a.to_radians()).collect(),
            );
            let (ts, ap) = log.valve_steps();
            let valve = ts.into_iter().zip(ap).collect();
            let p2_start_bar = if moving {
                flat_start(
                    &log.t,
                    &log.p2_bar,
                    MOVING_START_WINDOW_S,
                    START_JUMP_SIGMAS * noise.p2_bar,
                )
            } else {
                start_value(&log.t, &log.p2_bar, false)
            };
            let lp_start_bar = if moving {
                start_value(&log.t, &log.lp_bar, moving)
            } else {
                quadratic_start(&log.t, &log.lp_bar, LP_START_WINDOW_S)
            };
            Prepared {
                log,
                idx,
                motion,
                valve,
                p2_start_bar,
                lp_start_bar,
                rpm0,
                collapse,
                sigma_p2_bar: noise.p2_bar,
                sigma_rpm: noise.rpm,
                sigma_lp_bar: noise.lp_bar,
            }
        })
        .collect()
}

/// Start value of a logged pressure: one noisy sample would shift every later event — such as
/// the HP accumulator running empty — by its noise. With the input blocked the pressure decays
/// smoothly: a line through the first second, taken at the first sample. With the input moving,
/// P2 stays flat until the first chamber has compressed its trapped air and then climbs in
/// strokes, so a line would be biased: the mean of the first 0.3 s (at least three samples;
/// a moving log's P2 takes [`flat_start`] instead).
pub(super) fn start_value(t: &[f64], y: &[f64], moving: bool) -> f64 {
    let window = if moving { MOVING_START_WINDOW_S } else { 1.0 };
    let n = window_len(t, window, y.len());
    let (t, y) = (&t[..n], &y[..n]);
    let nf = n as f64;
    let ym = y.iter().sum::<f64>() / nf;
    if moving {
        return ym;
    }
    let tm = t.iter().sum::<f64>() / nf;
    let stt: f64 = t.iter().map(|x| (x - tm) * (x - tm)).sum();
    let sty: f64 = t.iter().zip(y).map(|(x, v)| (x - tm) * (v - ym)).sum();
    let slope = if stt > 0.0 { sty / stt } else { 0.0 };
    ym + slope * (t[0] - tm)
}

/// The window of a moving log's start values, s.
pub const MOVING_START_WINDOW_S: f64 = 0.3;

/// A step in a moving log's first samples larger than this many of the P2 noise's σ ends its
/// start value's window (2 bar at the sensor model's 0.5 bar).
pub const START_JUMP_SIGMAS: f64 = 4.0;

/// Start value of a moving log's P2: the mean of its first samples within `window` seconds, up
/// to the first that stands more than `jump` from their running mean and is followed by another
/// that does (one noisy sample is not a jump; a missing one, NaN, is). In a charge from below
/// the HP precharge the accumulator holds no oil and P2 jumps to the precharge within 0.1 s
/// (10 → 54 bar in 7 samples at 64 Hz): the mean of the whole first 0.3 s read such a log's
/// start as 42 bar and its truth fitted at χ²ᵣ 3.0; the prefix before the jump reads 10.0.
pub(super) fn flat_start(t: &[f64], y: &[f64], window: f64, jump: f64) -> f64 {
    let n = window_len(t, window, y.len());
    let (mut sum, mut k) = (0.0, 0usize);
    for i in 0..n {
        if k > 0 {
            // NaN (a missing sample) counts as off.
            let off = |v: f64| {
                matches!(
                    (v - sum / k as f64).abs().partial_cmp(&jump),
                    Some(Ordering::Greater) | None
                )
            };
            if off(y[i]) && y.get(i + 1).is_none_or(|&v| off(v)) {
                break;
            }
        }
        sum += y[i];
        k += 1;
    }
    sum / k.max(1) as f64
}

/// The window of a blocked log's LP start value, s: the LP pressure rises smoothly as the
/// accumulator's oil reaches it, and its start sets the pressure drop over the whole discharge
/// (0.15 bar of error on a 71 bar discharge moved its emptying by 3 s in 172 s).
pub const LP_START_WINDOW_S: f64 = 10.0;

/// Value at the first sample of a least-squares parabola through the samples of the first
/// `window` seconds (at least three); the mean if they do not determine one.
pub(super) fn quadratic_start(t: &[f64], y: &[f64], window: f64) -> f64 {
    let n = window_len(t, window, y.len());
    let (t, y) = (&t[..n], &y[..n]);
    // In u = t − t₀ scaled to [0, 1] for conditioning.
    let span = (t[n - 1] - t[0]).max(1e-9);
    let a = nalgebra::DMatrix::from_fn(n, 3, |i, k| ((t[i] - t[0]) / span).powi(k as i32));
    let b = nalgebra::DVector::from_column_slice(y);
    let mean = y.iter().sum::<f64>() / n as f64;
    (a.transpose() * &a)
        .lu()
        .solve(&(a.transpose() * b))
        .map_or(mean, |x| x[0])
}

/// How many samples lie within `window` seconds of the first (at least 3, at most `len`).
fn window_len(t: &[f64], window: f64, len: usize) -> usize {
    t.iter()
        .take_while(|&&x| x - t[0] <= window)
        .count()
        .max(3)
        .min(len)
}

/// Whether the shaft moves in a log (more than 0.5° of travel).
pub fn input_moves(log: &BenchLog) -> bool {
    let (lo, hi) = log
        .theta_deg
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
            (a.min(*x), b.max(*x))
        });
    hi - lo >= 0.5
}

/// Solver settings of the fit's simulations: rtol 1e-7 keeps the finite-difference Jacobian
/// (steps of 1e-4 in the bounded coordinates) two orders above the integration noise at a
/// third of the cost of the default 1e-8.
pub const FIT_SOLVER: SolverOptions = SolverOptions {
    rtol: 1e-7,
    atol_scale: 1e-2,
    reuse_kinematics: true,
};

/// Simulated (P2 bar, motor rpm) at every log sample.
pub fn simulate_log(bench: &Bench, p: &Prepared) -> Result<Vec<Truth>, FitError> {
    simulate_log_from(bench, p, [0.0; 2])
}

/// Like [`simulate_log`], with the start P2 and LP moved by `offset` bar.
pub fn simulate_log_from(
    bench: &Bench,
    p: &Prepared,
    offset: [f64; 2],
) -> Result<Vec<Truth>, FitError> {
    let log = &p.log;
    let on: [bool; 4] = log.on_duty;
    let plant = Plant::new(bench, log.config - 1, on, p.motion.clone());
    let t0 = log.t[0];
    let dur = log.t[log.t.len() - 1] - t0;
    let res = solver::simulate(Run {
        plant: &plant,
        valve: ValveSchedule::Table(p.valve.clone()),
        initial: Initial {
            p2_pa: (p.p2_start_bar + offset[0]) * BAR,
            lp_pa: (p.lp_start_bar + offset[1]) * BAR,
        },
        duration: dur,
        sample_dt: trace_dt(log),
        solver: FIT_SOLVER,
        progress: None,
    })
    .map_err(|source| FitError::Simulation {
        log: log.name(),
        source,
    })?;
    Ok(log.t.iter().map(|t| truth_at(&res.trace, t - t0)).collect())
}

/// The simulated trace's sample interval for a log, s: half the log's median interval, at most
/// 0.05 s (a 10 Hz log's as before), as `pto synth-logs` samples its own simulation. The trace
/// is interpolated linearly at the log's times; at 0.05 s for a 64 Hz log, the interpolation's
/// own error on a charge's pressure steps made the truth's χ²ᵣ 1.7 and the fit stop 10σ off.
fn trace_dt(log: &BenchLog) -> f64 {
    let mut dt: Vec<f64> = log.t.windows(2).map(|w| w[1] - w[0]).collect();
    if dt.is_empty() {
        return 0.05;
    }
    let mid = dt.len() / 2;
    let median = *dt.select_nth_unstable_by(mid, f64::total_cmp).1;
    (0.5 * median).clamp(1e-3, 0.05)
}

/// Residuals beyond this many σ are flattened (r → C·tanh(r/C)), so that a few samples far off
/// (a transient slightly shifted in time) cannot dominate the sum and pull the fit into a
/// compensating valley.
pub const ROBUST_SIGMAS: f64 = 10.0;

pub(super) fn residuals_of(p: &Prepared, sim: &[Truth], out: &mut Vec<f64>) {
    let from = out.len();
    raw_residuals(p, sim, out);
    for r in &mut out[from..] {
        *r = ROBUST_SIGMAS * (*r / ROBUST_SIGMAS).tanh();
    }
}

pub(super) fn raw_residuals(p: &Prepared, sim: &[Truth], out: &mut Vec<f64>) {
    pointwise_residuals(p, sim, out);
    if let Some(tc) = p.collapse {
        // A simulation that does not collapse within the log counts as collapsing at its end.
        let ts = simulated_collapse(p, sim).unwrap_or(p.log.t[p.log.t.len() - 1]);
        out.push((ts - tc) / SIGMA_COLLAPSE_S);
    }
}

/// Residuals per sample: P2, motor speed, LP.
pub const CHANNELS: usize = 3;

/// The P2, motor-speed and LP residuals at the log's residual samples, in units of the noise,
/// interleaved (P2, speed, LP, P2, …). LP carries the oil the accumulators exchange: what the
/// LP accumulator gives the cylinders in a charge, what it receives from the motor in a
/// discharge.
pub(super) fn pointwise_residuals(p: &Prepared, sim: &[Truth], out: &mut Vec<f64>) {
    for &i in &p.idx {
        out.push((sim[i].p2_bar - p.log.p2_bar[i]) / p.sigma_p2_bar);
        out.push((sim[i].motor_rpm - p.log.rpm[i]) / p.sigma_rpm);
        out.push((sim[i].lp_bar - p.log.lp_bar[i]) / p.sigma_lp_bar);
    }
}

/// When the simulated motor falls below [`COLLAPSE_FRACTION`] of the log's starting speed (the
/// simulated HP accumulator empty), s; `None` for a log that starts too slow to tell (< 50 rpm)
/// or a simulation that does not collapse.
pub fn simulated_collapse(p: &Prepared, sim: &[Truth]) -> Option<f64> {
    let rpm: Vec<f64> = sim.iter().map(|x| x.motor_rpm).collect();
    collapse_time(&p.log.t, &rpm, p.rpm0)
}

/// The HP accumulator's emptying in a motor-speed trace: the speed falls below
/// [`COLLAPSE_FRACTION`] of `rpm0` having been above half of it [`CLIFF_S`] earlier — a cliff,
/// not the slow decay of a discharge at low pressure that crosses the same level over minutes.
/// `None` for a trace that starts too slow to tell (< 50 rpm) or has no such cliff.
pub fn collapse_time(t: &[f64], rpm: &[f64], rpm0: f64) -> Option<f64> {
    if rpm0 <= 50.0 {
        return None;
    }
    let tc = crossing(t, rpm, COLLAPSE_FRACTION * rpm0)?;
    let before = t.iter().rposition(|x| *x <= tc - CLIFF_S)?;
    (rpm[before] >= 0.5 * rpm0).then_some(tc)
}

/// How fast the speed must fall from half its start to [`COLLAPSE_FRACTION`] of it for an
/// emptying, s. (An emptying takes well under a second; a discharge that merely slows takes
/// tens of seconds.)
pub const CLIFF_S: f64 = 3.0;

/// The collapse is where the motor speed falls below this fraction of its starting speed.
pub const COLLAPSE_FRACTION: f64 = 0.25;
/// σ of the collapse time, s.
pub const SIGMA_COLLAPSE_S: f64 = 2.0;

/// First time `y` falls below `level` after having been above it, linearly interpolated.
pub fn crossing(t: &[f64], y: &[f64], level: f64) -> Option<f64> {
    let first_above = y.iter().position(|v| *v >= level)?;
    (first_above + 1..y.len()).find(|&k| y[k] < level).map(|k| {
        let (y0, y1) = (y[k - 1], y[k]);
        let u = if y0 > y1 {
            (y0 - level) / (y0 - y1)
        } else {
            1.0
        };
        t[k - 1] + u.clamp(0.0, 1.0) * (t[k] - t[k - 1])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A charge's P2 that jumps from 10 bar to the precharge within the window starts at 10 bar;
    /// a flat one at its mean.
    #[test]
    fn a_moving_start_stops_at_the_first_jump() {
        let t: Vec<f64> = (0..40).map(|k| k as f64 / 64.0).collect();
        let y: Vec<f64> = (0..40)
            .map(|k| {
                let noise = if k % 2 == 0 { 0.4 } else { -0.4 };
                noise + if k < 8 { 10.0 } else { 54.0 }
            })
            .collect();
        let s = flat_start(&t, &y, MOVING_START_WINDOW_S, 2.0);
        println!(
            "start {s:.3} bar (mean of the window {:.1})",
            start_value(&t, &y, true)
        );
        assert!((s - 10.0).abs() < 0.1, "{s}");
        assert!((flat_start(&t, &[7.0; 40], 0.3, 2.0) - 7.0).abs() < 1e-12);
        // One sample 3 bar off is noise, not the jump: the window goes on past it.
        let mut spike = [7.0; 40];
        spike[1] = 10.0;
        let with_spike = flat_start(&t, &spike, 0.3, 2.0);
        assert!(
            (with_spike - (7.0 + 3.0 / 20.0)).abs() < 1e-9,
            "{with_spike}"
        );
        // A missing sample ends it.
        let mut gap = [7.0; 40];
        gap[3] = f64::NAN;
        gap[4] = f64::NAN;
        assert_eq!(flat_start(&t, &gap, 0.3, 2.0), 7.0);
    }

    /// The parabola's value at the first sample: exact for a parabola, the mean for a flat
    /// line, and less scattered than the first second's line on a noisy LP rise.
    #[test]
    fn the_lp_start_is_read_off_a_parabola() {
        let t: Vec<f64> = (0..200).map(|k| k as f64 * 0.1).collect();
        let y: Vec<f64> = t.iter().map(|x| 8.0 + 0.3 * x - 0.004 * x * x).collect();
        assert!((quadratic_start(&t, &y, LP_START_WINDOW_S) - 8.0).abs() < 1e-9);
        assert!((quadratic_start(&t, &[5.0; 200], LP_START_WINDOW_S) - 5.0).abs() < 1e-12);
        // Alternating ±0.2 bar on the rise: the parabola's start error is a fraction of it.
        let noisy: Vec<f64> = y
            .iter()
            .enumerate()
            .map(|(k, v)| v + if k % 2 == 0 { 0.2 } else { -0.2 })
            .collect();
        let e = (quadratic_start(&t, &noisy, LP_START_WINDOW_S) - 8.0).abs();
        println!("start error {e:.4} bar for ±0.2 bar of noise");
        assert!(e < 0.05, "{e}");
    }
}
