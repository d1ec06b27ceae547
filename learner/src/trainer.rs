//! The training loop: takes validated fragments off the ingest queue, filters stale ones,
//! batches, updates the algorithm, publishes each new policy version, checkpoints, reports
//! progress, and stops on budget or request.

use std::fs::OpenOptions;
use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::Context;
use tokio::sync::mpsc;

use junction_common::fragment::{PROTOCOL_VERSION, RolloutFragment};
use junction_common::proto;
use junction_common::spec::OBS_LAYOUT_VERSION;
use junction_common::weights;

use crate::algo::{Algorithm, Stage, UpdateStats};
use crate::checkpoint::{CheckpointMeta, Checkpointer};
use crate::metrics::DROP_STALE;
use crate::server::Shared;
use crate::stats::EpisodeWindow;

/// How long the loop waits for a fragment before it checks budget, progress and stop requests.
const POLL: Duration = Duration::from_millis(200);

/// Counters that survive a restart through checkpoints.
#[derive(Debug, Clone, Copy, Default)]
pub struct Progress {
    pub version: u64,
    pub updates: u64,
    pub agent_steps: u64,
    pub env_steps: u64,
    pub samples_trained: u64,
}

impl From<&CheckpointMeta> for Progress {
    fn from(m: &CheckpointMeta) -> Self {
        Progress {
            version: m.version,
            updates: m.updates,
            agent_steps: m.agent_steps,
            env_steps: m.env_steps,
            samples_trained: m.samples_trained,
        }
    }
}

pub struct Trainer {
    pub shared: Arc<Shared>,
    pub algorithm: Box<dyn Algorithm + Send>,
    pub queue: mpsc::Receiver<RolloutFragment>,
    pub runtime: tokio::runtime::Handle,
    pub checkpointer: Checkpointer,
    pub progress_log: PathBuf,
    pub stop: Arc<AtomicBool>,
    pub progress: Progress,
    /// The curriculum stage of the newest broadcast, so a change is logged once.
    pub stage: Stage,
}

/// Weights message for the current policy; actors simulate `active_agents` agents per scene
/// with it.
pub fn weights_message(
    algorithm: &dyn Algorithm,
    version: u64,
    active_agents: usize,
    run_finished: bool,
) -> anyhow::Result<proto::PolicyWeights> {
    let policy = algorithm.policy();
    Ok(proto::PolicyWeights {
        protocol_version: PROTOCOL_VERSION,
        version,
        format: "safetensors".into(),
        data: policy.to_bytes(version).context("serialising the policy")?,
        obs_dim: policy.obs_dim() as u32,
        action_dim: policy.action_dim() as u32,
        run_finished,
        active_agents: u32::try_from(active_agents).unwrap_or(u32::MAX),
    })
}

struct Reporter {
    /// Episodes finished since this process started.
    episodes: u64,
    last: Instant,
    last_agent_steps: u64,
    started: Instant,
}

