//! The learner's Prometheus metrics (names in `junction_common::telemetry::names`, label
//! values in [`super::labels`]), in groups by what records them. Each group registers its
//! metrics with the one registry (`register(&Registry)`) and has its own `record_*`;
//! [`LearnerMetrics::new`] composes them:
//! - [`IngestMetrics`]: what the transports received, refused, queued and dropped;
//! - [`EpisodeMetrics`]: the finished episodes of received fragments and the driving rates
//!   over the episode windows;
//! - [`UpdateMetrics`]: the policy version, the consumed steps and each update's diagnostics;
//! - [`LcfMetrics`]: the LCF angle φ after each update;
//! - [`DqnMetrics`]: the DQN's Q values, exploration and replay buffer;
//! - [`CurriculumMetrics`]: the curriculum stage of the newest broadcast;
//! - [`LocalActorMetrics`]: the local-actor supervisor's restarts.

use prometheus::{
    CounterVec, Gauge, GaugeVec, Histogram, IntCounter, IntCounterVec, IntGauge, Registry,
};

use junction_common::fragment::{FragmentError, RolloutFragment};
use junction_common::lcf::NEIGHBOUR_BUCKETS;
use junction_common::telemetry::{Registrar, names};
use junction_core::episode::Outcome;

use super::labels::{
    DROP_REASONS, REFUSED_STREAM_LIMIT, REFUSED_UNAUTHENTICATED, REJECT_DECODE, REJECT_SCENARIO,
    TRANSPORT_GRPC, TRANSPORT_SHM,
};
use super::stats::{SceneWindowSummary, WindowSummary};
use crate::algo::{Stage, UpdateStats};

/// Buckets of both policy-lag histograms, in versions.
const LAG_BUCKETS: [f64; 10] = [0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 32.0];

/// Every metric of the learner, by group, in one registry (what `/metrics` serves).
pub struct LearnerMetrics {
    pub registry: Registry,
    pub ingest: IngestMetrics,
    pub episodes: EpisodeMetrics,
    pub update: UpdateMetrics,
    pub lcf: LcfMetrics,
    pub dqn: DqnMetrics,
    pub curriculum: CurriculumMetrics,
    pub local_actors: LocalActorMetrics,
}

impl LearnerMetrics {
    pub fn new() -> Result<Self, prometheus::Error> {
        let registry = Registry::new();
        Ok(LearnerMetrics {
            ingest: IngestMetrics::register(&registry)?,
            episodes: EpisodeMetrics::register(&registry)?,
            update: UpdateMetrics::register(&registry)?,
            lcf: LcfMetrics::register(&registry)?,
            dqn: DqnMetrics::register(&registry)?,
            curriculum: CurriculumMetrics::register(&registry)?,
            local_actors: LocalActorMetrics::register(&registry)?,
            registry,
        })
    }

    /// Creates every bounded label value at zero, so dashboards and alerts see each series
    /// before its first event.
    pub fn initialise_labels(&self, scenario: &str) {
        self.ingest.initialise_labels();
        self.episodes.initialise_labels(scenario);
        self.lcf.initialise_labels();
    }

    /// One completed update, `seconds` long: its diagnostics, φ and the DQN's values.
    pub fn record_update(&self, stats: &UpdateStats, seconds: f64) {
        self.update.record(stats, seconds);
        self.lcf.record(stats);
        self.dqn.record(stats);
    }
}

/// What the transports received, refused, queued and dropped.
pub struct IngestMetrics {
    pub fragments: IntCounter,
    pub agent_steps_accepted: IntCounter,
    pub fragments_rejected: IntCounterVec,
    pub fragments_dropped: IntCounterVec,
    pub agent_steps_dropped: IntCounterVec,
    pub requests_refused: IntCounterVec,
    pub connected_actors: IntGauge,
    pub queue_fragments: IntGauge,
    pub transport_bytes: IntCounterVec,
    pub policy_lag: Histogram,
}

