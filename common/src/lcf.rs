//! Local coordination (paper §3.2, CoPO): the neighbourhood reward r_N, the coordinated reward
//! r_C = α·cos φ·r_i + β·sin φ·r_N, and the neighbourhood features S_N(i,t) that the paper's
//! dynamic LCF maps to an angle φ. The simulator computes S_N for every agent and step and
//! ships it in each `RolloutFragment`; this module owns its layout.
//!
//! | index | feature | normalisation (every value in [0, 1]) |
//! |---|---|---|
//! | 0 | neighbours within d_n | count / 20, capped at 1 |
//! | 1 | mean distance to them | d / d_n (1 when alone) |
//! | 2 | distance to the nearest | d / d_n (1 when alone) |
//! | 3 | mean relative speed ‖v_j − v_i‖ | / (2 · 80 km/h) |
//! | 4 | mean closing speed −d‖p_j − p_i‖/dt (+ = approaching) | (c / (2 · 80 km/h) + 1) / 2 (½ when alone) |

use std::borrow::Cow;

use crate::fragment::RolloutFragment;

/// Values per agent and step.
pub const FEATURES: usize = 5;
/// Neighbour count at which feature 0 saturates.
const COUNT_SCALE: f32 = 20.0;
/// Relative speeds are at most twice the top speed (80 km/h).
const SPEED_SCALE: f32 = 2.0 * 80.0 / 3.6;

/// r_C = α·cos φ·r_i + β·sin φ·r_N: φ = 0 is selfish (IPPO), φ = 90° fully cooperative.
pub fn coordinated_reward(
    own: f32,
    neighbourhood: f32,
    phi_rad: f32,
    alpha: f32,
    beta: f32,
) -> f32 {
    alpha * phi_rad.cos() * own + beta * phi_rad.sin() * neighbourhood
}

/// The reward each cell of `fragment` trains on under a fixed LCF angle (radians): the
/// fragment's own rewards when the coordination changes nothing (φ = 0, α = 1).
pub fn coordinated_rewards(
    fragment: &RolloutFragment,
    phi_rad: f32,
    alpha: f32,
    beta: f32,
) -> Cow<'_, [f32]> {
    if phi_rad == 0.0 && alpha == 1.0 {
        return Cow::Borrowed(&fragment.rewards);
    }
    let neighbourhood = neighbourhood_rewards(fragment);
    fragment
        .rewards
        .iter()
        .zip(neighbourhood)
        .map(|(&own, n)| coordinated_reward(own, n, phi_rad, alpha, beta))
        .collect()
}

/// r_N per (step, slot) of a fragment: the mean reward of the neighbours at that step (0 when
/// alone or for an empty cell).
pub fn neighbourhood_rewards(fragment: &RolloutFragment) -> Vec<f32> {
    let mut out = vec![0.0; fragment.steps * fragment.agents];
    for t in 0..fragment.steps {
        for slot in 0..fragment.agents {
            let neighbours = fragment.neighbours(t, slot);
            if fragment.alive[fragment.index(t, slot)] && !neighbours.is_empty() {
                let sum: f32 = neighbours
                    .iter()
                    .map(|&j| fragment.rewards[fragment.index(t, j as usize)])
                    .sum();
                out[fragment.index(t, slot)] = sum / neighbours.len() as f32;
            }
        }
    }
    out
}

/// A car's position and velocity, metres and m/s in the world frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    pub position: [f32; 2],
    pub velocity: [f32; 2],
}

