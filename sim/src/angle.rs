//! Angle helpers.

use std::f32::consts::{PI, TAU};

/// `angle` wrapped into (−π, π].
pub fn wrap(angle: f32) -> f32 {
    let a = (angle + PI).rem_euclid(TAU) - PI;
    if a <= -PI { a + TAU } else { a }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wraps_into_the_half_open_interval() {
        assert!((wrap(3.0 * PI) - PI).abs() < 1e-5);
        assert!((wrap(-PI) - PI).abs() < 1e-6);
        assert!((wrap(0.25) - 0.25).abs() < 1e-7);
        assert!((wrap(-TAU - 0.5) + 0.5).abs() < 1e-5);
    }
}
