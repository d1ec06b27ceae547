//! Bytes from the learner (or a checkpoint file) → the weights blob decoder → a policy.
//! Whatever the bytes, this must not panic or allocate beyond what the blob holds, and a
//! policy that decodes must run and re-encode.
#![no_main]

use libfuzzer_sys::fuzz_target;

use junction_common::policy::GaussianPolicy;
use junction_common::weights::Decoded;

fuzz_target!(|data: &[u8]| {
    if let Ok(mut decoded) = Decoded::decode(data) {
        let _ = decoded.meta::<u64>("version");
        let _ = decoded.take("policy_log_std", &[2]);
    }
    let Ok((policy, meta)) = GaussianPolicy::from_bytes(data, tch::Device::Cpu) else {
        return;
    };
    let obs = vec![0.5f32; policy.obs_dim()];
    let noise = vec![0.0f32; policy.action_dim()];
    let (actions, log_probs) = policy.act(&obs, &noise).expect("a decoded policy acts");
    assert_eq!((actions.len(), log_probs.len()), (policy.action_dim(), 1));
    let bytes = policy.to_bytes(meta.version).expect("a decoded policy encodes");
    GaussianPolicy::from_bytes(&bytes, tch::Device::Cpu).expect("and decodes again");
});