/// S_N of the agent `ego` given its neighbours within `radius` (all others, already filtered).
pub fn neighbourhood_features(
    ego: Motion,
    neighbours: impl Iterator<Item = Motion>,
    radius: f32,
) -> [f32; FEATURES] {
    let (mut count, mut distance_sum, mut nearest) = (0usize, 0.0f32, f32::INFINITY);
    let (mut relative_speed_sum, mut closing_sum) = (0.0f32, 0.0f32);
    for other in neighbours {
        let dp = [
            other.position[0] - ego.position[0],
            other.position[1] - ego.position[1],
        ];
        let dv = [
            other.velocity[0] - ego.velocity[0],
            other.velocity[1] - ego.velocity[1],
        ];
        let distance = dp[0].hypot(dp[1]);
        count += 1;
        distance_sum += distance;
        nearest = nearest.min(distance);
        relative_speed_sum += dv[0].hypot(dv[1]);
        if distance > 1e-6 {
            closing_sum -= (dp[0] * dv[0] + dp[1] * dv[1]) / distance;
        }
    }
    if count == 0 {
        return [0.0, 1.0, 1.0, 0.0, 0.5];
    }
    let n = count as f32;
    let scale = radius.max(1e-6);
    let unit = |x: f32| x.clamp(0.0, 1.0);
    [
        unit(n / COUNT_SCALE),
        unit(distance_sum / n / scale),
        unit(nearest / scale),
        unit(relative_speed_sum / n / SPEED_SCALE),
        unit((closing_sum / n / SPEED_SCALE + 1.0) / 2.0),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::FRAC_PI_2;

    #[test]
    fn coordinated_reward_spans_selfish_to_cooperative() {
        // φ = 0: the agent's own reward (IPPO); φ = 90°: only the neighbourhood's.
        assert_eq!(coordinated_reward(2.0, 7.0, 0.0, 1.0, 1.0), 2.0);
        assert!((coordinated_reward(2.0, 7.0, FRAC_PI_2, 1.0, 1.0) - 7.0).abs() < 1e-5);
        // φ = 60°, α = 1, β = 0.5: 2·½ + 0.5·7·(√3/2) = 1 + 3.0311
        let r = coordinated_reward(2.0, 7.0, FRAC_PI_2 * 2.0 / 3.0, 1.0, 0.5);
        assert!((r - 4.031_089).abs() < 1e-4, "{r}");
        // Alone (r_N = 0) at 90°: nothing to gain.
        assert!(coordinated_reward(2.0, 0.0, FRAC_PI_2, 1.0, 1.0).abs() < 1e-6);
    }

    #[test]
    fn neighbourhood_reward_is_the_mean_over_the_neighbours_at_that_step() {
        // 2 steps × 3 slots; step 0: 0 sees {1, 2}, 1 sees {0}, 2 alone; step 1: slot 2 empty,
        // 0 sees {1}.
        let fragment = RolloutFragment {
            steps: 2,
            agents: 3,
            rewards: vec![1.0, 2.0, 6.0, 3.0, 5.0, 0.0],
            alive: vec![true, true, true, true, true, false],
            dones: vec![false; 6],
            neighbour_offsets: vec![0, 2, 3, 3, 4, 4, 4],
            neighbour_ids: vec![1, 2, 0, 1],
            ..RolloutFragment::default()
        };
        assert_eq!(
            neighbourhood_rewards(&fragment),
            vec![4.0, 1.0, 0.0, 5.0, 0.0, 0.0]
        );
        // φ = 0, α = 1 trains on the own rewards untouched; φ = 90° on the neighbourhood's.
        assert!(matches!(
            coordinated_rewards(&fragment, 0.0, 1.0, 1.0),
            Cow::Borrowed(r) if r == fragment.rewards.as_slice()
        ));
        let cooperative = coordinated_rewards(&fragment, FRAC_PI_2, 1.0, 1.0);
        let expected = [4.0, 1.0, 0.0, 5.0, 0.0, 0.0];
        for (got, want) in cooperative.iter().zip(expected) {
            assert!((got - want).abs() < 1e-5, "{cooperative:?}");
        }
    }

    fn car(x: f32, y: f32, vx: f32, vy: f32) -> Motion {
        Motion {
            position: [x, y],
            velocity: [vx, vy],
        }
    }

    #[test]
    fn alone_is_far_and_still() {
        let f = neighbourhood_features(car(0.0, 0.0, 5.0, 0.0), std::iter::empty(), 40.0);
        assert_eq!(f, [0.0, 1.0, 1.0, 0.0, 0.5]);
    }

    #[test]
    fn two_neighbours_by_hand() {
        let ego = car(0.0, 0.0, 10.0, 0.0);
        // Ahead at 10 m and stopped: closing at 10 m/s, relative speed 10.
        // Left at 30 m driving the same way: not closing, relative speed 0.
        let others = [car(10.0, 0.0, 0.0, 0.0), car(0.0, 30.0, 10.0, 0.0)];
        let f = neighbourhood_features(ego, others.into_iter(), 40.0);
        let expected = [
            2.0 / 20.0,
            20.0 / 40.0,
            10.0 / 40.0,
            5.0 / SPEED_SCALE,
            (5.0 / SPEED_SCALE + 1.0) / 2.0,
        ];
        for (got, want) in f.iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{f:?} vs {expected:?}");
        }
    }

    #[test]
    fn a_crowd_saturates_and_receding_cars_read_below_a_half() {
        let ego = car(0.0, 0.0, 0.0, 0.0);
        let crowd = (0..30).map(|k| car(5.0 + k as f32, 0.0, 8.0, 0.0));
        let f = neighbourhood_features(ego, crowd, 40.0);
        assert_eq!(f[0], 1.0);
        assert!(f[4] < 0.5, "cars driving away are not closing: {f:?}");
    }
}
