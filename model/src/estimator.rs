//! The HP-pressure / restraining-torque estimator: the reduced-order node model of physics.md §2
//! as the prediction, corrected by the pressure transducers when they are valid.
//!
//! Per step: shaft angle and speed from the encoder (α–β tracker) → per cylinder on duty, rod
//! speed from the lever-arm table, delivered flow after the stroke-reversal lag (free play, then
//! compression of the chamber from LP to P2) → valve/motor flow from the steady valve table,
//! relief flow → P2 and LP predicted through the nodes' capacitance tables → scalar Kalman
//! correction of P2 (gain from a table of the prior variance, innovation gating, reset after a
//! run of rejections) and a fixed-gain correction of LP → torque from the chamber pressures
//! implied by the bridge (delivering chamber at P2, suction at LP) → motor speed (Eq. 9 on the
//! load line) and autonomy (table).

use crate::coeffs::Coefficients;
use crate::fx::{
    Angle, AngularSpeed, Aperture, Flow, Fx, ONE, Pressure, Rpm, Seconds, Torque, ZERO, clamp,
    mul_dt, sqrt0,
};

/// Fault flags (bit set).
pub mod fault {
    /// HP transducer reading missing or outside its range (wire break reads below range).
    pub const HP_SENSOR: u16 = 1 << 0;
    /// LP transducer reading missing or outside its range.
    pub const LP_SENSOR: u16 = 1 << 1;
    /// Encoder reading missing.
    pub const ENCODER: u16 = 1 << 2;
    /// Motor speed reading missing or outside its range.
    pub const MOTOR_SENSOR: u16 = 1 << 3;
    /// HP innovation outside the gate (reading rejected this step).
    pub const INNOVATION: u16 = 1 << 4;
    /// HP innovation rejected for the whole reset window: estimate reset to the reading.
    pub const INNOVATION_RESET: u16 = 1 << 5;
    /// P2 (estimated or measured) above the trip pressure.
    pub const OVERPRESSURE: u16 = 1 << 6;
    /// Encoder static for 2 s while the HP reading rises by more than 1 bar: shaft moving.
    pub const ENCODER_STUCK: u16 = 1 << 7;
    /// Configuration index out of range (step ignored the duty mask).
    pub const BAD_CONFIG: u16 = 1 << 8;
}

/// Sensor readings of one step. `None` = missing (the firmware also maps out-of-range raw
/// readings to `None`; the estimator range-checks what it gets as well).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Inputs {
    /// Shaft encoder count (quadrature-decoded, 0 at the neutral angle).
    pub encoder: Option<i32>,
    /// HP transducer.
    pub hp: Option<Pressure>,
    /// LP transducer.
    pub lp: Option<Pressure>,
    /// Motor speed sensor.
    pub motor: Option<Rpm>,
    /// Aperture commanded to the valve this step.
    pub aperture_cmd: Aperture,
    /// Cylinders on duty, bit i = HC3.(i+1).
    pub on_duty: u8,
    /// Geometry, 0..=3 = Config 1..4.
    pub config: u8,
}

/// What the estimator reports each step.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Estimate {
    /// Estimated P2.
    pub p2: Pressure,
    /// Its standard deviation.
    pub p2_sigma: Pressure,
    /// Estimated LP.
    pub lp: Pressure,
    /// Shaft angle.
    pub theta: Angle,
    /// Shaft speed.
    pub omega: AngularSpeed,
    /// Flow delivered into HP by the pump.
    pub q_pump: Flow,
    /// Pump flow averaged over ≈ one wave period.
    pub q_pump_mean: Flow,
    /// Control valve (= motor) flow.
    pub q_valve: Flow,
    /// Relief flow.
    pub q_relief: Flow,
    /// Restraining torque at the shaft.
    pub torque: Torque,
    /// Per cylinder.
    pub torque_cyl: [Torque; 4],
    /// Predicted motor speed (Eq. 9).
    pub motor_rpm: Rpm,
    /// Time the motor stays above the minimum speed if the input stops now.
    pub autonomy: Seconds,
    /// Effective spool aperture.
    pub aperture: Aperture,
    /// [`fault`] bits.
    pub faults: u16,
}

