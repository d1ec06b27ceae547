//! `learner`: trains the shared driving policy from actors' rollouts and broadcasts its weights.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::TcpListenerStream;
use tonic::service::interceptor::InterceptedService;

use junction_common::config::{DEFAULT_TOML, DeviceChoice, Layer, RunConfig, Simulator};
use junction_common::proto::learner_server::LearnerServer;
use junction_common::scenarios;
use junction_common::shutdown::end_by_sigint;
use junction_common::spec::OBS_LAYOUT_VERSION;
use junction_common::telemetry::{LogFormat, init_logging, serve_metrics};
use junction_common::{
    GRPC_CONNECTION_WINDOW_BYTES, GRPC_MAX_FRAME_BYTES, GRPC_STREAM_WINDOW_BYTES,
};
use junction_learner::algo;
use junction_learner::checkpoint::Checkpointer;
use junction_learner::ingest::Ingest;
use junction_learner::local::{ActorCommand, LocalActors};
use junction_learner::metrics::LearnerMetrics;
use junction_learner::security::{self, TokenCheck};
use junction_learner::server::{LearnerService, Shared};
use junction_learner::shm::ShmServer;
use junction_learner::tensorboard::EventWriter;
use junction_learner::trainer::{Progress, Trainer, weights_message};
use junction_learner::transport_bench;

#[derive(Parser)]
#[command(
    name = "learner",
    version,
    about = "Junction learner: trains a shared driving policy from actors' rollouts and broadcasts its weights."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Log format on stderr: pretty or json. Filter with RUST_LOG (default: info).
    #[arg(long, global = true, default_value = "pretty")]
    log_format: LogFormat,
}

#[derive(Subcommand)]
enum Command {
    /// Serve actors: take rollouts over gRPC and shared memory, train, broadcast weights,
    /// expose /metrics; with --local-actors, start and supervise the actors too.
    Serve(ServeArgs),
    /// Print the effective configuration as TOML (or, with --defaults, the annotated defaults).
    Config(ConfigArgs),
    /// Time the training update alone on synthetic fragments of the run's shape (scenario
    /// agents × rollout.fragment_length, ppo.train_batch_env_steps per update, or
    /// dqn.train_batch_env_steps for dqn) and print one JSON line with samples_per_s.
    Bench(BenchArgs),
    /// Time fragment throughput of each transport on this host through the learner's real
    /// receiving side (decode, validation, ingest queue), with fragments of the run's shape
    /// (30 agents × 200 steps × 91 observations by default); one JSON line per transport.
    BenchTransport(BenchTransportArgs),
}

#[derive(Args)]
struct BenchTransportArgs {
    #[command(flatten)]
    source: ConfigSource,
    /// Which transport to time: shm, grpc or both.
    #[arg(long, default_value = "both", value_parser = ["shm", "grpc", "both"])]
    transport: String,
    /// Fragments sent through each transport.
    #[arg(long, default_value_t = 300)]
    fragments: usize,
}

#[derive(Args)]
struct BenchArgs {
    #[command(flatten)]
    source: ConfigSource,
    /// Algorithm to time: ippo, cl, ccppo-mf, ccppo-concat, copo, dynamic-lcf or dqn
    /// [config: learner.algo, default ippo].
    #[arg(long)]
    algo: Option<String>,
    /// Timed updates (after one untimed warm-up update).
    #[arg(long, default_value_t = 5)]
    updates: usize,
    /// cpu, cuda or auto [config: learner.device].
    #[arg(long, value_name = "DEVICE")]
    device: Option<String>,
}

