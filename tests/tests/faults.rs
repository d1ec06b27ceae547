//! Faults with real processes on loopback: an actor killed mid-stream, a learner killed and
//! resumed on its port while its actors wait, a learner killed in the middle of writing a
//! checkpoint, a resume under a configuration that does not fit, an actor stopped by a signal.
//! Every process is stopped when a test ends, however it ends.

use std::os::unix::process::ExitStatusExt;
use std::time::Duration;

use junction_tests::{
    Endpoints, Process, QUICK_RUN, TempDir, bin, checkpoint_versions, free_port, metric_sum,
    scrape, start_actor, start_learner, start_learner_with_env, unique_shm_name, wait_until,
    workspace_root,
};

fn gauge(endpoints: &Endpoints, name: &str) -> f64 {
    metric_sum(&scrape(&endpoints.metrics), name)
}

fn version(endpoints: &Endpoints) -> f64 {
    gauge(endpoints, "junction_learner_policy_version")
}

/// The learner's log line `resumed` names the version it continued from.
fn resumed_version(learner: &Process) -> Option<u64> {
    let log = learner.log();
    let line = log.lines().rev().find(|l| l.contains("resumed"))?;
    let rest = &line[line.find("version=")? + "version=".len()..];
    rest.split(|c: char| !c.is_ascii_digit())
        .next()?
        .parse()
        .ok()
}

#[test]
fn an_actor_killed_mid_stream_leaves_the_learner_training_with_the_other() {
    let dir = TempDir::new("fault-actor");
    let run_dir = dir.path().join("run");
    let (mut learner, endpoints) = start_learner(
        &run_dir,
        dir.path(),
        &[&["--max-seconds", "300"], QUICK_RUN].concat(),
    );
    let mut doomed = start_actor(&endpoints, dir.path(), "doomed", &[]);
    let started = wait_until(Duration::from_secs(120), || version(&endpoints) >= 2.0);
    assert!(started, "no versions\n{}", learner.log_tail(30));
    // A late joiner gets the current weights first.
    let joined_at = version(&endpoints);
    let survivor_metrics = format!("127.0.0.1:{}", free_port());
    let survivor = start_actor(
        &endpoints,
        dir.path(),
        "survivor",
        &["--metrics-addr", &survivor_metrics],
    );
    let current = wait_until(Duration::from_secs(60), || {
        metric_sum(&scrape(&survivor_metrics), "junction_actor_policy_version") >= joined_at
    });
    assert!(
        current,
        "the late actor did not start from v{joined_at}\n{}",
        survivor.log_tail(20)
    );
    let both = wait_until(Duration::from_secs(120), || {
        let m = scrape(&endpoints.metrics);
        metric_sum(&m, "junction_learner_connected_actors") == 2.0
            && metric_sum(&m, "junction_learner_policy_version") >= 2.0
    });
    assert!(
        both,
        "two actors never trained together\n{}\n{}",
        learner.log_tail(30),
        doomed.log_tail(20)
    );

    // SIGKILL: no goodbye, possibly in the middle of a fragment.
    doomed.signal(libc::SIGKILL);
    assert!(doomed.wait_exit(Duration::from_secs(10)).is_some());
    let gone = wait_until(Duration::from_secs(30), || {
        gauge(&endpoints, "junction_learner_connected_actors") == 1.0
    });
    assert!(
        gone,
        "the dead actor's stream still counts as connected\n{}",
        learner.log_tail(30)
    );
    let after_kill = version(&endpoints);
    let advanced = wait_until(Duration::from_secs(120), || {
        version(&endpoints) >= after_kill + 3.0
    });
    assert!(
        advanced,
        "no new versions with the surviving actor (stuck at {after_kill})\n{}\n{}",
        learner.log_tail(30),
        survivor.log_tail(20)
    );
    let m = scrape(&endpoints.metrics);
    // A peer that vanished is not invalid data.
    assert_eq!(
        metric_sum(&m, "junction_learner_fragments_rejected_total"),
        0.0,
        "{m:?}"
    );
    assert!(learner.try_exit().is_none(), "the learner died");
    learner.signal(libc::SIGTERM);
    assert!(
        learner
            .wait_exit(Duration::from_secs(60))
            .is_some_and(|s| s.success()),
        "{}",
        learner.log_tail(30)
    );
}

