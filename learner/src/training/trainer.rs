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

use junction_common::fragment::RolloutFragment;
use junction_common::lcf::NEIGHBOUR_BUCKETS;
use junction_common::ledger::Event;
use junction_common::proto;
use junction_common::weights;
use junction_core::config::{AlgoKind, LrSchedule};
use junction_core::spec::{OBS_LAYOUT_VERSION, PROTOCOL_VERSION};

use super::checkpoint::{CheckpointMeta, Checkpointer};
use crate::algo::{Algorithm, Stage, UpdateStats};
use crate::hub::Shared;
use crate::telemetry::labels::{DROP_SHUTDOWN, DROP_STALE, DROP_UPDATE_FAILED};
use crate::telemetry::progress::{LcfProgress, ProgressLine, UpdateProgress};
use crate::telemetry::stats::{EpisodeWindow, SceneEpisodeWindow, WindowSummary};
use crate::telemetry::tensorboard::{EventWriter, Scalars};

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
    /// The progress lines' values as TensorBoard scalars, in the run directory.
    pub tensorboard: EventWriter,
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
        data: algorithm
            .policy_bytes(version)
            .context("serialising the policy")?,
        obs_dim: policy.obs_dim() as u32,
        action_dim: policy.action_dim() as u32,
        run_finished,
        active_agents: u32::try_from(active_agents).unwrap_or(u32::MAX),
    })
}