impl IngestMetrics {
    pub fn register(registry: &Registry) -> Result<Self, prometheus::Error> {
        let r = Registrar::new(registry);
        Ok(IngestMetrics {
            fragments: r.int_counter(
                names::LEARNER_FRAGMENTS,
                "Rollout fragments accepted by ingest.",
            )?,
            agent_steps_accepted: r.int_counter(
                names::LEARNER_AGENT_STEPS_ACCEPTED,
                "Agent-steps of accepted fragments; each is trained on or counted as dropped.",
            )?,
            fragments_rejected: r.int_counter_vec(
                names::LEARNER_FRAGMENTS_REJECTED,
                "Fragments refused as invalid, by reason.",
                &["reason"],
            )?,
            fragments_dropped: r.int_counter_vec(
                names::LEARNER_FRAGMENTS_DROPPED,
                "Accepted fragments not trained on, by reason (stale: more than max_policy_lag versions off; shutdown: queued or batched when the run ended; update_failed; off_grid: actions off the DQN's action grid).",
                &["reason"],
            )?,
            agent_steps_dropped: r.int_counter_vec(
                names::LEARNER_AGENT_STEPS_DROPPED,
                "Agent-steps of accepted fragments not trained on, by reason (as fragments_dropped).",
                &["reason"],
            )?,
            requests_refused: r.int_counter_vec(
                names::LEARNER_REQUESTS_REFUSED,
                "RPCs refused before reaching a handler, by reason (unauthenticated: missing or wrong token; stream_limit: server.max_rollout_streams reached).",
                &["reason"],
            )?,
            connected_actors: r.int_gauge(
                names::LEARNER_CONNECTED_ACTORS,
                "Actors with an open rollout stream.",
            )?,
            queue_fragments: r.int_gauge(
                names::LEARNER_QUEUE_FRAGMENTS,
                "Fragments waiting in the ingest queue.",
            )?,
            transport_bytes: r.int_counter_vec(
                names::LEARNER_TRANSPORT_BYTES,
                "Encoded fragment bytes received, by transport.",
                &["transport"],
            )?,
            policy_lag: r.histogram(
                names::LEARNER_POLICY_LAG,
                "Policy versions between a fragment's behaviour policy and the learner's newest, per received fragment.",
                LAG_BUCKETS.to_vec(),
            )?,
        })
    }

    /// Every refusal and drop reason and every transport, at zero.
    pub fn initialise_labels(&self) {
        for reason in FragmentError::REASONS
            .iter()
            .chain(&[REJECT_DECODE, REJECT_SCENARIO])
        {
            self.fragments_rejected.with_label_values(&[reason]);
        }
        for reason in DROP_REASONS {
            self.fragments_dropped.with_label_values(&[reason]);
            self.agent_steps_dropped.with_label_values(&[reason]);
        }
        for reason in [REFUSED_UNAUTHENTICATED, REFUSED_STREAM_LIMIT] {
            self.requests_refused.with_label_values(&[reason]);
        }
        for transport in [TRANSPORT_GRPC, TRANSPORT_SHM] {
            self.transport_bytes.with_label_values(&[transport]);
        }
    }

    /// Counts `fragments` (accepted earlier) as not trained on, for `reason`.
    pub fn record_drop(&self, reason: &'static str, fragments: &[RolloutFragment]) {
        let agent_steps: usize = fragments.iter().map(RolloutFragment::agent_steps).sum();
        self.fragments_dropped
            .with_label_values(&[reason])
            .inc_by(fragments.len() as u64);
        self.agent_steps_dropped
            .with_label_values(&[reason])
            .inc_by(agent_steps as u64);
    }

    /// Agent-steps dropped so far in this process, by reason.
    pub fn dropped_agent_steps(&self) -> Vec<(&'static str, u64)> {
        DROP_REASONS
            .iter()
            .map(|&r| (r, self.agent_steps_dropped.with_label_values(&[r]).get()))
            .collect()
    }
}

