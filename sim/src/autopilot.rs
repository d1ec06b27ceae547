//! A scripted driver for tests and `actor bench`: pure-pursuit steering along each agent's
//! route and a proportional speed controller that brakes for a vehicle close ahead. It does
//! not negotiate the junction, so crossing traffic still crashes now and then.

use parry2d::math::Vec2;

use junction_core::spec::{ACTION_DIM, LIDAR_OFFSET};

use super::Scene;
use super::network::{bend_speed, route_point, tightest_bend};
use super::vehicle::{MAX_STEER_RAD, WHEELBASE};

/// Brake when a lidar beam within this angle of straight ahead sees a body closer than
/// `FOLLOW_GAP` metres.
const FRONT_CONE_RAD: f32 = 0.25;
const FOLLOW_GAP: f32 = 8.0;
/// Cruising speed of `actor bench` and `actor render`: fast enough that unsupervised junction
/// crossings produce crashes.
pub const CRUISE_SPEED_MPS: f32 = 10.0;
/// The speed controller: throttle per m/s too slow, and deceleration (m/s²) per m/s too fast up
/// to `MAX_BRAKE_DECEL`, turned into the pedal of whatever brake the car has, so the autopilot
/// drives alike with every `[scenario.vehicle]` (and `actor bench` measures the same traffic).
/// The cap keeps its traffic moving: braking at up to 15 m/s² it stopped short of nearly
/// everything and, not negotiating the junction, jammed it: far fewer episodes ended.
const THROTTLE_PER_MPS: f32 = 0.5;
const BRAKE_DECEL_PER_MPS: f32 = 3.0;
const MAX_BRAKE_DECEL: f32 = 6.0;
/// Writes `[steer, throttle_brake]` for every alive slot into `out` (zeros elsewhere).
pub fn autopilot_actions(scene: &Scene, target_speed_mps: f32, out: &mut [f32]) {
    out.fill(0.0);
    let obs_dim = scene.obs_dim();
    let beams = scene.config().sensors.lidar_beams;
    let range = scene.config().sensors.lidar_range;
    let beam_step = std::f32::consts::TAU / beams as f32;
    let cone = (FRONT_CONE_RAD / beam_step) as usize;
    for slot in 0..scene.slots() {
        let Some(car) = scene.car(slot) else { continue };
        let route = &scene.network().routes()[car.route];
        // Shorter look-ahead in tight bends, so pure pursuit does not cut them.
        let lookahead = (4.0 + 0.8 * car.kin.speed)
            .min(tightest_bend(scene.network(), route, car.lane_index).max(2.0));
        let target = route_point(scene.network(), route, car.progress + lookahead);
        let forward = Vec2::from_angle(car.kin.heading);
        let rel = target - car.kin.position;
        let alpha = forward.perp_dot(rel).atan2(rel.dot(forward));
        let curvature = 2.0 * alpha.sin() / rel.length().max(1e-3);
        let steer_angle = (curvature * WHEELBASE).atan();
        // Paper convention: +1 steers right, i.e. clockwise.
        let steer = (-steer_angle / MAX_STEER_RAD).clamp(-1.0, 1.0);
        let lidar = &scene.observations()[slot * obs_dim + LIDAR_OFFSET..(slot + 1) * obs_dim];
        let front = (0..=cone)
            .flat_map(|k| [k, (beams - k) % beams])
            .map(|b| lidar[b] * range)
            .fold(f32::INFINITY, f32::min);
        let desired = if front < FOLLOW_GAP {
            0.0
        } else {
            target_speed_mps.min(bend_speed(scene.network(), route, car.lane_index))
        };
        let error = desired - car.kin.speed;
        let throttle = if error >= 0.0 {
            (THROTTLE_PER_MPS * error).min(1.0)
        } else {
            -car.kin
                .dynamics
                .brake_pedal((BRAKE_DECEL_PER_MPS * -error).min(MAX_BRAKE_DECEL))
        };
        out[slot * ACTION_DIM] = steer;
        out[slot * ACTION_DIM + 1] = throttle;
    }
}
