//! The actor side of the shared-memory transport (`actor --learner shm://NAME`; services in
//! `junction_common::shm`). Two threads own the iceoryx2 ports, since ports stay on the
//! thread that made them:
//!
//! - `shm-policy` registers, then follows the weights (newest wins) and watches the learner:
//!   when its services vanish (it exited or was killed) the actor stops with an error;
//! - `shm-send` writes each fragment from the rollout thread straight into a loaned sample
//!   and sends it, waiting while the learner's buffer is full (backpressure).
//!
//! Either sets the shared `abort` flag to end the other: a send blocked on a full learner
//! gives up once the learner is gone or the run is over.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, sync_channel};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use prost::Message;
use tokio::sync::{oneshot, watch};

use junction_common::fragment::{PROTOCOL_VERSION, RolloutFragment};
use junction_common::proto;
use junction_common::shm::{self, Names, Side};
use junction_common::shm_layout;
use junction_common::spec::ACTION_DIM;

use crate::metrics::{ActorMetrics, thread_cpu_seconds};
use crate::session::{ActorOptions, OUTBOX_FRAGMENTS, RunInfo, rollout_loop};

/// How long the learner has to answer a registration, and then to deliver the first weights.
const ANSWER_TIMEOUT: Duration = Duration::from_secs(30);
/// How often the policy thread looks for new weights and whether the learner is still there.
const POLL: Duration = Duration::from_millis(10);
const LIVENESS_CHECK: Duration = Duration::from_millis(500);

/// What the policy thread hands over once registered.
struct Registered {
    reply: proto::RegisterReply,
    weights: watch::Receiver<Arc<proto::PolicyWeights>>,
}

/// Runs until the learner says the run is finished (Ok) or goes away (Err).
pub async fn run(
    name: &str,
    options: ActorOptions,
    metrics: Arc<ActorMetrics>,
) -> anyhow::Result<()> {
    let names = Arc::new(Names::new(name)?);
    let mut threads = Threads::default();
    let finished = Arc::new(AtomicBool::new(false));
    let (registered_tx, registered_rx) = oneshot::channel();
    {
        let names = Arc::clone(&names);
        let abort = Arc::clone(&threads.abort);
        let finished = Arc::clone(&finished);
        let metrics = Arc::clone(&metrics);
        let hello = proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_name: options.name.clone(),
            scenes: options.scenes as u32,
        };
        let timeout = options.connect_timeout;
        threads.spawn("shm-policy", move || {
            follow_policy(
                &names,
                &hello,
                timeout,
                registered_tx,
                &abort,
                &finished,
                &metrics,
            )
        })?;
    }
    let registered = registered_rx
        .await
        .context("the shared-memory policy thread ended during registration")??;
    let run = RunInfo::from_reply(&registered.reply)?;
    run.record_in_span();
    tracing::info!(scenes = options.scenes, shm = name, "registered");

    let (outbox_tx, outbox_rx) = sync_channel::<RolloutFragment>(OUTBOX_FRAGMENTS);
    {
        let names = Arc::clone(&names);
        let abort = Arc::clone(&threads.abort);
        let metrics = Arc::clone(&metrics);
        let capacity = shm_layout::capacity_hint(
            run.fragment_length,
            run.scenario.agent_count(),
            run.scenario.obs_dim(),
            ACTION_DIM,
        );
        threads.spawn("shm-send", move || {
            send_fragments(&names, capacity, &outbox_rx, &abort, &metrics)
        })?;
    }
    let seed = run.seed(options.seed);
    let rollout = {
        let finished = Arc::clone(&finished);
        let metrics = Arc::clone(&metrics);
        let scenes = options.scenes;
        tokio::task::spawn_blocking(move || {
            // Err: the sender thread is gone (learner gone or run over); the threads say why.
            let send = |fragment| outbox_tx.send(fragment).is_ok();
            rollout_loop(
                run,
                scenes,
                seed,
                registered.weights,
                send,
                &finished,
                &metrics,
            )
        })
    };
    let rollout_result = rollout.await.context("rollout thread panicked")?;
    let transport_result = tokio::task::spawn_blocking(move || threads.stop())
        .await
        .context("stopping the shared-memory threads")?;
    rollout_result?;
    transport_result?;
    if finished.load(Ordering::Relaxed) {
        tracing::info!("the learner finished the run; actor exiting");
    }
    Ok(())
}

