//! `actor`: simulates traffic scenes with the learner's current policy and streams the
//! trajectories to it.

use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use tracing::Instrument;

use junction_actor::metrics::ActorMetrics;
use junction_actor::{bench, grpc};
use junction_common::scenarios;
use junction_common::telemetry::{LogFormat, init_logging, serve_metrics};

#[derive(Parser)]
#[command(
    name = "actor",
    version,
    about = "Junction rollout actor: simulates traffic scenes with the learner's current policy and streams trajectories to it.",
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: RunArgs,
    /// Log format on stderr: pretty or json. Filter with RUST_LOG (default: info).
    #[arg(long, global = true, default_value = "pretty")]
    log_format: LogFormat,
}

#[derive(Subcommand)]
enum Command {
    /// Time the simulator alone (scripted driving) and print one JSON line.
    Bench(BenchArgs),
}

#[derive(Args)]
struct RunArgs {
    /// The learner's gRPC address.
    #[arg(
        long,
        value_name = "URL",
        env = "JUNCTION_LEARNER",
        default_value = "http://127.0.0.1:50051"
    )]
    learner: String,
    /// Scenes this actor simulates side by side (their agents share one batched inference).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    scenes: u32,
    /// Actor seed, mixed with the run's seed and the id the learner assigns.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Serve Prometheus /metrics on this address (off by default, so several actors can share
    /// a host without port clashes).
    #[arg(long, value_name = "HOST:PORT")]
    metrics_addr: Option<String>,
    /// Threads libtorch may use for inference.
    #[arg(long, default_value_t = 1)]
    torch_threads: i32,
    /// Keep retrying the first connection to the learner for this many seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 60.0)]
    connect_timeout: f64,
    /// Largest gRPC message sent or accepted, in bytes.
    #[arg(long, default_value_t = 64 << 20)]
    max_message_bytes: usize,
    /// Name shown in the learner's logs [default: <hostname>/<pid>].
    #[arg(long)]
    name: Option<String>,
}

#[derive(Args)]
struct BenchArgs {
    /// A shipped scenario name (intersection, t-junction, roundabout, roundabout-compact-3arm,
    /// roundabout-large-5arm, tiny-straight) or a scenario TOML file.
    #[arg(long, default_value = "intersection")]
    scenario: String,
    /// Scene steps to simulate.
    #[arg(long, default_value_t = 5000)]
    steps: u64,
    /// Scene seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    init_logging(cli.log_format);
    match cli.command {
        Some(Command::Bench(args)) => {
            let scenario = scenarios::load(&args.scenario)?;
            let report =
                bench::run(&scenario, args.steps, args.seed).context("building the scene")?;
            println!("{}", serde_json::to_string(&report)?);
            Ok(())
        }
        None => run_actor(cli.run),
    }
}

fn run_actor(args: RunArgs) -> anyhow::Result<()> {
    tch::set_num_threads(args.torch_threads.max(1));
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(async move {
        let metrics = Arc::new(ActorMetrics::new().context("registering metrics")?);
        let (shutdown_tx, mut shutdown_rx) = tokio::sync::watch::channel(false);
        let metrics_server = match &args.metrics_addr {
            Some(addr) => {
                let listener = tokio::net::TcpListener::bind(addr)
                    .await
                    .with_context(|| format!("binding --metrics-addr {addr}"))?;
                tracing::info!(metrics = %listener.local_addr()?, "serving /metrics");
                let registry = metrics.registry.clone();
                Some(tokio::spawn(serve_metrics(
                    listener,
                    registry,
                    async move {
                        let _ = shutdown_rx.wait_for(|stop| *stop).await;
                    },
                )))
            }
            None => None,
        };
        let hostname = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
        let options = grpc::ActorOptions {
            learner: args.learner,
            name: args
                .name
                .unwrap_or_else(|| format!("{}/{}", hostname.trim(), std::process::id())),
            scenes: args.scenes as usize,
            seed: args.seed,
            connect_timeout: Duration::from_secs_f64(args.connect_timeout.max(0.0)),
            max_message_bytes: args.max_message_bytes,
        };
        let span = tracing::info_span!(
            "actor",
            id = tracing::field::Empty,
            scenario = tracing::field::Empty
        );
        let result = tokio::select! {
            result = grpc::run(options, metrics).instrument(span) => result,
            _ = tokio::signal::ctrl_c() => {
                tracing::info!("interrupted");
                Ok(())
            }
        };
        let _ = shutdown_tx.send(true);
        if let Some(server) = metrics_server {
            let _ = tokio::time::timeout(Duration::from_secs(2), server).await;
        }
        result
    })
}
