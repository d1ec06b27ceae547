//! DQN: double DQN (van Hasselt et al. 2016) with parameter sharing: one Q-network over a grid
//! of `[steering, throttle_brake]` actions for every agent, trained off-policy from a replay
//! buffer of agent transitions that the actors' ε-greedy fragments fill.
//!
//! ```text
//! for each update (a batch of fragments):
//!     r ← α·cos φ·r_i + β·sin φ·r_N (fixed LCF, `[lcf]`; φ = 0: own reward)
//!     add every alive cell to the replay buffer as (s, a, r, s', done)
//!     fold the batch's observations into the running normaliser
//!     once the buffer holds learning_starts transitions,
//!     repeat new transitions × replay_ratio / batch_size times:
//!         sample (s, a, r, s', done) uniformly
//!         a* = argmax_a' Q(s', a')                     (online network chooses …)
//!         y  = r + γ·(1 − done)·Q_target(s', a*)       (… target network evaluates)
//!         L  = Huber_δ(Q(s, a) − y)
//!         Adam step on ∇L, gradient norm clipped
//!         every target_update_gradient_steps: Q_target ← Q
//!     ε ← linear schedule over the agent-steps consumed; broadcast Q and ε
//! ```

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Reduction, Tensor};

use junction_common::fragment::RolloutFragment;
use junction_common::lcf;
use junction_common::policy::Policy;
use junction_common::q_policy::QPolicy;
use junction_common::weights::{Decoded, WeightsError};
use junction_core::action_grid::ActionGrid;
use junction_core::config::{DqnConfig, GlobalReturn, LcfConfig, NeighbourhoodReward};

use super::batch::{alive_neighbour_counts, alive_observations};
use super::coordination::LcfReport;
use super::replay::ReplayBuffer;
use super::{AlgoError, Algorithm, UpdateStats};
use crate::optim::Adam;
use crate::telemetry::labels::DROP_OFF_GRID;

/// Checkpoint prefix of the target network's variables.
const TARGET: &str = "target";

/// Double-DQN targets: y = r + γ·(1 − done)·Q_target(s', argmax_a Q_online(s', a)).
/// `next_online` and `next_target` are [n, actions]; `rewards` and `dones` (1 = done) [n].
pub fn double_dqn_targets(
    next_online: &Tensor,
    next_target: &Tensor,
    rewards: &Tensor,
    dones: &Tensor,
    gamma: f64,
) -> Tensor {
    let best = next_online.argmax(-1, true);
    let next_value = next_target.gather(-1, &best, false).squeeze_dim(-1);
    rewards + (1.0 - dones) * gamma * next_value
}

pub struct Dqn {
    config: DqnConfig,
    /// The fixed LCF the rewards are coordinated with (φ = 0: the agents' own rewards).
    coordination: LcfConfig,
    online: QPolicy,
    target: QPolicy,
    adam: Adam,
    replay: ReplayBuffer,
    seed: u64,
    updates: u64,
    gradient_steps: u64,
    /// Agent-steps added to the replay buffer: what the ε schedule follows.
    agent_steps: u64,
    /// Fractional gradient steps owed by the replay ratio, carried to the next update.
    step_debt: f32,
}

impl Dqn {
    pub fn new(
        config: &DqnConfig,
        obs_dim: usize,
        device: Device,
        seed: u64,
    ) -> Result<Self, AlgoError> {
        let grid = ActionGrid::new(config.steering.clone(), config.throttle.clone())?;
        let new = |grid| QPolicy::new(device, obs_dim as i64, &config.hidden, grid, config.dueling);
        let mut online = new(grid.clone());
        let mut target = new(grid);
        target.copy_from(&online)?;
        online.set_epsilon(config.epsilon_start);
        let adam = Adam::new(online.trainable(), config.learning_rate, config.adam_eps);
        Ok(Dqn {
            config: config.clone(),
            coordination: LcfConfig {
                phi_deg: 0.0,
                alpha: 1.0,
                beta: 1.0,
                global_return: GlobalReturn::Agent,
                neighbourhood_reward: NeighbourhoodReward::Mean,
            },
            replay: ReplayBuffer::new(config.replay_capacity, obs_dim),
            online,
            target,
            adam,
            seed,
            updates: 0,
            gradient_steps: 0,
            agent_steps: 0,
            step_debt: 0.0,
        })
    }

