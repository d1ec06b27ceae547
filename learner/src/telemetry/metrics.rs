//! The learner's Prometheus metrics (names in `junction_common::telemetry::names`).

use prometheus::{
    CounterVec, Gauge, GaugeVec, Histogram, HistogramOpts, IntCounter, IntCounterVec, IntGauge,
    Opts, Registry,
};

use junction_common::telemetry::names;

use junction_common::fragment::{FragmentError, Outcome, RolloutFragment};
use junction_common::lcf::NEIGHBOUR_BUCKETS;

use super::labels::{
    DROP_REASONS, REFUSED_STREAM_LIMIT, REFUSED_UNAUTHENTICATED, REJECT_DECODE, REJECT_SCENARIO,
    TRANSPORT_GRPC, TRANSPORT_SHM,
};
use super::stats::{SceneWindowSummary, WindowSummary};
use crate::algo::{Stage, UpdateStats};

pub struct LearnerMetrics {
    pub registry: Registry,
    pub policy_version: IntGauge,
    pub agent_steps: IntCounter,
    pub env_steps: IntCounter,
    pub fragments: IntCounter,
    pub fragments_rejected: IntCounterVec,
    pub fragments_dropped: IntCounterVec,
    pub agent_steps_accepted: IntCounter,
    pub agent_steps_dropped: IntCounterVec,
    pub requests_refused: IntCounterVec,
    pub samples_trained: IntCounter,
    pub updates: IntCounter,
    pub update_seconds: Histogram,
    pub connected_actors: IntGauge,
    pub queue_fragments: IntGauge,
    pub transport_bytes: IntCounterVec,
    pub episodes: IntCounterVec,
    human_episodes: IntCounterVec,
    pub policy_lag: Histogram,
    trained_policy_lag: Histogram,
    scene_episodes: IntCounterVec,
    scene_success_rate: GaugeVec,
    scene_crash_rate: GaugeVec,
    scene_out_of_road_rate: GaugeVec,
    collisions: IntCounterVec,
    simulated_seconds: CounterVec,
    success_rate: GaugeVec,
    crash_rate: GaugeVec,
    out_of_road_rate: GaugeVec,
    episode_reward_mean: GaugeVec,
    episode_length_mean: GaugeVec,
    episode_reward_max: GaugeVec,
    episode_length_max: GaugeVec,
    accel_mean: GaugeVec,
    accel_max: GaugeVec,
    learning_rate: Gauge,
    lcf_mean: Gauge,
    lcf_std: Gauge,
    lcf_phi: GaugeVec,
    lagrange_multiplier: Gauge,
    nonfinite_minibatches: IntCounter,
    policy_loss: Gauge,
    value_loss: Gauge,
    entropy: Gauge,
    approx_kl: Gauge,
    clip_fraction: Gauge,
    explained_variance: Gauge,
    grad_norm: Gauge,
    curriculum_stage: IntGauge,
    curriculum_agents: IntGauge,
    q_mean: Gauge,
    epsilon: Gauge,
    replay_transitions: IntGauge,
    pub local_actor_restarts: IntCounter,
}

