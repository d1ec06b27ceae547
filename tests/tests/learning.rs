//! A learning test that can fail: on the tiny straight-through scenario, each algorithm must take the
//! success rate from about 0 (random policy) to at least 0.9, with fixed seeds, within a bounded
//! number of updates and time.

use std::sync::{Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};

use junction_tests::{TempDir, start_actor, start_learner};

/// Hard limits of the test; the closing figures go to stdout.
const MAX_WALL: Duration = Duration::from_secs(170);
const MAX_UPDATES: u64 = 400;
const WINDOW: usize = 50;

fn progress_lines(path: &std::path::Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}

/// Two learning runs at a time. A run keeps about one core busy, its actor waiting for the
/// learner's weights and its learner for the actor's fragments, so two fill a 2-core machine;
/// more would slow each towards its limits.
const RUNS_AT_ONCE: usize = 2;
static RUNNING: (Mutex<usize>, Condvar) = (Mutex::new(0), Condvar::new());

/// A place among the `RUNS_AT_ONCE` running runs, given up when dropped, so a run that fails
/// (a panic unwinds through the drop) frees its place for the next.
struct Turn;

impl Turn {
    fn take() -> Turn {
        let (running, freed) = &RUNNING;
        let mut running = running.lock().unwrap_or_else(PoisonError::into_inner);
        while *running >= RUNS_AT_ONCE {
            running = freed.wait(running).unwrap_or_else(PoisonError::into_inner);
        }
        *running += 1;
        Turn
    }
}

impl Drop for Turn {
    fn drop(&mut self) {
        let (running, freed) = &RUNNING;
        *running.lock().unwrap_or_else(PoisonError::into_inner) -= 1;
        freed.notify_one();
    }
}

#[test]
fn ppo_learns_to_cross_the_tiny_intersection() {
    learns_to_cross_the_tiny_intersection("ippo");
}

/// The tiny scenario has one agent, so every curriculum stage has one agent too: this checks
/// that `cl` plumbs through the learner and actor and trains like IPPO.
#[test]
fn cl_learns_to_cross_the_tiny_intersection() {
    learns_to_cross_the_tiny_intersection("cl");
}

#[test]
fn ccppo_mf_learns_to_cross_the_tiny_intersection() {
    learns_to_cross_the_tiny_intersection("ccppo-mf");
}

#[test]
fn ccppo_concat_learns_to_cross_the_tiny_intersection() {
    learns_to_cross_the_tiny_intersection("ccppo-concat");
}

/// The tiny scenario has one agent, so it never has neighbours: these prove the learned LCFs'
/// plumbing (CoPO's φ column from actor to learner, the meta-gradient on every update) while
/// they train like IPPO.
#[test]
fn copo_learns_to_cross_the_tiny_intersection() {
    learns_to_cross_the_tiny_intersection("copo");
}

#[test]
fn dynamic_lcf_learns_to_cross_the_tiny_intersection() {
    learns_to_cross_the_tiny_intersection("dynamic-lcf");
}

/// DQN with its defaults: the actors act ε-greedily on the 5 × 5 grid the broadcast weights
/// carry; the same bar as PPO, with ε still exploring at its end value.
#[test]
fn dqn_learns_to_cross_the_tiny_intersection() {
    learns_to_cross_the_tiny_intersection("dqn");
}

/// The asynchronous path: updates of one fragment each while the actor's 8 scenes deliver 8
/// fragments per policy version and the queue holds 4 more, so most fragments are several
/// versions old when trained on. PPO must still learn (what `ppo.objective` is for).
#[test]
fn ppo_learns_from_fragments_several_versions_old() {
    let hit = learn(
        "ippo",
        &[
            "--set",
            "ppo.train_batch_env_steps=200",
            "--set",
            "learner.ingest_queue_fragments=4",
            "--set",
            "learner.max_policy_lag=16",
        ],
        4000,
    );
    let lag = hit["update"]["lag_mean"].as_f64().unwrap_or(0.0);
    println!("learning (ippo, lagging fragments): trained fragments {lag:.1} versions old");
    assert!(
        lag >= 3.0,
        "the trained fragments were only {lag} versions old: the test proves nothing about lag"
    );
}

