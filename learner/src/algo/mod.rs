//! Learning algorithms, one file each; the pieces they share (GAE, batching, PPO loss terms)
//! live beside them, written once.

pub mod batch;
pub mod ccppo_concat;
pub mod ccppo_mf;
pub mod cl;
pub mod dqn;
pub mod gae;
pub mod ippo;
pub mod ppo;
pub mod replay;
pub mod safety;
pub mod shared_ppo;

use tch::{Device, Tensor};

use junction_common::config::{AlgoKind, RunConfig};
use junction_common::fragment::RolloutFragment;
use junction_common::policy::Policy;
use junction_common::q_policy::GridError;
use junction_common::spec::ACTION_DIM;
use junction_common::weights::{Decoded, WeightsError};

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
    pub clip_fraction: f64,
    pub explained_variance: f64,
    pub grad_norm: f64,
    /// The optimiser's step size during this update.
    pub learning_rate: f64,
    /// Mean and standard deviation of the LCF angle φ over the batch, degrees (0 and 0 for
    /// methods without coordination: φ = 0 is IPPO).
    pub lcf_mean_deg: f64,
    pub lcf_std_deg: f64,
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

/// The configured algorithm (`learner.algo`) for the run's observation size, on `device`.
pub fn build(config: &RunConfig, device: Device) -> Result<Box<dyn Algorithm + Send>, AlgoError> {
    let (ppo, obs_dim, seed) = (&config.ppo, config.scenario.obs_dim(), config.run.seed);
    let (lcf, safety) = (&config.lcf, &config.safety);
    let ippo = || {
        ippo::Ippo::new(ppo, obs_dim, ACTION_DIM, device, seed)
            .with_coordination(lcf)
            .with_safety(safety)
    };
    Ok(match config.learner.algo {
        AlgoKind::Ippo => Box::new(ippo()),
        AlgoKind::Cl => Box::new(cl::Cl::new(ippo(), cl::Curriculum::new(&config.curriculum))),
        AlgoKind::CcppoMf => Box::new(
            ccppo_mf::CcppoMf::new(ppo, obs_dim, ACTION_DIM, device, seed)
                .with_coordination(lcf)
                .with_safety(safety),
        ),
        AlgoKind::CcppoConcat => Box::new(
            ccppo_concat::CcppoConcat::new(
                ppo,
                config.ccppo.neighbours,
                obs_dim,
                ACTION_DIM,
                device,
                seed,
            )
            .with_coordination(lcf)
            .with_safety(safety),
        ),
        AlgoKind::Dqn => {
            Box::new(dqn::Dqn::new(&config.dqn, obs_dim, device, seed)?.with_coordination(lcf))
        }
    })
}
