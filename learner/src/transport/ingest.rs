//! The one ingest path of every transport: count the bytes, check what they decoded to
//! (refusals counted by reason and logged once per reason), then the bounded queue the
//! trainer drains. gRPC and shared memory both end here, so a fragment is judged and counted
//! the same whichever way it came. A fragment counts as accepted (`fragments`,
//! `agent_steps_accepted`) only once the queue has taken it: from then on the trainer trains
//! on it or counts it as dropped.

use std::sync::Arc;

use tokio::sync::mpsc;

use junction_common::fragment::{FragmentError, RolloutFragment};
use junction_common::ledger::Event;
use junction_common::shm_layout::LayoutError;
use junction_core::spec::ACTION_DIM;

use crate::hub::Shared;
use crate::telemetry::labels::REJECT_SCENARIO;

/// A refused fragment: the metrics label and what was wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejection {
    pub reason: &'static str,
    pub detail: String,
}

impl From<FragmentError> for Rejection {
    fn from(e: FragmentError) -> Self {
        Rejection {
            reason: e.reason(),
            detail: e.to_string(),
        }
    }
}

impl From<LayoutError> for Rejection {
    fn from(e: LayoutError) -> Self {
        Rejection {
            reason: e.reason(),
            detail: e.to_string(),
        }
    }
}

/// The trainer has stopped taking fragments: the run is over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the learner has finished training and is shutting down")]
pub struct Closed;

#[derive(Clone)]
pub struct Ingest {
    shared: Arc<Shared>,
    queue: mpsc::Sender<RolloutFragment>,
}

impl Ingest {
    pub fn new(shared: Arc<Shared>, queue: mpsc::Sender<RolloutFragment>) -> Self {
        Ingest { shared, queue }
    }

    /// (obs_dim, action_dim) every fragment of this run must have: the policy's observation
    /// (CoPO's carries the LCF angle too).
    pub fn dims(&self) -> (usize, usize) {
        (self.shared.obs_dim(), ACTION_DIM)
    }

    /// Counts `bytes` received over `transport`, then checks what they decoded to against the
    /// run. A refusal is counted by reason, recorded in the ledger and logged (once per reason
    /// at warn level); `sender` (actor id, sequence number) names it there when the bytes
    /// did not decode to a fragment but said that much. What passes is not accepted yet: that
    /// takes [`Ingest::enqueue`] or [`Slot::fill`].
    pub fn admit(
        &self,
        transport: &'static str,
        bytes: usize,
        sender: Option<(&str, u64)>,
        decoded: Result<RolloutFragment, Rejection>,
    ) -> Result<RolloutFragment, Rejection> {
        let metrics = &self.shared.metrics;
        metrics
            .ingest
            .transport_bytes
            .with_label_values(&[transport])
            .inc_by(bytes as u64);
        match decoded {
            Ok(f) if f.scenario == self.shared.config.scenario.name => Ok(f),
            Ok(f) => {
                let rejection = Rejection {
                    reason: REJECT_SCENARIO,
                    detail: format!(
                        "fragment is from scenario {:?}, this run trains {:?}",
                        f.scenario, self.shared.config.scenario.name
                    ),
                };
                self.shared.reject(
                    rejection.reason,
                    Some((&f.actor_id, f.sequence)),
                    &rejection.detail,
                );
                Err(rejection)
            }
            Err(rejection) => {
                self.shared
                    .reject(rejection.reason, sender, &rejection.detail);
                Err(rejection)
            }
        }
    }

    /// Queues an admitted fragment, waiting while the queue is full (backpressure), and counts
    /// it as accepted; returns its agent-steps. A closed queue (the run is over) takes
    /// nothing, and nothing is counted.
    pub async fn enqueue(&self, fragment: RolloutFragment) -> Result<u64, Closed> {
        let permit = self.queue.reserve().await.map_err(|_| Closed)?;
        Ok(self.accept(permit, fragment))
    }

    /// A place in the queue if there is one now: a transport that must not block takes
    /// nothing from its peers without one.
    pub fn try_reserve(&self) -> Result<Option<Slot<'_>>, Closed> {
        match self.queue.try_reserve() {
            Ok(permit) => Ok(Some(Slot {
                permit,
                ingest: self,
            })),
            Err(mpsc::error::TrySendError::Full(())) => Ok(None),
            Err(mpsc::error::TrySendError::Closed(())) => Err(Closed),
        }
    }

    /// Records the fragment as accepted in the ledger before it is queued (a learner killed
    /// in between has it accepted and lost, which it is), queues it and counts it; returns its
    /// agent-steps.
    fn accept(&self, place: mpsc::Permit<'_, RolloutFragment>, fragment: RolloutFragment) -> u64 {
        let agent_steps = fragment.agent_steps() as u64;
        self.shared.ledger.record(&Event::Accepted {
            actor_id: &fragment.actor_id,
            seq: fragment.sequence,
            agent_steps,
        });
        place.send(fragment);
        let metrics = &self.shared.metrics;
        metrics.ingest.fragments.inc();
        metrics.ingest.agent_steps_accepted.inc_by(agent_steps);
        agent_steps
    }

    pub fn shared(&self) -> &Arc<Shared> {
        &self.shared
    }
}

/// A place reserved in the ingest queue. The trainer drains the queue until every such place
/// is filled or given back, so a fragment put here is trained on or counted as dropped even
/// when the run ends meanwhile.
pub struct Slot<'a> {
    permit: mpsc::Permit<'a, RolloutFragment>,
    ingest: &'a Ingest,
}

impl Slot<'_> {
    /// Queues an admitted fragment and counts it as accepted.
    pub fn fill(self, fragment: RolloutFragment) {
        self.ingest.accept(self.permit, fragment);
    }
}