/// The finished episodes of received fragments (counted whether trained on or dropped) and
/// the driving rates over the agent-episode and scene-episode windows, by scenario.
pub struct EpisodeMetrics {
    pub episodes: IntCounterVec,
    pub human_episodes: IntCounterVec,
    pub collisions: IntCounterVec,
    pub simulated_seconds: CounterVec,
    pub scene_episodes: IntCounterVec,
    pub success_rate: GaugeVec,
    pub crash_rate: GaugeVec,
    pub out_of_road_rate: GaugeVec,
    pub episode_reward_mean: GaugeVec,
    pub episode_length_mean: GaugeVec,
    pub episode_reward_max: GaugeVec,
    pub episode_length_max: GaugeVec,
    pub accel_mean: GaugeVec,
    pub accel_max: GaugeVec,
    pub scene_success_rate: GaugeVec,
    pub scene_crash_rate: GaugeVec,
    pub scene_out_of_road_rate: GaugeVec,
}

impl EpisodeMetrics {
    pub fn register(registry: &Registry) -> Result<Self, prometheus::Error> {
        let r = Registrar::new(registry);
        let by_scenario = |name: &str, help: &str| r.gauge_vec(name, help, &["scenario"]);
        Ok(EpisodeMetrics {
            episodes: r.int_counter_vec(
                names::LEARNER_EPISODES,
                "Finished agent episodes, by scenario and outcome.",
                &["scenario", "outcome"],
            )?,
            human_episodes: r.int_counter_vec(
                names::LEARNER_HUMAN_EPISODES,
                "Finished episodes of human-driven (non-connected) vehicles, by scenario and outcome.",
                &["scenario", "outcome"],
            )?,
            collisions: r.int_counter_vec(
                names::LEARNER_COLLISIONS,
                "Collisions of finished episodes of agents and human drivers, by scenario; divide its rate by the rate of simulated seconds for collisions per simulated second.",
                &["scenario"],
            )?,
            simulated_seconds: r.counter_vec(
                names::LEARNER_SIMULATED_SECONDS,
                "Simulated seconds of scene time consumed, by scenario.",
                &["scenario"],
            )?,
            scene_episodes: r.int_counter_vec(
                names::LEARNER_SCENE_EPISODES,
                "Scene episodes (MetaDrive's environment episodes: reset to reset) that ended, by scenario.",
                &["scenario"],
            )?,
            success_rate: by_scenario(
                names::LEARNER_SUCCESS_RATE,
                "Share of recent episodes that reached their destination.",
            )?,
            crash_rate: by_scenario(
                names::LEARNER_CRASH_RATE,
                "Share of recent episodes that ended in a crash.",
            )?,
            out_of_road_rate: by_scenario(
                names::LEARNER_OUT_OF_ROAD_RATE,
                "Share of recent episodes that left the road.",
            )?,
            episode_reward_mean: by_scenario(
                names::LEARNER_EPISODE_REWARD_MEAN,
                "Mean total reward of recent episodes.",
            )?,
            episode_length_mean: by_scenario(
                names::LEARNER_EPISODE_LENGTH_MEAN,
                "Mean length of recent episodes, in decision steps.",
            )?,
            episode_reward_max: by_scenario(
                names::LEARNER_EPISODE_REWARD_MAX,
                "Largest total reward among recent episodes.",
            )?,
            episode_length_max: by_scenario(
                names::LEARNER_EPISODE_LENGTH_MAX,
                "Longest of recent episodes, in decision steps.",
            )?,
            accel_mean: by_scenario(
                names::LEARNER_ACCEL_MEAN,
                "Mean over recent episodes of each episode's mean |longitudinal acceleration|.",
            )?,
            accel_max: by_scenario(
                names::LEARNER_ACCEL_MAX,
                "Mean over recent episodes of each episode's largest |longitudinal acceleration| (paper: mean acceleration, maximum value).",
            )?,
            scene_success_rate: by_scenario(
                names::LEARNER_SCENE_SUCCESS_RATE,
                "MetaDrive's success rate: per scene episode the share of its agents that arrived, averaged over the last run.stats_window_scene_episodes scene episodes.",
            )?,
            scene_crash_rate: by_scenario(
                names::LEARNER_SCENE_CRASH_RATE,
                "MetaDrive's crash rate: per scene episode the share of its agents that crashed, averaged over the scene-episode window.",
            )?,
            scene_out_of_road_rate: by_scenario(
                names::LEARNER_SCENE_OUT_OF_ROAD_RATE,
                "MetaDrive's out-of-road rate: per scene episode the share of its agents that left the road, averaged over the scene-episode window.",
            )?,
        })
    }

