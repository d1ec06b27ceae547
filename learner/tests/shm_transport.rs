//! The learner's shared-memory server against actor-side ports opened the way `actor` opens
//! them (`junction_common::shm`), in one process: same ingest as gRPC, backpressure instead of
//! loss, refusals counted, registration and weights. Every test uses its own service name.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use prost::Message;
use tokio::sync::mpsc;

use junction_common::fragment::RolloutFragment;
use junction_common::proto::{self, learner_client::LearnerClient, learner_server::LearnerServer};
use junction_common::shm::{self, Names, Side};
use junction_common::shm_layout;
use junction_core::config::RunConfig;
use junction_core::spec::PROTOCOL_VERSION;
use junction_learner::hub::Shared;
use junction_learner::telemetry::metrics::LearnerMetrics;
use junction_learner::transport::bench::realistic_fragment;
use junction_learner::transport::grpc::LearnerService;
use junction_learner::transport::ingest::Ingest;
use junction_learner::transport::shm::ShmServer;

fn small_run(queue: usize) -> RunConfig {
    let mut config = RunConfig::default();
    config.scenario.agents = 3;
    config.rollout.fragment_length = 6;
    config.learner.ingest_queue_fragments = queue;
    config
}

fn weights(version: u64) -> proto::PolicyWeights {
    proto::PolicyWeights {
        protocol_version: PROTOCOL_VERSION,
        version,
        format: "safetensors".into(),
        data: vec![version as u8; 1000],
        obs_dim: 91,
        action_dim: 2,
        run_finished: false,
        active_agents: 2,
    }
}

/// A learner's receiving side serving shared memory as a name unique to this test.
struct Learner {
    name: String,
    shared: Arc<Shared>,
    ingest: Ingest,
    queue: mpsc::Receiver<RolloutFragment>,
    server: Option<ShmServer>,
}

impl Learner {
    fn start(label: &str, config: RunConfig) -> Learner {
        let name = format!("test-{}-{label}", std::process::id());
        let metrics = LearnerMetrics::new().unwrap();
        let shared = Arc::new(Shared::new(config.clone(), metrics, weights(3)));
        let (tx, queue) = mpsc::channel(config.learner.ingest_queue_fragments);
        let ingest = Ingest::new(Arc::clone(&shared), tx);
        let server = ShmServer::start(ingest.clone(), &name, 4).unwrap();
        Learner {
            name,
            shared,
            ingest,
            queue,
            server: Some(server),
        }
    }

    fn names(&self) -> Names {
        Names::new(&self.name).unwrap()
    }

    /// The next queued fragment, or None after `timeout`.
    fn next(&mut self, timeout: Duration) -> Option<RolloutFragment> {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            match self.queue.try_recv() {
                Ok(fragment) => return Some(fragment),
                Err(_) => std::thread::sleep(Duration::from_millis(2)),
            }
        }
        None
    }

    fn rejected(&self, reason: &str) -> u64 {
        self.shared
            .metrics
            .ingest
            .fragments_rejected
            .with_label_values(&[reason])
            .get()
    }

    fn bytes(&self, transport: &str) -> u64 {
        self.shared
            .metrics
            .ingest
            .transport_bytes
            .with_label_values(&[transport])
            .get()
    }
}

/// What an actor's sender thread holds: its fragment publisher, registered (the learner has
/// attached to it).
struct ActorPorts {
    reply: proto::RegisterReply,
    publisher: shm::BytesPublisher,
    _services: (shm::BytesService, shm::RegisterService),
    _node: shm::ShmNode,
}

fn connect_actor(names: &Names) -> ActorPorts {
    let node = shm::node("junction-test-actor").unwrap();
    let fragments = shm::fragment_service(&node, names, Side::Actor).unwrap();
    let abort = Arc::new(AtomicBool::new(false));
    let publisher = shm::fragment_publisher(&fragments, 4096, Arc::clone(&abort)).unwrap();
    let register = shm::register_service(&node, names, Side::Actor).unwrap();
    let client = shm::register_client(&register).unwrap();
    let hello = proto::RegisterRequest {
        protocol_version: PROTOCOL_VERSION,
        actor_name: "test".into(),
        scenes: 1,
        instance: String::new(),
    };
    let reply = shm::register(&client, &hello, Duration::from_secs(10), &abort).unwrap();
    assert!(!reply.actor_id.is_empty());
    ActorPorts {
        reply,
        publisher,
        _services: (fragments, register),
        _node: node,
    }
}

