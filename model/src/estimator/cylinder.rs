//! The cylinders on duty: chamber pressures by the oil's strain law, stroke reversals and
//! their work units, the free play, the delivered and sucked flows and the torque.

use super::*;
use crate::coeffs::{ARM_RANGE_RAD, N_NODE, P_MAX_BAR, arm_m, ext_mm, fx, modulus_bar};
use crate::config::ModelConfig;

/// Per-cylinder constants.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CylinderCoeffs {
    /// ±1.
    pub side: Fx,
    /// Cap-side flow per rod speed, L/min per mm/s.
    pub q_cap: Fx,
    /// Rod-side flow per rod speed, L/min per mm/s.
    pub q_ann: Fx,
    /// Cap-side force per bar, kN/bar.
    pub f_cap: Fx,
    /// Rod-side force per bar, kN/bar.
    pub f_ann: Fx,
    /// Cap-chamber dead volume (with hose) as a length of cap area, mm.
    pub dead_cap_mm: Fx,
    /// Rod-chamber dead volume (with hose) as a length of annulus area, mm.
    pub dead_rod_mm: Fx,
    /// Stroke, mm.
    pub stroke_mm: Fx,
    /// A_ann / A_cap (new/old area after a reversal to extending).
    pub ratio_ext: Fx,
    /// A_cap / A_ann (new/old area after a reversal to retracting).
    pub ratio_ret: Fx,
}

/// The cylinders stage's coefficients (`estimator::cylinder`): per cylinder, the lever
/// geometry's tables and the oil's strain law in the chambers.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PumpCoeffs {
    /// Cylinders.
    pub cyl: [CylinderCoeffs; 4],
    /// Lever arm d (mm) vs s·θ (rad), per geometry. In mm so that d·F stays exact to
    /// 0.01 N·m (in m, Q16.16 would quantise the arm to 1e-4 of itself).
    pub arm: [Table1<N_ARM>; 4],
    /// Rod-eye extension x (mm) vs s·θ (rad), per geometry.
    pub ext: [Table1<N_ARM>; 4],
    /// Oil strain ∫_0^p dp/E in milli-strain vs p (0..160 bar).
    pub ms_of_p: Table1<N_NODE>,
    /// Its inverse: p (bar) vs milli-strain.
    pub p_of_ms: Table1<N_NODE>,
    /// Rod-fixation free play, mm.
    pub play_mm: Fx,
    /// Seal friction, kN per mm/s (2 kN·s/m = 0.002 kN per mm/s on the reference bench: 131
    /// LSB, 0.05 % resolution).
    pub seal_kn_per_mm_s: Fx,
    /// Open check-valve pressure drop, bar.
    pub check_drop_bar: Fx,
}

