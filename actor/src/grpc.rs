//! The actor side of the gRPC transport: register, follow the policy stream, and push
//! fragments produced by the rollout thread; reconnect with back-off when the learner goes
//! away (see docs/FAULTS.md). What happens between registering and sending is the
//! transport-independent `session`.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use tokio::sync::{mpsc, watch};
use tonic::service::Interceptor;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};

use junction_common::auth::{self, Token};
use junction_common::fragment::RolloutFragment;
use junction_common::proto::{self, learner_client::LearnerClient};
use junction_common::{GRPC_CONNECTION_WINDOW_BYTES, GRPC_STREAM_WINDOW_BYTES};
use junction_core::spec::PROTOCOL_VERSION;

use crate::metrics::ActorMetrics;
use crate::reconnect::{Backoff, OutboxStream, retryable};
use crate::session::{
    ActorOptions, Registration, RolloutPlan, RunTerms, check_weights, rollout_loop,
};

/// Fragments buffered between the rollout thread and the push stream; when full, the rollout
/// thread waits (the learner's backpressure reaches the simulator). While the learner is
/// unreachable these wait here and go out on the next connection; the simulation pauses once
/// the outbox is full.
const OUTBOX_FRAGMENTS: usize = 4;
/// How long one connection attempt, a registration or the first weights may take.
const CALL_TIMEOUT: Duration = Duration::from_secs(30);
/// How long a broken rollout stream waits for the learner's end-of-run message.
const FINISH_GRACE: Duration = Duration::from_secs(2);
/// HTTP/2 pings that notice a learner host that vanished without closing the connection.
const KEEPALIVE: Duration = Duration::from_secs(20);

/// How to reach the learner over gRPC.
pub struct GrpcOptions {
    pub learner: String,
    /// First and largest wait between connection attempts.
    pub retry_initial: Duration,
    pub retry_max: Duration,
    pub max_message_bytes: usize,
    pub tls: TlsOptions,
    pub token: Option<Token>,
}

/// Client-side TLS (used with an `https://` learner URL).
#[derive(Default)]
pub struct TlsOptions {
    /// PEM CA bundle that signed the learner's certificate (default: the system's roots).
    pub ca: Option<PathBuf>,
    /// Client certificate and key for a learner that requires them (mutual TLS).
    pub cert: Option<PathBuf>,
    pub key: Option<PathBuf>,
    /// Name to verify the learner's certificate against (default: the URL's host).
    pub domain: Option<String>,
}

fn read(path: &PathBuf, what: &str) -> anyhow::Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("reading the {what} {}", path.display()))
}

/// The learner's endpoint; a bad URL or unreadable TLS files are errors before any attempt.
fn endpoint(options: &GrpcOptions) -> anyhow::Result<Endpoint> {
    let url = &options.learner;
    let mut endpoint = Endpoint::from_shared(url.to_string())
        .with_context(|| {
            format!("--learner {url:?} is not a valid URL (expected e.g. http://127.0.0.1:50051)")
        })?
        .connect_timeout(Duration::from_secs(5))
        .initial_stream_window_size(GRPC_STREAM_WINDOW_BYTES)
        .initial_connection_window_size(GRPC_CONNECTION_WINDOW_BYTES)
        .tcp_nodelay(true)
        .http2_keep_alive_interval(KEEPALIVE)
        .keep_alive_timeout(KEEPALIVE)
        .keep_alive_while_idle(true);
    let tls = &options.tls;
    let wants_tls = tls.ca.is_some() || tls.cert.is_some() || tls.domain.is_some();
    if url.starts_with("https://") {
        let mut config = ClientTlsConfig::new();
        config = match &tls.ca {
            Some(ca) => config.ca_certificate(Certificate::from_pem(read(ca, "--tls-ca")?)),
            None => config.with_native_roots(),
        };
        match (&tls.cert, &tls.key) {
            (Some(cert), Some(key)) => {
                config = config.identity(Identity::from_pem(
                    read(cert, "--tls-cert")?,
                    read(key, "--tls-key")?,
                ));
            }
            (None, None) => {}
            _ => bail!("--tls-cert and --tls-key go together"),
        }
        if let Some(domain) = &tls.domain {
            config = config.domain_name(domain.clone());
        }
        endpoint = endpoint
            .tls_config(config)
            .context("configuring TLS for the learner connection")?;
    } else if wants_tls {
        bail!("--tls-* options need an https:// learner URL (got {url})");
    }
    Ok(endpoint)
}

