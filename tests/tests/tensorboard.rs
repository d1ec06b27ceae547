//! The run directory's TensorBoard event files, read back with TensorBoard's own reader (PyPI
//! `tensorboard` in the venv, installed by `scripts/setup.sh --test`): readable while the run
//! trains, and at its end holding exactly the values of `progress.jsonl` under the tags
//! researchers know from SB3 (`rollout/`, `train/`, `time/`), one point per progress line at
//! its agent-steps.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::process::Command;
use std::time::Duration;

use junction_tests::{QUICK_RUN, TempDir, start_actor, start_learner, wait_until, workspace_root};
use serde_json::Value;

/// Every scalar, and where its value is in a progress line.
const TAGS: &[(&str, &str)] = &[
    ("time/agent_steps_per_s", "/agent_steps_per_s"),
    ("rollout/success_rate", "/window/success_rate"),
    ("rollout/crash_rate", "/window/crash_rate"),
    ("rollout/out_of_road_rate", "/window/out_of_road_rate"),
    ("rollout/timeout_rate", "/window/timeout_rate"),
    ("rollout/ep_rew_mean", "/window/mean_reward"),
    ("rollout/ep_rew_max", "/window/max_reward"),
    ("rollout/ep_len_mean", "/window/mean_length"),
    ("rollout/ep_len_max", "/window/max_length"),
    ("rollout/collisions_per_s", "/window/collisions_per_s"),
    (
        "rollout/success_rate_metadrive",
        "/scene_window/success_rate",
    ),
    ("rollout/crash_rate_metadrive", "/scene_window/crash_rate"),
    (
        "rollout/out_of_road_rate_metadrive",
        "/scene_window/out_of_road_rate",
    ),
    (
        "rollout/timeout_rate_metadrive",
        "/scene_window/timeout_rate",
    ),
    ("train/policy_loss", "/update/policy_loss"),
    ("train/value_loss", "/update/value_loss"),
    ("train/entropy", "/update/entropy"),
    ("train/approx_kl", "/update/approx_kl"),
    ("train/clip_fraction", "/update/clip_fraction"),
    ("train/explained_variance", "/update/explained_variance"),
    ("train/grad_norm", "/update/grad_norm"),
    ("train/learning_rate", "/update/learning_rate"),
    ("train/kl", "/update/kl"),
    ("train/kl_coef", "/update/kl_coef"),
    ("train/lagrange_multiplier", "/update/lagrange_multiplier"),
    ("train/policy_lag_mean", "/update/lag_mean"),
    ("train/policy_lag_max", "/update/lag_max"),
    ("lcf/phi_mean_deg", "/lcf/mean_deg"),
    ("lcf/phi_std_deg", "/lcf/std_deg"),
    ("lcf/phi_deg_neighbours_0", "/lcf/phi_deg_by_neighbours/0"),
    (
        "lcf/phi_deg_neighbours_1-2",
        "/lcf/phi_deg_by_neighbours/1-2",
    ),
    (
        "lcf/phi_deg_neighbours_3-5",
        "/lcf/phi_deg_by_neighbours/3-5",
    ),
    ("lcf/phi_deg_neighbours_6+", "/lcf/phi_deg_by_neighbours/6+"),
];

/// `{tag: [(step, wall_time, value)]}` as TensorBoard reads the event files in `run_dir`.
fn read_back(run_dir: &Path) -> BTreeMap<String, Vec<(u64, f64, f64)>> {
    let python = workspace_root().join(".venv/bin/python");
    let script = workspace_root().join("tests/scripts/read_tensorboard.py");
    let out = Command::new(&python)
        .arg(&script)
        .arg(run_dir)
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "cannot run {} ({e}); run scripts/setup.sh --test",
                python.display()
            )
        });
    assert!(
        out.status.success(),
        "TensorBoard's reader failed (is tensorboard in the venv? scripts/setup.sh --test):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let parsed: BTreeMap<String, Vec<(u64, f64, f64)>> =
        serde_json::from_slice(&out.stdout).expect("the reader prints JSON");
    parsed
}

fn progress_lines(run_dir: &Path) -> Vec<Value> {
    std::fs::read_to_string(run_dir.join("progress.jsonl"))
        .unwrap_or_default()
        .lines()
        .map(|l| serde_json::from_str(l).expect("a progress line is JSON"))
        .collect()
}

