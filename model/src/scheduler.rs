//! The valve-aperture scheduler: four run-time modes, rate and aperture limits with anti-windup,
//! and a safety layer that overrides every mode.

use crate::coeffs::Coefficients;
use crate::config::ConfigError;
use crate::estimator::{Estimate, fault};
use crate::fx::{Aperture, Fx, Pressure, QMul, Rpm, ZERO, clamp, mul_dt};

/// What the scheduler aims for.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "protocol", derive(postcard_schema::Schema))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Mode {
    /// A fixed aperture.
    Fixed(Aperture),
    /// Hold P2 at a setpoint.
    HoldPressure(Pressure),
    /// Hold the motor speed at a setpoint.
    HoldSpeed(Rpm),
    /// Input blocked: the smallest aperture that keeps the motor above this speed (plus the
    /// configured margin), which maximises the autonomy of the stored oil.
    MaxAutonomy(Rpm),
}

/// Why the safety layer overrode the mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "protocol", derive(postcard_schema::Schema))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Override {
    /// No override.
    #[default]
    None,
    /// P2 above the trip pressure.
    Overpressure,
    /// HP transducer lost and the model-only estimate has become too uncertain.
    SensorFault,
}

/// The scheduler's output.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "protocol", derive(postcard_schema::Schema))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Command {
    /// Aperture to send to the valve.
    pub aperture: Aperture,
    /// Safety override in force.
    pub safety: Override,
}

/// Scheduler settings in physical units.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct SchedulerConfig {
    /// P2 loop proportional gain, % per bar.
    pub pressure_kp_pct_per_bar: f32,
    /// P2 loop integral gain, % per bar·s.
    pub pressure_ki_pct_per_bar_s: f32,
    /// Speed loop proportional gain, % per rpm.
    pub speed_kp_pct_per_rpm: f32,
    /// Speed loop integral gain, % per rpm·s.
    pub speed_ki_pct_per_rpm_s: f32,
    /// Aperture rate limit, %/s.
    pub rate_limit_pct_per_s: f32,
    /// Aperture limits, %.
    pub min_aperture_pct: f32,
    /// Aperture limits, %.
    pub max_aperture_pct: f32,
    /// Margin above the minimum speed in MaxAutonomy, fraction.
    pub autonomy_margin: f32,
    /// Aperture forced on overpressure, % (open: the motor drains HP).
    pub overpressure_aperture_pct: f32,
    /// Aperture forced on a sensor fault, %.
    pub sensor_fault_aperture_pct: f32,
    /// Model-only P2 uncertainty above which a lost HP transducer forces the safe aperture, bar.
    pub sensor_fault_sigma_bar: f32,
}

impl Default for SchedulerConfig {
    fn default() -> Self {
        SchedulerConfig {
            pressure_kp_pct_per_bar: 1.0,
            pressure_ki_pct_per_bar_s: 0.2,
            speed_kp_pct_per_rpm: 0.02,
            speed_ki_pct_per_rpm_s: 0.02,
            rate_limit_pct_per_s: 20.0,
            min_aperture_pct: 0.0,
            max_aperture_pct: 100.0,
            autonomy_margin: 0.1,
            overpressure_aperture_pct: 100.0,
            sensor_fault_aperture_pct: 12.0,
            sensor_fault_sigma_bar: 3.0,
        }
    }
}

/// Precomputed scheduler constants.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SchedulerCoeffs {
    kp_p: Fx,
    ki_p: Fx,
    kp_s: Fx,
    ki_s: Fx,
    rate_step: Fx,
    min: Fx,
    max: Fx,
    margin: Fx,
    safe_op: Fx,
    safe_fault: Fx,
    fault_var: Fx,
    lpm_per_rpm: Fx,
}

impl SchedulerConfig {
    /// Validates and precomputes for steps of 2^−dt_log2 s.
    pub fn coefficients(&self, k: &Coefficients) -> Result<SchedulerCoeffs, ConfigError> {
        let c = |field, v: f32, min, max| {
            if v.is_finite() && v >= min && v <= max {
                Ok(Fx::saturating_from_num(v))
            } else {
                Err(ConfigError {
                    field,
                    value: v,
                    min,
                    max,
                })
            }
        };
        let min = c("min_aperture_pct", self.min_aperture_pct, 0.0, 100.0)?;
        let max = c(
            "max_aperture_pct",
            self.max_aperture_pct,
            self.min_aperture_pct,
            100.0,
        )?;
        let sigma = c(
            "sensor_fault_sigma_bar",
            self.sensor_fault_sigma_bar,
            0.1,
            100.0,
        )?;
        Ok(SchedulerCoeffs {
            kp_p: c(
                "pressure_kp_pct_per_bar",
                self.pressure_kp_pct_per_bar,
                0.0,
                100.0,
            )?,
            ki_p: c(
                "pressure_ki_pct_per_bar_s",
                self.pressure_ki_pct_per_bar_s,
                0.0,
                100.0,
            )?,
            kp_s: c("speed_kp_pct_per_rpm", self.speed_kp_pct_per_rpm, 0.0, 10.0)?,
            ki_s: c(
                "speed_ki_pct_per_rpm_s",
                self.speed_ki_pct_per_rpm_s,
                0.0,
                10.0,
            )?,
            rate_step: mul_dt(
                c(
                    "rate_limit_pct_per_s",
                    self.rate_limit_pct_per_s,
                    0.1,
                    10_000.0,
                )?,
                k.dt_log2,
            )
            .max(Fx::DELTA),
            min,
            max,
            margin: c("autonomy_margin", self.autonomy_margin, 0.0, 2.0)?,
            safe_op: c(
                "overpressure_aperture_pct",
                self.overpressure_aperture_pct,
                0.0,
                100.0,
            )?,
            safe_fault: c(
                "sensor_fault_aperture_pct",
                self.sensor_fault_aperture_pct,
                0.0,
                100.0,
            )?,
            fault_var: sigma.qmul(sigma),
            lpm_per_rpm: Fx::saturating_from_num(1.0 / k.branch.rpm_per_lpm.to_num::<f32>()),
        })
    }
}

