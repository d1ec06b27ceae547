//! 2-D lidar against vehicle boxes. Each body in range is projected to the arc of beams it can
//! cover (from its bounding circle), and only those beams are ray-cast, so a scan costs about
//! (bodies in range × beams each covers), not bodies × all beams.

use std::f32::consts::TAU;

use parry2d::math::Vec2;

use super::vehicle::{BOUNDING_RADIUS, LENGTH, WIDTH};

/// Distance along the ray `origin + t·dir` (|dir| = 1) to a car-sized box at `centre` with
/// `heading`, if it is hit at t ≥ 0 (0 when the origin is inside).
pub fn ray_box(origin: Vec2, dir: Vec2, centre: Vec2, heading: f32) -> Option<f32> {
    let axis = Vec2::from_angle(heading);
    let rel = origin - centre;
    // Ray in the box frame (rotate by −heading).
    let o = Vec2::new(rel.dot(axis), axis.perp_dot(rel));
    let u = Vec2::new(dir.dot(axis), axis.perp_dot(dir));
    let half = [LENGTH / 2.0, WIDTH / 2.0];
    let (mut t_enter, mut t_exit) = (f32::NEG_INFINITY, f32::INFINITY);
    for axis_index in 0..2 {
        let (oi, ui, hi) = (o[axis_index], u[axis_index], half[axis_index]);
        if ui.abs() < 1e-9 {
            if oi.abs() > hi {
                return None;
            }
        } else {
            let (a, b) = ((-hi - oi) / ui, (hi - oi) / ui);
            t_enter = t_enter.max(a.min(b));
            t_exit = t_exit.min(a.max(b));
        }
    }
    (t_exit >= t_enter.max(0.0)).then_some(t_enter.max(0.0))
}

/// Fills `out` (one value per beam, beam 0 straight ahead, counter-clockwise) with the
/// distance to the nearest box, or `range` when none is within range.
pub fn scan(
    origin: Vec2,
    heading: f32,
    range: f32,
    others: impl Iterator<Item = (Vec2, f32)>,
    out: &mut [f32],
) {
    out.fill(range);
    let beams = out.len();
    let step = TAU / beams as f32;
    for (centre, body_heading) in others {
        let rel = centre - origin;
        let distance = rel.length();
        if distance - BOUNDING_RADIUS > range {
            continue;
        }
        let (first, last) = if distance <= BOUNDING_RADIUS {
            (0, beams as i64 - 1)
        } else {
            let bearing = rel.to_angle() - heading;
            let half_span = (BOUNDING_RADIUS / distance).asin();
            (
                ((bearing - half_span) / step).ceil() as i64,
                ((bearing + half_span) / step).floor() as i64,
            )
        };
        for b in first..=last {
            let beam = b.rem_euclid(beams as i64) as usize;
            let dir = Vec2::from_angle(heading + beam as f32 * step);
            if let Some(t) = ray_box(origin, dir, centre, body_heading)
                && t < out[beam]
            {
                out[beam] = t;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_car_ahead_and_a_car_to_the_left_match_geometry() {
        let mut out = vec![0.0; 72];
        // Ego at the origin heading east; one car 20 m ahead (its rear face at 20 − 2.2575),
        // one car 10 m to the left, parallel (its right side at 10 − 0.926).
        let others = [(Vec2::new(20.0, 0.0), 0.0), (Vec2::new(0.0, 10.0), 0.0)];
        scan(Vec2::ZERO, 0.0, 50.0, others.into_iter(), &mut out);
        assert!(
            (out[0] - (20.0 - LENGTH / 2.0)).abs() < 1e-3,
            "ahead: {}",
            out[0]
        );
        assert!(
            (out[18] - (10.0 - WIDTH / 2.0)).abs() < 1e-3,
            "left (90°): {}",
            out[18]
        );
        // 1.55 m off the axis at that distance, beam 1 (5°) passes beside the car ahead.
        assert_eq!(out[1], 50.0);
        assert_eq!(out[36], 50.0, "nothing behind");
        assert_eq!(out[54], 50.0, "nothing to the right");
        // A car 8 m ahead: beam 1 meets its rear face, 5.7425 / cos 5° away.
        scan(
            Vec2::ZERO,
            0.0,
            50.0,
            [(Vec2::new(8.0, 0.0), 0.0)].into_iter(),
            &mut out,
        );
        let expected = (8.0 - LENGTH / 2.0) / (5.0f32.to_radians()).cos();
        assert!(
            (out[1] - expected).abs() < 1e-3,
            "5°: {} vs {expected}",
            out[1]
        );
        assert!((out[71] - expected).abs() < 1e-3, "−5°: {}", out[71]);
    }

    #[test]
    fn rotated_boxes_and_out_of_range_bodies() {
        let mut out = vec![0.0; 4];
        // A car 30 m ahead turned 90°: the beam meets its side at 30 − 0.926.
        scan(
            Vec2::ZERO,
            0.0,
            50.0,
            [(Vec2::new(30.0, 0.0), std::f32::consts::FRAC_PI_2)].into_iter(),
            &mut out,
        );
        assert!((out[0] - (30.0 - WIDTH / 2.0)).abs() < 1e-3);
        scan(
            Vec2::ZERO,
            0.0,
            20.0,
            [(Vec2::new(30.0, 0.0), 0.0)].into_iter(),
            &mut out,
        );
        assert_eq!(out, vec![20.0; 4]);
        // Ego heading north sees a car due north on beam 0.
        scan(
            Vec2::ZERO,
            std::f32::consts::FRAC_PI_2,
            50.0,
            [(Vec2::new(0.0, 12.0), 0.0)].into_iter(),
            &mut out,
        );
        assert!((out[0] - (12.0 - WIDTH / 2.0)).abs() < 1e-3);
    }
}
