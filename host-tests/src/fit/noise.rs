//! What the logs themselves say before any fit: each sensor's noise (the residuals' weights and
//! the yardstick of the goodness of fit), and whether a column looks like what it claims to be.

use super::*;

/// One standard deviation of each sensor's noise.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Noise {
    /// HP pressure, bar.
    pub p2_bar: f64,
    /// Motor speed, rpm.
    pub rpm: f64,
    /// LP pressure, bar.
    pub lp_bar: f64,
    /// Estimated from the logs (`false`: given on the command line).
    pub p2_estimated: bool,
    /// Estimated from the logs (`false`: given on the command line).
    pub rpm_estimated: bool,
    /// Estimated from the logs (`false`: given on the command line).
    pub lp_estimated: bool,
}

/// The smallest noise a channel is given, in its unit: a channel cleaner than this (a simulated
/// log, a heavily filtered sensor) is weighted as if it had this noise, so that the model's own
/// error — not a vanishing σ — sets the scale.
pub const NOISE_FLOOR_P2_BAR: f64 = 0.01;
/// The smallest motor-speed noise, rpm (see [`NOISE_FLOOR_P2_BAR`]).
pub const NOISE_FLOOR_RPM: f64 = 0.1;

/// The noise σ of one sensor from every log's samples, pooled (one sensor, one noise).
///
/// The second difference `d = y[k+1] − 2y[k] + y[k−1]` of white noise has variance 6σ², while a
/// smooth signal sampled at the logs' rates contributes almost nothing to it. The largest 5 % of
/// |d| are dropped first — a stroke's pressure step, the accumulator's emptying, a start — and
/// the RMS of the rest corrected by the trimmed normal's factor: for |d| ≤ 1.96 σ_d,
/// `E[d²] = 0.759 σ_d²`. Hand-written: a dozen lines of statistics no crate of the field offers.
/// Quantisation: the estimate is not taken below q/√12 (q the channel's smallest step).
///
/// Windows within 5 samples of a value at or below `clipped_at` are left out when enough others
/// remain
/// (≥ 30): a standing motor's speed is its noise clipped at 0, half of it zeros, which would
/// make the noise look smaller than where the motor turns.
pub fn estimate_noise<'a>(
    channels: impl Iterator<Item = &'a [f64]>,
    floor: f64,
    clipped_at: f64,
) -> f64 {
    let mut d2: Vec<f64> = Vec::new();
    let mut d2_clipped: Vec<f64> = Vec::new();
    let mut q = f64::INFINITY;
    for y in channels {
        // Near a clipped value: within 5 samples of one (a standing motor's positive noise
        // samples come in short runs between zeros).
        let clipped: Vec<usize> = (0..y.len()).filter(|&k| y[k] <= clipped_at).collect();
        let near = |k: usize| {
            let i = clipped.partition_point(|&c| c + 5 < k);
            clipped.get(i).is_some_and(|&c| c <= k + 5)
        };
        for (k, w) in y.windows(3).enumerate() {
            let d = (w[2] - 2.0 * w[1] + w[0]).powi(2);
            if near(k + 1) {
                d2_clipped.push(d);
            } else {
                d2.push(d);
            }
        }
        for w in y.windows(2) {
            let s = (w[1] - w[0]).abs();
            if s > 1e-9 {
                q = q.min(s);
            }
        }
    }
    if d2.len() < 30 {
        d2.append(&mut d2_clipped);
    }
    if d2.is_empty() {
        return floor;
    }
    d2.sort_by(f64::total_cmp);
    let keep = ((d2.len() as f64) * 0.95).ceil() as usize;
    let kept = &d2[..keep.clamp(1, d2.len())];
    let var_d = kept.iter().sum::<f64>() / kept.len() as f64 / 0.759;
    let sigma = (var_d / 6.0).sqrt();
    let q_floor = if q.is_finite() { q / 12f64.sqrt() } else { 0.0 };
    sigma.max(q_floor).max(floor)
}

/// The sensor model's noise ([`SensorSpec`](crate::validation::sensors::SensorSpec)'s default: HP
/// 0.5 bar, motor 2 rpm, LP 0.2 bar), as `pto plan` assumes it without `--noise-from`.
pub fn sensor_noise() -> Noise {
    let s = crate::validation::sensors::SensorSpec::default();
    noise_of(
        &[],
        Some(s.hp_noise_bar),
        Some(s.motor_noise_rpm),
        Some(s.lp_noise_bar),
    )
}

