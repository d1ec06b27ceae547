//! Run configuration: TOML + serde.
//!
//! The defaults live in one place, the annotated `default.toml` compiled into the binaries.
//! Loading layers three sources over each other: defaults, then an optional file, then
//! `--set key=value` overrides. Every struct denies unknown keys so a typo is an error, not a
//! silently ignored setting.

// `!(x >= 0.0)` rather than `x < 0.0` throughout the checks: the negation also rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use std::path::Path;

use serde::{Deserialize, Serialize};

/// The annotated defaults; `learner config --defaults` prints it.
pub const DEFAULT_TOML: &str = include_str!("default.toml");

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read {path}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("{origin} is not a valid configuration")]
    Parse {
        origin: String,
        source: Box<toml::de::Error>,
    },
    #[error("override {0:?} is not of the form section.key=value")]
    OverrideSyntax(String),
    #[error("unknown config key {key:?} (see `learner config --defaults` for every key)")]
    UnknownKey { key: String },
    #[error("invalid configuration: {0}")]
    Invalid(String),
    #[error("unknown preset {name:?} (shipped presets: {known})")]
    UnknownPreset { name: String, known: String },
}

/// One source of configuration, applied over the defaults in order.
pub enum Layer<'a> {
    /// A shipped preset by name (`presets/`): a run configuration's keys, as a file's.
    Preset(&'a str),
    /// A run configuration file.
    File(&'a Path),
    /// A scenario (TOML of the `[scenario]` section's keys) replacing the scenario's keys.
    Scenario(&'a str),
    /// One `section.key=value` override.
    Set(&'a str),
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    pub run: RunSection,
    pub scenario: ScenarioConfig,
    pub rollout: RolloutConfig,
    pub ppo: PpoConfig,
    pub ccppo: CcppoConfig,
    pub dqn: DqnConfig,
    pub lcf: LcfConfig,
    pub copo: CopoConfig,
    pub dynamic_lcf: DynamicLcfConfig,
    pub safety: SafetyConfig,
    pub learner: LearnerSection,
    pub curriculum: CurriculumConfig,
    pub server: ServerSection,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunSection {
    pub seed: u64,
    pub max_seconds: f64,
    pub max_updates: u64,
    pub max_agent_steps: u64,
    pub progress_interval_s: f64,
    pub checkpoint_every_updates: u64,
    pub keep_checkpoints: usize,
    pub stats_window_episodes: usize,
    pub stats_window_scene_episodes: usize,
}

impl RunSection {
    /// The share of the run's budget used after `agent_steps` agent-steps and `seconds` of
    /// training: of `max_agent_steps` where set, else of `max_seconds` (a run bounded by the
    /// clock, such as `make run`'s), else None. What `ppo.lr_schedule = "linear"` follows.
    pub fn budget_spent(&self, agent_steps: u64, seconds: f64) -> Option<f64> {
        if self.max_agent_steps > 0 {
            Some(agent_steps as f64 / self.max_agent_steps as f64)
        } else if self.max_seconds > 0.0 {
            Some(seconds / self.max_seconds)
        } else {
            None
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioConfig {
    pub name: String,
    pub simulator: Simulator,
    pub kind: SceneKind,
    pub traffic: Traffic,
    pub agents: usize,
    pub horizon: u32,
    pub after_horizon: AfterHorizon,
    pub agent_horizon: u32,
    pub crash_obstacle_steps: u32,
    pub wreck_holds_slot: bool,
    pub neighbour_radius: f32,
    pub decision_dt: f32,
    pub substeps: u32,
    pub intersection: IntersectionConfig,
    pub roundabout: RoundaboutConfig,
    pub spawn: SpawnConfig,
    pub humans: HumanConfig,
    pub sensors: SensorConfig,
    pub vehicle: VehicleConfig,
    pub reward: RewardConfig,
    pub cost: CostConfig,
}

/// Which simulator runs a scenario's scenes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Simulator {
    /// This project's (`sim/`): every key of the scenario applies.
    Junction,
    /// MetaDrive's own multi-agent intersection or roundabout (by `kind`), run by the Python
    /// MetaDrive actor (`python -m junction.metadrive_actor`); docs/PYTHON.md lists the keys it
    /// reads. Rust actors refuse such a scenario.
    Metadrive,
}

/// What a scene does when it reaches `scenario.horizon` steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AfterHorizon {
    /// Every agent still driving ends as a timeout and the scene starts afresh.
    Reset,
    /// MetaDrive's multi-agent episodes: no more respawns; the agents on the road drive on
    /// until each is done (at the latest after `agent_horizon` steps of its own), then the
    /// scene starts afresh.
    Finish,
}

/// Traffic density (paper §4.1): presets scale the scene's reference agent count (MetaDrive's)
/// and set how eagerly empty slots are refilled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Traffic {
    /// `agents` and `spawn.respawn_probability` as configured.
    Custom,
    /// Half the reference agents; an empty slot refills with probability 0.05 per step.
    Light,
    /// The reference agents (intersection 30, roundabout 40); refills as soon as a spawn
    /// point is free.
    Medium,
    /// One and a half times the reference agents; refills as soon as a spawn point is free.
    Heavy,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SceneKind {
    Intersection,
    Roundabout,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntersectionConfig {
    /// 4 (a cross) or 3 (a T-junction: the south arm is left out).
    pub arms: usize,
    pub lanes_per_direction: usize,
    pub lane_width: f32,
    pub corner_radius: f32,
    pub approach_length: f32,
    pub routes: Vec<Manoeuvre>,
}

/// A roundabout: see `docs/SIMULATOR.md` for the geometry each key controls.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RoundaboutConfig {
    /// Radius of the central island (the ring's inner edge), metres.
    pub radius: f32,
    pub ring_lanes: usize,
    pub arms: usize,
    pub lanes_per_direction: usize,
    pub lane_width: f32,
    /// Degrees the entry arcs turn through from the arm onto the ring.
    pub entry_angle: f32,
    /// Centre-line radius of the outermost lane's exit arc, metres.
    pub exit_radius: f32,
    pub approach_length: f32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Manoeuvre {
    Straight,
    Left,
    Right,
    /// A half circle from the innermost incoming lane to the outermost outgoing lane of the
    /// same arm; needs 2 or more lanes per direction (1 lane is too tight for the car).
    #[serde(rename = "uturn")]
    UTurn,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpawnConfig {
    pub slot_spacing: f32,
    pub longitudinal_jitter: f32,
    pub lateral_jitter: f32,
    pub respawn_clear_length: f32,
    pub respawn_clear_width: f32,
    pub respawn_probability: f32,
    pub initial_speed: f32,
}

/// Limits of the vehicle model (docs/SIMULATOR.md, "Dynamics").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VehicleConfig {
    /// Largest lateral acceleration, m/s²; 0 = none (the pure kinematic bicycle).
    pub max_lateral_accel: f32,
    /// Deceleration of full braking, m/s².
    pub max_brake_decel: f32,
    /// Brake pedal (the negative throttle_brake) at which braking reaches `max_brake_decel`.
    pub brake_saturation: f32,
    /// Time constant of the wheel's lag behind the steering action, seconds; 0 = none.
    pub steering_time_constant: f32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorConfig {
    pub lidar_beams: usize,
    pub lidar_range: f32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardConfig {
    pub kind: RewardKind,
    pub displacement: f32,
    pub speed: f32,
    pub lateral: f32,
    pub heading: f32,
    pub steering: f32,
    pub collision: f32,
    pub success: f32,
    pub crash: f32,
    pub out_of_road: f32,
}

/// The paper's two reward functions (§3.4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum RewardKind {
    /// Progress and speed; the terminal reward replaces the last step's (as in MetaDrive).
    I,
    /// Progress, lane keeping, heading, smooth steering and a collision penalty, all summed
    /// with the terminal reward.
    II,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CostConfig {
    pub collision: f32,
    pub energy: f32,
}

/// Non-connected, human-driven vehicles (IDM car following + gap acceptance).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HumanConfig {
    pub share: f32,
    pub desired_speed: f32,
    pub time_headway: f32,
    pub min_gap: f32,
    pub max_accel: f32,
    pub comfort_decel: f32,
    pub critical_gap: f32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RolloutConfig {
    pub fragment_length: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PpoConfig {
    pub learning_rate: f64,
    pub lr_schedule: LrSchedule,
    pub adam_eps: f64,
    pub gamma: f32,
    pub gae_lambda: f32,
    pub clip: f64,
    pub epochs: usize,
    pub minibatch_size: usize,
    pub train_batch_env_steps: usize,
    pub entropy_coef: f64,
    pub value_coef: f64,
    pub value_clip: f64,
    pub max_grad_norm: f64,
    pub hidden: Vec<i64>,
    pub init_log_std: f64,
    pub normalize_advantages: bool,
    pub normalize_observations: bool,
    pub objective: PpoObjective,
    pub action_std: ActionStd,
    pub max_importance_weight: f64,
    pub kl_coef: f64,
    pub kl_target: f64,
}

/// Where the Gaussian policy's standard deviation comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ActionStd {
    /// One learned log-std per action value, the same in every state.
    Global,
    /// The network outputs the log-std beside the mean, per state.
    State,
}

impl ActionStd {
    pub fn label(self) -> &'static str {
        match self {
            ActionStd::Global => "global",
            ActionStd::State => "state",
        }
    }

    pub fn from_label(label: &str) -> Option<ActionStd> {
        [ActionStd::Global, ActionStd::State]
            .into_iter()
            .find(|s| s.label() == label)
    }
}

/// How PPO's learning rate moves over a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LrSchedule {
    /// `ppo.learning_rate` throughout.
    Constant,
    /// From `ppo.learning_rate` down to 0 as the run's budget is spent
    /// ([`RunSection::budget_spent`]); constant in a run without a budget.
    Linear,
}

impl LrSchedule {
    /// The step size once the share `spent` of the run's budget is used (None: no budget).
    pub fn learning_rate(self, base: f64, spent: Option<f64>) -> f64 {
        match (self, spent) {
            (LrSchedule::Linear, Some(spent)) => base * (1.0 - spent).max(0.0),
            // Without a budget (an endless run) there is nothing to anneal over.
            _ => base,
        }
    }
}

/// How the PPO algorithms treat data from actors whose policy lags the learner's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PpoObjective {
    /// The clipped ratio against the behaviour policy that produced the data.
    Clipped,
    /// Decoupled PPO: the clipped ratio against the policy at the update's start, each sample
    /// weighted by the truncated importance weight of that policy over the behaviour one.
    Decoupled,
}

/// `learner.algo = "dqn"`: double DQN over a grid of actions (defaults and their sources in
/// `default.toml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DqnConfig {
    /// The action grid: every steering value with every throttle value.
    pub steering: Vec<f32>,
    pub throttle: Vec<f32>,
    pub learning_rate: f64,
    pub adam_eps: f64,
    pub gamma: f32,
    pub batch_size: usize,
    pub replay_capacity: usize,
    pub learning_starts: usize,
    pub replay_ratio: f32,
    pub target_update_gradient_steps: u64,
    pub huber_delta: f64,
    pub max_grad_norm: f64,
    pub epsilon_start: f64,
    pub epsilon_end: f64,
    pub epsilon_decay_agent_steps: u64,
    pub train_batch_env_steps: usize,
    pub hidden: Vec<i64>,
    pub dueling: bool,
    pub normalize_observations: bool,
    pub checkpoint_replay: bool,
}

impl DqnConfig {
    /// What is wrong with the section, one line per problem.
    fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if crate::action_grid::ActionGrid::new(self.steering.clone(), self.throttle.clone())
            .is_err()
        {
            problems.push(format!(
                "dqn.steering and dqn.throttle must each list values in [-1, 1], strictly \
                 increasing, at most {} grid points in all",
                crate::action_grid::MAX_GRID_ACTIONS
            ));
        }
        if !(self.learning_rate > 0.0 && self.learning_rate.is_finite()) {
            problems.push("dqn.learning_rate must be a positive number".into());
        }
        if !(0.0..=1.0).contains(&self.gamma) {
            problems.push("dqn.gamma must be in [0, 1]".into());
        }
        if self.batch_size == 0
            || self.replay_capacity == 0
            || self.target_update_gradient_steps == 0
            || self.train_batch_env_steps == 0
        {
            problems.push(
                "dqn.batch_size, dqn.replay_capacity, dqn.target_update_gradient_steps and \
                 dqn.train_batch_env_steps must be > 0"
                    .into(),
            );
        }
        let positive = |x: f64| x > 0.0 && x.is_finite();
        let valid = positive(f64::from(self.replay_ratio))
            && positive(self.huber_delta)
            && (0.0..).contains(&self.max_grad_norm);
        if !valid {
            problems.push(
                "dqn.replay_ratio and dqn.huber_delta must be > 0, dqn.max_grad_norm >= 0".into(),
            );
        }
        let probability = 0.0..=1.0;
        if !probability.contains(&self.epsilon_start) || !probability.contains(&self.epsilon_end) {
            problems.push("dqn.epsilon_start and dqn.epsilon_end must be in [0, 1]".into());
        }
        if self.hidden.is_empty() || self.hidden.iter().any(|&h| h <= 0) {
            problems.push("dqn.hidden must list at least one positive layer size".into());
        }
        problems
    }
}

/// Safe RL for every PPO algorithm: a cost critic and a Lagrange multiplier on the episode cost.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SafetyConfig {
    pub mode: SafetyMode,
    pub cost_limit: f32,
    pub multiplier_lr: f32,
    pub initial_multiplier: f32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SafetyMode {
    Off,
    Lagrangian,
}

/// A fixed local coordination factor for every PPO algorithm (paper §3.2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LcfConfig {
    pub phi_deg: f32,
    pub alpha: f32,
    pub beta: f32,
    /// The global return the learned LCFs (copo, dynamic-lcf) climb.
    pub global_return: GlobalReturn,
    /// What r_N pays an agent for having neighbours.
    pub neighbourhood_reward: NeighbourhoodReward,
}

/// The neighbourhood reward r_N of an agent with neighbours.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NeighbourhoodReward {
    /// The paper's and CoPO's: the neighbours' mean reward. Positive on average, so under
    /// φ > 0 every step spent among neighbours pays, and staying on the road longer does too.
    Mean,
    /// The neighbours' mean reward less its mean over every agent with neighbours in the same
    /// fragment: being among neighbours is worth nothing in itself, their doing better than
    /// neighbourhoods usually do is.
    Centred,
}

/// Where an agent's global return (the scene's mean reward, step by step) ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GlobalReturn {
    /// CoPO's: with the agent, so at γ = 1 an agent's global return grows with its own
    /// lifetime, and waiting (or not arriving) earns it more of the scene's reward.
    Agent,
    /// With the scene: after the agent ends the return goes on, bootstrapped from the agents
    /// still in the scene, as the paper's objective (the scene's total reward) does.
    Scene,
}

