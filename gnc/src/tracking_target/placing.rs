//! Where a stereo location of the target lies in `map` and what it is: its covariance through the
//! rover's pose estimate, its weight at the estimate's depth, whether its box shows the ground
//! rather than a target standing on it; boxes carried between raw and rectified pixels, and the
//! ranges a selected box of a known size allows.

use super::TrackingTargetParams;
use crate::localization::rectify::Rectification;
use crate::tracking::estimate::Location;
use crate::tracking::locate::{LocateParams, Located};
use crate::tracking::markers::compose_covariance;
use crate::tracking::size::{SelectedView, range_bounds};
use crate::tracking::template::BBox;
use framework::camera::{StereoCalibration, StereoModel};
use framework::data::{LineOfSight, PoseEstimate};
use nalgebra::{Isometry3, Matrix3, Matrix6, Point2, Point3, SymmetricEigen, Vector3};

/// The covariance a point `p` in `map` takes from the rover's pose estimate `pose` (its position,
/// and its rotation's lever arm to the point).
pub(super) fn pose_term(pose: &PoseEstimate, p: &Point3<f64>) -> Matrix3<f64> {
    let in_base = Isometry3::from((pose.pose.inverse() * p).coords);
    let (_, through_pose) = compose_covariance(&pose.pose, &pose.covariance, &in_base, &Matrix6::zeros());
    through_pose.fixed_view::<3, 3>(0, 0).into_owned()
}

/// How far the rover's pose estimate `now` (its position, and its heading through the lever arm to
/// the point `p`) may have drifted since the pose term `then` of the newest fused location.
pub(super) fn pose_drift(then: Option<Matrix3<f64>>, now: &PoseEstimate, p: &Point3<f64>) -> Matrix3<f64> {
    let Some(then) = then else { return Matrix3::zeros() };
    // The error between the two is e_then - e_now: its covariance is about the difference of
    // theirs, grown or (after a correction) shrunk; either way its size.
    let change = SymmetricEigen::new(pose_term(now, p) - then);
    let d = Matrix3::from_diagonal(&change.eigenvalues.map(f64::abs));
    change.eigenvectors * d * change.eigenvectors.transpose()
}

/// A location `loc` (rectified left camera) placed in `map` through `map_from_rect`, with its
/// errors. Relative to the rover's pose estimate (`pose`): that estimate's own error moves the
/// rover and the target alike in `map`; what it adds is how far it drifts between the images (counted as this location's noise: `fix` is the
/// pose term of the last location fused) and until the position is used (`settle`).
pub(super) fn in_map(
    loc: &Located,
    map_from_rect: &Isometry3<f64>,
    pose: &PoseEstimate,
    fix: Option<Matrix3<f64>>,
) -> Location {
    let r = map_from_rect.rotation.to_rotation_matrix().into_inner();
    let p = *map_from_rect * loc.position;
    let cov = r * loc.covariance * r.transpose() + pose_drift(fix, pose, &p);
    let bias = r * loc.bias_covariance * r.transpose();
    Location::new(p, cov, bias).with_shared(r * loc.shared)
}

/// `loc` (by the camera `map_from_rect`) with the covariances it has at the depth where the
/// estimate `expected` (`map`) lies, not at its own ([`Located::at_depth`]): else the locations
/// that noise put nearer count for more, and an estimate far away is pulled metres short, onto
/// whatever lies in front of the target. Until the estimate is `established` (it may be a wrong
/// first location's), at the farther of the two depths: never more certain than it says itself.
pub(super) fn at_expected_depth(
    loc: &Located,
    map_from_rect: &Isometry3<f64>,
    expected: Option<Point3<f64>>,
    established: bool,
    model: &StereoModel,
    params: &LocateParams,
) -> Located {
    let Some(expected) = expected else { return loc.clone() };
    let z = (map_from_rect.inverse() * expected).z;
    let z = if established { z } else { z.max(loc.position.z) };
    loc.at_depth(model, params, z)
}

