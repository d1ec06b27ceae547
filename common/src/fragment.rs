//! `RolloutFragment`: T scene steps × N agent slots of one scene, structure of arrays.
//!
//! Slot semantics: `alive[t][i]` means slot `i` held an agent that observed `obs[t][i]` and took
//! `actions[t][i]`, receiving `rewards[t][i]`; `dones[t][i]` ends that agent's episode, and a
//! new agent may occupy the slot from `t + 1`. An agent alive and not done at `t < T - 1` is
//! alive at `t + 1`. Agents alive and not done at `T - 1` continue in the next fragment; their
//! value is bootstrapped from `bootstrap_obs`.
//!
//! Everything that crosses a process boundary is checked by [`RolloutFragment::validate`]
//! before use: shapes, finiteness, flags and the slot invariants above.

use crate::proto;
use junction_core::lcf_inputs;

use junction_core::episode::{EpisodeStats, Outcome, SceneEpisodeStats};
use junction_core::spec::{
    MAX_ACTION_DIM, MAX_AGENTS, MAX_NAME_BYTES, MAX_OBS_DIM, MAX_STEPS, PROTOCOL_VERSION,
};

fn scene_episode_from_proto(e: &proto::SceneEpisodeStats) -> SceneEpisodeStats {
    SceneEpisodeStats {
        steps: e.steps,
        successes: e.successes,
        crashes: e.crashes,
        out_of_road: e.out_of_road,
        timeouts: e.timeouts,
    }
}

fn scene_episode_to_proto(e: SceneEpisodeStats) -> proto::SceneEpisodeStats {
    proto::SceneEpisodeStats {
        steps: e.steps,
        successes: e.successes,
        crashes: e.crashes,
        out_of_road: e.out_of_road,
        timeouts: e.timeouts,
    }
}

#[derive(Debug, Clone, PartialEq, Default)]
pub struct RolloutFragment {
    pub actor_id: String,
    pub sequence: u64,
    pub behaviour_version: u64,
    pub scenario: String,
    pub steps: usize,
    pub agents: usize,
    pub obs_dim: usize,
    pub action_dim: usize,
    pub obs: Vec<f32>,
    pub actions: Vec<f32>,
    pub log_probs: Vec<f32>,
    pub rewards: Vec<f32>,
    pub costs: Vec<f32>,
    pub dones: Vec<bool>,
    pub alive: Vec<bool>,
    pub bootstrap_obs: Vec<f32>,
    pub neighbour_offsets: Vec<u32>,
    pub neighbour_ids: Vec<u32>,
    /// S_N per (step, slot), `lcf_inputs::FEATURES` each.
    pub lcf_features: Vec<f32>,
    pub episodes: Vec<EpisodeStats>,
    /// Episodes of human-driven vehicles (not trained on; counted separately).
    pub human_episodes: Vec<EpisodeStats>,
    /// Scene episodes that ended in this fragment.
    pub scene_episodes: Vec<SceneEpisodeStats>,
    pub sim_seconds: f32,
}

fn decode_episodes(episodes: &[proto::EpisodeStats]) -> Result<Vec<EpisodeStats>, FragmentError> {
    episodes
        .iter()
        .enumerate()
        .map(|(i, e)| {
            let outcome = Outcome::from_code(e.outcome).ok_or_else(|| {
                FragmentError::Invariant(format!("episode {i} has unknown outcome {}", e.outcome))
            })?;
            Ok(EpisodeStats {
                outcome,
                length: e.length,
                total_reward: e.total_reward,
                mean_abs_accel: e.mean_abs_accel,
                max_abs_accel: e.max_abs_accel,
                collisions: e.collisions,
                energy_kj: e.energy_kj,
                total_cost: e.total_cost,
            })
        })
        .collect()
}

fn episode_to_proto(e: EpisodeStats) -> proto::EpisodeStats {
    proto::EpisodeStats {
        outcome: e.outcome as u32,
        length: e.length,
        total_reward: e.total_reward,
        mean_abs_accel: e.mean_abs_accel,
        max_abs_accel: e.max_abs_accel,
        collisions: e.collisions,
        energy_kj: e.energy_kj,
        total_cost: e.total_cost,
    }
}

