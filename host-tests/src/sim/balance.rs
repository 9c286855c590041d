//! A run's oil-volume and energy balance: each node's oil and the whole circuit's, the energy
//! in against the losses and what was stored.

use crate::sim::plant::{Plant, QUAD_NAMES, Stored, quad};
use serde::Serialize;

/// Oil-volume and energy balance of a run.
#[derive(Debug, Clone, Serialize)]
pub struct Balance {
    /// Integrated flows (L) and energies (kJ), named by [`QUAD_NAMES`].
    pub integrals: Vec<(String, f64)>,
    /// Relative oil (mass) balance error per node (HP, motor inlet, LP, chambers) and of the
    /// whole closed circuit.
    pub volume_rel_error: [f64; 5],
    /// Relative energy error of the whole circuit.
    pub energy_rel_error: f64,
    /// Energy into storage (oil, accumulator gas, motor inertia, hard stops), kJ.
    pub stored_kj: f64,
    /// That change by where it is stored, J.
    pub stored: Stored,
}

impl Balance {
    /// An integrated term by its index in [`QUAD_NAMES`] (L or kJ).
    pub fn integral(&self, i: usize) -> f64 {
        self.integrals[i].1
    }
}

impl Balance {
    /// Worst of the volume and energy relative errors.
    pub fn worst(&self) -> f64 {
        self.volume_rel_error
            .iter()
            .copied()
            .fold(self.energy_rel_error, f64::max)
    }
}

pub(crate) fn balances(
    plant: &Plant,
    (t0, y0): (f64, &[f64]),
    (t1, y1): (f64, &[f64]),
    g: &[f64],
) -> Balance {
    let (m0, e0) = plant.storage(t0, y0);
    let (m1, e1) = plant.storage(t1, y1);
    let q = |i: usize| g[i] * 1e-3; // L -> m³ of reference volume
    let w = |i: usize| g[i] * 1e3; // kJ -> J
    // Oil (mass, as reference volume) per node: Δcontent = ∫ inflow − ∫ outflow.
    let (into_hp, valve, relief) = (q(quad::INTO_HP), q(quad::VALVE_FLOW), q(quad::RELIEF_FLOW));
    let (makeup, motor, to_chambers) = (
        q(quad::MAKEUP_FLOW),
        q(quad::MOTOR_FLOW),
        q(quad::LP_TO_CHAMBERS),
    );
    // In and out of the HP side, the motor inlet, the LP side, the chambers.
    let flows = [
        (into_hp, valve + relief),
        (valve + makeup, motor),
        (motor + relief, makeup + to_chambers),
        (to_chambers, into_hp),
    ];
    // Each node's error is relative to its own throughput plus 0.1 % of all the oil that moved
    // (a node that barely moves, like the chambers of a blocked run, is not judged on noise).
    let moved: f64 = (0..6).map(|i| q(i).abs()).sum();
    let mut volume_rel_error = [0.0; 5];
    for k in 0..4 {
        let (inflow, outflow) = flows[k];
        let dm = m1[k] - m0[k];
        let scale = inflow.abs() + outflow.abs() + dm.abs() + 1e-3 * moved;
        volume_rel_error[k] = if scale > 0.0 {
            (dm - (inflow - outflow)).abs() / scale
        } else {
            0.0
        };
    }
    // The circuit is closed: total oil is constant (a check on the solver alone).
    // Normalised by the oil that moved (or, in a run where nothing moved, by the oil present).
    let total = m1.iter().sum::<f64>() - m0.iter().sum::<f64>();
    let scale = if moved > 0.0 { moved } else { m0.iter().sum() };
    volume_rel_error[4] = total.abs() / scale;
    let stored_by = e1.since(&e0);
    let stored = stored_by.total();
    let losses: f64 = quad::OUT.iter().map(|&i| w(i)).sum();
    let input = w(quad::INPUT);
    let resid = input - losses - stored;
    let scale = input.abs() + losses.abs() + stored.abs();
    Balance {
        integrals: QUAD_NAMES
            .iter()
            .zip(g)
            .map(|(n, v)| (n.to_string(), *v))
            .collect(),
        volume_rel_error,
        energy_rel_error: if scale > 0.0 {
            resid.abs() / scale
        } else {
            0.0
        },
        stored_kj: stored * 1e-3,
        stored: stored_by,
    }
}
