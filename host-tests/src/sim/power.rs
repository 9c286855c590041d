//! Power and efficiency of a run, from the energy balance's own terms.
//!
//! Every figure is an integral of the balance (`Balance::integrals`) or its change of stored
//! energy, divided by the run's length: the mean input equals the mean losses plus the
//! generator's power plus the rate of storage, to the balance's own error (≤ 1e-4 of the
//! throughput, [`Power::closure_rel`]).

use crate::sim::balance::Balance;
use crate::sim::plant::{Stored, quad};
use serde::Serialize;

/// Mean dissipation by cause over a run, W.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Losses {
    /// Seal friction and the free-play and end-stop dampers of the cylinders.
    pub mechanical_w: f64,
    /// The cylinders' check valves and the make-up check valve.
    pub check_valves_w: f64,
    /// Throttling in the control valve.
    pub control_valve_w: f64,
    /// The relief valve.
    pub relief_w: f64,
    /// The motor's internal leakage.
    pub motor_leakage_w: f64,
    /// The motor's friction (its mechanical efficiency).
    pub motor_friction_w: f64,
    /// The HP and LP line resistances.
    pub lines_w: f64,
}

impl Losses {
    /// All of them, W.
    pub fn total_w(&self) -> f64 {
        self.mechanical_w
            + self.check_valves_w
            + self.control_valve_w
            + self.relief_w
            + self.motor_leakage_w
            + self.motor_friction_w
            + self.lines_w
    }

    /// (label, W) in the order of the path from the shaft to the generator.
    pub fn by_cause(&self) -> [(&'static str, f64); 7] {
        [
            ("cylinders (friction, stops)", self.mechanical_w),
            ("check valves", self.check_valves_w),
            ("lines", self.lines_w),
            ("relief valve", self.relief_w),
            ("control valve", self.control_valve_w),
            ("motor leakage", self.motor_leakage_w),
            ("motor friction", self.motor_friction_w),
        ]
    }
}

/// Mean powers of a run, W (means over its length).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Power {
    /// Length of the run, s.
    pub duration_s: f64,
    /// Mechanical input at the shaft (the lever's work on the cylinders).
    pub input_w: f64,
    /// Hydraulic power pumped: the exergy the active cylinders deliver into HP minus what they
    /// draw from LP.
    pub pumped_w: f64,
    /// Rate of change of the stored energy (positive: the run ended with more stored).
    pub stored_w: StoredPower,
    /// Dissipation by cause.
    pub losses: Losses,
    /// The motor's shaft power.
    pub motor_shaft_w: f64,
    /// Power into the load (the generator).
    pub generator_w: f64,
    /// The PTO's efficiency: generator / energy supplied, the supply being the shaft input
    /// plus what the run drew from storage (a discharge's accumulators count as a source, so
    /// the figure stays within 0…1; None when nothing was supplied).
    pub efficiency: Option<f64>,
    /// Share of the supply not dissipated: (generator + what the run stored) / supplied. It
    /// differs from the efficiency by the energy a charging run left in the accumulators.
    pub efficiency_with_storage: Option<f64>,
    /// |input − losses − generator − stored| / (input + losses + generator + |stored|).
    pub closure_rel: f64,
}

/// Rate of change of the stored energy by where it is stored, W.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct StoredPower {
    /// The accumulators' gas.
    pub accumulators_w: f64,
    /// The oil's compression.
    pub oil_w: f64,
    /// The motor's inertia.
    pub inertia_w: f64,
    /// The hard stops' springs.
    pub stops_w: f64,
}

impl StoredPower {
    /// All of it, W.
    pub fn total_w(&self) -> f64 {
        self.accumulators_w + self.oil_w + self.inertia_w + self.stops_w
    }
}