impl PumpCoeffs {
    /// The cylinders' coefficients for `cfg`, built into `self` in place: their areas and
    /// volumes, the lever's arm and extension tables per geometry, the oil's strain tables.
    #[inline(never)]
    pub(crate) fn build(&mut self, cfg: &ModelConfig) {
        self.cyl = core::array::from_fn(|i| {
            let c = &cfg.cylinders[i];
            let a_cap = core::f32::consts::PI / 4.0 * c.bore_mm * c.bore_mm * 1e-6;
            let a_ann = a_cap - core::f32::consts::PI / 4.0 * c.rod_mm * c.rod_mm * 1e-6;
            CylinderCoeffs {
                side: fx(f32::from(c.side)),
                q_cap: fx(a_cap * 60.0),
                q_ann: fx(a_ann * 60.0),
                f_cap: fx(a_cap * 100.0),
                f_ann: fx(a_ann * 100.0),
                dead_cap_mm: fx(cfg.chamber_dead_volume_cm3 * 1e-6 / a_cap * 1e3),
                dead_rod_mm: fx(cfg.chamber_dead_volume_cm3 * 1e-6 / a_ann * 1e3),
                stroke_mm: fx(c.stroke_mm),
                ratio_ext: fx(a_ann / a_cap),
                ratio_ret: fx(a_cap / a_ann),
            }
        });
        let stroke = cfg.cylinders[0].stroke_mm;
        for (g, (arm, ext)) in self.arm.iter_mut().zip(&mut self.ext).enumerate() {
            let geo = cfg.geometries[g];
            arm.sample_into(-ARM_RANGE_RAD, ARM_RANGE_RAD, move |th| {
                1e3 * arm_m(&geo, stroke, th)
            });
            ext.sample_into(-ARM_RANGE_RAD, ARM_RANGE_RAD, move |th| {
                ext_mm(&geo, stroke, th)
            });
        }
        // Milli-strain on a fine pressure grid (0.25 bar, accumulated once), then both tables
        // by linear interpolation of it: the strain law is monotone, so its inverse is too.
        const FINE: usize = 641;
        let step = P_MAX_BAR / (FINE - 1) as f32;
        let mut fine = [0.0f32; FINE];
        for i in 1..FINE {
            let mid = (i as f32 - 0.5) * step;
            fine[i] = fine[i - 1] + 1e3 * step / modulus_bar(cfg, mid);
        }
        let ms_at = |p: f32| {
            let u = (p / step).clamp(0.0, (FINE - 1) as f32);
            let i = (u as usize).min(FINE - 2);
            fine[i] + (u - i as f32) * (fine[i + 1] - fine[i])
        };
        let p_at = |ms: f32| {
            let i = fine.partition_point(|&v| v <= ms).clamp(1, FINE - 1);
            let (a, b) = (fine[i - 1], fine[i]);
            step * ((i - 1) as f32 + ((ms - a) / (b - a)).clamp(0.0, 1.0))
        };
        self.ms_of_p.sample_into(0.0, P_MAX_BAR, ms_at);
        self.p_of_ms.sample_into(0.0, fine[FINE - 1], p_at);
        self.play_mm = fx(cfg.free_play_mm);
        self.seal_kn_per_mm_s = fx(cfg.seal_friction_n_s_per_m * 1e-6);
        self.check_drop_bar = fx(cfg.check_valve_drop_bar);
    }
}

/// Pressures of the new (compressing) and old (relaxing) chambers after `u` mm of rod travel
/// since the reversal, bar: the strain moves by u·(strain per mm) from its value at the reversal.
#[inline]
pub(super) fn p_new_at(k: &PumpCoeffs, cs: &CylState, u: Fx, lo: Fx, hi: Fx) -> Fx {
    p_at_strain(k, cs.ms_new0.saturating_add(u.qmul(cs.ms_per_mm_n)), lo, hi)
}

#[inline]
pub(super) fn p_old_at(k: &PumpCoeffs, cs: &CylState, u: Fx, lo: Fx, hi: Fx) -> Fx {
    p_at_strain(k, cs.ms_old0.saturating_sub(u.qmul(cs.ms_per_mm_o)), lo, hi)
}

/// Oil pressure at a milli-strain, held between the check valves' limits.
#[inline]
pub(super) fn p_at_strain(k: &PumpCoeffs, ms: Fx, lo: Fx, hi: Fx) -> Fx {
    clamp(k.p_of_ms.at(ms), lo, hi)
}

/// `a·b/1000` for a milli-strain `a` and a length `b` in mm (a travel in mm), without a
/// division: the Q32.32 product times 2^32/1000 (relative error 7e-8), saturated.
#[inline]
pub(super) fn ms_times_mm(a: Fx, b: Fx) -> Fx {
    let p = wide::mul_q16(a.to_bits(), b.to_bits()); // Q16.16, |p| < 2^47
    let p = p.clamp(-(1i64 << 31), 1i64 << 31);
    Fx::from_bits(((wide::mul_i64_i32(p, 4_294_967) + (1i64 << 31)) >> 32) as i32)
}

/// The lever on one side of the shaft this step.
pub(super) struct Lever {
    /// s·θ, rad.
    pub(super) th: Fx,
    /// s·d: the signed lever arm, mm.
    pub(super) sd: Fx,
    /// Rod speed s·d·θ̇, mm/s.
    pub(super) v: Fx,
    /// Restraining torque of a rod's seal friction, N·m: s·d·c·v.
    pub(super) seal: Fx,
}

