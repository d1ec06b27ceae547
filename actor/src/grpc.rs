//! The actor side of the gRPC transport: register, follow the policy stream, and push
//! fragments produced by the rollout thread.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::{Channel, Endpoint};

use junction_common::config::ScenarioConfig;
use junction_common::fragment::PROTOCOL_VERSION;
use junction_common::policy::{self, Policy};
use junction_common::proto::{self, learner_client::LearnerClient};
use junction_common::spec::{ACTION_DIM, OBS_LAYOUT_VERSION};

use crate::metrics::ActorMetrics;
use crate::rollout::{RolloutWorker, derive_seed};

/// Fragments buffered between the rollout thread and the push stream; when full, the rollout
/// thread waits (the learner's backpressure reaches the simulator).
const OUTBOX_FRAGMENTS: usize = 4;

pub struct ActorOptions {
    pub learner: String,
    pub name: String,
    pub scenes: usize,
    pub seed: u64,
    pub connect_timeout: Duration,
    pub max_message_bytes: usize,
}

/// Connects, retrying with exponential back-off until `timeout` has passed.
async fn connect(url: &str, timeout: Duration) -> anyhow::Result<Channel> {
    let endpoint = Endpoint::from_shared(url.to_string())
        .with_context(|| {
            format!("--learner {url:?} is not a valid URL (expected e.g. http://127.0.0.1:50051)")
        })?
        .connect_timeout(Duration::from_secs(5))
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
pub async fn run(options: ActorOptions, metrics: Arc<ActorMetrics>) -> anyhow::Result<()> {
    let channel = connect(&options.learner, options.connect_timeout).await?;
    let mut client = LearnerClient::new(channel)
        .max_decoding_message_size(options.max_message_bytes)
        .max_encoding_message_size(options.max_message_bytes);
    let reply = client
        .register(proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_name: options.name.clone(),
            scenes: options.scenes as u32,
        })
        .await
        .context("registering with the learner")?
        .into_inner();
    if reply.protocol_version != PROTOCOL_VERSION || reply.obs_layout_version != OBS_LAYOUT_VERSION
    {
        bail!(
            "the learner speaks protocol {} with observation layout {}; this actor speaks {} with {}",
            reply.protocol_version,
            reply.obs_layout_version,
            PROTOCOL_VERSION,
            OBS_LAYOUT_VERSION
        );
    }
    let scenario =
        ScenarioConfig::from_toml(&reply.scenario_toml).context("the learner's scenario")?;
    if reply.obs_dim as usize != scenario.obs_dim() || reply.action_dim as usize != ACTION_DIM {
        bail!(
            "the learner's dimensions {}×{} do not match its scenario",
            reply.obs_dim,
            reply.action_dim
        );
    }
    let actor_id = reply.actor_id.clone();
    tracing::Span::current()
        .record("id", actor_id.as_str())
        .record("scenario", scenario.name.as_str());
    tracing::info!(scenes = options.scenes, "registered");

    // Policy stream → latest weights; the rollout thread picks them up between fragments.
    let mut policy_stream = client
        .watch_policy(proto::WatchPolicyRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_id: actor_id.clone(),
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
    let seed = derive_seed(
        reply.run_seed ^ options.seed,
        reply.actor_id.bytes().map(u64::from).sum(),
    );
    let rollout = {
        let finished = Arc::clone(&finished);
        let metrics = Arc::clone(&metrics);
        let fragment_length = reply.fragment_length as usize;
        let scenes = options.scenes;
        tokio::task::spawn_blocking(move || {
            rollout_loop(
                scenario,
                scenes,
                seed,
                fragment_length,
                actor_id,
                weights_rx,
                outbox_tx,
                finished,
                &metrics,
            )
        })
    };
    let pushed = client.push_rollouts(ReceiverStream::new(outbox_rx)).await;
    let rollout_result = rollout.await.context("rollout thread panicked")?;
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

/// Simulates the agent count the learner's curriculum asks for with `weights`.
fn apply_active_agents(
    worker: &mut RolloutWorker,
    weights: &proto::PolicyWeights,
    metrics: &ActorMetrics,
) -> anyhow::Result<()> {
    let before = worker.active_agents();
    let requested = usize::try_from(weights.active_agents).unwrap_or(usize::MAX);
    if worker
        .set_active_agents(requested)
        .context("rebuilding the scenes for the curriculum's agent count")?
    {
        tracing::info!(
            old_agents = before,
            new_agents = worker.active_agents(),
            version = weights.version,
            "scenes rebuilt with the curriculum's agent count"
        );
    }
    metrics.scene_agents.set(worker.active_agents() as i64);
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn rollout_loop(
    scenario: ScenarioConfig,
    scenes: usize,
    seed: u64,
    fragment_length: usize,
    actor_id: String,
    mut weights: watch::Receiver<Arc<proto::PolicyWeights>>,
    outbox: mpsc::Sender<proto::RolloutFragment>,
    finished: Arc<AtomicBool>,
    metrics: &ActorMetrics,
) -> anyhow::Result<()> {
    let _span =
        tracing::info_span!("rollout", actor = %actor_id, scenario = %scenario.name).entered();
    // The blob says which kind of policy it is (Gaussian or DQN's Q-policy): no flag needed.
    let load = |w: &proto::PolicyWeights| -> anyhow::Result<Box<dyn Policy>> {
        let (policy, meta) =
            policy::decode(&w.data, tch::Device::Cpu).context("decoding policy weights")?;
        if meta.obs_layout_version != OBS_LAYOUT_VERSION
            || policy.obs_dim() != scenario.obs_dim()
            || policy.action_dim() != ACTION_DIM
        {
            bail!(
                "policy v{} was trained for another observation layout or size or action size",
                w.version
            );
        }
        Ok(policy)
    };
    let initial = Arc::clone(&weights.borrow_and_update());
    let mut worker = RolloutWorker::new(
        &scenario,
        scenes,
        seed,
        fragment_length,
        load(&initial)?,
        initial.version,
        actor_id,
    )
    .context("building the scenes")?;
    metrics.policy_version.set(initial.version as i64);
    apply_active_agents(&mut worker, &initial, metrics)?;
    while !finished.load(Ordering::Relaxed) {
        if weights.has_changed().unwrap_or(false) {
            let latest = Arc::clone(&weights.borrow_and_update());
            if latest.version != worker.policy_version() {
                worker.set_policy(load(&latest)?, latest.version);
                metrics.policy_version.set(latest.version as i64);
                metrics.policy_switches.inc();
                tracing::debug!(version = latest.version, "switched policy");
            }
            apply_active_agents(&mut worker, &latest, metrics)?;
        }
        let _collect =
            tracing::info_span!("collect", policy_version = worker.policy_version()).entered();
        let (fragments, timings) = worker.collect().context("policy inference")?;
        metrics.inference_seconds.inc_by(timings.inference_s);
        metrics.simulation_seconds.inc_by(timings.simulation_s);
        for fragment in fragments {
            metrics.env_steps.inc_by(fragment.steps as u64);
            metrics.agent_steps.inc_by(fragment.agent_steps() as u64);
            if outbox.blocking_send(fragment.into_proto()).is_err() {
                // The push stream is gone (learner finished or failed); the caller reports why.
                return Ok(());
            }
            metrics.fragments_sent.inc();
        }
    }
    Ok(())
}