/// Per-cylinder state.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct CylState {
    /// Direction of the rod: 1 extending, −1 retracting, 0 unknown.
    pub dir: i8,
    /// Progress through the reversal lag, 0..1 (1 = delivering).
    pub lag: Fx,
}

/// Estimator state (≈ 100 bytes).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct State {
    /// Shaft angle estimate, rad.
    pub theta: Fx,
    /// Shaft speed estimate, rad/s.
    pub omega: Fx,
    /// The tracker has seen an encoder reading.
    pub enc_init: bool,
    /// Last encoder count.
    pub enc_last: i32,
    /// Steps since the encoder last changed.
    pub enc_still: u16,
    /// HP reading when the encoder last changed, bar.
    pub hp_at_enc_change: Fx,
    /// P2, bar.
    pub p2: Fx,
    /// P2 variance, bar².
    pub var: Fx,
    /// LP, bar.
    pub lp: Fx,
    /// Effective spool aperture, %.
    pub aperture: Fx,
    /// Averaged pump flow, L/min.
    pub q_mean: Fx,
    /// Cylinders.
    pub cyl: [CylState; 4],
    /// Consecutive rejected HP readings.
    pub rejected: u16,
}

impl State {
    /// A state starting from known pressures (bar) with the given P2 standard deviation.
    pub fn new(p2: Pressure, lp: Pressure, sigma: Pressure) -> Self {
        State {
            p2: p2.0,
            lp: lp.0,
            var: sigma.0.saturating_mul(sigma.0),
            ..State::default()
        }
    }
}

const P_MIN: Fx = Fx::from_bits(-65_536); // −1 bar
const P_MAX: Fx = Fx::from_bits(400 << 16);
const FLOW_LIM: Fx = Fx::from_bits(1000 << 16);

