//! `actor`: simulates traffic scenes with the learner's current policy and streams the
//! trajectories to it.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use tracing::Instrument;

use junction_actor::ledger::FragmentLog;
use junction_actor::metrics::ActorMetrics;
use junction_actor::replay::{self, Driver, ReplayOptions};
use junction_actor::session::ActorOptions;
use junction_actor::video::VideoWriter;
use junction_actor::{bench, eval, grpc, shm};
use junction_common::auth::Token;
use junction_common::shutdown::end_by_sigint;
use junction_common::telemetry::{LogFormat, init_logging, serve_metrics};
use junction_core::config::{AfterHorizon, ScenarioConfig};
use junction_core::evaluation::{EVAL_FORMAT, EvalActions, EvalReport};
use junction_core::scenarios;

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
    /// Draw an episode of the simulator from above as an animated GIF, MP4 or WebM (and PNG
    /// frames): roads and lane markings, agents (blue), human drivers (light grey), crashed
    /// cars left on the road (dark red), and brief rings where cars arrive (green), crash
    /// (orange) or leave the road (magenta).
    Render(RenderArgs),
    /// Evaluate a trained policy: every agent takes the policy's mean action (or a sampled
    /// one with --actions sample), in scenes seeded
    /// apart from training's, until N agent episodes have finished. Prints the paper's metrics
    /// (§4.2) and CoPO's with 95 % confidence intervals, and writes them to
    /// OUT/eval-<scenario>-seed<S>.json and .csv.
    Eval(EvalArgs),
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
    /// Give up (exit with an error) once the learner has been unreachable for this many
    /// seconds, at start or after losing it; 0 = retry for ever. Meanwhile a gRPC actor
    /// retries with exponential back-off and jitter; a shared-memory actor waits this long for
    /// the learner to appear and exits when it vanishes.
    #[arg(long, value_name = "SECONDS", default_value_t = 120.0)]
    connect_timeout: f64,
    /// First wait between connection attempts; it doubles per failed attempt up to
    /// --retry-max-delay (each wait drawn from [half, all] of it).
    #[arg(long, value_name = "SECONDS", default_value_t = 0.1)]
    retry_initial_delay: f64,
    /// Longest wait between connection attempts.
    #[arg(long, value_name = "SECONDS", default_value_t = 5.0)]
    retry_max_delay: f64,
    /// File holding the learner's shared token (or set JUNCTION_AUTH_TOKEN); sent with every
    /// RPC (gRPC only: shared memory is local to the host).
    #[arg(long, value_name = "FILE")]
    auth_token_file: Option<PathBuf>,
    /// PEM CA bundle to verify the learner's certificate (https:// URLs; default: the system's
    /// trust store).
    #[arg(long, value_name = "FILE")]
    tls_ca: Option<PathBuf>,
    /// Client certificate (PEM) for a learner that requires one (server.tls_client_ca).
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// Private key (PEM) of --tls-cert.
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Name to verify the learner's certificate against [default: the URL's host].
    #[arg(long, value_name = "NAME")]
    tls_domain: Option<String>,
    /// Largest gRPC message sent or accepted, in bytes (gRPC only).
    #[arg(long, default_value_t = 64 << 20)]
    max_message_bytes: usize,
    /// Name shown in the learner's logs [default: <hostname>/<pid>].
    #[arg(long)]
    name: Option<String>,
    /// Append this process's fragment ledger (what it produced and sent, one JSON line per
    /// event) to FILE, for `python -m junction.ledger` to reconcile with the learner's
    /// (docs/FAULTS.md). Restarted actors may share the file.
    #[arg(long, value_name = "FILE")]
    ledger: Option<PathBuf>,
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
    /// tiny-straight) or a scenario TOML file. Default: the scenario the checkpoint was
    /// trained on (its meta.json), else intersection.
    #[arg(long)]
    scenario: Option<String>,
    /// Drive every agent with this policy's deterministic action (a Gaussian policy's mean, a
    /// DQN policy's greedy grid point): a checkpoint directory
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
    /// The file to write; its extension picks the format: .gif (an animated GIF), .mp4
    /// (H.264) or .webm (VP9). MP4 and WebM need ffmpeg on PATH; without it a GIF of the same
    /// name ending in .gif is written instead (with a warning).
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
}

