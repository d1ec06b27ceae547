//! The vehicle: MetaDrive's default car as a kinematic bicycle with a longitudinal force model.
//!
//! Longitudinal model (also the basis of the energy cost, paper §3.5):
//! `m·a = F_engine − F_brake − F_roll − F_drag` with
//! `F_engine = throttle · 3300 N` (none at or above the top speed),
//! `F_brake = min(brake / brake_saturation, 1) · max_brake_decel · m` (by default 15 m/s² from
//! three quarters of the pedal on), `F_roll = 0.015 · m · g` and
//! `F_drag = ½ · 1.225 · 0.30 · 2.2 · v²` (air density, drag coefficient, frontal area). Speed
//! never goes below 0: no reverse. MetaDrive's Bullet "forces" (800 engine, 150 brake) are not
//! Newtons on the chassis; ours are calibrated to its 1100 kg car as measured in MetaDrive
//! 0.4.3: 3 m/s² peak acceleration, braking that saturates at 15 m/s².
//!
//! Energy: the work of the engine force, `∫ F_engine · v dt`, in kJ. Regeneration is off:
//! braking and coasting return nothing, and a car standing still uses nothing.
//!
//! Lateral model: yaw rate = v · tan(δ) / wheelbase. Following the paper (§3.3), the steering
//! action +1 turns fully right, so δ = −wheel · 40°, where the wheel angle follows the steering
//! action at once, or (with [`Dynamics::steering_time_constant`]) as a first-order lag.
//!
//! A kinematic bicycle has no tyres: at 10 m/s full lock turns with 34 m/s² of lateral
//! acceleration, where MetaDrive's Bullet car saturates near 6 m/s² and builds its yaw over a
//! few tenths of a second. [`Dynamics`] can cap the yaw rate at `max_lateral_accel / v` (a
//! friction limit: the car runs wide instead of turning tighter), lag the wheel behind the
//! steering action, and set the braking deceleration; docs/SIMULATOR.md compares them with
//! MetaDrive's measured car.

use parry2d::math::Vec2;

pub const LENGTH: f32 = 4.515;
pub const WIDTH: f32 = 1.852;
pub const WHEELBASE: f32 = 2.47;
pub const MAX_STEER_RAD: f32 = 40.0 * std::f32::consts::PI / 180.0;
pub const MAX_SPEED: f32 = 80.0 / 3.6;
pub const MASS: f32 = 1100.0;
pub const MAX_ENGINE_FORCE: f32 = 3300.0;
const GRAVITY: f32 = 9.81;
const ROLLING_RESISTANCE: f32 = 0.015;
const DRAG_FACTOR: f32 = 0.5 * 1.225 * 0.30 * 2.2;
/// Half the diagonal: no part of the car is farther than this from its centre.
pub const BOUNDING_RADIUS: f32 = 2.4399; // ≥ √(2.2575² + 0.926²) = 2.43996

/// The limits a car's tyres and brakes set (`[scenario.vehicle]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dynamics {
    /// Largest lateral acceleration v·ω, m/s² (0: none, the pure kinematic bicycle).
    pub max_lateral_accel: f32,
    /// Deceleration of full braking, m/s² (brake force = this × mass).
    pub max_brake_decel: f32,
    /// Brake pedal at which braking reaches `max_brake_decel` (1: proportional throughout).
    pub brake_saturation: f32,
    /// Time constant of the wheel's first-order lag behind the steering action, seconds (0:
    /// the wheel turns at once).
    pub steering_time_constant: f32,
}

impl Default for Dynamics {
    /// The default car (`[scenario.vehicle]`'s defaults): the kinematic bicycle with MetaDrive's
    /// measured brake, 15 m/s² from three quarters of the pedal on.
    fn default() -> Self {
        Dynamics {
            max_lateral_accel: 0.0,
            max_brake_decel: 15.0,
            brake_saturation: 0.75,
            steering_time_constant: 0.0,
        }
    }
}

