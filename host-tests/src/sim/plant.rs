//! The bench as an ODE: state layout, right-hand side, and every derived flow, force and power.
//!
//! States are scaled so one absolute tolerance means the same everywhere: pressures in bar, rod
//! positions in mm, motor speed in rad/s, spool aperture in %. Chambers of idle cylinders are
//! bypassed to LP and carry no state.
//!
//! Over 600 lines on purpose: the state layout and the right-hand side that indexes it
//! (`Plant::evaluate`) are read together; split, every index would cross a file.

use crate::sim::bench::{BAR, Bench};
use crate::sim::motion::Motion;
use crate::sim::physics::{self, Fluid, GasAccumulator, Lever, check_flow};
use std::cell::Cell;

/// Number of cylinders on the bench.
pub const N_CYL: usize = 4;

/// Names of the integrated balance terms (the diffsol output vector), with units.
/// Volumes are litres of reference volume (oil at 0 bar gauge), i.e. mass.
pub const QUAD_NAMES: [&str; N_QUAD] = [
    "into_hp_l",
    "valve_l",
    "relief_l",
    "makeup_l",
    "motor_l",
    "lp_to_chambers_l",
    "input_work_kj",
    "mechanical_loss_kj",
    "check_valve_loss_kj",
    "control_valve_loss_kj",
    "relief_loss_kj",
    "motor_friction_loss_kj",
    "load_work_kj",
    "line_loss_kj",
    "motor_leakage_loss_kj",
    "motor_shaft_work_kj",
    "pumped_kj",
];
/// Length of the integrated balance vector.
pub const N_QUAD: usize = 17;

/// Indices of the terms in [`QUAD_NAMES`]: the oil flows; the energy into the circuit,
/// dissipated by cause, to the generator, and two that split the path without entering the
/// balance (the active cylinders' net hydraulic exergy out of LP into HP, and the motor's shaft
/// work).
pub mod quad {
    /// Oil into the HP side from the cylinders' check valves.
    pub const INTO_HP: usize = 0;
    /// Oil through the control valve.
    pub const VALVE_FLOW: usize = 1;
    /// Oil through the relief valve.
    pub const RELIEF_FLOW: usize = 2;
    /// Oil through the make-up check valve.
    pub const MAKEUP_FLOW: usize = 3;
    /// Oil through the motor.
    pub const MOTOR_FLOW: usize = 4;
    /// Oil from the LP side into the cylinders' chambers.
    pub const LP_TO_CHAMBERS: usize = 5;
    /// Mechanical work into the cylinders' eyes (the shaft's input).
    pub const INPUT: usize = 6;
    /// Seal friction and the free-play and end-stop dampers.
    pub const MECHANICAL: usize = 7;
    /// The cylinders' check valves and the make-up check valve.
    pub const CHECK_VALVES: usize = 8;
    /// Throttling in the control valve.
    pub const CONTROL_VALVE: usize = 9;
    /// The relief valve.
    pub const RELIEF: usize = 10;
    /// The motor's mechanical efficiency (friction).
    pub const MOTOR_FRICTION: usize = 11;
    /// Work into the load (the generator).
    pub const GENERATOR: usize = 12;
    /// The HP and LP line resistances.
    pub const LINES: usize = 13;
    /// The motor's internal leakage.
    pub const MOTOR_LEAKAGE: usize = 14;
    /// Motor shaft work (displacement × Δp × η_mech × ω).
    pub const MOTOR_SHAFT: usize = 15;
    /// Net exergy the active cylinders deliver into HP minus what they draw from LP.
    pub const PUMPED: usize = 16;
    /// The terms that leave the circuit: the balance is input = Σ these + Δ stored.
    pub const OUT: [usize; 8] = [
        MECHANICAL,
        CHECK_VALVES,
        CONTROL_VALVE,
        RELIEF,
        MOTOR_FRICTION,
        MOTOR_LEAKAGE,
        LINES,
        GENERATOR,
    ];
}

/// Energy stored in the circuit at an instant (or its change over a run), J.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Stored {
    /// The gas of both accumulators (∫ p dV_oil).
    pub gas_j: f64,
    /// The oil's compression in every node and chamber.
    pub oil_j: f64,
    /// The motor's rotating inertia.
    pub inertia_j: f64,
    /// The hard stops' springs.
    pub stops_j: f64,
}

impl Stored {
    /// All of it, J.
    pub fn total(&self) -> f64 {
        self.gas_j + self.oil_j + self.inertia_j + self.stops_j
    }

    /// `self − before`, term by term.
    pub fn since(&self, before: &Stored) -> Stored {
        Stored {
            gas_j: self.gas_j - before.gas_j,
            oil_j: self.oil_j - before.oil_j,
            inertia_j: self.inertia_j - before.inertia_j,
            stops_j: self.stops_j - before.stops_j,
        }
    }
}

/// One cylinder on duty.
#[derive(Debug, Clone)]
struct Active {
    area_cap: f64,
    area_ann: f64,
    stroke: f64,
    /// Offset of (p_cap, p_rod, x_rod) in the state vector.
    at: usize,
}

/// One idle cylinder: chambers at LP through the bypass, rod following the eye.
#[derive(Debug, Clone)]
struct Idle {
    area_cap: f64,
    area_ann: f64,
    stroke: f64,
}

