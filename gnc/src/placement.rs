//! Where a camera was when it took a frame: the rover's pose estimate and the joint states at the
//! frame's capture time (interpolated from short histories of their blackboard slots), through the
//! believed mechanism model and the camera's believed mounting. Shared by the perception and
//! tracking modules, whose cameras sit on the pan-tilt unit and whose frames arrive after their
//! latency (seed 004: every datum carries its time).

use crate::history::{History, joints_at, pose_at};
use framework::camera::CameraCalibration;
use framework::data::{JointStates, PoseEstimate};
use framework::mechanism::MechanismModel;
use framework::prelude::*;
use nalgebra::Isometry3;

/// A joint group's states as the placement follows them.
struct JointInput {
    slot: String,
    reader: Option<Reader<JointStates>>,
    values: History<Vec<f64>>,
    names: Vec<String>,
}

/// The camera placement of a module: pose and joint histories over the believed mechanism.
pub struct Placement {
    mechanism: MechanismModel,
    pose_slot: String,
    pose: Option<Reader<PoseEstimate>>,
    joints: Vec<JointInput>,
    poses: History<PoseEstimate>,
    max_extrapolation_s: f64,
}

impl Placement {
    /// Placement on the robot of the believed `mechanism`, with the rover's pose from `pose_slot`
    /// and its joints from `joints_slots` (`JointStates` slots); histories of `history_s`.
    pub fn new(mechanism: MechanismModel, pose_slot: &str, joints_slots: &[&str], history_s: f64) -> Self {
        Placement {
            mechanism,
            pose_slot: pose_slot.to_string(),
            pose: None,
            joints: joints_slots
                .iter()
                .map(|s| JointInput {
                    slot: s.to_string(),
                    reader: None,
                    values: History::new(history_s),
                    names: Vec::new(),
                })
                .collect(),
            poses: History::new(history_s),
            max_extrapolation_s: 0.15,
        }
    }

    /// Declares the slots it reads.
    pub fn declare<M: Module>(&mut self, d: &mut Declare<'_, M>) {
        self.pose = Some(d.reads(&self.pose_slot));
        for group in &mut self.joints {
            group.reader = Some(d.reads(&group.slot));
        }
    }

    /// Restarts the histories with a new span, and sets how far past the newest sample a stamp
    /// may be placed, s.
    pub fn configure(&mut self, history_s: f64, max_extrapolation_s: f64) {
        self.poses = History::new(history_s);
        for group in &mut self.joints {
            group.values = History::new(history_s);
        }
        self.max_extrapolation_s = max_extrapolation_s;
    }

    /// Takes in the latest pose and joint states.
    pub fn update(&mut self, ctx: &Ctx<'_>) {
        if let Some(p) = self.pose.as_ref().and_then(|r| ctx.read(r)) {
            self.poses.push(p.stamp, p.value.clone());
        }
        for group in &mut self.joints {
            if let Some(j) = group.reader.as_ref().and_then(|r| ctx.read(r)) {
                if group.names.is_empty() {
                    group.names = j.value.joints.iter().map(|s| s.name.clone()).collect();
                }
                group.values.push(j.stamp, j.value.joints.iter().map(|s| s.position).collect());
            }
        }
    }

    /// The believed mechanism.
    pub fn mechanism(&self) -> &MechanismModel {
        &self.mechanism
    }

    /// The rover's pose estimate at `stamp`.
    pub fn pose_at(&self, stamp: Time) -> Result<PoseEstimate, String> {
        pose_at(&self.poses, stamp, self.max_extrapolation_s)
            .ok_or_else(|| format!("no '{}' pose at {stamp}", self.pose_slot))
    }

    /// The newest pose estimate taken in.
    pub fn newest_pose(&self) -> Option<&PoseEstimate> {
        self.poses.newest().map(|(_, p)| p)
    }

    /// The mechanism's joint values at `stamp`, from the joint histories.
    pub fn joints_at(&self, stamp: Time) -> Result<Vec<f64>, String> {
        let mut q = vec![0.0; self.mechanism.dof_count()];
        for group in &self.joints {
            let known = joints_at(&group.values, stamp, self.max_extrapolation_s)
                .ok_or_else(|| format!("no '{}' joint states at {stamp}", group.slot))?;
            for (d, name) in self.mechanism.dof_names().iter().enumerate() {
                if let Some(k) = group.names.iter().position(|n| n == name) {
                    q[d] = known[k];
                }
            }
        }
        Ok(q)
    }

    /// Pose of link `link` in the mechanism's root (`base_link`) for joint values `q`.
    pub fn base_from_link(&self, link: &str, q: &[f64]) -> Result<Isometry3<f64>, String> {
        let root = self.mechanism.root().to_string();
        self.mechanism.transform(&root, link, q).map_err(|e| e.to_string())
    }

    /// Pose of `cam`'s optical frame in `base_link` for joint values `q`.
    pub fn base_from_optical(&self, cam: &CameraCalibration, q: &[f64]) -> Result<Isometry3<f64>, String> {
        Ok(self.base_from_link(&cam.mount, q)? * cam.mount_from_optical)
    }

    /// The rover's pose and the camera's pose in `base_link` at `stamp`.
    pub fn camera_at(
        &self,
        cam: &CameraCalibration,
        stamp: Time,
    ) -> Result<(PoseEstimate, Isometry3<f64>), String> {
        let pose = self.pose_at(stamp)?;
        let q = self.joints_at(stamp)?;
        Ok((pose, self.base_from_optical(cam, &q)?))
    }
}
