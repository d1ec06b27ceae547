//! Driving metrics over a sliding window of finished episodes (paper §4.2, CoPO's rates).

use std::collections::VecDeque;

use junction_core::episode::{EpisodeStats, Outcome, SceneEpisodeStats};

/// The newest `capacity` agent episodes, and the fragments that delivered them (for the
/// collision rate, which needs the simulated time those episodes came from).
pub struct EpisodeWindow {
    capacity: usize,
    episodes: VecDeque<EpisodeStats>,
    fragments: VecDeque<FragmentTally>,
}

/// What one fragment contributed: its agent episodes, every vehicle's collisions (agents and
/// human drivers, as in `junction_learner_collisions_total`) and its scene time.
#[derive(Debug, Clone, Copy, PartialEq)]
struct FragmentTally {
    episodes: usize,
    collisions: u64,
    sim_seconds: f64,
}

/// Aggregates of the episodes in the window; rates are shares of episodes. Serialised as the
/// `window` object of every `progress.jsonl` line: add fields, never rename them (readers
/// such as `python -m junction.analysis` and the learning tests read them by name).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct WindowSummary {
    pub episodes: usize,
    pub success_rate: f64,
    pub crash_rate: f64,
    pub out_of_road_rate: f64,
    pub timeout_rate: f64,
    pub mean_reward: f64,
    pub max_reward: f64,
    pub mean_length: f64,
    pub max_length: u32,
    /// Mean of the episodes' mean |longitudinal acceleration|, m/s².
    pub mean_accel: f64,
    /// Mean of the episodes' largest |longitudinal acceleration|, m/s² (paper §4.2).
    pub mean_max_accel: f64,
    /// Collisions per simulated second of scene time (paper §4.2) over the fragments that
    /// delivered the window's episodes (and any newer ones); 0 before any time is simulated.
    pub collisions_per_s: f64,
    /// Simulated seconds behind `collisions_per_s`.
    pub sim_seconds: f64,
}

impl EpisodeWindow {
    pub fn new(capacity: usize) -> Self {
        EpisodeWindow {
            capacity: capacity.max(1),
            episodes: VecDeque::with_capacity(capacity),
            fragments: VecDeque::new(),
        }
    }

    /// Adds one received fragment: its agent episodes, the collisions of all its finished
    /// episodes (agents' and human drivers') and its simulated seconds.
    pub fn record(&mut self, episodes: &[EpisodeStats], collisions: u64, sim_seconds: f64) {
        for episode in episodes {
            if self.episodes.len() == self.capacity {
                self.episodes.pop_front();
            }
            self.episodes.push_back(*episode);
        }
        self.fragments.push_back(FragmentTally {
            episodes: episodes.len(),
            collisions,
            sim_seconds,
        });
        // Drop the oldest fragment while the newer ones still hold every windowed episode.
        let mut newer_episodes: usize = self.fragments.iter().map(|f| f.episodes).sum();
        while let Some(oldest) = self.fragments.front() {
            newer_episodes -= oldest.episodes;
            if self.fragments.len() == 1 || newer_episodes < self.episodes.len() {
                break;
            }
            self.fragments.pop_front();
        }
    }

    pub fn summary(&self) -> WindowSummary {
        let sim_seconds: f64 = self.fragments.iter().map(|f| f.sim_seconds).sum();
        let collisions: u64 = self.fragments.iter().map(|f| f.collisions).sum();
        let collisions_per_s = if sim_seconds > 0.0 {
            collisions as f64 / sim_seconds
        } else {
            0.0
        };
        let n = self.episodes.len();
        if n == 0 {
            return WindowSummary {
                collisions_per_s,
                sim_seconds,
                ..WindowSummary::default()
            };
        }
        let share = |outcome: Outcome| {
            self.episodes
                .iter()
                .filter(|e| e.outcome == outcome)
                .count() as f64
                / n as f64
        };
        let mean = |field: fn(&EpisodeStats) -> f32| {
            self.episodes
                .iter()
                .map(|e| f64::from(field(e)))
                .sum::<f64>()
                / n as f64
        };
        WindowSummary {
            episodes: n,
            success_rate: share(Outcome::Success),
            crash_rate: share(Outcome::Crash),
            out_of_road_rate: share(Outcome::OutOfRoad),
            timeout_rate: share(Outcome::Timeout),
            mean_reward: mean(|e| e.total_reward),
            max_reward: self
                .episodes
                .iter()
                .map(|e| f64::from(e.total_reward))
                .fold(f64::NEG_INFINITY, f64::max),
            mean_length: mean(|e| e.length as f32),
            max_length: self.episodes.iter().map(|e| e.length).max().unwrap_or(0),
            mean_accel: mean(|e| e.mean_abs_accel),
            mean_max_accel: mean(|e| e.max_abs_accel),
            collisions_per_s,
            sim_seconds,
        }
    }
}