/// Noise of the logs: estimated per sensor unless given.
pub fn noise_of(
    logs: &[BenchLog],
    p2_bar: Option<f64>,
    rpm: Option<f64>,
    lp_bar: Option<f64>,
) -> Noise {
    Noise {
        p2_bar: p2_bar.unwrap_or_else(|| {
            estimate_noise(
                logs.iter().map(|l| &l.p2_bar[..]),
                NOISE_FLOOR_P2_BAR,
                f64::NEG_INFINITY,
            )
        }),
        rpm: rpm.unwrap_or_else(|| {
            estimate_noise(logs.iter().map(|l| &l.rpm[..]), NOISE_FLOOR_RPM, 0.0)
        }),
        lp_bar: lp_bar.unwrap_or_else(|| {
            estimate_noise(
                logs.iter().map(|l| &l.lp_bar[..]),
                NOISE_FLOOR_P2_BAR,
                f64::NEG_INFINITY,
            )
        }),
        p2_estimated: p2_bar.is_none(),
        rpm_estimated: rpm.is_none(),
        lp_estimated: lp_bar.is_none(),
    }
}

/// How much a finding weighs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Severity {
    /// The fit cannot be trusted with this log as it is: the `logs` check fails.
    Error,
    /// Worth a look; the fit goes on.
    Warning,
}

/// Something implausible in a log.
#[derive(Debug, Clone, Serialize)]
pub struct Finding {
    /// The log's file.
    pub file: PathBuf,
    /// The column.
    pub column: &'static str,
    /// Error or warning.
    pub severity: Severity,
    /// What and why, with a hint where there is one.
    pub message: String,
}