struct Reporter {
    /// Episodes finished, collisions and simulated seconds received since this process started.
    episodes: u64,
    collisions: u64,
    sim_seconds: f64,
    /// The LCF angle after the newest update (none yet in this process).
    lcf: Option<LcfSnapshot>,
    /// The newest update's diagnostics (none yet in this process).
    update: Option<UpdateProgress>,
    /// MetaDrive's unit: whole scene episodes.
    scenes: SceneEpisodeWindow,
    last: Instant,
    last_agent_steps: u64,
    started: Instant,
    /// Seconds spent in updates since this process started.
    update_seconds: f64,
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
            collisions: 0,
            sim_seconds: 0.0,
            lcf: None,
            update: None,
            scenes: SceneEpisodeWindow::new(config.run.stats_window_scene_episodes),
            last: started,
            last_agent_steps: self.progress.agent_steps,
            started,
            update_seconds: 0.0,
        };
        let start_progress = self.progress;
        let mut refusals_logged = std::collections::HashSet::new();
        // A resumed run answers Status with its restored counters from the start.
        self.publish_status(&reporter, &window.summary());
        let _span = tracing::info_span!("trainer", algorithm = self.algorithm.name()).entered();
        tracing::info!(version = self.progress.version, "training started");
        let ppo_based = config.learner.algo != AlgoKind::Dqn;
        if ppo_based
            && config.ppo.lr_schedule == LrSchedule::Linear
            && budget.budget_spent(0, 0.0).is_none()
        {
            tracing::info!(
                learning_rate = config.ppo.learning_rate,
                "ppo.lr_schedule = \"linear\" anneals over run.max_agent_steps or run.max_seconds, and this run sets neither: the learning rate stays constant"
            );
        }
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
                .ingest
                .queue_fragments
                .set(self.queue.len() as i64);
            match received {
                Ok(Some(fragment)) => {
                    self.observe(&fragment, &mut reporter, &mut window);
                    let metrics = &self.shared.metrics;
                    // Both directions: a fragment from a *newer* version comes from a learner
                    // that died after its last checkpoint; its weights are as far from ours.
                    let lag = self.progress.version.abs_diff(fragment.behaviour_version);
                    metrics.ingest.policy_lag.observe(lag as f64);
                    if lag > config.learner.max_policy_lag {
                        self.shared
                            .drop_fragments(DROP_STALE, std::slice::from_ref(&fragment));
                        tracing::debug!(lag, actor = %fragment.actor_id, "dropped stale fragment");
                    } else if let Some(reason) = self.algorithm.refusal(&fragment) {
                        self.shared
                            .drop_fragments(reason, std::slice::from_ref(&fragment));
                        if refusals_logged.insert(reason) {
                            tracing::warn!(
                                reason,
                                actor = %fragment.actor_id,
                                "the algorithm cannot train on this fragment: counted as dropped (further drops of this reason are only counted)"
                            );
                        }
                    } else {
                        pending_env_steps += fragment.steps;
                        pending.push(fragment);
                    }
                }
                Ok(None) => break,
                Err(_) => {}
            }
            if pending_env_steps >= config.train_batch_env_steps() {
                let seconds = started.elapsed().as_secs_f64();
                if let Some((stats, update)) = self.update(&pending, seconds)? {
                    reporter.lcf.get_or_insert_default().record(&stats);
                    reporter.update_seconds += update.seconds;
                    reporter.update = Some(update);
                }
                pending.clear();
                pending_env_steps = 0;
            }
            if reporter.last.elapsed().as_secs_f64() >= budget.progress_interval_s {
                self.report(&mut reporter, &window)?;
            }
        }
        // Tell actors the run is over before refusing their fragments, so they take the
        // streams that end next for the end of the run, not for a failure.
        self.advance_stage();
        let last = weights_message(
            self.algorithm.as_ref(),
            self.progress.version,
            self.stage.agents,
            true,
        )?;
        self.shared.weights.send_replace(Arc::new(last));
        // Nothing accepted goes uncounted: refuse new fragments, then count what was queued
        // or waiting for a full batch. `recv` (not `try_recv`) also waits for places a
        // transport reserved before the close (the shared-memory server's), which it fills
        // in moments.
        self.queue.close();
        while let Some(fragment) = self.runtime.block_on(self.queue.recv()) {
            self.observe(&fragment, &mut reporter, &mut window);
            pending.push(fragment);
        }
        self.shared.metrics.ingest.queue_fragments.set(0);
        if !pending.is_empty() {
            tracing::info!(
                fragments = pending.len(),
                agent_steps = pending
                    .iter()
                    .map(RolloutFragment::agent_steps)
                    .sum::<usize>(),
                "run ended with fragments short of a batch: counted as dropped (shutdown)"
            );
            self.shared.drop_fragments(DROP_SHUTDOWN, &pending);
        }
        self.report(&mut reporter, &window)?;
        if let Some(lcf) = &reporter.lcf {
            tracing::info!(
                mean_deg = format!("{:.2}", lcf.mean_deg),
                std_deg = format!("{:.2}", lcf.std_deg),
                by_neighbours = %lcf.by_neighbours_text(),
                "final LCF angle φ"
            );
        }
        self.checkpoint()?;
        self.shared.ledger.record(&Event::LearnerStop);
        Ok(self.progress)
    }

    /// Folds a fragment's episodes, collisions and simulated time into the driving metrics,
    /// whether it is trained on or dropped.
    fn observe(
        &self,
        fragment: &RolloutFragment,
        reporter: &mut Reporter,
        window: &mut EpisodeWindow,
    ) {
        let (collisions, sim_seconds) = (fragment.collisions(), f64::from(fragment.sim_seconds));
        reporter.episodes += fragment.episodes.len() as u64;
        reporter.collisions += collisions;
        reporter.sim_seconds += sim_seconds;
        window.record(&fragment.episodes, collisions, sim_seconds);
        reporter.scenes.record(&fragment.scene_episodes);
        self.shared
            .metrics
            .episodes
            .record_fragment(&self.shared.config.scenario.name, fragment);
    }

    /// One update on `batch`, `run_seconds` into this process's training; its statistics, or
    /// none when it was skipped.
    fn update(
        &mut self,
        batch: &[RolloutFragment],
        run_seconds: f64,
    ) -> anyhow::Result<Option<(UpdateStats, UpdateProgress)>> {
        let _span = tracing::info_span!("update", version = self.progress.version + 1).entered();
        let lags: Vec<u64> = batch
            .iter()
            .map(|f| self.progress.version.abs_diff(f.behaviour_version))
            .collect();
        let started = Instant::now();
        self.algorithm.set_progress(
            self.shared
                .config
                .run
                .budget_spent(self.progress.agent_steps, run_seconds),
        );
        let stats = match self.algorithm.update(batch) {
            Ok(stats) => stats,
            Err(e) => {
                tracing::warn!(error = %e, "update skipped; its fragments are counted as dropped (update_failed)");
                self.shared.drop_fragments(DROP_UPDATE_FAILED, batch);
                return Ok(None);
            }
        };
        let seconds = started.elapsed().as_secs_f64();
        let env_steps: u64 = batch.iter().map(|f| f.steps as u64).sum();
        let agent_steps: u64 = batch.iter().map(|f| f.agent_steps() as u64).sum();
        self.progress.env_steps += env_steps;
        self.progress.agent_steps += agent_steps;
        self.shared.metrics.update.env_steps.inc_by(env_steps);
        self.shared.metrics.update.agent_steps.inc_by(agent_steps);
        self.shared
            .metrics
            .update
            .fragments_trained
            .inc_by(batch.len() as u64);
        self.progress.version += 1;
        self.progress.updates += 1;
        self.shared.ledger.record(&Event::Trained {
            update: self.progress.updates,
            fragments: batch
                .iter()
                .map(|f| (f.actor_id.as_str(), f.sequence))
                .collect(),
        });
        self.progress.samples_trained += stats.samples_trained as u64;
        self.shared.metrics.record_update(&stats, seconds);
        self.shared.metrics.update.record_trained_lags(&lags);
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
            .update
            .policy_version
            .set(self.progress.version as i64);
        log_update(&stats, seconds);
        let every = self.shared.config.run.checkpoint_every_updates;
        if every > 0 && self.progress.updates.is_multiple_of(every) {
            // A full disk or a lost mount must not end the run: training goes on, and the
            // next checkpoint tries again (the ledger counts what a crash now would cost).
            if let Err(e) = self.checkpoint() {
                self.shared.metrics.update.checkpoint_failures.inc();
                tracing::error!(error = %format!("{e:#}"), version = self.progress.version, "checkpoint failed; training goes on and the next one tries again");
            }
        }
        let progress = UpdateProgress {
            policy_loss: stats.policy_loss,
            value_loss: stats.value_loss,
            entropy: stats.entropy,
            approx_kl: stats.approx_kl,
            clip_fraction: stats.clip_fraction,
            explained_variance: stats.explained_variance,
            grad_norm: stats.grad_norm,
            learning_rate: stats.learning_rate,
            kl: stats.kl,
            kl_coef: stats.kl_coef,
            lag_mean: lags.iter().sum::<u64>() as f64 / lags.len().max(1) as f64,
            lag_max: lags.iter().copied().max().unwrap_or(0),
            seconds,
            lagrange_multiplier: stats.lagrange_multiplier,
            epsilon: stats.epsilon,
            q_mean: stats.q_mean,
        };
        Ok(Some((stats, progress)))
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
            self.shared.metrics.curriculum.record_stage(stage);
        }
    }

    fn checkpoint(&self) -> anyhow::Result<()> {
        let policy = self.algorithm.policy_bytes(self.progress.version)?;
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
            actors_registered: self.shared.actors_registered(),
            format_version: super::checkpoint::FORMAT_VERSION,
        };
        let path = self.checkpointer.write(&meta, &policy, &state)?;
        self.shared.ledger.record(&Event::Checkpoint {
            update: p.updates,
            version: p.version,
        });
        tracing::info!(version = p.version, path = %path.display(), "checkpoint written");
        Ok(())
    }

    fn report(&mut self, reporter: &mut Reporter, window: &EpisodeWindow) -> anyhow::Result<()> {
        let now = Instant::now();
        let dt = now.duration_since(reporter.last).as_secs_f64().max(1e-9);
        let rate = (self.progress.agent_steps - reporter.last_agent_steps) as f64 / dt;
        reporter.last = now;
        reporter.last_agent_steps = self.progress.agent_steps;
        let summary = window.summary();
        let scenes = reporter.scenes.summary();
        let scenario = &self.shared.config.scenario.name;
        self.shared
            .metrics
            .episodes
            .record_window(scenario, &summary);
        self.shared
            .metrics
            .episodes
            .record_scene_window(scenario, &scenes);
        let actors = self.shared.metrics.ingest.connected_actors.get();
        tracing::info!(
            version = self.progress.version,
            agent_steps_per_s = format!("{rate:.0}"),
            success = format!("{:.3}", summary.success_rate),
            success_md = format!("{:.3}", scenes.success_rate),
            crash = format!("{:.3}", summary.crash_rate),
            out_of_road = format!("{:.3}", summary.out_of_road_rate),
            episode_reward = format!("{:.2}", summary.mean_reward),
            episodes = summary.episodes,
            actors,
            queue = self.queue.len(),
            "progress"
        );
        self.publish_status(reporter, &summary);
        let config = &self.shared.config;
        let line = ProgressLine {
            elapsed_s: reporter.started.elapsed().as_secs_f64(),
            unix_s: SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| d.as_secs_f64())
                .unwrap_or(0.0),
            algorithm: self.algorithm.name().to_string(),
            scenario: scenario.clone(),
            seed: Some(config.run.seed),
            version: self.progress.version,
            updates: self.progress.updates,
            agent_steps: self.progress.agent_steps,
            env_steps: self.progress.env_steps,
            samples_trained: self.progress.samples_trained,
            agent_steps_per_s: rate,
            episodes_total: reporter.episodes,
            collisions_total: reporter.collisions,
            sim_seconds_total: reporter.sim_seconds,
            update_seconds_total: reporter.update_seconds,
            accepted_agent_steps: self.shared.metrics.ingest.agent_steps_accepted.get(),
            dropped_agent_steps: self
                .shared
                .metrics
                .ingest
                .dropped_agent_steps()
                .into_iter()
                .map(|(reason, steps)| (reason.to_string(), steps))
                .collect(),
            window: summary,
            scene_window: scenes,
            scene_totals: reporter.scenes.totals().clone(),
            lcf: reporter.lcf.as_ref().map(LcfSnapshot::to_progress),
            update: reporter.update.clone(),
        };
        let scalars = Scalars::new(config).of(&line);
        self.tensorboard
            .scalars(line.agent_steps, line.unix_s, &scalars)?;
        let line = serde_json::to_string(&line).context("encoding a progress line")?;
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