impl Idle {
    /// Volume of both (bypassed) chambers with the rod at `x`, m³.
    fn volume_at(&self, dead: f64, x: f64) -> f64 {
        2.0 * dead + self.area_cap * x + self.area_ann * (self.stroke - x)
    }
}

/// Everything the model computes at one instant.
#[derive(Debug, Clone, Default)]
pub struct Eval {
    /// Shaft angle, rad.
    pub theta_rad: f64,
    /// Shaft speed, rad/s.
    pub theta_dot_rad_s: f64,
    /// Rod positions, m (eye position for idle cylinders).
    pub rod_m: [f64; N_CYL],
    /// Cap chamber pressures, Pa.
    pub p_cap_pa: [f64; N_CYL],
    /// Rod chamber pressures, Pa.
    pub p_rod_pa: [f64; N_CYL],
    /// Flow delivered into HP per cylinder, m³/s.
    pub q_into_hp_m3_s: [f64; N_CYL],
    /// Torque the input must supply per cylinder (restraining torque), N·m.
    pub torque_nm: [f64; N_CYL],
    /// HP pressure P2, Pa.
    pub p2_pa: f64,
    /// LP pressure, Pa.
    pub lp_pa: f64,
    /// Motor inlet pressure, Pa.
    pub p_motor_pa: f64,
    /// Control valve flow, m³/s.
    pub q_valve_m3_s: f64,
    /// Relief flow, m³/s.
    pub q_relief_m3_s: f64,
    /// Make-up flow, m³/s.
    pub q_makeup_m3_s: f64,
    /// Flow through the motor (inlet -> LP, incl. leakage), m³/s.
    pub q_motor_m3_s: f64,
    /// Motor speed, rad/s.
    pub omega_rad_s: f64,
    /// Spool aperture, %.
    pub aperture_pct: f64,
    /// Motor shaft torque, N·m.
    pub motor_torque_nm: f64,
    /// Load (generator) torque, N·m.
    pub load_torque_nm: f64,
    /// Integrand of the balance quadratures (see [`QUAD_NAMES`]), SI units per second.
    pub quad: [f64; N_QUAD],
    /// Stored mechanical spring energy in the hard stops, J.
    pub spring_energy_j: f64,
}

/// The shaft and every cylinder's eye (extension m, its rate m/s, arm m) at one instant: functions
/// of time alone, so the evaluations of one step (Newton iterations, Jacobian columns) share them.
#[derive(Debug, Clone, Copy)]
struct Kinematics {
    t: f64,
    theta: f64,
    theta_dot: f64,
    eye: [(f64, f64, f64); N_CYL],
}

/// One rod's mechanics at a state (SI units, the eye's force positive pushing the rod in).
#[derive(Debug, Clone, Copy)]
struct RodForces {
    p_cap: f64,
    p_rod: f64,
    x: f64,
    /// Eye position − rod position.
    gap: f64,
    v_eye: f64,
    arm: f64,
    /// Penetration of the free play's stop spring (0 with the stops as events).
    pen: f64,
    /// Penetration of an end stop.
    pen_end: f64,
    x_dot: f64,
    f_contact: f64,
}

impl RodForces {
    /// The rod's two contact roots in `contact`: free, both faces' gaps stay positive;
    /// engaged, the face's force keeps its sign.
    fn roots(&self, contact: Contact, half: f64) -> (f64, f64) {
        match contact {
            // A rod set on a face starts CONTACT_SLACK_M inside: the root is positive where it
            // starts, and its only sign change is the next contact.
            Contact::Free => (
                half + CONTACT_SLACK_M - self.gap,
                self.gap + half + CONTACT_SLACK_M,
            ),
            Contact::Push => (self.f_contact, 1.0),
            Contact::Pull => (-self.f_contact, 1.0),
        }
    }
}

/// How far past a face a free rod's contact root changes sign, m: the rod starts on the face
/// it left (a root of zero, or a rounding error below it, would be no sign change for the
/// solver's root finder, and a penetration past it would go unseen).
/// 1 µm: well above the rod position's solver tolerance (1e-9 m at the default settings, 1.5e-7 m
/// at the twin's rtol 1e-6), which a first step after a release may move it by; 2.5e-4 of the
/// free play.
pub const CONTACT_SLACK_M: f64 = 1e-6;

/// Where a rod stands in its free play when the stops are located events: free between its
/// faces (moved by its chambers' pressures against the seal friction) or engaged on one face,
/// moving with the lever's eye (no penetration, no spring).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Contact {
    /// Inside the free play.
    Free,
    /// On the face that pushes the rod out (gap = +half the free play).
    Push,
    /// On the face that pulls it in (gap = −half).
    Pull,
}

