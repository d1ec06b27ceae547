//! `[safety]`: PPO-Lagrangian's cost critic and multiplier, for every PPO algorithm.

use serde::{Deserialize, Serialize};

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

impl SafetyConfig {
    /// What is wrong with the section (that DQN refuses it is a rule across sections).
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if !(self.cost_limit >= 0.0)
            || !(self.multiplier_lr >= 0.0)
            || !(self.initial_multiplier >= 0.0)
        {
            problems.push(
                "safety.cost_limit, safety.multiplier_lr and safety.initial_multiplier must be >= 0"
                    .into(),
            );
        }
        problems
    }
}
