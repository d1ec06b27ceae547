//! `learner`: trains the shared driving policy from actors' rollouts and broadcasts its weights.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use clap::{Args, Parser, Subcommand};

use junction_common::shutdown::end_by_sigint;
use junction_common::telemetry::{LogFormat, init_logging};
use junction_core::config::{DEFAULT_TOML, Layer, RunConfig};
use junction_core::scenarios;
use junction_learner::algo;
use junction_learner::app::{LearnerApp, RunDir, ServeOptions, StopHandle, resolve_device};
use junction_learner::transport::bench as transport_bench;

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
    /// A shipped preset applied over the defaults, before everything else: fast (what
    /// `make run` trains with: one pass over large minibatches, the shortest wall-clock to a
    /// driving policy on two cores) or gpu (one GPU fed by many local actors). `learner config --preset NAME` prints it applied;
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
    let mut algorithm =
        algo::configured::build(&config, device).context("building the algorithm")?;
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

async fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let run_dir = RunDir::open(args.resume.as_deref(), args.run_dir.as_deref())?;
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
    let config = args
        .source
        .load(run_dir.config_fallback().as_deref(), &flags)?;
    let app = LearnerApp::build(
        config,
        ServeOptions {
            run_dir,
            local_actors: args.local_actors,
            local_actor_scenes: args.local_actor_scenes,
            local_actor_metrics_port: args.local_actor_metrics_port,
        },
    )
    .await?;
    tokio::spawn(stop_on_signal(app.stop_handle()));
    app.run().await.map(|_| ())
}

/// Set when Ctrl-C (SIGINT), not SIGTERM, stopped `serve`: the process then ends by SIGINT
/// ([`end_by_sigint`]) after its clean shutdown.
static STOPPED_BY_CTRL_C: AtomicBool = AtomicBool::new(false);

/// Stops training on Ctrl-C or SIGTERM; a second signal exits at once.
async fn stop_on_signal(stop: StopHandle) {
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
        if stop.stop() {
            tracing::warn!("second stop signal: exiting immediately");
            std::process::exit(130);
        }
        STOPPED_BY_CTRL_C.store(ctrl_c, Ordering::Relaxed);
        tracing::info!("stop signal received: finishing the current step, writing a checkpoint");
    }
}