/// The newest `capacity` scene episodes: MetaDrive's (and CoPO's) success rate is the mean,
/// over environment episodes, of the share of the episode's agents that arrived.
pub struct SceneEpisodeWindow {
    capacity: usize,
    episodes: VecDeque<SceneEpisodeStats>,
    totals: SceneTotals,
}

/// Sums over every scene episode this process received, so that a reader can take MetaDrive's
/// rates over any window afterwards: CoPO smoothed over 100 environment episodes, the live
/// window is shorter, and a short window's noise alone moves "the lowest after the best". The
/// rate over the scene episodes between two lines is the difference of their sums over the
/// difference of their counts. Serialised as the `scene_totals` object of `progress.jsonl`.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct SceneTotals {
    pub scene_episodes: u64,
    /// Per outcome, the sum over scene episodes of its share of the episode's agents.
    pub success: f64,
    pub crash: f64,
    pub out_of_road: f64,
    pub timeout: f64,
}

/// Aggregates of the scene episodes in the window: each rate is the mean over scene episodes
/// of that outcome's share of the episode's agents (MetaDrive's definition). Serialised as
/// the `scene_window` object of `progress.jsonl` lines: add fields, never rename them.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct SceneWindowSummary {
    pub scene_episodes: usize,
    pub success_rate: f64,
    pub crash_rate: f64,
    pub out_of_road_rate: f64,
    pub timeout_rate: f64,
    /// Mean agent episodes per scene episode.
    pub mean_agents: f64,
    /// Mean scene steps per scene episode.
    pub mean_steps: f64,
}

impl SceneEpisodeWindow {
    pub fn new(capacity: usize) -> Self {
        SceneEpisodeWindow {
            capacity: capacity.max(1),
            episodes: VecDeque::with_capacity(capacity),
            totals: SceneTotals::default(),
        }
    }

    pub fn totals(&self) -> &SceneTotals {
        &self.totals
    }

    pub fn record(&mut self, episodes: &[SceneEpisodeStats]) {
        // Scene episodes without agents say nothing about the policy.
        for episode in episodes.iter().filter(|e| e.agents() > 0) {
            let totals = &mut self.totals;
            totals.scene_episodes += 1;
            totals.success += episode.share(Outcome::Success);
            totals.crash += episode.share(Outcome::Crash);
            totals.out_of_road += episode.share(Outcome::OutOfRoad);
            totals.timeout += episode.share(Outcome::Timeout);
            if self.episodes.len() == self.capacity {
                self.episodes.pop_front();
            }
            self.episodes.push_back(*episode);
        }
    }