/// CoPO's learned LCF distribution (`learner.algo = "copo"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CopoConfig {
    /// μ of N(μ, σ) before any meta-gradient step, degrees.
    pub initial_mean_deg: f32,
    /// σ before any meta-gradient step, degrees.
    pub initial_std_deg: f32,
    /// Bound of μ, degrees: μ = max_mean_deg·tanh(ψ_0).
    pub max_mean_deg: f32,
    /// Adam step size of the meta-gradient on (μ, log σ).
    pub lcf_lr: f64,
    /// Passes over the batch's minibatches of the meta-gradient after each PPO update.
    pub meta_iterations: usize,
    /// Estimate the meta-gradient's two factors from different fragments of the batch.
    pub meta_cross_fit: bool,
}

/// The paper's dynamic LCF φ = f_ψ(S_N) (`learner.algo = "dynamic-lcf"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DynamicLcfConfig {
    /// Hidden layer sizes of f_ψ (tanh).
    pub hidden: Vec<i64>,
    /// Adam step size of the meta-gradient on ψ.
    pub lcf_lr: f64,
    /// Passes over the batch's minibatches of the meta-gradient after each PPO update.
    pub meta_iterations: usize,
    /// Estimate the meta-gradient's two factors from different fragments of the batch.
    pub meta_cross_fit: bool,
    /// Bound of φ, degrees: φ = max_phi_deg · tanh(f_ψ).
    pub max_phi_deg: f32,
    /// Largest mean change of φ over a batch per update, degrees (0 = unpaced).
    pub max_phi_step_deg: f32,
}

