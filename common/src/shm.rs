//! The shared-memory transport's iceoryx2 services, in one place so that the learner (which
//! creates them) and its actors (which open them) agree on every setting. For a base name
//! `NAME` (`server.shm_name`, `actor --learner shm://NAME`):
//!
//! | service | pattern | direction | payload |
//! |---|---|---|---|
//! | `NAME/fragments` | publish-subscribe of bytes | actors → learner | [`crate::shm_layout`], written in place into the loaned sample |
//! | `NAME/weights` | publish-subscribe of bytes, history 1 | learner → actors | protobuf `PolicyWeights`, as gRPC's `WatchPolicy` sends it |
//! | `NAME/register` | request-response of bytes | actor ↔ learner | protobuf `RegisterRequest` → `RegisterReply`, as gRPC's `Register` |
//!
//! Fragments never overflow: the learner's subscriber buffer holds [`FRAGMENT_BUFFER`] samples
//! and a publisher whose sample does not fit waits (backpressure, like a gRPC stream the learner
//! stops reading). Weights overflow on purpose: an actor only wants the newest, and a late
//! joiner gets it from the history.
//!
//! Every process uses iceoryx2's built-in defaults with a directory and file prefix per user
//! (no config file is searched for, so none is reported missing), keeps its own signal handling, and logs through `tracing`. A process that
//! dies leaves stale resources behind; creating a node removes those of dead nodes, so a
//! restarted learner or actor starts cleanly.

use std::fmt::Debug;
use std::sync::Arc;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use iceoryx2::port::BackpressureAction;
use iceoryx2::port::client::Client;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::server::Server;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::{publish_subscribe, request_response};

use prost::Message;

use crate::fragment::RolloutFragment;
use crate::proto;
use crate::shm_layout::{self, LayoutError};
use junction_core::config::is_valid_shm_name;

pub type Ipc = ipc::Service;
pub type ShmNode = Node<Ipc>;
pub type BytesService = publish_subscribe::PortFactory<Ipc, [u8], ()>;
pub type RegisterService = request_response::PortFactory<Ipc, [u8], (), [u8], ()>;
pub type BytesPublisher = Publisher<Ipc, [u8], ()>;
pub type BytesSubscriber = Subscriber<Ipc, [u8], ()>;
pub type RegisterServer = Server<Ipc, [u8], (), [u8], ()>;
pub type RegisterClient = Client<Ipc, [u8], (), [u8], ()>;

/// Fragments the learner's subscriber buffers per actor before that actor's sends wait.
pub const FRAGMENT_BUFFER: usize = 2;
/// What an actor's publisher reserves per fragment sample before it knows the run (a default
/// fragment of 30 agents × 200 steps is about 2.7 MB); a larger fragment makes it grow.
pub const FRAGMENT_SAMPLE_BYTES: usize = 4 << 20;
/// How long a waiting publisher sleeps between retries: an eighth of the time waited so far,
/// within these bounds. A freed slot is taken within 50 ms, well before the learner has used
/// up the other fragment buffered for this actor (a CPU learner takes about one per second).
const BACKOFF_MIN: Duration = Duration::from_micros(20);
const BACKOFF_MAX: Duration = Duration::from_millis(50);
/// Registration messages are small; the ports grow if one is larger.
const REGISTER_BYTES: usize = 4096;

#[derive(Debug, thiserror::Error)]
pub enum ShmError {
    #[error("shared memory ({what}): {detail}")]
    Iceoryx { what: String, detail: String },
    #[error(
        "invalid shared-memory name {name:?}: use letters, digits, '-', '_' and '.', at most 200 characters"
    )]
    Name { name: String },
    #[error(transparent)]
    Layout(#[from] LayoutError),
    #[error("registration: {0}")]
    Registration(String),
}

/// Wraps an iceoryx2 error with what was being done.
pub fn failed<E: Debug>(what: impl Into<String>) -> impl FnOnce(E) -> ShmError {
    let what = what.into();
    move |e| ShmError::Iceoryx {
        what,
        detail: format!("{e:?}"),
    }
}

/// iceoryx2's built-in defaults, for every node of this process, except that each user gets a
/// directory (`/tmp/iceoryx2-<uid>/`) and file prefix (`iox2_<uid>_` in `/dev/shm`) of their
/// own: iceoryx2's shared `/tmp/iceoryx2/` belongs to whoever created it first (mode 0750), so
/// a second user of the host could not serve or join anything. A learner and its actors run as
/// one user and so agree. Also routes iceoryx2's log messages at warning level and above into
/// `tracing`.
fn config() -> &'static Config {
    static CONFIG: OnceLock<Config> = OnceLock::new();
    CONFIG.get_or_init(|| {
        set_log_level(LogLevel::Warn);
        let mut config = Config::default();
        // SAFETY: getuid has no preconditions and cannot fail.
        let uid = unsafe { libc::getuid() };
        // Both are short, plain ASCII: they are valid, and the defaults stay if not.
        if let Ok(root) = Path::new(format!("/tmp/iceoryx2-{uid}/").as_bytes()) {
            config.global.set_root_path(&root);
        }
        if let Ok(prefix) = FileName::new(format!("iox2_{uid}_").as_bytes()) {
            config.global.prefix = prefix;
        }
        config
    })
}

