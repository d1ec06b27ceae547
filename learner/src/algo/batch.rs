//! From fragments to a flat training batch, and minibatch order: written once for every
//! on-policy algorithm.

use std::borrow::Cow;

use rand::Rng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Tensor};

use junction_common::fragment::RolloutFragment;

use super::gae::{Estimates, Trajectories, gae};
use super::phases::Phases;

/// Alive cells of every fragment, in (fragment, step, slot) order, on the training device.
pub struct TrainBatch {
    /// Raw observations [n, obs_dim]; algorithms normalise with the policy's statistics.
    pub obs: Tensor,
    /// The critics' input rows [n, width], built by the algorithm's [`CriticInput`] from
    /// normalised observations (fixed for the whole update, like the statistics).
    pub critic_inputs: Tensor,
    pub actions: Tensor,
    pub old_log_probs: Tensor,
    /// One per [`Head`] given to [`assemble`], in that order.
    pub heads: Vec<HeadEstimates>,
    /// Live neighbours of each row's agent at its step (host side, for reports).
    pub neighbour_counts: Vec<usize>,
    pub len: usize,
}

/// What GAE made of one value head's reward signal, per row.
pub struct HeadEstimates {
    pub advantages: Tensor,
    pub returns: Tensor,
    pub old_values: Tensor,
}

/// A value head: a reward signal, the critic that values it, and its discount.
pub struct Head<'a> {
    /// The signal for every cell of each fragment, in the fragments' order.
    pub rewards: Vec<Cow<'a, [f32]>>,
    /// Critic-input rows → values [m].
    pub value: Box<dyn Fn(&Tensor) -> Tensor + 'a>,
    pub gamma: f32,
    /// The return goes on with the scene after the agent ends ([`super::gae::gae`]).
    pub outlives_agent: bool,
}

/// A fragment with its observations normalised by the policy's statistics: what critic inputs
/// are built from, so the critic sees the same scale as the actor.
pub struct NormalizedFragment<'a> {
    pub raw: &'a RolloutFragment,
    /// Normalised `raw.obs`, every cell (empty ones too).
    pub obs: Vec<f32>,
    /// Normalised `raw.bootstrap_obs`.
    pub bootstrap_obs: Vec<f32>,
}

impl NormalizedFragment<'_> {
    pub fn obs(&self, t: usize, slot: usize) -> &[f32] {
        let (i, d) = (self.raw.index(t, slot), self.raw.obs_dim);
        &self.obs[i * d..(i + 1) * d]
    }

    pub fn action(&self, t: usize, slot: usize) -> &[f32] {
        let (i, d) = (self.raw.index(t, slot), self.raw.action_dim);
        &self.raw.actions[i * d..(i + 1) * d]
    }

    /// Neighbours of `slot` at step `t` (nearest first) that hold an agent at `t`; the filter
    /// keeps a malformed list from feeding an empty cell's zeros to the critic.
    pub fn live_neighbours(&self, t: usize, slot: usize) -> impl Iterator<Item = usize> + '_ {
        live_neighbours(self.raw, t, slot)
    }
}