/// Scheduler state.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct SchedulerState {
    /// Integral term, %.
    pub integ: Fx,
    /// Last commanded aperture, %.
    pub last: Fx,
    /// Lower row of the valve-table cell the feed-forward inversion is in (see
    /// [`crate::table::Table2::invert_r_tracking`]).
    pub ff_row: u8,
    /// Feed-forward aperture of the last refresh, %.
    pub ff: Fx,
}

/// The feed-forward aperture for `q` L/min at P2 − LP = `dp` bar: refreshed when `refresh`,
/// else the last one.
#[inline(always)]
fn feed_forward(k: &Coefficients, st: &mut SchedulerState, refresh: bool, dp: Fx, q: Fx) -> Fx {
    if refresh {
        st.ff = k.branch.valve_flow.invert_r_tracking(dp, q, &mut st.ff_row);
    }
    st.ff
}

/// The aperture at which the steady valve flow equals `q` L/min at P2 − LP = `dp` bar: the
/// inverse of the valve table along its aperture axis ([`crate::table::Table2::invert_r`]; the
/// step uses its bounded-work form, [`crate::table::Table2::invert_r_tracking`]).
pub fn aperture_for_flow(k: &Coefficients, q: Fx, dp: Fx) -> Fx {
    k.branch.valve_flow.invert_r(dp, q)
}

/// One scheduler step after the estimator's. `measured_rpm` is the motor speed sensor (the
/// predicted speed is used without it).
pub fn step(
    k: &Coefficients,
    sc: &SchedulerCoeffs,
    st: &mut SchedulerState,
    mode: Mode,
    est: &Estimate,
    measured_rpm: Option<Rpm>,
) -> Command {
    let dtl = k.dt_log2;
    // Safety layer first: it overrides every mode, without rate limit.
    let safety = if est.faults & fault::OVERPRESSURE != 0 {
        Override::Overpressure
    } else if est.faults & fault::HP_SENSOR != 0 && est.p2_var.0 > sc.fault_var {
        Override::SensorFault
    } else {
        Override::None
    };
    let forced = match safety {
        Override::Overpressure => Some(sc.safe_op),
        Override::SensorFault => Some(sc.safe_fault),
        Override::None => None,
    };
    if let Some(a) = forced {
        st.integ = ZERO;
        st.last = a;
        return Command {
            aperture: Aperture(a),
            safety,
        };
    }
    let dp = est.p2.0.saturating_sub(est.lp.0).max(ZERO);
    let speed = measured_rpm.map_or(est.motor_rpm.0, |r| r.0);
    // The feed-forward (the valve table inverted at the flow to pass) is refreshed only in a
    // step in which the estimator spent no background work (stroke-reversal units, the
    // autonomy refresh): they share one background slot, so a step never pays for two. Its
    // inputs (the pump flow averaged over a wave period, a speed setpoint, P2 − LP) move
    // slowly; a reversal holds it for at most 4 × 16 steps.
    let refresh = est.background_units == 0;
    // (feed-forward, error, kp, ki)
    let (ff, err, kp, ki) = match mode {
        Mode::Fixed(a) => {
            // A fixed aperture is the aperture asked: no integral carried over from a mode
            // that ran before (a hold's wound-up term held the valve 15 % open on the twin),
            // and a regulating mode that follows starts its integral afresh.
            st.integ = ZERO;
            (a.0, ZERO, ZERO, ZERO)
        }
        Mode::HoldPressure(p) => (
            feed_forward(k, st, refresh, dp, est.q_pump_mean.0),
            est.p2.0.saturating_sub(p.0),
            sc.kp_p,
            sc.ki_p,
        ),
        Mode::HoldSpeed(r) | Mode::MaxAutonomy(r) => {
            let target = if matches!(mode, Mode::MaxAutonomy(_)) {
                r.0.saturating_add(r.0.qmul(sc.margin))
            } else {
                r.0
            };
            (
                feed_forward(k, st, refresh, dp, target.qmul(sc.lpm_per_rpm)),
                target.saturating_sub(speed),
                sc.kp_s,
                sc.ki_s,
            )
        }
    };
    let span = sc.max.saturating_sub(sc.min);
    let unclamped = ff.saturating_add(kp.qmul(err)).saturating_add(st.integ);
    // Anti-windup: integrate only while the output is inside its limits or the error pulls it
    // back in.
    let pushing_out = (unclamped >= sc.max && err > ZERO) || (unclamped <= sc.min && err < ZERO);
    if !pushing_out {
        st.integ = clamp(
            st.integ.saturating_add(mul_dt(ki.qmul(err), dtl)),
            span.saturating_neg(),
            span,
        );
    }
    let target = clamp(unclamped, sc.min, sc.max);
    let a = clamp(
        target,
        st.last.saturating_sub(sc.rate_step),
        st.last.saturating_add(sc.rate_step),
    );
    st.last = a;
    Command {
        aperture: Aperture(a),
        safety,
    }
}
