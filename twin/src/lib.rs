//! # twin: the simulator half of the digital twin
//!
//! - [`sim::Twin`]: the rapier3d world of a [`worlds::World`] with the rover (from
//!   `assets/rover/rover.urdf`, loaded with dimforge's rapier URDF loader), its arm, pan-tilt unit,
//!   gripper and the sample canister, at full-dynamics or kinematic fidelity; deterministic.
//! - [`proprio`]: the IMU's and the encoders' true signals, sampled at their rates.
//! - [`belief`]: the robot as built (each camera's own intrinsics) and as believed (the
//!   calibrations and models the software is given, off the truth by configured errors).
//! - [`devices`]: the Dry-Run implementations of the framework's HAL traits, and the device map that
//!   builds them from configuration.
//! - [`render`]: the headless wgpu renderer and the camera models.
//! - [`truth`]: ground truth, for the logger and the scorer only.
//!
//! Depends on `framework` and `worlds`, never on `gnc`.

pub mod belief;
pub mod config;
pub mod convert;
pub mod devices;
pub mod kinematic;
pub mod proprio;
pub mod render;
pub mod sim;
pub mod truth;
pub mod visibility;

pub use config::TwinConfig;
pub use sim::{CanisterMotion, Fidelity, StartPose, Twin, TwinError, assets_dir, rover_urdf};
