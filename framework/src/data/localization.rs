//! Localization products (seed 000, 8.3): the sources' estimates that the data fusion combines.

use crate::time::Time;
use nalgebra::{Isometry3, Matrix3, Matrix6, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// What an inertial unit says of the body's attitude.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AttitudeEstimate {
    /// `map` from `base_link`: roll and pitch from gravity, yaw from the integrated gyro.
    pub attitude: UnitQuaternion<f64>,
    /// Covariance of small rotations about the `map` axes (roll, pitch, yaw), rad^2.
    pub covariance: Matrix3<f64>,
    /// The bias-corrected gyro integrated since the start, with no gravity correction: the
    /// rotation between two estimates is `gyro_attitude_a^-1 * gyro_attitude_b`, body frame.
    pub gyro_attitude: UnitQuaternion<f64>,
    /// Angle random walk of the gyro (1 sigma), rad/sqrt(s): what an increment of
    /// `gyro_attitude` is worth.
    pub gyro_noise: f64,
    /// The mean unit specific force over the cycle in the body frame (up, at rest), when the unit
    /// was not accelerating beyond its gate; absent otherwise.
    pub gravity: Option<Vector3<f64>>,
    /// Gyro bias estimate, rad/s.
    pub gyro_bias: Vector3<f64>,
    /// The bias has been learnt at a standstill at least once.
    pub bias_learnt: bool,
    /// Bias-corrected body angular rate, rad/s.
    pub angular_rate: Vector3<f64>,
}

/// How a visual odometry frame went.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VisualOdometryStatus {
    /// A keyframe started with no motion yet (the first frame, or the first after a loss).
    Initialized,
    /// The motion from the keyframe was measured.
    Tracking,
    /// Tracking was lost in this frame; the next measurement starts from a new keyframe.
    Lost,
}

/// One stereo visual odometry frame: the body's motion since the keyframe, measured at the
/// images' capture times.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VisualOdometry {
    /// How it went.
    pub status: VisualOdometryStatus,
    /// Why tracking was lost, when it was.
    pub reason: Option<String>,
    /// Capture time of the keyframe's images.
    pub keyframe_stamp: Time,
    /// Capture time of this frame's images.
    pub stamp: Time,
    /// `base_link` at the keyframe from `base_link` now, when tracking.
    pub delta: Option<Isometry3<f64>>,
    /// Covariance of `delta`: the translation error in the keyframe's body frame (m^2), then the
    /// rotation error as a right perturbation (rad^2).
    pub covariance: Matrix6<f64>,
    /// This frame closed its keyframe: `delta` is final, and the next measurement starts here.
    pub keyframe_closed: bool,
    /// Corners tracked into this frame.
    pub tracked: u32,
    /// Corners that agree with the motion.
    pub inliers: u32,
    /// Corners of the keyframe this frame started, if it started one.
    pub keyframe_features: u32,
    /// Root-mean-square reprojection error of the inliers, pixels.
    pub rmse_px: f64,
    /// The inliers' positions in the rectified left image, pixels (for display).
    pub inlier_pixels: Vec<[f32; 2]>,
}
