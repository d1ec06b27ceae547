//! PPO with parameter sharing, written once for IPPO, the centralised-critic baselines and the
//! LCF methods: one decentralised Gaussian policy on each agent's own observation, value heads
//! on what the algorithm's [`CriticInput`] builds, one Adam over policy and heads. What the
//! heads learn and how their advantages make the policy's is the algorithm's [`Coordination`].
//!
//! ```text
//! for each update:
//!     fold the batch's observations into the running normaliser
//!     x ← critic_input(normalised obs, neighbourhoods)
//!     for each value head h (coordination's signals, + the cost with `[safety]`):
//!         V_h ← critic_h(x); A_h, R_h ← GAE(r_h, V_h, γ_h, λ) per agent
//!     A ← coordination(A_h…)   (fixed LCF: GAE of α·cos φ·r_i + β·sin φ·r_N; φ = 0: IPPO)
//!     repeat `epochs` times, over shuffled minibatches:
//!         ρ = π(a|s) / π_behaviour(a|s)
//!         L = −min(ρÂ, clip(ρ, 1±ε)Â) + c_v·Σ_h L_V(V_h(x), R_h) − c_e·H[π]
//!         (`ppo.objective = "decoupled"`: ρ = π / π_start, the policy before this update,
//!          and each sample weighted by min(π_start / π_behaviour, ρ̄), ppo.rs)
//!         (`ppo.kl_coef > 0`: + β·KL(π_start ‖ π), β adapted to ppo.kl_target per update)
//!         (with `[safety]`: Â mixes in the cost advantage, safety.rs)
//!         Adam step on ∇L, gradient norm clipped
//!     coordination learns (copo, dynamic-lcf: the meta-gradient on the LCF, meta_lcf.rs)
//! ```

use std::borrow::Cow;
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::nn;
use tch::{Device, Kind, Tensor};

use junction_common::fragment::RolloutFragment;
use junction_common::mlp::{Mlp, MlpPass};
use junction_common::policy::{
    GaussianPolicy, Policy, gaussian_entropy, gaussian_kl, gaussian_log_prob,
};
use junction_common::weights::{self, Decoded, WeightsError};
use junction_core::config::{PpoConfig, PpoObjective, RunConfig, SafetyMode};

use super::batch::{
    CriticInput, Head, TrainBatch, alive_observations, assemble, epoch_order, explained_variance,
    prioritised_order, standardize,
};
use super::coordination::{Coordination, MetaStep};
use super::phases::Phases;
use super::ppo::{decoupled_surrogate, value_loss, weighted_clipped_surrogate};
use super::safety::Lagrangian;
use super::{AlgoError, Algorithm, UpdateStats};
use crate::optim::Adam;

/// Checkpoint key of the Lagrange multiplier.
const SAFETY_MULTIPLIER: &str = "safety.multiplier";
/// Checkpoint key of the adaptive KL penalty's coefficient.
const KL_COEF: &str = "ppo.kl_coef";

pub struct SharedPpo<C> {
    /// `learner.algo` value; also prefixes the checkpointed update count.
    name: &'static str,
    critic_input: C,
    coordination: Box<dyn Coordination>,
    config: PpoConfig,
    /// PPO-Lagrangian's cost critic and multiplier, when `[safety] mode = "lagrangian"`.
    safety: Option<Lagrangian>,
    policy: GaussianPolicy,
    critic_store: nn::VarStore,
    /// One per coordination signal, in its order.
    critics: Vec<Mlp>,
    adam: Adam,
    /// The KL penalty's current coefficient (0: no penalty).
    kl_coef: f64,
    /// `ppo.log_std_cap`'s ceiling at the budget spent so far (None: no ceiling).
    log_std_ceiling: Option<f64>,
    /// `learner.split_update` in effect: the policy's and the value part of each minibatch
    /// on two threads.
    parallel: bool,
    seed: u64,
    updates: u64,
}