impl LearnerMetrics {
    pub fn new() -> Result<Self, prometheus::Error> {
        let registry = Registry::new();
        let int_gauge = |name: &str, help: &str| -> Result<IntGauge, prometheus::Error> {
            let g = IntGauge::new(name, help)?;
            registry.register(Box::new(g.clone()))?;
            Ok(g)
        };
        let gauge = |name: &str, help: &str| -> Result<Gauge, prometheus::Error> {
            let g = Gauge::new(name, help)?;
            registry.register(Box::new(g.clone()))?;
            Ok(g)
        };
        let counter = |name: &str, help: &str| -> Result<IntCounter, prometheus::Error> {
            let c = IntCounter::new(name, help)?;
            registry.register(Box::new(c.clone()))?;
            Ok(c)
        };
        let counter_vec =
            |name: &str, help: &str, labels: &[&str]| -> Result<IntCounterVec, prometheus::Error> {
                let c = IntCounterVec::new(Opts::new(name, help), labels)?;
                registry.register(Box::new(c.clone()))?;
                Ok(c)
            };
        let scenario_gauge = |name: &str, help: &str| -> Result<GaugeVec, prometheus::Error> {
            let g = GaugeVec::new(Opts::new(name, help), &["scenario"])?;
            registry.register(Box::new(g.clone()))?;
            Ok(g)
        };
        let update_seconds = Histogram::with_opts(
            HistogramOpts::new(
                names::LEARNER_UPDATE_SECONDS,
                "Wall time of one policy update.",
            )
            .buckets(vec![0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0]),
        )?;
        registry.register(Box::new(update_seconds.clone()))?;
        let policy_lag = Histogram::with_opts(
            HistogramOpts::new(
                names::LEARNER_POLICY_LAG,
                "Policy versions between a fragment's behaviour policy and the learner's newest, per received fragment.",
            )
            .buckets(vec![0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 32.0]),
        )?;
        registry.register(Box::new(policy_lag.clone()))?;
        let trained_policy_lag = Histogram::with_opts(
            HistogramOpts::new(
                names::LEARNER_TRAINED_POLICY_LAG,
                "Policy versions between a fragment's behaviour policy and the policy an update starts from, per fragment trained on (what the PPO ratio has to correct).",
            )
            .buckets(vec![0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 32.0]),
        )?;
        registry.register(Box::new(trained_policy_lag.clone()))?;
        let simulated_seconds = CounterVec::new(
            Opts::new(
                names::LEARNER_SIMULATED_SECONDS,
                "Simulated seconds of scene time consumed, by scenario.",
            ),
            &["scenario"],
        )?;
        registry.register(Box::new(simulated_seconds.clone()))?;
        let lcf_phi = GaugeVec::new(
            Opts::new(
                names::LEARNER_LCF_PHI,
                "Mean LCF angle phi after the last update of the batch's agents with this many neighbours (0, 1-2, 3-5, 6+), degrees; unchanged while a batch has none.",
            ),
            &["neighbours"],
        )?;
        registry.register(Box::new(lcf_phi.clone()))?;
        Ok(LearnerMetrics {
            policy_version: int_gauge(
                names::LEARNER_POLICY_VERSION,
                "Version of the newest published policy.",
            )?,
            agent_steps: counter(
                names::LEARNER_AGENT_STEPS,
                "Agent-steps trained on (counted when their update completes).",
            )?,
            env_steps: counter(
                names::LEARNER_ENV_STEPS,
                "Scene steps trained on (counted when their update completes).",
            )?,
            fragments: counter(
                names::LEARNER_FRAGMENTS,
                "Rollout fragments accepted by ingest.",
            )?,
            fragments_rejected: counter_vec(
                names::LEARNER_FRAGMENTS_REJECTED,
                "Fragments refused as invalid, by reason.",
                &["reason"],
            )?,
            fragments_dropped: counter_vec(
                names::LEARNER_FRAGMENTS_DROPPED,
                "Accepted fragments not trained on, by reason (stale: more than max_policy_lag versions off; shutdown: queued or batched when the run ended; update_failed; off_grid: actions off the DQN's action grid).",
                &["reason"],
            )?,
            agent_steps_accepted: counter(
                names::LEARNER_AGENT_STEPS_ACCEPTED,
                "Agent-steps of accepted fragments; each is trained on or counted as dropped.",
            )?,
            agent_steps_dropped: counter_vec(
                names::LEARNER_AGENT_STEPS_DROPPED,
                "Agent-steps of accepted fragments not trained on, by reason (as fragments_dropped).",
                &["reason"],
            )?,
            requests_refused: counter_vec(
                names::LEARNER_REQUESTS_REFUSED,
                "RPCs refused before reaching a handler, by reason (unauthenticated: missing or wrong token; stream_limit: server.max_rollout_streams reached).",
                &["reason"],
            )?,
            samples_trained: counter(
                names::LEARNER_SAMPLES_TRAINED,
                "Agent-steps passed through gradient steps (counted once per epoch).",
            )?,
            updates: counter(names::LEARNER_UPDATES, "Policy updates completed.")?,
            update_seconds,
            connected_actors: int_gauge(
                names::LEARNER_CONNECTED_ACTORS,
                "Actors with an open rollout stream.",
            )?,
            queue_fragments: int_gauge(
                names::LEARNER_QUEUE_FRAGMENTS,
                "Fragments waiting in the ingest queue.",
            )?,
            transport_bytes: counter_vec(
                names::LEARNER_TRANSPORT_BYTES,
                "Encoded fragment bytes received, by transport.",
                &["transport"],
            )?,
            episodes: counter_vec(
                names::LEARNER_EPISODES,
                "Finished agent episodes, by scenario and outcome.",
                &["scenario", "outcome"],
            )?,
            human_episodes: counter_vec(
                names::LEARNER_HUMAN_EPISODES,
                "Finished episodes of human-driven (non-connected) vehicles, by scenario and outcome.",
                &["scenario", "outcome"],
            )?,
            success_rate: scenario_gauge(
                names::LEARNER_SUCCESS_RATE,
                "Share of recent episodes that reached their destination.",
            )?,
            crash_rate: scenario_gauge(
                names::LEARNER_CRASH_RATE,
                "Share of recent episodes that ended in a crash.",
            )?,
            out_of_road_rate: scenario_gauge(
                names::LEARNER_OUT_OF_ROAD_RATE,
                "Share of recent episodes that left the road.",
            )?,
            episode_reward_mean: scenario_gauge(
                names::LEARNER_EPISODE_REWARD_MEAN,
                "Mean total reward of recent episodes.",
            )?,
            episode_length_mean: scenario_gauge(
                names::LEARNER_EPISODE_LENGTH_MEAN,
                "Mean length of recent episodes, in decision steps.",
            )?,
            episode_reward_max: scenario_gauge(
                names::LEARNER_EPISODE_REWARD_MAX,
                "Largest total reward among recent episodes.",
            )?,
            episode_length_max: scenario_gauge(
                names::LEARNER_EPISODE_LENGTH_MAX,
                "Longest of recent episodes, in decision steps.",
            )?,
            accel_mean: scenario_gauge(
                names::LEARNER_ACCEL_MEAN,
                "Mean over recent episodes of each episode's mean |longitudinal acceleration|.",
            )?,
            accel_max: scenario_gauge(
                names::LEARNER_ACCEL_MAX,
                "Mean over recent episodes of each episode's largest |longitudinal acceleration| (paper: mean acceleration, maximum value).",
            )?,
            collisions: counter_vec(
                names::LEARNER_COLLISIONS,
                "Collisions of finished episodes of agents and human drivers, by scenario; divide its rate by the rate of simulated seconds for collisions per simulated second.",
                &["scenario"],
            )?,
            simulated_seconds,
            policy_lag,
            trained_policy_lag,
            scene_episodes: counter_vec(
                names::LEARNER_SCENE_EPISODES,
                "Scene episodes (MetaDrive's environment episodes: reset to reset) that ended, by scenario.",
                &["scenario"],
            )?,
            scene_success_rate: scenario_gauge(
                names::LEARNER_SCENE_SUCCESS_RATE,
                "MetaDrive's success rate: per scene episode the share of its agents that arrived, averaged over the last run.stats_window_scene_episodes scene episodes.",
            )?,
            scene_crash_rate: scenario_gauge(
                names::LEARNER_SCENE_CRASH_RATE,
                "MetaDrive's crash rate: per scene episode the share of its agents that crashed, averaged over the scene-episode window.",
            )?,
            scene_out_of_road_rate: scenario_gauge(
                names::LEARNER_SCENE_OUT_OF_ROAD_RATE,
                "MetaDrive's out-of-road rate: per scene episode the share of its agents that left the road, averaged over the scene-episode window.",
            )?,
            learning_rate: gauge(
                names::LEARNER_LEARNING_RATE,
                "Optimiser step size of the last update.",
            )?,
            lagrange_multiplier: gauge(
                names::LEARNER_LAGRANGE_MULTIPLIER,
                "PPO-Lagrangian's price of cost after the last update ([safety]; 0 when off).",
            )?,
            lcf_mean: gauge(
                names::LEARNER_LCF_MEAN,
                "Mean LCF angle phi after the last update, degrees (0 = selfish, 90 = fully cooperative): the fixed phi, CoPO's learned mean, or the dynamic LCF's phi over the batch.",
            )?,
            lcf_std: gauge(
                names::LEARNER_LCF_STD,
                "Spread of the LCF angle phi after the last update, degrees: CoPO's learned sigma, or the standard deviation of the dynamic LCF's phi over the batch (0 for a fixed phi).",
            )?,
            lcf_phi,
            nonfinite_minibatches: counter(
                names::LEARNER_NONFINITE_MINIBATCHES,
                "Minibatches skipped because their loss was NaN or infinite.",
            )?,
            policy_loss: gauge(names::LEARNER_POLICY_LOSS, "PPO clipped surrogate loss.")?,
            value_loss: gauge(names::LEARNER_VALUE_LOSS, "Value-function loss.")?,
            entropy: gauge(names::LEARNER_ENTROPY, "Policy entropy (nats).")?,
            approx_kl: gauge(
                names::LEARNER_APPROX_KL,
                "Approximate KL(old ‖ new) per update.",
            )?,
            clip_fraction: gauge(
                names::LEARNER_CLIP_FRACTION,
                "Share of samples whose probability ratio was clipped.",
            )?,
            explained_variance: gauge(
                names::LEARNER_EXPLAINED_VARIANCE,
                "Share of return variance explained by the critic.",
            )?,
            grad_norm: gauge(names::LEARNER_GRAD_NORM, "Gradient norm before clipping.")?,
            curriculum_stage: int_gauge(
                names::LEARNER_CURRICULUM_STAGE,
                "Curriculum stage of the newest policy broadcast (0 for algorithms without a curriculum).",
            )?,
            curriculum_agents: int_gauge(
                names::LEARNER_CURRICULUM_AGENTS,
                "Learning agents per scene that actors are told to simulate.",
            )?,
            q_mean: gauge(
                names::LEARNER_Q_MEAN,
                "DQN: mean Q(s, a) of the transitions sampled in the last update (0 for PPO).",
            )?,
            epsilon: gauge(
                names::LEARNER_EPSILON,
                "DQN: exploration rate epsilon broadcast after the last update (0 for PPO and before the first update).",
            )?,
            replay_transitions: int_gauge(
                names::LEARNER_REPLAY_TRANSITIONS,
                "DQN: agent transitions held in the replay buffer (0 for PPO).",
            )?,
            local_actor_restarts: counter(
                names::LEARNER_LOCAL_ACTOR_RESTARTS,
                "Local actors (serve --local-actors) restarted after they exited.",
            )?,
            registry,
        })
    }

