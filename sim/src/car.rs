//! A car as the scene keeps it: its kinematics, where it is on its route, and the running
//! totals of its episode. The scene steps it; human drivers read it to choose their actions.

use super::vehicle::Kinematics;

/// One car of a scene, a learning agent's or a human driver's.
#[derive(Debug, Clone)]
pub struct Car {
    pub kin: Kinematics,
    pub route: usize,
    pub lane_index: usize,
    pub s: f32,
    pub lateral: f32,
    /// Distance travelled along the route (metres).
    pub progress: f32,
    pub age: u32,
    pub total_reward: f32,
    pub abs_accel_sum: f32,
    pub max_abs_accel: f32,
    pub collisions: u32,
    pub energy_kj: f32,
    pub total_cost: f32,
}
