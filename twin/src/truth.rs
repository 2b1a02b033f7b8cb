//! Ground truth of the simulated world. Read only by the logger and the scorer (and the scripted
//! operator, marked as such by the scenario): GNC code never sees it, which the crate layering
//! enforces (`gnc` cannot depend on `twin`).

use framework::time::Time;
use nalgebra::{Isometry3, Point3, Vector3};
use serde::{Deserialize, Serialize};

/// Pose and velocity of one body (a robot link or the canister), world frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BodyTruth {
    /// Link or object name.
    pub name: String,
    /// Pose in the world frame.
    pub pose: Isometry3<f64>,
    /// Linear velocity of the frame origin, m/s, world frame.
    pub linvel: Vector3<f64>,
    /// Angular velocity, rad/s, world frame.
    pub angvel: Vector3<f64>,
}

/// One touching pair of colliders.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ContactTruth {
    /// First collider's owner (link, rock, object or `terrain`).
    pub a: String,
    /// Second collider's owner.
    pub b: String,
    /// Contact points, world frame.
    pub points: Vec<Point3<f64>>,
    /// Deepest penetration, m.
    pub depth: f64,
}

/// Everything true about the world at one instant.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GroundTruth {
    /// Simulated time.
    pub time: Time,
    /// Every robot link, then the canister.
    pub bodies: Vec<BodyTruth>,
    /// Active contacts (dynamic fidelity).
    pub contacts: Vec<ContactTruth>,
    /// The gripper holds the canister.
    pub canister_held: bool,
    /// Collisions counted so far.
    pub collisions: u64,
    /// Wheel rates commanded, rad/s.
    pub wheel_command: Vec<f64>,
}

impl GroundTruth {
    /// A body by name.
    pub fn body(&self, name: &str) -> Option<&BodyTruth> {
        self.bodies.iter().find(|b| b.name == name)
    }
}