/// Plausibility of a log beyond the ranges `BenchLog::read` enforces: an aperture given as a
/// fraction, a channel that does not move (a disconnected or stuck sensor), a channel that sits
/// at its highest value (a saturated transducer).
pub fn sanity(log: &BenchLog) -> Vec<Finding> {
    let mut out = Vec::new();
    let mut add = |column: &'static str, severity, message: String| {
        out.push(Finding {
            file: log.path.clone(),
            column,
            severity,
            message,
        })
    };
    let max = |y: &[f64]| y.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let min = |y: &[f64]| y.iter().copied().fold(f64::INFINITY, f64::min);
    let ap_max = max(&log.aperture_pct);
    if ap_max > 0.0 && ap_max <= 1.0 {
        add(
            "aperture_pct",
            Severity::Error,
            format!(
                "at most {ap_max} %: looks like a fraction (0–1); this column is in % (0–100), \
                 e.g. 12 for 12 % — multiply by 100"
            ),
        );
    }
    let channels: [(&'static str, &[f64], &str, Severity); 3] = [
        ("p2_bar", &log.p2_bar, "bar", Severity::Error),
        ("motor_rpm", &log.rpm, "rpm", Severity::Error),
        ("lp_bar", &log.lp_bar, "bar", Severity::Warning),
    ];
    for (column, y, unit, severity) in channels {
        let (lo, hi) = (min(y), max(y));
        if hi - lo < 1e-9 {
            // A motor standing still through a log with the valve shut is no fault.
            let idle_motor = column == "motor_rpm" && ap_max <= 0.0;
            if !idle_motor {
                add(
                    column,
                    severity,
                    format!(
                        "constant {lo} {unit} over all {} samples: a disconnected or stuck \
                         sensor?",
                        y.len()
                    ),
                );
            }
            continue;
        }
        // Saturation: a run of at least 1 % of the samples (and 5) exactly at the highest value.
        let (mut run, mut longest) = (0usize, 0usize);
        for v in y {
            run = if *v == hi { run + 1 } else { 0 };
            longest = longest.max(run);
        }
        if longest >= 5 && longest * 100 >= y.len() {
            add(
                column,
                severity,
                format!(
                    "stays at its highest value {hi} {unit} for {longest} samples in a row: a \
                     saturated transducer or a clipped range?"
                ),
            );
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rng(seed: u64) -> impl FnMut() -> f64 {
        let mut s = seed;
        // Box–Muller from a 64-bit LCG: enough for a test's noise.
        move || {
            let mut u = || {
                s = s
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (a, b) = (u(), u());
            (-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
        }
    }

    /// A smooth decay with sparse steps (1 % of the samples) and a cliff, plus white noise of
    /// known σ: the estimate is within 5 % of it.
    #[test]
    fn noise_is_recovered_under_steps_and_a_cliff() {
        for sigma in [0.05, 0.5, 2.0] {
            let mut n = rng(7);
            let y: Vec<f64> = (0..4000)
                .map(|k| {
                    let t = k as f64 * 0.1;
                    let steps = (t / 20.0).floor() * 15.0;
                    let cliff = if t > 300.0 { -40.0 } else { 0.0 };
                    100.0 * (-t / 200.0).exp() + steps + cliff + sigma * n()
                })
                .collect();
            let est = estimate_noise(std::iter::once(&y[..]), 0.0, f64::NEG_INFINITY);
            println!(
                "σ {sigma}: estimated {est:.4} ({:+.1} %)",
                100.0 * (est / sigma - 1.0)
            );
            assert!((est / sigma - 1.0).abs() < 0.05, "σ {sigma}: {est}");
        }
    }

    /// A speed that stands (its noise clipped at 0) in one log and turns in another: the noise
    /// is that of the turning motor.
    #[test]
    fn a_standing_motor_does_not_shrink_the_speed_noise() {
        let mut n = rng(3);
        let standing: Vec<f64> = (0..3000).map(|_| (2.0 * n()).max(0.0)).collect();
        let turning: Vec<f64> = (0..1000)
            .map(|k| 300.0 - 0.1 * k as f64 + 2.0 * n())
            .collect();
        let both = [&standing[..], &turning[..]];
        let est = estimate_noise(both.iter().copied(), 0.0, 0.0);
        let all = estimate_noise(both.iter().copied(), 0.0, f64::NEG_INFINITY);
        println!("σ 2 rpm: estimated {est:.3} (with the standing samples {all:.3})");
        assert!((est / 2.0 - 1.0).abs() < 0.05, "{est}");
    }

    /// A noiseless quantised channel is given q/√12, not zero.
    #[test]
    fn a_quantised_clean_channel_gets_its_quantisation_noise() {
        let y: Vec<f64> = (0..1000)
            .map(|k| (k as f64 / 37.0).floor() * 0.25)
            .collect();
        let est = estimate_noise(std::iter::once(&y[..]), 0.0, f64::NEG_INFINITY);
        assert!((est - 0.25 / 12f64.sqrt()).abs() < 1e-12, "{est}");
    }

    fn log(aperture: f64, p2: impl Fn(usize) -> f64) -> BenchLog {
        let n = 200;
        BenchLog {
            path: "x.csv".into(),
            t: (0..n).map(|k| k as f64 * 0.1).collect(),
            theta_deg: vec![0.0; n],
            p2_bar: (0..n).map(&p2).collect(),
            lp_bar: (0..n).map(|k| 5.0 + 0.01 * (k % 3) as f64).collect(),
            rpm: (0..n).map(|k| 300.0 - k as f64).collect(),
            aperture_pct: vec![aperture; n],
            on_duty: [true, false, false, false],
            config: 1,
        }
    }

    #[test]
    fn implausible_columns_are_named_with_a_hint() {
        let ok = log(12.0, |k| 100.0 - 0.1 * k as f64);
        assert!(sanity(&ok).is_empty(), "{:?}", sanity(&ok));
        let frac = sanity(&log(0.12, |k| 100.0 - 0.1 * k as f64));
        assert_eq!(frac.len(), 1);
        assert_eq!(frac[0].column, "aperture_pct");
        assert_eq!(frac[0].severity, Severity::Error);
        assert!(frac[0].message.contains("fraction"), "{}", frac[0].message);
        let flat = sanity(&log(12.0, |_| 80.0));
        assert!(
            flat.iter()
                .any(|f| f.column == "p2_bar" && f.message.contains("constant"))
        );
        let sat = sanity(&log(12.0, |k| (100.0 - 0.1 * k as f64).min(95.0)));
        assert!(
            sat.iter()
                .any(|f| f.column == "p2_bar" && f.message.contains("saturated"))
        );
    }
}
