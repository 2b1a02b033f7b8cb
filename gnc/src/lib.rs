//! # gnc: guidance, navigation and control modules
//!
//! The mission's module set (seed 000, section 8). GNC code sees the world only through the
//! framework's HAL and blackboard; this crate never depends on `twin` and never reads ground truth.
//!
//! The HAL-level modules that scenarios command through message passing —
//! [`locomotion::Locomotion`] (body motion, `goto`, `follow_path`, stall detection),
//! [`joints::JointGroupModule`] (arm, pan-tilt unit, gripper), [`cameras::Cameras`] (stereo and ToF
//! frames on the blackboard) — the localization modules of seed 000, 8.3
//! ([`localization_mechanical::LocalizationMechanical`], [`localization_inertial::LocalizationInertial`],
//! [`localization_visual::LocalizationVisual`], [`localization_fusion::LocalizationDataFusion`], over
//! the algorithms of [`localization`]), and the
//! navigation chain of seed 000, 8.2: [`perception_tof::PerceptionToF`],
//! [`perception_fusion::PerceptionDataFusion`], [`traversability::Traversability`],
//! [`path_planning::PathPlanning`] and [`navigator::CoordinatorNavigator`], over the algorithms of
//! [`navigation`]; the vision modules of seed 000, 8.1 and 8.4:
//! [`tracking_marker::TrackingMarker`], [`tracking_target::TrackingTarget`] and
//! [`visual_tracking::CoordinatorVisualTracking`], over the algorithms of [`tracking`]; the
//! manipulation modules of seed 000, 8.3: [`manipulator_control::ManipulatorControl`] (planned arm
//! motions clear of the body, grasps under visual servoing with the wrist camera, placing in the
//! stowage slot) and [`coordinator_manipulation::CoordinatorManipulation`] (`acquire_canister`,
//! `stow_canister`), over the algorithms of [`manipulation`].
//! To come (see DESIGN.md): autonomy.

pub mod autonomy;
pub mod body;
pub mod cameras;
pub mod coordinator_manipulation;
pub mod history;
pub mod joints;
pub mod localization;
pub mod localization_fusion;
pub mod localization_inertial;
pub mod localization_mechanical;
pub mod localization_visual;
pub mod locomotion;
pub mod manipulation;
pub mod manipulator_control;
pub mod navigation;
pub mod navigator;
pub mod params;
pub mod path_planning;
pub mod peer;
pub mod perception_fusion;
pub mod perception_tof;
pub mod placement;
pub mod tracking;
pub mod tracking_marker;
pub mod tracking_target;
pub mod traversability;
pub mod visual_tracking;
