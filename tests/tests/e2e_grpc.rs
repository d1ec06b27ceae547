//! The walking skeleton end to end: a real learner and a real actor process talking gRPC on
//! loopback train, publish versions, expose metrics and shut down cleanly.

use std::time::Duration;

use junction_tests::{
    QUICK_RUN, TempDir, metric_sum, scrape, start_actor_with_metrics, start_learner, wait_until,
};

#[test]
fn learner_and_actor_train_over_grpc_and_shut_down_cleanly() {
    let dir = TempDir::new("e2e");
    let run_dir = dir.path().join("run");
    let (mut learner, endpoints) = start_learner(
        &run_dir,
        dir.path(),
        &[&["--max-seconds", "300"], QUICK_RUN].concat(),
    );
    let (mut actor, actor_metrics) = start_actor_with_metrics(&endpoints, dir.path());

    let published = wait_until(Duration::from_secs(180), || {
        let m = scrape(&endpoints.metrics);
        metric_sum(&m, "junction_learner_policy_version") >= 3.0
            && metric_sum(&m, "junction_learner_fragments_total") > 0.0
    });
    assert!(
        published,
        "no 3 policy versions within 180 s\n{}\n{}",
        learner.log_tail(30),
        actor.log_tail(30)
    );

    let m = scrape(&endpoints.metrics);
    for counter in [
        "junction_learner_agent_steps_total",
        "junction_learner_env_steps_total",
        "junction_learner_samples_trained_total",
        "junction_learner_transport_received_bytes_total",
    ] {
        assert!(
            metric_sum(&m, counter) > 0.0,
            "{counter} did not move: {m:?}"
        );
    }
    assert!(metric_sum(&m, "junction_learner_updates_total") >= 3.0);
    assert!(
        metric_sum(&m, "junction_learner_fragments_rejected_total") == 0.0,
        "valid fragments were rejected"
    );

    // The actor really runs newer weights than the initial version 0.
    let switched = wait_until(Duration::from_secs(60), || {
        let a = scrape(&actor_metrics);
        metric_sum(&a, "junction_actor_policy_version") >= 1.0
            && metric_sum(&a, "junction_actor_policy_switches_total") >= 1.0
    });
    assert!(
        switched,
        "actor never switched policy: {:?}\n{}",
        scrape(&actor_metrics),
        actor.log_tail(30)
    );
    assert!(
        metric_sum(
            &scrape(&actor_metrics),
            "junction_actor_fragments_sent_total"
        ) > 0.0
    );

    // Progress is reported every second (run.progress_interval_s) while training goes on.
    let progress_file = run_dir.join("progress.jsonl");
    let reported = wait_until(Duration::from_secs(30), || {
        std::fs::read_to_string(&progress_file).is_ok_and(|p| p.lines().count() >= 2)
    });
    assert!(reported, "fewer than 2 progress reports in 30 s");

    // SIGTERM: the learner checkpoints, tells the actor the run is over, and both exit 0.
    learner.signal(libc::SIGTERM);
    let learner_status = learner.wait_exit(Duration::from_secs(60));
    assert!(
        learner_status.is_some_and(|s| s.success()),
        "learner did not exit cleanly: {learner_status:?}\n{}",
        learner.log_tail(30)
    );
    let actor_status = actor.wait_exit(Duration::from_secs(30));
    assert!(
        actor_status.is_some_and(|s| s.success()),
        "actor did not exit cleanly: {actor_status:?}\n{}",
        actor.log_tail(30)
    );
    let checkpoints: Vec<_> = std::fs::read_dir(run_dir.join("checkpoints"))
        .expect("checkpoints directory")
        .flatten()
        .filter(|e| e.path().join("meta.json").exists())
        .collect();
    assert!(!checkpoints.is_empty(), "no checkpoint written");
    let progress = std::fs::read_to_string(&progress_file).expect("progress log");
    let last: serde_json::Value =
        serde_json::from_str(progress.lines().last().unwrap_or("")).expect("JSON progress line");
    assert!(
        last["version"].as_u64() >= Some(3),
        "the final report lacks the trained versions: {last}"
    );
}
