//! A learner and an actor in this process, through their libraries (linkerd's in-process
//! test): `LearnerApp::build` on loopback port 0, the actor library's gRPC entry point on a
//! thread of its own against `grpc_addr()`, a few policy versions trained, then a stop
//! through the app's stop handle and a clean end on both sides. The process tests keep
//! signals and exit codes.

use std::sync::Arc;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use junction_actor::grpc::{GrpcOptions, TlsOptions};
use junction_actor::ledger::FragmentLog;
use junction_actor::metrics::ActorMetrics;
use junction_actor::session::ActorOptions;
use junction_common::proto::{self, learner_client::LearnerClient};
use junction_common::telemetry::{LogFormat, init_logging};
use junction_core::config::{Layer, RunConfig};
use junction_core::scenarios;
use junction_learner::app::{LearnerApp, RunDir, ServeOptions, StopHandle};
use junction_tests::{TempDir, checkpoint_versions, unique_shm_name};

/// Versions the learner must publish before it is stopped.
const VERSIONS: u64 = 3;
/// How long those may take, and how long each side may take to stop.
const TRAIN_TIMEOUT: Duration = Duration::from_secs(120);
const STOP_TIMEOUT: Duration = Duration::from_secs(60);

/// Requests the stop and bounds the runtime's shutdown, also when an assertion fails first:
/// the training thread then ends and the test fails instead of hanging.
struct Learner {
    runtime: Option<tokio::runtime::Runtime>,
    stop: StopHandle,
}

impl Drop for Learner {
    fn drop(&mut self) {
        self.stop.stop();
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_timeout(STOP_TIMEOUT);
        }
    }
}

#[test]
fn learner_app_trains_an_in_process_actor_and_stops_cleanly() {
    if std::env::var_os("RUST_LOG").is_some() {
        init_logging(LogFormat::Pretty);
    }
    let started = Instant::now();
    let dir = TempDir::new("in-process");
    let run_path = dir.path().join("run");
    let scenario = scenarios::text("tiny-straight").unwrap();
    let sets: Vec<String> = [
        "server.addr=\"127.0.0.1:0\"",
        "server.metrics_addr=\"127.0.0.1:0\"",
        &format!("server.shm_name={:?}", unique_shm_name()),
        "learner.device=\"cpu\"",
        "ppo.hidden=[16]",
        "ppo.epochs=1",
        "rollout.fragment_length=25",
        "ppo.train_batch_env_steps=50",
        "run.max_seconds=300",
        "run.progress_interval_s=1",
        // Only the final checkpoint, the one a clean stop writes.
        "run.checkpoint_every_updates=0",
    ]
    .map(String::from)
    .into();
    let layers: Vec<Layer> = std::iter::once(Layer::Scenario(&scenario))
        .chain(sets.iter().map(|s| Layer::Set(s)))
        .collect();
    let config = RunConfig::from_layers(&layers).expect("configuration");

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let run_dir = RunDir::open(None, Some(&run_path)).expect("a new run directory");
    let app = runtime
        .block_on(LearnerApp::build(config, ServeOptions::new(run_dir)))
        .expect("the learner builds");
    let grpc_addr = app.grpc_addr();
    assert!(
        grpc_addr.ip().is_loopback() && grpc_addr.port() != 0,
        "{grpc_addr}"
    );
    assert_ne!(app.metrics_addr().port(), 0);
    assert!(!app.shm_name().is_empty());
    let stop = app.stop_handle();
    let learner = Learner {
        runtime: Some(runtime),
        stop: stop.clone(),
    };
    let runtime = learner.runtime.as_ref().unwrap();
    let run = runtime.spawn(app.run());

    // The actor, as `actor --learner http://ADDR` runs it: its own runtime on its own thread.
    let (actor_tx, actor_rx) = mpsc::channel();
    let actor = std::thread::spawn(move || {
        let options = ActorOptions {
            name: "in-process".into(),
            scenes: 1,
            seed: 0,
            give_up_after: Some(Duration::from_secs(30)),
            log: Arc::new(FragmentLog::off("in-process")),
        };
        let grpc = GrpcOptions {
            learner: format!("http://{grpc_addr}"),
            retry_initial: Duration::from_millis(100),
            retry_max: Duration::from_secs(1),
            max_message_bytes: 64 << 20,
            tls: TlsOptions::default(),
            token: None,
        };
        let metrics = Arc::new(ActorMetrics::new().expect("actor metrics"));
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let outcome = runtime.block_on(junction_actor::grpc::run(options, grpc, metrics));
        let _ = actor_tx.send(outcome.map_err(|e| format!("{e:#}")));
    });

    // The learner's Status, as any client sees it, until VERSIONS versions are out.
    let status = runtime.block_on(async {
        tokio::time::timeout(TRAIN_TIMEOUT, async {
            let mut client = loop {
                if let Ok(client) = LearnerClient::connect(format!("http://{grpc_addr}")).await {
                    break client;
                }
                tokio::time::sleep(Duration::from_millis(100)).await;
            };
            loop {
                let reply = client
                    .status(proto::StatusRequest {})
                    .await
                    .expect("Status answers")
                    .into_inner();
                if reply.policy_version >= VERSIONS {
                    return reply;
                }
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        })
        .await
    });
    let status = status.unwrap_or_else(|_| {
        panic!("fewer than {VERSIONS} policy versions within {TRAIN_TIMEOUT:?}")
    });
    assert!(status.agent_steps_consumed > 0, "{status:?}");
    assert_eq!(status.connected_actors, 1, "{status:?}");

    // Stop through the app: the trainer finishes its step, checkpoints, tells the actor the
    // run is over, and the servers stop in order.
    assert!(!stop.stop(), "no stop was requested before");
    let progress = runtime
        .block_on(async { tokio::time::timeout(STOP_TIMEOUT, run).await })
        .expect("the learner stops within the timeout")
        .expect("the learner task does not panic")
        .expect("the run ends cleanly");
    assert!(progress.version >= VERSIONS, "{progress:?}");
    assert!(
        progress.agent_steps > 0 && progress.samples_trained > 0,
        "{progress:?}"
    );

    let actor_outcome = actor_rx
        .recv_timeout(STOP_TIMEOUT)
        .expect("the actor exits once told the run is over");
    assert_eq!(actor_outcome, Ok(()), "the actor ends cleanly");
    actor.join().expect("the actor thread does not panic");

    // The run directory holds what `learner serve` leaves: the final checkpoint at the final
    // version, the configuration, progress lines and the endpoints.
    assert_eq!(checkpoint_versions(&run_path), vec![progress.version]);
    for file in ["config.toml", "progress.jsonl", "endpoints.json"] {
        assert!(run_path.join(file).exists(), "{file} is missing");
    }
    let endpoints: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run_path.join("endpoints.json")).unwrap())
            .unwrap();
    assert_eq!(endpoints["grpc"], grpc_addr.to_string());
    drop(learner);
    eprintln!("in-process run: {:.1} s", started.elapsed().as_secs_f64());
}