/// A node for this thread (iceoryx2 nodes and ports stay on the thread that made them).
/// Creating it removes the stale resources of dead processes.
pub fn node(label: &str) -> Result<ShmNode, ShmError> {
    let name = NodeName::new(label).map_err(failed(format!("node name {label:?}")))?;
    NodeBuilder::new()
        .name(&name)
        .config(config())
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .map_err(failed("creating a node"))
}

/// Which side opens the services: the learner creates them with their capacities, actors
/// only open them (and fail while there is no learner).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    Learner { max_actors: usize },
    Actor,
}

/// The three services of base name `base`.
pub struct Names {
    pub fragments: ServiceName,
    pub weights: ServiceName,
    pub register: ServiceName,
}

impl Names {
    pub fn new(base: &str) -> Result<Self, ShmError> {
        let name = |suffix: &str| {
            ServiceName::new(&format!("junction/{base}/{suffix}")).map_err(|_| ShmError::Name {
                name: base.to_string(),
            })
        };
        if !is_valid_shm_name(base) {
            return Err(ShmError::Name {
                name: base.to_string(),
            });
        }
        Ok(Names {
            fragments: name("fragments")?,
            weights: name("weights")?,
            register: name("register")?,
        })
    }
}

pub fn fragment_service(
    node: &ShmNode,
    names: &Names,
    side: Side,
) -> Result<BytesService, ShmError> {
    let builder = node
        .service_builder(&names.fragments)
        .publish_subscribe::<[u8]>()
        .enable_safe_overflow(false);
    match side {
        Side::Learner { max_actors } => builder
            .max_publishers(max_actors)
            .max_subscribers(1)
            .max_nodes(max_actors + 1)
            .history_size(0)
            .subscriber_max_buffer_size(FRAGMENT_BUFFER)
            .subscriber_max_borrowed_samples(1)
            .open_or_create()
            .map_err(failed(format!("creating {}", names.fragments))),
        Side::Actor => builder
            .open()
            .map_err(failed(format!("opening {}", names.fragments))),
    }
}

pub fn weights_service(
    node: &ShmNode,
    names: &Names,
    side: Side,
) -> Result<BytesService, ShmError> {
    let builder = node
        .service_builder(&names.weights)
        .publish_subscribe::<[u8]>()
        .enable_safe_overflow(true);
    match side {
        Side::Learner { max_actors } => builder
            .max_publishers(1)
            .max_subscribers(max_actors)
            .max_nodes(max_actors + 1)
            .history_size(1)
            .subscriber_max_buffer_size(1)
            .subscriber_max_borrowed_samples(1)
            .open_or_create()
            .map_err(failed(format!("creating {}", names.weights))),
        Side::Actor => builder
            .open()
            .map_err(failed(format!("opening {}", names.weights))),
    }
}

pub fn register_service(
    node: &ShmNode,
    names: &Names,
    side: Side,
) -> Result<RegisterService, ShmError> {
    let builder = node
        .service_builder(&names.register)
        .request_response::<[u8], [u8]>();
    match side {
        Side::Learner { max_actors } => builder
            .max_servers(1)
            .max_clients(max_actors)
            .max_nodes(max_actors + 1)
            .max_active_requests_per_client(1)
            .open_or_create()
            .map_err(failed(format!("creating {}", names.register))),
        Side::Actor => builder
            .open()
            .map_err(failed(format!("opening {}", names.register))),
    }
}

/// The learner's end of the fragment service.
pub fn fragment_subscriber(service: &BytesService) -> Result<BytesSubscriber, ShmError> {
    service
        .subscriber_builder()
        .buffer_size(FRAGMENT_BUFFER)
        .create()
        .map_err(failed(
            "subscribing to fragments (is another learner serving this shared-memory name?)",
        ))
}