    /// The run's scenario with every outcome, at zero.
    pub fn initialise_labels(&self, scenario: &str) {
        for outcome in Outcome::ALL {
            self.episodes
                .with_label_values(&[scenario, outcome.label()]);
            self.human_episodes
                .with_label_values(&[scenario, outcome.label()]);
        }
        self.collisions.with_label_values(&[scenario]);
        self.simulated_seconds.with_label_values(&[scenario]);
        self.scene_episodes.with_label_values(&[scenario]);
    }

    /// Counts what one received fragment simulated: its episodes, collisions and scene time.
    pub fn record_fragment(&self, scenario: &str, fragment: &RolloutFragment) {
        for (counter, episodes) in [
            (&self.episodes, &fragment.episodes),
            (&self.human_episodes, &fragment.human_episodes),
        ] {
            for episode in episodes {
                counter
                    .with_label_values(&[scenario, episode.outcome.label()])
                    .inc();
            }
        }
        self.collisions
            .with_label_values(&[scenario])
            .inc_by(fragment.collisions());
        self.scene_episodes
            .with_label_values(&[scenario])
            .inc_by(fragment.scene_episodes.len() as u64);
        self.simulated_seconds
            .with_label_values(&[scenario])
            .inc_by(f64::from(fragment.sim_seconds));
    }

    pub fn record_window(&self, scenario: &str, summary: &WindowSummary) {
        for (gauge, value) in [
            (&self.success_rate, summary.success_rate),
            (&self.crash_rate, summary.crash_rate),
            (&self.out_of_road_rate, summary.out_of_road_rate),
            (&self.episode_reward_mean, summary.mean_reward),
            (&self.episode_length_mean, summary.mean_length),
            (&self.episode_reward_max, summary.max_reward),
            (&self.episode_length_max, f64::from(summary.max_length)),
            (&self.accel_mean, summary.mean_accel),
            (&self.accel_max, summary.mean_max_accel),
        ] {
            gauge.with_label_values(&[scenario]).set(value);
        }
    }

    pub fn record_scene_window(&self, scenario: &str, summary: &SceneWindowSummary) {
        for (gauge, rate) in [
            (&self.scene_success_rate, summary.success_rate),
            (&self.scene_crash_rate, summary.crash_rate),
            (&self.scene_out_of_road_rate, summary.out_of_road_rate),
        ] {
            gauge.with_label_values(&[scenario]).set(rate);
        }
    }
}

/// The policy version, the steps consumed, and each update's diagnostics.
pub struct UpdateMetrics {
    pub policy_version: IntGauge,
    pub agent_steps: IntCounter,
    pub env_steps: IntCounter,
    pub samples_trained: IntCounter,
    pub updates: IntCounter,
    pub fragments_trained: IntCounter,
    pub checkpoint_failures: IntCounter,
    pub update_seconds: Histogram,
    pub trained_policy_lag: Histogram,
    pub learning_rate: Gauge,
    pub lagrange_multiplier: Gauge,
    pub nonfinite_minibatches: IntCounter,
    pub policy_loss: Gauge,
    pub value_loss: Gauge,
    pub entropy: Gauge,
    pub approx_kl: Gauge,
    pub clip_fraction: Gauge,
    pub explained_variance: Gauge,
    pub grad_norm: Gauge,
}

