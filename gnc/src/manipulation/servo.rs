//! Position-based visual servoing, eye-in-hand (Chaumette & Hutchinson 2006; "dynamic look and
//! move": each image gives the error, the arm moves, the next image is taken at rest).
//!
//! The wrist camera rides on the gripper, so the object's pose it measures, turned into the tool
//! frame through the believed camera mounting, is free of the arm's calibration errors (joint
//! zeros, link lengths): they place the camera and the tool alike. Each step moves the tool by a
//! fraction of the measured error through the believed kinematics; what that motion gets wrong
//! the next image measures again, so the loop converges to the pose the camera sees, not the one
//! the model predicts.
//!
//! What the camera measures badly is not servoed on. The tilt of a small marker seen face on (the
//! handle's, from above) is the weak part of its pose: a few tenths of a pixel of corner error,
//! or believed focal lengths off by a few per mille in x against y, make the square look
//! foreshortened, which the pose explains as a tilt of degrees, either way (the planar pose's two
//! solutions). On the twin the handle marker's tilt is 5.5 deg off at worst with the believed
//! calibration, 3 deg with the true one, and flips between neighbouring arm poses. Held a
//! pre-grasp height away along that tilted normal, the goal jumps by centimetres and the loop does
//! not settle. [`tilt_tolerant_correction`] therefore corrects
//! the tilt of the approach axis only beyond a dead band (wider than that error, narrower than
//! what the fingers tolerate) and puts the object on the tool's approach axis as it is: the
//! object's position and the turn about the axis, which the marker gives to a millimetre and a
//! fraction of a degree, converge.

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};

/// How far the tool is from where it should be.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ServoError {
    /// Translation, m.
    pub position_m: f64,
    /// Rotation, rad.
    pub angle_rad: f64,
}

impl ServoError {
    /// The size of a correction (the desired tool pose in the present tool's frame).
    fn of(correction: &Isometry3<f64>) -> ServoError {
        ServoError {
            position_m: correction.translation.vector.norm(),
            angle_rad: correction.rotation.angle(),
        }
    }
}

/// The error of a tool that sees the object at `tool_from_object` when it should see it at
/// `goal_tool_from_object`: the desired tool pose in the present tool's frame.
pub fn tool_correction(
    tool_from_object: &Isometry3<f64>,
    goal_tool_from_object: &Isometry3<f64>,
) -> (Isometry3<f64>, ServoError) {
    let t = tool_from_object * goal_tool_from_object.inverse();
    (t, ServoError::of(&t))
}

/// A servo correction that leaves the tilt of the tool's approach axis alone within `dead_band`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TiltTolerant {
    /// The desired tool pose in the present tool's frame.
    pub correction: Isometry3<f64>,
    /// Its size (the tilt inside the dead band excluded).
    pub error: ServoError,
    /// The measured tilt between the tool's approach axis and where the object wants it, rad
    /// (inside the dead band, left as it is).
    pub tilt_rad: f64,
}

/// Like [`tool_correction`], but the rotation's swing of the tool's `axis` (a unit vector of the
/// tool frame: the approach) is corrected only beyond `dead_band` rad, down to the band's edge
/// (continuous in the measured tilt); its twist about the axis is corrected in full. The
/// translation puts the object where the goal wants it in the corrected tool's frame, so the
/// object ends on the approach axis at the goal's distance whatever tilt is left.
pub fn tilt_tolerant_correction(
    tool_from_object: &Isometry3<f64>,
    goal_tool_from_object: &Isometry3<f64>,
    axis: &Unit<Vector3<f64>>,
    dead_band: f64,
) -> TiltTolerant {
    let (full, _) = tool_correction(tool_from_object, goal_tool_from_object);
    let (swing, twist) = swing_twist(&full.rotation, axis);
    let tilt = swing.angle();
    let kept = if tilt > dead_band { (tilt - dead_band) / tilt } else { 0.0 };
    let rotation = UnitQuaternion::identity().slerp(&swing, kept) * twist;
    // The object's origin seen from the corrected tool where the goal sees it:
    // correction * goal_t = object's position in the present tool frame.
    let translation =
        tool_from_object.translation.vector - rotation * goal_tool_from_object.translation.vector;
    let correction = Isometry3::from_parts(Translation3::from(translation), rotation);
    TiltTolerant { correction, error: ServoError::of(&correction), tilt_rad: tilt }
}