/// Adds the shared token to every request.
#[derive(Clone)]
struct TokenHeader(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl Interceptor for TokenHeader {
    fn call(
        &mut self,
        mut request: tonic::Request<()>,
    ) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request.metadata_mut().insert(auth::HEADER, value.clone());
        }
        Ok(request)
    }
}

type Client = LearnerClient<tonic::service::interceptor::InterceptedService<Channel, TokenHeader>>;

/// How one connection ended.
enum SessionEnd {
    /// The learner finished the run on purpose.
    Finished,
    /// The learner went away or refused for now: try again. `connected` says whether this
    /// connection got as far as registering and receiving weights.
    Lost {
        error: anyhow::Error,
        connected: bool,
    },
    /// Trying again would fail the same way.
    Fatal(anyhow::Error),
}

fn lost(error: anyhow::Error, connected: bool) -> SessionEnd {
    SessionEnd::Lost { error, connected }
}

/// A failed call: lost or fatal depending on its status.
fn call_failed(status: tonic::Status, what: &str, connected: bool) -> SessionEnd {
    let error = anyhow::anyhow!("{what}: {} ({:?})", status.message(), status.code());
    if retryable(&status) {
        lost(error, connected)
    } else {
        SessionEnd::Fatal(error)
    }
}

/// A failed connection or registration that is this actor's or the learner's configuration,
/// not an outage: the learner's certificate rejected, or TLS on one side only. Retrying cannot
/// fix these, so they end the actor at once instead of after --connect-timeout. A refused or
/// reset connection says nothing specific and stays an outage.
fn misconfiguration(
    error: &(dyn std::error::Error + 'static),
    options: &GrpcOptions,
) -> Option<String> {
    let mut cause = Some(error);
    while let Some(error) = cause {
        let problem = match rustls_error(error) {
            Some(tls) => tls_problem(tls, options),
            None => plain_text_to_tls(error, &options.learner),
        };
        if let Some(problem) = problem {
            return Some(format!(
                "{problem}; this is a configuration error, not an outage"
            ));
        }
        cause = error.source();
    }
    None
}

/// An http:// URL and a learner whose first bytes back are no HTTP/2 frame: a TLS learner
/// answers a plain-text request with a TLS alert, which reads as a frame megabytes long.
fn plain_text_to_tls(cause: &(dyn std::error::Error + 'static), learner: &str) -> Option<String> {
    let h2 = cause.downcast_ref::<h2::Error>()?;
    let not_http2 =
        h2.is_go_away() && h2.is_library() && h2.reason() == Some(h2::Reason::FRAME_SIZE_ERROR);
    (learner.starts_with("http://") && not_http2).then(|| {
        format!(
            "the learner at {learner} does not speak plain-text gRPC (its reply is not HTTP/2, as from a learner with server.tls_cert): use an https:// URL and --tls-ca"
        )
    })
}

/// The rustls error `error` is, if any. tokio-rustls wraps it in an `io::Error`, whose
/// `source()` skips the wrapped error, hence `get_ref`.
fn rustls_error<'a>(error: &'a (dyn std::error::Error + 'static)) -> Option<&'a rustls::Error> {
    error.downcast_ref::<rustls::Error>().or_else(|| {
        error
            .downcast_ref::<std::io::Error>()
            .and_then(std::io::Error::get_ref)
            .and_then(|inner| inner.downcast_ref::<rustls::Error>())
    })
}

/// What a TLS failure says about the configuration, if it is one.
fn tls_problem(error: &rustls::Error, options: &GrpcOptions) -> Option<String> {
    match error {
        rustls::Error::InvalidCertificate(reason) => Some(format!(
            "the learner's TLS certificate was rejected ({reason}): {}",
            certificate_fix(reason, options)
        )),
        rustls::Error::InvalidMessage(_) => Some(format!(
            "the learner at {} does not speak TLS: use an http:// URL for a plain-text learner, or give the learner server.tls_cert and server.tls_key",
            options.learner
        )),
        _ => None,
    }
}

/// What to check for a learner's certificate this actor rejected.
fn certificate_fix(reason: &rustls::CertificateError, options: &GrpcOptions) -> String {
    use rustls::CertificateError as E;
    let trusted = match &options.tls.ca {
        Some(ca) => format!("--tls-ca {}", ca.display()),
        None => "the system's trust store (pass --tls-ca)".to_string(),
    };
    match reason {
        E::UnknownIssuer | E::BadSignature => format!(
            "it is not signed by a CA in {trusted}; check --tls-ca and the learner's server.tls_cert"
        ),
        E::NotValidForName | E::NotValidForNameContext { .. } => format!(
            "it is not issued for {}; pass --tls-domain with a name it is issued for, or reach the learner by that name",
            options
                .tls
                .domain
                .as_deref()
                .unwrap_or("the host of the --learner URL")
        ),
        E::Expired | E::ExpiredContext { .. } | E::NotValidYet | E::NotValidYetContext { .. } => {
            "it is out of date (or a clock is wrong); renew the learner's server.tls_cert"
                .to_string()
        }
        _ => format!(
            "the learner's server.tls_cert must be its own server certificate (not a CA's), signed by a CA in {trusted}"
        ),
    }
}

/// What lives across connections: the outbox, the weights the rollout thread follows, the
/// rollout thread itself.
struct Actor {
    options: ActorOptions,
    grpc: GrpcOptions,
    metrics: Arc<ActorMetrics>,
    outbox_tx: Option<mpsc::Sender<proto::RolloutFragment>>,
    outbox: Arc<Mutex<mpsc::Receiver<proto::RolloutFragment>>>,
    terms: Option<RunTerms>,
    weights: Option<watch::Sender<Arc<proto::PolicyWeights>>>,
    actor_id: watch::Sender<String>,
    finished: Arc<AtomicBool>,
    rollout: Option<tokio::task::JoinHandle<anyhow::Result<()>>>,
    /// Rollout streams opened so far; the ledger numbers them.
    connections: u64,
}

/// Runs until the learner says the run is finished (Ok), the learner stays unreachable longer
/// than `give_up_after`, or something retrying cannot fix happens (Err).
pub async fn run(
    options: ActorOptions,
    grpc: GrpcOptions,
    metrics: Arc<ActorMetrics>,
) -> anyhow::Result<()> {
    let endpoint = endpoint(&grpc)?;
    let jitter_seed = options.seed
        ^ u64::from(std::process::id())
        ^ std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0);
    let mut backoff = Backoff::new(grpc.retry_initial, grpc.retry_max, jitter_seed);
    let busy_tracker = tokio::spawn(count_runtime_busy_time(Arc::clone(&metrics)));
    let (outbox_tx, outbox_rx) = mpsc::channel(OUTBOX_FRAGMENTS);
    let mut actor = Actor {
        options,
        grpc,
        metrics,
        outbox_tx: Some(outbox_tx),
        outbox: Arc::new(Mutex::new(outbox_rx)),
        terms: None,
        weights: None,
        actor_id: watch::channel(String::new()).0,
        finished: Arc::new(AtomicBool::new(false)),
        rollout: None,
        connections: 0,
    };
    let mut unreachable_since = Instant::now();
    let mut reported = false;
    let outcome = loop {
        let end = actor.session(&endpoint).await;
        actor.metrics.connected.set(0);
        match end {
            SessionEnd::Finished => break Ok(()),
            SessionEnd::Fatal(error) => break Err(error),
            SessionEnd::Lost { error, connected } => {
                if connected {
                    unreachable_since = Instant::now();
                    backoff.reset();
                    reported = false;
                }
                let waited = unreachable_since.elapsed();
                if let Some(limit) = actor.options.give_up_after
                    && waited >= limit
                {
                    break Err(error.context(format!(
                        "the learner at {} has been unreachable for {:.0} s (--connect-timeout)",
                        actor.grpc.learner,
                        waited.as_secs_f64()
                    )));
                }
                let delay = backoff.next_delay();
                if reported {
                    tracing::info!(error = %format!("{error:#}"), retry_in_ms = delay.as_millis() as u64, "learner still unreachable");
                } else {
                    tracing::warn!(
                        learner = %actor.grpc.learner,
                        error = %format!("{error:#}"),
                        retry_in_ms = delay.as_millis() as u64,
                        "learner unreachable; retrying with back-off (fragments already produced wait in the outbox)"
                    );
                    reported = true;
                }
                tokio::time::sleep(delay).await;
            }
        }
    };
    busy_tracker.abort();
    actor.stop().await.and(outcome)
}

impl Actor {
    /// One connection: register, follow the weights, push the outbox until something ends.
    async fn session(&mut self, endpoint: &Endpoint) -> SessionEnd {
        let channel = match tokio::time::timeout(CALL_TIMEOUT, endpoint.connect()).await {
            Ok(Ok(channel)) => channel,
            Ok(Err(e)) => {
                return match misconfiguration(&e, &self.grpc) {
                    Some(problem) => SessionEnd::Fatal(anyhow::Error::new(e).context(problem)),
                    None => lost(anyhow::Error::new(e).context("connecting"), false),
                };
            }
            Err(_) => return lost(anyhow::anyhow!("connecting timed out"), false),
        };
        let header = match &self.grpc.token {
            Some(token) => match token.header_value().parse() {
                Ok(value) => Some(value),
                Err(_) => {
                    return SessionEnd::Fatal(anyhow::anyhow!(
                        "the auth token is not a valid header value"
                    ));
                }
            },
            None => None,
        };
        let bytes = self.grpc.max_message_bytes;
        let mut client: Client = LearnerClient::with_interceptor(channel, TokenHeader(header))
            .max_decoding_message_size(bytes)
            .max_encoding_message_size(bytes);
        let hello = proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_name: self.options.name.clone(),
            scenes: self.options.scenes as u32,
            instance: self.options.log.instance().to_string(),
        };
        let reply = match tokio::time::timeout(CALL_TIMEOUT, client.register(hello)).await {
            Ok(Ok(reply)) => reply.into_inner(),
            Ok(Err(status)) => {
                return match misconfiguration(&status, &self.grpc) {
                    Some(problem) => SessionEnd::Fatal(anyhow::Error::new(status).context(problem)),
                    None => call_failed(status, "registering with the learner", false),
                };
            }
            Err(_) => return lost(anyhow::anyhow!("registering timed out"), false),
        };
        let registration = match Registration::check(&reply, Some(bytes)) {
            Ok(registration) => registration,
            Err(e) => return SessionEnd::Fatal(e),
        };
        if self
            .terms
            .as_ref()
            .is_some_and(|known| *known != registration.terms)
        {
            return SessionEnd::Fatal(anyhow::anyhow!(
                "the learner came back with another scenario, fragment length or seed; restart this actor to join the new run"
            ));
        }
        let actor_id = registration.actor_id.clone();

        let watch = proto::WatchPolicyRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_id: actor_id.clone(),
            have_version: 0,
        };
        let mut policy_stream = match client.watch_policy(watch).await {
            Ok(stream) => stream.into_inner(),
            Err(status) => return call_failed(status, "subscribing to policy weights", false),
        };
        let first = match tokio::time::timeout(CALL_TIMEOUT, policy_stream.message()).await {
            Ok(Ok(Some(weights))) => weights,
            Ok(Ok(None)) => {
                return lost(
                    anyhow::anyhow!("the learner closed the policy stream before sending weights"),
                    false,
                );
            }
            Ok(Err(status)) => return call_failed(status, "receiving the first policy", false),
            Err(_) => {
                return lost(
                    anyhow::anyhow!("the first policy did not arrive in time"),
                    false,
                );
            }
        };
        if let Err(e) = check_weights(&first) {
            return SessionEnd::Fatal(e);
        }

        // Connected: from here on a failure is a lost connection to come back to.
        let reconnect = self.terms.is_some();
        self.metrics.connected.set(1);
        self.actor_id.send_replace(actor_id.clone());
        if reconnect {
            self.metrics.reconnects.inc();
            tracing::info!(
                new_id = %actor_id,
                version = first.version,
                "reconnected and registered again"
            );
        } else {
            registration.record_in_span();
            tracing::info!(scenes = self.options.scenes, "registered");
        }
        let finished_now = first.run_finished;
        match &self.weights {
            Some(weights) => {
                weights.send_replace(Arc::new(first));
            }
            None => {
                let (weights, weights_rx) = watch::channel(Arc::new(first));
                self.weights = Some(weights);
                // Seeds come from the first registration: the scenes keep running across
                // reconnects.
                self.start_rollout(registration.plan(&self.options), weights_rx);
            }
        }
        self.terms = Some(registration.terms);
        if finished_now {
            self.finished.store(true, Ordering::Relaxed);
            return SessionEnd::Finished;
        }

        let ended = Arc::new(AtomicBool::new(false));
        let taken = Arc::new(AtomicU64::new(0));
        self.connections += 1;
        let connection = self.connections;
        let stream = OutboxStream::new(
            Arc::clone(&self.outbox),
            Arc::clone(&ended),
            Arc::clone(&taken),
        )
        .on_connection(actor_id.clone(), Arc::clone(&self.options.log), connection);
        let finished = Arc::clone(&self.finished);
        let rollout_handle = &mut self.rollout;
        let mut push = std::pin::pin!(client.push_rollouts(stream));
        let mut follow = std::pin::pin!(follow_policy(&mut policy_stream, self.weights.clone()));
        let mut following = true;
        let mut rollout_joined = false;
        let end = loop {
            let rollout = async {
                match rollout_handle.as_mut() {
                    Some(handle) => handle.await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                pushed = &mut push => break match pushed {
                    // The stream ends cleanly only once the rollout thread has let go of the
                    // outbox: the run finished, or the thread failed.
                    Ok(summary) => {
                        let s = summary.into_inner();
                        self.options.log.confirmed(connection, s.accepted_fragments);
                        self.metrics.fragments_confirmed.inc_by(s.accepted_fragments);
                        tracing::info!(
                            fragments = s.accepted_fragments,
                            agent_steps = s.accepted_agent_steps,
                            "rollout stream closed"
                        );
                        taken.store(0, Ordering::Relaxed);
                        match rollout_handle.take() {
                            Some(handle) => rollout_ended(handle.await),
                            None => SessionEnd::Finished,
                        }
                    }
                    // The learner ends streams when training is over; that is not a failure.
                    Err(_) if finished.load(Ordering::Relaxed) => SessionEnd::Finished,
                    Err(status) => {
                        // It announces the end of a run on the policy stream before it stops
                        // taking fragments; that message may still be on its way.
                        let announced = following
                            && matches!(
                                tokio::time::timeout(FINISH_GRACE, &mut follow).await,
                                Ok(Ok(()))
                            );
                        if announced {
                            finished.store(true, Ordering::Relaxed);
                            SessionEnd::Finished
                        } else {
                            call_failed(status, "the learner ended the rollout stream", true)
                        }
                    }
                },
                followed = &mut follow, if following => match followed {
                    // The run is over: keep pushing until the rollout thread has stopped and
                    // the learner has closed the stream (bounded by the learner's shutdown).
                    Ok(()) => {
                        finished.store(true, Ordering::Relaxed);
                        following = false;
                    }
                    Err(e) => break lost(e, true),
                },
                joined = rollout => {
                    rollout_joined = true;
                    break rollout_ended(joined);
                }
            }
        };
        if rollout_joined {
            // A JoinHandle must not be awaited twice.
            *rollout_handle = None;
        }
        ended.store(true, Ordering::Release);
        let unconfirmed = taken.load(Ordering::Relaxed);
        if unconfirmed > 0 {
            self.options.log.unconfirmed(connection, unconfirmed);
        }
        if unconfirmed > 0 && !matches!(end, SessionEnd::Finished) {
            // Some of these may have reached the learner before the connection broke; it
            // counts what it accepted, this side cannot know which.
            self.metrics.fragments_unconfirmed.inc_by(unconfirmed);
        }
        end
    }

    fn start_rollout(
        &mut self,
        plan: RolloutPlan,
        weights: watch::Receiver<Arc<proto::PolicyWeights>>,
    ) {
        let Some(outbox) = self.outbox_tx.take() else {
            return;
        };
        let finished = Arc::clone(&self.finished);
        let metrics = Arc::clone(&self.metrics);
        let actor_id = self.actor_id.subscribe();
        self.rollout = Some(tokio::task::spawn_blocking(move || {
            let send = |fragment: RolloutFragment| {
                let started = Instant::now();
                let message = fragment.into_proto();
                metrics
                    .transport_seconds
                    .inc_by(started.elapsed().as_secs_f64());
                // Err: the actor is stopping (run finished, or it gave up on the learner).
                outbox.blocking_send(message).is_ok()
            };
            rollout_loop(plan, actor_id, weights, send, &finished, &metrics)
        }));
    }

    /// Stops the rollout thread (closing the outbox wakes it if it waits there) and reports
    /// its error, if any.
    async fn stop(&mut self) -> anyhow::Result<()> {
        self.finished.store(true, Ordering::Relaxed);
        if let Ok(mut outbox) = self.outbox.lock() {
            outbox.close();
        }
        match self.rollout.take() {
            Some(handle) => handle.await.context("rollout thread panicked")?,
            None => Ok(()),
        }
    }
}

/// How the rollout thread ended, as the end of the session that noticed.
fn rollout_ended(joined: Result<anyhow::Result<()>, tokio::task::JoinError>) -> SessionEnd {
    match joined {
        Ok(Ok(())) => SessionEnd::Finished,
        Ok(Err(e)) => SessionEnd::Fatal(e),
        Err(e) => SessionEnd::Fatal(anyhow::Error::new(e).context("rollout thread panicked")),
    }
}

/// Forwards every new version from the learner to the rollout thread; Ok when the learner
/// says the run is finished, Err when the stream breaks.
async fn follow_policy(
    stream: &mut tonic::Streaming<proto::PolicyWeights>,
    weights: Option<watch::Sender<Arc<proto::PolicyWeights>>>,
) -> anyhow::Result<()> {
    loop {
        match stream.message().await {
            Ok(Some(message)) => {
                check_weights(&message)?;
                let done = message.run_finished;
                if let Some(weights) = &weights {
                    weights.send_replace(Arc::new(message));
                }
                if done {
                    return Ok(());
                }
            }
            Ok(None) => bail!("the learner closed the policy stream"),
            Err(status) => bail!(
                "policy stream failed: {} ({:?})",
                status.message(),
                status.code()
            ),
        }
    }
}

/// Adds the async runtime's busy time to the transport time every second: in a gRPC actor
/// the runtime does nothing but the transport (protobuf encoding, HTTP/2, sockets, the policy
/// stream).
async fn count_runtime_busy_time(metrics: Arc<ActorMetrics>) {
    let runtime = tokio::runtime::Handle::current().metrics();
    let busy = || -> Duration {
        (0..runtime.num_workers())
            .map(|w| runtime.worker_total_busy_duration(w))
            .sum()
    };
    let mut counted = busy();
    loop {
        tokio::time::sleep(Duration::from_secs(1)).await;
        let now = busy();
        metrics
            .transport_seconds
            .inc_by(now.saturating_sub(counted).as_secs_f64());
        counted = now;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// As tonic nests the io::Error that tokio-rustls made.
    #[derive(Debug, thiserror::Error)]
    #[error("transport error")]
    struct Transport(#[source] std::io::Error);

    fn options(learner: &str) -> GrpcOptions {
        GrpcOptions {
            learner: learner.to_string(),
            retry_initial: Duration::from_millis(100),
            retry_max: Duration::from_secs(5),
            max_message_bytes: 1 << 20,
            tls: TlsOptions::default(),
            token: None,
        }
    }

    fn tls(error: rustls::Error) -> Transport {
        Transport(std::io::Error::new(std::io::ErrorKind::InvalidData, error))
    }

    #[test]
    fn rejected_certificates_and_tls_to_plain_text_are_misconfigurations() {
        let https = options("https://learner.example:50051");
        let rejected = tls(rustls::Error::InvalidCertificate(
            rustls::CertificateError::UnknownIssuer,
        ));
        let problem = misconfiguration(&rejected, &https).expect("a misconfiguration");
        assert!(problem.contains("UnknownIssuer"), "{problem}");
        assert!(problem.contains("--tls-ca"), "{problem}");
        let plain = tls(rustls::Error::InvalidMessage(
            rustls::InvalidMessage::InvalidContentType,
        ));
        let problem = misconfiguration(&plain, &https).expect("a misconfiguration");
        assert!(problem.contains("does not speak TLS"), "{problem}");
    }

    #[test]
    fn outages_are_not_misconfigurations() {
        let https = options("https://learner.example:50051");
        for kind in [
            std::io::ErrorKind::ConnectionRefused,
            std::io::ErrorKind::ConnectionReset,
            std::io::ErrorKind::BrokenPipe,
            std::io::ErrorKind::TimedOut,
        ] {
            let outage = Transport(std::io::Error::from(kind));
            assert_eq!(misconfiguration(&outage, &https), None, "{kind:?}");
        }
        let closed = tls(rustls::Error::AlertReceived(
            rustls::AlertDescription::InternalError,
        ));
        assert_eq!(misconfiguration(&closed, &https), None);
    }
}
