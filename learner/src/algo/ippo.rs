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
//!
//! The loop is [`SharedPpo`]'s; IPPO is the choice of critic input: the agent's own
//! observation, nothing else.

use super::batch::{CriticInput, NormalizedFragment};
use super::shared_ppo::SharedPpo;

/// The critic sees what the actor sees: the agent's own normalised observation.
pub struct OwnObservation;

impl CriticInput for OwnObservation {
    fn width(&self, obs_dim: usize, _action_dim: usize) -> usize {
        obs_dim
    }

    fn row(&self, _: &NormalizedFragment, own: &[f32], _: usize, _: usize, out: &mut Vec<f32>) {
        out.extend_from_slice(own);
    }
}

pub type Ippo = SharedPpo<OwnObservation>;

/// Fixtures for the algorithms' tests that build on IPPO (compiled for tests only): the
/// algorithms above IPPO use them; `algo::testing` holds the ones that need no algorithm.
#[cfg(test)]
pub(crate) mod fixtures {
    use tch::{Device, Kind, Tensor};

    use junction_common::fragment::RolloutFragment;
    use junction_core::config::RunConfig;

    use super::{Ippo, OwnObservation};
    use crate::algo::batch::{Head, TrainBatch, assemble};
    use crate::algo::coordination::{Coordination, FixedLcf};
    use crate::algo::phases::Phases;
    use crate::algo::shared_ppo::SharedPpo;

    /// IPPO with the run's fixed LCF and safety option, on the CPU.
    pub fn ippo(run: &RunConfig, obs_dim: usize, action_dim: usize) -> Ippo {
        SharedPpo::new(
            "ippo",
            OwnObservation,
            Box::new(FixedLcf::new(&run.lcf)),
            run,
            obs_dim,
            action_dim,
            Device::Cpu,
        )
    }

    /// The batch of `fragment` with every critic predicting `value` (so GAE can be worked by
    /// hand): `coordination`'s heads, `gamma` where a head does not set its own.
    pub fn constant_critic_batch(
        coordination: &dyn Coordination,
        fragment: &RolloutFragment,
        value: f32,
        gamma: f32,
        lambda: f32,
    ) -> TrainBatch {
        let heads: Vec<Head> = coordination
            .signals()
            .iter()
            .enumerate()
            .map(|(index, signal)| Head {
                rewards: vec![coordination.rewards(index, fragment).unwrap()],
                value: Box::new(move |x: &Tensor| {
                    Tensor::full([x.size()[0]], f64::from(value), (Kind::Float, x.device()))
                }),
                gamma: signal.gamma.unwrap_or(gamma),
                outlives_agent: signal.outlives_agent,
            })
            .collect();
        let fragments = std::slice::from_ref(fragment);
        assemble(
            fragments,
            &OwnObservation,
            &heads,
            Tensor::shallow_clone,
            lambda,
            Device::Cpu,
            &mut Phases::default(),
        )
        .unwrap()
    }
}

#[cfg(test)]
mod tests {
    use super::fixtures::ippo;
    use crate::algo::Algorithm;
    use crate::algo::testing::one_step_fragment;
    use junction_common::fragment::RolloutFragment;
    use junction_common::policy::Policy;
    use junction_common::weights::{self, Decoded};
    use junction_core::config::{LogStdCap, LrSchedule, RunConfig};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use tch::Tensor;

    /// A one-step bandit: a single slot, observation constant, reward = −(a₀ − 0.5)². PPO must
    /// move the mean action towards 0.5.
    fn bandit_fragment(policy: &dyn Policy, rng_seed: u64) -> RolloutFragment {
        let agents = 64;
        let obs_dim = policy.obs_dim();
        let obs = vec![0.5f32; agents * obs_dim];
        let mut rng = ChaCha8Rng::seed_from_u64(rng_seed);
        let (actions, log_probs) = policy.sample(&obs, &mut rng).unwrap();
        let rewards = (0..agents)
            .map(|i| -(actions[2 * i] - 0.5).powi(2))
            .collect();
        one_step_fragment(obs, obs_dim, actions, log_probs, rewards)
    }

    fn mean_action(policy: &dyn Policy) -> f32 {
        policy
            .deterministic(&vec![0.5f32; policy.obs_dim()])
            .unwrap()[0]
    }

