//! The autonomy table (`Coefficients::autonomy`): how long the motor keeps turning with the
//! input blocked, integrated along each aperture row at configuration time.

use super::{
    AUTONOMY_CAP_S, N_APERTURE, N_PRESSURE, P_MAX_BAR, Table1, Table2, capacitance, steady_flow_k,
};
use crate::config::ModelConfig;

/// The two-point Gauss–Legendre rule on both halves of [lo, hi], the halves split at `split`
/// when it lies inside (where the integrand jumps): four (node, weight) pairs, exact for
/// cubics on each half.
fn gauss_halves(lo: f32, hi: f32, split: f32) -> [(f32, f32); 4] {
    // 1/√3: the nodes of the two-point rule on [−1, 1].
    const NODE: f32 = 0.577_350_26;
    let mid = if lo < split && split < hi {
        split
    } else {
        0.5 * (lo + hi)
    };
    let half = |a: f32, b: f32| {
        let (c, h) = (0.5 * (a + b), 0.5 * (b - a));
        [(c - h * NODE, h), (c + h * NODE, h)]
    };
    let ([a, b], [c, d]) = (half(lo, mid), half(mid, hi));
    [a, b, c, d]
}

impl ModelConfig {
    /// The autonomy table, s (aperture × P2): the time for the motor to fall below the minimum
    /// speed with the input blocked, from P2 at that aperture (LP nominal), ∫ 60·C(P)/Q dP from
    /// the stop pressure up to P2, capped at [`AUTONOMY_CAP_S`]. Built along each aperture row
    /// at once: the stop pressure in closed form (Q_min² / K² + β·Q_min above LP),
    /// then the time cumulated column by column, each 5 bar cell by the two-point Gauss rule on
    /// its halves (split at the precharge, where C jumps). C does not depend on the aperture,
    /// so its values at the full cells' nodes are worked out once for every row. Integrating
    /// afresh at each node (200 midpoint steps) took ≈ 136 M instructions on the Cortex-M4 and
    /// was up to 1.2 % off; this takes one evaluation of Q per Gauss node and row.
    /// Hand-written rather than a quadrature crate's: `no_std`, no heap, f32, and a fixed
    /// cost the firmware's boot budget can count on.
    #[inline(never)]
    pub(super) fn autonomy_table_into(&self, table: &mut Table2<N_APERTURE, N_PRESSURE>) {
        let lp = self.nominal_lp_bar;
        let pc = self.hp_accumulator.precharge_bar;
        let dc = Table1::<N_PRESSURE>::spacing(0.0, P_MAX_BAR);
        let cell = |j: usize| (dc * (j - 1) as f32, dc * j as f32);
        let c60 = |p: f32| 60.0 * capacitance(self, &self.hp_accumulator, p);
        // 60·C at the four nodes of each full cell j (ending at column j).
        let mut full = [[0.0f32; 4]; N_PRESSURE];
        for (j, c) in full.iter_mut().enumerate().skip(1) {
            let (lo, hi) = cell(j);
            for (c, (p, _)) in c.iter_mut().zip(gauss_halves(lo, hi, pc)) {
                *c = c60(p);
            }
        }
        let beta = self.motor_bar_per_lpm();
        let q_min = self.autonomy_min_rpm / self.rpm_per_lpm();
        table.sample_rows_into((0.0, 100.0), (0.0, P_MAX_BAR), |a, row| {
            let k = self.valve_k(a);
            if k <= 0.0 {
                return;
            }
            let p_stop = lp + q_min * q_min / (k * k) + beta * q_min;
            let mut t = 0.0f32;
            for j in 1..N_PRESSURE {
                let (lo, hi) = cell(j);
                if hi <= p_stop {
                    continue;
                }
                if lo >= p_stop {
                    for (&c, (p, w)) in full[j].iter().zip(gauss_halves(lo, hi, pc)) {
                        t += w * c / steady_flow_k(k, beta, p - lp);
                    }
                } else {
                    for (p, w) in gauss_halves(p_stop, hi, pc) {
                        t += w * c60(p) / steady_flow_k(k, beta, p - lp);
                    }
                }
                row[j] = t.min(AUTONOMY_CAP_S);
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The autonomy table, built a row at a time, against the integral ∫ 60·C/Q dP from the stop
    /// pressure worked out finely (f64 midpoint sums at ≤ 0.008 bar, split at the precharge;
    /// the stop pressure by bisection on Q itself): every node within 0.05 % or
    /// 0.05 s, on the reference configuration and on one whose precharge falls inside a cell.
    #[test]
    fn the_autonomy_table_is_the_integral_it_stands_for() {
        let mut other = ModelConfig::reference();
        other.hp_accumulator.precharge_bar = 42.5;
        for cfg in [ModelConfig::reference(), other] {
            let k = cfg.coefficients().unwrap();
            let lp = f64::from(cfg.nominal_lp_bar);
            let pc = f64::from(cfg.hp_accumulator.precharge_bar);
            let q_min = cfg.autonomy_min_rpm / cfg.rpm_per_lpm();
            let dc = f64::from(P_MAX_BAR) / (N_PRESSURE - 1) as f64;
            let (mut worst_rel, mut worst_s) = (0.0f64, 0.0f64);
            for i in 0..N_APERTURE {
                let a = 100.0 * i as f32 / (N_APERTURE - 1) as f32;
                let q = |p: f64| f64::from(cfg.steady_flow(a, (p - lp) as f32));
                let (mut lo, mut hi) = (lp, f64::from(P_MAX_BAR));
                if q(hi) <= f64::from(q_min) {
                    continue;
                }
                for _ in 0..60 {
                    let mid = 0.5 * (lo + hi);
                    if q(mid) > f64::from(q_min) {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                let p_stop = hi;
                let g = |p: f64| {
                    60.0 * f64::from(capacitance(&cfg, &cfg.hp_accumulator, p as f32)) / q(p)
                };
                // Midpoint sums at ≤ 0.008 bar, cumulated column by column (the integral from
                // the stop pressure to each column, as the table is built).
                let integral = |a: f64, b: f64| {
                    let n = ((b - a) / 0.008).ceil().max(1.0) as usize;
                    let h = (b - a) / n as f64;
                    (0..n).map(|m| g(a + (m as f64 + 0.5) * h) * h).sum::<f64>()
                };
                let (mut sum, mut from) = (0.0f64, p_stop);
                for j in 0..N_PRESSURE {
                    let p2 = dc * j as f64;
                    let want = if p2 <= p_stop {
                        0.0
                    } else {
                        sum += if from < pc && pc < p2 {
                            integral(from, pc) + integral(pc, p2)
                        } else {
                            integral(from, p2)
                        };
                        from = p2;
                        sum
                    }
                    .min(f64::from(AUTONOMY_CAP_S));
                    let got = f64::from(k.autonomy.y[i][j].to_num::<f32>());
                    let err = (got - want).abs();
                    worst_s = worst_s.max(err);
                    if want > 1.0 {
                        worst_rel = worst_rel.max(err / want);
                    }
                    assert!(
                        err <= (5e-4 * want).max(0.05),
                        "precharge {pc} bar, {a} %, {p2} bar: table {got} s, integral {want} s"
                    );
                }
            }
            println!("precharge {pc} bar: worst {worst_rel:.2e} of the integral, {worst_s:.3} s");
        }
    }
}
