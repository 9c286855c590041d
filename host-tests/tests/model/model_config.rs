//! The one conversion from the bench file to the firmware's configuration
//! (`pto_host::validation::model_config` and `controller_config`: the model, the scheduler and the
//! control settings), checked over every field: the reference bench gives
//! `ModelConfig::reference()`, `SchedulerConfig::default()` and `ControlConfig::default()` to
//! the bit in every field, and every numeric field of the bench file either changes the
//! firmware's configuration or is named below with the reason it does not apply.

use pto_host::sim::bench::Bench;
use pto_host::validation::{ModelError, controller_config, model_config};
use std::collections::BTreeMap;

/// Numeric leaves of a serialised value by dotted path (`a.b[2].c`): the value, and whether
/// it is an integer.
fn leaves(v: &serde_json::Value, path: &str, out: &mut BTreeMap<String, (f64, bool)>) {
    match v {
        serde_json::Value::Object(m) => {
            for (k, x) in m {
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                leaves(x, &p, out);
            }
        }
        serde_json::Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                leaves(x, &format!("{path}[{i}]"), out);
            }
        }
        serde_json::Value::Number(n) => {
            out.insert(
                path.to_string(),
                (n.as_f64().unwrap_or(f64::NAN), n.is_i64()),
            );
        }
        _ => {}
    }
}

/// Every number of the firmware's configuration made from a bench: the model's, the
/// scheduler's and the control settings (`scheduler.…`, `control.…`).
fn model_leaves(b: &Bench) -> Result<BTreeMap<String, (f64, bool)>, ModelError> {
    let m = model_config(b)?;
    let (sched, control) = controller_config(b);
    let mut out = BTreeMap::new();
    leaves(&serde_json::to_value(m).unwrap(), "", &mut out);
    leaves(&serde_json::to_value(sched).unwrap(), "scheduler", &mut out);
    leaves(&serde_json::to_value(control).unwrap(), "control", &mut out);
    Ok(out)
}

/// Bench-file fields the reduced model does not take, and why.
const NOT_IN_MODEL: &[(&str, &str)] = &[
    (
        "controller.board.hse_mhz",
        "the controller board's crystal: the firmware's clock (its PLL), built in by the build \
         script (`built_config::HSE_MHZ`), not the model",
    ),
    (
        "check_valve.",
        "the reduced model holds each chamber a constant `check_valve_drop_bar` (0.7 bar) above \
         P2 or below LP; the bench's flow-dependent valve law (cracking, full-open, area, Cd) has \
         no single value to map to yet",
    ),
    (
        "makeup_valve.",
        "no make-up valves in the reduced model: a sucking chamber is held at LP − the check \
         valve's drop",
    ),
    (
        "cylinder_mounting.hard_stop_",
        "the ends of the free play are rigid in the reduced model: the eye crosses the play, \
         then the rod moves with it",
    ),
    (
        "input.pinion_radius_mm",
        "turns the rack's motion into the shaft's in the simulation; the controller reads the \
         shaft angle from its encoder",
    ),
    (
        "lines.hp_line_resistance_bar_per_lpm",
        "one HP node in the reduced model, no line pressure drop (0 on the reference bench)",
    ),
    (
        "lines.lp_line_resistance_bar_per_lpm",
        "one LP node in the reduced model, no line pressure drop (0 on the reference bench)",
    ),
    (
        "lines.valve_to_motor_",
        "no node between the valve and the motor in the reduced model (the valve/motor branch \
         is one flow with the rotor's inertia)",
    ),
    (
        "oil.critical_reynolds",
        "laminar–turbulent transition of the simulation's orifices; the reduced model's valve \
         law is turbulent",
    ),
    (
        "oil.kinematic_viscosity_cst",
        "enters the simulation's laminar flows only (orifices below the critical Reynolds \
         number, leakage); the reduced model's motor leakage is its own coefficient",
    ),
    (
        "oil.leakage_area_mm2",
        "the cylinders' internal leakage (1e-6 mm² on the reference bench, negligible); none in \
         the reduced model",
    ),
];

