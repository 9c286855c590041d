//! The f64 mirror of `pto_model::estimator::step`: the same reduced model in f64 arithmetic,
//! to measure the fixed-point model's arithmetic error alone.

use pto_model::estimator::{Inputs, P_MAX, P_MIN, State};
use pto_model::fx::Fx;
use pto_model::table::{Table2, lerp_f64, locate_f64};
use pto_model::{Coefficients, ModelConfig};

/// The fixed-point model's pressure range, bar (its Q16.16 bounds, exactly).
const P_MIN_BAR: f64 = P_MIN.to_bits() as f64 / 65_536.0;
const P_MAX_BAR: f64 = P_MAX.to_bits() as f64 / 65_536.0;

/// The same reduced model as `pto_model::estimator` in f64 arithmetic: same equations, same
/// table nodes (read from the coefficients and interpolated in f64), f64 state, exact divisions
/// and square roots. The difference to the fixed-point estimator is its arithmetic error alone;
/// the model's own error is what the comparison with the full simulation measures.
pub struct Reference {
    cfg: ModelConfig,
    k: std::rc::Rc<Coefficients>,
    dt: f64,
    theta: f64,
    omega: f64,
    accel: f64,
    init: bool,
    /// P2, bar.
    pub p2_bar: f64,
    var: f64,
    /// LP, bar.
    pub lp_bar: f64,
    aperture: f64,
    /// Valve/motor flow, L/min (`None` before the first step).
    q_motor: Option<f64>,
    rejected: u32,
    cyl: [RefCyl; 4],
    /// The motor reading's filters while they run.
    meas: Option<RefMeas>,
    /// Steps the motor reading still waits.
    meas_wait: u32,
    /// Start-up steps of the shaft tracker run since it started.
    enc_n: u32,
}

/// The motor reading's state of the reference (`pto_model::estimator::State`'s `q_meas`,
/// `f_meas`, `meas_odd`, `meas_band`).
#[derive(Debug, Clone, Copy)]
struct RefMeas {
    q: f64,
    f: f64,
    odd: bool,
    /// The dead band, bar.
    band: f64,
    /// The reading's variance (noise and band), bar².
    var: f64,
}

/// Per-cylinder stroke state of the reference, as `pto_model::estimator::CylState`.
#[derive(Debug, Clone, Copy, Default)]
struct RefCyl {
    dir: i8,
    from_rest: bool,
    /// The play this stroke crosses, mm.
    play: f64,
    /// The last stroke's eye had pushed the rod before the lever turned (`CylState::engaged`).
    engaged: bool,
    /// It had delivered (`CylState::delivered`).
    delivered: bool,
    /// (engaged, delivered, gap) kept aside (`CylState::alt_engaged`).
    alt: (bool, bool, f64),
    /// The eye's distance from the face that drives the new stroke, mm (`CylState::gap`).
    gap: f64,
    setup_left: u8,
    bisect_left: u8,
    /// Eye travel since the reversal, mm.
    travel: f64,
    /// (new, old) chamber lengths, mm.
    len: (f64, f64),
    /// (ms_new0, ms_old0, ms/mm new, ms/mm old).
    strain: (f64, f64, f64, f64),
    u_bal: f64,
    u_bal_hi: f64,
    u_end: f64,
    u_suc: f64,
    /// (cap, rod) chamber pressures of the last step, bar.
    p: (f64, f64),
}

/// f64 outputs of the reference.
#[derive(Debug, Clone, Copy, Default)]
pub struct RefOut {
    /// P2, bar.
    pub p2_bar: f64,
    /// Torque, N·m.
    pub torque_nm: f64,
    /// Motor speed, rpm.
    pub motor_rpm: f64,
    /// Pump flow into HP, L/min.
    pub q_pump_lpm: f64,
    /// Valve (motor) flow out of HP, L/min.
    pub q_valve_lpm: f64,
}

impl Reference {
    /// Starts from known pressures.
    pub fn new(cfg: &ModelConfig, k: &Coefficients, p2: f64, lp: f64, sigma: f64) -> Self {
        Reference {
            cfg: cfg.clone(),
            k: std::rc::Rc::new(k.clone()),
            dt: 2f64.powi(-i32::from(cfg.dt_log2)),
            theta: 0.0,
            omega: 0.0,
            accel: 0.0,
            init: false,
            p2_bar: p2,
            var: sigma * sigma,
            lp_bar: lp,
            aperture: 0.0,
            q_motor: None,
            rejected: 0,
            cyl: [RefCyl::default(); 4],
            meas: None,
            meas_wait: 0,
            enc_n: 0,
        }
    }

