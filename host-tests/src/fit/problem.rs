//! The Levenberg–Marquardt problem: bounded coordinates, finite-difference Jacobian with its
//! simulations in parallel.

use super::*;

/// A progress callback: called once per simulation the fit runs (from any thread).
pub type Tick = Arc<dyn Fn() + Send + Sync>;

/// Each log's start-P2 and start-LP corrections, bar.
type Offsets = Vec<[f64; 2]>;

/// The fit problem.
pub(super) struct Problem {
    pub(super) start: BenchFile,
    pub(super) params: Vec<Param>,
    pub(super) logs: Arc<Vec<Prepared>>,
    /// z = the parameters' bounded coordinates, then (if `offsets`) the start-P2 and start-LP
    /// corrections of each log, bar.
    pub(super) offsets: bool,
    pub(super) z: DVector<f64>,
    pub(super) progress: Option<Tick>,
    pub(super) evals: std::sync::atomic::AtomicUsize,
    /// Simulations the fit may still run (shared by its stages); `None`: no limit.
    pub(super) budget: Option<Arc<std::sync::atomic::AtomicIsize>>,
    /// Finite-difference steps wide enough to stand above the solver's noise
    /// ([`STEP_OF_RANGE`]): the covariance's and the plan's Jacobian, and the optimiser's on
    /// logs without an emptying (`fit`); otherwise 1e-4 of the bounded coordinate.
    pub(super) wide_steps: bool,
}

/// A parameter's finite-difference step, as a fraction of its range (cd: 1e-3, 0.6 % of the
/// reference bench's; precharge 0.12 bar). Narrower steps (1e-4 of the bounded coordinate,
/// about 5e-5 of the range, as before) let the adaptive solver's step-to-step noise through
/// as sensitivity: a charge with the valve closed, where no oil reaches the valve,
/// "determined" Cd to 1 % and η_v to 3e-4 from that noise alone — in the fit's σ and in the
/// plan's prediction. The optimiser takes them only on logs without an emptying (see `fit`). Forward differences over a step this size stay within 1 % of the slope
/// for these smooth responses, far inside what a σ needs.
pub const STEP_OF_RANGE: f64 = 1e-3;
/// The finite-difference step of a start-pressure correction, bar.
pub const STEP_BAR: f64 = 0.01;

/// A parameter's wide step in its bounded coordinate at `z`: [`STEP_OF_RANGE`] of its range in
/// its own unit, towards the interior (near a bound, a fixed step in z would span most of the
/// range on one side and stop at the bound on the other).
fn wide_step(p: &Param, z: f64) -> f64 {
    let x = from_z(p, z);
    let d = STEP_OF_RANGE * (p.hi - p.lo);
    let to = if x + d < p.hi - d { x + d } else { x - d };
    let h = to_z(p, to) - z;
    if h.abs() > 1e-12 {
        h
    } else {
        1e-4 * (1.0 + z.abs())
    }
}

impl Problem {
    /// The same parameters at the same point over other logs, outside any budget.
    pub(super) fn over(&self, logs: Vec<Prepared>) -> Problem {
        Problem {
            start: self.start.clone(),
            params: self.params.clone(),
            logs: Arc::new(logs),
            offsets: self.offsets,
            z: self.z.clone(),
            progress: self.progress.clone(),
            evals: Default::default(),
            budget: None,
            wide_steps: self.wide_steps,
        }
    }

    pub(super) fn bench_at(&self, z: &[f64]) -> Result<Bench, BenchError> {
        let mut f = self.start.clone();
        for (p, &zi) in self.params.iter().zip(z) {
            (p.set)(&mut f, from_z(p, zi));
        }
        Bench::from_file(f, "fit")
    }

    pub(super) fn offsets_of(&self, z: &[f64]) -> Vec<[f64; 2]> {
        if self.offsets {
            z[self.params.len()..]
                .chunks(2)
                .map(|c| [c[0], c.get(1).copied().unwrap_or(0.0)])
                .collect()
        } else {
            vec![[0.0; 2]; self.logs.len()]
        }
    }