#[derive(Args)]
struct ConfigSource {
    /// A shipped preset applied over the defaults, before everything else: gpu (one GPU
    /// with many local actors). `learner config --preset NAME` prints it applied;
    /// docs/CONFIGURATION.md says what each holds and why.
    #[arg(long, value_name = "NAME")]
    preset: Option<String>,
    /// Run configuration (TOML); only the keys to change are needed. Default: the built-in
    /// defaults (`learner config --defaults`), or the run's config.toml when resuming.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Scenario to train on: a shipped one (intersection, intersection-metadrive, t-junction,
    /// roundabout, roundabout-metadrive, roundabout-compact-3arm, roundabout-large-5arm,
    /// tiny-straight) or a scenario TOML file; replaces the [scenario] keys it sets (applied
    /// after --config, before --set).
    #[arg(long, value_name = "NAME|FILE")]
    scenario: Option<String>,
    /// Override one config key, e.g. --set ppo.learning_rate=1e-4 (repeatable; applied after
    /// --config, before the dedicated flags below).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
}

impl ConfigSource {
    /// Defaults ← `--preset` ← `--config` (or `fallback`) ← `--scenario` ← `--set` ← `flags`.
    fn load(&self, fallback: Option<&Path>, flags: &[String]) -> anyhow::Result<RunConfig> {
        let scenario = self.scenario.as_deref().map(scenarios::text).transpose()?;
        let layers: Vec<Layer> = self
            .preset
            .as_deref()
            .map(Layer::Preset)
            .into_iter()
            .chain(self.config.as_deref().or(fallback).map(Layer::File))
            .chain(scenario.as_deref().map(Layer::Scenario))
            .chain(self.overrides.iter().chain(flags).map(|o| Layer::Set(o)))
            .collect();
        RunConfig::from_layers(&layers).context("loading the configuration")
    }
}

#[derive(Args)]
struct ServeArgs {
    #[command(flatten)]
    source: ConfigSource,
    /// gRPC listen address for actors [config: server.addr, default 0.0.0.0:50051]. Port 0
    /// picks a free port; the bound addresses are written to <run-dir>/endpoints.json.
    #[arg(long, value_name = "HOST:PORT")]
    addr: Option<String>,
    /// Prometheus /metrics listen address [config: server.metrics_addr, default 0.0.0.0:9100].
    #[arg(long, value_name = "HOST:PORT")]
    metrics_addr: Option<String>,
    /// Directory for checkpoints, config.toml, progress.jsonl and endpoints.json
    /// [default: runs/run-<unix time>].
    #[arg(long, value_name = "DIR")]
    run_dir: Option<PathBuf>,
    /// Continue the run in DIR from its newest complete checkpoint.
    #[arg(long, value_name = "DIR", conflicts_with = "run_dir")]
    resume: Option<PathBuf>,
    /// Training device: cpu, cuda or auto [config: learner.device, default auto]. cuda falls
    /// back to CPU with a warning when no GPU is usable.
    #[arg(long, value_name = "DEVICE")]
    device: Option<String>,
    /// Base seed of the run [config: run.seed].
    #[arg(long)]
    seed: Option<u64>,
    /// Training budget in seconds, 0 = until stopped [config: run.max_seconds, default 300].
    #[arg(long, value_name = "SECONDS")]
    max_seconds: Option<f64>,
    /// Base name of the shared-memory services, "" for none [config: server.shm_name,
    /// default junction]; actors on this host join with `actor --learner shm://NAME`.
    #[arg(long, value_name = "NAME")]
    shm_name: Option<String>,
    /// Start N actor processes (the `actor` binary next to this one) connected over shared
    /// memory, restart any that dies (with back-off), and stop them when the learner exits:
    /// the one-command local mode.
    #[arg(long, value_name = "N", default_value_t = 0)]
    local_actors: usize,
    /// Scenes each local actor simulates (`actor --scenes`).
    #[arg(long, value_name = "S", default_value_t = 1,
          value_parser = clap::value_parser!(u32).range(1..=256))]
    local_actor_scenes: u32,
    /// Local actor i (from 1) serves Prometheus /metrics on 127.0.0.1:(PORT + i - 1).
    #[arg(long, value_name = "PORT")]
    local_actor_metrics_port: Option<u16>,
}

