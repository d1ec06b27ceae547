//! `learner serve --local-actors N`, the one-command local mode, with real processes: the
//! learner starts its actors over shared memory and trains, restarts an actor that dies,
//! and leaves no actor behind however it ends.

use std::time::Duration;

use junction_tests::{
    QUICK_RUN, TempDir, children_of, is_running, metric_sum, scrape, start_learner,
    unique_shm_name, wait_until,
};

fn version(metrics: &str) -> f64 {
    metric_sum(&scrape(metrics), "junction_learner_policy_version")
}

#[test]
fn local_mode_trains_restarts_a_killed_actor_and_stops_its_actors_on_exit() {
    let dir = TempDir::new("local-mode");
    let run_dir = dir.path().join("run");
    let args = [&["--local-actors", "2", "--max-seconds", "300"], QUICK_RUN].concat();
    let (mut learner, endpoints) = start_learner(&run_dir, dir.path(), &args);

    let training = wait_until(Duration::from_secs(180), || {
        let m = scrape(&endpoints.metrics);
        metric_sum(&m, "junction_learner_policy_version") >= 3.0
            && metric_sum(&m, "junction_learner_connected_actors") == 2.0
    });
    assert!(
        training,
        "no 3 versions from 2 local actors within 180 s: {:?}\n{}",
        scrape(&endpoints.metrics),
        learner.log_tail(40)
    );
    let m = scrape(&endpoints.metrics);
    assert!(
        metric_sum(
            &m,
            "junction_learner_transport_received_bytes_total{transport=\"shm\"}"
        ) > 0.0
    );
    assert_eq!(
        metric_sum(
            &m,
            "junction_learner_transport_received_bytes_total{transport=\"grpc\"}"
        ),
        0.0,
        "local actors must use shared memory"
    );
    assert_eq!(
        metric_sum(&m, "junction_learner_fragments_rejected_total"),
        0.0
    );
    let first_actors = children_of(learner.pid());
    assert_eq!(first_actors.len(), 2, "{first_actors:?}");

    // A local actor killed mid-run is restarted (and counted); training goes on.
    let killed = first_actors[0];
    // SAFETY: kill(2) on a process this test just saw as the learner's child.
    unsafe {
        libc::kill(killed as i32, libc::SIGKILL);
    }
    let before = version(&endpoints.metrics);
    let restarted = wait_until(Duration::from_secs(120), || {
        let m = scrape(&endpoints.metrics);
        let actors = children_of(learner.pid());
        metric_sum(&m, "junction_learner_local_actor_restarts_total") == 1.0
            && actors.len() == 2
            && !actors.contains(&killed)
            && metric_sum(&m, "junction_learner_connected_actors") == 2.0
            && metric_sum(&m, "junction_learner_policy_version") >= before + 2.0
    });
    assert!(
        restarted,
        "the killed actor was not replaced: {:?} children {:?}\n{}",
        scrape(&endpoints.metrics),
        children_of(learner.pid()),
        learner.log_tail(40)
    );
    assert!(learner.log().contains("local actor exited; restarting it"));
    let actors = children_of(learner.pid());

    // SIGTERM: the learner checkpoints, its actors exit, and so does it.
    learner.signal(libc::SIGTERM);
    let status = learner.wait_exit(Duration::from_secs(90));
    assert!(
        status.is_some_and(|s| s.success()),
        "learner did not exit cleanly: {status:?}\n{}",
        learner.log_tail(40)
    );
    let gone = wait_until(Duration::from_secs(10), || {
        actors
            .iter()
            .chain(&first_actors)
            .all(|&pid| !is_running(pid))
    });
    assert!(gone, "actors outlived the learner: {actors:?}");
    assert!(
        learner.log().contains("local actor exited"),
        "{}",
        learner.log_tail(40)
    );
}

