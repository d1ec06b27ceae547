//! `[learner]` (algorithm, device, ingest queue, threads) and `[curriculum]` (the
//! agent-count curriculum of `learner.algo = "cl"`).

use serde::{Deserialize, Serialize};

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

impl LearnerSection {
    /// What is wrong with the section (its ceiling is among the run's size checks).
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.ingest_queue_fragments == 0 {
            problems.push("learner.ingest_queue_fragments must be > 0".to_string());
        }
        problems
    }
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

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum DeviceChoice {
    Cpu,
    Cuda,
    #[default]
    Auto,
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

impl CurriculumConfig {
    /// What is wrong with the schedule, one line per problem.
    pub(super) fn problems(&self) -> Vec<String> {
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

#[cfg(test)]
mod tests {
    use crate::config::*;

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
}
