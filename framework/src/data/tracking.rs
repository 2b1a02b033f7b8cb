//! Vision products (seed 000, 8.1 and 8.4): fiducial markers seen in an image and the object poses
//! they give, and the operator-selected target as a tracker follows it.

use crate::time::Time;
use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, Vector3};
use serde::{Deserialize, Serialize};

/// One fiducial marker found in an image.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MarkerObservation {
    /// The marker's id (tag36h11).
    pub id: u32,
    /// The object kind whose table carries this id in the object database; None for an unknown id.
    pub object: Option<String>,
    /// The corners in raw (distorted) image coordinates, pixels, in the order of the marker frame's
    /// corners (-s, +s), (+s, +s), (+s, -s), (-s, -s): top-left, top-right, bottom-right,
    /// bottom-left of the tag as printed.
    pub corners: [[f64; 2]; 4],
    /// The decoder's decision margin (higher: more confident).
    pub decision_margin: f64,
    /// Pose of the marker frame in the camera's optical frame from this marker alone, when its
    /// size is known (its id is in the database).
    pub camera_from_marker: Option<Isometry3<f64>>,
    /// Root-mean-square reprojection error of that pose, pixels (NaN without one).
    pub rmse_px: f64,
}

/// The markers found in one image.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MarkerDetections {
    /// The camera device.
    pub camera: String,
    /// The image's optical frame.
    pub frame: String,
    /// The image's capture time.
    pub stamp: Time,
    /// Image size, pixels (width, height).
    pub size: [u32; 2],
    /// What was found.
    pub markers: Vec<MarkerObservation>,
    /// The windows searched at full resolution besides the whole image (around where markers
    /// were expected), pixels: [u_min, v_min, u_max, v_max].
    pub regions: Vec<[f64; 4]>,
}

/// An object's pose from its marker table.
///
/// Covariances are over (x, y, z, roll, pitch, yaw) of the object frame in the named frame, m^2
/// and rad^2, small rotations about that frame's axes (as [`super::PoseEstimate`]'s).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectPose {
    /// The object kind (the database's name: `canister`, `marker_table`).
    pub object: String,
    /// The markers of its table used in this estimate.
    pub markers: Vec<u32>,
    /// Capture time of the image the pose was measured in.
    pub stamp: Time,
    /// Pose of the object frame in `base_link` at `stamp`: what the arm needs, free of the
    /// localization's uncertainty.
    pub base_from_object: Isometry3<f64>,
    /// Its covariance (image noise, through the believed calibration).
    pub base_covariance: Matrix6<f64>,
    /// Pose of the object frame in `map`, through the rover's pose estimate at `stamp`.
    pub map_from_object: Isometry3<f64>,
    /// Its covariance, the pose estimate's included.
    pub map_covariance: Matrix6<f64>,
    /// Root-mean-square reprojection error of the table's corners, pixels.
    pub rmse_px: f64,
    /// Images in which the object was measured since it was last (re)acquired after an absence
    /// (1: first sight; the tracker's `lost_after_s` sets how long an absence is).
    pub seen_frames: u32,
}

/// The objects whose poses the markers in one image gave.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectPoses {
    /// The camera device.
    pub camera: String,
    /// The image's capture time.
    pub stamp: Time,
    /// One pose per object seen.
    pub objects: Vec<ObjectPose>,
}

/// What a target tracker is doing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TargetStatus {
    /// Followed from the last image.
    Tracking,
    /// Found again after a loss.
    Redetected,
    /// Not in this image (occluded, out of view, or changed beyond recognition).
    Lost,
}

/// A ray in `map`: from a camera's centre through a point of its image, at the image's stamp.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LineOfSight {
    /// The camera's optical centre, m.
    pub origin: Point3<f64>,
    /// Unit direction.
    pub direction: Vector3<f64>,
}

impl LineOfSight {
    /// The point `range` metres along the ray.
    pub fn at(&self, range: f64) -> Point3<f64> {
        self.origin + self.direction * range
    }
}

/// A place ruled out for a target: an object there was found not to be it (the wrist camera saw
/// no canister where the head camera's estimate brought the rover), so nothing located within
/// `radius_m` of it (horizontally) is taken for the target again.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExcludedPlace {
    /// The object's place in `map`, m.
    pub position: Point3<f64>,
    /// How far round it (horizontally), m.
    pub radius_m: f64,
}

impl ExcludedPlace {
    /// Whether `p` (in `map`) lies within the excluded place.
    pub fn holds(&self, p: &Point3<f64>) -> bool {
        (p.xy() - self.position.xy()).norm() <= self.radius_m
    }
}