/// Why a fragment was refused; `reason()` is the bounded label used in metrics.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FragmentError {
    #[error("protocol version {got} is not supported (this learner speaks {expected})")]
    Version { got: u32, expected: u32 },
    #[error("shape mismatch: {0}")]
    Shape(String),
    #[error("non-finite value (NaN or inf) in {field} at index {index}")]
    NonFinite { field: &'static str, index: usize },
    #[error("invalid flag byte {value} in {field} at index {index} (must be 0 or 1)")]
    Flag {
        field: &'static str,
        index: usize,
        value: u8,
    },
    #[error("slot invariant violated: {0}")]
    Invariant(String),
}

impl FragmentError {
    /// Every value `reason()` returns.
    pub const REASONS: [&'static str; 4] = ["version", "shape", "non_finite", "invariant"];

    pub fn reason(&self) -> &'static str {
        match self {
            FragmentError::Version { .. } => "version",
            FragmentError::Shape(_) => "shape",
            FragmentError::NonFinite { .. } => "non_finite",
            FragmentError::Flag { .. } | FragmentError::Invariant(_) => "invariant",
        }
    }
}

impl RolloutFragment {
    /// Agent-steps carried (alive slot-steps).
    pub fn agent_steps(&self) -> usize {
        self.alive.iter().filter(|a| **a).count()
    }

    /// Collisions of the episodes that ended in this fragment, agents' and human drivers'
    /// (the numerator of collisions per simulated second).
    pub fn collisions(&self) -> u64 {
        self.episodes
            .iter()
            .chain(&self.human_episodes)
            .map(|e| u64::from(e.collisions))
            .sum()
    }

    pub fn index(&self, t: usize, slot: usize) -> usize {
        t * self.agents + slot
    }

    /// Neighbour slots of `slot` at step `t`.
    pub fn neighbours(&self, t: usize, slot: usize) -> &[u32] {
        let i = self.index(t, slot);
        &self.neighbour_ids
            [self.neighbour_offsets[i] as usize..self.neighbour_offsets[i + 1] as usize]
    }

    /// Does slot `slot` need a bootstrap value after the last step?
    pub fn needs_bootstrap(&self, slot: usize) -> bool {
        let last = self.index(self.steps - 1, slot);
        self.alive[last] && !self.dones[last]
    }

    /// Dimensions within bounds (and equal to `expected_dims`, if given) and every array as
    /// long as they call for: what an encoder needs before it sizes a buffer.
    pub fn check_shape(&self, expected_dims: Option<(usize, usize)>) -> Result<(), FragmentError> {
        Self::check_dims(
            (self.steps, self.agents, self.obs_dim, self.action_dim),
            expected_dims,
        )?;
        self.check_lengths()
    }

    /// (steps, agents, obs_dim, action_dim) within the MAX_* bounds, and the last two equal
    /// to `expected_dims` if given: checked before anything is sized from them.
    pub fn check_dims(
        (steps, agents, obs_dim, action_dim): (usize, usize, usize, usize),
        expected_dims: Option<(usize, usize)>,
    ) -> Result<(), FragmentError> {
        let shape = |msg: String| Err(FragmentError::Shape(msg));
        if steps == 0 || steps > MAX_STEPS {
            return shape(format!("steps = {} (must be 1..={MAX_STEPS})", steps));
        }
        if agents == 0 || agents > MAX_AGENTS {
            return shape(format!("agents = {} (must be 1..={MAX_AGENTS})", agents));
        }
        if obs_dim == 0 || obs_dim > MAX_OBS_DIM {
            return shape(format!("obs_dim = {} (must be 1..={MAX_OBS_DIM})", obs_dim));
        }
        if action_dim == 0 || action_dim > MAX_ACTION_DIM {
            return shape(format!(
                "action_dim = {} (must be 1..={MAX_ACTION_DIM})",
                action_dim
            ));
        }
        if let Some((want_obs, want_action)) = expected_dims
            && (obs_dim, action_dim) != (want_obs, want_action)
        {
            return shape(format!(
                "obs_dim × action_dim = {obs_dim} × {action_dim}, the run expects {want_obs} × {want_action}"
            ));
        }
        Ok(())
    }

