//! Bytes from an actor → protobuf `RolloutFragment` → `RolloutFragment::from_proto` (version,
//! shapes, finiteness, flags, slot invariants). Whatever the bytes, this must not panic, and
//! what validation lets through must be safe for everything the learner does with it.
#![no_main]

use std::sync::LazyLock;

use libfuzzer_sys::fuzz_target;
use prost::Message;

use junction_core::config::{LcfConfig, NeighbourhoodReward, RunConfig};
use junction_common::fragment::RolloutFragment;
use junction_common::{lcf, proto};

/// A coordination that reads every neighbour list, centred (the longer path); parsed once.
static COORDINATION: LazyLock<LcfConfig> = LazyLock::new(|| LcfConfig {
    neighbourhood_reward: NeighbourhoodReward::Centred,
    ..RunConfig::default().lcf
});

fuzz_target!(|data: &[u8]| {
    let Ok(message) = proto::RolloutFragment::decode(data) else {
        return;
    };
    let own_dims = Some((message.obs_dim as usize, message.action_dim as usize));
    for dims in [None, own_dims, Some((91, 2))] {
        let Ok(fragment) = RolloutFragment::from_proto(message.clone(), dims) else {
            continue;
        };
        assert!(fragment.agent_steps() <= fragment.steps * fragment.agents);
        for slot in 0..fragment.agents {
            let _ = fragment.needs_bootstrap(slot);
        }
        // Every neighbour list is in bounds and every neighbour a slot (the learner indexes
        // rewards and observations with them).
        let rewards = lcf::coordinated_rewards(&fragment, 0.7, &COORDINATION);
        assert_eq!(rewards.len(), fragment.steps * fragment.agents);
        // A valid fragment survives the trip back to the wire unchanged.
        let again = RolloutFragment::from_proto(fragment.clone().into_proto(), dims)
            .expect("a valid fragment validates again");
        assert_eq!(again, fragment);
    }
});