#[derive(Args)]
struct EvalArgs {
    /// The policy: a checkpoint directory (runs/<run>/checkpoints/ckpt-N), a run directory
    /// (its newest checkpoint) or a policy.safetensors file.
    #[arg(long, value_name = "PATH")]
    checkpoint: PathBuf,
    /// A shipped scenario name or a scenario TOML file [default: the scenario the checkpoint
    /// was trained on, from its meta.json].
    #[arg(long, value_name = "NAME|FILE")]
    scenario: Option<String>,
    /// Agent episodes to finish (the last step round may finish a few more; all are counted).
    #[arg(long, default_value_t = 1000, value_parser = clap::value_parser!(u64).range(1..))]
    episodes: u64,
    /// Evaluation seed. Scene k is seeded derive_seed(derive_seed(S, 0x4556414C00000000), k):
    /// a stream training never draws from (training scenes use the actor id's byte sum), so
    /// the traffic is held out from training whatever S is. Same seed, same result.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Scenes simulated side by side (each agent slot of each scene is a source of episodes).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..=256))]
    scenes: u32,
    /// What scenes do at the horizon (scenario.after_horizon) during the evaluation: finish
    /// (MetaDrive's evaluation: respawning stops and every agent on the road drives until it
    /// is done, so none is cut off) or reset (agents still driving end as timeouts). Only
    /// whole scene episodes are counted either way.
    #[arg(long, value_name = "MODE", default_value = "finish", value_parser = parse_after_horizon)]
    after_horizon: AfterHorizon,
    /// How agents act: mean (the policy's deterministic action, what a deployed policy does)
    /// or sample (drawn from its distribution as in training, seeded from --seed, so the
    /// figures compare with training-curve success such as CoPO's; a CoPO policy still sees
    /// its distribution's mean angle). Sampled results go to eval-<scenario>-seed<S>-sample.*
    #[arg(long, value_name = "MODE", default_value = "mean", value_parser = parse_eval_actions)]
    actions: EvalActions,
    /// Directory for the JSON and CSV [default: <run>/eval for a checkpoint inside a run
    /// directory, else ./eval].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Seconds between progress lines on stderr.
    #[arg(long, value_name = "SECONDS", default_value_t = 5.0)]
    progress_interval: f64,
    /// Threads libtorch may use for inference.
    #[arg(long, default_value_t = 1)]
    torch_threads: i32,
}

fn parse_eval_actions(text: &str) -> Result<EvalActions, String> {
    match text {
        "mean" => Ok(EvalActions::Mean),
        "sample" => Ok(EvalActions::Sample),
        other => Err(format!("{other:?} is not mean or sample")),
    }
}

fn parse_after_horizon(text: &str) -> Result<AfterHorizon, String> {
    match text {
        "finish" => Ok(AfterHorizon::Finish),
        "reset" => Ok(AfterHorizon::Reset),
        other => Err(format!("{other:?} is not finish or reset")),
    }
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
        Some(Command::Eval(args)) => evaluate(args),
        None => {
            if run_actor(cli.run)? {
                end_by_sigint();
            }
            Ok(())
        }
    }
}

