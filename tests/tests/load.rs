//! 32 actor connections against one learner: synthetic senders in this process, each on its
//! own TCP connection, stream valid pre-built fragments as fast as the learner lets them. The
//! learner's resident memory stays bounded (backpressure, not buffering), and every accepted
//! agent-step is trained on or counted as dropped by reason, checked three ways: the senders'
//! PushSummary totals, /metrics, and the final progress line written after the shutdown count.
//!
//! `JUNCTION_LOAD_SECONDS` (default 15) sets how long the senders push; the test prints one
//! JSON line with the figures (BENCHMARKS.md, "Load: 32 connections").

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use junction_common::proto::{self, learner_client::LearnerClient};
use junction_core::lcf_inputs;
use junction_core::spec::PROTOCOL_VERSION;
use junction_tests::{TempDir, metric_sum, rss_kib, scrape, start_learner};
use tonic::transport::Endpoint;

const CONNECTIONS: usize = 32;
const AGENTS: usize = 30;
const STEPS: usize = 50;
const OBS_DIM: usize = 91;

/// One valid fragment of the default intersection: 50 steps × 30 agents, agents finishing
/// and respawning now and then, a few neighbours each.
fn fragment() -> proto::RolloutFragment {
    let cells = STEPS * AGENTS;
    let mut dones = vec![0u8; cells];
    for slot in 0..AGENTS {
        // Slot s ends an episode at step (7s mod 50); a new agent takes it the next step.
        dones[((7 * slot) % STEPS) * AGENTS + slot] = 1;
    }
    let mut neighbour_offsets = vec![0u32];
    let mut neighbour_ids = Vec::new();
    for cell in 0..cells {
        let slot = cell % AGENTS;
        neighbour_ids.extend([(slot + 1) % AGENTS, (slot + 2) % AGENTS].map(|s| s as u32));
        neighbour_offsets.push(neighbour_ids.len() as u32);
    }
    proto::RolloutFragment {
        protocol_version: PROTOCOL_VERSION,
        scenario: "intersection".into(),
        steps: STEPS as u32,
        agents: AGENTS as u32,
        obs_dim: OBS_DIM as u32,
        action_dim: 2,
        obs: (0..cells * OBS_DIM)
            .map(|i| (i % 97) as f32 / 97.0)
            .collect(),
        actions: (0..cells * 2)
            .map(|i| ((i % 13) as f32 - 6.0) / 6.0)
            .collect(),
        log_probs: vec![-1.5; cells],
        rewards: (0..cells).map(|i| (i % 5) as f32 * 0.1).collect(),
        costs: vec![0.0; cells],
        dones,
        alive: vec![1; cells],
        bootstrap_obs: vec![0.5; AGENTS * OBS_DIM],
        neighbour_offsets,
        neighbour_ids,
        lcf_features: vec![0.25; cells * lcf_inputs::FEATURES],
        sim_seconds: STEPS as f32 * 0.1,
        ..Default::default()
    }
}

#[derive(Default)]
struct Totals {
    fragments: AtomicU64,
    agent_steps: AtomicU64,
}

/// One actor connection: register, then stream copies of `template` stamped with the newest
/// policy version seen, until `stop`; adds the learner's PushSummary to `totals`.
async fn sender(
    url: String,
    template: Arc<proto::RolloutFragment>,
    version: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
    totals: Arc<Totals>,
) -> Result<(), String> {
    let channel = Endpoint::from_shared(url)
        .map_err(|e| e.to_string())?
        .connect()
        .await
        .map_err(|e| e.to_string())?;
    let mut client = LearnerClient::new(channel).max_encoding_message_size(64 << 20);
    let actor_id = client
        .register(proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_name: "load".into(),
            scenes: 1,
            instance: String::new(),
        })
        .await
        .map_err(|e| e.to_string())?
        .into_inner()
        .actor_id;
    let mut sequence = 0;
    let fragments = std::iter::from_fn(move || {
        if stop.load(Ordering::Relaxed) {
            return None;
        }
        let mut f = (*template).clone();
        f.actor_id = actor_id.clone();
        f.sequence = sequence;
        f.behaviour_version = version.load(Ordering::Relaxed);
        sequence += 1;
        Some(f)
    });
    let summary = client
        .push_rollouts(tokio_stream::iter(fragments))
        .await
        .map_err(|e| e.to_string())?
        .into_inner();
    totals
        .fragments
        .fetch_add(summary.accepted_fragments, Ordering::Relaxed);
    totals
        .agent_steps
        .fetch_add(summary.accepted_agent_steps, Ordering::Relaxed);
    Ok(())
}