    /// Stores coordinated rewards r_C = α·cos φ·r_i + β·sin φ·r_N (`[lcf]`).
    pub fn with_coordination(mut self, lcf: &LcfConfig) -> Self {
        self.coordination = lcf.clone();
        self
    }

    /// ε after `agent_steps` agent-steps: linear from `epsilon_start` to `epsilon_end`.
    pub fn epsilon(config: &DqnConfig, agent_steps: u64) -> f64 {
        let progress = if config.epsilon_decay_agent_steps == 0 {
            1.0
        } else {
            (agent_steps as f64 / config.epsilon_decay_agent_steps as f64).min(1.0)
        };
        config.epsilon_end + (config.epsilon_start - config.epsilon_end) * (1.0 - progress)
    }

    /// One gradient step on a sampled minibatch: (TD loss, mean Q(s, a), gradient norm), or
    /// `None` when the loss was not finite and the step was skipped.
    fn gradient_step(&mut self, rng: &mut ChaCha8Rng) -> Result<Option<[f64; 3]>, AlgoError> {
        let c = &self.config;
        let s = self.replay.sample(c.batch_size, rng, self.online.device());
        let next = self.online.normalize(&s.next_obs);
        let y = tch::no_grad(|| {
            double_dqn_targets(
                &self.online.q_values(&next),
                &self.target.q_values(&next),
                &s.rewards,
                &s.dones,
                f64::from(c.gamma),
            )
        });
        let q_all = self.online.q_values(&self.online.normalize(&s.obs));
        let q = q_all
            .gather(1, &s.actions.unsqueeze(1), false)
            .squeeze_dim(1);
        let loss = q.huber_loss(&y, Reduction::Mean, c.huber_delta);
        let loss_value = f64::try_from(&loss)?;
        if !loss_value.is_finite() {
            return Ok(None);
        }
        self.adam.zero_grad();
        loss.backward();
        let grad_norm = self.adam.clip_grad_norm(c.max_grad_norm);
        self.adam.step();
        self.gradient_steps += 1;
        if self
            .gradient_steps
            .is_multiple_of(c.target_update_gradient_steps)
        {
            self.target.copy_from(&self.online)?;
        }
        let q_mean = f64::try_from(q.detach().mean(Kind::Float))?;
        Ok(Some([loss_value, q_mean, grad_norm]))
    }

    /// Coordinates each fragment's rewards with the fixed LCF and stores its alive cells as
    /// transitions, counting them (and the fragments refused for actions off the grid) in
    /// `stats`; returns what the normaliser and the LCF report need of the cells stored.
    fn add_to_replay(&mut self, fragments: &[RolloutFragment], stats: &mut UpdateStats) -> Added {
        let lcf = &self.coordination;
        let phi = lcf.phi_deg.to_radians();
        let grid = self.online.grid().clone();
        let mut added = Added::default();
        for f in fragments {
            let rewards = lcf::coordinated_rewards(f, phi, lcf);
            match self.replay.push_fragment(f, &rewards, |a| grid.index_of(a)) {
                Some(count) => {
                    stats.agent_steps += count;
                    let f = std::slice::from_ref(f);
                    added.neighbour_counts.extend(alive_neighbour_counts(f));
                    if self.config.normalize_observations {
                        added.observations.extend(alive_observations(f));
                    }
                }
                None => stats.off_grid_fragments += 1,
            }
        }
        added
    }

    /// The fixed φ every transition's reward was coordinated with, by neighbour count: the
    /// report the PPO algorithms' coordination gives, so DQN's reads like theirs.
    fn fixed_phi_by_neighbours(
        &self,
        neighbour_counts: &[usize],
    ) -> [Option<f64>; lcf::NEIGHBOUR_BUCKETS.len()] {
        let phi_deg = self.coordination.phi_deg;
        LcfReport::from_rows(&vec![phi_deg; neighbour_counts.len()], neighbour_counts).by_neighbours
    }

    /// Folds the stored observations into the online network's running statistics (empty
    /// without `normalize_observations`), the ones actors normalise with after the broadcast.
    fn fold_observations(&mut self, observations: &[f32]) -> Result<(), AlgoError> {
        if !observations.is_empty() {
            let mut normalizer = self.online.obs_stats()?;
            normalizer.update(observations);
            self.online.set_obs_stats(&normalizer);
        }
        Ok(())
    }

