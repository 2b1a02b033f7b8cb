//! Fiducial markers (seed 000, 8.4): the 6-DoF pose of a marker, or of a whole marker table, from
//! the corners [`MarkerDetector`](crate::tracking::marker_detector::MarkerDetector) finds.
//!
//! A marker's pose starts from kornia-3d's planar pose of its four corners (both of its solutions
//! when there are two), then every estimate, one marker's or a table's, is refined by weighted
//! Gauss-Newton on the reprojection error of all the corners it has (corners undistorted through
//! the believed camera model), which also gives its covariance. A table's corners are not coplanar
//! when markers on several faces are seen (the canister), which removes the planar ambiguity that
//! a single small marker suffers from.

use super::marker_detector::Detected;
use crate::localization::motion::{Correspondence, Intrinsics, RefineParams, refine};
use framework::camera::CameraModel;
use kornia_3d::camera::PinholeCamera;
use kornia_3d::pose::estimate_planar_pose;
use kornia_algebra::{Vec2F64, Vec3F64};
use nalgebra::{Isometry3, Matrix3, Matrix6, Point2, Point3, Rotation3, Translation3, UnitQuaternion};

/// The corners of a square marker of edge `size`, in its own frame (x right, y up as printed), in
/// the order [`Detected::corners`] holds them: top-left, top-right, bottom-right, bottom-left.
pub fn marker_corners(size: f64) -> [Point3<f64>; 4] {
    let s = size / 2.0;
    [Point3::new(-s, s, 0.0), Point3::new(s, s, 0.0), Point3::new(s, -s, 0.0), Point3::new(-s, -s, 0.0)]
}

/// A pose fitted to marker corners.
#[derive(Clone, Debug)]
pub struct PoseFit {
    /// Pose of the object (or marker) frame in the camera's optical frame.
    pub camera_from_object: Isometry3<f64>,
    /// Covariance of (x, y, z, roll, pitch, yaw) of that pose in the optical frame (see
    /// [`position_rotation_covariance`]).
    pub covariance: Matrix6<f64>,
    /// Root-mean-square reprojection error, pixels.
    pub rmse_px: f64,
    /// Which corners the fit kept.
    pub inliers: Vec<bool>,
}

/// Corner observations of one object: its points (object frame) and where the raw image shows them.
#[derive(Clone, Debug, Default)]
pub struct Corners {
    /// Object-frame points, m.
    pub points: Vec<Point3<f64>>,
    /// Raw image coordinates, pixels.
    pub pixels: Vec<Point2<f64>>,
}

impl Corners {
    /// Adds a marker at `object_from_marker` of edge `size` seen at `detected`.
    pub fn add(&mut self, object_from_marker: &Isometry3<f64>, size: f64, detected: &Detected) {
        for (p, uv) in marker_corners(size).iter().zip(&detected.corners) {
            self.points.push(object_from_marker * p);
            self.pixels.push(*uv);
        }
    }
}

/// The undistorted pinhole of `model`, and a raw pixel's image through it.
fn ideal(model: &CameraModel, uv: &Point2<f64>) -> Point2<f64> {
    let k = &model.pinhole;
    let n = model.ray(uv);
    Point2::new(k.fx * n.x + k.cx, k.fy * n.y + k.cy)
}

fn intrinsics(model: &CameraModel) -> Intrinsics {
    let k = &model.pinhole;
    Intrinsics { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy }
}

/// Refines `initial` over `corners` seen by `model` (corner noise `sigma_px`).
pub fn fit(
    model: &CameraModel,
    corners: &Corners,
    initial: &Isometry3<f64>,
    sigma_px: f64,
) -> Option<PoseFit> {
    let k = intrinsics(model);
    let obs: Vec<Correspondence> = corners
        .points
        .iter()
        .zip(&corners.pixels)
        .map(|(p, uv)| Correspondence { point: *p, covariance: Matrix3::zeros(), pixel: ideal(model, uv) })
        .collect();
    let params = RefineParams { pixel_sigma: sigma_px, huber: 3.0, outlier_sigma: 6.0, iterations: 20 };
    let m = refine(&k, &obs, initial, &vec![true; obs.len()], &params)?;
    Some(PoseFit {
        camera_from_object: m.pose,
        covariance: position_rotation_covariance(&m.pose, &m.covariance),
        rmse_px: m.rmse_px,
        inliers: m.inliers,
    })
}

/// The pose of one marker of edge `size` from its corners alone: kornia-3d's planar pose (each of
/// its solutions), refined; the better refined solution. None when no solution puts the marker in
/// front of the camera.
pub fn marker_pose(model: &CameraModel, detected: &Detected, size: f64, sigma_px: f64) -> Option<PoseFit> {
    let k = &model.pinhole;
    let camera = PinholeCamera { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy, ..PinholeCamera::IDENTITY };
    let object = marker_corners(size);
    let object_pts = object.map(|p| Vec3F64::new(p.x, p.y, p.z));
    let image_pts = detected.corners.map(|uv| {
        let p = ideal(model, &uv);
        Vec2F64::new(p.x, p.y)
    });
    let pair = estimate_planar_pose(&object_pts, &image_pts, &camera, 50).ok()?;
    let mut corners = Corners::default();
    corners.add(&Isometry3::identity(), size, detected);
    std::iter::once(pair.best)
        .chain(pair.second)
        .filter(|s| s.error.is_finite())
        .filter_map(|s| {
            let m = s.pose.rotation.to_cols_array();
            let r = Matrix3::from_column_slice(&m);
            let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r));
            let t = Translation3::new(s.pose.translation.x, s.pose.translation.y, s.pose.translation.z);
            let initial = Isometry3::from_parts(t, rot);
            (initial.translation.vector.z > 0.0).then(|| fit(model, &corners, &initial, sigma_px)).flatten()
        })
        .filter(|f| f.camera_from_object.translation.vector.z > 0.0)
        .min_by(|a, b| a.rmse_px.total_cmp(&b.rmse_px))
}