/// The plant: bench, cylinders on duty, geometry, input motion and the commanded aperture.
#[derive(Debug)]
pub struct Plant {
    bench: Bench,
    hp_acc: GasAccumulator,
    lp_acc: GasAccumulator,
    /// Every cylinder's lever, in bench order.
    levers: Vec<Lever>,
    /// The last instant's kinematics, when `reuse_kinematics` is on.
    kinematics: Cell<Option<Kinematics>>,
    /// Reuse the kinematics of the last evaluated instant and evaluate an irregular sea by its
    /// carrier (off: the reference path, which evaluates the motion and the levers at every call
    /// and a sea one component at a time).
    reuse_kinematics: Cell<bool>,
    active: Vec<Active>,
    active_index: Vec<usize>,
    idle: Vec<(usize, Idle)>,
    motion: Motion,
    fluid: Fluid,
    /// Commanded aperture, % (set by the valve schedule between solver segments).
    pub command_pct: Cell<f64>,
    /// The rods' free play as located contacts ([`Contact`], one per active cylinder) instead
    /// of the stiff stop spring: set by the solver for a run.
    contact_events: Cell<bool>,
    /// Each active cylinder's contact state while `contact_events` is on.
    contacts: Cell<[Contact; N_CYL]>,
    i_p2: usize,
    i_lp: usize,
    i_pm: usize,
    i_w: usize,
    i_a: Option<usize>,
    /// HP manifold pressure, when the HP line has a resistance.
    i_hm: Option<usize>,
    /// LP manifold pressure, when the LP line has a resistance.
    i_lm: Option<usize>,
    /// Oil volume of the HP manifold node (half the HP line), m³.
    vol_hm: f64,
    /// Line oil volume of the LP manifold node (half the LP->manifold line), m³.
    vol_lm: f64,
    n: usize,
}

impl Plant {
    /// Builds the plant for `on_duty` cylinders in geometry `config`.
    pub fn new(bench: &Bench, config: usize, on_duty: [bool; N_CYL], motion: Motion) -> Self {
        let geom = &bench.configs[config];
        let mut active = Vec::new();
        let mut active_index = Vec::new();
        let mut idle = Vec::new();
        for (i, c) in bench.cylinders.iter().enumerate() {
            if on_duty[i] {
                active.push(Active {
                    area_cap: c.area_cap_m2,
                    area_ann: c.area_ann_m2,
                    stroke: c.stroke_m,
                    at: 3 * active.len(),
                });
                active_index.push(i);
            } else {
                idle.push((
                    i,
                    Idle {
                        area_cap: c.area_cap_m2,
                        area_ann: c.area_ann_m2,
                        stroke: c.stroke_m,
                    },
                ));
            }
        }
        let base = 3 * active.len();
        let i_a = (bench.spool_tau_s > 0.0).then_some(base + 4);
        let mut next = base + 4 + usize::from(i_a.is_some());
        let mut take = |on: bool| {
            on.then(|| {
                next += 1;
                next - 1
            })
        };
        let i_hm = take(bench.hp_line_resistance_pa_s_per_m3 > 0.0);
        let i_lm = take(bench.lp_line_resistance_pa_s_per_m3 > 0.0);
        let levers = bench
            .cylinders
            .iter()
            .map(|c| Lever::new(geom, c.stroke_m, c.side))
            .collect();
        Plant {
            bench: bench.clone(),
            hp_acc: GasAccumulator::new(&bench.hp_acc),
            lp_acc: GasAccumulator::new(&bench.lp_acc),
            levers,
            kinematics: Cell::new(None),
            reuse_kinematics: Cell::new(true),
            active,
            active_index,
            idle,
            motion,
            fluid: Fluid::new(&bench.oil),
            command_pct: Cell::new(0.0),
            contact_events: Cell::new(false),
            contacts: Cell::new([Contact::Free; N_CYL]),
            i_p2: base,
            i_lp: base + 1,
            i_pm: base + 2,
            i_w: base + 3,
            n: next,
            i_a,
            i_hm,
            i_lm,
            vol_hm: if i_hm.is_some() {
                0.5 * bench.hp_line_volume_m3
            } else {
                0.0
            },
            vol_lm: if i_lm.is_some() {
                0.5 * bench.lp_manifold_line_volume_m3
            } else {
                0.0
            },
        }
    }

    /// Whether evaluations at the same instant share the motion and lever values (on by
    /// default; off reproduces the reference path that `pto perf` compares against).
    pub fn set_reuse_kinematics(&self, on: bool) {
        self.reuse_kinematics.set(on);
        self.kinematics.set(None);
    }

    fn kinematics(&self, t: f64) -> Kinematics {
        if self.reuse_kinematics.get()
            && let Some(k) = self.kinematics.get()
            && k.t == t
        {
            return k;
        }
        let (theta, theta_dot) = if self.reuse_kinematics.get() {
            self.motion.at(t)
        } else {
            self.motion.at_reference(t)
        };
        let mut eye = [(0.0, 0.0, 0.0); N_CYL];
        for (e, lever) in eye.iter_mut().zip(&self.levers) {
            *e = lever.eye(theta, theta_dot);
        }
        let k = Kinematics {
            t,
            theta,
            theta_dot,
            eye,
        };
        self.kinematics.set(Some(k));
        k
    }

    /// Number of states.
    pub fn len(&self) -> usize {
        self.n
    }

    /// True when there are no states (never: P2, LP, motor inlet and speed always exist).
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The bench.
    pub fn bench(&self) -> &Bench {
        &self.bench
    }

    /// The input motion.
    pub fn motion(&self) -> &Motion {
        &self.motion
    }

    /// Index of P2 (bar) in the state.
    pub fn p2_index(&self) -> usize {
        self.i_p2
    }