impl UpdateMetrics {
    pub fn register(registry: &Registry) -> Result<Self, prometheus::Error> {
        let r = Registrar::new(registry);
        Ok(UpdateMetrics {
            policy_version: r.int_gauge(
                names::LEARNER_POLICY_VERSION,
                "Version of the newest published policy.",
            )?,
            agent_steps: r.int_counter(
                names::LEARNER_AGENT_STEPS,
                "Agent-steps trained on (counted when their update completes).",
            )?,
            env_steps: r.int_counter(
                names::LEARNER_ENV_STEPS,
                "Scene steps trained on (counted when their update completes).",
            )?,
            samples_trained: r.int_counter(
                names::LEARNER_SAMPLES_TRAINED,
                "Agent-steps passed through gradient steps (counted once per epoch).",
            )?,
            updates: r.int_counter(names::LEARNER_UPDATES, "Policy updates completed.")?,
            fragments_trained: r.int_counter(
                names::LEARNER_FRAGMENTS_TRAINED,
                "Accepted fragments trained on (counted when their update completes).",
            )?,
            checkpoint_failures: r.int_counter(
                names::LEARNER_CHECKPOINT_FAILURES,
                "Periodic checkpoints that could not be written (training went on).",
            )?,
            update_seconds: r.histogram(
                names::LEARNER_UPDATE_SECONDS,
                "Wall time of one policy update.",
                vec![0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0],
            )?,
            trained_policy_lag: r.histogram(
                names::LEARNER_TRAINED_POLICY_LAG,
                "Policy versions between a fragment's behaviour policy and the policy an update starts from, per fragment trained on (what the PPO ratio has to correct).",
                LAG_BUCKETS.to_vec(),
            )?,
            learning_rate: r.gauge(
                names::LEARNER_LEARNING_RATE,
                "Optimiser step size of the last update.",
            )?,
            lagrange_multiplier: r.gauge(
                names::LEARNER_LAGRANGE_MULTIPLIER,
                "PPO-Lagrangian's price of cost after the last update ([safety]; 0 when off).",
            )?,
            nonfinite_minibatches: r.int_counter(
                names::LEARNER_NONFINITE_MINIBATCHES,
                "Minibatches skipped because their loss was NaN or infinite.",
            )?,
            policy_loss: r.gauge(names::LEARNER_POLICY_LOSS, "PPO clipped surrogate loss.")?,
            value_loss: r.gauge(names::LEARNER_VALUE_LOSS, "Value-function loss.")?,
            entropy: r.gauge(names::LEARNER_ENTROPY, "Policy entropy (nats).")?,
            approx_kl: r.gauge(
                names::LEARNER_APPROX_KL,
                "Approximate KL(old ‖ new) per update.",
            )?,
            clip_fraction: r.gauge(
                names::LEARNER_CLIP_FRACTION,
                "Share of samples whose probability ratio was clipped.",
            )?,
            explained_variance: r.gauge(
                names::LEARNER_EXPLAINED_VARIANCE,
                "Share of return variance explained by the critic.",
            )?,
            grad_norm: r.gauge(names::LEARNER_GRAD_NORM, "Gradient norm before clipping.")?,
        })
    }

    /// A completed update's diagnostics and duration (the steps it consumed and the new
    /// version are counted by the trainer as it publishes).
    pub fn record(&self, stats: &UpdateStats, seconds: f64) {
        self.updates.inc();
        self.learning_rate.set(stats.learning_rate);
        self.lagrange_multiplier.set(stats.lagrange_multiplier);
        self.nonfinite_minibatches
            .inc_by(stats.skipped_minibatches as u64);
        self.update_seconds.observe(seconds);
        self.samples_trained.inc_by(stats.samples_trained as u64);
        self.policy_loss.set(stats.policy_loss);
        self.value_loss.set(stats.value_loss);
        self.entropy.set(stats.entropy);
        self.approx_kl.set(stats.approx_kl);
        self.clip_fraction.set(stats.clip_fraction);
        self.explained_variance.set(stats.explained_variance);
        self.grad_norm.set(stats.grad_norm);
    }

    /// Lags, in policy versions, of the fragments an update trained on.
    pub fn record_trained_lags(&self, lags: &[u64]) {
        for &lag in lags {
            self.trained_policy_lag.observe(lag as f64);
        }
    }
}

/// The LCF angle φ after each update: its mean and spread, and by neighbour count.
pub struct LcfMetrics {
    pub mean: Gauge,
    pub std: Gauge,
    pub phi: GaugeVec,
}