#[test]
fn a_killed_learner_resumes_on_its_port_and_its_actors_come_back() {
    let dir = TempDir::new("fault-learner");
    let run_dir = dir.path().join("run");
    let run = run_dir.display().to_string();
    let addr = format!("127.0.0.1:{}", free_port());
    let settings = [
        &["--addr", &addr, "--max-seconds", "300"],
        QUICK_RUN,
        &["--set", "run.checkpoint_every_updates=1"],
    ]
    .concat();
    let (mut learner, endpoints) = start_learner(&run_dir, dir.path(), &settings);
    let actor_metrics = format!("127.0.0.1:{}", free_port());
    let mut actor = start_actor(
        &endpoints,
        dir.path(),
        "actor",
        &[
            "--metrics-addr",
            &actor_metrics,
            "--connect-timeout",
            "120",
            "--retry-max-delay",
            "1",
        ],
    );
    let trained = wait_until(Duration::from_secs(120), || {
        version(&endpoints) >= 3.0 && checkpoint_versions(&run_dir).len() >= 2
    });
    assert!(
        trained,
        "no versions and checkpoints\n{}",
        learner.log_tail(30)
    );

    learner.signal(libc::SIGKILL);
    assert!(learner.wait_exit(Duration::from_secs(10)).is_some());
    let checkpointed = *checkpoint_versions(&run_dir).last().expect("a checkpoint");
    // The actor waits: it retries instead of exiting, and says it is disconnected.
    let waiting = wait_until(Duration::from_secs(20), || {
        metric_sum(&scrape(&actor_metrics), "junction_actor_connected") == 0.0
    });
    assert!(waiting, "the actor did not notice\n{}", actor.log_tail(20));
    std::thread::sleep(Duration::from_secs(2));
    assert!(
        actor.try_exit().is_none(),
        "the actor gave up on the learner\n{}",
        actor.log_tail(20)
    );
    assert!(actor.log().contains("learner unreachable"));

    // Same port, same run: continue from the newest checkpoint.
    let (mut resumed, endpoints) = start_learner(
        &run_dir,
        dir.path(),
        &["--resume", &run, "--addr", &addr, "--max-seconds", "300"],
    );
    assert_eq!(
        resumed_version(&resumed),
        Some(checkpointed),
        "did not resume from ckpt {checkpointed}\n{}",
        resumed.log_tail(30)
    );
    let back = wait_until(Duration::from_secs(60), || {
        let a = scrape(&actor_metrics);
        metric_sum(&a, "junction_actor_connected") == 1.0
            && metric_sum(&a, "junction_actor_reconnects_total") >= 1.0
    });
    assert!(
        back,
        "the actor did not come back\n{}\n{}",
        actor.log_tail(30),
        resumed.log_tail(30)
    );
    let first = version(&endpoints);
    assert!(
        first >= checkpointed as f64,
        "the version went back from {checkpointed} to {first}"
    );
    let advanced = wait_until(Duration::from_secs(120), || {
        version(&endpoints) >= checkpointed as f64 + 3.0
    });
    assert!(
        advanced,
        "versions did not advance after the restart\n{}\n{}",
        resumed.log_tail(30),
        actor.log_tail(30)
    );
    // The actor runs the restarted learner's weights, the same process throughout.
    let running = metric_sum(&scrape(&actor_metrics), "junction_actor_policy_version");
    assert!(running > checkpointed as f64, "actor runs v{running}");
    assert!(
        checkpoint_versions(&run_dir).last() > Some(&checkpointed),
        "no new checkpoints after the restart"
    );

    resumed.signal(libc::SIGTERM);
    assert!(
        resumed
            .wait_exit(Duration::from_secs(60))
            .is_some_and(|s| s.success())
    );
    let actor_status = actor.wait_exit(Duration::from_secs(30));
    assert!(
        actor_status.is_some_and(|s| s.success()),
        "the actor did not finish with the run: {actor_status:?}\n{}",
        actor.log_tail(20)
    );
}