/// What the cylinders of one step share.
pub(super) struct Shared<'a> {
    pub(super) k: &'a PumpCoeffs,
    /// dt = 2^−dtl s.
    pub(super) dtl: u8,
    /// Rod-eye extension table of the geometry on duty.
    pub(super) ext: &'a Table1<N_ARM>,
    /// LP, bar.
    pub(super) lp: Fx,
    /// LP less the check valve's drop: a chamber at it sucks, bar.
    pub(super) lo: Fx,
    /// P2 plus the check valve's drop: a chamber at it delivers, bar.
    pub(super) hi: Fx,
    /// Reversal work units left this step.
    pub(super) budget: u8,
    /// Flow the cylinders deliver into HP so far, L/min.
    pub(super) q_pump: Fx,
    /// Flow the cylinders take from LP so far (suction − idle bypass return), L/min.
    pub(super) q_lp: Fx,
}

/// One unit of a cylinder's pending reversal work (see [`REVERSAL_UNITS_PER_STEP`]).
#[inline(never)]
pub(super) fn reversal_unit(sh: &Shared, c: &CylinderCoeffs, cs: &mut CylState, th: Fx) {
    let (k, lo, hi) = (sh.k, sh.lo, sh.hi);
    if cs.setup_left == 0 {
        // Force balance A_o·p_old(u) = A_n·p_new(u) (p_old falls, p_new rises): bisection.
        let ratio = area_ratio(c, cs.dir);
        let m = Fx::from_bits((cs.u_bal.to_bits() + cs.u_bal_hi.to_bits()) >> 1);
        let (pn, po) = (p_new_at(k, cs, m, lo, hi), p_old_at(k, cs, m, lo, hi));
        if po.saturating_sub(ratio.qmul(pn)) > ZERO {
            cs.u_bal = m;
        } else {
            cs.u_bal_hi = m;
        }
        cs.bisect_left -= 1;
        if cs.bisect_left == 0 {
            if cs.from_rest {
                // From rest both chambers start at LP and the eye sits in the middle of its free
                // play. Where their forces push the rod the new way (an extension: LP on the
                // larger cap side) it floats ahead to the balance u_bal as the lever starts, and
                // the eye meets it after u_bal + half the play: the eye's travel counts from
                // half the play, the rod held at u_bal until the eye arrives (counting from
                // u_bal + half, as before, met it u_bal early: Test I with HC3.1 started 1.4
                // bar off instead of 0.8). Against the stroke (a retraction: no balance) the
                // rod floated back by the extension's balance, which is not computed here: the
                // eye crosses half the play (≈ 0.2 mm too much for HC3.4 in Config 1, whose
                // model-only start is then 1.6 bar off, not the run's largest error).
                cs.travel = cs.travel.saturating_add(k.play_mm >> 1u32);
            } else if cs.u_bal_hi == cs.u_end.max(cs.u_suc) {
                // No balance up to full build-up: the old chamber's force still drives the rod
                // ahead of the eye once both chambers are at P2 and LP, so it stays there.
                cs.play = ZERO;
            }
        }
        return;
    }
    if cs.setup_left == SETUP_UNITS {
        // (1) Chamber lengths at the rod's position and the new chamber's strain per mm: a
        // chamber of length L (dead volume + chamber) moved by u changes its strain by u/L.
        // 1000/L is taken as (1024/L)·(1000/1024) so the reciprocal keeps 1e-5 precision.
        let pos = sh.ext.at(th);
        let l_cap = c.dead_cap_mm.saturating_add(pos);
        let l_rod = c
            .dead_rod_mm
            .saturating_add(c.stroke_mm.saturating_sub(pos));
        (cs.len_n, cs.len_o) = if cs.dir >= 0 {
            (l_rod, l_cap)
        } else {
            (l_cap, l_rod)
        };
        cs.ms_per_mm_n = recip(Fx::from_bits(cs.len_n.to_bits() >> 10)).qmul(KMS);
    } else if cs.setup_left == SETUP_UNITS - 1 {
        // (2) The old chamber's strain per mm, and the play the eye has to cross.
        cs.ms_per_mm_o = recip(Fx::from_bits(cs.len_o.to_bits() >> 10)).qmul(KMS);
        if !cs.from_rest {
            cs.play = if cs.engaged {
                play_to_cross(k, c, cs, lo, hi)
            } else {
                cs.gap
            };
        }
    } else if cs.setup_left == SETUP_UNITS - 2 {
        // (3) Start from the chambers' pressures at the reversal (held since), not from P2/LP:
        // in an irregular sea the shaft can turn back before a stroke has built up.
        let (p_new0, p_old0) = held_pressures(cs, lo, hi);
        cs.ms_new0 = k.ms_of_p.at(p_new0);
        cs.ms_old0 = k.ms_of_p.at(p_old0);
    } else {
        // (4) Travel for the new chamber to reach P2 (delivery) and the old one LP (suction):
        // strain to go × L / 1000; the bisection's bracket.
        let to_hi = k.ms_of_p.at(hi).saturating_sub(cs.ms_new0).max(ZERO);
        let to_lo = cs.ms_old0.saturating_sub(k.ms_of_p.at(lo)).max(ZERO);
        cs.u_end = ms_times_mm(to_hi, cs.len_n);
        cs.u_suc = ms_times_mm(to_lo, cs.len_o);
        cs.u_bal = ZERO;
        cs.u_bal_hi = cs.u_end.max(cs.u_suc);
        // The balance is sought only where the eye then crosses the whole play: a rod pushed at
        // once, or one that floated, has none to reach (u_bal = 0).
        if cs.from_rest || cs.play == k.play_mm {
            cs.bisect_left = BISECT_ITERATIONS;
        }
    }
    cs.setup_left -= 1;
}