impl Trainer {
    /// Runs until the budget is spent, a stop is requested, or every sender is gone; returns
    /// the final progress after writing a last checkpoint and telling actors the run is over.
    pub fn run(mut self) -> anyhow::Result<Progress> {
        let config = self.shared.config.clone();
        let mut window = EpisodeWindow::new(config.run.stats_window_episodes);
        let mut pending: Vec<RolloutFragment> = Vec::new();
        let mut pending_env_steps = 0usize;
        let started = Instant::now();
        let budget = &config.run;
        let mut reporter = Reporter {
            episodes: 0,
            last: started,
            last_agent_steps: self.progress.agent_steps,
            started,
        };
        let start_progress = self.progress;
        let _span = tracing::info_span!("trainer", algorithm = self.algorithm.name()).entered();
        tracing::info!(version = self.progress.version, "training started");
        loop {
            let budget_spent = (budget.max_seconds > 0.0
                && started.elapsed().as_secs_f64() >= budget.max_seconds)
                || (budget.max_updates > 0
                    && self.progress.updates - start_progress.updates >= budget.max_updates)
                || (budget.max_agent_steps > 0
                    && self.progress.agent_steps >= budget.max_agent_steps);
            if budget_spent {
                tracing::info!("budget reached");
                break;
            }
            if self.stop.load(Ordering::Relaxed) {
                tracing::info!("stop requested");
                break;
            }
            let received = self
                .runtime
                .block_on(tokio::time::timeout(POLL, self.queue.recv()));
            self.shared
                .metrics
                .queue_fragments
                .set(self.queue.len() as i64);
            match received {
                Ok(Some(fragment)) => {
                    reporter.episodes += fragment.episodes.len() as u64;
                    for episode in &fragment.episodes {
                        window.push(*episode);
                    }
                    let metrics = &self.shared.metrics;
                    metrics.record_fragment(&config.scenario.name, &fragment);
                    let lag = self
                        .progress
                        .version
                        .saturating_sub(fragment.behaviour_version);
                    metrics.policy_lag.observe(lag as f64);
                    if lag > config.learner.max_policy_lag {
                        metrics
                            .fragments_dropped
                            .with_label_values(&[DROP_STALE])
                            .inc();
                        tracing::debug!(lag, actor = %fragment.actor_id, "dropped stale fragment");
                    } else {
                        pending_env_steps += fragment.steps;
                        self.progress.env_steps += fragment.steps as u64;
                        self.progress.agent_steps += fragment.agent_steps() as u64;
                        self.shared.metrics.env_steps.inc_by(fragment.steps as u64);
                        self.shared
                            .metrics
                            .agent_steps
                            .inc_by(fragment.agent_steps() as u64);
                        pending.push(fragment);
                    }
                }
                Ok(None) => break,
                Err(_) => {}
            }
            if pending_env_steps >= config.train_batch_env_steps() {
                self.update(&pending)?;
                pending.clear();
                pending_env_steps = 0;
            }
            if reporter.last.elapsed().as_secs_f64() >= budget.progress_interval_s {
                self.report(&mut reporter, &window)?;
            }
        }
        self.report(&mut reporter, &window)?;
        // The checkpoint counts every agent-step received, so the stage it implies is logged.
        self.advance_stage();
        self.checkpoint()?;
        let last = weights_message(
            self.algorithm.as_ref(),
            self.progress.version,
            self.stage.agents,
            true,
        )?;
        self.shared.weights.send_replace(Arc::new(last));
        Ok(self.progress)
    }

    fn update(&mut self, batch: &[RolloutFragment]) -> anyhow::Result<()> {
        let _span = tracing::info_span!("update", version = self.progress.version + 1).entered();
        let started = Instant::now();
        let stats = match self.algorithm.update(batch) {
            Ok(stats) => stats,
            Err(e) => {
                tracing::warn!(error = %e, "update skipped");
                return Ok(());
            }
        };
        let seconds = started.elapsed().as_secs_f64();
        if stats.off_grid_fragments > 0 {
            static LOGGED: std::sync::Once = std::sync::Once::new();
            LOGGED.call_once(|| {
                tracing::warn!(
                    fragments = stats.off_grid_fragments,
                    "dropped fragments whose actions are off the action grid (counted as \
                     fragments_dropped_total{{reason=\"off_grid\"}}; further drops are only counted)"
                );
            });
        }
        self.progress.version += 1;
        self.progress.updates += 1;
        self.progress.samples_trained += stats.samples_trained as u64;
        self.shared.metrics.record_update(&stats, seconds);
        self.advance_stage();
        let message = weights_message(
            self.algorithm.as_ref(),
            self.progress.version,
            self.stage.agents,
            false,
        )?;
        self.shared.weights.send_replace(Arc::new(message));
        self.shared
            .metrics
            .policy_version
            .set(self.progress.version as i64);
        log_update(&stats, seconds);
        let every = self.shared.config.run.checkpoint_every_updates;
        if every > 0 && self.progress.updates % every == 0 {
            self.checkpoint()?;
        }
        Ok(())
    }

    /// Moves to the curriculum stage the consumed agent-steps call for, before a broadcast.
    fn advance_stage(&mut self) {
        let scenario_agents = self.shared.config.scenario.agent_count();
        let stage = self
            .algorithm
            .stage(self.progress.agent_steps, scenario_agents);
        if stage != self.stage {
            tracing::info!(
                old_stage = self.stage.index,
                new_stage = stage.index,
                old_agents = self.stage.agents,
                new_agents = stage.agents,
                agent_steps = self.progress.agent_steps,
                "curriculum stage changed"
            );
            self.stage = stage;
            self.shared.metrics.record_stage(stage);
        }
    }

