//! `[dqn]`: double DQN over a grid of actions (`learner.algo = "dqn"`).

use serde::{Deserialize, Serialize};

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
    pub(super) fn problems(&self) -> Vec<String> {
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

#[cfg(test)]
mod tests {
    use crate::config::*;

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
}
