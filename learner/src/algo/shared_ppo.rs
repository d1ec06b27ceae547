//! PPO with parameter sharing, written once for IPPO and the centralised-critic baselines: one
//! decentralised Gaussian policy on each agent's own observation, one critic on what the
//! algorithm's [`CriticInput`] builds, one Adam over both.
//!
//! ```text
//! for each update:
//!     fold the batch's observations into the running normaliser
//!     x ← critic_input(normalised obs, neighbourhoods); V ← critic(x)
//!     r ← α·cos φ·r_i + β·sin φ·r_N (fixed LCF, `[lcf]`; φ = 0: own reward)
//!     A, R ← GAE(r, V, γ, λ) per agent
//!     repeat `epochs` times, over shuffled minibatches:
//!         ρ = π(a|s) / π_behaviour(a|s)
//!         L = −min(ρÂ, clip(ρ, 1±ε)Â) + c_v·L_V(V(x), R) − c_e·H[π]
//!         (with `[safety]`: Â mixes in the cost advantage and L the cost critic, safety.rs)
//!         Adam step on ∇L, gradient norm clipped
//! ```

use std::borrow::Cow;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::nn::{self, Module};
use tch::{Device, Kind, Tensor};

use junction_common::config::{LcfConfig, PpoConfig, SafetyConfig, SafetyMode};
use junction_common::fragment::RolloutFragment;
use junction_common::lcf;
use junction_common::policy::{GaussianPolicy, Mlp, Policy, gaussian_entropy, gaussian_log_prob};
use junction_common::weights::{self, Decoded, WeightsError};

use super::batch::{
    CriticInput, alive_observations, assemble, epoch_minibatches, explained_variance, standardize,
};
use super::ppo::{clipped_surrogate, value_loss};
use super::safety::Lagrangian;
use super::{AlgoError, Algorithm, UpdateStats};
use crate::optim::Adam;

/// Checkpoint key of the Lagrange multiplier.
const SAFETY_MULTIPLIER: &str = "safety.multiplier";

