//! Learning algorithms, one file each; the pieces they share (GAE, batching, PPO loss terms)
//! live beside them, written once.
//!
//! Imports run one way, from the top: [`configured`] (the configured algorithm) → the
//! algorithms (`cl` → `ippo`, `ccppo_concat`, `ccppo_mf` → `shared_ppo`; `dynamic_lcf` →
//! `copo` → `meta_lcf`; `dqn` → `replay`) → what they share (`shared_ppo` → `coordination`,
//! `ppo`, `safety`; `meta_lcf` → `ppo`; all of them → `batch` → `gae`) → this file, what an
//! algorithm is, reports and fails with → [`phases`]. The tests keep to the same order: the
//! fixtures that need no algorithm are `testing`'s (compiled for tests only), those that
//! build an IPPO learner are `ippo::fixtures`, and a test that needs an algorithm above its
//! own file lives above it (the shared update's options in `ippo`, the meta-gradient check
//! in `copo`, the configured curriculum in `configured`).

pub mod batch;
pub mod ccppo_concat;
pub mod ccppo_mf;
pub mod cl;
pub mod configured;
pub mod coordination;
pub mod copo;
pub mod dqn;
pub mod dynamic_lcf;
pub mod gae;
pub mod ippo;
pub mod meta_lcf;
pub mod phases;
pub mod ppo;
pub mod replay;
pub mod safety;
pub mod shared_ppo;
#[cfg(test)]
pub(crate) mod testing;

use tch::Tensor;

use junction_common::fragment::RolloutFragment;
use junction_common::lcf::NEIGHBOUR_BUCKETS;
use junction_common::policy::Policy;
use junction_common::weights::{Decoded, WeightsError};
use junction_core::action_grid::GridError;

use phases::Phases;

/// Diagnostics of one policy update, averaged over its minibatches (DQN: over its gradient
/// steps; its TD loss is `value_loss`).
#[derive(Debug, Clone, Default)]
pub struct UpdateStats {
    pub agent_steps: usize,
    pub samples_trained: usize,
    pub policy_loss: f64,
    pub value_loss: f64,
    pub entropy: f64,
    pub approx_kl: f64,
    /// Mean analytic KL(π_start ‖ π) over the update's minibatches (with a KL penalty), and the
    /// penalty's coefficient after the update (0 without one).
    pub kl: f64,
    pub kl_coef: f64,
    pub clip_fraction: f64,
    pub explained_variance: f64,
    pub grad_norm: f64,
    /// The optimiser's step size during this update.
    pub learning_rate: f64,
    /// Mean and standard deviation of the LCF angle φ, degrees, after the update: the fixed φ
    /// (0 and 0 without coordination: φ = 0 is IPPO), CoPO's learned μ and σ, or the dynamic
    /// LCF's φ = f(S_N) over the batch.
    pub lcf_mean_deg: f64,
    pub lcf_std_deg: f64,
    /// Mean φ over the batch's agents with 0, 1–2, 3–5, 6+ neighbours (`None`: no such agent).
    pub lcf_phi_by_neighbours: [Option<f64>; NEIGHBOUR_BUCKETS.len()],
    /// The safety option's Lagrange multiplier after the update (0 when off).
    pub lagrange_multiplier: f64,
    /// Minibatches skipped because their loss was NaN or infinite.
    pub skipped_minibatches: usize,
    /// DQN: mean Q(s, a) of the sampled transitions (0 for PPO).
    pub q_mean: f64,
    /// DQN: the exploration rate broadcast with the new weights (0 for PPO).
    pub epsilon: f64,
    /// DQN: transitions in the replay buffer after the update (0 for PPO).
    pub replay_transitions: usize,
    /// Fragments not trained on because their actions are off the algorithm's action grid.
    pub off_grid_fragments: usize,
    /// Where the update's time went (the PPO algorithms; empty for DQN).
    pub phases: Phases,
}

#[derive(Debug, thiserror::Error)]
pub enum AlgoError {
    #[error("torch: {0}")]
    Torch(#[from] tch::TchError),
    #[error("weights: {0}")]
    Weights(#[from] WeightsError),
    #[error("an update needs at least one fragment with an alive agent")]
    EmptyBatch,
    #[error("{0}")]
    Grid(#[from] GridError),
}

/// A curriculum stage: its index and the learning agents each scene simulates in it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stage {
    pub index: usize,
    pub agents: usize,
}

/// What the training loop needs from an algorithm.
pub trait Algorithm {
    fn name(&self) -> &'static str;
    /// The policy actors run (broadcast after every update).
    fn policy(&self) -> &dyn Policy;
    /// The policy's blob for broadcasts and checkpoints, with whatever metadata actors need to
    /// run it (CoPO: its LCF distribution).
    fn policy_bytes(&self, version: u64) -> Result<Vec<u8>, WeightsError> {
        self.policy().to_bytes(version)
    }
    /// Why this algorithm cannot train on `fragment` (a drop reason of
    /// `junction_learner_fragments_dropped_total`), checked as it arrives; None: it can.
    fn refusal(&self, _fragment: &RolloutFragment) -> Option<&'static str> {
        None
    }
    /// How much of the run's budget is spent ([`RunSection::budget_spent`]; None: the run has
    /// none), told before every update, for schedules that follow it (PPO's
    /// `ppo.lr_schedule`). A resumed run restores its agent-step count, so a schedule over
    /// agent-steps continues where it was; one over `run.max_seconds` starts again.
    ///
    /// [`RunSection::budget_spent`]: junction_core::config::RunSection::budget_spent
    fn set_progress(&mut self, _budget_spent: Option<f64>) {}
    /// One update on a batch of fragments.
    fn update(&mut self, fragments: &[RolloutFragment]) -> Result<UpdateStats, AlgoError>;
    /// Everything besides the policy needed to resume exactly (critics, optimiser state).
    fn state_tensors(&self) -> Vec<(String, Tensor)>;
    /// Restores the policy from its blob and the rest from `state`.
    fn restore(&mut self, policy_blob: &[u8], state: &mut Decoded) -> Result<(), WeightsError>;
    /// The stage once `agent_steps` agent-steps have been consumed, in a scenario of
    /// `scenario_agents` agents. It depends on nothing else, so a run resumed from a checkpoint
    /// (which restores the count) continues in its stage. Without a curriculum: stage 0 with
    /// every agent, whatever the count.
    fn stage(&self, _agent_steps: u64, scenario_agents: usize) -> Stage {
        Stage {
            index: 0,
            agents: scenario_agents,
        }
    }
}