#[test]
fn a_learner_killed_while_writing_a_checkpoint_resumes_from_the_previous_one() {
    let dir = TempDir::new("fault-checkpoint");
    let run_dir = dir.path().join("run");
    let run = run_dir.display().to_string();
    let settings = [
        &["--max-seconds", "300"],
        QUICK_RUN,
        &["--set", "run.checkpoint_every_updates=1"],
    ]
    .concat();
    let (mut learner, endpoints) = start_learner(&run_dir, dir.path(), &settings);
    let mut actor = start_actor(&endpoints, dir.path(), "actor", &[]);
    let trained = wait_until(Duration::from_secs(120), || version(&endpoints) >= 2.0);
    assert!(trained, "no versions\n{}", learner.log_tail(30));
    // Ctrl-C stops as cleanly as SIGTERM, leaving a complete final checkpoint, and then ends
    // the learner by SIGINT, so that a shell script running it stops as well.
    learner.signal(libc::SIGINT);
    let status = learner.wait_exit(Duration::from_secs(60));
    assert_eq!(
        status.and_then(|s| s.signal()),
        Some(libc::SIGINT),
        "{status:?}\n{}",
        learner.log_tail(30)
    );
    assert!(learner.log().contains("writing a checkpoint"));
    assert!(actor.wait_exit(Duration::from_secs(30)).is_some());
    let complete = *checkpoint_versions(&run_dir).last().expect("a checkpoint");

    // A resume whose configuration does not fit the checkpoint (another network size) is
    // refused with a clear error, and every checkpoint stays where it was: a sound run is not
    // set aside as damaged over a changed flag.
    let shm_name = unique_shm_name();
    let misfit_args = [
        "serve",
        "--resume",
        &run,
        "--addr",
        "127.0.0.1:0",
        "--metrics-addr",
        "127.0.0.1:0",
        "--device",
        "cpu",
        "--shm-name",
        &shm_name,
        "--set",
        "ppo.hidden=[24]",
    ]
    .map(String::from);
    let mut misfit = Process::start("learner-misfit", &bin("learner"), &misfit_args, dir.path());
    misfit.assert_fails_saying(Duration::from_secs(60), &["another configuration"]);
    assert_eq!(checkpoint_versions(&run_dir).last(), Some(&complete));
    let set_aside = std::fs::read_dir(run_dir.join("checkpoints"))
        .unwrap()
        .flatten()
        .any(|e| e.file_name().to_string_lossy().starts_with("damaged-"));
    assert!(!set_aside, "a sound checkpoint was set aside as damaged");

    // Resume with the test hook that stalls every checkpoint after its first file: the next
    // checkpoint is caught half-written.
    let (mut stalled, endpoints) = start_learner_with_env(
        &run_dir,
        dir.path(),
        &["--resume", &run, "--max-seconds", "300"],
        &[("JUNCTION_TEST_CHECKPOINT_STALL_MS", "120000")],
    );
    let _actor = start_actor(&endpoints, dir.path(), "actor-2", &[]);
    let checkpoints = run_dir.join("checkpoints");
    let half_written = || {
        std::fs::read_dir(&checkpoints)
            .map(|entries| {
                entries.flatten().any(|e| {
                    e.file_name().to_string_lossy().starts_with(".tmp-")
                        && e.path().join("policy.safetensors").exists()
                        && !e.path().join("meta.json").exists()
                })
            })
            .unwrap_or(false)
    };
    assert!(
        wait_until(Duration::from_secs(120), half_written),
        "no checkpoint write began\n{}",
        stalled.log_tail(30)
    );
    stalled.signal(libc::SIGKILL);
    assert!(stalled.wait_exit(Duration::from_secs(10)).is_some());
    assert!(half_written(), "the half-written checkpoint is gone");
    assert_eq!(
        checkpoint_versions(&run_dir).last(),
        Some(&complete),
        "a half-written checkpoint counts as complete"
    );

    // The previous checkpoint loads; the leftover is cleared; training goes on.
    let (mut resumed, endpoints) = start_learner(
        &run_dir,
        dir.path(),
        &["--resume", &run, "--max-seconds", "300"],
    );
    assert_eq!(
        resumed_version(&resumed),
        Some(complete),
        "{}",
        resumed.log_tail(30)
    );
    assert!(!half_written(), "the interrupted write was not cleared");
    let _actor = start_actor(&endpoints, dir.path(), "actor-3", &[]);
    let advanced = wait_until(Duration::from_secs(120), || {
        version(&endpoints) >= complete as f64 + 2.0
    });
    assert!(advanced, "{}", resumed.log_tail(30));
    resumed.signal(libc::SIGTERM);
    assert!(
        resumed
            .wait_exit(Duration::from_secs(60))
            .is_some_and(|s| s.success())
    );
}

