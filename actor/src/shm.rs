//! The actor side of the shared-memory transport (`actor --learner shm://NAME`; services in
//! `junction_common::shm`). Two threads own the iceoryx2 ports, since ports stay on the
//! thread that made them:
//!
//! - `shm-send` creates the fragment publisher, then registers (so the learner has attached
//!   to the publisher before the first fragment), then writes each fragment from the rollout
//!   thread straight into a loaned sample and sends it, waiting while the learner's buffer is
//!   full (backpressure);
//! - `shm-policy` follows the weights (newest wins) and watches the learner: when its
//!   services vanish (it exited or was killed) the actor stops with an error.
//!
//! Whichever thread ends sets the shared `abort` flag, which ends the other: a send blocked
//! on a full learner gives up once the learner is gone or the run is over. All the CPU time of
//! both threads counts as transport time (`junction_actor_transport_seconds_total`).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, sync_channel};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use prost::Message;
use tokio::sync::{oneshot, watch};

use junction_common::fragment::RolloutFragment;
use junction_common::proto;
use junction_common::shm::{self, Names, Side};
use junction_core::spec::PROTOCOL_VERSION;

use crate::ledger::FragmentLog;
use crate::metrics::{ActorMetrics, ThreadCpu};
use crate::session::{ActorOptions, Registration, check_weights, rollout_loop};

/// Fragments waiting between the rollout thread and the sender thread. One: the learner
/// already buffers two per actor, and every fragment queued on the way ages (policy lag).
const OUTBOX_FRAGMENTS: usize = 1;
/// How long the learner has to answer a registration, and to deliver the first weights.
const ANSWER_TIMEOUT: Duration = Duration::from_secs(30);
/// How often the policy thread looks for new weights (a version lasts seconds).
const POLL: Duration = Duration::from_millis(50);
/// How often the policy thread checks that the learner is still there (a sweep for dead
/// processes' records, which costs a few system calls per process on the service).
const LIVENESS_CHECK: Duration = Duration::from_secs(2);

