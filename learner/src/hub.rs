//! The hub every part of the learner meets at: the run configuration, the metrics, the newest
//! weights (which every policy stream and the shared-memory server follow), the answer to
//! `Status`, actor registration (ids unique across transports), stream slots and the
//! once-per-reason log of refused fragments, and the fragment ledger every part of the
//! learner appends to. The transports (`transport::grpc`,
//! `transport::shm`) and the trainer hold it as `Arc<Shared>`.

use std::collections::HashSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::{OwnedSemaphorePermit, Semaphore, watch};
use tonic::Status;

use junction_common::fragment::RolloutFragment;
use junction_common::ledger::{Event, Ledger};
use junction_common::proto;
use junction_core::config::RunConfig;
use junction_core::spec::{ACTION_DIM, MAX_NAME_BYTES, OBS_LAYOUT_VERSION, PROTOCOL_VERSION};

use crate::telemetry::labels::REFUSED_STREAM_LIMIT;
use crate::telemetry::metrics::LearnerMetrics;

/// State the transports share with the training loop.
pub struct Shared {
    pub config: RunConfig,
    pub metrics: LearnerMetrics,
    /// The newest weights; every WatchPolicy stream follows it.
    pub weights: watch::Sender<Arc<proto::PolicyWeights>>,
    pub status: Mutex<proto::StatusReply>,
    /// What happened to each fragment, for the reconciliation across restarts (FAULTS.md).
    pub ledger: Ledger,
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
            ledger: Ledger::off(),
            next_actor: AtomicU64::new(1),
            logged_rejections: Mutex::new(HashSet::new()),
            rollout_streams: Arc::new(Semaphore::new(config.server.max_rollout_streams)),
            policy_streams: Arc::new(Semaphore::new(config.server.max_rollout_streams)),
            config,
        }
    }

    /// Records every fragment's fate in `ledger` from now on.
    pub fn with_ledger(mut self, ledger: Ledger) -> Self {
        self.ledger = ledger;
        self
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

    /// A rollout stream's slot, or RESOURCE_EXHAUSTED (counted) when all are taken.
    pub(crate) fn rollout_stream_slot(&self) -> Result<OwnedSemaphorePermit, Status> {
        self.stream_slot(&self.rollout_streams, "rollout")
    }

    /// A policy stream's slot, or RESOURCE_EXHAUSTED (counted) when all are taken.
    pub(crate) fn policy_stream_slot(&self) -> Result<OwnedSemaphorePermit, Status> {
        self.stream_slot(&self.policy_streams, "policy")
    }

    /// One of the `kind` stream slots, or RESOURCE_EXHAUSTED (counted) when all are taken.
    fn stream_slot(
        &self,
        slots: &Arc<Semaphore>,
        kind: &str,
    ) -> Result<OwnedSemaphorePermit, Status> {
        Arc::clone(slots).try_acquire_owned().map_err(|_| {
            self.metrics
                .ingest.requests_refused
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
        check_name("instance", &hello.instance)?;
        let actor_id = format!("actor-{}", self.next_actor.fetch_add(1, Ordering::Relaxed));
        tracing::info!(actor = %actor_id, name = %hello.actor_name, instance = %hello.instance, scenes = hello.scenes, transport, "actor registered");
        self.ledger.record(&Event::Register {
            actor_id: &actor_id,
            instance: &hello.instance,
            transport,
        });
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

    /// Counts `fragments` (accepted earlier) as not trained on, for `reason`, in the metrics
    /// and the ledger.
    pub fn drop_fragments(&self, reason: &'static str, fragments: &[RolloutFragment]) {
        self.metrics.ingest.record_drop(reason, fragments);
        for fragment in fragments {
            self.ledger.record(&Event::Dropped {
                actor_id: &fragment.actor_id,
                seq: fragment.sequence,
                reason,
            });
        }
    }

    /// Counts a refused fragment, records it in the ledger with the sender's actor id and
    /// sequence number where the bytes said, and logs its cause once at warn level.
    pub(crate) fn reject(&self, reason: &'static str, sender: Option<(&str, u64)>, detail: &str) {
        self.ledger.record(&Event::Rejected {
            actor_id: sender.map(|(actor, _)| actor),
            seq: sender.map(|(_, seq)| seq),
            reason,
        });
        let actor = sender.map_or("?", |(actor, _)| actor);
        self.metrics
            .ingest
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
    #[error(
        "protocol version {0} is not supported (this learner speaks {PROTOCOL_VERSION}): run actors from the learner's Junction release"
    )]
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

pub(crate) fn check_version(got: u32) -> Result<(), Refusal> {
    if got == PROTOCOL_VERSION {
        Ok(())
    } else {
        Err(Refusal::Version(got))
    }
}

/// Names and ids from peers end up in logs: bounded, or refused.
pub(crate) fn check_name(field: &'static str, value: &str) -> Result<(), Refusal> {
    if value.len() > MAX_NAME_BYTES {
        return Err(Refusal::NameTooLong {
            field,
            len: value.len(),
        });
    }
    Ok(())
}