impl Power {
    /// The mean powers of a run of `duration_s` seconds with this balance.
    pub fn of(balance: &Balance, duration_s: f64) -> Power {
        let per_s = if duration_s > 0.0 {
            1.0 / duration_s
        } else {
            0.0
        };
        // kJ over the run -> W.
        let w = |i: usize| balance.integral(i) * 1e3 * per_s;
        let s: &Stored = &balance.stored;
        let stored_w = StoredPower {
            accumulators_w: s.gas_j * per_s,
            oil_w: s.oil_j * per_s,
            inertia_w: s.inertia_j * per_s,
            stops_w: s.stops_j * per_s,
        };
        let losses = Losses {
            mechanical_w: w(quad::MECHANICAL),
            check_valves_w: w(quad::CHECK_VALVES),
            control_valve_w: w(quad::CONTROL_VALVE),
            relief_w: w(quad::RELIEF),
            motor_leakage_w: w(quad::MOTOR_LEAKAGE),
            motor_friction_w: w(quad::MOTOR_FRICTION),
            lines_w: w(quad::LINES),
        };
        let input_w = w(quad::INPUT);
        let generator_w = w(quad::GENERATOR);
        let stored = stored_w.total_w();
        let resid = input_w - losses.total_w() - generator_w - stored;
        let scale = input_w.abs() + losses.total_w().abs() + generator_w.abs() + stored.abs();
        let supplied = input_w + (-stored).max(0.0);
        let ratio = |x: f64| (supplied > 0.0).then(|| x / supplied);
        Power {
            duration_s,
            input_w,
            pumped_w: w(quad::PUMPED),
            stored_w,
            losses,
            motor_shaft_w: w(quad::MOTOR_SHAFT),
            generator_w,
            efficiency: ratio(generator_w),
            efficiency_with_storage: ratio(generator_w + stored.max(0.0)),
            closure_rel: if scale > 0.0 {
                resid.abs() / scale
            } else {
                0.0
            },
        }
    }
}

/// An efficiency as printed in summaries and figures: "37.2 %", or "-" when it is undefined
/// (nothing was supplied).
pub fn percent_text(efficiency: Option<f64>) -> String {
    efficiency.map_or("-".into(), |e| format!("{:.1} %", 100.0 * e))
}

#[cfg(test)]
mod tests {
    use super::Power;
    use crate::sim::bench::Bench;
    use crate::sim::scenario;
    use crate::sim::solver::SolverOptions;

    /// The powers of built-in scenario `name` cut to `duration_s`.
    fn power_of(name: &str, duration_s: f64) -> Power {
        let mut s = scenario::builtin_named(name).expect("built-in");
        s.duration_s = duration_s;
        let (_, r) = s
            .simulate(
                &Bench::reference(),
                std::path::Path::new("."),
                SolverOptions::default(),
                None,
            )
            .expect("runs");
        r.power
    }

    #[test]
    fn powers_close_and_follow_the_path_from_shaft_to_generator() {
        // Test III at 10 %, shortened: the valve opens at 100 bar after ≈ 155 s, so 200 s holds
        // both the charging and the motor running.
        let p = power_of("test3-ap10", 200.0);
        println!("{p:#?}");
        assert!(p.closure_rel <= 1e-4, "closure {:e}", p.closure_rel);
        // The path: input > pumped > motor shaft > generator > 0, each step losing its causes.
        assert!(
            p.input_w > p.pumped_w && p.pumped_w > p.motor_shaft_w,
            "{p:?}"
        );
        assert!(
            p.motor_shaft_w >= p.generator_w && p.generator_w > 0.0,
            "{p:?}"
        );
        // The input minus the cylinders' own losses and their chambers' storage is what they
        // pump, to the same closure (the chambers store little over a whole run).
        let upstream = p.losses.mechanical_w + p.losses.check_valves_w;
        let rel = (p.input_w - upstream - p.pumped_w).abs() / p.input_w;
        println!("input − cylinder losses − pumped: {rel:.2e} of the input");
        assert!(rel < 2e-3, "{rel:e}");
        let eff = p.efficiency.expect("positive input");
        assert!(eff > 0.0 && eff < 1.0, "{eff}");
    }

    #[test]
    fn a_discharge_counts_its_accumulators_as_the_supply() {
        // Blocked input from 102 bar at 10 %: no shaft input, the accumulator drives the motor.
        let p = power_of("blocked-ap10", 100.0);
        let eff = p.efficiency.expect("the accumulator supplied energy");
        let with = p.efficiency_with_storage.expect("same supply");
        println!(
            "input {:.2} W, stored {:.2} W, generator {:.2} W: efficiency {:.1} %",
            p.input_w,
            p.stored_w.total_w(),
            p.generator_w,
            eff * 100.0
        );
        assert!(p.stored_w.total_w() < 0.0 && p.input_w.abs() < 0.01 * p.generator_w);
        assert!(
            eff > 0.0 && eff < 1.0 && (with - eff).abs() < 1e-12,
            "{eff} {with}"
        );
        assert!(p.closure_rel <= 1e-4);
    }
}
