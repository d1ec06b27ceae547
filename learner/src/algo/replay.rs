//! The replay buffer of off-policy algorithms: agent transitions (s, a, r, s', done) cut out of
//! rollout fragments, in a ring of fixed capacity, sampled uniformly with replacement.
//!
//! A fragment's alive cell (t, i) is one transition, following the slot semantics of
//! `RolloutFragment`: s' is the slot's observation at t + 1 (the same agent: an agent alive
//! and not done stays in its slot), or `bootstrap_obs` after the last step; `done` ends the
//! agent's episode, so its s' is never used (stored as zeros) and the bootstrap is cut. Empty
//! cells are no transitions.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Tensor};

use junction_common::fragment::RolloutFragment;
use junction_common::weights::{Decoded, WeightsError};

/// Checkpoint names of the buffer's arrays, under this prefix.
const PREFIX: &str = "replay";

/// A minibatch of transitions on the training device.
pub struct Sample {
    /// Raw observations [n, obs_dim] (algorithms normalise them).
    pub obs: Tensor,
    /// Action indices [n] (int64).
    pub actions: Tensor,
    pub rewards: Tensor,
    pub next_obs: Tensor,
    /// 1 where the transition ended the agent's episode.
    pub dones: Tensor,
}

pub struct ReplayBuffer {
    capacity: usize,
    obs_dim: usize,
    obs: Vec<f32>,
    next_obs: Vec<f32>,
    actions: Vec<i64>,
    rewards: Vec<f32>,
    dones: Vec<f32>,
    /// Where the next transition goes once the ring is full.
    cursor: usize,
}

impl ReplayBuffer {
    /// An empty buffer; memory grows with the transitions up to `capacity`.
    pub fn new(capacity: usize, obs_dim: usize) -> Self {
        ReplayBuffer {
            capacity: capacity.max(1),
            obs_dim,
            obs: Vec::new(),
            next_obs: Vec::new(),
            actions: Vec::new(),
            rewards: Vec::new(),
            dones: Vec::new(),
            cursor: 0,
        }
    }

    pub fn len(&self) -> usize {
        self.actions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.actions.is_empty()
    }

    fn push(&mut self, obs: &[f32], action: i64, reward: f32, next: &[f32], done: bool) {
        let d = self.obs_dim;
        let done = if done { 1.0 } else { 0.0 };
        if self.len() < self.capacity {
            self.obs.extend_from_slice(obs);
            self.next_obs.extend_from_slice(next);
            self.actions.push(action);
            self.rewards.push(reward);
            self.dones.push(done);
        } else {
            let i = self.cursor;
            self.obs[i * d..(i + 1) * d].copy_from_slice(obs);
            self.next_obs[i * d..(i + 1) * d].copy_from_slice(next);
            self.actions[i] = action;
            self.rewards[i] = reward;
            self.dones[i] = done;
        }
        self.cursor = (self.cursor + 1) % self.capacity;
    }

    /// Adds every alive cell of `fragment` as a transition with reward `rewards[cell]` and the
    /// action index `action_index` gives its action. A fragment with any action it maps to
    /// `None` adds nothing and returns `None`; otherwise the number of transitions added.
    pub fn push_fragment(
        &mut self,
        fragment: &RolloutFragment,
        rewards: &[f32],
        action_index: impl Fn(&[f32]) -> Option<usize>,
    ) -> Option<usize> {
        let f = fragment;
        let (d, a) = (f.obs_dim, f.action_dim);
        let alive_cells = || (0..f.steps * f.agents).filter(|&cell| f.alive[cell]);
        let indices: Vec<usize> = alive_cells()
            .map(|cell| action_index(&f.actions[cell * a..(cell + 1) * a]))
            .collect::<Option<_>>()?;
        let zeros = vec![0.0; d];
        for (cell, action) in alive_cells().zip(indices) {
            let (t, slot) = (cell / f.agents, cell % f.agents);
            let next = if f.dones[cell] {
                &zeros
            } else if t + 1 < f.steps {
                let next_cell = cell + f.agents;
                &f.obs[next_cell * d..(next_cell + 1) * d]
            } else {
                &f.bootstrap_obs[slot * d..(slot + 1) * d]
            };
            let obs = &f.obs[cell * d..(cell + 1) * d];
            self.push(obs, action as i64, rewards[cell], next, f.dones[cell]);
        }
        Some(f.agent_steps())
    }