/// An actor's end of the fragment service. Sends wait while the learner's buffer is full,
/// until the learner takes a sample or `abort` is set (the learner is gone or done).
pub fn fragment_publisher(
    service: &BytesService,
    typical_bytes: usize,
    abort: Arc<AtomicBool>,
) -> Result<BytesPublisher, ShmError> {
    service
        .publisher_builder()
        .initial_max_slice_len(typical_bytes.max(1))
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .max_loaned_samples(1)
        .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
        .set_backpressure_handler(move |info| {
            if abort.load(Ordering::Relaxed) {
                return BackpressureAction::DiscardDataAndFail;
            }
            // Sleep between retries instead of iceoryx2's default of thousands of
            // sched_yield calls: a waiting actor should leave its core to the learner.
            std::thread::sleep((info.elapsed_time / 8).clamp(BACKOFF_MIN, BACKOFF_MAX));
            BackpressureAction::Retry
        })
        .create()
        .map_err(failed("creating the fragment publisher"))
}

/// Writes `fragment` straight into a loaned sample and sends it; returns the bytes sent.
/// Waits while the learner's buffer is full (see [`fragment_publisher`]).
pub fn send_fragment(
    publisher: &BytesPublisher,
    fragment: &RolloutFragment,
) -> Result<usize, ShmError> {
    let len = shm_layout::encoded_len(fragment)?;
    let mut sample = publisher
        .loan_slice_uninit(len)
        .map_err(failed("loaning a fragment sample"))?;
    shm_layout::encode_into(fragment, sample.payload_mut())?;
    // SAFETY: encode_into returned Ok, so it wrote every byte of the loaned payload.
    let sample = unsafe { sample.assume_init() };
    sample.send().map_err(failed("sending a fragment"))?;
    Ok(len)
}

/// Publishes `bytes` (an encoded message) as one sample.
pub fn publish_bytes(publisher: &BytesPublisher, bytes: &[u8]) -> Result<(), ShmError> {
    publisher
        .loan_slice_uninit(bytes.len())
        .map_err(failed("loaning a sample"))?
        .write_from_slice(bytes)
        .send()
        .map_err(failed("publishing"))?;
    Ok(())
}

/// The learner's end of the weights service.
pub fn weights_publisher(
    service: &BytesService,
    typical_bytes: usize,
) -> Result<BytesPublisher, ShmError> {
    service
        .publisher_builder()
        .initial_max_slice_len(typical_bytes.max(1))
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .max_loaned_samples(1)
        .create()
        .map_err(failed(
            "creating the weights publisher (is another learner serving this shared-memory name?)",
        ))
}

/// An actor's end of the weights service; it receives the newest weights at once.
pub fn weights_subscriber(service: &BytesService) -> Result<BytesSubscriber, ShmError> {
    service
        .subscriber_builder()
        .buffer_size(1)
        .create()
        .map_err(failed("subscribing to weights"))
}

pub fn register_server(service: &RegisterService) -> Result<RegisterServer, ShmError> {
    service
        .server_builder()
        .initial_max_slice_len(REGISTER_BYTES)
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .create()
        .map_err(failed(
            "creating the registration server (is another learner serving this shared-memory name?)",
        ))
}

pub fn register_client(service: &RegisterService) -> Result<RegisterClient, ShmError> {
    service
        .client_builder()
        .initial_max_slice_len(REGISTER_BYTES)
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .create()
        .map_err(failed("creating the registration client"))
}

/// Whether a learner has subscribed to the fragment service.
pub fn learner_subscribed(fragments: &BytesService) -> bool {
    fragments.dynamic_config().number_of_subscribers() > 0
}

/// Whether a learner is serving `service` (its weights publisher is alive). Removes the
/// stale resources of dead processes first, so a learner killed with SIGKILL counts as gone.
pub fn learner_present(weights: &BytesService) -> bool {
    weights.try_cleanup_dead_nodes();
    weights.dynamic_config().number_of_publishers() > 0
}

/// Registers with the learner and waits up to `timeout` for its answer.
///
/// Call it only once this process's fragment publisher exists: the learner attaches its
/// subscriber to every publisher before it answers, and a sample sent to a subscriber that has
/// not attached yet may be lost (iceoryx2 drops it when the buffer is full and nobody is
/// attached to wait for).
pub fn register(
    client: &RegisterClient,
    hello: &proto::RegisterRequest,
    timeout: Duration,
    abort: &AtomicBool,
) -> Result<proto::RegisterReply, ShmError> {
    let request = hello.encode_to_vec();
    let pending = client
        .loan_slice_uninit(request.len())
        .map_err(failed("loaning a registration request"))?
        .write_from_slice(&request)
        .send()
        .map_err(failed("sending the registration"))?;
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline && !abort.load(Ordering::Relaxed) {
        if let Some(response) = pending
            .receive()
            .map_err(failed("receiving the registration reply"))?
        {
            return proto::RegisterReply::decode(response.payload()).map_err(|e| {
                ShmError::Registration(format!("the reply is not a RegisterReply: {e}"))
            });
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    Err(ShmError::Registration(format!(
        "the learner did not answer within {} s",
        timeout.as_secs()
    )))
}