/// An operator-selected target as a tracker follows it (seed 000, 8.1): where it is in the image,
/// and where it is in the world as stereo locates it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetTrack {
    /// What the target is (`canister`).
    pub target: String,
    /// The camera device.
    pub camera: String,
    /// The image's capture time.
    pub stamp: Time,
    /// This image's outcome.
    pub status: TargetStatus,
    /// Best correlation with the learnt appearance, -1 to 1.
    pub confidence: f64,
    /// The target's box in the raw (distorted) left image, pixels: [u_min, v_min, u_max, v_max]
    /// (the last known one when lost).
    pub bbox: [f64; 4],
    /// Its position in `map` (stereo, fused over the images so far) at `position_stamp`, m; None
    /// until located.
    pub position: Option<Point3<f64>>,
    /// When the target was at `position`: the capture time of the newest location fused.
    pub position_stamp: Option<Time>,
    /// Its velocity in `map`, fitted to its recent locations, m/s (zero for a target the tracker is
    /// told is static).
    pub velocity: Vector3<f64>,
    /// How long past `position_stamp` the velocity carries the position, s (a target unseen for
    /// longer may have stopped or turned: its covariance then says how far it may be).
    pub velocity_horizon_s: f64,
    /// Its covariance relative to the rover's pose estimate (whose own error moves the rover and
    /// the target alike in `map`), m^2.
    pub covariance: Matrix3<f64>,
    /// Distance from the camera at the last location, m.
    pub range_m: Option<f64>,
    /// For a target of known size, the ranges along `line_of_sight` (from its origin) between
    /// which the selected box's size puts it, m: where it is before stereo ranges it (a box of a
    /// few pixels 25 m away). None for a target of unknown size or one that may move.
    #[serde(default)]
    pub sized_range_m: Option<[f64; 2]>,
    /// This image's stereo location (in `map`), when it gave one.
    pub measured: Option<Point3<f64>>,
    /// Images located so far.
    pub located: u32,
    /// The line of sight through the box's centre (the last known one when lost); None while the
    /// camera cannot be placed. Where the target is seen before stereo can range it.
    pub line_of_sight: Option<LineOfSight>,
    /// The places ruled out for the target (none until one is rejected).
    #[serde(default)]
    pub excluded: Vec<ExcludedPlace>,
}

/// A target at `position` at time `from`, moving at `velocity`, carried to `to`: never backwards,
/// and at most `horizon_s` (a target unseen longer may have stopped or turned).
pub fn carried(
    position: &Point3<f64>,
    velocity: &Vector3<f64>,
    horizon_s: f64,
    from: Time,
    to: Time,
) -> Point3<f64> {
    position + velocity * (to - from).as_secs_f64().clamp(0.0, horizon_s)
}

impl TargetTrack {
    /// A track of `target` in `camera`'s image of `stamp`, tracked but not located yet: no box,
    /// no position, no range, nothing ruled out.
    pub fn unlocated(target: &str, camera: &str, stamp: Time) -> Self {
        TargetTrack {
            target: target.to_string(),
            camera: camera.to_string(),
            stamp,
            status: TargetStatus::Tracking,
            confidence: 1.0,
            bbox: [0.0; 4],
            position: None,
            position_stamp: None,
            velocity: Vector3::zeros(),
            velocity_horizon_s: 0.0,
            covariance: Matrix3::zeros(),
            range_m: None,
            sized_range_m: None,
            measured: None,
            located: 0,
            line_of_sight: None,
            excluded: Vec::new(),
        }
    }

    /// Where the target is at `t`: its position carried by its velocity from `position_stamp`
    /// (see [`carried`]).
    pub fn position_at(&self, t: Time) -> Option<Point3<f64>> {
        let p = self.position?;
        Some(self.position_stamp.map_or(p, |s| carried(&p, &self.velocity, self.velocity_horizon_s, s, t)))
    }
}

/// What a visual-tracking coordinator is doing (seed 000, 8.1): its command, where the command is,
/// and where it points the head.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VisualTrackingState {
    /// The command in progress (`point_locate`, `point_locate_approach`,
    /// `point_locate_approach_track`).
    pub command: Option<String>,
    /// Where it is: `idle`, `await_target`, `locate`, `approach`, `face`.
    pub step: String,
    /// Whether the pan-tilt unit follows the target.
    pub pursuing: bool,
    /// Whether the pursuit is paused while another module (the navigator's scans) uses the unit.
    pub yielding: bool,
    /// The pan and tilt last commanded, rad.
    pub pan_tilt: Option<[f64; 2]>,
    /// The point the head is aimed at (`map`), m.
    pub aim: Option<Point3<f64>>,
    /// The goal (x, y) of the approach leg in progress (`map`), m.
    pub goal: Option<[f64; 2]>,
    /// Horizontal distance from the rover to the target's estimate, m.
    pub distance_m: Option<f64>,
    /// Approach legs driven by the command in progress.
    pub legs: u32,
    /// How the last command ended.
    pub last_outcome: Option<String>,
}
