//! Component laws of `docs/physics.md` §2 in SI units (pressures gauge, Pa).
//!
//! Pure functions of the bench parameters: the plant's right-hand side is assembled from them.

use crate::sim::bench::{Accumulator, Bench, CheckValve, Geometry, Load, Oil, P_ATM};

/// Equation of state of oil with trapped air.
///
/// Per unit of reference volume (the volume the oil-air mixture takes at 0 bar gauge), the mixture
/// occupies `v(p) = [e^(−p/E_l) + α·r(p)] / (1 + α)`, `r(p) = (p_a/(p_a+p))^(1/n)`: liquid with
/// constant modulus E_l plus air compressed polytropically. Its bulk modulus
///
/// `E(p) = −v/v' = [e^(−p/E_l) + α·r] / [e^(−p/E_l)/E_l + α·r/(n·(p_a+p))]`
///
/// is the SimHydraulics trapped-air formula of `docs/physics.md` with `e^(−p/E_l)` kept where the
/// formula rounds it to 1 (they differ by < 0.15 % up to 130 bar, see the tests). We keep the
/// exact form because mass and energy are then state functions in closed form (`content`,
/// [`Fluid::exergy`]): a volumetric (constant-density) flow balance loses ≈2 % of the pumped
/// volume per stroke through the chambers, which drains LP over a long run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fluid {
    el: f64,
    alpha: f64,
    n: f64,
}

impl Fluid {
    /// The fluid of a bench's oil.
    pub fn new(oil: &Oil) -> Self {
        Fluid {
            el: oil.liquid_modulus_pa,
            alpha: oil.trapped_air_fraction,
            n: oil.air_polytropic_index,
        }
    }

    /// Absolute pressure floored at 1 Pa so Newton iterates below vacuum stay finite (the
    /// simulation rejects accepted states below vacuum).
    fn pabs(p: f64) -> f64 {
        (P_ATM + p).max(1.0)
    }

    /// Specific volume relative to 0 bar gauge, v(p) (m³ per m³ of reference volume).
    pub fn volume_ratio(&self, p: f64) -> f64 {
        let r = (P_ATM / Self::pabs(p)).powf(1.0 / self.n);
        ((-p / self.el).exp() + self.alpha * r) / (1.0 + self.alpha)
    }

    /// v(p) and the bulk modulus E(p), Pa, in one evaluation.
    pub fn state(&self, p: f64) -> (f64, f64) {
        let pabs = Self::pabs(p);
        let r = (P_ATM / pabs).powf(1.0 / self.n);
        let liq = (-p / self.el).exp();
        let num = liq + self.alpha * r;
        let den = liq / self.el + self.alpha * r / (self.n * pabs);
        (num / (1.0 + self.alpha), num / den)
    }

    /// v(p), E(p) and, when `with_exergy`, G(p) (else 0), sharing one power and one
    /// exponential: the plant's nodes need all three for the balance integrands.
    pub fn state_exergy(&self, p: f64, with_exergy: bool) -> (f64, f64, f64) {
        let pabs = Self::pabs(p);
        let r = (P_ATM / pabs).powf(1.0 / self.n);
        let liq = (-p / self.el).exp();
        let num = liq + self.alpha * r;
        let den = liq / self.el + self.alpha * r / (self.n * pabs);
        let g = if with_exergy {
            // α·p_a^(1/n)·p_abs^(1−1/n) = α·p_abs·r: the exergy's power is the state's.
            let k = 1.0 - 1.0 / self.n;
            let liquid = self.el * (1.0 - liq);
            let air = self.alpha * (pabs * r - P_ATM) / k;
            (liquid + air) / (1.0 + self.alpha)
        } else {
            0.0
        };
        (num / (1.0 + self.alpha), num / den, g)
    }

    /// Bulk modulus E(p), Pa.
    pub fn bulk_modulus(&self, p: f64) -> f64 {
        self.state(p).1
    }

    /// Flow exergy per reference volume, G(p) = ∫_0^p v dp', J/m³: a mass flow from a to b
    /// dissipates `ṁ_ref·(G(p_a) − G(p_b))`.
    pub fn exergy(&self, p: f64) -> f64 {
        let k = 1.0 - 1.0 / self.n;
        let liquid = self.el * (1.0 - (-p / self.el).exp());
        let air =
            self.alpha * P_ATM.powf(1.0 / self.n) * (Self::pabs(p).powf(k) - P_ATM.powf(k)) / k;
        (liquid + air) / (1.0 + self.alpha)
    }

