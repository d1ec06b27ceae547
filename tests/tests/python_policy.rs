//! The Python actors act with the broadcast policy exactly as the Rust actor does: the same
//! blob, observations and noise give the same actions and behaviour log-probabilities through
//! `junction.policy` (PyTorch) as through `junction_common::policy` (tch), with a global or a
//! state-dependent std, and CoPO's LCF distribution reads back from the blob's metadata.

use std::process::Command;

use junction_common::lcf::LcfDistribution;
use junction_common::policy::{GaussianPolicy, ObsNormalizer};
use junction_core::config::ActionStd;
use junction_tests::{TempDir, workspace_root};
use tch::Device;

const ROWS: usize = 64;
const OBS_DIM: usize = 92;

const PYTHON_ACT: &str = r#"
import sys
import numpy as np
from junction.policy import GaussianPolicy

blob, obs, noise, out = sys.argv[1:5]
policy = GaussianPolicy(open(blob, "rb").read())
obs = np.fromfile(obs, "<f4").reshape(-1, policy.obs_dim)
noise = np.fromfile(noise, "<f4").reshape(-1, policy.action_dim)
actions, log_probs = policy.act(obs, noise)
mean = policy.deterministic(obs)
with open(out, "wb") as f:
    for a in (actions, log_probs, mean):
        f.write(np.ascontiguousarray(a, "<f4").tobytes())
print(policy.version, policy.lcf.mean_deg, policy.lcf.std_deg)
"#;

fn write_f32(path: &std::path::Path, values: &[f32]) {
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn python_policy_acts_bit_for_bit_as_the_rust_actor() {
    acts_bit_for_bit(ActionStd::Global);
}

#[test]
fn python_policy_with_a_state_dependent_std_acts_bit_for_bit_as_the_rust_actor() {
    acts_bit_for_bit(ActionStd::State);
}

fn acts_bit_for_bit(action_std: ActionStd) {
    tch::manual_seed(17);
    let mut policy =
        GaussianPolicy::with_std(Device::Cpu, OBS_DIM as i64, 2, &[64, 32], -0.7, action_std);
    // A normaliser that matters: statistics of rows unlike the evaluated ones.
    let rows: Vec<f32> = (0..200 * OBS_DIM)
        .map(|i| ((i * 37 % 101) as f32 / 101.0).powi(2))
        .collect();
    let mut stats = ObsNormalizer::new(OBS_DIM);
    stats.update(&rows);
    policy.set_obs_stats(&stats);
    let lcf = LcfDistribution {
        mean_deg: 12.5,
        std_deg: 7.25,
    };
    let blob = policy.to_bytes_with_metadata(9, lcf.to_metadata()).unwrap();
    let obs: Vec<f32> = (0..ROWS * OBS_DIM)
        .map(|i| (i * 53 % 97) as f32 / 97.0)
        .collect();
    let noise: Vec<f32> = (0..ROWS * 2)
        .map(|i| ((i * 29 % 61) as f32 - 30.0) / 12.0)
        .collect();
    let (actions, log_probs) = policy.act(&obs, &noise).unwrap();
    let (mean, mean_log_probs) = policy.act(&obs, &vec![0.0; ROWS * 2]).unwrap();
    // At the mean the log-probability is −Σ log std − ln 2π: the same for every row exactly
    // when the std does not depend on the state.
    let per_state = mean_log_probs.iter().any(|&l| l != mean_log_probs[0]);
    assert_eq!(
        per_state,
        action_std == ActionStd::State,
        "{mean_log_probs:?}"
    );

    let dir = TempDir::new(&format!("python-policy-{}", action_std.label()));
    let file = |name: &str| dir.path().join(name);
    std::fs::write(file("policy.safetensors"), &blob).unwrap();
    write_f32(&file("obs.bin"), &obs);
    write_f32(&file("noise.bin"), &noise);
    let python = workspace_root().join(".venv/bin/python");
    let output = Command::new(&python)
        .args(["-c", PYTHON_ACT])
        .args(["policy.safetensors", "obs.bin", "noise.bin", "out.bin"].map(file))
        .output()
        .unwrap_or_else(|e| panic!("running {}: {e}", python.display()));
    assert!(
        output.status.success(),
        "the Python policy failed (`make test` installs the package):\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert_eq!(
        String::from_utf8_lossy(&output.stdout).trim(),
        "9 12.5 7.25"
    );
    let got: Vec<f32> = std::fs::read(file("out.bin"))
        .unwrap()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let expected: Vec<f32> = [actions, log_probs, mean].concat();
    assert_eq!(got.len(), expected.len());
    let worst = got
        .iter()
        .zip(&expected)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert_eq!(worst, 0.0, "largest difference {worst}");
}
