//! Driving metrics over a sliding window of finished episodes (paper §4.2, CoPO's rates).

use std::collections::VecDeque;

use junction_common::fragment::{EpisodeStats, Outcome};

pub struct EpisodeWindow {
    capacity: usize,
    episodes: VecDeque<EpisodeStats>,
}

/// Aggregates of the episodes in the window; rates are shares of episodes.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
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
}

impl EpisodeWindow {
    pub fn new(capacity: usize) -> Self {
        EpisodeWindow {
            capacity: capacity.max(1),
            episodes: VecDeque::with_capacity(capacity),
        }
    }

    pub fn push(&mut self, episode: EpisodeStats) {
        if self.episodes.len() == self.capacity {
            self.episodes.pop_front();
        }
        self.episodes.push_back(episode);
    }

    pub fn summary(&self) -> WindowSummary {
        let n = self.episodes.len();
        if n == 0 {
            return WindowSummary::default();
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
        w.push(episode(Outcome::Crash, -100.0, 1000)); // falls out of the window
        w.push(episode(Outcome::Success, 10.0, 50));
        w.push(episode(Outcome::Success, 20.0, 70));
        w.push(episode(Outcome::Crash, -5.0, 10));
        w.push(episode(Outcome::OutOfRoad, 3.0, 30));
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
        assert_eq!(EpisodeWindow::new(3).summary(), WindowSummary::default());
    }
}