    /// Whole gradient steps the replay ratio asks for after `new_transitions`; the fraction
    /// left is owed to the next update, so the ratio holds over a run, not per update.
    fn gradient_steps_owed(&mut self, new_transitions: usize) -> usize {
        let c = &self.config;
        self.step_debt += new_transitions as f32 * c.replay_ratio / c.batch_size as f32;
        let steps = self.step_debt.floor();
        self.step_debt -= steps;
        steps as usize
    }

    /// `steps` gradient steps on minibatches drawn with this update's seed (a resumed run
    /// draws what the original would), their means into `stats`.
    fn train(&mut self, steps: usize, stats: &mut UpdateStats) -> Result<(), AlgoError> {
        let mut rng =
            ChaCha8Rng::seed_from_u64(self.seed ^ self.updates.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let mut taken = 0usize;
        for _ in 0..steps {
            match self.gradient_step(&mut rng)? {
                Some([loss, q_mean, grad_norm]) => {
                    stats.value_loss += loss;
                    stats.q_mean += q_mean;
                    stats.grad_norm += grad_norm;
                    stats.samples_trained += self.config.batch_size;
                    taken += 1;
                }
                None => stats.skipped_minibatches += 1,
            }
        }
        let n = taken.max(1) as f64;
        for field in [
            &mut stats.value_loss,
            &mut stats.q_mean,
            &mut stats.grad_norm,
        ] {
            *field /= n;
        }
        Ok(())
    }
}

/// What an update stored, as the normaliser and the LCF report take it.
#[derive(Default)]
struct Added {
    /// Observations of the stored cells, row-major (empty without `normalize_observations`).
    observations: Vec<f32>,
    /// Live neighbours of each stored cell's agent.
    neighbour_counts: Vec<usize>,
}

impl Algorithm for Dqn {
    fn name(&self) -> &'static str {
        "dqn"
    }

    fn policy(&self) -> &dyn Policy {
        &self.online
    }

    /// Actions off the grid have no Q-value to learn (an actor running another policy).
    fn refusal(&self, fragment: &RolloutFragment) -> Option<&'static str> {
        let grid = self.online.grid();
        let a = fragment.action_dim;
        let off_grid = (0..fragment.steps * fragment.agents)
            .filter(|&cell| fragment.alive[cell])
            .any(|cell| {
                grid.index_of(&fragment.actions[cell * a..(cell + 1) * a])
                    .is_none()
            });
        off_grid.then_some(DROP_OFF_GRID)
    }

    /// The module documentation's outline, one line per stage.
    fn update(&mut self, fragments: &[RolloutFragment]) -> Result<UpdateStats, AlgoError> {
        let mut stats = UpdateStats {
            learning_rate: self.adam.learning_rate(),
            lcf_mean_deg: f64::from(self.coordination.phi_deg),
            ..UpdateStats::default()
        };
        let added = self.add_to_replay(fragments, &mut stats);
        stats.lcf_phi_by_neighbours = self.fixed_phi_by_neighbours(&added.neighbour_counts);
        if stats.agent_steps == 0 && stats.off_grid_fragments == 0 {
            return Err(AlgoError::EmptyBatch);
        }
        self.fold_observations(&added.observations)?;
        self.agent_steps += stats.agent_steps as u64;
        if self.replay.len() >= self.config.learning_starts.max(1) {
            let steps = self.gradient_steps_owed(stats.agent_steps);
            self.train(steps, &mut stats)?;
        }
        self.online
            .set_epsilon(Self::epsilon(&self.config, self.agent_steps));
        stats.epsilon = self.online.epsilon();
        stats.replay_transitions = self.replay.len();
        self.updates += 1;
        Ok(stats)
    }

    fn state_tensors(&self) -> Vec<(String, Tensor)> {
        let mut state: Vec<(String, Tensor)> = self
            .target
            .named_tensors()
            .into_iter()
            .map(|(name, t)| (format!("{TARGET}.{name}"), t))
            .collect();
        state.extend(self.adam.state("adam"));
        for (name, value) in [
            ("dqn.updates", self.updates),
            ("dqn.gradient_steps", self.gradient_steps),
            ("dqn.agent_steps", self.agent_steps),
        ] {
            state.push((name.into(), counter_tensor(value)));
        }
        state.push((
            "dqn.step_debt".into(),
            Tensor::from_slice(&[self.step_debt]),
        ));
        if self.config.checkpoint_replay {
            state.extend(self.replay.state());
        }
        state
    }

    fn restore(&mut self, policy_blob: &[u8], state: &mut Decoded) -> Result<(), WeightsError> {
        self.online.load_bytes(policy_blob)?;
        // Check every tensor before changing the target network.
        let targets = self
            .target
            .named_tensors()
            .into_iter()
            .map(|(name, var)| Ok((state.take(&format!("{TARGET}.{name}"), &var.size())?, var)))
            .collect::<Result<Vec<_>, WeightsError>>()?;
        tch::no_grad(|| {
            for (source, mut var) in targets {
                var.copy_(&source);
            }
        });
        self.adam.load_state("adam", state)?;
        self.updates = read_counter(state, "dqn.updates")?;
        self.gradient_steps = read_counter(state, "dqn.gradient_steps")?;
        self.agent_steps = read_counter(state, "dqn.agent_steps")?;
        let debt = state.take("dqn.step_debt", &[1])?;
        self.step_debt = Vec::<f32>::try_from(debt)?[0];
        self.replay = ReplayBuffer::new(self.config.replay_capacity, self.online.obs_dim());
        if ReplayBuffer::in_state(state) {
            self.replay.load_state(state, self.online.grid().len())?;
        }
        self.online
            .set_epsilon(Self::epsilon(&self.config, self.agent_steps));
        Ok(())
    }
}

