//! PPO with parameter sharing, written once for IPPO and the centralised-critic baselines: one
//! decentralised Gaussian policy on each agent's own observation, one critic on what the
//! algorithm's [`CriticInput`] builds, one Adam over both.
//!
//! ```text
//! for each update:
//!     fold the batch's observations into the running normaliser
//!     x ← critic_input(normalised obs, neighbourhoods); V ← critic(x)
//!     A, R ← GAE(rewards, V, γ, λ) per agent
//!     repeat `epochs` times, over shuffled minibatches:
//!         ρ = π(a|s) / π_behaviour(a|s)
//!         L = −min(ρÂ, clip(ρ, 1±ε)Â) + c_v·L_V(V(x), R) − c_e·H[π]
//!         Adam step on ∇L, gradient norm clipped
//! ```

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::nn::{self, Module};
use tch::{Device, Kind, Tensor};

use junction_common::config::PpoConfig;
use junction_common::fragment::RolloutFragment;
use junction_common::policy::{GaussianPolicy, Mlp, gaussian_entropy, gaussian_log_prob};
use junction_common::weights::{self, Decoded, WeightsError};

use super::batch::{
    CriticInput, alive_observations, assemble, epoch_minibatches, explained_variance, standardize,
};
use super::ppo::{clipped_surrogate, value_loss};
use super::{AlgoError, Algorithm, UpdateStats};
use crate::optim::Adam;

pub struct SharedPpo<C> {
    /// `learner.algo` value; also prefixes the checkpointed update count.
    name: &'static str,
    critic_input: C,
    config: PpoConfig,
    policy: GaussianPolicy,
    critic_store: nn::VarStore,
    critic: Mlp,
    adam: Adam,
    seed: u64,
    updates: u64,
}

impl<C: CriticInput> SharedPpo<C> {
    pub fn with_critic_input(
        name: &'static str,
        critic_input: C,
        config: &PpoConfig,
        obs_dim: usize,
        action_dim: usize,
        device: Device,
        seed: u64,
    ) -> Self {
        let policy = GaussianPolicy::new(
            device,
            obs_dim as i64,
            action_dim as i64,
            &config.hidden,
            config.init_log_std,
        );
        let critic_store = nn::VarStore::new(device);
        let critic = Mlp::new(
            critic_store.root() / "critic",
            critic_input.width(obs_dim, action_dim) as i64,
            &config.hidden,
            1,
            1.0,
        );
        let mut params = policy.trainable();
        params.extend(critic_store.trainable_variables());
        let adam = Adam::new(params, config.learning_rate, config.adam_eps);
        SharedPpo {
            name,
            critic_input,
            config: config.clone(),
            policy,
            critic_store,
            critic,
            adam,
            seed,
            updates: 0,
        }
    }

    fn value(&self, critic_inputs: &Tensor) -> Tensor {
        self.critic.forward(critic_inputs).squeeze_dim(-1)
    }

    fn updates_key(&self) -> String {
        format!("{}.updates", self.name)
    }
}

impl<C: CriticInput> Algorithm for SharedPpo<C> {
    fn name(&self) -> &'static str {
        self.name
    }

    fn policy(&self) -> &GaussianPolicy {
        &self.policy
    }

    fn update(&mut self, fragments: &[RolloutFragment]) -> Result<UpdateStats, AlgoError> {
        let c = self.config.clone();
        if c.normalize_observations {
            // The policy's own (f32) statistics are the state, so a restored learner continues
            // bit for bit.
            let mut stats = self.policy.obs_stats()?;
            stats.update(&alive_observations(fragments));
            self.policy.set_obs_stats(&stats);
        }
        let device = self.policy.device();
        let batch = assemble(
            fragments,
            &self.critic_input,
            |obs| self.policy.normalize(obs),
            |x| self.value(x),
            c.gamma,
            c.gae_lambda,
            device,
        )?;
        if batch.len == 0 {
            return Err(AlgoError::EmptyBatch);
        }
        let mut rng =
            ChaCha8Rng::seed_from_u64(self.seed ^ self.updates.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let mut stats = UpdateStats {
            agent_steps: batch.len,
            explained_variance: explained_variance(&batch.old_values, &batch.returns),
            learning_rate: self.adam.learning_rate(),
            ..UpdateStats::default()
        };
        let mut minibatches = 0usize;
        for _ in 0..c.epochs {
            for idx in epoch_minibatches(batch.len, c.minibatch_size, &mut rng, device) {
                let obs = self.policy.normalize(&batch.obs.index_select(0, &idx));
                let advantages = batch.advantages.index_select(0, &idx);
                let advantages = if c.normalize_advantages {
                    standardize(&advantages)
                } else {
                    advantages
                };
                let (mean, log_std) = self.policy.distribution(&obs);
                let log_probs =
                    gaussian_log_prob(&mean, &log_std, &batch.actions.index_select(0, &idx));
                let surrogate = clipped_surrogate(
                    &log_probs,
                    &batch.old_log_probs.index_select(0, &idx),
                    &advantages,
                    c.clip,
                );
                let v_loss = value_loss(
                    &self.value(&batch.critic_inputs.index_select(0, &idx)),
                    &batch.old_values.index_select(0, &idx),
                    &batch.returns.index_select(0, &idx),
                    c.value_clip,
                );
                let entropy = gaussian_entropy(&log_std).mean(Kind::Float);
                let loss = &surrogate.loss + &v_loss * c.value_coef - &entropy * c.entropy_coef;
                let loss_value = f64::try_from(&loss)?;
                if !loss_value.is_finite() {
                    stats.skipped_minibatches += 1;
                    continue;
                }
                self.adam.zero_grad();
                loss.backward();
                stats.grad_norm += self.adam.clip_grad_norm(c.max_grad_norm);
                self.adam.step();
                stats.policy_loss += f64::try_from(&surrogate.loss)?;
                stats.value_loss += f64::try_from(&v_loss)?;
                stats.entropy += f64::try_from(&entropy)?;
                stats.approx_kl += f64::try_from(&surrogate.approx_kl)?;
                stats.clip_fraction += f64::try_from(&surrogate.clip_fraction)?;
                stats.samples_trained += idx.size()[0] as usize;
                minibatches += 1;
            }
        }
        let n = minibatches.max(1) as f64;
        for field in [
            &mut stats.policy_loss,
            &mut stats.value_loss,
            &mut stats.entropy,
            &mut stats.approx_kl,
            &mut stats.clip_fraction,
            &mut stats.grad_norm,
        ] {
            *field /= n;
        }
        self.updates += 1;
        Ok(stats)
    }

    fn state_tensors(&self) -> Vec<(String, Tensor)> {
        let mut state = weights::var_store_tensors(&self.critic_store);
        state.extend(self.adam.state("adam"));
        state.push((
            self.updates_key(),
            Tensor::from_slice(&[self.updates as f32]),
        ));
        state
    }

    fn restore(&mut self, policy_blob: &[u8], state: &mut Decoded) -> Result<(), WeightsError> {
        self.policy.load_bytes(policy_blob)?;
        weights::load_var_store(&self.critic_store, state)?;
        self.adam.load_state("adam", state)?;
        let updates = state.take(&self.updates_key(), &[1])?.sum(Kind::Float);
        self.updates = f64::try_from(updates)? as u64;
        Ok(())
    }
}
