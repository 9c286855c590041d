//! A run's sampled outputs ([`Trace`], SI units, its CSV in display units) and the plant's
//! values at an instant of it in the units the controller uses (bar, N·m, rpm).

use crate::sim::bench::{BAR, LPM, RPM};
use crate::sim::plant::{Eval, N_CYL, quad};
use serde::Serialize;

/// Sampled outputs on the user grid (SI units internally; CSV headers carry display units).
#[derive(Debug, Clone, Default, Serialize)]
pub struct Trace {
    /// s.
    pub t_s: Vec<f64>,
    /// Shaft angle, rad.
    pub theta_rad: Vec<f64>,
    /// Shaft speed, rad/s.
    pub theta_dot_rad_s: Vec<f64>,
    /// Rod positions per cylinder, m.
    pub rod_m: [Vec<f64>; N_CYL],
    /// Cap pressures, Pa.
    pub p_cap_pa: [Vec<f64>; N_CYL],
    /// Rod-side pressures, Pa.
    pub p_rod_pa: [Vec<f64>; N_CYL],
    /// Flow into HP per cylinder, m³/s.
    pub q_cyl_m3_s: [Vec<f64>; N_CYL],
    /// Total flow into HP, m³/s.
    pub q_inj_m3_s: Vec<f64>,
    /// Flow through the motor, m³/s.
    pub q_motor_m3_s: Vec<f64>,
    /// Flow through the control valve, m³/s.
    pub q_valve_m3_s: Vec<f64>,
    /// Relief flow, m³/s.
    pub q_relief_m3_s: Vec<f64>,
    /// Motor speed, rad/s.
    pub omega_rad_s: Vec<f64>,
    /// P2, Pa.
    pub p2_pa: Vec<f64>,
    /// LP, Pa.
    pub lp_pa: Vec<f64>,
    /// Motor inlet, Pa.
    pub p_motor_pa: Vec<f64>,
    /// Spool aperture, %.
    pub aperture_pct: Vec<f64>,
    /// Restraining torque (input must supply it), N·m.
    pub torque_nm: Vec<f64>,
    /// Per cylinder, N·m.
    pub torque_cyl_nm: [Vec<f64>; N_CYL],
    /// Mechanical input power at the shaft, W.
    pub input_power_w: Vec<f64>,
    /// Hydraulic power into the control valve, P2 · valve flow, W (what the controller's
    /// estimator reports).
    pub valve_power_w: Vec<f64>,
    /// Power into the load (the generator), W.
    pub generator_power_w: Vec<f64>,
}

impl Trace {
    pub(crate) fn push(&mut self, t: f64, e: &Eval) {
        self.t_s.push(t);
        self.theta_rad.push(e.theta_rad);
        self.theta_dot_rad_s.push(e.theta_dot_rad_s);
        for i in 0..N_CYL {
            self.rod_m[i].push(e.rod_m[i]);
            self.p_cap_pa[i].push(e.p_cap_pa[i]);
            self.p_rod_pa[i].push(e.p_rod_pa[i]);
            self.q_cyl_m3_s[i].push(e.q_into_hp_m3_s[i]);
            self.torque_cyl_nm[i].push(e.torque_nm[i]);
        }
        self.q_inj_m3_s.push(e.q_into_hp_m3_s.iter().sum());
        self.q_motor_m3_s.push(e.q_motor_m3_s);
        self.q_valve_m3_s.push(e.q_valve_m3_s);
        self.q_relief_m3_s.push(e.q_relief_m3_s);
        self.omega_rad_s.push(e.omega_rad_s);
        self.p2_pa.push(e.p2_pa);
        self.lp_pa.push(e.lp_pa);
        self.p_motor_pa.push(e.p_motor_pa);
        self.aperture_pct.push(e.aperture_pct);
        self.torque_nm.push(e.torque_nm.iter().sum());
        self.input_power_w.push(e.quad[quad::INPUT]);
        self.valve_power_w.push(e.p2_pa * e.q_valve_m3_s);
        self.generator_power_w
            .push(e.load_torque_nm * e.omega_rad_s);
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.t_s.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.t_s.is_empty()
    }

    /// Indices of samples with `from <= t <= to`.
    pub fn window(&self, from: f64, to: f64) -> std::ops::Range<usize> {
        let a = self.t_s.partition_point(|&x| x < from - 1e-9);
        let b = self.t_s.partition_point(|&x| x <= to + 1e-9);
        a..b
    }

    /// Writes the trace as CSV with units in the headers (to a temporary file renamed at the
    /// end, so an interrupted write leaves nothing half-written).
    pub fn write_csv(
        &self,
        path: &std::path::Path,
        names: &[String; N_CYL],
    ) -> std::io::Result<()> {
        let tmp = path.with_extension("csv.tmp");
        self.write_csv_to(&tmp, names)?;
        std::fs::rename(&tmp, path)
    }

    fn write_csv_to(&self, path: &std::path::Path, names: &[String; N_CYL]) -> std::io::Result<()> {
        let mut w = csv::Writer::from_path(path)?;
        let mut header: Vec<String> = [
            "time_s",
            "shaft_angle_deg",
            "shaft_speed_rpm",
            "p2_bar",
            "lp_bar",
            "motor_inlet_bar",
            "injected_flow_lpm",
            "motor_flow_lpm",
            "valve_flow_lpm",
            "relief_flow_lpm",
            "motor_speed_rpm",
            "valve_aperture_pct",
            "restraining_torque_nm",
            "input_power_w",
            "valve_power_w",
            "generator_power_w",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        for n in names {
            let n = n.replace('.', "_").to_lowercase();
            header.extend([
                format!("{n}_rod_mm"),
                format!("{n}_cap_bar"),
                format!("{n}_rod_side_bar"),
                format!("{n}_flow_lpm"),
                format!("{n}_torque_nm"),
            ]);
        }
        w.write_record(&header)?;
        for k in 0..self.len() {
            let mut row = vec![
                self.t_s[k],
                self.theta_rad[k].to_degrees(),
                self.theta_dot_rad_s[k] * RPM,
                self.p2_pa[k] / BAR,
                self.lp_pa[k] / BAR,
                self.p_motor_pa[k] / BAR,
                self.q_inj_m3_s[k] * LPM,
                self.q_motor_m3_s[k] * LPM,
                self.q_valve_m3_s[k] * LPM,
                self.q_relief_m3_s[k] * LPM,
                self.omega_rad_s[k] * RPM,
                self.aperture_pct[k],
                self.torque_nm[k],
                self.input_power_w[k],
                self.valve_power_w[k],
                self.generator_power_w[k],
            ];
            for i in 0..N_CYL {
                row.extend([
                    self.rod_m[i][k] * 1e3,
                    self.p_cap_pa[i][k] / BAR,
                    self.p_rod_pa[i][k] / BAR,
                    self.q_cyl_m3_s[i][k] * LPM,
                    self.torque_cyl_nm[i][k],
                ]);
            }
            w.write_record(row.iter().map(|v| format!("{v:.6}")))?;
        }
        w.flush()
    }
}

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