/// A count as two f32 (the high and low 24 bits), exact up to 2⁴⁸ where one f32 is exact only
/// up to 2²⁴ (17 M agent-steps pass in well under an hour).
fn counter_tensor(value: u64) -> Tensor {
    let (high, low) = (value >> 24, value & 0xFF_FFFF);
    Tensor::from_slice(&[high as f32, low as f32])
}

fn read_counter(state: &mut Decoded, name: &str) -> Result<u64, WeightsError> {
    let parts = Vec::<f32>::try_from(state.take(name, &[2])?)?;
    let valid = |x: f32| x >= 0.0 && x.fract() == 0.0;
    if !(valid(parts[0]) && valid(parts[1]) && parts[1] < (1 << 24) as f32) {
        return Err(WeightsError::Metadata { key: name.into() });
    }
    Ok(((parts[0] as u64) << 24) | parts[1] as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::testing::{
        assert_checkpoint_round_trip, host_state, neighbourhood_fragment, one_step_fragment,
    };
    use junction_common::weights;
    use junction_core::config::RunConfig;

    fn host(t: &Tensor) -> Vec<f32> {
        Vec::<f32>::try_from(t.to_kind(Kind::Float).flatten(0, -1)).unwrap()
    }

    #[test]
    fn double_dqn_targets_let_the_online_network_choose_and_the_target_evaluate() {
        // Row 0: the online network prefers action 1, whose target value is 20 (plain DQN
        // would bootstrap from the target's own maximum, 30). Row 1: done, no bootstrap.
        // Row 2: online prefers action 2 (-1), the target values it at -4.
        let next_online = Tensor::from_slice(&[1.0f32, 3.0, 2.0, 5.0, 0.0, 0.0, -3.0, -2.0, -1.0])
            .reshape([3, 3]);
        let next_target = Tensor::from_slice(&[10.0f32, 20.0, 30.0, 7.0, 8.0, 9.0, 6.0, 5.0, -4.0])
            .reshape([3, 3]);
        let rewards = Tensor::from_slice(&[1.0f32, 2.0, 0.5]);
        let dones = Tensor::from_slice(&[0.0f32, 1.0, 0.0]);
        let y = double_dqn_targets(&next_online, &next_target, &rewards, &dones, 0.5);
        // 1 + 0.5·20 = 11; 2 (done); 0.5 + 0.5·(−4) = −1.5
        assert_eq!(host(&y), vec![11.0, 2.0, -1.5]);
    }

    /// The fixture's actions, (0.1·(s + 1), 0.5 − t), are exactly the points of this grid.
    fn fixture_config() -> DqnConfig {
        let mut c = RunConfig::default().dqn;
        c.steering = (1..=6).map(|s| 0.1 * s as f32).collect();
        c.throttle = vec![-0.5, 0.5];
        c.hidden = vec![8];
        c.batch_size = 4;
        c.replay_ratio = 2.0;
        c.learning_starts = 1;
        c.target_update_gradient_steps = 3;
        c.epsilon_decay_agent_steps = 20;
        c
    }

    fn dqn(config: &DqnConfig) -> Dqn {
        tch::manual_seed(7);
        Dqn::new(config, 2, Device::Cpu, 3).unwrap()
    }

    #[test]
    fn an_update_stores_transitions_steps_by_the_replay_ratio_and_follows_the_epsilon_schedule() {
        let _rng = crate::test_rng::lock();
        let config = fixture_config();
        let mut learner = dqn(&config);
        assert_eq!(learner.online.epsilon(), 1.0, "ε starts at epsilon_start");
        let fragment = neighbourhood_fragment();
        let stats = learner.update(std::slice::from_ref(&fragment)).unwrap();
        // 11 alive cells; 11 × 2 / 4 = 5.5 → 5 steps of 4, 0.5 carried over.
        assert_eq!((stats.agent_steps, stats.replay_transitions), (11, 11));
        assert_eq!((stats.samples_trained, learner.gradient_steps), (20, 5));
        assert_eq!(learner.step_debt, 0.5);
        assert!(stats.value_loss > 0.0 && stats.q_mean.is_finite() && stats.grad_norm > 0.0);
        // ε = 0.01 + (1 − 0.01) · (1 − 11/20)
        assert!((stats.epsilon - (1.0 - 0.99 * 11.0 / 20.0)).abs() < 1e-12);
        // 5 steps synced the target once (after step 3), so it differs from the online net
        // again, but not from what it was at step 3: check it moved off its initial weights.
        let initial = dqn(&config).target.named_tensors();
        let moved = learner
            .target
            .named_tensors()
            .iter()
            .zip(&initial)
            .any(|((_, a), (_, b))| host(a) != host(b));
        assert!(moved, "the target was synced");

        let stats = learner.update(std::slice::from_ref(&fragment)).unwrap();
        // 11 × 2 / 4 + 0.5 = 6 steps; ε has reached its end value.
        assert_eq!((stats.samples_trained, learner.gradient_steps), (24, 11));
        assert_eq!((stats.epsilon, stats.replay_transitions), (0.01, 22));
        assert_eq!(learner.online.epsilon(), 0.01, "the broadcast carries ε");
    }

    #[test]
    fn no_gradient_step_before_learning_starts() {
        let _rng = crate::test_rng::lock();
        let mut config = fixture_config();
        config.learning_starts = 12;
        let mut learner = dqn(&config);
        let fragment = neighbourhood_fragment();
        let stats = learner.update(std::slice::from_ref(&fragment)).unwrap();
        assert_eq!((stats.samples_trained, stats.replay_transitions), (0, 11));
        let stats = learner.update(std::slice::from_ref(&fragment)).unwrap();
        // 22 ≥ 12: this update's 11 transitions are owed, 11 × 2 / 4 = 5 steps.
        assert_eq!(stats.samples_trained, 20);
    }

    #[test]
    fn off_grid_fragments_are_counted_and_not_learned_from() {
        let _rng = crate::test_rng::lock();
        let mut learner = dqn(&fixture_config());
        let on_grid = neighbourhood_fragment();
        let mut off_grid = neighbourhood_fragment();
        off_grid.actions[0] = 0.15;
        let stats = learner.update(&[off_grid.clone(), on_grid]).unwrap();
        assert_eq!((stats.off_grid_fragments, stats.agent_steps), (1, 11));
        let stats = learner.update(&[off_grid]).unwrap();
        assert_eq!((stats.off_grid_fragments, stats.agent_steps), (1, 0));
        assert_eq!(stats.replay_transitions, 11);
        // A Gaussian policy's continuous actions are off any grid.
        let mut gaussian = neighbourhood_fragment();
        gaussian.actions.iter_mut().for_each(|a| *a += 0.013);
        assert_eq!(learner.update(&[gaussian]).unwrap().off_grid_fragments, 1);
    }

    #[test]
    fn the_replay_stores_coordinated_rewards() {
        let _rng = crate::test_rng::lock();
        let fragment = neighbourhood_fragment();
        let cooperative = LcfConfig {
            phi_deg: 90.0,
            alpha: 1.0,
            beta: 1.0,
            global_return: GlobalReturn::Agent,
            neighbourhood_reward: NeighbourhoodReward::Mean,
        };
        let mut learner = dqn(&fixture_config()).with_coordination(&cooperative);
        learner.update(std::slice::from_ref(&fragment)).unwrap();
        let state = learner.replay.state();
        let stored = host(&state.iter().find(|(n, _)| n == "replay.rewards").unwrap().1);
        let expected: Vec<f32> =
            lcf::coordinated_rewards(&fragment, 90f32.to_radians(), &cooperative)
                .iter()
                .zip(&fragment.alive)
                .filter(|(_, alive)| **alive)
                .map(|(r, _)| *r)
                .collect();
        assert_eq!(stored, expected);
        assert_ne!(
            stored[..5],
            fragment.rewards[..5],
            "φ = 90° is not the own reward"
        );
    }

    #[test]
    fn a_restored_learner_with_its_replay_continues_bit_for_bit() {
        let mut config = fixture_config();
        config.checkpoint_replay = true;
        assert_checkpoint_round_trip(|| {
            let mut learner = dqn(&config);
            learner.update(&[neighbourhood_fragment()]).unwrap();
            learner
        });
    }

    #[test]
    fn without_its_replay_a_restored_learner_keeps_networks_optimiser_and_counters() {
        let _rng = crate::test_rng::lock();
        let config = fixture_config();
        let mut a = dqn(&config);
        a.update(&[neighbourhood_fragment()]).unwrap();
        let state = a.state_tensors();
        assert!(state.iter().all(|(n, _)| !n.starts_with("replay.")));
        let refs: Vec<(String, &Tensor)> = state.iter().map(|(n, t)| (n.clone(), t)).collect();
        let bytes = weights::encode(&refs, Default::default()).unwrap();
        let mut b = dqn(&config);
        b.restore(
            &a.policy().to_bytes(1).unwrap(),
            &mut Decoded::decode(&bytes).unwrap(),
        )
        .unwrap();
        assert_eq!(host_state(&a), host_state(&b));
        assert_eq!(
            a.policy().to_bytes(1).unwrap(),
            b.policy().to_bytes(1).unwrap()
        );
        assert_eq!(
            (b.replay.len(), b.online.epsilon()),
            (0, a.online.epsilon())
        );
        // A checkpoint of another grid size is refused.
        let mut other = config.clone();
        other.throttle = vec![0.5];
        assert!(
            dqn(&other)
                .restore(
                    &a.policy().to_bytes(1).unwrap(),
                    &mut Decoded::decode(&bytes).unwrap()
                )
                .is_err()
        );
    }

    #[test]
    fn counters_survive_beyond_what_one_float_holds() {
        for value in [
            0,
            1,
            (1 << 24) - 1,
            1 << 24,
            (1 << 30) + 5,
            (1u64 << 47) + 3,
        ] {
            let t = counter_tensor(value);
            let mut state = Decoded {
                tensors: [("c".to_string(), t)].into(),
                metadata: Default::default(),
            };
            assert_eq!(read_counter(&mut state, "c").unwrap(), value);
        }
    }

    /// A one-step bandit over the 5 × 5 grid: reward −(steering − 0.5)² − (throttle − 1)², every
    /// episode done after one step. DQN must learn Q ≈ r and act greedily at (0.5, 1).
    #[test]
    fn dqn_learns_the_best_grid_point_of_a_bandit() {
        let _rng = crate::test_rng::seeded(0);
        let mut config = RunConfig::default().dqn;
        config.hidden = vec![16];
        config.batch_size = 32;
        config.replay_ratio = 8.0;
        config.learning_starts = 64;
        config.learning_rate = 3e-3;
        config.epsilon_decay_agent_steps = 1_000_000;
        let mut learner = Dqn::new(&config, 3, Device::Cpu, 1).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let agents = 64;
        let obs = vec![0.5f32; agents * 3];
        for _ in 0..40 {
            let (actions, log_probs) = learner.policy().sample(&obs, &mut rng).unwrap();
            let rewards = actions
                .chunks(2)
                .map(|a| -(a[0] - 0.5).powi(2) - (a[1] - 1.0).powi(2))
                .collect();
            let fragment = one_step_fragment(obs.clone(), 3, actions, log_probs, rewards);
            fragment.validate(Some((3, 2))).unwrap();
            learner.update(&[fragment]).unwrap();
        }
        let greedy = learner.policy().deterministic(&obs[..3]).unwrap();
        assert_eq!(greedy, vec![0.5, 1.0]);
        let q = learner.online.q_values(
            &learner
                .online
                .normalize(&Tensor::from_slice(&obs[..3]).reshape([1, 3])),
        );
        let q = host(&q);
        assert!(q[23].abs() < 0.1, "Q(best) ≈ 0: {}", q[23]);
        assert!((q[0] + 6.25).abs() < 0.5, "Q(-1, -1) ≈ -6.25: {}", q[0]);
    }
}
