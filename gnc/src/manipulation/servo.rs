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
}
