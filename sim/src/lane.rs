//! Lanes: straight segments and circular arcs with a width and the distances from their
//! centre line to the edges of the drivable road on either side, measured in the lane's own
//! frame (longitudinal `s` from the lane start, lateral offset positive to the left).

use parry2d::math::Vec2;

use super::angle::wrap;

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LaneShape {
    Straight {
        start: Vec2,
        end: Vec2,
    },
    /// `sweep` > 0 turns left (counter-clockwise), < 0 right.
    Arc {
        centre: Vec2,
        radius: f32,
        start_angle: f32,
        sweep: f32,
    },
}

#[derive(Debug, Clone, PartialEq)]
pub struct Lane {
    pub shape: LaneShape,
    pub width: f32,
    /// Distance from the centre line to the left / right edge of the drivable road.
    pub left_edge: f32,
    pub right_edge: f32,
    length: f32,
}

impl Lane {
    pub fn straight(start: Vec2, end: Vec2, width: f32, left_edge: f32, right_edge: f32) -> Lane {
        let length = (end - start).length();
        Lane {
            shape: LaneShape::Straight { start, end },
            width,
            left_edge,
            right_edge,
            length,
        }
    }

    pub fn arc(
        centre: Vec2,
        radius: f32,
        start_angle: f32,
        sweep: f32,
        width: f32,
        left_edge: f32,
        right_edge: f32,
    ) -> Lane {
        let length = radius * sweep.abs();
        Lane {
            shape: LaneShape::Arc {
                centre,
                radius,
                start_angle,
                sweep,
            },
            width,
            left_edge,
            right_edge,
            length,
        }
    }

    pub fn length(&self) -> f32 {
        self.length
    }

    pub fn start(&self) -> Vec2 {
        self.point(0.0)
    }

    pub fn end(&self) -> Vec2 {
        self.point(self.length)
    }

    /// Centre-line point at `s` (extrapolated beyond the ends).
    pub fn point(&self, s: f32) -> Vec2 {
        match self.shape {
            LaneShape::Straight { start, end } => start + (end - start) * (s / self.length),
            LaneShape::Arc {
                centre,
                radius,
                start_angle,
                sweep,
            } => centre + Vec2::from_angle(start_angle + sweep.signum() * s / radius) * radius,
        }
    }

    /// Direction of travel at `s`, radians.
    pub fn heading(&self, s: f32) -> f32 {
        match self.shape {
            LaneShape::Straight { start, end } => (end - start).to_angle(),
            LaneShape::Arc {
                radius,
                start_angle,
                sweep,
                ..
            } => {
                let turn = sweep.signum();
                wrap(start_angle + turn * (s / radius + std::f32::consts::FRAC_PI_2))
            }
        }
    }

    /// (s, lateral) of `p`; lateral is positive to the left of the direction of travel.
    pub fn project(&self, p: Vec2) -> (f32, f32) {
        match self.shape {
            LaneShape::Straight { start, end } => {
                let dir = (end - start) / self.length;
                let rel = p - start;
                (rel.dot(dir), dir.perp_dot(rel))
            }
            LaneShape::Arc {
                centre,
                radius,
                start_angle,
                sweep,
            } => {
                let rel = p - centre;
                let turn = sweep.signum();
                // Angle travelled from the start, measured so the gap outside the arc is split
                // evenly between "before the start" and "after the end".
                let half = sweep.abs() / 2.0;
                let travelled = turn * wrap(rel.to_angle() - start_angle - turn * half) + half;
                let distance = rel.length();
                let lateral = if turn > 0.0 {
                    radius - distance
                } else {
                    distance - radius
                };
                (travelled * radius, lateral)
            }
        }
    }

    /// Signed radius of the bend (0 for straight lanes): > 0 left, < 0 right.
    pub fn bend(&self) -> (f32, f32) {
        match self.shape {
            LaneShape::Straight { .. } => (0.0, 0.0),
            LaneShape::Arc { radius, sweep, .. } => (radius * sweep.signum(), sweep),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::{FRAC_PI_2, PI};

    #[test]
    fn straight_projection_and_heading() {
        let lane = Lane::straight(Vec2::new(10.0, 0.0), Vec2::new(0.0, 0.0), 3.5, 1.75, 1.75);
        assert_eq!(lane.length(), 10.0);
        let (s, lat) = lane.project(Vec2::new(7.0, -1.0));
        assert!((s - 3.0).abs() < 1e-6);
        // Heading west, the left side is south: y = −1 is 1 m to the left.
        assert!((lat - 1.0).abs() < 1e-6);
        assert!((lane.heading(0.0).abs() - PI).abs() < 1e-6);
    }

    #[test]
    fn arc_points_headings_and_projection_agree() {
        // Left quarter turn from (10, 0) heading north around the origin.
        let lane = Lane::arc(Vec2::ZERO, 10.0, 0.0, FRAC_PI_2, 3.5, 1.75, 1.75);
        assert!((lane.length() - 10.0 * FRAC_PI_2).abs() < 1e-5);
        assert!((lane.end() - Vec2::new(0.0, 10.0)).length() < 1e-4);
        assert!((lane.heading(0.0) - FRAC_PI_2).abs() < 1e-6);
        let mid = lane.length() / 2.0;
        let inside = lane.point(mid) * 0.9; // towards the centre = to the left on a left turn
        let (s, lat) = lane.project(inside);
        assert!(
            (s - mid).abs() < 1e-3 && (lat - 1.0).abs() < 1e-4,
            "{s} {lat}"
        );
        // Before the start the travelled distance is negative.
        assert!(lane.project(Vec2::new(10.0, -2.0)).0 < 0.0);

        // Right quarter turn: from (0, 10) heading east, clockwise around the origin.
        let right = Lane::arc(Vec2::ZERO, 10.0, FRAC_PI_2, -FRAC_PI_2, 3.5, 1.75, 1.75);
        assert!((right.heading(0.0) - 0.0).abs() < 1e-6);
        assert!((right.end() - Vec2::new(10.0, 0.0)).length() < 1e-4);
        let (s, lat) = right.project(right.point(3.0) * 1.1);
        assert!(
            (s - 3.0).abs() < 1e-3 && (lat - 1.0).abs() < 1e-4,
            "outside of a right turn is left: {lat}"
        );
    }
}