/// Trains `algo` (`learner.algo`) on the tiny scenario until the success bar or the limits.
fn learns_to_cross_the_tiny_intersection(algo: &str) {
    learn(algo, &[], MAX_UPDATES);
}

/// Trains `algo` with `extra` learner flags until the success bar (returned: the progress
/// line that reached it) or the limits (a panic).
fn learn(algo: &str, extra: &[&str], max_updates: u64) -> serde_json::Value {
    let _turn = Turn::take();
    let dir = TempDir::new(&format!("learning-{algo}-{}", extra.len()));
    let run_dir = dir.path().join("run");
    let window = WINDOW.to_string();
    let window_flag = format!("run.stats_window_episodes={window}");
    let algo_flag = format!("learner.algo={algo}");
    let mut flags = vec![
        "--scenario",
        "tiny-straight",
        "--seed",
        "1",
        "--max-seconds",
        "200",
        "--set",
        "run.progress_interval_s=1",
        "--set",
        &window_flag,
        "--set",
        "run.checkpoint_every_updates=0",
        "--set",
        &algo_flag,
    ];
    flags.extend_from_slice(extra);
    let (mut learner, endpoints) = start_learner(&run_dir, dir.path(), &flags);
    let actor = start_actor(
        &endpoints,
        dir.path(),
        "actor",
        &["--scenes", "8", "--seed", "1"],
    );
    let started = Instant::now();
    let progress_file = run_dir.join("progress.jsonl");
    let mut first_full_window: Option<f64> = None;
    let learned = loop {
        let lines = progress_lines(&progress_file);
        let full: Vec<&serde_json::Value> = lines
            .iter()
            .filter(|l| l["window"]["episodes"].as_u64().unwrap_or(0) >= WINDOW as u64)
            .collect();
        if first_full_window.is_none() {
            first_full_window = full
                .first()
                .and_then(|l| l["window"]["success_rate"].as_f64());
        }
        if let Some(hit) = full
            .iter()
            .find(|l| l["window"]["success_rate"].as_f64().unwrap_or(0.0) >= 0.9)
        {
            break Some((**hit).clone());
        }
        let updates = lines
            .last()
            .and_then(|l| l["updates"].as_u64())
            .unwrap_or(0);
        if started.elapsed() > MAX_WALL || updates > max_updates || learner.try_exit().is_some() {
            break None;
        }
        std::thread::sleep(Duration::from_millis(500));
    };
    let Some(hit) = learned else {
        let last = progress_lines(&progress_file).pop();
        panic!(
            "success rate never reached 0.9 (last progress: {last:?})\n{}\n{}",
            learner.log_tail(20),
            actor.log_tail(20)
        );
    };
    println!(
        "learning ({algo}): success {:.3} after {} updates, {} agent-steps, {:.0} s (first full window: {first_full_window:?})",
        hit["window"]["success_rate"].as_f64().unwrap_or(0.0),
        hit["updates"],
        hit["agent_steps"],
        hit["elapsed_s"].as_f64().unwrap_or(0.0),
    );
    // Every algorithm reports its LCF angle by neighbour count; the lone agent has none.
    let lonely = &hit["lcf"]["phi_deg_by_neighbours"]["0"];
    assert!(lonely.is_number(), "progress line without φ: {hit}");
    if algo == "copo" {
        // CoPO's agents draw φ from a distribution of learned, positive spread.
        assert!(hit["lcf"]["std_deg"].as_f64().unwrap_or(0.0) > 0.0, "{hit}");
    }
    let start = first_full_window.expect("a full window of episodes before success");
    assert!(
        start <= 0.2,
        "the untrained policy already succeeds ({start}); the test would prove nothing"
    );
    hit
}
