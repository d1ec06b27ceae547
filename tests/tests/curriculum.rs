//! The `cl` curriculum end to end: a real learner and actor on an 8-agent intersection with
//! short stages. The learner's stage gauge must climb from 0 to at least 2, the actor must
//! rebuild its scenes with each stage's agent count (2, 4, 6: ¼, ½, ¾ of 8), and a learner
//! resumed from the final checkpoint must start in the stage it stopped in.

use std::time::{Duration, Instant};

use junction_tests::{
    TempDir, metric_sum, scrape, start_actor_with_metrics, start_learner, wait_until,
};

const STAGE: &str = "junction_learner_curriculum_stage";
const AGENTS: &str = "junction_learner_curriculum_agents";
const ACTOR_AGENTS: &str = "junction_actor_scene_agents";
/// The whole test, processes' start and shutdown included.
const BUDGET: Duration = Duration::from_secs(60);

/// The `new_agents` values of the actor's "scenes rebuilt" log lines, in order.
fn rebuilt_agent_counts(log: &str) -> Vec<u64> {
    log.lines()
        .filter(|l| l.contains("scenes rebuilt"))
        .filter_map(|l| {
            let value = l.split("new_agents=").nth(1)?;
            value
                .split(|c: char| !c.is_ascii_digit())
                .next()?
                .parse()
                .ok()
        })
        .collect()
}

#[test]
fn curriculum_stages_advance_and_actors_follow_them() {
    let started = Instant::now();
    let left = || BUDGET.saturating_sub(started.elapsed());
    let dir = TempDir::new("curriculum");
    let run_dir = dir.path().join("run");
    let settings = [
        "--max-seconds",
        "120",
        "--set",
        "learner.algo=cl",
        "--set",
        "scenario.agents=8",
        "--set",
        "curriculum.stage_agent_steps=2000",
        "--set",
        "rollout.fragment_length=50",
        "--set",
        "ppo.train_batch_env_steps=100",
        "--set",
        "ppo.epochs=1",
        "--set",
        "run.checkpoint_every_updates=0",
    ];
    let (mut learner, endpoints) = start_learner(&run_dir, dir.path(), &settings);
    let m = scrape(&endpoints.metrics);
    assert_eq!(
        (metric_sum(&m, STAGE), metric_sum(&m, AGENTS)),
        (0.0, 2.0),
        "a fresh cl run starts in stage 0 with ¼ of 8 agents"
    );
    let (mut actor, actor_metrics) = start_actor_with_metrics(&endpoints, dir.path());

    let advanced = wait_until(left().saturating_sub(Duration::from_secs(15)), || {
        metric_sum(&scrape(&endpoints.metrics), STAGE) >= 2.0
    });
    assert!(
        advanced,
        "the curriculum did not reach stage 2: {:?}\n{}\n{}",
        scrape(&endpoints.metrics),
        learner.log_tail(30),
        actor.log_tail(30)
    );
    // The actor switches at its next fragment boundary after the broadcast.
    let followed = wait_until(Duration::from_secs(5), || {
        metric_sum(&scrape(&actor_metrics), ACTOR_AGENTS) >= 6.0
    });
    assert!(
        followed,
        "the actor did not rebuild its scenes for stage 2: {:?}\n{}",
        scrape(&actor_metrics),
        actor.log_tail(30)
    );
    let counts = rebuilt_agent_counts(&actor.log());
    assert!(
        counts.starts_with(&[2, 4, 6]),
        "the actor's scenes should go 8 → 2 → 4 → 6 agents, got rebuilds to {counts:?}\n{}",
        actor.log_tail(30)
    );
    let learner_log = learner.log();
    for stage in 1..=2 {
        assert!(
            learner_log
                .lines()
                .any(|l| l.contains("curriculum stage changed")
                    && l.contains(&format!("new_stage={stage}"))),
            "the learner did not log the change to stage {stage}\n{}",
            learner.log_tail(30)
        );
    }

    // A stop writes the final checkpoint; the resumed learner starts in the same stage.
    learner.signal(libc::SIGTERM);
    let status = learner.wait_exit(Duration::from_secs(10));
    assert!(
        status.is_some_and(|s| s.success()),
        "learner did not stop cleanly: {status:?}\n{}",
        learner.log_tail(30)
    );
    let stopped_in = learner
        .log()
        .lines()
        .filter(|l| l.contains("curriculum stage changed"))
        .filter_map(|l| {
            l.split("new_stage=")
                .nth(1)?
                .split(' ')
                .next()?
                .parse()
                .ok()
        })
        .max()
        .unwrap_or(0u64);
    actor.stop(Duration::from_secs(5));
    let resume_dir = run_dir.display().to_string();
    let resumed_logs = dir.path().join("resumed");
    std::fs::create_dir_all(&resumed_logs).expect("create the resumed run's log directory");
    let (mut resumed, resumed_endpoints) =
        start_learner(&run_dir, &resumed_logs, &["--resume", &resume_dir]);
    let m = scrape(&resumed_endpoints.metrics);
    assert_eq!(
        metric_sum(&m, STAGE) as u64,
        stopped_in,
        "the resumed learner starts in another stage\n{}",
        resumed.log_tail(20)
    );
    assert_eq!(
        metric_sum(&m, AGENTS),
        [2.0, 4.0, 6.0, 8.0][stopped_in as usize]
    );
    resumed.stop(Duration::from_secs(5));
    assert!(
        started.elapsed() <= BUDGET,
        "the test took {:?}, over its {BUDGET:?} budget",
        started.elapsed()
    );
}
