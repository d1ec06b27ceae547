//! The per-agent observation: MetaDrive's multi-agent layout, every value in [0, 1]. This
//! module owns the layout; `docs/OBSERVATION.md` documents it and a test pins it.
//!
//! | index | value | normalisation |
//! |---|---|---|
//! | 0 | distance to the left edge of the drivable road (same direction) | d / 18 m |
//! | 1 | distance to the right edge | d / 18 m |
//! | 2 | heading error to the current lane, Δθ ∈ (−π, π] | (Δθ/π + 1) / 2 |
//! | 3 | speed | (km/h + 1) / 81 |
//! | 4 | steering: where the wheel points (fraction of 40°, + = right; lags the action with `vehicle.steering_time_constant`) | (δ + 1) / 2 |
//! | 5, 6 | last action: steering, throttle/brake | (a + 1) / 2 |
//! | 7 | yaw rate ω (rad/s, + = counter-clockwise) | (ω / (π/2) + 1) / 2 |
//! | 8 | lateral offset from the lane centre (+ = left) | (2·lat/lane width + 1) / 2 |
//! | 9–13, 14–18 | next two checkpoints (ends of the remaining route lanes): ego-frame x, y of the vector to it, each capped at ±50 m; bend radius of the lane ending there; bend direction; bend angle | (v/50 + 1)/2; radius/100 (0 straight); 1 left, 0 right, 0.5 straight; sweep/π |
//! | 19… | lidar: `lidar_beams` beams, beam 0 straight ahead, counter-clockwise; distance to the nearest other vehicle | d / range (1 = nothing) |
//!
//! Everything is clipped to [0, 1].

use std::f32::consts::PI;

use parry2d::math::Vec2;

use junction_core::spec::{EGO_DIM, LIDAR_OFFSET, NAV_PER_CHECKPOINT};

use super::lane::Lane;
use super::network::Route;
use super::vehicle::{Kinematics, MAX_SPEED};

const EDGE_SCALE: f32 = 18.0;
const CHECKPOINT_SCALE: f32 = 50.0;
const RADIUS_SCALE: f32 = 100.0;
const YAW_RATE_SCALE: f32 = PI / 2.0;

/// Where an agent is on its route.
pub struct RoutePosition<'a> {
    pub route: &'a Route,
    /// Index into `route.lanes` of the current lane.
    pub lane_index: usize,
    /// Position on the current lane: longitudinal and lateral (+ left).
    pub s: f32,
    pub lateral: f32,
}

fn unit(x: f32) -> f32 {
    x.clamp(0.0, 1.0)
}

fn signed_unit(x: f32) -> f32 {
    unit((x + 1.0) / 2.0)
}

/// Writes the ego and navigation parts (indices 0..LIDAR_OFFSET) into `out`.
pub fn write_state(out: &mut [f32], car: &Kinematics, at: &RoutePosition, lanes: &[Lane]) {
    let lane = &lanes[at.route.lanes[at.lane_index]];
    out[0] = unit((lane.left_edge - at.lateral) / EDGE_SCALE);
    out[1] = unit((lane.right_edge + at.lateral) / EDGE_SCALE);
    out[2] = signed_unit(super::angle::wrap(car.heading - lane.heading(at.s)) / PI);
    out[3] = unit((car.speed * 3.6 + 1.0) / (MAX_SPEED * 3.6 + 1.0));
    out[4] = signed_unit(car.wheel);
    out[5] = signed_unit(car.steer);
    out[6] = signed_unit(car.throttle);
    out[7] = signed_unit(car.yaw_rate() / YAW_RATE_SCALE);
    out[8] = signed_unit(2.0 * at.lateral / lane.width);
    let forward = Vec2::from_angle(car.heading);
    let last = at.route.lanes.len() - 1;
    for k in 0..2 {
        let checkpoint_lane = &lanes[at.route.lanes[(at.lane_index + k).min(last)]];
        let to = checkpoint_lane.end() - car.position;
        let ego = Vec2::new(to.dot(forward), forward.perp_dot(to));
        let (radius, sweep) = checkpoint_lane.bend();
        let base = EGO_DIM + k * NAV_PER_CHECKPOINT;
        out[base] = signed_unit(ego.x / CHECKPOINT_SCALE);
        out[base + 1] = signed_unit(ego.y / CHECKPOINT_SCALE);
        out[base + 2] = unit(radius.abs() / RADIUS_SCALE);
        out[base + 3] = match radius.partial_cmp(&0.0) {
            Some(std::cmp::Ordering::Greater) => 1.0,
            Some(std::cmp::Ordering::Less) => 0.0,
            _ => 0.5,
        };
        out[base + 4] = unit(sweep.abs() / PI);
    }
}

/// Writes lidar distances (metres, up to `range`) normalised into the lidar part of `out`.
pub fn write_lidar(out: &mut [f32], distances: &[f32], range: f32) {
    for (o, d) in out[LIDAR_OFFSET..].iter_mut().zip(distances) {
        *o = unit(d / range);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use junction_core::spec::obs_dim;

    #[test]
    fn layout_is_pinned() {
        // A car centred in its lane, aligned, at 36 km/h, steering 0, half throttle, on a
        // straight 100 m lane heading east, the lane's end 60 m ahead.
        let lanes = vec![
            Lane::straight(Vec2::new(0.0, 0.0), Vec2::new(100.0, 0.0), 3.5, 1.75, 5.25),
            Lane::arc(
                Vec2::new(100.0, 20.0),
                20.0,
                -PI / 2.0,
                PI / 2.0,
                3.5,
                1.75,
                5.25,
            ),
        ];
        let route = Route::new(vec![0, 1], &lanes);
        let mut car = Kinematics::new(Vec2::new(40.0, 0.5), 0.0, 10.0);
        car.throttle = 0.5;
        let at = RoutePosition {
            route: &route,
            lane_index: 0,
            s: 40.0,
            lateral: 0.5,
        };
        let mut out = vec![-1.0; obs_dim(4)];
        write_state(&mut out, &car, &at, &lanes);
        write_lidar(&mut out, &[50.0, 25.0, 0.0, 60.0], 50.0);
        let expected = [
            (1.75 - 0.5) / 18.0, // left edge
            (5.25 + 0.5) / 18.0, // right edge
            0.5,                 // aligned
            37.0 / 81.0,         // 36 km/h
            0.5,
            0.5,
            0.75,                          // last action
            0.5,                           // no yaw
            (2.0 * 0.5 / 3.5 + 1.0) / 2.0, // lateral
            1.0,                           // checkpoint 1: 60 m ahead → capped
            (-0.5 / 50.0 + 1.0) / 2.0,     // 0.5 m to the right
            0.0,
            0.5,
            0.0,                       // straight lane
            1.0,                       // checkpoint 2: (120, 20) → 80 m ahead, capped
            (19.5 / 50.0 + 1.0) / 2.0, // 19.5 m to the left
            0.2,                       // radius 20 m / 100
            1.0,                       // left bend
            0.5,                       // quarter turn
            1.0,
            0.5,
            0.0,
            1.0, // lidar
        ];
        assert_eq!(out.len(), expected.len());
        for (i, (got, want)) in out.iter().zip(expected).enumerate() {
            assert!(
                (got - want).abs() < 1e-5,
                "obs[{i}] = {got}, expected {want}"
            );
        }
    }
}
