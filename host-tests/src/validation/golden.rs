//! Golden vectors: a committed file of model inputs → exact fixed-point outputs (raw Q16.16
//! bits), checked on the host by `cargo test` and, bit for bit, inside the firmware.
//!
//! The inputs are 2048 consecutive steps of Test III at 10 % around the valve opening, made by
//! the full simulation and the sensor model, with faults injected: HP reading missing, an HP wire
//! break (reads −60 bar), noise bursts, a missing encoder. The estimator and the scheduler
//! (holding P2 at 100 bar) run from a known start.

use super::{commanded_aperture_pct, duty_mask, inputs};
use crate::sim::bench::Bench;
use crate::sim::scenario::RunError;
use crate::sim::trace::truth_at;
use crate::validation::sensors::{Readings, SensorSpec, SensorSynth};
use pto_model::estimator::{self, Estimate, Inputs, State};
use pto_model::fx::{Aperture, Pressure, Rpm};
use pto_model::protocol::vectors::checked_words;
use pto_model::scheduler::{self, Command, Mode, SchedulerConfig, SchedulerState};
use pto_model::{Coefficients, ConfigError, ModelConfig};
use std::fmt::Write as _;
use std::path::Path;

/// Why golden vectors could not be made, read or run.
#[derive(Debug, thiserror::Error)]
pub enum GoldenError {
    /// The built-in scenario the inputs come from is missing.
    #[error("{0} missing")]
    MissingScenario(String),
    /// Its run failed.
    #[error(transparent)]
    Run(#[from] RunError),
    /// The model configuration has no coefficients.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The golden file is empty.
    #[error("empty golden file")]
    Empty,
    /// Its first line lacks a start pressure.
    #[error("golden file line 1: missing {key}")]
    MissingStart {
        /// The key (`start_p2_bits=`).
        key: &'static str,
    },
    /// A line has the wrong number of columns.
    #[error("golden file line {line}: {columns} columns, want {want}")]
    Columns {
        /// 1-based line.
        line: usize,
        /// Columns found.
        columns: usize,
        /// Columns of the header.
        want: usize,
    },
    /// A cell is not an integer.
    #[error("line {line}")]
    Number {
        /// 1-based line.
        line: usize,
        /// The parser's error.
        source: std::num::ParseIntError,
    },
}

/// Where the vectors live.
pub const FILE: &str = "data/golden-vectors.csv";
/// Setpoint of the scheduler in the vectors, bar.
pub const SETPOINT_BAR: f32 = 100.0;
const HEADER: &str = "step,encoder,hp,lp,motor,aperture_cmd,on_duty,config,p2,p2_var,lp_est,q_pump,q_valve,q_relief,hydraulic_power,torque,motor_rpm,autonomy,aperture,faults,hp_empty,cmd_aperture,safety";

/// Which steps of a replay get a fault injected.
pub type Faults = fn(usize, Option<i32>, f64) -> (Option<i32>, Option<f64>);

fn golden_faults(i: usize, enc: Option<i32>, hp: f64) -> (Option<i32>, Option<f64>) {
    let hp = match i {
        600..900 => None,
        1200..1260 => Some(-60.0),
        // The spool settling after the valve opened, then the motor speed as the P2 reading.
        1300..1750 => None,
        1800..1820 => Some(hp + if i.is_multiple_of(2) { 30.0 } else { -30.0 }),
        _ => Some(hp),
    };
    let enc = if (1700..1750).contains(&i) { None } else { enc };
    (enc, hp)
}

fn no_faults(_: usize, enc: Option<i32>, hp: f64) -> (Option<i32>, Option<f64>) {
    (enc, Some(hp))
}

/// No HP reading at any step (for [`scenario_inputs`]: the model's P2 from the model and the
/// motor speed).
pub fn no_hp(_: usize, enc: Option<i32>, _: f64) -> (Option<i32>, Option<f64>) {
    (enc, None)
}

/// Model inputs made from a full-simulation run of scenario `name`: `steps` steps of 2^−10 s
/// from `t_start` s (or from 1 s before the valve opens), through the sensor model (seed 42),
/// with `faults` applied; plus the plant's P2 and LP at the start, bar.
pub fn scenario_inputs(
    bench: &Bench,
    name: &str,
    t_start: Option<f64>,
    steps: usize,
    faults: Faults,
) -> Result<(Vec<Inputs>, f32, f32), GoldenError> {
    let mut s = crate::sim::scenario::builtin_named(name)
        .ok_or_else(|| GoldenError::MissingScenario(name.into()))?;
    s.sample_interval_s = 1.0 / 128.0;
    let dt = 1.0 / 1024.0;
    if let Some(t0) = t_start {
        s.duration_s = s.duration_s.min(t0 + steps as f64 * dt + 1.0);
    }
    let (prep, res) = s.simulate(bench, Path::new("."), Default::default(), None)?;
    let t0 = t_start.unwrap_or_else(|| res.valve_opened_at.unwrap_or(50.0) - 1.0);
    let mut synth = SensorSynth::new(SensorSpec::default(), 42);
    let start = truth_at(&res.trace, t0);
    let duty = duty_mask(&prep.on_duty);
    let mut v = Vec::with_capacity(steps);
    for i in 0..steps {
        let t = t0 + i as f64 * dt;
        let truth = truth_at(&res.trace, t);
        let Readings {
            encoder_count: enc,
            hp_bar: hp,
            lp_bar: lp,
            motor_rpm: motor,
        } = synth.read(prep.plant.motion().at(t).0, &truth);
        let (enc, hp) = faults(i, Some(enc), hp);
        let ap = commanded_aperture_pct(&s, &res, t);
        v.push(inputs(
            enc,
            hp,
            Some(lp),
            Some(motor),
            ap,
            duty,
            prep.config as u8,
        ));
    }
    Ok((v, start.p2_bar as f32, start.lp_bar as f32))
}

/// Makes the 2048 golden input steps (Test III at 10 %, faults injected).
pub fn make_inputs(bench: &Bench) -> Result<(Vec<Inputs>, f32, f32), GoldenError> {
    scenario_inputs(bench, "test3-ap10", None, 2048, golden_faults)
}

/// A fault-free replay of `steps` steps of scenario `name` from `t_start`.
pub fn clean_inputs(
    bench: &Bench,
    name: &str,
    t_start: Option<f64>,
    steps: usize,
) -> Result<(Vec<Inputs>, f32, f32), GoldenError> {
    scenario_inputs(bench, name, t_start, steps, no_faults)
}

/// The mode the vectors hold P2 in ([`SETPOINT_BAR`]); `pto fw-cost` and the Cortex-M0 replay
/// measure in it too.
pub fn hold_p2() -> Mode {
    Mode::HoldPressure(Pressure::from_num(SETPOINT_BAR))
}

/// Runs the model over the inputs from the known start.
pub fn run(
    k: &Coefficients,
    inputs: &[Inputs],
    p2: f32,
    lp: f32,
) -> Result<Vec<(Estimate, Command)>, GoldenError> {
    let sc = SchedulerConfig::default().coefficients(k)?;
    let mut s = State::new(
        Pressure::from_num(p2),
        Pressure::from_num(lp),
        Pressure::from_num(1.0),
    );
    let mut st = SchedulerState::default();
    Ok(inputs
        .iter()
        .map(|inp| {
            let e = estimator::step(k, &mut s, inp);
            let c = scheduler::step(k, &sc, &mut st, hold_p2(), &e, inp.motor);
            (e, c)
        })
        .collect())
}

fn opt(v: Option<i32>) -> String {
    v.map_or(String::new(), |x| x.to_string())
}

/// The CSV text of a run (first line: `# start p2_bits lp_bits`).
pub fn to_csv(inputs: &[Inputs], out: &[(Estimate, Command)], p2: f32, lp: f32) -> String {
    let mut s = format!(
        "# start_p2_bits={} start_lp_bits={}\n{HEADER}\n",
        Pressure::from_num(p2).to_bits(),
        Pressure::from_num(lp).to_bits()
    );
    for (i, (inp, (e, c))) in inputs.iter().zip(out).enumerate() {
        // The outputs as the Cortex-M0 replay checks them (the same words, in this order).
        let outputs: Vec<String> = checked_words(e, c).iter().map(i32::to_string).collect();
        let _ = writeln!(
            s,
            "{i},{},{},{},{},{},{},{},{}",
            opt(inp.encoder),
            opt(inp.hp.map(|p| p.to_bits())),
            opt(inp.lp.map(|p| p.to_bits())),
            opt(inp.motor.map(|p| p.to_bits())),
            inp.aperture_cmd.to_bits(),
            inp.on_duty,
            inp.config,
            outputs.join(",")
        );
    }
    s
}

/// Parsed golden file: start pressures (bits), inputs and the expected CSV text.
pub fn parse(text: &str) -> Result<(i32, i32, Vec<Inputs>), GoldenError> {
    let mut lines = text.lines();
    let first = lines.next().ok_or(GoldenError::Empty)?;
    let field = |key: &'static str| -> Result<i32, GoldenError> {
        first
            .split_whitespace()
            .find_map(|w| w.strip_prefix(key))
            .and_then(|v| v.parse().ok())
            .ok_or(GoldenError::MissingStart { key })
    };
    let (p2, lp) = (field("start_p2_bits=")?, field("start_lp_bits=")?);
    lines.next();
    let mut inputs = Vec::new();
    for (n, l) in lines.enumerate() {
        let c: Vec<&str> = l.split(',').collect();
        let want = HEADER.split(',').count();
        if c.len() != want {
            return Err(GoldenError::Columns {
                line: n + 3,
                columns: c.len(),
                want,
            });
        }
        let num = |s: &str| -> Result<i32, GoldenError> {
            s.parse().map_err(|source| GoldenError::Number {
                line: n + 3,
                source,
            })
        };
        let o = |s: &str| -> Result<Option<i32>, GoldenError> {
            if s.is_empty() {
                Ok(None)
            } else {
                num(s).map(Some)
            }
        };
        inputs.push(Inputs {
            encoder: o(c[1])?,
            hp: o(c[2])?.map(Pressure::from_bits),
            lp: o(c[3])?.map(Pressure::from_bits),
            motor: o(c[4])?.map(Rpm::from_bits),
            aperture_cmd: Aperture::from_bits(num(c[5])?),
            on_duty: num(c[6])? as u8,
            config: num(c[7])? as u8,
        });
    }
    Ok((p2, lp, inputs))
}

/// The model configuration the vectors are made with: the firmware's `ModelConfig::reference()`
/// (a test keeps it equal to `model::model_config` of the reference bench).
pub fn coefficients() -> Result<Coefficients, GoldenError> {
    Ok(ModelConfig::reference().coefficients()?)
}

#[cfg(test)]
mod tests {
    /// The file's output columns are the words the Cortex-M0 replay checks, in their order.
    #[test]
    fn the_output_columns_are_the_checked_words() {
        let names = pto_model::protocol::vectors::CHECKED.join(",");
        assert!(
            super::HEADER.ends_with(&format!(",{names}")),
            "{}",
            super::HEADER
        );
    }
}