/// The free play the eye crosses after a reversal, from the chambers' net force on the rod when
/// the lever turned (held pressures, the old chamber's force less the new one's, as a pressure
/// on the old chamber: `p_old − (A_new/A_old)·p_new`). The rod lies against whichever end of the
/// play that force presses it to:
/// - it assists the new motion (the usual case: the old chamber delivered at P2 and resisted
///   the old motion): the rod follows the eye until the forces balance, then stands while the
///   eye crosses the whole play;
/// - it already resists the new motion: the rod ran ahead of the eye on the old stroke (P2 below
///   LP·A_suc/A_del, a low P2 on an annulus stroke) and lies against the end that now pushes
///   it: no play to cross;
/// - within ±[`FLOAT_BAND`] of zero, after a stroke that delivered ([`CylState::delivered`]),
///   the rod floated: the pump's delivery and the motor's draw held P2 at the balance while the
///   rod drifted ahead in its play. The full simulation shows it most of the way across when the
///   lever turns (0.2–1 mm of a 4 mm play left in the Test I runs with one cylinder); a quarter
///   of the play is taken. After a stroke that had pushed the rod but not yet delivered, the rod
///   stands where the eye left it: the whole play.
///
/// Only for a stroke whose eye pushed the rod ([`CylState::engaged`]); after one that turned
/// before, the play is the eye's distance back, [`CylState::gap`].
///
/// The band's edges are ramps [`FLOAT_RAMP`] wide (0 → a quarter at −band, a quarter → all of it
/// at +band), so that a rounding difference in the held pressures moves the play by a small
/// amount, not by a quarter of it: a step at the band's edge separates the fixed-point model
/// from its f64 reference by 0.5 bar in a Config 2 run. Inside the band the play stays a
/// quarter: a slope there would turn the 1e-4 bar by which the two models' pressures differ into
/// a persistent torque offset on every floating reversal (≈ 3 000 N·m per mm of play during
/// compression; a linear play over the whole band gave 0.6 N·m RMS in the irregular sea).
/// Both widths are powers of two: two shifts and a multiply.
pub(super) fn play_to_cross(
    k: &PumpCoeffs,
    c: &CylinderCoeffs,
    cs: &CylState,
    lo: Fx,
    hi: Fx,
) -> Fx {
    let (p_new0, p_old0) = held_pressures(cs, lo, hi);
    let net = p_old0.saturating_sub(area_ratio(c, cs.dir).qmul(p_new0));
    // A rod floats only while it delivers (the pump's delivery and the motor's draw holding P2
    // at the balance while it drifts); one the eye has pushed but that has not yet delivered
    // stands where the eye left it, the whole play behind the eye.
    let float = if cs.delivered {
        k.play_mm >> 2u32
    } else {
        k.play_mm
    };
    if net <= -FLOAT_BAND {
        ZERO
    } else if net >= FLOAT_BAND {
        k.play_mm
    } else if net < FLOAT_RAMP - FLOAT_BAND {
        // (net + band)/ramp in [0, 1).
        float.qmul((net + FLOAT_BAND) << FLOAT_RAMP_SHIFT)
    } else if net > FLOAT_BAND - FLOAT_RAMP {
        // (net − (band − ramp))/ramp in (0, 1).
        float + (k.play_mm - float).qmul((net - (FLOAT_BAND - FLOAT_RAMP)) << FLOAT_RAMP_SHIFT)
    } else {
        float
    }
}

