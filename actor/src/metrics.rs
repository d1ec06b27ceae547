//! The actor's Prometheus metrics (names in `junction_common::telemetry::names`).

use prometheus::{Counter, IntCounter, IntGauge, Registry};

use junction_common::telemetry::{Registrar, names};

pub struct ActorMetrics {
    pub registry: Registry,
    pub env_steps: IntCounter,
    pub agent_steps: IntCounter,
    pub fragments_sent: IntCounter,
    pub policy_version: IntGauge,
    pub policy_switches: IntCounter,
    pub inference_seconds: Counter,
    pub simulation_seconds: Counter,
    pub transport_seconds: Counter,
    pub scene_agents: IntGauge,
    pub connected: IntGauge,
    pub reconnects: IntCounter,
    pub fragments_unconfirmed: IntCounter,
    pub fragments_confirmed: IntCounter,
}

impl ActorMetrics {
    pub fn new() -> Result<Self, prometheus::Error> {
        let registry = Registry::new();
        let r = Registrar::new(&registry);
        Ok(ActorMetrics {
            env_steps: r.int_counter(names::ACTOR_ENV_STEPS, "Scene steps simulated.")?,
            agent_steps: r.int_counter(names::ACTOR_AGENT_STEPS, "Agent-steps simulated.")?,
            fragments_sent: r.int_counter(
                names::ACTOR_FRAGMENTS_SENT,
                "Rollout fragments handed to the transport.",
            )?,
            policy_version: r.int_gauge(
                names::ACTOR_POLICY_VERSION,
                "Policy version the actor is running.",
            )?,
            policy_switches: r.int_counter(
                names::ACTOR_POLICY_SWITCHES,
                "Times the actor switched to newer weights.",
            )?,
            inference_seconds: r.counter(
                names::ACTOR_INFERENCE_SECONDS,
                "Time spent in batched policy inference.",
            )?,
            simulation_seconds: r.counter(
                names::ACTOR_SIMULATION_SECONDS,
                "Time spent stepping scenes.",
            )?,
            transport_seconds: r.counter(
                names::ACTOR_TRANSPORT_SECONDS,
                "CPU time spent moving fragments and weights (encoding, shared memory or gRPC).",
            )?,
            scene_agents: r.int_gauge(
                names::ACTOR_SCENE_AGENTS,
                "Learning-agent slots per scene (fewer than the scenario's during a curriculum).",
            )?,
            connected: r.int_gauge(
                names::ACTOR_CONNECTED,
                "1 while registered with the learner and streaming, 0 while (re)connecting.",
            )?,
            reconnects: r.int_counter(
                names::ACTOR_RECONNECTS,
                "Times the actor registered again after losing the learner.",
            )?,
            fragments_unconfirmed: r.int_counter(
                names::ACTOR_FRAGMENTS_UNCONFIRMED,
                "Fragments sent on a rollout stream that broke before the learner confirmed it (the learner counts those it accepted).",
            )?,
            fragments_confirmed: r.int_counter(
                names::ACTOR_FRAGMENTS_CONFIRMED,
                "Fragments the learner confirmed it accepted (a rollout stream closed with its summary).",
            )?,
            registry,
        })
    }
}

/// CPU time the calling thread has used so far, in seconds (0 if the clock is unavailable).
pub fn thread_cpu_seconds() -> f64 {
    let mut now = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec, which we own.
    if unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut now) } != 0 {
        return 0.0;
    }
    now.tv_sec as f64 + now.tv_nsec as f64 * 1e-9
}

/// Charges all the CPU time of the calling thread to `counter`, for a thread that does one job
/// only (a transport thread): call [`ThreadCpu::record`] as it goes; dropping records the rest.
pub struct ThreadCpu {
    counter: Counter,
    recorded: f64,
}

impl ThreadCpu {
    /// Counts from the thread's start, so set-up is included.
    pub fn new(counter: &Counter) -> Self {
        ThreadCpu {
            counter: counter.clone(),
            recorded: 0.0,
        }
    }

    pub fn record(&mut self) {
        let now = thread_cpu_seconds();
        self.counter.inc_by((now - self.recorded).max(0.0));
        self.recorded = now;
    }
}

impl Drop for ThreadCpu {
    fn drop(&mut self) {
        self.record();
    }
}