#[derive(Args)]
struct ConfigArgs {
    #[command(flatten)]
    source: ConfigSource,
    /// Print the built-in defaults with the documentation of every key.
    #[arg(long)]
    defaults: bool,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    init_logging(cli.log_format);
    match cli.command {
        Command::Config(args) => {
            if args.defaults {
                print!("{DEFAULT_TOML}");
            } else {
                let config = args.source.load(None, &[])?;
                print!("{}", config.to_toml());
            }
            Ok(())
        }
        Command::Bench(args) => bench(args),
        Command::BenchTransport(args) => bench_transport(args),
        Command::Serve(args) => {
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .context("starting the async runtime")?;
            let served = runtime.block_on(serve(args));
            drop(runtime);
            if served.is_ok() && STOPPED_BY_CTRL_C.load(Ordering::Relaxed) {
                end_by_sigint();
            }
            served
        }
    }
}

fn bench(args: BenchArgs) -> anyhow::Result<()> {
    let flags: Vec<String> = [
        ("learner.device", args.device.as_ref()),
        ("learner.algo", args.algo.as_ref()),
    ]
    .into_iter()
    .filter_map(|(key, value)| value.map(|v| format!("{key}={v:?}")))
    .collect();
    let config = args.source.load(None, &flags)?;
    if config.learner.torch_threads > 0 {
        tch::set_num_threads(config.learner.torch_threads as i32);
    }
    tch::manual_seed(config.run.seed as i64);
    let device = resolve_device(config.learner.device);
    let mut algorithm = algo::build(&config, device).context("building the algorithm")?;
    let report = junction_learner::bench::run(
        &config,
        algorithm.as_mut(),
        format!("{device:?}"),
        args.updates.max(1),
    )
    .context("timing the update")?;
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}

fn bench_transport(args: BenchTransportArgs) -> anyhow::Result<()> {
    let config = args.source.load(None, &[])?;
    let count = args.fragments.max(1);
    if args.transport != "grpc" {
        let report = transport_bench::shm(&config, count).context("timing shared memory")?;
        println!("{}", serde_json::to_string(&report)?);
    }
    if args.transport != "shm" {
        let report = transport_bench::grpc(&config, count).context("timing gRPC")?;
        println!("{}", serde_json::to_string(&report)?);
    }
    Ok(())
}