/// An actor sending `fragments` from a thread of its own, as an actor's sender thread does;
/// counts each send that has returned. Like a real actor it stays connected (samples not yet
/// taken by the learner go with a departing publisher) until told to leave.
struct Sender {
    sent: Arc<AtomicUsize>,
    leave: Arc<AtomicBool>,
    thread: std::thread::JoinHandle<()>,
}

impl Sender {
    fn start(names: Names, fragments: Vec<RolloutFragment>) -> Sender {
        let sent = Arc::new(AtomicUsize::new(0));
        let leave = Arc::new(AtomicBool::new(false));
        let thread = {
            let (sent, leave) = (Arc::clone(&sent), Arc::clone(&leave));
            std::thread::spawn(move || {
                let actor = connect_actor(&names);
                for fragment in &fragments {
                    shm::send_fragment(&actor.publisher, fragment).unwrap();
                    sent.fetch_add(1, Ordering::SeqCst);
                }
                while !leave.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(5));
                }
            })
        };
        Sender {
            sent,
            leave,
            thread,
        }
    }

    fn sent(&self) -> usize {
        self.sent.load(Ordering::SeqCst)
    }

    fn leave(self) {
        self.leave.store(true, Ordering::SeqCst);
        self.thread.join().unwrap();
    }
}

/// Publishes raw bytes on the fragment service (what a broken or hostile actor could send);
/// the returned ports keep them deliverable.
/// A client of a gRPC learner service on 127.0.0.1 feeding `ingest` (the runtime's task
/// serves it until the runtime is dropped).
async fn grpc_client(ingest: &Ingest) -> LearnerClient<tonic::transport::Channel> {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let service = LearnerServer::new(LearnerService::new(ingest.clone()));
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(service)
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)),
    );
    LearnerClient::connect(format!("http://{addr}"))
        .await
        .unwrap()
}

fn publish_raw(names: &Names, messages: &[Vec<u8>]) -> ActorPorts {
    let actor = connect_actor(names);
    for bytes in messages {
        shm::publish_bytes(&actor.publisher, bytes).unwrap();
    }
    actor
}

#[test]
fn a_fragment_sent_over_grpc_and_over_shm_arrives_as_equal_values() {
    let config = small_run(4);
    let mut learner = Learner::start("equal", config.clone());
    let fragment = realistic_fragment(&config, 7);

    let actor = Sender::start(learner.names(), vec![fragment.clone()]);
    let via_shm = learner
        .next(Duration::from_secs(10))
        .expect("no fragment over shm");
    actor.leave();

    let runtime = tokio::runtime::Runtime::new().unwrap();
    let message = fragment.clone().into_proto();
    let grpc_bytes = message.encoded_len();
    runtime.block_on(async {
        let mut client = grpc_client(&learner.ingest).await;
        let summary = client
            .push_rollouts(tokio_stream::iter(vec![message]))
            .await
            .unwrap()
            .into_inner();
        assert_eq!(summary.accepted_fragments, 1);
    });
    let via_grpc = learner
        .next(Duration::from_secs(10))
        .expect("no fragment over gRPC");

    assert_eq!(via_shm, fragment);
    assert_eq!(via_grpc, fragment);
    assert_eq!(via_shm, via_grpc);
    assert_eq!(
        learner.bytes("shm"),
        shm_layout::encoded_len(&fragment).unwrap() as u64
    );
    assert_eq!(learner.bytes("grpc"), grpc_bytes as u64);
    assert_eq!(learner.shared.metrics.ingest.fragments.get(), 2);
    assert_eq!(
        learner.shared.metrics.ingest.agent_steps_accepted.get(),
        2 * fragment.agent_steps() as u64
    );
}

