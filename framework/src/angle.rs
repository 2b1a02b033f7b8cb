//! Angles.

use std::f64::consts::{PI, TAU};

/// An angle wrapped to [-pi, pi), rad.
pub fn wrap(a: f64) -> f64 {
    (a + PI).rem_euclid(TAU) - PI
}

/// Tilt of a body from the vertical (the angle between its z axis and the world's), degrees.
pub fn tilt_deg(pose: &nalgebra::Isometry3<f64>) -> f64 {
    (pose.rotation * nalgebra::Vector3::z()).z.clamp(-1.0, 1.0).acos().to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wraps_into_minus_pi_to_pi() {
        assert_eq!(wrap(0.5), 0.5);
        assert!((wrap(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
        assert!((wrap(-3.0 * PI / 2.0) - PI / 2.0).abs() < 1e-12);
        assert_eq!(wrap(PI), -PI);
    }
}