/// The tilt (degrees, at most: `ground_tilt_sigmas` towards upright) of the surface the box of a
/// location shows, where that makes it a patch of the ground rather than a target standing on it
/// (`ground_tilt_deg`); None where it is not, or where the box cannot tell.
pub(super) fn on_the_ground(
    loc: &Located,
    map_from_rect: &Isometry3<f64>,
    model: &StereoModel,
    params: &TrackingTargetParams,
) -> Option<f64> {
    if params.ground_tilt_deg <= -90.0 {
        return None;
    }
    let up = map_from_rect.rotation.inverse() * Vector3::z();
    loc.surface_tilt(model, &up, params.ground_tilt_sigmas).filter(|t| *t < params.ground_tilt_deg)
}

/// Whether the pixel `centre` lies inside box `b`.
pub(super) fn inside(b: &BBox, centre: Option<(f64, f64)>) -> bool {
    centre.is_some_and(|(u, v)| (b[0]..=b[2]).contains(&u) && (b[1]..=b[3]).contains(&v))
}

/// The transform and its inverse between raw left pixels and rectified left pixels.
pub(super) fn raw_to_rect(
    rect: &Rectification,
    cal: &StereoCalibration,
    uv: &Point2<f64>,
) -> Option<Point2<f64>> {
    let r = cal.left.model.ray(uv);
    let p = rect.left_from_rect.inverse() * Point3::new(r.x, r.y, 1.0);
    rect.model.left.project(&p)
}

pub(super) fn rect_to_raw(
    rect: &Rectification,
    cal: &StereoCalibration,
    uv: &Point2<f64>,
) -> Option<Point2<f64>> {
    let r = rect.model.left.ray(uv);
    cal.left.model.project(&(rect.left_from_rect * Point3::new(r.x, r.y, 1.0)))
}

/// The box spanning the images of a box's corners and edge midpoints under `f`.
pub(super) fn map_box(b: &BBox, f: impl Fn(&Point2<f64>) -> Option<Point2<f64>>) -> Option<BBox> {
    let (cx, cy) = (0.5 * (b[0] + b[2]), 0.5 * (b[1] + b[3]));
    let pts = [
        (b[0], b[1]),
        (b[2], b[1]),
        (b[0], b[3]),
        (b[2], b[3]),
        (cx, b[1]),
        (cx, b[3]),
        (b[0], cy),
        (b[2], cy),
    ];
    let mut out = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
    for (u, v) in pts {
        let p = f(&Point2::new(u, v))?;
        out = [out[0].min(p.x), out[1].min(p.y), out[2].max(p.x), out[3].max(p.y)];
    }
    Some(out)
}

/// The line of sight (in `map`) through the centre of box `b` of the rectified left image whose
/// camera is at `map_from_rect`.
pub(super) fn sight_through(rect: &Rectification, map_from_rect: &Isometry3<f64>, b: &BBox) -> LineOfSight {
    let ray = rect.model.left.ray(&Point2::new(0.5 * (b[0] + b[2]), 0.5 * (b[1] + b[3])));
    LineOfSight {
        origin: Point3::from(map_from_rect.translation.vector),
        direction: (map_from_rect.rotation * Vector3::new(ray.x, ray.y, 1.0)).normalize(),
    }
}

/// The selected box `bbox` (rectified pixels) seen by the rectified left camera `map_from_rect`.
pub(super) fn selected_view(map_from_rect: &Isometry3<f64>, bbox: &BBox) -> SelectedView {
    let (w, h) = (bbox[2] - bbox[0], bbox[3] - bbox[1]);
    SelectedView { camera: Point3::from(map_from_rect.translation.vector), width_px: w, extent_px: w.max(h) }
}