/// The new and the old chamber's pressures when the lever turned (held since; both at LP − drop
/// on a first stroke from rest), held to [LP − drop, P2 + drop], bar.
#[inline(always)]
pub(super) fn held_pressures(cs: &CylState, lo: Fx, hi: Fx) -> (Fx, Fx) {
    let (p_new0, p_old0) = if cs.from_rest {
        (lo, lo)
    } else if cs.dir >= 0 {
        (cs.p_rod, cs.p_cap)
    } else {
        (cs.p_cap, cs.p_rod)
    };
    (clamp(p_new0, lo, hi), clamp(p_old0, lo, hi))
}

/// A_new/A_old of a stroke in direction `dir` (extending: annulus over cap).
#[inline(always)]
pub(super) fn area_ratio(c: &CylinderCoeffs, dir: i8) -> Fx {
    if dir >= 0 { c.ratio_ext } else { c.ratio_ret }
}

/// Band of the net chamber force at a reversal within which the rod floats in its play (as a
/// pressure on the old chamber: ±0.25 bar, about the estimate's own noise with the HP
/// transducer).
pub const FLOAT_BAND: Fx = Fx::from_bits(16_384);

/// Width of the ramps at the float band's edges: 2^-4 = 0.0625 bar (the play to cross ramps
/// over it at each edge of [`FLOAT_BAND`]).
pub const FLOAT_RAMP: Fx = Fx::from_bits(1 << (16 - FLOAT_RAMP_SHIFT));
pub(super) const FLOAT_RAMP_SHIFT: u32 = 4;

/// 1000/1024, exact in Q16.16.
pub(super) const KMS: Fx = Fx::from_bits(64_000);

