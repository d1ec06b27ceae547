//! The learner as a library app: everything `learner serve` does between parsing its flags
//! and its exit code, so a test or an embedding program can start a learner in-process.
//!
//! The lifecycle, in order:
//! 1. [`RunDir::open`]: where the run lives; for a resume, the checkpoints to restore from
//!    and the `config.toml` the configuration falls back to ([`RunDir::config_fallback`]).
//! 2. [`LearnerApp::build`]: checks the options against the configuration, builds or
//!    restores the algorithm, records `config.toml`, registers the metrics, binds the gRPC
//!    and metrics ports, opens the checkpointer and the TensorBoard writer, starts the
//!    shared-memory server, writes `endpoints.json`, starts the local actors and the gRPC
//!    and metrics servers. Actors can connect once it returns; [`LearnerApp::grpc_addr`]
//!    and [`LearnerApp::metrics_addr`] say where.
//! 3. [`LearnerApp::run`]: trains ([`Trainer::run`]) until the budget is spent, every sender
//!    is gone or [`StopHandle::stop`] is called, then tears everything down in one place
//!    (`Servers::shutdown`, below) and returns the final [`Progress`].
//!
//! Signals, the exit code and the configuration layers stay in the binary (`main.rs`).

pub mod local_actors;
mod run_dir;

pub use run_dir::RunDir;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{Context, bail};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::service::interceptor::InterceptedService;

use junction_common::ledger::{Event, Ledger};
use junction_common::proto::learner_server::LearnerServer;
use junction_common::telemetry::serve_metrics;
use junction_common::{
    GRPC_CONNECTION_WINDOW_BYTES, GRPC_MAX_FRAME_BYTES, GRPC_STREAM_WINDOW_BYTES,
};
use junction_core::config::{DeviceChoice, RunConfig, Simulator};

use crate::hub::Shared;
use crate::telemetry::metrics::LearnerMetrics;
use crate::telemetry::tensorboard::EventWriter;
use crate::training::checkpoint::Checkpointer;
use crate::training::trainer::{Progress, Trainer, weights_message};
use crate::transport::grpc::LearnerService;
use crate::transport::ingest::Ingest;
use crate::transport::security::{self, TokenCheck};
use crate::transport::shm::ShmServer;
use local_actors::{ActorCommand, LocalActors};

/// How long local actors get to exit by themselves once they have been told the run is over.
const LOCAL_ACTOR_GRACE: Duration = Duration::from_secs(10);
/// How long remote actors' streams get to close after the run is over.
const STREAMS_GRACE: Duration = Duration::from_millis(500);
/// How long the gRPC server, then the metrics server, may take to stop.
const GRPC_STOP_TIMEOUT: Duration = Duration::from_secs(10);
const METRICS_STOP_TIMEOUT: Duration = Duration::from_secs(2);

/// What `serve` takes besides the run configuration.
#[derive(Debug, Clone)]
pub struct ServeOptions {
    pub run_dir: RunDir,
    /// Actor processes (the `actor` binary next to this executable) to start and supervise,
    /// connected over shared memory.
    pub local_actors: usize,
    /// Scenes each local actor simulates.
    pub local_actor_scenes: u32,
    /// Local actor i (from 1) serves /metrics on 127.0.0.1:(port + i - 1).
    pub local_actor_metrics_port: Option<u16>,
}

impl ServeOptions {
    /// No local actors.
    pub fn new(run_dir: RunDir) -> Self {
        ServeOptions {
            run_dir,
            local_actors: 0,
            local_actor_scenes: 1,
            local_actor_metrics_port: None,
        }
    }
}

/// Ends the run from outside: the trainer finishes its current step, writes a last
/// checkpoint and tells actors the run is over; [`LearnerApp::run`] then returns.
#[derive(Debug, Clone, Default)]
pub struct StopHandle(Arc<AtomicBool>);

impl StopHandle {
    /// Requests the stop; true when one had been requested already.
    pub fn stop(&self) -> bool {
        self.0.swap(true, Ordering::Relaxed)
    }