impl<C: CriticInput> SharedPpo<C> {
    /// The algorithm `name` for observations of `obs_dim` values (what the policy takes) and
    /// actions of `action_dim`, from the run's `[ppo]`, `[safety]` and seed.
    pub fn new(
        name: &'static str,
        critic_input: C,
        coordination: Box<dyn Coordination>,
        run: &RunConfig,
        obs_dim: usize,
        action_dim: usize,
        device: Device,
    ) -> Self {
        let config = &run.ppo;
        let policy = GaussianPolicy::with_std(
            device,
            obs_dim as i64,
            action_dim as i64,
            &config.hidden,
            config.init_log_std,
            config.action_std,
        );
        let critic_store = nn::VarStore::new(device);
        let width = critic_input.width(obs_dim, action_dim) as i64;
        let critics = coordination
            .signals()
            .iter()
            .map(|signal| {
                Mlp::new(
                    critic_store.root() / signal.critic,
                    width,
                    &config.hidden,
                    1,
                    1.0,
                )
            })
            .collect();
        let safety = (run.safety.mode == SafetyMode::Lagrangian).then(|| {
            Lagrangian::new(
                &run.safety,
                critic_store.root() / "cost_critic",
                width,
                &config.hidden,
            )
        });
        let mut params = policy.trainable();
        params.extend(critic_store.trainable_variables());
        let adam = Adam::new(params, config.learning_rate, config.adam_eps);
        SharedPpo {
            name,
            critic_input,
            coordination,
            config: config.clone(),
            safety,
            policy,
            critic_store,
            critics,
            adam,
            kl_coef: config.kl_coef,
            log_std_ceiling: None,
            parallel: run.learner.split_update
                && device == Device::Cpu
                && tch::get_num_threads() >= 2,
            seed: run.run.seed,
            updates: 0,
        }
    }

    fn updates_key(&self) -> String {
        format!("{}.updates", self.name)
    }

    /// Folds the batch's observations into the policy's running statistics. The policy's own
    /// (f32) statistics are the state, so a restored learner continues bit for bit.
    fn fold_observations(&mut self, fragments: &[RolloutFragment]) -> Result<(), AlgoError> {
        if self.config.normalize_observations {
            let mut stats = self.policy.obs_stats()?;
            stats.update(&alive_observations(fragments));
            self.policy.set_obs_stats(&stats);
        }
        Ok(())
    }

    /// Batch assembly (critic inputs, every value head's GAE), the policy's advantages, and
    /// what the objective needs of the policy this update starts from, all fixed for the
    /// update's minibatches.
    fn prepare(
        &self,
        fragments: &[RolloutFragment],
        phases: &mut Phases,
    ) -> Result<Prepared, AlgoError> {
        let c = &self.config;
        let heads = self.value_heads(fragments)?;
        let batch = assemble(
            fragments,
            &self.critic_input,
            &heads,
            |obs| self.policy.normalize(obs),
            c.gae_lambda,
            self.policy.device(),
            phases,
        )?;
        drop(heads);
        if batch.len == 0 {
            return Err(AlgoError::EmptyBatch);
        }
        let started = Instant::now();
        // The statistics stay fixed for the update: normalised once, not per minibatch.
        let obs = self.policy.normalize(&batch.obs);
        let objective = match c.objective {
            PpoObjective::Clipped => Objective::Clipped,
            PpoObjective::Decoupled => Objective::Decoupled,
        };
        let start = self.start_policy(&obs, objective);
        let proximal_log_probs = match (&start, objective) {
            (Some((mean, log_std)), Objective::Decoupled) => Some(tch::no_grad(|| {
                gaussian_log_prob(mean, log_std, &batch.actions)
            })),
            _ => None,
        };
        let rows = Rows {
            critic_inputs: batch.critic_inputs.shallow_clone(),
            actions: batch.actions.shallow_clone(),
            behaviour_log_probs: batch.old_log_probs.shallow_clone(),
            advantages: self.coordination.policy_advantages(&batch)?,
            value_targets: batch
                .heads
                .iter()
                .map(|h| (h.old_values.shallow_clone(), h.returns.shallow_clone()))
                .collect(),
            cost_advantages: self
                .safety
                .as_ref()
                .and_then(|_| batch.heads.last())
                .map(|h| h.advantages.shallow_clone()),
            proximal_log_probs,
            kl_anchor: start.filter(|_| self.kl_coef > 0.0),
            priority_weights: None,
            obs,
        };
        phases.add("advantages, start policy", started.elapsed().as_secs_f64());
        Ok(Prepared {
            batch,
            rows,
            objective,
        })
    }

