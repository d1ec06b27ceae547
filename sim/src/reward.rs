//! Per-step reward and cost of one agent (paper §3.4 and §3.5); formulas in docs/SIMULATOR.md.

use junction_core::config::{CostConfig, RewardConfig, RewardKind};
use junction_core::episode::Outcome;

use super::vehicle::MAX_SPEED;

/// What happened to one agent during one decision step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepFacts {
    /// Progress along the route since the last step, metres (R_disp).
    pub progress: f32,
    /// Speed after the step, m/s.
    pub speed: f32,
    /// Offset from the lane centre (+ left) and the lane's width, metres.
    pub lateral: f32,
    pub lane_width: f32,
    /// Heading minus the lane's heading, radians.
    pub heading_error: f32,
    /// Change of the steering action over the step, in action units ([-2, 2]).
    pub steer_change: f32,
    /// The car crashed this step.
    pub collided: bool,
    /// Engine work over the step, kJ.
    pub energy_kj: f32,
    /// How the agent's episode ended this step, if it did.
    pub outcome: Option<Outcome>,
}

impl StepFacts {
    fn termination(&self, reward: &RewardConfig) -> f32 {
        match self.outcome {
            Some(Outcome::Success) => reward.success,
            Some(Outcome::Crash) => reward.crash,
            Some(Outcome::OutOfRoad) => reward.out_of_road,
            Some(Outcome::Timeout) | None => 0.0,
        }
    }
}

pub fn reward(config: &RewardConfig, f: &StepFacts) -> f32 {
    let speed_share = f.speed / MAX_SPEED;
    match config.kind {
        RewardKind::I => match f.outcome {
            Some(Outcome::Success | Outcome::Crash | Outcome::OutOfRoad) => f.termination(config),
            Some(Outcome::Timeout) | None => {
                config.displacement * f.progress + config.speed * speed_share
            }
        },
        RewardKind::II => {
            let lateral = (1.0 - f.lateral.abs() / (f.lane_width / 2.0)).clamp(-1.0, 1.0);
            let heading = f.heading_error.cos();
            let steering = -f.steer_change.abs() * speed_share;
            let collision = if f.collided { 1.0 } else { 0.0 };
            config.displacement * f.progress
                + config.lateral * lateral
                + config.heading * heading
                + config.steering * steering
                - config.collision * collision
                + f.termination(config)
        }
    }
}

pub fn cost(config: &CostConfig, f: &StepFacts) -> f32 {
    let collision = if f.collided { 1.0 } else { 0.0 };
    config.collision * collision + config.energy * f.energy_kj
}

#[cfg(test)]
mod tests {
    use super::*;
    use junction_core::config::RunConfig;

    fn facts() -> StepFacts {
        StepFacts {
            progress: 1.5,
            speed: MAX_SPEED / 2.0,
            lateral: 0.875,
            lane_width: 3.5,
            heading_error: std::f32::consts::FRAC_PI_3,
            steer_change: -0.4,
            collided: false,
            energy_kj: 2.0,
            outcome: None,
        }
    }

    fn defaults() -> (RewardConfig, CostConfig) {
        let c = RunConfig::default().scenario;
        (c.reward, c.cost)
    }

    fn close(a: f32, b: f32) -> bool {
        (a - b).abs() < 1e-5
    }

    #[test]
    fn reward_one_is_progress_and_speed_replaced_at_the_end() {
        let (r, _) = defaults();
        // 1.0 · 1.5 m + 0.1 · ½
        assert!(close(reward(&r, &facts()), 1.55));
        let timeout = StepFacts {
            outcome: Some(Outcome::Timeout),
            ..facts()
        };
        assert!(
            close(reward(&r, &timeout), 1.55),
            "a timeout keeps the step reward"
        );
        let crash = StepFacts {
            outcome: Some(Outcome::Crash),
            collided: true,
            ..facts()
        };
        assert_eq!(reward(&r, &crash), -10.0);
        let arrived = StepFacts {
            outcome: Some(Outcome::Success),
            ..facts()
        };
        assert_eq!(reward(&r, &arrived), 10.0);
    }

    #[test]
    fn reward_two_sums_every_term_with_the_terminal_reward() {
        let (mut r, _) = defaults();
        r.kind = RewardKind::II;
        // lateral: 1 − 0.875/1.75 = 0.5; heading: cos 60° = 0.5; steering: −0.4 · ½ = −0.2
        // 1.5 + 0.1·0.5 + 0.1·0.5 + 0.1·(−0.2) = 1.58
        assert!(
            close(reward(&r, &facts()), 1.58),
            "{}",
            reward(&r, &facts())
        );
        let crash = StepFacts {
            outcome: Some(Outcome::Crash),
            collided: true,
            ..facts()
        };
        // 1.58 − 1.0 (P_collision) − 10 (termination)
        assert!(close(reward(&r, &crash), 1.58 - 11.0));
        let off_lane = StepFacts {
            lateral: -7.0,
            ..facts()
        };
        // lateral clipped to −1: 1.5 − 0.1 + 0.05 − 0.02
        assert!(close(reward(&r, &off_lane), 1.43));
    }

    #[test]
    fn cost_is_collision_plus_energy() {
        let (_, c) = defaults();
        assert!(close(cost(&c, &facts()), 0.02));
        let crash = StepFacts {
            collided: true,
            ..facts()
        };
        assert!(close(cost(&c, &crash), 1.02));
    }
}