    /// Free energy stored in `volume` m³ of oil at pressure p (gauge frame), J:
    /// content·(G − p·v) with content = volume/v.
    pub fn stored_energy(&self, volume: f64, p: f64) -> f64 {
        volume * self.exergy(p) / self.volume_ratio(p) - p * volume
    }
}

/// Bulk modulus of oil with trapped air, Pa (see [`Fluid`]).
pub fn bulk_modulus(oil: &Oil, p: f64) -> f64 {
    Fluid::new(oil).bulk_modulus(p)
}

/// The `docs/physics.md` (SimHydraulics) form of the trapped-air modulus, kept for comparison:
/// `E_l·[1 + α·(p_a/(p_a+p))^(1/n)] / [1 + α·p_a^(1/n)/(n·(p_a+p)^((n+1)/n))·E_l]`.
pub fn bulk_modulus_simhydraulics(oil: &Oil, p: f64) -> f64 {
    let pabs = (P_ATM + p).max(1.0);
    let n = oil.air_polytropic_index;
    let a = oil.trapped_air_fraction;
    let ratio = (P_ATM / pabs).powf(1.0 / n);
    oil.liquid_modulus_pa * (1.0 + a * ratio)
        / (1.0 + a * ratio / (n * pabs) * oil.liquid_modulus_pa)
}

/// Orifice flow with laminar transition, m³/s (positive from high to low for `dp > 0`).
///
/// `q = Cd·A·sqrt(2/ρ)·Δp/(Δp² + p_cr²)^(1/4)`, `p_cr = (ρ/2)·(Re_cr·ν/(Cd·D_H))²`,
/// `D_H = sqrt(4A/π)`, so `p_cr = (ρ/2)·(Re_cr·ν/Cd)²·π/(4A)`.
pub fn orifice(oil: &Oil, cd: f64, area: f64, dp: f64) -> f64 {
    if area <= 0.0 {
        return 0.0;
    }
    let k = oil.re_crit * oil.viscosity_m2_s / cd;
    let p_cr = 0.5 * oil.density_kg_m3 * k * k * std::f64::consts::PI / (4.0 * area);
    let root = (dp * dp + p_cr * p_cr).sqrt().sqrt();
    cd * area * (2.0 / oil.density_kg_m3).sqrt() * dp / root
}

/// C¹ smoothstep of u on [0, 1] (clamped).
fn smoothstep(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    u * u * (3.0 - 2.0 * u)
}

/// Opening area of a check valve at pressure drop `dp` across it, m².
///
/// Leakage area below cracking, full area at the full-open pressure; in between SimHydraulics is
/// linear. We blend with a C¹ smoothstep instead so the Jacobian has no jump at the two corners
/// (the BDF solver would otherwise cut its step at each of the hundreds of valve switches).
pub fn check_area(v: &CheckValve, leak: f64, dp: f64) -> f64 {
    let u = (dp - v.cracking_pa) / (v.full_open_pa - v.cracking_pa);
    leak + (v.max_area_m2 - leak) * smoothstep(u)
}

/// Check valve flow for a pressure drop `dp` = upstream − downstream, m³/s.
pub fn check_flow(oil: &Oil, v: &CheckValve, dp: f64) -> f64 {
    orifice(oil, v.cd, check_area(v, oil.leak_area_m2, dp), dp)
}

/// Relief valve flow HP -> LP, m³/s. The valve opens on its inlet gauge pressure `p_in` (pilot
/// referenced to the drain/atmosphere), from leakage at the setting to the full area at
/// setting + regulation range; the flow is driven by `p_in − p_out`.
pub fn relief_flow(bench: &Bench, p_in: f64, p_out: f64) -> f64 {
    let u = (p_in - bench.relief_setting_pa) / bench.relief_range_pa;
    let leak = bench.oil.leak_area_m2;
    let area = leak + (bench.relief_area_m2 - leak) * smoothstep(u);
    orifice(&bench.oil, bench.relief_cd, area, p_in - p_out)
}

/// Control valve area at aperture `a_pct` (%, 0..100): linear interpolation of the table, with
/// the leakage area as a floor so the closed valve leaks like every other closed valve.
pub fn valve_area(bench: &Bench, a_pct: f64) -> f64 {
    let xs = &bench.valve_aperture_pct;
    let ys = &bench.valve_area_m2;
    let a = a_pct.clamp(0.0, 100.0);
    let i = xs.partition_point(|&x| x <= a).clamp(1, xs.len() - 1);
    let (x0, x1, y0, y1) = (xs[i - 1], xs[i], ys[i - 1], ys[i]);
    let area = y0 + (y1 - y0) * (a - x0) / (x1 - x0);
    area.max(bench.oil.leak_area_m2)
}