/// Advances the estimator by one step. Cannot fail; every reading may be missing or wrong.
pub fn step(k: &Coefficients, s: &mut State, inp: &Inputs) -> Estimate {
    let dtl = k.dt_log2;
    let mut faults = 0u16;
    // --- Shaft: α–β tracker on the encoder angle.
    let pred_theta = s.theta.saturating_add(mul_dt(s.omega, dtl));
    match inp.encoder {
        Some(count) => {
            let theta_meas = Fx::from_bits(
                ((i64::from(count) * k.rad_per_count_q32) >> 16)
                    .clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32,
            );
            if !s.enc_init {
                s.theta = theta_meas;
                s.omega = ZERO;
                s.enc_init = true;
                s.enc_last = count;
                s.hp_at_enc_change = inp.hp.map_or(s.p2, |p| p.0);
            } else {
                let r = theta_meas.saturating_sub(pred_theta);
                s.theta = pred_theta.saturating_add(k.alpha.saturating_mul(r));
                s.omega = clamp(
                    s.omega.saturating_add(k.beta_over_dt.saturating_mul(r)),
                    Fx::from_bits(-100 << 16),
                    Fx::from_bits(100 << 16),
                );
            }
            if count != s.enc_last {
                s.enc_last = count;
                s.enc_still = 0;
                s.hp_at_enc_change = inp.hp.map_or(s.p2, |p| p.0);
            } else {
                s.enc_still = s.enc_still.saturating_add(1);
                if s.enc_still >= k.stuck_steps
                    && inp
                        .hp
                        .is_some_and(|p| p.0.saturating_sub(s.hp_at_enc_change) > ONE)
                {
                    faults |= fault::ENCODER_STUCK;
                }
            }
        }
        None => {
            // No reading: assume the input has stopped (the safe side for autonomy).
            faults |= fault::ENCODER;
            s.theta = pred_theta;
            s.omega = ZERO;
        }
    }
    // --- Spool lag.
    let cmd = clamp(inp.aperture_cmd.0, ZERO, Fx::from_num(100));
    s.aperture = s
        .aperture
        .saturating_add(k.spool_gain.saturating_mul(cmd.saturating_sub(s.aperture)));
    // --- Cylinders: delivered flow, suction flow, torque.
    let config = usize::from(inp.config);
    let (arm_table, duty) = match k.arm.get(config) {
        Some(t) => (t, inp.on_duty),
        None => {
            faults |= fault::BAD_CONFIG;
            (&k.arm[0], 0)
        }
    };
    let mut q_pump = ZERO;
    let mut q_lp_net = ZERO; // flow taken from LP by the cylinders (suction − idle bypass return)
    let mut torque_cyl = [Torque::ZERO; 4];
    let mut torque = ZERO;
    for (i, (c, cs)) in k.cyl.iter().zip(s.cyl.iter_mut()).enumerate() {
        let th = c.side.saturating_mul(s.theta);
        let d = arm_table.at(th);
        // Rod speed, m/s: v = s·d·θ̇.
        let v = c.side.saturating_mul(d).saturating_mul(s.omega);
        let on = duty & (1 << i) != 0;
        let tq;
        if on {
            let dir: i8 = if v > ZERO {
                1
            } else if v < ZERO {
                -1
            } else {
                cs.dir
            };
            if dir != cs.dir {
                cs.dir = dir;
                cs.lag = ZERO;
            }
            let speed = v.abs();
            // Extending: the rod chamber delivers, the cap chamber sucks.
            let (q_del, q_suc, inv_lag) = if dir >= 0 {
                (
                    c.q_ann.saturating_mul(speed),
                    c.q_cap.saturating_mul(speed),
                    &c.inv_lag_rod,
                )
            } else {
                (
                    c.q_cap.saturating_mul(speed),
                    c.q_ann.saturating_mul(speed),
                    &c.inv_lag_cap,
                )
            };
            if cs.lag < ONE {
                // mL this step = L/min × 1000/60 × dt.
                let ml = mul_dt(q_del.saturating_mul(Fx::from_bits(1_092_267)), dtl); // 16.6667
                cs.lag = cs
                    .lag
                    .saturating_add(ml.saturating_mul(inv_lag.at(s.p2)))
                    .min(ONE);
            } else {
                // After the lag both chambers exchange oil with the nodes; before it, the
                // old delivering chamber decompresses into the growing volume instead of
                // drawing from LP.
                q_pump = q_pump.saturating_add(q_del);
                q_lp_net = q_lp_net.saturating_add(q_suc);
            }
            // Delivering chamber pressure ramps from LP to P2 over the lag.
            let p_del =
                s.lp.saturating_add(cs.lag.saturating_mul(s.p2.saturating_sub(s.lp)));
            let (p_cap, p_rod) = if dir >= 0 {
                (s.lp, p_del)
            } else {
                (p_del, s.lp)
            };
            let f_hyd = p_cap
                .saturating_mul(c.f_cap)
                .saturating_sub(p_rod.saturating_mul(c.f_ann)); // kN
            tq = c
                .side
                .saturating_mul(d)
                .saturating_mul(f_hyd)
                .saturating_neg();
        } else {
            // Idle: bypassed to LP; LP·A_rod pushes the rod out, the rod volume flows to LP.
            let a_rod_q = c.q_cap.saturating_sub(c.q_ann);
            q_lp_net = q_lp_net.saturating_add(a_rod_q.saturating_mul(v));
            let f = s.lp.saturating_mul(c.f_cap.saturating_sub(c.f_ann));
            tq = c.side.saturating_mul(d).saturating_mul(f).saturating_neg();
        }
        // kN·m → N·m.
        let tq_nm = tq.saturating_mul(Fx::from_bits(1000 << 16));
        torque_cyl[i] = Torque(tq_nm);
        torque = torque.saturating_add(tq_nm);
    }
    // --- Valve, relief, motor.
    let dp = s.p2.saturating_sub(s.lp).max(ZERO);
    let q_valve = k.valve_flow.at(s.aperture, dp);
    let q_relief =
        s.p2.saturating_sub(k.relief_setting)
            .max(ZERO)
            .saturating_mul(k.relief_gain);
    let motor_rpm = q_valve.saturating_mul(k.rpm_per_lpm);
    // --- Predict.
    let net_hp = clamp(
        q_pump.saturating_sub(q_valve).saturating_sub(q_relief),
        -FLOW_LIM,
        FLOW_LIM,
    );
    s.p2 = clamp(
        s.p2.saturating_add(mul_dt(net_hp.saturating_mul(k.inv_c_hp.at(s.p2)), dtl)),
        P_MIN,
        P_MAX,
    );
    let net_lp = clamp(
        q_valve.saturating_add(q_relief).saturating_sub(q_lp_net),
        -FLOW_LIM,
        FLOW_LIM,
    );
    s.lp = clamp(
        s.lp.saturating_add(mul_dt(net_lp.saturating_mul(k.inv_c_lp.at(s.lp)), dtl)),
        P_MIN,
        P_MAX,
    );
    s.var = s.var.saturating_add(k.q_step);
    s.q_mean = s
        .q_mean
        .saturating_add(k.mean_gain.saturating_mul(q_pump.saturating_sub(s.q_mean)));
    // --- Correct P2 with the HP transducer.
    let hp = inp
        .hp
        .map(|p| p.0)
        .filter(|p| *p >= k.hp_range.0 && *p <= k.hp_range.1);
    match hp {
        Some(z) => {
            let innov = z.saturating_sub(s.p2);
            let s_innov = s.var.saturating_add(k.r);
            if innov.saturating_mul(innov) <= k.gate_sq.saturating_mul(s_innov) {
                let g = k.gain(s.var);
                s.p2 = clamp(s.p2.saturating_add(g.saturating_mul(innov)), P_MIN, P_MAX);
                s.var = ONE.saturating_sub(g).saturating_mul(s.var);
                s.rejected = 0;
            } else {
                faults |= fault::INNOVATION;
                s.rejected = s.rejected.saturating_add(1);
                if s.rejected >= k.gate_reset_steps {
                    faults |= fault::INNOVATION_RESET;
                    s.p2 = z;
                    s.var = k.r;
                    s.rejected = 0;
                }
            }
        }
        None => faults |= fault::HP_SENSOR,
    }
    // --- Correct LP with a fixed gain.
    match inp
        .lp
        .map(|p| p.0)
        .filter(|p| *p >= k.lp_range.0 && *p <= k.lp_range.1)
    {
        Some(z) => {
            s.lp =
                s.lp.saturating_add(k.gain_lp.saturating_mul(z.saturating_sub(s.lp)))
        }
        None => faults |= fault::LP_SENSOR,
    }
    if inp.motor.is_none_or(|m| m.0 < ZERO || m.0 > k.motor_max) {
        faults |= fault::MOTOR_SENSOR;
    }
    if s.p2 > k.trip || hp.is_some_and(|z| z > k.trip) {
        faults |= fault::OVERPRESSURE;
    }
    Estimate {
        p2: Pressure(s.p2),
        p2_sigma: Pressure(sqrt0(s.var)),
        lp: Pressure(s.lp),
        theta: Angle(s.theta),
        omega: AngularSpeed(s.omega),
        q_pump: Flow(q_pump),
        q_pump_mean: Flow(s.q_mean),
        q_valve: Flow(q_valve),
        q_relief: Flow(q_relief),
        torque: Torque(torque),
        torque_cyl,
        motor_rpm: Rpm(motor_rpm),
        autonomy: Seconds(k.autonomy.at(s.aperture, s.p2)),
        aperture: Aperture(s.aperture),
        faults,
    }
}
