//! `[scenario]`: the task. Its own keys (simulator, scene kind, traffic, agents, horizons,
//! stepping) are here, with the check that gathers its sub-sections' checks from beside them:
//! the roads and spawning (`roads.rs`), the car, its lidar and the human drivers
//! (`vehicles.rs`), the reward and cost (`reward.rs`).

use serde::{Deserialize, Serialize};

use super::reward::reward_problems;
use super::{
    ConfigError, CostConfig, HumanConfig, IntersectionConfig, Layer, RewardConfig,
    RoundaboutConfig, RunConfig, SensorConfig, SpawnConfig, VehicleConfig, join_problems,
};

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

impl SceneKind {
    /// MetaDrive's agent count for this kind of scene: the `medium` traffic preset.
    pub fn reference_agents(self) -> usize {
        match self {
            SceneKind::Intersection => 30,
            SceneKind::Roundabout => 40,
        }
    }
}

impl Default for ScenarioConfig {
    fn default() -> Self {
        RunConfig::default().scenario
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
        join_problems(self.problems())
    }

    /// What is wrong with the scenario, one line per problem: its own keys' and each
    /// sub-section's, in this order.
    fn problems(&self) -> Vec<String> {
        [
            self.episode_problems(),
            self.vehicle.problems(),
            self.step_problems(),
            self.intersection.problems(),
            self.roundabout.problems(),
            self.spawn
                .slot_problems(&self.intersection, &self.roundabout),
            self.humans.problems(),
            self.spawn.refill_problems(),
            self.sensors.problems(),
            reward_problems(&self.reward, &self.cost),
        ]
        .concat()
    }

    /// The agent count and the horizons.
    fn episode_problems(&self) -> Vec<String> {
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
        problems
    }

    /// The decision step, its physics substeps and the neighbourhood's radius.
    fn step_problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if !(self.decision_dt > 0.0) || self.substeps == 0 {
            problems.push("scenario.decision_dt and scenario.substeps must be > 0".to_string());
        }
        if !(self.neighbour_radius >= 0.0) {
            problems.push("scenario.neighbour_radius must be >= 0".to_string());
        }
        problems
    }
}

#[cfg(test)]
mod tests {
    use crate::config::*;

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