#[test]
fn a_killed_learner_takes_its_local_actors_with_it_and_a_new_one_starts_cleanly() {
    let dir = TempDir::new("local-kill");
    let shm_name = unique_shm_name();
    let args = [
        &[
            "--local-actors",
            "2",
            "--max-seconds",
            "300",
            "--shm-name",
            &shm_name,
        ],
        QUICK_RUN,
    ]
    .concat();
    let (mut learner, endpoints) = start_learner(&dir.path().join("first"), dir.path(), &args);
    let connected = wait_until(Duration::from_secs(120), || {
        metric_sum(
            &scrape(&endpoints.metrics),
            "junction_learner_connected_actors",
        ) == 2.0
    });
    assert!(connected, "{}", learner.log_tail(40));
    let actors = children_of(learner.pid());
    assert_eq!(actors.len(), 2, "{actors:?}");

    learner.signal(libc::SIGKILL);
    let _ = learner.wait_exit(Duration::from_secs(10));
    let gone = wait_until(Duration::from_secs(10), || {
        actors.iter().all(|&pid| !is_running(pid))
    });
    assert!(gone, "actors outlived a killed learner: {actors:?}");

    // The dead processes' shared-memory resources are still there; a new learner with the
    // same name cleans them up and trains.
    let second_dir = dir.path().join("second-logs");
    std::fs::create_dir_all(&second_dir).expect("log dir");
    let (mut learner, endpoints) = start_learner(&dir.path().join("second"), &second_dir, &args);
    let training = wait_until(Duration::from_secs(180), || {
        version(&endpoints.metrics) >= 2.0
    });
    assert!(
        training,
        "a learner reusing a killed learner's shm name did not train\n{}",
        learner.log_tail(40)
    );
    learner.signal(libc::SIGTERM);
    assert!(
        learner
            .wait_exit(Duration::from_secs(90))
            .is_some_and(|s| s.success()),
        "{}",
        learner.log_tail(40)
    );
}

/// Local actors load whatever policy the learner broadcasts over shared memory, as gRPC actors
/// do: CoPO's (one more observation value, the LCF angle drawn from the blob's distribution)
/// and DQN's Q-policy. An actor that could not would exit and be restarted, and no fragment
/// would reach the learner.
#[test]
fn local_actors_run_copo_and_dqn_policies_over_shm() {
    let dir = TempDir::new("local-algos");
    let algos: [(&str, &[&str]); 2] = [
        ("copo", &["--set", "ppo.train_batch_env_steps=100"]),
        (
            "dqn",
            &[
                "--set",
                "dqn.train_batch_env_steps=100",
                "--set",
                "dqn.learning_starts=100",
            ],
        ),
    ];
    for (algo, settings) in algos {
        let algo_setting = format!("learner.algo=\"{algo}\"");
        let args = [
            &[
                "--local-actors",
                "1",
                "--max-seconds",
                "120",
                "--scenario",
                "tiny-straight",
                "--set",
                &algo_setting,
                "--set",
                "rollout.fragment_length=50",
                "--set",
                "run.progress_interval_s=1",
            ],
            settings,
        ]
        .concat();
        let log_dir = dir.path().join(algo);
        std::fs::create_dir_all(&log_dir).expect("log dir");
        let (mut learner, endpoints) =
            start_learner(&dir.path().join(algo).join("run"), &log_dir, &args);
        let trained = wait_until(Duration::from_secs(90), || {
            version(&endpoints.metrics) >= 3.0
        });
        let m = scrape(&endpoints.metrics);
        assert!(
            trained,
            "{algo}: no 3 versions from a local actor: {m:?}\n{}",
            learner.log_tail(40)
        );
        assert!(
            metric_sum(
                &m,
                "junction_learner_transport_received_bytes_total{transport=\"shm\"}"
            ) > 0.0
        );
        assert_eq!(
            metric_sum(&m, "junction_learner_fragments_rejected_total"),
            0.0,
            "{algo}"
        );
        assert_eq!(
            metric_sum(&m, "junction_learner_local_actor_restarts_total"),
            0.0,
            "{algo}: the local actor failed\n{}",
            learner.log_tail(40)
        );
        learner.signal(libc::SIGTERM);
        assert!(
            learner
                .wait_exit(Duration::from_secs(90))
                .is_some_and(|s| s.success()),
            "{algo}\n{}",
            learner.log_tail(40)
        );
    }
}