    /// `size` transitions drawn uniformly with replacement by `rng`; the buffer must not be
    /// empty (learners sample once it holds `learning_starts` ≥ 1 transitions).
    pub fn sample(&self, size: usize, rng: &mut ChaCha8Rng, device: Device) -> Sample {
        let d = self.obs_dim;
        let picks: Vec<usize> = (0..size).map(|_| rng.gen_range(0..self.len())).collect();
        let rows = |source: &[f32]| -> Tensor {
            let mut out = Vec::with_capacity(size * d);
            for &i in &picks {
                out.extend_from_slice(&source[i * d..(i + 1) * d]);
            }
            Tensor::from_slice(&out)
                .reshape([size as i64, d as i64])
                .to_device(device)
        };
        let column = |source: &[f32]| -> Tensor {
            let values: Vec<f32> = picks.iter().map(|&i| source[i]).collect();
            Tensor::from_slice(&values).to_device(device)
        };
        let actions: Vec<i64> = picks.iter().map(|&i| self.actions[i]).collect();
        Sample {
            obs: rows(&self.obs),
            actions: Tensor::from_slice(&actions).to_device(device),
            rewards: column(&self.rewards),
            next_obs: rows(&self.next_obs),
            dones: column(&self.dones),
        }
    }

    /// The whole ring as it lies in memory, for checkpoints (`replay.*`).
    pub fn state(&self) -> Vec<(String, Tensor)> {
        let (n, d) = (self.len() as i64, self.obs_dim as i64);
        let actions: Vec<f32> = self.actions.iter().map(|&a| a as f32).collect();
        vec![
            (
                format!("{PREFIX}.len_cursor"),
                Tensor::from_slice(&[n as f32, self.cursor as f32]),
            ),
            (
                format!("{PREFIX}.obs"),
                Tensor::from_slice(&self.obs).reshape([n, d]),
            ),
            (
                format!("{PREFIX}.next_obs"),
                Tensor::from_slice(&self.next_obs).reshape([n, d]),
            ),
            (format!("{PREFIX}.actions"), Tensor::from_slice(&actions)),
            (
                format!("{PREFIX}.rewards"),
                Tensor::from_slice(&self.rewards),
            ),
            (format!("{PREFIX}.dones"), Tensor::from_slice(&self.dones)),
        ]
    }

    /// Whether `state` holds a checkpointed buffer.
    pub fn in_state(state: &Decoded) -> bool {
        state.tensors.contains_key(&format!("{PREFIX}.len_cursor"))
    }

