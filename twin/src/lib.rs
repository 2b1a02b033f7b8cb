//! # twin: the simulator half of the digital twin
//!
//! - [`sim::Twin`]: the rapier3d world of a [`worlds::World`] with the rover (from
//!   `assets/rover/rover.urdf`, loaded with dimforge's rapier URDF loader), its arm, pan-tilt unit,
//!   gripper and the sample canister, at full-dynamics or kinematic fidelity; deterministic.
//! - [`devices`]: the Dry-Run implementations of the framework's HAL traits, and the device map that
//!   builds them from configuration.
//! - [`truth`]: ground truth, for the logger and the scorer only.
//!
//! Depends on `framework` and `worlds`, never on `gnc`. Rendered sensors come with their own issue.

pub mod config;
pub mod convert;
pub mod devices;
pub mod render;
pub mod sim;
pub mod truth;

pub use config::TwinConfig;
pub use sim::{Fidelity, StartPose, Twin, TwinError, assets_dir, rover_urdf};
