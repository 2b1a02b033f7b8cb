//! Localization algorithms (seed 000, 8.3), apart from the module machinery so they can be tested
//! and benchmarked alone: stereo rectification, corners and stereo matching, motion refinement,
//! keyframe stereo visual odometry, its rotation from bearings, the pose filter and what it takes
//! from landmarks and standstills, the gyro bias learnt at standstills.

pub mod bearing;
pub mod features;
pub mod filter;
pub mod gyro_bias;
pub mod landmark;
pub mod motion;
pub mod rectify;
pub mod standstill;
pub mod visual;
