//! Prescribed shaft motion: sinusoid, blocked, a recorded trace, or an irregular (JONSWAP) sea.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// How the input moves, as written in scenario files (rack in mm, the shaft follows through the
/// pinion).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum MotionSpec {
    /// `x_rack = A·sin(2π f t)`.
    Sine {
        /// Rack amplitude, mm.
        amplitude_mm: f64,
        /// Frequency, Hz.
        frequency_hz: f64,
    },
    /// Input held (calm sea).
    Blocked {
        /// Held shaft angle, degrees.
        #[serde(default)]
        angle_deg: f64,
    },
    /// A recorded trace: CSV with columns `time_s` and `shaft_angle_deg`.
    Trace {
        /// The CSV file (relative paths are relative to the scenario file).
        file: PathBuf,
    },
    /// Irregular sea: sum of sinusoids drawn from a JONSWAP spectrum of rack displacement.
    Irregular {
        /// Significant rack displacement 4σ, mm.
        significant_mm: f64,
        /// Peak period, s.
        peak_period_s: f64,
        /// Peak enhancement factor γ (3.3 is the JONSWAP mean).
        #[serde(default = "default_gamma")]
        gamma: f64,
        /// Number of spectral components.
        #[serde(default = "default_components")]
        components: usize,
        /// Random seed of the phases.
        #[serde(default)]
        seed: u64,
    },
}

fn default_gamma() -> f64 {
    3.3
}
fn default_components() -> usize {
    64
}

/// Why a motion could not be built.
#[derive(Debug, thiserror::Error)]
pub enum MotionError {
    /// A parameter is out of range.
    #[error("{field}: {value} outside [{min}, {max}] ({unit})")]
    Range {
        /// Field name.
        field: &'static str,
        /// Offending value.
        value: f64,
        /// Minimum.
        min: f64,
        /// Maximum.
        max: f64,
        /// Unit.
        unit: &'static str,
    },
    /// The trace file is unusable.
    #[error("{file}:{line}: {message}")]
    Trace {
        /// File.
        file: String,
        /// 1-based line (0 = whole file).
        line: usize,
        /// What is wrong.
        message: String,
    },
}

fn range(
    field: &'static str,
    value: f64,
    min: f64,
    max: f64,
    unit: &'static str,
) -> Result<(), MotionError> {
    if value.is_finite() && value >= min && value <= max {
        Ok(())
    } else {
        Err(MotionError::Range {
            field,
            value,
            min,
            max,
            unit,
        })
    }
}

/// Shaft motion ready to evaluate: angle (rad) and speed (rad/s) at any time.
#[derive(Debug, Clone, PartialEq)]
pub enum Motion {
    /// θ = Θ sin(ωt).
    Sine {
        /// Θ, rad.
        amplitude: f64,
        /// ω, rad/s.
        omega: f64,
    },
    /// θ = const.
    Blocked(f64),
    /// Cubic Hermite (Catmull–Rom slopes) through recorded samples: continuous speed.
    Trace {
        /// Times, s.
        t: Vec<f64>,
        /// Angles, rad.
        theta: Vec<f64>,
        /// Slopes, rad/s.
        slope: Vec<f64>,
    },
    /// Σ a_i sin(ω_i t + φ_i) over evenly spaced ω_i (a JONSWAP sea).
    Sum(Comb),
}

/// A sum of sinusoids over evenly spaced frequencies, Σ a_i sin(ω_i t + φ_i) with
/// ω_i = ω_0 + i·Δω.
///
/// Hand-written evaluation: the irregular sea's cost was its 64–128 `sin_cos` per instant (55 %
/// of a run). [`Comb::at`] turns e^{iω_0 t} by e^{iΔω t} from one component to the next, with an
/// exact `sin_cos` every [`Comb::EXACT_EVERY`] components so the rounding of the turns cannot
/// build up (≤ 1e-13 rad over 1000 s: `comb_matches_the_direct_sum`); [`Comb::at_direct`] is
/// the per-component evaluation, the solver's reference path.
#[derive(Debug, Clone, PartialEq)]
pub struct Comb {
    /// (a_i rad, ω_i rad/s, φ_i rad).
    comps: Vec<(f64, f64, f64)>,
    /// (a_i·cos φ_i, a_i·sin φ_i).
    phasors: Vec<(f64, f64)>,
    /// Δω, rad/s.
    dw: f64,
}

impl Comb {
    /// Components between two exact evaluations of the carrier.
    pub const EXACT_EVERY: usize = 16;