pub struct SharedPpo<C> {
    /// `learner.algo` value; also prefixes the checkpointed update count.
    name: &'static str,
    critic_input: C,
    config: PpoConfig,
    /// The fixed LCF the rewards are coordinated with (φ = 0: the agents' own rewards).
    coordination: LcfConfig,
    /// PPO-Lagrangian's cost critic and multiplier, when `[safety] mode = "lagrangian"`.
    safety: Option<Lagrangian>,
    critic_width: i64,
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
        let critic_width = critic_input.width(obs_dim, action_dim) as i64;
        let critic = Mlp::new(
            critic_store.root() / "critic",
            critic_width,
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
            coordination: LcfConfig {
                phi_deg: 0.0,
                alpha: 1.0,
                beta: 1.0,
            },
            safety: None,
            critic_width,
            policy,
            critic_store,
            critic,
            adam,
            seed,
            updates: 0,
        }
    }

    /// Trains on coordinated rewards r_C = α·cos φ·r_i + β·sin φ·r_N (`[lcf]`).
    pub fn with_coordination(mut self, lcf: &LcfConfig) -> Self {
        self.coordination = lcf.clone();
        self
    }

    /// Adds PPO-Lagrangian's cost critic and multiplier (`[safety]`); before any update.
    pub fn with_safety(mut self, config: &SafetyConfig) -> Self {
        if config.mode == SafetyMode::Lagrangian {
            self.safety = Some(Lagrangian::new(
                config,
                self.critic_store.root() / "cost_critic",
                self.critic_width,
                &self.config.hidden,
            ));
            // The optimiser now also steps the cost critic.
            let mut params = self.policy.trainable();
            params.extend(self.critic_store.trainable_variables());
            self.adam = Adam::new(params, self.config.learning_rate, self.config.adam_eps);
        }
        self
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

    fn policy(&self) -> &dyn Policy {
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
        let lcf = &self.coordination;
        let phi = lcf.phi_deg.to_radians();
        let batch = assemble(
            fragments,
            &self.critic_input,
            |f| lcf::coordinated_rewards(f, phi, lcf.alpha, lcf.beta),
            |obs| self.policy.normalize(obs),
            |x| self.value(x),
            c.gamma,
            c.gae_lambda,
            device,
        )?;
        if batch.len == 0 {
            return Err(AlgoError::EmptyBatch);
        }
        // The cost side of PPO-Lagrangian: the same cells, the costs, the cost critic.
        let cost_batch = match &self.safety {
            Some(safety) => Some(assemble(
                fragments,
                &self.critic_input,
                |f| Cow::Borrowed(f.costs.as_slice()),
                |obs| self.policy.normalize(obs),
                |x| safety.cost_value(x),
                c.gamma,
                c.gae_lambda,
                device,
            )?),
            None => None,
        };
        let mut rng =
            ChaCha8Rng::seed_from_u64(self.seed ^ self.updates.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let mut stats = UpdateStats {
            agent_steps: batch.len,
            explained_variance: explained_variance(&batch.old_values, &batch.returns),
            learning_rate: self.adam.learning_rate(),
            lcf_mean_deg: f64::from(lcf.phi_deg),
            ..UpdateStats::default()
        };
        let mut minibatches = 0usize;
        for _ in 0..c.epochs {
            for idx in epoch_minibatches(batch.len, c.minibatch_size, &mut rng, device) {
                let obs = self.policy.normalize(&batch.obs.index_select(0, &idx));
                let advantages = batch.advantages.index_select(0, &idx);
                let scale = |a: Tensor| {
                    if c.normalize_advantages {
                        standardize(&a)
                    } else {
                        a
                    }
                };
                let mut advantages = scale(advantages);
                let mut cost_v_loss = Tensor::zeros([], (Kind::Float, device));
                if let (Some(safety), Some(costs)) = (&self.safety, &cost_batch) {
                    let cost_advantages = scale(costs.advantages.index_select(0, &idx));
                    advantages = safety.mixed_advantage(&advantages, &cost_advantages);
                    cost_v_loss = value_loss(
                        &safety.cost_value(&costs.critic_inputs.index_select(0, &idx)),
                        &costs.old_values.index_select(0, &idx),
                        &costs.returns.index_select(0, &idx),
                        c.value_clip,
                    );
                }
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
                let loss = &surrogate.loss + (&v_loss + &cost_v_loss) * c.value_coef
                    - &entropy * c.entropy_coef;
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
        if let Some(safety) = &mut self.safety {
            safety.update_multiplier(fragments);
            stats.lagrange_multiplier = safety.multiplier();
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
        if let Some(safety) = &self.safety {
            state.push((SAFETY_MULTIPLIER.into(), safety.multiplier_tensor()));
        }
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
        Ok(())
    }
}

/// Fixtures for the algorithms' tests: a fragment with a known neighbourhood and a checkpoint
/// round trip.
#[cfg(test)]
pub(crate) mod testing {
    use super::*;
    use crate::algo::batch::NormalizedFragment;

    /// 2 steps × 6 slots, obs_dim = action_dim = 2, all alive except slot 5 at t = 1 (done at
    /// t = 0). obs(t, s) = [s + 1, 10t + 1]; action(t, s) = [0.1(s + 1), 0.5 − t];
    /// bootstrap_obs(s) = [100 + s, 7]. Neighbours, nearest first:
    /// t = 0: 0 → [5, 4, 3, 2, 1]; 2 → [0]; 3 → [4, 2]; the rest none.
    /// t = 1: 0 → [5, 1] (5 is empty then); 3 → [4]; the rest none.
    pub fn neighbourhood_fragment() -> RolloutFragment {
        let (steps, agents) = (2, 6);
        let cells = steps * agents;
        let mut obs = Vec::new();
        let mut actions = Vec::new();
        for t in 0..steps {
            for s in 0..agents {
                obs.extend([s as f32 + 1.0, 10.0 * t as f32 + 1.0]);
                actions.extend([0.1 * (s as f32 + 1.0), 0.5 - t as f32]);
            }
        }
        let mut alive = vec![true; cells];
        alive[agents + 5] = false;
        let mut dones = vec![false; cells];
        dones[5] = true;
        let lists: [&[u32]; 12] = [
            &[5, 4, 3, 2, 1],
            &[],
            &[0],
            &[4, 2],
            &[],
            &[],
            &[5, 1],
            &[],
            &[],
            &[4],
            &[],
            &[],
        ];
        let mut neighbour_offsets = vec![0u32];
        let mut neighbour_ids = Vec::new();
        for list in lists {
            neighbour_ids.extend_from_slice(list);
            neighbour_offsets.push(neighbour_ids.len() as u32);
        }
        RolloutFragment {
            steps,
            agents,
            obs_dim: 2,
            action_dim: 2,
            obs,
            actions,
            log_probs: vec![-2.0; cells],
            rewards: (0..cells).map(|i| (i % 3) as f32 - 0.5).collect(),
            costs: vec![0.0; cells],
            dones,
            alive,
            bootstrap_obs: (0..agents).flat_map(|s| [100.0 + s as f32, 7.0]).collect(),
            neighbour_offsets,
            neighbour_ids,
            ..RolloutFragment::default()
        }
    }

    /// `raw` as if the normaliser were the identity, so expected rows can be hand-computed.
    pub fn unnormalized(raw: &RolloutFragment) -> NormalizedFragment<'_> {
        NormalizedFragment {
            raw,
            obs: raw.obs.clone(),
            bootstrap_obs: raw.bootstrap_obs.clone(),
        }
    }

    /// The critic row of `slot` at `t` (own = its observation there) and its bootstrap row.
    pub fn rows(
        input: &impl CriticInput,
        f: &NormalizedFragment,
        t: usize,
        slot: usize,
    ) -> Vec<f32> {
        let mut out = Vec::new();
        input.row(f, f.obs(t, slot), t, slot, &mut out);
        out
    }

    /// Equal up to float rounding, with both sides shown on failure.
    pub fn close(got: &[f32], expected: &[f32]) {
        assert_eq!(got.len(), expected.len(), "{got:?}");
        for (g, e) in got.iter().zip(expected) {
            assert!((g - e).abs() < 1e-6, "got {got:?}, expected {expected:?}");
        }
    }

    pub fn host_state(algo: &dyn Algorithm) -> Vec<(String, Vec<f32>)> {
        algo.state_tensors()
            .into_iter()
            .map(|(n, t)| (n, Vec::<f32>::try_from(t.flatten(0, -1)).unwrap()))
            .collect()
    }

    /// A learner restored from another's checkpoint holds the same state and, given the same
    /// fragment, makes the same next update (policy, critic and Adam moments alike).
    pub fn assert_checkpoint_round_trip<A: Algorithm>(make: impl Fn() -> A) {
        tch::manual_seed(3);
        let fragment = neighbourhood_fragment();
        let mut a = make();
        a.update(std::slice::from_ref(&fragment)).unwrap();
        let state = a.state_tensors();
        let refs: Vec<(String, &Tensor)> = state.iter().map(|(n, t)| (n.clone(), t)).collect();
        let bytes = weights::encode(&refs, Default::default()).unwrap();
        let mut b = make();
        b.restore(
            &a.policy().to_bytes(1).unwrap(),
            &mut Decoded::decode(&bytes).unwrap(),
        )
        .unwrap();
        assert_eq!(host_state(&a), host_state(&b), "restored state");
        a.update(std::slice::from_ref(&fragment)).unwrap();
        b.update(std::slice::from_ref(&fragment)).unwrap();
        assert_eq!(
            a.policy().to_bytes(2).unwrap(),
            b.policy().to_bytes(2).unwrap(),
            "policy after the next update"
        );
        assert_eq!(
            host_state(&a),
            host_state(&b),
            "state after the next update"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::testing::{self, host_state, neighbourhood_fragment};
    use super::*;
    use crate::algo::ippo::Ippo;
    use junction_common::config::RunConfig;

    fn learner(lcf: &LcfConfig) -> Ippo {
        tch::manual_seed(5);
        let mut config = RunConfig::default().ppo;
        config.hidden = vec![8];
        Ippo::new(&config, 2, 2, Device::Cpu, 3).with_coordination(lcf)
    }

    fn lagrangian_ippo() -> Ippo {
        let mut safety = RunConfig::default().safety;
        safety.mode = SafetyMode::Lagrangian;
        safety.cost_limit = 0.5;
        safety.multiplier_lr = 0.1;
        learner(&RunConfig::default().lcf).with_safety(&safety)
    }

    #[test]
    fn the_lagrangian_option_trains_a_cost_critic_prices_cost_and_checkpoints_it() {
        let mut fragment = neighbourhood_fragment();
        fragment.costs = (0..fragment.costs.len()).map(|i| (i % 2) as f32).collect();
        fragment.episodes = vec![junction_common::fragment::EpisodeStats {
            outcome: junction_common::fragment::Outcome::Crash,
            length: 1,
            total_reward: -5.0,
            mean_abs_accel: 0.0,
            max_abs_accel: 0.0,
            collisions: 1,
            energy_kj: 0.0,
            total_cost: 2.5,
        }];
        let mut safe = lagrangian_ippo();
        let names: Vec<String> = safe.state_tensors().into_iter().map(|(n, _)| n).collect();
        assert!(
            names.iter().any(|n| n.starts_with("cost_critic")),
            "{names:?}"
        );
        let stats = safe.update(std::slice::from_ref(&fragment)).unwrap();
        // λ = 0 + 0.1 · (2.5 − 0.5)
        assert!((stats.lagrange_multiplier - 0.2).abs() < 1e-6);
        // The cost changes what is learned: a learner without the option ends elsewhere.
        let mut plain = learner(&RunConfig::default().lcf);
        plain.update(std::slice::from_ref(&fragment)).unwrap();
        assert_ne!(
            safe.policy().to_bytes(1).unwrap(),
            plain.policy().to_bytes(1).unwrap()
        );
        // A learner restored mid-training (λ > 0) continues exactly.
        testing::assert_checkpoint_round_trip(|| {
            let mut learner = lagrangian_ippo();
            learner.update(std::slice::from_ref(&fragment)).unwrap();
            learner
        });
    }

    #[test]
    fn a_zero_lcf_is_ippo_and_a_cooperative_one_trains_on_other_rewards() {
        let fragment = neighbourhood_fragment();
        let lcf = |phi_deg| LcfConfig {
            phi_deg,
            alpha: 1.0,
            beta: 1.0,
        };
        let mut plain = learner(&lcf(0.0));
        let mut cooperative = learner(&lcf(90.0));
        let plain_stats = plain.update(std::slice::from_ref(&fragment)).unwrap();
        let cooperative_stats = cooperative.update(std::slice::from_ref(&fragment)).unwrap();
        assert_eq!(
            (plain_stats.lcf_mean_deg, cooperative_stats.lcf_mean_deg),
            (0.0, 90.0)
        );

        // φ = 0 is exactly IPPO without coordination configured.
        tch::manual_seed(5);
        let mut config = RunConfig::default().ppo;
        config.hidden = vec![8];
        let mut ippo = Ippo::new(&config, 2, 2, Device::Cpu, 3);
        ippo.update(std::slice::from_ref(&fragment)).unwrap();
        assert_eq!(host_state(&plain), host_state(&ippo));
        // φ = 90° learns from the neighbours' rewards: another value function.
        assert_ne!(host_state(&plain), host_state(&cooperative));
    }
}