/// The transport's threads; stopping (or dropping, e.g. on Ctrl-C) sets `abort` and waits
/// for them, so their iceoryx2 ports are released cleanly.
#[derive(Default)]
struct Threads {
    abort: Arc<AtomicBool>,
    handles: Vec<JoinHandle<anyhow::Result<()>>>,
}

impl Threads {
    fn spawn(
        &mut self,
        name: &str,
        body: impl FnOnce() -> anyhow::Result<()> + Send + 'static,
    ) -> anyhow::Result<()> {
        let abort = Arc::clone(&self.abort);
        let handle = std::thread::Builder::new()
            .name(name.into())
            .spawn(move || {
                let result = body();
                // Whatever ended this thread ends the other too.
                abort.store(true, Ordering::Relaxed);
                result
            })
            .with_context(|| format!("starting thread {name}"))?;
        self.handles.push(handle);
        Ok(())
    }

    /// The first error of any thread.
    fn stop(mut self) -> anyhow::Result<()> {
        self.abort.store(true, Ordering::Relaxed);
        let mut result = Ok(());
        for handle in self.handles.drain(..) {
            let outcome = handle
                .join()
                .unwrap_or_else(|_| Err(anyhow::anyhow!("a shared-memory thread panicked")));
            if result.is_ok() {
                result = outcome;
            }
        }
        result
    }
}

impl Drop for Threads {
    fn drop(&mut self) {
        self.abort.store(true, Ordering::Relaxed);
        for handle in self.handles.drain(..) {
            let _ = handle.join();
        }
    }
}

/// Registers, hands the reply and the first weights to `registered`, then follows the
/// weights until the run is finished, the learner is gone or `abort` is set.
fn follow_policy(
    names: &Names,
    hello: &proto::RegisterRequest,
    connect_timeout: Duration,
    registered: oneshot::Sender<anyhow::Result<Registered>>,
    abort: &AtomicBool,
    finished: &AtomicBool,
    metrics: &ActorMetrics,
) -> anyhow::Result<()> {
    let node = match shm::node("junction-actor") {
        Ok(node) => node,
        Err(e) => {
            let _ = registered.send(Err(e.into()));
            return Ok(());
        }
    };
    let connected = (|| -> anyhow::Result<_> {
        let (register, weights_service) = open_services(&node, names, connect_timeout, abort)?;
        let subscriber = shm::weights_subscriber(&weights_service)?;
        let client = shm::register_client(&register)?;
        let reply = request_registration(&client, hello, abort)?;
        let first = next_weights(&subscriber, metrics, Some(ANSWER_TIMEOUT), abort)?
            .context("the learner sent no weights after the registration")?;
        Ok((register, weights_service, subscriber, reply, first))
    })();
    let (_register, weights_service, subscriber, reply, first) = match connected {
        Ok(ports) => ports,
        Err(e) => {
            let _ = registered.send(Err(e));
            return Ok(());
        }
    };
    let finished_at_once = first.run_finished;
    let (weights_tx, weights_rx) = watch::channel(Arc::new(first));
    if registered
        .send(Ok(Registered {
            reply,
            weights: weights_rx,
        }))
        .is_err()
    {
        return Ok(());
    }
    if finished_at_once {
        finished.store(true, Ordering::Relaxed);
        return Ok(());
    }
    let mut last_check = Instant::now();
    while !abort.load(Ordering::Relaxed) {
        if let Some(weights) = next_weights(&subscriber, metrics, None, abort)? {
            let done = weights.run_finished;
            weights_tx.send_replace(Arc::new(weights));
            if done {
                finished.store(true, Ordering::Relaxed);
                return Ok(());
            }
        }
        if last_check.elapsed() >= LIVENESS_CHECK {
            last_check = Instant::now();
            if !shm::learner_present(&weights_service) {
                bail!(
                    "the learner is gone: its shared-memory services vanished without finishing the run"
                );
            }
        }
        std::thread::sleep(POLL);
    }
    Ok(())
}