/// Torque of one cylinder (N·m); adds its flows to the step's sums and advances its stroke
/// state, spending the step's reversal work budget. Kept out of line: the step would otherwise
/// carry four unrolled copies of it, ×4 the flash.
#[inline(never)]
pub(super) fn cylinder(
    sh: &mut Shared,
    c: &CylinderCoeffs,
    cs: &mut CylState,
    lever: &Lever,
    on: bool,
) -> Fx {
    let (k, lo, hi, dtl) = (sh.k, sh.lo, sh.hi, sh.dtl);
    let (th, sd, v) = (lever.th, lever.sd, lever.v);
    if !on {
        // Idle: bypassed to LP; LP·A_rod pushes the rod out, the rod volume flows to LP.
        let a_rod_q = c.q_cap.saturating_sub(c.q_ann);
        sh.q_lp = sh.q_lp.saturating_add(a_rod_q.qmul(v));
        let f = mul_bounded(sh.lp, c.f_cap.saturating_sub(c.f_ann));
        return sd.qmul(f).saturating_neg();
    }
    let dir: i8 = if v > ZERO {
        1
    } else if v < ZERO {
        -1
    } else {
        cs.dir
    };
    // After a reversal (eye travel e since it, mm): the rod first follows the lever while the
    // old delivering chamber relaxes and the new one compresses, until their forces balance at
    // u_bal; the eye then crosses the free play (`cs.play`) with the rod standing; then the rod
    // moves again until the new chamber reaches P2 and delivers. The rod's own travel u sets
    // both chamber pressures through the oil's strain law p = P(strain) (inverse strain table).
    // (A linear pressure–travel law put the new chamber at ~45 bar instead of ~19 bar when the
    // forces balance, so the torque built up too early.)
    if dir != cs.dir {
        // Where the eye stands in its free play as the lever turns (see `CylState::gap`):
        // until it has crossed this stroke's play (set-up pending, the rod following it to the
        // force balance, or the eye crossing the play with the rod standing) the rod stands
        // where it stopped, `rel` behind the eye. A stroke that turns before its set-up has
        // taken its play (unit 2: a few steps, the tracker's speed flickering about zero at
        // a slow reversal) is no stroke: the new one continues the stroke before it, whose
        // reading was kept aside (`CylState::alt_gap`), and this one's is kept aside in turn.
        if cs.setup_left > SETUP_UNITS - 2 {
            core::mem::swap(&mut cs.engaged, &mut cs.alt_engaged);
            core::mem::swap(&mut cs.delivered, &mut cs.alt_delivered);
            core::mem::swap(&mut cs.gap, &mut cs.alt_gap);
        } else {
            let rel = if cs.setup_left != 0 {
                cs.travel
            } else {
                let ub = if cs.bisect_left > 0 {
                    cs.u_bal_hi
                } else {
                    cs.u_bal
                };
                // The eye's travel past the rod: travel − u with u = min(travel, ub) ∨
                // (travel − play) the rod's travel, i.e. travel − ub held to [0, play].
                clamp(cs.travel.saturating_sub(ub), ZERO, cs.play)
            };
            cs.engaged = rel >= cs.play;
            cs.delivered = cs.setup_left == 0 && cs.travel >= cs.u_end.saturating_add(cs.play);
            cs.gap = k
                .play_mm
                .saturating_sub(cs.play)
                .saturating_add(rel)
                .min(k.play_mm);
            // Were the new stroke no stroke, the next would continue this one: the eye would
            // still have the rest of this stroke's play to cross.
            (cs.alt_engaged, cs.alt_delivered) = (false, false);
            cs.alt_gap = cs.play.saturating_sub(rel).max(ZERO);
        }
        cs.from_rest = cs.dir == 0;
        cs.dir = dir;
        cs.travel = ZERO;
        cs.play = k.play_mm;
        cs.setup_left = SETUP_UNITS;
        cs.bisect_left = 0;
    }
    if (cs.setup_left | cs.bisect_left) != 0 && sh.budget > 0 {
        sh.budget -= 1;
        reversal_unit(sh, c, cs, th);
    }
    let speed = v.abs();
    let mm = mul_dt(speed, dtl); // mm this step = mm/s × dt
    if cs.setup_left == 0 {
        // Flow per unit rod speed of the delivering and the sucking chamber (the flows
        // themselves are taken only when they pass a check valve).
        let (a_del, a_suc) = if dir >= 0 {
            (c.q_ann, c.q_cap)
        } else {
            (c.q_cap, c.q_ann)
        };
        // While the bisection runs, u_bal is known to lie in [u_bal, u_bal_hi]: the rod follows
        // the lever up to the upper end.
        let ub = if cs.bisect_left > 0 {
            cs.u_bal_hi
        } else {
            cs.u_bal
        };
        let e_end = cs.u_end.saturating_add(cs.play);
        // The rod's travel: the eye's up to the balance, held there while the eye crosses the
        // play, the eye's less the play after (branch-free: min/max of the three).
        let u = cs.travel.min(ub).max(cs.travel.saturating_sub(cs.play));
        // The travel counts until the new chamber delivers and the old one sucks (then it is
        // not needed: kept bounded). (Counting stopped at delivery alone once left an old
        // chamber that needs more travel than the new one short of LP for the rest of the
        // stroke: above LP, no suction flow, its strain table read every step.)
        if cs.travel < e_end {
            cs.travel = cs.travel.saturating_add(mm);
        } else {
            sh.q_pump = sh.q_pump.saturating_add(a_del.qmul(speed));
            if u < cs.u_suc {
                cs.travel = cs.travel.saturating_add(mm);
            }
        }
        if u >= cs.u_suc {
            sh.q_lp = sh.q_lp.saturating_add(a_suc.qmul(speed));
        }
        // Once delivering (sucking) the chamber follows P2 (LP), which may have moved since the
        // reversal the strain constants were taken at.
        // (The strain table is read only for a chamber that is still building up or relaxing.)
        let p_new = if cs.travel >= e_end {
            hi
        } else {
            p_new_at(k, cs, u, lo, hi)
        };
        let p_old = if u >= cs.u_suc {
            lo
        } else {
            p_old_at(k, cs, u, lo, hi)
        };
        (cs.p_cap, cs.p_rod) = if dir >= 0 {
            (p_old, p_new)
        } else {
            (p_new, p_old)
        };
    } else {
        // Set-up pending: the chambers hold the pressures they had at the reversal and pass no
        // flow; the eye's travel is counted.
        cs.travel = cs.travel.saturating_add(mm);
    }
    let f_hyd = mul_bounded(cs.p_cap, c.f_cap).saturating_sub(mul_bounded(cs.p_rod, c.f_ann)); // kN
    // mm·kN = N·m. The seals' drag adds to it: counted all stroke long, also while the eye
    // crosses its free play (the rod then stands in the plant, but that is right after a
    // reversal, where the lever's speed and with it the drag are small).
    lever.seal.saturating_sub(sd.qmul(f_hyd))
}

