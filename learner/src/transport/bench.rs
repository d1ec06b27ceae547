//! `learner bench-transport`: fragment throughput of each transport on this host, through
//! the learner's real receiving side (shared-memory server or gRPC service, decode,
//! validation, ingest queue) with a sender in the same process standing in for an actor.
//! Fragments have the run's shape (default: 30 agents × 200 steps × 91 observations).

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use prost::Message;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tokio::sync::mpsc;
use tokio_stream::wrappers::TcpListenerStream;

use junction_common::fragment::{FragmentError, RolloutFragment};
use junction_common::proto::{self, learner_client::LearnerClient, learner_server::LearnerServer};
use junction_common::shm::{self, Names, Side};
use junction_common::shm_layout;
use junction_common::{
    GRPC_CONNECTION_WINDOW_BYTES, GRPC_MAX_FRAME_BYTES, GRPC_STREAM_WINDOW_BYTES,
};
use junction_core::config::RunConfig;
use junction_core::episode::{EpisodeStats, Outcome};
use junction_core::lcf_inputs;
use junction_core::spec::{ACTION_DIM, PROTOCOL_VERSION};

use super::grpc::LearnerService;
use super::ingest::Ingest;
use super::shm::ShmServer;
use crate::bench::{SYNTHETIC_NEIGHBOURS, ring_neighbours};
use crate::hub::Shared;
use crate::telemetry::labels::{REJECT_DECODE, REJECT_SCENARIO};
use crate::telemetry::metrics::LearnerMetrics;

#[derive(Debug, serde::Serialize)]
pub struct TransportReport {
    pub bench: &'static str,
    pub transport: &'static str,
    pub fragments: usize,
    pub agents: usize,
    pub steps: usize,
    pub obs_dim: usize,
    /// Encoded size of one fragment on this transport.
    pub fragment_bytes: usize,
    pub seconds: f64,
    pub fragments_per_s: f64,
    /// Encoded bytes received per second, in 10⁹ bytes.
    pub gb_per_s: f64,
}

impl TransportReport {
    fn new(
        transport: &'static str,
        fragment: &RolloutFragment,
        count: usize,
        fragment_bytes: usize,
        seconds: f64,
    ) -> Self {
        TransportReport {
            bench: "transport",
            transport,
            fragments: count,
            agents: fragment.agents,
            steps: fragment.steps,
            obs_dim: fragment.obs_dim,
            fragment_bytes,
            seconds,
            fragments_per_s: count as f64 / seconds,
            gb_per_s: (count * fragment_bytes) as f64 / seconds / 1e9,
        }
    }
}

/// A valid fragment of the run's shape with realistic content: observations in [0, 1], every
/// slot's agent finishing once (and a new one taking its place), 8 neighbours per agent.
pub fn realistic_fragment(config: &RunConfig, seed: u64) -> RolloutFragment {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (steps, agents) = (
        config.rollout.fragment_length,
        config.scenario.agent_count(),
    );
    // What the run's policy takes (CoPO's observation carries the LCF angle too).
    let obs_dim = config.policy_obs_dim();
    let cells = steps * agents;
    let (neighbour_offsets, neighbour_ids) = ring_neighbours(steps, agents, SYNTHETIC_NEIGHBOURS);
    let mut uniform = |n: usize, low: f32, high: f32| -> Vec<f32> {
        (0..n).map(|_| rng.gen_range(low..high)).collect()
    };
    let mut dones = vec![false; cells];
    for slot in 0..agents {
        dones[(slot * 7 % steps) * agents + slot] = true;
    }
    RolloutFragment {
        actor_id: "actor-bench".into(),
        scenario: config.scenario.name.clone(),
        steps,
        agents,
        obs_dim,
        action_dim: ACTION_DIM,
        obs: uniform(cells * obs_dim, 0.0, 1.0),
        actions: uniform(cells * ACTION_DIM, -1.5, 1.5),
        log_probs: uniform(cells, -4.0, 0.0),
        rewards: uniform(cells, -1.0, 2.0),
        costs: uniform(cells, 0.0, 0.1),
        dones,
        alive: vec![true; cells],
        bootstrap_obs: uniform(agents * obs_dim, 0.0, 1.0),
        neighbour_offsets,
        neighbour_ids,
        lcf_features: uniform(cells * lcf_inputs::FEATURES, 0.0, 1.0),
        episodes: (0..agents)
            .map(|_| EpisodeStats {
                outcome: Outcome::Success,
                length: 120,
                total_reward: 12.5,
                mean_abs_accel: 0.8,
                max_abs_accel: 2.9,
                collisions: 0,
                energy_kj: 40.0,
                total_cost: 0.4,
            })
            .collect(),
        sim_seconds: steps as f32 * config.scenario.decision_dt,
        ..RolloutFragment::default()
    }
}

/// The learner's receiving side with nothing behind it: shared state, and an ingest queue
/// whose fragments are counted and dropped by a drain thread.
struct Receiver {
    ingest: Ingest,
    drained: std::thread::JoinHandle<usize>,
}

fn receiver(config: &RunConfig, expected: usize) -> anyhow::Result<Receiver> {
    let metrics = LearnerMetrics::new().context("registering metrics")?;
    let weights = proto::PolicyWeights {
        protocol_version: PROTOCOL_VERSION,
        format: "safetensors".into(),
        ..Default::default()
    };
    let shared = Arc::new(Shared::new(config.clone(), metrics, weights));
    let (tx, mut rx) = mpsc::channel(config.learner.ingest_queue_fragments);
    let drained = std::thread::spawn(move || {
        let mut received = 0;
        while received < expected && rx.blocking_recv().is_some() {
            received += 1;
        }
        received
    });
    Ok(Receiver {
        ingest: Ingest::new(shared, tx),
        drained,
    })
}

