//! # gnc: guidance, navigation and control modules
//!
//! The mission's module set (seed 000, section 8). GNC code sees the world only through the
//! framework's HAL and blackboard; this crate never depends on `twin` and never reads ground truth.
//!
//! Today: the HAL-level modules that scenarios command through message passing —
//! [`locomotion::Locomotion`] (body motion, `goto`, stall detection), [`joints::JointGroupModule`]
//! (arm, pan-tilt unit, gripper), [`cameras::Cameras`] (stereo and ToF frames on the blackboard) — and
//! [`odometry::Odometry`] (wheel-inertial dead reckoning).
//! To come (see DESIGN.md): ToF elevation maps and fusion, traversability, path planning, visual
//! odometry and localization fusion, target and marker tracking, visual servoing, autonomy.

pub mod cameras;
pub mod history;
pub mod joints;
pub mod locomotion;
pub mod navigation;
pub mod navigator;
pub mod odometry;
pub mod path_planning;
pub mod perception_fusion;
pub mod perception_tof;
pub mod traversability;
