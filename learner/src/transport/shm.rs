//! The learner's shared-memory server (iceoryx2; services in `junction_common::shm`): one
//! thread that owns the node and its ports, answers registrations, publishes every new policy
//! version and feeds received fragments into the same ingest path as gRPC.
//!
//! An actor creates its fragment publisher before it registers, and the server attaches to
//! it before answering, so no fragment can reach an unattached subscriber (iceoryx2 would drop
//! it once the buffer is full).
//!
//! Backpressure: a fragment is taken from the subscriber only when the ingest queue has room
//! for it. While the queue is full the subscriber's buffer fills, and then each actor's next
//! send waits in iceoryx2 until the learner takes a sample: actors slow down, nothing is
//! dropped.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Context;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::PortFactory;
use prost::Message;

use junction_common::proto;
use junction_common::shm::{self, Names, Side};
use junction_common::shm_layout;
use junction_core::spec::PROTOCOL_VERSION;

use super::ingest::{Ingest, Rejection};
use crate::hub::Shared;
use crate::telemetry::labels::TRANSPORT_SHM;

/// How often the server counts connected actors and clears dead processes' resources.
const HOUSEKEEPING: Duration = Duration::from_secs(1);
/// Longest sleep of an idle server: bounds the latency of a fragment, a registration or a
/// weights version while nothing else happens.
const MAX_IDLE_SLEEP: Duration = Duration::from_millis(4);

/// The running server; stops (and gives up the services) when stopped or dropped.
pub struct ShmServer {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl ShmServer {
    /// Creates the services `name/*` and serves them on a thread of their own. Fails here,
    /// not later, when they cannot be served (another learner uses `name`, no /dev/shm).
    pub fn start(ingest: Ingest, name: &str, max_actors: usize) -> anyhow::Result<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let thread = {
            let stop = Arc::clone(&stop);
            let name = name.to_string();
            std::thread::Builder::new()
                .name("shm-server".into())
                .spawn(move || match Ports::open(&name, max_actors, &ingest) {
                    Ok(ports) => {
                        let _ = ready_tx.send(Ok(()));
                        serve(&ports, &ingest, &stop);
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                    }
                })
                .context("starting the shared-memory server thread")?
        };
        ready_rx
            .recv()
            .context("the shared-memory server thread ended during start-up")?
            .with_context(|| format!("serving shared memory as {name:?}"))?;
        Ok(ShmServer {
            stop,
            thread: Some(thread),
        })
    }

    pub fn stop(mut self) {
        self.shut_down();
    }

