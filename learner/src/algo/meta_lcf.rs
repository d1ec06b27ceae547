//! The meta-gradient of the learned LCFs (CoPO's global coordination, Peng et al. 2021),
//! written once for CoPO's (μ, σ) and the dynamic LCF's f_ψ.
//!
//! ```text
//! ψ: the LCF parameters; A_C(ψ): the coordinated advantage the PPO update ascended;
//! θ, θ': the policy before and after that update; Â_G: the standardised global advantage.
//! J_G(θ') = mean_k min(ρ_k·Â_G,k, clip(ρ_k, 1±ε)·Â_G,k),  ρ_k = π_θ'(a_k|s_k) / π_b(a_k|s_k)
//! one policy-gradient step θ' = θ + η·∇θ mean_k[A_C,k(ψ)·log π_θ(a_k|s_k)], so (first order)
//!     ∇ψ J_G = η·mean_k[c_k·∇ψ A_C,k(ψ)]   with
//!     g   = ∇θ' J_G(θ')
//!     c_k = ∇θ log π_θ(a_k|s_k) · g        (a Jacobian-vector product: double backward)
//! repeat `meta_iterations` times, over shuffled minibatches:
//!     Adam ascent step on ψ along ∇ψ mean_{k∈mb}[c_k·A_C,k(ψ)] / s
//! ```
//!
//! Cross-fitting (`meta_cross_fit`): ∇ψ J_G is the product of two gradients of expectations,
//! g and ∇θ of the inner objective. Estimated from the same rows, it carries each row's own
//! term Â_G,k·A_C,k·|∇θ log π_k|², a covariance of the two advantages rather than a gradient:
//! the scene's mean reward and the neighbourhood's covary through everything the scene shares,
//! whatever the action, so that term pulls φ towards the neighbourhood. Cross-fitted, the
//! batch's fragments (each one scene's window) alternate between two folds and c_k takes g
//! from the other fold, so no row meets its own advantage twice.
//!
//! η only scales the gradient, which Adam does not see, so it is left out; s, the batch's
//! standard deviation of A_C (a constant), makes the step follow the standardised advantage
//! the PPO loss used, as CoPO does. CoPO multiplies batch means (g·mean_k ∇θ log π_k times
//! mean_k ∇ψ A_C,k); the per-sample form above is the chain rule itself.

use rand_chacha::ChaCha8Rng;
use tch::{Device, Tensor};

use junction_common::fragment::RolloutFragment;
use junction_common::policy::{GaussianPolicy, gaussian_log_prob};

use super::AlgoError;
use super::batch::{TrainBatch, epoch_minibatches, standardize};
use super::ppo::clipped_surrogate;
use crate::optim::Adam;

/// ∇ of a scalar `objective` with respect to `params`, without touching their `.grad`.
pub fn objective_gradient(
    objective: &Tensor,
    params: &[Tensor],
) -> Result<Vec<Tensor>, tch::TchError> {
    Tensor::f_run_backward(&[objective], params, false, false)
}

/// c_k = ∇θ log_probs[k] · direction for every k, exactly: differentiating the probe-weighted
/// sum Σ u_k·log_probs[k] gives Σ u_k·∇θ log_probs[k] (kept differentiable), whose dot product
/// with the direction is linear in u with gradient c.
pub fn log_prob_jvp(
    log_probs: &Tensor,
    params: &[Tensor],
    direction: &[Tensor],
) -> Result<Tensor, tch::TchError> {
    let probe = log_probs.zeros_like().detach().set_requires_grad(true);
    let weighted = (&probe * log_probs).sum(log_probs.kind());
    let grads = Tensor::f_run_backward(&[&weighted], params, true, true)?;
    let dot = grads
        .iter()
        .zip(direction)
        .filter(|(g, _)| g.defined())
        .map(|(g, d)| (g * d).sum(log_probs.kind()))
        .fold(log_probs.zeros_like().sum(log_probs.kind()), |a, b| a + b);
    let mut c = Tensor::f_run_backward(&[&dot], &[&probe], false, false)?;
    Ok(c.remove(0).detach())
}

/// Consecutive batch rows that take the global objective's gradient g from the same fold.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    pub start: usize,
    pub len: usize,
    pub fold: usize,
}

/// The batch's rows (alive cells of `fragments`, in order) as segments: one segment of fold 0
/// estimated from the same rows, or, cross-fitted, one per fragment with folds alternating
/// (a batch of one fragment is split into its earlier and later steps).
pub fn segments(fragments: &[RolloutFragment], cross_fit: bool) -> Vec<Segment> {
    let lens: Vec<usize> = fragments
        .iter()
        .map(|f| f.alive.iter().filter(|&&a| a).count())
        .filter(|&len| len > 0)
        .collect();
    let total: usize = lens.iter().sum();
    let whole = Segment {
        start: 0,
        len: total,
        fold: 0,
    };
    if !cross_fit || total < 2 {
        return vec![whole];
    }
    if lens.len() == 1 {
        let half = total / 2;
        return vec![
            Segment { len: half, ..whole },
            Segment {
                start: half,
                len: total - half,
                fold: 1,
            },
        ];
    }
    let mut start = 0;
    lens.iter()
        .enumerate()
        .map(|(i, &len)| {
            let segment = Segment {
                start,
                len,
                fold: i % 2,
            };
            start += len;
            segment
        })
        .collect()
}