    /// One value head per signal the coordination learns from (its rewards, its critic, its
    /// discount), and PPO-Lagrangian's cost head after them: the same rows, the costs, the
    /// cost critic.
    fn value_heads<'a>(
        &'a self,
        fragments: &'a [RolloutFragment],
    ) -> Result<Vec<Head<'a>>, AlgoError> {
        let mut heads = Vec::new();
        for (index, (signal, critic)) in self
            .coordination
            .signals()
            .iter()
            .zip(&self.critics)
            .enumerate()
        {
            heads.push(Head {
                rewards: fragments
                    .iter()
                    .map(|f| self.coordination.rewards(index, f))
                    .collect::<Result<_, _>>()?,
                value: Box::new(move |x| value(critic, x)),
                gamma: signal.gamma.unwrap_or(self.config.gamma),
                outlives_agent: signal.outlives_agent,
            });
        }
        if let Some(safety) = &self.safety {
            heads.push(Head {
                rewards: fragments
                    .iter()
                    .map(|f| Cow::Borrowed(f.costs.as_slice()))
                    .collect(),
                value: Box::new(|x| safety.cost_value(x)),
                gamma: self.config.gamma,
                outlives_agent: false,
            });
        }
        Ok(heads)
    }

    /// The policy this update starts from (its mean and log-std over `obs`), where the
    /// objective needs it: decoupled PPO's proximal policy, the KL penalty's anchor.
    fn start_policy(&self, obs: &Tensor, objective: Objective) -> Option<(Tensor, Tensor)> {
        (objective == Objective::Decoupled || self.kl_coef > 0.0).then(|| {
            tch::no_grad(|| {
                let (mean, log_std) = self.policy.distribution(obs);
                // Copies, not views of the parameters the optimiser is about to change.
                (mean, log_std.copy())
            })
        })
    }

    /// The policy before this update, for coordination that learns from the update's effect.
    fn snapshot_for_coordination(&self) -> Result<Option<GaussianPolicy>, AlgoError> {
        if !self.coordination.learns() {
            return Ok(None);
        }
        let bytes = self.policy.to_bytes(0)?;
        Ok(Some(
            GaussianPolicy::from_bytes(&bytes, self.policy.device())?.0,
        ))
    }

    /// One minibatch: the loss L = L_policy + c_v·L_value (PPO's clipped surrogate with the
    /// entropy and KL terms, the value heads' losses), its gradients, and Adam's step. The two
    /// parts share no parameter, so with `learner.split_update` each takes a thread of its own.
    /// None: the loss was not finite and the minibatch is skipped.
    fn minibatch_step(
        &mut self,
        mb: &Rows,
        objective: Objective,
        phases: &mut Phases,
    ) -> Result<Option<Losses>, AlgoError> {
        phases.time("zero gradients", || self.adam.zero_grad());
        let value_part = ValuePart {
            critics: self
                .critics
                .iter()
                .chain(self.safety.as_ref().map(Lagrangian::cost_critic))
                .map(Mlp::shallow_clone)
                .collect(),
            inputs: mb.critic_inputs.shallow_clone(),
            targets: mb
                .value_targets
                .iter()
                .map(|(old, returns)| (old.shallow_clone(), returns.shallow_clone()))
                .collect(),
            clip: self.config.value_clip,
            coef: self.config.value_coef,
        };
        let (policy, value) = if self.parallel {
            std::thread::scope(|scope| {
                let value = scope.spawn(move || {
                    // One thread each: libtorch's own threads would only compete with ours.
                    tch::set_num_threads(1);
                    value_part.loss_and_gradients()
                });
                let policy = self.policy_loss_and_gradients(mb, objective, phases);
                let waited = Instant::now();
                let value = value
                    .join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
                phases.add("wait for the value part", waited.elapsed().as_secs_f64());
                (policy, value)
            })
        } else {
            (
                self.policy_loss_and_gradients(mb, objective, phases),
                value_part.loss_and_gradients(),
            )
        };
        let (policy, value) = (policy?, value?);
        phases.merge(&value.phases);
        if !(policy.loss.is_finite() && value.total.is_finite()) {
            return Ok(None);
        }
        let max_grad_norm = self.config.max_grad_norm;
        let grad_norm = phases.time("gradient clip", || self.adam.clip_grad_norm(max_grad_norm));
        phases.time("Adam step", || self.adam.step());
        if let Some(ceiling) = self.log_std_ceiling {
            self.policy.cap_log_std(ceiling);
        }
        Ok(Some(Losses {
            policy: policy.surrogate,
            value: value.first_head,
            entropy: policy.entropy,
            approx_kl: policy.approx_kl,
            clip_fraction: policy.clip_fraction,
            kl: policy.kl,
            grad_norm,
            samples: mb.obs.size()[0] as usize,
        }))
    }

    /// The policy's part of a minibatch's loss: −clipped surrogate − c_e·entropy (+ β·KL),
    /// and its gradients when it is finite.
    fn policy_loss_and_gradients(
        &self,
        mb: &Rows,
        objective: Objective,
        phases: &mut Phases,
    ) -> Result<PolicyTerms, AlgoError> {
        let c = &self.config;
        let standardized = |a: &Tensor| {
            if c.normalize_advantages {
                standardize(a)
            } else {
                a.shallow_clone()
            }
        };
        // The network's pass: its gradients are taken by hand after the loss's (mlp.rs).
        let pass = phases.time("policy: network forward", || {
            self.policy.forward_pass(&mb.obs)
        });
        let started = Instant::now();
        let (mean, log_std) = self.policy.head(&pass.output);
        let log_probs = gaussian_log_prob(&mean, &log_std, &mb.actions);
        let mut advantages = standardized(&mb.advantages);
        if let (Some(safety), Some(cost)) = (&self.safety, &mb.cost_advantages) {
            advantages = safety.mixed_advantage(&advantages, &standardized(cost));
        }
        let surrogate = match (objective, &mb.proximal_log_probs) {
            (Objective::Decoupled, Some(proximal)) => decoupled_surrogate(
                &log_probs,
                proximal,
                &mb.behaviour_log_probs,
                &advantages,
                c.clip,
                c.max_importance_weight,
            ),
            _ => weighted_clipped_surrogate(
                &log_probs,
                &mb.behaviour_log_probs,
                &advantages,
                c.clip,
                mb.priority_weights.as_ref(),
            ),
        };
        let entropy = gaussian_entropy(&log_std).mean(Kind::Float);
        let mut loss = &surrogate.loss - &entropy * c.entropy_coef;
        let kl = mb.kl_anchor.as_ref().map(|(start_mean, start_log_std)| {
            gaussian_kl(start_mean, start_log_std, &mean, &log_std).mean(Kind::Float)
        });
        if let Some(kl) = &kl {
            loss += kl * self.kl_coef;
        }
        let loss_value = f64::try_from(&loss)?;
        phases.add("policy: loss", started.elapsed().as_secs_f64());
        if loss_value.is_finite() {
            phases.time("policy: loss backward (autograd)", || loss.backward());
            phases.time("policy: network backward", || pass.backward());
        }
        Ok(PolicyTerms {
            loss: loss_value,
            surrogate: f64::try_from(&surrogate.loss)?,
            entropy: f64::try_from(&entropy)?,
            approx_kl: f64::try_from(&surrogate.approx_kl)?,
            clip_fraction: f64::try_from(&surrogate.clip_fraction)?,
            kl: kl.as_ref().map(f64::try_from).transpose()?.unwrap_or(0.0),
        })
    }

    /// RLlib's schedule for the KL penalty's coefficient: keep the update's KL within a
    /// factor 2 of the target.
    fn adapt_kl_coef(&mut self, kl: f64) {
        if self.kl_coef <= 0.0 {
            return;
        }
        let target = self.config.kl_target;
        let factor = if kl > 2.0 * target {
            1.5
        } else if kl < 0.5 * target {
            0.5
        } else {
            1.0
        };
        // Kept at f32 precision, what checkpoints store, so a resumed run continues exactly.
        self.kl_coef = f64::from((self.kl_coef * factor) as f32);
    }

    /// After the epochs: coordination learns (the meta-gradient on the LCF), the LCF report,
    /// and PPO-Lagrangian's multiplier.
    fn after_epochs(
        &mut self,
        fragments: &[RolloutFragment],
        batch: &TrainBatch,
        before: Option<GaussianPolicy>,
        rng: &mut ChaCha8Rng,
        stats: &mut UpdateStats,
    ) -> Result<(), AlgoError> {
        if let Some(before) = &before {
            self.coordination.learn(MetaStep {
                fragments,
                batch,
                before,
                after: &self.policy,
                ppo: &self.config,
                rng,
            })?;
        }
        let lcf = self.coordination.report(fragments, batch)?;
        stats.lcf_mean_deg = lcf.mean_deg;
        stats.lcf_std_deg = lcf.std_deg;
        stats.lcf_phi_by_neighbours = lcf.by_neighbours;
        if let Some(safety) = &mut self.safety {
            safety.update_multiplier(fragments);
            stats.lagrange_multiplier = safety.multiplier();
        }
        Ok(())
    }
}

