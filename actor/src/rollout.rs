//! The rollout loop: S scenes stepped in lockstep, one batched policy inference per step over
//! every live agent of every scene, and one `RolloutFragment` per scene every T steps.

use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use junction_common::config::ScenarioConfig;
use junction_common::fragment::RolloutFragment;
use junction_common::lcf;
use junction_common::policy::GaussianPolicy;
use junction_common::spec::ACTION_DIM;
use junction_common::weights::WeightsError;

use crate::sim::{Scene, SimError};

/// Where the time of a fragment went, for the actor's metrics.
#[derive(Debug, Default, Clone, Copy)]
pub struct Timings {
    pub inference_s: f64,
    pub simulation_s: f64,
}

/// Accumulates one scene's fragment, step by step.
struct FragmentBuilder {
    fragment: RolloutFragment,
}

impl FragmentBuilder {
    fn new(scene: &Scene, steps: usize) -> Self {
        let (agents, obs_dim) = (scene.slots(), scene.obs_dim());
        let cells = steps * agents;
        let fragment = RolloutFragment {
            scenario: scene.config().name.clone(),
            steps: 0,
            agents,
            obs_dim,
            action_dim: ACTION_DIM,
            obs: Vec::with_capacity(cells * obs_dim),
            actions: Vec::with_capacity(cells * ACTION_DIM),
            log_probs: Vec::with_capacity(cells),
            rewards: Vec::with_capacity(cells),
            costs: Vec::with_capacity(cells),
            dones: Vec::with_capacity(cells),
            alive: Vec::with_capacity(cells),
            neighbour_offsets: vec![0],
            lcf_features: Vec::with_capacity(cells * lcf::FEATURES),
            ..RolloutFragment::default()
        };
        FragmentBuilder { fragment }
    }
}

pub struct RolloutWorker {
    scenes: Vec<Scene>,
    policy: GaussianPolicy,
    policy_version: u64,
    fragment_length: usize,
    rng: ChaCha8Rng,
    actor_id: String,
    sequence: u64,
    /// Reused per step: observations of all live agents, their noise, and where each row goes.
    batch_obs: Vec<f32>,
    batch_noise: Vec<f32>,
    batch_rows: Vec<(usize, usize)>,
    scene_actions: Vec<Vec<f32>>,
    scene_log_probs: Vec<Vec<f32>>,
}

impl RolloutWorker {
    /// `seed` drives every scene (scene `k` gets a seed derived from it) and the action noise.
    pub fn new(
        scenario: &ScenarioConfig,
        scenes: usize,
        seed: u64,
        fragment_length: usize,
        policy: GaussianPolicy,
        policy_version: u64,
        actor_id: String,
    ) -> Result<Self, SimError> {
        let scenes = (0..scenes)
            .map(|k| Scene::new(scenario, derive_seed(seed, k as u64 + 1)))
            .collect::<Result<Vec<_>, _>>()?;
        let scene_actions = scenes
            .iter()
            .map(|s| vec![0.0; s.slots() * ACTION_DIM])
            .collect();
        let scene_log_probs = scenes.iter().map(|s| vec![0.0; s.slots()]).collect();
        Ok(RolloutWorker {
            scenes,
            policy,
            policy_version,
            fragment_length,
            rng: ChaCha8Rng::seed_from_u64(derive_seed(seed, 0)),
            actor_id,
            sequence: 0,
            batch_obs: Vec::new(),
            batch_noise: Vec::new(),
            batch_rows: Vec::new(),
            scene_actions,
            scene_log_probs,
        })
    }

    pub fn policy_version(&self) -> u64 {
        self.policy_version
    }

    /// Switches to new weights; takes effect from the next fragment on.
    pub fn set_policy(&mut self, policy: GaussianPolicy, version: u64) {
        self.policy = policy;
        self.policy_version = version;
    }