/// The cylinders stage of a step: per cylinder on duty, its stroke and reversal work, its flows
/// and torque, from P2 and LP (bar), the shaft angle (rad, Q16.16) and speed (rad/s, Q32.32);
/// returns the total torque, the torque per cylinder and the step's shared sums (pump and
/// suction flows, reversal work left). Inlined into the step, its only caller.
// The step's own values, passed as they are (inlined into the step: its only caller).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn cylinders<'a>(
    k: &'a PumpCoeffs,
    dtl: u8,
    cyl: &mut [CylState; 4],
    p2: Fx,
    lp: Fx,
    theta: Fx,
    omega_q32: i64,
    inp: &Inputs,
    faults: &mut u16,
) -> (Fx, [Torque; 4], Shared<'a>) {
    let config = usize::from(inp.config);
    let (arm_table, ext_table, duty) = match (k.arm.get(config), k.ext.get(config)) {
        (Some(a), Some(e)) => (a, e, inp.on_duty),
        _ => {
            *faults |= fault::BAD_CONFIG;
            (&k.arm[0], &k.ext[0], 0)
        }
    };
    let mut torque_cyl = [Torque::ZERO; 4];
    let mut torque = ZERO;
    let mut sh = Shared {
        k,
        dtl,
        ext: ext_table,
        lp,
        lo: lp.saturating_sub(k.check_drop_bar),
        hi: p2.saturating_add(k.check_drop_bar),
        budget: REVERSAL_UNITS_PER_STEP,
        q_pump: ZERO,
        q_lp: ZERO,
    };
    // The lever on each side of the shaft (s = ±1): the arm tables are per geometry, so every
    // cylinder on one side shares s·θ, the signed arm s·d and the rod speed v = s·d·θ̇ (mm/s).
    // The shaft speed to 2^−24 rad/s for the rod speed: in Q16.16 its LSB is 6·10^−5 of a
    // 0.26 rad/s swing, and the pump flow on the empty HP node (≈ 0.18 bar per L/min a step)
    // took that as a P2 LSB a step. |ω| ≤ 100 rad/s (`OMEGA_LIM_Q32`) is < 2^31 in Q8.24, so
    // it is one word; times an arm (< 2^31 bits) < 2^62; the rod speed is held to the Q16.16
    // range.
    let omega24 = ((omega_q32 + (1 << 7)) >> 8) as i32;
    let lever = |th: Fx, negative: bool| {
        let d = arm_table.at(th);
        let sd = if negative { d.saturating_neg() } else { d };
        let v = mul_q24(sd, omega24);
        Lever {
            th,
            sd,
            v,
            seal: sd.qmul(v.qmul(k.seal_kn_per_mm_s)),
        }
    };
    let levers = [lever(theta, false), lever(theta.saturating_neg(), true)];
    for (i, (c, cs)) in k.cyl.iter().zip(cyl.iter_mut()).enumerate() {
        let on = duty & (1 << i) != 0;
        let lv = &levers[usize::from(c.side < ZERO)];
        let t = cylinder(&mut sh, c, cs, lv, on);
        torque_cyl[i] = Torque(t);
        torque = torque.saturating_add(t);
    }
    (torque, torque_cyl, sh)
}
