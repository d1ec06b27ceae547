//! `actor`: simulates traffic scenes with the learner's current policy and streams the
//! trajectories to it.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use tracing::Instrument;

use junction_actor::metrics::ActorMetrics;
use junction_actor::replay::{self, Driver, GifWriter, ReplayOptions};
use junction_actor::session::ActorOptions;
use junction_actor::{bench, grpc, shm};
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
    /// Draw an episode of the simulator from above as an animated GIF (and PNG frames):
    /// roads and lane markings, agents (blue), human drivers (light grey), crashed cars left on
    /// the road (dark red), and
    /// brief rings where cars arrive (green), crash (orange) or leave the road (magenta).
    Render(RenderArgs),
}

#[derive(Args)]
struct RunArgs {
    /// The learner: its gRPC address (http://HOST:PORT), or shm://NAME for the learner on
    /// this host serving shared memory as NAME (its server.shm_name).
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
    /// Largest gRPC message sent or accepted, in bytes (gRPC only).
    #[arg(long, default_value_t = 64 << 20)]
    max_message_bytes: usize,
    /// Name shown in the learner's logs [default: <hostname>/<pid>].
    #[arg(long)]
    name: Option<String>,
}

#[derive(Args)]
struct BenchArgs {
    /// A shipped scenario name (intersection, intersection-metadrive, t-junction,
    /// roundabout, roundabout-metadrive, roundabout-compact-3arm, roundabout-large-5arm,
    /// tiny-straight) or a scenario TOML file.
    #[arg(long, default_value = "intersection")]
    scenario: String,
    /// Scene steps to simulate.
    #[arg(long, default_value_t = 5000)]
    steps: u64,
    /// Scene seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

#[derive(Args)]
struct RenderArgs {
    /// A shipped scenario name (intersection, intersection-metadrive, t-junction,
    /// roundabout, roundabout-metadrive, roundabout-compact-3arm, roundabout-large-5arm,
    /// tiny-straight) or a scenario TOML file.
    #[arg(long, default_value = "intersection")]
    scenario: String,
    /// Drive every agent with this policy's mean action: a checkpoint directory
    /// (runs/<run>/checkpoints/ckpt-N), a run directory (its newest checkpoint) or a
    /// policy.safetensors file. Without it the scripted autopilot drives.
    #[arg(long, value_name = "DIR")]
    checkpoint: Option<PathBuf>,
    /// Scene seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Decision steps (0.1 s each) to simulate.
    #[arg(long, default_value_t = 200)]
    steps: u64,
    /// Draw one frame every K decision steps: the scene at steps 0, K, 2K, … up to --steps
    /// (the GIF still plays in simulated time).
    #[arg(long, value_name = "K", default_value_t = 1,
          value_parser = clap::value_parser!(u64).range(1..))]
    every: u64,
    /// Frame size in pixels: N for N×N, or WxH.
    #[arg(long, default_value = "640", value_parser = parse_size)]
    size: (usize, usize),
    /// Draw the lidar beams of the agent in this slot (slot 0 when given without a value);
    /// that agent is drawn in cyan.
    #[arg(long, value_name = "SLOT", num_args = 0..=1, default_missing_value = "0")]
    lidar: Option<usize>,
    /// Also write every frame as DIR/frame-<step>.png.
    #[arg(long, value_name = "DIR")]
    frames_dir: Option<PathBuf>,
    /// The animated GIF to write.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
}

/// Frames from 16 to 4096 pixels a side: GIF's own limit is 65535, but larger frames only
/// make huge files.
fn parse_size(text: &str) -> Result<(usize, usize), String> {
    let parse = |t: &str| -> Result<usize, String> {
        t.trim()
            .parse::<usize>()
            .ok()
            .filter(|n| (16..=4096).contains(n))
            .ok_or_else(|| format!("{t:?} is not a size from 16 to 4096 pixels"))
    };
    match text.split_once(['x', 'X']) {
        Some((w, h)) => Ok((parse(w)?, parse(h)?)),
        None => parse(text).map(|n| (n, n)),
    }
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
        Some(Command::Render(args)) => render(args),
        None => run_actor(cli.run),
    }
}

/// `actor render`: checks everything it can before creating the GIF, then streams the frames
/// into it and prints one JSON line.
fn render(args: RenderArgs) -> anyhow::Result<()> {
    let scenario = scenarios::load(&args.scenario)?;
    if let Some(slot) = args.lidar {
        anyhow::ensure!(
            slot < scenario.agents,
            "--lidar {slot}: scenario {:?} has agent slots 0..{}",
            scenario.name,
            scenario.agents
        );
    }
    let driver = match &args.checkpoint {
        Some(path) => {
            let file = replay::policy_file(path)?;
            let bytes =
                std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
            let policy = replay::load_policy(&bytes, &scenario)
                .with_context(|| format!("loading the policy in {}", file.display()))?;
            tracing::info!(policy = %file.display(), "driving with the policy's mean action");
            Driver::Policy(policy)
        }
        None => Driver::Autopilot,
    };
    if let Some(dir) = &args.frames_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let (width, height) = args.size;
    let frame_seconds = scenario.decision_dt * args.every as f32;
    let mut gif = GifWriter::create(&args.out, width, height, frame_seconds)?;
    let options = ReplayOptions {
        seed: args.seed,
        steps: args.steps,
        every: args.every,
        width,
        height,
        lidar_slot: args.lidar,
    };
    let summary = replay::run(&scenario, &driver, &options, |step, frame| {
        gif.write(frame)?;
        if let Some(dir) = &args.frames_dir {
            replay::write_png(&dir.join(format!("frame-{step:06}.png")), frame)?;
        }
        Ok(())
    })?;
    gif.finish()
        .with_context(|| format!("writing {}", args.out.display()))?;
    let mut report = serde_json::to_value(&summary)?;
    report["out"] = args.out.display().to_string().into();
    println!("{report}");
    Ok(())
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
        let options = ActorOptions {
            name: args
                .name
                .unwrap_or_else(|| format!("{}/{}", hostname.trim(), std::process::id())),
            scenes: args.scenes as usize,
            seed: args.seed,
            connect_timeout: Duration::from_secs_f64(args.connect_timeout.max(0.0)),
        };
        let span = tracing::info_span!(
            "actor",
            id = tracing::field::Empty,
            scenario = tracing::field::Empty
        );
        let transport = async {
            match args.learner.strip_prefix("shm://") {
                Some(name) => shm::run(name, options, metrics).await,
                None => grpc::run(&args.learner, args.max_message_bytes, options, metrics).await,
            }
        };
        let result = tokio::select! {
            result = transport.instrument(span) => result,
            signal = stop_signal() => {
                tracing::info!(signal, "interrupted");
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

/// Ctrl-C or SIGTERM (what `docker stop` and a supervising learner send).
async fn stop_signal() -> &'static str {
    let mut term = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
        Ok(term) => term,
        Err(e) => {
            tracing::warn!(error = %e, "cannot listen for SIGTERM");
            let _ = tokio::signal::ctrl_c().await;
            return "SIGINT";
        }
    };
    tokio::select! {
        _ = tokio::signal::ctrl_c() => "SIGINT",
        _ = term.recv() => "SIGTERM",
    }
}