/// Control valve flow at aperture `a_pct` (%), m³/s. With a pressure-dependent characteristic the Cd
/// varies linearly with |Δp| around 50 bar (kept ≥ 10 % of its nominal value).
pub fn valve_flow(bench: &Bench, a_pct: f64, dp: f64) -> f64 {
    let cd = if bench.valve_cd_slope_per_100bar == 0.0 {
        bench.valve_cd
    } else {
        let k = 1.0 + bench.valve_cd_slope_per_100bar * (dp.abs() / 1e5 - 50.0) / 100.0;
        bench.valve_cd * k.max(0.1)
    };
    orifice(&bench.oil, cd, valve_area(bench, a_pct), dp)
}

/// Width of the pressure band above the precharge over which the bladder lifts off its stop, Pa.
///
/// A real bladder does not leave its poppet at one exact pressure. More to the point for the
/// solver: with an ideal stop, dV/dp jumps from 0 to V_T/(k·p_abs) at the precharge, and a run
/// that hovers at the precharge (Test I with one cylinder) forces the BDF solver through that
/// corner every stroke; restarting it at every crossing proved fragile. Over the band the
/// capacitance rises continuously from 0 to the gas law's; above it the gas law holds exactly.
///
/// The band takes in exactly the oil the gas law takes in over it, so that above it the oil
/// volume is the gas law's to rounding (`fluid_volume_above_the_band_is_the_gas_laws`) and
/// below the precharge there is none: its capacitance c_top·(a·u + (1 − a)·u²) (a ≈ 4) rises
/// past the gas law's (by a third, at two thirds of the band) to hold the oil a linear ramp
/// would miss. A linear ramp from the precharge held half the band's oil and left the
/// accumulator short by V_T·w/(2k·p_abs) at every pressure above it (7 cm³ per litre of gas for
/// HP, 35 for LP); a linear ramp moved to start below the precharge held the right oil above the
/// band but some below the precharge, where the estimator's model (and a bladder on its stop)
/// holds none: the accumulator then ran empty late, and the model-only P2 fell below the plant's
/// for up to a second each time.
pub const BLADDER_BAND: f64 = 0.5e5;

/// A gas accumulator's law: the bench file's [`Accumulator`] with its lift-off band worked out
/// once (the right-hand side asks for it at every evaluation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GasAccumulator {
    /// Gas volume at the precharge (the accumulator's volume), m³.
    volume: f64,
    /// Precharge, Pa gauge.
    precharge: f64,
    /// Polytropic index k.
    index: f64,
    band: Band,
}

/// The lift-off band: from `start` the capacitance rises linearly to the gas law's `c_top` at
/// `top` (Pa, m³/Pa, J).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Band {
    start: f64,
    top: f64,
    c_top: f64,
    /// Shape: C = c_top·(a·u + (1 − a)·u²), u = (p − start)/width.
    a: f64,
    /// Energy taken in over the band, J.
    energy_top: f64,
}

impl Band {
    fn width(&self) -> f64 {
        self.top - self.start
    }

    fn u(&self, p: f64) -> f64 {
        (p - self.start) / self.width()
    }

    /// Oil volume and capacitance at p within the band (m³, m³/Pa).
    fn fluid(&self, p: f64) -> (f64, f64) {
        let (u, a, w) = (self.u(p), self.a, self.width());
        let c = self.c_top * (a * u + (1.0 - a) * u * u);
        let v = self.c_top * w * (a * u * u / 2.0 + (1.0 - a) * u.powi(3) / 3.0);
        (v, c)
    }

    /// ∫ p C dp from the band's start to p within the band, J.
    fn energy(&self, p: f64) -> f64 {
        let (u, a, w) = (self.u(p), self.a, self.width());
        let volume_part = a * u * u / 2.0 + (1.0 - a) * u.powi(3) / 3.0;
        let moment = a * u.powi(3) / 3.0 + (1.0 - a) * u.powi(4) / 4.0;
        self.c_top * w * (self.start * volume_part + w * moment)
    }
}

