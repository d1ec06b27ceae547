//! `[scenario.intersection]`, `[scenario.roundabout]` and `[scenario.spawn]`: the two scenes'
//! roads and where on them cars enter.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntersectionConfig {
    /// 4 (a cross) or 3 (a T-junction: the south arm is left out).
    pub arms: usize,
    pub lanes_per_direction: usize,
    pub lane_width: f32,
    pub corner_radius: f32,
    pub approach_length: f32,
    pub routes: Vec<Manoeuvre>,
}

impl IntersectionConfig {
    /// What is wrong with the section, one line per problem.
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if !(1..=3).contains(&self.lanes_per_direction) {
            problems.push("scenario.intersection.lanes_per_direction must be 1, 2 or 3".into());
        }
        if !(self.lane_width >= 2.5) || !(self.corner_radius >= 0.0) {
            problems.push(
                "scenario.intersection.lane_width must be >= 2.5 m and corner_radius >= 0".into(),
            );
        }
        if self.routes.is_empty() {
            problems.push("scenario.intersection.routes must name at least one manoeuvre".into());
        }
        if !(3..=4).contains(&self.arms) {
            problems.push("scenario.intersection.arms must be 3 (a T-junction) or 4".into());
        }
        problems
    }
}

/// A roundabout: see `docs/SIMULATOR.md` for the geometry each key controls.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RoundaboutConfig {
    /// Radius of the central island (the ring's inner edge), metres.
    pub radius: f32,
    pub ring_lanes: usize,
    pub arms: usize,
    pub lanes_per_direction: usize,
    pub lane_width: f32,
    /// Degrees the entry arcs turn through from the arm onto the ring.
    pub entry_angle: f32,
    /// Centre-line radius of the outermost lane's exit arc, metres.
    pub exit_radius: f32,
    pub approach_length: f32,
}

impl RoundaboutConfig {
    /// What is wrong with the section, one line per problem.
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if !(3..=5).contains(&self.arms) {
            problems.push("scenario.roundabout.arms must be 3, 4 or 5".into());
        }
        if !(1..=3).contains(&self.lanes_per_direction) || !(1..=3).contains(&self.ring_lanes) {
            problems.push(
                "scenario.roundabout.lanes_per_direction and ring_lanes must be 1, 2 or 3".into(),
            );
        }
        if self.ring_lanes < self.lanes_per_direction {
            problems.push(
                "scenario.roundabout.ring_lanes must be >= lanes_per_direction (every arm lane \
                 continues on its own ring lane)"
                    .into(),
            );
        }
        if !(2.5..).contains(&self.lane_width) || !(5.0..).contains(&self.radius) {
            problems
                .push("scenario.roundabout.lane_width must be >= 2.5 m and radius >= 5 m".into());
        }
        if !(self.entry_angle > 0.0 && self.entry_angle < 90.0) {
            problems
                .push("scenario.roundabout.entry_angle must lie strictly between 0 and 90°".into());
        }
        if !(self.lane_width..).contains(&self.exit_radius) {
            problems.push(
                "scenario.roundabout.exit_radius must be >= lane_width (the kerb needs a radius)"
                    .into(),
            );
        }
        problems
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Manoeuvre {
    Straight,
    Left,
    Right,
    /// A half circle from the innermost incoming lane to the outermost outgoing lane of the
    /// same arm; needs 2 or more lanes per direction (1 lane is too tight for the car).
    #[serde(rename = "uturn")]
    UTurn,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpawnConfig {
    pub slot_spacing: f32,
    pub longitudinal_jitter: f32,
    pub lateral_jitter: f32,
    pub respawn_clear_length: f32,
    pub respawn_clear_width: f32,
    pub respawn_probability: f32,
    pub initial_speed: f32,
}

impl SpawnConfig {
    /// The spawn slots: their spacing, and that both scenes' approaches hold one.
    pub(super) fn slot_problems(
        &self,
        intersection: &IntersectionConfig,
        roundabout: &RoundaboutConfig,
    ) -> Vec<String> {
        let mut problems = Vec::new();
        if !(self.slot_spacing >= 5.0) {
            problems.push("scenario.spawn.slot_spacing must be >= 5 m (a car is 4.5 m)".into());
        }
        let holds_a_slot = self.slot_spacing..;
        if !holds_a_slot.contains(&intersection.approach_length)
            || !holds_a_slot.contains(&roundabout.approach_length)
        {
            problems.push(
                "scenario.intersection.approach_length and scenario.roundabout.approach_length \
                 must each hold at least one spawn slot"
                    .into(),
            );
        }
        problems
    }

    /// How empty slots refill: the chance per step and the new car's speed.
    pub(super) fn refill_problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if !(0.0..=1.0).contains(&self.respawn_probability) {
            problems.push("scenario.spawn.respawn_probability must be in [0, 1]".into());
        }
        if !(self.initial_speed >= 0.0) {
            problems.push("scenario.spawn.initial_speed must be >= 0".into());
        }
        problems
    }
}