/// The centralised-critic baselines' own settings (`ccppo-concat`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CcppoConfig {
    /// k: nearest neighbours whose observations and actions the concat critic sees.
    pub neighbours: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LearnerSection {
    pub algo: AlgoKind,
    pub device: DeviceChoice,
    pub ingest_queue_fragments: usize,
    pub max_policy_lag: u64,
    pub torch_threads: usize,
    /// PPO on the CPU with 2+ threads: the policy's and the value heads' parts of each
    /// minibatch on two threads of one libtorch thread each.
    pub split_update: bool,
}

/// The learning algorithm (`learner/src/algo`, one file each).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AlgoKind {
    /// Independent PPO with parameter sharing.
    Ippo,
    /// IPPO with a curriculum over the number of agents (`[curriculum]`; CoPO's CL baseline).
    Cl,
    /// Centralised-critic PPO, critic on own obs + neighbours' mean obs and mean action.
    CcppoMf,
    /// Centralised-critic PPO, critic on own obs + k nearest neighbours' obs and actions.
    CcppoConcat,
    /// CoPO: a learned distribution over per-agent LCF angles, meta-gradient (`[copo]`).
    Copo,
    /// The paper's dynamic LCF φ = f(S_N), meta-gradient (`[dynamic_lcf]`).
    DynamicLcf,
    /// Double DQN over a grid of actions (`[dqn]`), acting ε-greedily.
    Dqn,
}

impl AlgoKind {
    pub fn name(self) -> &'static str {
        match self {
            AlgoKind::Ippo => "ippo",
            AlgoKind::Cl => "cl",
            AlgoKind::CcppoMf => "ccppo-mf",
            AlgoKind::CcppoConcat => "ccppo-concat",
            AlgoKind::Copo => "copo",
            AlgoKind::DynamicLcf => "dynamic-lcf",
            AlgoKind::Dqn => "dqn",
        }
    }

    /// Values the algorithm's policy takes beyond the scenario's observation (CoPO: its agent's
    /// LCF angle).
    pub fn extra_obs_columns(self) -> usize {
        match self {
            AlgoKind::Copo => crate::spec::LCF_OBS_COLUMNS,
            _ => 0,
        }
    }
}

