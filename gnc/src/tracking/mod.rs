//! Vision algorithms of seed 000, 8.1 and 8.4, free of the framework's module machinery: fiducial
//! markers ([`marker_detector`]) and the poses they give ([`markers`]), the operator-selected target's image tracker
//! ([`template`], on the weighted correlation of `correlation`) and where a lost one is looked for ([`search`]), its position by stereo
//! ([`locate`], within the ranges a box of known [`size`] allows, by [`stereo_match`]) fused over the images
//! ([`estimate`]) and the pan and tilt that point a camera at it
//! ([`pointing`]).

pub(crate) mod correlation;
pub mod estimate;
pub mod locate;
pub mod marker_detector;
pub mod markers;
pub mod pointing;
pub mod search;
pub mod size;
pub mod stereo_match;
pub mod template;

/// The larger of a target position covariance's x and y sigmas (m, `map`): what TrackingTarget's
/// `locate {max_sigma_m}` bounds.
pub fn locate_sigma(covariance: &nalgebra::Matrix3<f64>) -> f64 {
    covariance[(0, 0)].max(covariance[(1, 1)]).max(0.0).sqrt()
}