    /// Human-readable name of state `i` (for error messages).
    pub fn state_name(&self, i: usize) -> String {
        if i < self.i_p2 {
            let c = &self.bench.cylinders[self.active_index[i / 3]].name;
            return match i % 3 {
                0 => format!("{c} cap-chamber pressure (bar)"),
                1 => format!("{c} rod-chamber pressure (bar)"),
                _ => format!("{c} rod position (mm)"),
            };
        }
        match i - self.i_p2 {
            0 => "HP pressure P2 (bar)".into(),
            1 => "LP pressure (bar)".into(),
            2 => "motor inlet pressure (bar)".into(),
            3 => "motor speed (rad/s)".into(),
            _ if Some(i) == self.i_a => "spool aperture (%)".into(),
            _ if Some(i) == self.i_hm => "HP manifold pressure (bar)".into(),
            _ => "LP manifold pressure (bar)".into(),
        }
    }

    /// Per-state absolute tolerance in state units for a given scale factor.
    pub fn atol(&self, scale: f64) -> Vec<f64> {
        let mut a = vec![1e-3 * scale; self.n];
        // Pressures (bar), motor speed (rad/s), aperture (%): 1e-3; rod positions (mm): 1e-4.
        for c in &self.active {
            a[c.at + 2] = 1e-4 * scale;
        }
        a
    }

    /// Initial state: chambers at LP, rods touching their eyes' play centre, motor as given.
    pub fn initial_state(
        &self,
        p2: f64,
        lp: f64,
        p_motor: f64,
        omega: f64,
        aperture_pct: f64,
    ) -> Vec<f64> {
        let kin = self.kinematics(0.0);
        let mut y = vec![0.0; self.n];
        for (c, &ci) in self.active.iter().zip(&self.active_index) {
            let (x, _, _) = kin.eye[ci];
            y[c.at] = lp / BAR;
            y[c.at + 1] = lp / BAR;
            y[c.at + 2] = x * 1e3;
        }
        y[self.i_p2] = p2 / BAR;
        y[self.i_lp] = lp / BAR;
        y[self.i_pm] = p_motor / BAR;
        y[self.i_w] = omega;
        if let Some(i) = self.i_a {
            y[i] = aperture_pct;
        }
        if let Some(i) = self.i_hm {
            y[i] = p2 / BAR;
        }
        if let Some(i) = self.i_lm {
            y[i] = lp / BAR;
        }
        self.command_pct.set(aperture_pct);
        y
    }

    /// Number of contact root functions (two per active cylinder).
    pub fn contact_root_count(&self) -> usize {
        2 * self.active.len()
    }

    /// The contact root functions at (t, y): for a free rod the gaps to its two faces, for an
    /// engaged one the face's force (signed to be positive while it holds) and a constant 1.
    /// A sign change is a contact switch ([`Plant::switch_contact`]).
    pub fn contact_roots(&self, t: f64, y: &[f64], out: &mut [f64]) {
        // The rods' mechanics only: no flows, no fluid properties (the solver asks after every
        // step and in every root search).
        let kin = self.kinematics(t);
        let contacts = self.contacts.get();
        let half = 0.5 * self.bench.free_play_m;
        for j in 0..self.active.len() {
            (out[2 * j], out[2 * j + 1]) = self.rod(j, &kin, y).roots(contacts[j], half);
        }
    }

    /// Active cylinder `j`'s rod at state `y`: its chambers' pressures, its stops' penetrations,
    /// its speed and the eye's force on it (one formula for the right-hand side and the roots).
    fn rod(&self, j: usize, kin: &Kinematics, y: &[f64]) -> RodForces {
        let b = &self.bench;
        let c = &self.active[j];
        let half = 0.5 * b.free_play_m;
        let events = self.contact_events.get();
        let p_cap = y[c.at] * BAR;
        let p_rod = y[c.at + 1] * BAR;
        let x = y[c.at + 2] * 1e-3;
        let (x_eye, v_eye, arm) = kin.eye[self.active_index[j]];
        // Rod fixation: free play of width 2·half closed by a stiff, damped stop, or (events)
        // a rigid face the rod follows the eye on.
        let gap = x_eye - x;
        let engaged = events && self.contacts.get()[j] != Contact::Free;
        let pen = if events {
            0.0
        } else {
            physics::free_play_penetration(gap, half)
        };
        let pen_end = physics::end_stop_penetration(x, c.stroke);
        let f_hyd = p_cap * c.area_cap - p_rod * c.area_ann;
        let (x_dot, f_contact) =
            physics::RodStops::of(b).rod_motion(f_hyd, pen, pen_end, v_eye, engaged);
        RodForces {
            p_cap,
            p_rod,
            x,
            gap,
            v_eye,
            arm,
            pen,
            pen_end,
            x_dot,
            f_contact,
        }
    }

    /// Turns the located stops on or off, every rod free (a run's start: rods at their eyes).
    pub fn set_contact_events(&self, on: bool) {
        self.contact_events.set(on);
        self.contacts.set([Contact::Free; N_CYL]);
    }

    /// Whether the stops are located events.
    pub fn contact_events(&self) -> bool {
        self.contact_events.get()
    }

    /// The contact state of active cylinder `j`.
    pub fn contact(&self, j: usize) -> Contact {
        self.contacts.get()[j]
    }