/// The surrogate an update optimises, chosen once from `ppo.objective`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Objective {
    /// The ratio against the behaviour policy, clipped.
    Clipped,
    /// The ratio against the policy at the update's start, weighted by how far the behaviour
    /// policy was from it (ppo.rs).
    Decoupled,
}

/// An update's batch with what stays fixed for all its minibatches.
struct Prepared {
    batch: TrainBatch,
    rows: Rows,
    objective: Objective,
}

/// What the loss reads per row, in one order (the batch's, or an epoch's shuffle).
struct Rows {
    /// Observations normalised by the statistics of this update.
    obs: Tensor,
    critic_inputs: Tensor,
    actions: Tensor,
    behaviour_log_probs: Tensor,
    /// The policy's advantage (coordination's), before each minibatch's standardisation.
    advantages: Tensor,
    /// Per value head (coordination's, then the cost's with `[safety]`): old values, returns.
    value_targets: Vec<(Tensor, Tensor)>,
    /// With `[safety]`: the cost advantage.
    cost_advantages: Option<Tensor>,
    /// Decoupled PPO: the log-probabilities under the policy the update started from.
    proximal_log_probs: Option<Tensor>,
    /// With a KL penalty: that policy's mean and log-std, what the penalty measures from.
    kl_anchor: Option<(Tensor, Tensor)>,
    /// With `ppo.advantage_priority`: each drawn row's weight in the surrogate.
    priority_weights: Option<Tensor>,
}

