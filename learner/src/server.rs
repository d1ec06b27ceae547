//! The state the transports share with the training loop, and the gRPC face of the learner:
//! actor registration, rollout ingest (through [`crate::ingest`]), weight broadcast and status.

use std::collections::HashSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use prost::Message;
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};

use junction_common::config::RunConfig;
use junction_common::fragment::{MAX_NAME_BYTES, PROTOCOL_VERSION, RolloutFragment};
use junction_common::grpc_codec::is_request_decode_error;
use junction_common::proto::{self, learner_server::Learner};
use junction_common::spec::{ACTION_DIM, OBS_LAYOUT_VERSION};

use crate::ingest::{Ingest, Rejection};
use crate::metrics::{LearnerMetrics, REFUSED_STREAM_LIMIT, REJECT_DECODE, TRANSPORT_GRPC};

/// State the gRPC handlers share with the training loop.
pub struct Shared {
    pub config: RunConfig,
    pub metrics: LearnerMetrics,
    /// The newest weights; every WatchPolicy stream follows it.
    pub weights: watch::Sender<Arc<proto::PolicyWeights>>,
    pub status: Mutex<proto::StatusReply>,
    next_actor: AtomicU64,
    /// Rejection reasons already logged at warn level (later ones go to debug).
    logged_rejections: Mutex<HashSet<&'static str>>,
    /// Open rollout streams and policy streams, each capped at server.max_rollout_streams.
    rollout_streams: Arc<Semaphore>,
    policy_streams: Arc<Semaphore>,
}

impl Shared {
    pub fn new(config: RunConfig, metrics: LearnerMetrics, initial: proto::PolicyWeights) -> Self {
        let (weights, _) = watch::channel(Arc::new(initial));
        metrics.initialise_labels(&config.scenario.name);
        Shared {
            metrics,
            weights,
            status: Mutex::new(proto::StatusReply {
                protocol_version: PROTOCOL_VERSION,
                ..Default::default()
            }),
            next_actor: AtomicU64::new(1),
            logged_rejections: Mutex::new(HashSet::new()),
            rollout_streams: Arc::new(Semaphore::new(config.server.max_rollout_streams)),
            policy_streams: Arc::new(Semaphore::new(config.server.max_rollout_streams)),
            config,
        }
    }

    /// Actor ids handed out so far (recorded in checkpoints).
    pub fn actors_registered(&self) -> u64 {
        self.next_actor.load(Ordering::Relaxed).saturating_sub(1)
    }

    /// A resumed learner numbers new actors after those of the run it continues, so no two
    /// actors share an id (their scene seeds derive from it).
    pub fn continue_actor_ids(&self, registered: u64) {
        self.next_actor
            .fetch_max(registered.saturating_add(1), Ordering::Relaxed);
    }

    /// One of the `kind` stream slots, or RESOURCE_EXHAUSTED (counted) when all are taken.
    fn stream_slot(
        &self,
        slots: &Arc<Semaphore>,
        kind: &str,
    ) -> Result<OwnedSemaphorePermit, Status> {
        Arc::clone(slots).try_acquire_owned().map_err(|_| {
            self.metrics
                .requests_refused
                .with_label_values(&[REFUSED_STREAM_LIMIT])
                .inc();
            tracing::warn!(
                kind,
                limit = self.config.server.max_rollout_streams,
                "refused a stream: server.max_rollout_streams reached"
            );
            Status::resource_exhausted(format!(
                "the learner already serves {} {kind} streams (server.max_rollout_streams); retry later",
                self.config.server.max_rollout_streams
            ))
        })
    }

    /// Values per observation row in fragments: what the policy takes.
    pub fn obs_dim(&self) -> usize {
        self.config.policy_obs_dim()
    }

    /// Registers an actor whatever its transport: assigns its id (unique across transports)
    /// and answers with the run configuration.
    pub fn register(
        &self,
        hello: &proto::RegisterRequest,
        transport: &str,
    ) -> Result<proto::RegisterReply, Refusal> {
        check_version(hello.protocol_version)?;
        check_name("actor_name", &hello.actor_name)?;
        let actor_id = format!("actor-{}", self.next_actor.fetch_add(1, Ordering::Relaxed));
        tracing::info!(actor = %actor_id, name = %hello.actor_name, scenes = hello.scenes, transport, "actor registered");
        let config = &self.config;
        Ok(proto::RegisterReply {
            protocol_version: PROTOCOL_VERSION,
            actor_id,
            scenario_toml: config.scenario.to_toml(),
            fragment_length: config.rollout.fragment_length as u32,
            obs_dim: self.obs_dim() as u32,
            action_dim: ACTION_DIM as u32,
            obs_layout_version: OBS_LAYOUT_VERSION,
            run_seed: config.run.seed,
        })
    }

    /// Counts a refused fragment and logs its cause once at warn level.
    pub(crate) fn reject(&self, reason: &'static str, actor: &str, detail: &str) {
        self.metrics
            .fragments_rejected
            .with_label_values(&[reason])
            .inc();
        let first = self
            .logged_rejections
            .lock()
            .map(|mut seen| seen.insert(reason))
            .unwrap_or(true);
        if first {
            tracing::warn!(
                reason,
                actor,
                "rejected fragment: {detail} (further rejections of this kind log at debug)"
            );
        } else {
            tracing::debug!(reason, actor, "rejected fragment: {detail}");
        }
    }
}