/// The agent-count curriculum of `learner.algo = "cl"` (ignored by the other algorithms).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurriculumConfig {
    /// Fraction of the scenario's agents each scene simulates in each stage, increasing, in
    /// (0, 1], the last 1.
    pub stages: Vec<f64>,
    /// Agent-steps consumed in each stage before the next begins; the last stage runs on.
    pub stage_agent_steps: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum DeviceChoice {
    Cpu,
    Cuda,
    #[default]
    Auto,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerSection {
    pub addr: String,
    pub metrics_addr: String,
    pub max_message_bytes: usize,
    pub max_concurrent_streams: u32,
    pub max_rollout_streams: usize,
    pub keepalive_interval_s: f64,
    pub keepalive_timeout_s: f64,
    pub tls_cert: String,
    pub tls_key: String,
    pub tls_client_ca: String,
    pub auth_token_file: String,
    /// Base name of the shared-memory services; empty: shared memory off.
    pub shm_name: String,
    pub shm_max_actors: usize,
}

/// Ceilings that keep a configuration (or a scenario a learner sends to actors) from asking
/// for absurd allocations; far above any real run.
pub const MAX_LIDAR_BEAMS: usize = 4096;
pub const MAX_HIDDEN_WIDTH: i64 = 65_536;
pub const MAX_HIDDEN_LAYERS: usize = 16;

impl ServerSection {
    /// A path key's value, `None` when empty (the feature is off).
    pub fn path(value: &str) -> Option<&Path> {
        (!value.trim().is_empty()).then(|| Path::new(value))
    }
}

impl Default for RunConfig {
    fn default() -> Self {
        // The embedded defaults are checked by a unit test; failing here is a build defect.
        RunConfig::load(None, &[]).expect("embedded default.toml is valid")
    }
}

impl Default for ScenarioConfig {
    fn default() -> Self {
        RunConfig::default().scenario
    }
}

impl RunConfig {
    /// Defaults, then `file` (if any), then `overrides` (`section.key=value`), validated.
    pub fn load(file: Option<&Path>, overrides: &[String]) -> Result<Self, ConfigError> {
        let layers: Vec<Layer> = file
            .map(Layer::File)
            .into_iter()
            .chain(overrides.iter().map(|o| Layer::Set(o)))
            .collect();
        RunConfig::from_layers(&layers)
    }

    /// The defaults with `layers` applied in order, validated.
    pub fn from_layers(layers: &[Layer]) -> Result<Self, ConfigError> {
        let mut tree = parse_toml(DEFAULT_TOML, "defaults")?;
        for layer in layers {
            match layer {
                Layer::Preset(name) => {
                    let text = crate::presets::text(name)?;
                    merge(&mut tree, parse_toml(text, &format!("preset {name}"))?, "")?;
                }
                Layer::File(path) => {
                    let text =
                        std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
                            path: path.display().to_string(),
                            source,
                        })?;
                    merge(
                        &mut tree,
                        parse_toml(&text, &path.display().to_string())?,
                        "",
                    )?;
                }
                Layer::Scenario(text) => {
                    let section = tree
                        .get_mut("scenario")
                        .ok_or_else(|| ConfigError::Invalid("defaults lack [scenario]".into()))?;
                    merge(section, parse_toml(text, "scenario")?, "scenario")?;
                }
                Layer::Set(item) => apply_override(&mut tree, item)?,
            }
        }
        let config: RunConfig = deserialize(tree, "the merged configuration")?;
        config.validate()?;
        Ok(config)
    }

    /// Values per observation row the policy takes, which is what fragments carry: the
    /// scenario's observation plus what the algorithm appends.
    pub fn policy_obs_dim(&self) -> usize {
        self.scenario.obs_dim() + self.learner.algo.extra_obs_columns()
    }

    /// The effective configuration as TOML (recorded in checkpoints and run directories).
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# cannot serialise config: {e}"))
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        self.scenario.validate()?;
        let p = &self.ppo;
        let mut problems = Vec::new();
        if self.rollout.fragment_length == 0 {
            problems.push("rollout.fragment_length must be > 0".to_string());
        }
        if p.learning_rate <= 0.0 || !p.learning_rate.is_finite() {
            problems.push("ppo.learning_rate must be a positive number".to_string());
        }
        if !(0.0..=1.0).contains(&p.gamma) || !(0.0..=1.0).contains(&p.gae_lambda) {
            problems.push("ppo.gamma and ppo.gae_lambda must be in [0, 1]".to_string());
        }
        if p.clip <= 0.0 {
            problems.push("ppo.clip must be > 0".to_string());
        }
        if !(p.max_importance_weight > 0.0) {
            problems.push("ppo.max_importance_weight must be > 0".to_string());
        }
        // Written as "all valid" so that a NaN, which fails every comparison, is a problem too.
        let kl_valid = p.kl_coef >= 0.0 && p.kl_coef.is_finite() && p.kl_target > 0.0;
        if !kl_valid {
            problems.push("ppo.kl_coef must be >= 0 and ppo.kl_target > 0".to_string());
        }
        if p.epochs == 0 || p.minibatch_size == 0 || p.train_batch_env_steps == 0 {
            problems.push(
                "ppo.epochs, ppo.minibatch_size and ppo.train_batch_env_steps must be > 0"
                    .to_string(),
            );
        }
        if p.hidden.is_empty() || p.hidden.iter().any(|&h| h <= 0) {
            problems.push("ppo.hidden must list at least one positive layer size".to_string());
        }
        let safety = &self.safety;
        if !(safety.cost_limit >= 0.0)
            || !(safety.multiplier_lr >= 0.0)
            || !(safety.initial_multiplier >= 0.0)
        {
            problems.push(
                "safety.cost_limit, safety.multiplier_lr and safety.initial_multiplier must be >= 0"
                    .into(),
            );
        }
        let lcf = &self.lcf;
        if !(-90.0..=90.0).contains(&lcf.phi_deg) || !lcf.alpha.is_finite() || !lcf.beta.is_finite()
        {
            problems.push("lcf.phi_deg must be in [-90, 90] and lcf.alpha, lcf.beta finite".into());
        }
        let copo = &self.copo;
        // Written so NaN fails too.
        let bound_ok = copo.max_mean_deg > 0.0 && copo.max_mean_deg <= 90.0;
        let mean_ok = copo.initial_mean_deg.abs() < copo.max_mean_deg;
        let std_ok = copo.initial_std_deg > 0.0 && copo.initial_std_deg.is_finite();
        if !(bound_ok && mean_ok && std_ok) {
            problems.push(
                "copo.max_mean_deg must be in (0, 90], copo.initial_mean_deg within \
                 (-max_mean_deg, max_mean_deg) and copo.initial_std_deg > 0"
                    .into(),
            );
        }
        let dynamic = &self.dynamic_lcf;
        if dynamic.hidden.is_empty() || dynamic.hidden.iter().any(|&h| h <= 0) {
            problems.push("dynamic_lcf.hidden must list at least one positive layer size".into());
        }
        let phi_bounds_valid = dynamic.max_phi_deg > 0.0
            && dynamic.max_phi_deg <= 90.0
            && dynamic.max_phi_step_deg >= 0.0
            && dynamic.max_phi_step_deg.is_finite();
        if !phi_bounds_valid {
            problems.push(
                "dynamic_lcf.max_phi_deg must be in (0, 90] and dynamic_lcf.max_phi_step_deg >= 0"
                    .into(),
            );
        }
        for (key, lr, iterations) in [
            ("copo", copo.lcf_lr, copo.meta_iterations),
            ("dynamic_lcf", dynamic.lcf_lr, dynamic.meta_iterations),
        ] {
            let lr_ok = lr >= 0.0 && lr.is_finite();
            if !lr_ok {
                problems.push(format!("{key}.lcf_lr must be a number >= 0"));
            }
            if iterations == 0 {
                problems.push(format!("{key}.meta_iterations must be > 0"));
            }
        }
        if self.ccppo.neighbours == 0 {
            problems.push("ccppo.neighbours must be > 0".to_string());
        }
        if self.learner.ingest_queue_fragments == 0 {
            problems.push("learner.ingest_queue_fragments must be > 0".to_string());
        }
        if self.run.stats_window_episodes == 0
            || self.run.stats_window_scene_episodes == 0
            || self.run.keep_checkpoints == 0
        {
            problems.push(
                "run.stats_window_episodes, run.stats_window_scene_episodes and \
                 run.keep_checkpoints must be > 0"
                    .to_string(),
            );
        }
        if self.run.progress_interval_s <= 0.0 {
            problems.push("run.progress_interval_s must be > 0".to_string());
        }
        problems.extend(self.curriculum.problems());
        problems.extend(self.size_problems());
        problems.extend(self.server.problems());
        problems.extend(self.dqn.problems());
        if self.learner.algo == AlgoKind::Dqn && self.safety.mode != SafetyMode::Off {
            problems.push(
                "safety.mode = \"lagrangian\" is PPO-Lagrangian and works with the PPO algorithms \
                 only; learner.algo = \"dqn\" needs safety.mode = \"off\""
                    .into(),
            );
        }
        join_problems(problems)
    }

    /// Scene steps of accepted fragments that trigger an update: `dqn.train_batch_env_steps`
    /// for DQN, `ppo.train_batch_env_steps` for the PPO algorithms.
    pub fn train_batch_env_steps(&self) -> usize {
        match self.learner.algo {
            AlgoKind::Dqn => self.dqn.train_batch_env_steps,
            _ => self.ppo.train_batch_env_steps,
        }
    }

    /// Sizes beyond reason, and fragments too big for the message limit (actors could never
    /// deliver them).
    fn size_problems(&self) -> Vec<String> {
        use crate::spec::{MAX_AGENTS, MAX_STEPS};
        let mut problems = Vec::new();
        let p = &self.ppo;
        if p.hidden.len() > MAX_HIDDEN_LAYERS || p.hidden.iter().any(|&h| h > MAX_HIDDEN_WIDTH) {
            problems.push(format!(
                "ppo.hidden may list at most {MAX_HIDDEN_LAYERS} layers of at most {MAX_HIDDEN_WIDTH}"
            ));
        }
        if self.rollout.fragment_length > MAX_STEPS {
            problems.push(format!("rollout.fragment_length must be <= {MAX_STEPS}"));
        }
        if self.learner.ingest_queue_fragments > 65_536 {
            problems.push("learner.ingest_queue_fragments must be <= 65536".to_string());
        }
        let agents = self.scenario.agent_count();
        if agents > MAX_AGENTS
            || self.scenario.sensors.lidar_beams > MAX_LIDAR_BEAMS
            || self.rollout.fragment_length > MAX_STEPS
        {
            // The estimate below would be meaningless (and could overflow).
            return problems;
        }
        let bytes = self.fragment_bytes_estimate();
        if bytes > self.server.max_message_bytes {
            problems.push(format!(
                "a fragment of rollout.fragment_length = {} steps x {agents} agents is about {bytes} bytes, more than server.max_message_bytes = {}",
                self.rollout.fragment_length, self.server.max_message_bytes
            ));
        }
        problems
    }

    /// Encoded size of one fragment of this run, without neighbour lists (a lower bound).
    pub fn fragment_bytes_estimate(&self) -> usize {
        let cells = self.rollout.fragment_length * self.scenario.agent_count();
        let obs_dim = self.scenario.obs_dim();
        let floats_per_cell = obs_dim + crate::spec::ACTION_DIM + 3 + crate::lcf_inputs::FEATURES;
        // f32 values, two flag bytes and one neighbour offset per cell, the bootstrap rows.
        cells * (floats_per_cell * 4 + 2 + 4) + self.scenario.agent_count() * obs_dim * 4
    }
}