impl Rows {
    fn map(&self, f: impl Fn(&Tensor) -> Tensor) -> Rows {
        Rows {
            obs: f(&self.obs),
            critic_inputs: f(&self.critic_inputs),
            actions: f(&self.actions),
            behaviour_log_probs: f(&self.behaviour_log_probs),
            advantages: f(&self.advantages),
            value_targets: self
                .value_targets
                .iter()
                .map(|(old, returns)| (f(old), f(returns)))
                .collect(),
            cost_advantages: self.cost_advantages.as_ref().map(&f),
            proximal_log_probs: self.proximal_log_probs.as_ref().map(&f),
            kl_anchor: self.kl_anchor.as_ref().map(|(m, s)| (f(m), f(s))),
            priority_weights: self.priority_weights.as_ref().map(&f),
        }
    }

    /// One epoch's rows, drawn from `rng`: every row once in a fresh order, or with
    /// `ppo.advantage_priority` a prioritised draw and its weights. One copy per epoch: its
    /// minibatches are then views.
    fn epoch(&self, rng: &mut ChaCha8Rng, ppo: &PpoConfig) -> Result<Rows, tch::TchError> {
        let device = self.obs.device();
        let (order, weights) = if ppo.advantage_priority > 0.0 {
            let advantages =
                Vec::<f32>::try_from(self.advantages.to_device(Device::Cpu).to_kind(Kind::Float))?;
            let (order, weights) = prioritised_order(
                &advantages,
                ppo.advantage_priority,
                ppo.priority_correction,
                rng,
            );
            (order, Some(Tensor::from_slice(&weights).to_device(device)))
        } else {
            (epoch_order(self.obs.size()[0] as usize, rng), None)
        };
        let order = Tensor::from_slice(&order).to_device(device);
        let mut rows = self.map(|t| t.index_select(0, &order));
        rows.priority_weights = weights;
        Ok(rows)
    }