/// What the critic sees for one agent: the one thing the PPO algorithms with parameter sharing
/// differ in (IPPO: its own observation; CCPPO: plus its neighbours').
pub trait CriticInput {
    /// Values per row for a run's observation and action sizes.
    fn width(&self, obs_dim: usize, action_dim: usize) -> usize;
    /// Appends the row of `slot` at step `t` with `own` as its own (normalised) observation.
    /// For the bootstrap value after the fragment `own` is the bootstrap observation and `t`
    /// the last step, whose neighbourhood stands in for the unseen next one.
    fn row(&self, f: &NormalizedFragment, own: &[f32], t: usize, slot: usize, out: &mut Vec<f32>);
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

/// `normalize` applied to `rows` (row-major, `dim` wide) on `device`, back on the host.
fn normalized(
    rows: &[f32],
    dim: usize,
    normalize: &impl Fn(&Tensor) -> Tensor,
    device: Device,
) -> Result<Vec<f32>, tch::TchError> {
    let t = Tensor::from_slice(rows)
        .reshape([(rows.len() / dim) as i64, dim as i64])
        .to_device(device);
    Vec::<f32>::try_from(
        normalize(&t)
            .to_device(Device::Cpu)
            .to_kind(Kind::Float)
            .flatten(0, -1),
    )
}

/// Builds the critic rows of every alive cell and of every bootstrap observation once with
/// `input` (from observations passed through `normalize`), then for each head evaluates its
/// critic on all of them in one pass and runs GAE per fragment on its reward signal.
pub fn assemble(
    fragments: &[RolloutFragment],
    input: &impl CriticInput,
    heads: &[Head],
    normalize: impl Fn(&Tensor) -> Tensor,
    lambda: f32,
    device: Device,
    phases: &mut Phases,
) -> Result<TrainBatch, tch::TchError> {
    let obs_dim = fragments.first().map_or(1, |f| f.obs_dim);
    let action_dim = fragments.first().map_or(1, |f| f.action_dim);
    let width = input.width(obs_dim, action_dim);
    let (mut rows, bootstrap_rows) = phases.time("assembly: critic input rows", || {
        tch::no_grad(|| critic_rows(fragments, input, &normalize, obs_dim, device))
    })?;
    let alive_rows = rows.len() / width;
    rows.extend_from_slice(&bootstrap_rows);
    let all_rows = rows.len() / width;
    let critic_inputs = Tensor::from_slice(&rows)
        .reshape([all_rows as i64, width as i64])
        .to_device(device);
    let n = alive_rows as i64;
    let to = |v: &[f32]| Tensor::from_slice(v).to_device(device);
    let mut estimates = Vec::with_capacity(heads.len());
    for head in heads {
        let values = phases.time("assembly: value estimates", || {
            head_values(head, &critic_inputs)
        })?;
        let (advantages, returns, old_values) = phases.time("assembly: GAE", || {
            head_estimates(fragments, head, &values, alive_rows, lambda)
        });
        estimates.push(HeadEstimates {
            advantages: to(&advantages),
            returns: to(&returns),
            old_values: to(&old_values),
        });
    }
    phases.time("assembly: batch tensors", || {
        let (obs, actions, old_log_probs) = alive_samples(fragments, alive_rows * obs_dim);
        Ok(TrainBatch {
            obs: to(&obs).reshape([n, obs_dim as i64]),
            critic_inputs: critic_inputs.narrow(0, 0, n),
            actions: to(&actions).reshape([n, action_dim as i64]),
            old_log_probs: to(&old_log_probs),
            heads: estimates,
            neighbour_counts: alive_neighbour_counts(fragments),
            len: alive_rows,
        })
    })
}

/// The critic rows of every alive cell, then (apart) of every bootstrap observation, built
/// once for all heads: every critic then values the same rows in one pass.
fn critic_rows(
    fragments: &[RolloutFragment],
    input: &impl CriticInput,
    normalize: &impl Fn(&Tensor) -> Tensor,
    obs_dim: usize,
    device: Device,
) -> Result<(Vec<f32>, Vec<f32>), tch::TchError> {
    let (mut rows, mut bootstrap_rows) = (Vec::new(), Vec::new());
    for raw in fragments {
        let f = NormalizedFragment {
            raw,
            obs: normalized(&raw.obs, obs_dim, normalize, device)?,
            bootstrap_obs: normalized(&raw.bootstrap_obs, obs_dim, normalize, device)?,
        };
        for t in 0..raw.steps {
            for slot in (0..raw.agents).filter(|&s| raw.alive[raw.index(t, s)]) {
                input.row(&f, f.obs(t, slot), t, slot, &mut rows);
            }
        }
        for slot in (0..raw.agents).filter(|&s| raw.needs_bootstrap(s)) {
            let own = &f.bootstrap_obs[slot * obs_dim..(slot + 1) * obs_dim];
            input.row(&f, own, raw.steps - 1, slot, &mut bootstrap_rows);
        }
    }
    Ok((rows, bootstrap_rows))
}

/// `head`'s critic on every row, on the host: GAE runs there, per fragment.
fn head_values(head: &Head, critic_inputs: &Tensor) -> Result<Vec<f32>, tch::TchError> {
    tch::no_grad(|| {
        Vec::<f32>::try_from(
            (head.value)(critic_inputs)
                .to_device(Device::Cpu)
                .to_kind(Kind::Float)
                .flatten(0, -1),
        )
    })
}

/// The observations (`obs_values` of them), actions and behaviour log-probabilities of every
/// alive cell, in batch order: what the policy's loss reads, copied once.
fn alive_samples(
    fragments: &[RolloutFragment],
    obs_values: usize,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut obs = Vec::with_capacity(obs_values);
    let mut actions = Vec::new();
    let mut old_log_probs = Vec::new();
    for f in fragments {
        for t in 0..f.steps {
            for slot in (0..f.agents).filter(|&s| f.alive[f.index(t, s)]) {
                let cell = f.index(t, slot);
                obs.extend_from_slice(&f.obs[cell * f.obs_dim..(cell + 1) * f.obs_dim]);
                actions
                    .extend_from_slice(&f.actions[cell * f.action_dim..(cell + 1) * f.action_dim]);
                old_log_probs.push(f.log_probs[cell]);
            }
        }
    }
    (obs, actions, old_log_probs)
}

/// Live neighbours of every alive cell's agent, in (fragment, step, slot) order: the rows of
/// a batch.
pub fn alive_neighbour_counts(fragments: &[RolloutFragment]) -> Vec<usize> {
    let mut counts = Vec::new();
    for f in fragments {
        for t in 0..f.steps {
            for slot in (0..f.agents).filter(|&s| f.alive[f.index(t, s)]) {
                counts.push(live_neighbours(f, t, slot).count());
            }
        }
    }
    counts
}

/// Neighbours of `slot` at step `t` (nearest first) that hold an agent at `t`.
fn live_neighbours(f: &RolloutFragment, t: usize, slot: usize) -> impl Iterator<Item = usize> + '_ {
    f.neighbours(t, slot)
        .iter()
        .map(|&n| n as usize)
        .filter(move |&n| n != slot && f.alive[f.index(t, n)])
}

