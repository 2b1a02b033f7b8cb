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

/// A contact the twin counted: the rover against a rock or an object (a collision), or the arm
/// side (or a held canister) against the body side (a self-collision).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ContactEvent {
    /// When it began, simulated s.
    pub t_s: f64,
    /// A self-collision (else a collision).
    pub self_collision: bool,
    /// The two parts (collider or link names, `rover footprint` in kinematic fidelity).
    pub parts: [String; 2],
}

/// How the canister's handle sits in the gripper: its pose in the tool-centre-point frame against
/// the nominal grasp (handle centred between the fingers, its narrow axis along the closing axis,
/// its top towards the palm; either of the two symmetric ways round).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GraspTruth {
    /// Distance of the handle's centre from the tool centre point, m.
    pub position_error_m: f64,
    /// Rotation of the handle from the nominal grasp, degrees.
    pub angle_error_deg: f64,
    /// Angle between the fingers' closing axis and the handle's narrow axis, degrees.
    pub closing_axis_error_deg: f64,
}

impl GraspTruth {
    /// The grasp of a handle at `handle` by a gripper whose tool centre point is at `tcp` (both in
    /// one frame; the fingers close along the TCP's y axis, the palm is towards its -x).
    pub fn of(tcp: &nalgebra::Isometry3<f64>, handle: &nalgebra::Isometry3<f64>) -> GraspTruth {
        use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
        let rel = tcp.inverse() * handle;
        // Nominal: handle x along TCP z, handle y along TCP y, handle z along -TCP x.
        let nominal = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::new(
            0.0, 0.0, -1.0, //
            0.0, 1.0, 0.0, //
            1.0, 0.0, 0.0,
        )));
        let flipped = nominal * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI);
        let angle = rel.rotation.angle_to(&nominal).min(rel.rotation.angle_to(&flipped));
        let narrow = rel.rotation * Vector3::y();
        GraspTruth {
            position_error_m: rel.translation.vector.norm(),
            angle_error_deg: angle.to_degrees(),
            closing_axis_error_deg: narrow.y.abs().clamp(0.0, 1.0).acos().to_degrees(),
        }
    }
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
    /// Self-collisions (arm side against the rover's body) counted so far.
    pub self_collisions: u64,
    /// How the handle sits in the gripper, while it is held.
    pub grasp: Option<GraspTruth>,
    /// Wheel rates commanded, rad/s.
    pub wheel_command: Vec<f64>,
}

impl GroundTruth {
    /// A body by name.
    pub fn body(&self, name: &str) -> Option<&BodyTruth> {
        self.bodies.iter().find(|b| b.name == name)
    }
}