    /// Runs (bench, log, start offsets) simulations in parallel.
    fn run_jobs(
        &self,
        benches: &[Option<Bench>],
        jobs: &[(usize, usize, [f64; 2])],
    ) -> Vec<Option<Vec<Truth>>> {
        // Past the budget every simulation "fails": Levenberg–Marquardt stops on the spot.
        if let Some(b) = &self.budget
            && b.fetch_sub(jobs.len() as isize, std::sync::atomic::Ordering::Relaxed)
                < jobs.len() as isize
        {
            return vec![None; jobs.len()];
        }
        let sims = jobs
            .par_iter()
            .map(|&(b, l, off)| {
                let r = benches[b]
                    .as_ref()
                    .and_then(|b| simulate_log_from(b, &self.logs[l], off).ok());
                if let Some(tick) = &self.progress {
                    tick();
                }
                r
            })
            .collect();
        self.evals
            .fetch_add(jobs.len(), std::sync::atomic::Ordering::Relaxed);
        sims
    }

    /// The residual vector from one simulation per log (plus the start-offset priors).
    fn assemble(&self, sims: &[&Vec<Truth>], offsets: &[[f64; 2]]) -> Vec<f64> {
        let mut out = Vec::new();
        for (l, sim) in sims.iter().enumerate() {
            residuals_of(&self.logs[l], sim, &mut out);
        }
        if self.offsets {
            out.extend(offsets.iter().flatten().map(|o| o / SIGMA_START_BAR));
        }
        out
    }

    /// Whether the budget of simulations has run out.
    fn budget_spent(&self) -> bool {
        self.budget
            .as_ref()
            .is_some_and(|b| b.load(std::sync::atomic::Ordering::Relaxed) < 0)
    }

    /// The length of the residual vector (see `assemble`).
    fn residual_len(&self) -> usize {
        let logs: usize = self
            .logs
            .iter()
            .map(|p| CHANNELS * p.idx.len() + usize::from(p.collapse.is_some()))
            .sum();
        logs + if self.offsets { 2 * self.logs.len() } else { 0 }
    }

    fn base(&self, z: &[f64]) -> Option<(Vec<Vec<Truth>>, Offsets)> {
        let offsets = self.offsets_of(z);
        let benches = [self.bench_at(z).ok()];
        let jobs: Vec<(usize, usize, [f64; 2])> =
            (0..self.logs.len()).map(|l| (0, l, offsets[l])).collect();
        let sims: Option<Vec<Vec<Truth>>> = self.run_jobs(&benches, &jobs).into_iter().collect();
        Some((sims?, offsets))
    }
}

/// Each residual of a trial point whose simulation fails: above any residual the fit produces
/// (flattened ones stay below [`ROBUST_SIGMAS`], a start correction's prior below 1e3 for any
/// correction under 300 bar).
const FAILED_RESIDUAL: f64 = 1e4;

/// σ of a log's start P2 as read from its first samples, bar (the prior on its correction).
pub const SIGMA_START_BAR: f64 = 0.3;

