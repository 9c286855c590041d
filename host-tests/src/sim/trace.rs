//! Plant values at an instant of a run, in the units the controller uses (bar, N·m, rpm).

use crate::sim::bench::{BAR, RPM};
use crate::sim::solver::Trace;

/// Plant values at one instant (linear interpolation of a trace, or the plant's evaluation).
#[derive(Debug, Clone, Copy, Default)]
pub struct Truth {
    /// P2, bar.
    pub p2_bar: f64,
    /// LP, bar.
    pub lp_bar: f64,
    /// Restraining torque, N·m.
    pub torque_nm: f64,
    /// Motor speed, rpm.
    pub motor_rpm: f64,
}

impl Truth {
    /// The plant's values as its controller callback sees them.
    pub fn of_eval(p: &crate::sim::plant::Eval) -> Truth {
        Truth {
            p2_bar: p.p2_pa / BAR,
            lp_bar: p.lp_pa / BAR,
            torque_nm: p.torque_nm.iter().sum(),
            motor_rpm: p.omega_rad_s * RPM,
        }
    }
}

/// The sample pair around `t` and the fraction of the way from the first to the second.
fn bracket(tr: &Trace, t: f64) -> (usize, f64) {
    let n = tr.len();
    let k = tr.t_s.partition_point(|&x| x <= t).clamp(1, n - 1);
    let (t0, t1) = (tr.t_s[k - 1], tr.t_s[k]);
    (k, ((t - t0) / (t1 - t0)).clamp(0.0, 1.0))
}

/// Column `v` of a trace at time `t` (linear interpolation).
pub fn value_at(tr: &Trace, v: &[f64], t: f64) -> f64 {
    let (k, u) = bracket(tr, t);
    v[k - 1] + u * (v[k] - v[k - 1])
}

/// Plant values at time `t` of a trace (linear interpolation).
pub fn truth_at(tr: &Trace, t: f64) -> Truth {
    let (k, u) = bracket(tr, t);
    let l = |v: &[f64]| v[k - 1] + u * (v[k] - v[k - 1]);
    Truth {
        p2_bar: l(&tr.p2_pa) / BAR,
        lp_bar: l(&tr.lp_pa) / BAR,
        torque_nm: l(&tr.torque_nm),
        motor_rpm: l(&tr.omega_rad_s) * RPM,
    }
}