/// Follows the learner's versions, as actors do, so fragments carry a recent one.
async fn follow_versions(url: String, version: Arc<AtomicU64>) {
    let Ok(mut client) = LearnerClient::connect(url).await else {
        return;
    };
    let request = proto::WatchPolicyRequest {
        protocol_version: PROTOCOL_VERSION,
        actor_id: "load".into(),
        have_version: 0,
    };
    let Ok(response) = client.watch_policy(request).await else {
        return;
    };
    let mut stream = response.into_inner();
    while let Ok(Some(weights)) = stream.message().await {
        version.store(weights.version, Ordering::Relaxed);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thirty_two_connections_keep_memory_bounded_and_lose_no_agent_step() {
    let seconds: f64 = std::env::var("JUNCTION_LOAD_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(15.0);
    let dir = TempDir::new("load");
    let run_dir = dir.path().join("run");
    // A small network and one epoch, so the transport rather than the update is loaded; a
    // batch of about one fragment per connection (1600 scene steps) and max_policy_lag = 2,
    // so fragments that waited behind two updates are dropped as stale: every outcome occurs.
    let settings = [
        "--max-seconds",
        "0",
        "--set",
        "rollout.fragment_length=50",
        "--set",
        "ppo.hidden=[64, 64]",
        "--set",
        "ppo.epochs=1",
        "--set",
        "ppo.minibatch_size=4096",
        "--set",
        "ppo.train_batch_env_steps=1600",
        "--set",
        "learner.max_policy_lag=2",
        "--set",
        "run.checkpoint_every_updates=0",
        "--set",
        "run.progress_interval_s=1",
    ];
    let (mut learner, endpoints) =
        tokio::task::block_in_place(|| start_learner(&run_dir, dir.path(), &settings));
    let pid = learner.pid();
    let url = format!("http://{}", endpoints.grpc);
    let baseline_kib = rss_kib(pid).expect("learner RSS");

    let template = Arc::new(fragment());
    let fragment_bytes = prost::Message::encoded_len(template.as_ref());
    let version = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let totals = Arc::new(Totals::default());
    tokio::spawn(follow_versions(url.clone(), Arc::clone(&version)));
    let senders: Vec<_> = (0..CONNECTIONS)
        .map(|_| {
            tokio::spawn(sender(
                url.clone(),
                Arc::clone(&template),
                Arc::clone(&version),
                Arc::clone(&stop),
                Arc::clone(&totals),
            ))
        })
        .collect();

    let started = Instant::now();
    let mut samples = Vec::new();
    let mut connected_max = 0.0f64;
    while started.elapsed().as_secs_f64() < seconds {
        tokio::time::sleep(Duration::from_millis(250)).await;
        samples.push(rss_kib(pid).expect("the learner is running"));
        let m = tokio::task::block_in_place(|| scrape(&endpoints.metrics));
        connected_max = connected_max.max(metric_sum(&m, "junction_learner_connected_actors"));
    }
    let before_stop = tokio::task::block_in_place(|| scrape(&endpoints.metrics));
    let pushed_s = started.elapsed().as_secs_f64();
    stop.store(true, Ordering::Relaxed);
    for sender in senders {
        tokio::time::timeout(Duration::from_secs(120), sender)
            .await
            .expect("a sender finished within 120 s of the stop")
            .expect("sender task")
            .expect("sender got its PushSummary");
    }
    let accepted = totals.agent_steps.load(Ordering::Relaxed);
    let m = tokio::task::block_in_place(|| scrape(&endpoints.metrics));

    assert_eq!(
        connected_max, CONNECTIONS as f64,
        "not all connections streamed at once"
    );
    assert_eq!(
        metric_sum(&m, "junction_learner_agent_steps_accepted_total"),
        accepted as f64,
        "/metrics and the PushSummaries disagree on what was accepted"
    );
    assert_eq!(
        metric_sum(&m, "junction_learner_fragments_total"),
        totals.fragments.load(Ordering::Relaxed) as f64
    );
    assert_eq!(
        metric_sum(&m, "junction_learner_fragments_rejected_total"),
        0.0
    );

    // Stop the learner: it counts what is still queued or short of a batch, then reports.
    tokio::task::block_in_place(|| {
        learner.signal(libc::SIGTERM);
        let status = learner.wait_exit(Duration::from_secs(120));
        assert!(
            status.is_some_and(|s| s.success()),
            "{status:?}\n{}",
            learner.log_tail(30)
        );
    });
    let progress = std::fs::read_to_string(run_dir.join("progress.jsonl")).expect("progress");
    let last: serde_json::Value =
        serde_json::from_str(progress.lines().last().expect("a progress line")).expect("JSON");
    let trained = last["agent_steps"].as_u64().expect("agent_steps");
    let dropped = |reason: &str| last["dropped_agent_steps"][reason].as_u64().unwrap_or(0);
    assert_eq!(
        last["accepted_agent_steps"].as_u64(),
        Some(accepted),
        "{last}"
    );
    assert_eq!(
        trained + dropped("stale") + dropped("shutdown") + dropped("update_failed"),
        accepted,
        "trained + dropped != accepted: {last}"
    );
    assert!(trained > 0, "nothing was trained: {last}");

    let peak_kib = *samples.iter().max().expect("samples");
    let half = samples.len() / 2;
    let first_half_peak = *samples[..half].iter().max().unwrap_or(&peak_kib);
    let second_half_peak = *samples[half..].iter().max().unwrap_or(&peak_kib);
    let received_bytes = metric_sum(
        &before_stop,
        "junction_learner_transport_received_bytes_total",
    );
    let report = serde_json::json!({
        "connections": CONNECTIONS,
        "fragment_bytes": fragment_bytes,
        "seconds": pushed_s,
        "rss_baseline_mib": baseline_kib as f64 / 1024.0,
        "rss_peak_mib": peak_kib as f64 / 1024.0,
        "rss_first_half_peak_mib": first_half_peak as f64 / 1024.0,
        "rss_second_half_peak_mib": second_half_peak as f64 / 1024.0,
        // One sample every 5 s (samples are taken every 250 ms).
        "rss_mib_every_5s": samples.iter().step_by(20).map(|kib| kib / 1024).collect::<Vec<_>>(),
        "received_mb_per_s": received_bytes / pushed_s / 1e6,
        "accepted_agent_steps": accepted,
        "accepted_agent_steps_per_s": metric_sum(&before_stop, "junction_learner_agent_steps_accepted_total") / pushed_s,
        "trained_agent_steps": trained,
        "dropped_stale": dropped("stale"),
        "dropped_shutdown": dropped("shutdown"),
    });
    println!("{report}");
    // Bounded: what backpressure allows in flight (the queue, one fragment per stream in its
    // handler, the HTTP/2 windows) is tens of MB; 1 GiB over the idle learner means
    // something buffers without bound.
    assert!(
        peak_kib < baseline_kib + (1 << 20),
        "learner RSS grew from {baseline_kib} KiB to {peak_kib} KiB: {report}"
    );
}
