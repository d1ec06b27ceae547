//! From fragments to a flat training batch, and minibatch order: written once for every
//! on-policy algorithm.

use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Tensor};

use junction_common::fragment::RolloutFragment;

use super::gae::{Estimates, Trajectories, gae};

/// Alive cells of every fragment, in (fragment, step, slot) order, on the training device.
pub struct TrainBatch {
    /// Raw observations [n, obs_dim]; algorithms normalise with the policy's statistics.
    pub obs: Tensor,
    pub actions: Tensor,
    pub old_log_probs: Tensor,
    pub advantages: Tensor,
    pub returns: Tensor,
    pub old_values: Tensor,
    pub len: usize,
}

/// Observations of the alive cells of `fragments`, row-major.
pub fn alive_observations(fragments: &[RolloutFragment]) -> Vec<f32> {
    let mut rows = Vec::new();
    for f in fragments {
        for (cell, _) in f.alive.iter().enumerate().filter(|(_, a)| **a) {
            rows.extend_from_slice(&f.obs[cell * f.obs_dim..(cell + 1) * f.obs_dim]);
        }
    }
    rows
}

/// Evaluates `value_of` (raw obs [m, obs_dim] → values [m]) on every alive cell and bootstrap
/// observation in one pass, then runs GAE per fragment.
pub fn assemble(
    fragments: &[RolloutFragment],
    value_of: impl Fn(&Tensor) -> Tensor,
    gamma: f32,
    lambda: f32,
    device: Device,
) -> Result<TrainBatch, tch::TchError> {
    let obs_dim = fragments.first().map_or(1, |f| f.obs_dim);
    let mut rows = alive_observations(fragments);
    let alive_rows = rows.len() / obs_dim;
    for f in fragments {
        for slot in (0..f.agents).filter(|&s| f.needs_bootstrap(s)) {
            rows.extend_from_slice(&f.bootstrap_obs[slot * obs_dim..(slot + 1) * obs_dim]);
        }
    }
    let all_rows = rows.len() / obs_dim;
    let values: Vec<f32> = tch::no_grad(|| {
        let obs = Tensor::from_slice(&rows)
            .reshape([all_rows as i64, obs_dim as i64])
            .to_device(device);
        Vec::<f32>::try_from(
            value_of(&obs)
                .to_device(Device::Cpu)
                .to_kind(Kind::Float)
                .flatten(0, -1),
        )
    })?;
    let (alive_values, bootstrap_pool) = values.split_at(alive_rows);

    let mut actions = Vec::new();
    let mut old_log_probs = Vec::new();
    let mut advantages = Vec::with_capacity(alive_rows);
    let mut returns = Vec::with_capacity(alive_rows);
    let mut old_values = Vec::with_capacity(alive_rows);
    let (mut next_alive, mut next_bootstrap) = (alive_values.iter(), bootstrap_pool.iter());
    for f in fragments {
        let cells = f.steps * f.agents;
        let mut cell_values = vec![0.0f32; cells];
        for (cell, value) in cell_values.iter_mut().enumerate() {
            if f.alive[cell] {
                *value = next_alive.next().copied().unwrap_or(0.0);
            }
        }
        let bootstrap_values: Vec<f32> = (0..f.agents)
            .map(|s| {
                if f.needs_bootstrap(s) {
                    next_bootstrap.next().copied().unwrap_or(0.0)
                } else {
                    0.0
                }
            })
            .collect();
        let Estimates {
            advantages: adv,
            returns: ret,
        } = gae(
            &Trajectories {
                steps: f.steps,
                agents: f.agents,
                rewards: &f.rewards,
                dones: &f.dones,
                alive: &f.alive,
                values: &cell_values,
                bootstrap_values: &bootstrap_values,
            },
            gamma,
            lambda,
        );
        for cell in (0..cells).filter(|&c| f.alive[c]) {
            actions.extend_from_slice(&f.actions[cell * f.action_dim..(cell + 1) * f.action_dim]);
            old_log_probs.push(f.log_probs[cell]);
            advantages.push(adv[cell]);
            returns.push(ret[cell]);
            old_values.push(cell_values[cell]);
        }
    }
    let action_dim = fragments.first().map_or(1, |f| f.action_dim) as i64;
    let n = alive_rows as i64;
    let to = |v: &[f32]| Tensor::from_slice(v).to_device(device);
    Ok(TrainBatch {
        obs: Tensor::from_slice(&rows[..alive_rows * obs_dim])
            .reshape([n, obs_dim as i64])
            .to_device(device),
        actions: to(&actions).reshape([n, action_dim]),
        old_log_probs: to(&old_log_probs),
        advantages: to(&advantages),
        returns: to(&returns),
        old_values: to(&old_values),
        len: alive_rows,
    })
}

/// Index tensors of one epoch's minibatches: a fresh permutation cut into `size` chunks (the
/// last may be shorter).
pub fn epoch_minibatches(
    len: usize,
    size: usize,
    rng: &mut ChaCha8Rng,
    device: Device,
) -> Vec<Tensor> {
    let mut order: Vec<i64> = (0..len as i64).collect();
    order.shuffle(rng);
    order
        .chunks(size.max(1))
        .map(|chunk| Tensor::from_slice(chunk).to_device(device))
        .collect()
}

/// Zero mean, unit variance (per minibatch, as in well-tuned PPO implementations).
pub fn standardize(x: &Tensor) -> Tensor {
    if x.size()[0] < 2 {
        return x - x.mean(Kind::Float);
    }
    (x - x.mean(Kind::Float)) / (x.std(true) + 1e-8)
}

/// 1 − Var(returns − values) / Var(returns): how much of the return the critic explains.
pub fn explained_variance(values: &Tensor, returns: &Tensor) -> f64 {
    let var_returns = f64::try_from(returns.var(false)).unwrap_or(0.0);
    if var_returns <= 0.0 || returns.size()[0] < 2 {
        return 0.0;
    }
    let var_residual = f64::try_from((returns - values).var(false)).unwrap_or(f64::NAN);
    1.0 - var_residual / var_returns
}