impl ServerSection {
    fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.max_message_bytes < 1 << 16 {
            problems.push("server.max_message_bytes must be >= 65536".to_string());
        }
        if self.max_concurrent_streams < 2 || self.max_rollout_streams == 0 {
            problems.push(
                "server.max_concurrent_streams must be >= 2 (an actor opens two streams) and server.max_rollout_streams > 0"
                    .to_string(),
            );
        }
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.keepalive_interval_s) || !positive(self.keepalive_timeout_s) {
            problems.push(
                "server.keepalive_interval_s and server.keepalive_timeout_s must be > 0"
                    .to_string(),
            );
        }
        let (cert, key) = (Self::path(&self.tls_cert), Self::path(&self.tls_key));
        if cert.is_some() != key.is_some() {
            problems.push("server.tls_cert and server.tls_key must be set together".to_string());
        }
        if Self::path(&self.tls_client_ca).is_some() && cert.is_none() {
            problems.push(
                "server.tls_client_ca (client certificates) needs server.tls_cert and server.tls_key"
                    .to_string(),
            );
        }
        if !self.shm_name.is_empty() && !is_valid_shm_name(&self.shm_name) {
            problems.push(format!(
                "server.shm_name {:?} may only hold letters, digits, '-', '_' and '.' (at most 200), or be \"\" for no shared memory",
                self.shm_name
            ));
        }
        if !(1..=1024).contains(&self.shm_max_actors) {
            problems.push("server.shm_max_actors must be in 1..=1024".to_string());
        }
        problems
    }
}

impl CurriculumConfig {
    /// What is wrong with the schedule, one line per problem.
    fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        let s = &self.stages;
        if s.is_empty() {
            problems.push("curriculum.stages must list at least one stage".to_string());
        } else {
            if s.iter().any(|f| !f.is_finite() || *f <= 0.0 || *f > 1.0) {
                problems.push("curriculum.stages must be fractions in (0, 1]".to_string());
            }
            if s.windows(2)
                .any(|w| w[0].partial_cmp(&w[1]) != Some(std::cmp::Ordering::Less))
            {
                problems.push("curriculum.stages must increase strictly".to_string());
            }
            if s.last() != Some(&1.0) {
                problems.push(
                    "curriculum.stages must end with 1.0 (the last stage trains every agent)"
                        .to_string(),
                );
            }
        }
        if self.stage_agent_steps == 0 {
            problems.push("curriculum.stage_agent_steps must be > 0".to_string());
        }
        problems
    }
}

impl SceneKind {
    /// MetaDrive's agent count for this kind of scene: the `medium` traffic preset.
    pub fn reference_agents(self) -> usize {
        match self {
            SceneKind::Intersection => 30,
            SceneKind::Roundabout => 40,
        }
    }
}

impl ScenarioConfig {
    /// Learning agents alive at once, after the traffic preset.
    pub fn agent_count(&self) -> usize {
        let reference = self.kind.reference_agents();
        match self.traffic {
            Traffic::Custom => self.agents,
            Traffic::Light => reference / 2,
            Traffic::Medium => reference,
            Traffic::Heavy => reference * 3 / 2,
        }
    }

    /// Human-driven vehicles alive at once: `humans.share` of all vehicles.
    pub fn human_count(&self) -> usize {
        let share = self.humans.share;
        (self.agent_count() as f32 * share / (1.0 - share)).round() as usize
    }

    /// Chance per step that an empty slot is refilled (when a spawn point is free).
    pub fn respawn_probability(&self) -> f32 {
        match self.traffic {
            Traffic::Custom => self.spawn.respawn_probability,
            Traffic::Light => 0.05,
            Traffic::Medium | Traffic::Heavy => 1.0,
        }
    }