    #[test]
    fn ppo_moves_the_policy_towards_higher_reward() {
        let _rng = crate::test_rng::seeded(0);
        let mut run = RunConfig::default();
        run.run.seed = 7;
        run.ppo.hidden = vec![16];
        run.ppo.minibatch_size = 64;
        run.ppo.learning_rate = 0.01;
        let config = run.ppo.clone();
        let mut algo = ippo(&run, 3, 2);
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
    fn advantage_prioritised_minibatches_draw_a_batch_per_epoch_and_still_learn() {
        let _rng = crate::test_rng::seeded(3);
        let mut run = RunConfig::default();
        run.run.seed = 7;
        run.ppo.hidden = vec![16];
        run.ppo.minibatch_size = 64;
        run.ppo.learning_rate = 0.01;
        run.ppo.advantage_priority = 1.0;
        let mut algo = ippo(&run, 3, 2);
        let start = mean_action(algo.policy());
        for round in 0..30 {
            let fragment = bandit_fragment(algo.policy(), round);
            let stats = algo.update(&[fragment]).unwrap();
            assert_eq!(
                stats.samples_trained,
                64 * run.ppo.epochs,
                "a draw of 64 per epoch"
            );
            assert!(stats.policy_loss.is_finite());
        }
        let end = mean_action(algo.policy());
        assert!(
            (end - 0.5).abs() < 0.15 && (start - 0.5).abs() > 0.3,
            "mean action {start} → {end}"
        );
    }

    #[test]
    fn the_learning_rate_follows_the_schedule_told_before_each_update() {
        let _rng = crate::test_rng::seeded(2);
        let mut run = RunConfig::default();
        run.ppo.hidden = vec![8];
        run.ppo.lr_schedule = LrSchedule::Linear;
        run.run.max_agent_steps = 1000;
        let mut algo = ippo(&run, 3, 2);
        let mut rates = Vec::new();
        for consumed in [0, 250, 1000] {
            algo.set_progress(run.run.budget_spent(consumed, 0.0));
            let fragment = bandit_fragment(algo.policy(), 0);
            rates.push(algo.update(&[fragment]).unwrap().learning_rate);
        }
        let base = run.ppo.learning_rate;
        assert_eq!(rates, vec![base, 0.75 * base, 0.0]);
    }

    /// The spread of the first action value the policy samples in one state.
    fn sampled_std(policy: &dyn Policy) -> f32 {
        let rows = 4000;
        let obs = vec![0.5f32; rows * policy.obs_dim()];
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let (actions, _) = policy.sample(&obs, &mut rng).unwrap();
        let first: Vec<f32> = actions
            .iter()
            .step_by(policy.action_dim())
            .copied()
            .collect();
        let mean = first.iter().sum::<f32>() / rows as f32;
        (first.iter().map(|a| (a - mean).powi(2)).sum::<f32>() / rows as f32).sqrt()
    }

    #[test]
    fn the_log_std_cap_holds_the_policy_under_a_ceiling_falling_over_the_budget() {
        let _rng = crate::test_rng::seeded(4);
        let mut run = RunConfig::default();
        run.ppo.hidden = vec![8];
        run.run.max_agent_steps = 1000;
        let update_at = |run: &RunConfig, consumed| {
            let mut algo = ippo(run, 3, 2);
            algo.set_progress(run.run.budget_spent(consumed, 0.0));
            algo.update(&[bandit_fragment(algo.policy(), 0)]).unwrap();
            sampled_std(algo.policy())
        };
        // Learned freely, one update leaves the unit std about where it started.
        let free = update_at(&run, 500);
        assert!((free - 1.0).abs() < 0.1, "free std {free}");
        run.ppo.log_std_cap = LogStdCap::Linear;
        run.ppo.final_log_std_cap = -2.0;
        // Half the budget spent: the ceiling is −1, std e^−1 ≈ 0.37; at the start it is 0.
        let capped = update_at(&run, 500);
        assert!(
            (capped - (-1.0f32).exp()).abs() < 0.03,
            "capped std {capped}"
        );
        let at_start = update_at(&run, 0);
        assert!(
            (at_start - free).abs() < 0.05,
            "std at the start {at_start}"
        );
    }

    #[test]
    fn checkpoint_state_restores_an_identical_learner() {
        let _rng = crate::test_rng::seeded(1);
        let mut run = RunConfig::default();
        run.run.seed = 7;
        run.ppo.hidden = vec![8];
        let mut a = ippo(&run, 3, 2);
        a.update(&[bandit_fragment(a.policy(), 1)]).unwrap();
        let blob = a.policy().to_bytes(1).unwrap();
        let state = a.state_tensors();
        let refs: Vec<(String, &Tensor)> = state.iter().map(|(n, t)| (n.clone(), t)).collect();
        let bytes = weights::encode(&refs, Default::default()).unwrap();
        let mut b = ippo(&run, 3, 2);
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

/// The shared update's options (`shared_ppo.rs`) exercised through IPPO, the plain
/// `SharedPpo`: here, above both, rather than in the file IPPO builds on.
#[cfg(test)]
mod shared_ppo_tests {
    use super::Ippo;
    use super::fixtures::ippo;
    use crate::algo::Algorithm;
    use crate::algo::shared_ppo::copy_networks;
    use crate::algo::testing::{self, host_state, neighbourhood_fragment, small_run};
    use junction_core::config::{
        GlobalReturn, LcfConfig, NeighbourhoodReward, RunConfig, SafetyMode,
    };

    fn learner(lcf: &LcfConfig) -> Ippo {
        let mut run = small_run();
        run.run.seed = 3;
        run.lcf = lcf.clone();
        ippo(&run, 2, 2)
    }

    fn lagrangian_ippo() -> Ippo {
        tch::manual_seed(5);
        let mut run = small_run();
        run.run.seed = 3;
        run.safety.mode = SafetyMode::Lagrangian;
        run.safety.cost_limit = 0.5;
        run.safety.multiplier_lr = 0.1;
        ippo(&run, 2, 2)
    }

    #[test]
    fn the_lagrangian_option_trains_a_cost_critic_prices_cost_and_checkpoints_it() {
        let _rng = crate::test_rng::lock();
        let mut fragment = neighbourhood_fragment();
        fragment.costs = (0..fragment.costs.len()).map(|i| (i % 2) as f32).collect();
        fragment.episodes = vec![junction_core::episode::EpisodeStats {
            outcome: junction_core::episode::Outcome::Crash,
            length: 1,
            total_reward: -5.0,
            mean_abs_accel: 0.0,
            max_abs_accel: 0.0,
            collisions: 1,
            energy_kj: 0.0,
            total_cost: 2.5,
        }];
        let mut safe = lagrangian_ippo();
        let mut plain = learner(&RunConfig::default().lcf);
        copy_networks(&safe, &mut plain);
        let names: Vec<String> = safe.state_tensors().into_iter().map(|(n, _)| n).collect();
        assert!(
            names.iter().any(|n| n.starts_with("cost_critic")),
            "{names:?}"
        );
        let stats = safe.update(std::slice::from_ref(&fragment)).unwrap();
        // λ = 0 + 0.1 · (2.5 − 0.5)
        assert!((stats.lagrange_multiplier - 0.2).abs() < 1e-6);
        // The cost changes what is learned: a learner without the option ends elsewhere.
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

    fn kl_learner(kl_target: f64) -> Ippo {
        tch::manual_seed(5);
        let mut run = small_run();
        run.ppo.kl_coef = 0.2;
        run.ppo.kl_target = kl_target;
        ippo(&run, 2, 2)
    }

    #[test]
    fn the_kl_penalty_adapts_its_coefficient_to_the_target_and_is_checkpointed() {
        let _rng = crate::test_rng::lock();
        let fragment = neighbourhood_fragment();
        // Any update moves the policy by more than 2 · 1e-12, and by less than 1e6 / 2.
        let mut tight = kl_learner(1e-12);
        let stats = tight.update(std::slice::from_ref(&fragment)).unwrap();
        assert!(
            stats.kl > 0.0,
            "the update moved the policy: KL {}",
            stats.kl
        );
        assert!((stats.kl_coef - 0.3).abs() < 1e-7, "{}", stats.kl_coef);
        let mut loose = kl_learner(1e6);
        assert!(
            (loose
                .update(std::slice::from_ref(&fragment))
                .unwrap()
                .kl_coef
                - 0.1)
                .abs()
                < 1e-7
        );
        // The penalty changes the update: without it the policy ends elsewhere.
        let mut run = small_run();
        run.ppo.kl_target = 1e-12;
        let mut plain = ippo(&run, 2, 2);
        let mut penalised = kl_learner(1e-12);
        copy_networks(&plain, &mut penalised);
        for _ in 0..2 {
            plain.update(std::slice::from_ref(&fragment)).unwrap();
            penalised.update(std::slice::from_ref(&fragment)).unwrap();
        }
        assert_ne!(
            plain.policy().to_bytes(1).unwrap(),
            penalised.policy().to_bytes(1).unwrap()
        );
        testing::assert_checkpoint_round_trip(|| {
            let mut learner = kl_learner(1e-12);
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
            global_return: GlobalReturn::Agent,
            neighbourhood_reward: NeighbourhoodReward::Mean,
        };
        let mut plain = learner(&lcf(0.0));
        let mut cooperative = learner(&lcf(90.0));
        copy_networks(&plain, &mut cooperative);
        // IPPO without coordination configured, starting where `plain` starts.
        let mut run = small_run();
        run.run.seed = 3;
        let mut reference = ippo(&run, 2, 2);
        copy_networks(&plain, &mut reference);
        let plain_stats = plain.update(std::slice::from_ref(&fragment)).unwrap();
        let cooperative_stats = cooperative.update(std::slice::from_ref(&fragment)).unwrap();
        assert_eq!(
            (plain_stats.lcf_mean_deg, cooperative_stats.lcf_mean_deg),
            (0.0, 90.0)
        );
        // The fragment's agents have 0, 1–2 and 3–5 live neighbours, none 6 or more.
        assert_eq!(
            cooperative_stats.lcf_phi_by_neighbours,
            [Some(90.0), Some(90.0), Some(90.0), None]
        );

        // φ = 0 is exactly IPPO without coordination configured.
        reference.update(std::slice::from_ref(&fragment)).unwrap();
        assert_eq!(host_state(&plain), host_state(&reference));
        // φ = 90° learns from the neighbours' rewards: another value function.
        assert_ne!(host_state(&plain), host_state(&cooperative));
    }
}

/// A resumed shared update (`shared_ppo.rs`), exercised through IPPO.
#[cfg(test)]
mod resume_tests {
    use super::Ippo;
    use super::fixtures::ippo;
    use crate::algo::Algorithm;
    use crate::algo::testing::{host_state, neighbourhood_fragment, small_run};
    use junction_common::weights::{self, Decoded};
    use tch::Tensor;

    /// Minibatches of 4 of the fixture's 11 agent-steps: the shuffle decides what each
    /// gradient step sees.
    fn shuffling_learner() -> Ippo {
        tch::manual_seed(11);
        let mut run = small_run();
        run.ppo.minibatch_size = 4;
        run.ppo.epochs = 3;
        ippo(&run, 2, 2)
    }

    /// The state blob of `algo` with the update count set to `updates`.
    fn state_with_updates(algo: &Ippo, updates: f32) -> Vec<u8> {
        let mut state = algo.state_tensors();
        for (name, tensor) in &mut state {
            if name == "ippo.updates" {
                *tensor = Tensor::from_slice(&[updates]);
            }
        }
        let refs: Vec<(String, &Tensor)> = state.iter().map(|(n, t)| (n.clone(), t)).collect();
        weights::encode(&refs, Default::default()).unwrap()
    }

    #[test]
    fn a_resumed_learner_shuffles_its_next_minibatches_as_the_original_would() {
        let _rng = crate::test_rng::lock();
        let fragment = neighbourhood_fragment();
        let mut original = shuffling_learner();
        for _ in 0..2 {
            original.update(std::slice::from_ref(&fragment)).unwrap();
        }
        let policy = original.policy().to_bytes(2).unwrap();
        let restore = |updates: f32| {
            let mut learner = shuffling_learner();
            let state = state_with_updates(&original, updates);
            learner
                .restore(&policy, &mut Decoded::decode(&state).unwrap())
                .unwrap();
            learner
        };
        let mut resumed = restore(2.0);
        // The control: the same weights and optimiser state, but the update count lost.
        let mut forgetful = restore(0.0);
        original.update(std::slice::from_ref(&fragment)).unwrap();
        resumed.update(std::slice::from_ref(&fragment)).unwrap();
        forgetful.update(std::slice::from_ref(&fragment)).unwrap();
        assert_eq!(host_state(&original), host_state(&resumed));
        assert_eq!(
            original.policy().to_bytes(3).unwrap(),
            resumed.policy().to_bytes(3).unwrap()
        );
        assert_ne!(
            original.policy().to_bytes(3).unwrap(),
            forgetful.policy().to_bytes(3).unwrap(),
            "the minibatch order does not depend on the update count: this test proves nothing"
        );
    }
}