    /// Runs `fragment_length` steps of every scene; returns one fragment per scene.
    pub fn collect(&mut self) -> Result<(Vec<RolloutFragment>, Timings), WeightsError> {
        let mut builders: Vec<FragmentBuilder> = self
            .scenes
            .iter()
            .map(|s| FragmentBuilder::new(s, self.fragment_length))
            .collect();
        let mut timings = Timings::default();
        for _ in 0..self.fragment_length {
            let started = Instant::now();
            self.infer()?;
            timings.inference_s += started.elapsed().as_secs_f64();
            let started = Instant::now();
            for (k, (scene, builder)) in self.scenes.iter_mut().zip(&mut builders).enumerate() {
                let f = &mut builder.fragment;
                f.obs.extend_from_slice(scene.observations());
                f.alive.extend_from_slice(scene.alive());
                f.actions.extend_from_slice(&self.scene_actions[k]);
                f.log_probs.extend_from_slice(&self.scene_log_probs[k]);
                let (offsets, ids) = scene.neighbours();
                let base = *f.neighbour_offsets.last().unwrap_or(&0);
                f.neighbour_offsets
                    .extend(offsets[1..].iter().map(|o| base + o));
                f.neighbour_ids.extend_from_slice(ids);
                f.lcf_features.extend_from_slice(scene.lcf_features());
                let result = scene.step(&self.scene_actions[k]);
                f.rewards.extend_from_slice(&result.rewards);
                f.costs.extend_from_slice(&result.costs);
                f.dones.extend_from_slice(&result.dones);
                f.episodes.extend(result.finished.iter().map(|e| e.stats));
                f.human_episodes.extend_from_slice(&result.human_finished);
                f.steps += 1;
                f.sim_seconds += scene.config().decision_dt;
            }
            timings.simulation_s += started.elapsed().as_secs_f64();
        }
        let fragments = self
            .scenes
            .iter()
            .zip(builders)
            .map(|(scene, builder)| {
                let mut f = builder.fragment;
                // Agents alive and not done at the last step bootstrap from their observation now.
                f.bootstrap_obs = vec![0.0; f.agents * f.obs_dim];
                let continuing: Vec<usize> =
                    (0..f.agents).filter(|&s| f.needs_bootstrap(s)).collect();
                for slot in continuing {
                    let row = slot * f.obs_dim..(slot + 1) * f.obs_dim;
                    f.bootstrap_obs[row.clone()].copy_from_slice(&scene.observations()[row]);
                }
                f.actor_id = self.actor_id.clone();
                f.behaviour_version = self.policy_version;
                f.sequence = self.sequence;
                self.sequence += 1;
                f
            })
            .collect();
        Ok((fragments, timings))
    }

    /// One batched forward pass over every live agent; fills `scene_actions` and
    /// `scene_log_probs` (zeros for empty slots).
    fn infer(&mut self) -> Result<(), WeightsError> {
        self.batch_obs.clear();
        self.batch_rows.clear();
        for (k, scene) in self.scenes.iter().enumerate() {
            let obs_dim = scene.obs_dim();
            for (slot, _) in scene
                .alive()
                .iter()
                .enumerate()
                .filter(|(_, alive)| **alive)
            {
                self.batch_obs
                    .extend_from_slice(&scene.observations()[slot * obs_dim..(slot + 1) * obs_dim]);
                self.batch_rows.push((k, slot));
            }
        }
        for (actions, log_probs) in self.scene_actions.iter_mut().zip(&mut self.scene_log_probs) {
            actions.fill(0.0);
            log_probs.fill(0.0);
        }
        self.batch_noise.clear();
        let rng = &mut self.rng;
        self.batch_noise.extend(
            (0..self.batch_rows.len() * ACTION_DIM).map(|_| -> f32 { StandardNormal.sample(rng) }),
        );
        let (actions, log_probs) = if self.batch_rows.is_empty() {
            (Vec::new(), Vec::new())
        } else {
            self.policy.act(&self.batch_obs, &self.batch_noise)?
        };
        for (row, &(k, slot)) in self.batch_rows.iter().enumerate() {
            self.scene_actions[k][slot * ACTION_DIM..(slot + 1) * ACTION_DIM]
                .copy_from_slice(&actions[row * ACTION_DIM..(row + 1) * ACTION_DIM]);
            self.scene_log_probs[k][slot] = log_probs[row];
        }
        Ok(())
    }
}

/// A well-mixed seed for stream `stream` of base seed `seed` (SplitMix64 finaliser).
pub fn derive_seed(seed: u64, stream: u64) -> u64 {
    let mut z = seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}