impl GasAccumulator {
    /// The law of a bench's accumulator.
    pub fn new(a: &Accumulator) -> Self {
        let mut acc = GasAccumulator {
            volume: a.volume_m3,
            precharge: a.precharge_pa,
            index: a.index,
            band: Band {
                start: a.precharge_pa,
                top: a.precharge_pa,
                c_top: 0.0,
                a: 1.0,
                energy_top: 0.0,
            },
        };
        let (start, top) = (a.precharge_pa, a.precharge_pa + BLADDER_BAND);
        let c_top = acc.exact_capacitance(top);
        // ∫ C dp over the band = c_top·w·(a/2 + (1 − a)/3) equals the gas law's
        // V_T − V_gas(top): a = 6R − 2 with R that volume over c_top·w (≈ 1, so a ≈ 4).
        let ratio = (a.volume_m3 - acc.gas_volume(top)) / (c_top * BLADDER_BAND);
        acc.band = Band {
            start,
            top,
            c_top,
            a: 6.0 * ratio - 2.0,
            energy_top: 0.0,
        };
        acc.band.energy_top = acc.band.energy(top);
        acc
    }

    /// Gas volume of the ideal polytropic gas law at gauge pressure `p`, m³ (the charged volume
    /// at and below the precharge).
    pub fn gas_volume(&self, p: f64) -> f64 {
        if p <= self.precharge {
            self.volume
        } else {
            self.volume * ((self.precharge + P_ATM) / (p + P_ATM)).powf(1.0 / self.index)
        }
    }

    fn exact_capacitance(&self, p: f64) -> f64 {
        self.gas_volume(p) / (self.index * (p + P_ATM))
    }

    /// ∫ p dV of the exact gas law from the precharge to p (gauge frame), J.
    fn exact_energy(&self, p: f64) -> f64 {
        let (p0, p1) = (self.precharge + P_ATM, p + P_ATM);
        let v1 = self.gas_volume(p);
        // −∫ p_abs dV = (p1·V1 − p0·V0)/(k − 1); the atmosphere's share p_a·(V0 − V1) is not
        // stored in the gauge frame.
        (p1 * v1 - p0 * self.volume) / (self.index - 1.0) - P_ATM * (self.volume - v1)
    }

    /// Oil volume inside, m³, and dV_oil/dp, m³/Pa (0 below the lift-off band: the bladder
    /// rests on its stop), in one evaluation of the gas law.
    pub fn fluid(&self, p: f64) -> (f64, f64) {
        let b = &self.band;
        if p <= b.start {
            (0.0, 0.0)
        } else if p <= b.top {
            b.fluid(p)
        } else {
            let gas = self.gas_volume(p);
            (self.volume - gas, gas / (self.index * (p + P_ATM)))
        }
    }

    /// Oil volume inside, m³.
    pub fn fluid_volume(&self, p: f64) -> f64 {
        self.fluid(p).0
    }

    /// dV_oil/dp, m³/Pa.
    pub fn capacitance(&self, p: f64) -> f64 {
        self.fluid(p).1
    }

    /// Work done on the gas by the oil, with gauge pressures: ∫ p dV_oil, J.
    pub fn stored_energy(&self, p: f64) -> f64 {
        let b = &self.band;
        if p <= b.start {
            0.0
        } else if p <= b.top {
            b.energy(p)
        } else {
            b.energy_top + self.exact_energy(p) - self.exact_energy(b.top)
        }
    }
}

/// Lever geometry of one cylinder (Eq. 1): rod-eye extension and effective arm versus shaft angle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lever {
    r: f64,
    oc: f64,
    l: f64,
    phi0: f64,
    side: f64,
}

impl Lever {
    /// Lever of a cylinder with stroke `stroke` and side `side`, mounted in geometry `g` so that
    /// the eye sits at mid-stroke at shaft angle 0.
    pub fn new(g: &Geometry, stroke: f64, side: f64) -> Self {
        let mid = g.ac_m + 0.5 * stroke;
        let cos_phi0 = (g.ob_m * g.ob_m + g.oc_m * g.oc_m - mid * mid) / (2.0 * g.ob_m * g.oc_m);
        Lever {
            r: g.ob_m,
            oc: g.oc_m,
            l: g.ac_m,
            phi0: cos_phi0.clamp(-1.0, 1.0).acos(),
            side,
        }
    }