    pub fn is_stopped(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
}

/// A learner that serves: built by [`LearnerApp::build`], trained by [`LearnerApp::run`].
pub struct LearnerApp {
    trainer: Trainer,
    servers: Servers,
    stop: StopHandle,
    grpc_addr: SocketAddr,
    metrics_addr: SocketAddr,
    shm_name: String,
    run_dir: PathBuf,
}

/// What runs beside the trainer and stops after it, in [`Servers::shutdown`]'s order.
struct Servers {
    local_actors: Option<LocalActors>,
    shm: Option<ShmServer>,
    shutdown: watch::Sender<bool>,
    grpc: JoinHandle<Result<(), tonic::transport::Error>>,
    metrics: JoinHandle<()>,
}

impl LearnerApp {
    /// Wires a learner for `config` and starts serving; see the module documentation for
    /// what happens in which order. Runs inside a Tokio runtime (it spawns the servers).
    /// Seeds libtorch's global generator from `run.seed` and sets its thread count.
    pub async fn build(config: RunConfig, options: ServeOptions) -> anyhow::Result<LearnerApp> {
        let ServeOptions {
            run_dir,
            local_actors,
            local_actor_scenes,
            local_actor_metrics_port,
        } = options;
        if let Some(port) = local_actor_metrics_port
            && usize::from(port) + local_actors > usize::from(u16::MAX) + 1
        {
            bail!(
                "--local-actor-metrics-port {port}: {local_actors} actors need ports up to 65535"
            );
        }
        if local_actors > 0 && config.scenario.simulator == Simulator::Metadrive {
            bail!(
                "--local-actors starts Junction actors, and scenario {:?} runs on MetaDrive: start \
                 `python -m junction.metadrive_actor --learner http://HOST:PORT` instead (docs/PYTHON.md)",
                config.scenario.name
            );
        }
        if local_actors > 0 && config.server.shm_name.is_empty() {
            bail!(
                "--local-actors connects the actors over shared memory: server.shm_name must not be empty"
            );
        }

        if config.learner.torch_threads > 0 {
            tch::set_num_threads(config.learner.torch_threads as i32);
        }
        tch::manual_seed(config.run.seed as i64);
        let device = resolve_device(config.learner.device);
        let start = run_dir.start(&config, device)?;
        let (algorithm, progress) = (start.algorithm, start.progress);
        // Written once the checkpoint has restored: a resume refused for its configuration
        // leaves the run's own config.toml, the one a plain `--resume` reads back.
        run_dir.write_config(&config)?;

        // The stage follows from the restored agent-steps: a resumed run continues in its stage.
        let stage = algorithm.stage(progress.agent_steps, config.scenario.agent_count());
        tracing::info!(
            stage = stage.index,
            agents = stage.agents,
            agent_steps = progress.agent_steps,
            "curriculum stage"
        );
        let metrics = LearnerMetrics::new().context("registering metrics")?;
        metrics.update.policy_version.set(progress.version as i64);
        metrics.curriculum.record_stage(stage);
        let registry = metrics.registry.clone();
        let initial = weights_message(algorithm.as_ref(), progress.version, stage.agents, false)?;
        let refused = metrics.ingest.requests_refused.clone();
        let restarts = metrics.local_actors.restarts.clone();
        let ledger_path = run_dir.path().join("ledger.jsonl");
        let ledger = Ledger::open(&ledger_path)
            .with_context(|| format!("opening the fragment ledger {}", ledger_path.display()))?;
        let resumed = run_dir.is_resume();
        ledger.record(&Event::LearnerStart {
            pid: std::process::id(),
            resumed_update: resumed.then_some(progress.updates),
            resumed_version: resumed.then_some(progress.version),
        });
        let shared = Arc::new(Shared::new(config.clone(), metrics, initial).with_ledger(ledger));
        shared.continue_actor_ids(start.actors_registered);
        let tls = security::server_tls(&config.server).context("[server] TLS settings")?;
        let token = security::server_token(&config.server).context("[server] auth token")?;
        let (queue_tx, queue_rx) = mpsc::channel(config.learner.ingest_queue_fragments);
        let ingest = Ingest::new(Arc::clone(&shared), queue_tx);

        let grpc_listener = bind(&config.server.addr, "gRPC").await?;
        let metrics_listener = bind(&config.server.metrics_addr, "metrics").await?;
        let grpc_addr = grpc_listener.local_addr()?;
        let metrics_addr = metrics_listener.local_addr()?;
        // Clears what an interrupted checkpoint write left behind before anyone is told we serve.
        let checkpointer =
            Checkpointer::new(run_dir.checkpoint_dir(), config.run.keep_checkpoints)?;
        let unix_s = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_secs_f64())
            .unwrap_or(0.0);
        let tensorboard = EventWriter::create(run_dir.path(), unix_s)?;
        let shm_name = config.server.shm_name.clone();
        let shm = if shm_name.is_empty() {
            None
        } else {
            Some(ShmServer::start(
                ingest.clone(),
                &shm_name,
                config.server.shm_max_actors,
            )?)
        };
        run_dir.write_endpoints(grpc_addr, metrics_addr, &shm_name)?;
        tracing::info!(
            grpc = %grpc_addr,
            metrics = %metrics_addr,
            shm = %shm_name,
            run_dir = %run_dir.path().display(),
            device = ?device,
            scenario = %config.scenario.name,
            tls = tls.is_some(),
            token = token.is_some(),
            "learner serving"
        );
        if !grpc_addr.ip().is_loopback() && (tls.is_none() || token.is_none()) {
            tracing::warn!(
                grpc = %grpc_addr,
                "the gRPC port is reachable beyond this host without TLS and a token; set server.tls_cert/tls_key and server.auth_token_file (or JUNCTION_AUTH_TOKEN) unless the network is trusted"
            );
        }
        let local_actors = if local_actors > 0 {
            let command = ActorCommand::beside_this_executable(
                &shm_name,
                local_actor_scenes,
                local_actor_metrics_port,
                &run_dir.path().join("ledger"),
            )?;
            Some(LocalActors::start(local_actors, command, restarts)?)
        } else {
            None
        };