impl LcfMetrics {
    pub fn register(registry: &Registry) -> Result<Self, prometheus::Error> {
        let r = Registrar::new(registry);
        Ok(LcfMetrics {
            mean: r.gauge(
                names::LEARNER_LCF_MEAN,
                "Mean LCF angle phi after the last update, degrees (0 = selfish, 90 = fully cooperative): the fixed phi, CoPO's learned mean, or the dynamic LCF's phi over the batch.",
            )?,
            std: r.gauge(
                names::LEARNER_LCF_STD,
                "Spread of the LCF angle phi after the last update, degrees: CoPO's learned sigma, or the standard deviation of the dynamic LCF's phi over the batch (0 for a fixed phi).",
            )?,
            phi: r.gauge_vec(
                names::LEARNER_LCF_PHI,
                "Mean LCF angle phi after the last update of the batch's agents with this many neighbours (0, 1-2, 3-5, 6+), degrees; unchanged while a batch has none.",
                &["neighbours"],
            )?,
        })
    }

    /// Every neighbour-count bucket, at zero.
    pub fn initialise_labels(&self) {
        for bucket in NEIGHBOUR_BUCKETS {
            self.phi.with_label_values(&[bucket]);
        }
    }

    /// φ after an update; a bucket the batch had no agent in keeps its value.
    pub fn record(&self, stats: &UpdateStats) {
        self.mean.set(stats.lcf_mean_deg);
        self.std.set(stats.lcf_std_deg);
        for (bucket, phi) in NEIGHBOUR_BUCKETS.iter().zip(stats.lcf_phi_by_neighbours) {
            if let Some(phi) = phi {
                self.phi.with_label_values(&[bucket]).set(phi);
            }
        }
    }
}

/// The DQN's values after each update (zeros for the PPO algorithms).
pub struct DqnMetrics {
    pub q_mean: Gauge,
    pub epsilon: Gauge,
    pub replay_transitions: IntGauge,
}

impl DqnMetrics {
    pub fn register(registry: &Registry) -> Result<Self, prometheus::Error> {
        let r = Registrar::new(registry);
        Ok(DqnMetrics {
            q_mean: r.gauge(
                names::LEARNER_Q_MEAN,
                "DQN: mean Q(s, a) of the transitions sampled in the last update (0 for PPO).",
            )?,
            epsilon: r.gauge(
                names::LEARNER_EPSILON,
                "DQN: exploration rate epsilon broadcast after the last update (0 for PPO and before the first update).",
            )?,
            replay_transitions: r.int_gauge(
                names::LEARNER_REPLAY_TRANSITIONS,
                "DQN: agent transitions held in the replay buffer (0 for PPO).",
            )?,
        })
    }

    pub fn record(&self, stats: &UpdateStats) {
        self.q_mean.set(stats.q_mean);
        self.epsilon.set(stats.epsilon);
        self.replay_transitions
            .set(i64::try_from(stats.replay_transitions).unwrap_or(i64::MAX));
    }
}

/// The curriculum stage of the newest broadcast.
pub struct CurriculumMetrics {
    pub stage: IntGauge,
    pub agents: IntGauge,
}

impl CurriculumMetrics {
    pub fn register(registry: &Registry) -> Result<Self, prometheus::Error> {
        let r = Registrar::new(registry);
        Ok(CurriculumMetrics {
            stage: r.int_gauge(
                names::LEARNER_CURRICULUM_STAGE,
                "Curriculum stage of the newest policy broadcast (0 for algorithms without a curriculum).",
            )?,
            agents: r.int_gauge(
                names::LEARNER_CURRICULUM_AGENTS,
                "Learning agents per scene that actors are told to simulate.",
            )?,
        })
    }

    pub fn record_stage(&self, stage: Stage) {
        self.stage.set(stage.index as i64);
        self.agents.set(stage.agents as i64);
    }
}

/// The local-actor supervisor (`serve --local-actors`).
pub struct LocalActorMetrics {
    pub restarts: IntCounter,
}

impl LocalActorMetrics {
    pub fn register(registry: &Registry) -> Result<Self, prometheus::Error> {
        let r = Registrar::new(registry);
        Ok(LocalActorMetrics {
            restarts: r.int_counter(
                names::LEARNER_LOCAL_ACTOR_RESTARTS,
                "Local actors (serve --local-actors) restarted after they exited.",
            )?,
        })
    }
}