    /// Creates every bounded label value at zero, so dashboards and alerts see each series
    /// before its first event.
    pub fn initialise_labels(&self, scenario: &str) {
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
        for outcome in Outcome::ALL {
            self.episodes
                .with_label_values(&[scenario, outcome.label()]);
            self.human_episodes
                .with_label_values(&[scenario, outcome.label()]);
        }
        self.collisions.with_label_values(&[scenario]);
        self.simulated_seconds.with_label_values(&[scenario]);
        self.scene_episodes.with_label_values(&[scenario]);
        for bucket in NEIGHBOUR_BUCKETS {
            self.lcf_phi.with_label_values(&[bucket]);
        }
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

    /// Lags, in policy versions, of the fragments an update trained on.
    pub fn record_trained_lags(&self, lags: &[u64]) {
        for &lag in lags {
            self.trained_policy_lag.observe(lag as f64);
        }
    }

    pub fn record_update(&self, stats: &UpdateStats, seconds: f64) {
        self.updates.inc();
        self.learning_rate.set(stats.learning_rate);
        self.lcf_mean.set(stats.lcf_mean_deg);
        self.lagrange_multiplier.set(stats.lagrange_multiplier);
        self.lcf_std.set(stats.lcf_std_deg);
        for (bucket, phi) in NEIGHBOUR_BUCKETS.iter().zip(stats.lcf_phi_by_neighbours) {
            if let Some(phi) = phi {
                self.lcf_phi.with_label_values(&[bucket]).set(phi);
            }
        }
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
        self.q_mean.set(stats.q_mean);
        self.epsilon.set(stats.epsilon);
        self.replay_transitions
            .set(i64::try_from(stats.replay_transitions).unwrap_or(i64::MAX));
    }

    pub fn record_stage(&self, stage: Stage) {
        self.curriculum_stage.set(stage.index as i64);
        self.curriculum_agents.set(stage.agents as i64);
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

    pub fn record_window(&self, scenario: &str, summary: &WindowSummary) {
        self.success_rate
            .with_label_values(&[scenario])
            .set(summary.success_rate);
        self.crash_rate
            .with_label_values(&[scenario])
            .set(summary.crash_rate);
        self.out_of_road_rate
            .with_label_values(&[scenario])
            .set(summary.out_of_road_rate);
        self.episode_reward_mean
            .with_label_values(&[scenario])
            .set(summary.mean_reward);
        self.episode_length_mean
            .with_label_values(&[scenario])
            .set(summary.mean_length);
        self.episode_reward_max
            .with_label_values(&[scenario])
            .set(summary.max_reward);
        self.episode_length_max
            .with_label_values(&[scenario])
            .set(f64::from(summary.max_length));
        self.accel_mean
            .with_label_values(&[scenario])
            .set(summary.mean_accel);
        self.accel_max
            .with_label_values(&[scenario])
            .set(summary.mean_max_accel);
    }
}