    pub fn summary(&self) -> SceneWindowSummary {
        let n = self.episodes.len();
        if n == 0 {
            return SceneWindowSummary::default();
        }
        let mean = |f: &dyn Fn(&SceneEpisodeStats) -> f64| {
            self.episodes.iter().map(f).sum::<f64>() / n as f64
        };
        SceneWindowSummary {
            scene_episodes: n,
            success_rate: mean(&|e| e.share(Outcome::Success)),
            crash_rate: mean(&|e| e.share(Outcome::Crash)),
            out_of_road_rate: mean(&|e| e.share(Outcome::OutOfRoad)),
            timeout_rate: mean(&|e| e.share(Outcome::Timeout)),
            mean_agents: mean(&|e| e.agents() as f64),
            mean_steps: mean(&|e| f64::from(e.steps)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episode(outcome: Outcome, reward: f32, length: u32) -> EpisodeStats {
        EpisodeStats {
            outcome,
            length,
            total_reward: reward,
            mean_abs_accel: length as f32 / 100.0,
            max_abs_accel: length as f32 / 10.0,
            collisions: 0,
            energy_kj: 0.0,
            total_cost: 0.0,
        }
    }

    #[test]
    fn rates_and_means_over_the_newest_episodes_only() {
        let mut w = EpisodeWindow::new(4);
        let crash = episode(Outcome::Crash, -100.0, 1000); // falls out of the window
        w.record(&[crash, episode(Outcome::Success, 10.0, 50)], 1, 20.0);
        w.record(&[episode(Outcome::Success, 20.0, 70)], 0, 20.0);
        w.record(
            &[
                episode(Outcome::Crash, -5.0, 10),
                episode(Outcome::OutOfRoad, 3.0, 30),
            ],
            2,
            20.0,
        );
        let s = w.summary();
        assert_eq!(s.episodes, 4);
        assert_eq!(
            (
                s.success_rate,
                s.crash_rate,
                s.out_of_road_rate,
                s.timeout_rate
            ),
            (0.5, 0.25, 0.25, 0.0)
        );
        assert_eq!((s.mean_reward, s.max_reward), (7.0, 20.0));
        assert_eq!((s.mean_length, s.max_length), (40.0, 70));
        assert!((s.mean_accel - 0.4).abs() < 1e-6, "{}", s.mean_accel);
        assert!(
            (s.mean_max_accel - 4.0).abs() < 1e-6,
            "{}",
            s.mean_max_accel
        );
        // The first fragment still delivers a windowed episode: all three count.
        assert_eq!((s.sim_seconds, s.collisions_per_s), (60.0, 3.0 / 60.0));
        assert_eq!(EpisodeWindow::new(3).summary(), WindowSummary::default());
    }

    #[test]
    fn collision_rate_covers_the_fragments_of_the_windowed_episodes() {
        let mut w = EpisodeWindow::new(2);
        let success = episode(Outcome::Success, 1.0, 10);
        w.record(&[success, success], 4, 10.0);
        // No episodes, but simulated time: kept, newer than the windowed episodes.
        w.record(&[], 1, 5.0);
        let s = w.summary();
        assert_eq!(
            (s.episodes, s.sim_seconds, s.collisions_per_s),
            (2, 15.0, 5.0 / 15.0)
        );
        // Two newer episodes push both older fragments out.
        w.record(&[success, success], 0, 10.0);
        let s = w.summary();
        assert_eq!((s.sim_seconds, s.collisions_per_s), (10.0, 0.0));
        // One newer episode: the previous fragment still holds one of the window's two.
        w.record(&[success], 3, 10.0);
        assert_eq!(w.summary().sim_seconds, 20.0);
        let empty = EpisodeWindow::new(2);
        assert_eq!(empty.summary().collisions_per_s, 0.0);
    }

    #[test]
    fn scene_rates_are_means_of_per_episode_shares_over_the_newest_episodes() {
        let scene = |successes, crashes, timeouts| SceneEpisodeStats {
            steps: 1000,
            successes,
            crashes,
            out_of_road: 0,
            timeouts,
        };
        let mut w = SceneEpisodeWindow::new(2);
        w.record(&[scene(0, 10, 0)]); // pushed out by the two below
        w.record(&[scene(3, 1, 0), scene(0, 0, 0), scene(10, 30, 60)]);
        let s = w.summary();
        assert_eq!(s.scene_episodes, 2, "the empty episode is not counted");
        // (3/4 + 10/100) / 2: a mean of shares, not 13/104 pooled.
        assert!((s.success_rate - 0.425).abs() < 1e-12, "{}", s.success_rate);
        assert!((s.crash_rate - 0.275).abs() < 1e-12);
        assert!((s.timeout_rate - 0.3).abs() < 1e-12);
        assert_eq!((s.mean_agents, s.mean_steps), (52.0, 1000.0));
        // The totals keep the episode the window dropped: 0/10 + 3/4 + 10/100 successes.
        let t = w.totals();
        assert_eq!(t.scene_episodes, 3);
        assert!((t.success - 0.85).abs() < 1e-12, "{}", t.success);
        assert!((t.crash - 1.55).abs() < 1e-12, "{}", t.crash);
        assert!((t.timeout - 0.6).abs() < 1e-12, "{}", t.timeout);
        assert_eq!(t.out_of_road, 0.0);
        assert_eq!(
            SceneEpisodeWindow::new(5).summary(),
            SceneWindowSummary::default()
        );
    }

    #[test]
    fn summaries_without_the_newer_fields_still_parse() {
        let old = r#"{"episodes":3,"success_rate":0.5,"crash_rate":0.5,"out_of_road_rate":0,
            "timeout_rate":0,"mean_reward":1,"max_reward":2,"mean_length":3,"max_length":4,
            "mean_accel":0.1,"mean_max_accel":0.2}"#;
        let s: WindowSummary = serde_json::from_str(old).unwrap();
        assert_eq!(
            (s.episodes, s.success_rate, s.collisions_per_s),
            (3, 0.5, 0.0)
        );
    }
}
