//! The actor side of the gRPC transport: register, follow the policy stream, and push
//! fragments produced by the rollout thread (`session`).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::{Channel, Endpoint};

use junction_common::fragment::{PROTOCOL_VERSION, RolloutFragment};
use junction_common::proto::{self, learner_client::LearnerClient};
use junction_common::{GRPC_CONNECTION_WINDOW_BYTES, GRPC_STREAM_WINDOW_BYTES};

use crate::metrics::ActorMetrics;
use crate::session::{ActorOptions, RunInfo, rollout_loop};

/// Fragments buffered between the rollout thread and the push stream; when full, the rollout
/// thread waits (the learner's backpressure reaches the simulator).
const OUTBOX_FRAGMENTS: usize = 4;

/// Connects, retrying with exponential back-off until `timeout` has passed.
async fn connect(url: &str, timeout: Duration) -> anyhow::Result<Channel> {
    let endpoint = Endpoint::from_shared(url.to_string())
        .with_context(|| {
            format!("--learner {url:?} is not a valid URL (expected e.g. http://127.0.0.1:50051)")
        })?
        .connect_timeout(Duration::from_secs(5))
        .initial_stream_window_size(GRPC_STREAM_WINDOW_BYTES)
        .initial_connection_window_size(GRPC_CONNECTION_WINDOW_BYTES)
        .tcp_nodelay(true);
    let started = Instant::now();
    let mut delay = Duration::from_millis(100);
    loop {
        match endpoint.connect().await {
            Ok(channel) => return Ok(channel),
            Err(e) if started.elapsed() < timeout => {
                tracing::info!(learner = url, error = %e, retry_in_ms = delay.as_millis() as u64, "learner not reachable yet");
                tokio::time::sleep(delay).await;
                delay = (delay * 2).min(Duration::from_secs(5));
            }
            Err(e) => return Err(e).with_context(|| format!("connecting to the learner at {url}")),
        }
    }
}

/// Runs until the learner says the run is finished (Ok) or the connection fails (Err).
pub async fn run(
    url: &str,
    max_message_bytes: usize,
    options: ActorOptions,
    metrics: Arc<ActorMetrics>,
) -> anyhow::Result<()> {
    let channel = connect(url, options.connect_timeout).await?;
    let mut client = LearnerClient::new(channel)
        .max_decoding_message_size(max_message_bytes)
        .max_encoding_message_size(max_message_bytes);
    let reply = client
        .register(proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_name: options.name.clone(),
            scenes: options.scenes as u32,
        })
        .await
        .context("registering with the learner")?
        .into_inner();
    let run = RunInfo::from_reply(&reply)?;
    run.record_in_span();
    tracing::info!(scenes = options.scenes, "registered");

    // Policy stream → latest weights; the rollout thread picks them up between fragments.
    let mut policy_stream = client
        .watch_policy(proto::WatchPolicyRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_id: run.actor_id.clone(),
            have_version: 0,
        })
        .await
        .context("subscribing to policy weights")?
        .into_inner();
    let first = policy_stream
        .message()
        .await
        .context("receiving the first policy")?
        .context("the learner closed the policy stream before sending weights")?;
    let (weights_tx, weights_rx) = watch::channel(Arc::new(first));
    let finished = Arc::new(AtomicBool::new(false));
    let follower = {
        let finished = Arc::clone(&finished);
        tokio::spawn(async move {
            loop {
                match policy_stream.message().await {
                    Ok(Some(weights)) => {
                        let done = weights.run_finished;
                        weights_tx.send_replace(Arc::new(weights));
                        if done {
                            finished.store(true, Ordering::Relaxed);
                            return Ok(());
                        }
                    }
                    Ok(None) => {
                        return Err(anyhow::anyhow!("the learner closed the policy stream"));
                    }
                    Err(status) => return Err(anyhow::anyhow!("policy stream failed: {status}")),
                }
            }
        })
    };

    let (outbox_tx, outbox_rx) = mpsc::channel::<proto::RolloutFragment>(OUTBOX_FRAGMENTS);
    let busy_tracker = tokio::spawn(count_runtime_busy_time(Arc::clone(&metrics)));
    let seed = run.seed(options.seed);
    let rollout = {
        let finished = Arc::clone(&finished);
        let metrics = Arc::clone(&metrics);
        let scenes = options.scenes;
        tokio::task::spawn_blocking(move || {
            let send = |fragment: RolloutFragment| {
                let started = Instant::now();
                let message = fragment.into_proto();
                metrics
                    .transport_seconds
                    .inc_by(started.elapsed().as_secs_f64());
                // Err: the push stream is gone (learner finished or failed); the caller says why.
                outbox_tx.blocking_send(message).is_ok()
            };
            rollout_loop(run, scenes, seed, weights_rx, send, &finished, &metrics)
        })
    };
    let pushed = client.push_rollouts(ReceiverStream::new(outbox_rx)).await;
    let rollout_result = rollout.await.context("rollout thread panicked")?;
    busy_tracker.abort();
    match pushed {
        Ok(summary) => {
            let s = summary.into_inner();
            tracing::info!(
                fragments = s.accepted_fragments,
                agent_steps = s.accepted_agent_steps,
                "rollout stream closed"
            );
        }
        Err(status) => {
            // The learner ends streams when training is over; that is not a failure.
            let _ = tokio::time::timeout(Duration::from_secs(2), follower).await;
            if !finished.load(Ordering::Relaxed) {
                bail!(
                    "the learner ended the rollout stream: {} ({:?})",
                    status.message(),
                    status.code()
                );
            }
        }
    }
    rollout_result?;
    if finished.load(Ordering::Relaxed) {
        tracing::info!("the learner finished the run; actor exiting");
    }
    Ok(())
}

/// Adds the async runtime's busy time to the transport time every second: in a gRPC actor
/// the runtime does nothing but the transport (protobuf encoding, HTTP/2, sockets, the policy
/// stream).
async fn count_runtime_busy_time(metrics: Arc<ActorMetrics>) {
    let runtime = tokio::runtime::Handle::current().metrics();
    let busy = || -> Duration {
        (0..runtime.num_workers())
            .map(|w| runtime.worker_total_busy_duration(w))
            .sum()
    };
    let mut counted = busy();
    loop {
        tokio::time::sleep(Duration::from_secs(1)).await;
        let now = busy();
        metrics
            .transport_seconds
            .inc_by(now.saturating_sub(counted).as_secs_f64());
        counted = now;
    }
}
