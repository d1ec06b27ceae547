//! `[run]` (seed, budget, checkpoints, statistics windows) and `[rollout]` (fragment length).

use serde::{Deserialize, Serialize};

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

    /// What is wrong with the section, one line per problem.
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.stats_window_episodes == 0
            || self.stats_window_scene_episodes == 0
            || self.keep_checkpoints == 0
        {
            problems.push(
                "run.stats_window_episodes, run.stats_window_scene_episodes and \
                 run.keep_checkpoints must be > 0"
                    .to_string(),
            );
        }
        if self.progress_interval_s <= 0.0 {
            problems.push("run.progress_interval_s must be > 0".to_string());
        }
        problems
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RolloutConfig {
    pub fragment_length: usize,
}

impl RolloutConfig {
    /// What is wrong with the section (its ceiling is among the run's size checks).
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.fragment_length == 0 {
            problems.push("rollout.fragment_length must be > 0".to_string());
        }
        problems
    }
}

#[cfg(test)]
mod tests {
    use crate::config::*;

    #[test]
    fn a_run_bounded_by_the_clock_spends_its_budget_in_seconds() {
        let mut run = RunConfig::default().run;
        run.max_seconds = 300.0;
        assert_eq!(run.budget_spent(123_456, 75.0), Some(0.25));
        // An agent-step budget, where there is one, is what the schedule follows.
        run.max_agent_steps = 1_000_000;
        assert_eq!(run.budget_spent(500_000, 75.0), Some(0.5));
        let rate = LrSchedule::Linear.learning_rate(
            4e-4,
            RunSection {
                max_agent_steps: 0,
                ..run
            }
            .budget_spent(0, 150.0),
        );
        assert!((rate - 2e-4).abs() < 1e-12, "{rate}");
    }
}
