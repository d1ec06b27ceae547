//! Non-connected vehicles (human drivers): not trained, they follow their route with
//! pure-pursuit steering, the Intelligent Driver Model (Treiber et al. 2000) for speed, and a
//! simple gap acceptance before they leave their approach lane into the junction or ring.
//!
//! IDM: `a = a_max · (1 − (v/v0)^4 − (s*/s)²)` (v0 lowered for bends as the autopilot does), `s* = s0 + v·T + v·Δv / (2·√(a_max·b))`, with the
//! leader the nearest body ahead within half a lane of the path. Gap acceptance: within the
//! braking distance (+ 5 m) of its approach lane's end E, a driver treats E as a stopped
//! leader while a vehicle from another direction occupies E (within `ENTRY_CLEARANCE`) or
//! will reach it within `critical_gap` seconds at its current speed.

use parry2d::math::Vec2;

use junction_core::config::HumanConfig;

use super::car::Car;
use super::network::{RoadNetwork, bend_speed, route_point};
use super::vehicle::{LENGTH, MASS, MAX_ENGINE_FORCE, MAX_STEER_RAD, WHEELBASE};

/// Bodies farther ahead than this do not constrain the driver.
const LOOKAHEAD: f32 = 60.0;
/// A body counts as "ahead" when within this lateral distance of the heading line.
const PATH_HALF_WIDTH: f32 = 1.75;
/// Another vehicle this close to the driver's entry point occupies it.
const ENTRY_CLEARANCE: f32 = 8.0;

/// One vehicle as drivers see it: position, heading, speed.
#[derive(Debug, Clone, Copy)]
pub struct Seen {
    pub position: Vec2,
    pub heading: f32,
    pub speed: f32,
}

/// `[steer, throttle_brake]` for a human-driven `car`; `others` holds every other body.
pub fn drive(
    car: &Car,
    network: &dyn RoadNetwork,
    config: &HumanConfig,
    others: impl Iterator<Item = Seen> + Clone,
) -> [f32; 2] {
    let route = &network.routes()[car.route];
    let position = car.kin.position;
    let speed = car.kin.speed;
    let forward = Vec2::from_angle(car.kin.heading);

    // Pure pursuit on the route's centre line.
    let target = route_point(network, route, car.progress + 4.0 + 0.8 * speed);
    let to_target = target - position;
    let alpha = forward.perp_dot(to_target).atan2(to_target.dot(forward));
    let steer_angle = (2.0 * alpha.sin() / to_target.length().max(1e-3) * WHEELBASE).atan();
    let steer = (-steer_angle / MAX_STEER_RAD).clamp(-1.0, 1.0);

    // Leader: the nearest body ahead on the path (gap bumper to bumper, its speed along ours).
    let mut leader: Option<(f32, f32)> = None;
    for other in others.clone() {
        let rel = other.position - position;
        let ahead = rel.dot(forward);
        if ahead <= 0.0 || ahead > LOOKAHEAD || forward.perp_dot(rel).abs() > PATH_HALF_WIDTH {
            continue;
        }
        let gap = ahead - LENGTH;
        let along = other.speed * Vec2::from_angle(other.heading).dot(forward);
        if leader.is_none_or(|(g, _)| gap < g) {
            leader = Some((gap, along));
        }
    }

    // Gap acceptance at the end of the approach lane.
    if car.lane_index == 0 && route.lanes.len() > 1 {
        let lane = &network.lanes()[route.lanes[0]];
        let to_entry = lane.length() - car.s;
        let braking = speed * speed / (2.0 * config.comfort_decel) + 5.0;
        if to_entry <= braking {
            let entry = lane.end();
            let blocked = others.into_iter().any(|o| {
                let heading = Vec2::from_angle(o.heading);
                // Traffic beside or behind on the same approach never crosses the entry.
                let same_approach = heading.dot(forward) > 0.9;
                let distance = (o.position - entry).length();
                let closing = (entry - o.position).dot(heading) > 0.0;
                !same_approach
                    && (distance < ENTRY_CLEARANCE
                        || (closing && distance / o.speed.max(0.1) < config.critical_gap))
            });
            if blocked && leader.is_none_or(|(g, _)| to_entry < g) {
                leader = Some((to_entry.max(0.0), 0.0));
            }
        }
    }

    // IDM acceleration (desired speed capped for bends), then the force model's throttle or
    // brake for it.
    let v0 = config
        .desired_speed
        .min(bend_speed(network, route, car.lane_index))
        .max(0.1);
    let free = 1.0 - (speed / v0).powi(4);
    let interaction = leader.map_or(0.0, |(gap, leader_speed)| {
        let dv = speed - leader_speed;
        let desired_gap = config.min_gap
            + speed * config.time_headway
            + speed * dv / (2.0 * (config.max_accel * config.comfort_decel).sqrt());
        (desired_gap.max(0.0) / gap.max(0.1)).powi(2)
    });
    let accel = config.max_accel * (free - interaction);
    let throttle = if accel >= 0.0 {
        accel * MASS / MAX_ENGINE_FORCE
    } else {
        -car.kin.dynamics.brake_pedal(-accel)
    };
    [steer, throttle.clamp(-1.0, 1.0)]
}
