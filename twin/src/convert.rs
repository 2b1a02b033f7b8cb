//! Conversions between our math (nalgebra, f64, SI) and rapier's (glam, f32). The only place that
//! knows both.

use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use rapier3d::math::{Pose, Rotation, Vector};

/// nalgebra f64 vector to rapier vector.
pub fn to_rapier(v: &Vector3<f64>) -> Vector {
    Vector::new(v.x as f32, v.y as f32, v.z as f32)
}
/// nalgebra f64 point to rapier vector.
pub fn point_to_rapier(p: &Point3<f64>) -> Vector {
    Vector::new(p.x as f32, p.y as f32, p.z as f32)
}
/// rapier vector to nalgebra f64.
pub fn from_rapier(v: Vector) -> Vector3<f64> {
    Vector3::new(v.x as f64, v.y as f64, v.z as f64)
}
/// nalgebra f64 rotation to rapier.
pub fn rot_to_rapier(q: &UnitQuaternion<f64>) -> Rotation {
    let q32: UnitQuaternion<f32> = q.cast();
    q32.into()
}
/// rapier rotation to nalgebra f64.
pub fn rot_from_rapier(q: &Rotation) -> UnitQuaternion<f64> {
    let q32: UnitQuaternion<f32> = (*q).into();
    q32.cast()
}
/// nalgebra f64 isometry to rapier pose.
pub fn pose_to_rapier(i: &Isometry3<f64>) -> Pose {
    let i32: Isometry3<f32> = i.cast();
    i32.into()
}
/// rapier pose to nalgebra f64 isometry.
pub fn pose_from_rapier(p: &Pose) -> Isometry3<f64> {
    let i32: Isometry3<f32> = (*p).into();
    i32.cast()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips() {
        let i = Isometry3::new(Vector3::new(1.0, -2.0, 3.0), Vector3::new(0.1, 0.2, -0.3));
        let back = pose_from_rapier(&pose_to_rapier(&i));
        assert!((back.translation.vector - i.translation.vector).norm() < 1e-6);
        assert!(back.rotation.angle_to(&i.rotation) < 1e-6);
        assert_eq!(from_rapier(to_rapier(&Vector3::new(0.5, 0.25, 2.0))), Vector3::new(0.5, 0.25, 2.0));
    }
}
