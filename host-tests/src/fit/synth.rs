//! Bench logs made from the full simulation and the sensor model (`pto synth-logs`).

use super::*;

/// Makes a bench log of a built-in scenario from the full simulation and the sensor model
/// (encoder 16 384 counts/rev, 12-bit pressures with noise, motor speed noise), sampled at
/// `rate_hz`.
pub fn synth_log(
    bench: &Bench,
    scenario: &str,
    rate_hz: f64,
    seed: u64,
    out: &Path,
) -> Result<BenchLog, FitError> {
    let s = crate::sim::scenario::builtin_named(scenario)
        .ok_or_else(|| FitError::UnknownScenario(scenario.into()))?;
    synth_scenario_log(bench, &s, rate_hz, SensorSpec::default(), seed, out)
}

/// Makes a bench log of any scenario (a campaign's segment: `pto plan`) with the sensors of
/// `spec` (a spec without noise gives the noise-free log the plan's sensitivities start from),
/// sampled at `rate_hz`, named `<scenario>.csv` in `out`.
pub fn synth_scenario_log(
    bench: &Bench,
    scenario: &Scenario,
    rate_hz: f64,
    spec: SensorSpec,
    seed: u64,
    out: &Path,
) -> Result<BenchLog, FitError> {
    let mut s = scenario.clone();
    s.sample_interval_s = (0.5 / rate_hz).min(s.sample_interval_s);
    let (prep, res) = s.simulate(bench, Path::new("."), SolverOptions::default(), None)?;
    let mut synth = SensorSynth::new(spec, seed);
    let n = (s.duration_s * rate_hz).floor() as usize + 1;
    let mut log = BenchLog {
        path: out.join(format!("{}.csv", s.name)),
        t: Vec::with_capacity(n),
        theta_deg: Vec::with_capacity(n),
        p2_bar: Vec::with_capacity(n),
        lp_bar: Vec::with_capacity(n),
        rpm: Vec::with_capacity(n),
        aperture_pct: Vec::with_capacity(n),
        on_duty: prep.on_duty,
        config: prep.config + 1,
    };
    for k in 0..n {
        let t = k as f64 / rate_hz;
        let truth = truth_at(&res.trace, t);
        let theta = prep.plant.motion().at(t).0;
        let Readings {
            encoder_count: enc,
            hp_bar: hp,
            lp_bar: lp,
            motor_rpm: motor,
        } = synth.read(theta, &truth);
        log.t.push(t);
        log.theta_deg
            .push(f64::from(enc) * 360.0 / f64::from(spec.counts_per_rev));
        log.p2_bar.push(hp);
        log.lp_bar.push(lp);
        log.rpm.push(motor);
        log.aperture_pct
            .push(crate::validation::commanded_aperture_pct(&s, &res, t));
    }
    Ok(log)
}

/// The paper's experimental runs (Section 4.2), as built-in scenario names.
pub const EXPERIMENTAL_RUNS: [&str; 7] = [
    "exp-charge-64.5",
    "exp-charge-67.2",
    "exp-charge-72",
    "exp-9pct-101.5",
    "exp-discharge-102",
    "exp-discharge-84",
    "exp-discharge-71",
];