    fn shut_down(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl Drop for ShmServer {
    fn drop(&mut self) {
        self.shut_down();
    }
}

struct Ports {
    // Dropped last: the ports below belong to it.
    _node: shm::ShmNode,
    fragments: shm::BytesService,
    subscriber: shm::BytesSubscriber,
    _weights_service: shm::BytesService,
    weights: shm::BytesPublisher,
    _register_service: shm::RegisterService,
    register: shm::RegisterServer,
}

impl Ports {
    fn open(name: &str, max_actors: usize, ingest: &Ingest) -> anyhow::Result<Self> {
        let names = Names::new(name)?;
        let node = shm::node("junction-learner")?;
        let side = Side::Learner { max_actors };
        let fragments = shm::fragment_service(&node, &names, side)?;
        let weights_service = shm::weights_service(&node, &names, side)?;
        let register_service = shm::register_service(&node, &names, side)?;
        let subscriber = shm::fragment_subscriber(&fragments)?;
        let weights_bytes = ingest.shared().weights.borrow().encoded_len();
        let weights = shm::weights_publisher(&weights_service, weights_bytes)?;
        let register = shm::register_server(&register_service)?;
        Ok(Ports {
            _node: node,
            fragments,
            subscriber,
            _weights_service: weights_service,
            weights,
            _register_service: register_service,
            register,
        })
    }
}

fn serve(ports: &Ports, ingest: &Ingest, stop: &AtomicBool) {
    let shared = ingest.shared();
    let mut weights = shared.weights.subscribe();
    weights.mark_changed();
    let dims = Some(ingest.dims());
    let mut taking = true;
    let mut connected = 0i64;
    let mut last_housekeeping: Option<Instant> = None;
    let mut idle_sleep = Duration::ZERO;
    let mut warned = false;
    let mut warn_once = |what: &str, error: &dyn std::fmt::Debug| {
        if !std::mem::replace(&mut warned, true) {
            tracing::warn!(error = ?error, "shared memory: {what} (further errors log at debug)");
        } else {
            tracing::debug!(error = ?error, "shared memory: {what}");
        }
    };
    while !stop.load(Ordering::Relaxed) {
        let mut busy = false;

        loop {
            match ports.register.receive() {
                Ok(Some(request)) => {
                    busy = true;
                    // Attach to the new actor's publisher before it may send (see
                    // `shm::register`).
                    if let Err(e) = ports.subscriber.update_connections() {
                        warn_once("connecting to a new actor", &e);
                    }
                    let reply = registration_reply(shared, request.payload());
                    match request.loan_slice_uninit(reply.len()) {
                        Ok(response) => {
                            if let Err(e) = response.write_from_slice(&reply).send() {
                                warn_once("answering a registration", &e);
                            }
                        }
                        Err(e) => warn_once("answering a registration", &e),
                    }
                }
                Ok(None) => break,
                Err(e) => {
                    warn_once("receiving registrations", &e);
                    break;
                }
            }
        }

        if weights.has_changed().unwrap_or(false) {
            busy = true;
            let message = weights.borrow_and_update().encode_to_vec();
            if let Err(e) = shm::publish_bytes(&ports.weights, &message) {
                warn_once("publishing weights", &e);
            }
        }
        // Delivers the newest weights (the history) to actors that joined since.
        if let Err(e) = ports.weights.update_connections() {
            warn_once("connecting weight subscribers", &e);
        }

        while taking {
            let slot = match ingest.try_reserve() {
                Ok(Some(slot)) => slot,
                Ok(None) => break,
                Err(_) => {
                    // The trainer is done; actors wait until the run-finished weights reach them.
                    taking = false;
                    break;
                }
            };
            match ports.subscriber.receive() {
                Ok(Some(sample)) => {
                    busy = true;
                    let bytes = sample.payload();
                    let decoded = shm_layout::decode(bytes, dims).map_err(Rejection::from);
                    let len = bytes.len();
                    drop(sample);
                    if let Ok(fragment) = ingest.admit(TRANSPORT_SHM, len, None, decoded) {
                        slot.fill(fragment);
                    }
                }
                Ok(None) => break,
                Err(e) => {
                    warn_once("receiving fragments", &e);
                    break;
                }
            }
        }

        if last_housekeeping.is_none_or(|t| t.elapsed() >= HOUSEKEEPING) {
            last_housekeeping = Some(Instant::now());
            // Actors killed without a goodbye leave their ports behind until someone cleans up.
            ports.fragments.try_cleanup_dead_nodes();
            let now = ports.fragments.dynamic_config().number_of_publishers() as i64;
            shared.metrics.ingest.connected_actors.add(now - connected);
            connected = now;
        }

        if busy {
            idle_sleep = Duration::ZERO;
        } else {
            idle_sleep = (idle_sleep * 2).clamp(Duration::from_micros(100), MAX_IDLE_SLEEP);
            std::thread::sleep(idle_sleep);
        }
    }
    shared.metrics.ingest.connected_actors.sub(connected);
}

/// The encoded `RegisterReply` to an encoded `RegisterRequest`: the run configuration, or a
/// refusal (no actor id, this learner's protocol version) that the actor reports.
fn registration_reply(shared: &Shared, request: &[u8]) -> Vec<u8> {
    let reply = match proto::RegisterRequest::decode(request) {
        Ok(hello) => shared.register(&hello, TRANSPORT_SHM).unwrap_or_else(|refusal| {
            tracing::warn!(name = %hello.actor_name, "shared-memory registration refused: {refusal}");
            refused()
        }),
        Err(e) => {
            tracing::warn!(error = %e, "undecodable shared-memory registration refused");
            refused()
        }
    };
    reply.encode_to_vec()
}

fn refused() -> proto::RegisterReply {
    proto::RegisterReply {
        protocol_version: PROTOCOL_VERSION,
        ..Default::default()
    }
}