/// `actor render`: checks everything it can before creating the output, then streams the
/// frames into it and prints one JSON line.
fn render(args: RenderArgs) -> anyhow::Result<()> {
    let trained_on = match &args.checkpoint {
        Some(path) => eval::training_info(&replay::policy_file(path)?)?.1,
        None => None,
    };
    let scenario = match (&args.scenario, trained_on) {
        (Some(name), _) => scenarios::load(name)?,
        (None, Some(scenario)) => scenario,
        (None, None) => scenarios::load("intersection")?,
    };
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
            let loaded = replay::policy_driver(path, &scenario)?;
            tracing::info!(policy = %loaded.file.display(), "driving with the policy's deterministic action");
            loaded.driver
        }
        None => Driver::Autopilot,
    };
    if let Some(dir) = &args.frames_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let (width, height) = args.size;
    let frame_seconds = scenario.decision_dt * args.every as f32;
    let (mut video, written) = VideoWriter::create(&args.out, width, height, frame_seconds)?;
    let options = ReplayOptions {
        seed: args.seed,
        steps: args.steps,
        every: args.every,
        width,
        height,
        lidar_slot: args.lidar,
    };
    let summary = replay::run(&scenario, &driver, &options, |step, frame| {
        video.write(frame)?;
        if let Some(dir) = &args.frames_dir {
            replay::write_png(&dir.join(format!("frame-{step:06}.png")), frame)?;
        }
        Ok(())
    })?;
    video
        .finish()
        .with_context(|| format!("writing {}", written.path.display()))?;
    let mut report = serde_json::to_value(&summary)?;
    report["out"] = written.path.display().to_string().into();
    report["format"] = written.format.name().into();
    report["scenario"] = scenario.name.clone().into();
    println!("{report}");
    Ok(())
}

