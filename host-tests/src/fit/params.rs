//! The fittable parameters: their bench fields, bounds and the tanh transform that keeps every
//! trial inside them; their short names as `--set` shortcuts.

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
    /// The precision a fitted bench needs of it: its 3σ must be within this.
    pub needed: Precision,
}

impl Param {
    /// The precision this parameter needs at `value`, in its unit: the one stated in
    /// `precision` (`--precision NAME=VALUE`), else its default.
    pub fn needed_at(&self, value: f64, precision: &[(String, f64)]) -> f64 {
        precision
            .iter()
            .find(|(n, _)| *n == self.name)
            .map_or_else(|| self.needed.at(value), |(_, x)| *x)
    }
}

/// How precisely a parameter must be known for the fitted bench to be worth using (the
/// `precision` check: 3σ within it). The defaults are what moves the bench's behaviour by
/// about its sensors' noise: trapped air ± 0.005, Cd ± 3 %, precharge ± 2 bar, η_v ± 0.01.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// In the parameter's unit.
    Absolute(f64),
    /// A fraction of its value.
    Relative(f64),
}

impl Precision {
    /// The half-width at `value`, in the parameter's unit.
    pub fn at(self, value: f64) -> f64 {
        match self {
            Precision::Absolute(x) => x,
            Precision::Relative(f) => f * value.abs(),
        }
    }
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

/// A scalar parameter: (short name, bench field, unit, lower bound, upper bound, getter,
/// setter, precision needed).
type Scalar = (
    &'static str,
    &'static str,
    &'static str,
    f64,
    f64,
    fn(&BenchFile) -> f64,
    fn(&mut BenchFile, f64),
    Precision,
);

/// The scalar parameters (every name of [`PARAM_NAMES`] but `area_table`).
const SCALARS: [Scalar; 6] = [
    (
        "trapped_air",
        "oil.trapped_air_fraction",
        "-",
        0.0,
        0.3,
        |f| f.oil.trapped_air_fraction,
        |f, x| f.oil.trapped_air_fraction = x,
        Precision::Absolute(0.005),
    ),
    (
        "cd",
        "control_valve.discharge_coefficient",
        "-",
        0.02,
        1.0,
        |f| f.control_valve.discharge_coefficient,
        |f, x| f.control_valve.discharge_coefficient = x,
        Precision::Relative(0.03),
    ),
    (
        "precharge",
        "hp_accumulator.precharge_bar",
        "bar",
        1.0,
        120.0,
        |f| f.hp_accumulator.precharge_bar,
        |f, x| f.hp_accumulator.precharge_bar = x,
        Precision::Absolute(2.0),
    ),
    (
        "hp_volume",
        "hp_accumulator.volume_l",
        "L",
        0.1,
        200.0,
        |f| f.hp_accumulator.volume_l,
        |f, x| f.hp_accumulator.volume_l = x,
        Precision::Relative(0.05),
    ),
    (
        "cd_slope",
        "control_valve.cd_slope_per_100bar",
        "1/100 bar",
        -0.5,
        0.5,
        |f| f.control_valve.cd_slope_per_100bar,
        |f, x| f.control_valve.cd_slope_per_100bar = x,
        Precision::Absolute(0.05),
    ),
    // The motor's leakage as its volumetric efficiency; the total efficiency follows at the
    // bench's mechanical efficiency (η_total / η_v, unchanged), so no trial can make the
    // mechanical efficiency exceed 1 (a bench file the checks refuse).
    (
        "leakage",
        "motor.volumetric_efficiency",
        "-",
        0.5,
        1.0,
        |f| f.motor.volumetric_efficiency,
        |f, x| {
            let eta_mech = f.motor.total_efficiency / f.motor.volumetric_efficiency;
            f.motor.volumetric_efficiency = x;
            f.motor.total_efficiency = x * eta_mech;
        },
        Precision::Absolute(0.01),
    ),
];

/// A field the fit holds at the bench file's value: (bench field, unit, getter, setter).
type HeldField = (
    &'static str,
    &'static str,
    fn(&BenchFile) -> f64,
    fn(&mut BenchFile, f64),
);

/// The plant's fields a fit holds whose error can move what it fits (`pto plan`'s held-field
/// leverage): what compresses with the trapped air (the liquid's bulk modulus, the dead
/// volume), what sets the chambers' pressures (the check valves' cracking: a suction valve
/// that cracks late lets a chamber fall further below LP, where its air expands more), the
/// accumulators the fit does not fit, and the seals' friction.
const HELD: [HeldField; 6] = [
    (
        "check_valve.cracking_bar",
        "bar",
        |f| f.check_valve.cracking_bar,
        // The full-open pressure moves with it (the opening band kept).
        |f, x| {
            let band = f.check_valve.full_open_bar - f.check_valve.cracking_bar;
            f.check_valve.cracking_bar = x;
            f.check_valve.full_open_bar = x + band;
        },
    ),
    (
        "lp_accumulator.precharge_bar",
        "bar",
        |f| f.lp_accumulator.precharge_bar,
        |f, x| f.lp_accumulator.precharge_bar = x,
    ),
    (
        "hp_accumulator.volume_l",
        "L",
        |f| f.hp_accumulator.volume_l,
        |f, x| f.hp_accumulator.volume_l = x,
    ),
    (
        "oil.liquid_bulk_modulus_mpa",
        "MPa",
        |f| f.oil.liquid_bulk_modulus_mpa,
        |f, x| f.oil.liquid_bulk_modulus_mpa = x,
    ),
    (
        "cylinder_mounting.dead_volume_cm3",
        "cm³",
        |f| f.cylinder_mounting.dead_volume_cm3,
        |f, x| f.cylinder_mounting.dead_volume_cm3 = x,
    ),
    (
        "cylinder_mounting.seal_friction_n_s_per_m",
        "N·s/m",
        |f| f.cylinder_mounting.seal_friction_n_s_per_m,
        |f, x| f.cylinder_mounting.seal_friction_n_s_per_m = x,
    ),
];

/// A held field's bounds: its value ± this many times its value. Only the value and one
/// finite-difference step from it are simulated, so the bounds need not be physical; they put
/// the value mid-range, where the bounded coordinate's step is its slope to second order (the
/// information's units rest on that slope), and make the step ([`STEP_OF_RANGE`] of the range)
/// 1 % of the value, as the fitted parameters' are 0.5–1 % of theirs. With steps of 0.1 %
/// (bounds of 0.5–1.5 times the value) the small shifts are the solver's noise: the check
/// valves' cracking moved the precharge by 1.8e-2 bar per bar, against 3.4e-3 with steps of
/// 1 % (trapped air, the shift that matters, 1.00e-2 against 9.7e-3 per bar).
pub const HELD_HALF_RANGE: f64 = 5.0;

/// The held fields (the table above) that none of `fitted` fits, as parameters named by their
/// bench field, bounded by [`HELD_HALF_RANGE`] around their value in `start` (the loader keeps
/// these fields above 0). They have no precision of their own (never checked: infinite).
pub fn held_params(fitted: &[Param], start: &BenchFile) -> Vec<Param> {
    HELD.iter()
        .filter(|h| fitted.iter().all(|p| p.key != h.0))
        .filter_map(|&(key, unit, get, set)| {
            let value = get(start);
            (value.is_finite() && value > 0.0).then(|| Param {
                name: key.into(),
                key: key.into(),
                unit: unit.into(),
                lo: value * (1.0 - HELD_HALF_RANGE),
                hi: value * (1.0 + HELD_HALF_RANGE),
                get: Arc::new(get),
                set: Arc::new(set),
                needed: Precision::Absolute(f64::INFINITY),
            })
        })
        .collect()
}

/// The scalar parameter called `name`.
fn scalar_param(name: &str) -> Option<Param> {
    let &(name, key, unit, lo, hi, get, set, needed) = SCALARS.iter().find(|s| s.0 == name)?;
    Some(Param {
        name: name.into(),
        key: key.into(),
        unit: unit.into(),
        lo,
        hi,
        get: Arc::new(get),
        set: Arc::new(set),
        needed,
    })
}

/// The parameters called `names`, for a fit starting from `start`.
pub fn params(names: &[String], start: &BenchFile) -> Result<Vec<Param>, FitError> {
    let mut v = Vec::new();
    for n in names {
        if let Some(mut p) = scalar_param(n) {
            if p.name == "leakage" {
                // The total efficiency (η_v · η_mech) stays ≥ the bench file's 0.3.
                let eta_mech = start.motor.total_efficiency / start.motor.volumetric_efficiency;
                p.lo = p.lo.max(0.3 / eta_mech.max(1e-9));
            }
            v.push(p);
            continue;
        }
        match n.as_str() {
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
                        needed: Precision::Relative(0.1),
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
                return Err(FitError::UnknownParam { name: other.into() });
            }
        }
    }
    if v.is_empty() {
        return Err(FitError::NoParams);
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

/// The scalar parameters' short names as `--set` shortcuts (in [`PARAM_NAMES`]' order), for
/// [`apply_override`](crate::sim::bench::apply_override): `--set trapped_air=0.04` sets
/// `oil.trapped_air_fraction`.
pub fn set_shortcuts() -> Vec<Shortcut> {
    PARAM_NAMES
        .iter()
        .filter_map(|n| scalar_param(n))
        .map(|p| Shortcut {
            name: p.name,
            field: p.key,
            set: p.set,
        })
        .collect()
}