/// [`TrackingTarget::size_bounds`], of the parts it reads: none for a target that may move (its
/// range from where it was selected changes) or whose selected box was cut by the image's border
/// (`clipped`: smaller than the target).
pub(super) fn size_bounds(
    params: &TrackingTargetParams,
    target: &str,
    view: Option<SelectedView>,
    clipped: bool,
    rect: &Rectification,
) -> Option<(f64, f64)> {
    if params.max_target_speed_mps > 0.0 || clipped {
        return None;
    }
    let extent = params.known_sizes.get(target)?;
    range_bounds(*extent, rect.model.left.pinhole.fx, view?.extent_px, params.size_tolerance)
}

/// Whether a re-detection candidate's own box `bbox` (rectified pixels, camera `map_from_rect`),
/// located at `p` (`map`), is as large as a target of known size is at that range: a look-alike
/// matched at another size (the end of the rover's mast shadow a few metres off, matched as a
/// canister 25 m away) is not the target. True where the size says nothing (`size_bounds`: an
/// unknown size, a target that may move, a selection cut by the image's border).
pub(super) fn box_fits(
    params: &TrackingTargetParams,
    target: &str,
    clipped: bool,
    rect: &Rectification,
    map_from_rect: &Isometry3<f64>,
    bbox: &BBox,
    p: &Point3<f64>,
) -> bool {
    let own = selected_view(map_from_rect, bbox);
    own.allows(p, size_bounds(params, target, Some(own), clipped, rect))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tracking::locate::LocateNoise;
    use framework::camera::CameraModel;

    /// The head pair's model, a camera somewhere in map (turned about two axes), and a location
    /// 14 m ahead of it with its image errors (its covariances not yet worked out).
    fn scene() -> (StereoModel, Isometry3<f64>, Located) {
        let cam = CameraModel::from_hfov(640, 480, 70f64.to_radians(), "l");
        let model = StereoModel { left: cam.clone(), right: cam, baseline: 0.25 };
        let map_from_rect = Isometry3::new(Vector3::new(3.0, -2.0, 1.3), Vector3::new(1.2, -0.3, 0.8));
        let noise = LocateNoise { var_u: 0.3, var_v: 0.3, var_d: 0.05, var_bias_d: 0.01, shared_d: 0.4 };
        let measured = Located {
            position: Point3::new(0.4, -0.1, 14.0),
            covariance: Matrix3::zeros(),
            bias_covariance: Matrix3::zeros(),
            shared: Vector3::zeros(),
            noise,
            disparity: model.disparity(14.0),
            matched: 40,
            foreground: 20,
            profile: None,
        };
        (model, map_from_rect, measured)
    }

    #[test]
    fn a_location_is_weighed_at_the_estimates_depth_and_before_it_is_established_at_the_farther() {
        let p = LocateParams::default();
        let (model, map_from_rect, measured) = scene();
        let own = measured.at_depth(&model, &p, 14.0);
        let at = |z: f64| measured.at_depth(&model, &p, z);
        let close = |a: &Located, b: &Located| {
            let near = |x: f64, y: f64| x <= 1e-9 * y;
            a.position == b.position
                && near((a.covariance - b.covariance).norm(), b.covariance.norm())
                && near((a.bias_covariance - b.bias_covariance).norm(), b.bias_covariance.norm())
                && near((a.shared - b.shared).norm(), b.shared.norm())
        };
        let expected_at = |z: f64| Some(map_from_rect * Point3::new(-0.3, 0.2, z));
        let weighed = |z: f64, established: bool| {
            at_expected_depth(&own, &map_from_rect, expected_at(z), established, &model, &p)
        };
        // Established: at the estimate's depth, nearer or farther.
        assert!(close(&weighed(18.0, true), &at(18.0)));
        assert!(close(&weighed(10.0, true), &at(10.0)));
        // Not yet: never more certain than at its own depth.
        assert!(close(&weighed(18.0, false), &at(18.0)));
        assert!(close(&weighed(10.0, false), &own));
        // No estimate: as measured.
        assert!(close(&at_expected_depth(&own, &map_from_rect, None, true, &model, &p), &own));
        // Farther means less certain along the line of sight (its sigma as the depth squared).
        let ratio = at(18.0).covariance[(2, 2)] / own.covariance[(2, 2)];
        assert!(ratio > (18.0f64 / 14.0).powi(3), "{ratio}");
        // The share of the calibration's disparity error grows as the depth squared, along the
        // line of sight towards the camera.
        let (s14, s18) = (own.shared, at(18.0).shared);
        assert!((s18.norm() / s14.norm() - (18.0f64 / 14.0).powi(2)).abs() < 1e-9);
        assert!(
            s14.dot(&own.position.coords) < 0.0
                && s14.normalize().dot(&own.position.coords.normalize()) < -0.999
        );
    }

    #[test]
    fn a_location_placed_in_map_keeps_its_errors_apart_and_turned_with_it() {
        let p = LocateParams::default();
        let (model, map_from_rect, measured) = scene();
        let loc = measured.at_depth(&model, &p, 14.0);
        let pose = PoseEstimate::planar("map", 1.0, 2.0, 0.0, 0.3);
        let placed = in_map(&loc, &map_from_rect, &pose, None);
        let r = map_from_rect.rotation.to_rotation_matrix().into_inner();
        assert!((placed.position - map_from_rect * loc.position).norm() < 1e-12);
        assert!((placed.shared - r * loc.shared).norm() < 1e-12);
        assert!((placed.bias - r * loc.bias_covariance * r.transpose()).norm() < 1e-12);
        // What is left once the biases are taken out is the image's noise, turned.
        let left = placed.covariance - placed.bias - placed.shared * placed.shared.transpose();
        let image = loc.covariance - loc.bias_covariance - loc.shared * loc.shared.transpose();
        assert!((left - r * image * r.transpose()).norm() < 1e-9 * left.norm());
        assert!(SymmetricEigen::new(left).eigenvalues.min() > 0.0);
    }

    #[test]
    fn a_candidate_box_fits_only_where_a_target_of_known_size_spans_it_at_its_range() {
        let cam = CameraModel::from_hfov(640, 480, 70f64.to_radians(), "l");
        let calibration = |model: CameraModel| framework::camera::CameraCalibration {
            model,
            mount: "head".into(),
            mount_from_optical: Isometry3::identity(),
        };
        let rect = Rectification::new(&StereoCalibration {
            left: calibration(cam.clone()),
            right: cam,
            left_from_right: Isometry3::translation(0.25, 0.0, 0.0),
        });
        let mut params = TrackingTargetParams::default();
        params.known_sizes.insert("canister".into(), [0.2, 0.25]);
        let map_from_rect = Isometry3::new(Vector3::new(3.0, -2.0, 1.3), Vector3::new(1.2, -0.3, 0.8));
        // 3 m ahead, the canister's 0.22 m spans this many pixels; its box is 0.8 as wide.
        let p = map_from_rect * Point3::new(0.0, 0.0, 3.0);
        let side = rect.model.left.pinhole.fx * 0.22 / 3.0;
        let sized = |k: f64| [300.0, 200.0, 300.0 + 0.8 * k * side, 200.0 + k * side];
        let at = |target: &str, clipped: bool, params: &TrackingTargetParams, k: f64| {
            box_fits(params, target, clipped, &rect, &map_from_rect, &sized(k), &p)
        };
        // The canister's own size there: fits; a third of it (the end of a shadow matched as a
        // canister far away) or three times it: not.
        assert!(at("canister", false, &params, 1.0));
        assert!(!at("canister", false, &params, 1.0 / 3.0));
        assert!(!at("canister", false, &params, 3.0));
        // Where the size says nothing, anything fits: an unknown size, a selection cut by the
        // border, a target that may move.
        assert!(at("rock", false, &params, 1.0 / 3.0));
        assert!(at("canister", true, &params, 1.0 / 3.0));
        let moving = TrackingTargetParams { max_target_speed_mps: 0.5, ..params.clone() };
        assert!(at("canister", false, &moving, 1.0 / 3.0));
    }
}