    /// Consecutive minibatches of `size` rows (the last may be shorter).
    fn minibatches(&self, size: usize) -> impl Iterator<Item = Rows> + '_ {
        let len = self.obs.size()[0];
        let size = size.max(1) as i64;
        (0..len)
            .step_by(size as usize)
            .map(move |start| self.map(|t| t.narrow(0, start, size.min(len - start))))
    }
}

/// The value heads' part of a minibatch's loss, Σ_h L_V(V_h(x), R_h) over coordination's
/// heads (and the cost critic with `[safety]`). It owns what it reads (shallow clones: the
/// critics' parameters and gradients are the learner's own), so it can run on a thread of its
/// own.
struct ValuePart {
    critics: Vec<Mlp>,
    inputs: Tensor,
    /// Per head: old values, returns.
    targets: Vec<(Tensor, Tensor)>,
    clip: f64,
    /// c_v, the value loss's weight in the whole loss.
    coef: f64,
}

impl ValuePart {
    /// The loss and, when it is finite, the critics' gradients of c_v times it.
    fn loss_and_gradients(self) -> Result<ValueTerms, tch::TchError> {
        let mut phases = Phases::default();
        let passes: Vec<MlpPass> = phases.time("value: network forward", || {
            self.critics
                .iter()
                .map(|critic| critic.forward_pass(&self.inputs))
                .collect()
        });
        let started = Instant::now();
        let losses: Vec<Tensor> = passes
            .iter()
            .zip(&self.targets)
            .map(|(pass, (old, returns))| {
                value_loss(&pass.output.squeeze_dim(-1), old, returns, self.clip)
            })
            .collect();
        let other_heads = losses[1..].iter().fold(
            Tensor::zeros([], (Kind::Float, self.inputs.device())),
            |a, b| a + b,
        );
        let total = &losses[0] + other_heads;
        let total_value = f64::try_from(&total)?;
        phases.add("value: loss", started.elapsed().as_secs_f64());
        if total_value.is_finite() {
            phases.time("value: loss backward (autograd)", || {
                (total * self.coef).backward()
            });
            phases.time("value: network backward", || {
                passes.into_iter().for_each(MlpPass::backward)
            });
        }
        Ok(ValueTerms {
            total: total_value,
            first_head: f64::try_from(&losses[0])?,
            phases,
        })
    }
}