    /// The fixed-point estimator's state `s` as the reference's: every value the reference
    /// keeps, exactly (the pressure nodes, the variance and the motor flow with their bits
    /// below the Q16.16 LSB). One step of both from it measures the arithmetic's one-step
    /// difference alone (`tests/model/model_validation.rs`).
    pub fn from_state(cfg: &ModelConfig, k: &Coefficients, s: &State) -> Self {
        let q32 = |x: i64| x as f64 / 4_294_967_296.0;
        let ext =
            |p: Fx, lo: u16| (f64::from(p.to_bits()) * 65_536.0 + f64::from(lo)) / 4_294_967_296.0;
        let f = |x: Fx| x.to_num::<f64>();
        let mut r = Reference::new(
            cfg,
            k,
            ext(s.node.p2, s.node.p2_lo),
            ext(s.node.lp, s.node.lp_lo),
            0.0,
        );
        r.theta = q32(s.tracker.theta_q32);
        r.omega = q32(s.tracker.omega_q32);
        r.accel = q32(s.tracker.accel_q32);
        r.init = s.tracker.phase != 0;
        // enc_phase: 1 tracking, n + 1 with n start-up steps left.
        r.enc_n = u32::from(k.tracker.tracker_startup_len)
            .saturating_sub(u32::from(s.tracker.phase.saturating_sub(1)));
        r.var = ext(s.node.var, s.node.var_lo);
        r.aperture = f(s.branch.aperture);
        r.q_motor = s
            .branch
            .started
            .then(|| ext(s.branch.q_motor, s.branch.q_motor_lo));
        r.rejected = u32::from(s.node.rejected);
        for (rc, c) in r.cyl.iter_mut().zip(&s.cyl) {
            *rc = RefCyl {
                dir: c.dir,
                from_rest: c.from_rest,
                play: f(c.play),
                engaged: c.engaged,
                delivered: c.delivered,
                alt: (c.alt_engaged, c.alt_delivered, f(c.alt_gap)),
                gap: f(c.gap),
                setup_left: c.setup_left,
                bisect_left: c.bisect_left,
                travel: f(c.travel),
                len: (f(c.len_n), f(c.len_o)),
                strain: (
                    f(c.ms_new0),
                    f(c.ms_old0),
                    f(c.ms_per_mm_n),
                    f(c.ms_per_mm_o),
                ),
                u_bal: f(c.u_bal),
                u_bal_hi: f(c.u_bal_hi),
                u_end: f(c.u_end),
                u_suc: f(c.u_suc),
                p: (f(c.p_cap), f(c.p_rod)),
            };
        }
        r.meas = s.reading.live.then(|| RefMeas {
            q: f(s.reading.q),
            f: f(s.reading.f),
            odd: s.reading.odd,
            band: f(s.reading.band),
            var: f(s.reading.var),
        });
        r.meas_wait = u32::from(s.reading.wait);
        r
    }

    /// A per-row column of a 2-D table (`Table2::at_with`) at row coordinate `r`.
    fn row_lerp<const R: usize, const C: usize>(t: &Table2<R, C>, col: &[Fx; R], r: f64) -> f64 {
        lerp_f64(col, locate_f64(r, t.r0, t.inv_dr, R))
    }