impl Dynamics {
    /// The brake pedal (a positive number, at most 1) that decelerates at `decel` m/s² by the
    /// brakes alone: the inverse of the pedal-to-force curve in `Kinematics::acceleration`.
    pub fn brake_pedal(&self, decel: f32) -> f32 {
        (decel / self.max_brake_decel * self.brake_saturation).min(1.0)
    }
}

impl From<&junction_core::config::VehicleConfig> for Dynamics {
    fn from(c: &junction_core::config::VehicleConfig) -> Self {
        Dynamics {
            max_lateral_accel: c.max_lateral_accel,
            max_brake_decel: c.max_brake_decel,
            brake_saturation: c.brake_saturation,
            steering_time_constant: c.steering_time_constant,
        }
    }
}

/// Kinematic state of one car.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kinematics {
    pub position: Vec2,
    pub heading: f32,
    pub speed: f32,
    /// Last applied action, clipped to [-1, 1].
    pub steer: f32,
    pub throttle: f32,
    /// Where the wheel points, as a fraction of full lock (+ = right): the steering action
    /// itself, or lagging behind it.
    pub wheel: f32,
    pub dynamics: Dynamics,
}

impl Kinematics {
    pub fn new(position: Vec2, heading: f32, speed: f32) -> Self {
        Kinematics {
            position,
            heading,
            speed: speed.clamp(0.0, MAX_SPEED),
            steer: 0.0,
            throttle: 0.0,
            wheel: 0.0,
            dynamics: Dynamics::default(),
        }
    }

    pub fn with_dynamics(self, dynamics: Dynamics) -> Self {
        Kinematics { dynamics, ..self }
    }