/// Runs until the learner says the run is finished (Ok) or goes away (Err).
pub async fn run(
    name: &str,
    options: ActorOptions,
    metrics: Arc<ActorMetrics>,
) -> anyhow::Result<()> {
    let names = Arc::new(Names::new(name)?);
    let mut threads = Threads::default();
    let finished = Arc::new(AtomicBool::new(false));
    let (reply_tx, reply_rx) = oneshot::channel();
    let (weights_tx, weights_rx) = oneshot::channel();
    let (outbox_tx, outbox_rx) = sync_channel::<RolloutFragment>(OUTBOX_FRAGMENTS);
    {
        let names = Arc::clone(&names);
        let abort = Arc::clone(&threads.abort);
        let metrics = Arc::clone(&metrics);
        let hello = proto::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            actor_name: options.name.clone(),
            scenes: options.scenes as u32,
            instance: options.log.instance().to_string(),
        };
        let joining = Joining {
            hello,
            connect_timeout: options.give_up_after,
            answer: reply_tx,
        };
        let log = Arc::clone(&options.log);
        threads.spawn("shm-send", move || {
            send_fragments(&names, joining, &outbox_rx, &abort, &metrics, &log)
        })?;
    }
    {
        let names = Arc::clone(&names);
        let abort = Arc::clone(&threads.abort);
        let finished = Arc::clone(&finished);
        let metrics = Arc::clone(&metrics);
        let timeout = options.give_up_after;
        threads.spawn("shm-policy", move || {
            follow_policy(&names, timeout, weights_tx, &abort, &finished, &metrics)
        })?;
    }
    let reply = match reply_rx.await {
        Ok(reply) => reply?,
        Err(_) => return threads.stop_in_background().await,
    };
    // Shared memory has no message limit: a sample grows to the fragment.
    let registration = Registration::check(&reply, None)?;
    registration.record_in_span();
    tracing::info!(scenes = options.scenes, shm = name, "registered");
    let weights = match weights_rx.await {
        Ok(weights) => weights?,
        Err(_) => return threads.stop_in_background().await,
    };

    let plan = registration.plan(&options);
    // One registration per process: the id never changes (the sender stays alive so the
    // rollout loop sees no change).
    let (_actor_id, actor_id) = watch::channel(registration.actor_id);
    let rollout = {
        let finished = Arc::clone(&finished);
        let metrics = Arc::clone(&metrics);
        tokio::task::spawn_blocking(move || {
            // Err: the sender thread is gone (learner gone or run over); the threads say why.
            let send = |fragment| outbox_tx.send(fragment).is_ok();
            rollout_loop(plan, actor_id, weights, send, &finished, &metrics)
        })
    };
    let rollout_result = rollout.await.context("rollout thread panicked")?;
    let transport_result = threads.stop_in_background().await;
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

    /// Stops the threads without blocking the async runtime; the first error of any thread.
    async fn stop_in_background(self) -> anyhow::Result<()> {
        tokio::task::spawn_blocking(move || self.stop())
            .await
            .context("stopping the shared-memory threads")?
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

/// Opens what `open` opens once the learner serves it, retrying with back-off until
/// `timeout` has passed (`None`: for ever). `open` returns `Ok(None)` for services that exist
/// but that no learner serves (left behind by one that died).
fn open_when_served<T>(
    what: &str,
    timeout: Option<Duration>,
    abort: &AtomicBool,
    mut open: impl FnMut() -> Result<Option<T>, shm::ShmError>,
) -> anyhow::Result<T> {
    let started = Instant::now();
    let mut delay = Duration::from_millis(100);
    loop {
        let problem = match open() {
            Ok(Some(opened)) => return Ok(opened),
            Ok(None) => "its services exist, but no learner serves them".to_string(),
            Err(e) => e.to_string(),
        };
        if timeout.is_some_and(|t| started.elapsed() >= t) || abort.load(Ordering::Relaxed) {
            bail!(
                "no learner serves {what} (waited {:.0} s): {problem}",
                started.elapsed().as_secs_f64()
            );
        }
        tracing::debug!(
            retry_in_ms = delay.as_millis() as u64,
            "{what}: not served yet"
        );
        std::thread::sleep(delay);
        delay = (delay * 2).min(Duration::from_secs(2));
    }
}

/// How the sender thread registers, and where the learner's answer goes.
struct Joining {
    hello: proto::RegisterRequest,
    connect_timeout: Option<Duration>,
    answer: oneshot::Sender<anyhow::Result<proto::RegisterReply>>,
}

/// Creates the fragment publisher, registers (the reply to `joining.answer`), then sends
/// every fragment of `outbox` until it closes or `abort` is set, recording each in `log`.
fn send_fragments(
    names: &Names,
    joining: Joining,
    outbox: &Receiver<RolloutFragment>,
    abort: &Arc<AtomicBool>,
    metrics: &ActorMetrics,
    log: &FragmentLog,
) -> anyhow::Result<()> {
    let mut cpu = ThreadCpu::new(&metrics.transport_seconds);
    let setup = || -> anyhow::Result<_> {
        let node = shm::node("junction-actor")?;
        let (fragments, register) = open_when_served(
            &names.fragments.to_string(),
            joining.connect_timeout,
            abort,
            || {
                let fragments = shm::fragment_service(&node, names, Side::Actor)?;
                let register = shm::register_service(&node, names, Side::Actor)?;
                Ok(shm::learner_subscribed(&fragments).then_some((fragments, register)))
            },
        )?;
        let publisher =
            shm::fragment_publisher(&fragments, shm::FRAGMENT_SAMPLE_BYTES, Arc::clone(abort))?;
        let client = shm::register_client(&register)?;
        let reply = shm::register(&client, &joining.hello, ANSWER_TIMEOUT, abort)?;
        Ok((node, fragments, publisher, reply))
    };
    let (_node, _fragments, publisher) = match setup() {
        Ok((node, fragments, publisher, reply)) => {
            if joining.answer.send(Ok(reply)).is_err() {
                return Ok(());
            }
            (node, fragments, publisher)
        }
        Err(e) => {
            let _ = joining.answer.send(Err(e));
            return Ok(());
        }
    };
    while !abort.load(Ordering::Relaxed) {
        let fragment = match outbox.recv_timeout(Duration::from_millis(100)) {
            Ok(fragment) => fragment,
            Err(RecvTimeoutError::Timeout) => continue,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        let sent = shm::send_fragment(&publisher, &fragment);
        cpu.record();
        match sent {
            // Shared memory has one connection per process: number 0.
            Ok(_) => log.sent(fragment.sequence, 0),
            // Given up on purpose: the learner is gone or the run is over.
            Err(_) if abort.load(Ordering::Relaxed) => break,
            Err(e) => return Err(e).context("sending a fragment over shared memory"),
        }
    }
    Ok(())
}

/// Hands the current weights to `first`, then follows them until the run is finished, the
/// learner is gone or `abort` is set.
fn follow_policy(
    names: &Names,
    connect_timeout: Option<Duration>,
    first: oneshot::Sender<anyhow::Result<watch::Receiver<Arc<proto::PolicyWeights>>>>,
    abort: &AtomicBool,
    finished: &AtomicBool,
    metrics: &ActorMetrics,
) -> anyhow::Result<()> {
    let mut cpu = ThreadCpu::new(&metrics.transport_seconds);
    let setup = || -> anyhow::Result<_> {
        let node = shm::node("junction-actor")?;
        let service = open_when_served(&names.weights.to_string(), connect_timeout, abort, || {
            let service = shm::weights_service(&node, names, Side::Actor)?;
            Ok(shm::learner_present(&service).then_some(service))
        })?;
        let subscriber = shm::weights_subscriber(&service)?;
        let current = next_weights(&subscriber, Some(ANSWER_TIMEOUT), abort)?
            .context("the learner sent no weights")?;
        Ok((node, service, subscriber, current))
    };
    let (_node, service, subscriber, current) = match setup() {
        Ok(ports) => ports,
        Err(e) => {
            let _ = first.send(Err(e));
            return Ok(());
        }
    };
    let finished_already = current.run_finished;
    let (weights_tx, weights_rx) = watch::channel(Arc::new(current));
    if first.send(Ok(weights_rx)).is_err() {
        return Ok(());
    }
    if finished_already {
        finished.store(true, Ordering::Relaxed);
        return Ok(());
    }
    let mut last_check = Instant::now();
    while !abort.load(Ordering::Relaxed) {
        cpu.record();
        if let Some(weights) = next_weights(&subscriber, None, abort)? {
            let done = weights.run_finished;
            weights_tx.send_replace(Arc::new(weights));
            if done {
                finished.store(true, Ordering::Relaxed);
                return Ok(());
            }
        }
        if last_check.elapsed() >= LIVENESS_CHECK {
            last_check = Instant::now();
            if !shm::learner_present(&service) {
                bail!(
                    "the learner is gone: its shared-memory services vanished before the run finished"
                );
            }
        }
        std::thread::sleep(POLL);
    }
    Ok(())
}

/// The newest weights waiting, if any; with `wait`, waits up to that long for them.
fn next_weights(
    subscriber: &shm::BytesSubscriber,
    wait: Option<Duration>,
    abort: &AtomicBool,
) -> anyhow::Result<Option<proto::PolicyWeights>> {
    let deadline = wait.map(|w| Instant::now() + w);
    loop {
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
        if let Some(weights) = newest {
            check_weights(&weights)?;
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