#[test]
fn an_actor_stops_cleanly_on_sigterm_and_ends_by_sigint_on_ctrl_c() {
    let dir = TempDir::new("fault-actor-signals");
    // No learner listens here: the actor retries, the state in which people stop actors most.
    let learner = format!("127.0.0.1:{}", free_port());
    for (name, signal) in [("term", libc::SIGTERM), ("int", libc::SIGINT)] {
        let args = [
            "--learner",
            &learner,
            "--connect-timeout",
            "120",
            "--retry-max-delay",
            "1",
        ]
        .map(String::from);
        let mut actor = Process::start(name, &bin("actor"), &args, dir.path());
        let retrying = wait_until(Duration::from_secs(30), || {
            actor.log().contains("learner unreachable")
        });
        assert!(
            retrying,
            "the actor is not retrying\n{}",
            actor.log_tail(20)
        );
        actor.signal(signal);
        let status = actor.wait_exit(Duration::from_secs(30));
        // SIGTERM (`docker stop`, a learner's local mode) is a normal end; after Ctrl-C a
        // shell loop of actors stops too.
        match signal {
            libc::SIGTERM => assert!(
                status.is_some_and(|s| s.success()),
                "{status:?}\n{}",
                actor.log_tail(20)
            ),
            _ => assert_eq!(
                status.and_then(|s| s.signal()),
                Some(libc::SIGINT),
                "{status:?}\n{}",
                actor.log_tail(20)
            ),
        }
        assert!(
            actor.log().contains("interrupted"),
            "{}",
            actor.log_tail(20)
        );
    }
}

/// The fragment ledgers of a run with a killed gRPC actor, a killed learner resumed on its
/// port and shared-memory actors dying with it balance exactly: every fragment an actor
/// produced is trained, dropped, rejected or lost in one named way, and the losses are where
/// the faults were.
#[test]
fn every_fragment_is_accounted_for_across_killed_actors_and_a_resumed_learner() {
    let dir = TempDir::new("fault-ledger");
    let run_dir = dir.path().join("run");
    let run = run_dir.display().to_string();
    let addr = format!("127.0.0.1:{}", free_port());
    let settings = [
        &[
            "--max-seconds",
            "300",
            "--addr",
            &addr,
            "--local-actors",
            "1",
        ],
        QUICK_RUN,
        &["--set", "run.checkpoint_every_updates=2"],
    ]
    .concat();
    let (mut learner, endpoints) = start_learner(&run_dir, dir.path(), &settings);
    let ledger = dir.path().join("grpc-actors.jsonl");
    let ledger_arg = ledger.display().to_string();
    let actor_args = ["--ledger", &ledger_arg, "--connect-timeout", "0"];
    let mut doomed = start_actor(&endpoints, dir.path(), "doomed", &actor_args);
    assert!(
        wait_until(Duration::from_secs(120), || version(&endpoints) >= 3.0),
        "no versions\n{}",
        learner.log_tail(30)
    );
    doomed.signal(libc::SIGKILL);
    let _ = doomed.wait_exit(Duration::from_secs(10));
    let mut survivor = start_actor(&endpoints, dir.path(), "survivor", &actor_args);
    let before = version(&endpoints);
    assert!(wait_until(Duration::from_secs(120), || version(&endpoints)
        >= before + 3.0));
    learner.signal(libc::SIGKILL);
    let _ = learner.wait_exit(Duration::from_secs(10));

    let resume = [&["--resume", run.as_str()], &settings[..]].concat();
    let (mut resumed, endpoints) = start_learner(&run_dir, dir.path(), &resume);
    let from = version(&endpoints);
    assert!(
        wait_until(Duration::from_secs(120), || version(&endpoints)
            >= from + 3.0),
        "the resumed learner did not train\n{}",
        resumed.log_tail(30)
    );
    resumed.signal(libc::SIGTERM);
    assert!(
        resumed
            .wait_exit(Duration::from_secs(60))
            .is_some_and(|s| s.success())
    );
    assert!(survivor.wait_exit(Duration::from_secs(30)).is_some());

    let local_ledgers: Vec<_> = std::fs::read_dir(run_dir.join("ledger"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .collect();
    assert!(!local_ledgers.is_empty(), "local actors keep ledgers");
    let output = std::process::Command::new("python3")
        .env("PYTHONPATH", workspace_root().join("python"))
        .args(["-m", "junction.ledger", "--json"])
        .arg(run_dir.join("ledger.jsonl"))
        .arg(&ledger)
        .args(&local_ledgers)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let summary: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let class = |name: &str| summary["classes"][name].as_u64().unwrap_or(0);
    assert_eq!(summary["unexplained"], 0, "{summary}");
    assert_eq!(summary["learner_processes"], 2, "{summary}");
    assert_eq!(summary["learner_clean_stops"], 1, "{summary}");
    // Both learners trained; the killed one's fragments after its last checkpoint, its
    // local actor's outbox and the killed gRPC actor's show up as such.
    assert!(class("trained") > 0, "{summary}");
    assert!(class("lost_with_learner") > 0, "{summary}");
    assert!(
        class("lost_with_actor") + class("lost_in_transport") > 0,
        "{summary}"
    );
    let produced = summary["produced"].as_u64().unwrap();
    let classified: u64 = summary["classes"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(produced, classified, "{summary}");
}