/// What [`SharedPpo::policy_loss_and_gradients`] reports of a minibatch.
struct PolicyTerms {
    /// The policy's whole loss (finite: its gradients were taken).
    loss: f64,
    surrogate: f64,
    entropy: f64,
    approx_kl: f64,
    clip_fraction: f64,
    kl: f64,
}

/// What [`ValuePart::loss_and_gradients`] reports of a minibatch.
struct ValueTerms {
    /// Σ_h L_V (finite: its gradients were taken).
    total: f64,
    /// The first head's (coordination's main signal): what progress lines report.
    first_head: f64,
    /// Its time (on its own thread with `learner.split_update`, beside the policy's).
    phases: Phases,
}

/// libtorch at one thread on this thread until dropped, then back to what it was.
struct OneTorchThread(i32);

impl OneTorchThread {
    fn set() -> Self {
        let before = tch::get_num_threads();
        tch::set_num_threads(1);
        OneTorchThread(before)
    }
}

impl Drop for OneTorchThread {
    fn drop(&mut self) {
        tch::set_num_threads(self.0);
    }
}

/// One minibatch's loss terms and gradient norm, or their sums over an update.
#[derive(Debug, Default)]
struct Losses {
    policy: f64,
    value: f64,
    entropy: f64,
    approx_kl: f64,
    clip_fraction: f64,
    kl: f64,
    grad_norm: f64,
    samples: usize,
}

/// The sums of an update's minibatch losses, and how many were taken and skipped.
#[derive(Debug, Default)]
struct LossTotals {
    sum: Losses,
    minibatches: usize,
    skipped: usize,
}

impl LossTotals {
    fn add(&mut self, step: &Losses) {
        let sum = &mut self.sum;
        sum.policy += step.policy;
        sum.value += step.value;
        sum.entropy += step.entropy;
        sum.approx_kl += step.approx_kl;
        sum.clip_fraction += step.clip_fraction;
        sum.kl += step.kl;
        sum.grad_norm += step.grad_norm;
        sum.samples += step.samples;
        self.minibatches += 1;
    }

    /// Means over the minibatches taken.
    fn into_stats(self, batch: &TrainBatch, learning_rate: f64) -> UpdateStats {
        let n = self.minibatches.max(1) as f64;
        let main = &batch.heads[0];
        UpdateStats {
            agent_steps: batch.len,
            samples_trained: self.sum.samples,
            policy_loss: self.sum.policy / n,
            value_loss: self.sum.value / n,
            entropy: self.sum.entropy / n,
            approx_kl: self.sum.approx_kl / n,
            clip_fraction: self.sum.clip_fraction / n,
            kl: self.sum.kl / n,
            grad_norm: self.sum.grad_norm / n,
            explained_variance: explained_variance(&main.old_values, &main.returns),
            learning_rate,
            skipped_minibatches: self.skipped,
            ..UpdateStats::default()
        }
    }
}

fn value(critic: &Mlp, critic_inputs: &Tensor) -> Tensor {
    critic.infer(critic_inputs).squeeze_dim(-1)
}

