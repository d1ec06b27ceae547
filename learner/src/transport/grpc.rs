//! The gRPC face of the learner: actor registration (through the [`crate::hub`]), rollout
//! ingest (through [`super::ingest`]), weight broadcast and status.

use std::sync::Arc;

use prost::Message;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};

use junction_common::fragment::RolloutFragment;
use junction_common::grpc_codec::is_request_decode_error;
use junction_common::proto::{self, learner_server::Learner};

use super::ingest::{Ingest, Rejection};
use crate::hub::{Shared, check_name, check_version};
use crate::telemetry::labels::{REJECT_DECODE, TRANSPORT_GRPC};

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
        let _slot = shared.rollout_stream_slot()?;
        let _connected = ConnectedGuard::new(&shared.metrics.ingest.connected_actors);
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
                        shared.reject(REJECT_DECODE, None, status.message());
                    } else {
                        tracing::debug!(error = %status, "rollout stream ended with an error");
                    }
                    return Err(status);
                }
            };
            let bytes = message.encoded_len();
            let (actor, sequence) = (message.actor_id.clone(), message.sequence);
            let decoded = RolloutFragment::from_proto(message, dims).map_err(Rejection::from);
            let fragment = self
                .ingest
                .admit(TRANSPORT_GRPC, bytes, Some((&actor, sequence)), decoded)
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
        let slot = self.shared.policy_stream_slot()?;
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
        reply.connected_actors = self.shared.metrics.ingest.connected_actors.get().max(0) as u32;
        Ok(Response::new(reply))
    }
}
