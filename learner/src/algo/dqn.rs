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

use junction_common::config::{DqnConfig, LcfConfig};
use junction_common::fragment::RolloutFragment;
use junction_common::lcf;
use junction_common::policy::Policy;
use junction_common::q_policy::{ActionGrid, QPolicy};
use junction_common::weights::{Decoded, WeightsError};

use super::batch::alive_observations;
use super::replay::ReplayBuffer;
use super::{AlgoError, Algorithm, UpdateStats};
use crate::optim::Adam;

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
        let mut online = QPolicy::new(device, obs_dim as i64, &config.hidden, grid.clone());
        let mut target = QPolicy::new(device, obs_dim as i64, &config.hidden, grid);
        target.copy_from(&online)?;
        online.set_epsilon(config.epsilon_start);
        let adam = Adam::new(online.trainable(), config.learning_rate, config.adam_eps);
        Ok(Dqn {
            config: config.clone(),
            coordination: LcfConfig {
                phi_deg: 0.0,
                alpha: 1.0,
                beta: 1.0,
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
        config.epsilon_start + (config.epsilon_end - config.epsilon_start) * progress
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
        if self.gradient_steps % c.target_update_gradient_steps == 0 {
            self.target.copy_from(&self.online)?;
        }
        let q_mean = f64::try_from(q.detach().mean(Kind::Float))?;
        Ok(Some([loss_value, q_mean, grad_norm]))
    }
}

impl Algorithm for Dqn {
    fn name(&self) -> &'static str {
        "dqn"
    }

    fn policy(&self) -> &dyn Policy {
        &self.online
    }

    fn update(&mut self, fragments: &[RolloutFragment]) -> Result<UpdateStats, AlgoError> {
        let lcf = &self.coordination;
        let phi = lcf.phi_deg.to_radians();
        let grid = self.online.grid().clone();
        let mut stats = UpdateStats {
            learning_rate: self.adam.learning_rate(),
            lcf_mean_deg: f64::from(lcf.phi_deg),
            ..UpdateStats::default()
        };
        let mut observations = Vec::new();
        for f in fragments {
            let rewards = lcf::coordinated_rewards(f, phi, lcf.alpha, lcf.beta);
            match self.replay.push_fragment(f, &rewards, |a| grid.index_of(a)) {
                Some(added) => {
                    stats.agent_steps += added;
                    if self.config.normalize_observations {
                        observations.extend(alive_observations(std::slice::from_ref(f)));
                    }
                }
                None => stats.off_grid_fragments += 1,
            }
        }
        if stats.agent_steps == 0 && stats.off_grid_fragments == 0 {
            return Err(AlgoError::EmptyBatch);
        }
        if !observations.is_empty() {
            let mut normalizer = self.online.obs_stats()?;
            normalizer.update(&observations);
            self.online.set_obs_stats(&normalizer);
        }
        self.agent_steps += stats.agent_steps as u64;

        let c = &self.config;
        if self.replay.len() >= c.learning_starts.max(1) {
            self.step_debt += stats.agent_steps as f32 * c.replay_ratio / c.batch_size as f32;
            let steps = self.step_debt.floor();
            self.step_debt -= steps;
            let mut rng = ChaCha8Rng::seed_from_u64(
                self.seed ^ self.updates.wrapping_mul(0x9E37_79B9_7F4A_7C15),
            );
            let mut taken = 0usize;
            for _ in 0..steps as usize {
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