#[test]
fn a_full_learner_makes_shm_publishers_wait_and_loses_nothing() {
    let queue = 2;
    let config = small_run(queue);
    let mut learner = Learner::start("backpressure", config.clone());
    let total = 12;
    let fragments: Vec<RolloutFragment> = (0..total)
        .map(|i| {
            let mut f = realistic_fragment(&config, i as u64);
            f.sequence = i as u64;
            f
        })
        .collect();
    let actor = Sender::start(learner.names(), fragments.clone());

    // Nobody drains the queue: it fills, then the subscriber's buffer, then the publisher's
    // next send waits instead of dropping anything.
    let stalled_at = queue + shm::FRAGMENT_BUFFER;
    let deadline = Instant::now() + Duration::from_secs(20);
    while actor.sent() < stalled_at && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(
        actor.sent(),
        stalled_at,
        "the publisher should wait once queue and buffer are full"
    );
    assert_eq!(learner.queue.len(), queue);
    // Accepted means queued: the fragments waiting in the subscriber's buffer are not yet.
    assert_eq!(learner.shared.metrics.ingest.fragments.get(), queue as u64);

    // A slow learner: every fragment arrives, in order, none rejected or dropped.
    let mut received = Vec::new();
    while received.len() < total {
        let fragment = learner
            .next(Duration::from_secs(20))
            .unwrap_or_else(|| panic!("only {} of {total} fragments arrived", received.len()));
        received.push(fragment);
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(actor.sent(), total);
    actor.leave();
    assert_eq!(received, fragments);
    assert_eq!(learner.shared.metrics.ingest.fragments.get(), total as u64);
    assert_eq!(
        learner.shared.metrics.ingest.agent_steps_accepted.get(),
        fragments
            .iter()
            .map(|f| f.agent_steps() as u64)
            .sum::<u64>()
    );
    assert!(
        junction_common::fragment::FragmentError::REASONS
            .iter()
            .chain(&["decode", "scenario"])
            .all(|r| learner.rejected(r) == 0)
    );
}

#[test]
fn other_layout_versions_and_broken_buffers_are_refused_counted_and_survived() {
    let config = small_run(4);
    let mut learner = Learner::start("refusals", config.clone());
    let fragment = realistic_fragment(&config, 1);
    let valid = shm_layout::encode(&fragment).unwrap();
    let mut other_version = valid.clone();
    other_version[4..8].copy_from_slice(&(shm_layout::LAYOUT_VERSION + 1).to_ne_bytes());
    let truncated = valid[..valid.len() / 2].to_vec();
    let mut other_scenario = fragment.clone();
    other_scenario.scenario = "roundabout".into();
    let other_scenario = shm_layout::encode(&other_scenario).unwrap();
    let mut nan = fragment.clone();
    nan.rewards[3] = f32::NAN;
    let nan = shm_layout::encode(&nan).unwrap();
    let _actor = publish_raw(
        &learner.names(),
        &[
            other_version.clone(),
            truncated.clone(),
            other_scenario.clone(),
            nan.clone(),
            valid.clone(),
        ],
    );

    let arrived = learner
        .next(Duration::from_secs(10))
        .expect("the valid fragment after the refused ones");
    assert_eq!(arrived, fragment);
    assert_eq!(learner.rejected("version"), 1);
    assert_eq!(learner.rejected("decode"), 1);
    assert_eq!(learner.rejected("scenario"), 1);
    assert_eq!(learner.rejected("non_finite"), 1);
    assert_eq!(learner.shared.metrics.ingest.fragments.get(), 1);
    assert_eq!(
        learner.shared.metrics.ingest.agent_steps_accepted.get(),
        fragment.agent_steps() as u64
    );
    let all_bytes = [other_version, truncated, other_scenario, nan, valid]
        .iter()
        .map(Vec::len)
        .sum::<usize>();
    assert_eq!(learner.bytes("shm"), all_bytes as u64);
    assert!(learner.next(Duration::from_millis(200)).is_none());
}

#[test]
fn a_closed_queue_accepts_nothing_over_either_transport() {
    let config = small_run(4);
    let mut learner = Learner::start("closed", config.clone());
    // The trainer has finished: it closed the queue.
    learner.queue.close();
    let fragment = realistic_fragment(&config, 5);

    let actor = Sender::start(learner.names(), vec![fragment.clone()]);
    let deadline = Instant::now() + Duration::from_secs(10);
    while actor.sent() < 1 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(10));
    }
    assert_eq!(actor.sent(), 1, "the send fits the subscriber's buffer");
    std::thread::sleep(Duration::from_millis(300));
    actor.leave();

    let runtime = tokio::runtime::Runtime::new().unwrap();
    let status = runtime.block_on(async {
        let mut client = grpc_client(&learner.ingest).await;
        client
            .push_rollouts(tokio_stream::iter(vec![fragment.clone().into_proto()]))
            .await
            .unwrap_err()
    });
    assert_eq!(status.code(), tonic::Code::Unavailable, "{status:?}");

    let metrics = &learner.shared.metrics;
    assert_eq!(metrics.ingest.fragments.get(), 0);
    assert_eq!(metrics.ingest.agent_steps_accepted.get(), 0);
    // Not accepted, and not the data's fault either.
    assert!(
        junction_common::fragment::FragmentError::REASONS
            .iter()
            .chain(&["decode", "scenario"])
            .all(|r| learner.rejected(r) == 0)
    );
    assert!(learner.next(Duration::from_millis(100)).is_none());
}