        let (shutdown_tx, shutdown_rx) = watch::channel(false);
        let wait_for_shutdown = |mut rx: watch::Receiver<bool>| async move {
            let _ = rx.wait_for(|stop| *stop).await;
        };
        let server_config = &config.server;
        let max_bytes = server_config.max_message_bytes;
        let service = LearnerServer::new(LearnerService::new(ingest))
            .max_decoding_message_size(max_bytes)
            .max_encoding_message_size(max_bytes);
        let service = InterceptedService::new(service, TokenCheck::new(token, refused));
        let keepalive = Duration::from_secs_f64(server_config.keepalive_interval_s);
        let mut builder = tonic::transport::Server::builder()
            .initial_stream_window_size(GRPC_STREAM_WINDOW_BYTES)
            .initial_connection_window_size(GRPC_CONNECTION_WINDOW_BYTES)
            .max_frame_size(GRPC_MAX_FRAME_BYTES)
            .max_concurrent_streams(Some(server_config.max_concurrent_streams))
            .http2_keepalive_interval(Some(keepalive))
            .http2_keepalive_timeout(Some(Duration::from_secs_f64(
                server_config.keepalive_timeout_s,
            )))
            .tcp_keepalive(Some(keepalive));
        if let Some(tls) = tls {
            builder = builder
                .tls_config(tls)
                .context("configuring TLS on the gRPC port")?;
        }
        let grpc = tokio::spawn(builder.add_service(service).serve_with_incoming_shutdown(
            TcpListenerStream::new(grpc_listener),
            wait_for_shutdown(shutdown_rx.clone()),
        ));
        let metrics_server = tokio::spawn(serve_metrics(
            metrics_listener,
            registry,
            wait_for_shutdown(shutdown_rx),
        ));

        let stop = StopHandle::default();
        let trainer = Trainer {
            shared,
            algorithm,
            queue: queue_rx,
            runtime: tokio::runtime::Handle::current(),
            checkpointer,
            progress_log: run_dir.progress_log(),
            tensorboard,
            stop: Arc::clone(&stop.0),
            progress,
            stage,
        };
        Ok(LearnerApp {
            trainer,
            servers: Servers {
                local_actors,
                shm,
                shutdown: shutdown_tx,
                grpc,
                metrics: metrics_server,
            },
            stop,
            grpc_addr,
            metrics_addr,
            shm_name,
            run_dir: run_dir.path().to_path_buf(),
        })
    }

