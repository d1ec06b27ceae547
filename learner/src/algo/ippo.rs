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

#[cfg(test)]
mod tests {
    use crate::algo::Algorithm;
    use crate::algo::testing::{ippo, one_step_fragment};
    use junction_common::fragment::RolloutFragment;
    use junction_common::policy::Policy;
    use junction_common::weights::{self, Decoded};
    use junction_core::config::{LrSchedule, RunConfig};
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
