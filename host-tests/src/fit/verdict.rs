//! The verdict on a fit: the checks it must pass before its bench is called fitted. Each check
//! names what it measured and, when it fails, why.

use super::*;

/// One check of the verdict.
#[derive(Debug, Clone, Serialize)]
pub struct Check {
    /// Short name (`converged`, `goodness`, `bounds`, `emptying`, `determined`, `precision`,
    /// `correlation`, `logs`).
    pub name: &'static str,
    /// Whether it held.
    pub passed: bool,
    /// What was measured, and why it failed.
    pub detail: String,
}

/// Defaults of the checks' limits.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Limits {
    /// Largest reduced χ² of the P2, speed and LP residuals against the logs' noise.
    pub max_chi2: f64,
    /// Largest difference between the logged and the simulated emptying of the HP accumulator:
    /// this many seconds plus [`Limits::emptying_fraction`] of the logged time.
    pub emptying_s: f64,
    /// The part of the emptying limit that grows with the discharge's length (a 1 % error in
    /// the oil volume moves the emptying by 1 % of its time).
    pub emptying_fraction: f64,
    /// A parameter closer than this fraction of its range to a bound is "at the bound".
    pub bound_fraction: f64,
    /// Largest |correlation| between two fitted parameters.
    pub max_correlation: f64,
}

/// The limits `pto fit` uses unless told otherwise (`--max-chi2`).
pub const DEFAULT_LIMITS: Limits = Limits {
    max_chi2: 2.0,
    emptying_s: 0.5,
    emptying_fraction: 0.01,
    bound_fraction: 0.01,
    max_correlation: 0.999,
};

/// Everything the checks look at.
pub(super) struct Evidence<'a> {
    pub termination: &'a str,
    pub converged: bool,
    pub chi2_reduced: f64,
    pub noise: &'a Noise,
    pub params: &'a [Fitted],
    pub bounds: &'a [(f64, f64)],
    pub correlations: &'a [Vec<f64>],
    pub logs: &'a [LogFit],
    pub findings: &'a [Finding],
}

fn check(name: &'static str, passed: bool, detail: String) -> Check {
    Check {
        name,
        passed,
        detail,
    }
}

/// A check that holds when nothing was `found`: `ok()` describes the pass, `failed(found)`
/// the failure.
fn none_found(
    name: &'static str,
    found: Vec<String>,
    ok: impl FnOnce() -> String,
    failed: impl FnOnce(&[String]) -> String,
) -> Check {
    let passed = found.is_empty();
    check(name, passed, if passed { ok() } else { failed(&found) })
}

