//! What an actor does once registered, whatever carries its data: check the run the learner
//! describes, then simulate with the newest weights and hand every fragment to the transport.
//! The transports (`grpc`, `shm`) only register, move fragments and deliver weights.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context, bail};
use tokio::sync::watch;

use junction_common::config::ScenarioConfig;
use junction_common::fragment::{PROTOCOL_VERSION, RolloutFragment};
use junction_common::policy::GaussianPolicy;
use junction_common::proto;
use junction_common::spec::{ACTION_DIM, OBS_LAYOUT_VERSION};

use crate::metrics::ActorMetrics;
use crate::rollout::{RolloutWorker, derive_seed};

pub struct ActorOptions {
    pub name: String,
    pub scenes: usize,
    pub seed: u64,
    /// How long to keep retrying the first connection to the learner.
    pub connect_timeout: Duration,
}

/// The run an actor simulates, as the learner's registration reply describes it.
#[derive(Debug, Clone)]
pub struct RunInfo {
    pub actor_id: String,
    pub scenario: ScenarioConfig,
    pub fragment_length: usize,
    pub run_seed: u64,
}

impl RunInfo {
    /// Checks the learner's answer to a registration: protocol, observation layout and
    /// dimensions must be this actor's.
    pub fn from_reply(reply: &proto::RegisterReply) -> anyhow::Result<Self> {
        if reply.protocol_version != PROTOCOL_VERSION
            || (!reply.actor_id.is_empty() && reply.obs_layout_version != OBS_LAYOUT_VERSION)
        {
            bail!(
                "the learner speaks protocol {} with observation layout {}; this actor speaks {} with {}",
                reply.protocol_version,
                reply.obs_layout_version,
                PROTOCOL_VERSION,
                OBS_LAYOUT_VERSION
            );
        }
        if reply.actor_id.is_empty() {
            bail!("the learner refused the registration (see its log)");
        }
        let scenario =
            ScenarioConfig::from_toml(&reply.scenario_toml).context("the learner's scenario")?;
        if reply.obs_dim as usize != scenario.obs_dim() || reply.action_dim as usize != ACTION_DIM {
            bail!(
                "the learner's dimensions {}×{} do not match its scenario",
                reply.obs_dim,
                reply.action_dim
            );
        }
        if reply.fragment_length == 0 {
            bail!("the learner asks for fragments of 0 steps");
        }
        Ok(RunInfo {
            actor_id: reply.actor_id.clone(),
            scenario,
            fragment_length: reply.fragment_length as usize,
            run_seed: reply.run_seed,
        })
    }

    /// Seed of this actor's scenes: the run's seed, the actor's `--seed` and its id.
    pub fn seed(&self, actor_seed: u64) -> u64 {
        derive_seed(
            self.run_seed ^ actor_seed,
            self.actor_id.bytes().map(u64::from).sum(),
        )
    }

    /// Names the current span (`actor`) after the assigned id and scenario.
    pub fn record_in_span(&self) {
        tracing::Span::current()
            .record("id", self.actor_id.as_str())
            .record("scenario", self.scenario.name.as_str());
    }
}

/// Simulates `scenes` scenes of `run` with the newest `weights` and hands each fragment to
/// `send`, until `finished` is set or `send` returns false (the transport is gone; the
/// transport reports why).
#[allow(clippy::too_many_arguments)]
pub fn rollout_loop(
    run: RunInfo,
    scenes: usize,
    seed: u64,
    mut weights: watch::Receiver<Arc<proto::PolicyWeights>>,
    mut send: impl FnMut(RolloutFragment) -> bool,
    finished: &AtomicBool,
    metrics: &ActorMetrics,
) -> anyhow::Result<()> {
    let scenario = run.scenario;
    let _span =
        tracing::info_span!("rollout", actor = %run.actor_id, scenario = %scenario.name).entered();
    let load = |w: &proto::PolicyWeights| -> anyhow::Result<GaussianPolicy> {
        let (policy, meta) = GaussianPolicy::from_bytes(&w.data, tch::Device::Cpu)
            .context("decoding policy weights")?;
        if meta.obs_layout_version != OBS_LAYOUT_VERSION || policy.obs_dim() != scenario.obs_dim() {
            bail!(
                "policy v{} was trained for another observation layout or size",
                w.version
            );
        }
        Ok(policy)
    };
    let initial = Arc::clone(&weights.borrow_and_update());
    let mut worker = RolloutWorker::new(
        &scenario,
        scenes,
        seed,
        run.fragment_length,
        load(&initial)?,
        initial.version,
        run.actor_id,
    )
    .context("building the scenes")?;
    metrics.policy_version.set(initial.version as i64);
    apply_active_agents(&mut worker, &initial, metrics)?;
    while !finished.load(Ordering::Relaxed) {
        if weights.has_changed().unwrap_or(false) {
            let latest = Arc::clone(&weights.borrow_and_update());
            if latest.version != worker.policy_version() {
                worker.set_policy(load(&latest)?, latest.version);
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
            if !send(fragment) {
                return Ok(());
            }
            metrics.fragments_sent.inc();
        }
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
