//! Logs and the Prometheus `/metrics` endpoint, shared by both binaries.

use std::convert::Infallible;
use std::future::Future;

use http_body_util::Full;
use hyper::body::{Bytes, Incoming};
use hyper::{Request, Response, StatusCode};
use prometheus::core::Collector;
use prometheus::{
    Counter, CounterVec, Encoder, Gauge, GaugeVec, Histogram, HistogramOpts, IntCounter,
    IntCounterVec, IntGauge, Opts, Registry, TextEncoder,
};

/// Metric names, in one place so dashboards, tests and code agree. Prometheus conventions:
/// `junction_` prefix, base units, `_total` on counters.
pub mod names {
    pub const LEARNER_POLICY_VERSION: &str = "junction_learner_policy_version";
    pub const LEARNER_AGENT_STEPS: &str = "junction_learner_agent_steps_total";
    pub const LEARNER_ENV_STEPS: &str = "junction_learner_env_steps_total";
    pub const LEARNER_FRAGMENTS: &str = "junction_learner_fragments_total";
    pub const LEARNER_FRAGMENTS_REJECTED: &str = "junction_learner_fragments_rejected_total";
    pub const LEARNER_FRAGMENTS_DROPPED: &str = "junction_learner_fragments_dropped_total";
    pub const LEARNER_FRAGMENTS_TRAINED: &str = "junction_learner_fragments_trained_total";
    pub const LEARNER_AGENT_STEPS_ACCEPTED: &str = "junction_learner_agent_steps_accepted_total";
    pub const LEARNER_AGENT_STEPS_DROPPED: &str = "junction_learner_agent_steps_dropped_total";
    pub const LEARNER_REQUESTS_REFUSED: &str = "junction_learner_requests_refused_total";
    pub const LEARNER_SAMPLES_TRAINED: &str = "junction_learner_samples_trained_total";
    pub const LEARNER_UPDATES: &str = "junction_learner_updates_total";
    pub const LEARNER_CHECKPOINT_FAILURES: &str = "junction_learner_checkpoint_failures_total";
    pub const LEARNER_UPDATE_SECONDS: &str = "junction_learner_update_duration_seconds";
    pub const LEARNER_CONNECTED_ACTORS: &str = "junction_learner_connected_actors";
    pub const LEARNER_QUEUE_FRAGMENTS: &str = "junction_learner_ingest_queue_fragments";
    pub const LEARNER_TRANSPORT_BYTES: &str = "junction_learner_transport_received_bytes_total";
    pub const LEARNER_EPISODES: &str = "junction_learner_episodes_total";
    pub const LEARNER_HUMAN_EPISODES: &str = "junction_learner_human_episodes_total";
    pub const LEARNER_SUCCESS_RATE: &str = "junction_learner_success_rate";
    pub const LEARNER_CRASH_RATE: &str = "junction_learner_crash_rate";
    pub const LEARNER_OUT_OF_ROAD_RATE: &str = "junction_learner_out_of_road_rate";
    pub const LEARNER_EPISODE_REWARD_MEAN: &str = "junction_learner_episode_reward_mean";
    pub const LEARNER_EPISODE_LENGTH_MEAN: &str = "junction_learner_episode_length_mean";
    pub const LEARNER_EPISODE_REWARD_MAX: &str = "junction_learner_episode_reward_max";
    pub const LEARNER_EPISODE_LENGTH_MAX: &str = "junction_learner_episode_length_max";
    pub const LEARNER_ACCEL_MEAN: &str = "junction_learner_episode_accel_mean_meters_per_second2";
    pub const LEARNER_ACCEL_MAX: &str = "junction_learner_episode_accel_max_meters_per_second2";
    pub const LEARNER_COLLISIONS: &str = "junction_learner_collisions_total";
    pub const LEARNER_SIMULATED_SECONDS: &str = "junction_learner_simulated_seconds_total";
    pub const LEARNER_POLICY_LAG: &str = "junction_learner_policy_lag_versions";
    pub const LEARNER_TRAINED_POLICY_LAG: &str = "junction_learner_trained_policy_lag_versions";
    pub const LEARNER_SCENE_EPISODES: &str = "junction_learner_scene_episodes_total";
    pub const LEARNER_SCENE_SUCCESS_RATE: &str = "junction_learner_scene_success_rate";
    pub const LEARNER_SCENE_CRASH_RATE: &str = "junction_learner_scene_crash_rate";
    pub const LEARNER_SCENE_OUT_OF_ROAD_RATE: &str = "junction_learner_scene_out_of_road_rate";
    pub const LEARNER_LEARNING_RATE: &str = "junction_learner_learning_rate";
    pub const LEARNER_LAGRANGE_MULTIPLIER: &str = "junction_learner_lagrange_multiplier";
    pub const LEARNER_LCF_MEAN: &str = "junction_learner_lcf_mean_degrees";
    pub const LEARNER_LCF_STD: &str = "junction_learner_lcf_std_degrees";
    pub const LEARNER_LCF_PHI: &str = "junction_learner_lcf_phi_degrees";
    pub const LEARNER_NONFINITE_MINIBATCHES: &str =
        "junction_learner_nonfinite_loss_minibatches_total";
    pub const LEARNER_POLICY_LOSS: &str = "junction_learner_policy_loss";
    pub const LEARNER_VALUE_LOSS: &str = "junction_learner_value_loss";
    pub const LEARNER_ENTROPY: &str = "junction_learner_entropy";
    pub const LEARNER_APPROX_KL: &str = "junction_learner_approx_kl";
    pub const LEARNER_CLIP_FRACTION: &str = "junction_learner_clip_fraction";
    pub const LEARNER_EXPLAINED_VARIANCE: &str = "junction_learner_explained_variance";
    pub const LEARNER_GRAD_NORM: &str = "junction_learner_grad_norm";
    pub const LEARNER_CURRICULUM_STAGE: &str = "junction_learner_curriculum_stage";
    pub const LEARNER_CURRICULUM_AGENTS: &str = "junction_learner_curriculum_agents";
    pub const LEARNER_Q_MEAN: &str = "junction_learner_q_value_mean";
    pub const LEARNER_EPSILON: &str = "junction_learner_exploration_epsilon";
    pub const LEARNER_REPLAY_TRANSITIONS: &str = "junction_learner_replay_transitions";
    pub const LEARNER_LOCAL_ACTOR_RESTARTS: &str = "junction_learner_local_actor_restarts_total";