pub(super) fn verdict(e: &Evidence, lim: &Limits) -> Vec<Check> {
    let mut out = vec![check(
        "converged",
        e.converged,
        format!("Levenberg–Marquardt: {}", e.termination),
    )];
    let worst = e
        .logs
        .iter()
        .max_by(|a, b| a.chi2.total_cmp(&b.chi2))
        .map(|l| format!("; worst log {} at {:.2}", l.name, l.chi2))
        .unwrap_or_default();
    let est = |b: bool| {
        if b {
            "estimated from the logs"
        } else {
            "given"
        }
    };
    out.push(check(
        "goodness",
        e.chi2_reduced <= lim.max_chi2,
        format!(
            "reduced χ² {:.2} {} {} against the noise σ P2 {:.3} bar ({}), speed {:.2} rpm ({}), \
             LP {:.3} bar ({}){worst}",
            e.chi2_reduced,
            if e.chi2_reduced <= lim.max_chi2 {
                "≤"
            } else {
                ">"
            },
            lim.max_chi2,
            e.noise.p2_bar,
            est(e.noise.p2_estimated),
            e.noise.rpm,
            est(e.noise.rpm_estimated),
            e.noise.lp_bar,
            est(e.noise.lp_estimated),
        ),
    ));
    let at_bound: Vec<String> = e
        .params
        .iter()
        .zip(e.bounds)
        .filter_map(|(p, &(lo, hi))| {
            let margin = lim.bound_fraction * (hi - lo);
            let side = if p.value - lo <= margin {
                "lower"
            } else if hi - p.value <= margin {
                "upper"
            } else {
                return None;
            };
            let b = if side == "lower" { lo } else { hi };
            Some(format!(
                "{} = {:.4} at its {side} bound {b} {}",
                p.name, p.value, p.unit
            ))
        })
        .collect();
    out.push(none_found(
        "bounds",
        at_bound,
        || {
            format!(
                "every parameter more than {} % of its range from its bounds",
                100.0 * lim.bound_fraction
            )
        },
        |at_bound| {
            format!(
                "{}: the logs push it out of the range the fit allows (a wrong unit in a \
                 log, a parameter missing from --params, or a bench far from the start)",
                at_bound.join("; ")
            )
        },
    ));
    let mut empty_bad = Vec::new();
    let mut empty_n = 0;
    for l in e.logs {
        let (logged, simulated) = (l.emptying_s.logged, l.emptying_s.simulated);
        match (logged, simulated) {
            (None, None) => {}
            (Some(a), Some(b)) => {
                empty_n += 1;
                let limit = lim.emptying_s + lim.emptying_fraction * a;
                if (b - a).abs() > limit {
                    empty_bad.push(format!(
                        "{}: simulated at {b:.1} s, logged at {a:.1} s ({:+.1} s, limit {limit:.1} s)",
                        l.name,
                        b - a
                    ));
                }
            }
            (Some(a), None) => {
                empty_n += 1;
                empty_bad.push(format!(
                    "{}: logged at {a:.1} s, never in the simulation",
                    l.name
                ))
            }
            (None, Some(b)) => {
                empty_n += 1;
                empty_bad.push(format!(
                    "{}: simulated at {b:.1} s, never in the log",
                    l.name
                ))
            }
        }
    }
    out.push(none_found(
        "emptying",
        empty_bad,
        || {
            format!(
                "the HP accumulator runs empty within {} s + {} % of the logged moment in \
                 {empty_n} log(s)",
                lim.emptying_s,
                100.0 * lim.emptying_fraction
            )
        },
        |empty_bad| {
            format!(
                "the simulated HP accumulator runs empty at another moment than the logged one: \
                 {}",
                empty_bad.join("; ")
            )
        },
    ));
    let undetermined: Vec<String> = e
        .params
        .iter()
        .filter(|p| p.sigma.is_none())
        .map(|p| p.name.clone())
        .collect();
    out.push(none_found(
        "determined",
        undetermined,
        || "every parameter has a finite σ".into(),
        |undetermined| {
            format!(
                "the logs do not determine {}: add logs that exercise it, or leave it out of \
                 --params",
                undetermined.join(", ")
            )
        },
    ));
    let coarse: Vec<String> = e
        .params
        .iter()
        .filter_map(|p| {
            let s3 = 3.0 * p.sigma?;
            (s3 > p.needed).then(|| {
                format!(
                    "{} ± {s3:.4} {} (3σ) > ± {:.4} needed",
                    p.name, p.unit, p.needed
                )
            })
        })
        .collect();
    out.push(none_found(
        "precision",
        coarse,
        || {
            format!(
                "every parameter's 3σ within the precision needed ({})",
                e.params
                    .iter()
                    .map(|p| format!("{} ± {:.4}", p.name, p.needed))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        },
        |coarse| {
            format!(
                "the logs do not pin down {}: add logs that exercise it, fit fewer parameters, \
                 or state the precision you need with --precision NAME=VALUE",
                coarse.join("; ")
            )
        },
    ));
    let mut corr = Vec::new();
    let mut worst_c: f64 = 0.0;
    for (i, row) in e.correlations.iter().enumerate() {
        for (j, c) in row.iter().enumerate().skip(i + 1) {
            worst_c = worst_c.max(c.abs());
            if c.abs() > lim.max_correlation {
                corr.push(format!(
                    "{} and {} ({c:+.4})",
                    e.params[i].name, e.params[j].name
                ));
            }
        }
    }
    out.push(none_found(
        "correlation",
        corr,
        || {
            format!(
                "largest |correlation| {worst_c:.3} ≤ {}",
                lim.max_correlation
            )
        },
        |corr| {
            format!(
                "the logs cannot tell apart {} (|correlation| > {}): fit one of each pair, or \
                 add logs that separate them",
                corr.join(", "),
                lim.max_correlation
            )
        },
    ));
    let errors: Vec<String> = e
        .findings
        .iter()
        .filter(|f| f.severity == Severity::Error)
        .map(|f| format!("{} `{}`: {}", f.file.display(), f.column, f.message))
        .collect();
    out.push(none_found(
        "logs",
        errors,
        || "every log plausible".into(),
        |errors| errors.join("; "),
    ));
    out
}
