//! The rollout loop: S scenes stepped in lockstep, one batched policy inference per step over
//! every live agent of every scene, and one `RolloutFragment` per scene every T steps.

use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use junction_common::fragment::RolloutFragment;
use junction_common::lcf::LcfDistribution;
use junction_common::policy::Policy;
use junction_common::weights::WeightsError;
use junction_core::config::ScenarioConfig;
use junction_core::lcf_inputs;
use junction_core::spec::ACTION_DIM;

use crate::lcf_column::LcfColumn;
use junction_sim::{Scene, SimError};

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
    /// `extra_columns`: values the policy takes beyond the scene's observation.
    fn new(scene: &Scene, steps: usize, extra_columns: usize) -> Self {
        let (agents, obs_dim) = (scene.slots(), scene.obs_dim() + extra_columns);
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
            lcf_features: Vec::with_capacity(cells * lcf_inputs::FEATURES),
            ..RolloutFragment::default()
        };
        FragmentBuilder { fragment }
    }
}

pub struct RolloutWorker {
    /// The scenario as the learner sent it, with its full agent count.
    scenario: ScenarioConfig,
    /// Seeds the scenes; a new stream after every rebuild, so rebuilt scenes do not replay.
    scene_seed: u64,
    scenes: Vec<Scene>,
    /// Whatever the learner broadcast: a Gaussian (PPO) or an ε-greedy Q-policy (DQN).
    policy: Box<dyn Policy>,
    policy_version: u64,
    fragment_length: usize,
    rng: ChaCha8Rng,
    actor_id: String,
    sequence: u64,
    /// CoPO's per-agent LCF angle, when the policy takes one.
    lcf: LcfColumn,
    /// Reused per step: observations of all live agents and where each row goes.
    batch_obs: Vec<f32>,
    batch_rows: Vec<(usize, usize)>,
    scene_actions: Vec<Vec<f32>>,
    scene_log_probs: Vec<Vec<f32>>,
}

impl RolloutWorker {
    /// `seed` drives every scene (scene `k` gets a seed derived from it) and the policy's
    /// random choices.
    pub fn new(
        scenario: &ScenarioConfig,
        scenes: usize,
        seed: u64,
        fragment_length: usize,
        policy: Box<dyn Policy>,
        policy_version: u64,
        actor_id: String,
    ) -> Result<Self, SimError> {
        let scenes = build_scenes(scenario, scenes, seed)?;
        let lcf = LcfColumn::new(
            derive_seed(seed, LCF_STREAM),
            scenes.iter().map(Scene::slots),
        );
        let mut worker = RolloutWorker {
            scenario: scenario.clone(),
            scene_seed: seed,
            scenes,
            policy,
            policy_version,
            fragment_length,
            rng: ChaCha8Rng::seed_from_u64(derive_seed(seed, 0)),
            actor_id,
            sequence: 0,
            lcf,
            batch_obs: Vec::new(),
            batch_rows: Vec::new(),
            scene_actions: Vec::new(),
            scene_log_probs: Vec::new(),
        };
        worker.size_buffers();
        Ok(worker)
    }

    /// Per-scene action and log-probability buffers of the scenes' slot count.
    fn size_buffers(&mut self) {
        self.scene_actions = self
            .scenes
            .iter()
            .map(|s| vec![0.0; s.slots() * ACTION_DIM])
            .collect();
        self.scene_log_probs = self.scenes.iter().map(|s| vec![0.0; s.slots()]).collect();
    }

    /// Learning-agent slots per scene, i.e. the `agents` of every fragment.
    pub fn active_agents(&self) -> usize {
        self.scenes
            .first()
            .map_or(self.scenario.agent_count(), Scene::slots)
    }

    /// Simulates `agents` learning agents per scene from the next fragment on (0 = the
    /// scenario's count; more is capped to it). A change rebuilds the scenes from fresh
    /// seeds, so episodes in flight end unreported: a curriculum changes the count only a
    /// few times per run. Returns whether anything changed.
    pub fn set_active_agents(&mut self, agents: usize) -> Result<bool, SimError> {
        let full = self.scenario.agent_count();
        let agents = if agents == 0 { full } else { agents.min(full) };
        if agents == self.active_agents() {
            return Ok(false);
        }
        let scene_seed = derive_seed(self.scene_seed, u64::MAX);
        let scenario = self.scenario.with_agents(agents);
        self.scenes = build_scenes(&scenario, self.scenes.len(), scene_seed)?;
        self.scene_seed = scene_seed;
        self.lcf.reset(self.scenes.iter().map(Scene::slots));
        self.size_buffers();
        Ok(true)
    }

