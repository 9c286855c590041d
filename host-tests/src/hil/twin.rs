//! The twin's plant for a campaign (`pto twin --campaign`): the full simulation follows the
//! campaign's segments in order while `pto link campaign run` drives the firmware over the bench
//! link, so a whole campaign runs unattended under QEMU.
//!
//! The twin plays the operator at the rack drive. It learns where the runner is from the one
//! thing a plant sees of the controller, the solenoids it energises: between segments the runner
//! de-energises every cylinder (the safe state while the operator changes the set-up), and the
//! twin holds the lever still; when the runner energises segment i's cylinders, the twin's
//! operator starts segment i's motion [`OPERATOR_START_S`] later, as one does after the runner's
//! prompt; when the runner de-energises them again, segment i is over. The plant is one physical
//! history: each phase starts from the pressures the last one ended at.

use crate::hil::pil::{FirmwareController, Injection, PilError};
use crate::hil::qemu::Qemu;
use crate::plan::{Campaign, Segment};
use crate::sim::bench::{BAR, Bench};
use crate::sim::motion::MotionSpec;
use crate::sim::plant::Plant;
use crate::sim::scenario::{Prepared, ScenarioError};
use crate::sim::schedule::ValveSchedule;
use crate::sim::solver::{self, Initial, Run, SimError, SolverOptions};
use crate::validation::duty_mask;
use crate::validation::sensors::SensorSpec;
use std::path::Path;

/// Longest the twin waits, in simulated time, for the runner to energise a segment's cylinders
/// (the runner's own waits are shorter), s.
pub const IDLE_MAX_S: f64 = 900.0;
/// Longest a segment's motion runs past its planned length before the twin gives up on the
/// runner de-energising the cylinders (its motion check, pressure preparation and log), s.
pub const SEGMENT_SLACK_S: f64 = 900.0;

/// How long after the runner energises a segment's cylinders the twin's operator starts the
/// lever, s of simulated time. The runner's log opens at the first frame with the cylinders
/// energised, which comes up to a frame after the change: a lever started with the solenoids
/// would have moved (and compressed the chambers) before the log's first row, where the fit's
/// simulation starts the chambers at LP. That biased the twin's trapped air by −0.0012
/// (1.3 %, 4–6σ): a synthetic log without its first row fits the same.
pub const OPERATOR_START_S: f64 = 1.0;

/// Why the twin's campaign stopped.
#[derive(Debug, thiserror::Error)]
pub enum TwinError {
    /// The firmware session failed.
    #[error(transparent)]
    Pil(#[from] PilError),
    /// A segment's run does not prepare on the twin's bench.
    #[error("segment {index}: {source}")]
    Segment {
        /// The segment.
        index: usize,
        /// Why.
        source: ScenarioError,
    },
    /// The simulation failed.
    #[error("segment {index}: {source}")]
    Simulation {
        /// The segment.
        index: usize,
        /// Why.
        source: SimError,
    },
    /// The runner did not move on within the twin's patience.
    #[error(
        "segment {index} ({name}): the controller did not {what} within {limit_s} s of simulated time (is `pto link campaign run` running on the bench link?)"
    )]
    Stalled {
        /// The segment.
        index: usize,
        /// Its name.
        name: String,
        /// What was awaited.
        what: &'static str,
        /// The limit, s.
        limit_s: f64,
    },
}

/// What the twin's plant did in one phase.
#[derive(Debug, Clone)]
pub struct Phase {
    /// The segment.
    pub index: usize,
    /// Whether the lever moved (the segment's motion) or was held (between segments).
    pub moving: bool,
    /// Simulated time, s.
    pub duration_s: f64,
    /// P2 at its end, bar.
    pub p2_end_bar: f64,
}

/// Runs the campaign's plant on `bench` against the firmware in `q` from P2 `p2_start_bar`
/// (LP 8 bar), telling `say` each phase; returns the firmware and the phases.
pub fn run_campaign(
    q: Qemu,
    bench: &Bench,
    campaign: &Campaign,
    p2_start_bar: f64,
    spec: SensorSpec,
    mut say: impl FnMut(&str),
) -> Result<(Qemu, Vec<Phase>), TwinError> {
    let dt_log2 = pto_model::ModelConfig::reference().dt_log2;
    let mut ctrl = FirmwareController::new(q, dt_log2, spec, 23, Box::new(|_| Injection::None))?;
    ctrl.keep_rows(false);
    let mut state = Initial {
        p2_pa: p2_start_bar * BAR,
        lp_pa: crate::validation::closed_loop::LOOP_LP_START_BAR * BAR,
    };
    let mut phases = Vec::new();
    for (index, seg) in campaign.segment.iter().enumerate() {
        let prep = seg
            .run
            .prepare(bench, Path::new("."))
            .map_err(|source| TwinError::Segment { index, source })?;
        let mask = duty_mask(&prep.on_duty);
        let held = held_lever(seg, bench, index)?;
        let name = &seg.run.name;
        for (moving, plant, limit_s, end, what) in [
            (
                false,
                &held.plant,
                IDLE_MAX_S,
                mask,
                "energise the segment's cylinders",
            ),
            (
                true,
                &prep.plant,
                seg.run.duration_s + SEGMENT_SLACK_S,
                0,
                "de-energise the cylinders at the segment's end",
            ),
        ] {
            say(&format!(
                "twin: segment {} of {} ({name}): {}",
                index + 1,
                campaign.segment.len(),
                if moving {
                    format!("the lever runs: {}", seg.operator)
                } else {
                    "the lever held until the controller energises its cylinders".into()
                }
            ));
            ctrl.end_on_duty = Some(end);
            if ctrl.on_duty == end {
                // Already there (e.g. a segment on no cylinder): nothing to wait for.
                continue;
            }
            let done;
            (ctrl, done, state) = phase(ctrl, plant, state, limit_s, index, moving)?;
            say(&format!(
                "twin: {:.1} s simulated, P2 {:.1} bar, solenoids {:04b}",
                done.duration_s, done.p2_end_bar, ctrl.on_duty
            ));
            phases.push(done);
            if ctrl.on_duty != end {
                return Err(TwinError::Stalled {
                    index,
                    name: name.clone(),
                    what,
                    limit_s,
                });
            }
            if !moving {
                // The operator's reaction: the lever still held, the cylinders energised.
                ctrl.end_on_duty = None;
                let done;
                (ctrl, done, state) =
                    phase(ctrl, &held.plant, state, OPERATOR_START_S, index, false)?;
                phases.push(done);
            }
        }
    }
    // The runner's last commands (the valve closed after the cylinders) are answered while the
    // lever stays held a moment longer.
    if let Some(last) = campaign.segment.last() {
        let index = campaign.segment.len() - 1;
        let held = held_lever(last, bench, index)?;
        ctrl.end_on_duty = None;
        (ctrl, _, _) = phase(ctrl, &held.plant, state, FINAL_HOLD_S, index, false)?;
    }
    Ok((ctrl.into_target(), phases))
}