/// c_k for every row of `batch`: the policy `before` the update, the policy `after` it, the
/// batch's global advantages (standardised here over the whole batch), the rows' `segments`
/// (in row order, covering the batch; [`segments`]): g is the mean over a fold's rows, and a
/// row's c_k takes it from the other of two folds, or from its own where there is one. Rows
/// are taken `chunk` at a time to bound the memory of the double backward.
pub fn sensitivities(
    before: &GaussianPolicy,
    after: &GaussianPolicy,
    batch: &TrainBatch,
    global_advantages: &Tensor,
    clip: f64,
    chunk: usize,
    segments: &[Segment],
) -> Result<Tensor, AlgoError> {
    let chunk = chunk.max(1);
    let global = standardize(global_advantages);
    let g = fold_gradients(after, batch, &global, clip, chunk, segments)?;
    let params_before = before.trainable();
    let mut c = Vec::new();
    for segment in segments {
        let direction = &g[if g.len() == 1 { 0 } else { 1 - segment.fold }];
        for (start, len) in chunks(*segment, chunk) {
            c.push(log_prob_jvp(
                &log_probs(before, batch, start, len),
                &params_before,
                direction,
            )?);
        }
    }
    Ok(Tensor::f_cat(&c, 0)?)
}

/// g per fold: the gradient under the policy `after` the update of the global objective J_G
/// (the clipped surrogate on the `global` advantages) over the fold's rows. Summed chunk by
/// chunk, each weighted by its share of the fold, so g is the fold's mean however it is cut.
fn fold_gradients(
    after: &GaussianPolicy,
    batch: &TrainBatch,
    global: &Tensor,
    clip: f64,
    chunk: usize,
    segments: &[Segment],
) -> Result<Vec<Vec<Tensor>>, AlgoError> {
    let fold_rows = fold_rows(segments);
    let params_after = after.trainable();
    let mut g: Vec<Vec<Tensor>> = (0..fold_rows.len())
        .map(|_| params_after.iter().map(Tensor::zeros_like).collect())
        .collect();
    for segment in segments {
        for (start, len) in chunks(*segment, chunk) {
            let log_probs = log_probs(after, batch, start, len);
            let share = len as f64 / fold_rows[segment.fold] as f64;
            let objective = -clipped_surrogate(
                &log_probs,
                &batch.old_log_probs.narrow(0, start, len),
                &global.narrow(0, start, len),
                clip,
            )
            .loss
                * share;
            for (total, part) in g[segment.fold]
                .iter_mut()
                .zip(objective_gradient(&objective, &params_after)?)
            {
                *total += part;
            }
        }
    }
    Ok(g)
}

/// Rows in each fold, indexed by fold: what a chunk's share of its fold's mean is taken of.
fn fold_rows(segments: &[Segment]) -> Vec<usize> {
    let folds = segments.iter().map(|s| s.fold + 1).max().unwrap_or(0);
    let mut fold_rows = vec![0usize; folds];
    for segment in segments {
        fold_rows[segment.fold] += segment.len;
    }
    fold_rows
}

/// `segment`'s rows as (start, len) runs of at most `chunk`: what bounds the memory of the
/// double backward.
fn chunks(segment: Segment, chunk: usize) -> impl Iterator<Item = (i64, i64)> {
    (segment.start..segment.start + segment.len)
        .step_by(chunk)
        .map(move |start| {
            (
                start as i64,
                chunk.min(segment.start + segment.len - start) as i64,
            )
        })
}

/// log π(a|s) under `policy` of the batch rows `start..start + len`; the batch holds raw
/// observations, so the policy's statistics normalise them first.
fn log_probs(policy: &GaussianPolicy, batch: &TrainBatch, start: i64, len: i64) -> Tensor {
    let obs = policy.normalize(&batch.obs.narrow(0, start, len));
    let (mean, log_std) = policy.distribution(&obs);
    gaussian_log_prob(&mean, &log_std, &batch.actions.narrow(0, start, len))
}