/// Why a request from an actor was refused, whatever its transport.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    #[error("protocol version {0} is not supported (this learner speaks {PROTOCOL_VERSION})")]
    Version(u32),
    #[error("{field} is {len} bytes long (at most {MAX_NAME_BYTES})")]
    NameTooLong { field: &'static str, len: usize },
}

impl From<Refusal> for Status {
    fn from(refusal: Refusal) -> Self {
        match refusal {
            Refusal::Version(_) => Status::failed_precondition(refusal.to_string()),
            Refusal::NameTooLong { .. } => Status::invalid_argument(refusal.to_string()),
        }
    }
}

fn check_version(got: u32) -> Result<(), Refusal> {
    if got == PROTOCOL_VERSION {
        Ok(())
    } else {
        Err(Refusal::Version(got))
    }
}

/// Names and ids from peers end up in logs: bounded, or refused.
fn check_name(field: &'static str, value: &str) -> Result<(), Refusal> {
    if value.len() > MAX_NAME_BYTES {
        return Err(Refusal::NameTooLong {
            field,
            len: value.len(),
        });
    }
    Ok(())
}

pub struct LearnerService {
    shared: Arc<Shared>,
    ingest: Ingest,
}

impl LearnerService {
    pub fn new(ingest: Ingest) -> Self {
        LearnerService {
            shared: Arc::clone(ingest.shared()),
            ingest,
        }
    }
}

/// Keeps `connected_actors` right however a stream ends.
struct ConnectedGuard<'a>(&'a prometheus::IntGauge);

impl<'a> ConnectedGuard<'a> {
    fn new(gauge: &'a prometheus::IntGauge) -> Self {
        gauge.inc();
        ConnectedGuard(gauge)
    }
}

impl Drop for ConnectedGuard<'_> {
    fn drop(&mut self) {
        self.0.dec();
    }
}

#[tonic::async_trait]
impl Learner for LearnerService {
    async fn register(
        &self,
        request: Request<proto::RegisterRequest>,
    ) -> Result<Response<proto::RegisterReply>, Status> {
        let hello = request.into_inner();
        Ok(Response::new(self.shared.register(&hello, TRANSPORT_GRPC)?))
    }

    async fn push_rollouts(
        &self,
        request: Request<Streaming<proto::RolloutFragment>>,
    ) -> Result<Response<proto::PushSummary>, Status> {
        let shared = &self.shared;
        let _slot = shared.stream_slot(&shared.rollout_streams, "rollout")?;
        let _connected = ConnectedGuard::new(&shared.metrics.connected_actors);
        let mut stream = request.into_inner();
        let mut summary = proto::PushSummary::default();
        let dims = Some(self.ingest.dims());
        loop {
            let message = match stream.message().await {
                Ok(Some(message)) => message,
                Ok(None) => break,
                Err(status) => {
                    // Undecodable bytes are refused data; anything else is the peer going
                    // away mid-stream, which is not the data's fault.
                    if is_request_decode_error(&status) {
                        shared.reject(REJECT_DECODE, "?", status.message());
                    } else {
                        tracing::debug!(error = %status, "rollout stream ended with an error");
                    }
                    return Err(status);
                }
            };
            let bytes = message.encoded_len();
            let actor = message.actor_id.clone();
            let decoded = RolloutFragment::from_proto(message, dims).map_err(Rejection::from);
            let fragment = self
                .ingest
                .admit(TRANSPORT_GRPC, bytes, &actor, decoded)
                .map_err(|rejection| {
                    let message = format!("fragment rejected: {}", rejection.detail);
                    if rejection.reason == "version" {
                        Status::failed_precondition(message)
                    } else {
                        Status::invalid_argument(message)
                    }
                })?;
            // A full queue parks this stream here, so the actor's sends stall (backpressure).
            // A fragment counts as accepted once queued: from then on it is trained on or
            // counted as dropped.
            let agent_steps = self
                .ingest
                .enqueue(fragment)
                .await
                .map_err(|closed| Status::unavailable(closed.to_string()))?;
            summary.accepted_fragments += 1;
            summary.accepted_agent_steps += agent_steps;
        }
        Ok(Response::new(summary))
    }

    type WatchPolicyStream = ReceiverStream<Result<proto::PolicyWeights, Status>>;

    async fn watch_policy(
        &self,
        request: Request<proto::WatchPolicyRequest>,
    ) -> Result<Response<Self::WatchPolicyStream>, Status> {
        let watch_request = request.into_inner();
        check_version(watch_request.protocol_version)?;
        check_name("actor_id", &watch_request.actor_id)?;
        let slot = self
            .shared
            .stream_slot(&self.shared.policy_streams, "policy")?;
        let mut latest = self.shared.weights.subscribe();
        let (tx, rx) = mpsc::channel(2);
        tokio::spawn(async move {
            let _slot = slot;
            loop {
                let weights = Arc::clone(&latest.borrow_and_update());
                let finished = weights.run_finished;
                if tx.send(Ok(weights.as_ref().clone())).await.is_err() || finished {
                    break;
                }
                // An actor that went away frees its slot now, not at the next version.
                let changed = tokio::select! {
                    changed = latest.changed() => changed,
                    () = tx.closed() => break,
                };
                if changed.is_err() {
                    break;
                }
            }
            tracing::debug!(actor = %watch_request.actor_id, "policy stream closed");
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn status(
        &self,
        _request: Request<proto::StatusRequest>,
    ) -> Result<Response<proto::StatusReply>, Status> {
        let mut reply = self.shared.status.lock().map(|s| *s).unwrap_or_default();
        reply.connected_actors = self.shared.metrics.connected_actors.get().max(0) as u32;
        Ok(Response::new(reply))
    }
}