impl Trainer {
    fn publish_status(&self, reporter: &Reporter, summary: &WindowSummary) {
        if let Ok(mut status) = self.shared.status.lock() {
            status.policy_version = self.progress.version;
            status.agent_steps_consumed = self.progress.agent_steps;
            status.samples_trained = self.progress.samples_trained;
            status.success_rate = summary.success_rate;
            status.crash_rate = summary.crash_rate;
            status.mean_episode_reward = summary.mean_reward;
            status.episodes = reporter.episodes;
        }
    }
}

/// The LCF angle after the newest update, for progress lines and the final log; a
/// neighbour-count bucket keeps its last value while batches have no agent in it (like the
/// gauge).
#[derive(Default)]
struct LcfSnapshot {
    mean_deg: f64,
    std_deg: f64,
    by_neighbours: [Option<f64>; NEIGHBOUR_BUCKETS.len()],
}

impl LcfSnapshot {
    fn record(&mut self, stats: &UpdateStats) {
        self.mean_deg = stats.lcf_mean_deg;
        self.std_deg = stats.lcf_std_deg;
        for (kept, new) in self
            .by_neighbours
            .iter_mut()
            .zip(stats.lcf_phi_by_neighbours)
        {
            *kept = new.or(*kept);
        }
    }

    fn buckets(&self) -> impl Iterator<Item = (&'static str, f64)> + '_ {
        NEIGHBOUR_BUCKETS
            .into_iter()
            .zip(self.by_neighbours)
            .filter_map(|(bucket, phi)| Some((bucket, phi?)))
    }

    fn to_progress(&self) -> LcfProgress {
        LcfProgress {
            mean_deg: self.mean_deg,
            std_deg: self.std_deg,
            phi_deg_by_neighbours: self
                .buckets()
                .map(|(bucket, phi)| (bucket.to_string(), phi))
                .collect(),
        }
    }

    fn by_neighbours_text(&self) -> String {
        self.buckets()
            .map(|(bucket, phi)| format!("{bucket}: {phi:.2}"))
            .collect::<Vec<_>>()
            .join(", ")
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo;
    use crate::telemetry::metrics::LearnerMetrics;
    use junction_core::config::RunConfig;
    use junction_core::lcf_inputs;

    /// 2 steps of `agents` live agents of the default scenario, from policy `version`.
    fn fragment(agents: usize, version: u64) -> RolloutFragment {
        let (steps, obs_dim) = (2, 91);
        let cells = steps * agents;
        RolloutFragment {
            actor_id: "test".into(),
            behaviour_version: version,
            scenario: "intersection".into(),
            steps,
            agents,
            obs_dim,
            action_dim: 2,
            obs: vec![0.5; cells * obs_dim],
            actions: vec![0.1; cells * 2],
            log_probs: vec![-1.0; cells],
            rewards: vec![0.3; cells],
            costs: vec![0.0; cells],
            dones: vec![false; cells],
            alive: vec![true; cells],
            bootstrap_obs: vec![0.5; agents * obs_dim],
            neighbour_offsets: vec![0; cells + 1],
            lcf_features: vec![0.5; cells * lcf_inputs::FEATURES],
            sim_seconds: 0.2,
            ..RolloutFragment::default()
        }
    }

    #[test]
    fn every_received_agent_step_is_trained_or_dropped_by_reason() {
        let config = RunConfig::load(
            None,
            &[
                "ppo.hidden=[8]".into(),
                "ppo.epochs=1".into(),
                "ppo.train_batch_env_steps=4".into(),
                "run.max_updates=1".into(),
                "run.max_seconds=60".into(),
                "run.checkpoint_every_updates=0".into(),
                "learner.max_policy_lag=2".into(),
            ],
        )
        .unwrap();
        let dir = std::env::temp_dir().join(format!("junction-trainer-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        // As on the learner's blocking thread: inside the runtime's context.
        let _context = runtime.enter();
        let algorithm = algo::configured::build(&config, tch::Device::Cpu).unwrap();
        let initial = weights_message(algorithm.as_ref(), 0, 1, false).unwrap();
        let metrics = LearnerMetrics::new().unwrap();
        let shared = Arc::new(Shared::new(config.clone(), metrics, initial));
        let (tx, queue) = mpsc::channel(16);
        // Fresh 3 agents; stale by 5 versions in the future (a learner that died after its
        // checkpoint); fresh 2 agents: the batch is full, one update, the budget is spent.
        // Then two more wait in the queue when the run ends.
        let sent = [
            fragment(3, 0),
            fragment(4, 5),
            fragment(2, 0),
            fragment(1, 1),
            fragment(5, 0),
        ];
        for f in &sent {
            tx.try_send(f.clone()).unwrap();
        }
        // A place reserved before the run ends and filled after it (as the shared-memory
        // server may): that fragment is counted too.
        let late = fragment(3, 1);
        let reserved = tx.clone().try_reserve_owned().unwrap();
        let filler = {
            let late = late.clone();
            std::thread::spawn(move || {
                std::thread::sleep(std::time::Duration::from_millis(300));
                reserved.send(late);
            })
        };
        let trainer = Trainer {
            shared: Arc::clone(&shared),
            algorithm,
            queue,
            runtime: runtime.handle().clone(),
            checkpointer: Checkpointer::new(dir.join("checkpoints"), 1).unwrap(),
            progress_log: dir.join("progress.jsonl"),
            tensorboard: EventWriter::create(&dir, 0.0).unwrap(),
            stop: Arc::new(AtomicBool::new(false)),
            progress: Progress::default(),
            stage: Stage {
                index: 0,
                agents: 30,
            },
        };
        let progress = trainer.run().unwrap();
        filler.join().unwrap();
        let m = &shared.metrics;
        let dropped = |reason: &str| {
            m.ingest
                .agent_steps_dropped
                .with_label_values(&[reason])
                .get()
        };
        assert_eq!((progress.version, progress.agent_steps), (1, 2 * (3 + 2)));
        assert_eq!(m.update.agent_steps.get(), 10);
        assert_eq!(dropped(DROP_STALE), 2 * 4);
        assert_eq!(dropped(DROP_SHUTDOWN), 2 * (1 + 5 + 3));
        assert_eq!(dropped(DROP_UPDATE_FAILED), 0);
        let total: u64 = sent
            .iter()
            .chain([&late])
            .map(|f| f.agent_steps() as u64)
            .sum();
        assert_eq!(
            m.update.agent_steps.get() + dropped(DROP_STALE) + dropped(DROP_SHUTDOWN),
            total
        );
        assert_eq!(
            m.ingest
                .fragments_dropped
                .with_label_values(&[DROP_SHUTDOWN])
                .get(),
            3
        );
        // The queue is closed: nothing can be accepted after the final count.
        assert!(tx.try_send(fragment(1, 1)).is_err());
        // The last progress line carries the same accounting.
        let log = std::fs::read_to_string(dir.join("progress.jsonl")).unwrap();
        let last: serde_json::Value = serde_json::from_str(log.lines().last().unwrap()).unwrap();
        assert_eq!(last["dropped_agent_steps"]["shutdown"], 18);
        assert_eq!(last["dropped_agent_steps"]["stale"], 8);
        assert_eq!(last["agent_steps"], 10);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