    fn checkpoint(&self) -> anyhow::Result<()> {
        let policy = self.algorithm.policy().to_bytes(self.progress.version)?;
        let state_tensors = self.algorithm.state_tensors();
        let refs: Vec<(String, &tch::Tensor)> =
            state_tensors.iter().map(|(n, t)| (n.clone(), t)).collect();
        let state = weights::encode(&refs, Default::default())?;
        let p = self.progress;
        let meta = CheckpointMeta {
            version: p.version,
            updates: p.updates,
            agent_steps: p.agent_steps,
            env_steps: p.env_steps,
            samples_trained: p.samples_trained,
            algorithm: self.algorithm.name().to_string(),
            protocol_version: PROTOCOL_VERSION,
            obs_layout_version: OBS_LAYOUT_VERSION,
            created_unix_s: SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| d.as_secs())
                .unwrap_or(0),
            config: self.shared.config.to_toml(),
        };
        let path = self.checkpointer.write(&meta, &policy, &state)?;
        tracing::info!(version = p.version, path = %path.display(), "checkpoint written");
        Ok(())
    }

    fn report(&self, reporter: &mut Reporter, window: &EpisodeWindow) -> anyhow::Result<()> {
        let now = Instant::now();
        let dt = now.duration_since(reporter.last).as_secs_f64().max(1e-9);
        let rate = (self.progress.agent_steps - reporter.last_agent_steps) as f64 / dt;
        reporter.last = now;
        reporter.last_agent_steps = self.progress.agent_steps;
        let summary = window.summary();
        let scenario = &self.shared.config.scenario.name;
        self.shared.metrics.record_window(scenario, &summary);
        let actors = self.shared.metrics.connected_actors.get();
        tracing::info!(
            version = self.progress.version,
            agent_steps_per_s = format!("{rate:.0}"),
            success = format!("{:.3}", summary.success_rate),
            crash = format!("{:.3}", summary.crash_rate),
            out_of_road = format!("{:.3}", summary.out_of_road_rate),
            episode_reward = format!("{:.2}", summary.mean_reward),
            episodes = summary.episodes,
            actors,
            queue = self.queue.len(),
            "progress"
        );
        if let Ok(mut status) = self.shared.status.lock() {
            status.policy_version = self.progress.version;
            status.agent_steps_consumed = self.progress.agent_steps;
            status.samples_trained = self.progress.samples_trained;
            status.success_rate = summary.success_rate;
            status.crash_rate = summary.crash_rate;
            status.mean_episode_reward = summary.mean_reward;
            status.episodes = reporter.episodes;
        }
        let line = serde_json::json!({
            "elapsed_s": reporter.started.elapsed().as_secs_f64(),
            "unix_s": SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0),
            "version": self.progress.version,
            "updates": self.progress.updates,
            "agent_steps": self.progress.agent_steps,
            "env_steps": self.progress.env_steps,
            "samples_trained": self.progress.samples_trained,
            "agent_steps_per_s": rate,
            "scenario": scenario,
            "window": summary,
        });
        let mut file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.progress_log)
            .with_context(|| format!("opening {}", self.progress_log.display()))?;
        writeln!(file, "{line}")
            .with_context(|| format!("writing {}", self.progress_log.display()))?;
        Ok(())
    }
}

fn log_update(stats: &UpdateStats, seconds: f64) {
    tracing::debug!(
        seconds = format!("{seconds:.2}"),
        agent_steps = stats.agent_steps,
        policy_loss = format!("{:.4}", stats.policy_loss),
        value_loss = format!("{:.4}", stats.value_loss),
        entropy = format!("{:.3}", stats.entropy),
        approx_kl = format!("{:.4}", stats.approx_kl),
        clip_fraction = format!("{:.3}", stats.clip_fraction),
        explained_variance = format!("{:.3}", stats.explained_variance),
        skipped = stats.skipped_minibatches,
        "update"
    );
}