    /// The bound gRPC address (a port 0 in `server.addr` resolved).
    pub fn grpc_addr(&self) -> SocketAddr {
        self.grpc_addr
    }

    /// The bound address of Prometheus `/metrics`.
    pub fn metrics_addr(&self) -> SocketAddr {
        self.metrics_addr
    }

    /// The shared-memory services' base name ("" when none are served).
    pub fn shm_name(&self) -> &str {
        &self.shm_name
    }

    pub fn run_dir(&self) -> &Path {
        &self.run_dir
    }

    /// Ends the run when asked; valid before and during [`LearnerApp::run`].
    pub fn stop_handle(&self) -> StopHandle {
        self.stop.clone()
    }

    /// Trains until the budget is spent, a stop is requested or every sender is gone (the
    /// trainer then writes a last checkpoint and tells actors the run is over), then stops
    /// the servers (`Servers::shutdown`, in its documented order); returns the final progress, or the training
    /// error once everything has stopped.
    pub async fn run(self) -> anyhow::Result<Progress> {
        let LearnerApp {
            trainer, servers, ..
        } = self;
        let outcome = tokio::task::spawn_blocking(move || trainer.run())
            .await
            .context("training thread panicked")?;
        servers.shutdown(outcome.is_ok()).await?;
        let progress = outcome?;
        tracing::info!(
            version = progress.version,
            agent_steps = progress.agent_steps,
            samples_trained = progress.samples_trained,
            "learner stopped"
        );
        Ok(progress)
    }
}

impl Servers {
    /// The teardown, in this order once training has ended. Actors have been told the run is
    /// over (or, after a training error, will be stopped):
    /// 1. local actors get [`LOCAL_ACTOR_GRACE`] to exit by themselves (none after an
    ///    error), then are terminated;
    /// 2. remote streams get [`STREAMS_GRACE`] to close;
    /// 3. the shared-memory server stops (giving up its services);
    /// 4. the gRPC server stops (up to [`GRPC_STOP_TIMEOUT`], then a warning), then the
    ///    metrics server (up to [`METRICS_STOP_TIMEOUT`]).
    async fn shutdown(self, trained_ok: bool) -> anyhow::Result<()> {
        if let Some(local) = self.local_actors {
            let grace = if trained_ok {
                LOCAL_ACTOR_GRACE
            } else {
                Duration::ZERO
            };
            tokio::task::spawn_blocking(move || local.finish(grace))
                .await
                .context("stopping the local actors")?;
        }
        tokio::time::sleep(STREAMS_GRACE).await;
        if let Some(shm) = self.shm {
            tokio::task::spawn_blocking(move || shm.stop())
                .await
                .context("stopping the shared-memory server")?;
        }
        let _ = self.shutdown.send(true);
        if tokio::time::timeout(GRPC_STOP_TIMEOUT, self.grpc)
            .await
            .is_err()
        {
            tracing::warn!("gRPC server did not stop within 10 s; exiting anyway");
        }
        let _ = tokio::time::timeout(METRICS_STOP_TIMEOUT, self.metrics).await;
        Ok(())
    }
}

/// The training device for `learner.device`: cuda falls back to the CPU with a warning when
/// no GPU is usable.
pub fn resolve_device(choice: DeviceChoice) -> tch::Device {
    match choice {
        DeviceChoice::Cpu => tch::Device::Cpu,
        DeviceChoice::Auto => tch::Device::cuda_if_available(),
        DeviceChoice::Cuda if tch::Cuda::is_available() => tch::Device::Cuda(0),
        DeviceChoice::Cuda => {
            tracing::warn!("--device cuda: no usable CUDA device, training on the CPU instead");
            tch::Device::Cpu
        }
    }
}

async fn bind(addr: &str, what: &str) -> anyhow::Result<tokio::net::TcpListener> {
    tokio::net::TcpListener::bind(addr)
        .await
        .with_context(|| format!("binding the {what} address {addr}"))
}
