//! Writes the small seed inputs of the fuzz targets (fuzz/README.md):
//!   cargo run --release -p junction-common --example fuzz_seeds -- fuzz/seeds
//! `fragment/`: encoded `RolloutFragment`s (valid ones of two shapes, one of another protocol
//! version); `weights/`: policy blobs as the learner broadcasts them.

use std::path::PathBuf;

use prost::Message;

use junction_common::fragment::RolloutFragment;
use junction_common::policy::GaussianPolicy;
use junction_core::episode::{EpisodeStats, Outcome, SceneEpisodeStats};
use junction_core::lcf_inputs;

/// `steps` × `agents` of `obs_dim` observations: slot 0 finishes at step 0 and is refilled,
/// every slot lists the next one as its neighbour, one finished episode.
fn fragment(steps: usize, agents: usize, obs_dim: usize) -> RolloutFragment {
    let cells = steps * agents;
    let mut dones = vec![false; cells];
    dones[0] = true;
    let mut neighbour_offsets = vec![0];
    let mut neighbour_ids = Vec::new();
    for cell in 0..cells {
        if agents > 1 {
            neighbour_ids.push(((cell % agents + 1) % agents) as u32);
        }
        neighbour_offsets.push(neighbour_ids.len() as u32);
    }
    RolloutFragment {
        actor_id: "actor-1".into(),
        sequence: 3,
        behaviour_version: 2,
        scenario: "intersection".into(),
        steps,
        agents,
        obs_dim,
        action_dim: 2,
        obs: (0..cells * obs_dim)
            .map(|i| (i % 10) as f32 / 10.0)
            .collect(),
        actions: (0..cells * 2).map(|i| (i % 3) as f32 - 1.0).collect(),
        log_probs: vec![-1.25; cells],
        rewards: (0..cells).map(|i| i as f32 * 0.5).collect(),
        costs: vec![0.0; cells],
        dones,
        alive: vec![true; cells],
        bootstrap_obs: vec![0.25; agents * obs_dim],
        neighbour_offsets,
        neighbour_ids,
        lcf_features: vec![0.5; cells * lcf_inputs::FEATURES],
        episodes: vec![EpisodeStats {
            outcome: Outcome::Success,
            length: 12,
            total_reward: 3.5,
            mean_abs_accel: 0.5,
            max_abs_accel: 1.5,
            collisions: 0,
            energy_kj: 2.0,
            total_cost: 0.02,
        }],
        human_episodes: Vec::new(),
        scene_episodes: vec![SceneEpisodeStats {
            steps: 1000,
            successes: 50,
            crashes: 20,
            out_of_road: 3,
            timeouts: 1,
        }],
        sim_seconds: steps as f32 * 0.1,
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "fuzz/seeds".into()),
    );
    let fragments = out.join("fragment");
    let weights = out.join("weights");
    std::fs::create_dir_all(&fragments)?;
    std::fs::create_dir_all(&weights)?;
    let small = fragment(3, 2, 4).into_proto();
    let mut other_version = small.clone();
    other_version.protocol_version += 1;
    for (name, message) in [
        ("small.pb", small),
        ("run-dims.pb", fragment(2, 3, 91).into_proto()),
        ("other-version.pb", other_version),
    ] {
        std::fs::write(fragments.join(name), message.encode_to_vec())?;
    }
    tch::manual_seed(1);
    for (name, obs_dim, hidden) in [("tiny.st", 4, vec![3]), ("two-layers.st", 6, vec![4, 3])] {
        let policy = GaussianPolicy::new(tch::Device::Cpu, obs_dim, 2, &hidden, -0.5);
        std::fs::write(weights.join(name), policy.to_bytes(7)?)?;
    }
    println!("seeds written to {}", out.display());
    Ok(())
}