    /// This scenario with `agents` learning agents (traffic "custom"), keeping its preset's
    /// respawn rate; human drivers keep their share of the vehicles. An agent-count
    /// curriculum simulates its stages with it.
    pub fn with_agents(&self, agents: usize) -> ScenarioConfig {
        let mut scenario = self.clone();
        scenario.spawn.respawn_probability = self.respawn_probability();
        scenario.traffic = Traffic::Custom;
        scenario.agents = agents;
        scenario
    }

    /// Parses a scenario sent by the learner (or a scenario file), layered over the defaults.
    pub fn from_toml(text: &str) -> Result<Self, ConfigError> {
        Ok(RunConfig::from_layers(&[Layer::Scenario(text)])?.scenario)
    }

    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# cannot serialise scenario: {e}"))
    }

    pub fn obs_dim(&self) -> usize {
        crate::spec::obs_dim(self.sensors.lidar_beams)
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        let mut problems = Vec::new();
        if self.agents == 0 || self.agents > crate::spec::MAX_AGENTS {
            problems.push(format!(
                "scenario.agents must be in 1..={}",
                crate::spec::MAX_AGENTS
            ));
        }
        if self.horizon == 0 || self.agent_horizon == 0 {
            problems.push("scenario.horizon and scenario.agent_horizon must be > 0".to_string());
        }
        let v = &self.vehicle;
        let vehicle_valid = v.max_lateral_accel >= 0.0
            && v.max_lateral_accel.is_finite()
            && v.max_brake_decel > 0.0
            && v.max_brake_decel <= 20.0
            && v.brake_saturation > 0.0
            && v.brake_saturation <= 1.0
            && v.steering_time_constant >= 0.0
            && v.steering_time_constant <= 5.0;
        if !vehicle_valid {
            problems.push(
                "scenario.vehicle.max_lateral_accel must be >= 0 (0 = no limit), \
                 scenario.vehicle.max_brake_decel in (0, 20] m/s², \
                 scenario.vehicle.brake_saturation in (0, 1] and \
                 scenario.vehicle.steering_time_constant in [0, 5] s"
                    .into(),
            );
        }
        if !(self.decision_dt > 0.0) || self.substeps == 0 {
            problems.push("scenario.decision_dt and scenario.substeps must be > 0".to_string());
        }
        if !(self.neighbour_radius >= 0.0) {
            problems.push("scenario.neighbour_radius must be >= 0".to_string());
        }
        let i = &self.intersection;
        if !(1..=3).contains(&i.lanes_per_direction) {
            problems.push("scenario.intersection.lanes_per_direction must be 1, 2 or 3".into());
        }
        if !(i.lane_width >= 2.5) || !(i.corner_radius >= 0.0) {
            problems.push(
                "scenario.intersection.lane_width must be >= 2.5 m and corner_radius >= 0".into(),
            );
        }
        if i.routes.is_empty() {
            problems.push("scenario.intersection.routes must name at least one manoeuvre".into());
        }
        if !(3..=4).contains(&i.arms) {
            problems.push("scenario.intersection.arms must be 3 (a T-junction) or 4".into());
        }
        let ra = &self.roundabout;
        if !(3..=5).contains(&ra.arms) {
            problems.push("scenario.roundabout.arms must be 3, 4 or 5".into());
        }
        if !(1..=3).contains(&ra.lanes_per_direction) || !(1..=3).contains(&ra.ring_lanes) {
            problems.push(
                "scenario.roundabout.lanes_per_direction and ring_lanes must be 1, 2 or 3".into(),
            );
        }
        if ra.ring_lanes < ra.lanes_per_direction {
            problems.push(
                "scenario.roundabout.ring_lanes must be >= lanes_per_direction (every arm lane \
                 continues on its own ring lane)"
                    .into(),
            );
        }
        if !(2.5..).contains(&ra.lane_width) || !(5.0..).contains(&ra.radius) {
            problems
                .push("scenario.roundabout.lane_width must be >= 2.5 m and radius >= 5 m".into());
        }
        if !(ra.entry_angle > 0.0 && ra.entry_angle < 90.0) {
            problems
                .push("scenario.roundabout.entry_angle must lie strictly between 0 and 90°".into());
        }
        if !(ra.lane_width..).contains(&ra.exit_radius) {
            problems.push(
                "scenario.roundabout.exit_radius must be >= lane_width (the kerb needs a radius)"
                    .into(),
            );
        }
        let s = &self.spawn;
        if !(s.slot_spacing >= 5.0) {
            problems.push("scenario.spawn.slot_spacing must be >= 5 m (a car is 4.5 m)".into());
        }
        let holds_a_slot = s.slot_spacing..;
        if !holds_a_slot.contains(&i.approach_length) || !holds_a_slot.contains(&ra.approach_length)
        {
            problems.push(
                "scenario.intersection.approach_length and scenario.roundabout.approach_length \
                 must each hold at least one spawn slot"
                    .into(),
            );
        }
        let h = &self.humans;
        if !(0.0..=0.9).contains(&h.share) {
            problems.push("scenario.humans.share must be in [0, 0.9]".into());
        }
        let human_positive = [
            h.desired_speed,
            h.time_headway,
            h.max_accel,
            h.comfort_decel,
            h.critical_gap,
        ];
        if human_positive.iter().any(|v| !(*v > 0.0)) || !(h.min_gap >= 0.0) {
            problems.push(
                "scenario.humans: desired_speed, time_headway, max_accel, comfort_decel and critical_gap must be > 0, min_gap >= 0".into(),
            );
        }
        if !(0.0..=1.0).contains(&s.respawn_probability) {
            problems.push("scenario.spawn.respawn_probability must be in [0, 1]".into());
        }
        if !(s.initial_speed >= 0.0) {
            problems.push("scenario.spawn.initial_speed must be >= 0".into());
        }
        if !(1..=MAX_LIDAR_BEAMS).contains(&self.sensors.lidar_beams)
            || !(self.sensors.lidar_range > 0.0)
        {
            problems.push(format!(
                "scenario.sensors needs lidar_beams in 1..={MAX_LIDAR_BEAMS} and lidar_range > 0"
            ));
        }
        let r = &self.reward;
        let numbers = [
            r.displacement,
            r.speed,
            r.lateral,
            r.heading,
            r.steering,
            r.collision,
            r.success,
            r.crash,
            r.out_of_road,
            self.cost.collision,
            self.cost.energy,
        ];
        if numbers.iter().any(|v| !v.is_finite()) {
            problems.push("scenario.reward and scenario.cost values must be finite".into());
        }
        join_problems(problems)
    }
}

/// A base name for the shared-memory services (`server.shm_name`): 1 to 200 letters,
/// digits, '-', '_' or '.'.
pub fn is_valid_shm_name(base: &str) -> bool {
    (1..=200).contains(&base.len())
        && base
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
}

fn join_problems(problems: Vec<String>) -> Result<(), ConfigError> {
    if problems.is_empty() {
        Ok(())
    } else {
        Err(ConfigError::Invalid(problems.join("; ")))
    }
}

