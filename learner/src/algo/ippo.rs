//! IPPO: independent PPO with one policy and one critic shared by all agents (parameter
//! sharing), each agent learning from its own reward (de Witt et al. 2020; CoPO's baseline).
//!
//! ```text
//! for each update:
//!     fold the batch's observations into the running normaliser
//!     V ← critic(obs); A, R ← GAE(rewards, V, γ, λ) per agent
//!     repeat `epochs` times, over shuffled minibatches:
//!         ρ = π(a|s) / π_behaviour(a|s)
//!         L = −min(ρÂ, clip(ρ, 1±ε)Â) + c_v·L_V(V, R) − c_e·H[π]
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
    alive_observations, assemble, epoch_minibatches, explained_variance, standardize,
};
use super::ppo::{clipped_surrogate, value_loss};
use super::{AlgoError, Algorithm, UpdateStats};
use crate::optim::Adam;

pub struct Ippo {
    config: PpoConfig,
    policy: GaussianPolicy,
    critic_store: nn::VarStore,
    critic: Mlp,
    adam: Adam,
    seed: u64,
    updates: u64,
}

impl Ippo {
    pub fn new(
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
            obs_dim as i64,
            &config.hidden,
            1,
            1.0,
        );
        let mut params = policy.trainable();
        params.extend(critic_store.trainable_variables());
        let adam = Adam::new(params, config.learning_rate, config.adam_eps);
        Ippo {
            config: config.clone(),
            policy,
            critic_store,
            critic,
            adam,
            seed,
            updates: 0,
        }
    }

    fn value(&self, obs_normalized: &Tensor) -> Tensor {
        self.critic.forward(obs_normalized).squeeze_dim(-1)
    }
}

impl Algorithm for Ippo {
    fn name(&self) -> &'static str {
        "ippo"
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
            |obs| self.value(&self.policy.normalize(obs)),
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
                    &self.value(&obs),
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
            "ippo.updates".into(),
            Tensor::from_slice(&[self.updates as f32]),
        ));
        state
    }

    fn restore(&mut self, policy_blob: &[u8], state: &mut Decoded) -> Result<(), WeightsError> {
        self.policy.load_bytes(policy_blob)?;
        weights::load_var_store(&self.critic_store, state)?;
        self.adam.load_state("adam", state)?;
        self.updates = f64::try_from(state.take("ippo.updates", &[1])?.sum(Kind::Float))? as u64;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use junction_common::config::RunConfig;

    /// A one-step bandit: a single slot, observation constant, reward = −(a₀ − 0.5)². PPO must
    /// move the mean action towards 0.5.
    fn bandit_fragment(policy: &GaussianPolicy, rng_seed: u64) -> RolloutFragment {
        let agents = 64;
        let obs_dim = policy.obs_dim();
        let obs = vec![0.5f32; agents * obs_dim];
        let mut rng = ChaCha8Rng::seed_from_u64(rng_seed);
        let noise: Vec<f32> = (0..agents * 2)
            .map(|_| rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut rng))
            .collect();
        let (actions, log_probs) = policy.act(&obs, &noise).unwrap();
        let rewards = (0..agents)
            .map(|i| -(actions[2 * i] - 0.5).powi(2))
            .collect();
        RolloutFragment {
            steps: 1,
            agents,
            obs_dim,
            action_dim: 2,
            obs,
            actions,
            log_probs,
            rewards,
            costs: vec![0.0; agents],
            dones: vec![true; agents],
            alive: vec![true; agents],
            bootstrap_obs: vec![0.0; agents * obs_dim],
            neighbour_offsets: vec![0; agents + 1],
            ..RolloutFragment::default()
        }
    }

    fn mean_action(policy: &GaussianPolicy) -> f32 {
        policy
            .act(&vec![0.5f32; policy.obs_dim()], &[0.0, 0.0])
            .unwrap()
            .0[0]
    }

    #[test]
    fn ppo_moves_the_policy_towards_higher_reward() {
        tch::manual_seed(0);
        let mut config = RunConfig::default().ppo;
        config.hidden = vec![16];
        config.minibatch_size = 64;
        config.learning_rate = 0.01;
        let mut algo = Ippo::new(&config, 3, 2, Device::Cpu, 7);
        let start = mean_action(algo.policy());
        for round in 0..30 {
            let fragment = bandit_fragment(algo.policy(), round);
            let stats = algo.update(&[fragment]).unwrap();
            assert_eq!(stats.agent_steps, 64);
            assert_eq!(stats.samples_trained, 64 * config.epochs);
            assert!(stats.policy_loss.is_finite() && stats.value_loss.is_finite());
        }
        let end = mean_action(algo.policy());
        assert!(
            (end - 0.5).abs() < 0.15 && (start - 0.5).abs() > 0.3,
            "mean action {start} → {end}"
        );
    }

    #[test]
    fn checkpoint_state_restores_an_identical_learner() {
        tch::manual_seed(1);
        let mut config = RunConfig::default().ppo;
        config.hidden = vec![8];
        let mut a = Ippo::new(&config, 3, 2, Device::Cpu, 7);
        a.update(&[bandit_fragment(a.policy(), 1)]).unwrap();
        let blob = a.policy().to_bytes(1).unwrap();
        let state = a.state_tensors();
        let refs: Vec<(String, &Tensor)> = state.iter().map(|(n, t)| (n.clone(), t)).collect();
        let bytes = weights::encode(&refs, Default::default()).unwrap();
        let mut b = Ippo::new(&config, 3, 2, Device::Cpu, 7);
        b.restore(&blob, &mut Decoded::decode(&bytes).unwrap())
            .unwrap();
        assert_eq!(
            a.policy().to_bytes(1).unwrap(),
            b.policy().to_bytes(1).unwrap(),
            "restored policy"
        );
        let sa: Vec<_> = a
            .state_tensors()
            .into_iter()
            .map(|(n, t)| (n, Vec::<f32>::try_from(t.flatten(0, -1)).unwrap()))
            .collect();
        let sb: Vec<_> = b
            .state_tensors()
            .into_iter()
            .map(|(n, t)| (n, Vec::<f32>::try_from(t.flatten(0, -1)).unwrap()))
            .collect();
        for (x, y) in sa.iter().zip(&sb) {
            assert_eq!(x, y, "state {}", x.0);
        }
        // Same data → same next update → same weights.
        let next = bandit_fragment(a.policy(), 2);
        a.update(std::slice::from_ref(&next)).unwrap();
        b.update(&[next]).unwrap();
        assert_eq!(
            a.policy().to_bytes(2).unwrap(),
            b.policy().to_bytes(2).unwrap()
        );
    }
}
