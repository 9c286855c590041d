//! The fittable parameters: their bench fields, bounds and the tanh transform that keeps every
//! trial inside them; `--set` overrides by short name or dotted path.

use super::*;

/// A fittable parameter.
#[derive(Clone)]
pub struct Param {
    /// Short name (command line).
    pub name: String,
    /// Bench file field.
    pub key: String,
    /// Unit.
    pub unit: String,
    /// Range the optimiser keeps to.
    pub lo: f64,
    /// Range the optimiser keeps to.
    pub hi: f64,
    /// Value in a bench file.
    pub get: Arc<dyn Fn(&BenchFile) -> f64 + Send + Sync>,
    /// Sets it.
    pub set: Setter,
}

impl std::fmt::Debug for Param {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}, {} in [{}, {}])",
            self.name, self.key, self.unit, self.lo, self.hi
        )
    }
}

pub(super) fn scalar(
    name: &str,
    key: &str,
    unit: &str,
    lo: f64,
    hi: f64,
    get: fn(&BenchFile) -> f64,
    set: fn(&mut BenchFile, f64),
) -> Param {
    Param {
        name: name.into(),
        key: key.into(),
        unit: unit.into(),
        lo,
        hi,
        get: Arc::new(get),
        set: Arc::new(set),
    }
}

/// Names accepted by `--params` (`area_table` expands to one factor per table segment).
pub const PARAM_NAMES: &[&str] = &[
    "trapped_air",
    "cd",
    "cd_slope",
    "precharge",
    "hp_volume",
    "leakage",
    "area_table",
];

/// The parameters called `names`, for a fit starting from `start`.
pub fn params(names: &[String], start: &BenchFile) -> Result<Vec<Param>, String> {
    let mut v = Vec::new();
    for n in names {
        match n.as_str() {
            "trapped_air" => v.push(scalar(
                "trapped_air",
                "oil.trapped_air_fraction",
                "-",
                0.0,
                0.3,
                |f| f.oil.trapped_air_fraction,
                |f, x| f.oil.trapped_air_fraction = x,
            )),
            "cd" => v.push(scalar(
                "cd",
                "control_valve.discharge_coefficient",
                "-",
                0.02,
                1.0,
                |f| f.control_valve.discharge_coefficient,
                |f, x| f.control_valve.discharge_coefficient = x,
            )),
            "precharge" => v.push(scalar(
                "precharge",
                "hp_accumulator.precharge_bar",
                "bar",
                1.0,
                120.0,
                |f| f.hp_accumulator.precharge_bar,
                |f, x| f.hp_accumulator.precharge_bar = x,
            )),
            "hp_volume" => v.push(scalar(
                "hp_volume",
                "hp_accumulator.volume_l",
                "L",
                0.1,
                200.0,
                |f| f.hp_accumulator.volume_l,
                |f, x| f.hp_accumulator.volume_l = x,
            )),
            "cd_slope" => v.push(scalar(
                "cd_slope",
                "control_valve.cd_slope_per_100bar",
                "1/100 bar",
                -0.5,
                0.5,
                |f| f.control_valve.cd_slope_per_100bar,
                |f, x| f.control_valve.cd_slope_per_100bar = x,
            )),
            "leakage" => v.push(scalar(
                "leakage",
                "motor.volumetric_efficiency",
                "-",
                0.5,
                1.0,
                |f| f.motor.volumetric_efficiency,
                |f, x| f.motor.volumetric_efficiency = x,
            )),
            "area_table" => {
                let a = start.control_valve.area_mm2.clone();
                let ap = start.control_valve.aperture_pct.clone();
                for i in 1..a.len() {
                    let base = a.clone();
                    v.push(Param {
                        name: format!("area_seg{}", i),
                        key: format!(
                            "control_valve.area_mm2 increment {:.0}→{:.0} % (factor)",
                            ap[i - 1],
                            ap[i]
                        ),
                        unit: "×".into(),
                        lo: 0.0,
                        hi: 5.0,
                        get: {
                            let base = a.clone();
                            Arc::new(move |f: &BenchFile| {
                                let cur = &f.control_valve.area_mm2;
                                let b = base[i] - base[i - 1];
                                if b > 0.0 {
                                    (cur[i] - cur[i - 1]) / b
                                } else {
                                    1.0
                                }
                            })
                        },
                        // Segment i's increment = factor × its starting increment; the rest of
                        // the table is rebuilt cumulatively, so it stays monotone.
                        set: Arc::new(move |f, x| {
                            let cur = &mut f.control_valve.area_mm2;
                            let inc_now: Vec<f64> =
                                (1..cur.len()).map(|k| cur[k] - cur[k - 1]).collect();
                            let mut acc = cur[0];
                            for k in 1..cur.len() {
                                let inc = if k == i {
                                    x * (base[k] - base[k - 1])
                                } else {
                                    inc_now[k - 1]
                                };
                                acc += inc.max(0.0);
                                cur[k] = acc;
                            }
                        }),
                    });
                }
            }
            other => {
                return Err(format!(
                    "--params: unknown parameter `{other}` (known: {})",
                    PARAM_NAMES.join(", ")
                ));
            }
        }
    }
    if v.is_empty() {
        return Err("--params: nothing to fit".into());
    }
    Ok(v)
}

pub(super) fn to_z(p: &Param, x: f64) -> f64 {
    let u = (2.0 * (x - p.lo) / (p.hi - p.lo) - 1.0).clamp(-0.999_999, 0.999_999);
    u.atanh()
}

pub(super) fn from_z(p: &Param, z: f64) -> f64 {
    p.lo + (p.hi - p.lo) * 0.5 * (1.0 + z.tanh())
}

pub(super) fn dx_dz(p: &Param, z: f64) -> f64 {
    let c = z.cosh();
    (p.hi - p.lo) * 0.5 / (c * c)
}

/// Sets a `name=value` override on a bench file (`pto synth-logs --set`, `pto simulate
/// --set`): a fit parameter's short name (`trapped_air`, `cd`, `precharge`, …) or any bench
/// field by its dotted path (`hp_accumulator.volume_l`, `cylinder[1].bore_mm`).
pub fn apply_override(f: &mut BenchFile, kv: &str) -> Result<(), String> {
    let (k, v) = kv
        .split_once('=')
        .ok_or_else(|| format!("--set {kv}: want name=value"))?;
    let k = k.trim();
    if k.contains('.') || k.contains('[') {
        return f.set_field(k, v.trim()).map_err(|e| format!("--set {e}"));
    }
    let Ok(v) = v.trim().parse::<f64>() else {
        return f.set_field(k, v.trim()).map_err(|e| format!("--set {e}"));
    };
    let scalars: Vec<String> = PARAM_NAMES
        .iter()
        .filter(|n| **n != "area_table")
        .map(|n| n.to_string())
        .collect();
    let all = params(&scalars, f)?;
    match all.iter().find(|p| p.name == k || p.key == k) {
        Some(p) => {
            (p.set)(f, v);
            Ok(())
        }
        // Not a parameter name: a top-level bench field.
        None => f.set_field(k, &v.to_string()).map_err(|e| {
            format!(
                "--set {e} (or a parameter: {})",
                all.iter()
                    .map(|p| p.name.clone())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        }),
    }
}