    /// Switches the contact whose root `root` (of [`Plant::contact_roots`]) changed sign at
    /// (t, y): a free rod engages the face it reached, its position set on the face exactly; an
    /// engaged rod comes free. Returns the new state.
    pub fn switch_contact(&self, t: f64, y: &mut [f64], root: usize) -> Contact {
        let j = root / 2;
        let c = &self.active[j];
        let (x_eye, _, _) = self.kinematics(t).eye[self.active_index[j]];
        let half = 0.5 * self.bench.free_play_m;
        let mut contacts = self.contacts.get();
        // The rod set on the face exactly, engaging or leaving it: an engaged rod's position,
        // integrated from the eye's speed, drifts by the solver's error (1e-10 m), and a free
        // rod that starts a hair beyond the face it left would re-engage it at once.
        let (state, x) = match contacts[j] {
            Contact::Free if root.is_multiple_of(2) => (Contact::Push, x_eye - half),
            Contact::Free => (Contact::Pull, x_eye + half),
            Contact::Push => (Contact::Free, x_eye - half),
            Contact::Pull => (Contact::Free, x_eye + half),
        };
        y[c.at + 2] = x * 1e3;
        contacts[j] = state;
        self.contacts.set(contacts);
        contacts[j]
    }

    /// Switches every contact whose root is not positive at (t, y) — a free rod past a face
    /// (two rods crossing within one root search: the solver reports the first), an engaged
    /// one whose face pulls — until none is, at most `limit` switches. Returns the switches, or
    /// `None` when `limit` was not enough (a rod chattering on a face).
    pub fn settle_contacts(&self, t: f64, y: &mut [f64], limit: usize) -> Option<usize> {
        let mut r = vec![0.0; self.contact_root_count()];
        for n in 0..=limit {
            self.contact_roots(t, y, &mut r);
            match r.iter().position(|x| *x <= 0.0) {
                None => return Some(n),
                Some(_) if n == limit => return None,
                Some(i) => {
                    self.switch_contact(t, y, i);
                }
            }
        }
        None
    }

    /// Right-hand side in scaled units.
    pub fn rhs(&self, t: f64, y: &[f64], dy: &mut [f64]) {
        self.evaluate(t, y, Some(dy), false);
    }

