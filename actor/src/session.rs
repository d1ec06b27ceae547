//! What an actor does once registered, whatever carries its data: check the run the learner
//! describes, then simulate with the newest weights and hand every fragment to the transport.
//! The transports (`grpc`, `shm`) only register, move fragments and deliver weights.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context, bail};
use tokio::sync::watch;

use junction_common::any_policy;
use junction_common::fragment::RolloutFragment;
use junction_common::lcf::LcfDistribution;
use junction_common::policy::Policy;
use junction_common::proto;
use junction_core::config::{RolloutConfig, RunConfig, ScenarioConfig};
use junction_core::spec::{
    ACTION_DIM, MAX_NAME_BYTES, MAX_STEPS, OBS_LAYOUT_VERSION, PROTOCOL_VERSION,
};

use crate::lcf_column::blob_distribution;
use crate::ledger::FragmentLog;
use crate::metrics::ActorMetrics;
use crate::rollout::{RolloutWorker, derive_seed};

/// What every transport needs to know about this actor.
pub struct ActorOptions {
    pub name: String,
    pub scenes: usize,
    pub seed: u64,
    /// Give up once the learner has been unreachable this long (`None`: wait for ever).
    pub give_up_after: Option<Duration>,
    /// The fragment ledger, and the instance id sent at registration.
    pub log: Arc<FragmentLog>,
}

/// What the learner told this actor to simulate; a restarted learner must say the same.
#[derive(Debug, Clone, PartialEq)]
pub struct RunTerms {
    pub scenario_toml: String,
    pub fragment_length: u32,
    pub obs_dim: u32,
    pub action_dim: u32,
    pub obs_layout_version: u32,
    pub run_seed: u64,
}

impl RunTerms {
    pub fn of(reply: &proto::RegisterReply) -> Self {
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
    /// `max_fragment_bytes`: the transport's message limit, if it has one.
    pub fn check(&self, max_fragment_bytes: Option<usize>) -> anyhow::Result<ScenarioConfig> {
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
        if let Some(limit) = max_fragment_bytes {
            let run = RunConfig {
                scenario: scenario.clone(),
                rollout: RolloutConfig {
                    fragment_length: steps,
                },
                ..RunConfig::default()
            };
            let bytes = run.fragment_bytes_estimate();
            if bytes > limit {
                bail!(
                    "the learner's fragments (about {bytes} bytes) exceed --max-message-bytes {limit}"
                );
            }
        }
        Ok(scenario)
    }
}

/// A registration reply, checked: the id the learner assigned and the run it describes.
pub struct Registration {
    pub actor_id: String,
    pub terms: RunTerms,
    pub scenario: ScenarioConfig,
}

impl Registration {
    /// Refuses another protocol, a refusal (no actor id: the learner's log says why), an
    /// absurd id and anything [`RunTerms::check`] refuses.
    pub fn check(
        reply: &proto::RegisterReply,
        max_fragment_bytes: Option<usize>,
    ) -> anyhow::Result<Self> {
        if reply.protocol_version != PROTOCOL_VERSION {
            bail!(
                "the learner speaks protocol {}; this actor speaks {PROTOCOL_VERSION}: run actors from the learner's Junction release",
                reply.protocol_version
            );
        }
        if reply.actor_id.is_empty() {
            bail!("the learner refused the registration (see its log)");
        }
        if reply.actor_id.len() > MAX_NAME_BYTES {
            bail!("the learner's actor id is too long");
        }
        let terms = RunTerms::of(reply);
        let scenario = terms.check(max_fragment_bytes)?;
        Ok(Registration {
            actor_id: reply.actor_id.clone(),
            terms,
            scenario,
        })
    }

    /// What to simulate. The seed mixes the run's seed, the actor's `--seed` and its id; a
    /// reconnecting actor keeps the plan of its first registration.
    pub fn plan(&self, options: &ActorOptions) -> RolloutPlan {
        RolloutPlan {
            scenario: self.scenario.clone(),
            fragment_length: self.terms.fragment_length as usize,
            scenes: options.scenes,
            seed: derive_seed(
                self.terms.run_seed ^ options.seed,
                self.actor_id.bytes().map(u64::from).sum(),
            ),
            log: Arc::clone(&options.log),
        }
    }