fn parse_toml(text: &str, origin: &str) -> Result<toml::Value, ConfigError> {
    text.parse::<toml::Table>()
        .map(toml::Value::Table)
        .map_err(|source| ConfigError::Parse {
            origin: origin.to_string(),
            source: Box::new(source),
        })
}

fn deserialize<T: serde::de::DeserializeOwned>(
    tree: toml::Value,
    origin: &str,
) -> Result<T, ConfigError> {
    tree.try_into().map_err(|source| ConfigError::Parse {
        origin: origin.to_string(),
        source: Box::new(source),
    })
}

/// Overlays `user` onto `base`; only keys that exist in the defaults are accepted, so a typo
/// is reported with its full path.
fn merge(base: &mut toml::Value, user: toml::Value, prefix: &str) -> Result<(), ConfigError> {
    let (toml::Value::Table(base_table), toml::Value::Table(user_table)) = (&mut *base, &user)
    else {
        *base = user;
        return Ok(());
    };
    for (key, value) in user_table.clone() {
        let path = if prefix.is_empty() {
            key.clone()
        } else {
            format!("{prefix}.{key}")
        };
        match base_table.get_mut(&key) {
            Some(slot @ toml::Value::Table(_)) => merge(slot, value, &path)?,
            Some(slot) => *slot = value,
            None => return Err(ConfigError::UnknownKey { key: path }),
        }
    }
    Ok(())
}

