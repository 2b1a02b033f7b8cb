//! Position-based visual servoing, eye-in-hand (Chaumette & Hutchinson 2006; "dynamic look and
//! move": each image gives the error, the arm moves, the next image is taken at rest).
//!
//! The wrist camera rides on the gripper, so the object's pose it measures, turned into the tool
//! frame through the believed camera mounting, is free of the arm's calibration errors (joint
//! zeros, link lengths): they place the camera and the tool alike. Each step moves the tool by a
//! fraction of the measured error through the believed kinematics; what that motion gets wrong
//! the next image measures again, so the loop converges to the pose the camera sees, not the one
//! the model predicts.

use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// How far the tool is from where it should be.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ServoError {
    /// Translation, m.
    pub position_m: f64,
    /// Rotation, rad.
    pub angle_rad: f64,
}

/// The error of a tool that sees the object at `tool_from_object` when it should see it at
/// `goal_tool_from_object`: the desired tool pose in the present tool's frame.
pub fn tool_correction(
    tool_from_object: &Isometry3<f64>,
    goal_tool_from_object: &Isometry3<f64>,
) -> (Isometry3<f64>, ServoError) {
    let t = tool_from_object * goal_tool_from_object.inverse();
    let e = ServoError { position_m: t.translation.vector.norm(), angle_rad: t.rotation.angle() };
    (t, e)
}

/// The next tool pose in the root frame: the believed present pose `base_from_tool` moved by
/// `gain` (0..1] of the correction, its translation at most `max_step_m`.
pub fn next_tool_pose(
    base_from_tool: &Isometry3<f64>,
    correction: &Isometry3<f64>,
    gain: f64,
    max_step_m: f64,
) -> Isometry3<f64> {
    let mut v = correction.translation.vector * gain;
    if v.norm() > max_step_m {
        v *= max_step_m / v.norm();
    }
    let r = UnitQuaternion::identity().slerp(&correction.rotation, gain);
    base_from_tool * Isometry3::from_parts(Translation3::from(v), r)
}

/// The mean of poses that scatter a little (views of one object at rest): the mean translation
/// and the normalized mean of the unit quaternions, each turned to the first's hemisphere (the
/// chordal L2 mean, within a small fraction of a degree of the geodesic one at these spreads).
/// The identity when there are none.
pub fn mean_pose(poses: &[Isometry3<f64>]) -> Isometry3<f64> {
    let Some(first) = poses.first() else { return Isometry3::identity() };
    let n = poses.len() as f64;
    let t = poses.iter().map(|p| p.translation.vector).sum::<nalgebra::Vector3<f64>>() / n;
    let q0 = first.rotation.coords;
    let q = poses
        .iter()
        .map(|p| if p.rotation.coords.dot(&q0) < 0.0 { -p.rotation.coords } else { p.rotation.coords })
        .sum::<nalgebra::Vector4<f64>>();
    let rotation = UnitQuaternion::from_quaternion(nalgebra::Quaternion::from(q));
    Isometry3::from_parts(Translation3::from(t), rotation)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// A "robot" whose believed kinematics are off by a fixed rigid error: the loop closed on what
    /// the camera sees converges to the goal however wrong the open-loop prediction is.
    #[test]
    fn look_and_move_converges_despite_a_wrong_model() {
        let object = Isometry3::translation(1.0, 0.2, -0.2);
        let goal_tool_from_object = Isometry3::translation(0.0, 0.0, 0.12);
        // The truth: the tool is where the model says, composed with this error.
        let model_error = Isometry3::from_parts(
            Translation3::new(0.02, -0.015, 0.01),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.02, -0.01, 0.03)),
        );
        let truth = |commanded: &Isometry3<f64>| commanded * model_error;
        // Open loop: commanded where the goal is believed to be.
        let mut commanded = object * goal_tool_from_object.inverse();
        let open = tool_correction(&(truth(&commanded).inverse() * object), &goal_tool_from_object).1;
        assert!(open.position_m > 0.02, "{open:?}");
        let mut last = open;
        for _ in 0..8 {
            let seen = truth(&commanded).inverse() * object;
            let (corr, e) = tool_correction(&seen, &goal_tool_from_object);
            last = e;
            commanded = next_tool_pose(&commanded, &corr, 0.8, 0.05);
        }
        assert!(last.position_m < 1e-3 && last.angle_rad < 1e-3, "{last:?}");
    }

    #[test]
    fn the_mean_of_scattered_views_is_their_centre() {
        use nalgebra::Vector3;
        let centre = Isometry3::from_parts(
            Translation3::new(0.1, -0.02, 0.3),
            UnitQuaternion::from_euler_angles(0.3, -0.2, 2.0),
        );
        // Symmetric scatter: +-3 mm and +-1.5 deg about each axis, and one quaternion negated
        // (the same rotation).
        let mut views = Vec::new();
        for axis in [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()] {
            for s in [-1.0, 1.0] {
                let d = Isometry3::from_parts(
                    Translation3::from(axis.into_inner() * 0.003 * s),
                    UnitQuaternion::from_axis_angle(&axis, (1.5f64 * s).to_radians()),
                );
                views.push(centre * d);
            }
        }
        let q = views[0].rotation.into_inner();
        views[0].rotation = UnitQuaternion::new_unchecked(-q);
        let m = mean_pose(&views);
        assert!((m.translation.vector - centre.translation.vector).norm() < 1e-4);
        assert!((m.rotation.inverse() * centre.rotation).angle() < 0.01f64.to_radians());
        let one = mean_pose(&views[..1]);
        assert!((one.translation.vector - views[0].translation.vector).norm() < 1e-12);
        assert!((one.rotation.inverse() * views[0].rotation).angle() < 1e-9);
        assert_eq!(mean_pose(&[]), Isometry3::identity());
    }
}
