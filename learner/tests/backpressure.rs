//! Flow control, not loss: while the ingest queue is full the learner stops reading a rollout
//! stream, so the sender stalls after a bounded number of fragments; once the queue drains,
//! every fragment arrives, in order, and the summary counts exactly those queued.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use tokio::sync::mpsc;
use tokio_stream::wrappers::TcpListenerStream;

use junction_common::fragment::RolloutFragment;
use junction_common::proto::{self, learner_client::LearnerClient, learner_server::LearnerServer};
use junction_core::config::RunConfig;
use junction_core::lcf_inputs;
use junction_core::spec::PROTOCOL_VERSION;
use junction_learner::hub::Shared;
use junction_learner::telemetry::metrics::LearnerMetrics;
use junction_learner::transport::grpc::LearnerService;
use junction_learner::transport::ingest::Ingest;

const QUEUE: usize = 2;
const SENT: usize = 40;

/// A valid fragment of the default scenario: `steps` × 30 agents × 91 observations (about
/// 2.3 MB encoded at 200 steps).
fn fragment(sequence: u64, steps: usize) -> proto::RolloutFragment {
    let (agents, obs_dim) = (30, 91);
    let cells = steps * agents;
    proto::RolloutFragment {
        protocol_version: PROTOCOL_VERSION,
        actor_id: "bp".into(),
        sequence,
        scenario: "intersection".into(),
        steps: steps as u32,
        agents: agents as u32,
        obs_dim: obs_dim as u32,
        action_dim: 2,
        obs: vec![0.5; cells * obs_dim],
        actions: vec![0.1; cells * 2],
        log_probs: vec![-1.0; cells],
        rewards: vec![0.3; cells],
        costs: vec![0.0; cells],
        dones: vec![0; cells],
        alive: vec![1; cells],
        bootstrap_obs: vec![0.5; agents * obs_dim],
        neighbour_offsets: vec![0; cells + 1],
        lcf_features: vec![0.5; cells * lcf_inputs::FEATURES],
        sim_seconds: 0.1 * steps as f32,
        ..Default::default()
    }
}

/// A learner's gRPC service alone (no trainer): the test holds the ingest queue.
async fn serve(queue: usize) -> (SocketAddr, Arc<Shared>, mpsc::Receiver<RolloutFragment>) {
    let config = RunConfig::default();
    let metrics = LearnerMetrics::new().expect("metrics");
    let shared = Arc::new(Shared::new(
        config,
        metrics,
        proto::PolicyWeights::default(),
    ));
    let (tx, rx) = mpsc::channel(queue);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("addr");
    let service = LearnerServer::new(LearnerService::new(Ingest::new(Arc::clone(&shared), tx)))
        .max_decoding_message_size(64 << 20);
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(service)
            .serve_with_incoming(TcpListenerStream::new(listener)),
    );
    (addr, shared, rx)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_queue_stalls_the_stream_and_loses_nothing() {
    let (addr, shared, mut queue) = serve(QUEUE).await;
    let mut client = LearnerClient::connect(format!("http://{addr}"))
        .await
        .expect("connect")
        .max_encoding_message_size(64 << 20);
    let one = fragment(0, 200);
    let size = prost::Message::encoded_len(&one);
    let pulled = Arc::new(AtomicUsize::new(0));
    let counter = Arc::clone(&pulled);
    let stream = tokio_stream::iter((0..SENT as u64).map(move |sequence| {
        counter.fetch_add(1, Ordering::Relaxed);
        let mut f = one.clone();
        f.sequence = sequence;
        f
    }));
    let push = tokio::spawn(async move { client.push_rollouts(stream).await });

    // Nobody reads the queue: the stream must stall.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let stalled_at = pulled.load(Ordering::Relaxed);
    eprintln!("stalled after {stalled_at} fragments of {size} bytes");
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert_eq!(pulled.load(Ordering::Relaxed), stalled_at, "still sending");
    // Queued, one decoded in the handler waiting for room, and what HTTP/2's windows (1 MiB
    // per stream by default) and the client's encoder hold: a few fragments, not 40.
    let in_flight = 2 + (2 << 20) / size + 2;
    assert!(
        stalled_at <= QUEUE + 1 + in_flight,
        "{stalled_at} fragments of {size} bytes left the client with a queue of {QUEUE}"
    );
    assert!(
        !push.is_finished(),
        "the stream completed while the queue was full"
    );
    assert_eq!(shared.metrics.ingest.fragments.get() as usize, QUEUE);

    // Drain: everything arrives, in order, and the summary counts all of it.
    let mut received = Vec::new();
    while received.len() < SENT {
        let f = tokio::time::timeout(Duration::from_secs(30), queue.recv())
            .await
            .expect("a fragment within 30 s")
            .expect("queue open");
        received.push(f.sequence);
    }
    let summary = push
        .await
        .expect("push task")
        .expect("the stream completes once drained")
        .into_inner();
    assert_eq!(received, (0..SENT as u64).collect::<Vec<_>>());
    assert_eq!(summary.accepted_fragments as usize, SENT);
    assert_eq!(summary.accepted_agent_steps as usize, SENT * 200 * 30);
    assert_eq!(
        shared.metrics.ingest.agent_steps_accepted.get(),
        summary.accepted_agent_steps
    );

    // A learner that stopped taking fragments (its queue closed at shutdown) refuses the
    // next one instead of pretending to accept it.
    queue.close();
    let mut client = LearnerClient::connect(format!("http://{addr}"))
        .await
        .expect("connect");
    let refused = client
        .push_rollouts(tokio_stream::iter(vec![fragment(SENT as u64, 2)]))
        .await
        .expect_err("queue closed");
    assert_eq!(refused.code(), tonic::Code::Unavailable, "{refused:?}");
    assert_eq!(
        shared.metrics.ingest.fragments.get() as usize,
        SENT,
        "not counted as accepted"
    );
}