    /// Evaluates the model; writes the scaled derivative when `dy` is given, and the balance
    /// integrands and spring energy (which need the fluid exergy, not used by the right-hand
    /// side) when `want_quad` is set.
    ///
    /// Flows are mass-consistent: an orifice passes `q` m³/s at its upstream density, i.e.
    /// `q/v(p_up)` m³/s of reference volume, and each node turns its net reference inflow into a
    /// pressure rate through its own v(p) and E(p).
    pub fn evaluate(&self, t: f64, y: &[f64], dy: Option<&mut [f64]>, want_quad: bool) -> Eval {
        let b = &self.bench;
        let oil = &b.oil;
        let fl = &self.fluid;
        let kin = self.kinematics(t);
        let (theta, theta_dot) = (kin.theta, kin.theta_dot);
        let p2 = y[self.i_p2] * BAR;
        let lp = y[self.i_lp] * BAR;
        let pm = y[self.i_pm] * BAR;
        let omega = y[self.i_w];
        let aperture_pct = match self.i_a {
            Some(i) => y[i].clamp(0.0, 100.0),
            None => self.command_pct.get(),
        };
        let (v_hp, e_hp, g_hp) = fl.state_exergy(p2, want_quad);
        let (v_lp, e_lp, g_lp) = fl.state_exergy(lp, want_quad);
        let (v_pm, e_pm, g_pm) = fl.state_exergy(pm, want_quad);
        // Manifold nodes: their own state behind a line resistance, else the accumulator node.
        let node = |idx: Option<usize>, p: f64, v: f64, e: f64, g: f64| match idx {
            Some(i) => {
                let pi = y[i] * BAR;
                let (vi, ei, gi) = fl.state_exergy(pi, want_quad);
                (pi, vi, ei, gi)
            }
            None => (p, v, e, g),
        };
        let (p_hm, v_hm, e_hm, g_hm) = node(self.i_hm, p2, v_hp, e_hp, g_hp);
        let (p_lm, v_lm, e_lm, g_lm) = node(self.i_lm, lp, v_lp, e_lp, g_lp);
        // Reference-volume flow of an orifice flow q from a node with v_a to one with v_b.
        let mref = |q: f64, va: f64, vb: f64| if q >= 0.0 { q / va } else { q / vb };
        let mut e = Eval {
            theta_rad: theta,
            theta_dot_rad_s: theta_dot,
            p2_pa: p2,
            lp_pa: lp,
            p_motor_pa: pm,
            omega_rad_s: omega,
            aperture_pct,
            ..Eval::default()
        };
        let physics::RodStops { k, d, c_seal } = physics::RodStops::of(b);
        let mut m_into_hp = 0.0;
        let mut m_from_lp = 0.0;
        let mut dy = dy;
        for (j, c) in self.active.iter().enumerate() {
            let ci = self.active_index[j];
            let RodForces {
                p_cap,
                p_rod,
                x,
                v_eye,
                arm,
                pen,
                pen_end,
                x_dot,
                f_contact,
                ..
            } = self.rod(j, &kin, y);
            let (contact, end) = (pen != 0.0, pen_end != 0.0);
            let (v_cap, e_cap, g_cap) = fl.state_exergy(p_cap, want_quad);
            let (v_rod, e_rod, g_rod) = fl.state_exergy(p_rod, want_quad);
            let vol_cap = b.chamber_dead_volume_m3 + c.area_cap * x;
            let vol_rod = b.chamber_dead_volume_m3 + c.area_ann * (c.stroke - x);
            let suc_cap = mref(check_flow(oil, &b.check, p_lm - p_cap), v_lm, v_cap);
            let del_cap = mref(check_flow(oil, &b.check, p_cap - p_hm), v_cap, v_hm);
            let suc_rod = mref(check_flow(oil, &b.check, p_lm - p_rod), v_lm, v_rod);
            let del_rod = mref(check_flow(oil, &b.check, p_rod - p_hm), v_rod, v_hm);
            if let Some(dy) = dy.as_deref_mut() {
                let vdot_cap = c.area_cap * x_dot;
                let vdot_rod = -c.area_ann * x_dot;
                dy[c.at] = physics::chamber_pressure_rate(
                    e_cap,
                    vol_cap,
                    v_cap,
                    suc_cap - del_cap,
                    vdot_cap,
                ) / BAR;
                dy[c.at + 1] = physics::chamber_pressure_rate(
                    e_rod,
                    vol_rod,
                    v_rod,
                    suc_rod - del_rod,
                    vdot_rod,
                ) / BAR;
                dy[c.at + 2] = x_dot * 1e3;
            }
            m_into_hp += del_cap + del_rod;
            m_from_lp += suc_cap + suc_rod;
            e.rod_m[ci] = x;
            e.p_cap_pa[ci] = p_cap;
            e.p_rod_pa[ci] = p_rod;
            e.q_into_hp_m3_s[ci] = (del_cap + del_rod) * v_hm;
            e.torque_nm[ci] = self.levers[ci].side() * arm * f_contact;
            e.quad[quad::INPUT] += f_contact * v_eye;
            if want_quad {
                let v_rel = v_eye - x_dot;
                e.quad[quad::MECHANICAL] += c_seal * x_dot * x_dot
                    + if contact { d * v_rel * v_rel } else { 0.0 }
                    + if end { d * x_dot * x_dot } else { 0.0 };
                e.quad[quad::CHECK_VALVES] += suc_cap * (g_lm - g_cap)
                    + del_cap * (g_cap - g_hm)
                    + suc_rod * (g_lm - g_rod)
                    + del_rod * (g_rod - g_hm);
                e.quad[quad::PUMPED] += (del_cap + del_rod) * g_hm - (suc_cap + suc_rod) * g_lm;
                e.spring_energy_j += 0.5 * k * (pen * pen + pen_end * pen_end);
            }
        }
        // Idle cylinders: chambers bypassed to LP, so they are part of the LP node's volume; the
        // rods follow their eyes and LP·A_rod pushes them out against the lever.
        let mut idle_volume = 0.0;
        let mut idle_vdot = 0.0;
        for (ci, c) in &self.idle {
            let (x_eye, v_eye, arm) = kin.eye[*ci];
            let area_rod = c.area_cap - c.area_ann;
            let f_contact = -p_lm * area_rod;
            idle_volume += c.volume_at(b.chamber_dead_volume_m3, x_eye);
            idle_vdot += area_rod * v_eye;
            e.rod_m[*ci] = x_eye;
            e.p_cap_pa[*ci] = p_lm;
            e.p_rod_pa[*ci] = p_lm;
            e.torque_nm[*ci] = self.levers[*ci].side() * arm * f_contact;
            e.quad[quad::INPUT] += f_contact * v_eye;
        }
        let q_valve = physics::valve_flow(b, aperture_pct, p2 - pm);
        let q_relief = physics::relief_flow(b, p2, lp);
        let q_makeup = check_flow(oil, &b.makeup, lp - pm);
        let dp_motor = pm - lp;
        let q_motor = physics::motor_flow(b, omega, dp_motor);
        let m_valve = mref(q_valve, v_hp, v_pm);
        let m_relief = mref(q_relief, v_hp, v_lp);
        let m_makeup = mref(q_makeup, v_lp, v_pm);
        let m_motor = mref(q_motor, v_pm, v_lp);
        let t_load = physics::load_torque(b, omega);
        let t_motor = physics::motor_torque(b, dp_motor);
        // Line flows manifold <-> accumulator (pass-through when lumped).
        let m_hline = match self.i_hm {
            Some(_) => mref((p_hm - p2) / b.hp_line_resistance_pa_s_per_m3, v_hm, v_hp),
            None => m_into_hp,
        };
        let m_lline = match self.i_lm {
            Some(_) => mref((lp - p_lm) / b.lp_line_resistance_pa_s_per_m3, v_lp, v_lm),
            None => m_from_lp,
        };
        if let Some(dy) = dy {
            let (acc_hp, cap_hp) = self.hp_acc.fluid(p2);
            let (acc_lp, cap_lp) = self.lp_acc.fluid(lp);
            let [oil_hp, oil_lp] = self.accumulator_node_oil(acc_hp, acc_lp, idle_volume);
            let c_hp = cap_hp + oil_hp / e_hp;
            let c_lp = cap_lp + oil_lp / e_lp;
            let c_pm = b.motor_line_volume_m3 / e_pm;
            dy[self.i_p2] = v_hp * (m_hline - m_valve - m_relief) / c_hp / BAR;
            let idle_at_lp = if self.i_lm.is_some() { 0.0 } else { idle_vdot };
            dy[self.i_lp] =
                (v_lp * (m_motor + m_relief - m_lline - m_makeup) - idle_at_lp) / c_lp / BAR;
            if let Some(i) = self.i_hm {
                dy[i] = e_hm / self.vol_hm * v_hm * (m_into_hp - m_hline) / BAR;
            }
            if let Some(i) = self.i_lm {
                let vol = self.vol_lm + idle_volume;
                dy[i] = e_lm / vol * (v_lm * (m_lline - m_from_lp) - idle_vdot) / BAR;
            }
            dy[self.i_pm] = v_pm * (m_valve + m_makeup - m_motor) / c_pm / BAR;
            dy[self.i_w] = (t_motor - t_load) / b.motor_inertia_kg_m2;
            if let Some(i) = self.i_a {
                dy[i] = (self.command_pct.get() - y[i]) / b.spool_tau_s;
            }
        }
        e.q_valve_m3_s = q_valve;
        e.q_relief_m3_s = q_relief;
        e.q_makeup_m3_s = q_makeup;
        e.q_motor_m3_s = q_motor;
        e.motor_torque_nm = t_motor;
        e.load_torque_nm = t_load;
        e.quad[quad::INTO_HP] = m_into_hp;
        e.quad[quad::VALVE_FLOW] = m_valve;
        e.quad[quad::RELIEF_FLOW] = m_relief;
        e.quad[quad::MAKEUP_FLOW] = m_makeup;
        e.quad[quad::MOTOR_FLOW] = m_motor;
        e.quad[quad::LP_TO_CHAMBERS] = m_from_lp;
        if want_quad {
            e.quad[quad::CHECK_VALVES] += m_makeup * (g_lp - g_pm);
            e.quad[quad::CONTROL_VALVE] = m_valve * (g_hp - g_pm);
            e.quad[quad::RELIEF] = m_relief * (g_hp - g_lp);
            // The motor's exergy drop split between its leakage and its displacement flow (both
            // at the density `mref` took for the whole flow); the displacement share not turned
            // into shaft work is friction.
            let density = if q_motor >= 0.0 { v_pm } else { v_lp };
            let m_leak = b.motor_leak_m3_per_s_pa * dp_motor / density;
            e.quad[quad::MOTOR_LEAKAGE] = m_leak * (g_pm - g_lp);
            e.quad[quad::MOTOR_FRICTION] = (m_motor - m_leak) * (g_pm - g_lp) - t_motor * omega;
            e.quad[quad::MOTOR_SHAFT] = t_motor * omega;
            e.quad[quad::GENERATOR] = t_load * omega;
            e.quad[quad::LINES] = m_hline * (g_hm - g_hp) + m_lline * (g_lp - g_lm);
        }
        e
    }

