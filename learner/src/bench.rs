//! `learner bench`: the training update alone, timed on synthetic fragments of the run's shape
//! (random observations, actions and log-probabilities from the current policy, random
//! rewards), so the figure isolates the optimiser from simulation and transport.

use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use junction_common::fragment::RolloutFragment;
use junction_core::config::{AlgoKind, RunConfig};
use junction_core::lcf_inputs;
use junction_core::spec::ACTION_DIM;

use crate::algo::phases::Phases;
use crate::algo::{AlgoError, Algorithm};

#[derive(Debug, serde::Serialize)]
pub struct BenchReport {
    pub bench: &'static str,
    pub algo: &'static str,
    pub device: String,
    pub updates: usize,
    pub agent_steps_per_update: usize,
    /// Gradient passes over each agent-step: PPO's epochs, DQN's replay ratio.
    pub epochs: f64,
    pub seconds: f64,
    /// Agent-steps through gradient steps per second (each counted once per epoch).
    pub samples_per_s: f64,
    /// Agent-steps of rollout consumed per second of updating.
    pub agent_steps_per_s: f64,
    /// Where an update's time went: seconds per update by phase, in the update's order (the
    /// PPO algorithms; with `learner.split_update` the value part's phases run on their own
    /// thread beside the policy's, so the phases add up to more than the update).
    pub phases_s_per_update: Vec<PhaseSeconds>,
}

#[derive(Debug, serde::Serialize)]
pub struct PhaseSeconds {
    pub phase: &'static str,
    pub seconds: f64,
}

/// Neighbours every synthetic agent lists (the next slots, wrapping round): a stand-in so the
/// centralised critics pay for building their inputs, not a measured count.
pub const SYNTHETIC_NEIGHBOURS: usize = 8;