/// Fields no valid bench can move, and why.
const FIXED: &[(&str, &str)] = &[
    (
        "control_valve.aperture_pct[0]",
        "the valve table starts at a closed valve, 0 %",
    ),
    (
        "control_valve.aperture_pct[10]",
        "the valve table ends at a fully open valve, 100 %",
    ),
];

#[test]
fn the_reference_bench_gives_the_firmware_default_in_every_field() {
    let from_bench = model_leaves(&Bench::reference()).unwrap();
    let mut fw = BTreeMap::new();
    leaves(
        &serde_json::to_value(pto_model::ModelConfig::reference()).unwrap(),
        "",
        &mut fw,
    );
    leaves(
        &serde_json::to_value(pto_model::SchedulerConfig::default()).unwrap(),
        "scheduler",
        &mut fw,
    );
    leaves(
        &serde_json::to_value(pto_model::control::ControlConfig::default()).unwrap(),
        "control",
        &mut fw,
    );
    assert_eq!(
        from_bench.keys().collect::<Vec<_>>(),
        fw.keys().collect::<Vec<_>>()
    );
    // Equal to the bit: the firmware built for the reference bench (`PTO_BENCH` unset) and the
    // golden vectors made with `ModelConfig::reference()` are the same configuration.
    let differ: Vec<String> = from_bench
        .iter()
        .filter(|(k, b)| b.0 != fw[*k].0)
        .map(|(k, b)| {
            format!(
                "{k}: bench {:?} vs firmware {:?}",
                b.0 as f32, fw[k].0 as f32
            )
        })
        .collect();
    println!("{} fields, {} differ", fw.len(), differ.len());
    assert!(differ.is_empty(), "{differ:#?}");
    assert_eq!(
        model_config(&Bench::reference()).unwrap(),
        pto_model::ModelConfig::reference()
    );
}

#[test]
fn every_bench_field_reaches_the_model_or_is_named_as_not_applying() {
    let base_bench = Bench::reference();
    let base = model_leaves(&base_bench).unwrap();
    let file = serde_json::to_value(&base_bench.file).unwrap();
    let mut fields = BTreeMap::new();
    leaves(&file, "", &mut fields);
    let (mut reached, mut unused) = (Vec::new(), Vec::new());
    for (path, &(v, is_int)) in &fields {
        let tries = if is_int {
            vec![-v, v + 1.0]
        } else if v == 0.0 {
            vec![0.01, 1.0]
        } else {
            vec![v * 1.05, v * 0.95]
        };
        let mut outcome = None;
        for t in tries {
            let mut f = base_bench.file.clone();
            let value = if is_int {
                format!("{}", t as i64)
            } else {
                format!("{t:e}")
            };
            if f.set_field(path, &value).is_err() {
                continue;
            }
            let Ok(b) = Bench::from_file(f, "perturbed") else {
                continue;
            };
            outcome = Some(match model_leaves(&b) {
                // The model rejects it: the field reaches it.
                Err(_) => true,
                Ok(m) => m != base,
            });
            break;
        }
        match outcome {
            Some(true) => reached.push(path.clone()),
            Some(false) => unused.push(path.clone()),
            None => assert!(
                FIXED.iter().any(|(f, _)| f == path),
                "{path}: no valid bench with the field moved by ±5 %, and not named in FIXED"
            ),
        }
    }
    println!("{} fields reach the model: {reached:?}", reached.len());
    println!("{} do not: {unused:?}", unused.len());
    let named: Vec<&str> = NOT_IN_MODEL.iter().map(|(f, _)| *f).collect();
    for f in &unused {
        assert!(
            named.iter().any(|n| f.starts_with(n)),
            "{f}: changing it leaves the model's configuration unchanged and it is not named \
             in NOT_IN_MODEL"
        );
    }
    for n in &named {
        assert!(
            !reached.iter().any(|f| f.starts_with(n)),
            "{n}: named as not applying, yet it changes the model's configuration"
        );
    }
}