    /// P2 from the motor speed, mirroring `pto_model::estimator::motor_reading` (its
    /// coefficients as the fixed-point model holds them, the work alternating between two steps
    /// as there).
    fn motor_reading(&mut self, rpm: f64, cmd: f64, lp_dp: f64, dp: f64, q_ss: f64, g: f64) {
        let k = &*self.k;
        let f = |x: Fx| x.to_num::<f64>();
        let q_m = (rpm * f64::from(k.branch.lpm_per_rpm_q24) / 16_777_216.0).min(1000.0);
        let slope = g * f(k.reading.ldt);
        let fm = (lp_dp - slope * (q_ss - q_m)).clamp(P_MIN_BAR, P_MAX_BAR);
        let a = f(k.reading.filter);
        let Some(m) = self.meas.as_mut() else {
            self.meas = Some(RefMeas {
                q: q_m,
                f: fm,
                odd: false,
                band: 0.0,
                var: 0.0,
            });
            return;
        };
        m.odd = !m.odd;
        if m.odd {
            let q_cap = k
                .branch
                .valve_flow
                .at_f64(self.aperture, f(k.reading.p2_max) - self.lp_bar);
            if q_m > q_cap * (1.0 + f(k.reading.band)) + f(k.reading.min_lpm) {
                self.meas = None;
                self.meas_wait = u32::from(k.reading.warm_steps);
                return;
            }
            if slope > f(k.reading.max_slope)
                || (cmd - self.aperture).abs() > f(k.reading.spool_tol)
            {
                self.meas = None;
                self.meas_wait = u32::from(k.reading.warm_steps);
                return;
            }
            m.f += a * (fm - m.f);
            m.q += a * (q_m - m.q);
            m.band = dp * f(k.reading.band);
            m.var = m.band * m.band / 3.0 + f(k.reading.r);
            return;
        }
        if self.meas_wait > 0 {
            self.meas_wait -= 1;
        } else if q_m >= f(k.reading.min_lpm) {
            let z = m.f + (q_m - m.q) * f(k.reading.lt);
            let e = z - self.p2_bar;
            let e = e - e.clamp(-m.band, m.band);
            if z - m.band > f(k.reading.p2_max) {
                return;
            }
            let gain = f(k.reading.gain);
            self.p2_bar = (self.p2_bar + gain * e).clamp(P_MIN_BAR, P_MAX_BAR);
            if self.var > m.var {
                self.var += gain * (m.var - self.var);
            }
        }
    }

