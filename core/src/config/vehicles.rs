//! `[scenario.vehicle]`, `[scenario.sensors]` and `[scenario.humans]`: the learning agents'
//! car and lidar, and the human drivers sharing the road with them.

use serde::{Deserialize, Serialize};

use super::MAX_LIDAR_BEAMS;

/// Limits of the vehicle model (docs/SIMULATOR.md, "Dynamics").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VehicleConfig {
    /// Largest lateral acceleration, m/s²; 0 = none (the pure kinematic bicycle).
    pub max_lateral_accel: f32,
    /// Deceleration of full braking, m/s².
    pub max_brake_decel: f32,
    /// Brake pedal (the negative throttle_brake) at which braking reaches `max_brake_decel`.
    pub brake_saturation: f32,
    /// Time constant of the wheel's lag behind the steering action, seconds; 0 = none.
    pub steering_time_constant: f32,
}

impl VehicleConfig {
    /// What is wrong with the section (one line for all its limits).
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        let valid = self.max_lateral_accel >= 0.0
            && self.max_lateral_accel.is_finite()
            && self.max_brake_decel > 0.0
            && self.max_brake_decel <= 20.0
            && self.brake_saturation > 0.0
            && self.brake_saturation <= 1.0
            && self.steering_time_constant >= 0.0
            && self.steering_time_constant <= 5.0;
        if !valid {
            problems.push(
                "scenario.vehicle.max_lateral_accel must be >= 0 (0 = no limit), \
                 scenario.vehicle.max_brake_decel in (0, 20] m/s², \
                 scenario.vehicle.brake_saturation in (0, 1] and \
                 scenario.vehicle.steering_time_constant in [0, 5] s"
                    .into(),
            );
        }
        problems
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorConfig {
    pub lidar_beams: usize,
    pub lidar_range: f32,
}

impl SensorConfig {
    /// What is wrong with the section.
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if !(1..=MAX_LIDAR_BEAMS).contains(&self.lidar_beams) || !(self.lidar_range > 0.0) {
            problems.push(format!(
                "scenario.sensors needs lidar_beams in 1..={MAX_LIDAR_BEAMS} and lidar_range > 0"
            ));
        }
        problems
    }
}

/// Non-connected, human-driven vehicles (IDM car following + gap acceptance).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HumanConfig {
    pub share: f32,
    pub desired_speed: f32,
    pub time_headway: f32,
    pub min_gap: f32,
    pub max_accel: f32,
    pub comfort_decel: f32,
    pub critical_gap: f32,
}

impl HumanConfig {
    /// What is wrong with the section, one line per problem.
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if !(0.0..=0.9).contains(&self.share) {
            problems.push("scenario.humans.share must be in [0, 0.9]".into());
        }
        let positive = [
            self.desired_speed,
            self.time_headway,
            self.max_accel,
            self.comfort_decel,
            self.critical_gap,
        ];
        if positive.iter().any(|v| !(*v > 0.0)) || !(self.min_gap >= 0.0) {
            problems.push(
                "scenario.humans: desired_speed, time_headway, max_accel, comfort_decel and critical_gap must be > 0, min_gap >= 0".into(),
            );
        }
        problems
    }
}
