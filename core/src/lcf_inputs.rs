//! What an actor computes for the local-coordination methods, free of the wire and of
//! libtorch so the simulator can use it: the neighbourhood features S_N(i,t) the paper's
//! dynamic LCF maps to an angle φ (the simulator computes them for every agent and step and
//! ships them in each `RolloutFragment`; this module owns their layout), and the encoding of
//! CoPO's LCF angle as an observation value.
//!
//! | index | feature | normalisation (every value in [0, 1]) |
//! |---|---|---|
//! | 0 | neighbours within d_n | count / 20, capped at 1 |
//! | 1 | mean distance to them | d / d_n (1 when alone) |
//! | 2 | distance to the nearest | d / d_n (1 when alone) |
//! | 3 | mean relative speed ‖v_j − v_i‖ | / (2 · 80 km/h) |
//! | 4 | mean closing speed −d‖p_j − p_i‖/dt (+ = approaching) | (c / (2 · 80 km/h) + 1) / 2 (½ when alone) |

/// Values per agent and step.
pub const FEATURES: usize = 5;
/// Neighbour count at which feature 0 saturates.
const COUNT_SCALE: f32 = 20.0;
/// Relative speeds are at most twice the top speed (80 km/h).
const SPEED_SCALE: f32 = 2.0 * 80.0 / 3.6;

/// The largest |φ|, degrees (CoPO's range: fully cooperative to fully competitive).
pub const MAX_PHI_DEG: f32 = 90.0;

/// The observation value of an LCF angle: (φ/90° + 1)/2, in [0, 1] like every other value
/// (CoPO's encoding).
pub fn phi_observation(phi_deg: f32) -> f32 {
    (phi_deg / MAX_PHI_DEG + 1.0) / 2.0
}

/// The angle, degrees, an observation value [`phi_observation`] encodes.
pub fn phi_from_observation(value: f32) -> f32 {
    (2.0 * value - 1.0) * MAX_PHI_DEG
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

    #[test]
    fn the_phi_column_maps_the_angle_range_onto_the_unit_interval_and_back() {
        assert_eq!(phi_observation(-90.0), 0.0);
        assert_eq!(phi_observation(0.0), 0.5);
        assert_eq!(phi_observation(90.0), 1.0);
        assert_eq!(phi_from_observation(phi_observation(45.0)), 45.0);
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