/// Segment `index`'s plant with the lever held (between segments) at 0°, where each segment's
/// sine starts: the twin's operator returns the lever there at once when a segment ends, after
/// its log.
fn held_lever(seg: &Segment, bench: &Bench, index: usize) -> Result<Prepared, TwinError> {
    let mut held = seg.run.clone();
    held.motion = MotionSpec::Blocked { angle_deg: 0.0 };
    held.prepare(bench, Path::new("."))
        .map_err(|source| TwinError::Segment { index, source })
}

/// One phase of the plant from `state` against the firmware, until the controller's end
/// condition or `limit_s`: what it did and the pressures it ended at.
fn phase(
    ctrl: FirmwareController,
    plant: &Plant,
    state: Initial,
    limit_s: f64,
    index: usize,
    moving: bool,
) -> Result<(FirmwareController, Phase, Initial), TwinError> {
    let (res, mut ctrl) = solver::simulate_with(
        Run {
            plant,
            valve: ValveSchedule::Constant(0.0),
            initial: state,
            duration: limit_s,
            sample_dt: 0.05,
            solver: TWIN_SOLVER,
            progress: None,
        },
        ctrl,
    );
    if let Some(e) = ctrl.error.take() {
        return Err(e.into());
    }
    let res = res.map_err(|source| TwinError::Simulation { index, source })?;
    let t = &res.trace;
    let last = t.t_s.len() - 1;
    let done = Phase {
        index,
        moving,
        duration_s: t.t_s[last],
        p2_end_bar: t.p2_pa[last] / BAR,
    };
    let end = Initial {
        p2_pa: t.p2_pa[last],
        lp_pa: t.lp_pa[last],
    };
    Ok((ctrl, done, end))
}

/// The lever held after the campaign, s of simulated time.
pub const FINAL_HOLD_S: f64 = 2.0;

/// The twin's solver settings (as the processor-in-the-loop runs').
const TWIN_SOLVER: SolverOptions = SolverOptions {
    rtol: 1e-6,
    atol_scale: 0.1,
    reuse_kinematics: true,
};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::bench::apply_override;
    use crate::sim::plant::Eval;
    use crate::sim::schedule::ValveController;

    /// The valve held closed at the firmware's period.
    struct Closed;

    impl ValveController for Closed {
        fn period(&self) -> f64 {
            2f64.powi(-10)
        }
        fn update(&mut self, _: f64, _: &Eval) -> f64 {
            0.0
        }
    }

    /// The twin's charge (trapped air 9 %, all four cylinders at ±40 mm, 0.2 Hz, the valve
    /// closed at the firmware's period) from the pressures a twin campaign reached after the
    /// operator's second: the lever turns at 1.25 s, where the check valves close and the
    /// motor stands, and a BDF step failed at 1.3994 s ("step size is too small"), ending the
    /// campaign. It runs through now (the step restarted once from where it failed).
    #[test]
    fn the_twin_s_charge_runs_through_where_a_step_failed() {
        let reference = Bench::reference();
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/campaign-four.toml");
        let campaign = Campaign::load(&path, &reference).unwrap();
        let seg = campaign
            .segment
            .iter()
            .find(|s| s.run.name == "charge-cfg1-c1234-40mm-0.2hz-from10")
            .unwrap();
        let mut file = reference.file.clone();
        apply_override(&mut file, "trapped_air=0.09", &crate::fit::set_shortcuts()).unwrap();
        let plant = Bench::from_file(file, "the twin's plant").unwrap();
        let prep = seg.run.prepare(&plant, Path::new(".")).unwrap();
        let (res, _) = solver::simulate_with(
            Run {
                plant: &prep.plant,
                valve: ValveSchedule::Constant(0.0),
                initial: Initial {
                    p2_pa: 1.04574487894047e6,
                    lp_pa: 7.994923159705985e5,
                },
                duration: 2.0,
                sample_dt: 0.05,
                solver: TWIN_SOLVER,
                progress: None,
            },
            Closed,
        );
        let res = res.expect("the charge runs through the lever's turn");
        let t = &res.trace.t_s;
        println!(
            "{:.3} s simulated, P2 {:.2} bar",
            t[t.len() - 1],
            res.trace.p2_pa[t.len() - 1] / BAR
        );
        assert!(t[t.len() - 1] >= 2.0);
    }
}