impl Receiver {
    /// Waits for the drain thread; fails unless every fragment was accepted.
    fn finish(self, expected: usize) -> anyhow::Result<()> {
        let metrics = &self.ingest.shared().metrics;
        let rejected: u64 = FragmentError::REASONS
            .iter()
            .chain(&[REJECT_DECODE, REJECT_SCENARIO])
            .map(|r| {
                metrics
                    .ingest
                    .fragments_rejected
                    .with_label_values(&[r])
                    .get()
            })
            .sum();
        drop(self.ingest);
        let received = self
            .drained
            .join()
            .map_err(|_| anyhow::anyhow!("the drain thread panicked"))?;
        if received != expected || rejected > 0 {
            bail!("{received} of {expected} fragments arrived, {rejected} rejected");
        }
        Ok(())
    }
}

/// Shared memory: the learner's [`ShmServer`], and a publisher thread sending `count`
/// fragments the way an actor does (encoded straight into the loaned sample).
pub fn shm(config: &RunConfig, count: usize) -> anyhow::Result<TransportReport> {
    let fragment = realistic_fragment(config, config.run.seed);
    let fragment_bytes = shm_layout::encoded_len(&fragment)?;
    let receiver = receiver(config, count)?;
    let name = format!("bench-{}", std::process::id());
    let server = ShmServer::start(receiver.ingest.clone(), &name, 2)?;
    let sender = {
        let fragment = fragment.clone();
        std::thread::spawn(move || -> anyhow::Result<Instant> {
            // As an actor does: publisher first, then register.
            let names = Names::new(&name)?;
            let node = shm::node("junction-bench")?;
            let service = shm::fragment_service(&node, &names, Side::Actor)?;
            let abort = Arc::new(AtomicBool::new(false));
            let publisher = shm::fragment_publisher(&service, fragment_bytes, Arc::clone(&abort))?;
            let register = shm::register_service(&node, &names, Side::Actor)?;
            let hello = proto::RegisterRequest {
                protocol_version: PROTOCOL_VERSION,
                actor_name: "bench".into(),
                scenes: 1,
                instance: String::new(),
            };
            let client = shm::register_client(&register)?;
            shm::register(&client, &hello, Duration::from_secs(10), &abort)?;
            let started = Instant::now();
            let mut fragment = fragment;
            for sequence in 0..count as u64 {
                fragment.sequence = sequence;
                shm::send_fragment(&publisher, &fragment)?;
            }
            Ok(started)
        })
    };
    let started = sender
        .join()
        .map_err(|_| anyhow::anyhow!("the sender thread panicked"))??;
    let receive_deadline = Instant::now() + Duration::from_secs(60);
    while !receiver.drained.is_finished() && Instant::now() < receive_deadline {
        std::thread::sleep(Duration::from_micros(200));
    }
    let seconds = started.elapsed().as_secs_f64();
    server.stop();
    receiver.finish(count)?;
    Ok(TransportReport::new(
        "shm",
        &fragment,
        count,
        fragment_bytes,
        seconds,
    ))
}

/// gRPC on loopback: the learner's [`LearnerService`] and one client stream of `count`
/// fragments (each a clone of one protobuf message, as an actor converts its own).
pub fn grpc(config: &RunConfig, count: usize) -> anyhow::Result<TransportReport> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let fragment = realistic_fragment(config, config.run.seed);
    let message = fragment.clone().into_proto();
    let fragment_bytes = message.encoded_len();
    let receiver = receiver(config, count)?;
    let max_bytes = config.server.max_message_bytes;
    let seconds = runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let service = LearnerServer::new(LearnerService::new(receiver.ingest.clone()))
            .max_decoding_message_size(max_bytes);
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(
            tonic::transport::Server::builder()
                .initial_stream_window_size(GRPC_STREAM_WINDOW_BYTES)
                .initial_connection_window_size(GRPC_CONNECTION_WINDOW_BYTES)
                .max_frame_size(GRPC_MAX_FRAME_BYTES)
                .add_service(service)
                .serve_with_incoming_shutdown(TcpListenerStream::new(listener), async {
                    let _ = stop_rx.await;
                }),
        );
        let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))?
            .initial_stream_window_size(GRPC_STREAM_WINDOW_BYTES)
            .initial_connection_window_size(GRPC_CONNECTION_WINDOW_BYTES)
            .tcp_nodelay(true)
            .connect()
            .await?;
        let mut client = LearnerClient::new(channel).max_encoding_message_size(max_bytes);
        let started = Instant::now();
        let stream = tokio_stream::iter((0..count as u64).map(move |sequence| {
            let mut message = message.clone();
            message.sequence = sequence;
            message
        }));
        let summary = client.push_rollouts(stream).await?.into_inner();
        let seconds = started.elapsed().as_secs_f64();
        let _ = stop_tx.send(());
        let _ = server.await;
        anyhow::ensure!(
            summary.accepted_fragments == count as u64,
            "the learner accepted {} of {count} fragments",
            summary.accepted_fragments
        );
        anyhow::Ok(seconds)
    })?;
    receiver.finish(count)?;
    Ok(TransportReport::new(
        "grpc",
        &fragment,
        count,
        fragment_bytes,
        seconds,
    ))
}