/// Adam ascent on the parameters `adam` holds: `iterations` passes over shuffled minibatches
/// of `rows` rows, each step along the gradient of `objective(minibatch indices)`, a scalar to
/// maximise. Returns the mean objective over the steps taken (non-finite ones are skipped).
pub fn ascend(
    adam: &mut Adam,
    iterations: usize,
    rows: usize,
    minibatch: usize,
    rng: &mut ChaCha8Rng,
    device: Device,
    objective: impl Fn(&Tensor) -> Tensor,
) -> Result<f64, AlgoError> {
    let (mut total, mut steps) = (0.0, 0usize);
    for _ in 0..iterations {
        for idx in epoch_minibatches(rows, minibatch, rng, device) {
            let value = objective(&idx);
            let scalar = f64::try_from(&value)?;
            if !scalar.is_finite() {
                continue;
            }
            adam.zero_grad();
            (-value).backward();
            adam.step();
            total += scalar;
            steps += 1;
        }
    }
    Ok(total / steps.max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::testing::{F64, Tiny, t};
    use junction_common::fragment::RolloutFragment;
    use tch::Kind;

    fn alive(pattern: &[bool]) -> RolloutFragment {
        RolloutFragment {
            alive: pattern.to_vec(),
            ..RolloutFragment::default()
        }
    }

    #[test]
    fn segments_follow_the_fragments_rows_and_alternate_folds_when_cross_fitted() {
        let fragments = [
            alive(&[true, false, true]),
            alive(&[false, false]),
            alive(&[true; 3]),
            alive(&[true]),
        ];
        let at = |start, len, fold| Segment { start, len, fold };
        assert_eq!(segments(&fragments, false), [at(0, 6, 0)]);
        assert_eq!(
            segments(&fragments, true),
            [at(0, 2, 0), at(2, 3, 1), at(5, 1, 0)]
        );
        // One fragment: its earlier and later rows.
        assert_eq!(segments(&fragments[2..3], true), [at(0, 1, 0), at(1, 2, 1)]);
    }

    #[test]
    fn cross_fitted_rows_are_steered_only_by_the_other_folds_global_advantages() {
        let _rng = crate::test_rng::seeded(13);
        let rows = 10;
        let policy = GaussianPolicy::new(Device::Cpu, 3, 2, &[8], -0.5);
        let obs = Tensor::randn([rows, 3], (Kind::Float, Device::Cpu));
        let actions = Tensor::randn([rows, 2], (Kind::Float, Device::Cpu));
        let (mean, log_std) = policy.distribution(&policy.normalize(&obs));
        let batch = TrainBatch {
            critic_inputs: obs.zeros_like(),
            old_log_probs: gaussian_log_prob(&mean, &log_std, &actions).detach() - 0.05,
            obs,
            actions,
            heads: Vec::new(),
            neighbour_counts: vec![0; rows as usize],
            len: rows as usize,
        };
        let global = Tensor::randn([rows], (Kind::Float, Device::Cpu));
        // Fold 0's advantages shuffled among its rows: the batch's mean and std (and so fold
        // 1's standardised advantages) stay, fold 0's gradient g changes.
        let shuffled =
            global.index_select(0, &Tensor::from_slice(&[3i64, 0, 1, 2, 4, 5, 6, 7, 8, 9]));
        let folds = [
            Segment {
                start: 0,
                len: 4,
                fold: 0,
            },
            Segment {
                start: 4,
                len: 6,
                fold: 1,
            },
        ];
        let whole = [Segment {
            start: 0,
            len: 10,
            fold: 0,
        }];
        let c = |global: &Tensor, segments: &[Segment]| {
            let c = sensitivities(&policy, &policy, &batch, global, 0.3, 3, segments).unwrap();
            Vec::<f32>::try_from(c).unwrap()
        };
        let differs = |a: &[f32], b: &[f32]| {
            a.iter()
                .zip(b)
                .any(|(x, y)| (x - y).abs() > 1e-6 * (1.0 + x.abs()))
        };
        let (before, after) = (c(&global, &folds), c(&shuffled, &folds));
        assert!(
            !differs(&before[..4], &after[..4]),
            "{before:?} vs {after:?}"
        );
        assert!(
            differs(&before[4..], &after[4..]),
            "fold 1 ignored fold 0's g"
        );
        let (before, after) = (c(&global, &whole), c(&shuffled, &whole));
        assert!(
            differs(&before[..4], &after[..4]),
            "one fold: every row sees its own g"
        );
    }

    #[test]
    fn the_jacobian_vector_product_is_the_directional_derivative_of_each_log_prob() {
        let _rng = crate::test_rng::seeded(12);
        let theta = Tiny {
            w1: Tensor::randn([3, 4], F64).set_requires_grad(true),
            w2: Tensor::randn([4, 2], F64).set_requires_grad(true),
            log_std: t(&[0.1, -0.2], &[2]).set_requires_grad(true),
        };
        let (obs, actions) = (Tensor::randn([5, 3], F64), Tensor::randn([5, 2], F64));
        let direction: Vec<Tensor> = theta
            .params()
            .iter()
            .map(|p| Tensor::randn(p.size(), F64))
            .collect();
        let c = log_prob_jvp(
            &theta.log_probs(&obs, &actions),
            &theta.params(),
            &direction,
        )
        .unwrap();
        let h = 1e-6;
        let at = |eta: f64| theta.moved(&direction, eta).log_probs(&obs, &actions);
        let numeric = (at(h) - at(-h)) / (2.0 * h);
        let error = f64::try_from((&c - &numeric).abs().max()).unwrap();
        assert!(error < 1e-6, "{c} vs {numeric}");
    }
}
