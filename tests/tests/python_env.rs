//! The Python package's environments are the Rust simulator: the same scenario, seed and
//! actions give the same observations, rewards, costs, dones and alive masks, bit for bit,
//! through `junction.vector_env` as through `junction_sim::Scene`.

use std::process::Command;

use junction_core::config::{Layer, RunConfig};
use junction_core::scenarios;
use junction_sim::Scene;
use junction_tests::{TempDir, workspace_root};

const STEPS: usize = 400;
const SCENES: usize = 2;
const SEED: u64 = 11;
/// Small and short, with MetaDrive's horizon semantics, so the trace holds crashes,
/// arrivals, respawns and the end of a scene episode.
const OVERRIDES: &[&str] = &[
    "scenario.agents=12",
    "scenario.horizon=150",
    "scenario.after_horizon=\"finish\"",
];

/// The action of `slot` at step `t`: multiples of 1/8, exact in f32 on both sides, braking
/// one step in nine (the default car brakes hard: more and the cars never get anywhere).
fn action(t: usize, slot: usize) -> [f32; 2] {
    let steer = ((t * 7 + slot * 3) % 17) as f32 - 8.0;
    let throttle = ((t * 5 + slot) % 9) as f32 - 1.0;
    [steer / 8.0, throttle / 8.0]
}

const PYTHON_TRACE: &str = r#"
import sys
import numpy as np
import junction

out, steps, scenes, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
env = junction.vector_env("intersection", num_scenes=scenes, seed=seed,
                          agents=12, horizon=150, after_horizon="finish")
obs, info = env.reset(seed=seed)
t_idx = np.arange(steps)[:, None]
slot_idx = np.arange(env.slots)[None, :]
steer = ((t_idx * 7 + slot_idx * 3) % 17 - 8) / 8
throttle = ((t_idx * 5 + slot_idx) % 9 - 1) / 8
with open(out, "wb") as f:
    f.write(obs.tobytes()); f.write(info["alive"].tobytes())
    for t in range(steps):
        a = np.stack([steer[t], throttle[t]], axis=-1).astype(np.float32)
        a = np.broadcast_to(a, (scenes, env.slots, 2))
        obs, rewards, terminated, truncated, info = env.step(a)
        f.write(rewards.tobytes()); f.write(info["costs"].tobytes())
        f.write((terminated | truncated).tobytes())
        f.write(obs.tobytes()); f.write(info["alive"].tobytes())
"#;

fn push_f32(out: &mut Vec<u8>, values: &[f32]) {
    out.extend(values.iter().flat_map(|v| v.to_le_bytes()));
}

fn push_bool(out: &mut Vec<u8>, values: &[bool]) {
    out.extend(values.iter().map(|&b| u8::from(b)));
}

#[test]
fn python_vector_env_replays_the_rust_simulator_bit_for_bit() {
    let text = scenarios::text("intersection").unwrap();
    let layers: Vec<Layer> = std::iter::once(Layer::Scenario(&text))
        .chain(OVERRIDES.iter().map(|o| Layer::Set(o)))
        .collect();
    let config = RunConfig::from_layers(&layers).unwrap().scenario;
    let mut scenes: Vec<Scene> = (0..SCENES)
        .map(|k| Scene::new(&config, SEED + k as u64).unwrap())
        .collect();
    let slots = config.agent_count();
    // Grouped as the Python side writes them: each array over every scene, then the next.
    let mut expected = Vec::new();
    let state = |scenes: &[Scene], out: &mut Vec<u8>| {
        scenes.iter().for_each(|s| push_f32(out, s.observations()));
        scenes.iter().for_each(|s| push_bool(out, s.alive()));
    };
    state(&scenes, &mut expected);
    let mut scene_episodes = 0;
    for t in 0..STEPS {
        let actions: Vec<f32> = (0..slots).flat_map(|slot| action(t, slot)).collect();
        let results: Vec<_> = scenes
            .iter_mut()
            .map(|s| s.step(&actions).clone())
            .collect();
        scene_episodes += results.iter().filter(|r| r.scene_episode.is_some()).count();
        results
            .iter()
            .for_each(|r| push_f32(&mut expected, &r.rewards));
        results
            .iter()
            .for_each(|r| push_f32(&mut expected, &r.costs));
        results
            .iter()
            .for_each(|r| push_bool(&mut expected, &r.dones));
        state(&scenes, &mut expected);
    }
    assert!(
        scene_episodes >= SCENES,
        "the trace crosses the end of a scene episode"
    );

    let dir = TempDir::new("python-env");
    let trace = dir.path().join("trace.bin");
    let python = workspace_root().join(".venv/bin/python");
    let output = Command::new(&python)
        .args(["-c", PYTHON_TRACE])
        .arg(&trace)
        .args([STEPS.to_string(), SCENES.to_string(), SEED.to_string()])
        .output()
        .unwrap_or_else(|e| panic!("running {}: {e}", python.display()));
    assert!(
        output.status.success(),
        "the Python trace failed (is the package installed? `make test` builds it with \
         scripts/build-python.sh):\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let got = std::fs::read(&trace).unwrap();
    assert_eq!(got.len(), expected.len(), "trace sizes differ");
    let first = got.iter().zip(&expected).position(|(a, b)| a != b);
    assert_eq!(first, None, "the traces differ from byte {first:?} on");
}