    /// Names the current span (`actor`) after the assigned id and scenario.
    pub fn record_in_span(&self) {
        tracing::Span::current()
            .record("id", self.actor_id.as_str())
            .record("scenario", self.scenario.name.as_str());
    }
}

/// The scenes the rollout thread runs.
pub struct RolloutPlan {
    pub scenario: ScenarioConfig,
    pub fragment_length: usize,
    pub scenes: usize,
    pub seed: u64,
    pub log: Arc<FragmentLog>,
}

/// The envelope of a weights message (the blob itself is checked when decoded).
pub fn check_weights(weights: &proto::PolicyWeights) -> anyhow::Result<()> {
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

/// Simulates `plan` with the newest `weights` and hands each fragment to `send`, until
/// `finished` is set or `send` returns false (the transport is gone; it reports why).
/// Fragments carry the newest id in `actor_id` (a reconnected actor registers again).
pub fn rollout_loop(
    plan: RolloutPlan,
    mut actor_id: watch::Receiver<String>,
    mut weights: watch::Receiver<Arc<proto::PolicyWeights>>,
    mut send: impl FnMut(RolloutFragment) -> bool,
    finished: &AtomicBool,
    metrics: &ActorMetrics,
) -> anyhow::Result<()> {
    let scenario = plan.scenario;
    let first_id = actor_id.borrow_and_update().clone();
    let _span =
        tracing::info_span!("rollout", actor = %first_id, scenario = %scenario.name).entered();
    // The blob says which kind of policy it is (Gaussian or DQN's Q-policy) and whether it
    // takes CoPO's LCF angle: no flag needed.
    type Loaded = (Box<dyn Policy>, Option<LcfDistribution>);
    let load = |w: &proto::PolicyWeights| -> anyhow::Result<Loaded> {
        let (policy, meta) =
            any_policy::decode(&w.data, tch::Device::Cpu).context("decoding policy weights")?;
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
        plan.scenes,
        plan.seed,
        plan.fragment_length,
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
            // Before the outbox: a process killed after handing it over had produced it.
            plan.log.produced(&fragment);
            if !send(fragment) {
                // The actor is stopping (run finished, learner gone, or it gave up on it).
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

    fn reply(terms: &RunTerms, actor_id: &str) -> proto::RegisterReply {
        proto::RegisterReply {
            protocol_version: PROTOCOL_VERSION,
            actor_id: actor_id.into(),
            scenario_toml: terms.scenario_toml.clone(),
            fragment_length: terms.fragment_length,
            obs_dim: terms.obs_dim,
            action_dim: terms.action_dim,
            obs_layout_version: terms.obs_layout_version,
            run_seed: terms.run_seed,
        }
    }

    #[test]
    fn a_hostile_or_foreign_registration_reply_is_refused_before_anything_is_built() {
        let limit = Some(64 << 20);
        assert_eq!(terms().check(limit).unwrap().agents, 30);
        let refused = |t: RunTerms, bytes: Option<usize>, needle: &str| {
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
                None,
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
            None,
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
        // 200 steps × 30 agents × 91 values do not fit in 1 MB messages; a transport
        // without a message limit (shared memory) takes them.
        refused(terms(), Some(1 << 20), "--max-message-bytes");
        assert!(terms().check(None).is_ok());
    }

    #[test]
    fn copo_runs_with_the_lcf_column_are_accepted() {
        let copo = RunTerms {
            obs_dim: terms().obs_dim + LcfDistribution::OBS_COLUMNS as u32,
            ..terms()
        };
        assert!(copo.check(None).is_ok());
        let two_more = RunTerms {
            obs_dim: terms().obs_dim + 2,
            ..terms()
        };
        assert!(two_more.check(None).is_err());
    }

    #[test]
    fn a_refused_or_foreign_registration_is_an_error_and_the_seed_follows_the_id() {
        let t = terms();
        let options = ActorOptions {
            name: "a".into(),
            scenes: 1,
            seed: 7,
            give_up_after: None,
            log: Arc::new(FragmentLog::off("a")),
        };
        let one = Registration::check(&reply(&t, "actor-1"), None).unwrap();
        let two = Registration::check(&reply(&t, "actor-2"), None).unwrap();
        assert_eq!(one.plan(&options).seed, one.plan(&options).seed);
        assert_ne!(one.plan(&options).seed, two.plan(&options).seed);
        assert_eq!(one.plan(&options).fragment_length, 200);

        let err = |reply: proto::RegisterReply| {
            format!("{:#}", Registration::check(&reply, None).err().unwrap())
        };
        assert!(err(reply(&t, "")).contains("refused"));
        assert!(err(reply(&t, &"x".repeat(MAX_NAME_BYTES + 1))).contains("too long"));
        let other_protocol = proto::RegisterReply {
            protocol_version: PROTOCOL_VERSION + 1,
            ..reply(&t, "actor-1")
        };
        assert!(err(other_protocol).contains("protocol"));
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
