//! What a log can tell the fit before it is recorded: the Fisher information of the parameters
//! from the fit's own residuals (`pto plan`).
//!
//! For residuals r(θ) in units of white noise, the covariance of the least-squares estimate is
//! (JᵀJ)⁻¹ with J = ∂r/∂θ at the truth — the same matrix the fit inverts for its σ. A log made
//! without noise from the bench the plan starts from gives J through the fit's own
//! [`Problem`]: its residuals (P2, speed and LP at every residual sample, the emptying's one
//! residual), its weights (the noise), its per-log start-P2 and start-LP corrections with their
//! priors, and its forward differences with their simulations in parallel. Finite differences
//! rather than diffsol's forward sensitivities: the residuals pass through the emptying's
//! detection and the tanh flattening, which are not in the ODE; and the fit's own Jacobian is
//! the one whose inverse it reports, so the plan predicts exactly what the fit will say.

use super::*;

/// Information on `params` (in their physical units: the inverse is their covariance) from
/// one log `prepared` without noise on the bench `start` describes. Each log's start-P2 and
/// start-LP corrections, which the fit's last stage estimates with it, are marginalised out
/// (the Schur complement): information they absorb is not counted.
pub fn information(
    start: &BenchFile,
    params: &[Param],
    prepared: Prepared,
    progress: Option<Tick>,
) -> Result<DMatrix<f64>, FitError> {
    let np = params.len();
    let mut z: Vec<f64> = params.iter().map(|p| to_z(p, (p.get)(start))).collect();
    z.extend([0.0, 0.0]);
    let problem = Problem {
        start: start.clone(),
        params: params.to_vec(),
        logs: Arc::new(vec![prepared]),
        offsets: true,
        z: DVector::from_vec(z.clone()),
        progress,
        evals: Default::default(),
        budget: None,
        wide_steps: true,
    };
    let mut jac = problem.jacobian().ok_or(FitError::Jacobian)?;
    for (j, p) in params.iter().enumerate() {
        let s = dx_dz(p, z[j]);
        jac.column_mut(j).unscale_mut(s);
    }
    let full = jac.transpose() * &jac;
    let a = full.view((0, 0), (np, np)).into_owned();
    let b = full.view((0, np), (np, 2)).into_owned();
    let c = full.view((np, np), (2, 2)).into_owned();
    // The corrections' own block always holds their priors (1/0.3² bar⁻² each): invertible.
    let c_inv = c.try_inverse().ok_or(FitError::Jacobian)?;
    Ok(a - &b * c_inv * b.transpose())
}

/// `info`'s leading block for `params` with a weak prior on each (its whole range as one σ: a
/// parameter the logs say nothing of keeps a σ of its range, not an infinite one).
pub fn with_priors(info: &DMatrix<f64>, params: &[Param]) -> DMatrix<f64> {
    let np = params.len();
    let mut f = info.view((0, 0), (np, np)).into_owned();
    for (j, p) in params.iter().enumerate() {
        f[(j, j)] += (p.hi - p.lo).powi(-2);
    }
    f
}

/// σ and correlations from an information matrix, with the weak priors of [`with_priors`].
pub fn covariance_of(info: &DMatrix<f64>, params: &[Param]) -> (Vec<f64>, Vec<Vec<f64>>) {
    let f = with_priors(info, params);
    let n = params.len();
    let cov = f
        .clone()
        .cholesky()
        .map(|c| c.inverse())
        .unwrap_or_else(|| {
            f.pseudo_inverse(1e-300)
                .unwrap_or_else(|_| DMatrix::zeros(n, n))
        });
    let sigma: Vec<f64> = (0..n).map(|j| cov[(j, j)].max(0.0).sqrt()).collect();
    let corr = (0..n)
        .map(|i| {
            (0..n)
                .map(|j| {
                    if i == j {
                        1.0
                    } else {
                        cov[(i, j)] / (sigma[i] * sigma[j]).max(f64::MIN_POSITIVE)
                    }
                })
                .collect()
        })
        .collect();
    (sigma, corr)
}
