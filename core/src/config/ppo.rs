//! `[ppo]`: the PPO update every PPO algorithm shares, with its learning-rate schedule,
//! objective and action-std choices.

use serde::{Deserialize, Serialize};

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
    pub log_std_cap: LogStdCap,
    pub final_log_std_cap: f64,
    pub normalize_advantages: bool,
    pub normalize_observations: bool,
    pub objective: PpoObjective,
    pub action_std: ActionStd,
    pub max_importance_weight: f64,
    pub kl_coef: f64,
    pub kl_target: f64,
    /// α of advantage-prioritised minibatches (0: every row once per epoch).
    pub advantage_priority: f64,
    /// β: how much of the prioritised draw's bias the rows' weights undo (1: all of it).
    pub priority_correction: f64,
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
    /// ([`RunSection::budget_spent`](super::RunSection::budget_spent)); constant in a run
    /// without a budget.
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

/// Whether the policy's global log-std is held under a ceiling that falls over the run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LogStdCap {
    /// Learned freely.
    None,
    /// At most `init_log_std` at the start of the budget, falling linearly to
    /// `final_log_std_cap` at its end; no cap in a run without a budget.
    Linear,
}

impl LogStdCap {
    /// The ceiling once the share `spent` of the run's budget is used (None: no ceiling).
    pub fn ceiling(self, init: f64, last: f64, spent: Option<f64>) -> Option<f64> {
        match (self, spent) {
            (LogStdCap::Linear, Some(spent)) => {
                let spent = spent.clamp(0.0, 1.0);
                Some(init + (last - init) * spent)
            }
            _ => None,
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

impl PpoConfig {
    /// What is wrong with the section, one line per problem (its ceilings are among the run's
    /// size checks).
    pub(super) fn problems(&self) -> Vec<String> {
        let p = self;
        let mut problems = Vec::new();
        if p.learning_rate <= 0.0 || !p.learning_rate.is_finite() {
            problems.push("ppo.learning_rate must be a positive number".to_string());
        }
        if !(0.0..=1.0).contains(&p.gamma) || !(0.0..=1.0).contains(&p.gae_lambda) {
            problems.push("ppo.gamma and ppo.gae_lambda must be in [0, 1]".to_string());
        }
        if p.clip <= 0.0 {
            problems.push("ppo.clip must be > 0".to_string());
        }
        // Written as "all valid" so that a NaN is a problem too.
        let weights_valid = p.entropy_coef.is_finite()
            && p.value_coef >= 0.0
            && p.value_coef.is_finite()
            && p.value_clip >= 0.0
            && p.max_grad_norm >= 0.0
            && p.adam_eps > 0.0
            && p.init_log_std.is_finite();
        if !weights_valid {
            problems.push(
                "ppo.entropy_coef and ppo.init_log_std must be numbers, ppo.value_coef, \
                 ppo.value_clip and ppo.max_grad_norm >= 0, and ppo.adam_eps > 0"
                    .to_string(),
            );
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
        // Written as "all valid" so that a NaN is a problem too.
        let priority_valid = p.advantage_priority >= 0.0
            && p.advantage_priority.is_finite()
            && (0.0..=1.0).contains(&p.priority_correction);
        if !priority_valid {
            problems.push(
                "ppo.advantage_priority must be >= 0 and ppo.priority_correction in [0, 1]"
                    .to_string(),
            );
        }
        if p.advantage_priority > 0.0 && p.objective == PpoObjective::Decoupled {
            problems.push(
                "ppo.advantage_priority needs ppo.objective = \"clipped\" (the decoupled \
                 objective weights its rows already)"
                    .to_string(),
            );
        }
        if p.log_std_cap == LogStdCap::Linear
            && !(p.final_log_std_cap.is_finite() && p.final_log_std_cap <= p.init_log_std)
        {
            problems.push(
                "ppo.final_log_std_cap must be a number <= ppo.init_log_std when ppo.log_std_cap \
                 = \"linear\""
                    .to_string(),
            );
        }
        if p.hidden.is_empty() || p.hidden.iter().any(|&h| h <= 0) {
            problems.push("ppo.hidden must list at least one positive layer size".to_string());
        }
        problems
    }
}

#[cfg(test)]
mod tests {
    use crate::config::*;

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
    fn the_log_std_ceiling_falls_from_the_initial_value_to_the_final_one_over_the_budget() {
        let linear = LogStdCap::Linear;
        assert_eq!(linear.ceiling(0.0, -1.5, Some(0.0)), Some(0.0));
        assert_eq!(linear.ceiling(0.0, -1.5, Some(0.5)), Some(-0.75));
        assert_eq!(linear.ceiling(0.0, -1.5, Some(2.0)), Some(-1.5));
        assert_eq!(linear.ceiling(0.0, -1.5, None), None);
        assert_eq!(LogStdCap::None.ceiling(0.0, -1.5, Some(0.5)), None);
        assert_eq!(RunConfig::default().ppo.log_std_cap, LogStdCap::None);
        let load = |cap: &str| {
            RunConfig::load(
                None,
                &[
                    "ppo.log_std_cap=\"linear\"".into(),
                    format!("ppo.final_log_std_cap={cap}"),
                ],
            )
        };
        assert_eq!(load("-2.0").unwrap().ppo.final_log_std_cap, -2.0);
        // A ceiling that would rise above the initial log-std, or is not a number, is refused.
        for bad in ["0.5", "nan"] {
            let error = load(bad).unwrap_err().to_string();
            assert!(error.contains("ppo.final_log_std_cap"), "{bad}: {error}");
        }
    }

    #[test]
    fn loss_weights_that_are_not_numbers_or_are_negative_are_refused() {
        for bad in [
            "ppo.entropy_coef=nan",
            "ppo.value_coef=-1.0",
            "ppo.value_clip=-1.0",
            "ppo.max_grad_norm=nan",
            "ppo.adam_eps=0.0",
            "ppo.init_log_std=inf",
        ] {
            let error = RunConfig::load(None, &[bad.to_string()])
                .unwrap_err()
                .to_string();
            assert!(error.contains("ppo.value_coef"), "{bad}: {error}");
        }
        // A negative entropy weight (pushing the std down) is a choice, not an error.
        assert!(RunConfig::load(None, &["ppo.entropy_coef=-0.01".into()]).is_ok());
    }
}