impl LeastSquaresProblem<f64, Dyn, Dyn> for Problem {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, z: &DVector<f64>) {
        self.z.copy_from(z);
    }

    fn params(&self) -> DVector<f64> {
        self.z.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let z: Vec<f64> = self.z.iter().copied().collect();
        match self.base(&z) {
            Some((sims, offsets)) => {
                let refs: Vec<&Vec<Truth>> = sims.iter().collect();
                Some(DVector::from_vec(self.assemble(&refs, &offsets)))
            }
            // Past the budget: stop (see `run_jobs`).
            None if self.budget_spent() => None,
            // A trial point the plant cannot start from (a start correction that takes P2 below
            // vacuum) is a step too far, not the end of the fit: a residual larger than any the
            // fit can produce makes Levenberg–Marquardt refuse it and shrink its step. (`None`
            // would end the fit there, with the refused point as its result.)
            None => Some(DVector::from_element(self.residual_len(), FAILED_RESIDUAL)),
        }
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        // Forward differences. A parameter's column re-simulates every log; a log's start-P2 or
        // start-LP correction re-simulates that log only.
        let z: Vec<f64> = self.z.iter().copied().collect();
        let ng = self.params.len();
        let nl = self.logs.len();
        let h: Vec<f64> = z
            .iter()
            .enumerate()
            .map(|(j, &zi)| {
                let narrow = 1e-4 * (1.0 + zi.abs());
                match self.params.get(j) {
                    _ if !self.wide_steps => narrow,
                    Some(p) => wide_step(p, zi),
                    None => STEP_BAR,
                }
            })
            .collect();
        let offsets = self.offsets_of(&z);
        let mut benches = vec![self.bench_at(&z).ok()];
        for j in 0..ng {
            let mut zj = z.clone();
            zj[j] += h[j];
            benches.push(self.bench_at(&zj).ok());
        }
        let mut jobs: Vec<(usize, usize, [f64; 2])> = Vec::new();
        for b in 0..=ng {
            for (l, off) in offsets.iter().enumerate() {
                jobs.push((b, l, *off));
            }
        }
        if self.offsets {
            for (l, off) in offsets.iter().enumerate() {
                for k in 0..2 {
                    let mut o = *off;
                    o[k] += h[ng + 2 * l + k];
                    jobs.push((0, l, o));
                }
            }
        }
        let sims: Vec<Vec<Truth>> = self
            .run_jobs(&benches, &jobs)
            .into_iter()
            .collect::<Option<_>>()?;
        let base: Vec<&Vec<Truth>> = sims[..nl].iter().collect();
        let r0 = self.assemble(&base, &offsets);
        let mut jac = DMatrix::zeros(r0.len(), z.len());
        let mut fill = |j: usize, r: Vec<f64>| {
            for i in 0..r0.len() {
                jac[(i, j)] = (r[i] - r0[i]) / h[j];
            }
        };
        for j in 0..ng {
            let col: Vec<&Vec<Truth>> = sims[(j + 1) * nl..(j + 2) * nl].iter().collect();
            fill(j, self.assemble(&col, &offsets));
        }
        if self.offsets {
            for l in 0..nl {
                for k in 0..2 {
                    let mut col = base.clone();
                    col[l] = &sims[(ng + 1) * nl + 2 * l + k];
                    let mut off = offsets.clone();
                    off[l][k] += h[ng + 2 * l + k];
                    fill(ng + 2 * l + k, self.assemble(&col, &off));
                }
            }
        }
        Some(jac)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A trial whose start correction takes P2 below vacuum is a refused step (residuals above
    /// any real one, of the problem's length), not the end of the fit; past the budget the
    /// residuals are `None`, which ends it. (Before, the failed trial also returned `None`:
    /// the fit ended on it and reported it.)
    #[test]
    fn a_trial_the_plant_cannot_start_from_is_refused_not_the_end() {
        let bench = Bench::reference();
        let mut s = crate::sim::scenario::builtin_named("exp-discharge-71").unwrap();
        s.duration_s = 5.0;
        let dir = std::env::temp_dir().join(format!("pto-fit-trial-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let log = synth_scenario_log(&bench, &s, 10.0, SensorSpec::default(), 1, &dir).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        let logs = prepare(vec![log], 0.5, &sensor_noise());
        let p2_start = logs[0].p2_start_bar;
        let params = params(&["cd".to_string()], &bench.file).unwrap();
        let z_cd = to_z(&params[0], (params[0].get)(&bench.file));
        let budget = Arc::new(std::sync::atomic::AtomicIsize::new(100));
        let mut problem = Problem {
            start: bench.file.clone(),
            params,
            logs: Arc::new(logs),
            offsets: true,
            z: DVector::from_vec(vec![z_cd, 0.0, 0.0]),
            progress: None,
            evals: Default::default(),
            budget: Some(budget.clone()),
            wide_steps: false,
        };
        let fine = problem.residuals().expect("a physical start simulates");
        assert_eq!(fine.len(), problem.residual_len());
        let worst = fine.amax();
        // P2 started 5 bar below vacuum.
        problem.z[1] = -(p2_start + 6.0);
        let refused = problem.residuals().expect("a refused step, not the end");
        println!(
            "largest residual at the start {worst:.2}; the non-physical trial's {:.0}",
            refused.amin()
        );
        assert_eq!(refused.len(), fine.len());
        assert!(refused.amin() > 100.0 * worst.max(ROBUST_SIGMAS));
        budget.store(-1, std::sync::atomic::Ordering::Relaxed);
        problem.z[1] = 0.0;
        assert!(
            problem.residuals().is_none(),
            "past the budget the fit stops"
        );
    }
}
