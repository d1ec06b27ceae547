//! `[scenario.reward]` and `[scenario.cost]`: what each step pays an agent, and what it costs
//! under safe RL.

use serde::{Deserialize, Serialize};

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

/// What is wrong with the reward's and the cost's terms (one line for both).
pub(super) fn reward_problems(reward: &RewardConfig, cost: &CostConfig) -> Vec<String> {
    let mut problems = Vec::new();
    let r = reward;
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
        cost.collision,
        cost.energy,
    ];
    if numbers.iter().any(|v| !v.is_finite()) {
        problems.push("scenario.reward and scenario.cost values must be finite".into());
    }
    problems
}