#[test]
fn tensorboard_reads_the_progress_lines_back_while_and_after_training() {
    let dir = TempDir::new("tensorboard");
    let run_dir = dir.path().join("run");
    // Scene episodes of 100 steps, so MetaDrive's rates exist within seconds; the KL penalty
    // and the Lagrangian, so their scalars are written too.
    let flags = [
        &[
            "--scenario",
            "tiny-straight",
            "--max-seconds",
            "120",
            "--set",
            "scenario.horizon=100",
            "--set",
            "ppo.kl_coef=0.2",
            "--set",
            "safety.mode=\"lagrangian\"",
        ],
        QUICK_RUN,
    ]
    .concat();
    let (mut learner, endpoints) = start_learner(&run_dir, dir.path(), &flags);
    let actor = start_actor(&endpoints, dir.path(), "actor", &["--scenes", "4"]);

    // While it trains: TensorBoard already sees the updates written so far.
    let trained = wait_until(Duration::from_secs(60), || {
        progress_lines(&run_dir).iter().any(|l| {
            l["update"].is_object() && l["scene_window"]["scene_episodes"].as_u64() > Some(0)
        })
    });
    assert!(
        trained,
        "no update and scene episode within 60 s\n{}\n{}",
        learner.log_tail(30),
        actor.log_tail(20)
    );
    assert!(
        learner.try_exit().is_none(),
        "the run ended too early to be read while it trains"
    );
    let live = read_back(&run_dir);
    assert!(
        live.get("train/approx_kl")
            .is_some_and(|points| !points.is_empty()),
        "TensorBoard sees no update while the run trains: {:?}",
        live.keys().collect::<Vec<_>>()
    );

    // A few more progress lines, then a clean stop (SIGTERM: a final line and checkpoint).
    let seen = progress_lines(&run_dir).len();
    assert!(
        wait_until(Duration::from_secs(30), || progress_lines(&run_dir).len()
            >= seen + 2),
        "no progress lines after the first read\n{}",
        learner.log_tail(30)
    );
    learner.signal(libc::SIGTERM);
    let status = learner.wait_exit(Duration::from_secs(60));
    assert!(
        status.is_some_and(|s| s.success()),
        "learner did not stop cleanly: {status:?}\n{}",
        learner.log_tail(30)
    );
    let events: Vec<_> = std::fs::read_dir(&run_dir)
        .expect("run directory")
        .flatten()
        .filter(|e| {
            e.file_name()
                .to_string_lossy()
                .starts_with("events.out.tfevents.")
        })
        .collect();
    assert_eq!(events.len(), 1, "one event file per learner process");

    let lines = progress_lines(&run_dir);
    let mut expected: BTreeMap<String, Vec<(u64, f64, f64)>> = BTreeMap::new();
    for line in &lines {
        let step = line["agent_steps"].as_u64().expect("agent_steps");
        let wall = line["unix_s"].as_f64().expect("unix_s");
        for (tag, pointer) in TAGS {
            let section_written = match pointer.split('/').nth(1) {
                Some("window") => line["window"]["episodes"].as_u64() > Some(0),
                Some("scene_window") => line["scene_window"]["scene_episodes"].as_u64() > Some(0),
                _ => true,
            };
            if let (true, Some(value)) = (section_written, line.pointer(pointer)) {
                let value = value
                    .as_f64()
                    .unwrap_or_else(|| panic!("{pointer}: {value}"));
                // Event files hold 32-bit floats.
                let stored = f64::from(value as f32);
                expected
                    .entry(tag.to_string())
                    .or_default()
                    .push((step, wall, stored));
            }
        }
    }
    let got = read_back(&run_dir);
    let (got_tags, expected_tags): (BTreeSet<&String>, BTreeSet<&String>) =
        (got.keys().collect(), expected.keys().collect());
    assert_eq!(
        got_tags, expected_tags,
        "the scalars written are those of the progress lines"
    );
    assert_eq!(
        expected_tags.len(),
        TAGS.len(),
        "every tag has a value in this run (IPPO's fixed φ fills every neighbour bucket)"
    );
    for (tag, want) in &expected {
        let have = &got[tag];
        assert_eq!(have.len(), want.len(), "{tag}: one point per progress line");
        for (h, w) in have.iter().zip(want) {
            assert_eq!((h.0, h.2), (w.0, w.2), "{tag}: (step, value)");
            assert!(
                (h.1 - w.1).abs() < 1e-6,
                "{tag}: wall time {} vs {}",
                h.1,
                w.1
            );
        }
    }
    let updates = &got["train/approx_kl"];
    assert!(
        updates.windows(2).all(|w| w[0].0 <= w[1].0) && updates.last().is_some_and(|p| p.0 > 0),
        "steps are the agent-steps consumed, rising: {updates:?}"
    );
}