impl<C: CriticInput> Algorithm for SharedPpo<C> {
    fn name(&self) -> &'static str {
        self.name
    }

    fn policy(&self) -> &dyn Policy {
        &self.policy
    }

    fn policy_bytes(&self, version: u64) -> Result<Vec<u8>, WeightsError> {
        self.policy
            .to_bytes_with_metadata(version, self.coordination.policy_metadata())
    }

    fn set_progress(&mut self, budget_spent: Option<f64>) {
        let c = &self.config;
        self.adam
            .set_learning_rate(c.lr_schedule.learning_rate(c.learning_rate, budget_spent));
        self.log_std_ceiling =
            c.log_std_cap
                .ceiling(c.init_log_std, c.final_log_std_cap, budget_spent);
    }

    /// The module documentation's outline, one line per stage.
    fn update(&mut self, fragments: &[RolloutFragment]) -> Result<UpdateStats, AlgoError> {
        let mut phases = Phases::default();
        phases.time("fold observations", || self.fold_observations(fragments))?;
        let prepared = self.prepare(fragments, &mut phases)?;
        let before = phases.time("snapshot for coordination", || {
            self.snapshot_for_coordination()
        })?;
        let mut rng =
            ChaCha8Rng::seed_from_u64(self.seed ^ self.updates.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let mut losses = LossTotals::default();
        let one_thread_each = self.parallel.then(OneTorchThread::set);
        for _ in 0..self.config.epochs {
            let shuffled = phases.time("epoch shuffle", || {
                prepared.rows.epoch(&mut rng, &self.config)
            })?;
            for minibatch in shuffled.minibatches(self.config.minibatch_size) {
                match self.minibatch_step(&minibatch, prepared.objective, &mut phases)? {
                    Some(step) => losses.add(&step),
                    None => losses.skipped += 1,
                }
            }
        }
        drop(one_thread_each);
        let mut stats = losses.into_stats(&prepared.batch, self.adam.learning_rate());
        self.adapt_kl_coef(stats.kl);
        stats.kl_coef = self.kl_coef;
        phases.time("coordination, reports", || {
            self.after_epochs(fragments, &prepared.batch, before, &mut rng, &mut stats)
        })?;
        self.updates += 1;
        stats.phases = phases;
        Ok(stats)
    }

    fn state_tensors(&self) -> Vec<(String, Tensor)> {
        let mut state = weights::var_store_tensors(&self.critic_store);
        state.extend(self.adam.state("adam"));
        state.push((
            self.updates_key(),
            Tensor::from_slice(&[self.updates as f32]),
        ));
        if let Some(safety) = &self.safety {
            state.push((SAFETY_MULTIPLIER.into(), safety.multiplier_tensor()));
        }
        if self.config.kl_coef > 0.0 {
            state.push((KL_COEF.into(), Tensor::from_slice(&[self.kl_coef as f32])));
        }
        state.extend(self.coordination.state_tensors());
        state
    }

    fn restore(&mut self, policy_blob: &[u8], state: &mut Decoded) -> Result<(), WeightsError> {
        self.policy.load_bytes(policy_blob)?;
        weights::load_var_store(&self.critic_store, state)?;
        self.adam.load_state("adam", state)?;
        let updates = state.take(&self.updates_key(), &[1])?.sum(Kind::Float);
        self.updates = f64::try_from(updates)? as u64;
        if let Some(safety) = &mut self.safety {
            let multiplier = state.take(SAFETY_MULTIPLIER, &[1])?.sum(Kind::Float);
            safety.set_multiplier(f64::try_from(multiplier)?);
        }
        if self.config.kl_coef > 0.0 {
            let coef = state.take(KL_COEF, &[1])?.sum(Kind::Float);
            self.kl_coef = f64::try_from(coef)?;
        }
        self.coordination.restore(state)
    }
}

/// Gives `to` the policy and the same-named critic parameters of `from`. Two learners
/// compared for equality start equal this way, not by seeding torch twice: its global RNG
/// is shared with the tests running beside them. A fixture like `algo::testing`'s, kept here
/// because it reads the learner's private networks.
#[cfg(test)]
pub(crate) fn copy_networks<A: CriticInput, B: CriticInput>(
    from: &SharedPpo<A>,
    to: &mut SharedPpo<B>,
) {
    to.policy
        .load_bytes(&from.policy.to_bytes(0).unwrap())
        .unwrap();
    let source = from.critic_store.variables();
    tch::no_grad(|| {
        for (name, mut variable) in to.critic_store.variables() {
            if let Some(value) = source.get(&name) {
                variable.copy_(value);
            }
        }
    });
}