    /// The sum of `comps` (a_i, ω_i, φ_i), whose ω_i must be evenly spaced by `dw`.
    fn new(comps: Vec<(f64, f64, f64)>, dw: f64) -> Self {
        let phasors = comps
            .iter()
            .map(|&(a, _, ph)| {
                let (s, c) = ph.sin_cos();
                (a * c, a * s)
            })
            .collect();
        Comb { comps, phasors, dw }
    }

    /// Angle (rad) and speed (rad/s) at `t`.
    pub fn at(&self, t: f64) -> (f64, f64) {
        let (sd, cd) = (self.dw * t).sin_cos();
        let (mut theta, mut speed) = (0.0, 0.0);
        let (mut s, mut c) = (0.0, 0.0);
        for (i, (&(_, w, _), &(ac, as_))) in self.comps.iter().zip(&self.phasors).enumerate() {
            if i % Self::EXACT_EVERY == 0 {
                (s, c) = (w * t).sin_cos();
            } else {
                (s, c) = (s * cd + c * sd, c * cd - s * sd);
            }
            // a·sin(ωt + φ) = a·cos φ·sin ωt + a·sin φ·cos ωt, and its derivative.
            theta += ac * s + as_ * c;
            speed += w * (ac * c - as_ * s);
        }
        (theta, speed)
    }

    /// The same by one `sin_cos` per component.
    pub fn at_direct(&self, t: f64) -> (f64, f64) {
        self.comps.iter().fold((0.0, 0.0), |(a, v), &(amp, w, ph)| {
            let (s, co) = (w * t + ph).sin_cos();
            (a + amp * s, v + amp * w * co)
        })
    }

    /// Σ |a_i|, rad.
    fn amplitude_bound(&self) -> f64 {
        self.comps.iter().map(|x| x.0.abs()).sum()
    }
}

impl Motion {
    /// Builds the motion from its spec; `base` resolves relative trace paths.
    pub fn from_spec(
        spec: &MotionSpec,
        pinion_radius: f64,
        base: &Path,
    ) -> Result<Self, MotionError> {
        match spec {
            MotionSpec::Sine {
                amplitude_mm,
                frequency_hz,
            } => {
                range("motion.amplitude_mm", *amplitude_mm, 0.0, 500.0, "mm")?;
                range("motion.frequency_hz", *frequency_hz, 0.001, 5.0, "Hz")?;
                Ok(Motion::Sine {
                    amplitude: amplitude_mm * 1e-3 / pinion_radius,
                    omega: 2.0 * std::f64::consts::PI * frequency_hz,
                })
            }
            MotionSpec::Blocked { angle_deg } => {
                range("motion.angle_deg", *angle_deg, -30.0, 30.0, "deg")?;
                Ok(Motion::Blocked(angle_deg.to_radians()))
            }
            MotionSpec::Trace { file } => {
                let path = if file.is_relative() {
                    base.join(file)
                } else {
                    file.clone()
                };
                Self::from_trace_file(&path)
            }
            MotionSpec::Irregular {
                significant_mm,
                peak_period_s,
                gamma,
                components,
                seed,
            } => {
                range("motion.significant_mm", *significant_mm, 0.0, 200.0, "mm")?;
                range("motion.peak_period_s", *peak_period_s, 1.0, 60.0, "s")?;
                range("motion.gamma", *gamma, 1.0, 10.0, "-")?;
                range("motion.components", *components as f64, 4.0, 4096.0, "-")?;
                Ok(Self::jonswap(
                    significant_mm * 1e-3 / pinion_radius,
                    *peak_period_s,
                    *gamma,
                    *components,
                    *seed,
                ))
            }
        }
    }