    pub const ACTOR_ENV_STEPS: &str = "junction_actor_env_steps_total";
    pub const ACTOR_AGENT_STEPS: &str = "junction_actor_agent_steps_total";
    pub const ACTOR_FRAGMENTS_SENT: &str = "junction_actor_fragments_sent_total";
    pub const ACTOR_POLICY_VERSION: &str = "junction_actor_policy_version";
    pub const ACTOR_POLICY_SWITCHES: &str = "junction_actor_policy_switches_total";
    pub const ACTOR_INFERENCE_SECONDS: &str = "junction_actor_inference_seconds_total";
    pub const ACTOR_SIMULATION_SECONDS: &str = "junction_actor_simulation_seconds_total";
    pub const ACTOR_SCENE_AGENTS: &str = "junction_actor_scene_agents";
    pub const ACTOR_CONNECTED: &str = "junction_actor_connected";
    pub const ACTOR_RECONNECTS: &str = "junction_actor_reconnects_total";
    pub const ACTOR_FRAGMENTS_UNCONFIRMED: &str = "junction_actor_fragments_unconfirmed_total";
    pub const ACTOR_FRAGMENTS_CONFIRMED: &str = "junction_actor_fragments_confirmed_total";
    pub const ACTOR_TRANSPORT_SECONDS: &str = "junction_actor_transport_seconds_total";
}

/// Creates a metric and registers it in one call: how the actor's and the learner's metric
/// groups fill themselves from a shared [`Registry`] (each group's `register(&Registry)`).
/// Every call fails as `prometheus` does: a bad name or a name registered twice.
#[derive(Clone, Copy)]
pub struct Registrar<'a>(&'a Registry);

impl<'a> Registrar<'a> {
    pub fn new(registry: &'a Registry) -> Self {
        Registrar(registry)
    }

    /// Registers `metric` and hands it back.
    pub fn register<M: Collector + Clone + 'static>(
        &self,
        metric: M,
    ) -> Result<M, prometheus::Error> {
        self.0.register(Box::new(metric.clone()))?;
        Ok(metric)
    }

    pub fn int_counter(&self, name: &str, help: &str) -> Result<IntCounter, prometheus::Error> {
        self.register(IntCounter::new(name, help)?)
    }

    pub fn counter(&self, name: &str, help: &str) -> Result<Counter, prometheus::Error> {
        self.register(Counter::new(name, help)?)
    }

    pub fn int_gauge(&self, name: &str, help: &str) -> Result<IntGauge, prometheus::Error> {
        self.register(IntGauge::new(name, help)?)
    }

    pub fn gauge(&self, name: &str, help: &str) -> Result<Gauge, prometheus::Error> {
        self.register(Gauge::new(name, help)?)
    }

    pub fn int_counter_vec(
        &self,
        name: &str,
        help: &str,
        labels: &[&str],
    ) -> Result<IntCounterVec, prometheus::Error> {
        self.register(IntCounterVec::new(Opts::new(name, help), labels)?)
    }

    pub fn counter_vec(
        &self,
        name: &str,
        help: &str,
        labels: &[&str],
    ) -> Result<CounterVec, prometheus::Error> {
        self.register(CounterVec::new(Opts::new(name, help), labels)?)
    }

    pub fn gauge_vec(
        &self,
        name: &str,
        help: &str,
        labels: &[&str],
    ) -> Result<GaugeVec, prometheus::Error> {
        self.register(GaugeVec::new(Opts::new(name, help), labels)?)
    }

    pub fn histogram(
        &self,
        name: &str,
        help: &str,
        buckets: Vec<f64>,
    ) -> Result<Histogram, prometheus::Error> {
        self.register(Histogram::with_opts(
            HistogramOpts::new(name, help).buckets(buckets),
        )?)
    }
}