/// `actor eval`: loads the policy, simulates until enough episodes have finished (progress on
/// stderr), prints the metrics table and writes the JSON and CSV.
fn evaluate(args: EvalArgs) -> anyhow::Result<()> {
    tch::set_num_threads(args.torch_threads.max(1));
    let file = replay::policy_file(&args.checkpoint)?;
    let (training, trained_on) = eval::training_info(&file)?;
    let scenario = match (&args.scenario, trained_on) {
        (Some(name), _) => scenarios::load(name)?,
        (None, Some(scenario)) => scenario,
        (None, None) => anyhow::bail!(
            "{} has no meta.json naming its training scenario: give --scenario",
            file.display()
        ),
    };
    let scenario = ScenarioConfig {
        after_horizon: args.after_horizon,
        ..scenario
    };
    let loaded = replay::policy_driver(&file, &scenario)?;
    let out_dir = args
        .out
        .unwrap_or_else(|| eval::default_out_dir(&loaded.file));
    std::fs::create_dir_all(&out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    tracing::info!(
        policy = %loaded.file.display(),
        version = loaded.version,
        scenario = %scenario.name,
        episodes = args.episodes,
        seed = args.seed,
        actions = match args.actions {
            EvalActions::Mean => "the policy's mean",
            EvalActions::Sample => "sampled",
        },
        "evaluating the policy"
    );
    let options = eval::EvalOptions {
        seed: args.seed,
        episodes: args.episodes,
        scenes: args.scenes as usize,
        actions: args.actions,
    };
    let started = Instant::now();
    let mut last_report = started;
    let tally = eval::run(&scenario, &loaded.driver, &options, |tally| {
        if last_report.elapsed().as_secs_f64() < args.progress_interval {
            return;
        }
        last_report = Instant::now();
        let done = tally.episodes.len() as u64;
        let elapsed = started.elapsed().as_secs_f64();
        let remaining = args.episodes.saturating_sub(done) as f64;
        tracing::info!(
            episodes = format!("{done}/{}", args.episodes),
            scene_steps = tally.scene_steps,
            elapsed_s = format!("{elapsed:.0}"),
            eta_s = format!("{:.0}", elapsed * remaining / done.max(1) as f64),
            "evaluating"
        );
    })?;
    let report = EvalReport {
        format: EVAL_FORMAT.to_string(),
        policy: loaded.file.display().to_string(),
        policy_version: loaded.version,
        training,
        scenario: scenario.name.clone(),
        seed: args.seed,
        scenes: options.scenes,
        episodes_requested: args.episodes,
        episodes: tally.episodes.len() as u64,
        outcomes: tally.outcomes(),
        endings: tally.endings.clone(),
        scene_steps: tally.scene_steps,
        sim_seconds: tally.sim_seconds,
        collisions: tally.collisions,
        scene_episodes: tally.scene_episodes.len() as u64,
        after_horizon: Some(args.after_horizon),
        actions: args.actions,
        metrics: tally.metrics(args.seed),
        wall_s: started.elapsed().as_secs_f64(),
    };
    let stem = out_dir.join(format!(
        "eval-{}-seed{}{}",
        eval::file_safe(&scenario.name),
        args.seed,
        match args.actions {
            EvalActions::Mean => "",
            EvalActions::Sample => "-sample",
        }
    ));
    let json_path = stem.with_extension("json");
    let csv_path = stem.with_extension("csv");
    std::fs::write(&json_path, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("writing {}", json_path.display()))?;
    std::fs::write(&csv_path, report.to_csv())
        .with_context(|| format!("writing {}", csv_path.display()))?;
    print!("{}", report.to_table());
    println!("wrote {} and {}", json_path.display(), csv_path.display());
    Ok(())
}

/// A duration flag: finite and not negative.
fn seconds(value: f64, flag: &str) -> anyhow::Result<Duration> {
    Duration::try_from_secs_f64(value)
        .map_err(|_| anyhow::anyhow!("{flag} {value} is not a number of seconds"))
}

/// How this actor reaches its learner (`--learner`).
enum Transport {
    Shm(String),
    Grpc(grpc::GrpcOptions),
}

/// Runs until the learner ends the run or a stop signal arrives; true when Ctrl-C stopped it,
/// so that the process then ends by SIGINT ([`end_by_sigint`]).
fn run_actor(args: RunArgs) -> anyhow::Result<bool> {
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
        let transport = match args.learner.strip_prefix("shm://") {
            Some(name) => {
                if args.tls_ca.is_some()
                    || args.tls_cert.is_some()
                    || args.tls_domain.is_some()
                    || args.auth_token_file.is_some()
                {
                    anyhow::bail!(
                        "--tls-* and --auth-token-file secure gRPC; shm://NAME is local to this host and takes neither"
                    );
                }
                Transport::Shm(name.to_string())
            }
            None => Transport::Grpc(grpc::GrpcOptions {
                learner: args.learner.clone(),
                retry_initial: seconds(args.retry_initial_delay, "--retry-initial-delay")?,
                retry_max: seconds(args.retry_max_delay, "--retry-max-delay")?,
                max_message_bytes: args.max_message_bytes,
                tls: grpc::TlsOptions {
                    ca: args.tls_ca,
                    cert: args.tls_cert,
                    key: args.tls_key,
                    domain: args.tls_domain,
                },
                token: Token::load(args.auth_token_file.as_deref())?,
            }),
        };
        let name = args
            .name
            .unwrap_or_else(|| format!("{}/{}", hostname.trim(), std::process::id()));
        let transport_name = match transport {
            Transport::Shm(_) => "shm",
            Transport::Grpc(_) => "grpc",
        };
        let log = Arc::new(match &args.ledger {
            Some(path) => FragmentLog::open(path, &name, transport_name)
                .with_context(|| format!("opening the fragment ledger {}", path.display()))?,
            None => FragmentLog::off(&name),
        });
        let options = ActorOptions {
            name,
            log: Arc::clone(&log),
            scenes: args.scenes as usize,
            seed: args.seed,
            give_up_after: (args.connect_timeout > 0.0)
                .then(|| seconds(args.connect_timeout, "--connect-timeout"))
                .transpose()?,
        };
        let span = tracing::info_span!(
            "actor",
            id = tracing::field::Empty,
            scenario = tracing::field::Empty
        );
        let transport = async {
            match transport {
                Transport::Shm(name) => shm::run(&name, options, metrics).await,
                Transport::Grpc(grpc_options) => grpc::run(options, grpc_options, metrics).await,
            }
        };
        let result = tokio::select! {
            result = transport.instrument(span) => result.map(|()| false),
            signal = stop_signal() => {
                tracing::info!(signal, "interrupted");
                Ok(signal == "SIGINT")
            }
        };
        // Not killed: whatever it produced and did not send, it knows it did not.
        log.stop();
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