    /// One step, mirroring `pto_model::estimator::step`.
    pub fn step(&mut self, inp: &Inputs) -> RefOut {
        let c = self.cfg.clone();
        let k = self.k.clone();
        let k = &*k;
        let dt = self.dt;
        let rr = (-2.0 * std::f64::consts::PI * f64::from(c.encoder_bandwidth_hz) * dt).exp();
        let om = 1.0 - rr;
        let (alpha, beta, gamma) = (
            1.0 - rr * rr * rr,
            1.5 * om * om * (1.0 + rr),
            0.5 * om * om * om,
        );
        let pred = self.theta + self.omega * dt + 0.5 * self.accel * dt * dt;
        let pred_w = self.omega + self.accel * dt;
        match inp.encoder {
            Some(n) => {
                let meas =
                    f64::from(n) * 2.0 * std::f64::consts::PI / f64::from(c.encoder_counts_per_rev);
                if !self.init {
                    self.theta = meas;
                    self.omega = 0.0;
                    self.accel = 0.0;
                    self.init = true;
                    self.enc_n = 0;
                } else if self.enc_n < u32::from(k.tracker.tracker_startup_len) {
                    // The expanding-memory start-up gains, as the fixed-point model.
                    self.enc_n += 1;
                    let (ga, gb) = pto_model::coeffs::expanding_memory_gains(self.enc_n);
                    let r = meas - pred;
                    self.theta = pred + ga * r;
                    self.omega = pred_w + gb / dt * r;
                } else {
                    let r = meas - pred;
                    self.theta = pred + alpha * r;
                    self.omega = pred_w + beta / dt * r;
                    self.accel += 2.0 * gamma / (dt * dt) * r;
                }
            }
            None => {
                self.theta = pred;
                self.omega = 0.0;
                self.accel = 0.0;
                self.init = false;
            }
        }
        let spool = if c.spool_time_constant_ms <= 0.0 {
            1.0
        } else {
            (dt / (f64::from(c.spool_time_constant_ms) * 1e-3)).min(1.0)
        };
        let cmd = f64::from(inp.aperture_cmd.to_f32()).clamp(0.0, 100.0);
        self.aperture = match self.q_motor {
            Some(_) => self.aperture + spool * (cmd - self.aperture),
            None => cmd,
        };
        let config = usize::from(inp.config).min(3);
        let (mut q_pump, mut q_lp, mut torque) = (0.0, 0.0, 0.0);
        let mut budget = pto_model::estimator::REVERSAL_UNITS_PER_STEP;
        for i in 0..4 {
            let cc = &k.pump.cyl[i];
            let f = |x: Fx| x.to_num::<f64>();
            let side = f(cc.side);
            let d = k.pump.arm[config].at_f64(side * self.theta); // mm
            let v = side * d * self.omega; // mm/s
            if inp.on_duty & (1 << i) != 0 {
                use pto_model::estimator::{BISECT_ITERATIONS, SETUP_UNITS};
                let cs = &mut self.cyl[i];
                let dir: i8 = if v > 0.0 {
                    1
                } else if v < 0.0 {
                    -1
                } else {
                    cs.dir
                };
                let seal = v * f(k.pump.seal_kn_per_mm_s);
                let drop = f(k.pump.check_drop_bar);
                let (lo, hi) = (self.lp_bar - drop, self.p2_bar + drop);
                let pressures = |st: &(f64, f64, f64, f64), u: f64| {
                    let (ms_n0, ms_o0, kn, ko) = *st;
                    let pn = k.pump.p_of_ms.at_f64(ms_n0 + u * kn).max(lo).min(hi);
                    let po = k.pump.p_of_ms.at_f64(ms_o0 - u * ko).max(lo).min(hi);
                    (pn, po)
                };
                if dir != cs.dir {
                    if cs.setup_left > SETUP_UNITS - 2 {
                        std::mem::swap(&mut cs.engaged, &mut cs.alt.0);
                        std::mem::swap(&mut cs.delivered, &mut cs.alt.1);
                        std::mem::swap(&mut cs.gap, &mut cs.alt.2);
                    } else {
                        let rel = if cs.setup_left != 0 {
                            cs.travel
                        } else {
                            let ub = if cs.bisect_left > 0 {
                                cs.u_bal_hi
                            } else {
                                cs.u_bal
                            };
                            (cs.travel - ub).clamp(0.0, cs.play)
                        };
                        let full = f(k.pump.play_mm);
                        cs.engaged = rel >= cs.play;
                        cs.delivered = cs.setup_left == 0 && cs.travel >= cs.u_end + cs.play;
                        cs.gap = (full - cs.play + rel).min(full);
                        cs.alt = (false, false, (cs.play - rel).max(0.0));
                    }
                    cs.from_rest = cs.dir == 0;
                    cs.dir = dir;
                    cs.travel = 0.0;
                    cs.play = f(k.pump.play_mm);
                    cs.setup_left = SETUP_UNITS;
                    cs.bisect_left = 0;
                }
                // A_new/A_old of this stroke, and the chambers' pressures when the lever turned
                // (new, old; at LP − drop from rest), held to [lo, hi].
                let ratio = f(if dir >= 0 { cc.ratio_ext } else { cc.ratio_ret });
                let held = |cs: &RefCyl| {
                    let (pn, po) = if cs.from_rest {
                        (lo, lo)
                    } else if dir >= 0 {
                        (cs.p.1, cs.p.0)
                    } else {
                        (cs.p.0, cs.p.1)
                    };
                    (pn.max(lo).min(hi), po.max(lo).min(hi))
                };
                // The same work units, in the same order and budget, as the fixed-point model.
                if (cs.setup_left > 0 || cs.bisect_left > 0) && budget > 0 {
                    budget -= 1;
                    if cs.setup_left == SETUP_UNITS {
                        let pos = k.pump.ext[config].at_f64(side * self.theta);
                        let l_cap = f(cc.dead_cap_mm) + pos;
                        let l_rod = f(cc.dead_rod_mm) + f(cc.stroke_mm) - pos;
                        cs.len = if dir >= 0 {
                            (l_rod, l_cap)
                        } else {
                            (l_cap, l_rod)
                        };
                        cs.strain.2 = 1000.0 / cs.len.0;
                        cs.setup_left -= 1;
                    } else if cs.setup_left == SETUP_UNITS - 1 {
                        cs.strain.3 = 1000.0 / cs.len.1;
                        if !cs.from_rest && !cs.engaged {
                            cs.play = cs.gap;
                        } else if !cs.from_rest {
                            let (p_new0, p_old0) = held(cs);
                            let net = p_old0 - ratio * p_new0;
                            // Inside the band a quarter of the play once the stroke delivered
                            // (else all of it), ramps at its edges.
                            let band = f(pto_model::estimator::FLOAT_BAND);
                            let ramp = f(pto_model::estimator::FLOAT_RAMP);
                            let play = f(k.pump.play_mm);
                            let float = if cs.delivered { 0.25 * play } else { play };
                            cs.play = if net <= -band {
                                0.0
                            } else if net >= band {
                                play
                            } else if net < ramp - band {
                                float * (net + band) / ramp
                            } else if net > band - ramp {
                                float + (play - float) * (net - (band - ramp)) / ramp
                            } else {
                                float
                            };
                        }
                        cs.setup_left -= 1;
                    } else if cs.setup_left == SETUP_UNITS - 2 {
                        let (p_new0, p_old0) = held(cs);
                        cs.strain.0 = k.pump.ms_of_p.at_f64(p_new0);
                        cs.strain.1 = k.pump.ms_of_p.at_f64(p_old0);
                        cs.setup_left -= 1;
                    } else if cs.setup_left > 0 {
                        let to_hi = (k.pump.ms_of_p.at_f64(hi) - cs.strain.0).max(0.0);
                        let to_lo = (cs.strain.1 - k.pump.ms_of_p.at_f64(lo)).max(0.0);
                        cs.u_end = to_hi * cs.len.0 / 1000.0;
                        cs.u_suc = to_lo * cs.len.1 / 1000.0;
                        cs.u_bal = 0.0;
                        cs.u_bal_hi = cs.u_end.max(cs.u_suc);
                        if cs.from_rest || cs.play == f(k.pump.play_mm) {
                            cs.bisect_left = BISECT_ITERATIONS;
                        }
                        cs.setup_left = 0;
                    } else {
                        let m = 0.5 * (cs.u_bal + cs.u_bal_hi);
                        let (pn, po) = pressures(&cs.strain, m);
                        if po - ratio * pn > 0.0 {
                            cs.u_bal = m;
                        } else {
                            cs.u_bal_hi = m;
                        }
                        cs.bisect_left -= 1;
                        if cs.bisect_left == 0 {
                            if cs.from_rest {
                                cs.travel += 0.5 * f(k.pump.play_mm);
                            } else if cs.u_bal_hi == cs.u_end.max(cs.u_suc) {
                                cs.play = 0.0;
                            }
                        }
                    }
                }
                let step_mm = v.abs() * dt;
                if cs.setup_left == 0 {
                    let ub = if cs.bisect_left > 0 {
                        cs.u_bal_hi
                    } else {
                        cs.u_bal
                    };
                    let e = cs.travel;
                    let play = cs.play;
                    let u = if e <= ub {
                        e
                    } else if e <= ub + play {
                        ub
                    } else {
                        e - play
                    };
                    let (q_del, q_suc) = if dir >= 0 {
                        (f(cc.q_ann) * v.abs(), f(cc.q_cap) * v.abs())
                    } else {
                        (f(cc.q_cap) * v.abs(), f(cc.q_ann) * v.abs())
                    };
                    let e_end = cs.u_end + play;
                    if e < e_end {
                        cs.travel += step_mm;
                    } else {
                        q_pump += q_del;
                        if u < cs.u_suc {
                            cs.travel += step_mm;
                        }
                    }
                    if u >= cs.u_suc {
                        q_lp += q_suc;
                    }
                    let (mut p_new, mut p_old) = pressures(&cs.strain, u);
                    if cs.travel >= e_end {
                        p_new = hi;
                    }
                    if u >= cs.u_suc {
                        p_old = lo;
                    }
                    cs.p = if dir >= 0 {
                        (p_old, p_new)
                    } else {
                        (p_new, p_old)
                    };
                } else {
                    cs.travel += step_mm;
                }
                torque -= side * d * (cs.p.0 * f(cc.f_cap) - cs.p.1 * f(cc.f_ann) - seal);
            } else {
                q_lp += (f(cc.q_cap) - f(cc.q_ann)) * v;
                torque -= side * d * self.lp_bar * (f(cc.f_cap) - f(cc.f_ann));
            }
        }
        let dp = (self.p2_bar - self.lp_bar).max(0.0);
        let q_ss = k.branch.valve_flow.at_f64(self.aperture, dp);
        let q = self.q_motor.unwrap_or(q_ss);
        let gain_valve = Self::row_lerp(
            &k.branch.valve_flow,
            &k.branch.motor_gain_valve,
            self.aperture,
        );
        let g = (k.branch.motor_gain0.to_num::<f64>() + (q_ss + q) * gain_valve).min(1.0);
        let lp_dp = self.lp_bar + dp;
        let q = q + g * (q_ss - q);
        self.q_motor = Some(q);
        let motor_rpm = q * k.branch.rpm_per_lpm.to_num::<f64>();
        let q_valve = if dp > 0.0 { q } else { 0.0 };
        let q_relief = (self.p2_bar - k.branch.relief_setting_bar.to_num::<f64>()).max(0.0)
            * k.branch.relief_gain_lpm_per_bar.to_num::<f64>();
        let inv_c_hp = k.observer.inv_c_hp.at_f64(self.p2_bar);
        self.p2_bar = (self.p2_bar + (q_pump - q_valve - q_relief) * inv_c_hp * dt)
            .clamp(P_MIN_BAR, P_MAX_BAR);
        self.lp_bar = (self.lp_bar
            + (q_valve + q_relief - q_lp) * k.observer.inv_c_lp.at_f64(self.lp_bar) * dt)
            .clamp(P_MIN_BAR, P_MAX_BAR);
        let r = f64::from(c.pressure_noise_bar).powi(2);
        self.var += k.observer.q_step.at_f64(self.p2_bar);
        let hp = inp.hp.map(|p| f64::from(p.to_f32())).filter(|p| {
            *p >= f64::from(c.hp_sensor_range_bar.0) && *p <= f64::from(c.hp_sensor_range_bar.1)
        });
        let f = |x: Fx| x.to_num::<f64>();
        let closed = cmd < f(k.reading.min_aperture) || self.aperture < f(k.reading.min_aperture);
        if let Some(z) = hp {
            if self.p2_bar >= f(k.observer.relief_setting_bar) {
                self.var += f(k.observer.q_relief);
            }
            let innov = z - self.p2_bar;
            if innov * innov <= f64::from(c.gate_sigma).powi(2) * (self.var + r) {
                let g = if self.var < k.observer.r.to_num::<f64>() {
                    k.observer.gain_fine.at_f64(self.var)
                } else {
                    k.observer.gain_coarse.at_f64(self.var).clamp(0.0, 1.0)
                };
                // The reading held to the model's pressure range, as in the fixed-point model.
                self.p2_bar += g * (z.clamp(P_MIN_BAR, P_MAX_BAR) - self.p2_bar);
                self.var *= 1.0 - g;
                self.rejected = 0;
            } else {
                // Fading memory on rejection, capped at 16 r, as in the fixed-point model.
                if self.var < 16.0 * r {
                    self.var = (self.var + r).min(16.0 * r);
                }
                self.rejected += 1;
                if f64::from(self.rejected) * dt * 1e3 >= f64::from(c.gate_reset_ms) {
                    self.p2_bar = z;
                    self.var = r;
                    self.rejected = 0;
                }
            }
        }
        // Without the HP reading: P2 from the motor speed, as `estimator::motor_reading`.
        let motor = inp
            .motor
            .map(|m| f64::from(m.to_f32()))
            .filter(|m| *m >= 0.0 && *m <= f64::from(c.motor_sensor_max_rpm));
        match motor.filter(|_| hp.is_none()) {
            Some(rpm) if !closed => self.motor_reading(rpm, cmd, lp_dp, dp, q_ss, g),
            Some(_) => {
                self.meas = None;
                self.meas_wait = u32::from(k.reading.warm_steps);
            }
            None => {
                self.meas = None;
                self.meas_wait = 0;
            }
        }
        if hp.is_none() && self.p2_bar <= f(k.observer.precharge_band_top_bar) {
            self.var = self.var.max(f(k.observer.var_precharge));
        }
        if let Some(z) = inp.lp.map(|p| f64::from(p.to_f32())).filter(|p| {
            *p >= f64::from(c.lp_sensor_range_bar.0) && *p <= f64::from(c.lp_sensor_range_bar.1)
        }) {
            self.lp_bar +=
                k.observer.gain_lp.to_num::<f64>() * (z.clamp(P_MIN_BAR, P_MAX_BAR) - self.lp_bar);
        }
        RefOut {
            p2_bar: self.p2_bar,
            torque_nm: torque,
            motor_rpm,
            q_pump_lpm: q_pump,
            q_valve_lpm: q_valve,
        }
    }
}