    pub fn policy_version(&self) -> u64 {
        self.policy_version
    }

    /// The id new fragments carry (after registering again with a restarted learner).
    pub fn set_actor_id(&mut self, actor_id: String) {
        self.actor_id = actor_id;
    }

    /// Switches to new weights; takes effect from the next fragment on.
    pub fn set_policy(&mut self, policy: Box<dyn Policy>, version: u64) {
        self.policy = policy;
        self.policy_version = version;
    }

    /// The LCF distribution that came with the policy (CoPO's), or none: agents spawned from
    /// now on draw from it, and fragments carry the φ column while it is set.
    pub fn set_lcf_distribution(&mut self, distribution: Option<LcfDistribution>) {
        self.lcf.set_distribution(distribution);
    }

    /// Runs `fragment_length` steps of every scene; returns one fragment per scene.
    pub fn collect(&mut self) -> Result<(Vec<RolloutFragment>, Timings), WeightsError> {
        let columns = self.lcf.columns();
        let mut builders: Vec<FragmentBuilder> = self
            .scenes
            .iter()
            .map(|s| FragmentBuilder::new(s, self.fragment_length, columns))
            .collect();
        let mut timings = Timings::default();
        for _ in 0..self.fragment_length {
            let started = Instant::now();
            for (k, scene) in self.scenes.iter().enumerate() {
                self.lcf.spawn(k, scene.alive());
            }
            self.infer()?;
            timings.inference_s += started.elapsed().as_secs_f64();
            let started = Instant::now();
            for (k, (scene, builder)) in self.scenes.iter_mut().zip(&mut builders).enumerate() {
                let f = &mut builder.fragment;
                f.obs.extend_from_slice(&self.lcf.observations(
                    k,
                    scene.observations(),
                    scene.obs_dim(),
                ));
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
                self.lcf.finish(k, &result.dones);
                f.rewards.extend_from_slice(&result.rewards);
                f.costs.extend_from_slice(&result.costs);
                f.dones.extend_from_slice(&result.dones);
                f.episodes.extend(result.finished.iter().map(|e| e.stats));
                f.human_episodes.extend_from_slice(&result.human_finished);
                f.scene_episodes.extend(result.scene_episode);
                f.steps += 1;
                f.sim_seconds += scene.config().decision_dt;
            }
            timings.simulation_s += started.elapsed().as_secs_f64();
        }
        let fragments = self
            .scenes
            .iter()
            .zip(builders)
            .enumerate()
            .map(|(k, (scene, builder))| {
                let mut f = builder.fragment;
                // Agents alive and not done at the last step bootstrap from their observation now.
                f.bootstrap_obs = vec![0.0; f.agents * f.obs_dim];
                let now = self
                    .lcf
                    .observations(k, scene.observations(), scene.obs_dim());
                let continuing: Vec<usize> =
                    (0..f.agents).filter(|&s| f.needs_bootstrap(s)).collect();
                for slot in continuing {
                    let row = slot * f.obs_dim..(slot + 1) * f.obs_dim;
                    f.bootstrap_obs[row.clone()].copy_from_slice(&now[row]);
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
            let obs_dim = scene.obs_dim() + self.lcf.columns();
            let rows = self
                .lcf
                .observations(k, scene.observations(), scene.obs_dim());
            for (slot, _) in scene
                .alive()
                .iter()
                .enumerate()
                .filter(|(_, alive)| **alive)
            {
                self.batch_obs
                    .extend_from_slice(&rows[slot * obs_dim..(slot + 1) * obs_dim]);
                self.batch_rows.push((k, slot));
            }
        }
        for (actions, log_probs) in self.scene_actions.iter_mut().zip(&mut self.scene_log_probs) {
            actions.fill(0.0);
            log_probs.fill(0.0);
        }
        let (actions, log_probs) = if self.batch_rows.is_empty() {
            (Vec::new(), Vec::new())
        } else {
            self.policy.sample(&self.batch_obs, &mut self.rng)?
        };
        for (row, &(k, slot)) in self.batch_rows.iter().enumerate() {
            self.scene_actions[k][slot * ACTION_DIM..(slot + 1) * ACTION_DIM]
                .copy_from_slice(&actions[row * ACTION_DIM..(row + 1) * ACTION_DIM]);
            self.scene_log_probs[k][slot] = log_probs[row];
        }
        Ok(())
    }
}

/// The stream of the worker's seed that draws CoPO's LCF angles (scenes use 1…, the action
/// noise 0, rebuilt scenes `u64::MAX`).
const LCF_STREAM: u64 = u64::MAX - 1;

/// `count` scenes of `scenario`, scene `k` seeded from stream `k + 1` of `seed`.
fn build_scenes(
    scenario: &ScenarioConfig,
    count: usize,
    seed: u64,
) -> Result<Vec<Scene>, SimError> {
    (0..count)
        .map(|k| Scene::new(scenario, derive_seed(seed, k as u64 + 1)))
        .collect()
}

/// A well-mixed seed for stream `stream` of base seed `seed` (SplitMix64 finaliser).
pub fn derive_seed(seed: u64, stream: u64) -> u64 {
    let mut z = seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use junction_common::policy::GaussianPolicy;

    /// Two scenes of an 8-agent intersection driven by `policy` (serialised weights).
    fn worker(seed: u64, policy: &[u8]) -> RolloutWorker {
        let scenario = ScenarioConfig {
            agents: 8,
            ..ScenarioConfig::default()
        };
        let (policy, _) = junction_common::any_policy::decode(policy, tch::Device::Cpu).unwrap();
        RolloutWorker::new(&scenario, 2, seed, 40, policy, 0, "test".into()).unwrap()
    }

    fn random_policy() -> Vec<u8> {
        let obs_dim = ScenarioConfig::default().obs_dim() as i64;
        GaussianPolicy::new(tch::Device::Cpu, obs_dim, ACTION_DIM as i64, &[16], 0.0)
            .to_bytes(0)
            .unwrap()
    }

    /// Most agents alive at one step of any fragment.
    fn max_alive(fragments: &[RolloutFragment]) -> usize {
        fragments
            .iter()
            .flat_map(|f| f.alive.chunks(f.agents))
            .map(|step| step.iter().filter(|&&a| a).count())
            .max()
            .unwrap_or(0)
    }

    #[test]
    fn fewer_active_agents_shrink_every_fragment_and_all_restores_the_scenario() {
        let mut w = worker(3, &random_policy());
        let (full, _) = w.collect().unwrap();
        assert!(full.iter().all(|f| f.agents == 8));
        assert!(
            max_alive(&full) > 2,
            "the full scene should fill more than 2 slots"
        );

        assert!(w.set_active_agents(2).unwrap());
        assert!(
            !w.set_active_agents(2).unwrap(),
            "the same count rebuilds nothing"
        );
        for _ in 0..5 {
            let (fragments, _) = w.collect().unwrap();
            for f in &fragments {
                assert_eq!(f.agents, 2);
                f.validate(Some((f.obs_dim, ACTION_DIM))).unwrap();
            }
            let alive = max_alive(&fragments);
            assert!(
                (1..=2).contains(&alive),
                "{alive} agents alive with 2 active"
            );
        }

        // 0 (a learner without a curriculum) and more than the scenario both mean all of it.
        assert!(w.set_active_agents(0).unwrap());
        assert_eq!(w.active_agents(), 8);
        assert!(!w.set_active_agents(100).unwrap());
        let (fragments, _) = w.collect().unwrap();
        assert!(fragments.iter().all(|f| f.agents == 8));
    }

    #[test]
    fn with_copos_distribution_every_agent_carries_its_own_phi_for_its_whole_episode() {
        let scenario = ScenarioConfig {
            agents: 8,
            ..ScenarioConfig::default()
        };
        let obs_dim = scenario.obs_dim();
        let policy = GaussianPolicy::new(
            tch::Device::Cpu,
            (obs_dim + 1) as i64,
            ACTION_DIM as i64,
            &[16],
            0.0,
        );
        let mut w =
            RolloutWorker::new(&scenario, 2, 5, 40, Box::new(policy), 0, "test".into()).unwrap();
        w.set_lcf_distribution(Some(LcfDistribution {
            mean_deg: 10.0,
            std_deg: 30.0,
        }));
        let mut distinct = std::collections::HashSet::new();
        for _ in 0..3 {
            let (fragments, _) = w.collect().unwrap();
            for f in &fragments {
                f.validate(Some((obs_dim + 1, ACTION_DIM))).unwrap();
                let phi = |cell: usize| f.obs[cell * f.obs_dim + obs_dim];
                for t in 0..f.steps {
                    for slot in 0..f.agents {
                        let cell = f.index(t, slot);
                        if !f.alive[cell] {
                            assert_eq!(phi(cell), 0.0, "an empty slot's φ value is 0");
                            continue;
                        }
                        assert!((0.0..=1.0).contains(&phi(cell)));
                        distinct.insert(phi(cell).to_bits());
                        // The same agent one step later keeps its φ.
                        if t + 1 < f.steps && !f.dones[cell] {
                            assert_eq!(phi(f.index(t + 1, slot)), phi(cell));
                        }
                    }
                }
                // Continuing agents bootstrap with their φ too.
                let last = f.steps - 1;
                for slot in (0..f.agents).filter(|&s| f.needs_bootstrap(s)) {
                    assert_eq!(
                        f.bootstrap_obs[(slot + 1) * f.obs_dim - 1],
                        phi(f.index(last, slot))
                    );
                }
            }
        }
        assert!(distinct.len() > 8, "agents draw their own φ: {distinct:?}");
    }

    #[test]
    fn a_q_policy_blob_makes_the_actor_act_epsilon_greedily_on_its_grid() {
        use junction_common::q_policy::QPolicy;
        use junction_core::action_grid::ActionGrid;
        let obs_dim = ScenarioConfig::default().obs_dim() as i64;
        let grid = ActionGrid::new(vec![-0.5, 0.0, 0.5], vec![-1.0, 1.0]).unwrap();
        let mut q = QPolicy::new(tch::Device::Cpu, obs_dim, &[16], grid.clone(), true);
        q.set_epsilon(0.3);
        let blob = Policy::to_bytes(&q, 0).unwrap();
        let (fragments, _) = worker(4, &blob).collect().unwrap();
        assert_eq!(
            fragments,
            worker(4, &blob).collect().unwrap().0,
            "deterministic"
        );
        // ln(ε/|A| + (1 − ε)) for the greedy choice, ln(ε/|A|) for any other.
        let greedy_lp = (0.3f64 / 6.0 + 0.7).ln() as f32;
        let other_lp = (0.3f64 / 6.0).ln() as f32;
        let (mut explored, mut cells) = (0, 0);
        for f in &fragments {
            f.validate(Some((f.obs_dim, ACTION_DIM))).unwrap();
            for cell in (0..f.steps * f.agents).filter(|&c| f.alive[c]) {
                let action = &f.actions[cell * ACTION_DIM..(cell + 1) * ACTION_DIM];
                assert!(
                    grid.index_of(action).is_some(),
                    "{action:?} is off the grid"
                );
                let obs = &f.obs[cell * f.obs_dim..(cell + 1) * f.obs_dim];
                let greedy = q.deterministic(obs).unwrap();
                let lp = f.log_probs[cell];
                if action == greedy.as_slice() {
                    assert_eq!(lp, greedy_lp);
                } else {
                    assert_eq!(lp, other_lp);
                    explored += 1;
                }
                cells += 1;
            }
        }
        // About ε · 5/6 of the cells leave the greedy action.
        let share = explored as f64 / cells as f64;
        assert!(
            (0.15..0.35).contains(&share),
            "{explored} of {cells} explored"
        );
    }

    #[test]
    fn rebuilt_scenes_are_deterministic_and_freshly_seeded() {
        let policy = random_policy();
        let run = |seed| {
            let mut w = worker(seed, &policy);
            let (before, _) = w.collect().unwrap();
            w.set_active_agents(4).unwrap();
            let (after, _) = w.collect().unwrap();
            (before, after)
        };
        let (a_before, a_after) = run(5);
        let (b_before, b_after) = run(5);
        assert_eq!(a_before, b_before);
        assert_eq!(a_after, b_after);
        // A rebuild does not replay the first scenes' opening (other seeds, other spawns).
        let first_obs = |f: &RolloutFragment| f.obs[..f.obs_dim].to_vec();
        assert_ne!(first_obs(&a_before[0]), first_obs(&a_after[0]));
    }
}