    /// Balance integrands scaled to litres (of reference volume) and kJ per second (the
    /// diffsol output function).
    pub fn quadrature(&self, t: f64, y: &[f64], out: &mut [f64]) {
        let e = self.evaluate(t, y, None, true);
        for (i, (o, q)) in out.iter_mut().zip(e.quad).enumerate() {
            *o = if i < 6 { q * 1e3 } else { q * 1e-3 };
        }
    }

    /// Oil volume of the HP and LP accumulator nodes (line share + the accumulators' oil
    /// `acc_hp`, `acc_lp`, plus the idle chambers when they are not behind an LP line
    /// resistance), m³.
    fn accumulator_node_oil(&self, acc_hp: f64, acc_lp: f64, idle_volume: f64) -> [f64; 2] {
        let b = &self.bench;
        let idle = if self.i_lm.is_some() {
            0.0
        } else {
            idle_volume
        };
        [
            b.hp_line_volume_m3 - self.vol_hm + acc_hp,
            b.lp_line_volume_m3 - self.vol_lm + acc_lp + idle,
        ]
    }

    /// Oil content (m³ of reference volume) and stored energy at time `t` and state `y`:
    /// `[HP side, motor inlet, LP side (with idle chambers), active chambers]`, a side being
    /// its accumulator node plus its manifold node when the line has a resistance. Energy: the
    /// gas of both accumulators, the oil's compression, the motor inertia and the hard-stop
    /// springs.
    pub fn storage(&self, t: f64, y: &[f64]) -> ([f64; 4], Stored) {
        let b = &self.bench;
        let fl = &self.fluid;
        let (p2, lp, pm) = (y[self.i_p2] * BAR, y[self.i_lp] * BAR, y[self.i_pm] * BAR);
        let kin = self.kinematics(t);
        let idle: f64 = self
            .idle
            .iter()
            .map(|(ci, c)| c.volume_at(b.chamber_dead_volume_m3, kin.eye[*ci].0))
            .sum();
        let [oil_hp, oil_lp] = self.accumulator_node_oil(
            self.hp_acc.fluid_volume(p2),
            self.lp_acc.fluid_volume(lp),
            idle,
        );
        // (side, oil volume, pressure)
        let mut nodes = vec![
            (0, oil_hp, p2),
            (1, b.motor_line_volume_m3, pm),
            (2, oil_lp, lp),
        ];
        if let Some(i) = self.i_hm {
            nodes.push((0, self.vol_hm, y[i] * BAR));
        }
        if let Some(i) = self.i_lm {
            nodes.push((2, self.vol_lm + idle, y[i] * BAR));
        }
        let mut content = [0.0; 4];
        let mut energy = Stored {
            gas_j: self.hp_acc.stored_energy(p2) + self.lp_acc.stored_energy(lp),
            ..Stored::default()
        };
        for (side, vol, p) in nodes {
            content[side] += vol / fl.volume_ratio(p);
            energy.oil_j += fl.stored_energy(vol, p);
        }
        for c in &self.active {
            let x = y[c.at + 2] * 1e-3;
            for (vol, pc) in [
                (b.chamber_dead_volume_m3 + c.area_cap * x, y[c.at] * BAR),
                (
                    b.chamber_dead_volume_m3 + c.area_ann * (c.stroke - x),
                    y[c.at + 1] * BAR,
                ),
            ] {
                content[3] += vol / fl.volume_ratio(pc);
                energy.oil_j += fl.stored_energy(vol, pc);
            }
        }
        energy.inertia_j = 0.5 * b.motor_inertia_kg_m2 * y[self.i_w].powi(2);
        energy.stops_j = self.evaluate(t, y, None, true).spring_energy_j;
        (content, energy)
    }