#[test]
fn copo_runs_take_fragments_with_the_lcf_column_over_shm() {
    let mut config = small_run(4);
    config.learner.algo = junction_core::config::AlgoKind::Copo;
    let mut learner = Learner::start("copo", config.clone());
    let fragment = realistic_fragment(&config, 9);
    assert_eq!(fragment.obs_dim, config.scenario.obs_dim() + 1);
    let scenario_sized = realistic_fragment(&small_run(4), 9);
    let actor = connect_actor(&learner.names());
    // Registration over shared memory tells the actor what the policy takes, as over gRPC.
    assert_eq!(actor.reply.obs_dim as usize, config.policy_obs_dim());
    shm::send_fragment(&actor.publisher, &scenario_sized).unwrap();
    shm::send_fragment(&actor.publisher, &fragment).unwrap();
    let arrived = learner
        .next(Duration::from_secs(10))
        .expect("the CoPO-shaped fragment");
    assert_eq!(arrived, fragment);
    // A fragment without the LCF column does not fit the run.
    assert_eq!(learner.rejected("shape"), 1);
    assert_eq!(learner.shared.metrics.ingest.fragments.get(), 1);
}

#[test]
fn actors_register_and_follow_the_newest_weights_over_shm() {
    let config = small_run(4);
    let learner = Learner::start("register", config.clone());
    let names = learner.names();
    let node = shm::node("junction-test-actor").unwrap();
    let register = shm::register_service(&node, &names, Side::Actor).unwrap();
    let client = shm::register_client(&register).unwrap();
    let ask_as = |protocol_version: u32, actor_name: &str| -> proto::RegisterReply {
        let hello = proto::RegisterRequest {
            protocol_version,
            actor_name: actor_name.into(),
            scenes: 2,
            instance: String::new(),
        }
        .encode_to_vec();
        let pending = client
            .loan_slice_uninit(hello.len())
            .unwrap()
            .write_from_slice(&hello)
            .send()
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if let Some(response) = pending.receive().unwrap() {
                return proto::RegisterReply::decode(response.payload()).unwrap();
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        panic!("no registration reply");
    };
    let ask = |protocol_version: u32| ask_as(protocol_version, "test");
    let first = ask(PROTOCOL_VERSION);
    let second = ask(PROTOCOL_VERSION);
    assert!(first.actor_id.starts_with("actor-"), "{first:?}");
    assert_ne!(first.actor_id, second.actor_id);
    assert_eq!(first.fragment_length, 6);
    assert_eq!(first.obs_dim, 91);
    assert_eq!(first.run_seed, config.run.seed);
    assert_eq!(
        junction_core::config::ScenarioConfig::from_toml(&first.scenario_toml).unwrap(),
        config.scenario
    );
    let refused = ask(PROTOCOL_VERSION + 1);
    assert!(refused.actor_id.is_empty());
    assert_eq!(refused.protocol_version, PROTOCOL_VERSION);
    // Names end up in logs: an absurd one is refused as over gRPC.
    let long_name = "x".repeat(junction_core::spec::MAX_NAME_BYTES + 1);
    assert!(ask_as(PROTOCOL_VERSION, &long_name).actor_id.is_empty());

    // A late joiner gets the current weights from the history, then every newer version.
    let weights_service = shm::weights_service(&node, &names, Side::Actor).unwrap();
    assert!(shm::learner_present(&weights_service));
    let subscriber = shm::weights_subscriber(&weights_service).unwrap();
    let next = || -> proto::PolicyWeights {
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if let Some(sample) = subscriber.receive().unwrap() {
                return proto::PolicyWeights::decode(sample.payload()).unwrap();
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        panic!("no weights");
    };
    assert_eq!(next(), weights(3));
    learner.shared.weights.send_replace(Arc::new(weights(4)));
    assert_eq!(next(), weights(4));
    let mut last = weights(5);
    last.run_finished = true;
    learner.shared.weights.send_replace(Arc::new(last.clone()));
    assert_eq!(next(), last);

    // A stopped learner is seen as gone.
    let mut learner = learner;
    drop(learner.server.take());
    assert!(!shm::learner_present(&weights_service));
}

#[test]
fn a_second_learner_on_the_same_name_is_refused() {
    let learner = Learner::start("twice", small_run(2));
    let (tx, _rx) = mpsc::channel(2);
    let second = Ingest::new(Arc::clone(&learner.shared), tx);
    let err = match ShmServer::start(second, &learner.name, 4) {
        Ok(_) => panic!("a second learner served the same name"),
        Err(e) => format!("{e:#}"),
    };
    assert!(err.contains("another learner"), "{err}");
}