/// GAE of one head over every fragment; `values` holds the head's value of every alive row,
/// then of every bootstrap row, in assembly order. Returns advantages, returns and values of
/// the alive rows.
fn head_estimates(
    fragments: &[RolloutFragment],
    head: &Head,
    values: &[f32],
    alive_rows: usize,
    lambda: f32,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let (alive_values, bootstrap_pool) = values.split_at(alive_rows.min(values.len()));
    let mut advantages = Vec::with_capacity(alive_rows);
    let mut returns = Vec::with_capacity(alive_rows);
    let mut old_values = Vec::with_capacity(alive_rows);
    let (mut next_alive, mut next_bootstrap) = (alive_values.iter(), bootstrap_pool.iter());
    for (f, rewards) in fragments.iter().zip(&head.rewards) {
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
                rewards,
                dones: &f.dones,
                alive: &f.alive,
                values: &cell_values,
                bootstrap_values: &bootstrap_values,
            },
            head.gamma,
            lambda,
            head.outlives_agent,
        );
        for cell in (0..cells).filter(|&c| f.alive[c]) {
            advantages.push(adv[cell]);
            returns.push(ret[cell]);
            old_values.push(cell_values[cell]);
        }
    }
    (advantages, returns, old_values)
}

/// Index tensors of one epoch's minibatches: a fresh permutation cut into `size` chunks (the
/// last may be shorter).
pub fn epoch_minibatches(
    len: usize,
    size: usize,
    rng: &mut ChaCha8Rng,
    device: Device,
) -> Vec<Tensor> {
    epoch_order(len, rng)
        .chunks(size.max(1))
        .map(|chunk| Tensor::from_slice(chunk).to_device(device))
        .collect()
}

