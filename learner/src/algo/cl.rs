//! CL: IPPO with a curriculum over the number of agents (CoPO's CL baseline: four stages with
//! ¼, ½, ¾ and all of the agents). The update is IPPO's, unchanged; what CL adds is the
//! schedule, which the learner sends to actors with every policy broadcast.
//!
//! ```text
//! stage k = min(⌊agent-steps consumed / stage_agent_steps⌋, stages − 1)
//! agents  = max(1, round(stages[k] × scenario agents))
//! each update: IPPO's update on whatever the actors simulated
//! ```

use tch::Tensor;

use junction_common::fragment::RolloutFragment;
use junction_common::policy::Policy;
use junction_common::weights::{Decoded, WeightsError};
use junction_core::config::CurriculumConfig;

use super::ippo::Ippo;
use super::{AlgoError, Algorithm, Stage, UpdateStats};

/// The stage schedule: a pure function of the agent-steps consumed, so it needs no state of
/// its own in checkpoints.
#[derive(Debug, Clone, PartialEq)]
pub struct Curriculum {
    stages: Vec<f64>,
    stage_agent_steps: u64,
}

impl Curriculum {
    /// From a validated `[curriculum]`; an empty stage list behaves as one stage of every agent.
    pub fn new(config: &CurriculumConfig) -> Self {
        Curriculum {
            stages: config.stages.clone(),
            stage_agent_steps: config.stage_agent_steps.max(1),
        }
    }

    /// The stage index after `agent_steps` consumed; the last stage lasts for ever.
    pub fn stage_index(&self, agent_steps: u64) -> usize {
        let last = self.stages.len().saturating_sub(1);
        usize::try_from(agent_steps / self.stage_agent_steps)
            .unwrap_or(usize::MAX)
            .min(last)
    }

    /// Agents a scene of `scenario_agents` simulates in stage `index`: at least one, at most
    /// all.
    pub fn agents(&self, index: usize, scenario_agents: usize) -> usize {
        let fraction = self.stages.get(index).copied().unwrap_or(1.0);
        let agents = (fraction * scenario_agents as f64).round() as usize;
        agents.clamp(1, scenario_agents.max(1))
    }

    pub fn stage(&self, agent_steps: u64, scenario_agents: usize) -> Stage {
        let index = self.stage_index(agent_steps);
        Stage {
            index,
            agents: self.agents(index, scenario_agents),
        }
    }
}

/// IPPO whose actors follow a [`Curriculum`].
pub struct Cl {
    ippo: Ippo,
    curriculum: Curriculum,
}

impl Cl {
    pub fn new(ippo: Ippo, curriculum: Curriculum) -> Self {
        Cl { ippo, curriculum }
    }
}

impl Algorithm for Cl {
    fn name(&self) -> &'static str {
        "cl"
    }

    fn policy(&self) -> &dyn Policy {
        self.ippo.policy()
    }

    fn policy_bytes(&self, version: u64) -> Result<Vec<u8>, WeightsError> {
        self.ippo.policy_bytes(version)
    }

    fn set_progress(&mut self, budget_spent: Option<f64>) {
        self.ippo.set_progress(budget_spent);
    }

    fn update(&mut self, fragments: &[RolloutFragment]) -> Result<UpdateStats, AlgoError> {
        self.ippo.update(fragments)
    }

    fn state_tensors(&self) -> Vec<(String, Tensor)> {
        self.ippo.state_tensors()
    }

    fn restore(&mut self, policy_blob: &[u8], state: &mut Decoded) -> Result<(), WeightsError> {
        self.ippo.restore(policy_blob, state)
    }

    fn stage(&self, agent_steps: u64, scenario_agents: usize) -> Stage {
        self.curriculum.stage(agent_steps, scenario_agents)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn copo(stage_agent_steps: u64) -> Curriculum {
        Curriculum::new(&CurriculumConfig {
            stages: vec![0.25, 0.5, 0.75, 1.0],
            stage_agent_steps,
        })
    }

    #[test]
    fn stages_advance_exactly_at_their_boundaries_and_the_last_one_stays() {
        let c = copo(1000);
        let at = |steps| c.stage_index(steps);
        assert_eq!(
            [at(0), at(999), at(1000), at(1999), at(2000), at(2999)],
            [0, 0, 1, 1, 2, 2]
        );
        assert_eq!([at(3000), at(3999), at(4000), at(1_000_000)], [3, 3, 3, 3]);
        assert_eq!(at(u64::MAX), 3);
    }

    #[test]
    fn agents_are_the_rounded_fraction_at_least_one_at_most_all() {
        let c = copo(1000);
        let agents = |n| (0..4).map(|k| c.agents(k, n)).collect::<Vec<_>>();
        // MetaDrive's intersection: 7.5 and 22.5 round half away from zero.
        assert_eq!(agents(30), [8, 15, 23, 30]);
        assert_eq!(agents(8), [2, 4, 6, 8]);
        assert_eq!(agents(40), [10, 20, 30, 40]);
        // A single-agent scene never drops to zero agents.
        assert_eq!(agents(1), [1, 1, 1, 1]);
        assert_eq!(agents(3), [1, 2, 2, 3]);
        assert_eq!(
            c.stage(2500, 30),
            Stage {
                index: 2,
                agents: 23
            }
        );
    }
}
