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

    fn base(&self, z: &[f64]) -> Option<(Vec<Vec<Truth>>, Offsets)> {
        let offsets = self.offsets_of(z);
        let benches = [self.bench_at(z).ok()];
        let jobs: Vec<(usize, usize, [f64; 2])> =
            (0..self.logs.len()).map(|l| (0, l, offsets[l])).collect();
        let sims: Option<Vec<Vec<Truth>>> = self.run_jobs(&benches, &jobs).into_iter().collect();
        Some((sims?, offsets))
    }
}

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
        let (sims, offsets) = self.base(&z)?;
        let refs: Vec<&Vec<Truth>> = sims.iter().collect();
        Some(DVector::from_vec(self.assemble(&refs, &offsets)))
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        // Forward differences. A parameter's column re-simulates every log; a log's start-P2 or
        // start-LP correction re-simulates that log only.
        let z: Vec<f64> = self.z.iter().copied().collect();
        let ng = self.params.len();
        let nl = self.logs.len();
        let h: Vec<f64> = z.iter().map(|zi| 1e-4 * (1.0 + zi.abs())).collect();
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