    /// Eye extension x = CB − L (m), its rate dx/dθ·θ̇ (m/s) and the arm d (m) at angle `theta`.
    pub fn eye(&self, theta: f64, theta_dot: f64) -> (f64, f64, f64) {
        let phi = self.phi0 + self.side * theta;
        let (s, c) = phi.sin_cos();
        let cb = (self.r * self.r + self.oc * self.oc - 2.0 * self.r * self.oc * c).sqrt();
        let d = self.r * self.oc * s / cb;
        (cb - self.l, self.side * d * theta_dot, d)
    }

    /// Side of the shaft, ±1.
    pub fn side(&self) -> f64 {
        self.side
    }
}

/// Penetration of a rod's free play, m: the eye `gap` (m) ahead of its rod against a play of
/// half-width `half` (m); positive past the far face, negative past the near one, 0 within.
pub fn free_play_penetration(gap: f64, half: f64) -> f64 {
    if gap > half {
        gap - half
    } else if gap < -half {
        gap + half
    } else {
        0.0
    }
}

/// Penetration of a cylinder's end stops by its rod at `x` (m) of `stroke` (m): positive below
/// 0, negative past the stroke, 0 between.
pub fn end_stop_penetration(x: f64, stroke: f64) -> f64 {
    if x < 0.0 {
        -x
    } else if x > stroke {
        stroke - x
    } else {
        0.0
    }
}

/// A rod's stops and seal: each stop a spring of `k` (N/m) with a damper of `d` (N·s/m), the
/// seal's viscous friction `c_seal` (N·s/m).
#[derive(Debug, Clone, Copy)]
pub struct RodStops {
    /// Stop stiffness, N/m.
    pub k: f64,
    /// Stop damping, N·s/m.
    pub d: f64,
    /// Seal friction, N·s/m.
    pub c_seal: f64,
}

impl RodStops {
    /// The bench's.
    pub fn of(b: &Bench) -> RodStops {
        RodStops {
            k: b.stop_stiffness_n_per_m,
            d: b.stop_damping_n_s_per_m,
            c_seal: b.seal_friction_n_s_per_m,
        }
    }

    /// The massless rod's speed (m/s) and the force its eye's contact takes (N), from
    /// 0 = F_contact + F_hyd + F_end − c·ẋ: `f_hyd` the chambers' force (N), `pen` the free
    /// play's and `pen_end` the end stops' penetration (m), the eye at `v_eye` (m/s). `engaged`:
    /// the rod rides its eye on a rigid face (the stops as located events), so ẋ is the eye's
    /// speed.
    pub fn rod_motion(
        &self,
        f_hyd: f64,
        pen: f64,
        pen_end: f64,
        v_eye: f64,
        engaged: bool,
    ) -> (f64, f64) {
        let RodStops { k, d, c_seal } = *self;
        let (contact, end) = (pen != 0.0, pen_end != 0.0);
        let mut num = f_hyd + k * pen_end;
        let mut den = c_seal;
        if contact {
            num += k * pen + d * v_eye;
            den += d;
        }
        if end {
            den += d;
        }
        if engaged {
            let f_end = k * pen_end - if end { d * v_eye } else { 0.0 };
            (v_eye, c_seal * v_eye - f_hyd - f_end)
        } else {
            let x_dot = num / den;
            let f = if contact {
                k * pen + d * (v_eye - x_dot)
            } else {
                0.0
            };
            (x_dot, f)
        }
    }
}

/// A chamber's pressure rate before its unit (Pa/s): oil of modulus `e` (Pa) and specific
/// volume `v` (m³ per m³ of reference volume) in a volume `vol` (m³) that grows at `vol_dot`
/// (m³/s), with `m_net` (m³/s of reference volume) flowing in.
pub fn chamber_pressure_rate(e: f64, vol: f64, v: f64, m_net: f64, vol_dot: f64) -> f64 {
    e / vol * (v * m_net - vol_dot)
}

/// The motor's flow, m³/s: its displacement at `omega` (rad/s) and its internal leakage under
/// `dp` (Pa).
pub fn motor_flow(b: &Bench, omega: f64, dp: f64) -> f64 {
    b.motor_disp_m3_per_rad * omega + b.motor_leak_m3_per_s_pa * dp
}

/// The motor's shaft torque under `dp` (Pa), N·m.
pub fn motor_torque(b: &Bench, dp: f64) -> f64 {
    b.motor_disp_m3_per_rad * dp * b.motor_eta_mech
}

/// A constant load's torque rises over the first rpm of speed (tanh(ω / 1 rpm)), rad/s: a load
/// that opposes motion without a step at standstill, which the solver could not take.
pub const LOAD_SMOOTHING_RAD_S: f64 = 0.104_719_755;