/// The covariance of (x, y, z, roll, pitch, yaw) of `pose` (position and small rotations about
/// the reference frame's axes) from the covariance of a left perturbation ξ = (ρ, φ) of it
/// (T ← Exp(ξ) T, whose translation part moves the position by ρ + φ × t).
pub fn position_rotation_covariance(pose: &Isometry3<f64>, left: &Matrix6<f64>) -> Matrix6<f64> {
    let mut j = Matrix6::identity();
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&-pose.translation.vector.cross_matrix());
    j * left * j.transpose()
}

/// The pose `a * b` and its covariance (both in [`position_rotation_covariance`]'s convention),
/// from the covariances of `a` (in its reference frame) and `b` (in `a`'s child frame),
/// independent.
pub fn compose_covariance(
    a: &Isometry3<f64>,
    a_cov: &Matrix6<f64>,
    b: &Isometry3<f64>,
    b_cov: &Matrix6<f64>,
) -> (Isometry3<f64>, Matrix6<f64>) {
    let r = a.rotation.to_rotation_matrix().into_inner();
    // Position a.t + R b.t: moved by a's rotation about a's origin, and by b's own errors turned.
    let mut ja = Matrix6::identity();
    ja.fixed_view_mut::<3, 3>(0, 3).copy_from(&-(r * b.translation.vector).cross_matrix());
    let mut jb = Matrix6::zeros();
    jb.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    jb.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    (a * b, ja * a_cov * ja.transpose() + jb * b_cov * jb.transpose())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn camera() -> CameraModel {
        let mut m = CameraModel::from_hfov(640, 480, 70f64.to_radians(), "cam");
        m.distortion.k1 = -0.02;
        m
    }

    /// A marker seen by `model` at `pose`, its corners projected exactly.
    fn seen(model: &CameraModel, pose: &Isometry3<f64>, size: f64) -> Detected {
        let c = marker_corners(size).map(|p| model.project(&(pose * p)).unwrap());
        Detected { id: 1, corners: c, decision_margin: 100.0, hamming: 0 }
    }

    fn angle_deg(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
        a.rotation.angle_to(&b.rotation).to_degrees()
    }

    #[test]
    fn exact_corners_give_the_exact_pose_through_distortion() {
        let model = camera();
        let pose = Isometry3::from_parts(
            Translation3::new(0.2, -0.1, 1.5),
            UnitQuaternion::from_euler_angles(2.6, 0.3, 0.2),
        );
        let fit = marker_pose(&model, &seen(&model, &pose, 0.072), 0.072, 0.2).unwrap();
        assert!((fit.camera_from_object.translation.vector - pose.translation.vector).norm() < 1e-6);
        assert!(angle_deg(&fit.camera_from_object, &pose) < 1e-4);
        assert!(fit.rmse_px < 1e-6);
    }

    #[test]
    fn a_table_of_markers_on_two_faces_is_fitted_from_all_its_corners() {
        let model = camera();
        // Two faces of a box 0.1 m wide, at 45 degrees to the camera.
        let faces = [
            Isometry3::from_parts(
                Translation3::new(0.05, 0.0, 0.0),
                UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0),
            ),
            Isometry3::from_parts(
                Translation3::new(0.0, 0.0, -0.05),
                UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0),
            ),
        ];
        let pose = Isometry3::from_parts(
            Translation3::new(0.1, 0.05, 1.2),
            UnitQuaternion::from_euler_angles(0.1, 0.785, 0.05),
        );
        let mut corners = Corners::default();
        for f in &faces {
            let d = seen(&model, &(pose * f), 0.07);
            corners.add(f, 0.07, &d);
        }
        let start = Isometry3::from_parts(
            Translation3::from(pose.translation.vector + Vector3::new(0.02, -0.01, 0.05)),
            pose.rotation * UnitQuaternion::from_euler_angles(0.05, -0.04, 0.03),
        );
        let fit = fit(&model, &corners, &start, 0.2).unwrap();
        assert!((fit.camera_from_object.translation.vector - pose.translation.vector).norm() < 1e-6);
        assert!(angle_deg(&fit.camera_from_object, &pose) < 1e-4);
    }

    #[test]
    fn composed_covariance_adds_the_lever_arm_of_the_first_rotation() {
        // a: 1 rad^2 of yaw alone; b: 2 m ahead along x, exact. The composition's y varies by
        // 2 m per rad of yaw.
        let a = Isometry3::identity();
        let mut a_cov = Matrix6::zeros();
        a_cov[(5, 5)] = 1.0;
        let b = Isometry3::translation(2.0, 0.0, 0.0);
        let (_, c) = compose_covariance(&a, &a_cov, &b, &Matrix6::zeros());
        assert!(
            (c[(1, 1)] - 4.0).abs() < 1e-12 && c[(0, 0)].abs() < 1e-12 && (c[(5, 5)] - 1.0).abs() < 1e-12
        );
    }
}
