//! The data interface: types that modules publish on the blackboard and that tools (the logger, the
//! scorer, consoles) know how to show. Each type has one meaning and one way to be logged; new GNC
//! products (maps, paths, tracks) join here as they arrive.

use nalgebra::{Isometry3, Matrix6, Point3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// A pose estimate with its uncertainty: where `child` is in `frame`.
///
/// The covariance is over (x, y, z, roll, pitch, yaw) in `frame`, m^2 and rad^2, small-angle
/// perturbations of the rotation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseEstimate {
    /// The reference frame (`odom`: the start pose, drifting; `map`: the localization frame).
    pub frame: String,
    /// The estimated frame (usually `base_link`).
    pub child: String,
    /// Pose of `child` in `frame`.
    pub pose: Isometry3<f64>,
    /// Covariance of (x, y, z, roll, pitch, yaw).
    pub covariance: Matrix6<f64>,
    /// Body-frame forward speed and yaw rate at the estimate's time, m/s and rad/s.
    pub velocity: crate::hal::BodyTwist,
    /// How often the estimate has been moved at once onto an absolute reference (a surveyed
    /// landmark, after drifting from it): what was placed in `frame` with the estimate before such
    /// a move is displaced by the move from what is placed after it.
    #[serde(default)]
    pub relocalizations: u32,
}

impl PoseEstimate {
    /// A planar pose (x, y, yaw) in `frame` with a diagonal covariance for those three, the others 0.
    pub fn planar(frame: &str, x: f64, y: f64, z: f64, yaw: f64) -> Self {
        PoseEstimate {
            frame: frame.to_string(),
            child: "base_link".to_string(),
            pose: Isometry3::from_parts(
                nalgebra::Translation3::new(x, y, z),
                UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
            ),
            covariance: Matrix6::zeros(),
            velocity: Default::default(),
            relocalizations: 0,
        }
    }
    /// Position, m.
    pub fn position(&self) -> Point3<f64> {
        Point3::from(self.pose.translation.vector)
    }
    /// Heading (yaw), rad.
    pub fn yaw(&self) -> f64 {
        self.pose.rotation.euler_angles().2
    }
    /// Standard deviations of (x, y, z), m.
    pub fn position_sigma(&self) -> Vector3<f64> {
        Vector3::new(self.covariance[(0, 0)], self.covariance[(1, 1)], self.covariance[(2, 2)])
            .map(|v| v.max(0.0).sqrt())
    }
}

/// Measured states of a joint group (an arm, a pan-tilt unit, a gripper), in its joint order.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointStates {
    /// The group (device) name.
    pub group: String,
    /// One state per joint.
    pub joints: Vec<crate::hal::JointState>,
}

/// What a locomotion module is doing: the body twist in force and its mode.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LocomotionState {
    /// The twist commanded to the locomotor.
    pub command: crate::hal::BodyTwist,
    /// The current manoeuvre (`idle`, `drive`, `goto`, `turn`, `fault`).
    pub mode: String,
    /// The goal of the current manoeuvre in the odometry frame, if it has one (x, y), m.
    pub goal: Option<[f64; 2]>,
}

/// A stereo pair captured together (left and right images of one exposure).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StereoImages {
    /// Left image.
    pub left: crate::camera::GreyImage,
    /// Right image.
    pub right: crate::camera::GreyImage,
}

/// A target region selected in a camera image (by the ground operator, or by a detector).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetSelection {
    /// What the target is (`canister`).
    pub target: String,
    /// The camera device whose image was used.
    pub camera: String,
    /// The optical frame of that image.
    pub frame: String,
    /// Stamp of the image the region was selected in.
    pub image_stamp: crate::time::Time,
    /// The region, pixels: [u_min, v_min, u_max, v_max].
    pub bbox: [f64; 4],
    /// Who selected it (`operator`: a person at the ground station, from what they see).
    pub source: String,
}

/// What a navigator is doing (seed 000, 8.2): its goal, mode and progress.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NavigationState {
    /// `idle`, `scan`, `await_map`, `plan`, `drive`.
    pub phase: String,
    /// `stop_and_go` or `continuous`.
    pub mode: String,
    /// The goal (x, y) in `map`, m, while navigating.
    pub goal: Option<[f64; 2]>,
    /// Straight-line distance from the estimated position to the goal, m.
    pub distance_to_goal_m: Option<f64>,
    /// Plans made for the current goal.
    pub plans: u32,
    /// Consecutive failures (no path, a failed scan or drive) for the current goal.
    pub failures: u32,
}

mod autonomy;
mod localization;
mod manipulation;
mod maps;
mod tracking;
pub use autonomy::{
    Activity, ActivityReport, ActivityStatus, AutonomyState, FailurePolicy, FaultReport, MissionEnd, Plan,
    PlanStep,
};
pub use localization::{AttitudeEstimate, VisualOdometry, VisualOdometryStatus};
pub use manipulation::ManipulationState;
pub use maps::{ElevationMap, GridGeometry, NavigationMap, Path, cost};
pub use tracking::{
    ExcludedPlace, LineOfSight, MarkerDetections, MarkerObservation, ObjectPose, ObjectPoses, TargetStatus,
    TargetTrack, VisualTrackingState, carried,
};
