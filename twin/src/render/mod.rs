//! Rendered sensors: a headless wgpu renderer of the twin's world and the Dry-Run camera devices
//! built on it (stereo cameras and Time-of-Flight cameras).

pub mod gpu;
pub mod scene;
pub mod sensors;

pub use gpu::{RenderError, Shading};
pub use sensors::{SensorConfig, SensorRenderer};