    /// Checks that a state is physical: finite, and every pressure above vacuum.
    pub fn check_state(&self, y: &[f64]) -> Result<(), (usize, f64)> {
        for (i, v) in y.iter().enumerate() {
            if !v.is_finite() {
                return Err((i, *v));
            }
        }
        let pressure_idx = self
            .active
            .iter()
            .flat_map(|c| [c.at, c.at + 1])
            .chain([self.i_p2, self.i_lp, self.i_pm])
            .chain(self.i_hm)
            .chain(self.i_lm);
        for i in pressure_idx {
            if y[i] * BAR <= -crate::sim::bench::P_ATM {
                return Err((i, y[i]));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plant() -> Plant {
        let b = Bench::reference();
        Plant::new(&b, 0, [true, false, false, true], Motion::Blocked(0.0))
    }

    /// A free rod's roots are both positive; pushed past a face by more than the slack the
    /// face's root is negative; switched, the rod sits on the face and its root is the face's
    /// force, positive while it holds; released, it is free on the face with both roots
    /// positive again (no sign change left to re-engage it at once).
    #[test]
    fn a_contact_engages_on_its_face_and_leaves_it_free() {
        let p = plant();
        p.set_contact_events(true);
        let mut y = p.initial_state(60.0 * BAR, 8.0 * BAR, 8.0 * BAR, 0.0, 0.0);
        let mut r = vec![0.0; p.contact_root_count()];
        p.contact_roots(0.0, &y, &mut r);
        assert!(r.iter().all(|x| *x > 0.0), "{r:?}");
        // HC3.1's rod 2.1 mm behind its eye (half the free play is 2 mm): past the push face.
        let half_mm = 0.5 * p.bench().free_play_m * 1e3;
        let x_eye_mm = y[2];
        y[2] = x_eye_mm - half_mm - 0.1;
        p.contact_roots(0.0, &y, &mut r);
        assert!(r[0] < 0.0 && r[1] > 0.0, "{r:?}");
        assert_eq!(p.switch_contact(0.0, &mut y, 0), Contact::Push);
        assert!((y[2] - (x_eye_mm - half_mm)).abs() < 1e-9);
        // Engaged: the first root is the face's force, the second a constant.
        p.contact_roots(0.0, &y, &mut r);
        assert_eq!(r[1], 1.0);
        assert_eq!(p.switch_contact(0.0, &mut y, 0), Contact::Free);
        p.contact_roots(0.0, &y, &mut r);
        assert!(r.iter().all(|x| *x > 0.0), "{r:?}");
        assert!((r[0] - CONTACT_SLACK_M).abs() < 1e-15, "{r:?}");
        assert_eq!(p.contact(1), Contact::Free);
    }

    /// Two rods past their faces at once (the solver reports one root a search): settling
    /// engages both, then releases the one whose face would have to pull — the lever is still
    /// and LP on the cap's larger area pushes each rod out (+x), which the pull face holds and
    /// the push face cannot — and a settled state has every root positive.
    #[test]
    fn contacts_crossed_together_are_all_settled() {
        let p = plant();
        p.set_contact_events(true);
        let mut y = p.initial_state(60.0 * BAR, 8.0 * BAR, 8.0 * BAR, 0.0, 0.0);
        let half_mm = 0.5 * p.bench().free_play_m * 1e3;
        // HC3.1 past its push face, HC3.4 (the second active rod) past its pull face.
        y[2] -= half_mm + 0.05;
        y[5] += half_mm + 0.05;
        assert_eq!(p.settle_contacts(0.0, &mut y, 16), Some(3));
        assert_eq!((p.contact(0), p.contact(1)), (Contact::Free, Contact::Pull));
        let mut r = vec![0.0; p.contact_root_count()];
        p.contact_roots(0.0, &y, &mut r);
        assert!(r.iter().all(|x| *x > 0.0), "{r:?}");
        assert_eq!(p.settle_contacts(0.0, &mut y, 0), Some(0));
    }

    #[test]
    fn non_physical_states_are_named() {
        let p = plant();
        let mut y = p.initial_state(100.0 * BAR, 8.0 * BAR, 8.0 * BAR, 0.0, 0.0);
        assert!(p.check_state(&y).is_ok());
        y[4] = -1.5; // HC3.4 rod-chamber pressure below vacuum (bar gauge)
        let (i, v) = p.check_state(&y).unwrap_err();
        assert_eq!(
            (p.state_name(i).as_str(), v),
            ("HC3.4 rod-chamber pressure (bar)", -1.5)
        );
        y[4] = 8.0;
        y[p.p2_index()] = f64::NAN;
        let (i, _) = p.check_state(&y).unwrap_err();
        assert_eq!(p.state_name(i), "HP pressure P2 (bar)");
    }
}
