//! The actor side of the gRPC transport: register, follow the policy stream, and push
//! fragments produced by the rollout thread; reconnect with back-off when the learner goes
//! away (see README, "Faults").

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use tokio::sync::{mpsc, watch};
use tonic::service::Interceptor;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};

use junction_common::auth::{self, Token};
use junction_common::config::{RolloutConfig, RunConfig, ScenarioConfig};
use junction_common::fragment::{MAX_STEPS, PROTOCOL_VERSION};
use junction_common::lcf::LcfDistribution;
use junction_common::policy::{self, Policy};
use junction_common::proto::{self, learner_client::LearnerClient};
use junction_common::spec::{ACTION_DIM, OBS_LAYOUT_VERSION};

use crate::lcf_column::blob_distribution;
use crate::metrics::ActorMetrics;
use crate::reconnect::{Backoff, OutboxStream, retryable};
use crate::rollout::{RolloutWorker, derive_seed};

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

pub struct ActorOptions {
    pub learner: String,
    pub name: String,
    pub scenes: usize,
    pub seed: u64,
    /// Give up once the learner has been unreachable this long, at start or after losing it
    /// (`None`: retry for ever).
    pub give_up_after: Option<Duration>,
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
fn endpoint(options: &ActorOptions) -> anyhow::Result<Endpoint> {
    let url = &options.learner;
    let mut endpoint = Endpoint::from_shared(url.to_string())
        .with_context(|| {
            format!("--learner {url:?} is not a valid URL (expected e.g. http://127.0.0.1:50051)")
        })?
        .connect_timeout(Duration::from_secs(5))
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

/// What the learner told this actor to simulate; a restarted learner must say the same.
#[derive(Clone, PartialEq)]
struct RunTerms {
    scenario_toml: String,
    fragment_length: u32,
    obs_dim: u32,
    action_dim: u32,
    obs_layout_version: u32,
    run_seed: u64,
}

impl RunTerms {
    fn of(reply: &proto::RegisterReply) -> Self {
        RunTerms {
            scenario_toml: reply.scenario_toml.clone(),
            fragment_length: reply.fragment_length,
            obs_dim: reply.obs_dim,
            action_dim: reply.action_dim,
            obs_layout_version: reply.obs_layout_version,
            run_seed: reply.run_seed,
        }
    }

    /// Checks everything taken from the learner's reply before anything is allocated for it.
    fn check(&self, max_message_bytes: usize) -> anyhow::Result<ScenarioConfig> {
        if self.obs_layout_version != OBS_LAYOUT_VERSION {
            bail!(
                "the learner uses observation layout {}; this actor uses {OBS_LAYOUT_VERSION}",
                self.obs_layout_version
            );
        }
        let scenario =
            ScenarioConfig::from_toml(&self.scenario_toml).context("the learner's scenario")?;
        // The policy takes the scenario's observation, or that and CoPO's LCF angle.
        let policy_obs_dims = [
            scenario.obs_dim(),
            scenario.obs_dim() + LcfDistribution::OBS_COLUMNS,
        ];
        if !policy_obs_dims.contains(&(self.obs_dim as usize))
            || self.action_dim as usize != ACTION_DIM
        {
            bail!(
                "the learner's dimensions {}×{} do not match its scenario",
                self.obs_dim,
                self.action_dim
            );
        }
        let steps = self.fragment_length as usize;
        if !(1..=MAX_STEPS).contains(&steps) {
            bail!("the learner asks for fragments of {steps} steps (1..={MAX_STEPS})");
        }
        let run = RunConfig {
            scenario: scenario.clone(),
            rollout: RolloutConfig {
                fragment_length: steps,
            },
            ..RunConfig::default()
        };
        let bytes = run.fragment_bytes_estimate();
        if bytes > max_message_bytes {
            bail!(
                "the learner's fragments (about {bytes} bytes) exceed --max-message-bytes {max_message_bytes}"
            );
        }
        Ok(scenario)
    }
}

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

/// What lives across connections: the outbox, the weights the rollout thread follows, the
/// rollout thread itself.
struct Actor {
    options: ActorOptions,
    metrics: Arc<ActorMetrics>,
    outbox_tx: Option<mpsc::Sender<proto::RolloutFragment>>,
    outbox: Arc<Mutex<mpsc::Receiver<proto::RolloutFragment>>>,
    terms: Option<RunTerms>,
    weights: Option<watch::Sender<Arc<proto::PolicyWeights>>>,
    actor_id: watch::Sender<String>,
    finished: Arc<AtomicBool>,
    rollout: Option<tokio::task::JoinHandle<anyhow::Result<()>>>,
}

/// Runs until the learner says the run is finished (Ok), the learner stays unreachable longer
/// than `give_up_after`, or something retrying cannot fix happens (Err).
pub async fn run(options: ActorOptions, metrics: Arc<ActorMetrics>) -> anyhow::Result<()> {
    let endpoint = endpoint(&options)?;
    let jitter_seed = options.seed
        ^ u64::from(std::process::id())
        ^ std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0);
    let mut backoff = Backoff::new(options.retry_initial, options.retry_max, jitter_seed);
    let (outbox_tx, outbox_rx) = mpsc::channel(OUTBOX_FRAGMENTS);
    let mut actor = Actor {
        options,
        metrics,
        outbox_tx: Some(outbox_tx),
        outbox: Arc::new(Mutex::new(outbox_rx)),
        terms: None,
        weights: None,
        actor_id: watch::channel(String::new()).0,
        finished: Arc::new(AtomicBool::new(false)),
        rollout: None,
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
                        actor.options.learner,
                        waited.as_secs_f64()
                    )));
                }
                let delay = backoff.next_delay();
                if reported {
                    tracing::info!(error = %format!("{error:#}"), retry_in_ms = delay.as_millis() as u64, "learner still unreachable");
                } else {
                    tracing::warn!(
                        learner = %actor.options.learner,
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
    actor.stop().await.and(outcome)
}

impl Actor {
    /// One connection: register, follow the weights, push the outbox until something ends.
    async fn session(&mut self, endpoint: &Endpoint) -> SessionEnd {
        let channel = match tokio::time::timeout(CALL_TIMEOUT, endpoint.connect()).await {
            Ok(Ok(channel)) => channel,
            Ok(Err(e)) => return lost(anyhow::Error::new(e).context("connecting"), false),
            Err(_) => return lost(anyhow::anyhow!("connecting timed out"), false),
        };
        let header = match &self.options.token {
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
        let bytes = self.options.max_message_bytes;
        let mut client: Client = LearnerClient::with_interceptor(channel, TokenHeader(header))
            .max_decoding_message_size(bytes)
            .max_encoding_message_size(bytes);
        let hello = proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_name: self.options.name.clone(),
            scenes: self.options.scenes as u32,
        };
        let reply = match tokio::time::timeout(CALL_TIMEOUT, client.register(hello)).await {
            Ok(Ok(reply)) => reply.into_inner(),
            Ok(Err(status)) => return call_failed(status, "registering with the learner", false),
            Err(_) => return lost(anyhow::anyhow!("registering timed out"), false),
        };
        if reply.protocol_version != PROTOCOL_VERSION {
            return SessionEnd::Fatal(anyhow::anyhow!(
                "the learner speaks protocol {}; this actor speaks {PROTOCOL_VERSION}",
                reply.protocol_version
            ));
        }
        let terms = RunTerms::of(&reply);
        let scenario = match terms.check(bytes) {
            Ok(scenario) => scenario,
            Err(e) => return SessionEnd::Fatal(e),
        };
        if self.terms.as_ref().is_some_and(|known| *known != terms) {
            return SessionEnd::Fatal(anyhow::anyhow!(
                "the learner came back with another scenario, fragment length or seed; restart this actor to join the new run"
            ));
        }
        let actor_id = reply.actor_id.clone();
        if actor_id.len() > junction_common::fragment::MAX_NAME_BYTES {
            return SessionEnd::Fatal(anyhow::anyhow!("the learner's actor id is too long"));
        }

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
            tracing::Span::current()
                .record("id", actor_id.as_str())
                .record("scenario", scenario.name.as_str());
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
                self.start_rollout(&reply, scenario, weights_rx);
            }
        }
        self.terms = Some(terms);
        if finished_now {
            self.finished.store(true, Ordering::Relaxed);
            return SessionEnd::Finished;
        }

        let ended = Arc::new(AtomicBool::new(false));
        let taken = Arc::new(AtomicU64::new(0));
        let stream = OutboxStream::new(
            Arc::clone(&self.outbox),
            Arc::clone(&ended),
            Arc::clone(&taken),
        );
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
        if unconfirmed > 0 && !matches!(end, SessionEnd::Finished) {
            // Some of these may have reached the learner before the connection broke; it
            // counts what it accepted, this side cannot know which.
            self.metrics.fragments_unconfirmed.inc_by(unconfirmed);
        }
        end
    }

    fn start_rollout(
        &mut self,
        reply: &proto::RegisterReply,
        scenario: ScenarioConfig,
        weights: watch::Receiver<Arc<proto::PolicyWeights>>,
    ) {
        // Seeds come from the first registration: the scenes keep running across reconnects.
        let seed = derive_seed(
            reply.run_seed ^ self.options.seed,
            reply.actor_id.bytes().map(u64::from).sum(),
        );
        let Some(outbox) = self.outbox_tx.take() else {
            return;
        };
        let finished = Arc::clone(&self.finished);
        let metrics = Arc::clone(&self.metrics);
        let fragment_length = reply.fragment_length as usize;
        let scenes = self.options.scenes;
        let actor_id = self.actor_id.subscribe();
        self.rollout = Some(tokio::task::spawn_blocking(move || {
            rollout_loop(
                scenario,
                scenes,
                seed,
                fragment_length,
                actor_id,
                weights,
                outbox,
                finished,
                &metrics,
            )
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

/// The envelope of a weights message (the blob itself is checked when decoded).
fn check_weights(weights: &proto::PolicyWeights) -> anyhow::Result<()> {
    if weights.protocol_version != PROTOCOL_VERSION {
        bail!(
            "policy v{} comes in protocol {}; this actor speaks {PROTOCOL_VERSION}",
            weights.version,
            weights.protocol_version
        );
    }
    if weights.format != "safetensors" {
        bail!(
            "policy v{} has unknown format {:?}",
            weights.version,
            weights.format
        );
    }
    Ok(())
}

/// Simulates the agent count the learner's curriculum asks for with `weights`.
fn apply_active_agents(
    worker: &mut RolloutWorker,
    weights: &proto::PolicyWeights,
    metrics: &ActorMetrics,
) -> anyhow::Result<()> {
    let before = worker.active_agents();
    let requested = usize::try_from(weights.active_agents).unwrap_or(usize::MAX);
    if worker
        .set_active_agents(requested)
        .context("rebuilding the scenes for the curriculum's agent count")?
    {
        tracing::info!(
            old_agents = before,
            new_agents = worker.active_agents(),
            version = weights.version,
            "scenes rebuilt with the curriculum's agent count"
        );
    }
    metrics.scene_agents.set(worker.active_agents() as i64);
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn rollout_loop(
    scenario: ScenarioConfig,
    scenes: usize,
    seed: u64,
    fragment_length: usize,
    mut actor_id: watch::Receiver<String>,
    mut weights: watch::Receiver<Arc<proto::PolicyWeights>>,
    outbox: mpsc::Sender<proto::RolloutFragment>,
    finished: Arc<AtomicBool>,
    metrics: &ActorMetrics,
) -> anyhow::Result<()> {
    let first_id = actor_id.borrow_and_update().clone();
    let _span =
        tracing::info_span!("rollout", actor = %first_id, scenario = %scenario.name).entered();
    // The blob says which kind of policy it is (Gaussian or DQN's Q-policy) and whether it
    // takes CoPO's LCF angle: no flag needed.
    type Loaded = (Box<dyn Policy>, Option<LcfDistribution>);
    let load = |w: &proto::PolicyWeights| -> anyhow::Result<Loaded> {
        let (policy, meta) =
            policy::decode(&w.data, tch::Device::Cpu).context("decoding policy weights")?;
        let lcf = blob_distribution(&w.data).context("reading the policy's LCF distribution")?;
        let columns = lcf.map_or(0, |_| LcfDistribution::OBS_COLUMNS);
        if meta.obs_layout_version != OBS_LAYOUT_VERSION
            || policy.obs_dim() != scenario.obs_dim() + columns
            || policy.action_dim() != ACTION_DIM
        {
            bail!(
                "policy v{} was trained for another observation layout or size or action size",
                w.version
            );
        }
        Ok((policy, lcf))
    };
    let initial = Arc::clone(&weights.borrow_and_update());
    let (policy, lcf) = load(&initial)?;
    let mut worker = RolloutWorker::new(
        &scenario,
        scenes,
        seed,
        fragment_length,
        policy,
        initial.version,
        first_id,
    )
    .context("building the scenes")?;
    worker.set_lcf_distribution(lcf);
    metrics.policy_version.set(initial.version as i64);
    apply_active_agents(&mut worker, &initial, metrics)?;
    while !finished.load(Ordering::Relaxed) {
        if actor_id.has_changed().unwrap_or(false) {
            // Registered again with a restarted learner: new fragments carry the new id.
            worker.set_actor_id(actor_id.borrow_and_update().clone());
        }
        if weights.has_changed().unwrap_or(false) {
            let latest = Arc::clone(&weights.borrow_and_update());
            // Any other version, older too: a restarted learner continues from its checkpoint.
            if latest.version != worker.policy_version() {
                let (policy, lcf) = load(&latest)?;
                worker.set_policy(policy, latest.version);
                worker.set_lcf_distribution(lcf);
                metrics.policy_version.set(latest.version as i64);
                metrics.policy_switches.inc();
                tracing::debug!(version = latest.version, "switched policy");
            }
            apply_active_agents(&mut worker, &latest, metrics)?;
        }
        let _collect =
            tracing::info_span!("collect", policy_version = worker.policy_version()).entered();
        let (fragments, timings) = worker.collect().context("policy inference")?;
        metrics.inference_seconds.inc_by(timings.inference_s);
        metrics.simulation_seconds.inc_by(timings.simulation_s);
        for fragment in fragments {
            metrics.env_steps.inc_by(fragment.steps as u64);
            metrics.agent_steps.inc_by(fragment.agent_steps() as u64);
            if outbox.blocking_send(fragment.into_proto()).is_err() {
                // The actor is stopping (run finished, or it gave up on the learner).
                return Ok(());
            }
            metrics.fragments_sent.inc();
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn terms() -> RunTerms {
        let scenario = ScenarioConfig::default();
        RunTerms {
            scenario_toml: scenario.to_toml(),
            fragment_length: 200,
            obs_dim: scenario.obs_dim() as u32,
            action_dim: ACTION_DIM as u32,
            obs_layout_version: OBS_LAYOUT_VERSION,
            run_seed: 1,
        }
    }

    #[test]
    fn a_hostile_or_foreign_registration_reply_is_refused_before_anything_is_built() {
        let limit = 64 << 20;
        assert_eq!(terms().check(limit).unwrap().agents, 30);
        let refused = |t: RunTerms, bytes: usize, needle: &str| {
            let err = format!("{:#}", t.check(bytes).unwrap_err());
            assert!(err.contains(needle), "{err} lacks {needle:?}");
        };
        refused(
            RunTerms {
                obs_layout_version: OBS_LAYOUT_VERSION + 1,
                ..terms()
            },
            limit,
            "observation layout",
        );
        for steps in [0, u32::MAX] {
            refused(
                RunTerms {
                    fragment_length: steps,
                    ..terms()
                },
                limit,
                "fragments of",
            );
        }
        refused(
            RunTerms {
                obs_dim: 90,
                ..terms()
            },
            limit,
            "dimensions",
        );
        let huge = ScenarioConfig {
            agents: 1_000_000,
            ..ScenarioConfig::default()
        };
        refused(
            RunTerms {
                scenario_toml: huge.to_toml(),
                ..terms()
            },
            limit,
            "scenario.agents",
        );
        refused(
            RunTerms {
                scenario_toml: "agents = \"many\"".into(),
                ..terms()
            },
            limit,
            "scenario",
        );
        // 200 steps × 30 agents × 91 values do not fit in 1 MB messages.
        refused(terms(), 1 << 20, "--max-message-bytes");
    }

    #[test]
    fn weights_of_another_protocol_or_format_are_refused() {
        let ok = proto::PolicyWeights {
            protocol_version: PROTOCOL_VERSION,
            format: "safetensors".into(),
            ..Default::default()
        };
        assert!(check_weights(&ok).is_ok());
        assert!(
            check_weights(&proto::PolicyWeights {
                protocol_version: PROTOCOL_VERSION + 1,
                ..ok.clone()
            })
            .is_err()
        );
        assert!(
            check_weights(&proto::PolicyWeights {
                format: "pickle".into(),
                ..ok
            })
            .is_err()
        );
    }
}
