//! `<run-dir>/progress.jsonl`: one JSON object per line, appended every
//! `run.progress_interval_s` and once when training stops, so a finished run can be plotted
//! offline (`python -m junction.analysis report`) without Prometheus.
//!
//! | key | meaning |
//! |---|---|
//! | `elapsed_s` | wall-clock seconds since this learner process started (restarts at 0 on `--resume`) |
//! | `unix_s` | wall-clock time of the line |
//! | `algorithm`, `scenario`, `seed` | `learner.algo`, `scenario.name`, `run.seed` |
//! | `version`, `updates` | policy version and updates so far (restored on resume) |
//! | `agent_steps`, `env_steps`, `samples_trained` | agent-steps and scene steps consumed, samples trained (restored on resume) |
//! | `agent_steps_per_s` | consumption rate since the previous line |
//! | `episodes_total`, `collisions_total`, `sim_seconds_total` | agent episodes, collisions (agents' and human drivers') and simulated scene seconds received by this process |
//! | `lcf` | after the first update of this process: the LCF angle φ of the newest batch, `mean_deg`, `std_deg` and `phi_deg_by_neighbours` (mean φ per neighbour-count bucket "0", "1-2", "3-5", "6+"; a bucket keeps its last value while batches have no agent in it) |
//! | `update_seconds_total` | seconds this process spent updating; its growth over `elapsed_s` is the learner's utilisation |
//! | `accepted_agent_steps`, `dropped_agent_steps` | agent-steps this process accepted, and those it dropped by reason (`stale`, `shutdown`, `update_failed`): the rest were trained on |
//! | `window.*` | the sliding window of the last `run.stats_window_episodes` episodes: `episodes`, `success_rate`, `crash_rate`, `out_of_road_rate`, `timeout_rate`, `mean_reward`, `max_reward`, `mean_length`, `max_length`, `mean_accel`, `mean_max_accel` (m/s²), `collisions_per_s` and the `sim_seconds` behind it |
//! | `scene_window.*` | MetaDrive's (CoPO's) rates over the last `run.stats_window_scene_episodes` scene episodes: per scene episode the share of its agents with that outcome, averaged: `scene_episodes`, `success_rate`, `crash_rate`, `out_of_road_rate`, `timeout_rate`, `mean_agents` (agent episodes per scene episode), `mean_steps` |
//! | `scene_totals.*` | the sums behind MetaDrive's rates over every scene episode this process received: `scene_episodes`, and per outcome (`success`, `crash`, `out_of_road`, `timeout`) the sum of its per-scene-episode shares. The rate over the scene episodes between two lines of one process is the difference of their sums over the difference of their counts: CoPO's smoothing over 100 environment episodes, or any other, afterwards |
//! | `update` | after the first update of this process, the newest update's diagnostics: `policy_loss`, `value_loss`, `entropy`, `approx_kl`, `clip_fraction`, `explained_variance`, `grad_norm` (before clipping), `learning_rate`, `kl` and `kl_coef` (the adaptive KL penalty's, 0 without one), the policy lag of the fragments it trained on (`lag_mean`, `lag_max`, versions), `lagrange_multiplier` (PPO-Lagrangian's λ, 0 when off), and DQN's `epsilon` and `q_mean` (0 for PPO; DQN's TD loss is `value_loss`) |
//!
//! Fields are only ever added: every reader takes a missing field as its default. The same
//! values go to the run's TensorBoard event file (`super::tensorboard`).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::stats::{SceneTotals, SceneWindowSummary, WindowSummary};

/// One line of `progress.jsonl` (written by the trainer, read by `python -m junction.analysis`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ProgressLine {
    pub elapsed_s: f64,
    pub unix_s: f64,
    pub algorithm: String,
    pub scenario: String,
    pub seed: Option<u64>,
    pub version: u64,
    pub updates: u64,
    pub agent_steps: u64,
    pub env_steps: u64,
    pub samples_trained: u64,
    pub agent_steps_per_s: f64,
    pub episodes_total: u64,
    pub collisions_total: u64,
    pub sim_seconds_total: f64,
    /// Seconds this process spent in updates (utilisation = its growth / the clock's).
    pub update_seconds_total: f64,
    /// This process's ingest accounting: every accepted agent-step is trained on or dropped
    /// for a reason (in the final line, after the shutdown count).
    pub accepted_agent_steps: u64,
    pub dropped_agent_steps: BTreeMap<String, u64>,
    pub window: WindowSummary,
    pub scene_window: SceneWindowSummary,
    pub scene_totals: SceneTotals,
    pub lcf: Option<LcfProgress>,
    pub update: Option<UpdateProgress>,
}

/// Diagnostics of the newest update (means over its minibatches).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct UpdateProgress {
    pub policy_loss: f64,
    pub value_loss: f64,
    pub entropy: f64,
    pub approx_kl: f64,
    pub clip_fraction: f64,
    pub explained_variance: f64,
    pub grad_norm: f64,
    pub learning_rate: f64,
    /// Mean KL(π_start ‖ π) of the update and the KL penalty's coefficient after it (0
    /// without a penalty).
    pub kl: f64,
    pub kl_coef: f64,
    /// Policy versions between the behaviour policies of the fragments trained on and the
    /// policy the update started from.
    pub lag_mean: f64,
    pub lag_max: u64,
    /// Wall-clock seconds the update took.
    pub seconds: f64,
    /// PPO-Lagrangian's multiplier λ after the update (0 when `[safety]` is off).
    pub lagrange_multiplier: f64,
    /// DQN: the exploration rate broadcast after the update and the mean Q(s, a) of its
    /// samples (0 for PPO).
    pub epsilon: f64,
    pub q_mean: f64,
}

/// The learned (or fixed) LCF angle of the newest update, degrees.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LcfProgress {
    pub mean_deg: f64,
    pub std_deg: f64,
    pub phi_deg_by_neighbours: BTreeMap<String, f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_of_older_learners_parse_with_defaults() {
        let old = r#"{"elapsed_s":10.5,"unix_s":1.0,"version":3,"updates":3,"agent_steps":900,
            "env_steps":300,"samples_trained":4500,"agent_steps_per_s":90.0,
            "scenario":"intersection","window":{"episodes":2,"success_rate":0.5}}"#;
        let line: ProgressLine = serde_json::from_str(old).unwrap();
        assert_eq!((line.agent_steps, line.updates), (900, 3));
        assert_eq!((line.window.episodes, line.window.success_rate), (2, 0.5));
        assert_eq!((line.algorithm.as_str(), line.seed), ("", None));
    }
}