/// One epoch's order of `len` rows: a fresh permutation.
pub fn epoch_order(len: usize, rng: &mut ChaCha8Rng) -> Vec<i64> {
    let mut order: Vec<i64> = (0..len as i64).collect();
    order.shuffle(rng);
    order
}

/// An epoch's rows drawn by priority: `len` draws with replacement, row i with probability
/// P(i) ∝ |advantage_i|^α, and each draw's weight (len·P(i))^−β over the largest weight.
pub fn prioritised_order(
    advantages: &[f32],
    alpha: f64,
    beta: f64,
    rng: &mut ChaCha8Rng,
) -> (Vec<i64>, Vec<f32>) {
    // A floor so a row with no advantage can still be drawn (and its weight stays finite).
    const FLOOR: f64 = 1e-6;
    let priorities: Vec<f64> = advantages
        .iter()
        .map(|a| f64::from(a.abs()).powf(alpha) + FLOOR)
        .collect();
    let total: f64 = priorities.iter().sum();
    let mut cumulative = Vec::with_capacity(priorities.len());
    let mut running = 0.0;
    for p in &priorities {
        running += p / total;
        cumulative.push(running);
    }
    let len = advantages.len();
    let order: Vec<i64> = (0..len)
        .map(|_| {
            let u = rng.r#gen::<f64>() * running;
            cumulative.partition_point(|&c| c <= u).min(len - 1) as i64
        })
        .collect();
    let weights: Vec<f64> = order
        .iter()
        .map(|&i| (len as f64 * priorities[i as usize] / total).powf(-beta))
        .collect();
    let largest = weights.iter().copied().fold(f64::MIN_POSITIVE, f64::max);
    (
        order,
        weights.iter().map(|w| (w / largest) as f32).collect(),
    )
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

#[cfg(test)]
mod tests {
    use rand::SeedableRng;

    use super::*;

    #[test]
    fn a_prioritised_epoch_draws_by_advantage_and_weights_the_draws_back() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        // Row 0 has no advantage, row 3 three times row 1's.
        let advantages = [0.0f32, 1.0, -2.0, 3.0];
        let draws = 60_000;
        let mut counts = [0usize; 4];
        let mut weight_of = [0.0f32; 4];
        for _ in 0..draws / advantages.len() {
            let (order, weights) = prioritised_order(&advantages, 1.0, 1.0, &mut rng);
            assert_eq!((order.len(), weights.len()), (4, 4), "one draw per row");
            for (&row, &w) in order.iter().zip(&weights) {
                counts[row as usize] += 1;
                weight_of[row as usize] = w;
            }
        }
        let share = |row: usize| counts[row] as f64 / draws as f64;
        assert_eq!(
            counts[0], 0,
            "a row without advantage is (almost) never drawn"
        );
        for (row, expected) in [(1, 1.0 / 6.0), (2, 2.0 / 6.0), (3, 3.0 / 6.0)] {
            assert!(
                (share(row) - expected).abs() < 0.01,
                "row {row}: {}",
                share(row)
            );
        }
        // Full correction: weight ∝ 1/P, the rarest drawn row's weight the largest (1).
        assert!((weight_of[1] - 1.0).abs() < 1e-6);
        assert!((weight_of[3] - 1.0 / 3.0).abs() < 1e-4, "{weight_of:?}");
        // α = 0: uniform draws, every weight 1.
        let (_, weights) = prioritised_order(&advantages, 0.0, 1.0, &mut rng);
        assert!(
            weights.iter().all(|&w| (w - 1.0).abs() < 1e-6),
            "{weights:?}"
        );
        // β = 0: no correction.
        let (_, weights) = prioritised_order(&advantages, 1.0, 0.0, &mut rng);
        assert!(weights.iter().all(|&w| w == 1.0), "{weights:?}");
    }
}