    /// Checks everything a learner relies on; `expected_dims` pins (obs_dim, action_dim).
    pub fn validate(&self, expected_dims: Option<(usize, usize)>) -> Result<(), FragmentError> {
        let shape = |msg: String| Err(FragmentError::Shape(msg));
        for (field, text) in [("actor_id", &self.actor_id), ("scenario", &self.scenario)] {
            if text.len() > MAX_NAME_BYTES {
                return shape(format!(
                    "{field} is {} bytes long (at most {MAX_NAME_BYTES})",
                    text.len()
                ));
            }
        }
        self.check_shape(expected_dims)?;
        // Bounded by the MAX_* constants, so these products cannot overflow.
        let cells = self.steps * self.agents;
        let floats: [(&'static str, &[f32]); 7] = [
            ("obs", &self.obs),
            ("actions", &self.actions),
            ("log_probs", &self.log_probs),
            ("rewards", &self.rewards),
            ("costs", &self.costs),
            ("bootstrap_obs", &self.bootstrap_obs),
            ("lcf_features", &self.lcf_features),
        ];
        for (field, values) in floats {
            if let Some(index) = first_non_finite(values) {
                return Err(FragmentError::NonFinite { field, index });
            }
        }
        if !self.sim_seconds.is_finite() || self.sim_seconds < 0.0 {
            return Err(FragmentError::NonFinite {
                field: "sim_seconds",
                index: 0,
            });
        }
        for (i, (&done, &alive)) in self.dones.iter().zip(&self.alive).enumerate() {
            if done && !alive {
                return Err(FragmentError::Invariant(format!(
                    "step {} slot {} is done but not alive",
                    i / self.agents,
                    i % self.agents
                )));
            }
        }
        for t in 0..self.steps - 1 {
            for slot in 0..self.agents {
                let (now, next) = (self.index(t, slot), self.index(t + 1, slot));
                if self.alive[now] && !self.dones[now] && !self.alive[next] {
                    return Err(FragmentError::Invariant(format!(
                        "slot {slot} is alive and not done at step {t} but not alive at step {}",
                        t + 1
                    )));
                }
            }
        }
        if self.neighbour_offsets[0] != 0 {
            return Err(FragmentError::Invariant(
                "neighbour_offsets must start at 0".into(),
            ));
        }
        if self.neighbour_offsets.windows(2).any(|w| w[1] < w[0]) {
            return Err(FragmentError::Invariant(
                "neighbour_offsets must not decrease".into(),
            ));
        }
        if self.neighbour_offsets[cells] as usize != self.neighbour_ids.len() {
            return shape(format!(
                "neighbour_offsets ends at {}, but there are {} neighbour_ids",
                self.neighbour_offsets[cells],
                self.neighbour_ids.len()
            ));
        }
        if let Some(bad) = self
            .neighbour_ids
            .iter()
            .find(|&&id| id as usize >= self.agents)
        {
            return Err(FragmentError::Invariant(format!(
                "neighbour id {bad} is not a slot (agents = {})",
                self.agents
            )));
        }
        // A scene episode lasts at least a step.
        if self.scene_episodes.len() > self.steps {
            return Err(FragmentError::Invariant(format!(
                "{} scene episodes cannot end within {} steps",
                self.scene_episodes.len(),
                self.steps
            )));
        }
        for (field, episodes) in [
            ("episodes", &self.episodes),
            ("human_episodes", &self.human_episodes),
        ] {
            for (index, e) in episodes.iter().enumerate() {
                let values = [
                    e.total_reward,
                    e.mean_abs_accel,
                    e.max_abs_accel,
                    e.energy_kj,
                    e.total_cost,
                ];
                if values.iter().any(|v| !v.is_finite()) {
                    return Err(FragmentError::NonFinite { field, index });
                }
            }
        }
        Ok(())
    }

    /// Every array holds as many values as the dimensions call for (which `check_shape` has
    /// bounded, so the products cannot overflow).
    fn check_lengths(&self) -> Result<(), FragmentError> {
        let cells = self.steps * self.agents;
        let lengths: [(&str, usize, usize); 10] = [
            ("obs", self.obs.len(), cells * self.obs_dim),
            ("actions", self.actions.len(), cells * self.action_dim),
            ("log_probs", self.log_probs.len(), cells),
            ("rewards", self.rewards.len(), cells),
            ("costs", self.costs.len(), cells),
            ("dones", self.dones.len(), cells),
            ("alive", self.alive.len(), cells),
            (
                "bootstrap_obs",
                self.bootstrap_obs.len(),
                self.agents * self.obs_dim,
            ),
            ("neighbour_offsets", self.neighbour_offsets.len(), cells + 1),
            (
                "lcf_features",
                self.lcf_features.len(),
                cells * lcf_inputs::FEATURES,
            ),
        ];
        for (field, got, want) in lengths {
            if got != want {
                return Err(FragmentError::Shape(format!(
                    "{field} has {got} values, expected {want} for {} steps × {} agents",
                    self.steps, self.agents
                )));
            }
        }
        Ok(())
    }

    /// Decodes and validates a fragment received from the network.
    pub fn from_proto(
        msg: proto::RolloutFragment,
        expected_dims: Option<(usize, usize)>,
    ) -> Result<Self, FragmentError> {
        if msg.protocol_version != PROTOCOL_VERSION {
            return Err(FragmentError::Version {
                got: msg.protocol_version,
                expected: PROTOCOL_VERSION,
            });
        }
        let dones = flags("dones", &msg.dones)?;
        let alive = flags("alive", &msg.alive)?;
        let episodes = decode_episodes(&msg.episodes)?;
        let human_episodes = decode_episodes(&msg.human_episodes)?;
        let fragment = RolloutFragment {
            actor_id: msg.actor_id,
            sequence: msg.sequence,
            behaviour_version: msg.behaviour_version,
            scenario: msg.scenario,
            steps: msg.steps as usize,
            agents: msg.agents as usize,
            obs_dim: msg.obs_dim as usize,
            action_dim: msg.action_dim as usize,
            obs: msg.obs,
            actions: msg.actions,
            log_probs: msg.log_probs,
            rewards: msg.rewards,
            costs: msg.costs,
            dones,
            alive,
            bootstrap_obs: msg.bootstrap_obs,
            neighbour_offsets: msg.neighbour_offsets,
            neighbour_ids: msg.neighbour_ids,
            lcf_features: msg.lcf_features,
            episodes,
            human_episodes,
            scene_episodes: msg
                .scene_episodes
                .iter()
                .map(scene_episode_from_proto)
                .collect(),
            sim_seconds: msg.sim_seconds,
        };
        fragment.validate(expected_dims)?;
        Ok(fragment)
    }

    pub fn into_proto(self) -> proto::RolloutFragment {
        let bytes = |v: Vec<bool>| v.into_iter().map(u8::from).collect::<Vec<u8>>();
        proto::RolloutFragment {
            protocol_version: PROTOCOL_VERSION,
            actor_id: self.actor_id,
            sequence: self.sequence,
            behaviour_version: self.behaviour_version,
            scenario: self.scenario,
            steps: self.steps as u32,
            agents: self.agents as u32,
            obs_dim: self.obs_dim as u32,
            action_dim: self.action_dim as u32,
            obs: self.obs,
            actions: self.actions,
            log_probs: self.log_probs,
            rewards: self.rewards,
            costs: self.costs,
            dones: bytes(self.dones),
            alive: bytes(self.alive),
            bootstrap_obs: self.bootstrap_obs,
            neighbour_offsets: self.neighbour_offsets,
            neighbour_ids: self.neighbour_ids,
            lcf_features: self.lcf_features,
            episodes: self.episodes.into_iter().map(episode_to_proto).collect(),
            human_episodes: self
                .human_episodes
                .into_iter()
                .map(episode_to_proto)
                .collect(),
            scene_episodes: self
                .scene_episodes
                .into_iter()
                .map(scene_episode_to_proto)
                .collect(),
            sim_seconds: self.sim_seconds,
        }
    }
}

/// Index of the first NaN or infinity. The common all-finite case is checked branch-free,
/// which vectorises (the fragment's arrays are megabytes; validation runs on every one).
fn first_non_finite(values: &[f32]) -> Option<usize> {
    let all_finite = values
        .chunks(4096)
        .all(|chunk| chunk.iter().fold(true, |ok, v| ok & v.is_finite()));
    if all_finite {
        None
    } else {
        values.iter().position(|v| !v.is_finite())
    }
}

pub(crate) fn flags(field: &'static str, bytes: &[u8]) -> Result<Vec<bool>, FragmentError> {
    bytes
        .iter()
        .enumerate()
        .map(|(index, &value)| match value {
            0 => Ok(false),
            1 => Ok(true),
            _ => Err(FragmentError::Flag {
                field,
                index,
                value,
            }),
        })
        .collect()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A small valid fragment: 3 steps × 2 slots; slot 0 finishes at step 1 and a new agent
    /// takes the slot at step 2; slot 1 lives throughout.
    pub(crate) fn sample() -> RolloutFragment {
        let (steps, agents, obs_dim, action_dim) = (3, 2, 4, 2);
        let cells = steps * agents;
        RolloutFragment {
            actor_id: "actor-1".into(),
            sequence: 7,
            behaviour_version: 3,
            scenario: "intersection".into(),
            steps,
            agents,
            obs_dim,
            action_dim,
            obs: (0..cells * obs_dim).map(|i| i as f32 / 100.0).collect(),
            actions: (0..cells * action_dim)
                .map(|i| (i as f32 - 5.0) / 4.0)
                .collect(),
            log_probs: (0..cells).map(|i| -(i as f32)).collect(),
            rewards: vec![0.5, 1.0, 10.0, 1.5, 0.25, 2.0],
            costs: vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            dones: vec![false, false, true, false, false, false],
            alive: vec![true, true, true, true, true, true],
            bootstrap_obs: vec![0.1; agents * obs_dim],
            neighbour_offsets: vec![0, 1, 2, 3, 4, 4, 4],
            neighbour_ids: vec![1, 0, 1, 0],
            lcf_features: (0..cells * lcf_inputs::FEATURES)
                .map(|i| i as f32 / 40.0)
                .collect(),
            episodes: vec![EpisodeStats {
                outcome: Outcome::Success,
                length: 2,
                total_reward: 10.5,
                mean_abs_accel: 0.7,
                max_abs_accel: 1.9,
                collisions: 0,
                energy_kj: 12.5,
                total_cost: 0.125,
            }],
            human_episodes: vec![EpisodeStats {
                outcome: Outcome::Crash,
                length: 40,
                total_reward: 0.0,
                mean_abs_accel: 0.4,
                max_abs_accel: 2.5,
                collisions: 1,
                energy_kj: 3.0,
                total_cost: 0.0,
            }],
            scene_episodes: vec![SceneEpisodeStats {
                steps: 1000,
                successes: 120,
                crashes: 70,
                out_of_road: 9,
                timeouts: 1,
            }],
            sim_seconds: 0.3,
        }
    }

    #[test]
    fn a_scene_episode_shares_its_agents_by_outcome_and_at_most_one_ends_per_step() {
        let e = sample().scene_episodes[0];
        assert_eq!(e.agents(), 200);
        assert_eq!(e.share(Outcome::Success), 0.6);
        assert_eq!(e.share(Outcome::Crash), 0.35);
        assert_eq!(SceneEpisodeStats::default().share(Outcome::Success), 0.0);
        let mut f = sample();
        f.scene_episodes = vec![e; f.steps + 1];
        assert_eq!(f.validate(None).unwrap_err().reason(), "invariant");
    }

    #[test]
    fn protobuf_round_trip_is_lossless() {
        use prost::Message;
        let fragment = sample();
        let bytes = fragment.clone().into_proto().encode_to_vec();
        let decoded = proto::RolloutFragment::decode(bytes.as_slice()).unwrap();
        assert_eq!(
            RolloutFragment::from_proto(decoded, Some((4, 2))).unwrap(),
            fragment
        );
    }

    #[test]
    fn rejects_wrong_shapes_nan_versions_and_broken_invariants() {
        let mut p = sample().into_proto();
        p.protocol_version = 99;
        assert_eq!(
            RolloutFragment::from_proto(p, None).unwrap_err().reason(),
            "version"
        );

        let mut p = sample().into_proto();
        p.obs.pop();
        let err = RolloutFragment::from_proto(p, None).unwrap_err();
        assert_eq!(err.reason(), "shape");
        assert!(
            err.to_string().contains("obs has 23 values, expected 24"),
            "{err}"
        );

        let mut p = sample().into_proto();
        p.rewards[4] = f32::NAN;
        let err = RolloutFragment::from_proto(p, None).unwrap_err();
        assert_eq!(
            err,
            FragmentError::NonFinite {
                field: "rewards",
                index: 4
            }
        );

        let mut p = sample().into_proto();
        p.lcf_features[3] = f32::NAN;
        assert_eq!(
            RolloutFragment::from_proto(p, None).unwrap_err(),
            FragmentError::NonFinite {
                field: "lcf_features",
                index: 3
            }
        );

        let mut p = sample().into_proto();
        p.lcf_features.pop();
        assert_eq!(
            RolloutFragment::from_proto(p, None).unwrap_err().reason(),
            "shape"
        );

        let mut p = sample().into_proto();
        p.actions[0] = f32::INFINITY;
        assert_eq!(
            RolloutFragment::from_proto(p, None).unwrap_err().reason(),
            "non_finite"
        );

        let mut p = sample().into_proto();
        p.dones[1] = 2;
        assert_eq!(
            RolloutFragment::from_proto(p, None).unwrap_err().reason(),
            "invariant"
        );

        // Slot 1 vanishes at step 1 without having been done.
        let mut p = sample().into_proto();
        p.alive[3] = 0;
        assert_eq!(
            RolloutFragment::from_proto(p, None).unwrap_err().reason(),
            "invariant"
        );

        let mut p = sample().into_proto();
        p.neighbour_ids[0] = 2;
        assert_eq!(
            RolloutFragment::from_proto(p, None).unwrap_err().reason(),
            "invariant"
        );

        // Dimensions other than the run's are refused even when self-consistent.
        assert_eq!(
            RolloutFragment::from_proto(sample().into_proto(), Some((91, 2)))
                .unwrap_err()
                .reason(),
            "shape"
        );

        // A header asking for absurd sizes is refused before anything is allocated for it.
        let mut p = sample().into_proto();
        p.steps = u32::MAX;
        assert_eq!(
            RolloutFragment::from_proto(p, None).unwrap_err().reason(),
            "shape"
        );
    }

    #[test]
    fn every_rejection_reason_is_listed_for_metrics() {
        let errors = [
            FragmentError::Version {
                got: 2,
                expected: 1,
            },
            FragmentError::Shape(String::new()),
            FragmentError::NonFinite {
                field: "obs",
                index: 0,
            },
            FragmentError::Flag {
                field: "dones",
                index: 0,
                value: 7,
            },
            FragmentError::Invariant(String::new()),
        ];
        let mut reasons: Vec<&str> = errors.iter().map(FragmentError::reason).collect();
        reasons.dedup();
        assert_eq!(reasons, FragmentError::REASONS);
    }

    #[test]
    fn bootstrap_and_neighbour_accessors_follow_the_slot_semantics() {
        let f = sample();
        assert_eq!(f.agent_steps(), 6);
        assert!(f.needs_bootstrap(0) && f.needs_bootstrap(1));
        assert_eq!(f.neighbours(0, 0), &[1]);
        assert_eq!(f.neighbours(2, 1), &[] as &[u32]);
    }
}