fn apply_override(tree: &mut toml::Value, item: &str) -> Result<(), ConfigError> {
    let (path, raw) = item
        .split_once('=')
        .ok_or_else(|| ConfigError::OverrideSyntax(item.to_string()))?;
    let path = path.trim();
    if path.is_empty() {
        return Err(ConfigError::OverrideSyntax(item.to_string()));
    }
    // A value is TOML (`0.5`, `true`, `[64, 64]`, `"x"`); a bare word is taken as a string.
    let value = format!("v = {raw}")
        .parse::<toml::Table>()
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(raw.trim().to_string()));
    let mut node = tree;
    let keys: Vec<&str> = path.split('.').collect();
    for (depth, key) in keys.iter().enumerate() {
        let unknown = || ConfigError::UnknownKey {
            key: path.to_string(),
        };
        let table = node.as_table_mut().ok_or_else(unknown)?;
        let child = table.get_mut(*key).ok_or_else(unknown)?;
        if depth + 1 == keys.len() {
            if child.is_table() {
                return Err(ConfigError::Invalid(format!(
                    "{path} is a section; override one of its keys instead"
                )));
            }
            *child = value;
            return Ok(());
        }
        node = child;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_defaults_load_and_match_metadrive() {
        let c = RunConfig::load(None, &[]).unwrap();
        assert_eq!(c.scenario.agents, 30);
        assert_eq!(c.scenario.intersection.lanes_per_direction, 2);
        assert_eq!(c.scenario.obs_dim(), 91);
        assert_eq!(c.ppo.hidden, vec![256, 256]);
        assert_eq!(c.rollout.fragment_length, 200);
    }

    #[test]
    fn every_default_key_is_documented_by_a_comment() {
        // The key lines of default.toml must each follow a comment line (or a key of the
        // same documented group): the file is the reference documentation of the config.
        let mut previous_was_doc = false;
        for line in DEFAULT_TOML.lines().map(str::trim) {
            if line.starts_with('#') {
                previous_was_doc = true;
            } else if line.is_empty() || line.starts_with('[') {
                previous_was_doc = false;
            } else {
                assert!(previous_was_doc, "undocumented key in default.toml: {line}");
            }
        }
    }

    #[test]
    fn overrides_reach_nested_keys_and_reject_typos() {
        let c = RunConfig::load(
            None,
            &[
                "ppo.learning_rate=1e-3".into(),
                "scenario.intersection.routes=[\"left\"]".into(),
            ],
        )
        .unwrap();
        assert_eq!(c.ppo.learning_rate, 1e-3);
        assert_eq!(c.scenario.intersection.routes, vec![Manoeuvre::Left]);
        let err = RunConfig::load(None, &["ppo.learnin_rate=1".into()]).unwrap_err();
        assert!(matches!(err, ConfigError::UnknownKey { ref key } if key == "ppo.learnin_rate"));
        let bare = RunConfig::load(None, &["learner.device=cpu".into()]).unwrap();
        assert_eq!(bare.learner.device, DeviceChoice::Cpu);
    }

    #[test]
    fn file_layer_rejects_unknown_keys_and_bad_values() {
        let dir = std::env::temp_dir().join(format!("junction-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("c.toml");
        std::fs::write(&path, "[ppo]\nclip = 0.2\n[scenario]\nagents = 4\n").unwrap();
        let c = RunConfig::load(Some(&path), &[]).unwrap();
        assert_eq!((c.ppo.clip, c.scenario.agents), (0.2, 4));
        std::fs::write(&path, "[ppo]\nclipp = 0.2\n").unwrap();
        assert!(matches!(
            RunConfig::load(Some(&path), &[]),
            Err(ConfigError::UnknownKey { .. })
        ));
        std::fs::write(&path, "[ppo]\nepochs = 0\n").unwrap();
        assert!(matches!(
            RunConfig::load(Some(&path), &[]),
            Err(ConfigError::Invalid(_))
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn learned_lcf_bounds_outside_their_range_are_refused() {
        let c = RunConfig::default();
        assert_eq!(
            (c.copo.max_mean_deg, c.dynamic_lcf.max_phi_deg),
            (90.0, 10.0)
        );
        for bad in [
            vec!["copo.max_mean_deg=0.0"],
            vec!["copo.max_mean_deg=91.0"],
            vec!["copo.max_mean_deg=nan"],
            vec!["copo.max_mean_deg=20.0", "copo.initial_mean_deg=20.0"],
            vec!["copo.initial_mean_deg=-90.0"],
            vec!["dynamic_lcf.max_phi_deg=0.0"],
            vec!["dynamic_lcf.max_phi_step_deg=-1.0"],
        ] {
            let overrides: Vec<String> = bad.iter().map(|s| s.to_string()).collect();
            let err = RunConfig::load(None, &overrides);
            assert!(
                matches!(err, Err(ConfigError::Invalid(_))),
                "{bad:?} was accepted: {err:?}"
            );
        }
        let bounded = RunConfig::load(None, &["copo.max_mean_deg=20.0".into()]).unwrap();
        assert_eq!(bounded.copo.max_mean_deg, 20.0);
    }

    #[test]
    fn curriculum_defaults_follow_copo_and_bad_schedules_are_refused() {
        let c = RunConfig::default();
        assert_eq!(c.curriculum.stages, vec![0.25, 0.5, 0.75, 1.0]);
        assert_eq!(c.curriculum.stage_agent_steps, 500_000);
        let cl = RunConfig::load(None, &["learner.algo=\"cl\"".into()]).unwrap();
        assert_eq!(cl.learner.algo, AlgoKind::Cl);
        for bad in [
            "curriculum.stages=[]",
            "curriculum.stages=[0.5, 0.25, 1.0]",
            "curriculum.stages=[0.5, 0.5, 1.0]",
            "curriculum.stages=[0.0, 1.0]",
            "curriculum.stages=[0.5, 1.5]",
            "curriculum.stages=[0.25, 0.5]",
            "curriculum.stage_agent_steps=0",
        ] {
            let err = RunConfig::load(None, &[bad.into()]);
            assert!(
                matches!(err, Err(ConfigError::Invalid(_))),
                "{bad} was accepted: {err:?}"
            );
        }
        let one = RunConfig::load(None, &["curriculum.stages=[1.0]".into()]).unwrap();
        assert_eq!(one.curriculum.stages, vec![1.0]);
    }

    #[test]
    fn absurd_sizes_and_half_configured_security_are_refused() {
        for bad in [
            "scenario.agents=1000000",
            "scenario.sensors.lidar_beams=100000",
            "ppo.hidden=[100000]",
            "ppo.hidden=[8,8,8,8,8,8,8,8,8,8,8,8,8,8,8,8,8]",
            "rollout.fragment_length=1000000",
            "learner.ingest_queue_fragments=100000000",
            "server.max_message_bytes=1000",
            "server.max_rollout_streams=0",
            "server.max_concurrent_streams=1",
            "server.keepalive_interval_s=0",
            "server.keepalive_timeout_s=nan",
            "server.tls_cert=\"cert.pem\"",
            "server.tls_client_ca=\"ca.pem\"",
        ] {
            let err = RunConfig::load(None, &[bad.into()]);
            assert!(
                matches!(
                    err,
                    Err(ConfigError::Invalid(_)) | Err(ConfigError::Parse { .. })
                ),
                "{bad} was accepted: {err:?}"
            );
        }
        // A fragment that cannot fit the message limit: 2000 steps x 30 agents x 91 values.
        let err = RunConfig::load(
            None,
            &[
                "rollout.fragment_length=2000".into(),
                "server.max_message_bytes=4000000".into(),
            ],
        )
        .unwrap_err();
        assert!(
            err.to_string().contains("server.max_message_bytes"),
            "{err}"
        );
        let tls = RunConfig::load(
            None,
            &[
                "server.tls_cert=\"c.pem\"".into(),
                "server.tls_key=\"k.pem\"".into(),
            ],
        )
        .unwrap();
        assert_eq!(
            ServerSection::path(&tls.server.tls_cert),
            Some(Path::new("c.pem"))
        );
        assert_eq!(ServerSection::path(&tls.server.auth_token_file), None);
    }

    #[test]
    fn the_linear_learning_rate_falls_to_zero_at_the_budget_and_stays_constant_without_one() {
        let linear = LrSchedule::Linear;
        let mut run = RunConfig::default().run;
        run.max_agent_steps = 1000;
        let rate = |schedule: LrSchedule, run: &RunSection, steps| {
            schedule.learning_rate(4e-4, run.budget_spent(steps, 30.0))
        };
        assert_eq!(rate(linear, &run, 0), 4e-4);
        assert!((rate(linear, &run, 250) - 3e-4).abs() < 1e-12);
        assert_eq!(rate(linear, &run, 1500), 0.0);
        assert_eq!(rate(LrSchedule::Constant, &run, 900), 4e-4);
        run.max_agent_steps = 0;
        run.max_seconds = 0.0;
        assert_eq!(rate(linear, &run, 1500), 4e-4);
        assert_eq!(RunConfig::default().ppo.lr_schedule, LrSchedule::Linear);
        let constant = RunConfig::load(None, &["ppo.lr_schedule=\"constant\"".into()]);
        assert_eq!(constant.unwrap().ppo.lr_schedule, LrSchedule::Constant);
    }

    #[test]
    fn a_run_bounded_by_the_clock_spends_its_budget_in_seconds() {
        let mut run = RunConfig::default().run;
        run.max_seconds = 300.0;
        assert_eq!(run.budget_spent(123_456, 75.0), Some(0.25));
        // An agent-step budget, where there is one, is what the schedule follows.
        run.max_agent_steps = 1_000_000;
        assert_eq!(run.budget_spent(500_000, 75.0), Some(0.5));
        let rate = LrSchedule::Linear.learning_rate(4e-4, RunSection {
            max_agent_steps: 0,
            ..run
        }
        .budget_spent(0, 150.0));
        assert!((rate - 2e-4).abs() < 1e-12, "{rate}");
    }

    #[test]
    fn dqn_defaults_use_metadrive_grid_and_bad_dqn_settings_are_refused() {
        let c = RunConfig::load(None, &["learner.algo=\"dqn\"".into()]).unwrap();
        assert_eq!(c.dqn.steering, vec![-1.0, -0.5, 0.0, 0.5, 1.0]);
        assert_eq!(c.dqn.throttle, c.dqn.steering);
        assert_eq!(c.train_batch_env_steps(), c.dqn.train_batch_env_steps);
        assert_eq!(
            RunConfig::default().train_batch_env_steps(),
            c.ppo.train_batch_env_steps
        );
        for bad in [
            "dqn.steering=[]",
            "dqn.steering=[0.5, 0.0]",
            "dqn.throttle=[0.0, 2.0]",
            "dqn.batch_size=0",
            "dqn.replay_capacity=0",
            "dqn.replay_ratio=0.0",
            "dqn.epsilon_end=1.5",
            "dqn.gamma=1.1",
            "dqn.hidden=[]",
            "dqn.target_update_gradient_steps=0",
        ] {
            let err = RunConfig::load(None, &[bad.into()]);
            assert!(
                matches!(err, Err(ConfigError::Invalid(_))),
                "{bad} was accepted: {err:?}"
            );
        }
        // PPO-Lagrangian is PPO's; DQN says so instead of ignoring it.
        let err = RunConfig::load(
            None,
            &[
                "learner.algo=\"dqn\"".into(),
                "safety.mode=\"lagrangian\"".into(),
            ],
        );
        assert!(
            matches!(&err, Err(ConfigError::Invalid(m)) if m.contains("PPO")),
            "{err:?}"
        );
    }

    #[test]
    fn with_agents_changes_only_the_agent_count() {
        let heavy = ScenarioConfig {
            traffic: Traffic::Light,
            ..ScenarioConfig::default()
        };
        let fewer = heavy.with_agents(4);
        assert_eq!(fewer.agent_count(), 4);
        assert_eq!(fewer.respawn_probability(), heavy.respawn_probability());
        assert_eq!(fewer.name, heavy.name);
        assert_eq!(fewer.obs_dim(), heavy.obs_dim());
    }

    #[test]
    fn scenario_round_trips_through_toml() {
        let s = ScenarioConfig {
            agents: 3,
            ..ScenarioConfig::default()
        };
        assert_eq!(ScenarioConfig::from_toml(&s.to_toml()).unwrap(), s);
    }
}