/// The load's torque at `omega` (rad/s), N·m.
pub fn load_torque(b: &Bench, omega: f64) -> f64 {
    match b.load {
        Load::Viscous(c) => c * omega,
        Load::Constant(tq) => tq * (omega / LOAD_SMOOTHING_RAD_S).tanh(),
    }
}

/// Steady motor state (inlet pressure Pa, speed rad/s) for P2, LP and aperture.
pub fn steady_motor(bench: &Bench, p2: f64, lp: f64, aperture_pct: f64) -> (f64, f64) {
    let dp_of = |w: f64| match bench.load {
        Load::Viscous(c) => c * w / (bench.motor_disp_m3_per_rad * bench.motor_eta_mech),
        Load::Constant(t) => t / (bench.motor_disp_m3_per_rad * bench.motor_eta_mech),
    };
    let resid = |w: f64| {
        let dpm = dp_of(w);
        valve_flow(bench, aperture_pct, p2 - lp - dpm)
            - bench.motor_disp_m3_per_rad * w
            - bench.motor_leak_m3_per_s_pa * dpm
    };
    if aperture_pct <= 0.0 || resid(0.0) <= 0.0 {
        return (lp, 0.0);
    }
    let (mut lo, mut hi) = (0.0, 1.0);
    while resid(hi) > 0.0 && hi < 1e5 {
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if resid(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let w = 0.5 * (lo + hi);
    (lp + dp_of(w), w)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::bench::{BAR, Bench};

    #[test]
    fn bulk_modulus_matches_hand_values() {
        let b = Bench::reference();
        // With no air the modulus is the liquid's.
        let mut pure = b.oil.clone();
        pure.trapped_air_fraction = 0.0;
        assert!((bulk_modulus(&pure, 100.0 * BAR) / 1.6e9 - 1.0).abs() < 1e-12);
        // 6 % air: ≈1.28 GPa at 100 bar, a few MPa near 0 bar gauge.
        let e100 = bulk_modulus_simhydraulics(&b.oil, 100.0 * BAR);
        assert!((e100 / 1e9 - 1.28).abs() < 0.01, "{e100}");
        assert_eq!(bulk_modulus_simhydraulics(&pure, 100.0 * BAR), 1.6e9);
        let e0 = bulk_modulus(&b.oil, 0.0);
        assert!(e0 > 1e6 && e0 < 1e7, "{e0}");
    }

    #[test]
    fn exact_modulus_stays_within_0_15_pct_of_the_physics_md_formula() {
        let oil = Bench::reference().oil;
        let mut worst = 0.0f64;
        for k in 0..=130 {
            let p = k as f64 * BAR;
            let rel = (bulk_modulus(&oil, p) / bulk_modulus_simhydraulics(&oil, p) - 1.0).abs();
            worst = worst.max(rel);
        }
        println!("max |E/E_simhydraulics − 1| over 0..130 bar: {worst:.2e}");
        assert!(worst < 1.5e-3);
    }

    #[test]
    fn equation_of_state_is_self_consistent() {
        // E = −v/v' and G' = v, checked by central differences.
        let f = Fluid::new(&Bench::reference().oil);
        for p_bar in [-0.5, 0.0, 3.0, 8.0, 50.0, 100.0, 130.0, 300.0] {
            let p = p_bar * BAR;
            let h = 10.0;
            let dv = (f.volume_ratio(p + h) - f.volume_ratio(p - h)) / (2.0 * h);
            let e = -f.volume_ratio(p) / dv;
            let rel_e = (e / f.bulk_modulus(p) - 1.0).abs();
            let (v, e_fused, g) = f.state_exergy(p, true);
            assert_eq!((v, e_fused), f.state(p));
            assert!(
                (g / f.exergy(p) - 1.0).abs() < 1e-12 || g == f.exergy(p),
                "{p_bar}"
            );
            let dg = (f.exergy(p + h) - f.exergy(p - h)) / (2.0 * h);
            let rel_g = (dg / f.volume_ratio(p) - 1.0).abs();
            assert!(
                rel_e < 1e-6 && rel_g < 1e-8,
                "{p_bar} bar: {rel_e:e} {rel_g:e}"
            );
        }
    }

    #[test]
    fn valve_flow_reproduces_the_arithmetic_check_of_physics_md() {
        // 10 % at 92 bar: ≈1.53 L/min; 15 %: ≈2.61 L/min (turbulent regime).
        let b = Bench::reference();
        let q10 = valve_flow(&b, 10.0, 92.0 * BAR) * 60_000.0;
        let q15 = valve_flow(&b, 15.0, 92.0 * BAR) * 60_000.0;
        println!("q10 {q10:.3} L/min, q15 {q15:.3} L/min");
        assert!((q10 - 1.53).abs() < 0.01);
        assert!((q15 - 2.61).abs() < 0.015);
    }

    #[test]
    fn hp_accumulator_gas_volume_at_102_bar() {
        let b = Bench::reference();
        let acc = GasAccumulator::new(&b.hp_acc);
        let v = acc.gas_volume(102.0 * BAR) * 1e3;
        assert!((v - 3.74).abs() < 0.01, "{v}");
        // Stored energy is ∫ p dV and capacitance is dV/dp: compare with fine sums.
        let (p0, p1) = (b.hp_acc.precharge_pa - BLADDER_BAND, 102.0 * BAR);
        // (Points off the band's ends, where C is continuous but its slope is not.)
        let pc = b.hp_acc.precharge_pa;
        for p in [pc + 0.1e5, pc + 0.3e5, pc + 0.7e5, pc + 3e5, p1] {
            let h = 1.0;
            let dv = (acc.fluid_volume(p + h) - acc.fluid_volume(p - h)) / (2.0 * h);
            let rel = (dv / acc.capacitance(p) - 1.0).abs();
            assert!(rel < 1e-6, "{p}: {rel:e}");
        }
        let n = 100_000;
        let mut e = 0.0;
        for k in 0..n {
            let pa = p0 + (p1 - p0) * k as f64 / n as f64;
            let pb = p0 + (p1 - p0) * (k + 1) as f64 / n as f64;
            e += 0.5 * (pa + pb) * (acc.fluid_volume(pb) - acc.fluid_volume(pa));
        }
        let rel = (acc.stored_energy(p1) - e).abs() / e;
        assert!(rel < 1e-8, "{rel}");
    }

    #[test]
    fn fluid_volume_above_the_band_is_the_gas_laws() {
        // Over 0..130 bar, for both accumulators of the reference bench and a few others: above
        // the band the oil volume equals V_T − V_gas(p) of the gas law; inside it the deviation
        // is the band's own (reported), and the band's oil and the law's agree at its top.
        let b = Bench::reference();
        let mut accs = vec![("HP", b.hp_acc), ("LP", b.lp_acc)];
        for (precharge_bar, index) in [(2.0, 1.0), (15.0, 1.4), (90.0, 1.2)] {
            let mut a = b.hp_acc;
            a.precharge_pa = precharge_bar * BAR;
            a.index = index;
            accs.push(("other", a));
        }
        for (name, acc) in accs {
            let a = GasAccumulator::new(&acc);
            let band = a.band;
            let (mut worst_above, mut worst_in) = (0.0f64, 0.0f64);
            for k in 0..=13_000 {
                let p = k as f64 * 0.01 * BAR;
                let law = a.volume - a.gas_volume(p);
                // cm³ per litre of gas.
                let dev = (a.fluid_volume(p) - law).abs() / a.volume * 1e3;
                if p > band.top {
                    worst_above = worst_above.max(dev);
                } else {
                    worst_in = worst_in.max(dev);
                }
            }
            println!(
                "{name} (precharge {:.1} bar, k {}): band {:.3}..{:.3} bar (shape a = {:.3}); \
                 |V_oil − V_law| above it {worst_above:.2e} cm³/L, inside it {worst_in:.3} cm³/L",
                a.precharge / BAR,
                a.index,
                band.start / BAR,
                band.top / BAR,
                band.a
            );
            assert!(worst_above <= 1e-6, "{name}: {worst_above} cm³/L");
            assert_eq!(
                (band.start, band.top),
                (a.precharge, a.precharge + BLADDER_BAND)
            );
            // No oil below the precharge; the capacitance within the band stays positive and
            // within 60 % above the gas law's (a²/(4(a − 1)) at most: 1.56 for a = 5).
            assert_eq!(a.fluid(a.precharge - 1.0), (0.0, 0.0));
            for k in 1..=100 {
                let p = a.precharge + BLADDER_BAND * k as f64 / 100.0;
                let (_, c) = a.fluid(p);
                assert!(
                    c > 0.0 && c < 1.6 * a.exact_capacitance(p),
                    "{name} {p}: {c}"
                );
            }
        }
    }

    #[test]
    fn config_rod_travel_orders_as_the_paper() {
        // ±40 mm rack on a 96 mm pinion; travel of the eye of HC3.1 per config.
        let b = Bench::reference();
        let amp = 0.040 / b.pinion_radius_m;
        let travel: Vec<f64> = b
            .configs
            .iter()
            .map(|g| {
                let lever = Lever::new(g, 0.2, 1.0);
                (lever.eye(amp, 0.0).0 - lever.eye(-amp, 0.0).0) * 1e3
            })
            .collect();
        println!("eye travel per config (mm): {travel:?}");
        // docs/physics.md: rod travel ≈ 101 / 97 / 65 / 81 mm (eye travel minus nothing here).
        for (t, want) in travel.iter().zip([101.0, 97.0, 65.0, 81.0]) {
            assert!((t - want).abs() < 2.0, "{t} vs {want}");
        }
        // Arm at neutral = R.
        let lever = Lever::new(&b.configs[0], 0.2, 1.0);
        assert!((lever.eye(0.0, 0.0).2 - 0.125).abs() < 1e-4);
    }

    #[test]
    fn check_area_is_continuous_and_monotone() {
        let b = Bench::reference();
        let mut prev = 0.0;
        for k in -100..400 {
            let dp = k as f64 * 0.01 * BAR;
            let a = check_area(&b.check, b.oil.leak_area_m2, dp);
            assert!(a >= prev);
            prev = a;
        }
        assert_eq!(prev, b.check.max_area_m2);
    }
}

#[cfg(test)]
mod properties {
    use super::*;
    use crate::sim::bench::{BAR, Bench};
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn orifice_flow_is_odd_and_monotone_in_dp(area_mm2 in 1e-3f64..50.0, dp_bar in 0.0f64..200.0, extra in 1e-3f64..10.0) {
            let oil = Bench::reference().oil;
            let a = area_mm2 * 1e-6;
            let q = orifice(&oil, 0.7, a, dp_bar * BAR);
            prop_assert!((q + orifice(&oil, 0.7, a, -dp_bar * BAR)).abs() <= 1e-15 * q.abs().max(1.0));
            prop_assert!(orifice(&oil, 0.7, a, (dp_bar + extra) * BAR) > q);
        }

        #[test]
        fn valve_flow_is_monotone_in_aperture(a in 0.0f64..99.0, da in 0.1f64..50.0, dp_bar in 1.0f64..150.0) {
            let b = Bench::reference();
            let q0 = valve_flow(&b, a, dp_bar * BAR);
            let q1 = valve_flow(&b, (a + da).min(100.0), dp_bar * BAR);
            prop_assert!(q1 >= q0);
        }

        #[test]
        fn accumulator_volume_and_energy_grow_with_pressure(p_bar in 0.0f64..300.0, dp in 0.01f64..50.0) {
            let acc = GasAccumulator::new(&Bench::reference().hp_acc);
            let (p0, p1) = (p_bar * BAR, (p_bar + dp) * BAR);
            prop_assert!(acc.fluid_volume(p1) >= acc.fluid_volume(p0));
            prop_assert!(acc.stored_energy(p1) >= acc.stored_energy(p0));
            prop_assert!(acc.fluid_volume(p1) < acc.volume);
        }

        #[test]
        fn fluid_is_stiffer_at_higher_pressure(p_bar in -0.9f64..300.0, dp in 0.1f64..50.0) {
            let f = Fluid::new(&Bench::reference().oil);
            prop_assert!(f.bulk_modulus((p_bar + dp) * BAR) > f.bulk_modulus(p_bar * BAR));
            prop_assert!(f.volume_ratio((p_bar + dp) * BAR) < f.volume_ratio(p_bar * BAR));
        }

        #[test]
        fn lever_extension_rate_matches_its_arm(theta in -0.5f64..0.5, cfg in 0usize..4, side in prop::bool::ANY) {
            let b = Bench::reference();
            let s = if side { 1.0 } else { -1.0 };
            let lever = Lever::new(&b.configs[cfg], 0.2, s);
            let h = 1e-6;
            let dx = (lever.eye(theta + h, 0.0).0 - lever.eye(theta - h, 0.0).0) / (2.0 * h);
            let (_, v, _) = lever.eye(theta, 1.0);
            prop_assert!((dx - v).abs() < 1e-7);
        }
    }
}