/// Opens the registration and weights services, retrying with back-off until the learner
/// has created them or `timeout` has passed.
fn open_services(
    node: &shm::ShmNode,
    names: &Names,
    timeout: Duration,
    abort: &AtomicBool,
) -> anyhow::Result<(shm::RegisterService, shm::BytesService)> {
    let started = Instant::now();
    let mut delay = Duration::from_millis(100);
    loop {
        let opened = shm::register_service(node, names, Side::Actor).and_then(|register| {
            let weights = shm::weights_service(node, names, Side::Actor)?;
            Ok((register, weights))
        });
        let problem = match opened {
            Ok((register, weights)) if shm::learner_present(&weights) => {
                return Ok((register, weights));
            }
            Ok(_) => "its services exist, but no learner serves them".to_string(),
            Err(e) => e.to_string(),
        };
        if started.elapsed() >= timeout || abort.load(Ordering::Relaxed) {
            bail!(
                "no learner serves shared memory as {} (waited {:.0} s): {problem}",
                names.weights,
                timeout.as_secs_f64()
            );
        }
        tracing::info!(
            retry_in_ms = delay.as_millis() as u64,
            "learner not reachable over shared memory yet"
        );
        std::thread::sleep(delay);
        delay = (delay * 2).min(Duration::from_secs(2));
    }
}

fn request_registration(
    client: &shm::RegisterClient,
    hello: &proto::RegisterRequest,
    abort: &AtomicBool,
) -> anyhow::Result<proto::RegisterReply> {
    let request = hello.encode_to_vec();
    let pending = client
        .loan_slice_uninit(request.len())
        .map_err(shm::failed("loaning a registration request"))?
        .write_from_slice(&request)
        .send()
        .map_err(shm::failed("sending the registration"))?;
    let deadline = Instant::now() + ANSWER_TIMEOUT;
    while Instant::now() < deadline && !abort.load(Ordering::Relaxed) {
        if let Some(response) = pending
            .receive()
            .map_err(shm::failed("receiving the registration reply"))?
        {
            return proto::RegisterReply::decode(response.payload())
                .context("the learner's registration reply is not a RegisterReply");
        }
        std::thread::sleep(POLL);
    }
    bail!(
        "the learner did not answer the registration within {} s",
        ANSWER_TIMEOUT.as_secs()
    )
}

/// The newest weights waiting, if any; with `wait`, waits up to that long for them. Counts the
/// time spent decoding as transport time.
fn next_weights(
    subscriber: &shm::BytesSubscriber,
    metrics: &ActorMetrics,
    wait: Option<Duration>,
    abort: &AtomicBool,
) -> anyhow::Result<Option<proto::PolicyWeights>> {
    let deadline = wait.map(|w| Instant::now() + w);
    loop {
        let cpu = thread_cpu_seconds();
        let mut newest = None;
        while let Some(sample) = subscriber
            .receive()
            .map_err(shm::failed("receiving weights"))?
        {
            newest = Some(
                proto::PolicyWeights::decode(sample.payload())
                    .context("the learner's weights are not a PolicyWeights message")?,
            );
        }
        metrics.transport_seconds.inc_by(thread_cpu_seconds() - cpu);
        if let Some(weights) = newest {
            if weights.protocol_version != PROTOCOL_VERSION {
                bail!(
                    "the learner sent weights of protocol {}, this actor speaks {PROTOCOL_VERSION}",
                    weights.protocol_version
                );
            }
            return Ok(Some(weights));
        }
        match deadline {
            Some(deadline) if Instant::now() < deadline && !abort.load(Ordering::Relaxed) => {
                std::thread::sleep(POLL);
            }
            _ => return Ok(None),
        }
    }
}

/// Sends every fragment of `outbox` until it closes or `abort` is set; counts the CPU time
/// of encoding and sending as transport time.
fn send_fragments(
    names: &Names,
    capacity: usize,
    outbox: &Receiver<RolloutFragment>,
    abort: &Arc<AtomicBool>,
    metrics: &ActorMetrics,
) -> anyhow::Result<()> {
    let node = shm::node("junction-actor")?;
    let service = shm::fragment_service(&node, names, Side::Actor)?;
    let publisher = shm::fragment_publisher(&service, capacity, Arc::clone(abort))?;
    while !abort.load(Ordering::Relaxed) {
        let fragment = match outbox.recv_timeout(Duration::from_millis(100)) {
            Ok(fragment) => fragment,
            Err(RecvTimeoutError::Timeout) => continue,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        let cpu = thread_cpu_seconds();
        let sent = shm::send_fragment(&publisher, &fragment);
        metrics.transport_seconds.inc_by(thread_cpu_seconds() - cpu);
        match sent {
            Ok(_) => {}
            // Given up on purpose: the learner is gone or the run is over.
            Err(_) if abort.load(Ordering::Relaxed) => break,
            Err(e) => return Err(e).context("sending a fragment over shared memory"),
        }
    }
    Ok(())
}
