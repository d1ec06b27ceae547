//! The vehicle: MetaDrive's default car as a kinematic bicycle with a longitudinal force model.
//!
//! Longitudinal model (also the basis of the energy cost, paper §3.5):
//! `m·a = F_engine − F_brake − F_roll − F_drag` with
//! `F_engine = throttle · 3300 N` (none at or above the top speed), `F_brake = brake · 6600 N`,
//! `F_roll = 0.015 · m · g` and `F_drag = ½ · 1.225 · 0.30 · 2.2 · v²` (air density, drag
//! coefficient, frontal area). Speed never goes below 0: no reverse. MetaDrive's Bullet
//! "forces" (800 engine, 150 brake) are not Newtons on the chassis; ours are calibrated to
//! 3 m/s² peak acceleration and 6 m/s² peak braking for its 1100 kg car.
//!
//! Energy: the work of the engine force, `∫ F_engine · v dt`, in kJ. Regeneration is off:
//! braking and coasting return nothing, and a car standing still uses nothing.
//!
//! Lateral model: yaw rate = v · tan(δ) / wheelbase, steering applied at once. Following the
//! paper (§3.3), the steering action +1 turns fully right, so δ = −steer · 40°.

use parry2d::math::Vec2;

pub const LENGTH: f32 = 4.515;
pub const WIDTH: f32 = 1.852;
pub const WHEELBASE: f32 = 2.47;
pub const MAX_STEER_RAD: f32 = 40.0 * std::f32::consts::PI / 180.0;
pub const MAX_SPEED: f32 = 80.0 / 3.6;
pub const MASS: f32 = 1100.0;
pub const MAX_ENGINE_FORCE: f32 = 3300.0;
pub const MAX_BRAKE_FORCE: f32 = 6600.0;
const GRAVITY: f32 = 9.81;
const ROLLING_RESISTANCE: f32 = 0.015;
const DRAG_FACTOR: f32 = 0.5 * 1.225 * 0.30 * 2.2;
/// Half the diagonal: no part of the car is farther than this from its centre.
pub const BOUNDING_RADIUS: f32 = 2.4399; // ≥ √(2.2575² + 0.926²) = 2.43996

/// Kinematic state of one car.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kinematics {
    pub position: Vec2,
    pub heading: f32,
    pub speed: f32,
    /// Last applied action, clipped to [-1, 1].
    pub steer: f32,
    pub throttle: f32,
}

impl Kinematics {
    pub fn new(position: Vec2, heading: f32, speed: f32) -> Self {
        Kinematics {
            position,
            heading,
            speed: speed.clamp(0.0, MAX_SPEED),
            steer: 0.0,
            throttle: 0.0,
        }
    }

    /// Yaw rate (rad/s, counter-clockwise positive) for the current speed and steering.
    pub fn yaw_rate(&self) -> f32 {
        self.speed * (-self.steer * MAX_STEER_RAD).tan() / WHEELBASE
    }

    /// Engine force (N) under the current throttle at `speed`.
    fn engine_force(&self, speed: f32) -> f32 {
        if speed < MAX_SPEED {
            self.throttle.max(0.0) * MAX_ENGINE_FORCE
        } else {
            0.0
        }
    }

    /// Net longitudinal acceleration (m/s²) under the current throttle/brake at `speed`.
    fn acceleration(&self, speed: f32) -> f32 {
        let engine = self.engine_force(speed);
        let resist = if speed > 0.0 {
            (-self.throttle).max(0.0) * MAX_BRAKE_FORCE
                + ROLLING_RESISTANCE * MASS * GRAVITY
                + DRAG_FACTOR * speed * speed
        } else {
            0.0
        };
        (engine - resist) / MASS
    }

    /// Applies `[steer, throttle_brake]` (clipped; NaN counts as 0) for `substeps` sub-steps
    /// of `dt / substeps` seconds; returns the engine's energy over the step, in kJ.
    pub fn advance(&mut self, action: [f32; 2], dt: f32, substeps: u32) -> f32 {
        let clean = |a: f32| if a.is_nan() { 0.0 } else { a.clamp(-1.0, 1.0) };
        self.steer = clean(action[0]);
        self.throttle = clean(action[1]);
        let h = dt / substeps.max(1) as f32;
        let mut energy_j = 0.0;
        for _ in 0..substeps.max(1) {
            let yaw_rate = self.yaw_rate();
            let speed = (self.speed + self.acceleration(self.speed) * h).clamp(0.0, MAX_SPEED);
            let mean_speed = 0.5 * (self.speed + speed);
            energy_j += self.engine_force(self.speed) * mean_speed * h;
            self.heading = super::angle::wrap(self.heading + yaw_rate * h);
            self.position += Vec2::from_angle(self.heading) * (mean_speed * h);
            self.speed = speed;
        }
        energy_j / 1000.0
    }

    /// The four corners of the body.
    pub fn corners(&self) -> [Vec2; 4] {
        let forward = Vec2::from_angle(self.heading) * (LENGTH / 2.0);
        let left = Vec2::from_angle(self.heading).perp() * (WIDTH / 2.0);
        let c = self.position;
        [
            c + forward + left,
            c + forward - left,
            c - forward - left,
            c - forward + left,
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn full_throttle_accelerates_at_about_three_metres_per_second_squared() {
        let mut k = Kinematics::new(Vec2::ZERO, 0.0, 0.0);
        k.advance([0.0, 1.0], 1.0, 50);
        assert!((2.7..3.0).contains(&k.speed), "{}", k.speed);
        assert!(k.position.y.abs() < 1e-6 && k.position.x > 1.3 && k.position.x < 1.6);
    }

    #[test]
    fn energy_is_the_engine_work_and_braking_returns_none() {
        // From rest, full throttle for 1 s: ≈ 3300 N over the ≈ 1.45 m travelled.
        let mut k = Kinematics::new(Vec2::ZERO, 0.0, 0.0);
        let kj = k.advance([0.0, 1.0], 1.0, 50);
        let expected = MAX_ENGINE_FORCE * k.position.x / 1000.0;
        assert!(
            (kj - expected).abs() < 0.01 * expected,
            "{kj} vs {expected}"
        );
        assert_eq!(k.advance([0.0, -1.0], 0.1, 5), 0.0, "no regeneration");
        let mut parked = Kinematics::new(Vec2::ZERO, 0.0, 0.0);
        assert_eq!(parked.advance([0.0, 0.0], 0.1, 5), 0.0);
    }

    #[test]
    fn braking_stops_without_reversing() {
        let mut k = Kinematics::new(Vec2::ZERO, 0.0, 10.0);
        for _ in 0..30 {
            k.advance([0.0, -1.0], 0.1, 5);
        }
        assert_eq!(k.speed, 0.0);
        let x = k.position.x;
        k.advance([0.0, -1.0], 0.1, 5);
        assert_eq!(k.position.x, x, "a stopped car stays put");
    }

    #[test]
    fn positive_steer_turns_right() {
        let mut k = Kinematics::new(Vec2::ZERO, 0.0, 5.0);
        k.advance([1.0, 0.0], 0.1, 5);
        assert!(
            k.heading < 0.0 && k.position.y < 0.0,
            "heading {}",
            k.heading
        );
        assert!(k.yaw_rate() < 0.0);
    }

    #[test]
    fn top_speed_is_never_exceeded_and_nan_actions_are_neutral() {
        let mut k = Kinematics::new(Vec2::ZERO, 0.0, MAX_SPEED);
        k.advance([f32::NAN, 1.0], 0.1, 5);
        assert!(k.speed <= MAX_SPEED);
        assert_eq!(k.steer, 0.0);
    }
}