/// `--log-format` of both binaries (parsed by clap through `FromStr`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LogFormat {
    #[default]
    Pretty,
    Json,
}

impl std::str::FromStr for LogFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "pretty" => Ok(LogFormat::Pretty),
            "json" => Ok(LogFormat::Json),
            other => Err(format!("unknown log format {other:?} (use pretty or json)")),
        }
    }
}

/// Installs the global `tracing` subscriber; `RUST_LOG` filters (default `info`).
pub fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    // Colours only on a terminal: logs redirected to files stay plain text.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(ansi)
        .with_writer(std::io::stderr);
    // A second init (e.g. in tests) keeps the first subscriber.
    let _ = match format {
        LogFormat::Pretty => builder.try_init(),
        LogFormat::Json => builder.json().with_current_span(true).try_init(),
    };
}

/// Serves `GET /metrics` (Prometheus text format) until `shutdown` completes.
pub async fn serve_metrics(
    listener: tokio::net::TcpListener,
    registry: Registry,
    shutdown: impl Future<Output = ()>,
) {
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            () = &mut shutdown => return,
        };
        let stream = match accepted {
            Ok((stream, _)) => stream,
            Err(e) => {
                // Out of file descriptors and the like: keep serving once it passes.
                tracing::warn!(error = %e, "metrics endpoint: accept failed");
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                continue;
            }
        };
        let registry = registry.clone();
        tokio::spawn(async move {
            let service = hyper::service::service_fn(move |request: Request<Incoming>| {
                let response = respond(&registry, &request);
                async move { Ok::<_, Infallible>(response) }
            });
            let io = hyper_util::rt::TokioIo::new(stream);
            if let Err(e) = hyper::server::conn::http1::Builder::new()
                .serve_connection(io, service)
                .await
            {
                tracing::debug!(error = %e, "metrics connection ended with an error");
            }
        });
    }
}

fn respond(registry: &Registry, request: &Request<Incoming>) -> Response<Full<Bytes>> {
    let reply = |status: StatusCode, content_type: &str, body: Vec<u8>| {
        let mut response = Response::new(Full::new(Bytes::from(body)));
        *response.status_mut() = status;
        if let Ok(value) = content_type.parse() {
            response
                .headers_mut()
                .insert(hyper::header::CONTENT_TYPE, value);
        }
        response
    };
    match (request.method(), request.uri().path()) {
        (&hyper::Method::GET, "/metrics") => {
            let encoder = TextEncoder::new();
            let mut body = Vec::new();
            match encoder.encode(&registry.gather(), &mut body) {
                Ok(()) => reply(StatusCode::OK, encoder.format_type(), body),
                Err(e) => reply(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    "text/plain",
                    e.to_string().into_bytes(),
                ),
            }
        }
        (&hyper::Method::GET, "/") => reply(
            StatusCode::OK,
            "text/plain",
            b"Junction: metrics at /metrics\n".to_vec(),
        ),
        _ => reply(StatusCode::NOT_FOUND, "text/plain", b"not found\n".to_vec()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_registrar_registers_each_metric_it_makes_once() {
        let registry = Registry::new();
        let r = Registrar::new(&registry);
        r.int_counter("junction_test_total", "A counter.")
            .unwrap()
            .inc_by(3);
        r.histogram("junction_test_seconds", "A histogram.", vec![1.0, 2.0])
            .unwrap()
            .observe(1.5);
        r.gauge_vec("junction_test_rate", "A gauge by label.", &["scenario"])
            .unwrap()
            .with_label_values(&["tiny"])
            .set(0.5);
        let families = registry.gather();
        let names: Vec<&str> = families.iter().map(|f| f.name()).collect();
        assert_eq!(
            names,
            [
                "junction_test_rate",
                "junction_test_seconds",
                "junction_test_total"
            ]
        );
        assert_eq!(families[2].get_metric()[0].get_counter().get_value(), 3.0);
        assert_eq!(
            families[1].get_metric()[0]
                .get_histogram()
                .get_sample_count(),
            1
        );
        assert!(r.int_counter("junction_test_total", "Again.").is_err());
    }
}