/// One training batch: enough fragments of every agent alive for the algorithm's train batch
/// (`ppo.train_batch_env_steps`, or `dqn.train_batch_env_steps` for DQN), acted by its policy
/// (on the DQN's action grid, ε-greedily).
pub fn synthetic_batch(
    config: &RunConfig,
    algorithm: &dyn Algorithm,
    seed: u64,
) -> Result<Vec<RolloutFragment>, AlgoError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (steps, agents) = (
        config.rollout.fragment_length,
        config.scenario.agent_count(),
    );
    let obs_dim = config.policy_obs_dim();
    let cells = steps * agents;
    let fragments = config.train_batch_env_steps().div_ceil(steps);
    let (neighbour_offsets, neighbour_ids) = ring_neighbours(steps, agents, SYNTHETIC_NEIGHBOURS);
    (0..fragments)
        .map(|_| {
            let obs: Vec<f32> = (0..cells * obs_dim).map(|_| rng.r#gen::<f32>()).collect();
            let (actions, log_probs) = algorithm.policy().sample(&obs, &mut rng)?;
            Ok(RolloutFragment {
                scenario: config.scenario.name.clone(),
                steps,
                agents,
                obs_dim,
                action_dim: ACTION_DIM,
                obs,
                actions,
                log_probs,
                rewards: (0..cells).map(|_| rng.gen_range(-1.0..2.0)).collect(),
                costs: vec![0.0; cells],
                dones: vec![false; cells],
                alive: vec![true; cells],
                bootstrap_obs: (0..agents * obs_dim).map(|_| rng.r#gen::<f32>()).collect(),
                neighbour_offsets: neighbour_offsets.clone(),
                neighbour_ids: neighbour_ids.clone(),
                lcf_features: vec![0.0; cells * lcf_inputs::FEATURES],
                ..RolloutFragment::default()
            })
        })
        .collect()
}

/// Neighbour lists (CSR offsets and ids) of `steps` × `agents` cells in which every agent sees
/// the next `per_agent` slots round the ring (at most every other agent): synthetic fragments
/// with a neighbourhood to build critic inputs and coordination from.
pub fn ring_neighbours(steps: usize, agents: usize, per_agent: usize) -> (Vec<u32>, Vec<u32>) {
    let cells = steps * agents;
    let per_agent = per_agent.min(agents.saturating_sub(1));
    let offsets = (0..=cells).map(|c| (c * per_agent) as u32).collect();
    let ids = (0..cells)
        .flat_map(|cell| (1..=per_agent).map(move |d| ((cell % agents + d) % agents) as u32))
        .collect();
    (offsets, ids)
}

/// Times `updates` updates of `algorithm` on one synthetic batch.
pub fn run(
    config: &RunConfig,
    algorithm: &mut dyn Algorithm,
    device: String,
    updates: usize,
) -> Result<BenchReport, AlgoError> {
    let batch = synthetic_batch(config, algorithm, config.run.seed)?;
    // One untimed update: allocations and lazy initialisation.
    algorithm.update(&batch)?;
    let started = Instant::now();
    let (mut samples, mut agent_steps) = (0usize, 0usize);
    let mut phases = Phases::default();
    for _ in 0..updates {
        let stats = algorithm.update(&batch)?;
        samples += stats.samples_trained;
        agent_steps += stats.agent_steps;
        phases.merge(&stats.phases);
    }
    let seconds = started.elapsed().as_secs_f64();
    Ok(BenchReport {
        bench: "learner_update",
        algo: algorithm.name(),
        device,
        updates,
        agent_steps_per_update: agent_steps / updates.max(1),
        epochs: match config.learner.algo {
            AlgoKind::Dqn => f64::from(config.dqn.replay_ratio),
            _ => config.ppo.epochs as f64,
        },
        seconds,
        samples_per_s: samples as f64 / seconds,
        agent_steps_per_s: agent_steps as f64 / seconds,
        phases_s_per_update: phases
            .0
            .into_iter()
            .map(|(phase, total)| PhaseSeconds {
                phase,
                seconds: total / updates.max(1) as f64,
            })
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::ippo::fixtures::ippo;

    #[test]
    fn the_synthetic_batch_is_a_valid_training_batch_of_the_run_shape() {
        let mut config = RunConfig::default();
        config.ppo.hidden = vec![8];
        config.scenario.agents = 3;
        config.rollout.fragment_length = 10;
        config.ppo.train_batch_env_steps = 25;
        let ippo = ippo(&config, config.scenario.obs_dim(), 2);
        let batch = synthetic_batch(&config, &ippo, 1).unwrap();
        assert_eq!(batch.len(), 3, "25 env steps need 3 fragments of 10");
        for fragment in batch {
            let dims = Some((config.scenario.obs_dim(), ACTION_DIM));
            let proto = fragment.clone().into_proto();
            assert_eq!(RolloutFragment::from_proto(proto, dims).unwrap(), fragment);
        }
    }

    #[test]
    fn dqn_benches_its_own_batch_size_on_its_grid_and_trains() {
        let mut config = RunConfig::default();
        config.learner.algo = AlgoKind::Dqn;
        config.dqn.hidden = vec![8];
        config.dqn.batch_size = 16;
        config.dqn.learning_starts = 1;
        config.scenario.agents = 2;
        config.rollout.fragment_length = 10;
        config.dqn.train_batch_env_steps = 15;
        let mut dqn = crate::algo::configured::build(&config, tch::Device::Cpu).unwrap();
        let batch = synthetic_batch(&config, dqn.as_ref(), 1).unwrap();
        assert_eq!(batch.len(), 2, "15 env steps need 2 fragments of 10");
        let stats = dqn.update(&batch).unwrap();
        assert_eq!(stats.off_grid_fragments, 0, "the bench acts on the grid");
        // 40 transitions × 32 / 16 = 80 gradient steps of 16.
        assert_eq!((stats.agent_steps, stats.samples_trained), (40, 1280));
        let report = run(&config, dqn.as_mut(), "Cpu".into(), 1).unwrap();
        assert_eq!((report.algo, report.epochs), ("dqn", 32.0));
        assert!(report.samples_per_s > 0.0);
    }
}