    /// Yaw rate (rad/s, counter-clockwise positive) for the current speed and steering, within
    /// the lateral-acceleration limit.
    pub fn yaw_rate(&self) -> f32 {
        let geometric = self.speed * (-self.wheel * MAX_STEER_RAD).tan() / WHEELBASE;
        let limit = self.dynamics.max_lateral_accel;
        if limit > 0.0 && self.speed > 0.0 {
            let most = limit / self.speed;
            geometric.clamp(-most, most)
        } else {
            geometric
        }
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
            let brake = ((-self.throttle).max(0.0) / self.dynamics.brake_saturation).min(1.0);
            brake * self.dynamics.max_brake_decel * MASS
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
        let tau = self.dynamics.steering_time_constant;
        let follow = if tau > 0.0 {
            1.0 - (-h / tau).exp()
        } else {
            1.0
        };
        let mut energy_j = 0.0;
        for _ in 0..substeps.max(1) {
            self.wheel += (self.steer - self.wheel) * follow;
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
    fn the_lateral_limit_caps_the_yaw_rate_at_speed_only() {
        let tyres = Dynamics {
            max_lateral_accel: 9.0,
            ..Dynamics::default()
        };
        let fast = Kinematics {
            wheel: 1.0,
            ..Kinematics::new(Vec2::ZERO, 0.0, 10.0).with_dynamics(tyres)
        };
        // Geometric: 10 · tan(40°) / 2.47 = 3.40 rad/s, 34 m/s² laterally; capped: 0.9 rad/s.
        assert!((fast.yaw_rate() + 0.9).abs() < 1e-5, "{}", fast.yaw_rate());
        let unlimited = Kinematics {
            dynamics: Dynamics::default(),
            ..fast
        };
        assert!((unlimited.yaw_rate() + 3.397).abs() < 1e-2);
        // At walking pace full lock stays within the limit: the cap changes nothing.
        let slow = Kinematics { speed: 1.5, ..fast };
        let geometric = -1.5 * MAX_STEER_RAD.tan() / WHEELBASE;
        assert_eq!(slow.yaw_rate(), geometric);
    }

    #[test]
    fn a_lagging_wheel_follows_the_steering_action_at_its_time_constant() {
        let lagging = Dynamics {
            steering_time_constant: 0.25,
            ..Dynamics::default()
        };
        let mut k = Kinematics::new(Vec2::ZERO, 0.0, 10.0).with_dynamics(lagging);
        k.advance([1.0, 0.0], 0.1, 5);
        // After 0.1 s: 1 − e^(−0.1/0.25) = 0.33 of full lock (exactly, over 5 sub-steps).
        assert!(
            (k.wheel - (1.0 - (-0.4f32).exp())).abs() < 1e-5,
            "{}",
            k.wheel
        );
        assert_eq!(k.steer, 1.0, "the action itself is kept");
        for _ in 0..20 {
            k.advance([1.0, 0.0], 0.1, 5);
        }
        assert!(k.wheel > 0.99);
        // Step-to-step noise in the action is smoothed: ±1 alternating moves the wheel little.
        let mut noisy = Kinematics::new(Vec2::ZERO, 0.0, 10.0).with_dynamics(lagging);
        for i in 0..20 {
            noisy.advance([if i % 2 == 0 { 1.0 } else { -1.0 }, 0.0], 0.1, 5);
            assert!(noisy.wheel.abs() < 0.4, "{}", noisy.wheel);
        }
        let mut instant = Kinematics::new(Vec2::ZERO, 0.0, 10.0);
        instant.advance([0.5, 0.0], 0.1, 5);
        assert_eq!(instant.wheel, 0.5, "no lag: the wheel is the action");
    }

    #[test]
    fn braking_decelerates_at_the_configured_rate() {
        let mut k = Kinematics::new(Vec2::ZERO, 0.0, 10.0).with_dynamics(Dynamics {
            max_brake_decel: 8.5,
            ..Dynamics::default()
        });
        k.advance([0.0, -1.0], 0.1, 5);
        // 8.5 from the brake, ≈ 0.15 rolling resistance, ≈ 0.04 drag at 10 m/s.
        assert!((k.speed - (10.0 - 0.1 * 8.69)).abs() < 0.01, "{}", k.speed);
    }

    #[test]
    fn braking_saturates_at_the_configured_pedal() {
        // MetaDrive-like: 15 m/s² reached at 0.6 of the pedal, proportional below it.
        let strong = Dynamics {
            max_brake_decel: 15.0,
            brake_saturation: 0.6,
            ..Dynamics::default()
        };
        let decel = |pedal: f32, dynamics: Dynamics| {
            let mut k = Kinematics::new(Vec2::ZERO, 0.0, 10.0).with_dynamics(dynamics);
            k.advance([0.0, -pedal], 0.01, 1);
            (10.0 - k.speed) / 0.01
        };
        // Rolling resistance (0.147) and drag (0.037 at 10 m/s) come on top of the brake.
        let rest = 0.015 * 9.81 + 0.5 * 1.225 * 0.30 * 2.2 * 100.0 / MASS;
        assert!(
            (decel(0.3, strong) - (7.5 + rest)).abs() < 0.01,
            "{}",
            decel(0.3, strong)
        );
        assert!((decel(0.6, strong) - (15.0 + rest)).abs() < 0.01);
        assert!(
            (decel(1.0, strong) - (15.0 + rest)).abs() < 0.01,
            "saturated"
        );
        let proportional = Dynamics {
            max_brake_decel: 6.0,
            brake_saturation: 1.0,
            ..Dynamics::default()
        };
        assert!((decel(0.3, proportional) - (1.8 + rest)).abs() < 0.01);
        // The default car brakes like MetaDrive's: 6 m/s² at a third of the pedal.
        assert!((decel(0.3, Dynamics::default()) - (6.0 + rest)).abs() < 0.01);
        // brake_pedal inverts the curve, so the human drivers' IDM gets the braking it asks for.
        for dynamics in [strong, proportional, Dynamics::default()] {
            for wanted in [0.5, 3.0, 6.0] {
                let pedal = dynamics.brake_pedal(wanted);
                assert!((decel(pedal, dynamics) - (wanted + rest)).abs() < 0.01);
            }
            assert_eq!(dynamics.brake_pedal(100.0), 1.0, "at most the full pedal");
        }
    }

    #[test]
    fn top_speed_is_never_exceeded_and_nan_actions_are_neutral() {
        let mut k = Kinematics::new(Vec2::ZERO, 0.0, MAX_SPEED);
        k.advance([f32::NAN, 1.0], 0.1, 5);
        assert!(k.speed <= MAX_SPEED);
        assert_eq!(k.steer, 0.0);
    }
}