fn resolve_device(choice: DeviceChoice) -> tch::Device {
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

async fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let run_dir = match (&args.resume, &args.run_dir) {
        (Some(dir), _) | (None, Some(dir)) => dir.clone(),
        (None, None) => {
            let now = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| d.as_secs())
                .unwrap_or(0);
            PathBuf::from(format!("runs/run-{now}"))
        }
    };
    let checkpoint_dir = run_dir.join("checkpoints");
    let resume = if args.resume.is_some() {
        let candidates = Checkpointer::newest_first(&checkpoint_dir)?;
        if candidates.is_empty() {
            bail!(
                "--resume: no complete checkpoint in {}",
                checkpoint_dir.display()
            );
        }
        Some(candidates)
    } else {
        if Checkpointer::latest(&checkpoint_dir)?.is_some() {
            bail!(
                "{} already holds checkpoints of another run: continue it with --resume {} or choose another --run-dir",
                checkpoint_dir.display(),
                run_dir.display()
            );
        }
        None
    };

    let saved_config = run_dir.join("config.toml");
    // A resumed run keeps its recorded configuration unless told otherwise.
    let fallback = (resume.is_some() && saved_config.exists()).then_some(saved_config.as_path());
    let flags: Vec<String> = [
        ("server.addr", args.addr.as_ref().map(|a| format!("{a:?}"))),
        (
            "server.metrics_addr",
            args.metrics_addr.as_ref().map(|a| format!("{a:?}")),
        ),
        (
            "learner.device",
            args.device.as_ref().map(|d| format!("{d:?}")),
        ),
        ("run.seed", args.seed.map(|s| s.to_string())),
        (
            "run.max_seconds",
            args.max_seconds.map(|s| format!("{s:?}")),
        ),
        (
            "server.shm_name",
            args.shm_name.as_ref().map(|n| format!("{n:?}")),
        ),
    ]
    .into_iter()
    .filter_map(|(key, value)| value.map(|v| format!("{key}={v}")))
    .collect();
    let config = args.source.load(fallback, &flags)?;
    if let Some(port) = args.local_actor_metrics_port
        && usize::from(port) + args.local_actors > usize::from(u16::MAX) + 1
    {
        bail!(
            "--local-actor-metrics-port {port}: {} actors need ports up to 65535",
            args.local_actors
        );
    }
    if args.local_actors > 0 && config.scenario.simulator == Simulator::Metadrive {
        bail!(
            "--local-actors starts Junction actors, and scenario {:?} runs on MetaDrive: start \
             `python -m junction.metadrive_actor --learner http://HOST:PORT` instead (docs/PYTHON.md)",
            config.scenario.name
        );
    }
    if args.local_actors > 0 && config.server.shm_name.is_empty() {
        bail!(
            "--local-actors connects the actors over shared memory: server.shm_name must not be empty"
        );
    }

    if config.learner.torch_threads > 0 {
        tch::set_num_threads(config.learner.torch_threads as i32);
    }
    tch::manual_seed(config.run.seed as i64);
    let device = resolve_device(config.learner.device);
    let (algorithm, progress, actors_registered) = match &resume {
        Some(candidates) => restore_newest(candidates, &config, device)?,
        None => (
            algo::build(&config, device).context("building the algorithm")?,
            Progress::default(),
            0,
        ),
    };
    // Written once the checkpoint has restored: a resume refused for its configuration leaves
    // the run's own config.toml, the one a plain `--resume` reads back.
    std::fs::create_dir_all(&run_dir).with_context(|| format!("creating {}", run_dir.display()))?;
    write_atomically(&saved_config, config.to_toml().as_bytes())?;

    // The stage follows from the restored agent-steps: a resumed run continues in its stage.
    let stage = algorithm.stage(progress.agent_steps, config.scenario.agent_count());
    tracing::info!(
        stage = stage.index,
        agents = stage.agents,
        agent_steps = progress.agent_steps,
        "curriculum stage"
    );
    let metrics = LearnerMetrics::new().context("registering metrics")?;
    metrics.policy_version.set(progress.version as i64);
    metrics.record_stage(stage);
    let registry = metrics.registry.clone();
    let initial = weights_message(algorithm.as_ref(), progress.version, stage.agents, false)?;
    let refused = metrics.requests_refused.clone();
    let restarts = metrics.local_actor_restarts.clone();
    let shared = Arc::new(Shared::new(config.clone(), metrics, initial));
    shared.continue_actor_ids(actors_registered);
    let tls = security::server_tls(&config.server).context("[server] TLS settings")?;
    let token = security::server_token(&config.server).context("[server] auth token")?;
    let (queue_tx, queue_rx) = mpsc::channel(config.learner.ingest_queue_fragments);
    let ingest = Ingest::new(Arc::clone(&shared), queue_tx);

    let grpc_listener = bind(&config.server.addr, "gRPC").await?;
    let metrics_listener = bind(&config.server.metrics_addr, "metrics").await?;
    let grpc_addr = grpc_listener.local_addr()?;
    let metrics_addr = metrics_listener.local_addr()?;
    // Clears what an interrupted checkpoint write left behind before anyone is told we serve.
    let checkpointer = Checkpointer::new(checkpoint_dir, config.run.keep_checkpoints)?;
    let unix_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0);
    let tensorboard = EventWriter::create(&run_dir, unix_s)?;
    let shm_name = &config.server.shm_name;
    let shm = if shm_name.is_empty() {
        None
    } else {
        Some(ShmServer::start(
            ingest.clone(),
            shm_name,
            config.server.shm_max_actors,
        )?)
    };
    write_endpoints(&run_dir, grpc_addr, metrics_addr, shm_name)?;
    tracing::info!(
        grpc = %grpc_addr,
        metrics = %metrics_addr,
        shm = %shm_name,
        run_dir = %run_dir.display(),
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
    let local_actors = if args.local_actors > 0 {
        let command = ActorCommand::beside_this_executable(
            shm_name,
            args.local_actor_scenes,
            args.local_actor_metrics_port,
        )?;
        Some(LocalActors::start(args.local_actors, command, restarts)?)
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

    let stop = Arc::new(AtomicBool::new(false));
    tokio::spawn(stop_on_signal(Arc::clone(&stop)));
    let trainer = Trainer {
        shared: Arc::clone(&shared),
        algorithm,
        queue: queue_rx,
        runtime: tokio::runtime::Handle::current(),
        checkpointer,
        progress_log: run_dir.join("progress.jsonl"),
        tensorboard,
        stop,
        progress,
        stage,
    };
    let outcome = tokio::task::spawn_blocking(move || trainer.run())
        .await
        .context("training thread panicked")?;

    // Actors have been told the run is over (or, after an error, will be stopped): local ones
    // get a moment to exit by themselves, remote streams a moment to close, then all stops.
    if let Some(local) = local_actors {
        let grace = if outcome.is_ok() {
            LOCAL_ACTOR_GRACE
        } else {
            Duration::ZERO
        };
        tokio::task::spawn_blocking(move || local.finish(grace))
            .await
            .context("stopping the local actors")?;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    if let Some(shm) = shm {
        tokio::task::spawn_blocking(move || shm.stop())
            .await
            .context("stopping the shared-memory server")?;
    }
    let _ = shutdown_tx.send(true);
    if tokio::time::timeout(Duration::from_secs(10), grpc)
        .await
        .is_err()
    {
        tracing::warn!("gRPC server did not stop within 10 s; exiting anyway");
    }
    let _ = tokio::time::timeout(Duration::from_secs(2), metrics_server).await;
    let progress = outcome?;
    tracing::info!(
        version = progress.version,
        agent_steps = progress.agent_steps,
        samples_trained = progress.samples_trained,
        "learner stopped"
    );
    Ok(())
}

/// Restores the newest checkpoint that restores completely; ones that do not (damaged after
/// their meta.json was written, e.g. a disk error) are set aside with a warning and the next
/// older one is tried. Returns the algorithm, the counters and the actor ids handed out.
fn restore_newest(
    candidates: &[PathBuf],
    config: &RunConfig,
    device: tch::Device,
) -> anyhow::Result<(Box<dyn algo::Algorithm + Send>, Progress, u64)> {
    for path in candidates {
        let mut algorithm = algo::build(config, device).context("building the algorithm")?;
        match restore(path, algorithm.as_mut()) {
            Ok(meta) => {
                tracing::info!(path = %path.display(), version = meta.version, "resumed");
                return Ok((algorithm, Progress::from(&meta), meta.actors_registered));
            }
            // A checkpoint of another algorithm, layout or configuration is an error, not damage.
            Err(RestoreError::Incompatible(e)) => return Err(e),
            Err(RestoreError::Damaged(e)) => {
                let moved = Checkpointer::set_aside(path)
                    .map(|p| p.display().to_string())
                    .unwrap_or_else(|e| format!("(could not move it: {e})"));
                tracing::warn!(
                    path = %path.display(),
                    moved_to = %moved,
                    error = %format!("{e:#}"),
                    "checkpoint cannot be restored; trying the previous one"
                );
            }
        }
    }
    bail!(
        "--resume: none of the {} checkpoints could be restored",
        candidates.len()
    )
}

enum RestoreError {
    Incompatible(anyhow::Error),
    Damaged(anyhow::Error),
}

fn restore(
    path: &Path,
    algorithm: &mut dyn algo::Algorithm,
) -> Result<junction_learner::checkpoint::CheckpointMeta, RestoreError> {
    let damaged = |e: anyhow::Error| RestoreError::Damaged(e);
    let checkpoint = Checkpointer::read(path)
        .map_err(anyhow::Error::new)
        .map_err(damaged)?;
    let meta = checkpoint.meta;
    if meta.algorithm != algorithm.name() {
        return Err(RestoreError::Incompatible(anyhow::anyhow!(
            "checkpoint {} was trained by {}, the configuration asks for {} (learner.algo)",
            path.display(),
            meta.algorithm,
            algorithm.name()
        )));
    }
    if meta.obs_layout_version != OBS_LAYOUT_VERSION {
        return Err(RestoreError::Incompatible(anyhow::anyhow!(
            "checkpoint {} uses observation layout {}, this build uses {}",
            path.display(),
            meta.obs_layout_version,
            OBS_LAYOUT_VERSION
        )));
    }
    let mut state = junction_common::weights::Decoded::decode(&checkpoint.state)
        .with_context(|| format!("reading {}", path.display()))
        .map_err(damaged)?;
    algorithm
        .restore(&checkpoint.policy, &mut state)
        .map_err(|e| {
            let mismatch = e.is_configuration_mismatch();
            let e = anyhow::Error::new(e).context(format!("restoring from {}", path.display()));
            if mismatch {
                // Setting it aside would discard a sound run over a changed flag.
                RestoreError::Incompatible(e.context(
                    "the checkpoint was written under another configuration: resume without the \
                     --config or --set that changes it (a resumed run reads its own config.toml)",
                ))
            } else {
                RestoreError::Damaged(e)
            }
        })?;
    Ok(meta)
}

async fn bind(addr: &str, what: &str) -> anyhow::Result<tokio::net::TcpListener> {
    tokio::net::TcpListener::bind(addr)
        .await
        .with_context(|| format!("binding the {what} address {addr}"))
}

/// Set when Ctrl-C (SIGINT), not SIGTERM, stopped `serve`: the process then ends by SIGINT
/// ([`end_by_sigint`]) after its clean shutdown.
static STOPPED_BY_CTRL_C: AtomicBool = AtomicBool::new(false);

/// Stops training on Ctrl-C or SIGTERM; a second signal exits at once.
async fn stop_on_signal(stop: Arc<AtomicBool>) {
    let mut term = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
        Ok(term) => term,
        Err(e) => {
            tracing::warn!(error = %e, "cannot listen for SIGTERM");
            return;
        }
    };
    for _ in 0..2 {
        let ctrl_c = tokio::select! {
            _ = tokio::signal::ctrl_c() => true,
            _ = term.recv() => false,
        };
        if stop.swap(true, Ordering::Relaxed) {
            tracing::warn!("second stop signal: exiting immediately");
            std::process::exit(130);
        }
        STOPPED_BY_CTRL_C.store(ctrl_c, Ordering::Relaxed);
        tracing::info!("stop signal received: finishing the current step, writing a checkpoint");
    }
}

/// How long local actors get to exit by themselves once they have been told the run is over.
const LOCAL_ACTOR_GRACE: Duration = Duration::from_secs(10);

fn write_endpoints(
    run_dir: &Path,
    grpc: SocketAddr,
    metrics: SocketAddr,
    shm: &str,
) -> anyhow::Result<()> {
    let body = serde_json::json!({
        "grpc": grpc.to_string(),
        "metrics": metrics.to_string(),
        "shm": shm,
        "pid": std::process::id(),
    });
    write_atomically(&run_dir.join("endpoints.json"), body.to_string().as_bytes())
}

/// Readers (tests, scripts) never see a half-written file.
fn write_atomically(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("renaming {} into place", tmp.display()))
}