/// `r` as swing * twist: the twist turns about `axis`, the swing about an axis perpendicular to
/// it (the shortest rotation taking `axis` to `r * axis`).
pub fn swing_twist(
    r: &UnitQuaternion<f64>,
    axis: &Unit<Vector3<f64>>,
) -> (UnitQuaternion<f64>, UnitQuaternion<f64>) {
    let q = r.quaternion();
    let along = axis.into_inner() * q.imag().dot(axis);
    let twist = if along.norm_squared() + q.w * q.w < 1e-24 {
        // A half turn about a perpendicular axis: no twist.
        UnitQuaternion::identity()
    } else {
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::from_parts(q.w, along))
    };
    (r * twist.inverse(), twist)
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
    use crate::manipulation::kinematics::top_down_grasps;
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
    fn swing_and_twist_compose_the_rotation_and_split_it_about_the_axis() {
        let axis = Vector3::x_axis();
        for r in [
            UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
            UnitQuaternion::from_euler_angles(2.0, 0.05, -0.02),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.3),
            // A pure twist, and a half turn about a perpendicular axis (no twist at all).
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.5),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI),
            UnitQuaternion::identity(),
        ] {
            let (swing, twist) = swing_twist(&r, &axis);
            assert!(((swing * twist).inverse() * r).angle() < 1e-12);
            // The twist keeps the axis; the swing turns it about a perpendicular axis.
            assert!((twist * axis.into_inner() - axis.into_inner()).norm() < 1e-12);
            if let Some(a) = swing.axis() {
                assert!(a.dot(&axis).abs() < 1e-12);
            }
            let tilt = (r * axis.into_inner()).dot(&axis).clamp(-1.0, 1.0).acos();
            assert!((swing.angle() - tilt).abs() < 1e-9);
        }
    }

    /// The marker's tilt error flips sign from one arm pose to the next (the planar pose's
    /// ambiguity) while its position is good: the loop that corrects the whole pose chases the
    /// goal a pre-grasp height away along the wrong normal; the tilt-tolerant one converges.
    #[test]
    fn a_flipping_tilt_error_stops_the_full_loop_not_the_tilt_tolerant_one() {
        let object = Isometry3::from_parts(
            Translation3::new(1.0, 0.05, -0.2),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 1.2),
        );
        // Seen from the pre-grasp pose 0.12 m above it, as ManipulatorControl's servo wants it:
        // the tool's x axis (its approach) along the object's -z, its x and y axes tilt it.
        let goal = (Isometry3::translation(0.0, 0.0, 0.12) * top_down_grasps(0.0)[0]).inverse();
        assert!((goal.translation.vector - Vector3::new(0.12, 0.0, 0.0)).norm() < 1e-12);
        let model_error = Isometry3::from_parts(
            Translation3::new(0.01, -0.008, 0.005),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.01, -0.01, 0.02)),
        );
        let truth = |commanded: &Isometry3<f64>| commanded * model_error;
        let tilt_error = |k: usize| {
            let s = if k.is_multiple_of(2) { 1.0 } else { -1.0 };
            Isometry3::rotation(Vector3::new(4f64.to_radians() * s, 3f64.to_radians() * s, 0.0))
        };
        let axis = Vector3::x_axis();
        let dead_band = 6f64.to_radians();
        let run = |tolerant: bool| {
            let mut commanded = object * goal.inverse() * Isometry3::translation(0.02, 0.015, 0.0);
            let mut errors = Vec::new();
            for k in 0..10 {
                // The pose the camera measures: right position, tilt off.
                let seen = truth(&commanded).inverse() * object * tilt_error(k);
                let (corr, e) = if tolerant {
                    let t = tilt_tolerant_correction(&seen, &goal, &axis, dead_band);
                    (t.correction, t.error)
                } else {
                    tool_correction(&seen, &goal)
                };
                errors.push(e);
                commanded = next_tool_pose(&commanded, &corr, 0.8, 0.06);
            }
            // Where the object really is from the tool at the end.
            let seen = truth(&commanded).inverse() * object;
            (errors, seen)
        };
        let (full, _) = run(false);
        let last = full.last().unwrap();
        assert!(last.position_m > 0.005, "{last:?}");
        let (tolerant, seen) = run(true);
        let last = tolerant.last().unwrap();
        // The reading beyond the band is corrected a little each other step: a few hundredths of
        // a degree left, far inside the servo's 1.5 deg.
        assert!(last.position_m < 1e-3 && last.angle_rad < 0.2f64.to_radians(), "{last:?}");
        // The object lies on the approach axis at the pre-grasp height.
        assert!((seen.translation.vector - goal.translation.vector).norm() < 1e-3, "{seen:?}");
    }

    /// A tilt beyond the dead band is corrected to the band's edge, and the object still ends on
    /// the approach axis.
    #[test]
    fn a_tilt_beyond_the_dead_band_is_corrected_to_its_edge() {
        let goal = Isometry3::translation(0.12, 0.0, 0.0);
        let axis = Vector3::x_axis();
        let dead_band = 6f64.to_radians();
        let object = goal * Isometry3::rotation(Vector3::new(0.0, 0.0, 15f64.to_radians()));
        let mut tool = Isometry3::identity();
        for _ in 0..30 {
            let t = tilt_tolerant_correction(&(tool.inverse() * object), &goal, &axis, dead_band);
            tool = next_tool_pose(&tool, &t.correction, 0.8, 0.06);
        }
        let t = tilt_tolerant_correction(&(tool.inverse() * object), &goal, &axis, dead_band);
        assert!((t.tilt_rad - dead_band).abs() < 0.1f64.to_radians(), "{}", t.tilt_rad.to_degrees());
        assert!(t.error.position_m < 1e-4 && t.error.angle_rad < 1e-4, "{:?}", t.error);
        let seen = tool.inverse() * object;
        assert!((seen.translation.vector - goal.translation.vector).norm() < 1e-4);
        // Inside the band nothing turns the axis.
        let small = goal * Isometry3::rotation(Vector3::new(0.0, 0.05, 0.0));
        let t = tilt_tolerant_correction(&small, &goal, &axis, dead_band);
        assert!(t.error.angle_rad < 1e-12 && t.error.position_m < 1e-12, "{:?}", t.error);
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
