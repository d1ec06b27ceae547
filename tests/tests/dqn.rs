//! DQN end to end: a real learner (`learner.algo = "dqn"`) and actor on the tiny scenario. The
//! actor must act with the broadcast Q-policy (no flag tells it to), the learner must fill its
//! replay buffer, train and anneal ε, drop nothing as off the grid, and checkpoint a Q-policy
//! that `actor render` drives greedily. A learner resumed from that checkpoint continues with
//! the checkpointed replay buffer and ε schedule.

use std::time::{Duration, Instant};

use junction_common::weights::Decoded;
use junction_tests::{
    TempDir, bin, metric_sum, scrape, start_actor_with_metrics, start_learner, wait_until,
};

const UPDATES: &str = "junction_learner_updates_total";
const REPLAY: &str = "junction_learner_replay_transitions";
const EPSILON: &str = "junction_learner_exploration_epsilon";
const SAMPLES: &str = "junction_learner_samples_trained_total";
const OFF_GRID: &str = "junction_learner_fragments_dropped_total{reason=\"off_grid\"}";
const ACTOR_VERSION: &str = "junction_actor_policy_version";
/// The whole test, processes' start and shutdown included.
const BUDGET: Duration = Duration::from_secs(90);

/// The newest checkpoint directory of a run.
fn newest_checkpoint(run_dir: &std::path::Path) -> std::path::PathBuf {
    let mut checkpoints: Vec<_> = std::fs::read_dir(run_dir.join("checkpoints"))
        .expect("checkpoints directory")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("meta.json").exists())
        .collect();
    checkpoints.sort();
    checkpoints.pop().expect("a complete checkpoint")
}

#[test]
fn dqn_trains_checkpoints_a_greedy_q_policy_and_resumes_with_its_replay() {
    let started = Instant::now();
    let left = || BUDGET.saturating_sub(started.elapsed());
    let dir = TempDir::new("dqn");
    let run_dir = dir.path().join("run");
    let settings = [
        "--scenario",
        "tiny-straight",
        "--max-seconds",
        "120",
        "--set",
        "learner.algo=dqn",
        "--set",
        "rollout.fragment_length=50",
        "--set",
        "dqn.train_batch_env_steps=100",
        "--set",
        "dqn.learning_starts=200",
        "--set",
        "dqn.epsilon_decay_agent_steps=5000",
        "--set",
        "dqn.checkpoint_replay=true",
        "--set",
        "run.checkpoint_every_updates=0",
    ];
    let (mut learner, endpoints) = start_learner(&run_dir, dir.path(), &settings);
    let (mut actor, actor_metrics) = start_actor_with_metrics(&endpoints, dir.path());

    let trained = wait_until(left().saturating_sub(Duration::from_secs(40)), || {
        let m = scrape(&endpoints.metrics);
        metric_sum(&m, UPDATES) >= 6.0 && metric_sum(&m, SAMPLES) > 0.0
    });
    let m = scrape(&endpoints.metrics);
    assert!(
        trained,
        "the DQN learner did not train: {m:?}\n{}\n{}",
        learner.log_tail(30),
        actor.log_tail(30)
    );
    let (replay, epsilon) = (metric_sum(&m, REPLAY), metric_sum(&m, EPSILON));
    assert!(replay >= 600.0, "replay buffer of {replay} transitions");
    assert!(
        (0.01..1.0).contains(&epsilon),
        "ε = {epsilon} should be annealing"
    );
    assert_eq!(m.get(OFF_GRID), Some(&0.0), "the actor acts on the grid");
    let actor_version = metric_sum(&scrape(&actor_metrics), ACTOR_VERSION);
    assert!(
        actor_version >= 1.0,
        "the actor never switched to a Q-policy"
    );

    learner.signal(libc::SIGTERM);
    let status = learner.wait_exit(Duration::from_secs(10));
    assert!(
        status.is_some_and(|s| s.success()),
        "learner did not stop cleanly: {status:?}\n{}",
        learner.log_tail(30)
    );
    actor.stop(Duration::from_secs(5));
    let checkpoint = newest_checkpoint(&run_dir);
    let blob = std::fs::read(checkpoint.join("policy.safetensors")).expect("policy blob");
    let meta = Decoded::decode(&blob).expect("a valid blob").metadata;
    assert_eq!(meta.get("policy").map(String::as_str), Some("q"));
    let stopped_epsilon: f64 = meta["epsilon"].parse().expect("ε in the blob");
    assert!(stopped_epsilon <= epsilon);

    // `actor render` drives the Q-policy's greedy actions: two replays are identical although
    // the blob's ε would make actors explore. Without --scenario it draws the scenario the
    // checkpoint was trained on.
    let render = |name: &str| {
        let out = dir.path().join(name);
        let status = std::process::Command::new(bin("actor"))
            .args(["render", "--steps", "30", "--size", "64"])
            .arg("--checkpoint")
            .arg(&run_dir)
            .arg("--out")
            .arg(&out)
            .output()
            .expect("actor render runs");
        assert!(
            status.status.success(),
            "actor render failed: {}",
            String::from_utf8_lossy(&status.stderr)
        );
        let report: serde_json::Value =
            serde_json::from_slice(&status.stdout).expect("render prints one JSON line");
        assert_eq!(report["scenario"], "tiny-straight", "{report}");
        std::fs::read(out).expect("the GIF")
    };
    assert_eq!(
        render("a.gif"),
        render("b.gif"),
        "a replay is deterministic"
    );

    // The resumed learner keeps its buffer: its first update adds to what was checkpointed.
    let resumed_logs = dir.path().join("resumed");
    std::fs::create_dir_all(&resumed_logs).expect("create the resumed run's log directory");
    let resume_dir = run_dir.display().to_string();
    let (mut resumed, resumed_endpoints) =
        start_learner(&run_dir, &resumed_logs, &["--resume", &resume_dir]);
    let (mut actor, _) = start_actor_with_metrics(&resumed_endpoints, &resumed_logs);
    let updated = wait_until(left(), || {
        metric_sum(&scrape(&resumed_endpoints.metrics), UPDATES) >= 1.0
    });
    let m = scrape(&resumed_endpoints.metrics);
    assert!(
        updated,
        "the resumed learner did not update: {m:?}\n{}",
        resumed.log_tail(30)
    );
    assert!(
        metric_sum(&m, REPLAY) > replay,
        "the resumed buffer holds {} transitions, the stopped one held at least {replay}",
        metric_sum(&m, REPLAY)
    );
    assert!(
        metric_sum(&m, EPSILON) <= stopped_epsilon,
        "ε restarted instead of continuing its schedule"
    );
    actor.stop(Duration::from_secs(5));
    resumed.stop(Duration::from_secs(5));
    assert!(
        started.elapsed() <= BUDGET,
        "the test took {:?}, over its {BUDGET:?} budget",
        started.elapsed()
    );
}