    /// Restores a ring written by [`ReplayBuffer::state`]; it must fit this buffer's capacity
    /// and observation size, and its actions must be indices below `actions`.
    pub fn load_state(&mut self, state: &mut Decoded, actions: usize) -> Result<(), WeightsError> {
        let bad = |what: &str| WeightsError::Metadata {
            key: format!("{PREFIX}.{what}"),
        };
        let header = Vec::<f32>::try_from(state.take(&format!("{PREFIX}.len_cursor"), &[2])?)?;
        let (len, cursor) = (header[0] as usize, header[1] as usize);
        let full_or_tail = cursor == len % self.capacity || len == self.capacity;
        if len > self.capacity || cursor >= self.capacity || !full_or_tail {
            return Err(bad("len_cursor (does not fit dqn.replay_capacity)"));
        }
        let (n, d) = (len as i64, self.obs_dim as i64);
        let host = |t: Tensor| -> Result<Vec<f32>, WeightsError> {
            Ok(Vec::<f32>::try_from(t.to_kind(Kind::Float).flatten(0, -1))?)
        };
        let obs = host(state.take(&format!("{PREFIX}.obs"), &[n, d])?)?;
        let next_obs = host(state.take(&format!("{PREFIX}.next_obs"), &[n, d])?)?;
        let action_values = host(state.take(&format!("{PREFIX}.actions"), &[n])?)?;
        let rewards = host(state.take(&format!("{PREFIX}.rewards"), &[n])?)?;
        let dones = host(state.take(&format!("{PREFIX}.dones"), &[n])?)?;
        let in_range = |a: &f32| a.fract() == 0.0 && *a >= 0.0 && (*a as usize) < actions;
        if !action_values.iter().all(in_range) {
            return Err(bad("actions (not indices of the configured grid)"));
        }
        if !dones.iter().all(|&x| x == 0.0 || x == 1.0) {
            return Err(bad("dones"));
        }
        *self = ReplayBuffer {
            capacity: self.capacity,
            obs_dim: self.obs_dim,
            obs,
            next_obs,
            actions: action_values.into_iter().map(|a| a as i64).collect(),
            rewards,
            dones,
            cursor,
        };
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::testing::neighbourhood_fragment;
    use rand::SeedableRng;

    fn host(t: &Tensor) -> Vec<f32> {
        Vec::<f32>::try_from(t.to_kind(Kind::Float).flatten(0, -1)).unwrap()
    }

    #[test]
    fn transitions_follow_the_slot_semantics_of_fragments() {
        // 2 steps × 6 slots; slot 5 is done at t = 0 and empty at t = 1 (see the fixture).
        let f = neighbourhood_fragment();
        let rewards: Vec<f32> = (0..12).map(|i| i as f32).collect();
        let mut buffer = ReplayBuffer::new(100, 2);
        // Action index = 10 · the action's first value (0.1 … 0.6 → 1 … 6).
        let index = |a: &[f32]| Some((a[0] * 10.0).round() as usize);
        assert_eq!(buffer.push_fragment(&f, &rewards, index), Some(11));
        assert_eq!(buffer.len(), 11, "the empty cell is no transition");
        // Cells in order: t = 0 slots 0–5, then t = 1 slots 0–4.
        // obs(t, s) = [s + 1, 10t + 1], bootstrap(s) = [100 + s, 7].
        assert_eq!(&buffer.obs[..4], &[1.0, 1.0, 2.0, 1.0]);
        // t = 0, slot 0 → s' = obs(1, 0) = [1, 11].
        assert_eq!(&buffer.next_obs[..2], &[1.0, 11.0]);
        // t = 0, slot 5 is done: no s', the bootstrap is cut.
        assert_eq!(
            (buffer.dones[5], &buffer.next_obs[10..12]),
            (1.0, &[0.0, 0.0][..])
        );
        // t = 1 (the last step), slot 2 → s' = bootstrap(2) = [102, 7], reward of cell 8.
        assert_eq!(&buffer.next_obs[16..18], &[102.0, 7.0]);
        assert_eq!((buffer.rewards[8], buffer.dones[8]), (8.0, 0.0));
        assert_eq!(buffer.actions, vec![1, 2, 3, 4, 5, 6, 1, 2, 3, 4, 5]);

        // A fragment with any unmapped action adds nothing.
        let before = buffer.len();
        let refuse_six = |a: &[f32]| Some((a[0] * 10.0).round() as usize).filter(|&i| i != 6);
        assert_eq!(buffer.push_fragment(&f, &rewards, refuse_six), None);
        assert_eq!(buffer.len(), before);
    }

    #[test]
    fn the_ring_overwrites_the_oldest_and_round_trips_through_a_checkpoint() {
        let f = neighbourhood_fragment();
        let rewards: Vec<f32> = (0..12).map(|i| i as f32).collect();
        let mut buffer = ReplayBuffer::new(8, 2);
        let index = |a: &[f32]| Some((a[0] * 10.0).round() as usize);
        buffer.push_fragment(&f, &rewards, index);
        assert_eq!((buffer.len(), buffer.cursor), (8, 3));
        // Transitions 8, 9, 10 (cells 8, 9, 10, with those rewards) replaced 0–2.
        assert_eq!(&buffer.rewards[..3], &[8.0, 9.0, 10.0]);

        let state = buffer.state();
        let refs: Vec<(String, &Tensor)> = state.iter().map(|(n, t)| (n.clone(), t)).collect();
        let bytes = junction_common::weights::encode(&refs, Default::default()).unwrap();
        let mut restored = ReplayBuffer::new(8, 2);
        let mut decoded = Decoded::decode(&bytes).unwrap();
        assert!(ReplayBuffer::in_state(&decoded));
        restored.load_state(&mut decoded, 7).unwrap();
        let draw = |b: &ReplayBuffer| {
            let s = b.sample(5, &mut ChaCha8Rng::seed_from_u64(3), Device::Cpu);
            (
                host(&s.obs),
                host(&s.actions),
                host(&s.rewards),
                host(&s.next_obs),
                host(&s.dones),
            )
        };
        assert_eq!(draw(&restored), draw(&buffer));
        // A smaller buffer cannot hold it, and actions beyond the grid are refused.
        assert!(
            ReplayBuffer::new(4, 2)
                .load_state(&mut Decoded::decode(&bytes).unwrap(), 7)
                .is_err()
        );
        assert!(
            ReplayBuffer::new(8, 2)
                .load_state(&mut Decoded::decode(&bytes).unwrap(), 5)
                .is_err()
        );
    }
}