    /// Reads a `time_s, shaft_angle_deg` CSV (header required; extra columns ignored).
    pub fn from_trace_file(path: &Path) -> Result<Self, MotionError> {
        let file = path.display().to_string();
        let err = |line: usize, message: String| MotionError::Trace {
            file: file.clone(),
            line,
            message,
        };
        let mut rdr = csv::Reader::from_path(path).map_err(|e| err(0, e.to_string()))?;
        let headers = rdr.headers().map_err(|e| err(1, e.to_string()))?.clone();
        let col = |name: &str| {
            headers
                .iter()
                .position(|h| h.trim() == name)
                .ok_or_else(|| {
                    err(
                        1,
                        format!(
                            "missing column `{name}` (have: {})",
                            headers.iter().collect::<Vec<_>>().join(", ")
                        ),
                    )
                })
        };
        let (it, ia) = (col("time_s")?, col("shaft_angle_deg")?);
        let (mut t, mut theta) = (Vec::new(), Vec::new());
        for (k, rec) in rdr.records().enumerate() {
            let line = k + 2;
            let rec = rec.map_err(|e| err(line, e.to_string()))?;
            let get = |i: usize, name: &str| -> Result<f64, MotionError> {
                rec.get(i)
                    .and_then(|s| s.trim().parse::<f64>().ok())
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| {
                        err(
                            line,
                            format!(
                                "column `{name}`: not a number: {:?}",
                                rec.get(i).unwrap_or("")
                            ),
                        )
                    })
            };
            let (ti, ai) = (get(it, "time_s")?, get(ia, "shaft_angle_deg")?);
            if let Some(&last) = t.last()
                && ti <= last
            {
                return Err(err(
                    line,
                    format!("column `time_s`: {ti} s is not after {last} s (time must increase)"),
                ));
            }
            if !(-30.0..=30.0).contains(&ai) {
                return Err(err(
                    line,
                    format!("column `shaft_angle_deg`: {ai} outside [-30, 30] (deg)"),
                ));
            }
            t.push(ti);
            theta.push(ai.to_radians());
        }
        if t.len() < 2 {
            return Err(err(0, "needs at least 2 samples".into()));
        }
        Ok(Self::from_samples(t, theta))
    }

    /// Hermite interpolant through samples (times strictly increasing).
    pub fn from_samples(t: Vec<f64>, theta: Vec<f64>) -> Self {
        let n = t.len();
        let slope = (0..n)
            .map(|i| {
                let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
                (theta[b] - theta[a]) / (t[b] - t[a])
            })
            .collect();
        Motion::Trace { t, theta, slope }
    }

    /// JONSWAP sum of sinusoids with shaft significant amplitude `hs` (rad, 4σ).
    fn jonswap(hs: f64, tp: f64, gamma: f64, n: usize, seed: u64) -> Self {
        let fp = 1.0 / tp;
        let (f0, f1) = (0.5 * fp, 3.0 * fp);
        let df = (f1 - f0) / n as f64;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut comps: Vec<(f64, f64, f64)> = (0..n)
            .map(|i| {
                let f = f0 + (i as f64 + 0.5) * df;
                let sigma = if f <= fp { 0.07 } else { 0.09 };
                let r = (-(f - fp).powi(2) / (2.0 * sigma * sigma * fp * fp)).exp();
                let s = f.powi(-5) * (-1.25 * (fp / f).powi(4)).exp() * gamma.powf(r);
                let phase = rng.random::<f64>() * 2.0 * std::f64::consts::PI;
                ((2.0 * s * df).sqrt(), 2.0 * std::f64::consts::PI * f, phase)
            })
            .collect();
        // Scale so that 4σ = hs exactly (σ² = Σ a²/2).
        let var: f64 = comps.iter().map(|c| 0.5 * c.0 * c.0).sum();
        let k = if var > 0.0 {
            hs / (4.0 * var.sqrt())
        } else {
            0.0
        };
        for c in &mut comps {
            c.0 *= k;
        }
        Motion::Sum(Comb::new(comps, 2.0 * std::f64::consts::PI * df))
    }

    /// Shaft angle (rad) and speed (rad/s) at time `t`.
    pub fn at(&self, t: f64) -> (f64, f64) {
        match self {
            Motion::Sine { amplitude, omega } => {
                let (s, c) = (omega * t).sin_cos();
                (amplitude * s, amplitude * omega * c)
            }
            Motion::Blocked(a) => (*a, 0.0),
            Motion::Trace {
                t: ts,
                theta,
                slope,
            } => {
                let n = ts.len();
                if t <= ts[0] {
                    return (theta[0], 0.0);
                }
                if t >= ts[n - 1] {
                    return (theta[n - 1], 0.0);
                }
                let i = ts.partition_point(|&x| x <= t) - 1;
                let h = ts[i + 1] - ts[i];
                let u = (t - ts[i]) / h;
                let (u2, u3) = (u * u, u * u * u);
                let (y0, y1, m0, m1) = (theta[i], theta[i + 1], slope[i] * h, slope[i + 1] * h);
                let y = (2.0 * u3 - 3.0 * u2 + 1.0) * y0
                    + (u3 - 2.0 * u2 + u) * m0
                    + (-2.0 * u3 + 3.0 * u2) * y1
                    + (u3 - u2) * m1;
                let dy = ((6.0 * u2 - 6.0 * u) * y0
                    + (3.0 * u2 - 4.0 * u + 1.0) * m0
                    + (-6.0 * u2 + 6.0 * u) * y1
                    + (3.0 * u2 - 2.0 * u) * m1)
                    / h;
                (y, dy)
            }
            Motion::Sum(c) => c.at(t),
        }
    }

    /// [`Motion::at`] on the reference path: an irregular sea by one `sin_cos` per component.
    pub fn at_reference(&self, t: f64) -> (f64, f64) {
        match self {
            Motion::Sum(c) => c.at_direct(t),
            _ => self.at(t),
        }
    }

    /// The period of a sinusoid (None otherwise).
    pub fn period(&self) -> Option<f64> {
        match self {
            Motion::Sine { omega, .. } if *omega > 0.0 => Some(2.0 * std::f64::consts::PI / omega),
            _ => None,
        }
    }

    /// Peak |θ| (rad): exact for a sinusoid, sampled bound for the others.
    pub fn peak_angle(&self) -> f64 {
        match self {
            Motion::Sine { amplitude, .. } => amplitude.abs(),
            Motion::Blocked(a) => a.abs(),
            Motion::Trace { theta, .. } => theta.iter().fold(0.0, |m, a| m.max(a.abs())),
            Motion::Sum(c) => c.amplitude_bound(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn comb_matches_the_direct_sum() {
        // The built-in sea's 64 components and the family's 128, over 1000 s.
        for (n, tp) in [(64, 10.0), (128, 6.0), (4096, 14.0)] {
            let Motion::Sum(c) = Motion::jonswap(0.4, tp, 3.3, n, 7) else {
                panic!("a sum");
            };
            let (mut worst_a, mut worst_v) = (0.0f64, 0.0f64);
            for k in 0..20_000 {
                let t = k as f64 * 0.05 + 0.0123;
                let (a, v) = c.at(t);
                let (ad, vd) = c.at_direct(t);
                worst_a = worst_a.max((a - ad).abs());
                worst_v = worst_v.max((v - vd).abs());
            }
            println!("{n} components: |Δθ| ≤ {worst_a:.1e} rad, |Δθ̇| ≤ {worst_v:.1e} rad/s");
            assert!(
                worst_a <= 1e-13 && worst_v <= 1e-13,
                "{worst_a:e} {worst_v:e}"
            );
        }
    }

    #[test]
    fn sine_peak_speed_is_2_5_rpm() {
        let m = Motion::from_spec(
            &MotionSpec::Sine {
                amplitude_mm: 40.0,
                frequency_hz: 0.1,
            },
            0.096,
            Path::new("."),
        )
        .unwrap();
        let rpm = m.at(0.0).1 * 30.0 / std::f64::consts::PI;
        assert!((rpm - 2.5).abs() < 0.01, "{rpm}");
    }

    #[test]
    fn jonswap_has_requested_significant_amplitude() {
        let m = Motion::jonswap(0.5, 10.0, 3.3, 64, 7);
        let n = 200_000;
        let dt = 0.05;
        let var = (0..n).map(|k| m.at(k as f64 * dt).0.powi(2)).sum::<f64>() / n as f64;
        let hs = 4.0 * var.sqrt();
        println!("Hs from 10^4 s of samples: {hs:.4} (want 0.5)");
        assert!((hs - 0.5).abs() < 0.02);
    }

    #[test]
    fn trace_interpolation_is_exact_at_samples_and_smooth_between() {
        let t: Vec<f64> = (0..50).map(|k| k as f64 * 0.2).collect();
        let th: Vec<f64> = t.iter().map(|x| (0.6 * x).sin() * 0.3).collect();
        let m = Motion::from_samples(t.clone(), th.clone());
        for (ti, a) in t.iter().zip(&th) {
            assert!((m.at(*ti).0 - a).abs() < 1e-12);
        }
        let mut max_err = 0.0f64;
        for k in 0..900 {
            let x = 0.4 + k as f64 * 0.01;
            max_err = max_err.max((m.at(x).0 - (0.6 * x).sin() * 0.3).abs());
        }
        println!("Hermite max error {max_err:.2e} rad");
        assert!(max_err < 1e-4);
    }

    #[test]
    fn bad_trace_names_file_line_and_column() {
        let dir = std::env::temp_dir().join(format!("pto-trace-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("t.csv");
        std::fs::write(&f, "time_s,shaft_angle_deg\n0,0\n1,2\n1,3\n").unwrap();
        let e = Motion::from_trace_file(&f).unwrap_err().to_string();
        assert!(
            e.ends_with(":4: column `time_s`: 1 s is not after 1 s (time must increase)"),
            "{e}"
        );
        std::fs::write(&f, "t,angle\n0,0\n").unwrap();
        let e = Motion::from_trace_file(&f).unwrap_err().to_string();
        assert!(e.contains(":1: missing column `time_s`"), "{e}");
    }
}
