//! Bytes in a shared-memory sample → `shm_layout::decode` (magic, version, header sizes,
//! truncation, reserved bytes, then `RolloutFragment::validate`). Whatever the bytes, this
//! must not panic; what it accepts must be safe to train on and encode back to the very same
//! bytes. Each input is tried as it is, and written over a valid buffer at an offset it picks
//! (so mutations reach the checks behind the header without a seed corpus).
#![no_main]

use std::sync::LazyLock;

use libfuzzer_sys::fuzz_target;

use junction_common::fragment::RolloutFragment;
use junction_common::{lcf, shm_layout};
use junction_core::config::{LcfConfig, NeighbourhoodReward, RunConfig};
use junction_core::episode::{EpisodeStats, Outcome, SceneEpisodeStats};
use junction_core::lcf_inputs;

/// A coordination that reads every neighbour list, centred (the longer path); parsed once.
static COORDINATION: LazyLock<LcfConfig> = LazyLock::new(|| LcfConfig {
    neighbourhood_reward: NeighbourhoodReward::Centred,
    ..RunConfig::default().lcf
});

/// 3 steps × 2 slots: slot 0's agent finishes at step 1 and a new one takes the slot.
static VALID: LazyLock<Vec<u8>> = LazyLock::new(|| {
    let (steps, agents, obs_dim, action_dim) = (3, 2, 4, 2);
    let cells = steps * agents;
    let fragment = RolloutFragment {
        actor_id: "actor-1".into(),
        sequence: 7,
        behaviour_version: 3,
        scenario: "intersection".into(),
        steps,
        agents,
        obs_dim,
        action_dim,
        obs: (0..cells * obs_dim).map(|i| i as f32 / 100.0).collect(),
        actions: (0..cells * action_dim).map(|i| i as f32 / 8.0 - 0.5).collect(),
        log_probs: (0..cells).map(|i| -(i as f32)).collect(),
        rewards: vec![0.5, 1.0, 10.0, 1.5, 0.25, 2.0],
        costs: vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        dones: vec![false, false, true, false, false, false],
        alive: vec![true; cells],
        bootstrap_obs: vec![0.1; agents * obs_dim],
        neighbour_offsets: vec![0, 1, 2, 3, 4, 4, 4],
        neighbour_ids: vec![1, 0, 1, 0],
        lcf_features: (0..cells * lcf_inputs::FEATURES).map(|i| i as f32 / 40.0).collect(),
        episodes: vec![EpisodeStats {
            outcome: Outcome::Success,
            length: 2,
            total_reward: 10.5,
            mean_abs_accel: 0.7,
            max_abs_accel: 1.9,
            collisions: 0,
            energy_kj: 12.5,
            total_cost: 0.125,
        }],
        human_episodes: Vec::new(),
        scene_episodes: vec![SceneEpisodeStats {
            steps: 1000,
            successes: 120,
            crashes: 70,
            out_of_road: 9,
            timeouts: 1,
        }],
        sim_seconds: 0.3,
    };
    shm_layout::encode(&fragment).expect("a valid fragment encodes")
});

fn check(bytes: &[u8]) {
    for dims in [None, Some((4, 2)), Some((91, 2))] {
        match shm_layout::decode(bytes, dims) {
            Ok(fragment) => {
                assert!(fragment.agent_steps() <= fragment.steps * fragment.agents);
                for slot in 0..fragment.agents {
                    let _ = fragment.needs_bootstrap(slot);
                }
                // Neighbour lists in bounds, neighbours real slots: the learner indexes with them.
                let rewards = lcf::coordinated_rewards(&fragment, 0.7, &COORDINATION);
                assert_eq!(rewards.len(), fragment.steps * fragment.agents);
                let again = shm_layout::encode(&fragment).expect("an accepted fragment encodes");
                assert_eq!(again, bytes, "accepted bytes must encode back unchanged");
            }
            Err(e) => {
                let _ = (e.reason(), e.to_string());
            }
        }
    }
}

fuzz_target!(|data: &[u8]| {
    check(data);
    if let [high, low, patch @ ..] = data {
        let mut bytes = VALID.clone();
        let at = usize::from(u16::from_be_bytes([*high, *low])) % bytes.len();
        let end = (at + patch.len()).min(bytes.len());
        bytes[at..end].copy_from_slice(&patch[..end - at]);
        check(&bytes);
    }
});
